"""Physics-informed GP inputs for Anand constants: flow stresses at a reference state.

The FE outputs of the specimen change sharply with Q/R: the creep rate factor exp(-Q/RT) spans
seven decades over the seed box, and where it crosses the rate of the thermal cycle the solder
switches from "relaxes fully" to "stays elastic". A stationary GP on the raw box sees that switch
as a ridge whose position moves with s0, xi and m. What the response depends on smoothly is how
hard the solder is at the rates and temperatures of the cycle. :class:`FlowStressInputs` feeds
the GP exactly that: with ``z = ln(rate_ref / A) + Q/R / T_ref``,

- ``log sigma_0 = log( s0 / xi * asinh(exp(m z)) )``: the flow stress at the initial
  deformation resistance s0;
- ``log sigma_sat = log( s_hat exp(n z) / xi * asinh(exp(m z)) )``: the steady-state flow
  stress (deformation resistance at saturation, s* = s_hat (rate/A exp(Q/RT))^n, the Anand
  law of docs/configuration.md),

replacing the columns s0 and Q/R; every other input passes through on its unit-cube scale. For
fixed xi, m (and A, s_hat, n) the map (s0, Q/R) -> (log sigma_0, log sigma_sat) is a bijection
(sigma_sat is increasing in Q/R, then sigma_0 is increasing in s0), so no information is lost.

Measured on the reference case (docs/calibration.md, held-out FE runs): with 50 LHS runs the
8-output PCA surrogate's RMSE falls from 0.48 um on the raw box to 0.10 um at
T_ref = 125 degC, rate_ref = 1e-5 1/s (the hold at the cycle's top temperature).
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np
import torch

from solderpyro.params import Box

#: Anand constants the flow stresses are built from (the four replaced/used + the fixed three).
NEEDED = ("s0", "QR", "xi", "m")
FIXABLE = ("A", "s_hat", "n")
#: Values of the config key ``surrogate.inputs``.
INPUTS = ("raw", "flow_stress")


def check_reference(T_ref_C: float, rate_ref: float) -> None:
    """Validate the reference state of :class:`FlowStressInputs` (degC, 1/s); the error names
    the config key (``surrogate.inputs_T_C`` / ``surrogate.inputs_rate``)."""
    if not math.isfinite(T_ref_C) or T_ref_C <= -273.15:
        raise ValueError(f"surrogate.inputs_T_C must be above -273.15 degC, got {T_ref_C}")
    if not math.isfinite(rate_ref) or rate_ref <= 0:
        raise ValueError(f"surrogate.inputs_rate must be a positive rate in 1/s, got "
                         f"{rate_ref}")


def input_map(inputs: str, box: Box, fixed: Mapping[str, float], T_ref_C: float = 125.0,
              rate_ref: float = 1e-5) -> FlowStressInputs | None:
    """The GP input map named by the config key ``surrogate.inputs``.

    Args:
        inputs: ``"raw"`` (None: the GP sees the box's unit cube) or ``"flow_stress"``.
        box, fixed, T_ref_C, rate_ref: as :class:`FlowStressInputs`.
    Raises:
        ValueError naming ``surrogate.inputs`` for any other name.
    """
    if inputs not in INPUTS:
        raise ValueError(f"surrogate.inputs must be one of {INPUTS}, got {inputs!r}")
    return FlowStressInputs(box, fixed, T_ref_C, rate_ref) if inputs == "flow_stress" else None


def log_asinh_exp(w: torch.Tensor) -> torch.Tensor:
    """``log(asinh(exp(w)))`` without overflow or underflow, for any real ``w`` (any shape).

    Large ``w``: ``asinh(e^w) = w + log(1 + sqrt(1 + e^{-2w}))``; very negative ``w``:
    ``asinh(e^w) ~ e^w`` so the log is ``w``. Both branches are finite everywhere (safe
    gradients through ``torch.where``).
    """
    wp = w.clamp(min=0.0)
    wn = w.clamp(max=0.0)
    pos = torch.log(wp + torch.log1p(torch.sqrt(1.0 + torch.exp(-2.0 * wp))))
    neg = torch.where(wn < -30.0, wn, torch.log(torch.asinh(torch.exp(wn.clamp(min=-30.0)))))
    return torch.where(w >= 0, pos, neg)


class FlowStressInputs:
    """Map physical inputs ``(..., d)`` to GP inputs ``(..., d)`` (see the module docstring).

    Args:
        box: the surrogate's inputs; must contain s0, QR, xi and m (others pass through).
        fixed: values of A (1/s), s_hat (MPa) and n (-) for those not in ``box``.
        T_ref_C: reference temperature, degC (default 125: the cycle's hold temperature).
        rate_ref: reference inelastic strain rate, 1/s (> 0).

    Raises:
        ValueError: naming the missing parameter or the bad reference value.
    """

    def __init__(self, box: Box, fixed: Mapping[str, float], T_ref_C: float = 125.0,
                 rate_ref: float = 1e-5) -> None:
        missing = [n for n in NEEDED if n not in box.names]
        if missing:
            raise ValueError(f"surrogate.inputs=flow_stress needs {', '.join(NEEDED)} among the "
                             f"calibrated parameters; missing {', '.join(missing)} (use "
                             f"surrogate.inputs=raw)")
        check_reference(T_ref_C, rate_ref)
        for k in FIXABLE:
            if k not in box.names and k not in fixed:
                raise ValueError(f"surrogate.inputs=flow_stress: no value for the fixed "
                                 f"Anand constant {k!r}")
        self.box, self.T_ref_K, self.rate_ref = box, T_ref_C + 273.15, rate_ref
        self.fixed = {k: float(fixed[k]) for k in FIXABLE if k not in box.names}
        self.idx = {n: box.names.index(n) for n in (*NEEDED, *FIXABLE) if n in box.names}

    def param(self, x: torch.Tensor, name: str) -> torch.Tensor | float:
        """Anand constant ``name`` of physical inputs ``x (..., d)``: its column ``(...)``
        when it is an input of the box, else its fixed value (a float); its own units."""
        return x[..., self.idx[name]] if name in self.idx else self.fixed[name]

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        """``(..., d)`` physical inputs -> ``(..., d)`` GP inputs (differentiable in ``x``)."""
        s0, qr, xi, m = (x[..., self.idx[n]] for n in NEEDED)
        a, s_hat, n = (self.param(x, k) for k in FIXABLE)
        log_a = torch.log(a) if isinstance(a, torch.Tensor) else math.log(a)
        log_sh = torch.log(s_hat) if isinstance(s_hat, torch.Tensor) else math.log(s_hat)
        z = math.log(self.rate_ref) - log_a + qr / self.T_ref_K
        common = log_asinh_exp(m * z) - torch.log(xi)
        cols = list(self.box.to_unit(x).unbind(-1))
        cols[self.idx["s0"]] = torch.log(s0) + common
        cols[self.idx["QR"]] = log_sh + n * z + common
        return torch.stack(cols, -1)

    def value_and_jacobian(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The map and its Jacobian at one point, in NumPy (what the reduced likelihood's
        analytic gradient chains through; checked against autograd in the tests).

        Args:
            x: ``(d,)`` physical inputs.
        Returns:
            ``f (d,)`` (as :meth:`__call__`) and ``df/dx (d, d)``.
        """
        d = x.shape[0]
        ix = self.idx
        if not hasattr(self, "_np_box"):
            lh = self.box.to_working(torch.tensor([self.box.lower, self.box.upper],
                                            dtype=torch.float64)).numpy()
            self._np_box = (lh[0], lh[1], np.asarray(self.box.log_scale, dtype=bool))
        lo, hi, logm = self._np_box
        zx = np.where(logm, np.log(np.where(logm, x, 1.0)), x)
        f = (zx - lo) / (hi - lo)
        jac = np.diag(np.where(logm, 1.0 / x, 1.0) / (hi - lo))

        def val(name: str) -> float:
            return float(x[ix[name]]) if name in ix else self.fixed[name]

        s0, qr, xi, m = (float(x[ix[n]]) for n in NEEDED)
        a, s_hat, n = val("A"), val("s_hat"), val("n")
        z = math.log(self.rate_ref) - math.log(a) + qr / self.T_ref_K
        w = m * z
        ash = math.asinh(math.exp(min(w, 700.0))) if w > -30.0 else math.exp(w)
        common = math.log(ash) - math.log(xi)
        # h(w) = log asinh(e^w): h'(w) = e^w / (asinh(e^w) sqrt(1 + e^2w)), -> 1 as w -> -inf
        if w >= 0.0:
            hp = 1.0 / (ash * math.sqrt(1.0 + math.exp(-2.0 * w)))
        else:
            hp = (1.0 if w < -30.0 else math.exp(w) / ash) / math.sqrt(1.0 + math.exp(2 * w))
        dcommon = np.zeros(d)  # d common / dx
        dz = np.zeros(d)  # dz / dx
        dz[ix["QR"]] = 1.0 / self.T_ref_K
        if "A" in ix:
            dz[ix["A"]] = -1.0 / a
        dcommon += hp * m * dz
        dcommon[ix["m"]] += hp * z
        dcommon[ix["xi"]] += -1.0 / xi
        i_s0, i_qr = ix["s0"], ix["QR"]
        f[i_s0] = math.log(s0) + common
        jac[i_s0] = dcommon
        jac[i_s0, i_s0] += 1.0 / s0
        f[i_qr] = math.log(s_hat) + n * z + common
        jac[i_qr] = dcommon + n * dz
        if "s_hat" in ix:
            jac[i_qr, ix["s_hat"]] += 1.0 / s_hat
        if "n" in ix:
            jac[i_qr, ix["n"]] += z
        return f, jac

    def describe(self) -> str:
        """One line for logs and reports."""
        return (f"GP inputs: log flow stresses at s0 and at saturation, at "
                f"{self.T_ref_K - 273.15:g} degC and {self.rate_ref:g} 1/s, replacing s0 and QR")
