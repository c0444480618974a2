"""solderpyro.specimen: the observation-side offsets, one parameter set or a batch."""

import numpy as np
import torch

from solderpyro.config.compose import build, coarsened, compose
from solderpyro.effects import effect_set
from solderpyro.specimen import observation_offset


def test_observation_offset_of_a_batch_is_the_offsets_row_by_row():
    """A batch ``(B, n_q)`` gives the B offsets one call at a time would; moire rigid motion
    has its own c and w per image, so the two images' offsets differ."""
    setup = build(compose(["effects=[moire_rigid_motion]"]))
    times = (600.0, 2700.0)
    fx = effect_set(["moire_rigid_motion"], times, setup.effect_bounds)
    ti, oi = np.array([0, 0, 1, 1]), np.array([0, 1, 0, 1])
    off = observation_offset(fx, setup.problem, ("A", "B"), 2, ti, oi)
    q = torch.rand(7, fx.box.dim, generator=torch.Generator().manual_seed(0),
                   dtype=torch.float64)
    batch = off(q)
    assert batch.shape == (7, 4) and off(q[0]).shape == (4,)
    torch.testing.assert_close(batch, torch.stack([off(v) for v in q]), rtol=0, atol=0)
    assert float((batch[:, 0] - batch[:, 2]).abs().min()) > 0  # A at 600 s vs A at 2700 s


def test_coarsened_halves_the_runs_own_mesh_and_doubles_its_steps():
    """The half-resolution model of a run is made from the run's own mesh: the fine mesh
    (60 x 16/8/16) becomes the default's element counts (30 x 8/4/8), the time steps' largest
    temperature change and duration double, and the other overrides stay."""
    base = ["mesh=fine", "solver.stepping.dT_max=3.0"]
    ov = coarsened(base)
    assert ov[:2] == base
    cfg, ref = compose(ov), compose([])
    assert cfg.mesh.nx == ref.mesh.nx == 30
    assert {k: r.ny for k, r in cfg.mesh.rows.items()} == {
        k: r.ny for k, r in ref.mesh.rows.items()}
    assert cfg.solver.stepping.dT_max == 6.0
    assert cfg.solver.stepping.dt_max == 2.0 * ref.solver.stepping.dt_max
    assert cfg.mesh.x_grading == ref.mesh.x_grading
    build(cfg)  # the model builds
