"""Self-calibration on held-out simulated logs: the filter told nothing against told the truth.

Each log: a wobbly loop (a 20 m circle with a 0.3 m, 6 m-wavelength lateral wobble, so the
heading turns by up to about 0.15 rad a step), 40 random trees in 60 m x 60 m, a 12 m sensor,
250 steps of 0.5 m. Odometry noise: Table 1 of Geiser et al. (ICAROB 2023) times
``--odometry-scale``; sensor noise: range std (0.005 d + 0.002) and bearing std
(0.0005 d + 0.0002) times ``--sensor-scale`` (Table 2 with a small constant). Each run draws its
own forest and noise from ``fold_in(PRNGKey(seed), run)``; no run is used to choose a setting.

For each run it reports the final position error and the map size of
  * dead reckoning (the controls integrated),
  * the filter given the true noise and the true 12 m range ("true"),
  * the filter after ``calibrate_params`` from the log alone, started from
    ``starting_params`` ("calibrated"),
and the recovered coefficients against the true ones. Recovery of the noise, per group
(``recovery``): EM's typical std (heading, translation, range, bearing: the rms of the
model's std over this log's moves and observations, ``CalibrationInfo.typical_std`` with the
likelihood search's scales divided out) over the true model's on the same log, and whether
that ratio lies within the interval the calibration states, 1 +- 1.96
``CalibrationInfo.relative_std`` (its 95 % interval if the std's error were only the
sampling error of its samples). With ``--bootstrap B`` also whether the truth lies within
the parametric bootstrap's interval (``jaxslam.calibration_bootstrap``: B replicate logs
drawn from the calibrated model and calibrated again, which counts EM's bias as well).

``--odometry-gain G_T G_R`` reads each log's moves with a systematic error (the robot drives
G_T times and turns G_R times what its odometry says); ``--fit-gain`` has the calibration fit
``params.odometry_gain`` as well (off by default, as in the library).

    python experiments/self_calibration.py --runs 8 --odometry-scale 2 --sensor-scale 5
"""
from __future__ import annotations

import argparse
import pathlib
import sys
import time
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

# Run this checkout's jaxslam, also when an editable install points at another checkout
# (an experiment started from a git worktree of an older commit).
sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

from experiments.common import add_em_significance, em_significance
from jaxslam import lineage, metrics
from jaxslam.calibration_bootstrap import bootstrap_intervals, burst_rms_factor
from jaxslam.calibration_residuals import NOISE_GROUPS, typical_stds
from jaxslam.datasets.odometry import odometry_path
from jaxslam.filter import estimate, run_filter
from jaxslam.motion import control_to_odometry, with_gain
from jaxslam.pipeline import offline_path
from jaxslam.self_calibration import (calibrate_params, em_typical_std,
                                      group_scales, starting_params)
from jaxslam.types import FilterConfig, default_params
from sims.forest import random_forest
from sims.paths import resample_polyline
from sims.scenario import build_scenario

NUM_STEPS = 250
STEP = 0.5
SIZE = 60.0
MAX_RANGE = 12.0


def wobbly_loop(num_steps: int = NUM_STEPS, radius: float = 20.0, amplitude: float = 0.3,
                wavelength: float = 6.0):
    """(T+1, 3) a circle about the forest centre with a sinusoidal radial wobble."""
    phi = np.linspace(0.0, 2 * np.pi, 4000, endpoint=False)
    arc = radius * phi
    r = radius + amplitude * np.sin(2 * np.pi * arc / wavelength)
    points = np.stack([0.5 * SIZE + r * np.cos(phi), 0.5 * SIZE + r * np.sin(phi)], -1)
    return resample_polyline(points, num_steps, STEP, closed=True)


def true_params(odometry_scale: float, sensor_scale: float):
    base = default_params()
    return default_params(
        rot1_noise=odometry_scale * np.asarray(base.rot1_noise),
        trans_noise=odometry_scale * np.asarray(base.trans_noise),
        rot2_noise=odometry_scale * np.asarray(base.rot2_noise),
        range_noise=(0.005 * sensor_scale, 0.002 * sensor_scale),
        bearing_noise=(0.0005 * sensor_scale, 0.0002 * sensor_scale),
        range_std_floor=1e-4, bearing_std_floor=1e-5, max_range=MAX_RANGE)


def read_with_gain(controls, gain):
    """The log's measured moves (T, 3) as an odometry with gains ``gain`` = (g_t, g_r) reads
    them: divided by the gains (``motion.with_gain`` of the readings gives them back). The
    gains (1, 1) return ``controls`` itself."""
    if tuple(gain) == (1.0, 1.0):
        return controls
    return with_gain(jnp.asarray(controls), 1.0 / jnp.asarray(gain, jnp.float32))


def make_log(key, params, wobble: float = 0.3):
    """(controls (T, 3), observations (T, K), truth poses (T+1, 3), trees (N, 2))."""
    key_forest, key_runs = jax.random.split(key)
    path = wobbly_loop(amplitude=wobble)
    dense = wobbly_loop(2000, amplitude=wobble)
    forest = random_forest(key_forest, 40, (SIZE, SIZE), keep_clear=dense[:, :2])
    scenario = build_scenario(key_runs, forest, path, 1, params=params, max_obs=12)
    return (scenario.controls[0], jax.tree.map(lambda a: a[0], scenario.observations),
            scenario.poses[0], forest.centres)


def offline_error(config, params, final, trace, controls, obs, truth) -> float:
    """Final position error [m] of the offline estimate of a filter run with its lineage
    (``final``, ``trace``): the best particle's history smoothed with the loops the filter
    missed closed (``pipeline.offline_path``, as ``jaxslam run --smooth --close-loops``);
    inf when the smoother fails."""
    history = lineage.trace_lineage(trace.lineage, estimate(final).best_particle)
    try:
        path, _ = offline_path(history, controls, obs, truth[0], params, config.motion_model,
                               close_loops=True)
    except (RuntimeError, np.linalg.LinAlgError, ValueError):
        return float("inf")
    return float(np.hypot(*(np.asarray(path[-1, :2]) - np.asarray(truth[-1, :2]))))


def score(config, key, params, controls, obs, truth, trees, offline: bool = False):
    """One filter run: (online final error [m], landmarks, trees seen, map metrics, offline
    final error [m]: ``offline_error`` of the same run with ``offline``, else NaN). The
    lineage recorded for the offline estimate does not change the run's draws."""
    final, trace = run_filter(config, key, params, controls, obs, truth[0],
                              record_lineage=offline)
    est = estimate(final)
    error = float(np.hypot(*(np.asarray(trace.mean_pose[-1, :2]) - np.asarray(truth[-1, :2]))))
    after = (offline_error(config, params, final, trace, controls, obs, truth) if offline
             else float("nan"))
    seen = np.zeros(len(trees), bool)
    ids = np.asarray(obs.landmark_id)[np.asarray(obs.valid)]
    seen[ids] = True
    found = metrics.map_metrics(est.landmark_mean, est.active, trees, jnp.asarray(seen), 1.0)
    return error, int(np.sum(np.asarray(est.active))), int(seen.sum()), found, after


class Recovery(NamedTuple):
    """Noise recovery of one run, per group (4,) in ``NOISE_GROUPS`` order.

    ratio: EM's typical std over the true model's on the same log. half_width: the stated
    95 % half-width 1.96 x ``relative_std`` (inf for a group not fitted). inside: |ratio - 1|
    <= half_width. scaled: (4,) bool, the likelihood's search changed EM's noise of the group
    (its scales are divided out of ``ratio``: ``relative_std`` describes EM's estimate).
    ratio counts only the core std. total_ratio: with fitted bursts (burst probability eps
    and scale kappa fitted by the M-step, not the defaults it keeps when the log shows none:
    ``self_calibration.defensive_bursts``) the motion groups' ratio times the mixture's rms
    factor sqrt(1 - eps + eps kappa^2), the std the whitened residuals measure, and so the
    one ``relative_std`` describes (the simulated truth has no bursts, so its rms is its
    std); else ratio. total_inside: |total_ratio - 1| <= half_width."""

    ratio: np.ndarray
    half_width: np.ndarray
    inside: np.ndarray
    scaled: np.ndarray
    total_ratio: np.ndarray
    total_inside: np.ndarray


def true_typical_std(truth_params, odometry, observations) -> np.ndarray:
    """(4,) the true model's typical std per group over this log's moves (T, 3) and valid
    observations (non-finite rows not counted)."""
    z = np.asarray(observations.z, np.float64)
    valid = np.asarray(observations.valid) & np.all(np.isfinite(z), axis=-1)
    return np.asarray(typical_stds(truth_params, np.asarray(odometry, np.float64),
                                   z[valid][:, 0]))


def recovery(truth_params, info, odometry, observations) -> Recovery:
    """``Recovery`` of one calibration. odometry (T, 3): the log's moves (rot1, trans, rot2);
    observations: z (T, K, 2), valid (T, K) (non-finite rows are not counted).

    The ratio is EM's own estimate (``self_calibration.em_typical_std``: the likelihood
    search's scales divided out) over the truth's."""
    true = true_typical_std(truth_params, odometry, observations)
    scales = group_scales(info)
    ratio = em_typical_std(info) / true
    half = np.array([1.96 * info.relative_std.get(g, np.inf) for g in NOISE_GROUPS])
    bursts = burst_rms_factor(info)
    total = ratio * np.array([bursts, bursts, 1.0, 1.0])
    return Recovery(ratio, half, np.abs(ratio - 1.0) <= half, scales != 1.0, total,
                    np.abs(total - 1.0) <= half)


def _append_rows(name: str, header: str, rows: str) -> None:
    """Append ``rows`` to results/self_calibration/``name`` under ``header`` (each call of
    the script adds its regime's rows). A new file starts with ``header``; a file whose
    last table has another header (other columns, particles or proposal: an earlier call's
    or an earlier version's) gets ``header`` again first, so no row lands under a header
    that does not describe it. The file is only appended to, so earlier rows are never
    rewritten."""
    table = pathlib.Path("results") / "self_calibration" / name
    table.parent.mkdir(parents=True, exist_ok=True)
    text = table.read_text() if table.exists() else ""
    lines = text.splitlines()
    separators = [i for i, line in enumerate(lines) if line.startswith("|---")]
    current = "\n".join(lines[:separators[-1] + 1]) if separators else ""
    prefix = "\n" if text and not text.endswith("\n") else ""
    if not current.endswith(header.rstrip("\n")):
        prefix += ("\n" if text else "") + header
    with table.open("a") as handle:
        handle.write(prefix + rows)


def _gain_cell(args) -> str:
    """The odometry's gains the logs were read with, and whether the calibration fitted
    gains: e.g. "0.93, 0.9; fitted" or "1, 1; not fitted"."""
    g_t, g_r = args.odometry_gain
    return f"{g_t:g}, {g_r:g}; {'fitted' if args.fit_gain else 'not fitted'}"


def _stack_fields(records):
    """Each field of a list of NamedTuples of (4,) arrays, stacked over the runs: a tuple of
    (R, 4) arrays in field order."""
    return tuple(np.stack([getattr(r, name) for r in records]) for name in records[0]._fields)


def _write_recovery(args, recovered):
    """Append this regime's recovery rows to results/self_calibration/recovery.md."""
    header = (
        "EM's typical std / the true one per noise group (the likelihood's scales divided "
        "out), median [min, max] over runs; the stated 95 % half-width 1.96 x "
        "relative_std (median); runs whose ratio lies in 1 +- that half-width; runs whose "
        "group the search scaled; the same with fitted bursts counted in the motion "
        "groups' std (the mixture's rms, ``Recovery.total_ratio``). One block of rows per "
        "call (seed, runs).\n\n"
        "| seed | odometry x Table 1 | sensor x Table 2 | wobble [m] | log's gains; calibration "
        "| group | runs | EM / true | stated half-width | truth inside | scaled by the search | "
        "EM / true, bursts counted | truth inside, bursts counted |\n"
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|\n")
    ratio, half, inside, scaled, total, total_inside = _stack_fields(recovered)
    spread = lambda x: f"{np.median(x):.2f} [{x.min():.2f}, {x.max():.2f}]"
    _append_rows("recovery.md", header, "".join(
        f"| {args.seed} | {args.odometry_scale:g} | {args.sensor_scale:g} | "
        f"{args.wobble:g} | {_gain_cell(args)} | {group} | {len(recovered)} | "
        f"{spread(ratio[:, g])} | "
        f"{np.median(half[:, g]):.3f} | {int(inside[:, g].sum())} of {len(recovered)} "
        f"| {int(scaled[:, g].sum())} | {spread(total[:, g])} | "
        f"{int(total_inside[:, g].sum())} of {len(recovered)} |\n"
        for g, group in enumerate(NOISE_GROUPS)))


class BootstrapRecovery(NamedTuple):
    """The bootstrap interval of one run against the truth, per group (4,): lower / upper
    the interval's limits over EM's estimate (``calibration_bootstrap.total_typical_std``),
    truth the true typical std over it, inside: the truth within the limits."""

    lower: np.ndarray
    upper: np.ndarray
    truth: np.ndarray
    inside: np.ndarray


def bootstrap_recovery(truth_params, found, odometry, observations) -> BootstrapRecovery:
    """``BootstrapRecovery`` of ``found`` (``BootstrapIntervals``); odometry (T, 3) and
    observations as ``recovery``'s."""
    true = true_typical_std(truth_params, odometry, observations)
    return BootstrapRecovery(found.lower / found.estimate, found.upper / found.estimate,
                             true / found.estimate,
                             (found.lower <= true) & (true <= found.upper))


def _write_bootstrap(args, booted):
    """Append this regime's bootstrap rows to results/self_calibration/bootstrap.md."""
    header = (
        "Parametric-bootstrap intervals (``calibration_bootstrap``, bias-corrected normal, "
        "95 %) of each group's typical std, bursts counted: the limits and the truth over "
        "EM's estimate, median over runs, and the runs whose truth lies inside.\n\n"
        "| seed | odometry x Table 1 | sensor x Table 2 | wobble [m] | log's gains; "
        "calibration | replicates | group | runs | lower / EM | upper / EM | truth / EM | "
        "truth inside |\n"
        "|---|---|---|---|---|---|---|---|---|---|---|---|\n")
    lower, upper, truth, inside = _stack_fields(booted)
    _append_rows("bootstrap.md", header, "".join(
        f"| {args.seed} | {args.odometry_scale:g} | {args.sensor_scale:g} | {args.wobble:g} "
        f"| {_gain_cell(args)} | {args.bootstrap} | {group} | {len(booted)} | "
        f"{np.median(lower[:, g]):.2f} | {np.median(upper[:, g]):.2f} | "
        f"{np.median(truth[:, g]):.2f} | "
        f"{int(inside[:, g].sum())} of {len(booted)} |\n"
        for g, group in enumerate(NOISE_GROUPS)))


def offline_row(args, rows, offline) -> str:
    """One markdown row: dead reckoning, then online / offline final error [m] of the filter
    given the true noise and of the calibrated one (median over runs; runs over 0.5 m in
    brackets); rows (R, 6) as ``main`` collects them, offline (R, 2) true, calibrated."""
    def cell(errors):
        return f"{np.median(errors):.3f} ({int(np.sum(errors > 0.5))})"

    return (f"| {args.odometry_scale:g} | {args.sensor_scale:g} | {args.wobble:g} | "
            f"{_gain_cell(args)} | {len(rows)} | {np.median(rows[:, 0]):.2f} | "
            f"{cell(rows[:, 1])} | {cell(offline[:, 0])} | {cell(rows[:, 2])} | "
            f"{cell(offline[:, 1])} |\n")


def _write_offline(args, rows, offline):
    """Append this regime's ``offline_row`` to results/self_calibration/offline.md."""
    _append_rows("offline.md", (
        "Final position error [m], median over runs (runs over 0.5 m in brackets): online "
        "(the filter's weighted mean) and offline (the best particle's history smoothed, "
        "missed loops closed). P = %d, proposal %s.\n\n"
        "| odometry x Table 1 | sensor x Table 2 | wobble [m] | log's gains; calibration | "
        "runs | dead reckoning | true noise: online | true noise: offline | calibrated: "
        "online | calibrated: offline |\n|---|---|---|---|---|---|---|---|---|---|\n"
        % (args.particles, args.proposal)),
        offline_row(args, rows, offline))


def _write_results(args, rows):
    """Append this regime's row to results/self_calibration/results.md (one row a regime)."""
    med = np.median(rows, axis=0)
    _append_rows("results.md", (
        "Final position error [m], median over runs (runs over 0.5 m in brackets); map "
        "size against trees seen. P = %d, proposal %s.\n\n"
        "| odometry x Table 1 | sensor x Table 2 | wobble [m] | log's gains; calibration | "
        "runs | dead reckoning | true noise given | calibrated | calibrated / true (median "
        "ratio) | map true / calibrated / seen |\n|---|---|---|---|---|---|---|---|---|---|\n"
        % (args.particles, args.proposal)),
        f"| {args.odometry_scale:g} | {args.sensor_scale:g} | {args.wobble:g} | "
        f"{_gain_cell(args)} | {len(rows)} "
        f"| {med[0]:.2f} | {med[1]:.2f} ({int(np.sum(rows[:, 1] > 0.5))}) | {med[2]:.2f} "
        f"({int(np.sum(rows[:, 2] > 0.5))}) | "
        f"{np.median(rows[:, 2] / np.maximum(rows[:, 1], 1e-3)):.2f} | {med[3]:.0f} / "
        f"{med[4]:.0f} / {med[5]:.0f} |\n")


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=4)
    parser.add_argument("--seed", type=int, default=100)
    parser.add_argument("--particles", type=int, default=100)
    parser.add_argument("--odometry-scale", type=float, default=2.0)
    parser.add_argument("--sensor-scale", type=float, default=5.0)
    parser.add_argument("--proposal", default=FilterConfig().proposal)
    parser.add_argument("--wobble", type=float, default=0.3,
                        help="lateral wobble amplitude [m]; 0.3 turns up to ~0.15 rad a step, "
                        "0 is a smooth circle (0.025 rad a step)")
    parser.add_argument("--odometry-gain", type=float, nargs=2, default=(1.0, 1.0),
                        metavar=("G_T", "G_R"),
                        help="the robot drives G_T times and turns G_R times what its odometry "
                             "reads: each log's moves are read divided by these gains (the "
                             "true-noise filter is given them) (default: 1 1: no systematic "
                             "error)")
    parser.add_argument("--fit-gain", action="store_true",
                        help="also fit the odometry's gains (calibrate_gain=True) "
                             "(default: off, as in the library)")
    parser.add_argument("--bootstrap", type=int, default=0, metavar="B",
                        help="also state each noise group's parametric-bootstrap interval "
                        "from B replicate calibrations (calibration_bootstrap; B >= 2, about "
                        "20) and count the runs whose truth lies inside; "
                        "results/self_calibration/bootstrap.md")
    parser.add_argument("--offline", action="store_true",
                        help="also score the offline estimate (smoothed, missed loops closed: "
                        "offline_error) of both filters; results/self_calibration/offline.md")
    add_em_significance(parser)
    args = parser.parse_args(argv)
    significance = em_significance(parser, args)
    if min(args.odometry_gain) <= 0.0:
        parser.error(f"--odometry-gain {args.odometry_gain}: expected two gains > 0")
    config = FilterConfig(num_particles=args.particles, max_landmarks=96, max_obs=12,
                          proposal=args.proposal)
    truth_params = true_params(args.odometry_scale, args.sensor_scale)._replace(
        odometry_gain=jnp.asarray(args.odometry_gain, jnp.float32))
    rows, recovered, offline, booted = [], [], [], []
    for run in range(args.runs):
        key = jax.random.fold_in(jax.random.PRNGKey(args.seed), run)
        key_log, key_filter = jax.random.split(key)
        controls, obs, truth, trees = make_log(key_log, truth_params, args.wobble)
        controls = read_with_gain(controls, args.odometry_gain)
        dr = odometry_path(np.asarray(controls), np.asarray(truth[0]))
        dr_error = float(np.hypot(*(dr[-1, :2] - np.asarray(truth[-1, :2]))))
        true_error, true_map, seen, _, true_offline = score(
            config, key_filter, truth_params, controls, obs, truth, trees, args.offline)
        start = time.perf_counter()
        calibrated, info = calibrate_params(config, key_filter, controls, obs, truth[0],
                                            starting_params(config),
                                            calibrate_gain=args.fit_gain,
                                            significance=significance)
        seconds = time.perf_counter() - start
        cal_error, cal_map, _, _, cal_offline = score(
            config, key_filter, calibrated, controls, obs, truth, trees, args.offline)
        rows.append((dr_error, true_error, cal_error, true_map, cal_map, seen))
        # The true noise's typical std over the true model's moves (the readings times
        # the true gains).
        true_moves = control_to_odometry(jnp.asarray(controls), truth_params, "odometry")
        recovered.append(recovery(truth_params, info, true_moves, obs))
        if args.bootstrap:
            start = time.perf_counter()
            found = bootstrap_intervals(config, key_filter, controls, obs, truth[0],
                                        starting_params(config), calibrated, info,
                                        replicates=args.bootstrap,
                                        calibrate_gain=args.fit_gain,
                                        significance=significance)
            booted.append(bootstrap_recovery(truth_params, found, true_moves, obs))
            print(f"   bootstrap ({args.bootstrap} replicates, "
                  f"{time.perf_counter() - start:.0f} s): true typical std inside the interval:",
                  dict(zip(NOISE_GROUPS, booted[-1].inside)), "interval / EM estimate:",
                  {g: (round(lo, 2), round(hi, 2)) for g, lo, hi in zip(
                      NOISE_GROUPS, booted[-1].lower, booted[-1].upper)})
        if args.offline:
            offline.append([true_offline, cal_offline])
            print(f"   offline (smoothed, loops closed): true noise {offline[-1][0]:.3f} m, "
                  f"calibrated {offline[-1][1]:.3f} m")
        print(f"run {run}: dead reckoning {dr_error:.3f} m | true noise {true_error:.3f} m, "
              f"{true_map} landmarks | calibrated {cal_error:.3f} m, {cal_map} landmarks "
              f"({seen} trees seen) | {info.iterations} iterations, {seconds:.1f} s, "
              f"{info.verdict}")
        print("   fitted:", {k: v for k, v in info.values.items()})
        print("   EM / true typical std:", dict(zip(NOISE_GROUPS, recovered[-1].ratio.round(3))),
              "within the stated 95 % interval:", dict(zip(NOISE_GROUPS, recovered[-1].inside)),
              "(scaled by the search)" if recovered[-1].scaled.any() else "")
        print("   with fitted bursts counted:", dict(zip(NOISE_GROUPS,
                                                      recovered[-1].total_ratio.round(3))),
              "within:", dict(zip(NOISE_GROUPS, recovered[-1].total_inside)))
    rows = np.asarray(rows)
    med = np.median(rows, axis=0)
    _write_results(args, rows)
    _write_recovery(args, recovered)
    if args.offline:
        _write_offline(args, rows, np.asarray(offline))
    if args.bootstrap:
        _write_bootstrap(args, booted)
    print(f"median over {args.runs} runs: dead reckoning {med[0]:.3f} m, true noise "
          f"{med[1]:.3f} m, calibrated {med[2]:.3f} m; map true {med[3]:.0f}, calibrated "
          f"{med[4]:.0f}, trees seen {med[5]:.0f}")
    print(f"calibrated / true final error (median of ratios): "
          f"{np.median(rows[:, 2] / np.maximum(rows[:, 1], 1e-3)):.2f}; runs over 0.5 m: "
          f"{int(np.sum(rows[:, 2] > 0.5))} calibrated, {int(np.sum(rows[:, 1] > 0.5))} true")
    print("true:", {"rot1_noise": np.asarray(truth_params.rot1_noise).round(5).tolist(),
                    "trans_noise": np.asarray(truth_params.trans_noise).round(5).tolist(),
                    "rot2_noise": np.asarray(truth_params.rot2_noise).round(5).tolist(),
                    "range_noise": np.asarray(truth_params.range_noise).round(5).tolist(),
                    "bearing_noise": np.asarray(truth_params.bearing_noise).round(5).tolist()})


if __name__ == "__main__":
    main()
