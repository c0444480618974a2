"""SpecimenModel API, ParameterSpace maps, time grid."""

import numpy as np
import pytest
import torch

from solderpyro import ParameterSpace, SpecimenModel
from solderpyro.fem.loading import (
    REFERENCE_CYCLE,
    SEED_TIMES,
    ThermalCycle,
    TimeStepping,
    time_grid,
)
from solderpyro.fem.mesh import graded
from solderpyro.params import ANAND_NAMES, LIU2008, parse_theta


def test_parameter_space_roundtrip_and_full():
    sp = ParameterSpace(("s0", "m"), (5.0, 0.05), (25.0, 0.5), (False, True))
    th = torch.tensor([[10.0, 0.1], [25.0, 0.05]])
    u = sp.to_unit(th)
    assert torch.allclose(sp.from_unit(u), th)
    assert u[1].tolist() == pytest.approx([1.0, 0.0])
    full = sp.full(th)
    assert full.shape == (2, 9)
    assert full[0, ANAND_NAMES.index("QR")] == LIU2008["QR"]
    assert full[0, ANAND_NAMES.index("m")] == 0.1
    with pytest.raises(ValueError, match="unknown parameter 'foo'"):
        ParameterSpace(("foo",), (0.0,), (1.0,))
    with pytest.raises(ValueError, match="lower .* must be < upper"):
        ParameterSpace(("s0",), (5.0,), (1.0,))


def test_parse_theta_errors_name_the_item():
    assert parse_theta("s0=12.9, QR=10586") == {"s0": 12.9, "QR": 10586.0}
    for bad, msg in [("s0", "not name=value"), ("s0=x", "not a number"), ("z=1", "'z'"),
                     ("m=0", "outside")]:
        with pytest.raises(ValueError, match=msg):
            parse_theta(bad)


def test_time_grid_hits_knots_and_outputs():
    g = time_grid(REFERENCE_CYCLE, SEED_TIMES, TimeStepping())
    for t in REFERENCE_CYCLE.times[1:] + SEED_TIMES:
        assert np.min(np.abs(g - t)) < 1e-9
    dT = np.abs(np.diff([REFERENCE_CYCLE(t) for t in g]))
    assert dT.max() <= TimeStepping().dT_max + 1e-9
    assert np.all(np.diff(g) > 0)
    with pytest.raises(ValueError, match="outside the cycle"):
        time_grid(REFERENCE_CYCLE, (9000.0,), TimeStepping())
    with pytest.raises(ValueError, match="increase strictly"):
        ThermalCycle((0.0, 10.0, 5.0), (25.0, 30.0, 40.0))


def test_graded_spacing():
    x = graded(0.0, 15.0, 10, 0.2, "top")
    h = np.diff(x)
    assert x[0] == 0 and x[-1] == pytest.approx(15.0)
    assert h[-1] / h[0] == pytest.approx(0.2)


def test_specimen_model_shapes_names_and_validation():
    from solderpyro.fem.loading import ThermalCycle as TC
    from solderpyro.fem.mesh import Layer, MeshSpec
    from solderpyro.fem.problem import Problem

    layers = (Layer("copper", "copper", -4.0, 0.0, 3, 0.25, "top"),
              Layer("solder", "solder", 0.0, 0.5, 2),
              Layer("steel", "steel", 0.5, 4.5, 3, 0.25, "bottom"))
    pr = Problem(layers=layers, mesh=MeshSpec(nx=8), cycle=TC((0.0, 600.0), (25.0, 75.0)),
                 stepping=TimeStepping(dT_max=10.0))
    shift = lambda V: V + 1.0  # noqa: E731  observation seam
    m = SpecimenModel(pr, times=(300.0, 600.0), field=True, observation=shift)
    th = torch.tensor([[12.41, 9400.0, 1.5, 0.303]], dtype=torch.float64)
    V = m(th)
    assert V.shape == (1, 2, 2 + 558)
    assert m.output_names[:3] == ["A", "B", "g_00_00"]
    assert torch.allclose(V - 1.0, m.last.V)
    assert m.output_points.shape == (560, 2)
    with pytest.raises(ValueError, match=r"shape \(B, 4\)"):
        m(torch.ones(1, 3, dtype=torch.float64))
    with pytest.raises(ValueError, match="m=5"):
        m(torch.tensor([[12.0, 9400.0, 1.5, 5.0]], dtype=torch.float64))
