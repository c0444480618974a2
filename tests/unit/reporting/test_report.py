"""The run directory's reports: ``report.md`` states the draws the posterior holds (not the
settings' count), and ``index.html`` is the one entry page, linking every other file."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import torch

from solderpyro.calibration.mcmc import Posterior
from solderpyro.config.rundir import RunDir, RunInfo
from solderpyro.io.measurements import from_arrays
from solderpyro.reporting import report
from solderpyro.reporting.index import write_index
from solderpyro.surrogate.gp import LooResult

TIMES = [600.0, 900.0, 1500.0]
POINTS = {"A": (15.0, 4.5), "B": (15.0, -4.0)}
#: asked for 1500 draws per chain; the chains ran on to 2250 (as reach_min_ess does)
ASKED = {"chains": 4, "draws": 1500, "warmup": 500}


def _posterior(n_chain: int, n_draw: int) -> Posterior:
    g = torch.Generator().manual_seed(0)
    t = torch.randn(n_chain, n_draw, 2, generator=g, dtype=torch.float64)
    return Posterior(samples={"t": t, "sigma": 0.05 + 0.0 * t[..., 0]},
                     labels={"t": ["s0", "QR"]}, divergences=[0] * n_chain, seconds=3.0)


def test_sampled_text_reads_the_draws_not_the_settings() -> None:
    post = _posterior(4, 2250)
    txt = report.sampled_text(post, ASKED)
    assert txt.startswith("4 chains x 2250 draws kept after 500 warm-up")
    assert "1500 asked; the chains ran on for 750 more" in txt
    assert report.sampled_text(post, {}) == "4 chains x 2250 draws kept"
    same = report.sampled_text(_posterior(2, 100), {"chains": 2, "draws": 100, "warmup": 50})
    assert same == "2 chains x 100 draws kept after 50 warm-up"


def _write_report(tmp_path, interval: str = "central", exact: dict | None = None) -> str:
    """report.md of a two-parameter run whose s0 row has the interval kind ``interval``, with
    the FE-exact record ``exact`` in run.json (None: no FE-exact step)."""
    rng = np.random.default_rng(1)
    truth = np.array([[1.0, -0.5], [1.4, -0.7], [2.0, -1.1]])
    meas = from_arrays(TIMES, list(POINTS), list(POINTS.values()),
                       truth + 0.05 * rng.standard_normal(truth.shape), sigma_um=0.05)
    info = RunInfo(parameters=["s0", "QR"], lower=[5.0, 7000.0], upper=[25.0, 13000.0],
                   effects=[], sigma_known=None, times_s=TIMES, points=list(POINTS),
                   settings={"sampler": dict(ASKED)}, trust="the surrogate posterior",
                   exact=exact)
    run = RunDir(tmp_path, info).write(meas)
    y = torch.as_tensor(truth.reshape(-1))
    loo = LooResult(y=y[:, None], mean=y[:, None], sd=0.1 + 0 * y[:, None],
                    z=0 * y[:, None], coverage95=1.0, rmse_rel=0.01, max_abs_z=0.0)
    bands = SimpleNamespace(median=y, obs_lo=y - 0.1, obs_hi=y + 0.1)
    rows = [{"parameter": nm, "q2.5": -2.0, "median": 0.0, "mean": 0.0, "q97.5": 2.0,
             "lo95": -2.0, "hi95": 2.0, "interval": interval if nm == "s0" else "central",
             "r_hat": 1.0, "ess_bulk": 900} for nm in ("s0", "QR")]
    return report.write(report.CalibrationReport(
        run, meas, rows, _posterior(4, 2250), loo, bands, truth.reshape(-1) + 0.3,
        report.FeRunCounts(20, 0, 0, 20))).read_text()


def test_report_states_the_kept_draws_and_index_links_everything(tmp_path) -> None:
    (tmp_path / "summary.csv").write_text("parameter,q2.5,median,q97.5\ns0,-2,0,2\n")
    (tmp_path / "posterior.nc").write_bytes(b"x")
    (tmp_path / "extra_notes.txt").write_text("kept\n")
    md = _write_report(tmp_path)
    assert "4 chains x 2250 draws kept after 500 warm-up" in md
    assert "x 1500 draws" not in md
    html_report = (tmp_path / "report.html").read_text()
    for text in (md, html_report):
        assert "entry page is <code>index.html</code>" in text or "entry page is `index.html`" \
            in text
        assert "open it first" not in text and "opens first" not in text

    page = write_index(tmp_path).read_text()
    for f in ("report.html", "report.md", "summary.csv", "posterior.nc", "data.csv",
              "run.json", "fig9_posterior.png", "extra_notes.txt"):
        assert f'href="{f}"' in page, f
    assert 'href="index.html"' not in page


def test_an_interval_widened_to_its_profile_says_why_it_was_profiled(tmp_path) -> None:
    """The report says why an interval holds the FE's profile: the data leave an effect's form
    open after a reliable FE-exact posterior, its weights are not reliable otherwise."""
    from solderpyro.calibration.intervals import PROFILE

    md = _write_report(tmp_path / "a", PROFILE, {"reliable": True})
    assert "leave the form of an effect open" in md and "intervals of s0 are widened" in md
    assert "not reliable" not in md
    md = _write_report(tmp_path / "b", PROFILE, {"reliable": False})
    assert "weights are not reliable, so the 95 % intervals of s0 are widened" in md
    assert "leave the form of an effect open" not in md
    assert "profile-likelihood" not in _write_report(tmp_path / "c")
