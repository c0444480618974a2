"""Moire rigid motion: each image carries its own rigid offset and small in-plane rotation.

Moire measures fringe orders, and only their differences are defined (V = N / f, N the fringe
order, f the reference grating's frequency; docs/data-format.md, "Fringe orders"): an
image fixes V up to an additive constant, and a small rotation of the specimen (or of the
reference grating) between the reference image and image k adds a field linear in x. The
baseline reports V relative to O, which removes both exactly only if O's own reading is exact
and the specimen does not rotate; in practice O is interpolated between fringes and the holder
rotates a little, so per image k (output time k, ascending) the observed field is

    V'_k(x) = V_k(x) + c_k + 1e-3 * w_k * (x - x_O)      [um; c_k in um, w_k in urad, x in mm]

(urad * mm = 1e-3 um). Parameters ``moire_c_1..n`` and ``moire_w_1..n`` (n = number of output
times: the effect is bound to the output times by the solver/model). Off: all zero.
Note: points A and B both lie at x = 15 mm, so with point data only c_k and w_k enter as one
combination c_k + 0.015 w_k per image (not separately identifiable); full-field data separate
them.
Seam: the observation operator (no FE involved; exactly linear in the parameters).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import torch

from solderpyro.effects.base import Effect, box_pair
from solderpyro.fem.loading import SEED_TIMES
from solderpyro.params import Box


@dataclass(frozen=True)
class MoireRigidMotion(Effect):
    """Per-image rigid offset ``moire_c_k`` (um) and rotation ``moire_w_k`` (urad).

    Attributes:
        n_images: number of images (output times); the registry's default is the seed's four,
            :meth:`bind` sets it from the output times.
        c_range, w_range: prior bounds of every offset (um) and every rotation (urad); the box
            keys ``c`` and ``w`` of :meth:`with_box` set them.
    """

    name = "moire_rigid_motion"
    seam = "observation operator"
    n_images: int = len(SEED_TIMES)
    c_range: tuple[float, float] = field(default=(-1.0, 1.0), metadata={"prior": True})
    w_range: tuple[float, float] = field(default=(-50.0, 50.0), metadata={"prior": True})

    def default_box(self) -> Box:
        n = self.n_images
        names = tuple(f"moire_c_{k + 1}" for k in range(n)) + tuple(
            f"moire_w_{k + 1}" for k in range(n))
        return Box(names, (self.c_range[0],) * n + (self.w_range[0],) * n,
                   (self.c_range[1],) * n + (self.w_range[1],) * n,
                   units=("um",) * n + ("urad",) * n)

    @property
    def params(self) -> Box:
        return self.default_box()

    @property
    def off(self) -> tuple[float, ...]:
        return (0.0,) * (2 * self.n_images)

    def bind(self, times: Sequence[float]) -> Effect:
        return dataclasses.replace(self, n_images=len(times))

    def rebind_params(self, q: torch.Tensor, times_from: Sequence[float],
                      times_to: Sequence[float]) -> torch.Tensor:
        """Each image's ``c_k, w_k`` go to the same time in ``times_to``; an image at a time
        that was not observed gets no rigid motion (0). ``(b, 2 n_from) -> (b, 2 n_to)``."""
        n0, n1 = len(times_from), len(times_to)
        if q.shape[1] != 2 * n0:
            raise ValueError(f"moire_rigid_motion: {q.shape[1]} parameters for {n0} images")
        out = q.new_zeros(q.shape[0], 2 * n1)
        for j, t in enumerate(times_to):
            hit = [i for i, s in enumerate(times_from) if abs(float(s) - float(t)) < 1e-6]
            if hit:
                out[:, j], out[:, n1 + j] = q[:, hit[0]], q[:, n0 + hit[0]]
        return out

    def with_box(self, bounds: Mapping[str, Sequence[float]]) -> Effect:
        """Keys ``c`` (um) and ``w`` (urad) set the bounds of all images at once."""
        c, w = self.c_range, self.w_range
        for key, pair in bounds.items():
            if key not in ("c", "w"):
                raise ValueError(f"effect {self.name!r} has box keys c (um) and w (urad), "
                                 f"got {key!r}")
            if key == "c":
                c = box_pair(self.name, key, pair)
            else:
                w = box_pair(self.name, key, pair)
        return dataclasses.replace(self, c_range=c, w_range=w)

    def observe(self, V: torch.Tensor, x: torch.Tensor, x_O: float,
                q: torch.Tensor) -> torch.Tensor:
        """``V + c_k + 1e-3 w_k (x - x_O)`` ``(b, n_time, n_out)`` um."""
        n = self.n_images
        if V.shape[1] != n:
            raise ValueError(f"moire_rigid_motion is bound to {n} images, V has {V.shape[1]} "
                             f"output times")
        c, w = q[:, :n, None], q[:, n:, None]  # (b, n_time, 1)
        return V + c + 1e-3 * w * (x.to(V) - x_O)


EFFECT = MoireRigidMotion()
