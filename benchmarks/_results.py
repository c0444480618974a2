"""Helper: a benchmark's results file, ``benchmarks/results/<script>.json`` by default.

Every run overwrites it with the run's figures and what they were measured on: the command
line, the inputs the script names (data, run directory, store), the machine
(``platform.node()``, CPU count, ``OMP_NUM_THREADS``, the 1-minute load average at the start),
the date and the wall time. Usage in a script::

    from _results import Results, json_option  # benchmarks/ is on sys.path when a script runs

    ap = argparse.ArgumentParser(...)
    json_option(ap, __file__)
    a = ap.parse_args()
    res = Results(a.json)  # starts the clock
    ...
    res.write({"figure": ...}, data=a.data)
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import sys
import time
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results"
ROOT = RESULTS.parent.parent


def json_option(ap: argparse.ArgumentParser, script: str) -> None:
    """Add ``--json PATH`` (default ``benchmarks/results/<script stem>.json``)."""
    default = RESULTS / f"{Path(script).stem}.json"
    ap.add_argument("--json", default=str(default), metavar="PATH",
                    help=f"the results file, overwritten by every run (default: "
                         f"{_shown(default)})")


def _shown(p: Path | str) -> str:
    """A path relative to the repository root where it lies inside it."""
    p = Path(p).resolve()
    try:
        return str(p.relative_to(ROOT))
    except ValueError:
        return str(p)


class Results:
    """The results file of one run: created before the work (the clock and the load start
    then), written once at its end."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.t0 = time.perf_counter()
        self.load = round(os.getloadavg()[0], 2)
        self.date = datetime.datetime.now().astimezone().isoformat(timespec="seconds")

    def write(self, figures: dict, **inputs) -> dict:
        """Overwrite the file with ``figures`` and the run's inputs; return the record."""
        torch = sys.modules.get("torch")
        rec = {"command": " ".join(["python", _shown(sys.argv[0]), *sys.argv[1:]]),
               "inputs": {k: _shown(v) if isinstance(v, Path) else v
                          for k, v in inputs.items()},
               "machine": {"node": platform.node(), "cpus": os.cpu_count(),
                           "omp_num_threads": os.environ.get("OMP_NUM_THREADS"),
                           "torch_threads": torch.get_num_threads() if torch else None,
                           "load_average_1min_at_start": self.load},
               "date": self.date,
               "wall_s": round(time.perf_counter() - self.t0, 1),
               **figures}
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.path.write_text(json.dumps(rec, indent=1, default=float) + "\n")
        print(f"results: {_shown(self.path)}", flush=True)
        return rec
