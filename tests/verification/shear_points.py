"""Pure shear at a material point, shared by the kinematic-hardening closed-form tests."""

import math

import torch

from solderpyro.materials.anand import saturation
from solderpyro.params import anand_tensor


def shear(gamma: torch.Tensor) -> torch.Tensor:
    """In-plane Mandel strain ``(n, 3)`` of pure shear with engineering strains ``gamma (n,)``."""
    z = torch.zeros_like(gamma)
    return torch.stack([z, z, gamma / math.sqrt(2.0)], -1)


def constant_rate_cases(cases: list[tuple]) -> tuple[torch.Tensor, ...]:
    """The members of ``cases``, rows ``(constants, T in C, eq. inelastic rate 1/s, *extra,
    s0 / s*)``: ``(p (n, 9), T (n,) K, rate (n,), *extra as (n,) tensors, eps_end (n,))``,
    with s0 the given share of the saturation s* at that rate and temperature and eps_end
    about half way to saturation."""
    ps, T, rate, eps_end = [], [], [], []
    extra: list[list[float]] = [[] for _ in cases[0][3:-1]]
    for base, TC, r, *ex, f in cases:
        _, s_star = saturation(torch.tensor(r), torch.tensor(TC + 273.15),
                               anand_tensor(base=base))
        p = anand_tensor({"s0": f * s_star.item()}, base=base)
        ps.append(p)
        T.append(TC + 273.15)
        rate.append(r)
        for col, v in zip(extra, ex, strict=True):
            col.append(v)
        eps_end.append(0.6 * s_star.item() / p[5].item())
    return (torch.stack(ps), torch.tensor(T), torch.tensor(rate),
            *(torch.tensor(c) for c in extra), torch.tensor(eps_end))
