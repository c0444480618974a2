"""Before/after: how much an added effect improves the fit (``solderpyro compare``).

Reads two run directories of ``solderpyro calibrate`` on the same data (e.g. without and with
``effects=[NAME]``) and reports, from their posterior predictive draws:

- RMS residual of the predictive median against the data, um;
- the posterior predictive misfit statistic (mean of ``sum((y - mu)^2 / sigma^2)``) and its
  p-value (:func:`~solderpyro.diagnose.stats.predictive_check`);
- the log predictive density of the data, ``elpd = sum_i log N(y_i; m_i, v_i)`` with ``m_i``,
  ``v_i`` the mean and variance of the posterior predictive of observation i (its draws carry
  code uncertainty and noise; nats, higher is better; standard error ``sqrt(n var_i)``). It is
  the in-sample log predictive density in a Gaussian approximation (no WAIC penalty: the
  predictive draws sample the GP's code variance per observation, which a WAIC variance term
  would mistake for parameter uncertainty);
- the shift of every common parameter's posterior (median and 95 % interval).
"""

from __future__ import annotations

import csv
import json
from pathlib import Path
from typing import Any

import numpy as np

from solderpyro.diagnose.stats import predictive_check


def _logpdf(y: np.ndarray, mu: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    return -0.5 * ((y - mu) / sigma) ** 2 - np.log(sigma) - 0.5 * np.log(2 * np.pi)


def run_metrics(run_dir: str | Path) -> dict[str, Any]:
    """Fit metrics of one calibration run (see the module docstring).

    Returns:
        dict with ``rms_um``, ``misfit_mean``, ``misfit_p``, ``elpd``, ``elpd_se``, ``n``,
        ``effects`` and ``summary`` (parameter -> row of summary.csv).
    """
    d = Path(run_dir)
    with np.load(d / "draws.npz") as z:
        y, mu, sig, obs = z["y_obs"], z["process"], z["sigma_pred"], z["observed"]
    info = json.loads((d / "run.json").read_text())
    elpd_i = _logpdf(y, obs.mean(0), obs.std(0, ddof=1))
    pc = predictive_check(y, mu, sig)
    with open(d / "summary.csv", newline="") as fh:
        summ = {r["parameter"]: {k: float(v) for k, v in r.items() if k != "parameter"}
                for r in csv.DictReader(fh)}
    return {"rms_um": float(np.sqrt(np.mean((np.median(mu, 0) - y) ** 2))),
            "misfit_mean": float(pc.t_obs.mean()), "misfit_p": pc.p_value,
            "elpd": float(elpd_i.sum()), "elpd_se": float(np.sqrt(len(y) * elpd_i.var())),
            "n": int(len(y)),
            "effects": info.get("effects", []), "summary": summ}


def compare(before: str | Path, after: str | Path, out: str | Path | None = None
            ) -> dict[str, Any]:
    """Compare two runs on the same data; writes ``comparison.json`` and ``comparison.md`` into
    ``out`` (default: ``after``).

    Raises:
        ValueError when the two runs were calibrated on different data.
    """
    a, b = run_metrics(before), run_metrics(after)
    ya = np.load(Path(before) / "draws.npz")["y_obs"]
    yb = np.load(Path(after) / "draws.npz")["y_obs"]
    if ya.shape != yb.shape or not np.allclose(ya, yb):
        raise ValueError(f"{before} and {after} were calibrated on different data")
    shifts = []
    for p in a["summary"]:
        if p in b["summary"]:
            ra, rb = a["summary"][p], b["summary"][p]
            shifts.append({"parameter": p, "before": [ra["q2.5"], ra["median"], ra["q97.5"]],
                           "after": [rb["q2.5"], rb["median"], rb["q97.5"]]})
    added = [p for p in b["summary"] if p not in a["summary"]]
    res = {"before": {k: v for k, v in a.items() if k != "summary"},
           "after": {k: v for k, v in b.items() if k != "summary"},
           "elpd_gain": b["elpd"] - a["elpd"], "shifts": shifts,
           "added": {p: b["summary"][p] for p in added}}
    o = Path(out or after)
    o.mkdir(parents=True, exist_ok=True)
    (o / "comparison.json").write_text(json.dumps(res, indent=2) + "\n")
    lines = [f"# Before / after: {', '.join(b['effects']) or 'baseline'} vs "
             f"{', '.join(a['effects']) or 'baseline'}", "",
             "| | before | after |", "|---|---|---|",
             f"| RMS residual (um) | {a['rms_um']:.4g} | {b['rms_um']:.4g} |",
             f"| misfit statistic (mean; n = {a['n']}) | {a['misfit_mean']:.4g} | "
             f"{b['misfit_mean']:.4g} |",
             f"| predictive p-value | {a['misfit_p']:.3g} | {b['misfit_p']:.3g} |",
             f"| log predictive density (nats) | {a['elpd']:.2f} +- {a['elpd_se']:.2f} | "
             f"{b['elpd']:.2f} +- {b['elpd_se']:.2f} |", "",
             "## Posterior shifts (2.5 / 50 / 97.5 %)", "",
             "| parameter | before | after |", "|---|---|---|"]
    for s in shifts:
        lines.append(f"| {s['parameter']} | " + " / ".join(f"{v:.4g}" for v in s["before"])
                     + " | " + " / ".join(f"{v:.4g}" for v in s["after"]) + " |")
    for p, r in res["added"].items():
        lines.append(f"| {p} (added) | | {r['q2.5']:.4g} / {r['median']:.4g} / "
                     f"{r['q97.5']:.4g} |")
    (o / "comparison.md").write_text("\n".join(lines) + "\n")
    return res
