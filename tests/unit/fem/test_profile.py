"""Measured temperature profiles (solderpyro.fem.loading): reading a CSV log, simplifying it to
a piecewise-linear profile within a temperature tolerance, and repeating a cycle whose ends are
knots of the time grid."""

import numpy as np
import pytest

from solderpyro.fem.loading import (
    ThermalCycle,
    TimeStepping,
    read_profile_csv,
    repeat_cycle,
    simplify_profile,
    time_grid,
)

#: one -40/125 degC cycle from and back to 25 degC: 10 degC/min ramps, 15 min dwells
KNOTS_T = np.array([0.0, 600.0, 1500.0, 2490.0, 3390.0, 3780.0])
KNOTS_C = np.array([25.0, 125.0, 125.0, -40.0, -40.0, 25.0])


def _write(tmp_path, text, name="p.csv"):
    p = tmp_path / name
    p.write_text(text)
    return p


def test_csv_reads_columns_by_header_and_starts_at_zero(tmp_path):
    """Columns are found by name in any order (others ignored), '#' lines and blank lines are
    skipped, and the times are shifted so the first row is t = 0."""
    p = _write(tmp_path, "# chamber 3\ntemp_C,chamber,time_s\n25,a,100\n\n75,b,700\n75,c,1000\n")
    t, T = read_profile_csv(p)
    np.testing.assert_array_equal(t, [0.0, 600.0, 900.0])
    np.testing.assert_array_equal(T, [25.0, 75.0, 75.0])


@pytest.mark.parametrize("text, match", [
    ("time_s,temp_C\n0,25\n60,hot\n", r"line 3, column temp_C: 'hot' is not a number"),
    ("time_s,temp_C\n0,25\n60,nan\n", r"line 3, column temp_C: 'nan' is not a number"),
    ("time_s,temp_C\n0,25\n60\n", r"line 3, column temp_C: '' is not a number"),
    ("time_s,temp_C\n0,25\n60,30\n60,35\n", r"line 4, column time_s: 60 s is not after"),
    ("time_s,temp_C\n0,25\n60,30\n30,35\n", r"line 4, column time_s: 30 s is not after"),
    ("time,temp_C\n0,25\n60,30\n", r"line 1: the header .* has no column time_s"),
    ("time_s,temp_C\n0,25\n", r"1 data row\(s\); a profile needs at least 2"),
    ("# nothing\n", r"empty"),
])
def test_csv_errors_name_the_line_and_column(tmp_path, text, match):
    with pytest.raises(ValueError, match=match):
        read_profile_csv(_write(tmp_path, text))


def test_csv_missing_file_is_named(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.csv"):
        read_profile_csv(tmp_path / "nope.csv")


def test_a_densely_logged_piecewise_linear_profile_simplifies_to_its_corners():
    """Samples every 30 s of a piecewise-linear cycle whose corners are samples: the corners
    are exactly the knots kept (any tolerance below the smallest corner's deviation)."""
    t = np.arange(0.0, 3780.0 + 1.0, 30.0)
    T = np.interp(t, KNOTS_T, KNOTS_C)
    for tol in (0.0, 0.5, 2.0):
        keep = simplify_profile(t, T, tol)
        np.testing.assert_array_equal(t[keep], KNOTS_T)


def test_simplified_profile_stays_within_the_tolerance_of_every_sample():
    """A noisy log (0.3 K rms) with a tolerance of 1 K: the kept knots' interpolant misses no
    sample by more than 1 K, far fewer knots remain than samples, and a smaller tolerance
    keeps more."""
    rng = np.random.default_rng(0)
    t = np.arange(0.0, 3780.0 + 1.0, 10.0)
    T = np.interp(t, KNOTS_T, KNOTS_C) + 0.3 * rng.standard_normal(len(t))
    keep = simplify_profile(t, T, 1.0)
    err = np.abs(np.interp(t, t[keep], T[keep]) - T)
    assert err.max() <= 1.0 + 1e-12
    assert keep[0] == 0 and keep[-1] == len(t) - 1
    assert len(keep) < len(t) // 5
    assert len(simplify_profile(t, T, 0.2)) > len(keep)
    with pytest.raises(ValueError, match="tolerance"):
        simplify_profile(t, T, -1.0)


def test_repeated_cycle_has_its_ends_on_the_time_grid():
    """Three cycles: 3 (n - 1) + 1 knots, the ends at 1, 2, 3 periods, T periodic; every end is
    a point of the time grid (where per-cycle quantities are read), also with output times
    between them."""
    c = repeat_cycle(KNOTS_T, KNOTS_C, 3)
    period = 3780.0
    assert len(c.times) == 3 * (len(KNOTS_T) - 1) + 1
    assert c.cycle_ends == (period, 2 * period, 3 * period) and c.n_cycles == 3
    assert c.end == 3 * period
    for t in np.linspace(0.0, period, 37):
        assert c(t + period) == pytest.approx(c(t), abs=1e-12)
        assert c(t + 2 * period) == pytest.approx(c(t), abs=1e-12)
    g = time_grid(c, (1000.0, 5000.0), TimeStepping())
    for tm in c.cycle_ends:
        assert np.abs(g - tm).min() < 1e-9, tm
    one = repeat_cycle(KNOTS_T, KNOTS_C, 1)
    assert one == ThermalCycle(tuple(KNOTS_T), tuple(KNOTS_C))
    assert one.cycle_ends == (3780.0,)


def test_repeating_needs_a_closed_cycle_and_ends_must_be_knots():
    with pytest.raises(ValueError, match="start temperature"):
        repeat_cycle([0.0, 600.0], [25.0, 75.0], 2)
    with pytest.raises(ValueError, match="cycles must be >= 1"):
        repeat_cycle(KNOTS_T, KNOTS_C, 0)
    repeat_cycle([0.0, 600.0], [25.0, 75.0], 1)  # one open cycle is fine
    with pytest.raises(ValueError, match="cycle_ends"):
        ThermalCycle((0.0, 600.0, 1200.0), (25.0, 75.0, 25.0), (500.0, 1200.0))
    with pytest.raises(ValueError, match="cycle_ends"):
        ThermalCycle((0.0, 600.0, 1200.0), (25.0, 75.0, 25.0), (600.0,))
    # the default: one cycle, its end
    assert ThermalCycle((0.0, 600.0), (25.0, 75.0)).cycle_ends == (600.0,)
