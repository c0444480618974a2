"""Crash-safe run store for FE runs: the records, their hashes and their files.

Layout on disk (one JSON file per completed run, written atomically)::

    root/<config_hash>/meta.json                 hash inputs in readable form
    root/<config_hash>/runs/<param_hash>.json    one run: 9 Anand constants, ok, V, ...

``config_hash`` covers everything the FE outputs depend on except the Anand constants (the
:class:`~solderpyro.fem.problem.Problem`, the output times, the field flag, the dtype, and the
physical effects switched on with their settings, so runs with effects never share a directory
with baseline runs); ``param_hash`` covers the nine constants, followed by the effects'
parameters when there are effects (exact float64 values). A record is written to a
temporary file in the same directory, flushed, fsynced and renamed over its final name, so a
crash or ``kill -9`` leaves either the whole record or none (:func:`write_atomic`). Failed
members are stored (``ok=False`` with the reason) and are not recomputed on rerun.

The solver's code is not part of the hash: after changing the solver (not the problem), use a
new ``root``. Each record names the solderpyro version that computed it.

This module imports nothing that runs FE batches: :mod:`solderpyro.compute.executor` (where batches
run, and where workers write their runs) and :mod:`solderpyro.compute.store` (the DOE runner
:func:`~solderpyro.compute.store.run_doe`) build on it.
"""

from __future__ import annotations

import base64
import dataclasses
import datetime as _dt
import enum
import functools
import hashlib
import json
import logging
import os
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from solderpyro.params import ANAND_NAMES
from solderpyro.version import __version__

log = logging.getLogger(__name__)

#: Version of the record layout; part of the config hash, so a new layout never reads old files.
STORE_SCHEMA = 1
_MAX_DEPTH = 32


def _qualname(obj: Any) -> str:
    return f"{getattr(obj, '__module__', '?')}.{getattr(obj, '__qualname__', repr(obj))}"


def _canon(obj: Any, depth: int = 0) -> Any:
    """JSON-able canonical form of ``obj``: same value -> same form in every process."""
    if depth > _MAX_DEPTH:
        raise ValueError("config_hash: object nesting too deep (a reference cycle?)")
    d = depth + 1
    if obj is None or isinstance(obj, (bool, str)):
        return obj
    if isinstance(obj, enum.Enum):
        return {"__enum__": _qualname(type(obj)), "name": obj.name}
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        return float(obj)  # json writes floats with repr: exact round trip
    if isinstance(obj, (np.ndarray, torch.Tensor)):
        a = obj.detach().cpu().numpy() if isinstance(obj, torch.Tensor) else obj
        return {"__array__": str(a.dtype), "shape": list(a.shape), "data": _canon(a.tolist(), d)}
    if isinstance(obj, (torch.dtype, torch.device, os.PathLike)):
        return str(obj)
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        # a field may say when it is left out (``metadata["omit_in_hash"](obj)``): one added
        # later, at the value that means what the class did without it, keeps old hashes
        return {"__type__": _qualname(type(obj)),
                **{f.name: _canon(getattr(obj, f.name), d) for f in dataclasses.fields(obj)
                   if not f.metadata.get("omit_in_hash", lambda o: False)(obj)}}
    if isinstance(obj, (tuple, list)):
        return [_canon(v, d) for v in obj]
    if isinstance(obj, dict):
        return {"__dict__": sorted(([_canon(k, d), _canon(v, d)] for k, v in obj.items()),
                                   key=lambda kv: json.dumps(kv[0], sort_keys=True))}
    if isinstance(obj, (set, frozenset)):
        return {"__set__": sorted((_canon(v, d) for v in obj), key=json.dumps)}
    if isinstance(obj, functools.partial):
        return {"__partial__": _canon(obj.func, d), "args": _canon(obj.args, d),
                "keywords": _canon(obj.keywords, d)}
    if isinstance(obj, type) or callable(obj) and not hasattr(obj, "__dict__"):
        return {"__callable__": _qualname(obj)}
    if callable(obj) and hasattr(obj, "__code__"):  # functions, lambdas, methods
        return {"__callable__": _qualname(obj)}
    state = {k: v for k, v in getattr(obj, "__dict__", {}).items() if not k.startswith("_")}
    return {"__type__": _qualname(type(obj)), "vars": _canon(state, d)}


def config_inputs(problem: Any, times: Sequence[float], field: bool,
                  dtype: torch.dtype, effects: Any = ()) -> dict:
    """The inputs of :func:`config_hash` in canonical, readable (JSON-able) form.

    Args:
        problem: the :class:`~solderpyro.fem.problem.Problem` (any dataclass tree works).
        times: output times, s (order does not matter: the solver reports them sorted).
        field: whether V is also reported on the full-field grid.
        dtype: torch dtype of the solve.
        effects: physical effects switched on (names, :class:`~solderpyro.effects.Effect`
            instances or an :class:`~solderpyro.effects.EffectSet`); each enters as its name and
            settings (:meth:`~solderpyro.effects.Effect.settings`), in order. Prior boxes do
            not enter (they do not change the outputs). No effects: the key is absent, so
            baseline hashes are those of stores written before effects existed.
    """
    out = {"schema": STORE_SCHEMA, "problem": _canon(problem),
           "times": sorted(float(t) for t in times), "field": bool(field), "dtype": str(dtype)}
    fx = _effect_settings(effects, times)
    if fx:
        out["effects"] = _canon(fx)
    return out


def _effect_settings(effects: Any, times: Sequence[float]) -> list[dict]:
    from solderpyro.effects import EffectSet

    if effects is None or len(effects) == 0:
        return []
    fx = effects if isinstance(effects, EffectSet) else EffectSet(list(effects))
    return fx.bind(times).settings()


def config_hash(problem: Any, times: Sequence[float], field: bool, dtype: torch.dtype,
                effects: Any = ()) -> str:
    """Short hex hash (sha256 of canonical JSON, 16 hex digits) of what the FE outputs depend
    on besides the parameters: problem (mesh, cycle, materials, plane, stepping, points, ...),
    output times, field flag, dtype and effects (see :func:`config_inputs`). Stable across
    processes and sessions."""
    text = json.dumps(config_inputs(problem, times, field, dtype, effects), sort_keys=True,
                      separators=(",", ":"), allow_nan=True)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def _as_values(values: Any) -> list[float]:
    if isinstance(values, torch.Tensor):
        values = values.detach().cpu().to(torch.float64).tolist()
    vals = [float(v) for v in np.asarray(values, dtype=np.float64).reshape(-1)]
    if len(vals) < len(ANAND_NAMES):
        raise ValueError(f"expected {len(ANAND_NAMES)} Anand constants "
                         f"({', '.join(ANAND_NAMES)}), then any effect parameters; "
                         f"got {len(vals)} values")
    return vals


def param_hash(values: Any) -> str:
    """Hex hash (24 digits) of the nine Anand constants in ANAND_NAMES order, followed by the
    effects' parameters when there are effects: ``(9 + n_eff,)``.

    Uses the exact ``repr`` of the float64 values: two sets hash alike iff they are bitwise equal
    (after conversion to float64). Nine values hash as before effects existed.
    """
    text = ",".join(repr(v) for v in _as_values(values))
    return hashlib.sha256(text.encode()).hexdigest()[:24]


def _now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


def _version() -> str:
    return str(__version__)


@dataclass(frozen=True)
class RunRecord:
    """One completed FE run.

    Attributes:
        params: the nine Anand constants by name (MPa, K, 1/s), then the effects' parameters
            by name (in column order).
        ok: False when the member failed to converge; ``reason`` says where.
        times: ``(n_time,)`` output times, s (sorted).
        names: ``n_out`` output labels.
        V: ``(n_time, n_out)`` float64 array, um; NaN where not computed (failed member).
        n_steps: grid steps of the solve; n_substeps: extra sub-steps summed over the batch
            the run was solved in (``batch_size`` members); None when the solver gave none.
        created: ISO time (UTC) of the record; version: solderpyro version that computed it.
    """

    params: dict[str, float]
    ok: bool
    reason: str
    times: tuple[float, ...]
    names: tuple[str, ...]
    V: np.ndarray
    n_steps: int | None = None
    n_substeps: int | None = None
    batch_size: int | None = None
    created: str = ""
    version: str = ""

    @property
    def param_names(self) -> list[str]:
        """ANAND_NAMES, then the effect parameters' names, ``(9 + n_eff,)``."""
        return [*ANAND_NAMES, *(k for k in self.params if k not in ANAND_NAMES)]

    @property
    def values(self) -> list[float]:
        """The constants in ANAND_NAMES order, then the effect parameters: ``(9 + n_eff,)``."""
        return [float(self.params[k]) for k in self.param_names]

    def to_json(self) -> dict:
        """The record as a JSON object; ``V`` as little-endian float64 bytes in base64
        (:func:`encode_array`: exact, NaN kept, and 4.7x faster to read back than a list of
        numbers: 0.26 vs 1.21 ms a field record, benchmarks/scaling.py store; lists from
        older records are still read)."""
        V = encode_array(self.V)
        return {"schema": STORE_SCHEMA,
                "params": {k: float(self.params[k]) for k in self.param_names},
                "ok": bool(self.ok), "reason": str(self.reason),
                "times": [float(t) for t in self.times], "names": [str(n) for n in self.names],
                "V": V, "n_steps": self.n_steps, "n_substeps": self.n_substeps,
                "batch_size": self.batch_size, "created": self.created or _now(),
                "version": self.version or _version()}

    @classmethod
    def from_json(cls, d: dict) -> RunRecord:
        """Inverse of :meth:`to_json`; raises ``ValueError``/``KeyError``/``TypeError`` when
        the dict is incomplete or inconsistent."""
        if d.get("schema") != STORE_SCHEMA:
            raise ValueError(f"record schema {d.get('schema')!r}, expected {STORE_SCHEMA}")
        params = {k: float(d["params"][k]) for k in ANAND_NAMES}
        params.update({str(k): float(v) for k, v in d["params"].items() if k not in params})
        times = tuple(float(t) for t in d["times"])
        names = tuple(str(n) for n in d["names"])
        V = decode_array(d["V"]).reshape(len(times), len(names))
        if not isinstance(d["ok"], bool):
            raise TypeError(f"record 'ok' must be a bool, got {d['ok']!r}")
        return cls(params, d["ok"], str(d["reason"]), times, names, V,
                   d.get("n_steps"), d.get("n_substeps"), d.get("batch_size"),
                   str(d.get("created", "")), str(d.get("version", "")))


def encode_array(a: np.ndarray) -> dict:
    """``a`` (any shape, cast to float64) as ``{"dtype": "<f8", "shape": [...], "base64": ...}``:
    the exact bytes, NaN and inf included."""
    x = np.ascontiguousarray(np.asarray(a, dtype="<f8"))
    return {"dtype": "<f8", "shape": list(x.shape),
            "base64": base64.b64encode(x.tobytes()).decode("ascii")}


def decode_array(v: Any) -> np.ndarray:
    """Inverse of :func:`encode_array`; also reads the nested lists of numbers (None for NaN)
    that records written before the base64 form hold. Returns float64."""
    if isinstance(v, dict):
        if v.get("dtype") != "<f8":
            raise ValueError(f"array dtype {v.get('dtype')!r}, expected '<f8'")
        x = np.frombuffer(base64.b64decode(v["base64"]), dtype="<f8")
        return x.reshape([int(n) for n in v["shape"]]).astype(np.float64)
    return np.array([[np.nan if x is None else float(x) for x in row] for row in v],
                    dtype=np.float64)


_UMASK = os.umask(0)  # the process's umask, read once (os.umask can only read by setting)
os.umask(_UMASK)


def write_atomic(path: Path, payload: dict) -> None:
    """Write ``payload`` (a JSON-able dict) as JSON to the file ``path``: a temporary file in
    the same directory, flushed, fsynced and renamed over ``path`` (then the directory is
    fsynced), so a crash leaves the old file or the new one, never a part. The file gets the
    permissions ``open()`` would give it (0666 less the umask)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.stem}.", suffix=".tmp")
    try:
        os.fchmod(fd, 0o666 & ~_UMASK)  # as open() would: mkstemp's 0600 hides the record
        with os.fdopen(fd, "w") as f:  # from the other users of a shared store
            json.dump(payload, f, indent=1, allow_nan=False)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    try:  # make the rename itself durable
        dfd = os.open(path.parent, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(dfd)
    except OSError:
        pass
    finally:
        os.close(dfd)


class RunStore:
    """Directory of FE runs, keyed by config hash and parameter hash (see module docstring).

    Args:
        root: directory of the store (created on first write).
    """

    def __init__(self, root: str | os.PathLike) -> None:
        self.root = Path(root)

    def config_dir(self, cfg_hash: str) -> Path:
        """The directory of the configuration ``cfg_hash`` (its ``meta.json`` and ``runs/``)."""
        return self.root / cfg_hash

    def register(self, problem: Any, times: Sequence[float], field: bool,
                 dtype: torch.dtype, effects: Any = ()) -> str:
        """Hash of the configuration (``effects``: as in :func:`config_inputs`); writes
        ``meta.json`` for it when missing. Returns the hash."""
        h = config_hash(problem, times, field, dtype, effects)
        meta = self.config_dir(h) / "meta.json"
        if not meta.exists():
            write_atomic(meta, {"config_hash": h, "created": _now(), "version": _version(),
                                 "inputs": config_inputs(problem, times, field, dtype,
                                                         effects)})
        return h

    def meta(self, cfg_hash: str) -> dict | None:
        """Contents of ``meta.json`` for ``cfg_hash`` (None when absent or unreadable)."""
        return self._read_json(self.config_dir(cfg_hash) / "meta.json")

    def path(self, cfg_hash: str, values: Any) -> Path:
        """File of the run with parameters ``values`` ``(9 + n_eff,)``."""
        return self.config_dir(cfg_hash) / "runs" / f"{param_hash(values)}.json"

    def put(self, cfg_hash: str, record: RunRecord) -> Path:
        """Store ``record`` atomically (replacing any earlier record of the same constants)."""
        p = self.path(cfg_hash, record.values)
        write_atomic(p, record.to_json())
        return p

    def get(self, cfg_hash: str, values: Any) -> RunRecord | None:
        """The stored run of ``values`` ``(9 + n_eff,)``, or None (missing, unreadable or
        mismatched)."""
        p = self.path(cfg_hash, values)
        rec = self._read(p)
        if rec is not None and rec.values != _as_values(values):
            log.warning("run store: %s holds other parameters than its name says; ignored", p)
            return None
        return rec

    def records(self, cfg_hash: str) -> list[RunRecord]:
        """All readable runs of ``cfg_hash`` (unreadable files are skipped with a warning)."""
        runs = self.config_dir(cfg_hash) / "runs"
        paths = sorted(runs.glob("*.json")) if runs.is_dir() else []
        return [r for r in map(self._read, paths) if r is not None]

    def _read(self, path: Path) -> RunRecord | None:
        d = self._read_json(path)
        if d is None:
            return None
        try:
            return RunRecord.from_json(d)
        except (KeyError, ValueError, TypeError, AttributeError) as e:
            log.warning("run store: skipping malformed record %s (%s: %s)", path,
                        type(e).__name__, e)
            return None

    @staticmethod
    def _read_json(path: Path) -> dict | None:
        try:
            with open(path) as f:
                d = json.load(f)
        except FileNotFoundError:
            return None
        except (OSError, ValueError) as e:  # JSONDecodeError and UnicodeDecodeError included
            log.warning("run store: skipping unreadable file %s (%s: %s)", path,
                        type(e).__name__, e)
            return None
        if not isinstance(d, dict):
            log.warning("run store: skipping %s (not a JSON object)", path)
            return None
        return d
