"""The mission's loop on full-field data, timed as a user runs it.

    python benchmarks/loop.py --effect modulus_temperature --out runs/loop

1. data: the FE with a hidden effect on a finer mesh and time step than the calibration's
   (``mesh=fine``, half the temperature step, half the largest time step) plus N(0, 0.05^2)
   noise on the 31 x 18 grid at the seed times (2,240 values; no inverse crime);
2. ``solderpyro calibrate`` with default flags;
3. ``solderpyro diagnose`` of that run;
4. ``solderpyro calibrate ... effects=[TOP] --warm-from BASE`` with the top-ranked effect;
5. ``solderpyro compare BASE WITH``.

Each command runs as its own process (what a user waits for); the wall time of each, the
calibrations' own stage times (run.json ``timing_s``), R-hat, bulk ESS and divergences go to
``--json`` (default benchmarks/results/loop.json). Data and runs stay in ``--out``.
"""

from __future__ import annotations

import argparse
import csv
import json
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FINE = ["mesh=fine", "solver.stepping.dT_max=2.0", "solver.stepping.dt_max=150"]


def _run(cmd: list[str], log: Path) -> float:
    t0 = time.perf_counter()
    with log.open("w") as f:
        r = subprocess.run(cmd, stdout=f, stderr=subprocess.STDOUT, cwd=ROOT)
    if r.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed (exit {r.returncode}); see {log}")
    return time.perf_counter() - t0


def _summary(run: Path) -> dict:
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        import arviz as az

    from solderpyro.config.rundir import RunDir

    with (run / "summary.csv").open() as f:
        rows = list(csv.DictReader(f))
    info = RunDir.read(run).info
    idata = az.from_netcdf(str(run / "posterior.nc"))
    rhat = az.rhat(idata)
    ess = az.ess(idata, method="bulk")
    div = int(idata.sample_stats["diverging"].values.sum())
    return {"r_hat_max": float(max(rhat[v].values.max() for v in rhat.data_vars)),
            "ess_bulk_min": float(min(ess[v].values.min() for v in ess.data_vars)),
            "divergences": div, "rows": rows, "timing_s": info.timing_s,
            "fe_check": info.checks.fe_check}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--effect", default="modulus_temperature",
                    help="the hidden effect of the data (an effect name, or none)")
    ap.add_argument("--out", default="runs/loop")
    ap.add_argument("--seed", type=int, default=0, help="noise seed of the data")
    ap.add_argument("--json", default=str(ROOT / "benchmarks" / "results" / "loop.json"))
    a = ap.parse_args()
    out = Path(a.out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    exe = [sys.executable, "-m", "solderpyro.cli"]
    data = out / "data.csv"
    if not data.is_file():
        code = ("import sys; from solderpyro.config.compose import build, compose; "
                "from solderpyro.diagnose.hidden import make_dataset; "
                "from solderpyro.fem.loading import SEED_TIMES; "
                f"s = build(compose({FINE!r})); "
                f"make_dataset(s, None if {a.effect!r} == 'none' else {a.effect!r}, "
                f"{str(data)!r}, True, tuple(SEED_TIMES), noise=0.05, seed={a.seed})")
        subprocess.run([sys.executable, "-c", code], check=True, cwd=ROOT)
    store = str(out / "store")
    res: dict = {"effect": a.effect, "data": str(data), "stages": {}}
    base, top_dir = out / "base", out / "with_effect"
    res["stages"]["calibrate"] = _run(exe + ["calibrate", "--data", str(data), "--out",
                                             str(base), "--store", store, "--quiet"],
                                      out / "calibrate.log")
    res["base"] = _summary(base)
    res["stages"]["diagnose"] = _run(exe + ["diagnose", str(base), "--quiet"],
                                     out / "diagnose.log")
    dg = json.loads((base / "diagnosis.json").read_text())
    # the effects the diagnosis selected (forward steps), none where it found a tie or none
    top = ",".join(dg.get("selected") or []) or None
    res["verdict"], res["top"] = dg["verdict"], top
    if top is not None:
        res["stages"]["recalibrate"] = _run(
            exe + ["calibrate", "--data", str(data), "--out", str(top_dir), "--store", store,
                   "--quiet", "--warm-from", str(base), f"effects=[{top}]"],
            out / "recalibrate.log")
        res["with_effect"] = _summary(top_dir)
        res["stages"]["compare"] = _run(exe + ["compare", str(base), str(top_dir)],
                                        out / "compare.log")
    res["total_s"] = sum(res["stages"].values())
    Path(a.json).write_text(json.dumps(res, indent=1, default=str) + "\n")
    print(json.dumps({"stages_s": res["stages"], "total_s": res["total_s"], "top": top,
                      "base_rhat": res["base"]["r_hat_max"],
                      "base_ess": res["base"]["ess_bulk_min"]}, indent=1))


if __name__ == "__main__":
    main()
