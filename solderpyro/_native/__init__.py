"""Optional native (C) kernels of the CPU float64 no-autograd path, compiled with gcc at first use.

The C sources next to this file are compiled once per source, compiler and CPU into a shared
library in a cache directory (``$SOLDERPYRO_CACHE_DIR``, else ``$XDG_CACHE_HOME/solderpyro``,
else ``~/.cache/solderpyro``; the file name carries a hash of all of it), and loaded with
:mod:`ctypes`. Where no compiler is found or the build fails, :func:`library` returns None after
one warning and the callers keep their pure-torch path, which also serves every other device,
dtype and autograd. ``SOLDERPYRO_NATIVE=0`` switches the native kernels off.

The kernels implement the same algorithms as the torch code they replace, point by point or
member by member; results agree to rounding (tests/unit/native/test_native.py).
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import platform
import shutil
import subprocess
import tempfile
import threading
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any, NamedTuple

import torch

_DIR = Path(__file__).resolve().parent
SOURCES = ("anand.c", "linalg.c", "pool.c", "reduced.c", "ridgemap.c", "flowflat.c")
HEADERS = ("anand_simd.h", "pool.h")
CFLAGS = ("-O3", "-march=native", "-ffp-contract=off", "-fPIC", "-shared", "-fno-math-errno",
          "-pthread", "-fopenmp-simd")
#: Tried in order: glibc's vector math library (the 4-lane Anand update on AVX2), then without.
VARIANTS = ((("-DSP_MVEC",), ("-lmvec", "-lm")), ((), ("-lm",)))

#: Points per element the fused element kernels handle (solder_eval, dezz).
MAX_QP = 64
#: Least work for which a kernel uses torch's thread count: points of a material update, members
#: of a factorization or of a solve. Smaller calls run on one thread (a parallel region costs
#: more than it saves there, and much more when the machine is loaded).
PARALLEL_MIN = {"points": 16384, "factor": 8, "solve": 32}

_lock = threading.Lock()
_lib: ctypes.CDLL | None = None
_tried = False


def enabled() -> bool:
    """Whether the native kernels may be used (``SOLDERPYRO_NATIVE`` is not ``0``/``off``)."""
    return os.environ.get("SOLDERPYRO_NATIVE", "1").strip().lower() not in ("0", "off", "false",
                                                                             "no")


def cache_dir() -> Path:
    """Directory of the compiled libraries."""
    env = os.environ.get("SOLDERPYRO_CACHE_DIR")
    if env:
        return Path(env)
    xdg = os.environ.get("XDG_CACHE_HOME")
    return (Path(xdg) if xdg else Path.home() / ".cache") / "solderpyro"


def _cpu_id() -> str:
    """What ``-march=native`` depends on: the CPU's model and flags (Linux), else the platform."""
    try:
        with open("/proc/cpuinfo") as f:
            lines = [ln for ln in f if ln.startswith(("model name", "flags"))]
        return "".join(sorted(set(lines)))
    except OSError:
        return platform.platform() + platform.processor()


def _compiler() -> str | None:
    return os.environ.get("CC") or shutil.which("gcc") or shutil.which("cc")


def _build(cc: str) -> Path:
    src = b"".join((_DIR / s).read_bytes() for s in (*SOURCES, *HEADERS))
    ver = subprocess.run([cc, "--version"], capture_output=True, text=True, check=True).stdout
    key = hashlib.sha256(b"\0".join([src, " ".join(CFLAGS).encode(), repr(VARIANTS).encode(),
                                     ver.encode(), _cpu_id().encode()])).hexdigest()[:16]
    out = cache_dir() / f"solderpyro_native_{key}.so"
    if out.exists():
        return out
    out.parent.mkdir(parents=True, exist_ok=True)
    errors = []
    for defs, libs in VARIANTS:
        fd, tmp = tempfile.mkstemp(suffix=".so", dir=out.parent)
        os.close(fd)
        try:
            cmd = [cc, *CFLAGS, *defs, *(str(_DIR / s) for s in SOURCES), "-o", tmp, *libs]
            r = subprocess.run(cmd, capture_output=True, text=True)
            if r.returncode == 0:
                ctypes.CDLL(tmp)  # loads (e.g. libmvec resolvable) before it is published
                os.replace(tmp, out)  # atomic: concurrent builds of the same key are harmless
                return out
            errors.append(f"{' '.join(cmd)}:\n{r.stderr[-1500:]}")
        except OSError as e:
            errors.append(f"{' '.join(cmd)}: {e}")
        finally:
            if os.path.exists(tmp):
                os.unlink(tmp)
    raise RuntimeError("building the native kernels failed:\n" + "\n".join(errors))


def library() -> ctypes.CDLL | None:
    """The loaded native library, or None (disabled, no compiler, or a failed build: then one
    warning per process names the reason and the torch path is used)."""
    global _lib, _tried
    if not enabled():
        return None
    if _tried:
        return _lib
    with _lock:
        if _tried:
            return _lib
        try:
            cc = _compiler()
            if cc is None:
                raise RuntimeError("no C compiler (gcc or $CC) found")
            lib = ctypes.CDLL(str(_build(cc)))
            _declare(lib)
            _lib = lib
        except Exception as e:  # noqa: BLE001 - any failure means: use the torch path
            warnings.warn(f"solderpyro: native kernels unavailable, using the torch path ({e})",
                          RuntimeWarning, stacklevel=2)
            _lib = None
        _tried = True
    return _lib


def _declare(lib: ctypes.CDLL) -> None:
    P, L, I = ctypes.c_void_p, ctypes.c_long, ctypes.c_int
    dims = ctypes.POINTER(ctypes.c_long)
    for name, res, args in (
            ("sp_anand_update", I, [L, *([P] * 13), I, *([P] * 10), I, I]),
            ("sp_simd_width", I, []),
            ("sp_solder_eval", I, [dims, *([P] * 17), P, P, I, *([P] * 12), I, I]),
            ("sp_dezz", None, [dims, *([P] * 8), P]),
            ("sp_bb_factor", None, [dims, *([P] * 7), L, P, P, P, P, P, P, L, P, I, P, L, P, I]),
            ("sp_bb_solve", None, [dims, P, P, P, L, P, P, P, P, I]),
            ("sp_reduced_work_size", L, [P]),
            ("sp_reduced_loglik", I, [P, P, P, P, ctypes.c_double, P, P]),
            ("sp_ridge_forward", None, [L, *([P] * 9)]),
            ("sp_ridge_vjp", None, [L, *([P] * 7)]),
            ("sp_flowflat_work_size", L, [P, L]),
            ("sp_flowflat", I, [P] * 8)):
        f = getattr(lib, name)
        f.restype = res
        f.argtypes = args


def usable(*tensors: torch.Tensor | None) -> bool:
    """Whether the native path applies: enabled, built, and every tensor a CPU float64 one
    that needs no gradient (non-tensors and None are ignored)."""
    for t in tensors:
        if isinstance(t, torch.Tensor) and (t.device.type != "cpu" or t.dtype != torch.float64
                                            or (t.requires_grad and torch.is_grad_enabled())):
            return False
    return library() is not None


def simd_width() -> int:
    """Lanes of the compiled Anand update: 4 with the AVX2 / libmvec path, else 1 (0: no
    library)."""
    lib = library()
    return 0 if lib is None else int(lib.sp_simd_width())


_budget = threading.local()  # thread count handed to the kernels by kernel_threads()


def threads(kind: str, work: int) -> int:
    """Threads for a kernel call of ``work`` items of ``kind`` (see :data:`PARALLEL_MIN`): the
    count of :func:`kernel_threads` where active, else torch's."""
    n = getattr(_budget, "n", None) or torch.get_num_threads()
    return n if work >= PARALLEL_MIN[kind] else 1


_omp: list[ctypes.CDLL | None] = []  # torch's OpenMP runtime, once looked up


def _openmp() -> ctypes.CDLL | None:
    """torch's OpenMP runtime when ATen's parallel backend is OpenMP, else None."""
    if not _omp:
        found = None
        if "parallel backend: OpenMP" in torch.__config__.parallel_info():
            lib = Path(torch.__file__).resolve().parent / "lib" / "libgomp.so.1"
            for name in (str(lib), "libgomp.so.1"):
                try:
                    found = ctypes.CDLL(name)
                    break
                except OSError:
                    continue
        _omp.append(found)
    return _omp[0]


@contextmanager
def kernel_threads() -> Iterator[None]:
    """The native kernels keep torch's current intra-op thread count while torch's own
    operations run on one thread inside the block (restored on exit).

    Used around a solve whose heavy work is in the kernels: the remaining torch operations are
    small, and each of their parallel regions waits for every thread of the team, which on a
    machine shared with other jobs costs milliseconds per region; the kernels' pool
    (``pool.c``) never waits for a thread that has not started. Only the OpenMP thread count of
    the calling thread is changed (``omp_set_num_threads``, which ATen's OpenMP backend reads),
    not ``torch.set_num_threads``: with torch 2.13 / MKL an explicit
    ``torch.set_num_threads(n > 1)`` breaks batched LU solves for the rest of the process.
    Without an OpenMP backend the block changes nothing.
    """
    old, prev = torch.get_num_threads(), getattr(_budget, "n", None)
    omp = _openmp() if old > 1 else None
    _budget.n = prev or old
    if omp is not None:
        omp.omp_set_num_threads(1)
    try:
        yield
    finally:
        if omp is not None:
            omp.omp_set_num_threads(old)
        _budget.n = prev


def ptr(t: torch.Tensor | None) -> int | None:
    """The address of ``t``'s data for a kernel's pointer argument (``t`` contiguous, of the
    kernel's dtype; the caller keeps it alive for the call), or None for a NULL pointer."""
    return None if t is None else t.data_ptr()


def _field(a, shape: tuple[int, ...], width: int = 0) -> tuple[torch.Tensor, int]:
    """``a`` (broadcastable to ``shape``, or to ``(*shape, width)`` when ``width``) as a flat
    contiguous float64 tensor and the divisor ``d`` such that point ``i`` reads row ``i // d``."""
    a = torch.as_tensor(a, dtype=torch.float64)
    lead = a.shape[:-1] if width else a.shape
    if width and a.shape[-1] != width:
        raise ValueError(f"expected a last dimension of {width}, got {tuple(a.shape)}")
    n = 1
    for d in shape:
        n *= d
    lead = (1,) * (len(shape) - len(lead)) + tuple(lead)
    k = len(lead)
    while k > 0 and lead[k - 1] == 1:
        k -= 1
    if tuple(lead[:k]) == tuple(shape[:k]):
        div = 1
        for d in shape[k:]:
            div *= d
        return a.reshape(-1).contiguous(), max(div, 1) if n else 1
    full = torch.broadcast_to(a, (*shape, width) if width else shape)
    return full.reshape(-1).contiguous(), 1


def _point_fields(p, inputs, shape: tuple[int, ...]):
    """The per-point inputs of a kernel call as flat float64 fields with their row divisors
    (:func:`_field`): ``[p, T, dt, eps_th, E, nu]``, the ``C_k`` field or None, and the
    divisors ``(7,)`` in the kernels' order."""
    fields = [_field(p, shape, 9), *(_field(v, shape) for v in inputs[:5])]
    ck = None if inputs.C_k is None else _field(inputs.C_k, shape)
    div = (ctypes.c_long * 7)(*[f[1] for f in fields], 1 if ck is None else ck[1])
    return fields, ck, div


def anand_update(eps, state, p, inputs, guess, tangent: bool, simd: bool = True):
    """Backward-Euler Anand update at every point, fused (the C twin of the no-autograd path of
    :func:`solderpyro.materials.integrate.return_map_3d`).

    Args:
        eps: total strain, Mandel ``(..., 4)``.
        state: the start-of-step state (a :class:`~solderpyro.materials.integrate.PointState`
            or anything with its fields): inelastic strain ``eps_p (..., 4)``, resistance
            ``s (...)`` MPa, back stress ``X (..., 4)`` MPa or None.
        p: Anand constants broadcastable to ``(..., 9)``.
        inputs: the step's conditions, a :class:`~solderpyro.materials.integrate.PointInputs`
            (read by position, then ``C_k`` by name): ``T`` (K), ``dt`` (s), ``eps_th``,
            ``E`` (MPa), ``nu`` broadcastable to ``(...)``; ``C_k``: Prager modulus (MPa)
            broadcastable to ``(...)``, or None (no kinematic hardening).
        guess: warm start ``(..., 2)`` = (zeta, s), or None.
        tangent: whether to return the factored tangent.
        simd: use the 4-lane path where it is compiled in (:func:`simd_width`); False runs the
            scalar loop (the same iterates; for tests).
    Returns:
        ``(sigma (..., 4), eps_p (..., 4), s (...), X (..., 4) or None, dep (...), x (..., 2),
        tangent)`` with ``tangent = (K, g2, coef, nb (..., 4))`` (each ``(...)``) or None;
        ``X`` is returned whenever ``C_k`` or ``state.X`` is given.
    """
    lib = library()
    assert lib is not None
    shape = tuple(eps.shape[:-1])
    n = 1
    for d in shape:
        n *= d
    tkw = dict(dtype=torch.float64, device=eps.device)
    flat = lambda t, w: t.reshape(n, w).contiguous() if w else t.reshape(n).contiguous()  # noqa: E731
    X_n = state.X
    e4 = flat(torch.broadcast_to(eps, (*shape, 4)), 4)
    pn = flat(torch.broadcast_to(state.eps_p, (*shape, 4)), 4)
    sn = flat(torch.broadcast_to(state.s, shape), 0)
    Xn = None if X_n is None else flat(torch.broadcast_to(X_n, (*shape, 4)), 4)
    g = None if guess is None else flat(torch.broadcast_to(guess, (*shape, 2)), 2)
    fields, ck, div = _point_fields(p, inputs, shape)
    sigma, ep_out = torch.empty(n, 4, **tkw), torch.empty(n, 4, **tkw)
    s_out, dep, x = torch.empty(n, **tkw), torch.empty(n, **tkw), torch.empty(n, 2, **tkw)
    X_out = None if (ck is None and X_n is None) else torch.empty(n, 4, **tkw)
    tg = (torch.empty(n, **tkw), torch.empty(n, **tkw), torch.empty(n, **tkw),
          torch.empty(n, 4, **tkw)) if tangent else (None,) * 4
    nt = threads("points", n)
    lib.sp_anand_update(n, ptr(e4), ptr(pn), ptr(sn), ptr(Xn),
                        *(ptr(f[0]) for f in fields), None if ck is None else ptr(ck[0]),
                        ctypes.addressof(div),
                        ptr(g), int(bool(tangent)), ptr(sigma), ptr(ep_out), ptr(s_out),
                        ptr(X_out), ptr(dep), ptr(x), *(ptr(t) for t in tg), nt,
                        int(simd))
    r = lambda t, *w: t.reshape(*shape, *w)  # noqa: E731
    tan = None if not tangent else (r(tg[0]), r(tg[1]), r(tg[2]), r(tg[3], 4))
    return (r(sigma, 4), r(ep_out, 4), r(s_out), None if X_out is None else r(X_out, 4),
            r(dep), r(x, 2), tan)


class SolderLayer(NamedTuple):
    """The fixed operators of a solder layer for :func:`solder_eval` (set up once per mesh).

    Attributes:
        edof: ``(n_e, 8)`` int32 retained dof of each element dof (a fixed dof: any index, with
            zero columns in ``B`` and ``Bw``).
        B: ``(n_e, n_qp, 3, 8)`` B-matrices, 1/mm.
        Bw: ``B * w det J`` ``(n_e, n_qp, 3, 8)``, mm.
        S_border: ``(dof_D (n_D,) int32, S_DD (n_D, n_D))``: the retained dofs where the
            condensed linear stiffness ``S`` (MPa mm) is nonzero and that block; ``S u`` is
            added to the forces.
        plane_stress: condense the in-plane stress on eps_zz (else plane strain).
    """

    edof: torch.Tensor
    B: torch.Tensor
    Bw: torch.Tensor
    S_border: tuple[torch.Tensor, torch.Tensor]
    plane_stress: bool


def _element_call(u: torch.Tensor, B: torch.Tensor) -> tuple[ctypes.CDLL, tuple[int, int, int]]:
    """The library and the point-array shape ``(b, n_e, n_qp)`` of an element-wise call on
    ``u (b, n_r)`` with strain operators ``B (n_e, n_qp, ...)``; at most :data:`MAX_QP`
    points per element (the kernels' stack buffers)."""
    lib = library()
    assert lib is not None
    n_e, n_qp = B.shape[:2]
    if n_qp > MAX_QP:
        raise ValueError(f"at most {MAX_QP} points per element, got {n_qp}")
    return lib, (u.shape[0], n_e, n_qp)


def solder_eval(u, ezz, layer: SolderLayer, state, p, inputs, guess, simd: bool = True):
    """Fused evaluation of a solder layer: strains, the Anand update (:func:`anand_update`),
    the plane-stress condensation of the in-plane stress on eps_zz and the internal forces.

    Args:
        u: ``(b, n_r)`` retained displacements, mm.
        ezz: ``(b, n_e, n_qp)`` out-of-plane strain (plane stress), or None (plane strain: 0).
        layer: the layer's :class:`SolderLayer` operators.
        state: start-of-step :class:`~solderpyro.materials.integrate.PointState`, leading shape
            ``(b, n_e, n_qp)``.
        p, inputs, guess: as in :func:`anand_update`, broadcastable to the points
            ``(b, n_e, n_qp)``.
        simd: as in :func:`anand_update`.
    Returns:
        ``(sigma_ip (b, n_e, n_qp, 3), sigma_zz (b, n_e, n_qp), eps_p (..., 4), s, X or None,
        dep, x (..., 2), (K, g2, coef, nb (..., 4)), f (b, n_r))``; stresses MPa, forces
        ``f = S u + sum_e Bw^T sigma_ip`` (N/mm) on the retained dofs.
    """
    lib, shape = _element_call(u, layer.B)
    b, n_r = u.shape
    n_e, n_qp = shape[1:]
    n = b * n_e * n_qp
    tkw = dict(dtype=torch.float64, device=u.device)
    flat = lambda t, *w: torch.broadcast_to(t, (*shape, *w)).reshape(n, *w).contiguous()  # noqa: E731
    uc, edof = u.contiguous(), layer.edof.contiguous()
    B, Bw = layer.B.contiguous(), layer.Bw.contiguous()
    zc = None if ezz is None else flat(ezz)
    pn, sn = flat(state.eps_p, 4), flat(state.s)
    Xn = None if state.X is None else flat(state.X, 4)
    g = None if guess is None else flat(guess, 2)
    fields, ck, div = _point_fields(p, inputs, shape)
    e = lambda *w: torch.empty(n, *w, **tkw)  # noqa: E731
    sig, szz, ep, s_out, dep, x = e(3), e(), e(4), e(), e(), e(2)
    X_out = None if (ck is None and state.X is None) else e(4)
    tg = (e(), e(), e(), e(4))
    fint = torch.empty(b, n_r, **tkw)
    dof_D, S_DD = (t.contiguous() for t in layer.S_border)
    dims = (ctypes.c_long * 5)(b, n_e, n_qp, n_r, len(dof_D))
    rc = lib.sp_solder_eval(dims, ptr(uc), ptr(zc), ptr(edof), ptr(dof_D), ptr(S_DD),
                            ptr(B), ptr(Bw), ptr(pn),
                            ptr(sn), ptr(Xn), *(ptr(f[0]) for f in fields),
                            None if ck is None else ptr(ck[0]), ctypes.addressof(div), ptr(g),
                            int(layer.plane_stress), ptr(sig), ptr(szz), ptr(ep), ptr(s_out),
                            ptr(X_out), ptr(dep), ptr(x), *(ptr(t) for t in tg), ptr(fint),
                            threads("points", n), int(simd))
    if rc != 0:
        raise RuntimeError(f"sp_solder_eval failed ({'out of memory' if rc == -1 else rc})")
    r = lambda t, *w: t.reshape(*shape, *w)  # noqa: E731
    return (r(sig, 3), r(szz), r(ep, 4), r(s_out), None if X_out is None else r(X_out, 4),
            r(dep), r(x, 2), (r(tg[0]), r(tg[1]), r(tg[2]), r(tg[3], 4)), fint)


def dezz(du, szz, edof, B, tangent):
    """Newton update of eps_zz that accompanies ``du`` (plane stress), fused:
    ``-(sigma_zz + C[zz, ip] . B du) / C[zz, zz]``.

    Args:
        du: ``(b, n_r)`` displacement update, mm; szz: ``(b, n_e, n_qp)`` sigma_zz, MPa.
        edof, B: as the fields of :class:`SolderLayer`.
        tangent: factored 3-D tangent ``(K, g2, coef (b, n_e, n_qp), nb (..., 4))``.
    Returns:
        ``(b, n_e, n_qp)`` eps_zz update.
    """
    lib, shape = _element_call(du, B)
    b, n_r = du.shape
    n_e, n_qp = shape[1:]
    tg = [torch.broadcast_to(t, (*shape, 4) if i == 3 else shape).contiguous()
          for i, t in enumerate(tangent)]
    szc = torch.broadcast_to(szz, shape).contiguous()
    out = torch.empty(shape, dtype=torch.float64, device=du.device)
    dims = (ctypes.c_long * 4)(b, n_e, n_qp, n_r)
    duc, edof, B = du.contiguous(), edof.contiguous(), B.contiguous()
    lib.sp_dezz(dims, ptr(duc), ptr(szc), ptr(edof), ptr(B),
                *(ptr(t) for t in tg), ptr(out))
    return out


def _required() -> ctypes.CDLL:
    """The loaded library for the kernel classes below (RuntimeError where there is none)."""
    lib = library()
    if lib is None:
        raise RuntimeError("the native kernels are not available")
    return lib


class GPArrays(NamedTuple):
    """The K component GPs of :class:`ReducedLoglik` (NumPy float64 arrays).

    Attributes:
        U: ``(n_sim, d')`` training inputs; os: ``(K,)`` outputscales; inv_ls2: ``(K, d')``
        inverse squared lengthscales; c0: ``(K,)`` constant means; w: ``(K, d')`` linear means
        or None; alpha: ``(K, n_sim)``; linv: ``(K, n_sim, n_sim)`` inverse Cholesky factors
        (lower); matern: Matern 5/2 (else Gaussian) kernel.
    """

    U: Any
    os: Any
    inv_ls2: Any
    c0: Any
    w: Any
    alpha: Any
    linv: Any
    matern: bool


class MomentSeries(NamedTuple):
    """The truncation variance's moment series of :class:`ReducedLoglik`
    (``calibration.reduced``'s weight moments): ``Mq (rows, L + 1)``, ``mt (L + 1,)``, the
    centre ``mid`` and half-width ``half`` of the variances (um^2) and the series' relative
    tolerance ``tol``."""

    Mq: Any
    mt: Any
    mid: float
    half: float
    tol: float


class ReducedLoglik:
    """The reduced PCA log density and its gradient in one native call
    (``reduced.c``: :class:`~solderpyro.calibration.reduced.ComponentGPs`, its vector-Jacobian
    product and ``PCAReduction._loglik_projected``, fused).

    Args (NumPy float64 arrays, kept referenced here):
        gps: the component GPs (:class:`GPArrays`).
        series: the truncation variance's moment series (:class:`MomentSeries`).
        d: ``(n,)`` truncation variance, um^2; Qt: ``(rows, n)`` the sums' rows.
    Raises:
        RuntimeError: no native library (check :func:`library` first).
    """

    def __init__(self, gps: GPArrays, series: MomentSeries, d, Qt) -> None:
        import numpy as np

        lib = _required()
        U, os, inv_ls2, c0, w, alpha, linv, matern = gps
        Mq, mt, mid, half, tol = series
        c = lambda a: np.ascontiguousarray(a, dtype=np.float64)  # noqa: E731
        self._keep = [c(a) for a in (U, os, inv_ls2, c0, alpha, linv, Mq, mt, d, Qt)]
        Uc, osc, ils, c0c, al, li, Mqc, mtc, dc, Qtc = self._keep
        wc = None if w is None else c(w)
        if wc is not None:
            self._keep.append(wc)
        K, ns = al.shape
        dp = Uc.shape[1]
        rows, L1 = Mqc.shape
        if L1 > 128:
            raise ValueError(f"ReducedLoglik: at most 127 series terms, got {L1 - 1}")
        self.K, self.dp = K, dp
        self._dims = (ctypes.c_long * 8)(K, ns, dp, rows, dc.shape[0], int(matern),
                                         int(wc is not None), L1 - 1)
        addr = lambda a: None if a is None else a.ctypes.data  # noqa: E731
        low = np.tril_indices(ns)
        self._keep[5] = li = c(li[:, low[0], low[1]])  # (K, ns (ns + 1) / 2): rows packed
        self._ptrs = (ctypes.c_void_p * 11)(*(addr(a) for a in (
            Uc, osc, ils, c0c, wc, al, li, Mqc, mtc, dc, Qtc)))
        self._sc = np.array([mid, half, tol])
        self._work = np.empty(int(lib.sp_reduced_work_size(ctypes.addressof(self._dims))))
        self._u = np.empty(dp)
        self._out = np.empty(2 + dp + 2 * K)
        self._f = lib.sp_reduced_loglik
        self._args = (ctypes.addressof(self._dims), ctypes.addressof(self._ptrs),
                      self._sc.ctypes.data, self._u.ctypes.data)
        self._tail = (self._out.ctypes.data, self._work.ctypes.data)
        self._lock = threading.Lock()

    def __call__(self, u, sigma: float):
        """``u (d',)`` GP inputs, ``sigma`` (um) -> ``(ll, d ll/du (d',), d ll/dsigma, c (K,),
        v (K,))`` (fresh arrays).

        Raises:
            FloatingPointError: ``I + V^1/2 A V^1/2`` not positive definite (non-finite input).
        """
        o, dp, K = self._out, self.dp, self.K
        with self._lock:  # the buffers are this object's: one call at a time
            self._u[:] = u
            if self._f(*self._args, sigma, *self._tail) != 0:
                raise FloatingPointError("reduced likelihood: I + V^1/2 A V^1/2 is not positive "
                                         "definite (non-finite inputs?)")
            return (float(o[0]), o[1:1 + dp].copy(), float(o[1 + dp]),
                    o[2 + dp:2 + dp + K].copy(), o[2 + dp + K:].copy())


class RidgeMapKernel:
    """:class:`~solderpyro.calibration.ridgemap.RidgeMap`'s one-point ``forward`` and ``vjp``
    in C (``ridgemap.c``).

    Args (NumPy float64): mean, sd, span, c0 ``(d,)``; b ``(d, d)`` (row k: ``b_k`` in its
        first k columns); A, S ``(d, d, d)`` (``A_k``, ``S_k`` in the leading ``(k, k)``
        block).
    Raises:
        RuntimeError: no native library; ValueError: d > 64.
    """

    def __init__(self, mean, sd, span, c0, b, A, S) -> None:
        import numpy as np

        lib = _required()
        self.d = d = len(mean)
        if d > 64:
            raise ValueError(f"RidgeMapKernel: at most 64 coordinates, got {d}")
        c = lambda a: np.ascontiguousarray(a, dtype=np.float64)  # noqa: E731
        self._keep = [c(a) for a in (mean, sd, span, c0, b, A, S)]
        mean, sd, span, c0, b, A, S = (a.ctypes.data for a in self._keep)
        self._w, self._q, self._z = np.empty(d), np.empty(d), np.empty(d)
        self._g, self._out = np.empty(d), np.empty(d)
        fargs = (d, mean, sd, span, c0, b, A, self._w.ctypes.data, self._q.ctypes.data,
                 self._z.ctypes.data)
        vargs = (d, sd, span, b, S, self._z.ctypes.data, self._g.ctypes.data,
                 self._out.ctypes.data)
        self._fwd = lambda: lib.sp_ridge_forward(*fargs)  # noqa: E731
        self._vjp = lambda: lib.sp_ridge_vjp(*vargs)  # noqa: E731
        self._lock = threading.Lock()

    def forward(self, w):
        """``w (d,)`` -> ``q (d,)``, ``z (d,)`` (fresh arrays)."""
        with self._lock:  # the buffers are this object's: one call at a time
            self._w[:] = w
            self._fwd()
            return self._q.copy(), self._z.copy()

    def vjp(self, z, g):
        """``(dq/dw)^T g (d,)`` at standardized ``z (d,)`` (a fresh array)."""
        with self._lock:
            self._z[:] = z
            self._g[:] = g
            self._vjp()
            return self._out.copy()


class FlowFlat:
    """The full-field posterior's whole log density and gradient in one native call
    (``flowflat.c``: :meth:`~solderpyro.calibration.flat.FlatModel.logp_and_grad` of
    :func:`~solderpyro.calibration.reduced.pca_flat` in the soft-walled flow-stress
    coordinates, without observation offsets).

    Args:
        dims: ``(p, sigma_positive, i_s0, i_qr, i_xi, i_m)``; par: the scalars and per-input
            arrays ``flowflat.c`` lists (float64); reduced: the :class:`ReducedLoglik` of the
            same surrogate and data.
    Raises:
        RuntimeError: no native library; ValueError: more than 64 parameters.
    """

    def __init__(self, dims, par, reduced: ReducedLoglik) -> None:
        import numpy as np

        lib = _required()
        p = int(dims[0])
        if p > 64:
            raise ValueError(f"FlowFlat: at most 64 parameters, got {p}")
        self.dim = p + 1
        self._red = reduced  # keeps its arrays alive
        self._dims = (ctypes.c_long * 6)(*(int(v) for v in dims))
        self._par = np.ascontiguousarray(par, dtype=np.float64)
        rd = ctypes.addressof(reduced._dims)
        self._work = np.empty(int(lib.sp_flowflat_work_size(rd, p)))
        self._q = np.empty(p + 1)
        self._out = np.empty(p + 2)
        self._f = lib.sp_flowflat
        self._args = (ctypes.addressof(self._dims), self._par.ctypes.data, rd,
                      ctypes.addressof(reduced._ptrs), reduced._sc.ctypes.data,
                      self._q.ctypes.data, self._out.ctypes.data, self._work.ctypes.data)
        self._lock = threading.Lock()

    def __call__(self, q):
        """``q (p + 1,)`` the flat vector -> ``(log density, gradient (p + 1,))``."""
        with self._lock:  # the buffers are this object's: one call at a time
            self._q[:] = q
            self._f(*self._args)
            return float(self._out[0]), self._out[1:].copy()
