"""Native (C) kernels of the CPU float64 path against the torch path they replace: the fused Anand
update (4-lane and scalar), the fused solder-layer evaluation, the bordered-band factorization,
whole solves (with effects), thread counts, and the fallback to torch (switched off, or no
compiler)."""

import shutil
import warnings

import pytest
import torch

from solderpyro import _native
from solderpyro.fem.loading import ThermalCycle, TimeStepping
from solderpyro.fem.mesh import Layer, MeshSpec
from solderpyro.fem.points import BandTangent
from solderpyro.fem.problem import Problem
from solderpyro.fem.solver import SpecimenSolver
from solderpyro.fem.thermo import MemberStep
from solderpyro.materials.elastic import condense_zz, iso_3d
from solderpyro.materials.integrate import PointInputs, PointState, Tangent3D, return_map_3d
from solderpyro.params import anand_tensor

F64 = torch.float64
SHORT = ThermalCycle((0.0, 600.0, 1500.0), (25.0, 75.0, 75.0))
LAYERS = (Layer("copper", "copper", -4.0, 0.0, 4, 0.25, "top"),
          Layer("solder", "solder", 0.0, 0.5, 2),
          Layer("steel", "steel", 0.5, 4.5, 4, 0.25, "bottom"))
#: the contract tests' members: Liu's constants and three corners of the seed box
ROWS = [{}, {"s0": 5.0, "QR": 7000.0, "xi": 5.0, "m": 0.05},
        {"s0": 25.0, "QR": 13000.0, "xi": 1.0, "m": 0.5}, {"s0": 9.0, "xi": 3.0, "m": 0.1}]


def small_problem(**kw):
    return Problem(layers=LAYERS, mesh=MeshSpec(nx=10), cycle=SHORT,
                   stepping=TimeStepping(dT_max=10.0, dwell_dt0=20.0, dt_max=450.0), **kw)


def params(rows):
    return torch.stack([anand_tensor(r, dtype=F64) for r in rows])
HAVE_CC = bool(shutil.which("gcc") or shutil.which("cc"))

pytestmark = pytest.mark.skipif(not HAVE_CC, reason="no C compiler: the torch path only")


@pytest.fixture(autouse=True)
def _native_on(monkeypatch):
    monkeypatch.delenv("SOLDERPYRO_NATIVE", raising=False)
    assert _native.library() is not None, "the native kernels failed to build"


def _random_points(n, seed, kinematic=False):
    """States, strains and constants over and beyond the seed box: xi*q_tr/s up to ~50,
    m down to 0.05, start resistances from 0.5 to 1.5 s0, steps from 0.1 to 100 s."""
    g = torch.Generator().manual_seed(seed)
    r = lambda *s: torch.rand(*s, generator=g, dtype=F64)  # noqa: E731
    p = anand_tensor({}, dtype=F64).repeat(n, 1)
    p[:, 0] = 5 + 20 * r(n)
    p[:, 1] = 7000 + 6000 * r(n)
    p[:, 3] = 1 + 4 * r(n)
    p[:, 4] = torch.where(r(n) < 0.3, torch.full((n,), 0.05, dtype=F64), 0.05 + 0.45 * r(n))
    p[:, 8] = 0.8 + 0.8 * r(n)
    eps = (r(n, 4) - 0.5) * 10 ** (-1.5 - 3 * r(n, 1))  # up to |eps| ~ 0.03: q_tr/s ~ 10
    X = (r(n, 4) - 0.5) * 10 if kinematic else None
    st = PointState((r(n, 4) - 0.5) * 1e-3, p[:, 0] * (0.5 + r(n)), torch.zeros(n, dtype=F64), X)
    T, dt = 298 + 100 * r(n), 10 ** (3 * r(n) - 1)
    Ck = 2000 * r(n) if kinematic else None
    return eps, st, p, T, dt, Ck


def _close(a, b, rtol):
    """|a - b| <= rtol * max|b| per field (None or factored tangents field by field)."""
    if a is None or b is None:
        assert a is None and b is None
        return
    if isinstance(a, Tangent3D):
        for f in ("K", "g2", "coef", "nb"):
            _close(torch.broadcast_to(getattr(a, f), getattr(b, f).shape), getattr(b, f), rtol)
        return
    scale = b.abs().max().clamp_min(1e-300)
    assert (a - b).abs().max() <= rtol * scale, ((a - b).abs().max() / scale).item()


def _fields(out):
    sig, st, C, dep, x = out
    return [sig, st.eps_p, st.s, st.eps_zz, st.X, C, dep, x]


@pytest.mark.parametrize("kinematic", [False, True])
@pytest.mark.parametrize("warm", [False, True])
@pytest.mark.parametrize("n", [3, 4099])
def test_kernel_matches_torch_path(monkeypatch, kinematic, warm, n):
    """The fused update equals the torch path on random states to 1e-12 relative: stress,
    state, back stress, factored tangent, dep and the local solution (both from the predictor
    and from a perturbed warm start; 4099 points: the 4-lane loop and its scalar tail)."""
    eps, st, p, T, dt, Ck = _random_points(n, seed=n + 7 * kinematic, kinematic=kinematic)
    args = (eps, st, p, PointInputs(T, dt, 2e-4 * torch.ones(n, dtype=F64), 32000.0, 0.35, Ck))
    guess = None
    if warm:
        x0 = return_map_3d(*args, tangent=False)[4]
        guess = x0 * (1 + 1e-3 * torch.randn(x0.shape, generator=torch.Generator().manual_seed(1),
                                               dtype=F64))
    nat = return_map_3d(*args, guess=guess, tangent="factored")
    monkeypatch.setenv("SOLDERPYRO_NATIVE", "0")
    ref = return_map_3d(*args, guess=guess, tangent="factored")
    assert isinstance(ref[2], Tangent3D) and isinstance(nat[2], Tangent3D)
    for a, b in zip(_fields(nat), _fields(ref), strict=True):
        _close(a, b, 1e-12)
    assert (nat[3] / ref[3] - 1).abs().max() <= 1e-12  # dep, relative at every point
    assert (nat[1].s / ref[1].s - 1).abs().max() <= 1e-12


def test_simd_and_scalar_paths_agree():
    """The 4-lane (libmvec) and the scalar loop of the kernel: same iterates, rounding only."""
    if _native.simd_width() != 4:
        pytest.skip("no 4-lane path on this machine")
    eps, st, p, T, dt, Ck = _random_points(4096, seed=3, kinematic=True)
    args = (eps, st, p, PointInputs(T, dt, 2e-4, 32000.0, 0.35, Ck), None, True)
    a = _native.anand_update(*args, simd=True)
    b = _native.anand_update(*args, simd=False)
    for x, y in zip(a, b, strict=True):
        for u, v in zip(x, y, strict=True) if isinstance(x, tuple) else [(x, y)]:
            if v is None:
                assert u is None
                continue
            assert (u - v).abs().max() <= 1e-12 * v.abs().max()


def test_threads_do_not_change_the_result(monkeypatch):
    """Points are independent: 1 or 2 threads of the kernels' pool give the same bits.
    (The budget is set directly: torch.set_num_threads(n > 1) itself breaks batched LU solves
    with torch 2.13 / MKL for the rest of the process.)"""
    eps, st, p, T, dt, Ck = _random_points(40000, seed=5, kinematic=True)
    args = (eps, st, p, PointInputs(T, dt, 2e-4, 32000.0, 0.35, Ck), None, True)
    monkeypatch.setattr(_native._budget, "n", 1, raising=False)
    a = _native.anand_update(*args)
    monkeypatch.setattr(_native._budget, "n", 2, raising=False)
    assert _native.threads("points", 40000) == 2 and _native.threads("points", 100) == 1
    b = _native.anand_update(*args)
    for x, y in zip(a, b, strict=True):
        for u, v in zip(x, y, strict=True) if isinstance(x, tuple) else [(x, y)]:
            assert (u is None and v is None) or torch.equal(u, v)


def _chol_solve(K, rhs):
    """Reference dense solve through torch's Cholesky (``(b, n, n)``, ``(b, n)``)."""
    return torch.cholesky_solve(rhs.unsqueeze(-1), torch.linalg.cholesky(K)).squeeze(-1)


def _tangents(solver, b, seed):
    """Random positive definite factored tangents ``(b, n_e, n_qp)`` of the solder points."""
    g = torch.Generator().manual_seed(seed)
    sh = (b, solver.n_s, solver.B.shape[1])
    K = torch.full(sh, 32000.0 / (3 * 0.3), dtype=F64)
    g2 = 2 * 11851 * (0.05 + torch.rand(sh, generator=g, dtype=F64))
    coef = -0.9 * g2 * torch.rand(sh, generator=g, dtype=F64)
    nb = torch.randn(*sh, 4, generator=g, dtype=F64)
    nb[..., :3] -= nb[..., :3].mean(-1, keepdim=True)
    return Tangent3D(K, g2, coef, nb / nb.norm(dim=-1, keepdim=True))


@pytest.mark.parametrize("plane", ["stress", "strain"])
def test_bordered_band_solve_matches_dense(plane):
    """Assembly + bordered-band Cholesky + solve equal the dense torch path (assembled tangent,
    torch.linalg.solve) on the reference mesh, for a subset of cache slots."""
    solver = SpecimenSolver(Problem(plane=plane))
    bb = solver.bb
    assert bb is not None and bb.nI > 0 and bb.nD > 0
    T3 = _tangents(solver, 5, seed=2)
    F = torch.zeros(8, bb.nbuf, dtype=F64)
    slots = torch.tensor([6, 0, 3, 1, 7])
    info = solver.newton.factor_native(F, slots, T3)
    assert torch.equal(info, torch.zeros(5, dtype=torch.int32))
    rhs = torch.randn(5, solver.n_r, generator=torch.Generator().manual_seed(4), dtype=F64)
    x = bb.solve(F, slots, rhs)
    ref = _chol_solve(solver.newton.tangent(solver.points.condense(T3)), rhs)
    assert ((x - ref).norm(dim=1) / ref.norm(dim=1)).max() < 1e-10


def test_bordered_band_with_plastic_band_matches_dense():
    """The banded discretisation (copper band with condensed incompatible modes) too."""
    solver = SpecimenSolver(Problem(), effects=("copper_plasticity",)).banded
    assert solver is not None and solver.band is not None and solver.bb is not None
    b = 3
    T3 = _tangents(solver, b, seed=5)
    n_eb = solver.B.shape[0] - solver.n_s
    Cb = condense_zz(iso_3d(torch.tensor(130e3 / 3 / 0.32, dtype=F64),
                            torch.tensor(130e3 / 2.68, dtype=F64)), "stress")
    scale = 0.5 + torch.rand(b, n_eb, 4, 1, 1, generator=torch.Generator().manual_seed(0),
                             dtype=F64)
    C3 = BandTangent(T3, Cb * scale)
    F = torch.zeros(b, solver.bb.nbuf, dtype=F64)
    info = solver.newton.factor_native(F, torch.arange(b), C3)
    assert torch.equal(info, torch.zeros(b, dtype=torch.int32))
    rhs = torch.randn(b, solver.n_r, generator=torch.Generator().manual_seed(1), dtype=F64)
    x = solver.bb.solve(F, torch.arange(b), rhs)
    ref = _chol_solve(solver.newton.tangent(solver.points.condense(C3)), rhs)
    assert ((x - ref).norm(dim=1) / ref.norm(dim=1)).max() < 1e-10


def test_not_positive_definite_is_reported():
    """A tangent that is not positive definite gives a nonzero info (the member refactors or
    fails, as with the dense Cholesky)."""
    solver = SpecimenSolver(Problem())
    T3 = _tangents(solver, 2, seed=0)
    T3.g2[1] = -1e6  # negative shear stiffness everywhere in member 1
    F = torch.zeros(2, solver.bb.nbuf, dtype=F64)
    info = solver.newton.factor_native(F, torch.arange(2), T3)
    assert info[0] == 0 and info[1] != 0


@pytest.mark.parametrize("plane", ["stress", "strain"])
def test_fused_evaluation_matches_torch(monkeypatch, plane):
    """Strains, update, plane-stress condensation and residual in one native call equal the
    torch path of the solver (its _material and _residual) to 1e-12 relative."""
    solver = SpecimenSolver(small_problem(plane=plane))
    b = 3
    p = params(ROWS[:b])
    g = torch.Generator().manual_seed(0)
    u = 2e-3 * torch.randn(b, solver.n_r, generator=g, dtype=F64)
    st = PointState(1e-4 * torch.randn(b, *solver.wdet.shape, 4, generator=g, dtype=F64),
                    p[:, 0, None, None] * (1 + 0.1 * torch.rand(b, *solver.wdet.shape,
                                                                 generator=g, dtype=F64)),
                    torch.zeros(b, *solver.wdet.shape, dtype=F64))
    ezz = 1e-4 * torch.randn(b, *solver.wdet.shape, generator=g, dtype=F64)
    ezz = ezz if plane == "stress" else None
    fext = solver.f_ext(60.0).expand(b, -1)
    step = MemberStep(p, solver.thermo.at_temperature(60.0), 30.0)
    nat = solver.points.material_fused(u, ezz, st, step, None)
    assert nat is not None
    monkeypatch.setenv("SOLDERPYRO_NATIVE", "0")
    assert solver.points.material_fused(u, ezz, st, step, None) is None
    ref = solver.points.material(u, ezz, st, step, condense=False)
    R = solver.newton.residual(u, ref[0], fext)
    for a, r in zip([nat[0], nat[2], nat[3], nat[4].eps_p, nat[4].s, nat[5], nat[6]],
                    [ref[0], ref[2], ref[3], ref[4].eps_p, ref[4].s, ref[5], ref[6]],
                    strict=True):
        _close(a, r, 1e-12)
    _close(nat[7] - fext, R, 1e-12)
    if plane == "stress":  # the accompanying eps_zz update
        du = 1e-4 * torch.randn(b, solver.n_r, generator=g, dtype=F64)
        dz = solver.points.dezz(du, ref[2], nat[3])
        monkeypatch.delenv("SOLDERPYRO_NATIVE")
        _close(solver.points.dezz(du, ref[2], nat[3]), dz, 1e-12)


@pytest.mark.parametrize("plane", ["stress", "strain"])
def test_solve_matches_torch_path(monkeypatch, plane):
    """Whole solves (the batch of the contract tests): native and torch paths agree to 1e-11
    of max|V| (both Newton iterations reach the same discrete solution; their different
    factorizations and sums leave ~1e-14 of max|V|, measured)."""
    solver = SpecimenSolver(small_problem(plane=plane))
    p = params(ROWS)
    V = solver.solve(p, [600.0, 1500.0]).V
    monkeypatch.setenv("SOLDERPYRO_NATIVE", "0")
    ref = solver.solve(p, [600.0, 1500.0]).V
    assert (V - ref).abs().max() <= 1e-11 * ref.abs().max()
    assert (V[0] - V[1]).abs().max() > 0.05


def test_solve_with_effects_matches_torch_path(monkeypatch):
    """Back stress, temperature-dependent modulus and a yielding copper band (per-member
    fields, the banded discretisation): native and torch paths agree to 1e-11 of max|V|."""
    effects = ("kinematic_hardening", "modulus_temperature", "copper_plasticity")
    solver = SpecimenSolver(small_problem(), effects=effects)
    names = solver.param_names()
    q = torch.tensor([[800.0, 60.0, 3e-3, 0.0, 0.01, 400.0], [0.0, 0.0, 0.0, 0.0, 0.01, 10.0],
                      [1500.0, 150.0, 1e-3, 0.7, 0.2, 12.0]],
                     dtype=F64)  # C_k, gamma_k, k_E, n_E, r_E, sigma_y
    p = torch.cat([anand_tensor({}, dtype=F64)[None].expand(3, -1), q], 1)
    assert p.shape[1] == len(names)
    V = solver.solve(p, [600.0, 1500.0]).V
    monkeypatch.setenv("SOLDERPYRO_NATIVE", "0")
    ref = solver.solve(p, [600.0, 1500.0]).V
    assert torch.isfinite(V).all() and (V - ref).abs().max() <= 1e-11 * ref.abs().max()


def test_switched_off_uses_the_torch_path(monkeypatch):
    """SOLDERPYRO_NATIVE=0: no native call at all (they would raise), dense factors."""
    monkeypatch.setenv("SOLDERPYRO_NATIVE", "0")

    def boom(*a, **k):
        raise AssertionError("native kernel called although switched off")

    for name in ("anand_update", "solder_eval", "dezz"):
        monkeypatch.setattr(_native, name, boom)
    solver = SpecimenSolver(small_problem())
    assert not solver.newton.native_linalg() and "U" in solver.newton.factor_cache(1)
    r = solver.solve(params(ROWS[:2]), [600.0])
    assert bool(r.ok.all())


def test_missing_compiler_warns_once_and_falls_back(monkeypatch, tmp_path):
    """No compiler (or a failed build): one RuntimeWarning, then the torch path."""
    monkeypatch.setattr(_native, "_lib", None)
    monkeypatch.setattr(_native, "_tried", False)
    monkeypatch.setenv("SOLDERPYRO_CACHE_DIR", str(tmp_path))
    monkeypatch.setenv("CC", str(tmp_path / "no-such-compiler"))
    with pytest.warns(RuntimeWarning, match="native kernels unavailable"):
        assert _native.library() is None
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert _native.library() is None  # no second warning
        eps, st, p, T, dt, _ = _random_points(5, seed=0)
        assert not _native.usable(eps)
        sig = return_map_3d(eps, st, p, PointInputs(T, dt, 2e-4, 32000.0, 0.35))[0]
    assert torch.isfinite(sig).all()


def test_autograd_keeps_the_torch_path():
    """Inputs that need a gradient are not native-usable; the solver's implicit correction
    keeps exact derivatives (the contract test checks them against finite differences)."""
    p = anand_tensor({}, dtype=F64).requires_grad_(True)
    assert not _native.usable(p)
    with torch.no_grad():
        assert _native.usable(p)
