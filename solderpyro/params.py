"""One parameter description for every layer: names, units, bounds, log-scale, unit-cube maps.

Anand constants use the names of the Anand law in docs/configuration.md ("The reference case"):
``s0, QR, A, xi, m, h0, s_hat, n, a`` (QR = Q/R in kelvin, not Q in J/mol). Units inside the
library: MPa, K, 1/s.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
import torch

ANAND_NAMES: tuple[str, ...] = ("s0", "QR", "A", "xi", "m", "h0", "s_hat", "n", "a")
ANAND_UNITS: dict[str, str] = {
    "s0": "MPa", "QR": "K", "A": "1/s", "xi": "-", "m": "-",
    "h0": "MPa", "s_hat": "MPa", "n": "-", "a": "-",
}
#: Liu et al. (2008) Sn37Pb, seed Table IV: the baseline constants of the reference case
#: (docs/configuration.md, "The reference case").
LIU2008: dict[str, float] = {
    "s0": 12.41, "QR": 9400.0, "A": 4.0e6, "xi": 1.5, "m": 0.303,
    "h0": 1379.0, "s_hat": 13.79, "n": 0.07, "a": 1.3,
}
#: Wang et al. (2001) 60Sn40Pb, the constants of the closed-form saturation checks
#: (tests/verification/test_anand_closed_form.py, docs/verification.md).
WANG2001: dict[str, float] = {
    "s0": 56.33, "QR": 10830.0, "A": 1.49e7, "xi": 11.0, "m": 0.303,
    "h0": 2640.75, "s_hat": 80.42, "n": 0.0231, "a": 1.34,
}
#: Physically admissible open/closed ranges used to validate user input (lo, hi).
PHYSICAL_RANGE: dict[str, tuple[float, float]] = {
    "s0": (1e-6, 1e4), "QR": (1.0, 1e6), "A": (1e-30, 1e30), "xi": (1e-6, 1e3),
    "m": (0.01, 1.0), "h0": (0.0, 1e7), "s_hat": (1e-6, 1e5), "n": (0.0, 1.0),
    "a": (0.1, 10.0),
}
#: The seed's calibrated box (seed §4; docs/configuration.md, "The reference case").
SEED_BOX: dict[str, tuple[float, float]] = {
    "s0": (5.0, 25.0), "QR": (7000.0, 13000.0), "xi": (1.0, 5.0), "m": (0.05, 0.5),
}


def check_anand_values(values: Mapping[str, float]) -> None:
    """Raise ``ValueError`` naming the first unknown name or out-of-range value.

    Args:
        values: mapping name -> value (units of ``ANAND_UNITS``).
    """
    for name, val in values.items():
        if name not in PHYSICAL_RANGE:
            raise ValueError(
                f"unknown Anand parameter {name!r}; valid names: {', '.join(ANAND_NAMES)}"
            )
        lo, hi = PHYSICAL_RANGE[name]
        v = float(val)
        if not (lo <= v <= hi) or v != v:
            raise ValueError(
                f"Anand parameter {name}={val} is outside its physical range [{lo:g}, {hi:g}] "
                f"{ANAND_UNITS[name]}"
            )


@dataclass(frozen=True)
class Box:
    """A named box of inputs with an explicit, invertible map to the unit cube.

    The one parameter description that feeds the FE (physical values), the GP input transform
    (unit cube), the Pyro priors (uniform on the box) and the BoTorch bounds.

    Attributes:
        names: input names; ``dim = len(names)``.
        lower, upper: bounds in physical units, one per name (``lower < upper``).
        log_scale: per name, whether the unit-cube map is logarithmic (needs ``lower > 0``).
        units: optional unit strings, one per name (for tables and plots).
    """

    names: tuple[str, ...]
    lower: tuple[float, ...]
    upper: tuple[float, ...]
    log_scale: tuple[bool, ...] = ()
    units: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        n = len(self.names)
        object.__setattr__(self, "names", tuple(self.names))
        object.__setattr__(self, "lower", tuple(float(v) for v in self.lower))
        object.__setattr__(self, "upper", tuple(float(v) for v in self.upper))
        object.__setattr__(self, "log_scale", tuple(bool(v) for v in self.log_scale)
                           or (False,) * n)
        object.__setattr__(self, "units", tuple(self.units) or ("",) * n)
        cls = type(self).__name__
        for attr in ("lower", "upper", "log_scale", "units"):
            if len(getattr(self, attr)) != n:
                raise ValueError(f"{cls}.{attr} has {len(getattr(self, attr))} "
                                 f"entries, names has {n}")
        if len(set(self.names)) != n:
            raise ValueError(f"{cls}.names has duplicates: {self.names}")
        for nm, lo, hi, lg in zip(self.names, self.lower, self.upper, self.log_scale,
                                  strict=True):
            if not (lo < hi):
                raise ValueError(f"bounds of {nm}: lower {lo} must be < upper {hi}")
            if lg and lo <= 0:
                raise ValueError(f"bounds of {nm}: log scale needs lower > 0, got {lo}")

    @property
    def dim(self) -> int:
        return len(self.names)

    def row(self, point: Mapping[str, float] | None) -> np.ndarray | None:
        """``(dim,)`` the values of ``point`` (name -> value, physical units; other names
        ignored) in the box's order, or None where it lacks one of the box's names."""
        if not point or not all(nm in point for nm in self.names):
            return None
        return np.array([float(point[nm]) for nm in self.names])

    @property
    def n_theta(self) -> int:
        return len(self.names)

    def bounds(self, **tkw) -> torch.Tensor:
        """Box as a ``(2, dim)`` tensor (BoTorch's convention), physical units."""
        return torch.tensor([self.lower, self.upper], **tkw)

    def to_unit(self, theta: torch.Tensor) -> torch.Tensor:
        """Map ``(..., dim)`` physical values to the unit cube (log where flagged)."""
        lo, hi = self._lohi(theta)
        return (self.to_working(theta) - lo) / (hi - lo)

    def from_unit(self, u: torch.Tensor) -> torch.Tensor:
        """Inverse of :meth:`to_unit`: ``(..., dim)`` in [0, 1] -> physical units."""
        lo, hi = self._lohi(u)
        z = lo + u * (hi - lo)
        logm = torch.tensor(self.log_scale, device=u.device)
        # inner where: exp never sees a large linear-scale value (inf there poisons gradients)
        return torch.where(logm, torch.exp(torch.where(logm, z, torch.zeros_like(z))), z)

    def to_working(self, x: torch.Tensor) -> torch.Tensor:
        """``(..., dim)`` physical values on the box's working scale: the log of the columns
        flagged log-scale (values <= 0 clamped to 1e-300 first), the others unchanged. The unit
        cube is this scale's affine image."""
        logm = torch.tensor(self.log_scale, device=x.device)
        safe = torch.where(logm, x, torch.ones_like(x)).clamp_min(1e-300)
        return torch.where(logm, torch.log(safe), x)

    def _lohi(self, like: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        b = torch.tensor([self.lower, self.upper], dtype=like.dtype, device=like.device)
        b = self.to_working(b)
        return b[0], b[1]

    @classmethod
    def around(cls, names: Sequence[str], values: torch.Tensor) -> Box:
        """The tightest box around ``values`` ``(n, dim)`` (a constant column gets +-0.5)."""
        if values.ndim != 2 or values.shape[1] != len(names):
            raise ValueError(f"values must have shape (n, {len(names)}), got "
                             f"{tuple(values.shape)}")
        lo, hi = values.min(0).values.tolist(), values.max(0).values.tolist()
        lo2 = [a - 0.5 if a == b else a for a, b in zip(lo, hi, strict=True)]
        hi2 = [b + 0.5 if a == b else b for a, b in zip(lo, hi, strict=True)]
        return cls(tuple(names), tuple(lo2), tuple(hi2))


@dataclass(frozen=True)
class ParameterSpace(Box):
    """Calibration parameters: which Anand constants vary, their box, scaling and defaults.

    Attributes:
        names: the varied parameters, e.g. ``("s0", "QR", "xi", "m")``; ``n_theta = len(names)``.
        lower, upper: box bounds in physical units, one per name.
        log_scale: per name, whether the unit-cube map is logarithmic.
        units: filled from ``ANAND_UNITS`` when omitted.
        defaults: values of all nine Anand constants used for those not in ``names``.
    """

    defaults: Mapping[str, float] = field(default_factory=lambda: dict(LIU2008))

    def __post_init__(self) -> None:
        for nm in self.names:
            if nm not in ANAND_NAMES:
                raise ValueError(f"unknown parameter {nm!r}; valid: {', '.join(ANAND_NAMES)}")
        if not self.units:
            object.__setattr__(self, "units", tuple(ANAND_UNITS[n] for n in self.names))
        super().__post_init__()
        check_anand_values({k: v for k, v in self.defaults.items()})

    @classmethod
    def seed(cls) -> ParameterSpace:
        """The seed's four calibrated constants on their box (:data:`SEED_BOX`)."""
        names = tuple(SEED_BOX)
        return cls(names, tuple(SEED_BOX[k][0] for k in names),
                   tuple(SEED_BOX[k][1] for k in names))

    def full(self, theta: torch.Tensor) -> torch.Tensor:
        """Insert ``theta`` into the defaults: ``(..., n_theta)`` -> ``(..., 9)`` (ANAND_NAMES).

        Differentiable with respect to ``theta``.
        """
        if theta.shape[-1] != self.n_theta:
            raise ValueError(f"theta has {theta.shape[-1]} columns, expected {self.n_theta} "
                             f"({', '.join(self.names)})")
        cols = []
        for nm in ANAND_NAMES:
            if nm in self.names:
                cols.append(theta[..., self.names.index(nm)])
            else:
                cols.append(torch.full(theta.shape[:-1], float(self.defaults[nm]),
                                       dtype=theta.dtype, device=theta.device))
        return torch.stack(cols, dim=-1)


def anand_tensor(values: Mapping[str, float] | None = None, base: Mapping[str, float] = LIU2008,
                 **tkw) -> torch.Tensor:
    """A ``(9,)`` tensor of Anand constants from ``base`` updated by ``values`` (validated)."""
    merged = dict(base)
    if values:
        check_anand_values(values)
        merged.update(values)
    return torch.tensor([float(merged[k]) for k in ANAND_NAMES], **tkw)


def parse_theta(text: str) -> dict[str, float]:
    """Parse ``"s0=12.9,QR=10586"`` into a validated dict; errors name the offending item."""
    out: dict[str, float] = {}
    for item in filter(None, (t.strip() for t in text.split(","))):
        if "=" not in item:
            raise ValueError(f"--theta item {item!r} is not name=value")
        k, v = (p.strip() for p in item.split("=", 1))
        try:
            out[k] = float(v)
        except ValueError:
            raise ValueError(f"--theta value of {k!r} is not a number: {v!r}") from None
    check_anand_values(out)
    return out
