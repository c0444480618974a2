"""The specimen calibration as a sequence of stages, one module each, read top-down:

1. :mod:`.problem` -- what is observed (the data, :class:`~.problem.ObservedData`) and how the
   FE runs (:class:`~solderpyro.specimen.SpecimenModel` through the run store).
2. :mod:`.surrogate` -- the GP of the observed outputs.
3. :mod:`.posterior` -- modular KOH with NUTS through the surrogate.
4. :mod:`.adaptive` -- the adaptive design that repeats 2-3 and places FE runs
   (:mod:`solderpyro.design`) until the FE confirms the surrogate; then the discretization
   correction, which returns the corrected data, and the final posterior on them. By default
   (``calibration.design.optimizer=draws``) each round's runs are the posterior draws that
   maximize the acquisition, chosen one at a time in closed form
   (:func:`~solderpyro.design.acquisition.greedy_draws`); ``optimizer=optimize`` runs
   BoTorch's ``optimize_acqf`` over the box instead.
5. :mod:`.fe_check` -- the FE at posterior draws: does the model itself fit?
6. :mod:`.fe_exact` -- the FE-exact posterior and profile intervals, when the design's budget
   ran out with the FE disagreeing.
7. :mod:`.outputs` -- the run directory (and :mod:`solderpyro.reporting.report` for the report).

:mod:`.warm` says where a recalibration (``--warm-from``) starts: the related run's sampler
state, with the chains at the diagnosis's FE refit of the new model where there is one.

:func:`calibrate_specimen` (:mod:`.calibrate`) runs them; :class:`CalibrationSettings`
(:mod:`solderpyro.config.settings`, also the Hydra schema of the ``calibration`` group) holds every
setting. A new stage is a module here and a line in
:mod:`.calibrate`; a new acquisition function goes to :mod:`solderpyro.design.acquisition`.

The names below load on first use (importing the package does not load every stage).
"""

from typing import Any

__all__ = ["CalibrationSettings", "SpecimenCalibration", "calibrate_specimen"]


def __getattr__(name: str) -> Any:
    if name == "calibrate_specimen":
        from solderpyro.pipeline.calibrate import calibrate_specimen

        return calibrate_specimen
    if name == "SpecimenCalibration":
        from solderpyro.pipeline.outputs import SpecimenCalibration

        return SpecimenCalibration
    if name == "CalibrationSettings":
        from solderpyro.config.settings import CalibrationSettings

        return CalibrationSettings
    raise AttributeError(f"module 'solderpyro.pipeline' has no attribute {name!r}")
