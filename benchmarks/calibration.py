"""Benchmark of ``jaxslam.calibrate_params``: its time as a multiple of one filter run.

One filter run is ``run_filter(..., record_lineage=True)`` after compiling; the calibration
runs it once an EM iteration, so a calibration can never cost less than its iterations'
runs (two search candidates can share one run's time: ``noise_scale.default_workers``). The
filter is compiled by an untimed first call (same shapes as the calibration's runs), then
``--repeats`` runs (their median is the unit) and the whole calibration are timed back to
back in this process, and the ratio is calibration / run. Everything else a calibration
does, compiles included, counts against it: a user calls ``calibrate_params`` once, in a
fresh process. Logs: a held-out simulated loop
(the ``experiments/self_calibration.py`` generator: 250 steps, 40 trees), UTIAS MRCLAM
robot 1 (3,809 steps; ``--robots`` names others) and Victoria Park (7,230 scans; its
calibration takes about 4.5-5.5 minutes on 2 cores) when their folders are given.

    python benchmarks/calibration.py [--particles 100] [--stages]
    python benchmarks/calibration.py --mrclam DIR     # or JAXSLAM_MRCLAM=DIR; --skip-mrclam
    python benchmarks/calibration.py --only mrclam --mrclam DIR --robots 1 2 3 4 5
    python benchmarks/calibration.py --only victoria_park --victoria-park DIR
    python benchmarks/calibration.py --only mrclam --mrclam DIR --command-delay auto

``--command-delay auto`` times MRCLAM as ``experiments/mrclam.py`` runs it by default: the
commands' lag fitted from the log (``command_delay.fit_log_command_delay``: one filter run
with the calibration's first settings and five smoothings for a lag between about -0.1 and
0.3 s), and the calibration of the log rebuilt at the fitted lag; one more line gives each part
and their sum as multiples of one filter run of the log as stamped (compiled before the fit).

How to read a line:

    simulated loop: T=250 P=100 K=12 | filter run 0.46 s (first call with compile 7.55 s) |
      calibration 1.03 s, 2 iterations (converged) | 2.2x one filter run, 1.12x a run per
      iteration

* ``Nx one filter run``: the figure of merit (target: under 10x). Its floor is the number of
  iterations (each runs the filter once; two search candidates can share one run's time);
  ``x a run per iteration`` shows what an iteration costs beyond its filter run (1.0 would
  be the filter alone).
* The iteration count is the calibration's own (EM stops when every noise group's typical std
  moved by less than 5 %, else after 5, or when two runs in a row did not beat the best): a
  log whose calibration does not converge (MRCLAM) costs up to 5 runs whatever the rest
  costs, and the count can differ between logs, keys, and versions of the code (the filter
  is a chaotic function of its settings).
* The machine is shared: a ratio moves by 20-30 % from one invocation to the next. Compare
  versions in one process, back to back, and repeat.
* The next lines: EM's log marginal likelihood and dropped births for each iteration's filter
  run, and the likelihood's scale search (``noise_scale.describe_search``): each candidate's
  score (nan for one its walk did not run, and for one stopped at its first dropped birth)
  and, when any run dropped births, those counts (a stopped run's: those of the step it
  stopped at; EM's own x1 run's: its whole run's).
* ``--stages`` adds the seconds spent in each stage, summed over the iterations and as a
  multiple of the filter run: the filter runs, tracing the best particle's history, the
  smoother (its Levenberg-Marquardt solves and the variance components inside it), the
  motion and observation noise fits and the sensor fit. What no stage covers (typical stds,
  trust region, residual geometry) is the remainder.

Measured on the shared 2-core development machine (P = 100), before and after the EM loop's
JAX calls between filter runs were replaced by NumPy twins and the smoother kept its
elimination order: simulated loop 28-42x -> 2.2-2.8x (2-3 iterations; the jitted noise fits
had been recompiled every iteration, 2-4 s each, as the sample count changes with the
association, and ``estimate``, ``trace_lineage`` and the residual geometry compiled eager JAX
ops); MRCLAM robot 1 15-23x -> 7-9x (6 iterations: the 6 filter runs are 6-6.7x of it, the
smoother 2.0x, of which 0.3x the variance components; the rest 0.2x).
"""
from __future__ import annotations

import argparse
import collections
import functools
import os
import pathlib
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

from jaxslam import self_calibration, smoothing  # noqa: E402
from jaxslam.filter import run_filter  # noqa: E402
from jaxslam.noise_scale import describe_search  # noqa: E402
from jaxslam.self_calibration import calibrate_params, starting_params  # noqa: E402
from jaxslam.smoothing import solver  # noqa: E402
from jaxslam.types import FilterConfig  # noqa: E402

# (module, function, label): the stages ``--stages`` times; nested ones are indented.
STAGES = ((self_calibration, "run_filter", "filter runs"),
          (self_calibration, "best_history", "best particle's history"),
          (smoothing, "smooth_path", "smoother"),
          (solver, "levenberg_marquardt", "  Levenberg-Marquardt solves"),
          (solver, "variance_factors", "  variance components"),
          (self_calibration, "motion_noise_update", "motion noise fit"),
          (self_calibration, "observation_noise_update", "observation noise fit"),
          (self_calibration, "sensor_update", "sensor fit"))


def _time(function):
    start = time.perf_counter()
    out = function()
    jax.block_until_ready(jax.tree.leaves(out))
    return time.perf_counter() - start, out


def _timed_stages(totals):
    """Wrap the ``STAGES`` functions so that their seconds add up in ``totals``; returns a
    function that puts the originals back."""
    originals = []
    for module, name, label in STAGES:
        function = getattr(module, name)
        originals.append((module, name, function))

        @functools.wraps(function)
        def timed(*args, _function=function, _label=label, **kwargs):
            start = time.perf_counter()
            out = _function(*args, **kwargs)
            jax.block_until_ready(jax.tree.leaves(out))
            totals[_label] += time.perf_counter() - start
            return out

        setattr(module, name, timed)

    def restore():
        for module, name, function in originals:
            setattr(module, name, function)

    return restore


def filter_seconds(config, controls, obs, start, params, repeats: int = 3):
    """(first, run): the seconds of a first filter run (with its compile) and the median of
    ``repeats`` more, each with the lineage recorded, as the calibration's runs are."""
    key = jax.random.PRNGKey(0)
    controls = jnp.asarray(controls, jnp.float32)
    start32 = jnp.asarray(start, jnp.float32)
    first, _ = _time(lambda: run_filter(config, key, params, controls, obs, start32,
                                        record_lineage=True))
    run = float(np.median([_time(lambda: run_filter(config, key, params, controls, obs,
                                                    start32, record_lineage=True))[0]
                           for _ in range(repeats)]))
    return first, run


def bench(name, config, controls, obs, start, stages: bool = False, params=None,
          repeats: int = 3, search_workers: int | None = None):
    """Print one log's line (module docstring); ``params``: the calibration's starting point
    (default ``starting_params(config)``); ``repeats``: filter runs whose median time is the
    ratio's unit; ``search_workers``: ``calibrate_params``' (None: its default)."""
    key = jax.random.PRNGKey(0)
    params = starting_params(config) if params is None else params
    controls = jnp.asarray(controls, jnp.float32)
    # The calibration gets the start pose as given (float64, as ``filter_log`` passes it: its
    # smoother works in float64, and a start rounded to float32 moves EM's later runs, the
    # filter being chaotic in its inputs); the timed runs take the filter's float32.
    first, run = filter_seconds(config, controls, obs, start, params, repeats)
    totals = collections.defaultdict(float)
    restore = _timed_stages(totals) if stages else (lambda: None)
    try:
        seconds, (params_out, info) = _time(lambda: calibrate_params(
            config, key, controls, obs, start, params, search_workers=search_workers))
    finally:
        restore()
    print(f"{name}: T={controls.shape[0]} P={config.num_particles} K={config.max_obs} | "
          f"filter run {run:.2f} s (first call with compile {first:.2f} s) | calibration "
          f"{seconds:.2f} s, {info.iterations} iterations ({info.verdict}) | "
          f"{seconds / run:.1f}x one filter run, {seconds / info.iterations / run:.2f}x a run "
          f"per iteration")
    print(f"    log marginal likelihood per iteration {np.round(info.objective, 1).tolist()}, "
          f"births dropped {np.asarray(info.dropped_births).tolist()}")
    if info.noise_scales is not None:
        print(f"    scale search: {describe_search(info.noise_scales)}")
    if stages:
        top = sum(v for label, v in totals.items() if not label.startswith(" "))
        for _, _, label in STAGES:
            print(f"    {label:30s} {totals[label]:7.2f} s  {totals[label] / run:6.2f}x")
        print(f"    {'remainder':30s} {seconds - top:7.2f} s  {(seconds - top) / run:6.2f}x")
    return seconds, run, params_out


def bench_command_delay(name, folder, robot: int, config: FilterConfig, stages: bool,
                        **timing):
    """MRCLAM robot ``robot`` with its command lag fitted (module docstring): the stamped
    log's filter run (compiled first: the unit), the fit, the rebuilt log's ``bench`` line,
    and the sum."""
    from jaxslam.command_delay import fit_log_command_delay
    from jaxslam.datasets.mrclam import read_mrclam
    from jaxslam.datasets.mrclam_convert import DEFAULT_MAX_OBS, mrclam_log, mrclam_steps
    from jaxslam.pipeline import log_inputs

    raw = read_mrclam(folder, robot)
    steps = mrclam_steps(raw, DEFAULT_MAX_OBS)

    def log_at(delay):
        return mrclam_log(raw, steps, command_delay=delay)

    stamped = log_inputs(log_at(0.0), config)
    _, run = filter_seconds(*stamped, starting_params(stamped[0]),
                            timing.get("repeats", 3))
    fit_s, fit = _time(lambda: fit_log_command_delay(log_at, config, jax.random.PRNGKey(0)))
    print(f"{name}: lag fit {fit_s:.2f} s ({fit.delay:.3f} s from "
          f"{len(fit.delays)} candidates) | filter run of the log as stamped {run:.2f} s")
    second, _, _ = bench(f"{name}, commands {fit.delay:+.3f} s late",
                         *log_inputs(log_at(fit.delay), config), stages, **timing)
    total = fit_s + second
    print(f"    with the lag fitted: fit {fit_s:.1f} s ({fit_s / run:.1f}x) + calibration at "
          f"{fit.delay:.3f} s {second / run:.1f}x = {total:.1f} s, {total / run:.1f}x one "
          f"filter run of the log as stamped")


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--particles", type=int, default=100)
    parser.add_argument("--mrclam", type=pathlib.Path, default=os.environ.get("JAXSLAM_MRCLAM"),
                        help="folder of the UTIAS MRCLAM data set 1 files (default: "
                        "$JAXSLAM_MRCLAM; without either, MRCLAM is skipped)")
    parser.add_argument("--skip-mrclam", action="store_true")
    parser.add_argument("--robots", type=int, nargs="+", default=[1], choices=range(1, 6),
                        help="MRCLAM robots to calibrate, each its own line (default: 1)")
    parser.add_argument("--victoria-park", type=pathlib.Path,
                        default=os.environ.get("JAXSLAM_VICTORIA_PARK"),
                        help="folder of the Victoria Park files (default: "
                        "$JAXSLAM_VICTORIA_PARK; without either, Victoria Park is skipped: "
                        "its calibration takes about 4.5-5.5 minutes)")
    parser.add_argument("--only", choices=["simulated", "mrclam", "victoria_park"],
                        nargs="+", help="run only these logs")
    parser.add_argument("--repeats", type=int, default=3,
                        help="filter runs timed for the ratio's unit, their median (default 3)")
    parser.add_argument("--search-workers", type=int, default=None,
                        help="candidates the scale search runs at once (default: "
                        "calibrate_params' own, 2 on a CPU with two or more cores)")
    parser.add_argument("--command-delay", choices=["none", "auto"], default="none",
                        help="MRCLAM: 'auto' also times the lag fit and the calibration at "
                             "the fitted lag (module docstring)")
    parser.add_argument("--stages", action="store_true",
                        help="print the seconds spent in each stage of the calibration")
    args = parser.parse_args(argv)
    if args.repeats < 1:
        parser.error(f"--repeats must be a positive integer; got {args.repeats}")
    timing = dict(repeats=args.repeats, search_workers=args.search_workers)
    from experiments.self_calibration import make_log, true_params

    only = set(args.only or ("simulated", "mrclam", "victoria_park"))
    if "simulated" in only:
        controls, obs, poses, _ = make_log(jax.random.PRNGKey(7), true_params(2.0, 2.0), 0.0)
        bench("simulated loop", FilterConfig(num_particles=args.particles, max_landmarks=96,
                                             max_obs=12), controls, obs, poses[0], args.stages,
              **timing)
    if "mrclam" in only and not args.skip_mrclam:
        if args.mrclam is None or not pathlib.Path(args.mrclam).is_dir():
            print(f"MRCLAM: skipped (no data folder: give --mrclam DIR or set "
                  f"JAXSLAM_MRCLAM; got {args.mrclam})")
        else:
            from jaxslam.datasets.mrclam import load_mrclam
            from jaxslam.pipeline import log_inputs

            config = FilterConfig(num_particles=args.particles, max_landmarks=64)
            for robot in args.robots:
                if args.command_delay == "auto":
                    bench_command_delay(f"MRCLAM robot {robot}", pathlib.Path(args.mrclam),
                                        robot, config, args.stages, **timing)
                    continue
                log = load_mrclam(pathlib.Path(args.mrclam), robot)
                bench(f"MRCLAM robot {robot}", *log_inputs(log, config), args.stages,
                      **timing)
    if "victoria_park" in only:
        if args.victoria_park is None or not pathlib.Path(args.victoria_park).is_dir():
            print(f"Victoria Park: skipped (no data folder: give --victoria-park DIR or set "
                  f"JAXSLAM_VICTORIA_PARK; got {args.victoria_park})")
        else:
            config, controls, obs, start, params = victoria_park_case(args.victoria_park,
                                                                       args.particles)
            bench("Victoria Park", config, controls, obs, start, args.stages, params, **timing)


def victoria_park_case(folder, num_particles):
    """(config, controls, observations, start pose, starting Params) of the whole Victoria
    Park log as ``experiments/victoria_park.py`` calibrates it: trunks detected in every
    scan, controls corrected by the laser-only steering bias, 320 landmark slots, the
    calibrated settings set's fixed values as the starting point."""
    from experiments import victoria_park_pipeline as vps
    from jaxslam.datasets import victoria_park as vpm
    from jaxslam.pipeline import log_inputs

    data = vpm.load_victoria_park(folder)
    settings = vps.load_settings("calibrated")
    config = vps.settings_config(settings, num_particles=num_particles, max_landmarks=320)
    log, _, _ = vps.calibration_log(data, settings, config)
    config, controls, obs, start = log_inputs(log, config)
    return config, controls, obs, start, vps.settings_params(settings, config)


if __name__ == "__main__":
    main()
