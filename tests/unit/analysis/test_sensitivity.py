"""Sensitivity estimators against analytic answers, and the FE Jacobian against finite
differences (solderpyro/analysis/sensitivity.py)."""

import math

import pytest
import torch

from solderpyro.analysis.sensitivity import (
    SEED_CHOICE,
    dgsm,
    fe_jacobian,
    jacobian_rows,
    parse_bounds,
    sensitivity_box,
    sobol_indices,
    verdict,
)
from solderpyro.params import ANAND_NAMES, LIU2008

A_ISH, B_ISH = 7.0, 0.1
#: 25 -> 75 C in 600 s, dwell to 1500 s (Hydra overrides): the FE checks' short cycle
SHORT_CYCLE = ["loading.times_s=[0,600,1500]", "loading.temps_C=[25,75,75]",
               "loading.output_times=[600,1500]"]


def ishigami(u):
    """Ishigami function on the unit cube: x = pi (2u - 1) in [-pi, pi]^3; (N, 3) -> (N,)."""
    x = math.pi * (2 * u - 1)
    return (torch.sin(x[:, 0]) + A_ISH * torch.sin(x[:, 1]) ** 2
            + B_ISH * x[:, 2] ** 4 * torch.sin(x[:, 0]))


def ishigami_indices():
    """Analytic S1 and ST (Ishigami & Homma 1990; Sobol' & Levitan 1999)."""
    a, b, p = A_ISH, B_ISH, math.pi
    v1 = 0.5 * (1 + b * p**4 / 5) ** 2
    v2 = a**2 / 8
    v13 = b**2 * p**8 * (1 / 18 - 1 / 50)
    var = v1 + v2 + v13
    return torch.tensor([v1, v2, 0.0]) / var, torch.tensor([v1 + v13, v2, v13]) / var, var


def test_sobol_ishigami_matches_analytic_indices():
    """Eight independent scramblings (randomized QMC, iid estimates) of n = 4096: the mean of
    each index is within 4.5 standard errors of the truth (t with 7 df: p ~ 0.003 per index),
    the standard error is below 0.01 (the check has teeth), and every single estimate's 95 %
    bootstrap interval covers the truth (the bootstrap treats the points as iid and so is
    conservative for scrambled Sobol' points)."""
    s1_true, st_true, _ = ishigami_indices()
    runs = [sobol_indices(ishigami, 3, n=4096, seed=s, n_boot=50) for s in range(8)]
    for key, truth in (("S1", s1_true), ("ST", st_true)):
        est = torch.stack([getattr(r, f"{key}_agg") for r in runs])  # (8, 3)
        se = est.std(0) / math.sqrt(len(runs))
        assert (se < 0.01).all(), (key, se)
        assert ((est.mean(0) - truth).abs() < 4.5 * se + 1e-4).all(), (key, est.mean(0), truth)
        for r in runs:
            lo, hi = getattr(r, f"{key}_lo"), getattr(r, f"{key}_hi")
            assert ((lo <= truth + 1e-3) & (truth - 1e-3 <= hi)).all(), (key, lo, hi, truth)
    # a single output is its own aggregate; the main index never exceeds the total
    r = runs[0]
    assert torch.allclose(r.S1[:, 0], r.S1_agg) and (r.S1_agg <= r.ST_agg + 0.02).all()


def test_sobol_aggregate_is_variance_weighted():
    """Two outputs, x1 only in the first and x2 only in the second with 4x its variance:
    the aggregated ST is (1, 4) / 5 exactly up to sampling error."""
    f = lambda u: torch.stack([u[:, 0], 2 * u[:, 1]], -1)  # noqa: E731
    r = sobol_indices(f, 2, n=1024, seed=0, n_boot=20)
    assert torch.allclose(r.ST_agg, torch.tensor([0.2, 0.8]), atol=0.01)
    assert torch.allclose(r.S1, torch.eye(2), atol=0.01)


def test_dgsm_linear_function_is_exact_and_bounds_the_total_index():
    """f(u) = c . u: du f = c, so nu_i = c_i^2 at any point; Var = sum c^2 / 12, ST_i =
    c_i^2 / (12 Var), hence the bound nu / (pi^2 Var) = (12 / pi^2) ST (the worst case of the
    inequality for linear functions)."""
    c = torch.tensor([3.0, -1.0, 0.5, 0.0])
    u = torch.rand(7, 4, generator=torch.Generator().manual_seed(0))
    y, J = jacobian_rows(lambda x: x @ c, u)
    assert torch.allclose(y[:, 0], u @ c) and J.shape == (7, 1, 4)
    var = (c**2).sum() / 12
    res = dgsm(J, var[None])
    assert torch.allclose(res.nu[:, 0], c**2, rtol=0, atol=1e-12)
    st = c**2 / 12 / var
    assert torch.allclose(res.bound_agg, 12 / math.pi**2 * st, atol=1e-12)


def test_dgsm_ishigami_matches_analytic_measures():
    """nu_i of the Ishigami function on the unit cube (chain factor 2 pi):
    nu_1 = 2 pi^2 (1 + 2b pi^4/5 + b^2 pi^8/9), nu_2 = 2 pi^2 a^2, nu_3 = 32 b^2 pi^8 / 7.
    Monte Carlo with 4096 iid points: within 4 standard errors; and each bound is above the
    analytic total index (Sobol' & Kucherenko 2009)."""
    a, b, p = A_ISH, B_ISH, math.pi
    nu_true = torch.tensor([2 * p**2 * (1 + 2 * b * p**4 / 5 + b**2 * p**8 / 9),
                            2 * p**2 * a**2, 32 * b**2 * p**8 / 7])
    u = torch.rand(4096, 3, generator=torch.Generator().manual_seed(1))
    _, J = jacobian_rows(ishigami, u)
    _, st_true, var = ishigami_indices()
    res = dgsm(J, torch.tensor([var]))
    sq = J[:, 0].square()  # (N, 3)
    se = sq.std(0) / math.sqrt(sq.shape[0])
    assert ((res.nu[:, 0] - nu_true).abs() < 4 * se).all(), (res.nu[:, 0], nu_true, se)
    assert (nu_true / (p**2 * var) >= st_true).all()
    assert (res.lo <= res.bound_agg).all() and (res.bound_agg <= res.hi).all()


def test_fe_jacobian_matches_central_differences():
    """d V / d u for A and h0 (log-scale coordinates: the chain rule through Box.from_unit and
    the implicit-function gradients of the solver) vs central differences with du = 1e-3;
    coarse mesh, the first ramp and dwell of the reference cycle, float64. FD truncation
    ~ du^2 |V'''| and solver noise (Newton rtol 1e-10) / du are both ~1e-6 relative or below
    (measured: 6e-7 for A and for h0 at this du); rtol 1e-4 of the largest derivative leaves
    margin yet catches a wrong chain factor (ln(A_hi/A_lo) = 4.6) or a missing implicit
    correction."""
    from solderpyro.config.compose import build, compose
    from solderpyro.specimen import SpecimenModel

    setup = build(compose(["experiment=quick", *SHORT_CYCLE]))
    box = sensitivity_box(setup.space)
    model = SpecimenModel(setup.problem, box, setup.times)
    u0 = torch.full((1, 9), 0.5)
    _, J = fe_jacobian(model, box, u0, progress=False)  # (1, 4, 9): 2 times x A, B
    cols = [ANAND_NAMES.index("A"), ANAND_NAMES.index("h0")]
    du = 1e-3
    up = u0.repeat(2 * len(cols), 1)
    for k, j in enumerate(cols):
        up[2 * k, j] += du
        up[2 * k + 1, j] -= du
    with torch.no_grad():
        V = model(box.from_unit(up)).reshape(len(up), -1)
    for k, j in enumerate(cols):
        fd = (V[2 * k] - V[2 * k + 1]) / (2 * du)
        scale = J[0, :, j].abs().max()
        assert scale > 1e-3, (ANAND_NAMES[j], scale)  # a derivative worth checking
        assert torch.allclose(J[0, :, j], fd, rtol=0, atol=1e-4 * scale), (j, J[0, :, j], fd)


def test_box_and_verdict():
    box = sensitivity_box()
    assert box.names == ANAND_NAMES and box.dim == 9
    for nm in ANAND_NAMES:  # Liu 2008 lies inside the box
        i = box.names.index(nm)
        assert box.lower[i] < LIU2008[nm] < box.upper[i]
    assert [box.names[i] for i, lg in enumerate(box.log_scale) if lg] == ["A", "h0"]
    b2 = sensitivity_box(bounds=parse_bounds("A=1e5:1e8"))
    assert b2.lower[2] == 1e5 and b2.log_scale[2]
    with pytest.raises(ValueError, match="zeta"):
        sensitivity_box(bounds={"zeta": (1.0, 2.0)})
    with pytest.raises(ValueError, match="name=lower:upper"):
        parse_bounds("A=1e5")
    st = torch.tensor([0.3, 0.5, 0.05, 0.2, 0.1, 0.0, 0.01, 0.0, 0.0])
    v = verdict(ANAND_NAMES, st, st - 0.01, st + 0.01)
    assert v["reproduced"] and set(v["top"]) == set(SEED_CHOICE) and v["separated"]
    st[2] = 0.15  # A overtakes m
    v = verdict(ANAND_NAMES, st, st - 0.06, st + 0.06)
    assert not v["reproduced"] and v["missing"] == ["m"] and v["extra"] == ["A"]
    assert not v["separated"] and "not reproduced" in v["text"]
    # surrogate refits: the 4th/5th gap (xi - m here) flips sign between refits -> unresolved
    st[2] = 0.25
    refits = st.repeat(4, 1)
    refits[::2, 3] = 0.05
    v = verdict(ANAND_NAMES, st, st - 0.01, st + 0.01, refits=refits)
    assert v["top"] == ["QR", "s0", "A", "xi"] and v["separated"]
    assert v["gap_se_surrogate"] > v["gap"] / 2 and v["text"].endswith("not resolved.")


def test_jackknife_se_of_a_mean_is_the_standard_error():
    """Leave-one-out means of x: the jackknife SE equals s / sqrt(n) exactly."""
    from solderpyro.analysis.sensitivity import _jackknife_se

    x = torch.randn(20, generator=torch.Generator().manual_seed(2))
    loo = (x.sum() - x) / (len(x) - 1)
    assert torch.allclose(_jackknife_se(loo), x.std() / math.sqrt(len(x)), rtol=1e-12)


def test_sensitivity_settings_match_the_cli_and_are_checked_first():
    """The settings record's defaults are the CLI's; a bad one is refused before the setup is
    read (here: no setup at all)."""
    import dataclasses

    from solderpyro.analysis.sensitivity import SensitivitySettings, run_sensitivity
    from solderpyro.cli import build_parser

    a = build_parser().parse_args(["sensitivity", "--out", "o"])
    d = SensitivitySettings()
    assert (d.n_runs, d.grad_points, d.grad_batch, d.seed, d.n_sobol, d.n_boot, d.batch_size,
            d.refits) == (a.runs, a.grad_points, a.grad_batch, a.seed, a.sobol_samples,
                          a.bootstrap, a.batch, a.refits)
    for bad, needle in (({"n_runs": 5}, "--runs"), ({"n_sobol": 1000}, "--sobol-samples"),
                        ({"refits": 200}, "--refits"), ({"grad_batch": 0}, "--grad-batch")):
        with pytest.raises(ValueError, match=needle):
            run_sensitivity(None, "unused", dataclasses.replace(d, **bad))
