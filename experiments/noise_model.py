"""Geiser et al. 2023, section 4.1: estimate Tables 1 and 2 from simulation data.

Motion: R MJX differential-drive robots (``sims.robot``, wheel-ground contact and slip) driven by
random diversified wheel-speed commands for T intervals of 0.5 s each; (true move, encoder
odometry move) pairs go to ``jaxslam.calibrate.fit_motion_noise``.
Observations: lidar scans (``sims.lidar`` via ``sims.scenario.lidar_observations``, per-beam
range noise) from random poses in a random forest, trunks detected by
``jaxslam.detect.detect_trunks``; each detection is matched to the nearest true trunk (within
``--match-radius``) and (true, detected) range-bearing pairs go to
``jaxslam.calibrate.fit_observation_noise``.

Writes results/noise_model/: table.md (fitted tables beside the paper's), fits.json (numbers),
noise_model.png (group stds against |rot| and distance with the fitted lines).

    .venv/bin/python experiments/noise_model.py [--robots 16] [--intervals 200]
        [--friction 0.8] [--poses 300] [--method kasa] [--out results/noise_model]
"""
from __future__ import annotations

import argparse
import json
import pathlib
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

# Run this checkout's jaxslam, also when an editable install points at another checkout
# (an experiment started from a git worktree of an older commit).
sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

from jaxslam import calibrate
from jaxslam.filter import run_filter
from jaxslam.geometry import compose, range_bearing
from jaxslam.metrics import ate_rmse, final_pose_error
from jaxslam.types import FilterConfig, default_params
from sims import robot as rb
from sims.forest import random_forest, world_from_forest
from sims.scenario import analytic_observations, lidar_observations, with_start_scan

DEAD_RECKONING = "odometry only (dead reckoning)"  # the results row every filter is compared to
TABLE_1 = np.array([[0.0, 0.06, 0.0002], [0.02, 0.006, 0.00003], [0.0, 0.06, 0.0003]])
TABLE_2 = np.array([[0.005, 0.0], [0.0005, 0.0]])


def parse_args():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--robots", type=int, default=16)
    parser.add_argument("--intervals", type=int, default=200)
    parser.add_argument("--interval", type=float, default=0.5, help="seconds per move")
    parser.add_argument("--friction", type=float, default=0.8)
    parser.add_argument("--min-translation", type=float, default=0.01,
                        help="moves shorter than this [m] are pure turns (rot1 = 0)")
    parser.add_argument("--poses", type=int, default=300)
    parser.add_argument("--trees", type=int, default=80)
    parser.add_argument("--beams", type=int, default=1440)
    parser.add_argument("--wheel-accel", type=float, default=10.0,
                        help="wheel speed set-point ramp [rad/s^2] (inf: step commands)")
    parser.add_argument("--beam-noise", type=float, nargs=2, default=(0.005, 0.0),
                        help="per-beam range std (per metre, constant); default sims.lidar's "
                             "Table 2 beam noise")
    parser.add_argument("--method", default="kasa")
    parser.add_argument("--match-radius", type=float, default=0.5)
    parser.add_argument("--filter-runs", type=int, default=8,
                        help="robots driven through a forest for the filter comparison (0: skip)")
    parser.add_argument("--filter-intervals", type=int, default=200)
    parser.add_argument("--particles", type=int, default=50)
    parser.add_argument("--first-scan", action=argparse.BooleanOptionalAction, default=True,
                        help="the filter also gets a scan at the start pose, before the first "
                             "move (a zero move); --no-first-scan: the first scan comes after "
                             "the first move")
    parser.add_argument("--out", default="results/noise_model")
    return parser.parse_args()


def motion_data(args):
    """True and odometry moves (S, 3) and a valid mask (S,) from R x T simulated intervals.

    A move is ambiguous (masked) when one of its two versions is a pure turn (trans below
    ``min_translation``) and the other is not: rot1 is then defined for one only.
    """
    spec = rb.RobotSpec(max_wheel_acceleration=args.wheel_accel)
    robot = rb.make_robot(spec)
    keys = jax.random.split(jax.random.key(args.seed), args.robots)
    commands = jax.vmap(lambda k: rb.random_commands(k, args.intervals, robot.spec))(keys)
    log = rb.simulate_batch(robot, commands, args.friction, args.interval,
                            args.min_translation)
    true = np.asarray(log.true_moves).reshape(-1, 3)
    odometry = np.asarray(log.odometry_moves).reshape(-1, 3)
    valid = (true[:, 1] >= args.min_translation) == (odometry[:, 1] >= args.min_translation)
    return true, odometry, valid


def random_poses(key, centres, radii, num_poses, low, high, clearance=1.0):
    """Poses (num_poses, 3) uniform in [low, high]^2 with random heading, >= clearance m off
    every trunk surface (rejection on the host)."""
    candidates = np.array(jax.random.uniform(key, (8 * num_poses, 3)), np.float64)
    candidates[:, :2] = low + (high - low) * candidates[:, :2]
    candidates[:, 2] = np.pi * (2.0 * candidates[:, 2] - 1.0)
    gap = np.hypot(*(candidates[:, None, :2] - np.asarray(centres)[None]).transpose(2, 0, 1))
    clear = np.all(gap - np.asarray(radii)[None] > clearance, axis=1)
    return candidates[clear][:num_poses]


def observation_data(args, max_obs=16, max_range=20.0):
    """True and detected (range, bearing) (S, 2) and valid (S,) from scans at random poses."""
    key_forest, key_poses, key_scans = jax.random.split(jax.random.key(args.seed + 1), 3)
    forest = random_forest(key_forest, args.trees, (60.0, 60.0))
    world = world_from_forest(forest)
    poses = random_poses(key_poses, forest.centres, forest.radii, args.poses, 10.0, 50.0)
    scan_keys = jax.random.split(key_scans, poses.shape[0])
    observe = jax.jit(jax.vmap(lambda k, p: lidar_observations(
        k, world, p, max_obs, max_range, args.beams, tuple(args.beam_noise), args.method,
        {"min_range": 0.1}), in_axes=(0, 0)))
    obs = observe(scan_keys, jnp.asarray(poses, jnp.float32))
    z, valid = np.asarray(obs.z, np.float64), np.asarray(obs.valid)
    # Detected trunk centres in the world frame, matched to the nearest true trunk.
    local = np.stack([z[..., 0] * np.cos(z[..., 1]), z[..., 0] * np.sin(z[..., 1]),
                      np.zeros_like(z[..., 0])], -1)
    world_points = np.asarray(compose(jnp.asarray(poses)[:, None, :], jnp.asarray(local)))
    centres = np.asarray(forest.centres, np.float64)
    gap = np.hypot(*(world_points[..., None, :2] - centres).transpose(3, 0, 1, 2))
    nearest = np.argmin(gap, axis=-1)
    matched = valid & (np.min(gap, axis=-1) < args.match_radius)
    truth = np.asarray(range_bearing(jnp.asarray(poses)[:, None, :],
                                     jnp.asarray(centres[nearest])))
    return (truth.reshape(-1, 2), z.reshape(-1, 2), matched.reshape(-1),
            dict(detections=int(valid.sum()), matched=int(matched.sum()),
                 poses=int(poses.shape[0])))


def grid_forest(key, half_width=70.0, spacing=6.0, jitter=2.0):
    """Trunk centres (N, 2) on a jittered square grid over [-half_width, half_width]^2."""
    ticks = np.arange(-half_width, half_width + 1e-9, spacing)
    grid = np.stack(np.meshgrid(ticks, ticks), -1).reshape(-1, 2)
    offsets = np.asarray(jax.random.uniform(key, grid.shape, minval=-jitter, maxval=jitter))
    return jnp.asarray(grid + offsets, jnp.float32)


def filter_comparison(args, fitted_params, max_obs=16, max_landmarks=256):
    """FastSLAM on MJX-robot odometry: hand-set Table 1 versus the fitted motion noise.

    R robots (new random commands) drive T intervals at the same wheel friction; controls are
    their encoder odometry moves (the filter's min_translation); observations are analytic
    range-bearing to a jittered-grid forest with Table 2 noise at the true poses, so the two
    conditions differ only in the motion-noise coefficients. With ``args.first_scan`` the
    robot also scans at rest at its start pose (``sims.scenario.with_start_scan``): the MJX
    robot's first move starts from rest and can slip by 0.1 rad, and without that scan the
    map would be built from the pose after it, tilted by that error for the whole run.
    Final error and ATE are over the poses after each move (T of them), either way.
    Returns per-run metrics.
    """
    spec = rb.RobotSpec(max_wheel_acceleration=args.wheel_accel)
    robot = rb.make_robot(spec)
    key_commands, key_forest, key_obs, key_filter = jax.random.split(
        jax.random.key(args.seed + 2), 4)
    commands = jax.vmap(lambda k: rb.random_commands(k, args.filter_intervals, robot.spec))(
        jax.random.split(key_commands, args.filter_runs))
    hand_set = default_params()
    log = rb.simulate_batch(robot, commands, args.friction, args.interval,
                            float(hand_set.min_translation))
    centres = grid_forest(key_forest)
    radii = jnp.full(centres.shape[:1], 0.15, jnp.float32)
    obs_keys = jax.random.split(key_obs, args.filter_runs * args.filter_intervals).reshape(
        args.filter_runs, args.filter_intervals)
    observe = jax.vmap(jax.vmap(lambda k, p: analytic_observations(
        k, p, centres, radii, hand_set, max_obs)))
    observations = observe(obs_keys, log.true_poses[:, 1:])
    controls = log.odometry_moves
    if args.first_scan:  # a scan at rest at the start pose anchors the map (with_start_scan)
        # A key no step uses: with JAX's default partitionable threefry, fold_in(k, n) is
        # split(k, n + 1)[n], the key after the R T step keys.
        start_keys = jax.random.split(jax.random.fold_in(
            key_obs, args.filter_runs * args.filter_intervals), args.filter_runs)
        start_scans = jax.tree.map(lambda a: a[:, 0], observe(start_keys[:, None],
                                                               log.true_poses[:, :1]))
        controls, observations = with_start_scan(controls, observations, start_scans)
    config = FilterConfig(num_particles=args.particles, max_landmarks=max_landmarks,
                          max_obs=max_obs)
    skip = int(args.first_scan)  # trace row of the pose after the first move

    def one_run(params, run, controls, obs, truth):
        state, trace = run_filter(config, jax.random.fold_in(key_filter, run), params,
                                  controls, obs, truth[0])
        return (final_pose_error(trace.mean_pose[-1], truth[-1]),
                ate_rmse(trace.mean_pose[skip:], truth[1:]))

    runs = jnp.arange(args.filter_runs)
    batched = jax.jit(jax.vmap(one_run, in_axes=(None, 0, 0, 0, 0)))  # one compile for both
    results = {}
    for name, params in (("hand-set (Table 1)", hand_set), ("fitted", fitted_params)):
        start = time.perf_counter()
        final, ate = batched(params, runs, controls, observations, log.true_poses)
        results[name] = dict(final_pose_error=np.asarray(final).tolist(),
                             ate_rmse=np.asarray(ate).tolist(),
                             seconds=time.perf_counter() - start)
    # Told nothing: each robot's settings calibrated from its own log (odometry and
    # observations; the start pose fixes the map frame), ground truth only scores.
    from jaxslam.self_calibration import calibrate_params, starting_params

    single = jax.jit(one_run)
    start = time.perf_counter()
    final, ate, verdicts = [], [], []
    for run in range(args.filter_runs):
        obs = jax.tree.map(lambda a: a[run], observations)
        params, info = calibrate_params(config, jax.random.fold_in(key_filter, run),
                                        controls[run], obs, log.true_poses[run, 0],
                                        starting_params(config))
        run_final, run_ate = single(params, run, controls[run], obs, log.true_poses[run])
        final.append(float(run_final))
        ate.append(float(run_ate))
        verdicts.append(info.verdict)
    results["calibrated from the log"] = dict(final_pose_error=final, ate_rmse=ate,
                                              seconds=time.perf_counter() - start,
                                              verdicts=verdicts)
    odometry_drift = np.hypot(*(np.asarray(log.true_poses[:, -1, :2])
                                - np.asarray(log.odometry_poses[:, -1, :2])).T)
    odometry_ate = jax.vmap(ate_rmse)(log.odometry_poses[:, 1:], log.true_poses[:, 1:])
    results[DEAD_RECKONING] = dict(
        final_pose_error=odometry_drift.tolist(), ate_rmse=np.asarray(odometry_ate).tolist())
    return results


def config_proposal() -> str:
    """The proposal of the comparison's ``FilterConfig`` (the library default)."""
    return FilterConfig().proposal


def config_matching() -> str:
    """The association and boundary of the comparison's ``FilterConfig`` (library defaults)."""
    config = FilterConfig()
    return f"{config.association} matching, boundary {config.boundary}"


def filter_markdown(results, args) -> str:
    lines = ["", "## Filter accuracy with hand-set versus fitted motion noise", "",
             f"{args.filter_runs} MJX robots x {args.filter_intervals} intervals of "
             f"{args.interval} s (wheel friction {args.friction}, acceleration limit "
             f"{args.wheel_accel} rad/s^2); controls = encoder odometry; "
             "observations = analytic range-bearing (Table 2 noise) to a jittered-grid forest "
             f"(6 m spacing, 20 m range), "
             + ("plus a scan at rest at the start pose behind a zero move (`with_start_scan`); "
                if args.first_scan else "the first scan after the first move; ")
             + f"FastSLAM P={args.particles}, {config_matching()}, "
             f"proposal {config_proposal()}. Hand-set and fitted differ only in the "
             "motion-noise coefficients (fitted against the simulator's truth); 'calibrated "
             "from the log' is told nothing (``jaxslam.calibrate_params`` on each robot's "
             "odometry and observations alone).", "",
             "| Condition | final pose error mean [m] | median | ATE RMSE mean [m] | median | "
             "robots 2x better than dead reckoning | worst robot: dead reckoning / filter |",
             "|---|---|---|---|---|---|---|"]
    reckoning = np.asarray(results[DEAD_RECKONING]["final_pose_error"])
    for name, row in results.items():
        final = np.asarray(row["final_pose_error"])
        ate = np.asarray(row.get("ate_rmse", [np.nan]))
        ratio = reckoning / final  # per robot, final pose error
        compared = ("- | -" if name == DEAD_RECKONING else
                    f"{int(np.sum(ratio >= 2.0))} of {ratio.size} | {np.min(ratio):.1f}x")
        lines.append(f"| {name} | {final.mean():.3f} | {np.median(final):.3f} | "
                     f"{np.nanmean(ate):.3f} | {np.nanmedian(ate):.3f} | {compared} |")
    return "\n".join(lines) + "\n"


def coefficient_rows(fit):
    return np.stack([np.asarray(part.coefficients) for part in fit])


def table_markdown(motion, observation, args, counts, seconds) -> str:
    def fmt(value):
        return f"{value:.3g}" if value != 0 else "0"

    lines = ["# Noise-model estimation (Geiser et al. 2023, section 4.1, Tables 1 and 2)", "",
             "Regenerate: `.venv/bin/python experiments/noise_model.py "
             f"--robots {args.robots} --intervals {args.intervals} --friction {args.friction} "
             f"--wheel-accel {args.wheel_accel} --poses {args.poses} --method {args.method} "
             f"--beam-noise {args.beam_noise[0]} {args.beam_noise[1]} "
             f"--filter-runs {args.filter_runs}"
             + ("" if args.first_scan else " --no-first-scan") + f" --out {args.out}`", "",
             f"Motion data: {counts['motion_samples']} moves of {args.interval} s "
             f"({counts['motion_valid']} unambiguous) from {args.robots} MJX robots "
             f"(wheel friction {args.friction}, wheel acceleration limit {args.wheel_accel} "
             "rad/s^2), random diversified wheel-speed commands; "
             f"simulated in {seconds['motion']:.1f} s.",
             f"Observation data: {counts['matched']} detections matched to true trunks "
             f"(of {counts['detections']}) from {counts['poses']} scans of {args.beams} beams, "
             f"per-beam range noise {tuple(args.beam_noise)}, detector `{args.method}`; "
             f"{seconds['observation']:.1f} s.", "",
             "Per-group ML variance with the mean known to be zero (Eq. (1) centres the truth "
             "on the measurement, so a bias is counted as noise); sample outliers by the MAD "
             "rule (5 robust stds), group outliers by the MAD rule on log(std / fit) (4, and "
             "off the fit by more than a factor 2), "
             "groups of fewer than 10 samples dropped; non-negative fit weighted by group "
             "size (optax, checked against SciPy nnls in tests).", "",
             "## Table 1: motion noise (std = a |trans| + b |rot| + c)", "",
             "| Error | a: Translation (fit / paper) | b: Rotation (fit / paper) "
             "| c: Constant (fit / paper) | groups kept / used |",
             "|---|---|---|---|---|"]
    for name, row, paper, part in zip(("First rotation", "Translation", "Second rotation"),
                                      coefficient_rows(motion), TABLE_1, motion):
        lines.append(f"| {name} | " + " | ".join(
            f"{fmt(row[j])} / {fmt(paper[j])}" for j in range(3))
            + f" | {int(part.kept.sum())} / {int(part.used.sum())} |")
    lines += ["", "## Table 2: observation noise (std = d distance + e)", "",
              "| Error | d: Distance (fit / paper) | e: Constant (fit / paper) "
              "| groups kept / used |", "|---|---|---|---|"]
    for name, row, paper, part in zip(("Distance", "Azimuth"), coefficient_rows(observation),
                                      TABLE_2, observation):
        lines.append(f"| {name} | " + " | ".join(
            f"{fmt(row[j])} / {fmt(paper[j])}" for j in range(2))
            + f" | {int(part.kept.sum())} / {int(part.used.sum())} |")
    return "\n".join(lines) + "\n"


def plot(motion, observation, path):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 4, figsize=(18, 4))
    for ax, part, label in zip(axes[:2], (motion.rot1, motion.rot2), ("rot1", "rot2")):
        groups = part.groups
        features, std = np.asarray(groups.features), np.asarray(groups.std)
        kept, used = np.asarray(part.kept), np.asarray(part.used)
        scatter = ax.scatter(features[used, 1], std[used], c=features[used, 0],
                             s=8 + np.asarray(groups.count)[used] / 5, cmap="viridis",
                             marker="o", edgecolors=np.where(kept[used], "none", "red"))
        rot = np.linspace(0.0, features[used, 1].max(initial=0.1), 50)
        for trans in np.quantile(features[used, 0], [0.1, 0.9]) if used.any() else ():
            ax.plot(rot, part.coefficients[0] * trans + part.coefficients[1] * rot
                    + part.coefficients[2], lw=1, label=f"fit, |trans| = {trans:.2f} m")
        ax.set_xlabel(f"|{label}| [rad]")
        ax.set_ylabel(f"std of {label} error [rad]")
        ax.legend(fontsize=7)
        fig.colorbar(scatter, ax=ax, label="|trans| [m]")
    for ax, part, label, unit in zip(axes[2:], observation, ("range", "bearing"), ("m", "rad")):
        groups = part.groups
        features, std = np.asarray(groups.features), np.asarray(groups.std)
        used, kept = np.asarray(part.used), np.asarray(part.kept)
        ax.scatter(features[used & kept, 0], std[used & kept], label="groups (kept)")
        ax.scatter(features[used & ~kept, 0], std[used & ~kept], c="red", label="removed")
        distance = np.linspace(0.0, features[used, 0].max(initial=1.0), 50)
        ax.plot(distance, part.coefficients[0] * distance + part.coefficients[1], "k-",
                label="fit")
        paper = TABLE_2[0] if label == "range" else TABLE_2[1]
        ax.plot(distance, paper[0] * distance + paper[1], "k--", label="Geiser et al. 2023, Table 2")
        ax.set_xlabel("distance [m]")
        ax.set_ylabel(f"std of {label} error [{unit}]")
        ax.legend(fontsize=7)
    fig.suptitle("Per-group ML std (red edge: removed group) and the non-negative fits")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main():
    args = parse_args()
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    true_moves, odometry_moves, valid = motion_data(args)
    motion_seconds = time.perf_counter() - start
    motion = calibrate.fit_motion_noise(true_moves, odometry_moves, valid)
    start = time.perf_counter()
    true_z, measured_z, matched, counts = observation_data(args)
    observation_seconds = time.perf_counter() - start
    observation = calibrate.fit_observation_noise(true_z, measured_z, matched)
    counts.update(motion_samples=int(valid.size), motion_valid=int(valid.sum()))
    seconds = dict(motion=motion_seconds, observation=observation_seconds)
    params = calibrate.with_fitted_noise(default_params(), motion, observation)
    table = table_markdown(motion, observation, args, counts, seconds)
    filter_results = {}
    if args.filter_runs > 0:
        # The comparison's observations follow Table 2, so only the motion fit is swapped in.
        filter_results = filter_comparison(args, calibrate.with_fitted_noise(default_params(),
                                                                             motion))
        table += filter_markdown(filter_results, args)
    (out / "table.md").write_text(table)
    (out / "fits.json").write_text(json.dumps(dict(
        args=vars(args), counts=counts, seconds=seconds,
        params={name: np.asarray(getattr(params, name)).tolist() for name in
                ("rot1_noise", "trans_noise", "rot2_noise", "range_noise", "bearing_noise")},
        motion_error_mean=np.mean((true_moves - odometry_moves)[valid], 0).tolist(),
        filter=filter_results),
        indent=2))
    plot(motion, observation, out / "noise_model.png")
    print((out / "table.md").read_text())


if __name__ == "__main__":
    main()
