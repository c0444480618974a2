"""Read and write measured displacement data (the long-form CSV of shared/data-format.md).

File format (one row per measured value, header required, any column order)::

    # specimen: S1                      <- '# key: value' comment lines become metadata
    # grating_lines_per_mm: 2400
    time_s,temperature_C,point,x_mm,y_mm,quantity,value_um,sigma_um
    600.0,75.0,A,15.0,4.5,V,1.234,0.05
    ...

Required columns: ``time_s``, ``point``, ``x_mm``, ``y_mm``, ``quantity`` and one of
``value_um`` (µm) or ``fringe_order`` (Moiré fringe order N, converted with V = N / f, f the
virtual reference grating frequency in lines/mm, so that V [µm] = 1000 N / f). Optional:
``temperature_C`` (°C) and ``sigma_um`` (µm, the measurement's standard deviation). Extra columns
are ignored. Rows with quantity ``U`` are dropped (with a logged note); only ``V`` (vertical
displacement relative to O) is kept.

Every problem in a file raises :class:`ValueError` with a message naming the file, the 1-based
line number in the file (comments and header included) and the offending column or point.
"""

from __future__ import annotations

import csv
import difflib
import logging
import math
import os
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

__all__ = ["Measurements", "read_measurements", "write_measurements", "from_arrays"]

log = logging.getLogger(__name__)

#: Column order used by :func:`write_measurements`.
COLUMNS = (
    "time_s", "temperature_C", "point", "x_mm", "y_mm", "quantity", "value_um", "sigma_um",
)
REQUIRED_COLUMNS = ("time_s", "point", "x_mm", "y_mm", "quantity")
KNOWN_QUANTITIES = ("V", "U")
#: Tolerance (mm) when comparing file coordinates with the model's output points.
COORD_TOL_MM = 1e-6
#: Metadata key holding the Moiré grating frequency (lines/mm) in fringe-order files.
GRATING_KEY = "grating_lines_per_mm"

_META_RE = re.compile(r"^#\s*([A-Za-z_][A-Za-z0-9_.\-]*)\s*:\s?(.*?)\s*$")


@dataclass(frozen=True, eq=False)
class Measurements:
    """Long-form measured data. All arrays have shape (n_obs,).

    Arrays are copied on construction and made read-only.

    Attributes:
        time_s: (n_obs,) float, time since the start of the thermal cycle, s.
        temperature_C: (n_obs,) float, specimen temperature, °C (NaN where unknown).
        point: (n_obs,) object array of str, point labels (``'A'``, ``'B'``, ``'g_12_05'``...).
        x_mm: (n_obs,) float, x of the measured point, mm (specimen frame).
        y_mm: (n_obs,) float, y of the measured point, mm (specimen frame).
        quantity: (n_obs,) object array of str, always ``'V'`` (vertical displacement rel. to O).
        value_um: (n_obs,) float, measured value, µm.
        sigma_um: (n_obs,) float, measurement standard deviation, µm (NaN where unknown).
        meta: metadata from ``# key: value`` comment lines (str -> str).
    """

    time_s: np.ndarray
    temperature_C: np.ndarray
    point: np.ndarray
    x_mm: np.ndarray
    y_mm: np.ndarray
    quantity: np.ndarray
    value_um: np.ndarray
    sigma_um: np.ndarray
    meta: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        n = None
        for name in ("time_s", "temperature_C", "x_mm", "y_mm", "value_um", "sigma_um"):
            arr = np.array(getattr(self, name), dtype=float).reshape(-1)
            arr.setflags(write=False)
            object.__setattr__(self, name, arr)
            n = arr.shape[0] if n is None else n
            if arr.shape[0] != n:
                raise ValueError(f"Measurements.{name} has {arr.shape[0]} entries, expected {n}")
        for name in ("point", "quantity"):
            vals = np.asarray(getattr(self, name)).reshape(-1)
            arr = np.empty(vals.shape[0], dtype=object)
            arr[:] = [str(v) for v in vals]
            arr.setflags(write=False)
            object.__setattr__(self, name, arr)
            if arr.shape[0] != n:
                raise ValueError(f"Measurements.{name} has {arr.shape[0]} entries, expected {n}")
        object.__setattr__(self, "meta", {str(k): str(v) for k, v in dict(self.meta).items()})

    def __len__(self) -> int:
        """Number of observations (rows), n_obs."""
        return int(self.time_s.shape[0])

    def times(self) -> np.ndarray:
        """Sorted unique observation times.

        Returns:
            (n_time,) float array, s.
        """
        return np.unique(self.time_s)

    def points(self) -> list[str]:
        """Unique point labels in first-seen order.

        Returns:
            List of n_point labels.
        """
        return list(dict.fromkeys(self.point.tolist()))

    def to_table(
        self,
        times: Sequence[float] | np.ndarray | None = None,
        points: Sequence[str] | None = None,
        *,
        field_name: str = "value_um",
    ) -> np.ndarray:
        """Gather the values into a dense (time, point) table.

        Times are matched with a relative tolerance of 1e-9 (absolute 1e-9 s near 0). Rows at
        times or points not requested are ignored.

        Args:
            times: (n_time,) requested times, s. Default: :meth:`times`.
            points: n_point requested labels. Default: :meth:`points`.
            field_name: which per-row array to tabulate (``'value_um'``, ``'sigma_um'``,
                ``'temperature_C'``).

        Returns:
            (n_time, n_point) float array of the field (µm for values), NaN where missing.

        Raises:
            ValueError: if two rows fall on the same (time, point) cell.
        """
        t_req = self.times() if times is None else np.asarray(times, dtype=float).reshape(-1)
        p_req = self.points() if points is None else [str(p) for p in points]
        data = np.asarray(getattr(self, field_name), dtype=float)
        table = np.full((t_req.shape[0], len(p_req)), np.nan)
        if len(self) == 0 or t_req.size == 0 or not p_req:
            return table
        col_of = {p: j for j, p in enumerate(p_req)}
        tol = 1e-9 * np.maximum(1.0, np.abs(self.time_s))
        close = np.abs(self.time_s[:, None] - t_req[None, :]) <= tol[:, None]
        filled = np.zeros(table.shape, dtype=bool)
        for k in range(len(self)):
            j = col_of.get(self.point[k])
            if j is None:
                continue
            hits = np.flatnonzero(close[k])
            if hits.size == 0:
                continue
            i = int(hits[0])
            if filled[i, j]:
                raise ValueError(
                    f"duplicate observation for point {p_req[j]} at time {t_req[i]!r} s"
                )
            table[i, j] = data[k]
            filled[i, j] = True
        return table


def _fail(path: str, line: int | None, msg: str, hint: str = "") -> ValueError:
    where = f" at line {line}" if line is not None else ""
    tail = f"; {hint}" if hint else ""
    return ValueError(f"{path}: {msg}{where}{tail}")


def _parse_float(text: str, column: str, path: str, line: int, *, optional: bool) -> float:
    """Parse one numeric cell; empty/NaN is an error unless ``optional`` (then NaN)."""
    s = text.strip()
    if s == "" or s.lower() in ("nan", "+nan", "-nan"):
        if optional:
            return math.nan
        raise _fail(path, line, f"missing value in column {column}")
    try:
        v = float(s)
    except ValueError:
        raise _fail(path, line, f"non-numeric value {s!r} in column {column}") from None
    if not math.isfinite(v):
        raise _fail(path, line, f"non-finite value {s!r} in column {column}")
    return v


def _point_hint(label: str, valid: Sequence[str]) -> str:
    close = difflib.get_close_matches(label, valid, n=3, cutoff=0.6)
    shown = ", ".join(valid[:8]) + (", ..." if len(valid) > 8 else "")
    hint = f"valid points ({len(valid)}): {shown}"
    if close:
        hint = f"did you mean {', '.join(close)}? " + hint
    return hint


def read_measurements(
    path: str | os.PathLike,
    valid_points: Mapping[str, tuple[float, float]] | None = None,
    grating_lines_per_mm: float | None = None,
) -> Measurements:
    """Read a long-form measurement CSV.

    Args:
        path: the CSV file.
        valid_points: the model's output points, label -> (x_mm, y_mm). When given, every row's
            point must be one of them, at coordinates within 1e-6 mm. Without it, a label must
            keep the same coordinates throughout the file.
        grating_lines_per_mm: virtual reference grating frequency f (lines/mm) for files with a
            ``fringe_order`` column; overrides ``# grating_lines_per_mm:`` in the file.

    Returns:
        The ``V`` rows as :class:`Measurements` (n_obs rows, values in µm, times in s).
        ``temperature_C`` and ``sigma_um`` are NaN where absent or empty.

    Raises:
        ValueError: with the file, 1-based line and column named, for a missing column,
            non-numeric / empty / NaN / non-finite value, non-positive ``sigma_um``, unknown
            quantity, a point not in ``valid_points``, coordinates disagreeing with
            ``valid_points`` (or with an earlier row of the same point), a missing grating
            frequency in fringe-order mode, a malformed row, or a file without data rows.
        OSError: if the file cannot be read.
    """
    spath = os.fspath(path)
    with open(spath, encoding="utf-8-sig", newline="") as fh:
        lines = fh.read().splitlines()

    meta: dict[str, str] = {}
    header: list[str] | None = None
    header_line = 0
    rows: list[tuple[int, list[str]]] = []
    for lineno, raw in enumerate(lines, start=1):
        stripped = raw.strip()
        if not stripped:
            continue
        if stripped.startswith("#"):
            mm = _META_RE.match(stripped)
            if mm:
                meta[mm.group(1)] = mm.group(2)
            continue
        cells = [c.strip() for c in next(csv.reader([raw]))]
        if header is None:
            header, header_line = cells, lineno
        else:
            rows.append((lineno, cells))

    if header is None:
        raise _fail(spath, None, "empty file: no header line found")
    seen: set[str] = set()
    for name in header:
        if name == "":
            raise _fail(spath, header_line, "empty column name in header")
        if name in seen:
            raise _fail(spath, header_line, f"duplicate column {name}")
        seen.add(name)
    col = {name: i for i, name in enumerate(header)}
    for name in REQUIRED_COLUMNS:
        if name not in col:
            raise _fail(
                spath, header_line,
                f"missing required column {name}", f"header: {', '.join(header)}",
            )
    if "value_um" in col:
        fringe = False
        value_col = "value_um"
        if "fringe_order" in col:
            log.info("%s: both value_um and fringe_order present; using value_um", spath)
    elif "fringe_order" in col:
        fringe = True
        value_col = "fringe_order"
    else:
        raise _fail(
            spath, header_line,
            "missing required column value_um (or fringe_order)", f"header: {', '.join(header)}",
        )

    scale = 1.0
    if fringe:
        if grating_lines_per_mm is not None:
            f = float(grating_lines_per_mm)
            src = "argument grating_lines_per_mm"
        elif GRATING_KEY in meta:
            try:
                f = float(meta[GRATING_KEY])
            except ValueError:
                raise _fail(
                    spath, None,
                    f"non-numeric metadata {GRATING_KEY}: {meta[GRATING_KEY]!r}",
                ) from None
            src = f"metadata '# {GRATING_KEY}:'"
        else:
            raise _fail(
                spath, header_line,
                f"column fringe_order needs the grating frequency: add '# {GRATING_KEY}: <f>' "
                "to the file or pass grating_lines_per_mm",
            )
        if not (math.isfinite(f) and f > 0):
            raise _fail(spath, None, f"grating frequency from {src} must be > 0, got {f!r}")
        scale = 1000.0 / f  # µm per fringe: V = N / f [mm] = 1000 N / f [µm]

    valid_names = list(valid_points) if valid_points is not None else []
    has_temp = "temperature_C" in col
    has_sigma = "sigma_um" in col
    out_t: list[float] = []
    out_T: list[float] = []
    out_p: list[str] = []
    out_x: list[float] = []
    out_y: list[float] = []
    out_v: list[float] = []
    out_s: list[float] = []
    first_xy: dict[str, tuple[float, float, int]] = {}
    n_u = 0
    ncol = len(header)
    for lineno, cells in rows:
        if len(cells) < ncol:
            raise _fail(spath, lineno, f"expected {ncol} fields, found {len(cells)}")
        if len(cells) > ncol and any(c for c in cells[ncol:]):
            raise _fail(spath, lineno, f"expected {ncol} fields, found {len(cells)}")

        q = cells[col["quantity"]]
        if q == "":
            raise _fail(spath, lineno, "missing value in column quantity")
        if q not in KNOWN_QUANTITIES:
            raise _fail(
                spath, lineno,
                f"unknown quantity {q!r} in column quantity",
                f"expected one of {', '.join(KNOWN_QUANTITIES)}",
            )
        if q == "U":
            n_u += 1
            continue

        t = _parse_float(cells[col["time_s"]], "time_s", spath, lineno, optional=False)
        p = cells[col["point"]]
        if p == "" or p.lower() == "nan":
            raise _fail(spath, lineno, "missing value in column point")
        x = _parse_float(cells[col["x_mm"]], "x_mm", spath, lineno, optional=False)
        y = _parse_float(cells[col["y_mm"]], "y_mm", spath, lineno, optional=False)
        v = _parse_float(cells[col[value_col]], value_col, spath, lineno, optional=False)
        temp = (
            _parse_float(cells[col["temperature_C"]], "temperature_C", spath, lineno,
                         optional=True)
            if has_temp else math.nan
        )
        sig = (
            _parse_float(cells[col["sigma_um"]], "sigma_um", spath, lineno, optional=True)
            if has_sigma else math.nan
        )
        if not math.isnan(sig) and sig <= 0:
            raise _fail(spath, lineno, f"sigma_um must be > 0, got {sig!r} in column sigma_um")

        if valid_points is not None:
            if p not in valid_points:
                raise _fail(
                    spath, lineno,
                    f"point {p!r} in column point is not a model output point",
                    _point_hint(p, valid_names),
                )
            vx, vy = (float(c) for c in valid_points[p])
            if abs(x - vx) > COORD_TOL_MM or abs(y - vy) > COORD_TOL_MM:
                raise _fail(
                    spath, lineno,
                    f"coordinates (x_mm, y_mm) = ({x!r}, {y!r}) of point {p!r} disagree with "
                    f"the model's ({vx!r}, {vy!r}) by more than {COORD_TOL_MM} mm",
                )
        else:
            prev = first_xy.setdefault(p, (x, y, lineno))
            if abs(x - prev[0]) > COORD_TOL_MM or abs(y - prev[1]) > COORD_TOL_MM:
                raise _fail(
                    spath, lineno,
                    f"coordinates (x_mm, y_mm) = ({x!r}, {y!r}) of point {p!r} disagree with "
                    f"({prev[0]!r}, {prev[1]!r})",
                    f"the same point was given at line {prev[2]}",
                )

        out_t.append(t)
        out_T.append(temp)
        out_p.append(p)
        out_x.append(x)
        out_y.append(y)
        out_v.append(v * scale if fringe else v)
        out_s.append(sig)

    if n_u:
        log.info("%s: dropped %d row(s) with quantity U (only V is used)", spath, n_u)
    if not out_t:
        if rows:
            raise _fail(spath, None, f"no data rows with quantity V ({n_u} U row(s) dropped)")
        raise _fail(spath, None, "no data rows after the header")

    return Measurements(
        time_s=np.array(out_t), temperature_C=np.array(out_T), point=np.array(out_p, dtype=object),
        x_mm=np.array(out_x), y_mm=np.array(out_y),
        quantity=np.array(["V"] * len(out_t), dtype=object),
        value_um=np.array(out_v), sigma_um=np.array(out_s), meta=meta,
    )


def _fmt(v: float) -> str:
    v = float(v)
    return "" if math.isnan(v) else repr(v)


def write_measurements(
    path: str | os.PathLike,
    m: Measurements,
    meta: Mapping[str, str] | None = None,
) -> None:
    """Write measurements as a long-form CSV that :func:`read_measurements` reads back exactly.

    Columns: time_s, temperature_C, point, x_mm, y_mm, quantity, value_um, sigma_um. Floats are
    written with ``repr`` (shortest exact round trip); NaN temperature/sigma are left empty.
    ``m.meta`` (updated with ``meta``) is written first as ``# key: value`` lines.

    Args:
        path: the output file (overwritten).
        m: the data, n_obs rows (times in s, coordinates in mm, values and sigma in µm).
        meta: extra metadata; overrides keys of ``m.meta``.

    Raises:
        ValueError: for NaN/infinite time, coordinates or values, a metadata key that is not an
            identifier-like word, or a metadata value containing a newline.
    """
    all_meta = dict(m.meta)
    if meta:
        all_meta.update({str(k): str(v) for k, v in meta.items()})
    for k, v in all_meta.items():
        if not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_.\-]*", k):
            raise ValueError(f"metadata key {k!r} is not a valid key (letters, digits, _ . -)")
        if "\n" in v or "\r" in v:
            raise ValueError(f"metadata value for {k!r} contains a newline")
    for name in ("time_s", "x_mm", "y_mm", "value_um"):
        arr = getattr(m, name)
        if not np.all(np.isfinite(arr)):
            k = int(np.flatnonzero(~np.isfinite(arr))[0])
            raise ValueError(f"cannot write non-finite {name} at row {k} (point {m.point[k]})")
    with open(os.fspath(path), "w", encoding="utf-8", newline="") as fh:
        for k, v in all_meta.items():
            fh.write(f"# {k}: {v}\n")
        w = csv.writer(fh, lineterminator="\n")
        w.writerow(COLUMNS)
        for i in range(len(m)):
            w.writerow([
                _fmt(m.time_s[i]), _fmt(m.temperature_C[i]), m.point[i], _fmt(m.x_mm[i]),
                _fmt(m.y_mm[i]), m.quantity[i], _fmt(m.value_um[i]), _fmt(m.sigma_um[i]),
            ])


def from_arrays(
    times: Sequence[float] | np.ndarray,
    names: Sequence[str],
    coords: Sequence[Sequence[float]] | np.ndarray,
    values: np.ndarray,
    temperature_C: Sequence[float] | np.ndarray | float | None = None,
    sigma_um: np.ndarray | float | None = None,
    meta: Mapping[str, str] | None = None,
) -> Measurements:
    """Build long-form measurements from dense arrays (e.g. a model prediction plus noise).

    Rows are ordered time-major: all points at ``times[0]``, then all at ``times[1]``, ...

    Args:
        times: (n_time,) observation times, s.
        names: n_out point labels.
        coords: (n_out, 2) point coordinates (x, y), mm.
        values: (n_time, n_out) vertical displacement V relative to O, µm.
        temperature_C: (n_time,) temperature at each time, °C, or a scalar; None -> NaN.
        sigma_um: standard deviation, µm: scalar, (n_out,) or (n_time, n_out); None -> NaN.
        meta: metadata (str -> str).

    Returns:
        :class:`Measurements` with n_time * n_out rows, quantity ``'V'``.

    Raises:
        ValueError: on inconsistent shapes, non-finite values, or non-positive sigma.
    """
    t = np.asarray(times, dtype=float).reshape(-1)
    labels = [str(n) for n in names]
    xy = np.asarray(coords, dtype=float)
    vals = np.asarray(values, dtype=float)
    nt, no = t.shape[0], len(labels)
    if xy.shape != (no, 2):
        raise ValueError(f"coords has shape {xy.shape}, expected ({no}, 2)")
    if vals.shape != (nt, no):
        raise ValueError(f"values has shape {vals.shape}, expected ({nt}, {no})")
    if not np.all(np.isfinite(vals)):
        raise ValueError("values contains NaN or infinite entries")
    if temperature_C is None:
        temp = np.full(nt, np.nan)
    else:
        temp = np.broadcast_to(np.asarray(temperature_C, dtype=float), (nt,))
    if sigma_um is None:
        sig = np.full((nt, no), np.nan)
    else:
        sig = np.broadcast_to(np.asarray(sigma_um, dtype=float), (nt, no))
        if np.any(sig[~np.isnan(sig)] <= 0):
            raise ValueError("sigma_um must be > 0")
    return Measurements(
        time_s=np.repeat(t, no),
        temperature_C=np.repeat(temp, no),
        point=np.array(labels * nt, dtype=object),
        x_mm=np.tile(xy[:, 0], nt),
        y_mm=np.tile(xy[:, 1], nt),
        quantity=np.array(["V"] * (nt * no), dtype=object),
        value_um=vals.reshape(-1),
        sigma_um=np.array(sig).reshape(-1),
        meta=dict(meta or {}),
    )
