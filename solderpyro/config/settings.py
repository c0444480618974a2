"""Every setting of a specimen calibration (:func:`solderpyro.pipeline.calibrate_specimen`)
in one typed object, which is also the Hydra structured config of the ``calibration`` group
(``solderpyro/conf/calibration/default.yaml``).

>>> s = CalibrationSettings()                       # the defaults: the adaptive design
>>> s = CalibrationSettings(design=DesignSettings(budget=60), seed=3)
>>> s.validate()                                    # ValueError naming the bad field

From the command line the same fields are ``solderpyro calibrate --budget 60`` or, in the
Hydra scripts, ``calibration.design.budget=60``.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields
from typing import Any

from solderpyro.design.loop import LoopSettings

DesignSettings = LoopSettings

EXACT_MODES = ("auto", "on", "off")
#: the profile-likelihood intervals: auto computes them only where the FE-exact posterior is
#: not reliable (then they are the FE's own intervals, and the reported ones are widened to
#: hold them)
PROFILE_CI_MODES = ("auto", "on", "off")
DISCRETIZATION_MODES = ("correct", "check")


@dataclass
class SurrogateSettings:
    """The GP surrogate (:class:`~solderpyro.surrogate.GPSurrogate`); the ``surrogate``
    config group. ``inputs``: ``"raw"`` (the box's unit cube) or ``"flow_stress"`` (log flow
    stresses at ``inputs_T_C`` degC and ``inputs_rate`` 1/s replace s0 and Q/R).
    ``truncation``: a PCA surrogate keeps components until the variance they leave, summed
    over the observed values in noise variances, is at most ``truncation * sqrt(2 n)`` (a
    chi-square no added FE run could remove; see ``GPOptions.resid_chi2``). 0.01: on 54
    runs of the clean field case it keeps 19 components where 0.1 kept 13, and the
    surrogate's error at posterior draws ``|FE - surrogate|^2 / sigma^2`` falls 1.35 -> 0.06
    (most of it was the FE's part outside the kept components, which no GP learns);
    docs/design.md."""

    kernel: str = "matern52"
    ard: bool = True
    mean: str = "constant"
    output: str = "pca"
    inputs: str = "flow_stress"
    inputs_T_C: float = 125.0
    inputs_rate: float = 1e-5
    truncation: float = 0.01


@dataclass
class SamplerSettings:
    """NUTS (:func:`~solderpyro.calibration.mcmc.run_nuts`): the final posterior's length,
    and the shorter, warm-started runs of the design rounds, whose trees stop at
    ``round_max_depth`` (2^depth leapfrog steps): when the surrogate sharpens between rounds,
    the previous round's mass matrix is too wide for the new posterior until the warm-up's
    window re-estimates it, and full-depth trees then cost 1,023 gradients per iteration
    (208 s for one round on the full-field case). ``workers``: processes for the chains (0:
    one per core).

    ``draws`` 1500: with 1000 the hidden-effect recalibrations met the loop's bars (R-hat
    <= 1.01, bulk ESS >= 400 for every parameter) in only some runs (R-hat up to 1.016, min
    ESS 377); on the modulus field recalibration, paired on an idle machine, 1500 took min
    ESS 422 -> 782 and R-hat 1.007 -> 1.004 for 137 s instead of 120 s (BENCHMARKS.md, "The
    loop as a user runs it").

    ``final_ridge`` (default on): the final posterior in the ridge map's coordinates, as the
    design rounds are (:func:`~solderpyro.calibration.mcmc.ridge_map`; off: the sampler's own
    coordinates). Measured (``benchmarks/ridge_coords.py``, three seeds each), it depends on
    the posterior: on the loop's full-field recalibration the map takes 40 s
    against 83 s but diverges 52-160 times in 6,000 where the posterior's tail meets the Q/R
    face (own coordinates: 1) with min bulk ESS 409-732 against 775-1022; on the demo's
    8-value posterior the own coordinates diverge 13-68 times (map 7-41) and their min ESS
    fell to 249 (map 175-480), and the demo run with them ended at s0's ESS 54 and R-hat
    1.019 after 4 x 1500 draws (239 and 1.019 after running on to 4,500). An unreliable
    report is worse than a warned divergence count, so the map stays the default.

    ``final_accept`` 0.95: NUTS's target acceptance for the final posterior in ridge
    coordinates (the rounds keep :data:`~solderpyro.calibration.mcmc.MAPPED_ACCEPT`, 0.9).
    Same benchmark: on the loop's recalibration 30, 38 and 54 divergent with min ESS 742, 828
    and 507 in 55-63 s, against 52, 62 and 160, ESS 588, 732 and 409 in 40 s at 0.9; on the
    demo's 4, 4 and 1, ESS 733, 427 and 644 in 40-50 s, against 8, 41 and 7, ESS 431, 175 and
    480 in 30-40 s (seeds 0-2).

    ``min_ess`` (0: off): when the final posterior's smallest bulk ESS falls short of it, the
    chains run on from their last draws for the draws the shortfall asks for (at most twice
    ``draws``), once, with the adapted step and metric in the coordinates they sampled in
    (where the run kept no ridge map: a map fitted to their draws and a ``round_warmup``
    warm-up): the ridge map's min ESS was 175-732 over the two posteriors and six seeds above,
    with 4 x 1500 draws, against the loop's bar of 400 for every parameter (BENCHMARKS.md,
    "The loop as a user runs it"). ``max_rhat`` (1.01, the loop's bar; 0: off): the chains
    also run on, for at least half of ``draws``, when the largest R-hat is above it but at
    most :data:`~solderpyro.pipeline.posterior.RUN_ON_RHAT` (1.5; chains further apart sit in
    different places, and running on does not join them): without it the loop's
    recalibration can end at R-hat 1.011-1.012 on Q/R and m with every ESS above 400."""

    chains: int = 4
    warmup: int = 500
    draws: int = 1500
    round_warmup: int = 150
    round_draws: int = 200
    round_max_depth: int = 6
    workers: int = 0
    final_ridge: bool = True
    final_accept: float = 0.95
    min_ess: int = 400
    max_rhat: float = 1.01


@dataclass
class ExactSettings:
    """The FE-exact posterior (adaptive importance sampling with the FE in the likelihood)
    and the profile-likelihood intervals.

    ``mode``: ``"auto"`` runs them when the design stops on its budget with the FE still
    disagreeing with the surrogate; ``"on"`` always; ``"off"`` never. ``runs`` FE runs per
    round, ``rounds`` rounds and up to ``extra_rounds`` more while its weights are not
    reliable (ESS < 50 or Pareto k-hat > 0.7: a round of 64 runs costs far less than the
    profile intervals that would follow), a ``profile``-point chi-square profile along the
    ridge (0: none), ``profile_ci``: the 95 % profile-likelihood intervals through the FE after it:
    ``"auto"`` only where its posterior is not reliable (a reliable FE-exact posterior already
    gives the intervals; the profiles take many minutes of FE runs), ``"on"`` always,
    ``"off"`` never (true/false, as older run records hold it, read as on/off)."""

    mode: str = "auto"
    runs: int = 64
    rounds: int = 3
    extra_rounds: int = 3
    profile: int = 9
    profile_ci: str = "auto"


@dataclass
class CalibrationSettings:
    """How :func:`~solderpyro.pipeline.calibrate_specimen` runs.

    Attributes:
        design: the adaptive design (:class:`~solderpyro.design.loop.LoopSettings`): start,
            q per round, FE budget, criterion, stopping tolerances.
        surrogate: the GP. sampler: NUTS. exact: the FE-exact fallback.
        seed: of the design, the sampler and the predictive draws.
        store: the run store's directory (shared by calibrations of the same problem).
        batch: FE runs per batched solve. progress: progress bars (on a terminal).
        discretization: ``"correct"`` (default): before the final posterior, the FE's
            discretization error is estimated by one refinement (elements and time steps
            x1.5) at the last round's best checked draw and taken off the data (the FE's
            outputs, the store and the surrogate stay as they are); ``"check"``: only
            measured and reported after the posterior. Why: on field data from a finer FE
            the calibration FE's error (chi2 5.8 against the data-making FE at the truth)
            pushed the truths to and past the intervals' ends (Q/R, xi, s0 low); taken at
            one point of the posterior's ridge, the correction leaves chi2 0.001-0.004
            against the refined FE all along it (0.9-1.1 against the data-making FE: the
            x1.5 refinement's own error), and the truth's chi2 above the FE's best fit fell
            7.4 -> 4.9 (5.3 under the data-making FE itself) on the clean data
            (docs/calibration.md).
    """

    design: LoopSettings = field(default_factory=LoopSettings)
    surrogate: SurrogateSettings = field(default_factory=SurrogateSettings)
    sampler: SamplerSettings = field(default_factory=SamplerSettings)
    exact: ExactSettings = field(default_factory=ExactSettings)
    seed: int = 0
    store: str = "runs/store"
    batch: int = 64
    progress: bool = True
    discretization: str = "correct"

    def validate(self, dim: int = 4) -> CalibrationSettings:
        """Raise ``ValueError`` naming the first bad field; returns self."""
        self.design.validate(dim)
        sg = self.surrogate
        for nm, ok in (("kernel", ("gaussian", "matern52")), ("mean", ("constant", "linear")),
                       ("output", ("pca", "batched")), ("inputs", ("raw", "flow_stress"))):
            if getattr(sg, nm) not in ok:
                raise ValueError(f"surrogate.{nm} must be one of {ok}, got "
                                 f"{getattr(sg, nm)!r}")
        if not sg.truncation > 0:
            raise ValueError(f"surrogate.truncation must be > 0, got {sg.truncation}")
        sp = self.sampler
        for nm in ("chains", "warmup", "draws", "round_warmup", "round_draws",
                   "round_max_depth"):
            if getattr(sp, nm) < 1:
                raise ValueError(f"sampler.{nm} must be >= 1, got {getattr(sp, nm)}")
        if not 0.0 < sp.final_accept < 1.0:
            raise ValueError(f"sampler.final_accept must be in (0, 1), got {sp.final_accept}")
        if sp.min_ess < 0:
            raise ValueError(f"sampler.min_ess must be >= 0 (0: off), got {sp.min_ess}")
        if not (sp.max_rhat == 0 or sp.max_rhat > 1.0):
            raise ValueError(f"sampler.max_rhat must be > 1 (0: off), got {sp.max_rhat}")
        if not isinstance(sp.final_ridge, bool):
            raise ValueError(f"sampler.final_ridge must be true or false, got "
                             f"{sp.final_ridge!r}")
        if sp.workers < 0:
            raise ValueError(f"sampler.workers must be >= 0 (0: one per core), got "
                             f"{sp.workers}")
        ex = self.exact
        if ex.mode not in EXACT_MODES:
            raise ValueError(f"exact.mode must be one of {EXACT_MODES}, got {ex.mode!r}")
        if isinstance(ex.profile_ci, bool):
            ex.profile_ci = "on" if ex.profile_ci else "off"
        if ex.profile_ci not in PROFILE_CI_MODES:
            raise ValueError(f"exact.profile_ci must be one of {PROFILE_CI_MODES}, got "
                             f"{ex.profile_ci!r}")
        if ex.runs < 2 or ex.rounds < 1 or ex.profile < 0 or ex.profile == 1:
            raise ValueError(f"exact: need runs >= 2, rounds >= 1 and profile = 0 or >= 2, got "
                             f"runs={ex.runs}, rounds={ex.rounds}, profile={ex.profile}")
        if ex.extra_rounds < 0:
            raise ValueError(f"exact.extra_rounds must be >= 0, got {ex.extra_rounds}")
        if self.batch < 1:
            raise ValueError(f"batch must be >= 1, got {self.batch}")
        if self.discretization not in DISCRETIZATION_MODES:
            raise ValueError(f"discretization must be one of {DISCRETIZATION_MODES}, got "
                             f"{self.discretization!r}")
        return self

    def as_dict(self) -> dict[str, Any]:
        """Plain nested dict (for the run record, :class:`~solderpyro.config.rundir.RunInfo`)."""
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any] | None) -> CalibrationSettings:
        """From a nested mapping (e.g. an OmegaConf node turned into a dict); unknown keys are
        an error naming them."""
        d = dict(d or {})
        parts = {"design": LoopSettings, "surrogate": SurrogateSettings,
                 "sampler": SamplerSettings, "exact": ExactSettings}
        known = {f.name for f in fields(cls)}
        bad = sorted(set(d) - known)
        if bad:
            raise ValueError(f"unknown calibration settings {bad}; known: {sorted(known)}")
        kw: dict[str, Any] = {}
        for k, v in d.items():
            if k in parts:
                sub = dict(v or {})
                ok = {f.name for f in fields(parts[k])}
                badk = sorted(set(sub) - ok)
                if badk:
                    raise ValueError(f"unknown {k} settings {badk}; known: {sorted(ok)}")
                kw[k] = parts[k](**sub)
            else:
                kw[k] = v
        return cls(**kw)


def register_configs() -> None:
    """Register :class:`CalibrationSettings` with Hydra's ConfigStore as ``calibration/base``,
    so the ``calibration`` group is type-checked (``calibration.design.budget=abc`` fails
    with the field's name)."""
    from hydra.core.config_store import ConfigStore

    ConfigStore.instance().store(group="calibration", name="base", node=CalibrationSettings)
