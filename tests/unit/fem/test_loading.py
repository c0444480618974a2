"""Temperature programs and the FE time grid (solderpyro.fem.loading): the reference cycle of
the reference case (docs/configuration.md), and a grid that hits every knot and output time
within the step limits."""

import numpy as np
import pytest

from solderpyro.fem.loading import (
    EXTENDED_TIMES,
    REFERENCE_CYCLE,
    SEED_TIMES,
    ThermalCycle,
    TimeStepping,
    time_grid,
)

RAMP = 5.0 / 60.0  # K/s, the reference case (docs/configuration.md)


def test_reference_cycle_is_the_specimen_md_program():
    """25 -> 75 -> 100 -> 125 -> 25 degC; every ramp at 5 degC/min, every dwell 30 min; the
    seed's observation times (a)-(d) are the dwell starts and the end of cooling, the
    extended set adds the dwell ends."""
    c = REFERENCE_CYCLE
    assert c.times == (0.0, 600.0, 2400.0, 2700.0, 4500.0, 4800.0, 6600.0, 7800.0)
    assert c.temps_C == (25.0, 75.0, 75.0, 100.0, 100.0, 125.0, 125.0, 25.0)
    t, T = np.array(c.times), np.array(c.temps_C)
    rate = np.diff(T) / np.diff(t)
    ramps, dwells = rate != 0, rate == 0
    np.testing.assert_allclose(np.abs(rate[ramps]), RAMP, rtol=1e-14)
    np.testing.assert_array_equal(np.diff(t)[dwells], 1800.0)
    assert c.end == 7800.0 and c.breakpoints == c.times and c(0.0) == 25.0
    assert SEED_TIMES == (600.0, 2700.0, 4800.0, 7800.0)
    assert [c(s) for s in SEED_TIMES] == [75.0, 100.0, 125.0, 25.0]
    assert set(EXTENDED_TIMES) == set(SEED_TIMES) | {2400.0, 4500.0, 6600.0}
    # linear between knots: 300 s into the first ramp is 25 + 300 * 5/60 = 50 degC
    assert c(300.0) == pytest.approx(50.0, rel=1e-15)
    assert c(7200.0) == pytest.approx(125.0 - 600.0 * RAMP, rel=1e-15)
    assert c(-5.0) == 25.0 and c(9000.0) == 25.0  # held at the ends


def test_cycle_and_stepping_reject_bad_input_by_name():
    with pytest.raises(ValueError, match="same length"):
        ThermalCycle((0.0, 1.0), (25.0,))
    with pytest.raises(ValueError, match="increase strictly"):
        ThermalCycle((0.0, 10.0, 10.0), (25.0, 30.0, 30.0))
    with pytest.raises(ValueError, match="stepping.scheme"):
        TimeStepping(scheme="rk4")
    for k in ("dT_max", "dwell_dt0", "dt_max", "dep_max"):
        with pytest.raises(ValueError, match=f"stepping.{k} must be > 0"):
            TimeStepping(**{k: 0.0})
    with pytest.raises(ValueError, match="stepping.growth must be >= 1"):
        TimeStepping(growth=0.9)


@pytest.mark.parametrize("ts", [TimeStepping(), TimeStepping(dT_max=1.5, dwell_dt0=3.0,
                                                             growth=1.3, dt_max=120.0)])
@pytest.mark.parametrize("out", [SEED_TIMES, EXTENDED_TIMES + (1000.0, 3333.3)])
def test_time_grid_hits_every_knot_and_respects_the_step_limits(ts, out):
    """From 0 to the cycle's end, strictly increasing; every breakpoint and output time is a
    grid point (to rounding of the rescaled cumulative sum, 1e-9 s); no step exceeds dt_max,
    no step changes the temperature by more than dT_max, the first step after each knot is at
    most dwell_dt0 and consecutive steps within a segment grow by at most ``growth``
    (rounding allowance 1e-9 relative)."""
    c = REFERENCE_CYCLE
    g = time_grid(c, out, ts)
    assert g[0] == 0.0 and g[-1] == pytest.approx(c.end, abs=1e-9)
    h = np.diff(g)
    assert np.all(h > 0)
    knots = sorted(set(c.times) | set(out))
    for k in knots:
        assert np.abs(g - k).min() < 1e-9, k
    T = np.array([c(t) for t in g])
    assert np.all(h <= ts.dt_max * (1 + 1e-9))
    assert np.all(np.abs(np.diff(T)) <= ts.dT_max * (1 + 1e-9))
    idx = [int(np.argmin(np.abs(g - k))) for k in knots]
    for a, b in zip(idx[:-1], idx[1:], strict=False):
        hs = h[a:b]
        assert hs[0] <= ts.dwell_dt0 * (1 + 1e-9)
        assert np.all(hs[1:] / hs[:-1] <= ts.growth * (1 + 1e-9))
    # the limit binds on the first ramp (600 s): 5 degC/min allows dT_max/RAMP s; fitting the
    # steps to the segment shrinks them by at most the factor 600 / (600 + cap)
    cap = min(ts.dT_max / RAMP, ts.dt_max)
    hr = h[g[1:] <= 600.0].max()
    assert cap * 600.0 / (600.0 + cap) <= hr <= cap * (1 + 1e-9)


def test_time_grid_rejects_output_times_outside_the_cycle():
    with pytest.raises(ValueError, match="output time 9000.0 s is outside the cycle"):
        time_grid(REFERENCE_CYCLE, (600.0, 9000.0), TimeStepping())
    with pytest.raises(ValueError, match="output time 0.0 s"):
        time_grid(REFERENCE_CYCLE, (0.0,), TimeStepping())


def test_time_grid_depends_on_the_cycle_only():
    """Same cycle, same outputs, same settings: the same grid (every batch member shares it);
    a cycle with twice the ramp rate takes steps half as long on its ramp (dT_max binds; the
    fit to the 1200 s segment shrinks the largest step by at most cap / (1200 + cap))."""
    ts = TimeStepping(dwell_dt0=10.0, growth=1.5, dt_max=300.0, dT_max=4.0)
    np.testing.assert_array_equal(time_grid(REFERENCE_CYCLE, SEED_TIMES, ts),
                                  time_grid(REFERENCE_CYCLE, SEED_TIMES, ts))
    slow = ThermalCycle((0.0, 1200.0), (25.0, 125.0))
    fast = ThermalCycle((0.0, 1200.0), (25.0, 225.0))
    for cyc, cap in ((slow, 4.0 / (100.0 / 1200.0)), (fast, 4.0 / (200.0 / 1200.0))):
        hmax = np.diff(time_grid(cyc, (1200.0,), ts)).max()
        assert cap * 1200.0 / (1200.0 + cap) <= hmax <= cap * (1 + 1e-9)
