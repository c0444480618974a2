"""Stage 3, the posterior: modular KOH through the surrogate, sampled with NUTS."""

from __future__ import annotations

import logging
import math
from typing import Any

from solderpyro.calibration import calibrate_emulator
from solderpyro.calibration.emulators import GPEmulator, ObservedEmulator
from solderpyro.calibration.mcmc import Posterior, WarmStart
from solderpyro.config.settings import SamplerSettings
from solderpyro.design.loop import Draws
from solderpyro.pipeline.problem import CalibrationProblem
from solderpyro.surrogate import GPSurrogate

log = logging.getLogger("solderpyro")


def nuts_options(s: SamplerSettings, seed: int, progress: bool, final: bool = True
                 ) -> dict[str, Any]:
    """Keyword arguments of :func:`~solderpyro.calibration.mcmc.run_nuts`: the full length
    when ``final``, else the design rounds' (never longer than the final one). Chains start
    at likelihood-resampled prior draws: the specimen posterior can have minor modes a random
    start never leaves. Each chain is one INFO log line with its time whatever ``progress``
    says (a line, not a bar: a log written to a file keeps it)."""
    del progress  # NUTS draws no bars; its per-chain lines are wanted in every log
    nk = dict(chains=s.chains, warmup=s.warmup if final else min(s.round_warmup, s.warmup),
              draws=s.draws if final else min(s.round_draws, s.draws), seed=seed,
              progress=True, init="sir", workers=s.workers or None)
    if not final:
        nk["max_tree_depth"] = s.round_max_depth
    elif not s.final_ridge:
        nk["ridge"] = "never"
    else:
        nk["mapped_accept"] = s.final_accept
    return nk


def sample_posterior(cp: CalibrationProblem, gp: GPSurrogate, s: SamplerSettings, seed: int,
                     warm: WarmStart | None = None, final: bool = True,
                     progress: bool = True) -> tuple[Posterior, Any]:
    """The modular KOH posterior of ``cp.space`` with ``gp`` as the code (its variance in the
    likelihood), observation-side effects added after it.

    Returns:
        ``(Posterior, ObsInputs)`` (the inputs feed the posterior predictive).
    """
    em: Any = GPEmulator(gp)
    off = cp.offset()
    if off is not None:
        em = ObservedEmulator(em, cp.n_fe, off)
    nk = nuts_options(s, seed, progress, final)
    if warm is not None:
        nk["warm"] = warm
    post, inp = calibrate_emulator(em, cp.y, cp.space, priors=cp.priors, **nk)
    if final and (s.min_ess > 0 or s.max_rhat > 0):
        post = reach_min_ess(post, s, lambda **kw: calibrate_emulator(
            em, cp.y, cp.space, priors=cp.priors, **{**nk, **kw})[0], seed)
    return post, inp


#: the largest R-hat at which the final chains run on (:func:`reach_min_ess`). Chains further
#: apart sit in separate places that running on does not join. Why 1.5, not the ridge map's
#: 1.1 (:data:`~solderpyro.calibration.mcmc.MAP_RHAT`): the islands a tighter bound guards
#: against (a misfitting base run, R-hat 2.8-3.1) are not sampled at full length, an island
#: only the surrogate fits is caught by the design's FE check in every chain, and slow mixing
#: in one broad posterior reaches 1.2-1.25 on point data (the demo: R-hat 1.227, min ESS 13;
#: run on: 1.024, 194, +3 s)
RUN_ON_RHAT = 1.5


def reach_min_ess(post: Posterior, s: SamplerSettings, run: Any, seed: int) -> Posterior:
    """``post``, or its chains run on once when its smallest bulk ESS is under
    ``s.min_ess`` or its largest R-hat over ``s.max_rhat``, and they are not apart (largest
    R-hat at most :data:`RUN_ON_RHAT`; see :class:`~solderpyro.config.settings.SamplerSettings`).

    Args:
        run: ``run(warm=, draws=, warmup=, ridge=, seed=) -> Posterior``, the same sampler
            call as the one that made ``post``.
    """
    rows = post.summary()
    ess = min(float(r["ess_bulk"]) for r in rows)
    rhat = max(float(r["r_hat"]) for r in rows)
    # chains far apart (R-hat above RUN_ON_RHAT: surrogate islands of a model that misfits)
    # are not helped by running on: on the loop's base run 3,000 more draws per chain left
    # its min ESS at 5 and cost 28 s
    short = s.min_ess > 0 and ess < s.min_ess
    split = s.max_rhat > 0 and rhat > s.max_rhat
    if not (short or split) or not rhat <= RUN_ON_RHAT:
        return post
    more = s.draws // 2 if split else 0
    if short:
        more = max(more, s.draws // 4,
                   math.ceil(s.draws * (1.1 * s.min_ess / max(ess, 1.0) - 1)))
    more = int(min(2 * s.draws, more))
    log.info("posterior: %s: the chains run on for %d more draws each",
             "; ".join(([f"smallest bulk ESS {ess:.0f} < {s.min_ess}"] if short else [])
                       + ([f"largest R-hat {rhat:.3f} > {s.max_rhat:g}"] if split else [])),
             more)
    # the adapted step and metric carry over as they are: in the sampler's own coordinates,
    # or in the ridge coordinates the chains sampled in (a plain continuation: refitting the
    # map to these draws and a 150-iteration warm-up to find its step cost 18 s of the loop's
    # recalibration, for 750 draws per chain); where the run kept no map,
    # a map fitted to these draws and a short warm-up
    same = s.final_ridge and post.warm is not None and post.warm.mapped is not None
    ridge = "same" if same else "auto" if s.final_ridge else "never"
    cont = run(warm=post.warm, draws=more, ridge=ridge, seed=seed + 7919,
               warmup=min(s.round_warmup, s.warmup) if ridge == "auto" else 0)
    out = post.extend(cont)
    rows = out.summary()
    log.info("posterior: smallest bulk ESS %.0f, largest R-hat %.3f after %d draws per chain",
             min(float(r["ess_bulk"]) for r in rows), max(float(r["r_hat"]) for r in rows),
             s.draws + more)
    return out


def as_draws(cp: CalibrationProblem, post: Posterior, inp: Any) -> Draws:
    """What the design loop needs of a posterior (FE parameters, sigma, offsets)."""
    t = post.flat("t").detach().to("cpu")
    return Draws(theta=t[:, :cp.n_fe], sigma=post.flat("sigma").detach().to("cpu"),
                 offset=cp.offsets(t), posterior=(post, inp), chains=post.n_chains)
