"""The specimen as the calibration observes it: which parameters the FE varies, which model
outputs the measurements are, and the observation-side effects' offsets.

The lowest layer of the specimen pipeline with :mod:`.model`: :mod:`solderpyro.pipeline` (the
calibration) and :mod:`solderpyro.diagnose` (the diagnosis) both build on it, and it imports
neither.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from solderpyro.effects import EffectSet, effect_set
from solderpyro.fem.problem import reference_grid
from solderpyro.params import Box

if TYPE_CHECKING:
    from solderpyro.config.compose import Setup
    from solderpyro.io.measurements import Measurements


def calibration_box(setup: Setup, fx: EffectSet | None = None) -> Box:
    """The calibrated parameters: ``setup.space`` (Anand constants), then the parameters of the
    switched-on effects ``fx`` (bound to the data's times), with their prior boxes."""
    sp = setup.space
    if fx is None or len(fx) == 0:
        return sp
    eb = fx.box
    return Box(tuple(sp.names) + tuple(eb.names), tuple(sp.lower) + tuple(eb.lower),
               tuple(sp.upper) + tuple(eb.upper), tuple(sp.log_scale) + tuple(eb.log_scale),
               tuple(sp.units) + tuple(eb.units))


OBSERVATION_SEAM = "observation operator"


def split_effects(setup: Setup, times: tuple[float, ...]
                  ) -> tuple[EffectSet | None, EffectSet | None, EffectSet | None]:
    """The switched-on effects bound to ``times``: all (FE-side first, then observation-side),
    those the FE must simulate, and the observation-side ones (applied after the surrogate);
    None where empty."""
    if not setup.effects:
        return None, None, None
    fx = effect_set(setup.effects, times, setup.effect_bounds)
    obs = [e.name for e in fx.effects if e.seam == OBSERVATION_SEAM]
    fe = [e.name for e in fx.effects if e.seam != OBSERVATION_SEAM]

    def mk(names: list[str]) -> EffectSet | None:
        return effect_set(names, times, setup.effect_bounds) if names else None

    return mk(fe + obs), mk(fe), mk(obs)


def observation_offset(fx_obs: EffectSet, problem: Any, names: Sequence[str], n_time: int,
                       ti: np.ndarray, oi: np.ndarray) -> Any:
    """``q (n_q,) -> (n_obs,)`` (or a batch ``(B, n_q) -> (B, n_obs)``): what additive
    observation effects add to each observation, um (they act on V after the FE:
    ``EffectSet.observe`` of a zero field)."""
    pts = output_points(problem)
    x = torch.tensor([pts[n][0] for n in names], dtype=torch.float64)
    x_O = float(problem.origin[0])
    tt, oo = torch.as_tensor(ti), torch.as_tensor(oi)

    def offset(q: torch.Tensor) -> torch.Tensor:
        qb = q.reshape(-1, q.shape[-1])
        z = torch.zeros(qb.shape[0], n_time, len(names), dtype=q.dtype)
        out = fx_obs.observe(z, x, x_O, qb)[:, tt, oo]
        return out[0] if q.ndim == 1 else out

    return offset


def output_points(problem: Any) -> dict[str, tuple[float, float]]:
    """Every label a measurement may name: the problem's points (A, B) and the 31 x 18 grid.

    Returns:
        label -> (x_mm, y_mm), for ``read_measurements(valid_points=...)``.
    """
    labels, pts = reference_grid()
    return {**{k: (float(v[0]), float(v[1])) for k, v in problem.points.items()},
            **{lab: (float(x), float(y)) for lab, (x, y) in zip(labels, pts, strict=True)}}


def observation_index(meas: Measurements, times: tuple[float, ...], names: tuple[str, ...]
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Where each measured row sits in the model output ``(n_time, n_out)``.

    Returns:
        ``(n_obs,)`` time indices and ``(n_obs,)`` output indices.

    Raises:
        ValueError: naming the first row whose time or point is not a model output.
    """
    ti = np.searchsorted(np.asarray(times), meas.time_s)
    oi = np.empty(len(meas), dtype=int)
    lookup = {n: j for j, n in enumerate(names)}
    for r in range(len(meas)):
        t, p = float(meas.time_s[r]), str(meas.point[r])
        if ti[r] >= len(times) or abs(times[ti[r]] - t) > 1e-6:
            raise ValueError(f"measurement row {r + 1}: time {t} s is not an output time")
        if p not in lookup:
            raise ValueError(f"measurement row {r + 1}: point {p!r} is not a model output; "
                             f"valid: A, B or grid labels g_ii_jj")
        oi[r] = lookup[p]
    return ti, oi


