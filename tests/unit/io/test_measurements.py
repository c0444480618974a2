"""Tests for solderpyro.io.measurements (the long-form measurement CSV)."""

from __future__ import annotations

import logging
import re

import numpy as np
import pytest

from solderpyro.io.measurements import (
    Measurements,
    from_arrays,
    read_measurements,
    write_measurements,
)

HEADER = "time_s,temperature_C,point,x_mm,y_mm,quantity,value_um,sigma_um"


def specimen_points() -> dict[str, tuple[float, float]]:
    """A, B and the 31 x 18 grid g_ii_jj of the reference case (docs/configuration.md)."""
    pts = {"A": (15.0, 4.5), "B": (15.0, -4.0)}
    for i in range(31):
        for j in range(18):
            pts[f"g_{i:02d}_{j:02d}"] = (-15.0 + i, -4.0 + 0.5 * j)
    return pts


def write(tmp_path, text: str, name: str = "m.csv"):
    p = tmp_path / name
    p.write_text(text)
    return p


def sample(rng=None) -> Measurements:
    rng = np.random.default_rng(0) if rng is None else rng
    pts = specimen_points()
    names = ["A", "B", "g_12_05", "g_30_17"]
    coords = np.array([pts[n] for n in names])
    times = np.array([600.0, 2700.0, 4800.0, 7800.0])
    values = rng.normal(size=(4, 4)) * 3.0 + 1.0 / 3.0
    sigma = np.array([0.05, 0.1, np.nan, 0.05 / 3.0])
    return from_arrays(times, names, coords, values, temperature_C=[75.0, 100.0, 125.0, 25.0],
                       sigma_um=sigma, meta={"specimen": "S1", "source": "synthetic"})


# ----------------------------------------------------------------------------- round trip


def test_round_trip_is_exact(tmp_path):
    m = sample()
    p = tmp_path / "rt.csv"
    write_measurements(p, m, meta={"operator": "me"})
    r = read_measurements(p, valid_points=specimen_points())
    assert len(r) == len(m) == 16
    for name in ("time_s", "temperature_C", "x_mm", "y_mm", "value_um", "sigma_um"):
        np.testing.assert_array_equal(getattr(r, name), getattr(m, name), err_msg=name)
    assert r.point.tolist() == m.point.tolist()
    assert r.quantity.tolist() == ["V"] * 16
    assert r.meta == {"specimen": "S1", "source": "synthetic", "operator": "me"}
    # writing the re-read data gives the identical file
    p2 = tmp_path / "rt2.csv"
    write_measurements(p2, r)
    assert p2.read_text() == p.read_text()


def test_round_trip_awkward_floats(tmp_path):
    vals = np.array([[0.1 + 0.2, -1e-300, 5e-324, 1.7976931348623157e308, -0.0]])
    names = [f"p{k}" for k in range(5)]
    coords = np.column_stack([np.arange(5.0) / 3.0, -np.arange(5.0) / 7.0])
    m = from_arrays([1.0 / 3.0], names, coords, vals)
    p = tmp_path / "f.csv"
    write_measurements(p, m)
    r = read_measurements(p)
    np.testing.assert_array_equal(r.value_um, m.value_um)
    np.testing.assert_array_equal(r.x_mm, m.x_mm)
    np.testing.assert_array_equal(r.y_mm, m.y_mm)
    assert r.time_s[0] == 1.0 / 3.0
    assert np.all(np.isnan(r.sigma_um)) and np.all(np.isnan(r.temperature_C))


def test_written_file_layout(tmp_path):
    m = from_arrays([600.0], ["A"], [[15.0, 4.5]], [[1.5]], meta={"k": "v"})
    p = tmp_path / "w.csv"
    write_measurements(p, m)
    assert p.read_text().splitlines() == ["# k: v", HEADER, "600.0,,A,15.0,4.5,V,1.5,"]


# ----------------------------------------------------------------------------- parsing


def test_column_order_independent_and_extra_columns(tmp_path):
    a = write(tmp_path, f"{HEADER}\n600,75,A,15,4.5,V,1.25,0.05\n2700,100,B,15,-4,V,-2.5,\n", "a")
    b = write(
        tmp_path,
        "value_um,point,note,quantity,y_mm,sigma_um,time_s,x_mm,temperature_C\n"
        "1.25,A,hello,V,4.5,0.05,600,15,75\n-2.5,B,,V,-4,,2700,15,100\n",
        "b",
    )
    ra, rb = read_measurements(a), read_measurements(b)
    for name in ("time_s", "temperature_C", "x_mm", "y_mm", "value_um", "sigma_um"):
        np.testing.assert_array_equal(getattr(ra, name), getattr(rb, name), err_msg=name)
    assert ra.point.tolist() == rb.point.tolist() == ["A", "B"]
    assert np.isnan(rb.sigma_um[1]) and rb.sigma_um[0] == 0.05


def test_optional_columns_absent(tmp_path):
    p = write(tmp_path, "point,time_s,x_mm,y_mm,quantity,value_um\nA,600,15,4.5,V,1.0\n")
    r = read_measurements(p)
    assert np.isnan(r.temperature_C).all() and np.isnan(r.sigma_um).all()
    assert r.value_um.tolist() == [1.0]


def test_comments_and_meta(tmp_path):
    text = (
        "# Moire measurement of specimen S1\n"
        "# specimen: S1\n"
        "#camera : Nikon D850 \n"
        "\n"
        f"{HEADER}\n"
        "# mid-file comment, ignored\n"
        "600,75,A,15,4.5,V,1.0,0.05\n"
        "   \n"
        "# operator: someone: with colon\n"
        "2700,100,A,15,4.5,V,2.0,0.05\n"
    )
    r = read_measurements(write(tmp_path, text))
    assert len(r) == 2
    assert r.meta == {"specimen": "S1", "camera": "Nikon D850",
                      "operator": "someone: with colon"}


def test_u_rows_dropped_with_note(tmp_path, caplog):
    text = f"{HEADER}\n600,75,A,15,4.5,U,9.0,\n600,75,A,15,4.5,V,1.0,\n600,75,B,15,-4,U,8.0,\n"
    with caplog.at_level(logging.INFO, logger="solderpyro.io.measurements"):
        r = read_measurements(write(tmp_path, text))
    assert r.value_um.tolist() == [1.0] and r.quantity.tolist() == ["V"]
    assert "dropped 2 row(s) with quantity U" in caplog.text


def test_fringe_order_conversion(tmp_path):
    text = (
        "# grating_lines_per_mm: 2400\n"
        "time_s,point,x_mm,y_mm,quantity,fringe_order\n"
        "600,A,15,4.5,V,3\n"
        "600,B,15,-4,V,1\n"
    )
    r = read_measurements(write(tmp_path, text))
    assert r.value_um[0] == pytest.approx(1.25, rel=1e-14)
    assert r.value_um[1] == pytest.approx(0.4167, abs=5e-5)  # um per fringe at 2400 l/mm
    assert r.meta["grating_lines_per_mm"] == "2400"


def test_fringe_order_argument_and_missing_frequency(tmp_path):
    text = "time_s,point,x_mm,y_mm,quantity,fringe_order\n600,A,15,4.5,V,3\n"
    p = write(tmp_path, text)
    r = read_measurements(p, grating_lines_per_mm=1200.0)
    assert r.value_um[0] == pytest.approx(2.5, rel=1e-14)
    with pytest.raises(ValueError, match=r"grating_lines_per_mm.*at line 1"):
        read_measurements(p)
    with pytest.raises(ValueError, match=r"must be > 0"):
        read_measurements(p, grating_lines_per_mm=0.0)


def test_valid_points_ok(tmp_path):
    text = f"{HEADER}\n600,75,g_12_05,-3,-1.5,V,1.0,0.05\n600,75,A,15.0000000001,4.5,V,1.0,\n"
    r = read_measurements(write(tmp_path, text), valid_points=specimen_points())
    assert r.points() == ["g_12_05", "A"]


# ----------------------------------------------------------------------------- errors


def _err(tmp_path, text, **kw):
    p = write(tmp_path, text, "bad.csv")
    with pytest.raises(ValueError) as ei:
        read_measurements(p, **kw)
    msg = str(ei.value)
    assert "bad.csv" in msg
    return msg


@pytest.mark.parametrize("missing", ["time_s", "point", "x_mm", "y_mm", "quantity", "value_um"])
def test_missing_column(tmp_path, missing):
    cols = HEADER.split(",")
    cols.remove(missing)
    text = "# c\n" + ",".join(cols) + "\n" + ",".join("1" for _ in cols) + "\n"
    msg = _err(tmp_path, text)
    assert re.search(rf"missing required column {missing}.*at line 2", msg)


def test_missing_value_names_line_and_column(tmp_path):
    text = (
        "# specimen: S1\n# another comment\n\n"
        f"{HEADER}\n"
        "600,75,A,15,4.5,V,1.0,0.05\n"
        "2700,100,A,15,4.5,V,2.0,0.05\n"
        "4800,125,A,15,4.5,V,,0.05\n"
    )
    with pytest.raises(ValueError, match=r"bad\.csv.*missing value in column value_um at line 7"):
        read_measurements(write(tmp_path, text, "bad.csv"))


@pytest.mark.parametrize(
    "row, pattern",
    [
        ("600,75,A,15,4.5,V,NaN,0.05", r"missing value in column value_um at line 3"),
        ("nan,75,A,15,4.5,V,1.0,0.05", r"missing value in column time_s at line 3"),
        ("600,75,A,,4.5,V,1.0,0.05", r"missing value in column x_mm at line 3"),
        ("600,75,,15,4.5,V,1.0,0.05", r"missing value in column point at line 3"),
        ("600,75,A,15,4.5,,1.0,0.05", r"missing value in column quantity at line 3"),
        ("600,75,A,15,4.5,V,1.0x,0.05", r"non-numeric value '1.0x' in column value_um at line 3"),
        ("600,hot,A,15,4.5,V,1.0,0.05",
         r"non-numeric value 'hot' in column temperature_C at line 3"),
        ("600,75,A,15,abc,V,1.0,0.05", r"non-numeric value 'abc' in column y_mm at line 3"),
        ("600,75,A,15,4.5,V,inf,0.05", r"non-finite value 'inf' in column value_um at line 3"),
        ("600,75,A,15,4.5,V,1.0,0", r"sigma_um must be > 0.*column sigma_um at line 3"),
        ("600,75,A,15,4.5,V,1.0,-0.05", r"sigma_um must be > 0.*column sigma_um at line 3"),
        ("600,75,A,15,4.5,W,1.0,0.05", r"unknown quantity 'W' in column quantity at line 3"),
        ("600,75,A,15,4.5,V,1.0", r"expected 8 fields, found 7 at line 3"),
    ],
)
def test_bad_values(tmp_path, row, pattern):
    text = f"{HEADER}\n600,75,B,15,-4,V,1.0,0.05\n{row}\n"
    msg = _err(tmp_path, text)
    assert re.search(pattern, msg), msg


def test_unknown_point_with_hint(tmp_path):
    text = f"# c\n{HEADER}\n600,75,A,15,4.5,V,1.0,0.05\n600,75,g_12_5,-3,-1.5,V,1.0,0.05\n"
    msg = _err(tmp_path, text, valid_points=specimen_points())
    assert re.search(r"point 'g_12_5' in column point is not a model output point at line 4", msg)
    assert "at line 4" in msg
    assert "valid points (560): A, B, g_00_00" in msg
    assert "did you mean" in msg and "g_12_05" in msg


def test_coordinates_disagree_with_valid_points(tmp_path):
    text = f"{HEADER}\n600,75,A,15,4.5,V,1.0,0.05\n600,75,B,15,-3.99999,V,1.0,0.05\n"
    msg = _err(tmp_path, text, valid_points=specimen_points())
    assert re.search(r"coordinates \(x_mm, y_mm\).*point 'B' disagree.*at line 3", msg), msg


def test_coordinates_inconsistent_within_file(tmp_path):
    text = f"{HEADER}\n600,75,A,15,4.5,V,1.0,\n2700,100,A,15,4.4,V,1.0,\n"
    msg = _err(tmp_path, text)
    pattern = r"point 'A' disagree .* at line 3; the same point was given at line 2"
    assert re.search(pattern, msg), msg


@pytest.mark.parametrize(
    "text, pattern",
    [
        ("", r"empty file"),
        ("# only: comments\n\n", r"empty file"),
        (f"# c\n{HEADER}\n", r"no data rows"),
        (f"{HEADER}\n600,75,A,15,4.5,U,1.0,\n", r"no data rows with quantity V"),
    ],
)
def test_empty(tmp_path, text, pattern):
    msg = _err(tmp_path, text)
    assert re.search(pattern, msg), msg


FRINGE = "time_s,point,x_mm,y_mm,quantity,fringe_order\n600,A,15,4.5,V,3\n"


@pytest.mark.parametrize(
    "text, pattern",
    [
        ("time_s,,point\n1,2,A\n", r"empty column name in header at line 1"),
        ("# c\ntime_s,point,time_s\n1,A,2\n", r"duplicate column time_s at line 2"),
        (f"# grating_lines_per_mm: fine\n{FRINGE}",
         r"non-numeric metadata grating_lines_per_mm: 'fine'$"),
        (f"# grating_lines_per_mm: -2400\n{FRINGE}",
         r"grating frequency from metadata '# grating_lines_per_mm:' must be > 0, got -2400.0$"),
        (f"{HEADER}\n600,75,A,15,4.5,V,1.0,0.05,,x\n", r"expected 8 fields, found 10 at line 2"),
    ],
)
def test_bad_header_grating_and_row_length(tmp_path, text, pattern):
    msg = _err(tmp_path, text)
    assert re.search(pattern, msg), msg


def test_trailing_empty_fields_and_value_um_over_fringe_order(tmp_path, caplog):
    text = f"{HEADER},fringe_order\n600,75,A,15,4.5,V,1.0,0.05,7,,\n"
    with caplog.at_level(logging.INFO, logger="solderpyro.io.measurements"):
        r = read_measurements(write(tmp_path, text))
    assert r.value_um.tolist() == [1.0] and r.sigma_um.tolist() == [0.05]
    assert "both value_um and fringe_order present; using value_um" in caplog.text


# ----------------------------------------------------------------------------- API


def test_from_arrays_layout_and_table():
    m = sample()
    assert len(m) == 16
    np.testing.assert_array_equal(m.times(), [600.0, 2700.0, 4800.0, 7800.0])
    assert m.points() == ["A", "B", "g_12_05", "g_30_17"]
    assert m.point[:4].tolist() == m.points() and m.time_s[:4].tolist() == [600.0] * 4
    assert np.isnan(m.sigma_um[2]) and m.sigma_um[1] == 0.1
    assert m.temperature_C[4] == 100.0
    tab = m.to_table(m.times(), m.points())
    assert tab.shape == (4, 4)
    np.testing.assert_array_equal(tab.reshape(-1), m.value_um)


def test_to_table_missing_and_unrequested():
    m = from_arrays([600.0, 2700.0], ["A", "B"], [[15, 4.5], [15, -4]], [[1.0, 2.0], [3.0, 4.0]])
    tab = m.to_table([600.0, 4800.0, 2700.0], ["B", "C", "A"])
    assert tab.shape == (3, 3)
    expected = np.array([[2.0, np.nan, 1.0], [np.nan] * 3, [4.0, np.nan, 3.0]])
    np.testing.assert_array_equal(tab, expected)
    # unrequested rows are ignored; default arguments use all times and points
    assert m.to_table([2700.0], ["A"]).tolist() == [[3.0]]
    np.testing.assert_array_equal(m.to_table(), [[1.0, 2.0], [3.0, 4.0]])


def test_to_table_duplicate_raises():
    m = from_arrays([600.0, 600.0], ["A"], [[15, 4.5]], [[1.0], [1.1]])
    with pytest.raises(ValueError, match="duplicate observation for point A"):
        m.to_table([600.0], ["A"])


def test_measurements_arrays_read_only_and_shape_checked():
    m = sample()
    with pytest.raises(ValueError):
        m.value_um[0] = 1.0
    with pytest.raises(ValueError, match="expected 2"):
        Measurements(time_s=[1.0, 2.0], temperature_C=[np.nan] * 2, point=["A", "B"],
                     x_mm=[0.0], y_mm=[0.0, 0.0], quantity=["V", "V"], value_um=[0.0, 0.0],
                     sigma_um=[np.nan] * 2, meta={})


def test_from_arrays_shape_errors():
    with pytest.raises(ValueError, match="values has shape"):
        from_arrays([1.0], ["A", "B"], [[0, 0], [1, 1]], np.zeros((2, 2)))
    with pytest.raises(ValueError, match="coords has shape"):
        from_arrays([1.0], ["A", "B"], [[0, 0]], np.zeros((1, 2)))
    with pytest.raises(ValueError, match="sigma_um must be > 0"):
        from_arrays([1.0], ["A"], [[0, 0]], np.zeros((1, 1)), sigma_um=0.0)
