"""Read and write measured displacement data (the long-form CSV of docs/data-format.md).

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

from solderpyro.io.text import read_text

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


@dataclass(frozen=True)
class _Columns:
    """Where a file's columns are: ``index`` name -> position, ``ncol`` fields per row,
    ``value_col`` the column read as the value (``value_um`` or ``fringe_order``)."""

    index: dict[str, int]
    ncol: int
    value_col: str


def _split_lines(spath: str) -> tuple[dict[str, str], list[str], int, list[tuple[int, list[str]]]]:
    """Read a file into its metadata, header and data rows.

    Blank lines are skipped; ``# key: value`` comment lines become metadata, other comments are
    skipped; the first other line is the header.

    Returns:
        ``(meta, header, header_line, rows)``: the ``# key: value`` pairs, the header's stripped
        column names, its 1-based line number and, per data row, its 1-based line number and
        stripped cells.

    Raises:
        ValueError: for a file without a header line or one that is not UTF-8 text.
        OSError: if it cannot be read.
    """
    lines = read_text(spath).splitlines()
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
    return meta, header, header_line, rows


def _map_columns(spath: str, header: list[str], header_line: int) -> _Columns:
    """Check the header (no empty or duplicate names, the required columns present) and pick
    the value column: ``value_um`` when present (logged if ``fringe_order`` is too), else
    ``fringe_order``.

    Raises:
        ValueError: naming the file and the header's line.
    """
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
        if "fringe_order" in col:
            log.info("%s: both value_um and fringe_order present; using value_um", spath)
        return _Columns(col, len(header), "value_um")
    if "fringe_order" in col:
        return _Columns(col, len(header), "fringe_order")
    raise _fail(
        spath, header_line,
        "missing required column value_um (or fringe_order)", f"header: {', '.join(header)}",
    )


def _fringe_scale(spath: str, meta: Mapping[str, str], header_line: int,
                  grating_lines_per_mm: float | None) -> float:
    """µm per fringe, ``1000 / f``, for a fringe-order file (V = N / f mm = 1000 N / f µm).

    ``f`` (lines/mm) is ``grating_lines_per_mm`` when given, else the file's
    ``# grating_lines_per_mm:`` metadata.

    Raises:
        ValueError: naming the file for a missing, non-numeric or non-positive frequency.
    """
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
    return 1000.0 / f


#: One parsed V row: time_s, temperature_C, point, x_mm, y_mm, value (file units), sigma_um.
_Row = tuple[float, float, str, float, float, float, float]


def _parse_row(spath: str, lineno: int, cells: list[str], cols: _Columns) -> _Row | None:
    """Parse and check one data row's cells; None for a ``U`` row (dropped).

    Temperature and sigma are NaN where their column is absent or the cell empty; the value is
    in the file's units (µm, or fringes for ``fringe_order``).

    Raises:
        ValueError: naming the file, ``lineno`` and the column, for a wrong field count, a
            missing or unknown quantity, a missing / non-numeric / non-finite value, or a
            non-positive ``sigma_um``.
    """
    ncol, col = cols.ncol, cols.index
    if len(cells) < ncol or (len(cells) > ncol and any(c for c in cells[ncol:])):
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
        return None

    def num(name: str, optional: bool = False) -> float:
        if name not in col:
            return math.nan
        return _parse_float(cells[col[name]], name, spath, lineno, optional=optional)

    t = num("time_s")
    p = cells[col["point"]]
    if p == "" or p.lower() == "nan":
        raise _fail(spath, lineno, "missing value in column point")
    x, y, v = num("x_mm"), num("y_mm"), num(cols.value_col)
    temp, sig = num("temperature_C", optional=True), num("sigma_um", optional=True)
    if not math.isnan(sig) and sig <= 0:
        raise _fail(spath, lineno, f"sigma_um must be > 0, got {sig!r} in column sigma_um")
    return t, temp, p, x, y, v, sig


def _check_point(spath: str, lineno: int, row: _Row,
                 valid_points: Mapping[str, tuple[float, float]] | None,
                 first_xy: dict[str, tuple[float, float, int]]) -> None:
    """Check a row's point: one of ``valid_points`` at its coordinates (within
    ``COORD_TOL_MM`` mm) when given, else at the coordinates of its first row, which
    ``first_xy`` (label -> (x_mm, y_mm, line)) records.

    Raises:
        ValueError: naming the file, ``lineno`` and the point.
    """
    _, _, p, x, y, _, _ = row
    if valid_points is not None:
        if p not in valid_points:
            raise _fail(
                spath, lineno,
                f"point {p!r} in column point is not a model output point",
                _point_hint(p, list(valid_points)),
            )
        vx, vy = (float(c) for c in valid_points[p])
        if abs(x - vx) > COORD_TOL_MM or abs(y - vy) > COORD_TOL_MM:
            raise _fail(
                spath, lineno,
                f"coordinates (x_mm, y_mm) = ({x!r}, {y!r}) of point {p!r} disagree with "
                f"the model's ({vx!r}, {vy!r}) by more than {COORD_TOL_MM} mm",
            )
        return
    prev = first_xy.setdefault(p, (x, y, lineno))
    if abs(x - prev[0]) > COORD_TOL_MM or abs(y - prev[1]) > COORD_TOL_MM:
        raise _fail(
            spath, lineno,
            f"coordinates (x_mm, y_mm) = ({x!r}, {y!r}) of point {p!r} disagree with "
            f"({prev[0]!r}, {prev[1]!r})",
            f"the same point was given at line {prev[2]}",
        )


def _assemble(parsed: list[_Row], scale: float, meta: dict[str, str]) -> Measurements:
    """:class:`Measurements` of the parsed V rows, values times ``scale`` (µm per file unit)."""
    t, temp, p, x, y, v, sig = (list(c) for c in zip(*parsed, strict=True))
    return Measurements(
        time_s=np.array(t), temperature_C=np.array(temp), point=np.array(p, dtype=object),
        x_mm=np.array(x), y_mm=np.array(y),
        quantity=np.array(["V"] * len(t), dtype=object),
        value_um=np.array([vi * scale for vi in v]), sigma_um=np.array(sig), meta=meta,
    )


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
    meta, header, header_line, rows = _split_lines(spath)
    cols = _map_columns(spath, header, header_line)
    scale = (_fringe_scale(spath, meta, header_line, grating_lines_per_mm)
             if cols.value_col == "fringe_order" else 1.0)
    parsed: list[_Row] = []
    first_xy: dict[str, tuple[float, float, int]] = {}
    for lineno, cells in rows:
        row = _parse_row(spath, lineno, cells, cols)
        if row is not None:
            _check_point(spath, lineno, row, valid_points, first_xy)
            parsed.append(row)
    n_u = len(rows) - len(parsed)
    if n_u:
        log.info("%s: dropped %d row(s) with quantity U (only V is used)", spath, n_u)
    if not parsed:
        if rows:
            raise _fail(spath, None, f"no data rows with quantity V ({n_u} U row(s) dropped)")
        raise _fail(spath, None, "no data rows after the header")
    return _assemble(parsed, scale, meta)


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
