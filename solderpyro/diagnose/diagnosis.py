"""The record of a diagnosis (:class:`Diagnosis`), written to ``diagnosis.json``."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any


@dataclass
class Diagnosis:
    """What :func:`diagnose` found (also written to ``diagnosis.json``)."""

    misfit: bool
    verdict: str
    ranking: list[dict]
    check: dict
    indistinguishable: list[list[str]]
    suggestions: list[str]
    separation: dict | None = None
    #: stage -> ``{"seconds", "fe_runs" (computed), "fe_reused" (read from the run store or
    #: shared with another row)}``, then ``"total"``
    timing: dict[str, dict[str, float | int]] = dataclasses.field(default_factory=dict)
    #: the denoised residual (full-field data): :meth:`~.denoise.Smooth.summary`
    denoise: dict | None = None
    #: the FE's best fit every statistic is taken at (start, chi2 history, parameters)
    base: dict | None = None
    #: candidates whose refit ended above its base after a retry: reported, never ranked
    failed: list[dict] = dataclasses.field(default_factory=list)
    #: effects the forward steps added, in order
    selected: list[str] = dataclasses.field(default_factory=list)
    #: True: the selected effects (or a tie) explain the misfit; False: none of the candidates
    #: does; None: no misfit
    explained: bool | None = None
    #: the discretization floor used (:class:`~solderpyro.diagnose.decide.Floor`)
    floor: dict | None = None
    #: per forward step, each refit judged (:func:`~solderpyro.diagnose.decide.judge`)
    steps: list[list[dict]] = dataclasses.field(default_factory=list)
    #: where the model fits: candidates the data do not reject that would move a constant
    #: outside its reported interval (:func:`~solderpyro.diagnose.ruleout.cannot_rule_out`)
    cannot_rule_out: list[dict] = dataclasses.field(default_factory=list)
    #: the constants' reported intervals widened to admit each of those effects: name ->
    #: ``[lo, hi]``, physical units (:func:`~solderpyro.diagnose.ruleout.admitting`); empty
    #: where the data rule every effect out
    admitting: dict[str, list[float]] = dataclasses.field(default_factory=dict)
    #: the Anand constants the FE's best fit presses against the prior box's faces
    #: (:class:`~solderpyro.diagnose.faces.Face` records)
    faces: list[dict] = dataclasses.field(default_factory=list)

    def to_json(self) -> dict[str, Any]:
        """The record as ``diagnosis.json`` holds it (every field, ``timing`` last)."""
        return {"misfit": self.misfit, "explained": self.explained, "verdict": self.verdict,
                "selected": self.selected, "ranking": self.ranking, "failed": self.failed,
                "check": self.check, "base": self.base, "floor": self.floor,
                "steps": self.steps, "indistinguishable": self.indistinguishable,
                "suggestions": self.suggestions, "separation": self.separation,
                "cannot_rule_out": self.cannot_rule_out, "admitting": self.admitting,
                "faces": self.faces,
                "denoise": self.denoise, "timing": self.timing}
