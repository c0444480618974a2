"""The run directory of ``solderpyro calibrate``, typed: what it holds, how it is written and
read back (every command and stage goes through :class:`RunDir`).

Files (names fixed: older run directories and users' scripts read them):

- ``run.json``: :class:`RunInfo`, the run's record (how it was asked for, the settings, the
  parameter box, the alloy and source of its materials file, the surrogate, the design's
  summary, the checks, the stage timings, which posterior is reported). ``schema`` is its
  version (:data:`SCHEMA`); a file without it is version 1, the same keys without ``schema``.
  A newer schema, or a required key missing, is an error naming the file and the key
  (:class:`RunDirError`). Optional keys (``data``, ``exact``, ``alloy``, the surrogate's) are
  written only where set and read as absent (None) where a file has none.
- ``data.csv``: the measurements (:mod:`solderpyro.io.measurements`, exact round trip).
- ``draws.npz``: :class:`Draws`, the reported posterior's flat draws and its predictive.
- ``posterior.nc``: the surrogate's NUTS posterior (ArviZ InferenceData), ``summary.csv``: the
  reported rows, ``sampler_state.npz``: the sampler's adapted state (``--warm-from``).
- ``diagnosis.json`` (``solderpyro diagnose``), ``comparison.json`` (``solderpyro compare``).

This module imports nothing of solderpyro at import time but the measurement reader, so that
every stage may use it without an import cycle.
"""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np

#: the version of ``run.json`` this code writes; it reads 1 (no ``schema`` key) up to this. A
#: new optional key keeps the version: a reader of the same version keeps a key it does not know
#: in ``RunInfo.extra`` and writes it back unchanged
SCHEMA = 2
RUN_JSON = "run.json"
DATA_CSV = "data.csv"
DRAWS_NPZ = "draws.npz"
POSTERIOR_NC = "posterior.nc"
SUMMARY_CSV = "summary.csv"
DIAGNOSIS_JSON = "diagnosis.json"
COMPARISON_JSON = "comparison.json"
#: the discretization correction the final posterior used (``y_measured``, ``delta`` in um)
CORRECTION_NPZ = "discretization_correction.npz"
#: the sampler's adapted state (:class:`~solderpyro.calibration.mcmc.WarmStart`)
WARM_FILE = "sampler_state.npz"
#: what a later ``solderpyro diagnose`` or ``compare`` needs of a calibration
RUN_FILES = (RUN_JSON, DATA_CSV, DRAWS_NPZ)
#: ``run.json`` keys every schema has (written with the parameter box since the first one)
REQUIRED = ("parameters", "lower", "upper", "effects", "sigma_known", "times_s", "points")
#: ``run.json`` keys of :class:`SurrogateRecord` (the record's field names differ for two)
SURROGATE_KEYS = {"kernel": "kernel", "ard": "ard", "mean": "mean",
                  "surrogate_output": "output", "surrogate_inputs": "inputs",
                  "inputs_T_C": "inputs_T_C", "inputs_rate": "inputs_rate"}


class RunDirError(ValueError):
    """A run directory's file that this version cannot read (its message names the file and
    the key or schema)."""


@dataclass
class SurrogateRecord:
    """The surrogate a run used (``run.json``'s ``kernel``, ``ard``, ``mean``,
    ``surrogate_output``, ``surrogate_inputs``, ``inputs_T_C``, ``inputs_rate``)."""

    kernel: Any = None
    ard: Any = None
    mean: Any = None
    output: Any = None
    inputs: Any = None
    inputs_T_C: Any = None
    inputs_rate: Any = None


@dataclass(frozen=True)
class AlloyRecord:
    """The solder a run calibrated: its materials file's ``alloy`` entry (``run.json``'s
    ``alloy``, ``{"name": ..., "source": ...}``).

    Attributes:
        name: the alloy, e.g. ``Sn37Pb`` or ``SAC305``.
        source: where the materials file's constants come from (a citation).
    """

    name: str
    source: str

    def to_json(self) -> dict[str, str]:
        """``{"name": ..., "source": ...}``."""
        return {"name": self.name, "source": self.source}

    @classmethod
    def from_json(cls, obj: Any, path: str | Path = RUN_JSON) -> AlloyRecord:
        """Read ``run.json``'s ``alloy`` object.

        Raises:
            RunDirError: not an object with string ``name`` and ``source`` (naming ``path``
                and the key).
        """
        if not isinstance(obj, dict):
            raise RunDirError(f"{path}: key 'alloy' must be an object with 'name' and "
                              f"'source', got {obj!r}")
        for key in ("name", "source"):
            if not isinstance(obj.get(key), str):
                raise RunDirError(f"{path}: key 'alloy.{key}' must be a string, got "
                                  f"{obj.get(key)!r}")
        return cls(obj["name"], obj["source"])


@dataclass
class Checks:
    """The calibration's checks of its own result.

    Attributes:
        fe_check: the FE at posterior draws (:func:`~solderpyro.pipeline.fe_check.fe_check`:
            ``ok``, ``rms_um`` (um), ``rms_over_sigma``, ``chi2``, ``n``, ``draws``, ...).
        discretization: the FE's discretization error against the data (``warn``,
            ``message``, ...). loo_rmse_rel, loo_coverage95: the surrogate's leave-one-out
            RMSE (share of the output spread) and 95 % coverage.
    """

    fe_check: dict[str, Any] = field(default_factory=dict)
    discretization: dict[str, Any] = field(default_factory=dict)
    loo_rmse_rel: float | None = None
    loo_coverage95: float | None = None

    @property
    def fe_ok(self) -> bool:
        """Whether the FE check accepted the posterior (False where none was recorded)."""
        return bool(self.fe_check.get("ok", False))


@dataclass
class DesignSummary:
    """The adaptive design's record (``run.json``'s ``design``, as
    :meth:`~solderpyro.design.loop.LoopResult.as_dict` writes it), with typed accessors."""

    record: dict[str, Any] = field(default_factory=dict)

    @property
    def reason(self) -> str | None:
        """Why the design stopped (``"converged"``, ``"budget"``, ``"misfit"``, ...)."""
        r = self.record.get("reason")
        return None if r is None else str(r)

    @property
    def fe_runs(self) -> int | None:
        """FE runs of the design."""
        n = self.record.get("fe_runs")
        return None if n is None else int(n)

    @property
    def budget(self) -> int | None:
        """The most FE runs the design was allowed (the set ``--budget``, or the default's
        for the box's dimension); None in records that do not say."""
        n = self.record.get("budget")
        return None if n is None else int(n)

    @property
    def best_fit(self) -> dict[str, Any]:
        """The FE's own best fit where the design made one (``x``: name -> value in physical
        units, ``chi2``, ``starts``, ...), else empty."""
        return dict(self.record.get("best_fit") or {})


@dataclass
class RunInfo:
    """``run.json``: the record of a calibration run.

    Attributes:
        parameters, lower, upper: the calibrated parameter box (names, physical units).
        effects: the switched-on effects (registry names). sigma_known: the data's stated
            noise sd (um), or None where it was calibrated. times_s: the measured times (s);
            points: the measured point labels.
        overrides: the model's config overrides (``solderpyro diagnose`` rebuilds the model
            from them). data: the measurement file as given. store: the FE run store (a
            relative path is from the working directory of the calibration). seed: RNG seed.
        settings: :meth:`~solderpyro.config.settings.CalibrationSettings.as_dict`.
        surrogate: :class:`SurrogateRecord` or None. n_runs: FE runs of the design.
        design: :class:`DesignSummary`. checks: :class:`Checks`.
        timing_s: seconds per stage. trust: the trust line. posterior: the reported
            posterior (``"surrogate"``, ``"fe-exact"``, ``"fe-best-fit"``).
        exact: the FE-exact step's record, or None. alloy: the solder of the materials file
            the run started from (:class:`AlloyRecord`), or None where the file has no
            ``alloy`` entry or ``run.json`` no ``alloy`` key. extra: any other key of
            ``run.json`` (kept as it is). schema: the version read (written as :data:`SCHEMA`).
    """

    parameters: list[str]
    lower: list[float]
    upper: list[float]
    effects: list[str]
    sigma_known: float | None
    times_s: list[float]
    points: list[str]
    overrides: list[str] = field(default_factory=list)
    data: str | None = None
    store: str | None = None
    seed: int | None = None
    settings: dict[str, Any] = field(default_factory=dict)
    surrogate: SurrogateRecord | None = None
    n_runs: int | None = None
    design: DesignSummary = field(default_factory=DesignSummary)
    checks: Checks = field(default_factory=Checks)
    timing_s: dict[str, float] = field(default_factory=dict)
    trust: str = ""
    posterior: str = "surrogate"
    exact: dict[str, Any] | None = None
    alloy: AlloyRecord | None = None
    extra: dict[str, Any] = field(default_factory=dict)
    schema: int = SCHEMA

    @property
    def sampler(self) -> dict[str, int]:
        """The final NUTS run's ``chains``, ``draws`` and ``warmup`` (from ``settings``)."""
        s = self.settings.get("sampler") or {}
        return {k: int(s[k]) for k in ("chains", "draws", "warmup") if k in s}

    def to_json(self) -> dict[str, Any]:
        """The JSON object of ``run.json`` (schema :data:`SCHEMA`; the keys of version 1 plus
        ``schema``; ``data``, ``exact``, ``alloy`` and the surrogate's keys only where set)."""
        out: dict[str, Any] = {"schema": SCHEMA, "overrides": list(self.overrides)}
        if self.data is not None:
            out["data"] = self.data
        out.update(settings=self.settings, seed=self.seed, store=self.store)
        if self.surrogate is not None:
            out.update({k: getattr(self.surrogate, f) for k, f in SURROGATE_KEYS.items()})
        c = self.checks
        out.update(n_runs=self.n_runs, design=self.design.record,
                   loo_rmse_rel=c.loo_rmse_rel, loo_coverage95=c.loo_coverage95,
                   fe_check=c.fe_check, discretization=c.discretization,
                   timing_s=self.timing_s, trust=self.trust, posterior=self.posterior)
        if self.exact is not None:
            out["exact"] = self.exact
        if self.alloy is not None:
            out["alloy"] = self.alloy.to_json()
        out.update(parameters=list(self.parameters), lower=list(self.lower),
                   upper=list(self.upper), sigma_known=self.sigma_known,
                   effects=list(self.effects), times_s=list(self.times_s),
                   points=list(self.points))
        out.update({k: v for k, v in self.extra.items() if k not in out})
        return out

    @classmethod
    def from_json(cls, obj: Any, path: str | Path = RUN_JSON) -> RunInfo:
        """Read the JSON object of ``run.json`` (``path`` names the file in errors).

        Raises:
            RunDirError: not a JSON object, a ``schema`` that is not an integer in
                1..:data:`SCHEMA`, a missing key of :data:`REQUIRED`, or a key of the wrong
                type (each message names ``path`` and the key). A missing ``alloy`` (or
                ``null``) reads as None.
        """
        if not isinstance(obj, dict):
            raise RunDirError(f"{path}: expected a JSON object, got {type(obj).__name__}")
        d = dict(obj)
        schema = d.pop("schema", 1)
        if isinstance(schema, bool) or not isinstance(schema, int) or not 1 <= schema <= SCHEMA:
            raise RunDirError(
                f"{path}: key 'schema' is {schema!r}; this solderpyro reads run.json schema 1 "
                f"to {SCHEMA} (a newer solderpyro wrote it? recalibrate, or read it with that "
                "version)")
        for key in REQUIRED:
            if key not in d:
                raise RunDirError(f"{path}: required key {key!r} is missing (run.json schema "
                                  f"{schema}); is this a run directory of 'solderpyro "
                                  "calibrate'?")
        for key in ("parameters", "lower", "upper", "effects", "times_s", "points"):
            if not isinstance(d[key], list):
                raise RunDirError(f"{path}: key {key!r} must be a list, got {d[key]!r}")
        for key in ("overrides",):
            if key in d and not isinstance(d[key], list):
                raise RunDirError(f"{path}: key {key!r} must be a list, got {d[key]!r}")
        for key in ("settings", "design", "fe_check", "discretization", "timing_s"):
            if d.get(key) is not None and not isinstance(d[key], dict):
                raise RunDirError(f"{path}: key {key!r} must be an object, got {d[key]!r}")
        sur = None
        if any(k in d for k in SURROGATE_KEYS):
            sur = SurrogateRecord(**{f: d.pop(k, None) for k, f in SURROGATE_KEYS.items()})
        checks = Checks(d.pop("fe_check", None) or {}, d.pop("discretization", None) or {},
                        d.pop("loo_rmse_rel", None), d.pop("loo_coverage95", None))
        raw_alloy = d.pop("alloy", None)
        alloy = None if raw_alloy is None else AlloyRecord.from_json(raw_alloy, path)
        simple = {f.name for f in fields(cls)} - {"surrogate", "checks", "design", "extra",
                                                  "schema", "alloy"}
        kw = {k: d.pop(k) for k in list(d) if k in simple}
        for k in ("overrides", "settings", "timing_s"):
            if kw.get(k) is None:
                kw.pop(k, None)
        design = DesignSummary(d.pop("design", None) or {})
        kw["posterior"] = str(kw.get("posterior") or "surrogate")
        kw["trust"] = str(kw.get("trust") or "")
        sk = kw["sigma_known"]
        kw["sigma_known"] = None if sk is None else float(sk)
        return cls(**kw, surrogate=sur, design=design, checks=checks, alloy=alloy, extra=d,
                   schema=schema)


@dataclass
class Draws:
    """``draws.npz``: the reported posterior's draws and its predictive.

    Attributes:
        theta: ``(n, dim)`` flat posterior draws, physical units, columns ``names``.
        sigma: ``(n,)`` noise sd draws, um. names: the parameters (``dim``).
        process: ``(n_pred, n_obs)`` predictive draws of the model (um); observed: ``(n_pred,
            n_obs)`` of a new measurement (um); sigma_pred: ``(n_pred,)`` their noise sd (um,
            NaN where none). y_obs: ``(n_obs,)`` the data the run fitted (um, the corrected
            ones where a discretization correction was used); y_liu: ``(n_obs,)`` the model
            with the literature constants (um).
    """

    theta: np.ndarray
    sigma: np.ndarray
    names: list[str]
    process: np.ndarray
    observed: np.ndarray
    y_obs: np.ndarray
    y_liu: np.ndarray
    sigma_pred: np.ndarray

    def arrays(self) -> dict[str, Any]:
        """The arrays by their ``draws.npz`` names (``names`` as a list of str)."""
        return {f.name: getattr(self, f.name) for f in fields(self)}

    def save(self, path: str | Path) -> None:
        """Write ``draws.npz`` at ``path``."""
        np.savez(path, theta=self.theta, sigma=self.sigma, names=np.array(self.names),
                 process=self.process, observed=self.observed, y_obs=self.y_obs,
                 y_liu=self.y_liu, sigma_pred=self.sigma_pred)

    @classmethod
    def load(cls, path: str | Path) -> Draws:
        """Read ``draws.npz``.

        Raises:
            FileNotFoundError: naming the file.
            RunDirError: naming it and a missing array.
        """
        p = Path(path)
        if not p.is_file():
            raise FileNotFoundError(f"{p} is missing: not a run directory written by "
                                    "'solderpyro calibrate'")
        with np.load(p) as z:
            arrays = {k: z[k] for k in z.files}
        for f in fields(cls):
            if f.name not in arrays and f.name != "sigma_pred":
                raise RunDirError(f"{p}: array {f.name!r} is missing")
        n_pred = arrays["process"].shape[0]
        return cls(theta=arrays["theta"], sigma=arrays["sigma"],
                   names=[str(n) for n in arrays["names"]], process=arrays["process"],
                   observed=arrays["observed"], y_obs=arrays["y_obs"], y_liu=arrays["y_liu"],
                   sigma_pred=arrays.get("sigma_pred", np.full(n_pred, np.nan)))


@dataclass
class RunDir:
    """A run directory and its ``run.json`` (:class:`RunInfo`); the other files are read on
    demand (:meth:`draws`, :meth:`measurements`, :meth:`summary`, :meth:`diagnosis`).

    Attributes:
        path: the directory. info: its ``run.json``.
    """

    path: Path
    info: RunInfo

    @property
    def posterior_path(self) -> Path:
        """``posterior.nc`` (may be absent)."""
        return self.path / POSTERIOR_NC

    @property
    def warm_path(self) -> Path:
        """The sampler's adapted state (``sampler_state.npz``; may be absent)."""
        return self.path / WARM_FILE

    def write(self, meas: Any = None, draws: Draws | None = None) -> RunDir:
        """Write ``run.json`` (schema :data:`SCHEMA`), and ``data.csv`` and ``draws.npz``
        where ``meas`` (:class:`~solderpyro.io.measurements.Measurements`) and ``draws`` are
        given; creates the directory. Returns self."""
        self.path.mkdir(parents=True, exist_ok=True)
        if meas is not None:
            from solderpyro.io.measurements import write_measurements

            write_measurements(self.path / DATA_CSV, meas)
        if draws is not None:
            draws.save(self.path / DRAWS_NPZ)
        text = json.dumps(self.info.to_json(), indent=2, default=str) + "\n"
        (self.path / RUN_JSON).write_text(text)
        return self

    @classmethod
    def read(cls, path: str | Path, files: tuple[str, ...] = (RUN_JSON,)) -> RunDir:
        """Read ``path/run.json``, after checking that every file of ``files`` is there
        (:data:`RUN_FILES` for a diagnosis).

        Raises:
            FileNotFoundError: naming the first missing file.
            RunDirError: naming ``run.json`` and the key (not JSON, an unknown schema, a
                required key missing).
        """
        d = Path(path)
        for f in files:
            if not (d / f).is_file():
                raise FileNotFoundError(f"{d / f} is missing: not a run directory written by "
                                        "'solderpyro calibrate'")
        p = d / RUN_JSON
        try:
            obj = json.loads(p.read_text())
        except json.JSONDecodeError as err:
            raise RunDirError(f"{p}: not JSON ({err})") from err
        return cls(d, RunInfo.from_json(obj, p))

    def draws(self) -> Draws:
        """``draws.npz`` (:class:`Draws`)."""
        return Draws.load(self.path / DRAWS_NPZ)

    def measurements(self, valid_points: Any = None) -> Any:
        """``data.csv`` as :class:`~solderpyro.io.measurements.Measurements`;
        ``valid_points``: label -> (x_mm, y_mm) the model outputs (checked where given)."""
        from solderpyro.io.measurements import read_measurements

        return read_measurements(self.path / DATA_CSV, valid_points=valid_points)

    def correction(self) -> dict[str, np.ndarray] | None:
        """The discretization correction the run used (``delta (n_obs,)``, ``y_measured
        (n_obs,)``, um), or None."""
        p = self.path / CORRECTION_NPZ
        if not p.is_file():
            return None
        with np.load(p) as z:
            return {k: z[k] for k in z.files}

    def summary(self) -> dict[str, dict[str, Any]]:
        """``summary.csv``: parameter -> its row (numbers as floats, ``interval`` the word).

        Raises:
            FileNotFoundError: naming the file.
        """
        p = self.path / SUMMARY_CSV
        if not p.is_file():
            raise FileNotFoundError(f"{p} is missing: not a run directory written by "
                                    "'solderpyro calibrate'")
        with open(p, newline="") as fh:
            return {r["parameter"]: {k: v if k == "interval" else float(v)
                                     for k, v in r.items() if k != "parameter"}
                    for r in csv.DictReader(fh)}

    def diagnosis(self) -> dict[str, Any] | None:
        """``diagnosis.json`` (``solderpyro diagnose``), or None where there is none (or it is
        not JSON)."""
        return read_json(self.path / DIAGNOSIS_JSON)

    def comparison(self) -> dict[str, Any] | None:
        """``comparison.json`` (``solderpyro compare``), or None."""
        return read_json(self.path / COMPARISON_JSON)


def read_json(path: Path) -> dict[str, Any] | None:
    """A JSON object file, or None where it is absent or not a JSON object."""
    try:
        obj = json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return None
    return obj if isinstance(obj, dict) else None


def try_read(path: str | Path) -> RunDir | None:
    """:meth:`RunDir.read`, or None where ``path`` holds no readable ``run.json`` (for pages
    that show whatever a directory holds, :mod:`solderpyro.reporting.index`)."""
    try:
        return RunDir.read(path)
    except (OSError, RunDirError):
        return None

