"""Config edge: compose the YAML configs (Hydra) and turn them into typed library objects.

:func:`compose` and :func:`build` (Hydra configs -> a :class:`Setup`) serve the CLI, the
experiment scripts and ``diagnose``'s reload of a run's config. :class:`Setup` is also the
typed bundle (problem, parameter space, output times, dtype, surrogate settings, effects) that
the specimen calibration (:mod:`solderpyro.specimen`) and the pipeline stages
(:mod:`solderpyro.pipeline`) take as input. The solver, the surrogate and the calibration
core take the typed objects themselves (:class:`~solderpyro.fem.problem.Problem`,
:class:`~solderpyro.params.ParameterSpace`) and never import this module.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from solderpyro.config.settings import SurrogateSettings, register_configs
from solderpyro.effects import EFFECTS, EffectSet, effect_set
from solderpyro.fem.loading import EXTENDED_TIMES, SEED_TIMES, ThermalCycle, TimeStepping
from solderpyro.fem.mesh import Layer, MeshSpec
from solderpyro.fem.problem import LAWS, Problem
from solderpyro.params import ANAND_NAMES, Box, ParameterSpace, check_anand_values

#: the packaged configs (``solderpyro/conf``, inside the installed package)
CONFIG_MODULE = "solderpyro.conf"
CONFIG_DIR = Path(__file__).resolve().parents[1] / "conf"
register_configs()  # the calibration group's schema, also for @hydra.main scripts


def config_dir_override(config_dir: str | Path) -> str:
    """The Hydra override that adds a user's config directory to the search path, after the
    packaged configs: ``hydra.searchpath=[file:///abs/DIR]`` (what Hydra's ``--config-dir``
    does for a ``@hydra.main`` script). A run's record keeps it with the other overrides, so
    ``solderpyro diagnose`` rebuilds the same model.

    The directory holds config groups as the package does (``DIR/mesh/mine.yaml``, selected
    by ``mesh=mine``; ``DIR/experiment/mine.yaml`` by ``experiment=mine``; a new group
    ``DIR/extra/x.yaml`` by ``+extra=x``). Hydra resolves a name to the first file on the
    search path, so a file named like a packaged one (``DIR/mesh/default.yaml``,
    ``DIR/config.yaml``) would be ignored: that is an error here, naming the file.

    Raises:
        FileNotFoundError: naming the directory when it is not one.
        ValueError: naming a file that shadows a packaged one.
    """
    d = Path(config_dir).expanduser().resolve()
    if not d.is_dir():
        raise FileNotFoundError(f"config directory not found: {d}")
    shadow = sorted(str(f) for f in d.rglob("*.yaml")
                    if (CONFIG_DIR / f.relative_to(d)).is_file())
    if shadow:
        raise ValueError(f"config directory {d}: {', '.join(shadow)} has the name of a packaged "
                         f"config, which takes precedence; give it a new name (e.g. "
                         f"mesh/mine.yaml) and select it (mesh=mine)")
    return f"hydra.searchpath=[file://{d}]"


def compose(overrides: list[str] | None = None, config_name: str = "config",
            config_dir: str | Path | None = None):
    """Compose the config with Hydra overrides (``key=value``); errors name the bad override.

    The packaged configs (``pkg://solderpyro.conf``) are the defaults; ``config_dir`` adds a
    directory of the user's own config groups (:func:`config_dir_override`).
    """
    from hydra import compose as _compose
    from hydra import initialize_config_module
    from hydra.core.global_hydra import GlobalHydra
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

    ov = list(overrides or [])
    if config_dir is not None:
        ov.insert(0, config_dir_override(config_dir))

    def run():
        with initialize_config_module(CONFIG_MODULE, version_base=None):
            return _compose(config_name, overrides=ov)

    try:
        if GlobalHydra.instance().is_initialized():  # inside a @hydra.main script
            saved = GlobalHydra.instance().hydra
            GlobalHydra.instance().clear()
            try:
                return run()
            finally:
                if saved is not None:
                    GlobalHydra.instance().initialize(saved)
        return run()
    except (HydraException, OmegaConfBaseException) as e:
        raise ValueError(f"bad config override in {ov}: {e}") from None


def coarsened(overrides: list[str], config_dir: str | Path | None = None) -> list[str]:
    """``overrides`` plus those that make the same model at half its resolution: half the
    elements along the length and through each row of the composed mesh (at least one), and
    twice the time steps' largest temperature change and duration.

    The cheap model of a search that only ranks starts (the diagnosis's global refits). On the
    reference specimen its field differs from the default model's by 0.011 um RMS (0.049 um
    at most) and it costs a fifth as much per run (64 runs: 7.5 s against 36 s, 2 threads).
    """
    cfg = compose(overrides, config_dir=config_dir)
    mesh, step = cfg.mesh, cfg.solver.stepping
    out = list(overrides) + [f"mesh.nx={max(int(mesh.nx) // 2, 1)}"]
    out += [f"mesh.rows.{name}.ny={max(int(row.ny) // 2, 1)}" for name, row in mesh.rows.items()]
    out += [f"solver.stepping.dT_max={2.0 * float(step.dT_max)}",
            f"solver.stepping.dt_max={2.0 * float(step.dt_max)}"]
    return out


def calibration_settings(cfg: Any, surrogate: Mapping[str, Any] | None = None) -> Any:
    """The composed config's ``calibration`` group as a
    :class:`~solderpyro.config.settings.CalibrationSettings` (its ``surrogate`` from the
    ``surrogate`` group, i.e. ``Setup.surrogate``, when given)."""
    from omegaconf import OmegaConf

    from solderpyro.config.settings import CalibrationSettings, SurrogateSettings

    d = OmegaConf.to_container(cfg.calibration, resolve=True) if "calibration" in cfg else {}
    s = CalibrationSettings.from_dict(dict(d))  # type: ignore[arg-type]
    if surrogate:
        s.surrogate = SurrogateSettings(**surrogate)
    return s


def task_overrides() -> list[str]:
    """Inside a ``@hydra.main`` script: the command line's overrides of the model (what
    the run record keeps so that ``solderpyro diagnose`` rebuilds the same model), without the
    script's own settings (``data.``, ``calibration.``, ``case.``, ``hydra.``)."""
    from hydra.core.hydra_config import HydraConfig

    return [o for o in HydraConfig.get().overrides.task
            if not o.startswith(("data.", "calibration.", "case.", "+case.", "hydra."))]


@dataclass(frozen=True)
class Setup:
    """Typed objects built from a config."""

    problem: Problem
    space: ParameterSpace
    anand: dict
    times: tuple[float, ...]
    dtype: torch.dtype
    device: str
    surrogate: dict = field(default_factory=dict)  # GPSurrogate kernel / ard / mean
    #: physical effects switched on (``effects: [...]``), names of solderpyro.effects.EFFECTS
    effects: tuple[str, ...] = ()
    #: prior-box overrides ``{effect: {param: (lower, upper)}}`` (``effect_box`` in the config)
    effect_bounds: Mapping[str, Mapping[str, tuple[float, float]]] = field(default_factory=dict)

    @property
    def effect_set(self) -> EffectSet:
        """The switched-on effects with their boxes, bound to :attr:`times` (pass it as
        ``effects=`` to :class:`~solderpyro.specimen.SpecimenModel` / the solver)."""
        return effect_set(self.effects, self.times, self.effect_bounds)

    @property
    def effect_box(self) -> Box:
        """Prior box of the effects' parameters, in column order (empty box: no effects)."""
        return self.effect_set.box


def _num(cfg, key: str, path: str, lo: float | None = None, hi: float | None = None) -> float:
    try:
        v = float(cfg[key])
    except (TypeError, ValueError, KeyError):
        raise ValueError(f"config {path}.{key} must be a number, got {cfg.get(key)!r}") from None
    if (lo is not None and v < lo) or (hi is not None and v > hi):
        raise ValueError(f"config {path}.{key}={v:g} is outside [{lo}, {hi}]")
    return v


def parse_times(spec) -> tuple[float, ...]:
    """``"seed"``, ``"extended"``, ``"t1,t2,..."`` or a list of seconds -> tuple of times."""
    if isinstance(spec, str):
        s = spec.strip().lower()
        if s == "seed":
            return SEED_TIMES
        if s == "extended":
            return EXTENDED_TIMES
        try:
            return tuple(float(t) for t in s.split(",") if t.strip())
        except ValueError:
            raise ValueError(f"times must be 'seed', 'extended' or t1,t2,... in s; "
                             f"got {spec!r}") from None
    return tuple(float(t) for t in spec)


def build(cfg) -> Setup:
    """Typed :class:`Setup` from a composed config; errors name the offending key."""
    mats = {}
    for key in ("steel", "solder", "copper"):
        if key not in cfg.materials:
            raise ValueError(f"config materials.{key} is missing")
    for key, m in cfg.materials.items():
        if key in ("anand", "calibrate"):
            continue
        E = _num(m, "E_GPa", f"materials.{key}", 1e-6) * 1e3
        nu = _num(m, "nu", f"materials.{key}", -0.999, 0.4999)
        a = _num(m, "cte_ppm", f"materials.{key}", -1e3, 1e3) * 1e-6
        law = str(m.get("law", "elastic"))
        if law not in LAWS:
            raise ValueError(f"config materials.{key}.law must be one of {sorted(LAWS)}, "
                             f"got {law!r}")
        mats[key] = LAWS[law](E=E, nu=nu, alpha=a)
    anand = {k: float(v) for k, v in cfg.materials.anand.items()}
    unknown = set(anand) - set(ANAND_NAMES)
    if unknown:
        raise ValueError(f"config materials.anand has unknown constants {sorted(unknown)}")
    check_anand_values(anand)
    cal = cfg.materials.calibrate
    names = tuple(cal.keys())
    space = ParameterSpace(names, tuple(float(cal[n][0]) for n in names),
                           tuple(float(cal[n][1]) for n in names), defaults=anand)
    sp, mc = cfg.specimen, cfg.mesh
    for key in ("nx",):
        if not isinstance(mc.get(key), int) or mc.get(key) < 1:
            raise ValueError(f"config mesh.{key} must be a positive integer, got {mc.get(key)!r}")
    layers = []
    for lay in sp.layers:
        rows = mc.rows.get(lay.name)
        if rows is None:
            raise ValueError(f"config mesh.rows has no entry for layer {lay.name!r}")
        layers.append(Layer(str(lay.name), str(lay.material), float(lay.y0_mm), float(lay.y1_mm),
                            int(rows.ny), float(rows.get("grading", 1.0)),
                            str(rows.get("toward", "none"))))
    st = cfg.solver.stepping
    conv = {"max_depth": int, "scheme": str, "max_iter": int}
    try:
        stepping = TimeStepping(**{k: conv.get(k, float)(v) for k, v in st.items()})
    except (TypeError, ValueError) as e:
        raise ValueError(f"config solver.stepping: {e}") from None
    ld = cfg.loading
    problem = Problem(
        layers=tuple(layers), materials=mats, half_length=float(sp.half_length_mm),
        mesh=MeshSpec(int(mc.nx), float(mc.x_grading), bool(mc.half)), plane=str(sp.plane),
        T_ref_C=float(ld.stress_free_C),
        cycle=ThermalCycle(tuple(float(t) for t in ld.times_s),
                           tuple(float(t) for t in ld.temps_C)),
        stepping=stepping, points={k: tuple(map(float, v)) for k, v in sp.points.items()},
        origin=(float(sp.origin[0]), float(sp.origin[1])),
        incompatible_modes=bool(mc.incompatible_modes))
    dt = {"float64": torch.float64, "float32": torch.float32}.get(str(cfg.solver.dtype))
    if dt is None:
        raise ValueError(f"config solver.dtype must be float64|float32, got {cfg.solver.dtype!r}")
    names, bounds = _effects(cfg)
    return Setup(problem, space, anand, parse_times(ld.output_times), dt, str(cfg.solver.device),
                 _surrogate(cfg), names, bounds)


def _effects(cfg) -> tuple[tuple[str, ...], dict[str, dict[str, tuple[float, float]]]]:
    """``effects`` (list of names) and ``effect_box`` (``{effect: {param: [lo, hi]}}``)."""
    valid = ", ".join(sorted(EFFECTS))
    raw = cfg.get("effects") or []
    names = (str(raw),) if isinstance(raw, str) else tuple(str(n) for n in raw)
    for n in names:
        if n not in EFFECTS:
            raise ValueError(f"config effects: unknown effect {n!r}; valid effects: {valid}")
    if len(set(names)) != len(names):
        raise ValueError(f"config effects lists an effect twice: {list(names)}")
    bounds: dict[str, dict[str, tuple[float, float]]] = {}
    for key, box in (cfg.get("effect_box") or {}).items():
        if key not in EFFECTS:
            raise ValueError(f"config effect_box.{key}: unknown effect {key!r}; valid effects: "
                             f"{valid}")
        if not hasattr(box, "items"):
            raise ValueError(f"config effect_box.{key} must map parameters to [lower, upper], "
                             f"got {box!r}")
        try:
            EFFECTS[key].with_box({str(k): v for k, v in box.items()})
        except (TypeError, ValueError) as e:
            raise ValueError(f"config effect_box.{key}: {e}") from None
        bounds[str(key)] = {str(k): (float(v[0]), float(v[1])) for k, v in box.items()}
    return names, bounds


def _surrogate(cfg) -> dict:
    """GP settings from the ``surrogate`` group (absent in older configs: the defaults)."""
    sc = cfg.get("surrogate") or {}
    out: dict[str, Any] = {
        "kernel": str(sc.get("kernel", "gaussian")), "ard": bool(sc.get("ard", True)),
        "mean": str(sc.get("mean", "constant")), "output": str(sc.get("output", "pca")),
        "inputs": str(sc.get("inputs", "raw"))}
    for key, ok in (("kernel", ("gaussian", "matern52")), ("mean", ("constant", "linear")),
                    ("output", ("pca", "batched")), ("inputs", ("raw", "flow_stress"))):
        if out[key] not in ok:
            raise ValueError(f"config surrogate.{key} must be one of {ok}, got {out[key]!r}")
    for key, default in (("inputs_T_C", 125.0), ("inputs_rate", 1e-5),
                         ("truncation", SurrogateSettings.truncation)):
        try:
            out[key] = float(sc.get(key, default))
        except (TypeError, ValueError):
            raise ValueError(f"config surrogate.{key} must be a number, got "
                             f"{sc.get(key)!r}") from None
    if not out["inputs_rate"] > 0:
        raise ValueError(f"config surrogate.inputs_rate must be > 0 (1/s), got "
                         f"{out['inputs_rate']}")
    if not out["truncation"] > 0:
        raise ValueError(f"config surrogate.truncation must be > 0 (a share of sqrt(2 n)), "
                         f"got {out['truncation']}")
    if not out["inputs_T_C"] > -273.15:
        raise ValueError(f"config surrogate.inputs_T_C must be above -273.15 degC, got "
                         f"{out['inputs_T_C']}")
    return out
