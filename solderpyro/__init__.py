"""solderpyro: identify solder viscoplasticity (Anand) from Moire data, with honest uncertainty.

Public API:
    SpecimenModel       theta (B, n_theta) -> V (B, n_time, n_out) um, batched, differentiable
    SpecimenSolver      the FE solver (mesh, condensation, batched Newton, adaptive steps)
    Problem             typed description of the specimen, materials, cycle and outputs
    ParameterSpace      names, bounds, log-scale and unit-cube maps of calibrated constants
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from solderpyro.version import __version__

#: public name -> the module that defines it; imported on first use (PEP 562), so that
#: ``import solderpyro`` and ``solderpyro --help`` do not load torch
_LAZY = {
    "EXTENDED_TIMES": "solderpyro.fem.loading", "REFERENCE_CYCLE": "solderpyro.fem.loading",
    "SEED_TIMES": "solderpyro.fem.loading", "ThermalCycle": "solderpyro.fem.loading",
    "TimeStepping": "solderpyro.fem.loading", "Layer": "solderpyro.fem.mesh",
    "MeshSpec": "solderpyro.fem.mesh", "AnandSolder": "solderpyro.fem.problem",
    "Elastic": "solderpyro.fem.problem", "Problem": "solderpyro.fem.problem",
    "SolveResult": "solderpyro.fem.solver", "SpecimenSolver": "solderpyro.fem.solver",
    "ANAND_NAMES": "solderpyro.params", "LIU2008": "solderpyro.params",
    "ParameterSpace": "solderpyro.params", "SpecimenModel": "solderpyro.specimen.model",
}

if TYPE_CHECKING:
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


def __getattr__(name: str):
    """The public names of ``__all__``, imported from their modules on first access."""
    if name in _LAZY:
        import importlib

        value = getattr(importlib.import_module(_LAZY[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'solderpyro' has no attribute {name!r}")


__all__ = [
    "ANAND_NAMES", "AnandSolder", "Elastic", "EXTENDED_TIMES", "LIU2008", "Layer", "MeshSpec",
    "ParameterSpace", "Problem", "REFERENCE_CYCLE", "SEED_TIMES", "SolveResult",
    "SpecimenModel", "SpecimenSolver", "ThermalCycle", "TimeStepping", "__version__",
]
