"""Stage 4, the FE check: does the FE itself fit where the surrogate posterior lies?"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

#: the FE check warns when even the best of the checked posterior draws misfits by more than
#: this many noise sd (the yardstick of issue 6: a fit at the noise level is within 1.5 sd) ...
FE_CHECK_RMS = 1.5
#: ... and its chi-square exceeds this quantile of chi2(n) (guards small n against chance)
FE_CHECK_QUANTILE = 0.999
#: posterior draws the FE check runs (one batched FE solve)
FE_CHECK_DRAWS = 8


def misfits(chi2: float, n: int) -> bool:
    """The FE check's rule: a chi-square ``chi2`` (residuals over the noise sd) on ``n``
    values misfits when it is not finite, or when its RMS residual exceeds
    :data:`FE_CHECK_RMS` noise sd and it exceeds the :data:`FE_CHECK_QUANTILE` quantile of
    chi2(n)."""
    from scipy.stats import chi2 as chi2_dist

    if not np.isfinite(chi2):
        return True
    return bool(np.sqrt(chi2 / n) > FE_CHECK_RMS and chi2 > chi2_dist.ppf(FE_CHECK_QUANTILE, n))


def fe_check(V: np.ndarray, y_obs: torch.Tensor, sigma: float) -> dict[str, Any]:
    """Does the FE itself fit where the surrogate posterior lies?

    A surrogate posterior can sit where the GP, not the FE, fits the data (a GP error in a
    region of large code variance soaks up the misfit). The FE at a few posterior draws shows
    it: if even the best of them misfits, the posterior is the surrogate's. (The marginal
    medians are no test point: for a weakly identified, curved posterior they can lie off the
    ridge where the model fits.)

    Args:
        V: ``(b, n_obs)`` FE outputs at ``b`` posterior draws, um (NaN rows: not converged);
        y_obs: ``(n_obs,)`` um; sigma: noise sd, um.
    Returns:
        ``{"chi2", "n", "rms_um", "rms_over_sigma", "draws", "ok"}`` of the best-fitting draw;
        ``ok`` is False when its RMS residual exceeds :data:`FE_CHECK_RMS` noise sd and its
        chi-square the :data:`FE_CHECK_QUANTILE` quantile of chi2(n) (or no draw converged).
    """
    y = y_obs.detach().cpu().numpy()
    r = np.atleast_2d(np.asarray(V, float)) - y
    c2 = np.where(np.isfinite(r).all(1), ((r / sigma) ** 2).sum(1), np.inf)
    k = int(np.argmin(c2))
    n = int(y.size)
    rms = float(np.sqrt(c2[k] / n)) * sigma if np.isfinite(c2[k]) else float("nan")
    bad = misfits(float(c2[k]), n)
    return {"chi2": float(c2[k]), "n": n, "rms_um": rms, "rms_over_sigma": rms / sigma,
            "draws": int(r.shape[0]), "ok": not bad}
