"""GPyTorch exact-GP surrogates of a computer model, with explicit input/output transforms."""

from solderpyro.surrogate.gp import (
    GPFactors,
    GPOptions,
    GPSurrogate,
    LooResult,
    SurrogateWarning,
    exact_linear_algebra,
)
from solderpyro.surrogate.kernels import gaussian, matern52
from solderpyro.surrogate.transforms import Standardizer

__all__ = ["GPFactors", "GPOptions", "GPSurrogate", "LooResult", "Standardizer", "SurrogateWarning",
           "exact_linear_algebra", "gaussian", "matern52"]
