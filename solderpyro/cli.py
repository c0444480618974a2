"""Command-line interface: ``solderpyro <command> [options] [key=value ...]``.

Trailing ``key=value`` arguments are Hydra overrides of the packaged configs
(``solderpyro/conf``; e.g. ``mesh=fine specimen.plane=strain solver.device=cuda``);
``--config-dir DIR`` adds a directory of the user's own config groups.

Exit status: 0 done, 2 a usage error (a bad flag, flag value, config override or config value,
e.g. an unknown effect), 1 a failure of the computation (a data file it cannot use: malformed,
or binary where a text CSV is expected; a solve that fails); the message names the cause and
the file. Every heavy import (torch, the solver, Hydra) happens inside the command
that needs it, so ``--help`` and ``--version`` answer without loading them.
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path
from typing import Any

from solderpyro.version import __version__

log = logging.getLogger("solderpyro")

#: Commands whose model comes from the configs (they take overrides and ``--config-dir``).
CONFIG_COMMANDS = ("simulate", "demo", "calibrate", "sweep", "sensitivity", "predict")

#: The defaults the calibration flags' help shows, equal to the fields of
#: :class:`~solderpyro.config.settings.CalibrationSettings` (a test checks it): the settings
#: module imports the design loop and torch, which ``--help`` does not wait for.
HELP_DEFAULTS: dict[str, Any] = {
    "budget": None, "budget_base": 110, "budget_dims": 5, "start": 30, "batch": 8,
    "criterion": "loglik", "optimizer": "draws",
    "exact_mode": "auto", "exact_runs": 64, "exact_rounds": 3, "exact_profile": 9,
    "chains": 4, "warmup": 500, "draws": 1500}


class UsageError(Exception):
    """A bad command line (flag value, config override): exit status 2."""


def _usage(fn, *args, **kw):
    """``fn(*args, **kw)``, its ValueError (a bad value from the command line) re-raised as a
    :class:`UsageError`."""
    try:
        return fn(*args, **kw)
    except ValueError as e:
        raise UsageError(str(e)) from None


def _split_overrides(rest: list[str]) -> list[str]:
    bad = [a for a in rest if "=" not in a or a.startswith("-")]
    if bad:
        raise UsageError(f"unrecognized arguments {' '.join(bad)}: options are listed by "
                         f"'solderpyro COMMAND --help'; config overrides are key=value")
    return rest


def _no_overrides(command: str, overrides: list[str]) -> None:
    if overrides:
        raise UsageError(f"'{command}' takes no config overrides, got {overrides}")


def _need_file(flag: str, path, what: str = "file") -> None:
    """A path named on the command line must exist (before any computation): a missing one is
    a usage error naming the flag and the path."""
    p = Path(path)
    ok = p.is_dir() if what == "directory" else p.is_file()
    if not ok:
        raise UsageError(f"{flag}: no such {what}: {p}")


def _setup(overrides):
    """The typed setup of the composed configs; a bad override or config value (an unknown
    effect in ``effects=[...]``, a value outside its range) is a usage error."""
    from solderpyro.config.compose import build, compose

    return _usage(build, _usage(compose, overrides))


def simulate_table(setup, anand: dict, times, field: bool, progress: bool = True):
    """Run one parameter set: ``anand`` (name -> value; the others ``setup.anand``) at
    ``times`` (s), at A and B (and the 31 x 18 grid with ``field``).

    Returns:
        ``(times (n_time,) s, names (n_out,), coords (n_out, 2) mm, V (n_time, n_out) um)``.
    """
    from solderpyro.analysis.sensitivity import sensitivity_box
    from solderpyro.params import anand_tensor
    from solderpyro.specimen import SpecimenModel

    model = SpecimenModel(setup.problem, sensitivity_box(defaults=setup.anand), times, field,
                          dtype=setup.dtype, device=setup.device)
    p = anand_tensor(anand, base=setup.anand, dtype=setup.dtype, device=setup.device)[None]
    res = model.run(p, progress=progress)
    if not bool(res.ok.all()):
        raise RuntimeError(f"the FE solve failed: {res.reasons[0]}")
    return (res.times.cpu().numpy(), res.names, model.output_points.numpy(),
            res.V[0].detach().cpu().numpy())


def cmd_simulate(a, overrides) -> int:
    from solderpyro.config.compose import parse_times
    from solderpyro.io.measurements import from_arrays, write_measurements
    from solderpyro.params import parse_theta

    theta = _usage(parse_theta, a.theta) if a.theta else {}
    if a.noise is not None and not a.noise > 0:
        raise UsageError(f"--noise must be > 0 um, got {a.noise}")
    setup = _setup(overrides)
    times = _usage(parse_times, a.times) if a.times else setup.times
    import numpy as np

    t, names, pts, V = simulate_table(setup, theta, times, a.field, progress=not a.quiet)
    sigma = None
    if a.noise is not None:
        rng = np.random.default_rng(a.seed)
        V = V + a.noise * rng.standard_normal(V.shape)
        sigma = np.full(V.shape, a.noise)
    temps = np.array([setup.problem.cycle(x) for x in t])
    meta = {"generator": "solderpyro simulate", "theta": a.theta or "(config defaults)",
            "overrides": " ".join(overrides) or "(none)", "plane": setup.problem.plane,
            "noise_sigma_um": str(a.noise) if a.noise is not None else "0",
            "seed": str(a.seed)}
    m = from_arrays(t, names, pts, V, temperature_C=temps, sigma_um=sigma, meta=meta)
    out = Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    write_measurements(out, m)
    log.info("wrote %d values (%d times x %d points) to %s", V.size, len(t), len(names), out)
    return 0


def cmd_demo(a, overrides) -> int:
    import numpy as np

    from solderpyro.fem.loading import EXTENDED_TIMES
    from solderpyro.io.measurements import from_arrays, write_measurements

    setup = _setup(overrides)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    cyc = setup.problem.cycle
    marks = [x for x in EXTENDED_TIMES if x <= cyc.end]
    dense = sorted(set(np.arange(150.0, cyc.end + 1e-9, 150.0).tolist()) | set(marks))
    log.info("simulating the reference case with Liu 2008 constants (%d output times)",
             len(dense))
    t, names, pts, V = simulate_table(setup, {}, dense, field=False, progress=not a.quiet)
    temps = np.array([cyc(x) for x in t])
    write_measurements(out / "simulation.csv",
                       from_arrays(t, names, pts, V, temperature_C=temps,
                                   meta={"generator": "solderpyro demo",
                                         "anand": "Liu 2008 (seed Table IV)"}))
    from solderpyro.reporting.plots import plot_cycle

    fig = plot_cycle(t, V, names, temps, cyc, marks=marks)
    fig.savefig(out / "cycle.png", dpi=130)
    seed = [i for i, x in enumerate(t) if x in (600.0, 2700.0, 4800.0, 7800.0)]
    print("\nV relative to O at the seed points (a)-(d) that lie in the cycle, um:")
    print(f"{'time_s':>8} {'T_C':>6} " + " ".join(f"{n:>9}" for n in names))
    for i in seed:
        print(f"{t[i]:8.0f} {temps[i]:6.1f} " + " ".join(f"{v:9.4f}" for v in V[i]))
    print(f"\noutputs: {out / 'simulation.csv'}\nplot:    {out / 'cycle.png'}")
    if a.no_calibrate:
        return 0
    return _demo_calibration(a, setup, out, overrides)


#: The demo's documented truth (seed Table V medians, m moved inside the box's interior).
DEMO_TRUTH = {"s0": 12.92, "QR": 10586.0, "xi": 2.04, "m": 0.1}
DEMO_NOISE_UM = 0.05


def _demo_calibration(a, setup, out: Path, overrides=()) -> int:
    """Synthetic measurements at DEMO_TRUTH (+ N(0, 0.05^2) um) -> calibrate -> report."""
    import numpy as np

    from solderpyro.io.measurements import from_arrays, write_measurements
    from solderpyro.pipeline import calibrate_specimen

    log.info("demo calibration: synthetic data at %s with noise %.2g um", DEMO_TRUTH,
             DEMO_NOISE_UM)
    t, names, pts, V = simulate_table(setup, DEMO_TRUTH, setup.times, field=False,
                                      progress=False)
    rng = np.random.default_rng(a.seed)
    V = V + DEMO_NOISE_UM * rng.standard_normal(V.shape)
    temps = np.array([setup.problem.cycle(x) for x in t])
    meta = {"generator": "solderpyro demo", "truth": str(DEMO_TRUTH),
            "noise_sigma_um": str(DEMO_NOISE_UM), "seed": str(a.seed)}
    data = out / "data.csv"
    write_measurements(data, from_arrays(t, names, pts, V, temperature_C=temps,
                                         sigma_um=np.full(V.shape, DEMO_NOISE_UM), meta=meta))
    from solderpyro.io.measurements import read_measurements

    a.store = out / "store"
    res = calibrate_specimen(setup, read_measurements(data), out / "calibration",
                             _settings(a, setup, overrides))
    from solderpyro.calibration.intervals import reported_interval

    inside = {}
    for r in res.summary:
        if r["parameter"] in DEMO_TRUTH:
            lo, hi = reported_interval(r)
            inside[r["parameter"]] = lo <= DEMO_TRUTH[str(r["parameter"])] <= hi
    print(f"\ntruth {DEMO_TRUTH}; inside the 95 % interval: {inside}")
    print(f"report:  {res.out / 'report.html'}")
    return 0


def _nuts_args(a) -> dict:
    return dict(chains=a.chains, warmup=a.warmup, draws=a.draws, seed=a.seed,
                progress=not a.quiet)


def cmd_example(a, overrides) -> int:
    _no_overrides("example", overrides)
    from solderpyro.examples import seed_math

    res = seed_math.run(a.out, **_nuts_args(a))
    print(seed_math.report(res))
    print(f"\noutputs in {a.out}")
    return 0


def cmd_koh(a, overrides) -> int:
    _no_overrides("koh", overrides)
    if a.mode not in ("joint", "modular"):
        raise UsageError(f"--mode must be 'joint' or 'modular', got {a.mode!r}")
    _need_file("--sim", a.sim, "SIM file")
    _need_file("--obs", a.obs, "OBS file")
    from solderpyro.calibration.tables import RunTables, koh_from_tables

    koh_from_tables(RunTables(a.sim, a.obs, _names(a.x), _names(a.t), a.y), a.out, mode=a.mode,
                    discrepancy=a.discrepancy, propose=a.propose, **_nuts_args(a))
    print(f"\nsummary: {Path(a.out) / 'summary.csv'}")
    print(f"index:   {Path(a.out) / 'index.html'} (open in a browser)")
    return 0


def _settings(a, setup, overrides=()):
    """The calibration's settings: the composed config's ``calibration`` group (so that
    ``calibration.design.code_tol=...`` and the other overrides take effect), its surrogate
    from the config's surrogate group, then every command-line flag that differs from its
    default (a flag given at its default leaves the config's value)."""
    import dataclasses

    from solderpyro.config.compose import calibration_settings, compose
    from solderpyro.config.settings import CalibrationSettings, SurrogateSettings

    s = calibration_settings(_usage(compose, list(overrides)))
    s.surrogate = SurrogateSettings(**setup.surrogate)
    d0 = CalibrationSettings()

    def flag(value, default, part, field):
        if value is not None and value != default:
            setattr(part, field, value)

    ds, sp, ex = s.design, s.sampler, s.exact
    flag(a.start, None, ds, "start")
    flag(a.q, d0.design.batch, ds, "batch")
    flag(a.criterion, d0.design.criterion, ds, "criterion")
    flag(a.optimizer, d0.design.optimizer, ds, "optimizer")
    if a.budget is not None:
        ds.budget = a.budget
    elif a.start is not None and ds.budget is not None:  # a larger start moves a set budget
        ds.budget = max(ds.budget, ds.start + ds.check)
    flag(a.chains, d0.sampler.chains, sp, "chains")
    flag(a.warmup, d0.sampler.warmup, sp, "warmup")
    flag(a.draws, d0.sampler.draws, sp, "draws")
    flag(a.exact, d0.exact.mode, ex, "mode")
    flag(a.exact_runs, d0.exact.runs, ex, "runs")
    flag(a.exact_rounds, d0.exact.rounds, ex, "rounds")
    flag(a.exact_profile, d0.exact.profile, ex, "profile")
    if a.no_profile_ci:
        ex.profile_ci = "off"
    elif a.profile_ci:
        ex.profile_ci = "on"
    top = {"seed": a.seed, "store": str(a.store), "batch": a.batch}
    s = dataclasses.replace(s, **{k: v for k, v in top.items()
                                  if v != getattr(d0, k)},
                            progress=not getattr(a, "quiet", False))
    return s


def cmd_calibrate(a, overrides) -> int:
    from solderpyro.io.measurements import read_measurements
    from solderpyro.pipeline import calibrate_specimen
    from solderpyro.specimen import output_points

    _need_file("--data", a.data, "measurement file")
    if a.warm_from:
        _need_file("--warm-from", a.warm_from, "directory")
    setup = _setup(overrides)
    meas = read_measurements(a.data, valid_points=output_points(setup.problem))
    s = _settings(a, setup, overrides)
    _usage(s.validate, setup.space.dim)
    warm = None
    if a.warm_from:
        from solderpyro.pipeline.warm import warm_start

        warm = warm_start(a.warm_from, setup.effects)
    res = calibrate_specimen(setup, meas, a.out, s,
                             record={"overrides": list(overrides), "data": str(a.data)},
                             warm=warm)
    print(f"\ndesign: {res.design['message'] if res.design else ''}")
    print(f"report:  {res.out / 'report.html'}\nsummary: {res.out / 'summary.csv'}")
    print(f"index:   {res.out / 'index.html'} (open in a browser)")
    return 0


def cmd_sweep(a, overrides) -> int:
    import glob

    from solderpyro.compute.executor import current_executor
    from solderpyro.compute.sweep import calibrate_job, sweep

    files = sorted({f for pat in a.data for f in (glob.glob(pat) or [pat])})
    missing = [f for f in files if not Path(f).is_file()]
    if missing:
        raise UsageError(f"--data: no such measurement file(s): {', '.join(missing)}")
    stems = [Path(f).stem for f in files]
    if len(set(stems)) != len(stems):
        raise UsageError(f"--data: file names must differ (each names its run directory), "
                         f"got {stems}")
    out = Path(a.out)
    store = str(Path(a.store).resolve())
    extra = [*a.args.split(), *overrides]
    by_stem = dict(zip(stems, files, strict=True))

    def job(stem: str) -> dict:
        return calibrate_job(str(Path(by_stem[stem]).resolve()),
                             str((out / stem).resolve()), store, extra)

    res = sweep(stems, job, out / "sweep.json", current_executor())
    print(f"\n{'dataset':<24} {'ok':<4} {'wall_s':>8}  design / FE check")
    for k, r in res.items():
        info = (f"{r['design']['reason']} ({r['design']['fe_runs']} FE runs); FE check "
                f"{r['fe_check_rms_sd']:.2f} sd" if r.get("ok") else r.get("error", ""))
        ok = "yes" if r.get("ok") else "NO"
        print(f"{k:<24} {ok:<4} {r.get('wall_s', 0):8.0f}  {info}")
    print(f"\nrecord: {out / 'sweep.json'}")
    return 0 if all(r.get("ok") for r in res.values()) else 1


def cmd_diagnose(a, overrides) -> int:
    if overrides:
        raise UsageError(f"'diagnose' takes no config overrides (the run's own are used), "
                         f"got {overrides}")
    if a.draws < 1:
        raise UsageError(f"--draws must be >= 1, got {a.draws}")
    _need_file("RUN_DIR", Path(a.run_dir) / "run.json", "run record (not a run directory)")
    from solderpyro.diagnose import diagnose
    from solderpyro.diagnose.decide import share_text
    from solderpyro.diagnose.load import candidate_effects

    cands = tuple(_names(a.effects)) if a.effects else None
    if cands:  # the names, before the run is loaded: an unknown one is a usage error
        try:
            candidate_effects((), cands)
        except ValueError as e:
            raise UsageError(f"--effects: {e}") from None
    dg = diagnose(a.run_dir, candidates=cands, n_draws=a.draws, seed=a.seed,
                  progress=not a.quiet, refit=not a.no_refit)
    print(f"\nverdict: {dg.verdict}\n")
    print(f"{'effect':26s} {'LR/score':>10s} {'dof':>4s} {'RMS after':>10s} {'systematic':>10s}"
          f" {'floor':>6s}  flagged  refit")
    for r in dg.ranking + dg.failed:
        print(f"{r['effect']:26s} {r['statistic']:10.1f} {r['dof']:4d} "
              f"{r['rms_after_sd']:7.2f} sd {share_text(r['systematic_share']):>10s} "
              f"{'clears' if r['clears_floor'] else 'below':>6s}  "
              f"{'yes' if r['flagged'] else '':7s}  {r['refit']}")
    for s in dg.suggestions:
        print(f"suggestion: {s}")
    print(f"\ndiagnosis: {Path(a.run_dir) / 'diagnosis.json'} and diagnosis.html")
    print(f"index:     {Path(a.run_dir) / 'index.html'} (open in a browser)")
    return 0


def _point(spec: str) -> tuple[str, tuple[float, float]]:
    """``--point [NAME=]X,Y`` (mm) -> ``(name, (x, y))``."""
    name, _, xy = spec.rpartition("=")
    try:
        x, y = (float(v) for v in xy.split(","))
    except ValueError:
        raise UsageError(f"--point must be [NAME=]X,Y in mm, got {spec!r}") from None
    return (name or f"({x:g}, {y:g})"), (x, y)


def cmd_predict(a, overrides) -> int:
    if a.draws < 1:
        raise UsageError(f"--draws must be >= 1, got {a.draws}")
    _need_file("RUN_DIR", Path(a.run_dir) / "run.json", "run record (not a run directory)")
    points = dict(_point(p) for p in a.point) if a.point else None
    from solderpyro.config.compose import build, compose
    from solderpyro.config.rundir import RunDir

    info = RunDir.read(a.run_dir, ("run.json",)).info
    _usage(build, _usage(compose, [*info.overrides, *overrides]))  # a bad override: exit 2
    from solderpyro.predict import predict

    if a.layer_mm is not None and not a.layer_mm > 0:
        raise UsageError(f"--layer-mm must be > 0 mm, got {a.layer_mm}")
    pred = predict(a.run_dir, overrides, n_draws=a.draws, points=points, out=a.out,
                   progress=not a.quiet, layer_mm=a.layer_mm)
    out = Path(a.out) if a.out else Path(a.run_dir) / "prediction"
    n_c = len(pred.cycle_ends)
    print(f"\nthe solder over {len(pred.fields.ok)} posterior draws, cycle {n_c} of {n_c} "
          f"(median [95 % band], share of the band from the constants):")
    for (q, r, c), b in pred.bands.items():
        if c in (n_c, 0) and r in ("upper_interface", "lower_interface", "max"):
            share = (f"{100 * b.constants_share:5.1f} %" if b.constants_share == b.constants_share
                     else "  n/a (too few draws)")
            print(f"  {q:9s} {r:16s} {b.median:10.4g} [{b.lo:.4g}, {b.hi:.4g}]  {share}")
    for n in pred.notes:
        print(f"note: {n}")
    print(f"\ntable:  {out / 'prediction.csv'}\nindex:  {out / 'index.html'} (open in a "
          "browser)")
    return 0


def cmd_sensitivity(a, overrides) -> int:
    from solderpyro.analysis.sensitivity import (
        SensitivitySettings,
        parse_bounds,
        run_sensitivity,
    )
    from solderpyro.config.compose import parse_times

    bounds = _usage(parse_bounds, a.box)
    setup = _setup(overrides)
    times = _usage(parse_times, a.times) if a.times else setup.times
    cmd = " ".join(["solderpyro sensitivity", "--out", str(a.out), "--runs", str(a.runs),
                    "--grad-points", str(a.grad_points), "--seed", str(a.seed),
                    *(["--times", a.times] if a.times else []),
                    *(["--box", a.box] if a.box else []), *overrides])
    settings = SensitivitySettings(n_runs=a.runs, grad_points=a.grad_points,
                                   grad_batch=a.grad_batch, times=times, store_root=a.store,
                                   seed=a.seed, n_sobol=a.sobol_samples, n_boot=a.bootstrap,
                                   bounds=bounds, batch_size=a.batch, refits=a.refits,
                                   progress=not a.quiet)
    res = run_sensitivity(setup, a.out, settings, command=cmd)
    print(f"\n{'parameter':>9} {'DGSM':>9} {'S1':>7} {'ST':>7} {'ST 95 %':>15} rank")
    for r in sorted(res.rows, key=lambda r: r["rank"]):
        print(f"{r['parameter']:>9} {r['dgsm']:9.3g} {r['S1']:7.3f} {r['ST']:7.3f} "
              f"[{r['ST_lo']:5.3f}, {r['ST_hi']:5.3f}] {r['rank']:4d}")
    print(f"\n{res.verdict['text']}\nreport: {res.out / 'sensitivity.md'}")
    return 0


def cmd_compare(a, overrides) -> int:
    _no_overrides("compare", overrides)
    from solderpyro.diagnose.compare import compare

    r = compare(a.before, a.after, a.out)
    print(f"RMS residual {r['before']['rms_um']:.4g} -> {r['after']['rms_um']:.4g} um; "
          f"ELPD {r['before']['elpd']:.2f} -> {r['after']['elpd']:.2f} "
          f"(gain {r['elpd_gain']:.2f} +- {r['elpd_gain_se']:.2f} nats, "
          f"{r['after']['elpd_method']})")
    for w in r["warnings"]:
        print(f"warning: {w}")
    print(f"comparison: {Path(a.out or a.after) / 'comparison.md'}")
    print(f"index:      {Path(a.out or a.after) / 'index.html'} (open in a browser)")
    return 0


def _names(text: str) -> list[str]:
    return [n.strip() for n in text.split(",") if n.strip()]


def _common() -> argparse.ArgumentParser:
    """``-q`` / ``-v``, accepted before the command and after it (defaults suppressed, so a
    sub-command's absent flag does not undo the main parser's)."""
    c = argparse.ArgumentParser(add_help=False)
    g = c.add_mutually_exclusive_group()
    g.add_argument("-q", "--quiet", action="store_true", default=argparse.SUPPRESS,
                   help="warnings and errors only, no progress bars")
    g.add_argument("-v", "--verbose", action="store_true", default=argparse.SUPPRESS,
                   help="debug logging")
    return c


def _add_config_dir(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config-dir", default=None, metavar="DIR",
                   help="a directory of your own config groups, searched after the packaged "
                   "ones (e.g. DIR/mesh/mine.yaml, selected by mesh=mine; docs/configuration.md, "
                   "'Your own specimen, alloy and cycle')")


def _add_nuts(p: argparse.ArgumentParser, chains: int = 4, draws: int = 1000,
              warmup: int = 500) -> None:
    p.add_argument("--seed", type=int, default=0, help="random seed (data and sampler)")
    p.add_argument("--chains", type=int, default=chains, help="NUTS chains")
    p.add_argument("--warmup", type=int, default=warmup, help="warm-up iterations per chain")
    p.add_argument("--draws", type=int, default=draws, help="kept draws per chain")


def _add_design(p: argparse.ArgumentParser) -> None:
    """The adaptive design's and the FE-exact fallback's options (calibrate, demo)."""
    d = HELP_DEFAULTS
    p.add_argument("--budget", type=int, default=None, metavar="N",
                   help=f"most FE runs the adaptive design makes (default {d['budget_base']} up to "
                   f"{d['budget_dims']} FE parameters, and one round of runs more for each "
                   "parameter past them): a "
                   "Latin-hypercube start, then rounds of acquired runs and FE checks at "
                   "posterior draws until the FE confirms the surrogate. Each round's runs are "
                   "the posterior draws where the surrogate's code uncertainty matters most, "
                   "chosen by a closed-form greedy selection (design/acquisition.py): the same "
                   "batch as BoTorch's optimize_acqf_discrete, ~40x faster "
                   "(benchmarks/results/acquisition_optimizers.json)")
    p.add_argument("--start", type=int, default=None, metavar="N",
                   help=f"Latin-hypercube FE runs before the first round (default {d['start']})")
    p.add_argument("--q", type=int, default=d["batch"],
                   help=f"FE runs acquired per round, one batched solve (default {d['batch']})")
    p.add_argument("--criterion", default=d["criterion"], choices=["loglik", "variance"],
                   help="acquisition: loglik (posterior-weighted code variance of the "
                   "log-likelihood, default) or variance (the integrated posterior variance "
                   "at the observed outputs, BoTorch's qNegIntegratedPosteriorVariance)")
    p.add_argument("--optimizer", default=d["optimizer"], choices=["draws", "optimize"],
                   help="draws: the best q of the posterior draws, closed-form greedy "
                   "(default); optimize: BoTorch's optimize_acqf over the box (minutes per "
                   "round)")
    p.add_argument("--batch", type=int, default=64, help="FE runs per batched solve")
    p.add_argument("--exact", default=d["exact_mode"], choices=["auto", "on", "off"],
                   help="the FE-exact posterior (adaptive importance sampling with the FE in "
                   "the likelihood) and profile-likelihood intervals: auto (default) runs them "
                   "when the design's budget runs out with the FE disagreeing with the "
                   "surrogate; on: always; off: never")
    p.add_argument("--exact-runs", type=int, default=d["exact_runs"], metavar="N",
                   help=f"FE runs per importance-sampling round (default {d['exact_runs']})")
    p.add_argument("--exact-rounds", type=int, default=d["exact_rounds"], metavar="R",
                   help=f"importance-sampling rounds (default {d['exact_rounds']})")
    p.add_argument("--exact-profile", type=int, default=d["exact_profile"], metavar="G",
                   help=f"grid points of the chi-square profile along the ridge (default "
                   f"{d['exact_profile']}; 0: none)")
    p.add_argument("--no-profile-ci", action="store_true",
                   help="skip the 95 %% profile-likelihood intervals after the FE-exact step")
    p.add_argument("--profile-ci", action="store_true",
                   help="compute them even where the FE-exact posterior is reliable (by "
                   "default only where it is not: they take many minutes of FE runs)")


def _add_cluster(p: argparse.ArgumentParser) -> None:
    """``--cluster`` / ``--scheduler``: where FE batches (or sweep jobs) run."""
    g = p.add_mutually_exclusive_group()
    g.add_argument("--cluster", default=None, metavar="local:N",
                   help="run FE batches on a Dask LocalCluster of N single-threaded worker "
                        "processes (default: in this process)")
    g.add_argument("--scheduler", default=None, metavar="tcp://HOST:PORT",
                   help="run FE batches on a running Dask cluster (e.g. dask_jobqueue's "
                        "SLURMCluster; see docs/scaling.md); the run store must be on a "
                        "filesystem the workers share")


def build_parser() -> argparse.ArgumentParser:
    """The whole command line; building it imports nothing heavy (torch, Hydra, the solver)."""
    common = _common()
    p = argparse.ArgumentParser(
        prog="solderpyro", parents=[common],
        description="Bayesian identification of Anand solder constants from Moire data. "
                    "Trailing key=value arguments override the packaged configs (Hydra "
                    "syntax), e.g. mesh=fine specimen.plane=strain solver.device=cuda; "
                    "--config-dir DIR adds your own. Exit status: 0 done, 2 usage error, "
                    "1 failure of the computation.")
    p.add_argument("--version", action="version", version=f"solderpyro {__version__}")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for add in (_add_simulate_command, _add_demo_command, _add_example_command,
                _add_koh_command, _add_calibrate_command, _add_sweep_command,
                _add_diagnose_command, _add_sensitivity_command, _add_compare_command,
                _add_predict_command):
        add(sub, common)
    return p


def _add_simulate_command(sub: argparse._SubParsersAction, common) -> None:
    """The ``simulate`` sub-command's arguments (the FE model for one parameter set)."""
    s = sub.add_parser("simulate", parents=[common], help="run the FE model for one parameter "
                       "set and write the measurement CSV (docs/data-format.md)")
    s.add_argument("--theta", default="", help="Anand constants, e.g. s0=12.9,QR=10586,xi=2.04,"
                   "m=0.2 (names: s0, QR, A, xi, m, h0, s_hat, n, a; others from the config)")
    s.add_argument("--times", default=None, help="seed (600,2700,4800,7800 s) | extended "
                   "(+ dwell ends) | t1,t2,... in s (default: config loading.output_times)")
    s.add_argument("--field", action="store_true",
                   help="also write V on the 31 x 18 grid of the reference case "
                   "(docs/configuration.md)")
    s.add_argument("--noise", type=float, default=None,
                   help="add Gaussian noise with this standard deviation, um")
    s.add_argument("--seed", type=int, default=0, help="random seed of the noise")
    s.add_argument("--out", required=True, help="output CSV path")
    _add_config_dir(s)


def _add_demo_command(sub: argparse._SubParsersAction, common) -> None:
    """The ``demo`` sub-command's arguments (the reference case and its synthetic-data
    calibration)."""
    d = sub.add_parser("demo", parents=[common], help="the whole workflow on the reference "
                       "case: simulate it with the Liu 2008 constants (outputs and a plot of "
                       "V_A, V_B and temperature), then calibrate s0, QR, xi, m against "
                       "synthetic measurements made at known constants (adaptive FE design, "
                       "KOH with NUTS, report) and say whether the 95 %% intervals hold them "
                       "(minutes; --no-calibrate: the simulation only)")
    d.add_argument("--out", default="runs/demo", help="output directory")
    d.add_argument("--no-calibrate", action="store_true",
                   help="only simulate (skip the synthetic-data calibration)")
    _add_design(d)
    # the calibration's own sampler defaults (4 x 1500 draws after 500 warm-up): with 400
    # draws its report said R-hat 1.02 > 1.01, "not reliable until a longer run"; the
    # design's rounds leave it ~90 s in all
    _add_nuts(d, draws=HELP_DEFAULTS["draws"], warmup=HELP_DEFAULTS["warmup"])
    _add_config_dir(d)


def _add_example_command(sub: argparse._SubParsersAction, common) -> None:
    """The ``example`` sub-command's arguments (the worked examples)."""
    e = sub.add_parser("example", parents=[common], help="worked examples; 'seed-math' "
                       "reproduces the seed paper's mathematical example (Tables I, II, "
                       "Figures 1-4)")
    e.add_argument("name", choices=["seed-math"])
    e.add_argument("--out", required=True, help="output directory")
    _add_nuts(e)


def _add_koh_command(sub: argparse._SubParsersAction, common) -> None:
    """The ``koh`` sub-command's arguments (Kennedy-O'Hagan calibration from CSV tables)."""
    k = sub.add_parser("koh", parents=[common], help="Kennedy-O'Hagan calibration of any "
                       "simulator from CSV tables of its runs and of the observations")
    k.add_argument("--sim", required=True, help="CSV of runs: columns x..., t..., y")
    k.add_argument("--obs", required=True, help="CSV of observations: columns x..., y")
    k.add_argument("--x", default="", help="controllable input columns, e.g. x1,x2")
    k.add_argument("--t", required=True, help="calibration input columns, e.g. t1,t2")
    k.add_argument("--y", required=True, help="output column")
    k.add_argument("--out", required=True, help="output directory")
    k.add_argument("--mode", default="joint", help="joint (seed, Eq. 5-8) | modular")
    k.add_argument("--discrepancy", action="store_true", help="add a GP discrepancy delta(x)")
    k.add_argument("--propose", type=int, default=0, metavar="Q",
                   help="also write the next Q parameter sets for your simulator to "
                   "OUT/proposed.csv: posterior draws where the surrogate's code variance at "
                   "the observed x matters most for the posterior (the GP's variance at the "
                   "observed x and posterior draws, averaged, computed in closed form; sets "
                   "chosen one at a time); one row per run to make, each set at "
                   "every distinct observed x (replicates share a run). Append their results to "
                   "--sim and call again; sets still pending (OUT/pending.csv) are not "
                   "proposed twice")
    _add_nuts(k)


def _add_calibrate_command(sub: argparse._SubParsersAction, common) -> None:
    """The ``calibrate`` sub-command's arguments (the specimen calibration)."""
    c = sub.add_parser("calibrate", parents=[common], help="calibrate the Anand constants of "
                       "the config's box (default s0, QR, xi, m) against a measurement CSV: an "
                       "adaptive design of FE runs (run store) that stops when the FE confirms "
                       "the GP surrogate, KOH with NUTS, report")
    c.add_argument("--data", required=True, help="measurement CSV (docs/data-format.md); "
                   "points A, B or grid labels g_ii_jj, any output times")
    c.add_argument("--out", required=True,
                   help="run directory (report.html, report.md, summary.csv, ...)")
    c.add_argument("--warm-from", default=None, metavar="RUN_DIR",
                   help="start NUTS from an earlier calibration's adapted state (its chains' "
                   "last positions and mass matrix, matched by parameter name), e.g. the base "
                   "run when recalibrating with one more effect")
    c.add_argument("--store", default="runs/store", help="run store directory (reused runs)")
    _add_cluster(c)
    _add_design(c)
    _add_nuts(c, draws=HELP_DEFAULTS["draws"])
    _add_config_dir(c)


def _add_sweep_command(sub: argparse._SubParsersAction, common) -> None:
    """The ``sweep`` sub-command's arguments (many calibrations on a Dask cluster)."""
    w = sub.add_parser("sweep", parents=[common], help="calibrate many datasets, one job each, "
                       "in parallel on a Dask cluster (--cluster local:N) or one after "
                       "another; each dataset's run directory is OUT/<file stem>, results "
                       "recorded in OUT/sweep.json as each job ends (a rerun skips finished "
                       "ones)")
    w.add_argument("--data", nargs="+", required=True, metavar="CSV",
                   help="measurement CSVs or glob patterns")
    w.add_argument("--out", required=True, help="output directory")
    w.add_argument("--store", default="runs/store", help="run store shared by the jobs")
    w.add_argument("--args", default="", help="extra 'solderpyro calibrate' options for every "
                   "job, e.g. \"--budget 80 --chains 2\"")
    _add_cluster(w)
    _add_config_dir(w)


def _add_diagnose_command(sub: argparse._SubParsersAction, common) -> None:
    """The ``diagnose`` sub-command's arguments (model checks and candidate effects of a
    run)."""
    g = sub.add_parser("diagnose", parents=[common], help="does the calibrated model fit the "
                       "data, and which physical effect is missing? Posterior predictive "
                       "checks, a misfit test and a score test per candidate effect through the "
                       "FE; writes RUN_DIR/diagnosis.json, diagnosis.md/.html and figures")
    g.add_argument("run_dir", help="a run directory written by 'solderpyro calibrate'")
    g.add_argument("--effects", default="", help="comma-separated candidate effects (default: "
                   "every effect the run did not switch on)")
    g.add_argument("--draws", type=int, default=3, help="posterior draws at which the FE and "
                   "its finite-difference Jacobians are evaluated (the first is the draw "
                   "nearest the posterior median)")
    g.add_argument("--seed", type=int, default=0, help="random seed (draw choice, replicates)")
    g.add_argument("--no-refit", action="store_true", help="test at the posterior draw itself, "
                   "not at the FE's best fit started from it (Levenberg-Marquardt, ~8 FE "
                   "solves)")
    _add_cluster(g)


def _add_predict_command(sub: argparse._SubParsersAction, common) -> None:
    """The ``predict`` sub-command's arguments (the solder's fields at posterior draws)."""
    p = sub.add_parser("predict", parents=[common], help="stresses, inelastic strains and the "
                       "inelastic strain energy density per cycle in the solder, with 95 %% "
                       "bands, from a calibration's posterior; on its own specimen and cycle, "
                       "or on another assembly and cycle given as config overrides (e.g. "
                       "specimen=die_attach mesh=die_attach loading=jedec_m40_125); writes "
                       "RUN_DIR/prediction/ (CSV, ArviZ, figures, index.html)")
    p.add_argument("run_dir", help="a run directory written by 'solderpyro calibrate'")
    p.add_argument("--draws", type=int, default=200, help="posterior draws to solve, spread "
                   "evenly through the run's draws (default 200)")
    p.add_argument("--point", action="append", default=[], metavar="[NAME=]X,Y",
                   help="a history point in the solder, mm (repeatable; default: the free "
                   "end on the upper interface and at mid-thickness, and mid-length)")
    p.add_argument("--layer-mm", type=float, default=None, help="thickness of the interface "
                   "layers the inelastic work is averaged over, mm (default: a quarter of the "
                   "solder's thickness)")
    p.add_argument("--out", default=None, help="output directory (default RUN_DIR/prediction;"
                   " its fields/ keeps the solved draws, which a rerun reads)")
    _add_config_dir(p)
    _add_cluster(p)


def _add_sensitivity_command(sub: argparse._SubParsersAction, common) -> None:
    """The ``sensitivity`` sub-command's arguments (the Anand constants ranked by influence)."""
    v = sub.add_parser("sensitivity", parents=[common], help="rank the nine Anand constants "
                       "by their influence on V_A, V_B over a prior box: DGSM through the FE "
                       "(autograd) and Sobol main/total indices through a GP surrogate; writes "
                       "sensitivity.csv/.json/.png/.md")
    v.add_argument("--out", required=True, help="output directory")
    v.add_argument("--runs", type=int, default=100, help="LHS FE runs for the GP surrogate "
                   "(>= 10; kept in the run store)")
    v.add_argument("--grad-points", type=int, default=32, help="LHS points of the DGSM, each "
                   "an FE solve with autograd (>= 2)")
    v.add_argument("--grad-batch", type=int, default=16, help="members per autograd FE solve "
                   "(memory: ~0.5 GB per member on the default mesh)")
    v.add_argument("--times", default=None, help="seed (600,2700,4800,7800 s) | extended "
                   "(+ dwell ends) | t1,t2,... in s (default: config loading.output_times)")
    v.add_argument("--store", default="runs/store", help="run store directory (reused runs)")
    v.add_argument("--seed", type=int, default=0, help="seed of the designs, the Sobol "
                   "scrambling and the bootstrap")
    v.add_argument("--sobol-samples", type=int, default=8192, help="Sobol base sample on the "
                   "GP mean (power of two; (9 + 2) x this many GP evaluations)")
    v.add_argument("--bootstrap", type=int, default=200, help="bootstrap resamples for the "
                   "intervals (>= 10)")
    v.add_argument("--box", default="", help="override bounds of the nine-constant box, e.g. "
                   "A=1e5:1e8,h0=500:3000 (defaults: docs/sensitivity.md)")
    v.add_argument("--refits", type=int, default=5, help="GP refits, each without 1/REFITS "
                   "of the runs, for the surrogate's standard error of S_T (0: none)")
    v.add_argument("--batch", type=int, default=64, help="FE runs per batched DOE solve")
    _add_cluster(v)
    _add_config_dir(v)


def _add_compare_command(sub: argparse._SubParsersAction, common) -> None:
    """The ``compare`` sub-command's arguments (before/after of two calibrations)."""
    q = sub.add_parser("compare", parents=[common], help="before/after of two calibrations on "
                       "the same data (e.g. without and with effects=[NAME]): RMS residual, "
                       "misfit, ELPD, posterior shifts; writes comparison.md/.json")
    q.add_argument("before", help="run directory of the first calibration")
    q.add_argument("after", help="run directory of the second calibration")
    q.add_argument("--out", default=None, help="where to write (default: AFTER)")


def _setup_logging(a: argparse.Namespace) -> None:
    """solderpyro's INFO lines (WARNING and above with ``-q``, DEBUG with ``-v``); other
    packages' loggers from WARNING only (no ``arviz.preview`` chatter). ``a.quiet`` then means
    "no progress bars": set by ``-q``, and implied when ``sys.stderr`` is not a TTY (into a
    file or a pipe the log is one line per stage or NUTS chain, with its time)."""
    import warnings

    a.quiet = bool(getattr(a, "quiet", False))
    a.verbose = bool(getattr(a, "verbose", False))
    level = logging.DEBUG if a.verbose else logging.WARNING if a.quiet else logging.INFO
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    logging.getLogger("solderpyro").setLevel(level)
    warnings.filterwarnings("ignore", category=FutureWarning, module="arviz")
    if not sys.stderr.isatty():
        a.quiet = True


#: Failures of the computation (exit 1); anything else is a bug and keeps its traceback.
FAILURES = (ValueError, OSError, RuntimeError, ConnectionError)


def main(argv: list[str] | None = None) -> int:
    """Run the command line ``argv`` (default ``sys.argv[1:]``); returns the exit status."""
    parser = build_parser()
    a, rest = parser.parse_known_args(argv)  # argparse's own usage errors exit 2 here
    _setup_logging(a)
    cmds = {"simulate": cmd_simulate, "demo": cmd_demo, "example": cmd_example,
            "koh": cmd_koh, "calibrate": cmd_calibrate, "diagnose": cmd_diagnose,
            "sensitivity": cmd_sensitivity, "compare": cmd_compare, "sweep": cmd_sweep,
            "predict": cmd_predict}
    try:
        overrides = _split_overrides(rest)
        if getattr(a, "config_dir", None) is not None:
            from solderpyro.config.compose import config_dir_override

            try:
                overrides = [config_dir_override(a.config_dir), *overrides]
            except (ValueError, FileNotFoundError) as e:
                raise UsageError(f"--config-dir: {e}") from None
        from solderpyro.compute.executor import executor_from_options

        with executor_from_options(getattr(a, "cluster", None), getattr(a, "scheduler", None)):
            return cmds[a.command](a, overrides)
    except UsageError as e:
        print(f"solderpyro {a.command}: error: {e} (see 'solderpyro {a.command} --help')",
              file=sys.stderr)
        return 2
    except FAILURES as e:
        if a.verbose:
            log.exception("solderpyro %s failed", a.command)
        print(f"solderpyro {a.command}: error: {e}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
