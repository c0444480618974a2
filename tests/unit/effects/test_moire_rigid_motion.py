"""moire_rigid_motion's hook (solderpyro.effects.moire_rigid_motion): V untouched at zero
offsets and rotations, else V + c_k + 1e-3 w_k (x - x_O) image by image (urad * mm = nm)."""

import pytest
import torch

from solderpyro.effects import EFFECTS

F64 = torch.float64
EFF = EFFECTS["moire_rigid_motion"].bind((600.0, 2700.0, 4800.0))
X = torch.tensor([15.0, 15.0, -3.0, 0.0], dtype=F64)  # A, B, two grid points; mm


def _V():
    return torch.randn(2, 3, 4, generator=torch.Generator().manual_seed(0), dtype=F64)


def test_off_is_the_baseline_exactly():
    assert EFF.n_images == 3 and EFF.off == (0.0,) * 6
    V = _V()
    assert torch.equal(EFF.observe(V, X, 0.0, torch.zeros(2, 6, dtype=F64)), V)


def test_adds_the_rigid_offset_and_rotation_of_each_image():
    """Member 1: c = (0.3, -0.2, 0) um, w = (0, 20, -50) urad; at x = 15 mm image 2 moves by
    -0.2 + 0.3 = 0.1 um, at x = -3 mm by -0.2 - 0.06; O (x = 0) only by c. Points A and B
    (both at x = 15) move alike: c_k + 0.015 w_k (rounding 1e-15)."""
    V = _V()
    q = torch.tensor([[0.0] * 6, [0.3, -0.2, 0.0, 0.0, 20.0, -50.0]], dtype=F64)
    d = EFF.observe(V, X, 0.0, q) - V
    assert torch.equal(d[0], torch.zeros_like(d[0]))
    want = torch.tensor([[0.3, 0.3, 0.3, 0.3],
                         [0.1, 0.1, -0.26, -0.2],
                         [-0.75, -0.75, 0.15, 0.0]], dtype=F64)
    assert (d[1] - want).abs().max() < 1e-15
    # relative to an origin at x_O = 15 mm the rotation drops out at A and B
    d15 = EFF.observe(V, X, 15.0, q) - V
    assert (d15[1, :, :2] - torch.tensor([0.3, -0.2, 0.0], dtype=F64)[:, None]).abs().max() \
        < 1e-15


def test_image_count_must_match_and_box_keys_set_every_image():
    with pytest.raises(ValueError, match="bound to 3 images, V has 2 output times"):
        EFF.observe(torch.zeros(1, 2, 4, dtype=F64), X, 0.0, torch.zeros(1, 6, dtype=F64))
    b = EFF.with_box({"c": (-2.0, 2.0)}).params
    assert b.lower == (-2.0,) * 3 + (-50.0,) * 3 and b.upper == (2.0,) * 3 + (50.0,) * 3
    assert b.units == ("um",) * 3 + ("urad",) * 3
