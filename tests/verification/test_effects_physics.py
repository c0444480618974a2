"""Verification of each physical effect's own physics (solderpyro.effects) against closed
forms, ODE integration and superposition, and of its size at the top of its prior box."""

import dataclasses
import math

import numpy as np
import pytest
import torch
from scipy.integrate import solve_ivp

from solderpyro.config.compose import build, compose
from solderpyro.effects import EFFECTS, EffectSet
from solderpyro.effects.modulus_temperature import R_MIN
from solderpyro.effects.thermal_lag import lag
from solderpyro.fem.loading import EXTENDED_TIMES, REFERENCE_CYCLE, ThermalCycle, TimeStepping
from solderpyro.fem.mesh import Layer, MeshSpec
from solderpyro.fem.problem import AnandSolder, Elastic, Problem
from solderpyro.fem.solver import SDIRK_GAMMA, SpecimenSolver
from solderpyro.materials.elastic import bulk_shear
from solderpyro.materials.integrate import PointInputs, PointState, full_strain, return_map_3d
from solderpyro.materials.j2 import j2_update
from solderpyro.params import anand_tensor

F64 = torch.float64
SHORT = ThermalCycle((0.0, 600.0, 1500.0), (25.0, 75.0, 75.0))
LAYERS = (Layer("copper", "copper", -4.0, 0.0, 4, 0.25, "top"),
          Layer("solder", "solder", 0.0, 0.5, 2),
          Layer("steel", "steel", 0.5, 4.5, 4, 0.25, "bottom"))
STEP = TimeStepping(dT_max=10.0, dwell_dt0=20.0, dt_max=450.0)
TIMES = (600.0, 1500.0)
ELASTIC = {"A": 1e-30}  # Liu's constants with a negligible creep rate: an elastic solder


pytestmark = pytest.mark.usefixtures("one_thread")


def small_problem(**kw):
    kw.setdefault("stepping", STEP)
    kw.setdefault("cycle", SHORT)
    return Problem(layers=LAYERS, mesh=MeshSpec(nx=10), **kw)


def rows(q, anand=None):
    """``(b, 9 + n)`` parameter rows from effect values ``q`` ``(b, n)``."""
    q = torch.as_tensor(q, dtype=F64)
    return torch.cat([anand_tensor(anand, dtype=F64)[None].expand(q.shape[0], -1), q], 1)


# ------------------------------------------------------------------ thermal lag

@pytest.mark.parametrize("tau", [5.0, 60.0, 300.0])
def test_thermal_lag_closed_form_matches_ode(tau):
    """The closed form per linear segment against a DOP853 integration of dT/dt = (T_p - T)/tau
    over the reference cycle (segment by segment, rtol 1e-12): agreement to 1e-8 K."""
    cyc = REFERENCE_CYCLE
    ts = np.linspace(0.0, cyc.end, 157)
    T, T_ode = 25.0, {}
    for a, b in zip(cyc.times[:-1], cyc.times[1:], strict=True):
        inside = ts[(ts >= a) & (ts <= b)]
        sol = solve_ivp(lambda t, y: [(cyc(t) - y[0]) / tau], (a, b), [T], method="DOP853",
                        t_eval=inside, rtol=1e-12, atol=1e-12, dense_output=True)
        T_ode.update(zip(inside.tolist(), sol.y[0].tolist(), strict=True))
        T = float(sol.sol(b)[0])
    err = max(abs(cyc(t) - lag(cyc, t, torch.tensor([tau], dtype=F64)).item() - T_ode[t])
              for t in ts)
    assert err < 1e-8, err


@pytest.mark.parametrize("tau", [60.0, 300.0])
@pytest.mark.parametrize("split", [0.25, 0.5])
def test_two_stage_thermal_lag_closed_form_matches_ode(split, tau):
    """The two-stage closed form per linear segment (split 1/4: the direct divided difference;
    1/2: its equal-stage limit) against a Radau integration of
    dT1/dt = (T_p - T1)/tau_1, dT/dt = (T1 - T)/tau_2 over the reference cycle (segment by
    segment, each from the ODE's own end state of the last; rtol 1e-12, atol 1e-12 K, the
    constant Jacobian given): agreement to 1e-8 K at 157 times, as the first-order check
    (2e-11 K measured; DOP853 at the same tolerances drifts to 2e-9 K on this system)."""
    cyc = REFERENCE_CYCLE
    t1, t2 = (1.0 - split) * tau, split * tau
    ts = np.linspace(0.0, cyc.end, 157)
    y, T_ode = [25.0, 25.0], {}
    for a, b in zip(cyc.times[:-1], cyc.times[1:], strict=True):
        inside = ts[(ts >= a) & (ts <= b)]
        sol = solve_ivp(lambda t, z: [(cyc(t) - z[0]) / t1, (z[0] - z[1]) / t2], (a, b), y,
                        method="Radau", t_eval=inside, rtol=1e-12, atol=1e-12,
                        jac=[[-1.0 / t1, 0.0], [1.0 / t2, -1.0 / t2]], dense_output=True)
        T_ode.update(zip(inside.tolist(), sol.y[1].tolist(), strict=True))
        y = [float(v) for v in sol.sol(b)]
    tt = torch.tensor([tau], dtype=F64)
    ss = torch.tensor([split], dtype=F64)
    err = max(abs(cyc(t) - lag(cyc, t, tt, ss).item() - T_ode[t]) for t in ts)
    print(f"split {split}, tau {tau:g} s: max |closed form - Radau| = {err:.2e} K")
    assert err < 1e-8, err


def test_thermal_lag_tau_to_zero_recovers_the_program():
    """tau = 0 gives the program exactly; small tau lags by at most |rate| * tau."""
    cyc = REFERENCE_CYCLE
    rmax = 5.0 / 60.0  # K/s, the ramps of the reference cycle
    for t in np.linspace(0.0, cyc.end, 97):
        e = lag(cyc, float(t), torch.tensor([0.0, 1e-3, 1e-6], dtype=F64))
        assert e[0].item() == 0.0
        assert abs(e[1].item()) <= rmax * 1e-3 * (1 + 1e-12)
        assert abs(e[2].item()) <= rmax * 1e-6 * (1 + 1e-12)


def test_thermal_lag_enters_the_fe_as_the_member_temperature():
    """Elastic solder: V is linear in the uniform temperature, so with a lag V(t) must equal the
    baseline's V per kelvin times the lagged temperature rise, for every member, one lag or two
    equal stages (split 1/2) (1e-10 of max|V|: the elastic solves agree to rounding, ~1e-14 of
    max|V| measured)."""
    times = [300.0, 600.0, 700.0, 1500.0]
    base = SpecimenSolver(small_problem()).solve(anand_tensor(ELASTIC, dtype=F64)[None],
                                                 [600.0]).V[0, 0]  # (n_out,) at 75 degC
    per_K = base / 50.0
    taus = torch.tensor([[0.0, 0.0], [40.0, 0.0], [250.0, 0.0], [250.0, 0.5]], dtype=F64)
    V = SpecimenSolver(small_problem(), effects=("thermal_lag",)).solve(
        rows(taus, ELASTIC), times).V
    for k, t in enumerate(times):
        dT = SHORT(t) - lag(SHORT, t, taus[:, 0], taus[:, 1]) - 25.0  # (b,)
        err = (V[:, k] - dT[:, None] * per_K).abs().max().item()
        assert err < 1e-10 * V.abs().max().item(), (t, err)
    assert (V[2, 1] - V[0, 1]).abs().max() > 1.0  # 250 s: ~18 K short at the end of the ramp
    assert (V[3, 1] - V[2, 1]).abs().max() > 0.1  # the split: ~2 K more at the ramp's end


# ------------------------------------------------------------------ stress-free temperature

def test_stress_free_temperature_superposition_elastic_and_relaxation_with_creep():
    """Elastic solder: the residual stress of cooling from T_sf superposes, and V relative to
    the start (the Moire reference image) is exactly that of T_sf = 25 (1e-10 of max|V|: each
    solve stops at a residual of 1e-10 of its forces, which the cool-down from T_sf = 183
    triples; 7e-12 of max|V| measured). With creep the residual stress relaxes during the
    cycle and V changes."""
    solver = SpecimenSolver(small_problem(), effects=("stress_free_temperature",))
    q = [[25.0, 1800.0, 1.0], [100.0, 1800.0, 1.0], [183.0, 1800.0, 1.0], [150.0, 1800.0, 3.0]]
    V = solver.solve(rows(q, ELASTIC), [600.0, 1500.0]).V
    err = (V - V[:1]).abs().max().item()
    assert err < 1e-10 * V.abs().max().item(), err
    Vc = solver.solve(rows(q), [600.0, 1500.0]).V
    assert (Vc[2] - Vc[0]).abs().max() > 0.5
    assert (Vc[2] - Vc[0]).abs().max() > (Vc[1] - Vc[0]).abs().max()  # grows with T_sf - 25


def test_a_slower_cool_down_relaxes_more_and_members_keep_their_own():
    """The cool-down is each member's own: members with different cool-downs in one batch give
    what each gives alone (the shared grid; 1e-9 of max|V|, the Newton tolerance), and a slower
    cool-down from the same T_sf lets more of the residual stress relax before t = 0, so the
    cycle's V moves less from the stress-free baseline (T_sf = 25)."""
    solver = SpecimenSolver(small_problem(), effects=("stress_free_temperature",))
    q = [[25.0, 1800.0, 1.0], [150.0, 900.0, 1.0], [150.0, 3000.0, 1.0], [150.0, 9000.0, 1.0],
         [150.0, 3000.0, 3.0]]
    V = solver.solve(rows(q), [600.0, 1500.0]).V
    for i in (1, 3, 4):
        alone = solver.solve(rows([q[i]]), [600.0, 1500.0]).V[0]
        assert (V[i] - alone).abs().max() < 1e-9 * V.abs().max(), i
    shift = [(V[i] - V[0]).abs().max().item() for i in (1, 2, 3)]
    assert shift[0] > shift[1] > shift[2] > 0.0, shift
    # the shape moves V: the same T_sf and cool-down, three times the mean rate at first
    assert (V[4] - V[2]).abs().max() > 0.01 * shift[1]


def test_the_pre_history_runs_each_member_along_its_own_shape():
    """Before t = 0 a member is ``s ** p`` of the way from the program's start to its T_sf at
    the share ``s = -t / D`` of its cool-down still to run (rests at T_sf before -D; 1e-12 K):
    p = 1 the constant rate, p = 3 three times the mean rate at first; the shared grid
    resolves the box's fastest start (steps at most dT_max there)."""
    from solderpyro.effects import EffectSet

    fx = EffectSet(["stress_free_temperature"])
    cyc = REFERENCE_CYCLE
    q = torch.tensor([[150.0, 3000.0, 1.0], [150.0, 3000.0, 3.0], [100.0, 900.0, 2.0]],
                     dtype=F64)
    for t in (-4000.0, -3000.0, -2000.0, -450.0, -1.0):
        T = fx.temperature(cyc, t, 25.0, q)
        s = np.minimum(-t / q[:, 1].numpy(), 1.0)
        expect = 25.0 + (q[:, 0].numpy() - 25.0) * s ** q[:, 2].numpy()
        assert np.abs(T.numpy() - expect).max() < 1e-12, t
    ph = fx.pre_history()
    ts = small_problem().stepping
    g = ph.grid(ts)
    D, dT = 900.0, 158.0  # the fastest member the box allows: T_sf 183, 900 s, p = 3
    Tg = 25.0 + dT * np.clip(-g / D, 0.0, 1.0) ** 3.0
    assert np.abs(np.diff(Tg)).max() <= ts.dT_max * (1 + 1e-9)


def _fit_noise_free(effect: str, truth: list[float], start: list[float], free: list[int]):
    """Levenberg-Marquardt through the small problem's FE on the columns ``free`` of the
    effect's parameters, from ``start``, to noise-free V made at ``truth`` (the effect's box;
    noise 1e-3 of max|V| scales the chi-square). Returns the fit (``x``, ``history``)."""
    from solderpyro.exact.fit import LMOptions, lm_fit

    solver = SpecimenSolver(small_problem(), effects=(effect,))
    times = [300.0, 600.0, 1000.0, 1500.0]
    box = EFFECTS[effect].params
    y = solver.solve(rows([truth]), times).V[0].reshape(-1).numpy()

    def fun(X):
        return solver.solve(rows(X), times).V.reshape(len(X), -1).numpy()

    sig = 1e-3 * float(np.abs(y).max())
    fit = lm_fit(fun, np.array([start]), box.lower, box.upper, y, sig, [np.array(free)],
                 LMOptions(iters=25, tol=1e-6))[0]
    print(f"{effect} {truth}: fit {fit.x}, chi2 {fit.history[0]:.3g} -> {fit.chi2:.3g} in "
          f"{fit.iters} steps")
    return fit


def test_the_cool_down_is_recovered_from_noise_free_data():
    """A form nuisance parameter the data inform: V made at T_sf = 150 degC cooled over 4,000 s
    is fitted through the FE (Levenberg-Marquardt on the cool-down, T_sf known, from the
    library's 1,800 s); the fit returns the cool-down within 5 % (noise-free data, so only the
    LM's stopping tolerance and its finite differences limit it). On this short cycle T_sf and
    the cool-down trade off (a lower T_sf cooled faster leaves a similar residual stress), so
    T_sf is held at its truth here, as a measured reflow profile would give it."""
    fit = _fit_noise_free("stress_free_temperature", [150.0, 4000.0, 1.0],
                          [150.0, 1800.0, 1.0], [1])
    assert abs(fit.x[1] / 4000.0 - 1.0) < 0.05, fit.x
    assert fit.x[0] == 150.0 and fit.x[2] == 1.0


def test_the_cool_down_shape_is_recovered_from_noise_free_data():
    """The cool-down's shape is a form the data inform too: V made at T_sf = 150 degC cooled
    over 3,000 s, fastest at first (shape 2.4), is fitted through the FE (Levenberg-Marquardt
    on the shape, T_sf and the cool-down known, from the constant rate); the fit returns the
    shape within 0.02 (noise-free data: the LM's stopping and finite differences limit it;
    measured 2.4 to 1e-10), and the constant rate misfits them (chi-square 398 at noise 1e-3
    of max|V|)."""
    fit = _fit_noise_free("stress_free_temperature", [150.0, 3000.0, 2.4],
                          [150.0, 3000.0, 1.0], [2])
    assert fit.history[0] > 1.0
    assert abs(fit.x[2] - 2.4) < 0.02, fit.x
    assert fit.x[0] == 150.0 and fit.x[1] == 3000.0


@pytest.mark.parametrize("n_true", [1.0, 0.5, 1.6])
def test_the_softening_law_form_is_recovered_from_noise_free_data(n_true):
    """A form nuisance parameter the data inform: V made at k_E = 6e-3 /K with the linear law
    (n_E = 1), halfway to the exponential (0.5) or quickening (1.6) is fitted through the FE
    (Levenberg-Marquardt on k_E and n_E together, the plateau at its default, from the
    library's exponential form n_E = 0 at the true k_E); the fit returns n_E within 0.01 and
    k_E within 1e-3 relative. Noise-free data, so only the LM's stopping and its finite
    differences limit it (measured: n_E to 1e-8 and k_E to 1e-9 of its value, chi-square from
    1.2-24 down to 1e-12 or below, in 4-5 steps). The tolerance is
    what the fit must reach, not what it reached: on this small problem k_E and n_E are
    correlated (0.998 between the Jacobian's columns), so n_E's sd per unit of
    sqrt(chi-square) is ~5: n_E within 0.01 needs chi-square below ~4e-6, i.e. a converged
    fit, where the start's chi-square is above 1. (At noise 1e-3 of max|V| the same sd means
    the small problem could not tell the forms apart; this checks that the form can be
    fitted, not how well data inform it.)"""
    fit = _fit_noise_free("modulus_temperature", [6e-3, n_true, R_MIN], [6e-3, 0.0, R_MIN],
                          [0, 1])
    assert fit.history[0] > 1.0  # the exponential form does not fit the data
    assert abs(fit.x[1] - n_true) < 0.01, fit.x
    assert abs(fit.x[0] / 6e-3 - 1.0) < 1e-3, fit.x


def test_the_softening_plateau_is_recovered_from_noise_free_data():
    """The plateau r_E, a form nuisance parameter: V made with the linear law at k_E =
    2e-2 /K levelling off at 30 % of E25 (reached at 60 degC, held through the small cycle's
    dwell at 75 degC) is fitted through the FE (LM on k_E and r_E, the linear form known, from
    a plateau of 45 %, reached at 52.5 degC); the fit returns r_E within 0.01 and k_E within
    1e-3 relative (noise-free data: the LM's stopping and finite differences limit it). Below
    its plateau the linear law does not depend on r_E, so the start must reach its plateau
    inside the cycle for the data to inform it."""
    fit = _fit_noise_free("modulus_temperature", [2e-2, 1.0, 0.3], [2e-2, 1.0, 0.45], [0, 2])
    assert fit.history[0] > 1.0  # the 45 % plateau does not fit the data
    assert abs(fit.x[2] - 0.3) < 0.01, fit.x
    assert abs(fit.x[0] / 2e-2 - 1.0) < 1e-3, fit.x


@pytest.mark.parametrize("n_true", [0.0, 1.6])
def test_the_cte_rise_form_is_recovered_from_noise_free_data(n_true):
    """A form nuisance parameter the data inform: V made at c_alpha = 2e-3 /K with the
    exponential rise (n_alpha = 0) or a concave one (1.6) is fitted through the
    FE (Levenberg-Marquardt on c_alpha and n_alpha together, from the library's linear form at
    the true c_alpha); the fit returns n_alpha within 0.02 and c_alpha within 1e-3 relative.
    Noise-free data, so only the LM's stopping and its finite differences limit it (measured:
    both to 1e-8 in 3 steps); the linear start misfits them (chi-square 6.2 and 1.9 at noise
    1e-3 of max|V|)."""
    fit = _fit_noise_free("cte_temperature", [2e-3, n_true], [2e-3, 1.0], [0, 1])
    assert fit.history[0] > 1.0  # the linear form does not fit the data
    assert abs(fit.x[1] - n_true) < 0.02, fit.x
    assert abs(fit.x[0] / 2e-3 - 1.0) < 1e-3, fit.x


# ------------------------------------------------------------------ CTE(T): free expansion

def _uniform_block():
    """Three layers of one material, one step 25 -> 75 degC (elastic: no more is needed; the
    stress-free temperature's cool-down takes a few growing steps)."""
    E, nu, alpha = 100e3, 0.3, 15e-6
    mats = {"steel": Elastic(E, nu, alpha), "solder": AnandSolder(E, nu, alpha),
            "copper": Elastic(E, nu, alpha)}
    prob = small_problem(materials=mats, cycle=ThermalCycle((0.0, 1.0), (25.0, 75.0)),
                         stepping=TimeStepping(dT_max=1e3, dwell_dt0=1.0, dt_max=1e3))
    xs, ys = np.meshgrid([-15.0, -6.0, 0.0, 9.0, 15.0], [-4.0, -2.0, 0.0, 0.25, 0.5, 3.0, 4.5])
    pts = np.stack([xs.ravel(), ys.ravel()], 1)
    return prob, pts, alpha


def _alpha_integral(dT: float, c: float, n: float) -> float:
    """``int_0^dT alpha(25 + v) / alpha25 dv`` of the CTE family, by 40-point Gauss-Legendre
    (the integrand is analytic on the interval: exact to rounding)."""
    x, w = np.polynomial.legendre.leggauss(40)
    v = 0.5 * dT * (x + 1.0)
    f = np.exp(c * v) if n == 0.0 else np.exp(np.log1p(n * c * v) / n)
    return float(0.5 * dT * (w * f).sum())


@pytest.mark.parametrize("effects", [("cte_temperature",),
                                     ("stress_free_temperature", "cte_temperature")])
def test_cte_temperature_free_expansion_is_the_integral(effects):
    """A one-material block expands freely: v = eps (y - y_O) with eps the integral of
    alpha25 (1 + n c (T - 25))^(1/n) from the stress-free temperature, i.e. relative to the
    start, alpha25 int_0^(T-25) (1 + n c v)^(1/n) dv (T_sf cancels in V relative to the
    start), for the linear (n = 1), hyperbolic (-1) and square-root (2) forms. 1e-10 of
    max|v| (rounding of the elastic solve: ~3e-14 of it measured)."""
    prob, pts, alpha = _uniform_block()
    solver = SpecimenSolver(prob, field_points=([f"p{i}" for i in range(len(pts))], pts),
                            effects=effects)
    c = torch.tensor([0.0, 2e-3, -1e-3, 3e-3, 3e-3, 3e-3], dtype=F64)
    n = torch.tensor([1.0, 1.0, 1.0, 1.0, -1.0, 2.0], dtype=F64)
    q = torch.stack([c, n], 1) if len(effects) == 1 else torch.stack([torch.tensor(
        [25.0, 120.0, 60.0, 183.0, 150.0, 100.0], dtype=F64), torch.tensor(
        [1800.0, 900.0, 9000.0, 3000.0, 2000.0, 5000.0], dtype=F64), torch.tensor(
        [1.0, 2.0, 1.0, 3.0, 1.5, 1.0], dtype=F64), c, n], 1)
    res = solver.solve(rows(q, ELASTIC), [1.0])
    assert bool(res.ok.all())
    dT = 50.0
    eps = alpha * torch.tensor([_alpha_integral(dT, ci, ni) for ci, ni in
                                zip(c.tolist(), n.tolist(), strict=True)], dtype=F64)
    assert eps[1].item() == pytest.approx(alpha * (dT + 0.5 * 2e-3 * dT ** 2), rel=1e-13)
    y = torch.tensor(np.concatenate([[4.5, -4.0], pts[:, 1]]), dtype=F64)
    expect = 1e3 * eps[:, None] * (y - prob.origin[1])  # (b, n_out) um
    err = (res.V[:, 0] - expect).abs().max().item()
    assert err < 1e-10 * expect.abs().max().item(), err
    assert (res.V[1, 0] - res.V[0, 0]).abs().max() > 0.1  # c changes V (here by ~0.4 um)
    # the form moves V at the box's top c: convex above linear above concave
    top = res.V[3:, 0, 0]
    assert top[1] > top[0] > top[2]


# ------------------------------------------------------------------ E(T)

def test_modulus_temperature_elastic_solution_uses_E_of_T():
    """Elastic solder, heated 25 -> 75 degC: the response depends on the current temperature
    only, so the effect's V must equal the baseline's with the solder modulus replaced by
    E25 (r + (1 - r) exp(-k (75 - 25) / (1 - r))) (n_E = 0, the default plateau r = 1 %),
    E25 (1 - k (75 - 25)) (n_E = 1, the linear law) or its plateau r E25 where the law falls
    below it (k = 0.015, r = 0.5) (1e-10 of max|V|: rounding of two elastic solves), and differ
    from the baseline's with E25."""
    prob = small_problem(cycle=ThermalCycle((0.0, 1.0), (25.0, 75.0)),
                         stepping=TimeStepping(dT_max=1e3, dwell_dt0=1.0, dt_max=1.0))
    k = torch.tensor([[0.0, 0.0, 0.01], [4e-3, 0.0, 0.01], [4e-3, 1.0, 0.01],
                      [1.5e-2, 1.0, 0.5]], dtype=F64)  # k_E, n_E, r_E
    V = SpecimenSolver(prob, effects=("modulus_temperature",)).solve(rows(k, ELASTIC), [1.0]).V
    sol = prob.materials["solder"]
    for i in range(4):
        u, r = k[i, 0].item() * 50.0, k[i, 2].item()
        E = sol.E * (max(r, 1.0 - u) if k[i, 1].item() == 1.0
                     else r + (1 - r) * math.exp(-u / (1 - r)))
        mats = {**prob.materials, "solder": AnandSolder(E, sol.nu, sol.alpha)}
        ref = SpecimenSolver(dataclasses.replace(prob, materials=mats)).solve(
            anand_tensor(ELASTIC, dtype=F64)[None], [1.0]).V[0]
        err = (V[i] - ref).abs().max().item()
        assert err < 1e-10 * ref.abs().max().item(), (i, err)
    assert (V[1] - V[0]).abs().max() > 1e-3  # a softer solder transmits less shear
    assert (V[2] - V[1]).abs().max() > 1e-3  # the linear law is softer still (0.80 < 0.82)
    assert (V[3] - V[0]).abs().max() > 1e-3  # at its plateau, half as stiff


# ------------------------------------------------------------------ Moire rigid motion

def test_moire_offset_and_rotation_per_image_are_exact():
    """V' - V = c_k + 1e-3 w_k (x - x_O) um at every point (urad * mm = nm), image by image."""
    xs = np.array([-15.0, -7.5, 0.0, 4.0, 15.0])
    pts = np.stack([xs, np.full_like(xs, 2.0)], 1)
    times = [600.0, 1500.0]
    solver = SpecimenSolver(small_problem(), field_points=([f"p{i}" for i in range(5)], pts),
                            effects=("moire_rigid_motion",))
    q = torch.tensor([[0.0] * 4, [0.4, -0.7, 30.0, -45.0]], dtype=F64)
    V = solver.solve(rows(q), times).V
    x = torch.tensor(np.concatenate([[15.0, 15.0], xs]), dtype=F64)
    for k in range(2):
        expect = q[1, k] + 1e-3 * q[1, 2 + k] * (x - 0.0)
        assert torch.allclose(V[1, k] - V[0, k], expect, rtol=0, atol=1e-12)


# ------------------------------------------------------------------ kinematic hardening

def test_kinematic_hardening_fe_stages_follow_the_gauss_point_law():
    """Each backward-Euler stage of the FE solve, members with C_k = 0, 300 and 2000 MPa in one
    batch (the last with Armstrong-Frederick recovery gamma_k = 100): replaying the Gauss-point
    law with back stress (return_map_3d with the member's own C_k and gamma_k) from the stage's
    start state on the FE's converged strain gives the FE's end state (back stress, inelastic
    strain, resistance, lagged rate: 1e-9 relative), and SDIRK2's second stage starts from the
    back stress extrapolated like the inelastic strain, X* = X0 + (1-gamma)/gamma (X1 - X0)
    (1e-13 MPa), with the first stage's rate as its lagged rate (exactly). So the back stress
    and the rate are carried between steps and stages, and each member's C_k and gamma_k reach
    its own points."""
    solver = SpecimenSolver(small_problem(), effects=("kinematic_hardening",))
    calls, step = [], solver.step

    def record(u, st, p, T1, dt, du0=None, gid=None):
        out = step(u, st, p, T1, dt, du0=du0, gid=gid)
        calls.append((st, out[0], out[1], T1, dt, p))
        return out

    solver.step = record  # type: ignore[method-assign]
    P = rows([[0.0, 0.0], [300.0, 0.0], [2000.0, 100.0]])
    res = solver.solve(P, [600.0, 1500.0])
    assert bool(res.ok.all()) and len(calls) % 2 == 0 and len(calls) > 20
    nu, k = solver.solder.nu, (1.0 - SDIRK_GAMMA) / SDIRK_GAMMA
    for j, (st0, u1, st1, T1, dt, p) in enumerate(calls):
        Ck = P[:, 9] if len(p) == len(P) else None
        if Ck is None:  # a sub-step of some members: not in this test's reference cycle
            continue
        full = full_strain(solver.points.strain(u1), st1.eps_zz)
        inputs = PointInputs(T1.T + 273.15, dt, T1.eps_th, T1.E, nu, Ck[:, None, None],
                             P[:, 10, None, None])
        _, ref, *_ = return_map_3d(full, st0, p[:, None, None, :9], inputs)
        for a, b in ((ref.X, st1.X), (ref.eps_p, st1.eps_p), (ref.s, st1.s),
                     (ref.p_rate, st1.p_rate)):
            assert (a - b).abs().max() <= 1e-9 * b.abs().max() + 1e-15, j
        if j % 2 == 1:  # stage 2 of a step: its start extrapolates stage 1
            s0, s1 = calls[j - 1][0], calls[j - 1][2]
            assert torch.allclose(st0.X, s0.X + k * (s1.X - s0.X), rtol=0, atol=1e-13)
            assert torch.equal(st0.p_rate, s1.p_rate)
    X = calls[-1][2].X
    assert X[0].abs().max() == 0.0 and X[1].abs().max() > 0.1 and X[2].abs().max() > 0.5


def test_kinematic_hardening_stiff_limit_is_the_elastic_solder():
    """The back stress X = (2/3) C_k eps_p caps the inelastic strain at ~ q / C_k, so as C_k
    grows the FE tends to the elastic solder (negligible creep rate), the gap falling as
    1/C_k: 1e6 -> 1e8 MPa shrinks it ~100-fold, to < 1e-3 um, while the baseline (C_k = 0)
    creeps by > 0.3 um."""
    V = SpecimenSolver(small_problem(), effects=("kinematic_hardening",)).solve(
        rows([[0.0, 0.0], [1e6, 0.0], [1e8, 0.0]]), TIMES).V
    V_el = SpecimenSolver(small_problem()).solve(anand_tensor(ELASTIC, dtype=F64)[None],
                                                 TIMES).V[0]
    gap = [(V[i] - V_el).abs().max().item() for i in range(3)]
    print("max |V - V_elastic| (um) at C_k = 0, 1e6, 1e8 MPa:", gap)
    assert gap[0] > 0.3 and gap[2] < 1e-3
    assert 60.0 < gap[1] / gap[2] < 160.0


# ------------------------------------------------------------------ copper plasticity

def test_j2_pure_shear_closed_form_loading_and_reversal():
    """Homogeneous pure shear at a Gauss point in steps (J2, linear isotropic hardening): the
    radial return is exact for proportional loading, so on the plastic branch
    gamma_p = (3G gamma - sqrt3 sigma_y)/(3G + H), sqrt3 tau = sigma_y + H ebar with
    ebar = gamma_p/sqrt3, to rounding (1e-12 relative); on reversal the shear is elastic until
    sqrt3 |tau| reaches sigma_y + H ebar again (isotropic hardening: no Bauschinger effect)."""
    E, nu, sy, H = 130e3, 0.34, 40.0, 1000.0
    _, G = bulk_shear(E, nu)
    r2, r3 = 2.0 ** 0.5, 3.0 ** 0.5
    st = PointState(torch.zeros(4, dtype=F64), torch.tensor(0.0, dtype=F64),
                    torch.tensor(0.0, dtype=F64))
    gy = sy / (r3 * G)  # shear strain at first yield
    for gam in np.linspace(0.5 * gy, 20 * gy, 12):  # loading
        eps = torch.tensor([0.0, 0.0, 0.0, gam / r2], dtype=F64)  # Mandel: sqrt2 * gamma/2
        sig, st, _, _ = j2_update(eps, st, 0.0, E, nu, sy, H)
        tau = sig[3].item() / r2
        gp = max(0.0, (3 * G * gam - r3 * sy) / (3 * G + H))
        assert abs(tau - G * (gam - gp)) <= 1e-12 * abs(tau)
        assert abs(st.s.item() - gp / r3) <= 1e-12 * gp / r3 + 1e-300
        if gp > 0:
            assert abs(r3 * tau - (sy + H * st.s.item())) <= 1e-12 * r3 * tau
        assert abs(sig[:3]).max() < 1e-9  # no normal stress in pure shear
    gp, flow = r3 * st.s.item(), sy + H * st.s.item()  # plastic shear strain, flow stress
    g_rev = gp - flow / (r3 * G)  # reverse yield: tau = G (gamma - gp) = -flow / sqrt3
    for gam, plastic in ((g_rev + 1e-3 * gy, False), (g_rev - 0.5 * gy, True)):
        eps = torch.tensor([0.0, 0.0, 0.0, gam / r2], dtype=F64)
        sig, st2, _, dg = j2_update(eps, st, 0.0, E, nu, sy, H)
        assert bool(dg > 0) == plastic
        tau = sig[3].item() / r2
        if plastic:
            assert abs(r3 * tau + sy + H * st2.s.item()) <= 1e-12 * flow
        else:
            assert abs(tau - G * (gam - gp)) <= 1e-12 * abs(tau)


def test_copper_plasticity_elastic_limit_is_the_baseline():
    """The off member (400 MPa, baseline path) is the baseline to the last bit, and the solver
    reports the largest elastic von Mises stress of the band over the cycle; with sigma_y
    0.1 % above it the banded solve (plastic band, QM6 modes solved per element) gives the
    baseline to 1e-10 of max|V| (nothing yields; ~1e-14 of it measured), 2 % below it the
    copper yields and V changes (so the reported peak is right to 2 %), and more so at 0.7 x."""
    base = SpecimenSolver(small_problem()).solve(anand_tensor(dtype=F64)[None], TIMES).V[0]
    solver = SpecimenSolver(small_problem(), effects=("copper_plasticity",))
    r0 = solver.solve(rows([[400.0]]), TIMES)
    assert torch.equal(r0.V[0], base)
    peak = r0.extra["band_elastic_vm"][0].item()
    assert 5.0 < peak < 400.0
    res = solver.solve(rows([[1.001 * peak], [0.98 * peak], [0.7 * peak]]), TIMES)
    err, dev1, dev = ((res.V[i] - base).abs().max().item() for i in range(3))
    print(f"band peak {peak:.3f} MPa; 1.001 x: {err:.2e} um; 0.98 x: {dev1:.2e} um; "
          f"0.7 x: {dev:.3f} um")
    assert err < 1e-10 * base.abs().max().item() and dev1 > 1e-7 and dev > 1e-2


# ------------------------------------------------------------------ (e) size at the box top

def test_each_effect_changes_point_data_at_the_top_of_its_box():
    """Reference specimen and cycle (coarse mesh: within 1 % of the default mesh on these
    differences), Liu's constants, V_A and V_B at the seven extended times: each effect at the
    edge of its box farthest from its off value (the upper edge, except copper_plasticity's
    lower 15 MPa; its form parameters, Effect.nuisance, at their default: the exponential
    softening, one lag, the 1,800 s cool-down; the others off) changes the noise-free data by
    > 0.3 um RMS, except
    modulus_temperature (E(125 degC) = E25/10 at the top of its box moves the data by only
    ~0.29 um at Liu's fast-creeping constants) and copper_plasticity, whose copper yields only
    in a small zone at Liu's constants (~0.2 um; docs/effects.md): these are asserted as the
    measured sizes.
    The copper around the plastic band stays below 15 MPa (the band is deep enough)."""
    prob = build(compose(["mesh=coarse"])).problem
    fx = EffectSet(list(EFFECTS)).bind(EXTENDED_TIMES)
    off = torch.tensor(fx.off, dtype=F64)
    q = [off]
    for e, (a, b) in zip(fx.effects, fx._edges, strict=True):
        r = off.clone()
        far = [o if nm in e.nuisance else lo if abs(lo - o) > abs(hi - o) else hi
               for nm, lo, hi, o in zip(e.params.names, e.params.lower, e.params.upper, e.off,
                                        strict=True)]
        r[a:b] = torch.tensor(far, dtype=F64)
        q.append(r)
    res = SpecimenSolver(prob, effects=fx).solve(rows(torch.stack(q)), EXTENDED_TIMES)
    assert bool(res.ok.all())
    rms = {e.name: (res.V[i + 1] - res.V[0]).pow(2).mean().sqrt().item()
           for i, e in enumerate(fx.effects)}
    print("\nRMS change of V_A, V_B at the box's far edge (um):", rms)
    for name, r in rms.items():
        if name == "modulus_temperature":
            assert 0.25 < r < 0.4, r
        elif name == "copper_plasticity":
            assert 0.1 < r < 0.4, r
        else:
            assert r > 0.45, (name, r)
    i_cu = 1 + list(EFFECTS).index("copper_plasticity")
    ring = res.extra["outside_band_vm"][i_cu].item()
    print("largest von Mises stress around the copper band (MPa):", ring)
    assert ring < 15.0
