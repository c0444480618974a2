"""The hidden-effect measurement files of the diagnosis benchmarks, made by a finer FE.

One CSV per case in DIR: the finer FE (``mesh=fine``, 2 K / 150 s steps) at the truth
(:data:`solderpyro.diagnose.hidden.TRUTH`) with one hidden effect at its
:func:`~solderpyro.diagnose.hidden.hidden_values` size, or none, noise 0.05 um, at the seed
paper's four times. ``--kind field``: the 31 x 18 grid plus A and B; ``point``: A and B only.
A file already there is kept (the data of a benchmark do not change under it).

Usage: python benchmarks/make_hidden_data.py DIR [--kind field|point] [--seed 0]
       [--cases NAME ...]
Then:  python benchmarks/diagnosis_cases.py --data NAME=DIR/NAME.csv ... --with-hidden
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from solderpyro.config.compose import build, compose
from solderpyro.diagnose.hidden import make_dataset
from solderpyro.effects import EFFECTS
from solderpyro.fem.loading import SEED_TIMES

FINE = ["mesh=fine", "solver.stepping.dT_max=2.0", "solver.stepping.dt_max=150"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("dir")
    ap.add_argument("--kind", default="field", choices=("field", "point"))
    ap.add_argument("--seed", type=int, default=0, help="noise seed")
    ap.add_argument("--cases", nargs="*", default=None,
                    help=f"effects (default: all and none): {', '.join(sorted(EFFECTS))}")
    a = ap.parse_args()
    cases = a.cases or [*sorted(EFFECTS), "none"]
    bad = [c for c in cases if c != "none" and c not in EFFECTS]
    if bad:
        raise SystemExit(f"--cases: unknown {bad}; valid: {', '.join(sorted(EFFECTS))}, none")
    out = Path(a.dir)
    out.mkdir(parents=True, exist_ok=True)
    setup = build(compose(FINE))
    for c in cases:
        p = out / f"{c}.csv"
        if p.exists():
            print(f"{p}: there, kept")
            continue
        t0 = time.perf_counter()
        make_dataset(setup, None if c == "none" else c, p, a.kind == "field", SEED_TIMES,
                     noise=0.05, seed=a.seed)
        print(f"{p}: {time.perf_counter() - t0:.1f} s", flush=True)


if __name__ == "__main__":
    main()
