"""Every analytic log density is the Pyro model it is declared to implement.

:mod:`solderpyro.calibration.koh`'s Pyro models define the KOH likelihoods; the sampler takes
the analytic densities declared on them (``koh.FAST_DENSITIES``, ``@implemented_by``) where
they cover the configuration. For every declared (model, density) pair and each of its small
problems, at random unconstrained points, the density's value differs from Pyro's
``-potential_energy`` of the model (``initialize_model``: the same sites, priors and
``biject_to`` transforms) by one constant (the analytic densities drop constants), and its
gradient equals Pyro's autograd gradient. The cases come from the table, so a new pair fails
here until it has a problem.

Where a density samples some coordinates in its own map (``FlatModel.reparam``: the PCA
surrogate's soft-walled flow-stress coordinates), Pyro's density is carried into them through
that map's ``forward``/``vjp`` (whose own Jacobian is checked in test_flowcoords.py).

Tolerance: both sides are float64 evaluations of the same density through different
factorizations (LAPACK Cholesky, Kronecker eigendecompositions or the K-dimensional Woodbury
reduction against torch's n-dimensional Cholesky); they agree to about ``eps * cond`` relative
to the size of the terms, and the worst conditioned covariance here (the joint's 1e-6 nugget
on a unit-variance correlation) has cond ~1e8, so ``REL = 1e-7`` of the log density's
magnitude (value) and of the largest gradient entry (gradient). Measured: 1e-16 to 1e-14
(direct, dense joint), 1e-11 (Kronecker joint), 1e-12 to 1e-9 (PCA; the largest with a
known, small sigma).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable

import numpy as np
import pytest
import torch
from scipy.stats import qmc

from solderpyro.calibration import CalibrationData, Priors
from solderpyro.calibration.data import InputAxes
from solderpyro.calibration.emulators import FunctionEmulator, GPEmulator, ObservedEmulator
from solderpyro.calibration.fastkoh import flat_model
from solderpyro.calibration.koh import (
    FAST_DENSITIES,
    fast_densities,
    prepare_joint,
    prepare_observation,
)
from solderpyro.calibration.kronjoint import MIN_RUNS, kron_joint
from solderpyro.design import lhs
from solderpyro.examples.seed_math import LHS_T, X_BOX, code, lhs_runs, make_data
from solderpyro.params import Box
from solderpyro.surrogate import GPOptions, GPSurrogate
from solderpyro.surrogate.features import FlowStressInputs

DT = torch.float64
REL = 1e-7
N_POINTS = 5
T_BOX = Box(("t",), (0.0,), (2.0,))
LOG_T_BOX = Box(("t",), (0.05,), (3.0,), log_scale=(True,))


# ------------------------------------------------------------------------------ problems
def _direct(box: Box, pr: Priors) -> tuple:
    """The seed's direct example: 11 observations of 5 exp(-t x), one t."""
    x, y = make_data(0)
    return prepare_observation(y, FunctionEmulator(code, x), box, x), pr


def _seed_joint(pr: Priors) -> tuple:
    """The seed's full joint: 5 LHS runs, 11 observations, one t."""
    x, y = make_data(0)
    xs, ts, ys = lhs_runs(5, 0)
    data = CalibrationData.create(xs, ts, ys, x, y,
                                  InputAxes(["x"], ["t"], theta_box=LHS_T, x_box=X_BOX))
    return prepare_joint(data, nugget=1e-4), pr


def _multi_joint(ard: bool, pr: Priors) -> tuple:
    """Two x and three t inputs (one log-scaled), 12 runs, 5 observations."""
    tb = Box(("a", "b", "c"), (0.5, 0.5, 0.1), (1.5, 3.0, 1.0), log_scale=(False, True, False))
    xb = Box(("x1", "x2"), (0.0, 0.0), (1.0, 2.0))
    u = torch.as_tensor(qmc.LatinHypercube(d=5, seed=3).random(12), dtype=DT)
    xs, ts = xb.from_unit(u[:, :2]), tb.from_unit(u[:, 2:])

    def f(xx: torch.Tensor, tt: torch.Tensor) -> torch.Tensor:
        return tt[..., 0] * torch.exp(-tt[..., 1] * xx[:, 0]) + tt[..., 2] * xx[:, 1]

    ys = torch.stack([f(xs[i:i + 1], ts[i])[0] for i in range(12)])
    xo = xb.from_unit(torch.as_tensor(qmc.LatinHypercube(d=2, seed=4).random(5), dtype=DT))
    yo = f(xo, torch.tensor([1.0, 1.5, 0.5], dtype=DT)) + 0.05 * torch.linspace(-1, 1, 5)
    data = CalibrationData.create(xs, ts, ys, xo, yo, InputAxes(list(xb.names), list(tb.names),
                                                                     theta_box=tb, x_box=xb))
    return prepare_joint(data, ard=ard, nugget=1e-4), pr


def _product_joint(pr: Priors) -> tuple:
    """A product design of MIN_RUNS runs (16 parameter sets x 8 inputs, default nugget 1e-6):
    the joint's default path is the Kronecker form."""
    rng = np.random.default_rng(0)
    mt, mx = 16, MIN_RUNS // 16
    t = qmc.LatinHypercube(d=1, seed=0).random(mt)
    x = qmc.LatinHypercube(d=1, seed=1).random(mx)
    ts, xs = np.repeat(t, mx, 0), np.tile(x, (mt, 1))

    def f(xx: np.ndarray, tt: np.ndarray) -> np.ndarray:
        return np.sin(3.0 * xx[:, 0]) * np.exp(-tt[:, 0]) + xx[:, 0] * tt[:, 0]

    xo = rng.random((5, 1))
    yo = f(xo, np.full((5, 1), 0.4)) + 0.01 * rng.standard_normal(5)
    box = Box(("t",), (0.0,), (1.0,))
    xb = Box(("x",), (0.0,), (1.0,))
    tt = functools.partial(torch.as_tensor, dtype=DT)
    data = CalibrationData.create(tt(xs), tt(ts), tt(f(xs, ts)), tt(xo), tt(yo),
                                  InputAxes(["x"], ["t"], theta_box=box, x_box=xb))
    inp = prepare_joint(data)
    assert kron_joint(inp) is not None  # the problem is the Kronecker path's
    return inp, pr


PCA_BOX = Box(("a", "b"), (0.5, 0.2), (2.0, 1.5))
N_FIELD = 30


def _field(theta: torch.Tensor) -> torch.Tensor:
    """A smooth field ``(b, N_FIELD)`` of two parameters ``theta (b, 2)``."""
    x = torch.linspace(0, 1, N_FIELD, dtype=DT)
    return theta[:, :1] * torch.sin(3 * x + theta[:, 1:2]) + 0.3 * theta[:, 1:2] * x ** 2


@functools.lru_cache(maxsize=1)
def _pca_gp() -> GPSurrogate:
    th = lhs(PCA_BOX, 20, 0).to(DT)
    return GPSurrogate(PCA_BOX, output="pca", kernel="gaussian", mean="linear", ard=True,
                       options=GPOptions(n_pc=3, restarts=1)).fit(th, _field(th))


def _pca(offsets: bool, pr: Priors) -> tuple:
    """A PCA surrogate of the 30-value field (3 components), optionally followed by a rigid
    offset and tilt of the observations (``ObservedEmulator``, two more parameters)."""
    gp = _pca_gp()
    g = torch.Generator().manual_seed(0)
    y = _field(torch.tensor([[1.2, 0.7]], dtype=DT))[0] + 0.05 * torch.randn(
        N_FIELD, generator=g, dtype=DT)
    if not offsets:
        return prepare_observation(y, GPEmulator(gp), PCA_BOX), pr
    x = torch.linspace(-1, 1, N_FIELD, dtype=DT)

    def off(q: torch.Tensor) -> torch.Tensor:
        return q[..., 0] + q[..., 1] * x

    box = Box((*PCA_BOX.names, "c", "w"), (*PCA_BOX.lower, -1.0, -0.5),
              (*PCA_BOX.upper, 1.0, 0.5))
    return prepare_observation(y, ObservedEmulator(GPEmulator(gp), 2, off), box), pr


ANAND = Box(("s0", "QR", "xi", "m"), (5.0, 7000.0, 1.0, 0.05), (25.0, 13000.0, 5.0, 0.5),
            log_scale=(False, False, True, False))
ANAND_N = Box((*ANAND.names, "n"), (*ANAND.lower, 0.03), (*ANAND.upper, 0.12),
              log_scale=(*ANAND.log_scale, False))
FIXED = {"A": 4e6, "s_hat": 13.79, "n": 0.07}
N_ANAND = 60


def _anand_field(box: Box, theta: torch.Tensor) -> torch.Tensor:
    """A smooth field ``(b, N_ANAND)`` (um) of Anand constants ``theta (b, box.dim)``."""
    x = torch.linspace(0, 1, N_ANAND, dtype=DT)
    f = FlowStressInputs(box, FIXED)(theta)  # log flow stresses, xi, m on [0, 1] (, n)
    return (torch.sin(3 * x + f[:, :1]) * f[:, 1:2] + 0.3 * f[:, 2:3] * x ** 2
            + 0.2 * torch.cos(5 * x * f[:, 3:4]))


@functools.lru_cache(maxsize=2)
def _flow_gp(with_n: bool) -> GPSurrogate:
    box = ANAND_N if with_n else ANAND
    th = lhs(box, 25, 0).to(DT)
    return GPSurrogate(box, output="pca", kernel="matern52", mean="constant", ard=True,
                       options=GPOptions(n_pc=4, restarts=1), inputs=FlowStressInputs(box, FIXED)
                       ).fit(th, _anand_field(box, th))


def _flow(with_n: bool, offsets: bool, pr: Priors) -> tuple:
    """A PCA surrogate on flow-stress inputs of (s0, QR, xi, m): the default density samples
    them in the soft-walled flow coordinates (natively where no offsets). With ``n`` free
    as well the flow coordinates do not apply: the logit, through the same input map."""
    gp = _flow_gp(with_n)
    box = gp.box
    th = torch.tensor([[12.9, 10586.0, 2.04, 0.1, 0.07][:box.dim]], dtype=DT)
    g = torch.Generator().manual_seed(0)
    y = _anand_field(box, th)[0] + 0.05 * torch.randn(N_ANAND, generator=g, dtype=DT)
    if not offsets:
        return prepare_observation(y, GPEmulator(gp), box), pr
    x = torch.linspace(-1, 1, N_ANAND, dtype=DT)

    def off(q: torch.Tensor) -> torch.Tensor:
        return q[..., 0] + q[..., 1] * x

    obox = Box((*box.names, "c", "w"), (*box.lower, -1.0, -0.5), (*box.upper, 1.0, 0.5),
               log_scale=(*box.log_scale, False, False))
    return prepare_observation(y, ObservedEmulator(GPEmulator(gp), box.dim, off), obox), pr


KNOWN = Priors(sigma_known=0.05)
JOINT_PRIORS = Priors(sigma_known=0.05, sigma_c_max=7.0, corr_range=(0.1, 20.0))

#: declared density ("module:function", as in koh.FAST_DENSITIES) -> its problems: name ->
#: a function returning the model's arguments (inputs, priors)
PROBLEMS: dict[str, dict[str, Callable[[], tuple]]] = {
    "solderpyro.calibration.fastkoh:direct_flat": {
        "seed": lambda: _direct(T_BOX, Priors(sigma_max=5.0)),
        "log-box-known-sigma": lambda: _direct(LOG_T_BOX, Priors(sigma_known=0.6)),
    },
    "solderpyro.calibration.fastkoh:joint_flat": {
        "seed": lambda: _seed_joint(Priors()),
        "three-t-shared-corr": lambda: _multi_joint(False, Priors()),
        "three-t-ard-known-sigma": lambda: _multi_joint(True, JOINT_PRIORS),
        "product-design-kronecker": lambda: _product_joint(Priors()),
    },
    "solderpyro.calibration.reduced:pca_flat": {
        "pca": lambda: _pca(False, Priors(sigma_max=2.0)),
        "pca-known-sigma": lambda: _pca(False, KNOWN),
        "pca-offsets": lambda: _pca(True, Priors(sigma_max=2.0)),
        "pca-offsets-known-sigma": lambda: _pca(True, KNOWN),
        "flow-coords": lambda: _flow(False, False, Priors(sigma_max=2.0)),
        "flow-coords-known-sigma": lambda: _flow(False, False, KNOWN),
        "flow-coords-offsets": lambda: _flow(False, True, Priors(sigma_max=2.0)),
        "flow-inputs-logit": lambda: _flow(True, False, KNOWN),
    },
}

CASES = [(model, ref, name) for model, refs in FAST_DENSITIES.items() for ref in refs
         for name in PROBLEMS.get(ref, {"(no problem declared)": None})]


# -------------------------------------------------------------------------- comparison
def _points(fm, pr: Priors, rng: np.random.Generator) -> list[np.ndarray]:
    """Unconstrained flat vectors: uniform in (-1.5, 1.5); a LogNormal site near its prior;
    coordinates of a joint map (``fm.reparam``) at unit values uniform in (0.05, 0.95)."""
    out = []
    for _ in range(N_POINTS):
        q = rng.uniform(-1.5, 1.5, fm.dim)
        for s in fm.sites:
            if s.positive:
                q[s.offset:s.offset + s.size] = (math.log(pr.sigma_known)
                                                 + 0.1 * rng.standard_normal(s.size))
        if getattr(fm, "reparam", None) is not None:
            ri, rc = fm.reparam
            q[ri] = rc.inverse(rng.uniform(0.05, 0.95, len(ri)))
        out.append(q)
    return out


def _pyro_logp_and_grad(potential, fm, q: np.ndarray) -> tuple[float, np.ndarray]:
    """Pyro's -potential_energy at the flat vector ``q (d,)`` laid out as ``fm.sites``
    (Pyro's own unconstrained coordinates: the logit of a unit interval), and its autograd
    gradient ``(d,)``.

    Where ``fm`` samples unit-interval coordinates ``ri`` in another map (``fm.reparam``:
    ``t = forward(q)`` with ``log|det dt/dq|`` and the gradient ``vjp``), Pyro's density is
    carried into those coordinates: ``u_ri = logit(t)``, ``log p(q) = log p_pyro(u) -
    sum log(t (1 - t)) + log|det dt/dq|`` (the logit's Jacobian out, the map's in), and the
    gradient in ``q`` is ``vjp`` of ``d/dt [log p_pyro(u) - sum log(t (1 - t))] =
    (g_u - (1 - 2 t)) / (t (1 - t))``."""
    rep = getattr(fm, "reparam", None)
    u = q.copy()
    if rep is not None:
        ri, rc = rep
        t, ld, vjp = rc.forward(q[ri])
        u[ri] = np.log(t) - np.log1p(-t)
    ut = torch.tensor(u, dtype=DT, requires_grad=True)
    params = {s.name: ut[s.offset:s.offset + s.size] if s.vector else ut[s.offset]
              for s in fm.sites}
    pe = potential(params)
    (g,) = torch.autograd.grad(pe, ut)
    lp, grad = -float(pe.detach()), -g.numpy()
    if rep is not None:
        lp += ld - float(np.log(t * (1.0 - t)).sum())
        grad[ri] = vjp((grad[ri] - (1.0 - 2.0 * t)) / (t * (1.0 - t)))
    return lp, grad


def compare(model, density, args, seed: int = 0) -> tuple[float, float]:
    """The largest value difference (after removing the constant) and gradient difference
    between ``density(*args)`` and Pyro's potential of ``model(*args)``, each relative to the
    scale its tolerance follows (``max(1, |log density|)``, ``max(1, max |gradient|)``)."""
    import pyro
    from pyro.infer.mcmc.util import initialize_model

    fm = density(*args)
    pyro.set_rng_seed(seed)
    _, potential, _, _ = initialize_model(model, model_args=args, jit_compile=False)
    rng = np.random.default_rng(seed)
    diffs, scale, g_err = [], 1.0, 0.0
    for q in _points(fm, args[1], rng):
        lp, g = fm.logp_and_grad(q)
        lp_ref, g_ref = _pyro_logp_and_grad(potential, fm, q)
        assert math.isfinite(lp) and math.isfinite(lp_ref), (q, lp, lp_ref)
        diffs.append(lp - lp_ref)
        scale = max(scale, abs(lp_ref))
        g_err = max(g_err, float(np.abs(g - g_ref).max()) / max(1.0, np.abs(g_ref).max()))
    return float(np.ptp(diffs)) / scale, g_err


@pytest.mark.parametrize("model,ref,problem", CASES,
                         ids=[f"{m.__name__}-{r.rpartition(':')[2]}-{p}" for m, r, p in CASES])
def test_fast_density_equals_the_pyro_model(model, ref, problem):
    """Value (up to one constant) and gradient equal to Pyro's potential of the model, and
    the default dispatch (``flat_model``) takes this density for the problem."""
    assert ref in PROBLEMS, f"give {ref} (declared on {model.__name__}) a problem in PROBLEMS"
    args = PROBLEMS[ref][problem]()
    density = fast_densities(model)[FAST_DENSITIES[model].index(ref)]
    assert type(flat_model(model, args)) is type(density(*args))
    for earlier in fast_densities(model)[:FAST_DENSITIES[model].index(ref)]:
        with pytest.raises(NotImplementedError):
            earlier(*args)
    val_err, grad_err = compare(model, density, args)
    print(f"{model.__name__} {ref} {problem}: value {val_err:.2e}, gradient {grad_err:.2e}")
    assert val_err <= REL, (problem, val_err)
    assert grad_err <= REL, (problem, grad_err)


@pytest.mark.parametrize("model,ref,problem", CASES,
                         ids=[f"{m.__name__}-{r.rpartition(':')[2]}-{p}" for m, r, p in CASES])
def test_constrained_round_trip(model, ref, problem):
    """Unconstrained -> constrained (to_samples) -> unconstrained is the identity (1e-9)."""
    fm = flat_model(model, PROBLEMS[ref][problem]())
    q = _points(fm, PROBLEMS[ref][problem]()[1], np.random.default_rng(2))[0]
    logit = np.abs(q) < 1.5  # interval sites in Pyro's coordinates: out to +-3
    if getattr(fm, "reparam", None) is not None:
        logit[fm.reparam[0]] = False  # a joint map's: at unit values in (0.05, 0.95)
    q[logit] *= 2.0
    samples = fm.to_samples(q[None, None])
    back = fm.to_unconstrained({k: v[0, 0] for k, v in samples.items()})
    np.testing.assert_allclose(back, q, rtol=1e-9, atol=1e-9)
