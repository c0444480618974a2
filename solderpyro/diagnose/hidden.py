"""Synthetic data with a hidden effect: the proof that a diagnosis finds what is missing.

The FE with one effect switched on at a known value (and the Anand constants at known values)
plus N(0, sigma^2) noise; the file's metadata records the truth. The effect's magnitude is the
smallest of a ladder of values whose change of the noise-free point data (V at A and B at the
extended times) reaches ``target_rms`` (at least 0.3 um).

Units: um, s, and each effect's own parameter units (docs/effects.md).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from solderpyro.effects.base import Effect
from solderpyro.fem.loading import EXTENDED_TIMES

#: Anand constants of the synthetic truths (the demo's): s0 MPa, QR K, xi, m
TRUTH = {"s0": 12.92, "QR": 10586.0, "xi": 2.04, "m": 0.1}
#: shares of the way from "off" toward the box's far edge (on the box's unit-cube scale, so
#: logarithmic for a log-scale parameter); the 0.9 rung gives an effect that reaches the target
#: size before the edge a value inside the box, where a central interval can cover it
FRACTIONS = (0.05, 0.1, 0.2, 0.35, 0.5, 0.75, 0.9, 1.0)


def _ladder(eff: Any, seed: int) -> np.ndarray:
    """``(len(FRACTIONS), n_p)`` candidate values from "off" toward the box's far side, on the
    box's unit-cube scale. An effect sized by one parameter moves it alone, its form
    parameters (:attr:`~solderpyro.effects.Effect.nuisance`) held at the library's default
    form; one sized by several gets one fixed random direction (seeded)."""
    b = eff.params
    off = b.to_unit(torch.as_tensor(eff.off, dtype=torch.float64)).numpy()
    far = np.where(1.0 - off >= off, 1.0, 0.0)
    if eff.size_index is not None:
        d = np.zeros_like(off)
        d[eff.size_index] = far[eff.size_index] - off[eff.size_index]
    elif len(off) > 1:
        u = np.random.default_rng(seed).uniform(0.3, 1.0, len(off))
        u *= np.random.default_rng(seed + 1).choice([-1.0, 1.0], len(off))
        far = np.where(u > 0, 1.0, 0.0)
        d = np.abs(u) * (far - off)
    else:
        d = far - off
    lad = off[None] + np.asarray(FRACTIONS)[:, None] * d[None]
    return b.from_unit(torch.as_tensor(lad)).numpy()


def _ladder_times(setup: Any) -> tuple[float, ...]:
    """The times at which :func:`hidden_values` measures an effect's size (s)."""
    if max(EXTENDED_TIMES) <= setup.problem.cycle.end:
        return tuple(EXTENDED_TIMES)
    return tuple(setup.times)


def hidden_values(setup: Any, effect: str | Effect, target_rms: float = 0.4, seed: int = 0,
                  anand: dict[str, float] | None = None) -> tuple[np.ndarray, float]:
    """The effect's hidden parameter values and their RMS change of the point data.

    Args:
        setup: typed problem (:func:`solderpyro.config.compose.build`).
        effect: registry name, or an effect instance (a benchmark's own form).
        target_rms: the RMS change (um) of V_A, V_B at the extended times to reach (at the
            configured output times when the cycle is shorter than the reference one).
        anand: Anand constants (default :data:`TRUTH`, others from the config).
    Returns:
        ``(values (n_p,), rms_um)``; the largest ladder value when none reaches the target.
    """
    from solderpyro.analysis.sensitivity import sensitivity_box
    from solderpyro.effects import effect_set
    from solderpyro.params import anand_tensor
    from solderpyro.specimen import SpecimenModel

    times = _ladder_times(setup)
    fx = effect_set((effect,), times, setup.effect_bounds)
    eff = fx.effects[0]
    lad = _ladder(eff, seed)
    rows = np.vstack([np.asarray(eff.off, float)[None], lad])
    a = anand_tensor(anand or TRUTH, base=setup.anand, dtype=torch.float64)
    P = torch.cat([a.expand(len(rows), -1), torch.tensor(rows)], 1)
    model = SpecimenModel(setup.problem, sensitivity_box(defaults=setup.anand), times,
                          dtype=setup.dtype, effects=fx)
    V = model.run(P).V.detach().numpy()
    rms = np.sqrt(((V[1:] - V[:1]) ** 2).mean((1, 2)))
    ok = np.flatnonzero(rms >= target_rms)
    k = int(ok[0]) if len(ok) else len(rms) - 1
    return lad[k], float(rms[k])


@dataclass(frozen=True)
class HiddenTruth:
    """Where a hidden-effect dataset is made.

    Attributes:
        values: ``(n_p,)`` the effects' parameters, concatenated in the order of the effects
            (None: :func:`hidden_values` per effect).
        anand: Anand constants of the truth (None: :data:`TRUTH`).
    """

    values: np.ndarray | None = None
    anand: dict[str, float] | None = None


def make_dataset(setup: Any, effect: Any, path: str | Path, field: bool,
                 times: tuple[float, ...], noise: float = 0.05, seed: int = 0,
                 truth: HiddenTruth = HiddenTruth()) -> Path:
    """Write a measurement CSV with a hidden ``effect`` (None: a clean dataset).

    Args:
        setup: typed problem (its FE makes the data: e.g. ``mesh=fine``, or
            ``experiment=plane_strain`` for a misfit no candidate describes).
        effect: a registry name or an :class:`~solderpyro.effects.Effect` instance (e.g. a
            form of the physics other than the library's: benchmarks/forms.py), a tuple of
            them (several hidden effects, each at its own :func:`hidden_values` size), or
            None.
        path: the CSV to write. field: the 31 x 18 grid (plus A, B) instead of A and B only.
        times: observation times, s. noise: sd of the added Gaussian noise, um.
        truth: the effects' parameters and the Anand constants (:class:`HiddenTruth`).
    Returns:
        the path; metadata lines name the truth (``hidden_effect``, ``hidden_values``;
        several effects joined by ``+``).
    """
    from solderpyro.analysis.sensitivity import sensitivity_box
    from solderpyro.effects import effect_set
    from solderpyro.io.measurements import from_arrays, write_measurements
    from solderpyro.params import anand_tensor
    from solderpyro.specimen import SpecimenModel

    names = () if effect is None else (
        tuple(effect) if isinstance(effect, (tuple, list)) else (effect,))
    label = "+".join(nm if isinstance(nm, str) else nm.name for nm in names)
    values = truth.values
    truth_c = dict(truth.anand or TRUTH)
    a = anand_tensor(truth_c, base=setup.anand, dtype=torch.float64)[None]
    meta = {"generator": "solderpyro hidden-effect dataset", "truth": str(truth_c),
            "noise_sigma_um": str(noise), "hidden_effect": label or "none"}
    forms = [nm.settings() for nm in names if not isinstance(nm, str)]
    if forms:  # a form other than the library's: what it is, for the record
        meta["hidden_form"] = str(forms)
    fx: Any = None
    if names:
        fx = effect_set(names, times, setup.effect_bounds)
        if values is None:
            parts, sizes = [], []
            for nm in names:
                v, rms = hidden_values(setup, nm, seed=seed, anand=truth_c)
                parts.append(np.atleast_1d(np.asarray(v, float)))
                sizes.append(f"{rms:.4g}")
            values = np.concatenate(parts)
            meta["hidden_rms_point_um"] = ",".join(sizes)
        if np.asarray(values).size != fx.n_params:  # per-image values sized at other times
            t_l = _ladder_times(setup)
            fx_l = effect_set(names, t_l, setup.effect_bounds)
            if np.asarray(values).size != fx_l.n_params:
                raise ValueError(f"HiddenTruth.values: {np.asarray(values).size} values for "
                                 f"the {fx.n_params} parameters {', '.join(fx.names)}")
            values = fx_l.rebind_params(
                torch.as_tensor(np.asarray(values, float))[None], t_l, times)[0].numpy()
        meta["hidden_values"] = str(dict(zip(fx.names, np.asarray(values).tolist(),
                                             strict=True)))
        a = torch.cat([a, torch.tensor(np.asarray(values, float))[None]], 1)
    model = SpecimenModel(setup.problem, sensitivity_box(defaults=setup.anand), times, field,
                          dtype=setup.dtype, effects=fx or ())
    res = model.run(a)
    if not bool(res.ok.all()):
        raise RuntimeError(f"the FE solve of the hidden-effect data failed: {res.reasons[0]}")
    V = res.V[0].detach().numpy()
    pts = model.output_points.numpy()
    rng = np.random.default_rng(seed + 1000)
    y = V + noise * rng.standard_normal(V.shape)
    temps = [setup.problem.cycle(t) for t in res.times.tolist()]
    m = from_arrays(res.times.numpy(), res.names, pts, y, temperature_C=temps,
                    sigma_um=noise, meta=meta)
    write_measurements(path, m)
    return Path(path)
