"""What ``predict`` solves: the calibration's own specimen and cycle, or the user's assembly
and cycle, and whether the calibration's constants apply there.

The target is the run's config with the user's overrides on top (``specimen=die_attach
loading=jedec_m40_125`` ...). Its solder takes the run's Anand constants: the calibrated ones
from the posterior draws, the others from the run's materials file. Effects follow the
constants where they belong to the solder or the materials (:attr:`Effect.transfers
<solderpyro.effects.base.Effect.transfers>`); those of the specimen, its history, the chamber or
the measurement stay with the calibration when the target is another assembly or cycle.
Observation-side effects (the Moire image's rigid motion) never enter a prediction, and an
elasto-plastic copper band is left out (the solder's fields are recorded on the one-mesh
path only); the notes say so.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from solderpyro.config.compose import Setup


@dataclass(frozen=True)
class Target:
    """The model ``predict`` solves and what it took from the calibration.

    Attributes:
        setup: the composed target (the run's overrides, then the user's).
        effects: the effects solved, in the run's order (names).
        columns: ``(n_target,)`` indices into the run's draw columns: the calibrated Anand
            constants, then the kept effects' parameters.
        names: the target's parameter names (``len(columns)``).
        transfer: whether the target is another assembly or cycle than the calibration's.
        notes: what the user should know (effects left out, elastic constants changed).
    """

    setup: Setup
    effects: tuple[str, ...]
    columns: tuple[int, ...]
    names: tuple[str, ...]
    transfer: bool
    notes: tuple[str, ...]


def _geometry(problem: Any) -> tuple:
    """What makes an assembly and its load (everything but the discretization)."""
    lay = tuple((x.name, x.material, x.y0, x.y1, getattr(x, "x1", None))
                for x in problem.layers)
    mats = tuple(sorted((k, repr(v)) for k, v in problem.materials.items()))
    return (lay, mats, problem.half_length, problem.plane, problem.T_ref_C,
            tuple(problem.cycle.times), tuple(problem.cycle.temps_C))


def build_target(run_setup: Setup, run_effects: tuple[str, ...], draw_names: list[str],
                 target_setup: Setup) -> Target:
    """The target of a prediction: ``target_setup`` with the run's constants and effects.

    Args:
        run_setup: the calibration's setup (from its ``run.json`` overrides).
        run_effects: the run's effects (names, in its order).
        draw_names: the columns of the run's draws (the calibrated constants, then the effects'
            parameters).
        target_setup: the composed target.
    Raises:
        ValueError: the target's solder is another alloy than the calibration's (naming both
            and the materials files' sources).
    """
    from solderpyro.effects import EFFECTS, effect_set

    notes: list[str] = []
    ra, ta = run_setup.alloy, target_setup.alloy
    if ra is not None and ta is not None and ra.name.lower() != ta.name.lower():
        raise ValueError(f"the calibration's constants are for {ra.name} ({ra.source}); the "
                         f"target's solder is {ta.name} ({ta.source}): predict with the "
                         f"calibration's materials, or calibrate {ta.name}")
    rs, ts = run_setup.problem.materials["solder"], target_setup.problem.materials["solder"]
    for attr, unit, scale in (("E", "GPa", 1e-3), ("nu", "", 1.0), ("alpha", "ppm/K", 1e6)):
        a, b = float(getattr(rs, attr)), float(getattr(ts, attr))
        if abs(a - b) > 1e-9 * max(abs(a), 1e-30):
            notes.append(f"the target's solder {attr} is {b * scale:g} {unit}, the "
                         f"calibration's {a * scale:g} {unit}: the calibrated constants were "
                         "fitted with the latter")
    if any(abs(float(run_setup.anand[k]) - float(v)) > 1e-12 * max(abs(float(v)), 1.0)
           for k, v in target_setup.anand.items()):
        notes.append("the target's materials file has other Anand constants; the "
                     "calibration's are used (its draws, and its file's uncalibrated ones)")
    transfer = _geometry(run_setup.problem) != _geometry(target_setup.problem)
    keep = []
    for name in run_effects:
        e = EFFECTS[name]
        if e.seam == "observation operator":
            notes.append(f"{name} describes the measurement, not the part: left out")
        elif name == "copper_plasticity":
            notes.append("copper_plasticity: the solder's fields are recorded with elastic "
                         "copper (the copper band's plasticity is left out)")
        elif transfer and not e.transfers:
            notes.append(f"{name} belongs to the calibration's specimen, history or chamber: "
                         "left out of the prediction for another assembly or cycle")
        else:
            keep.append(name)
    k = run_setup.space.n_theta
    cols = list(range(k))
    fx = effect_set(tuple(run_effects), run_setup.times, run_setup.effect_bounds)
    j = k
    for e in fx.effects:
        if e.name in keep:
            cols.extend(range(j, j + e.n_params))
        j += e.n_params
    if j != len(draw_names):
        raise ValueError(f"the run's draws have {len(draw_names)} columns ({draw_names}); its "
                         f"constants and effects make {j}")
    names = tuple(draw_names[c] for c in cols)
    return Target(target_setup, tuple(keep), tuple(cols), names, transfer, tuple(notes))


def temperature_range(setup: Setup, theta: np.ndarray | None = None,
                      names: tuple[str, ...] = ()) -> tuple[float, float]:
    """The lowest and highest temperature ``(2,)`` degC the solder sees in ``setup``'s cycle,
    with its stress-free temperature (and a ``T_sf`` draw column of ``theta`` ``(N, n)``,
    ``names``, where the stress-free temperature is calibrated)."""
    temps = [*setup.problem.cycle.temps_C, setup.problem.T_ref_C]
    if theta is not None and "T_sf" in names:
        t_sf = theta[:, names.index("T_sf")]
        temps += [float(t_sf.min()), float(t_sf.max())]
    return float(min(temps)), float(max(temps))
