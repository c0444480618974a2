"""GPyTorch exact-GP surrogates of a computer model, with explicit input/output transforms."""

from solderpyro.surrogate.gp import GPFactors, GPSurrogate, LooResult, SurrogateWarning
from solderpyro.surrogate.kernels import gaussian, matern52
from solderpyro.surrogate.transforms import Standardizer

__all__ = ["GPFactors", "GPSurrogate", "LooResult", "Standardizer", "SurrogateWarning", "gaussian",
           "matern52"]
