"""The output standardization (solderpyro.surrogate.transforms.Standardizer): standardized
training columns have mean 0 and sd 1, inverse(forward(y)) = y, constant columns pass through
unscaled."""

import torch

from solderpyro.surrogate.transforms import Standardizer

F64 = torch.float64


def test_standardized_columns_have_zero_mean_unit_sd_and_round_trip():
    """Columns of very different scales and offsets: after forward the column means are 0
    and the sds 1 (1e-13 in standardized units: rounding of means over 50 rows whose
    offsets reach 2e3 sd); inverse(forward(y)) = y to a few ulp of |y|; leading batch
    dimensions broadcast."""
    g = torch.Generator().manual_seed(0)
    y = torch.randn(50, 3, generator=g, dtype=F64) * torch.tensor([0.05, 20.0, 3e3]) + \
        torch.tensor([12.0, -300.0, 1e4])
    st = Standardizer.fit(y)
    z = st.forward(y)
    assert z.mean(0).abs().max() < 1e-13
    assert (z.std(0) - 1).abs().max() < 1e-13
    back = st.inverse(z)
    assert ((back - y).abs() / y.abs()).max() < 8 * torch.finfo(F64).eps
    zb = torch.randn(4, 7, 3, generator=g, dtype=F64)
    assert (st.forward(st.inverse(zb)) - zb).abs().max() < 1e-11


def test_constant_column_and_single_row_keep_unit_scale():
    """A constant column gets scale 1 (not 0: no division by zero) and standardizes to 0; a
    single training row gives scale 1 in every column and its own mean."""
    y = torch.tensor([[1.0, 5.0], [2.0, 5.0], [4.0, 5.0]], dtype=F64)
    st = Standardizer.fit(y)
    assert st.scale[1] == 1.0 and bool((st.forward(y)[:, 1] == 0).all())
    assert st.scale[0] == y[:, 0].std()
    one = Standardizer.fit(y[:1])
    assert torch.equal(one.scale, torch.ones(2, dtype=F64)) and torch.equal(one.mean, y[0])
    assert torch.equal(one.forward(y[:1]), torch.zeros(1, 2, dtype=F64))
