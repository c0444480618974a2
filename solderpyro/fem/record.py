"""What happens inside the solder during a solve: its stress, inelastic strain and work.

The time loop keeps only the Gauss-point state (the inelastic strain ``eps_p``, Anand's ``s``,
the out-of-plane strain, a back stress and its lagged rate); the solder's stress is not stored.
It is recovered exactly at the end of every grid step from that state and the displacements:

    sigma = K tr(e) m + 2 G dev(e),   e = eps(u) - eps_p - eps_th m,

with ``K, G`` from the solder's modulus at the step's temperature (per member with effects),
``eps(u)`` the element's strain (B-bar in plane strain, the converged ``eps_zz`` out of plane)
and ``m = (1, 1, 1, 0)``: the stress the return map computed (the same elastic law at the same
state). Mandel vectors ``(xx, yy, zz, sqrt2 xy)``, so ``a . b = a : b``.

:class:`SolderRecorder` accumulates, per member and solder Gauss point:

* the inelastic work density ``W = integral sigma : d eps_p`` (MPa = MJ/m^3 = mJ/mm^3), by
  the trapezoid rule over the grid steps (``dW = (sigma_n + sigma_n+1)/2 . (eps_p,n+1 -
  eps_p,n)``), read at the marks (times on the grid, e.g. the cycles' ends): a cycle's
  ``Delta W`` is the difference of two marks;
* the equivalent inelastic strain ``p = sum sqrt(2/3) |Delta eps_p|`` at the marks;
* the largest von Mises stress and the largest ``|sigma_xy|`` over the solve (MPa), and the
  largest equivalent inelastic strain rate (1/s, a grid step's ``Delta p / Delta t``);
* at chosen Gauss points, the histories of ``sigma`` and ``eps_p`` at every grid step.

Sub-steps and SDIRK stages are inside a grid step and not seen: the trapezoid's error is of
the grid step's order, which the step-refinement study of ``docs/verification.md`` measures.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import torch

from solderpyro.materials.elastic import bulk_shear
from solderpyro.materials.integrate import PointState, full_strain

#: the volumetric Mandel vector (xx, yy, zz, sqrt2 xy)
_M = (1.0, 1.0, 1.0, 0.0)


def von_mises(sig: torch.Tensor) -> torch.Tensor:
    """Von Mises stress ``(...)`` MPa of Mandel stresses ``(..., 4)`` MPa."""
    m = torch.tensor(_M, dtype=sig.dtype, device=sig.device)
    d = sig - sig[..., :3].sum(-1, keepdim=True) / 3.0 * m
    return (1.5 * (d * d).sum(-1)).sqrt()


def shear_xy(sig: torch.Tensor) -> torch.Tensor:
    """In-plane shear stress ``sigma_xy`` ``(...)`` MPa of Mandel stresses ``(..., 4)``."""
    return sig[..., 3] / math.sqrt(2.0)


@dataclass
class SolderFields:
    """What a :class:`SolderRecorder` gathered over one solve (``B`` members, ``n_e`` solder
    elements, ``n_qp`` Gauss points each, ``K`` marks, ``n_p`` history points, ``S`` grid
    steps).

    Attributes:
        marks: ``(K,)`` s, the times the cumulative fields were read at.
        work: ``(B, K, n_e, n_qp)`` inelastic work density from the solve's start, MPa.
        eps_p_eq: ``(B, K, n_e, n_qp)`` equivalent inelastic strain from the start.
        vm_max, tau_max: ``(B, n_e, n_qp)`` the largest von Mises stress and ``|sigma_xy|``
            over the grid steps, MPa.
        rate_max: ``(B, n_e, n_qp)`` 1/s, the largest equivalent inelastic strain rate over
            the grid steps (a step's mean).
        t: ``(S,)`` s, the grid steps' ends; sigma, eps_p: ``(B, S, n_p, 4)`` Mandel stress
            (MPa) and inelastic strain at the history points; p_hist: ``(B, S, n_p)`` their
            equivalent inelastic strain accumulated from the start.
        weight: ``(n_e, n_qp)`` mm^2 per unit depth, each Gauss point's share of the solder's
            area (quadrature weight times the Jacobian); xy: ``(n_e, n_qp, 2)`` mm, their
            positions.
    """

    marks: torch.Tensor
    work: torch.Tensor
    eps_p_eq: torch.Tensor
    vm_max: torch.Tensor
    tau_max: torch.Tensor
    rate_max: torch.Tensor
    t: torch.Tensor
    sigma: torch.Tensor
    eps_p: torch.Tensor
    p_hist: torch.Tensor
    weight: torch.Tensor
    xy: torch.Tensor


@dataclass
class SolderRecorder:
    """Gathers :class:`SolderFields` during a :meth:`SpecimenSolver.solve
    <solderpyro.fem.solver.SpecimenSolver.solve>` (its ``recorder`` argument).

    Args:
        marks: times (s) at which to read the cumulative work and inelastic strain; each must
            be a knot of the solve's time grid (the cycle's breakpoints and output times are).
        points: ``(n_p, 2)`` flat indices ``(element, Gauss point)`` into the solder's
            ``(n_e, n_qp)`` points whose histories to keep (e.g. from :func:`nearest_points`).
    """

    marks: tuple[float, ...] = ()
    points: tuple[tuple[int, int], ...] = ()
    _state: dict[str, Any] = field(default_factory=dict, repr=False)

    def start(self, solver: Any, b: int, t_start: float = 0.0) -> None:
        """Reset for a solve of ``b`` members by ``solver`` whose time grid starts at
        ``t_start`` s."""
        n_s, tkw = solver.n_s, solver.tkw
        shape = (b, *solver.wdet[:n_s].shape)
        self._state = {
            "solver": solver, "sig": torch.zeros(*shape, 4, **tkw),
            "eps_p": torch.zeros(*shape, 4, **tkw), "W": torch.zeros(shape, **tkw),
            "p": torch.zeros(shape, **tkw), "vm": torch.zeros(shape, **tkw),
            "tau": torch.zeros(shape, **tkw), "rate": torch.zeros(shape, **tkw),
            "t_prev": float(t_start), "at": {}, "t": [], "h_sig": [], "h_ep": [], "h_p": [],
            "e_i": torch.tensor([p[0] for p in self.points], dtype=torch.long),
            "q_i": torch.tensor([p[1] for p in self.points], dtype=torch.long)}

    def stress(self, u: torch.Tensor, st: PointState, th: Any) -> torch.Tensor:
        """The solder's Mandel stress ``(b, n_e, n_qp, 4)`` MPa at displacements ``u``
        ``(b, n_r)`` mm and state ``st``, with the step's inputs ``th``
        (:class:`~solderpyro.fem.thermo.StepThermo`)."""
        slv = self._state["solver"]
        n = slv.n_s
        eps = full_strain(slv.points.strain(u)[:, :n], st.eps_zz[:, :n])
        m = torch.tensor(_M, **slv.tkw)
        E = torch.as_tensor(th.E, **slv.tkw)
        K, G = bulk_shear(E, slv.solder.nu)
        eth = torch.as_tensor(th.eps_th, **slv.tkw)
        e = eps - st.eps_p[:, :n] - eth[..., None] * m
        tr = e[..., :3].sum(-1, keepdim=True)
        return K[..., None] * tr * m + 2.0 * G[..., None] * (e - tr / 3.0 * m)

    def step(self, t1: float, u: torch.Tensor, st: PointState, th: Any) -> None:
        """Take the end of a grid step at ``t1`` s (every member: ``u`` ``(B, n_r)`` mm,
        state ``st``, inputs ``th``)."""
        s = self._state
        n = s["solver"].n_s
        sig = self.stress(u, st, th)
        ep = st.eps_p[:, :n]
        dep = ep - s["eps_p"]
        s["W"] = s["W"] + 0.5 * ((s["sig"] + sig) * dep).sum(-1)
        dp = math.sqrt(2.0 / 3.0) * dep.norm(dim=-1)
        s["p"] = s["p"] + dp
        if t1 > s["t_prev"]:
            s["rate"] = torch.maximum(s["rate"], dp / (t1 - s["t_prev"]))
        s["t_prev"] = t1
        s["vm"] = torch.maximum(s["vm"], von_mises(sig))
        s["tau"] = torch.maximum(s["tau"], shear_xy(sig).abs())
        s["sig"], s["eps_p"] = sig, ep.clone()
        for tm in self.marks:
            if abs(t1 - tm) < 1e-9:
                s["at"][tm] = (s["W"].clone(), s["p"].clone())
        s["t"].append(t1)
        if self.points:
            s["h_sig"].append(sig[:, s["e_i"], s["q_i"]])
            s["h_ep"].append(ep[:, s["e_i"], s["q_i"]])
            s["h_p"].append(s["p"][:, s["e_i"], s["q_i"]])

    def finish(self, alive: torch.Tensor) -> SolderFields:
        """The fields of the solve; NaN for members that failed (``alive`` ``(B,)`` False).

        Raises:
            ValueError: naming a mark the time grid never reached.
        """
        s = self._state
        slv = s["solver"]
        missing = [tm for tm in self.marks if tm not in s["at"]]
        if missing:
            raise ValueError(f"SolderRecorder.marks: {missing} s are not on the solve's time "
                             "grid (use the cycle's breakpoints or output times)")
        b = s["W"].shape[0]
        n_p = len(self.points)

        def dead(x: torch.Tensor) -> torch.Tensor:
            keep = alive.reshape(b, *([1] * (x.dim() - 1)))
            return torch.where(keep, x, torch.full_like(x, float("nan")))

        def stack(xs: list[torch.Tensor], shape: tuple[int, ...]) -> torch.Tensor:
            return torch.stack(xs, 1) if xs else torch.zeros(shape, **slv.tkw)

        W = stack([s["at"][tm][0] for tm in self.marks], (b, 0, *s["W"].shape[1:]))
        P = stack([s["at"][tm][1] for tm in self.marks], (b, 0, *s["W"].shape[1:]))
        return SolderFields(
            torch.tensor(self.marks, **slv.tkw), dead(W), dead(P), dead(s["vm"]),
            dead(s["tau"]), dead(s["rate"]), torch.tensor(s["t"], **slv.tkw),
            dead(stack(s["h_sig"], (b, 0, n_p, 4))), dead(stack(s["h_ep"], (b, 0, n_p, 4))),
            dead(stack(s["h_p"], (b, 0, n_p))), slv.wdet[:slv.n_s].clone(), gauss_points(slv))


def gauss_points(solver: Any) -> torch.Tensor:
    """Positions ``(n_e, n_qp, 2)`` mm of the solder's Gauss points of ``solver`` (bilinear
    quadrilaterals, the element's own map)."""
    from solderpyro.fem.elements import XI

    mesh = solver.mesh
    xy = torch.as_tensor(mesh.nodes[mesh.elems[solver.el_solder]], **solver.tkw)  # (e, 4, 2)
    xi = torch.as_tensor(XI, **solver.tkw)
    N = 0.25 * torch.stack([(1 - xi[:, 0]) * (1 - xi[:, 1]), (1 + xi[:, 0]) * (1 - xi[:, 1]),
                            (1 + xi[:, 0]) * (1 + xi[:, 1]), (1 - xi[:, 0]) * (1 + xi[:, 1])],
                           1)  # (n_qp, 4)
    return torch.einsum("qk,ekd->eqd", N, xy)


def nearest_points(solver: Any, xy: Any) -> tuple[tuple[int, int], ...]:
    """``(element, Gauss point)`` of the solder Gauss point nearest each of ``xy``
    ``(n_p, 2)`` mm (for :attr:`SolderRecorder.points`)."""
    g = gauss_points(solver).reshape(-1, 2)
    n_qp = solver.wdet.shape[1]
    q = torch.as_tensor(xy, dtype=g.dtype).reshape(-1, 2)
    k = torch.cdist(q, g).argmin(1).tolist()
    return tuple((int(i) // n_qp, int(i) % n_qp) for i in k)
