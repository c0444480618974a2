"""The global refits on a toy where the screen cannot see the right candidate.

The toy: calibrated constants ``(a, b)`` on a box, data ``y = a x + b x^2 + q (b_max - b)
x^2.5`` with a hidden effect ``q = 1`` ("right") and ``b_max`` the box's upper face of ``b``.
Without the effect, ``b`` absorbs what it can and the best fit presses it against that face;
there the effect's signature ``(b_max - b) x^2.5`` vanishes, so its score (and its refit from
the base point) sees nothing, just as at the corner of the Anand box where the solder barely
creeps the stress-free temperature's signature is small. A decoy ("decoy", a cosine) scores
better at the face. Every fit below is the real Levenberg-Marquardt of the diagnosis
(:func:`solderpyro.diagnose.refits.fit_models`) through a stand-in for the FE.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from solderpyro.diagnose.decide import Floor, explained, needs_global, settled
from solderpyro.diagnose.faces import on_faces
from solderpyro.diagnose.refits import (
    Layout,
    Reach,
    base_fit,
    first_refits,
    forward,
    global_refits,
    ladder_values,
    last_gain,
    refit_candidates,
    within_reach,
)
from solderpyro.params import Box

B_MAX = 1.6
X = np.linspace(0.05, 1.0, 40)
SIGMA = 0.002


def toy_model(rows: np.ndarray) -> np.ndarray:
    """``rows (N, 4)`` = (a, b, decoy r, right q) -> ``(N, 40)`` predictions."""
    a, b, r, q = (rows[:, k, None] for k in range(4))
    return a * X + b * X**2 + q * (B_MAX - b) * X**2.5 + r * 0.05 * np.cos(4.0 * X)


class ToyFE:
    """Stands in for :class:`~solderpyro.specimen.SpecimenModels`: ``runs`` returns the toy's
    predictions as one output time with 40 named points."""

    names = tuple(f"p{i}" for i in range(len(X)))

    def runs(self, P: torch.Tensor, times, field, fx, keep=None) -> SimpleNamespace:
        V = torch.as_tensor(toy_model(P.numpy()))[:, None, :]
        return SimpleNamespace(V=V, ok=torch.ones(len(P), dtype=torch.bool), times=(0.0,),
                               names=self.names)


class ToyData:
    """The measurement as the diagnosis reads it: values, times and point labels."""

    def __init__(self, y: np.ndarray) -> None:
        self.value_um = y
        self.time_s = np.zeros(len(y))
        self.point = np.array(ToyFE.names)

    def __len__(self) -> int:
        return len(self.value_um)


@pytest.fixture(scope="module")
def toy():
    space = Box(("a", "b"), (0.5, 0.5), (2.0, B_MAX))
    setup = SimpleNamespace(space=space, anand={"a": 1.2, "b": 1.2})
    lay = Layout(setup, (), ("decoy", "right"), (0.0,), False, None, 2,
                 np.array([0.5, 0.5, 0.0, 0.0]), np.array([2.0, B_MAX, 1.0, 2.0]),
                 np.zeros(2), np.array(["decoy", "right"], dtype=object), ("a", "b", "r", "q"))
    truth = np.array([[1.0, 1.0, 0.0, 1.0]])
    y = toy_model(truth)[0] + SIGMA * np.random.default_rng(3).standard_normal(len(X))
    meas, fe = ToyData(y), ToyFE()
    base = base_fit(lay, fe, meas, SIGMA, {"posterior median": np.array([1.2, 1.2])})
    # the screen at the face: the decoy scores, the right effect's signature is zero there
    scores = [SimpleNamespace(effect="decoy", statistic=50.0, dof=1, lr=None, lr_value=None),
              SimpleNamespace(effect="right", statistic=0.0, dof=1, lr=None, lr_value=None)]
    return lay, fe, meas, base, scores


def test_the_base_fit_presses_the_constant_against_the_face_and_misfits(toy):
    lay, _, meas, base, _ = toy
    faces = on_faces(base["x"][:2], lay.setup.space)
    assert [(f.name, f.side) for f in faces] == [("b", "upper")]
    n = len(meas)
    assert not explained(base["chi2"], n, SIGMA, Floor())  # far above the noise
    assert needs_global(True, base["chi2"], n, 2, False)


def test_the_local_refit_misses_the_right_effect_and_the_global_one_finds_it(toy):
    lay, fe, meas, base, scores = toy
    n = len(meas)
    local = first_refits(lay, fe, meas, SIGMA, base, scores, scores)
    by = {r.name: r for r in local}
    # from the base point the right effect's column is zero: it stays where the base is
    assert by["right"].chi2 > base["chi2"] - 1.0
    steps, chosen, tie = forward(lay, fe, meas, SIGMA, local, Floor())
    assert not settled(steps, chosen, tie, n, SIGMA, Floor())

    nb, first = global_refits(lay, fe, meas, SIGMA, base, scores, local)
    g = {r.name: r for r in first}
    # at the noise level: chi2 within 4 sd of its expectation n - 3 (sd sqrt(2 (n - 3)))
    assert g["right"].chi2 < (n - 3) + 4 * np.sqrt(2 * (n - 3))
    assert np.allclose(g["right"].x[[0, 1, 3]], [1.0, 1.0, 1.0], atol=0.15)
    assert g["decoy"].chi2 > 10 * g["right"].chi2
    steps, chosen, tie = forward(lay, fe, meas, SIGMA, first, Floor())
    assert chosen == ("right",) and tie == []
    assert settled(steps, chosen, tie, n, SIGMA, Floor())
    assert nb["chi2"] <= base["chi2"]  # the base model can only improve from more starts


def test_ladder_values_keep_only_magnitudes_that_lowered_chi2():
    sc = [SimpleNamespace(effect="x", lr=3.0, lr_value=0.4),
          SimpleNamespace(effect="y", lr=0.0, lr_value=0.9),
          SimpleNamespace(effect="z", lr=None, lr_value=None)]
    assert ladder_values(sc) == {"x": 0.4}


class CheapToyFE(ToyFE):
    """The toy's half-resolution stand-in: its predictions off by a smooth error of a few noise
    sd (a coarser mesh's discretization error), its rows counted."""

    def __init__(self) -> None:
        self.rows = 0

    def runs(self, P: torch.Tensor, times, field, fx, keep=None) -> SimpleNamespace:
        self.rows += len(P)
        out = super().runs(P, times, field, fx)
        out.V = out.V + torch.as_tensor(3.0 * SIGMA * X**3)[None, None, :]
        return out


class CountedToyFE(ToyFE):
    def __init__(self) -> None:
        self.rows = 0

    def runs(self, P: torch.Tensor, times, field, fx, keep=None) -> SimpleNamespace:
        self.rows += len(P)
        return super().runs(P, times, field, fx)


def test_a_cheap_model_ranks_the_starts_and_the_own_fe_reaches_the_same_optimum(toy):
    """The starts scouted and converged through a model whose predictions are off by a few
    noise sd, then finished through the own FE: every candidate ends at the optimum the own FE
    alone reaches (chi2 within the stopping rule's tolerance, a few LM_TOL; the constants to
    1e-3 of their box), and the own FE evaluates fewer rows than when it does all the work."""
    from solderpyro.diagnose.refits import LM_TOL

    lay, _, meas, base, scores = toy
    alone, own, cheap = CountedToyFE(), CountedToyFE(), CheapToyFE()
    local = first_refits(lay, ToyFE(), meas, SIGMA, base, scores, scores)
    _, ref = global_refits(lay, alone, meas, SIGMA, base, scores, local)
    _, got = global_refits(lay, own, meas, SIGMA, base, scores, local, scout_fe=cheap)
    for r, g in zip(ref, got, strict=True):
        assert r.name == g.name
        assert g.chi2 == pytest.approx(r.chi2, abs=4 * LM_TOL)
        np.testing.assert_allclose(g.x[:2], r.x[:2], atol=1e-3 * (B_MAX - 0.5))
    assert cheap.rows > 0 and own.rows < alone.rows
    # the forward steps through the cheap model first decide as those through the own FE
    assert forward(lay, own, meas, SIGMA, got, Floor(), cheap)[1:] == \
        forward(lay, alone, meas, SIGMA, ref, Floor())[1:] == (("right",), [])
    # a next candidate refitted beside the chosen one ends where the own FE alone puts it
    right = next(g for g in got if g.name == "right")
    st = {"decoy": right.x.copy()}
    a = refit_candidates(lay, alone, meas, SIGMA, right.x, right.chi2, ("right",), st)[0]
    b = refit_candidates(lay, own, meas, SIGMA, right.x, right.chi2, ("right",), st, cheap)[0]
    assert b.ok and b.chi2 == pytest.approx(a.chi2, abs=4 * LM_TOL)


def test_only_refits_that_could_overtake_or_tie_with_the_best_go_on_at_full_resolution():
    """The lead is the best chi-square reached through the FE. A refit whose half-resolution
    optimum, less twice the resolution's change there, 15 times its last gain and 10 %, still
    lies more than the tie margin above the lead is left where it is; one still gaining fast,
    or whose resolution change is large, or that sits within the margin, goes on."""
    lead = Reach(cheap=2100.0, gain=0.1, full=2140.0)
    far = Reach(cheap=450_000.0, gain=0.3, full=450_800.0)
    gaining = Reach(cheap=450_000.0, gain=30_000.0, full=450_800.0)
    near = Reach(cheap=2300.0, gain=0.2, full=2330.0)
    shifted = Reach(cheap=3000.0, gain=0.2, full=3500.0)
    got = within_reach({"lead": lead, "far": far, "gaining": gaining, "near": near,
                        "shifted": shifted}, {})
    assert got == {"lead", "near", "gaining", "shifted"}
    # near: 0.9 * 2300 - 60 - 3 = 2007 <= 2140 + 6; shifted: 2700 - 1000 - 3 = 1697;
    # gaining: 405,000 - 1,600 - 450,000 < 0; far: 405,000 - 1,600 - 4.5 > 2146
    assert far.floor > lead.full + 6.0 and near.floor < lead.full
    # a local refit from the base point can be the lead
    assert within_reach({"near": near}, {"x": 1000.0}) == set()


def test_last_gain_is_what_the_last_accepted_iteration_took():
    f = SimpleNamespace(history=[100.0, 40.0, 38.5])
    assert last_gain(f) == pytest.approx(1.5)
    assert last_gain(SimpleNamespace(history=[7.0])) == 0.0



def test_global_refits_whose_scouted_starts_all_converged_go_on(toy, monkeypatch):
    """Scouting long enough for every start to converge leaves nothing to converge on the
    cheap model: the refits go on (no empty batch through the FE) and end where the own FE
    alone puts them."""
    import solderpyro.diagnose.refits as refits
    from solderpyro.diagnose.refits import LM_TOL

    lay, _, meas, base, scores = toy
    monkeypatch.setattr(refits, "SCOUT_ITERS", refits.LM_ITERS)
    _, ref = global_refits(lay, CountedToyFE(), meas, SIGMA, base, scores, [])
    _, got = global_refits(lay, CountedToyFE(), meas, SIGMA, base, scores, [],
                           scout_fe=CheapToyFE())
    for r, g in zip(ref, got, strict=True):
        assert g.chi2 == pytest.approx(r.chi2, abs=4 * LM_TOL)


def test_a_face_says_its_unit_and_a_dimensionless_constant_none():
    from solderpyro.diagnose.faces import Face

    assert Face("s0", "upper", 25.0, 25.0, "MPa").text() == "s0 = 25 MPa (upper bound 25)"
    assert Face("xi", "lower", 1.0, 1.0, "-").text() == "xi = 1 (lower bound 1)"


TOP = 1.6


def nested_toy_model(rows: np.ndarray) -> np.ndarray:
    """``rows (N, 4)`` = (a, b, first p, right q) -> ``(N, 40)``: the right effect's
    signature ``q (TOP - b) x^3`` vanishes where ``b`` sits on its upper face; the first
    effect's (a fast cosine) does not."""
    a, b, p, q = (rows[:, k, None] for k in range(4))
    return a * X + b * X**2 + p * 0.05 * np.cos(14.0 * X) + q * (TOP - b) * X**3


class NestedToyFE(ToyFE):
    def runs(self, P: torch.Tensor, times, field, fx, keep=None) -> SimpleNamespace:
        V = torch.as_tensor(nested_toy_model(P.numpy()))[:, None, :]
        return SimpleNamespace(V=V, ok=torch.ones(len(P), dtype=torch.bool), times=(0.0,),
                               names=self.names)


def test_a_next_candidate_trapped_at_the_faces_is_refitted_from_the_literature_constants():
    """Two hidden effects. The base fit and the first one's refit press both constants against
    their upper faces (the second effect's ``3 (TOP - b) x^3`` absorbed by ``a x + b x^2``),
    where the second's signature vanishes: refitted only from the first's fit
    it stays there (chi-square unchanged, far above the noise). From the literature constants
    as well, the forward steps add it, at the noise level, the constants off the faces."""
    space = Box(("a", "b"), (0.5, 0.5), (TOP, TOP))
    setup = SimpleNamespace(space=space, anand={"a": 1.2, "b": 1.2})
    lay = Layout(setup, (), ("first", "right"), (0.0,), False, None, 2,
                 np.array([0.5, 0.5, -4.0, 0.0]), np.array([TOP, TOP, 4.0, 12.0]),
                 np.zeros(2), np.array(["first", "right"], dtype=object), ("a", "b", "p", "q"))
    y = (nested_toy_model(np.array([[1.0, 1.0, 1.0, 3.0]]))[0]
         + SIGMA * np.random.default_rng(3).standard_normal(len(X)))
    meas, fe = ToyData(y), NestedToyFE()
    n = len(meas)
    base = base_fit(lay, fe, meas, SIGMA, {"posterior median": np.array([1.2, 1.2])})
    assert len(on_faces(base["x"][:2], space)) == 2
    scores = [SimpleNamespace(effect="first", statistic=50.0, dof=1, lr=None, lr_value=None),
              SimpleNamespace(effect="right", statistic=0.0, dof=1, lr=None, lr_value=None)]
    local = first_refits(lay, fe, meas, SIGMA, base, scores, scores)
    by = {r.name: r for r in local}
    assert len(on_faces(by["first"].x[:2], space)) == 2
    # from the first effect's fit the right one cannot move: its refit from there is trapped
    trapped = refit_candidates(lay, fe, meas, SIGMA, by["first"].x, by["first"].chi2,
                               ("first",), {"right": by["first"].x.copy()})[0]
    assert trapped.chi2 > 100 * n
    steps, chosen, tie = forward(lay, fe, meas, SIGMA, local, Floor())
    assert chosen == ("first", "right") and tie == []
    assert settled(steps, chosen, tie, n, SIGMA, Floor())
    got = next(j.refit for j in steps[1] if j.refit.name == "right")
    # at the noise level: within 4 sd of its expectation n - 4 (sd sqrt(2 (n - 4)))
    assert got.chi2 < (n - 4) + 4 * np.sqrt(2 * (n - 4))
    assert on_faces(got.x[:2], space) == []
    # within 5 of their Gauss-Newton sd at the truth (0.005, 0.016, 0.010, 0.062)
    assert np.all(np.abs(got.x - [1.0, 1.0, 1.0, 3.0]) < 5 * np.array([0.0053, 0.0163,
                                                                       0.0097, 0.062]))
