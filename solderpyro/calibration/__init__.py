"""Kennedy-O'Hagan calibration in Pyro: data, emulators, models, NUTS, posterior predictive."""

from solderpyro.calibration.data import CalibrationData
from solderpyro.calibration.emulators import FunctionEmulator, GPEmulator
from solderpyro.calibration.koh import Priors, joint_model, observation_model
from solderpyro.calibration.mcmc import Posterior, run_nuts
from solderpyro.calibration.nuts import NutsResult, sample_nuts
from solderpyro.calibration.predictive import Bands, predict_joint, predict_observation_model

__all__ = ["Bands", "CalibrationData", "FunctionEmulator", "GPEmulator", "NutsResult",
           "Posterior", "Priors", "joint_model", "observation_model", "predict_joint",
           "predict_observation_model", "run_nuts", "sample_nuts"]

from solderpyro.calibration.api import (  # noqa: E402
    calibrate_direct,
    calibrate_emulator,
    calibrate_joint,
    calibrate_modular,
)

__all__ += ["calibrate_direct", "calibrate_emulator", "calibrate_joint", "calibrate_modular"]
