"""Find what the model is missing: predictive checks, misfit and score tests of effects."""

from .diagnosis import Diagnosis
from .load import load_run
from .run import diagnose
from .stats import confusion, misfit, predictive_check, score_test

__all__ = ["Diagnosis", "confusion", "diagnose", "load_run", "misfit", "predictive_check",
           "score_test"]
