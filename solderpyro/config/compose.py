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

import logging
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from solderpyro.config.settings import SurrogateSettings, register_configs
from solderpyro.effects import EFFECTS, EffectSet, effect_set
from solderpyro.fem.loading import (
    EXTENDED_TIMES,
    SEED_TIMES,
    ThermalCycle,
    TimeStepping,
    read_profile_csv,
    repeat_cycle,
    simplify_profile,
)
from solderpyro.fem.mesh import Layer, MeshSpec, XSegment, on_material
from solderpyro.fem.problem import LAWS, Problem
from solderpyro.params import ANAND_NAMES, Box, ParameterSpace, check_anand_values

log = logging.getLogger(__name__)

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
    out += [f"mesh.x_segments.{k}.nx={max(int(sg.nx) // 2, 1)}"
            for k, sg in enumerate(mesh.get("x_segments") or [])]
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
class Alloy:
    """The solder a materials file describes: its ``alloy`` entry.

    Attributes:
        name: the alloy, e.g. ``Sn37Pb`` or ``SAC305`` (compared by ``predict``).
        source: where the file's constants come from (a citation).
    """

    name: str
    source: str


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
    #: the solder's alloy and the constants' source (the materials file's ``alloy`` entry)
    alloy: Alloy | None = None

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
        if key in ("anand", "calibrate", "alloy"):
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
        x1 = lay.get("x1_mm")
        layers.append(Layer(str(lay.name), str(lay.material), float(lay.y0_mm), float(lay.y1_mm),
                            int(rows.ny), float(rows.get("grading", 1.0)),
                            str(rows.get("toward", "none")),
                            None if x1 is None else float(x1)))
    mats.update(_specimen_materials(sp, mats))
    st = cfg.solver.stepping
    conv = {"max_depth": int, "scheme": str, "max_iter": int}
    try:
        stepping = TimeStepping(**{k: conv.get(k, float)(v) for k, v in st.items()})
    except (TypeError, ValueError) as e:
        raise ValueError(f"config solver.stepping: {e}") from None
    cycle, T_ref_C, out_times = _loading(cfg.loading)
    points = _points(sp, tuple(layers))
    problem = Problem(
        layers=tuple(layers), materials=mats, half_length=float(sp.half_length_mm),
        mesh=MeshSpec(int(mc.nx), float(mc.x_grading), bool(mc.half), _x_segments(mc)),
        plane=str(sp.plane), T_ref_C=T_ref_C, cycle=cycle, stepping=stepping, points=points,
        origin=(float(sp.origin[0]), float(sp.origin[1])),
        incompatible_modes=bool(mc.incompatible_modes))
    dt = {"float64": torch.float64, "float32": torch.float32}.get(str(cfg.solver.dtype))
    if dt is None:
        raise ValueError(f"config solver.dtype must be float64|float32, got {cfg.solver.dtype!r}")
    names, bounds = _effects(cfg)
    return Setup(problem, space, anand, out_times, dt, str(cfg.solver.device),
                 _surrogate(cfg), names, bounds, _alloy(cfg))


def _material(m, path: str):
    """A material law from its config entry ``{E_GPa, nu, cte_ppm, law}`` at ``path``."""
    E = _num(m, "E_GPa", path, 1e-6) * 1e3
    nu = _num(m, "nu", path, -0.999, 0.4999)
    a = _num(m, "cte_ppm", path, -1e3, 1e3) * 1e-6
    law = str(m.get("law", "elastic"))
    if law not in LAWS:
        raise ValueError(f"config {path}.law must be one of {sorted(LAWS)}, got {law!r}")
    return LAWS[law](E=E, nu=nu, alpha=a)


def _specimen_materials(sp, mats: Mapping[str, Any]) -> dict[str, Any]:
    """The specimen file's own materials (``materials: {key: {E_GPa, nu, cte_ppm}}``, e.g. a
    die's silicon), added to those of the materials group; a key both define is an error."""
    out = {}
    for key, m in (sp.get("materials") or {}).items():
        if key in mats:
            raise ValueError(f"config specimen.materials.{key}: the materials group defines "
                             f"{key!r} too; give the specimen's material another name")
        out[str(key)] = _material(m, f"specimen.materials.{key}")
    return out


def _points(sp, layers: tuple[Layer, ...]) -> dict[str, tuple[float, float]]:
    """The output points ``{name: (x, y)}`` mm, each on the material of a layer."""
    pts = {str(k): (float(v[0]), float(v[1])) for k, v in sp.points.items()}
    half = float(sp.half_length_mm)
    try:
        for k, xy in pts.items():
            if not on_material(layers, half, xy):
                raise ValueError(f"config specimen.points.{k}={list(xy)} mm lies off the "
                                 f"material (outside every layer's y range and x extent)")
    except ValueError as e:
        raise ValueError(str(e) if str(e).startswith("config") else
                         f"config specimen.layers: {e}") from None
    return pts


def _x_segments(mc) -> tuple[XSegment, ...]:
    """``mesh.x_segments``: ``[{nx, grading, toward: left|right|none}, ...]`` (none: empty)."""
    out = []
    for k, sg in enumerate(mc.get("x_segments") or []):
        nx = sg.get("nx")
        if not isinstance(nx, int) or nx < 1:
            raise ValueError(f"config mesh.x_segments[{k}].nx must be a positive integer, "
                             f"got {nx!r}")
        toward = str(sg.get("toward", "none"))
        if toward not in ("left", "right", "none"):
            raise ValueError(f"config mesh.x_segments[{k}].toward must be left, right or none, "
                             f"got {toward!r}")
        out.append(XSegment(nx, _num(sg, "grading", f"mesh.x_segments[{k}]", 1e-6)
                            if "grading" in sg else 1.0, toward))
    return tuple(out)


#: default ``loading.profile_tol_C``: the largest temperature error (K) of the simplified profile
PROFILE_TOL_C = 0.5


def _profile_path(name: str) -> Path:
    """``loading.profile_csv`` as a file: absolute, or relative to the working directory, else
    to the packaged ``conf/loading/`` directory (the shipped profiles)."""
    p = Path(name).expanduser()
    if p.is_absolute() or p.is_file():
        return p
    packaged = CONFIG_DIR / "loading" / p
    if packaged.is_file():
        return packaged
    raise FileNotFoundError(f"config loading.profile_csv={name}: no such file in the working "
                            f"directory ({Path.cwd()}) nor in {CONFIG_DIR / 'loading'}")


def _profile(ld) -> tuple[Any, Any, float]:
    """Knots ``(times (n,), temps (n,))`` s, degC of the loading group, and how close (K) its
    last temperature must be to its first one to repeat it."""
    has_csv = ld.get("profile_csv") is not None
    has_knots = ld.get("times_s") is not None or ld.get("temps_C") is not None
    if has_csv == has_knots:
        raise ValueError("config loading: give either profile_csv (a CSV file of time_s, temp_C) "
                         "or times_s and temps_C, " + ("not both" if has_csv else "got neither"))
    if not has_csv:
        try:
            c = ThermalCycle(tuple(float(t) for t in ld.times_s),
                             tuple(float(t) for t in ld.temps_C))
        except (TypeError, ValueError) as e:
            raise ValueError(f"config loading.times_s/temps_C: {e}") from None
        return c.times, c.temps_C, 1e-9
    tol = _num(ld, "profile_tol_C", "loading", 0.0) if "profile_tol_C" in ld else PROFILE_TOL_C
    path = _profile_path(str(ld.profile_csv))
    try:
        t, T = read_profile_csv(path)
    except ValueError as e:
        raise ValueError(f"config loading.profile_csv: {e}") from None
    keep = simplify_profile(t, T, tol)
    log.info("loading.profile_csv %s: %d rows simplified to %d knots (within %g K)", path,
             len(t), len(keep), tol)
    return t[keep], T[keep], tol


def _loading(ld) -> tuple[ThermalCycle, float, tuple[float, ...]]:
    """The loading group as ``(cycle, stress-free temperature degC, output times s)``."""
    t, T, close = _profile(ld)
    cycles = ld.get("cycles", 1)
    if not isinstance(cycles, int) or cycles < 1:
        raise ValueError(f"config loading.cycles must be a positive integer, got {cycles!r}")
    T = [float(x) for x in T]
    if cycles > 1:
        if abs(T[-1] - T[0]) > close:
            raise ValueError(f"config loading.cycles={cycles} repeats the profile, which must end "
                             f"at its start temperature: it goes {T[0]:g} -> {T[-1]:g} degC")
        T[-1] = T[0]
    cycle = repeat_cycle(t, T, cycles)
    T0 = cycle(0.0)
    T_ref = float(ld.stress_free_C) if ld.get("stress_free_C") is not None else T0
    if abs(T_ref - T0) > 1e-9:
        raise ValueError(f"config loading.stress_free_C={T_ref:g} differs from the profile's "
                         f"temperature at t = 0 ({T0:g} degC): the solve starts stress-free at "
                         f"t = 0, so start the profile at the stress-free temperature")
    spec = ld.get("output_times")
    word = spec.strip().lower() if isinstance(spec, str) else None
    if spec is None or word == "ends":
        return cycle, T_ref, cycle.cycle_ends
    if word in ("seed", "extended") and (ld.get("profile_csv") is not None or cycles > 1):
        raise ValueError(f"config loading.output_times={spec}: the reference cycle's times do "
                         f"not apply to a measured profile or repeated cycles; use 'ends' (the "
                         f"cycle ends) or a list of seconds")
    return cycle, T_ref, parse_times(spec)


def _alloy(cfg) -> Alloy | None:
    """The materials file's ``alloy: {name, source}``; None where it has none."""
    a = cfg.materials.get("alloy")
    if a is None:
        return None
    for key in ("name", "source"):
        if not str(a.get(key) or "").strip():
            raise ValueError(f"config materials.alloy.{key} must be a non-empty string")
    return Alloy(str(a.name), str(a.source))


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
