"""How long the command line takes to answer ``solderpyro --help`` and ``solderpyro --version``.

Usage: python benchmarks/cli_startup.py [--runs 5] [--label NAME]
       [--out benchmarks/results/cli_startup.json]

Each run is a fresh interpreter started as the ``solderpyro`` console script starts one
(``from solderpyro.cli import main; sys.exit(main())``), timed from ``subprocess.run`` to its
exit (wall seconds), in an empty directory. It times the ``solderpyro`` that this
interpreter imports there (set ``PYTHONPATH`` to time a checkout, e.g. the code before a change
with ``--label before``). The record
keeps every run, their median, the exit status of the last and the machine's 1-minute load
average at the start (other processes slow a start-up that imports torch most).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ENTRY = "import sys; from solderpyro.cli import main; sys.exit(main())"


def time_command(args: list[str], runs: int) -> dict:
    """Wall seconds of ``runs`` fresh ``solderpyro ARGS`` processes (one untimed first run
    warms the file cache)."""
    cmd = [sys.executable, "-c", ENTRY, *args]
    with tempfile.TemporaryDirectory() as empty:  # -c puts the working directory on sys.path
        subprocess.run(cmd, capture_output=True, cwd=empty)
        walls, rc = [], 0
        for _ in range(runs):
            t0 = time.perf_counter()
            r = subprocess.run(cmd, capture_output=True, cwd=empty)
            walls.append(round(time.perf_counter() - t0, 3))
            rc = r.returncode
    return {"wall_s": walls, "median_s": statistics.median(walls), "returncode": rc}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--label", default="current")
    ap.add_argument("--out", default="benchmarks/results/cli_startup.json")
    a = ap.parse_args()
    where = subprocess.run([sys.executable, "-c", "import solderpyro; print(solderpyro.__file__)"],
                           capture_output=True, text=True, cwd=tempfile.gettempdir())
    rec = {"command": " ".join(["python", "benchmarks/cli_startup.py", *sys.argv[1:]]),
           "solderpyro": where.stdout.strip(),
           "load_average_1min": round(os.getloadavg()[0], 2),
           "help": time_command(["--help"], a.runs),
           "version": time_command(["--version"], a.runs)}
    out = Path(a.out)
    data = json.loads(out.read_text()) if out.is_file() else {}
    data[a.label] = rec
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(data, indent=1) + "\n")
    print(json.dumps({a.label: rec}, indent=1))


if __name__ == "__main__":
    main()
