"""UTIAS MRCLAM dataset 1, five robots, unknown association, settings calibrated from each log.

Leung, Halpern, Barfoot and Liu, "The UTIAS Multi-Robot Cooperative Localization and Mapping
Dataset" (IJRR 2011). Barcodes are dropped: the filter does not know which landmark it sees.
For each robot the pipeline (``jaxslam.pipeline.filter_log``) calibrates the noise and the
sensor settings from that robot's odometry and measurements alone, then filters; Vicon only
scores (ATE of the online mean path and of the smoothed one, against dead reckoning).

    python experiments/mrclam.py [--robots 1 2 3 4 5] [--particles 100] [--close-loops]
                                 [--filter-keys N] [--fit-gain] [--em-iterations N]
                                 [--em-significance LEVEL]
                                 [--proposal observation|mixture] [--mixture-ratio PHI]

``--filter-keys N`` runs the calibrated settings with N more filter keys and prints, for each,
the ratio of dead reckoning's ATE to the online path's and to the smoothed best history's.
``--fit-gain`` also fits the odometry's gains (``calibrate_params(calibrate_gain=True)``).
``--em-iterations N`` caps EM's filter runs (the library's 5 by default);
``--em-significance LEVEL`` ranks EM's runs by the t test of ``calibrate_params``'
``significance``; ``--proposal mixture --mixture-ratio PHI`` runs the calibration and the
filter with the mixture proposal (a share 1 - PHI of the particles drawn from the motion
model). All three are diagnostics of the calibration on these logs, not settings chosen
for them.
``--seed 0 1 2 3`` calibrates each robot once per key; with ``--filter-keys`` the keys' ratios
are then pooled per robot over the calibrations as well. A robot's result is a draw over
both: a float-rounding change in the filter alone moved robot 1's median over six filter keys
from 3.13x to 1.70x (docs/results.md, mrclam).

The odometry is the commanded velocities, which the robots follow with a lag. By default
(``--command-delay auto``) the lag is fitted from the log too: one filter run of the log as
stamped with the calibration's first settings gives the associations, the smoother's profile
likelihood over the delay is read with them (``jaxslam.command_delay.fit_log_command_delay``),
and the log rebuilt at the fitted delay is calibrated and filtered; that run is the result
(``pipeline.filter_log(..., command_delay="auto")`` does all of it).
``--command-delay 0`` runs the log as stamped, ``--command-delay S`` at S seconds. Dead
reckoning is always the log as stamped (a delay shifts its path in time by S and changes
its ATE by under 1 mm on these robots). The seconds printed for a robot include the fit.

With ``--close-loops`` the smoothed path is ``loop_closure.close_loops``' (loops the filter
missed closed by registration, each tested by the smoother's cost rise).

Diagnostic, not the dataset's task: ``--barcodes both`` gives the filter the barcodes
(``association="known"``) in the calibration and in the run; ``--barcodes calibration`` only
in the calibration, the run then associates by itself with those settings. The two bound what
a better association (``both``) and better-calibrated noise (``calibration``) could give.

    python experiments/mrclam.py --barcodes both

``--existence-max X`` starts the calibration (and the run) from a landmark existence cap of X
instead of the library's 6; the calibration keeps it. 1000 stands for "no practical cap", as
for tubes the README calls static (docs/results.md, mrclam, "The existence cap deletes real
landmarks here").
"""
from __future__ import annotations

import argparse
import dataclasses
import pathlib
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

# Run this checkout's jaxslam, also when an editable install points at another checkout
# (an experiment started from a git worktree of an older commit).
sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

from jaxslam import metrics, pipeline
from jaxslam.command_delay import command_delay_argument, profile_text
from jaxslam.datasets.mrclam import read_mrclam
from jaxslam.datasets.mrclam_convert import DEFAULT_MAX_OBS, mrclam_log, mrclam_steps
from jaxslam.datasets.odometry import odometry_path
from jaxslam.filter import run_filter
from jaxslam.self_calibration import calibrate_params, starting_params
from jaxslam.types import FilterConfig, default_params

from experiments.common import add_em_significance, em_significance  # noqa: E402
from experiments.mrclam_diagnostics import filter_variant  # noqa: E402

DATA = pathlib.Path(__file__).resolve().parents[2] / "shared" / "data" / "mrclam1"


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", default=str(DATA))
    parser.add_argument("--robots", type=int, nargs="+", default=[1, 2, 3, 4, 5])
    parser.add_argument("--particles", type=int, default=100)
    parser.add_argument("--seed", type=int, nargs="+", default=[0],
                        help="calibration keys, one calibration of each robot per key; with "
                             "several and --filter-keys the keys' ratios are also pooled per "
                             "robot (default: 0)")
    parser.add_argument("--no-calibrate", action="store_true")
    parser.add_argument("--close-loops", action="store_true")
    parser.add_argument("--existence-max", type=float, default=None,
                        help="cap of a landmark's existence log-odds (default: the library's, "
                             "6); 1000: no practical cap, for landmarks known to be static "
                             "(the dataset's README: 15 static tubes)")
    parser.add_argument("--barcodes", choices=("none", "calibration", "both"), default="none",
                        help="diagnostic: association known from the barcodes in the "
                             "calibration, or in the calibration and the run")
    parser.add_argument("--command-delay", default="auto", type=command_delay_argument,
                        help="[s] the commands take effect this much later than stamped; "
                             "'auto' (default) fits it from the log (module docstring), 0 runs "
                             "the log as stamped")
    parser.add_argument("--filter-keys", type=int, default=0,
                        help="also run the calibrated settings (blind, or with --barcodes) "
                             "with this many more filter keys (100, 101, ...) and print their "
                             "median ratio (default: 0): single runs of one setting vary by "
                             "up to 3.2x on these robots at the default settings, more with "
                             "--barcodes or without the existence cap")
    parser.add_argument("--fit-gain", action="store_true",
                        help="also fit the odometry's gains (calibrate_gain=True) "
                             "(default: off, as in the library)")
    parser.add_argument("--filter-particles", type=int, default=None,
                        help="particles of the --filter-keys runs (default: --particles); "
                             "the calibration and the key-0 run keep --particles, so this "
                             "measures what a larger compute budget gives the same settings")
    parser.add_argument("--proposal", choices=("observation", "mixture"), default="observation",
                        help="the filter's proposal in the calibration and the runs; "
                             "'mixture' draws a share 1 - phi of the particles from the "
                             "motion model (default: observation, as in the library)")
    parser.add_argument("--mixture-ratio", type=float, default=None,
                        help="phi of --proposal mixture, the probability of an observation "
                             "draw (default: the library's Params.mixture_ratio)")
    parser.add_argument("--em-iterations", type=int, default=None,
                        help="EM's filter runs in the calibration (calibrate_params' "
                             "iterations; 2 returns the settings of EM's first M-step) "
                             "(default: the library's 5)")
    add_em_significance(parser)
    args = parser.parse_args(argv)
    if args.em_iterations is not None and (args.em_iterations < 1 or args.no_calibrate):
        parser.error(f"--em-iterations {args.em_iterations}: expected 1 or more, and a "
                     "calibration (not with --no-calibrate)")
    args.em_significance = em_significance(parser, args, not args.no_calibrate)
    if args.mixture_ratio is not None and (args.proposal != "mixture"
                                           or not 0.0 <= args.mixture_ratio <= 1.0):
        parser.error(f"--mixture-ratio {args.mixture_ratio}: expected a probability in [0, 1] "
                     "with --proposal mixture")
    if args.filter_keys < 0:
        parser.error(f"--filter-keys {args.filter_keys}: expected 0 or more")
    if args.filter_particles is not None and args.filter_particles < 1:
        parser.error(f"--filter-particles {args.filter_particles}: expected 1 or more")
    if args.filter_particles is not None and not args.filter_keys:
        parser.error("--filter-particles sets the particles of the --filter-keys runs: give "
                     "--filter-keys N too")
    if args.barcodes != "none" and (args.no_calibrate or args.close_loops or args.fit_gain):
        parser.error("--barcodes calibrates and filters only (no --no-calibrate, "
                     "--close-loops, --fit-gain)")
    if args.fit_gain and args.no_calibrate:
        parser.error("--fit-gain fits the gains in the calibration: not with --no-calibrate")
    if args.command_delay == "auto" and (args.no_calibrate or args.barcodes != "none"):
        parser.error("--command-delay auto fits the delay with the blind calibration: give "
                     "--command-delay 0 (or a number of seconds) with --no-calibrate or "
                     "--barcodes")
    config = FilterConfig(num_particles=args.particles, max_landmarks=64, max_obs=8,
                          proposal=args.proposal)
    rows, pooled = [], {}
    for robot in args.robots:
        for seed in args.seed:
            row, online_ratios, smoothed_ratios = robot_seed(args, config, robot, seed)
            rows.append(row)
            previous = pooled.get(robot, ((), ()))
            pooled[robot] = (previous[0] + tuple(online_ratios),
                             previous[1] + tuple(smoothed_ratios))
    rows = np.asarray(rows)
    smoothed = ("" if args.barcodes != "none"  # the barcode runs are not smoothed
                else f", smoothed {np.median(rows[:, 2]):.3f} m")
    print(f"median: dead reckoning {np.median(rows[:, 0]):.3f} m, filter "
          f"{np.median(rows[:, 1]):.3f} m{smoothed}; ratio dead reckoning / filter "
          f"{np.median(rows[:, 0] / rows[:, 1]):.2f}; landmarks {np.median(rows[:, 3]):.0f}")
    if len(args.seed) > 1 and args.filter_keys:
        for robot, (online, smoothed) in pooled.items():
            print(pooled_summary(robot, online, smoothed, len(args.seed), args.filter_keys))


def robot_seed(args, config: FilterConfig, robot: int, seed: int):
    """Calibrate robot ``robot``'s log with key ``seed``, filter and print (module
    docstring); with ``--filter-keys`` also the keys' runs. Returns (row: dead reckoning
    ATE, filter ATE, smoothed ATE (NaN with --barcodes), landmarks, trees mapped (NaN with
    --barcodes); the keys' ratios online; the keys' ratios smoothed (both empty without
    --filter-keys, the smoothed ones also with --barcodes))."""
    raw = read_mrclam(args.data, robot)
    steps = mrclam_steps(raw, DEFAULT_MAX_OBS)
    log = mrclam_log(raw, steps)
    truth = np.asarray(log.truth_pose)
    dr = np.asarray(odometry_path(log.controls, log.initial_pose))[-len(truth):]
    dr_ate = float(metrics.ate_rmse(dr, truth))
    start = time.perf_counter()
    delay = args.command_delay
    if delay != "auto":  # else the pipeline fits it from the log as stamped
        log = mrclam_log(raw, steps, command_delay=delay)
    label = f"robot {robot}" + (f", seed {seed}" if len(args.seed) > 1 else "")
    if args.barcodes != "none":
        keys = range(100, 100 + args.filter_keys)
        ate, landmarks, info, key_runs = with_barcodes(
            log, steps.obs_landmark, config, args.barcodes, seed, args.existence_max,
            keys, args.filter_particles)
        where = args.barcodes.replace('both', 'calibration and run')
        print(f"{label}: T={log.num_steps} | commands {delay:+.3f} s | dead "
              f"reckoning ATE {dr_ate:.3f} m | barcodes in the {where}: "
              f"filter ATE {ate:.3f} m (dead reckoning / filter {dr_ate / ate:.2f}) | "
              f"{landmarks} landmarks | {time.perf_counter() - start:.1f} s | "
              f"{info.verdict}", flush=True)
        for line in info.warnings:
            print("   WARNING:", line)
        ratios = [dr_ate / key_ate for key_ate, _ in key_runs]
        if key_runs:
            print(keys_summary(ratios, np.median([kept for _, kept in key_runs]),
                               args.filter_keys, args.filter_particles or args.particles),
                  flush=True)
        return (dr_ate, ate, np.nan, landmarks, np.nan), ratios, ()
    run = pipeline.filter_log(log, config, start_params(config, args.existence_max,
                                                        not args.no_calibrate,
                                                        args.mixture_ratio),
                              jax.random.PRNGKey(seed),
                              calibrate=not args.no_calibrate, smooth=True,
                              close_loops=args.close_loops,
                              calibration_options=calibration_options(args),
                              command_delay="auto" if delay == "auto" else None)
    seconds = time.perf_counter() - start
    if run.delay_fit is not None:
        delay = run.delay_fit.delay
        print(f"{label}: command delay fitted from the log "
              f"{profile_text(run.delay_fit)}", flush=True)
        log = log.at_command_delay(delay)  # what the pipeline filtered (for the keys)
    m = run.metrics
    verdict = run.calibration.verdict if run.calibration is not None else "not calibrated"
    print(f"{label}: T={log.num_steps} | commands {delay:+.3f} s | dead reckoning "
          f"ATE {dr_ate:.3f} m | filter ATE {m['ate_rmse']:.3f} m, smoothed "
          f"{m['smoothed_ate_rmse']:.3f} m | "
          f"{m['num_landmarks']:.0f} landmarks, {m['num_trees_mapped']:.0f} of 15 mapped "
          f"(map error {m['map_error']:.3f} m) | {seconds:.1f} s | {verdict}"
          + (f" | {m['loop_closures']} closures, {m['landmarks_joined']} landmarks joined"
             if args.close_loops else ""),
          flush=True)
    if run.calibration is not None:
        print("   EM's log marginal likelihood per iteration:",
              np.round(run.calibration.objective, 1).tolist())
        print("   fitted:", {k: (np.round(v, 5).tolist() if isinstance(v, tuple)
                                else round(v, 5)) for k, v in run.calibration.values.items()})
    for line in run.warnings:
        print("   WARNING:", line)
    row = (dr_ate, m["ate_rmse"], m["smoothed_ate_rmse"], m["num_landmarks"],
           m["num_trees_mapped"])
    if not args.filter_keys:
        return row, [], ()
    keys_config = dataclasses.replace(config,
                                      num_particles=args.filter_particles or args.particles)
    runs = filter_variant(run.params, pipeline.log_inputs(log, keys_config), truth, dr_ate,
                          range(100, 100 + args.filter_keys), smooth=True,
                          close_loops=args.close_loops)
    print(keys_summary(runs.ratios, runs.kept, args.filter_keys, keys_config.num_particles,
                       runs.smoothed), flush=True)
    return row, runs.ratios, runs.smoothed


def pooled_summary(robot: int, online, smoothed, num_seeds: int, num_keys: int) -> str:
    """One line on a robot's filter-key runs pooled over its calibration seeds: the median
    dead reckoning / ATE ratio online and smoothed, the range, and the share of runs at 3x
    or more (the acceptance's bar). NaN (a smoother that failed) is left out of the
    smoothed figures and counted."""
    online, smoothed = np.asarray(online, float), np.asarray(smoothed, float)
    line = (f"robot {robot}, {num_seeds} calibration seeds x {num_keys} filter keys: online "
            f"median {np.median(online):.2f}x ({online.min():.2f}-{online.max():.2f}), "
            f"{int(np.sum(online >= 3.0))} of {len(online)} at 3x or more")
    if not len(smoothed):
        return line
    kept = smoothed[~np.isnan(smoothed)]
    failed = len(smoothed) - len(kept)
    if len(kept):
        line += (f"; smoothed median {np.median(kept):.2f}x ({kept.min():.2f}-"
                 f"{kept.max():.2f}), {int(np.sum(kept >= 3.0))} of {len(kept)} at 3x or more")
    if failed:
        line += f"; {failed} smoother failures"
    return line


def keys_summary(ratios, kept, num_keys: int, particles: int, smoothed=()) -> str:
    """One line on the filter keys 100, 101, ...: the median (and each) dead reckoning /
    filter ATE ratio, the median final landmark count ``kept`` and, when given, the same
    ratios of each run's smoothed best history ``smoothed`` (NaN: the smoother failed; the
    median is over the others)."""
    line = (f"   filter keys 100-{99 + num_keys} (P = {particles}): dead reckoning / filter "
            f"ATE median {np.median(ratios):.2f}x ({' '.join(f'{r:.2f}' for r in ratios)}); "
            f"landmarks kept, median {kept:.0f}")
    if len(smoothed):
        failed = int(np.sum(np.isnan(smoothed)))
        line += (f"; smoothed: median {np.nanmedian(smoothed):.2f}x "
                 f"({' '.join(f'{r:.2f}' for r in smoothed)})"
                 + (f", {failed} smoother failures" if failed else ""))
    return line


def calibration_options(args) -> dict:
    """``calibrate_params`` keywords from the options: ``calibrate_gain`` always,
    ``iterations`` when ``--em-iterations`` is given and ``significance`` when
    ``--em-significance`` is given (checked: a level, or None for 0)."""
    options = {"calibrate_gain": args.fit_gain}
    if getattr(args, "em_iterations", None) is not None:
        options["iterations"] = args.em_iterations
    if getattr(args, "em_significance", None):
        options["significance"] = args.em_significance
    return options


def start_params(config: FilterConfig, existence_max: float | None, calibrate: bool = True,
                 mixture_ratio: float | None = None):
    """The settings the pipeline starts from (``calibrate``: ``starting_params``, else
    ``default_params``), with ``existence_max`` and ``mixture_ratio`` where given; None (the
    pipeline's own default) when neither is changed."""
    overrides = {name: value for name, value in (("existence_max", existence_max),
                                                 ("mixture_ratio", mixture_ratio))
                 if value is not None}
    if not overrides:
        return None
    return (starting_params if calibrate else default_params)(config, **overrides)


def barcode_calibration(log, obs_landmark, config: FilterConfig, seed: int,
                        existence_max: float | None = None):
    """(config sized to the log, the same with ``association="known"``, Params, the
    ``CalibrationInfo``, (controls, observations with the barcodes as ids, start)): one
    robot's log calibrated with key ``seed`` and the association known from the barcodes
    (obs_landmark (T, K), -1 padding; -1 on invalid rows too)."""
    config, controls, obs, start = pipeline.log_inputs(log, config)
    obs = obs._replace(landmark_id=jnp.asarray(
        np.where(np.asarray(obs.valid), obs_landmark, -1), jnp.int32))
    known = dataclasses.replace(config, association="known")
    params, info = calibrate_params(known, jax.random.PRNGKey(seed), controls, obs, start,
                                    start_params(known, existence_max))
    return config, known, params, info, (controls, obs, start)


def with_barcodes(log, obs_landmark, config: FilterConfig, barcodes: str, seed: int,
                  existence_max: float | None = None, filter_keys=(),
                  filter_particles: int | None = None):
    """(filter ATE [m], final landmarks, ``CalibrationInfo``, [(ATE, final landmarks)] of
    each key in ``filter_keys``) of one robot's log calibrated with the association known
    from the barcodes (obs_landmark (T, K), -1 padding), and filtered with it
    (``barcodes="both"``) or with the config's own association (``"calibration"``): key
    ``seed`` at the config's particles, then the calibrated settings again with each of
    ``filter_keys`` at ``filter_particles`` (default: the config's). Vicon only scores."""
    config, known, params, info, (controls, obs, start) = barcode_calibration(
        log, obs_landmark, config, seed, existence_max)
    key = jax.random.PRNGKey(seed)
    run_config = known if barcodes == "both" else config

    def scored(run_config, key):
        _, trace = run_filter(run_config, key, params, controls, obs,
                              jnp.asarray(start, jnp.float32))
        ate = float(metrics.ate_rmse(np.asarray(trace.mean_pose, np.float64),
                                     np.asarray(log.truth_pose)))
        return ate, int(np.asarray(trace.num_landmarks)[-1])

    ate, kept = scored(run_config, key)
    keys_config = dataclasses.replace(
        run_config, num_particles=filter_particles or run_config.num_particles)
    return ate, kept, info, [scored(keys_config, jax.random.PRNGKey(k)) for k in filter_keys]


if __name__ == "__main__":
    main()
