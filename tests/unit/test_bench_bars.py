"""benchmarks/cases_table.py's bars: what counts as found, a false alarm and a covered truth."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
from cases_table import bars  # noqa: E402


def _run(seconds, truths, missed=(), rms=None):
    r = {"seconds": seconds, "truths": list(truths), "missed": list(missed)}
    if rms is not None:
        r["compare_rms_um"] = [0.1, rms]
    return r


def test_bars_count_selections_ties_alarms_and_the_runs_a_user_ends_with():
    """Three cases: one selected and recalibrated (s0 missed), one tie recalibrated with both
    tied effects (the wrong one misses two truths), one clean case flagged as a misfit. The
    tie counts as named, not selected; both tied recalibrations count in the coverage and the
    loop time; the clean misfit is a false alarm."""
    recs = [
        {"hidden": "lag", "selected": ["lag"], "tie": [], "misfit": True, "sigma_um": 0.05,
         "diagnose_seconds": 100, "base": _run(200, ["s0", "m"]),
         "with": _run(50, ["s0", "m", "tau"], missed=["s0"], rms=0.051)},
        {"hidden": "kin", "selected": [], "tie": [["kin", "sf"]], "misfit": True,
         "sigma_um": 0.05, "diagnose_seconds": 10, "base": _run(300, ["s0", "m"]),
         "with_kin": _run(30, ["s0", "m"]), "with_sf": _run(40, ["s0", "m"], ["s0", "m"])},
        {"hidden": "none", "selected": [], "tie": [], "misfit": True, "sigma_um": 0.05,
         "diagnose_seconds": 5, "base": _run(100, ["s0", "m"])},
    ]
    b = bars(recs)
    assert b["selected"] == [1, 2] and b["named"] == [2, 2]
    assert b["false_alarms"] == [1, 1]
    # lag: 2 of 3; tie: 2 of 2 and 0 of 2; clean base: 2 of 2
    assert b["coverage"] == [6, 9]
    assert b["coverage_per_parameter"] == {"s0": [2, 4], "m": [3, 4], "tau": [1, 1]}
    assert b["coverage_constants"] == [5, 8]
    assert b["rms_after_sd_max"] == round(0.051 / 0.05, 3)
    # loops: 200 + 100 + 50, 300 + 10 + 30 + 40, 100 + 5: median 350
    assert b["loop_s_median"] == 350 and b["loop_cases_timed"] == 3
    assert b["loop_s_by_threads"] == {"1": [350, 3]}  # no thread count: one thread
    recs[0]["threads"] = 2  # that case alone on 2 cores
    # the others: 380 and 105, median 242.5 (Python rounds half to even)
    assert bars(recs)["loop_s_by_threads"] == {"1": [242, 2], "2": [350, 1]}


def test_a_case_counts_as_caveated_only_where_selection_and_caveat_name_every_hidden_effect():
    """Hidden-effect cases not selected: where the model fits, one whose verdict cannot rule out
    the hidden effect, one that names another; a misfit case naming nothing; a two-effect case
    with one selected and the other named by the caveat. A selected case and a clean case are
    not among those counted."""
    recs = [
        {"hidden": "kin", "selected": [], "misfit": False, "cannot_rule_out": ["sf", "kin"],
         "base": _run(60, ["m"], ["m"])},
        {"hidden": "lag", "selected": [], "misfit": False, "cannot_rule_out": ["kin"],
         "base": _run(60, ["m"])},
        {"hidden": "cte", "selected": [], "misfit": True, "cannot_rule_out": [],
         "base": _run(60, ["m"])},
        {"hidden": "none", "selected": [], "misfit": False, "cannot_rule_out": ["kin"],
         "base": _run(60, ["m"])},
        {"hidden": "sf+lag", "selected": ["lag"], "misfit": True, "cannot_rule_out": ["sf"],
         "base": _run(60, ["m"])},
        {"hidden": "lag", "selected": ["lag"], "misfit": True, "cannot_rule_out": [],
         "base": _run(60, ["m"])},
    ]
    b = bars(recs)
    assert b["caveat"] == [2, 4] and b["selected"] == [1, 5]


def test_the_recalibration_a_caveat_advises_beside_the_selection_counts_as_a_final_run():
    """A selection whose verdict cannot rule out a candidate that frees the faces advises
    recalibrating with both too: a user who follows it holds both runs, so both count (the
    selection's misses all four constants, the one with both holds them) and both take time."""
    both = "with_lag+sf"
    rec = {"hidden": "lag+sf", "selected": ["lag"], "tie": [], "misfit": True,
           "sigma_um": 0.05, "diagnose_seconds": 100, "cannot_rule_out": ["sf"],
           "caveat_runs": [both], "base": _run(60, ["s0", "m"]),
           "with": _run(50, ["s0", "m"], ["s0", "m"], rms=0.05),
           both: _run(70, ["s0", "m"], rms=0.049)}
    b = bars([rec])
    assert b["coverage_per_parameter"] == {"s0": [1, 2], "m": [1, 2]}
    assert b["loop_s_median"] == 60 + 100 + 50 + 70
    assert b["caveat"] == [1, 1] and b["selected"] == [0, 1]  # named by the caveat


def test_where_a_diagnosis_gives_intervals_admitting_what_it_cannot_rule_out_they_are_scored(
        tmp_path):
    """A base run whose summary.csv misses the true m, and whose diagnosis's
    intervals_admitting.csv holds it: the truth counts as covered; without the file, not."""
    from diagnosis_cases import _covered

    (tmp_path / "summary.csv").write_text(
        "parameter,q2.5,median,mean,q97.5,lo95,hi95,interval\n"
        "s0,10,12,12,14,10,14,central\nm,0.05,0.06,0.06,0.066,0.05,0.066,central\n")
    truth = {"s0": 12.5, "m": 0.07}
    assert _covered(tmp_path, truth) == {"s0": True, "m": False}
    (tmp_path / "intervals_admitting.csv").write_text(
        "parameter,lo95,hi95,reported_lo95,reported_hi95\n"
        "s0,10,14,10,14\nm,0.05,0.078,0.05,0.066\n")
    assert _covered(tmp_path, truth) == {"s0": True, "m": True}
