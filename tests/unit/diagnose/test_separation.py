"""Which measurement separates equally good refits (solderpyro.diagnose.separation), on FE
outputs given by a stand-in for the run store: the new values of each candidate measurement,
the chi-square of the hardest pair over them, the ranking and the advice. No FE is run.
(The diagnose command runs it end to end in tests/experiments/test_diagnose_command.py.)"""

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from solderpyro.diagnose.decide import APART_CHI2
from solderpyro.diagnose.separation import separation, separation_options
from solderpyro.fem.loading import EXTENDED_TIMES
from solderpyro.fem.problem import reference_grid

SIGMA = 0.05
GRID = reference_grid()[0]
NAMES = ["A", "B"] + GRID
T_MEAS = (600.0, 2700.0)


def _setup():
    return SimpleNamespace(problem=SimpleNamespace(cycle=SimpleNamespace(end=7800.0),
                                                   points={"A": (15.0, 4.5), "B": (15.0, -4.0)}),
                           space=SimpleNamespace(dim=2), effect_bounds={})


def _meas():
    t = np.repeat(T_MEAS, 2)
    return SimpleNamespace(times=lambda: T_MEAS, time_s=t, point=np.array(["A", "B"] * 2))


class FakeFE:
    """Stands in for SpecimenModels.runs: three rows whose outputs differ by known amounts."""

    def __init__(self, ok=(True, True, True)):
        self.ok, self.calls = ok, []

    def runs(self, rows, times, field, fx, keep=None):
        self.calls.append((rows.shape, tuple(times), field, fx))
        T = len(times)
        V = np.zeros((3, T, len(NAMES)))
        i48 = times.index(4800.0)
        V[1, i48, 0] = 0.5  # A at 4800 s (not measured): 0.5 um = 10 sd
        V[1, :, 2:] = 0.01  # the whole grid at every time: 0.2 sd
        V[1, times.index(600.0), 0] = 10.0  # measured already: must not count
        V[2] = 2.0 * V[1]  # row 2 is twice as far from row 0; rows 1-2 as far as 0-1
        return SimpleNamespace(V=torch.as_tensor(V), ok=torch.tensor(self.ok), times=times,
                               names=NAMES, reasons=["" if o else "diverged" for o in self.ok])


def test_options_count_only_new_values_and_rank_by_the_hardest_pair():
    """Points at the extended times: 2 x 7 - 4 measured = 10 new values, the hardest pair
    (0-1 and 1-2 tie; the first is kept) differs by 0.5 um at one of them: chi2 = 100. Full
    field at the 2 measured times: 1116 values of 0.01 um: chi2 = 44.64; at the 7 extended
    times: 3906 values: chi2 = 156.24. Best first; the measured (600 s, A) value of 10 um
    counts in none."""
    fe = FakeFE()
    X = np.array([[12.0, 9000.0], [13.0, 9500.0], [14.0, 10000.0]])
    opts, failed = separation_options(_setup(), (), X, ["a", "b", "c"], _meas(), SIGMA, fe=fe)
    assert failed is None
    assert fe.calls[0][1] == tuple(sorted(set(T_MEAS) | set(EXTENDED_TIMES)))
    assert fe.calls[0][2] is True and fe.calls[0][3] is None
    got = {o["measurement"]: o for o in opts}
    pts = got["V at the points at the extended times"]
    ff_m = got["full-field V (31 x 18 grid) at the measured times"]
    ff_e = got["full-field V (31 x 18 grid) at the extended times"]
    assert (pts["n_new"], ff_m["n_new"], ff_e["n_new"]) == (10, 1116, 3906)
    assert pts["chi2_apart"] == pytest.approx(0.5**2 / SIGMA**2, rel=1e-12)
    assert ff_m["chi2_apart"] == pytest.approx(1116 * 0.01**2 / SIGMA**2, rel=1e-12)
    assert ff_e["chi2_apart"] == pytest.approx(3906 * 0.01**2 / SIGMA**2, rel=1e-12)
    assert [o["measurement"] for o in opts] == [ff_e["measurement"], pts["measurement"],
                                                ff_m["measurement"]]
    assert pts["pair"] == ["a", "b"] and pts["max_diff_um"] == pytest.approx(0.5)
    assert pts["time_s"] == 4800.0 and pts["point"] == "A" and pts["xy_mm"] == [15.0, 4.5]
    assert pts["rms_diff_um"] == pytest.approx(np.sqrt(0.25 / 10), rel=1e-12)
    assert ff_e["max_diff_um"] == pytest.approx(0.01) and ff_e["point"] in GRID


def test_advice_names_the_best_measurement_or_says_none_separates():
    fits = {k: {"x": np.array([12.0 + i, 9000.0])} for i, k in enumerate("abc")}
    out = separation(_setup(), (), (), fits, ["a", "b", "c"], _meas(), SIGMA, fe=FakeFE())
    assert out["effects"] == ["a", "b", "c"] and len(out["options"]) == 3
    assert 156.24 >= APART_CHI2
    assert out["advice"].startswith("to tell a, b and c apart, measure full-field V (31 x 18 "
                                    "grid) at the extended times")
    # noise 100x larger: every chi2 falls below APART_CHI2 (1.56 at most)
    out = separation(_setup(), (), (), fits, ["a", "b", "c"], _meas(), 100 * SIGMA,
                     fe=FakeFE())
    assert out["options"][0]["chi2_apart"] < APART_CHI2
    assert "no measurement tried" in out["advice"]
    one = separation(_setup(), (), (), fits, ["a"], _meas(), SIGMA, fe=FakeFE())
    assert one["options"] == [] and one["advice"].startswith("a: no measurement tried")


def test_a_failed_fe_row_gives_no_options_and_says_which():
    fits = {k: {"x": np.array([12.0, 9000.0])} for k in "abc"}
    out = separation(_setup(), (), (), fits, ["a", "b", "c"], _meas(), SIGMA,
                     fe=FakeFE(ok=(True, False, True)))
    assert out["options"] == [] and "best fit of b did not converge" in out["advice"]


def test_bad_rows_are_named():
    with pytest.raises(ValueError, match="need >= 2 rows and one label per row"):
        separation_options(_setup(), (), np.zeros((1, 2)), ["a"], _meas(), SIGMA, fe=FakeFE())
    with pytest.raises(ValueError, match=r"X must have 2 columns .* got shape \(2, 3\)"):
        separation_options(_setup(), (), np.zeros((2, 3)), ["a", "b"], _meas(), SIGMA,
                           fe=FakeFE())
