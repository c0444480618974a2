"""The stage clock of a diagnosis (solderpyro.diagnose.costs): a stage's seconds cover the
block's wall time, and without an FE counter it reports no runs. Stage run counts and the
total are in tests/unit/diagnose/test_run.py."""

import time

from solderpyro.diagnose.costs import STAGES, Costs


def test_stage_seconds_cover_the_block_and_the_total_covers_the_stages():
    """A block sleeping 50 ms takes >= 0.05 s (rounded to 1 ms, so >= 0.049) and at most
    what the caller measured around it (+1 ms rounding); no FE counter: 0 runs."""
    cost = Costs()
    t0 = time.perf_counter()
    with cost.stage("best_fit"):
        time.sleep(0.05)
    outer = time.perf_counter() - t0
    row = cost.table()["best_fit"]
    assert 0.049 <= row["seconds"] <= outer + 1e-3
    assert row["fe_runs"] == 0 and row["fe_reused"] == 0
    tab = cost.table()
    assert tab["total"]["seconds"] >= row["seconds"] - 1e-3
    assert set(tab) - {"total"} <= set(STAGES)


def test_every_stage_the_diagnosis_times_has_a_label():
    """Each ``cost.stage("...")`` in diagnose/run.py names a key of STAGES (the log and
    diagnosis.md label it; an unknown name would fail the diagnosis at its end)."""
    import re
    from pathlib import Path

    import solderpyro.diagnose.run as run
    from solderpyro.diagnose.costs import STAGES

    names = set(re.findall(r'cost\.stage\("([a-z_]+)"\)', Path(run.__file__).read_text()))
    assert "global_refits" in names and names <= set(STAGES), names - set(STAGES)


def test_a_stage_that_raises_is_counted():
    import pytest

    from solderpyro.diagnose.costs import Costs

    c = Costs()
    with pytest.raises(RuntimeError), c.stage("best_fit"):
        raise RuntimeError("the fit failed")
    assert "best_fit" in c.stages and c.stages["best_fit"]["fe_runs"] == 0
