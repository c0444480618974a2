"""The verdict's pure functions (solderpyro.diagnose.verdict) on a linear toy: an explained
misfit names its effect and its check, a clean fit flags nothing, where() points at the largest
residual, and what the data cannot rule out is added to the verdict."""

from types import SimpleNamespace

import numpy as np
import pytest

from solderpyro.diagnose.decide import Floor, Refit, forward_steps
from solderpyro.diagnose.diagnosis import Diagnosis
from solderpyro.diagnose.stats import misfit, predictive_check, score_test
from solderpyro.diagnose.verdict import (
    VerdictInputs,
    add_cannot_rule_out,
    check,
    headline,
    rank_candidates,
    unexplained_text,
    verdict,
    where,
)

N = 200
X = np.linspace(0.0, 1.0, N)
JT = np.column_stack([np.ones(N), X])
SIG = {"a": np.sin(3 * np.pi * X), "b": np.exp(-((X - 0.3) / 0.05) ** 2)}


def _inputs(y: np.ndarray, sigma: float, sig: dict | None = None) -> VerdictInputs:
    SIG_ = SIG if sig is None else sig

    def chi2(cols):
        A = np.column_stack(cols)
        r = y - A @ np.linalg.lstsq(A, y, rcond=None)[0]
        return float(r @ r) / sigma**2

    base = chi2([JT])
    first = [Refit((e,), chi2([JT, SIG_[e][:, None]]), 1, np.zeros(0), base) for e in SIG_]

    def nxt(cur, chosen, others):
        return [Refit((*chosen, c), chi2([JT, *[SIG_[e][:, None] for e in (*chosen, c)]]), 1,
                      np.zeros(0), cur.chi2) for c in others]

    steps, chosen, tie = forward_steps(first, nxt, N, 2, sigma, Floor(), len(SIG_))
    w = np.full(N, 1 / sigma**2)
    r = y - JT @ np.linalg.lstsq(JT, y, rcond=None)[0]
    scores = [score_test(e, r, JT, SIG_[e][:, None], w) for e in SIG_]
    pc = predictive_check(y, np.tile(y, (20, 1)), np.full(20, sigma))
    return VerdictInputs(misfit(r, JT, w), pc, scores, [scores], sigma, steps, chosen, tie,
                         base, 2, Floor())


def test_an_explained_misfit_names_its_effect_and_ranks_it_first():
    rng = np.random.default_rng(0)
    sigma = 0.05
    y = JT @ np.array([1.0, 2.0]) + 0.3 * SIG["a"] + sigma * rng.standard_normal(N)
    v = _inputs(y, sigma)
    ranking, failed = rank_candidates(v)
    assert [e["effect"] for e in ranking] == ["a", "b"] and failed == []
    assert ranking[0]["correlation_with_top"] == pytest.approx(1.0)
    dg = verdict(v)
    assert dg.misfit and dg.explained is True and dg.selected == ["a"]
    assert "Best explanation: a" in dg.verdict and headline(v) in dg.verdict
    c = check(v)
    assert c["chi2"] == v.base_chi2 and c["dof"] == N - 2
    assert c["rms_um"] == pytest.approx(np.sqrt(v.base_chi2 / N) * sigma)
    assert dg.check == c and len(dg.steps) == len(v.steps)


def test_a_clean_fit_flags_nothing():
    rng = np.random.default_rng(1)
    sigma = 0.05
    y = JT @ np.array([1.0, 2.0]) + sigma * rng.standard_normal(N)
    dg = verdict(_inputs(y, sigma))
    assert not dg.misfit and dg.explained is None and dg.selected == []
    assert dg.verdict.startswith("the model fits")
    assert not any(e["flagged"] for e in dg.ranking)


def test_where_points_at_the_largest_standardized_residual():
    meas = SimpleNamespace(point=["A", "B", "C"], time_s=np.array([600.0, 900.0, 1500.0]))
    fp = SimpleNamespace(smooth=None, residual=np.array([0.01, -0.2, 0.05]))
    text = where(meas, fp, 0.05)
    assert "point B, t = 900 s" in text and "-4.0 noise sd" in text


def test_what_the_data_cannot_rule_out_is_added_to_the_verdict(monkeypatch):
    dg = Diagnosis(False, "the model fits", [], {}, [], [])
    eff = SimpleNamespace(name="cu", n_params=1, size_index=0,
                          params=SimpleNamespace(names=("cu_yield",), units=("MPa",)))
    found = [{"effect": "cu", "outside": ["m"], "value": 15.0, "shift": {"m": -0.03}}]
    fx_all = SimpleNamespace(effects=[eff])
    monkeypatch.setattr("solderpyro.diagnose.verdict.describe",
                        lambda r, param, unit: f"{r['effect']} {param} {unit}")
    add_cannot_rule_out(dg, found, fx_all)
    assert dg.cannot_rule_out[0]["text"] == "cu cu_yield MPa"
    assert "cannot rule out cu, which would move m outside" in dg.verdict
    assert dg.suggestions == ["recalibrate with effects=[cu] to see the constants' intervals if "
                              "it is present: these data cannot tell"]
    empty = Diagnosis(False, "fits", [], {}, [], [])
    add_cannot_rule_out(empty, [], fx_all)
    assert empty.verdict == "fits" and empty.suggestions == [] and empty.cannot_rule_out == []


def test_an_unexplained_verdict_never_says_a_refit_below_the_bar_is_above_it():
    """"None of the candidates" quotes the best testable refit's RMS; it says "above the 1.5"
    only when it is (a refit at the noise level that was not selected is named as such)."""
    def v(chi2):
        r = SimpleNamespace(refit=SimpleNamespace(ok=True, dof=1, chi2=chi2))
        return SimpleNamespace(steps=[[r]], n=N, n_cal=2, chosen=("a",), tie=[])
    high = unexplained_text(v(4.0 * N), "misfit")
    assert "2.00 noise sd, above the 1.5" in high
    low = unexplained_text(v(1.1**2 * N), "misfit")
    assert "1.10 noise sd" in low and "above" not in low and "not selected" in low


def test_a_tie_after_a_selected_effect_keeps_the_selection():
    """The strong effect a explains the misfit on its own (within 1.5 noise sd); what remains
    with it on (a alone leaves 1.34 noise sd, 0.2 bump amplitude), two nearly identical bumps
    take up alike: the verdict selects a, says
    the data cannot attribute the remainder, and advises recalibrating with a."""
    rng = np.random.default_rng(1)
    sigma = 0.05
    bump = np.exp(-((X - 0.6) / 0.05) ** 2)
    sig = {"a": np.sin(3 * np.pi * X), "b": bump,
           "c": np.exp(-((X - 0.6005) / 0.05) ** 2)}
    y = JT @ np.array([1.0, 2.0]) + 0.3 * sig["a"] + 0.2 * bump \
        + sigma * rng.standard_normal(N)
    v = _inputs(y, sigma, sig)
    assert v.chosen == ("a",) and sorted(v.tie) == ["b", "c"]
    dg = verdict(v)
    assert dg.selected == ["a"] and dg.explained is True
    assert "Best explanation: a" in dg.verdict and "cannot attribute" in dg.verdict
    assert dg.suggestions[0].endswith("effects=[a]")
