"""The hidden-effect measurement files of the diagnosis benchmarks, made by a finer FE.

One CSV per case in DIR, made by the finer FE (``mesh=fine``, 2 K / 150 s steps), noise
0.05 um, at the seed paper's four times. ``--kind field``: the 31 x 18 grid plus A and B;
``point``: A and B only. A file already there is kept (a benchmark's data do not change under
it).

* ``--cases``: library effects at the truth (:data:`solderpyro.diagnose.hidden.TRUTH`), each at
  its :func:`~solderpyro.diagnose.hidden.hidden_values` size, or ``none`` (default: every
  effect and none). Files ``NAME.csv``.
* ``--forms``: effects in forms other than the library's (benchmarks/forms.py), at each
  ``--sizes`` (the RMS change of the point data, um, that the hidden value reaches; forms with
  fixed values ignore it) and each ``--anand`` set of constants (:data:`ANAND_SETS`). Files
  ``FORM_SIZE_SET_sSEED.csv``.

Usage: python benchmarks/make_hidden_data.py DIR [--kind field|point] [--seed 0]
       [--cases NAME ...] [--forms FORM ... [--sizes 0.2 0.4 1.2] [--anand truth ...]]
Then:  python benchmarks/diagnosis_cases.py --data NAME=DIR/NAME.csv ... --with-hidden
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from solderpyro.config.compose import build, compose
from solderpyro.diagnose.hidden import TRUTH, HiddenTruth, hidden_values, make_dataset
from solderpyro.effects import EFFECTS
from solderpyro.fem.loading import SEED_TIMES

sys.path.insert(0, str(Path(__file__).resolve().parent))
from forms import FORMS, form  # noqa: E402

FINE = ["mesh=fine", "solver.stepping.dT_max=2.0", "solver.stepping.dt_max=150"]

#: Anand constants of the truth: the seed's, the residual-stress case's, one near the faces
ANAND_SETS = {
    "truth": dict(TRUTH),
    "interior": {"s0": 10.0, "QR": 11000.0, "xi": 1.5, "m": 0.3},
    "near_faces": {"s0": 22.0, "QR": 12500.0, "xi": 1.3, "m": 0.07},
}


def made(p: Path, t0: float) -> None:
    print(f"{p}: {time.perf_counter() - t0:.1f} s", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("dir")
    ap.add_argument("--kind", default="field", choices=("field", "point"))
    ap.add_argument("--seed", type=int, default=0, help="noise seed")
    ap.add_argument("--cases", nargs="*", default=None,
                    help=f"library effects or none: {', '.join(sorted(EFFECTS))}")
    ap.add_argument("--forms", nargs="*", default=None, help=f"forms: {', '.join(FORMS)}")
    ap.add_argument("--sizes", nargs="*", type=float, default=[0.2, 0.4, 1.2],
                    help="RMS change of the point data, um, per form")
    ap.add_argument("--anand", nargs="*", default=["truth"], choices=list(ANAND_SETS))
    a = ap.parse_args()
    cases = a.cases if a.cases is not None else (
        [] if a.forms else [*sorted(EFFECTS), "none"])
    bad = [c for c in cases if c != "none" and c not in EFFECTS]
    if bad:
        raise SystemExit(f"--cases: unknown {bad}; valid: {', '.join(sorted(EFFECTS))}, none")
    for f in a.forms or []:
        form(f)
    out = Path(a.dir)
    out.mkdir(parents=True, exist_ok=True)
    setup = build(compose(FINE))
    field = a.kind == "field"
    for c in cases:
        p = out / f"{c}.csv"
        if not p.exists():
            t0 = time.perf_counter()
            make_dataset(setup, None if c == "none" else c, p, field, SEED_TIMES,
                         noise=0.05, seed=a.seed)
            made(p, t0)
    for f in a.forms or []:
        eff, _, fixed = form(f)
        for aset in a.anand:
            truth = ANAND_SETS[aset]
            for size in ([None] if fixed else a.sizes):
                tag = "fixed" if fixed else f"{size:g}"
                p = out / f"{f}_{tag}_{aset}_s{a.seed}.csv"
                if p.exists():
                    continue
                t0 = time.perf_counter()
                vals = (np.asarray(fixed, float) if fixed else
                        hidden_values(setup, eff, target_rms=float(size), anand=truth)[0])
                make_dataset(setup, eff, p, field, SEED_TIMES, noise=0.05, seed=a.seed,
                             truth=HiddenTruth(vals, truth))
                made(p, t0)


if __name__ == "__main__":
    main()
