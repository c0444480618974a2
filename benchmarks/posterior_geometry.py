"""Why the full-field surrogate posterior is hard to sample.

Rebuilds a calibration run's final surrogate from its ``design.csv`` runs (read back from the
run store: no FE solve), then, at posterior draws of the run, the Hessian of the reduced
log likelihood (central differences of its analytic gradient) whitened by the draws'
covariance, in four coordinate systems: the logit of the box's unit cube (Pyro's transform
and NumPyro's), the unit cube itself, the GP's own inputs (flow stresses), and the soft-walled
flow-stress coordinates NUTS samples in
(:class:`solderpyro.calibration.flowcoords.SoftFlowCoords`, ``--frac`` its walls' width).
For a Gaussian every eigenvalue is 1; large ones are directions far narrower locally than
the posterior's spread, negative ones are curvature (a bent ridge). Optionally
(``--fe-at``) the FE's chi-square at given parameter rows, to test a surrogate mode against
the FE.

Usage: python benchmarks/posterior_geometry.py RUN_DIR [--points 8] [--seed 0]
       [--frac 0.01] [--fe-at s0,QR,xi,m ...] [--json benchmarks/results/posterior_geometry.json]
Prints one line per point and coordinate system (the sorted eigenvalues) and a JSON summary;
writes the summary, the spectra and the inputs to the results file (overwritten).
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
from pathlib import Path

import numpy as np
import torch

from solderpyro.calibration.reduced import ComponentGPs, GPInputMap, PCAReduction
from solderpyro.config.settings import CalibrationSettings
from solderpyro.diagnose.load import load_run
from solderpyro.pipeline.problem import CalibrationProblem
from solderpyro.pipeline.surrogate import fit_surrogate

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _results import Results, json_option  # noqa: E402


def rebuild(run: Path) -> tuple[CalibrationProblem, object, dict]:
    """The run's problem, its final surrogate refitted to the design's converged runs (noise
    sd for the PCA truncation: the posterior median, as the design's last round used), and
    the run as :func:`load_run` reads it."""
    r = load_run(run)
    sm = CalibrationProblem.build(r["setup"], r["meas"], r["info"].store, 64, False)
    with (run / "design.csv").open() as f:
        rows = [row for row in csv.DictReader(f) if row["converged"] == "1"]
    X = torch.tensor([[float(row[n]) for n in sm.gp_box.names] for row in rows],
                     dtype=torch.float64)
    V, _ = sm.fe(X)
    gp = fit_surrogate(sm, CalibrationSettings().surrogate, X, V,
                       float(np.median(r["draws"]["sigma"])))
    return sm, gp, r


def whitened_spectrum(f, x: np.ndarray, cov: np.ndarray, h: float) -> np.ndarray:
    """Sorted eigenvalues of ``L^T (-H) L`` (``cov = L L^T``, ``H`` the Hessian of ``f`` at
    ``x`` by central differences of its gradient ``f(x)[1]``, step ``h``)."""
    d = len(x)
    H = np.empty((d, d))
    for j in range(d):
        e = np.zeros(d)
        e[j] = h
        H[:, j] = (f(x + e)[1] - f(x - e)[1]) / (2 * h)
    H = 0.5 * (H + H.T)
    L = np.linalg.cholesky(cov)
    return np.linalg.eigvalsh(L.T @ (-H) @ L)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("--points", type=int, default=8)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--frac", type=float, default=0.01,
                    help="the soft walls' width as a share of each interval (flow coordinates)")
    ap.add_argument("--fe-at", nargs="*", default=[], metavar="s0,QR,xi,m")
    json_option(ap, __file__)
    a = ap.parse_args()
    res = Results(a.json)
    sm, gp, r = rebuild(a.run)
    n_fe = sm.n_fe
    if sm.space.dim != n_fe:
        raise SystemExit("observation-side effects are not covered: the likelihood here is "
                         "the FE part's")
    red, gps, umap = PCAReduction(gp, sm.y), ComponentGPs(gp), GPInputMap(gp, sm.space)
    sigma = float(np.median(r["draws"]["sigma"]))
    th = r["draws"]["theta"][:, :n_fe]
    u = sm.space.to_unit(torch.as_tensor(th)).numpy().clip(1e-9, 1 - 1e-9)

    def ll_v(v: np.ndarray) -> tuple[float, np.ndarray]:  # the GP's inputs
        c, var, vjp = gps(v)
        ll, gc, gv, _, _ = red.loglik(c, var, sigma, None)
        return ll, vjp(gc, gv)

    def ll_u(x: np.ndarray) -> tuple[float, np.ndarray]:  # the unit cube
        v, dv = umap(x)
        ll, g = ll_v(v)
        return ll, g @ dv

    def ll_q(q: np.ndarray) -> tuple[float, np.ndarray]:  # logits, with their Jacobian
        s = 1.0 / (1.0 + np.exp(-q))
        ll, g = ll_u(s)
        return ll + float(np.log(s * (1 - s)).sum()), g * s * (1 - s) + (1 - 2 * s)

    from solderpyro.calibration.flowcoords import SoftFlowCoords

    fc = SoftFlowCoords(sm.space, gp.inputs.fixed, gp.inputs.T_ref_K - 273.15,
                        gp.inputs.rate_ref, frac=a.frac)

    def ll_f(q: np.ndarray) -> tuple[float, np.ndarray]:  # soft-walled flow coordinates
        t, ld, vjp = fc.forward(q)
        ll, g = ll_u(t)
        return ll + ld, vjp(g)

    coords = {"logit": (np.log(u) - np.log1p(-u), ll_q, 1e-5),
              "flow": (np.array([fc.inverse(ui) for ui in u]), ll_f, 1e-6),
              "unit": (u, ll_u, 1e-6),
              "gp_inputs": (np.array([umap(ui)[0] for ui in u]), ll_v, 1e-6)}
    idx = np.random.default_rng(a.seed).choice(len(u), a.points, replace=False)
    out: dict[str, dict] = {}
    spectra: dict[str, dict] = {}
    for name, (pts, f, h) in coords.items():
        cov = np.cov(pts.T)
        ev = np.array([whitened_spectrum(f, pts[i], cov, h) for i in idx])
        for i, e in zip(idx, ev, strict=True):
            print(f"{name:9s} draw {i:5d}: " + " ".join(f"{v:10.3g}" for v in e))
        out[name] = {"largest": [float(ev[:, -1].min()), float(ev[:, -1].max())],
                     "smallest": float(ev[:, 0].min())}
        spectra[name] = {str(i): e.tolist() for i, e in zip(idx, ev, strict=True)}
    if a.fe_at:
        rows = np.array([[float(v) for v in s.split(",")] for s in a.fe_at])
        V = sm.observed(rows)
        out["fe_chi2"] = {s: float((((V[k] - sm.y.numpy()) / sigma) ** 2).sum())
                          for k, s in enumerate(a.fe_at)}
    print(json.dumps(out, indent=1))
    res.write({**out, "spectra_by_draw": spectra}, run=a.run.resolve(), points=a.points,
              seed=a.seed, frac=a.frac, fe_at=a.fe_at, store=str(r["info"].store),
              data=str(r["info"].data))


if __name__ == "__main__":
    main()
