"""Selecting and writing batch members of the solver's records.

A solve iterates, line-searches and sub-steps only the members that need it; these helpers take
the rows of a subset of members from a batched record (tensor, :class:`PointState`,
:class:`Tangent3D`, :class:`~solderpyro.fem.points.BandTangent`,
:class:`~solderpyro.fem.thermo.StepThermo`, or a tuple of them) and write them back, without a
copy where the subset is the whole batch.
"""

from __future__ import annotations

from solderpyro.fem.points import BandTangent
from solderpyro.fem.thermo import StepThermo
from solderpyro.materials.integrate import PointState, Tangent3D


def rows(a, idx):
    """``a[idx]`` (tensor, ``PointState``, ``Tangent3D``, ``BandTangent`` or ``StepThermo``)
    for sorted, unique member indices ``idx``; ``a`` itself (no copy) when they are all of its
    members."""
    if isinstance(a, StepThermo):
        return a.rows(idx)
    if isinstance(a, PointState | Tangent3D | BandTangent):
        n = (a.s.shape[0] if isinstance(a, PointState) else a.K.shape[0]
             if isinstance(a, Tangent3D) else a.band.shape[0])
        return a if len(idx) == n else a.index(idx)
    return a if len(idx) == a.shape[0] else a[idx]


def take(ev, idx):
    """Members ``idx`` of a tuple of batched results."""
    return tuple(None if a is None else rows(a, idx) for a in ev)


def put(ev, sub, idx, inplace=False):
    """Write the members ``idx`` of a batched result tuple from ``sub`` (in place where
    ``inplace`` and the array allows it, see :func:`scatter`)."""
    out = []
    for a, b in zip(ev, sub, strict=True):
        if a is None:
            out.append(None)
        elif isinstance(a, PointState):
            out.append(scatter_state(a, b, idx, inplace))
        elif isinstance(a, Tangent3D):
            out.append(scatter_tangent(a, b, idx, inplace))
        elif isinstance(a, BandTangent):
            sol = (scatter_tangent(a.solder, b.solder, idx, inplace)
                   if isinstance(a.solder, Tangent3D)
                   else scatter(a.solder, b.solder, idx, inplace))
            out.append(BandTangent(sol, scatter(a.band, b.band, idx, inplace)))
        else:
            out.append(scatter(a, b, idx, inplace))
    return tuple(out)


def scatter_tangent(full: Tangent3D, part: Tangent3D, idx, inplace=False) -> Tangent3D:
    """:func:`scatter` field by field of a :class:`Tangent3D`."""
    return Tangent3D(*(scatter(getattr(full, f), getattr(part, f), idx, inplace)
                       for f in ("K", "g2", "coef", "nb")))


def scatter(full, part, idx, inplace=False):
    """``full`` with the rows ``idx`` replaced by ``part``: a copy, or ``full`` itself written
    in place when ``inplace`` and ``full`` is a contiguous array (the caller owns it)."""
    if part.shape[0] == full.shape[0] and len(idx) == full.shape[0]:
        return part
    if inplace and full.is_contiguous() and part.dtype == full.dtype:
        return full.index_copy_(0, idx, part)
    out = full.clone()
    out[idx] = part
    return out


def scatter_state(full: PointState, part: PointState, idx, inplace=False) -> PointState:
    """:func:`scatter` field by field of a :class:`PointState`."""
    X = None if full.X is None else scatter(full.X, part.X, idx, inplace)
    r = None if full.p_rate is None else scatter(full.p_rate, part.p_rate, idx, inplace)
    return PointState(scatter(full.eps_p, part.eps_p, idx, inplace),
                      scatter(full.s, part.s, idx, inplace),
                      scatter(full.eps_zz, part.eps_zz, idx, inplace), X, r)
