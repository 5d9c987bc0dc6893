"""Victoria Park end to end: detection figures, FastSLAM (P=100) against GPS, Monte Carlo runs.

Writes results/victoria_park/: results.md (tables), results.json (numbers), map.png (the map
and path over the GPS track), mc_rmse.png (RMSE of the Monte Carlo runs).

    .venv/bin/python experiments/victoria_park.py [--particles 100] [--mc-runs 100]
        [--mc-particles 100] [--mc-chunk 20] [--scans N] [--out results/victoria_park]
"""
from __future__ import annotations

import argparse
import json
import pathlib
import time

import jax
import numpy as np

from jaxslam.datasets import victoria_park as vpm
from jaxslam.datasets import victoria_park_slam as vps


def parse_args():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--particles", type=int, default=100)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--mc-runs", type=int, default=100)
    parser.add_argument("--mc-particles", type=int, default=100)
    parser.add_argument("--mc-chunk", type=int, default=20,
                        help="runs vmapped at a time (each records a 64 MB lineage)")
    parser.add_argument("--scans", type=int, default=None, help="prefix length (default all)")
    parser.add_argument("--smooth-visit-gap", type=int, default=None, metavar="SCANS",
                        help="let the smoother revise loop closures, visits split at gaps of "
                             "SCANS (100 tested; off by default, see victoria_park_slam)")
    parser.add_argument("--out", default="results/victoria_park")
    return parser.parse_args()


def detection_figures(log):
    """(Observations, DetectionSummary, compile+run seconds, run seconds)."""
    start = time.perf_counter()
    obs = jax.block_until_ready(vps.detect_scans(log.scan_ranges, log.scan_angles))
    first = time.perf_counter() - start
    start = time.perf_counter()
    jax.block_until_ready(vps.detect_scans(log.scan_ranges, log.scan_angles))
    return obs, vps.summarize_detections(obs), first, time.perf_counter() - start


def plot_map(run, dead_reckoning_error, out_png):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    gps = run.gps
    angle, shift = gps.rotation, gps.translation
    trees = vpm.rigid_transform_2d(run.landmark_mean[run.active], angle, shift)
    path = vpm.rigid_transform_2d(run.path[:, :2], angle, shift)
    fig, ax = plt.subplots(figsize=(9, 9))
    ax.plot(gps.gps_xy[:, 0], gps.gps_xy[:, 1], ".", color="0.5", ms=2, label="GPS (filtered)")
    ax.plot(dead_reckoning_error.aligned_xy[:, 0], dead_reckoning_error.aligned_xy[:, 1], "-",
            color="tab:blue", lw=0.6, alpha=0.6,
            label=f"dead reckoning (RMSE {dead_reckoning_error.rmse:.1f} m)")
    ax.plot(path[:, 0], path[:, 1], "-", color="tab:red", lw=0.8,
            label=f"FastSLAM path, online (RMSE {gps.rmse:.2f} m)")
    if run.smoothed_gps is not None:
        smoothed = vpm.rigid_transform_2d(run.smoothed_path[:, :2],
                                          run.smoothed_gps.rotation,
                                          run.smoothed_gps.translation)
        ax.plot(smoothed[:, 0], smoothed[:, 1], "-", color="black", lw=0.8,
                label=f"best particle's history, smoothed (RMSE {run.smoothed_gps.rmse:.2f} m)")
    ax.plot(trees[:, 0], trees[:, 1], "g^", ms=4, label=f"trees ({run.num_trees})")
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title("Victoria Park: FastSLAM map over the GPS track (rigid fit to GPS)")
    ax.legend(loc="best", fontsize=8)
    fig.savefig(out_png, dpi=120, bbox_inches="tight")
    plt.close(fig)


def plot_mc(batch, particles, out_png):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(10, 4))
    largest = max(np.max(batch.rmse), np.max(batch.smoothed_rmse)
                  if batch.smoothed_rmse is not None else 0.0)
    bins = np.linspace(0.0, float(largest) + 0.5, 40)
    ax[0].hist(batch.rmse, bins=bins, alpha=0.6, label="online (weighted mean)")
    if batch.smoothed_rmse is not None:
        ax[0].hist(batch.smoothed_rmse, bins=bins, alpha=0.6, label="smoothed history")
    ax[0].axvline(2.0, color="tab:red", ls="--", label="target 2 m")
    ax[0].set_xlabel("RMSE vs GPS [m]")
    ax[1].hist(batch.num_trees, bins=30)
    ax[1].axvspan(130, 200, color="tab:green", alpha=0.15, label="target 130-200")
    ax[1].set_xlabel("final tree count")
    for axis in ax:
        axis.set_ylabel("runs")
        axis.legend(fontsize=8)
    fig.suptitle(f"{batch.rmse.size} Monte Carlo runs of the whole log, P = {particles}, "
                 "in one call")
    fig.savefig(out_png, dpi=100, bbox_inches="tight")
    plt.close(fig)


def settings_line() -> str:
    """The filter settings behind the tables (``victoria_park_config`` / ``_params``)."""
    config = vps.victoria_park_config()
    noise = vps.MOTION_NOISE
    return (f"{config.proposal} proposal (pose-uncertainty matching "
            f"{'on' if config.match_pose_uncertainty else 'off'}), {config.association} "
            f"matching over the {config.association_window} nearest landmarks, "
            f"{config.boundary} boundary, M = {config.max_landmarks}, K = {config.max_obs}; "
            f"motion noise rot {noise['rot1_noise']}, trans {noise['trans_noise']} "
            f"(Geiser et al. 2023, Eq. 1); observation noise range "
            f"{vps.PARAM_DEFAULTS['range_noise']}, bearing {vps.PARAM_DEFAULTS['bearing_noise']}, "
            f"trunk radius std {vps.PARAM_DEFAULTS['radius_noise']} m (in association and "
            f"weights; gate {vps.PARAM_DEFAULTS['association_gate']}); "
            f"matching out to {vps.PARAM_DEFAULTS['max_range']:.0f} m, misses counted within "
            f"{vps.PARAM_DEFAULTS['miss_range']:.0f} m; steering bias: the laser-only profile "
            f"(steering_bias_profile, {vps.BIAS_WINDOW}-scan windows)")


def markdown(numbers) -> str:
    det, run, mc = numbers["detection"], numbers["run"], numbers.get("monte_carlo")
    lines = [
        "# Victoria Park: FastSLAM against GPS", "",
        "## Trunk detection (all scans, batched with jax.vmap)", "",
        "| figure | jaxslam (centroid) | classic detector (README) |", "|---|---|---|",
        f"| beams used | < {vps.CLASSIC_DETECTOR['max_range']:.0f} m, > {vps.BODY_RANGE} m "
        "(body mask) | < 75 m |",
        f"| segment split | range jump > {vps.CLASSIC_DETECTOR['range_jump']} m; dropouts of "
        f"<= {vps.GROUND_STRIKE_BRIDGING['max_missing_beams']} beams bridged when the ranges "
        f"agree within {vps.GROUND_STRIKE_BRIDGING['bridge_range_jump']} m (ground strikes) "
        "| > 1.5 m |",
        "| rejected | occluded, chord > 1 m, < 3 points, bad circle fit | occluded, > 1 m wide |",
        f"| trunks per scan (mean / max) | {det['per_scan_mean']:.2f} / {det['per_scan_max']} "
        "| at most 18 |",
        f"| scans at the cap of {vps.CLASSIC_MAX_TRUNKS} | {det['scans_at_cap']} | |",
        f"| total detections | {det['total']} | |",
        "| range percentiles 5/25/50/75/95 [m] | "
        + " / ".join(f"{v:.1f}" for v in det["range_percentiles"]) + " | |",
        f"| median radius [m] | {det['radius_median']:.2f} | |",
        f"| time, compile+run / run [s] | {det['first_s']:.2f} / {det['run_s']:.2f} | |", "",
        f"## FastSLAM, P = {run['particles']}, {run['scans']} scans", "",
        f"Settings: {settings_line()}.", "",
        "| metric | value | target |", "|---|---|---|",
        f"| RMSE vs GPS [m] (rigid fit, outliers removed), online weighted mean | "
        f"{run['rmse']:.2f} | <= 2 (EKF-SLAM 1.4-1.8) |",
        f"| RMSE vs GPS [m], best particle's history smoothed (its associations fixed) | "
        f"{run['smoothed_rmse']:.2f} | <= 2 |",
        f"| mean / median / max error [m] | {run['mean']:.2f} / {run['median']:.2f} / "
        f"{run['max']:.2f} | |",
        f"| steering bias [mrad]: used, laser-only profile median (10-90%) / constant "
        f"laser-only fit / GPS course fit | {1e3 * run['profile_median']:.2f} "
        f"({1e3 * run['profile_p10']:.2f}-{1e3 * run['profile_p90']:.2f}) / "
        f"{1e3 * run['laser_bias']:.2f} +- {1e3 * run['laser_bias_se']:.2f} / "
        f"{1e3 * run['gps_bias']:.2f} | |",
        f"| dead-reckoning RMSE [m], raw / constant laser bias / laser bias profile | "
        f"{run['dead_reckoning_rmse']:.1f} / {run['corrected_dead_reckoning_rmse']:.1f} / "
        f"{run['profile_dead_reckoning_rmse']:.1f} | |",
        f"| final tree count (best particle) | {run['num_trees']} | 130-200 (~150 known) |",
        f"| trees updated >= 3 times | {run['num_confirmed']} | |",
        f"| compile [s] | {run['compile_s']:.1f} | |",
        f"| run after compilation [s]: filter + smoothing | {run['run_s']:.1f} + "
        f"{run['smooth_s']:.1f} | <= 30 |",
        f"| mean ESS | {run['mean_ess']:.1f} | |", "",
    ]
    if mc:
        lines += [
            f"## Monte Carlo: {mc['runs']} runs, P = {mc['particles']}, one compiled call "
            f"({mc['chunk']} runs vmapped at a time), each run's best history then smoothed",
            "",
            "| metric | online | smoothed |", "|---|---|---|",
            f"| RMSE median / mean [m] | {mc['rmse_median']:.2f} / {mc['rmse_mean']:.2f} | "
            f"{mc['smoothed_median']:.2f} / {mc['smoothed_mean']:.2f} |",
            f"| RMSE 10 / 90 percentile [m] | {mc['rmse_p10']:.2f} / {mc['rmse_p90']:.2f} | "
            f"{mc['smoothed_p10']:.2f} / {mc['smoothed_p90']:.2f} |",
            f"| RMSE best / worst [m] | {min(mc['rmse']):.2f} / {max(mc['rmse']):.2f} | "
            f"{min(mc['smoothed_rmse']):.2f} / {max(mc['smoothed_rmse']):.2f} |",
            f"| runs with RMSE <= 2 m | {mc['runs_within_2m']} | "
            f"{mc['smoothed_within_2m']} |",
            f"| tree count median (min-max) | {mc['trees_median']:.0f} ({mc['trees_min']}-"
            f"{mc['trees_max']}) | (the same maps) |",
            f"| compile / filter run / smoothing [s] | {mc['compile_s']:.1f} / "
            f"{mc['run_s']:.1f} / {mc['smooth_s']:.1f} |", "",
        ]
    lines += ["Command: `.venv/bin/python experiments/victoria_park.py` "
              f"{numbers['argv']}", ""]
    return "\n".join(lines)


def main():
    args = parse_args()
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    data = vpm.load_victoria_park()
    log = vpm.victoria_park_log(data)
    obs, summary, first_s, detect_s = detection_figures(log)
    numbers = {"argv": " ".join(f"--{k.replace('_', '-')} {v}" for k, v in vars(args).items()),
               "detection": {**{k: np.asarray(v).tolist() for k, v in summary._asdict().items()},
                             "first_s": first_s, "run_s": detect_s}}
    print("detection:", numbers["detection"], flush=True)

    steps = log.num_steps if args.scans is None else args.scans
    # The bias profile of the scans this run sees (what the runs' default "laser" computes).
    profile = vps.steering_bias_profile(data, jax.tree.map(lambda leaf: leaf[:steps], obs))
    config = vps.victoria_park_config(num_particles=args.particles)
    run = vps.run_victoria_park(jax.random.key(args.seed), data, config, observations=obs,
                                num_scans=args.scans, steering_bias=profile,
                                smooth_visit_gap=args.smooth_visit_gap)

    def dead_reckoning_error(path):
        return vpm.gps_error(log.time[:steps], path[:steps, :2], log.gps_time, log.gps_xy)

    dead_reckoning = dead_reckoning_error(vpm.dead_reckoning_path(data))
    corrected = dead_reckoning_error(vpm.odometry_path(vps.victoria_park_controls(data)))
    profiled = dead_reckoning_error(vpm.odometry_path(vps.victoria_park_controls(data,
                                                                                 profile)))
    laser_bias, laser_bias_se = vps.steering_bias_from_scans(data, obs)
    numbers["run"] = dict(particles=args.particles, scans=steps, rmse=run.gps.rmse,
                          laser_bias=laser_bias, laser_bias_se=laser_bias_se,
                          gps_bias=vps.steering_bias_from_gps(data),
                          mean=run.gps.mean, median=run.gps.median, max=run.gps.max,
                          dead_reckoning_rmse=dead_reckoning.rmse,
                          corrected_dead_reckoning_rmse=corrected.rmse,
                          profile_dead_reckoning_rmse=profiled.rmse,
                          profile_median=float(np.median(profile)),
                          profile_p10=float(np.percentile(profile, 10)),
                          profile_p90=float(np.percentile(profile, 90)),
                          num_trees=run.num_trees,
                          num_confirmed=run.num_confirmed, compile_s=run.compile_s,
                          run_s=run.run_s, mean_ess=float(run.ess.mean()),
                          smoothed_rmse=run.smoothed_gps.rmse, smooth_s=run.smooth_s)
    print("run:", numbers["run"], flush=True)
    plot_map(run, dead_reckoning, out / "map.png")

    if args.mc_runs > 0:
        mc_config = vps.victoria_park_config(num_particles=args.mc_particles)
        # No progress bar inside one compiled call: say what to expect (runs x one run's time).
        print(f"monte carlo: {args.mc_runs} runs x P={args.mc_particles} in one compiled call; "
              f"about {args.mc_runs * run.run_s * args.mc_particles / args.particles / 60:.0f} "
              "min at the single run's speed, then smoothing (a progress bar)", flush=True)
        batch = vps.run_victoria_park_batch(jax.random.key(args.seed + 1), data, args.mc_runs,
                                            mc_config, observations=obs, num_scans=args.scans,
                                            steering_bias=profile, smooth=True,
                                            chunk=args.mc_chunk,
                                            smooth_visit_gap=args.smooth_visit_gap)
        smoothed = batch.smoothed_rmse
        numbers["monte_carlo"] = dict(
            runs=args.mc_runs, particles=args.mc_particles,
            rmse_median=float(np.median(batch.rmse)), rmse_mean=float(batch.rmse.mean()),
            rmse_p10=float(np.percentile(batch.rmse, 10)),
            rmse_p90=float(np.percentile(batch.rmse, 90)),
            runs_within_2m=int(np.sum(batch.rmse <= 2.0)),
            trees_median=float(np.median(batch.num_trees)),
            trees_min=int(batch.num_trees.min()), trees_max=int(batch.num_trees.max()),
            smoothed_median=float(np.median(smoothed)), smoothed_mean=float(smoothed.mean()),
            smoothed_p10=float(np.percentile(smoothed, 10)),
            smoothed_p90=float(np.percentile(smoothed, 90)),
            smoothed_within_2m=int(np.sum(smoothed <= 2.0)), chunk=args.mc_chunk,
            compile_s=batch.compile_s, run_s=batch.run_s, smooth_s=batch.smooth_s,
            rmse=batch.rmse.tolist(), smoothed_rmse=smoothed.tolist(),
            num_trees=batch.num_trees.tolist())
        print("monte carlo:", {k: v for k, v in numbers["monte_carlo"].items()
                               if k not in ("rmse", "smoothed_rmse", "num_trees")}, flush=True)
        plot_mc(batch, args.mc_particles, out / "mc_rmse.png")

    (out / "results.json").write_text(json.dumps(numbers, indent=2))
    (out / "results.md").write_text(markdown(numbers))
    print((out / "results.md").read_text())


if __name__ == "__main__":
    main()
