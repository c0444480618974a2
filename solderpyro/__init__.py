"""solderpyro: identify solder viscoplasticity (Anand) from Moire data, with honest uncertainty.

Public API:
    SpecimenModel       theta (B, n_theta) -> V (B, n_time, n_out) um, batched, differentiable
    SpecimenSolver      the FE solver (mesh, condensation, batched Newton, adaptive steps)
    Problem             typed description of the specimen, materials, cycle and outputs
    ParameterSpace      names, bounds, log-scale and unit-cube maps of calibrated constants
"""

from solderpyro.fem.loading import (
    EXTENDED_TIMES,
    REFERENCE_CYCLE,
    SEED_TIMES,
    ThermalCycle,
    TimeStepping,
)
from solderpyro.fem.mesh import Layer, MeshSpec
from solderpyro.fem.problem import AnandSolder, Elastic, Problem
from solderpyro.fem.solver import SolveResult, SpecimenSolver
from solderpyro.params import ANAND_NAMES, LIU2008, ParameterSpace
from solderpyro.specimen.model import SpecimenModel
from solderpyro.version import __version__

__all__ = [
    "ANAND_NAMES", "AnandSolder", "Elastic", "EXTENDED_TIMES", "LIU2008", "Layer", "MeshSpec",
    "ParameterSpace", "Problem", "REFERENCE_CYCLE", "SEED_TIMES", "SolveResult",
    "SpecimenModel", "SpecimenSolver", "ThermalCycle", "TimeStepping", "__version__",
]
