"""Find what the model is missing: predictive checks, misfit and score tests of effects."""

from solderpyro.diagnose.diagnosis import Diagnosis
from solderpyro.diagnose.load import load_run
from solderpyro.diagnose.run import diagnose
from solderpyro.diagnose.stats import confusion, misfit, predictive_check, score_test

__all__ = ["Diagnosis", "confusion", "diagnose", "load_run", "misfit", "predictive_check",
           "score_test"]
