"""The magnitude ladder of the hidden-effect datasets (solderpyro.diagnose.hidden): shares of
the way from "off" to the far edge of the box, on the box's own unit-cube scale."""

import numpy as np
import pytest

from solderpyro.configure import build, compose
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


def test_fe_check_flags_an_fe_misfit_beyond_one_and_a_half_noise_sd():
    """fe_check: residuals at the noise level pass; a 0.1 um bias on 0.05 um noise (RMS
    ~2.2 sd) is flagged; a non-converged FE (NaN) is flagged."""
    import torch

    from solderpyro.workflow import fe_check

    rng = np.random.default_rng(0)
    y = torch.tensor(rng.normal(size=2000))
    noise = 0.05 * rng.normal(size=2000)
    good = fe_check(y.numpy() + noise, y, 0.05)
    assert good["ok"] and 0.9 < good["rms_over_sigma"] < 1.1 and good["n"] == 2000
    bad = fe_check(y.numpy() + noise + 0.1, y, 0.05)
    assert not bad["ok"] and 2.1 < bad["rms_over_sigma"] < 2.4
    v = y.numpy().copy()
    v[3] = np.nan
    assert not fe_check(v, y, 0.05)["ok"]
