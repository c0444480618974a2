"""The seed's mathematical example (Tables I, II; Figures 1-4) as an experiment script.

Usage: python experiments/seed_math.py --out runs/seed-math [--seed N] [--chains 4]
       [--warmup 500] [--draws 1000]
Same as ``solderpyro example seed-math``; see solderpyro/examples/seed_math.py.
"""

import sys

from solderpyro.cli import main

if __name__ == "__main__":
    sys.exit(main(["example", "seed-math", *sys.argv[1:]]))
