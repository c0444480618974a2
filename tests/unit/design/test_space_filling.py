"""Latin hypercube designs (solderpyro.design.space_filling.lhs): one point per stratum in
every coordinate of the unit cube (in log for log-scale inputs), inside the box, reproducible
by seed."""

import numpy as np
import pytest
import torch

from solderpyro.design.space_filling import lhs
from solderpyro.params import Box, ParameterSpace


@pytest.mark.parametrize("n", [1, 7, 40])
def test_each_stratum_of_each_coordinate_holds_exactly_one_point(n):
    """Seed box (s0, QR, xi, m; MPa, K, -, -) and a box with a log-scale coordinate: in the
    unit cube, floor(n u) over the n points is a permutation of 0..n-1 in every column; the
    points lie in [lower, upper] (physical) column by column."""
    for box in (ParameterSpace.seed(),
                Box(("A", "m"), (1e3, 0.05), (1e8, 0.5), log_scale=(True, False))):
        x = lhs(box, n, seed=3)
        assert x.shape == (n, box.dim) and x.dtype == torch.float64
        lo, hi = torch.tensor(box.lower), torch.tensor(box.upper)
        assert bool(((x >= lo) & (x <= hi)).all())
        u = box.to_unit(x).numpy()
        # rounding of the log/exp map moves u by ~1e-15; strata edges are 1/n apart
        k = np.floor(n * np.clip(u, 0, 1 - 1e-12) + 1e-9).astype(int)
        for j in range(box.dim):
            assert sorted(k[:, j]) == list(range(n)), (box.names[j], k[:, j])


def test_log_scale_spreads_evenly_in_the_logarithm():
    """A over [1e3, 1e8] log scale with 5 points: one point in each decade-wide stratum
    [10^(3+k), 10^(4+k)), k = 0..4."""
    box = Box(("A",), (1e3,), (1e8,), log_scale=(True,))
    x = lhs(box, 5, seed=0)[:, 0].numpy()
    assert sorted(np.floor(np.log10(x) + 1e-12).astype(int)) == [3, 4, 5, 6, 7]


def test_seeded_designs_repeat_and_differ_between_seeds():
    box = ParameterSpace.seed()
    assert torch.equal(lhs(box, 9, seed=4), lhs(box, 9, seed=4))
    assert not torch.equal(lhs(box, 9, seed=4), lhs(box, 9, seed=5))
    assert lhs(box, 3, seed=1, dtype=torch.float32).dtype == torch.float32


def test_bad_point_count():
    with pytest.raises(ValueError, match="lhs needs n >= 1 points, got 0"):
        lhs(ParameterSpace.seed(), 0)
