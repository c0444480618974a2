"""The magnitude ladder of the hidden-effect datasets (solderpyro.diagnose.hidden): shares of
the way from "off" to the far edge of the box, on the box's own unit-cube scale."""

import numpy as np
import pytest

from solderpyro.config.compose import build, compose
from solderpyro.diagnose.hidden import FRACTIONS, _ladder
from solderpyro.effects import effect_set
from solderpyro.fem.loading import EXTENDED_TIMES


def _effect(name):
    setup = build(compose([]))
    return effect_set((name,), EXTENDED_TIMES, setup.effect_bounds).effects[0]


def test_ladder_is_linear_on_a_linear_box():
    """thermal_lag: off 0 s, box [0, 300] s -> f * 300 s."""
    lad = _ladder(_effect("thermal_lag"), seed=1)
    np.testing.assert_allclose(lad[:, 0], 300.0 * np.asarray(FRACTIONS), rtol=1e-12)


def test_ladder_is_geometric_on_a_log_box():
    """copper_plasticity: off 400 MPa (upper edge), log box [15, 400] MPa -> 400 (15/400)^f, so
    the rungs are spread where the copper yields (below ~30 MPa), not where it stays elastic."""
    eff = _effect("copper_plasticity")
    assert eff.params.log_scale == (True,)
    lad = _ladder(eff, seed=1)[:, 0]
    np.testing.assert_allclose(lad, 400.0 * (15.0 / 400.0) ** np.asarray(FRACTIONS), rtol=1e-12)
    assert np.all(np.diff(lad) < 0) and lad[-1] == pytest.approx(15.0)
    assert (lad < 31.0).sum() >= 2  # at least two rungs where the copper can yield


def test_fe_check_flags_an_fe_misfit_at_every_draw():
    """fe_check over draws: the best draw decides. Residuals at the noise level pass; a 0.1 um
    bias on 0.05 um noise at every draw (RMS ~2.2 sd, chi2 ~ 4.9 n) is flagged; one good draw
    among bad ones passes; non-converged draws (NaN) are skipped, all NaN is flagged; with few
    values a chance excess (RMS 1.6 sd on 8 values, chi2 20.5 < the 0.999 quantile 26.1) is
    not flagged."""
    import torch

    from solderpyro.pipeline.fe_check import fe_check

    rng = np.random.default_rng(0)
    y = torch.tensor(rng.normal(size=2000))
    good = y.numpy() + 0.05 * rng.normal(size=2000)
    bad = good + 0.1
    c = fe_check(good[None], y, 0.05)
    assert c["ok"] and 0.9 < c["rms_over_sigma"] < 1.1 and c["n"] == 2000 and c["draws"] == 1
    c = fe_check(np.stack([bad, bad + 0.01]), y, 0.05)
    assert not c["ok"] and 2.1 < c["rms_over_sigma"] < 2.4 and c["draws"] == 2
    assert fe_check(np.stack([bad, good, bad]), y, 0.05)["ok"]
    nan = good.copy()
    nan[3] = np.nan
    assert fe_check(np.stack([nan, good]), y, 0.05)["ok"]
    assert not fe_check(nan[None], y, 0.05)["ok"]
    y8 = torch.zeros(8)
    assert fe_check(np.full((1, 8), 1.6 * 0.05), y8, 0.05)["ok"]
    assert not fe_check(np.full((1, 8), 2.0 * 0.05), y8, 0.05)["ok"]  # chi2 32 > 26.1
