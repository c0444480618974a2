"""The specimen as the calibration and the diagnosis see it.

:mod:`.model`: the forward model, :class:`SpecimenModel` (a ``torch.nn.Module``: parameter rows
-> the FE's outputs ``(B, n_time, n_out)`` um, or the observed ones ``(B, n_obs)``; directly and
differentiably, or through the run store) and :class:`SpecimenModels` (one per configuration).
:mod:`.observed`: which parameters the FE varies, which outputs the measurements are, the
observation-side effects' offsets.

The lowest layer of the specimen pipeline: :mod:`solderpyro.pipeline` (the calibration) and
:mod:`solderpyro.diagnose` (the diagnosis) both build on it, and it imports neither.
"""

from solderpyro.specimen.model import (
    ModelRuns,
    RunTally,
    SpecimenModel,
    SpecimenModels,
    StoreUse,
)
from solderpyro.specimen.observed import (
    OBSERVATION_SEAM,
    calibration_box,
    observation_index,
    observation_offset,
    output_points,
    split_effects,
)

__all__ = [
    "OBSERVATION_SEAM", "ModelRuns", "RunTally", "SpecimenModel",
    "SpecimenModels", "StoreUse", "calibration_box", "observation_index",
    "observation_offset", "output_points", "split_effects",
]
