"""The stage clock of a diagnosis: seconds and FE runs (computed, reused) per stage."""

from __future__ import annotations

import logging
import time
from collections.abc import Iterator
from contextlib import contextmanager

from solderpyro.specimen import SpecimenModels

log = logging.getLogger("solderpyro")


#: stage -> its label in the log and in diagnosis.md
STAGES = {"load": "loading the run", "predictive_check": "posterior predictive check",
          "best_fit": "FE best fit (baseline refit)",
          "fe_jacobians": "FE Jacobians (+ ladder runs)", "score_tests": "score tests",
          "ladder": "likelihood-ratio ladder", "profile_refits": "profile refits",
          "global_refits": "global refits (every candidate, several starts)",
          "verdict": "ranking and verdict", "cannot_rule_out": "what the data cannot rule out",
          "separation": "separation",
          "fingerprints": "fingerprints (refit predictions, denoising)",
          "write": "writing (figures)"}


class Costs:
    """Seconds and FE runs (computed, reused) per stage of a diagnosis."""

    def __init__(self) -> None:
        self.t0 = time.perf_counter()
        self.fe: SpecimenModels | None = None
        self.others: list[SpecimenModels] = []
        self.stages: dict[str, dict[str, float | int]] = {}

    def fe_also(self, models: SpecimenModels) -> None:
        """Count ``models``' runs too (another model of the same diagnosis, e.g. the
        half-resolution one its global refits rank their starts with)."""
        self.others.append(models)

    def _counts(self) -> tuple[int, int]:
        ms = ([] if self.fe is None else [self.fe]) + self.others
        return sum(m.computed for m in ms), sum(m.reused for m in ms)

    @contextmanager
    def stage(self, name: str) -> Iterator[None]:
        """Time the block as stage ``name`` (a key of :data:`STAGES`): its seconds and the FE
        runs of :attr:`fe` (computed, reused) it took are kept and logged."""
        t0, (c0, r0) = time.perf_counter(), self._counts()
        try:
            yield
        finally:  # a stage that raises is counted too (its FE runs are stored all the same)
            c1, r1 = self._counts()
            row = {"seconds": round(time.perf_counter() - t0, 3), "fe_runs": c1 - c0,
                   "fe_reused": r1 - r0}
            self.stages[name] = row
            log.info("diagnose: %-30s %8.2f s, %4d FE runs computed, %4d reused",
                     STAGES[name], row["seconds"], row["fe_runs"], row["fe_reused"])

    def table(self) -> dict[str, dict[str, float | int]]:
        """The stages, then ``"total"`` (wall time since the start)."""
        total = {"seconds": round(time.perf_counter() - self.t0, 3),
                 "fe_runs": sum(int(r["fe_runs"]) for r in self.stages.values()),
                 "fe_reused": sum(int(r["fe_reused"]) for r in self.stages.values())}
        return {**self.stages, "total": total}
