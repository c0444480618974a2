"""Constants pressed against the faces of their prior box: a finding of its own.

When a model lacks a piece of physics, the calibrated constants absorb what they can of it.
They then often end where the box stops them: on the hidden stress-free-temperature field
data the FE's best fit went to s0 25, Q/R 13,000, xi 1.0 (three faces at once) and fitted at
the noise level with every constant wrong. A fit at the noise level with constants on faces
is therefore not "the model fits": :func:`on_faces` finds such constants, the diagnosis says
so first and refits every candidate globally (:func:`~solderpyro.diagnose.refits.global_refits`).

A constant is on a face when it lies within :data:`FACE_SHARE` of the box's width from a bound,
measured on the box's working scale (log for log-scale constants), where the unit-cube map of
:class:`~solderpyro.params.Box` measures it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from solderpyro.diagnose.decide import APART_CHI2, Refit
from solderpyro.params import Box

#: a constant within this share of its box's width from a bound is on that face (the LM's
#: steps stop at the bound itself; 1 % leaves room for a fit that has not quite arrived)
FACE_SHARE = 0.01
#: after the chosen effects, a constant within this share of a bound counts as pressed there,
#: and a candidate frees it by moving it farther in. Measured on the moderate residual stress
#: plus lag field data: the lag's refit left xi 0.3 %, s0 1.9 %, Q/R 4.5 % of their widths
#: from the bounds; with the residual stress on too they went to 0.6 %, 39 %, 26 % at a fit as
#: good, while every other candidate moved xi alone, by about 1 % of its width
NEAR_SHARE = 0.05


@dataclass(frozen=True)
class Face:
    """One constant on a face of its prior box.

    Attributes:
        name: the constant; side: ``"lower"`` or ``"upper"``.
        value: where it is; bound: the face's value (physical units, ``unit``).
    """

    name: str
    side: str
    value: float
    bound: float
    unit: str = ""

    def text(self) -> str:
        """``"s0 = 25 MPa (upper bound 25)"``."""
        u = f" {self.unit}" if self.unit not in ("", "-") else ""  # "-": dimensionless
        return f"{self.name} = {self.value:.4g}{u} ({self.side} bound {self.bound:.4g})"

    def to_json(self) -> dict[str, str | float]:
        return {"name": self.name, "side": self.side, "value": self.value,
                "bound": self.bound, "unit": self.unit}


def on_faces(x: np.ndarray, box: Box, share: float = FACE_SHARE) -> list[Face]:
    """The constants of ``x`` that lie on a face of ``box``.

    Args:
        x: ``(box.dim,)`` values, physical units.
        box: their prior box (log-scale columns measured in log).
        share: distance from a bound, as a share of the width on the working scale, within
            which a constant counts as on the face.
    Returns:
        one :class:`Face` per constant on a face, in the box's order.
    """
    x = np.asarray(x, float)
    if x.shape != (box.dim,):
        raise ValueError(f"on_faces: x must have shape ({box.dim},) for "
                         f"{', '.join(box.names)}; got {x.shape}")
    if not 0.0 <= share < 0.5:
        raise ValueError(f"on_faces: share must be in [0, 0.5), got {share}")
    u = box.to_unit(torch.as_tensor(x, dtype=torch.float64)).numpy()
    out = []
    for k, nm in enumerate(box.names):
        unit = box.units[k] if box.units else ""
        if u[k] <= share:
            out.append(Face(nm, "lower", float(x[k]), float(box.lower[k]), unit))
        elif u[k] >= 1.0 - share:
            out.append(Face(nm, "upper", float(x[k]), float(box.upper[k]), unit))
    return out


def faces_text(faces: list[Face], at_noise: bool) -> str:
    """The finding in words, for the verdict's first sentence.

    Args:
        faces: the constants on faces (:func:`on_faces`), at least one.
        at_noise: whether the fit is at the noise level (then the fit itself hides it).
    """
    if not faces:
        raise ValueError("faces_text: no face given")
    lead = ("the FE's best fit is at the noise level but presses " if at_noise
            else "the FE's best fit presses ")
    return (lead + ", ".join(f.text() for f in faces) + " against the faces of the prior "
            "box: a missing effect is likely being compensated by the constants, so every "
            "candidate was refitted from several starts across the box")


def freeing(refits: list[Refit], base_chi2: float, box: Box, faces: list[Face]
            ) -> list[tuple[str, tuple[str, ...]]]:
    """The candidates that could be what the constants on the faces compensate: refitted (from
    several starts), they fit at least as well as the base (within
    :data:`~solderpyro.diagnose.decide.APART_CHI2`) with fewer constants on faces.

    Args:
        refits: the candidates' refits (``x`` full rows, the Anand constants first).
        base_chi2: the base fit's chi-square; box: the Anand constants' box;
        faces: the constants the base fit has on faces (:func:`on_faces`).
    Returns:
        ``(candidate, the constants it moves off the faces)``, best fit first.
    """
    on = [f.name for f in faces]
    out = []
    for r in sorted(refits, key=lambda r: r.chi2):
        if not r.ok or r.chi2 > base_chi2 + APART_CHI2:
            continue
        left = {f.name for f in on_faces(r.x[:box.dim], box)}
        if len(left) < len(on):
            out.append((r.name, tuple(c for c in on if c not in left)))
    return out
