"""Victoria Park end to end: detection figures, FastSLAM (P=100) against GPS, Monte Carlo runs.

Writes results/victoria_park/: results.md (tables), results.json (numbers), map.png (the map
and path over the GPS track), mc_rmse.png (RMSE of the Monte Carlo runs) and, for the
calibrated set, calibrated_params.toml (``victoria_park_runs.py --params-file``).

    .venv/bin/python experiments/victoria_park.py [--settings calibrated|legacy]
        [--particles 100] [--mc-runs 100] [--mc-particles 100] [--mc-chunk 20] [--scans N]
        [--out results/victoria_park]

Settings sets (experiments/configs/victoria_park.toml): "calibrated" (default; every setting
from the dataset documentation, the library default, or the log itself, GPS only scores) and
"legacy" (the earlier set chosen by GPS score, in-sample).
"""
from __future__ import annotations

import argparse
import json
import pathlib
import sys
import time

import jax
import numpy as np

import victoria_park_pipeline as vps  # experiments/ (this script's folder)
# Run this checkout's jaxslam, also when an editable install points at another checkout
# (an experiment started from a git worktree of an older commit).
sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

from jaxslam.datasets import victoria_park as vpm
from jaxslam.self_calibration import interval_text


def parse_args():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--settings", choices=(vps.CALIBRATED, vps.LEGACY),
                        default=vps.CALIBRATED,
                        help="settings set of experiments/configs/victoria_park.toml")
    parser.add_argument("--particles", type=int, default=100)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--mc-runs", type=int, default=100)
    parser.add_argument("--mc-particles", type=int, default=100)
    parser.add_argument("--mc-chunk", type=int, default=20,
                        help="runs vmapped at a time (each records a 64 MB lineage)")
    parser.add_argument("--scans", type=int, default=None, help="prefix length (default all)")
    parser.add_argument("--smooth-visit-gap", type=int, default=None, metavar="SCANS",
                        help="let the smoother revise loop closures, visits split at gaps of "
                             "SCANS (100 tested; off by default, docs/results.md)")
    parser.add_argument("--close-loops", action="store_true",
                        help="also smooth the key run's history with the loops the filter "
                             "missed closed (pipeline.offline_path, loop_closure.close_loops)")
    parser.add_argument("--out", default="results/victoria_park")
    args = parser.parse_args()
    if args.close_loops and args.smooth_visit_gap is not None:
        parser.error("--close-loops and --smooth-visit-gap exclude each other (visits are the "
                     "smoother's own soft loop closures; choose one)")
    return args


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


def _fmt(value) -> str:
    array = np.asarray(value, np.float64)
    if array.ndim == 0:
        return f"{float(array):.4g}"
    return "(" + ", ".join(f"{float(v):.4g}" for v in array) + ")"


def settings_line(settings, config, params, bias_text: str) -> str:
    """The filter settings behind the tables, with where each group came from."""
    source = settings.sources
    return (f"set **{settings.name}** ({settings.description}); {config.proposal} proposal "
            f"(pose-uncertainty matching {'on' if config.match_pose_uncertainty else 'off'}, "
            f"bursts {'on' if config.burst_proposal else 'off'}), {config.association} "
            f"matching over {config.association_window or 'all'} nearest landmarks, "
            f"{config.boundary} boundary, M = {config.max_landmarks}, K = {config.max_obs}; "
            f"motion noise rot1 {_fmt(params.rot1_noise)}, trans {_fmt(params.trans_noise)}, "
            f"rot2 {_fmt(params.rot2_noise)} (Geiser et al. 2023, Eq. 1), bursts "
            f"{_fmt(params.motion_outlier_probability)} x {_fmt(params.motion_outlier_scale)} "
            f"[{source['params.rot1_noise']}]; observation noise range "
            f"{_fmt(params.range_noise)}, bearing {_fmt(params.bearing_noise)}, floors "
            f"{_fmt(params.range_std_floor)} m / {_fmt(params.bearing_std_floor)} rad "
            f"[{source['params.range_noise']}]; trunk radius std {_fmt(params.radius_noise)} m "
            f"[{source['params.radius_noise']}], gate {_fmt(params.association_gate)} "
            f"[{source['params.association_gate']}]; matching out to "
            f"{_fmt(params.max_range)} m, misses counted within {_fmt(params.miss_range)} m "
            f"and |bearing| {_fmt(params.miss_bearing)} rad [{source['params.max_range']}]; "
            f"detection / false-alarm probability {_fmt(params.detection_probability)} / "
            f"{_fmt(params.false_alarm_probability)} [{source['params.detection_probability']}]"
            f"; existence log-odds init / delete / cap {_fmt(params.existence_init)} / "
            f"{_fmt(params.existence_delete)} / {_fmt(params.existence_max)} "
            f"[{source['params.existence_max']}]; steering bias: {bias_text} "
            f"[{source['run.steering_bias']}]; smoother {settings.smoother} "
            f"[{source['smoother.calibrate_rounds']}]")


def calibration_lines(calibration) -> list[str]:
    """Markdown rows of the calibration (none for a set without one)."""
    if not calibration:
        return []
    values = calibration["values"]
    lines = ["### Calibration from the log (GPS unused)", "",
             f"jaxslam.pipeline.filter_log(calibrate=True) on the log as a RobotLog "
             f"(calibrate_params: EM with the smoother; the trunk-radius std from the "
             f"within-landmark radius scatter in each M-step): {calibration['seconds']:.0f} s, "
             f"{calibration['iterations']} EM iterations, {calibration['verdict']}.", "",
             "| field | calibrated value |", "|---|---|"]
    lines += [f"| {name} | {_fmt(value)} |" for name, value in values.items()]
    spread = interval_text(calibration.get("radius_relative_std", float("nan")))
    lines += [f"| radius_noise (from {calibration['radius_samples']} observations; 95 % "
              f"interval: {spread}, bootstrap over landmarks) | "
              f"{calibration['radius_noise']:.4g} |",
              f"| filter_log's own run (its key): online RMSE [m] / trees "
              f"| {calibration['online_rmse']:.2f} / {calibration['num_trees']} |", ""]
    if calibration["warnings"]:
        lines += ["Warnings: " + "; ".join(calibration["warnings"]), ""]
    return lines


def markdown(numbers) -> str:
    det, run, mc = numbers["detection"], numbers["run"], numbers.get("monte_carlo")
    lines = [
        "# Victoria Park: FastSLAM against GPS", "",
        f"Settings set: **{numbers['settings']}** (experiments/configs/victoria_park.toml"
        "; GPS only scores" + (")." if numbers["settings"] == "calibrated" else
                               ", but these settings were chosen by GPS score: in-sample)."),
        "",
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
        f"Settings: {numbers['settings_line']}.", "",
        *calibration_lines(numbers.get("calibration")),
        "| metric | value | target |", "|---|---|---|",
        f"| RMSE vs GPS [m] (rigid fit, outliers removed), online weighted mean | "
        f"{run['rmse']:.2f} | <= 3 (EKF-SLAM 1.4-1.8) |",
        f"| RMSE vs GPS [m], best particle's history smoothed (its associations fixed) | "
        f"{run['smoothed_rmse']:.2f} | <= 2 |",
        *([] if run.get("closed_rmse") is None else [
            f"| RMSE vs GPS [m], the same history smoothed with the loops the filter missed "
            f"closed ({run['closures']['loop_closures']} closures, "
            f"{run['closures']['landmarks_joined']} landmarks joined; "
            f"{run['close_s']:.0f} s) | {run['closed_rmse']:.2f} | <= 2 |"]),
        f"| mean / median / max error [m] | {run['mean']:.2f} / {run['median']:.2f} / "
        f"{run['max']:.2f} | |",
        f"| steering bias [mrad]: used ({run['bias_used']}) / laser-only profile median "
        f"(10-90%) / constant laser-only fit / GPS course fit (comparison only) | "
        f"{1e3 * run['bias_used_median']:.2f} / {1e3 * run['profile_median']:.2f} "
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
    settings = vps.load_settings(args.settings)
    numbers["settings"] = args.settings
    obs_steps = jax.tree.map(lambda leaf: leaf[:steps], obs)
    # The laser-only bias profile (the legacy set's choice), for the table in every case.
    profile = vps.steering_bias_profile(data, obs_steps)
    config = vps.settings_config(settings, num_particles=args.particles)
    if settings.calibrate:
        calibration = vps.calibrate_victoria_park(
            jax.random.key(args.seed), data, settings, obs, num_scans=args.scans,
            progress=lambda line: print(line, flush=True), config=config)
        params, bias = calibration.params, calibration.steering_bias
        info = calibration.info
        online = vpm.gps_error(log.time[:steps], calibration.path[:, :2], log.gps_time,
                               log.gps_xy)
        numbers["calibration"] = dict(
            seconds=calibration.seconds, iterations=int(info.iterations),
            verdict=info.verdict, warnings=list(calibration.warnings),
            values={name: np.asarray(getattr(params, name)).tolist()
                    for name in settings.calibrated if name != "radius_noise"},
            radius_noise=calibration.radius_noise, radius_samples=calibration.radius_samples,
            radius_relative_std=float(info.relative_std.get("radius", float("nan"))),
            online_rmse=online.rmse, num_trees=calibration.num_trees,
            objective=np.asarray(info.objective).tolist(),
            dropped_births=np.asarray(info.dropped_births).tolist())
        print("calibration:", numbers["calibration"], flush=True)
        from jaxslam.pipeline import save_params

        save_params(out / "calibrated_params.toml", params,
                    "Victoria Park Params calibrated from the log (experiments/victoria_park.py"
                    f" {numbers['argv']})")
    else:
        params = vps.settings_params(settings, config)
        bias = vps.steering_bias_of(settings, data, obs_steps)
    bias_used = ("the laser-only profile (steering_bias_profile, "
                 f"{settings.run.get('bias_window', vps.BIAS_WINDOW)}-scan windows)"
                 if np.ndim(bias) else f"{1e3 * float(bias):.2f} mrad, the constant laser-only "
                 "fit (steering_bias_from_scans)")
    numbers["settings_line"] = settings_line(settings, config, params, bias_used)
    run = vps.run_victoria_park(jax.random.key(args.seed), data, config, params,
                                observations=obs, num_scans=args.scans, steering_bias=bias,
                                smooth_visit_gap=args.smooth_visit_gap,
                                smoother=settings.smoother, close_loops=args.close_loops)

    def dead_reckoning_error(path):
        return vpm.gps_error(log.time[:steps], path[:steps, :2], log.gps_time, log.gps_xy)

    dead_reckoning = dead_reckoning_error(vpm.dead_reckoning_path(data))
    laser_bias, laser_bias_se = vps.steering_bias_from_scans(data, obs_steps)
    corrected = dead_reckoning_error(vpm.odometry_path(vps.victoria_park_controls(data,
                                                                                  laser_bias)))
    profiled = dead_reckoning_error(vpm.odometry_path(vps.victoria_park_controls(data,
                                                                                 profile)))
    numbers["run"] = dict(particles=args.particles, scans=steps, rmse=run.gps.rmse,
                          bias_used="profile" if np.ndim(bias) else "constant",
                          bias_used_median=float(np.median(bias)),
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
                          smoothed_rmse=run.smoothed_gps.rmse, smooth_s=run.smooth_s,
                          closed_rmse=(None if run.closed_gps is None
                                       else run.closed_gps.rmse),
                          closures=run.closures, close_s=run.close_s)
    print("run:", numbers["run"], flush=True)
    plot_map(run, dead_reckoning, out / "map.png")

    if args.mc_runs > 0:
        mc_config = vps.settings_config(settings, num_particles=args.mc_particles)
        # No progress bar inside one compiled call: say what to expect (runs x one run's time).
        print(f"monte carlo: {args.mc_runs} runs x P={args.mc_particles} in one compiled call; "
              f"about {args.mc_runs * run.run_s * args.mc_particles / args.particles / 60:.0f} "
              "min at the single run's speed, then smoothing (a progress bar)", flush=True)
        batch = vps.run_victoria_park_batch(jax.random.key(args.seed + 1), data, args.mc_runs,
                                            mc_config, params, observations=obs,
                                            num_scans=args.scans, steering_bias=bias,
                                            smooth=True, chunk=args.mc_chunk,
                                            smooth_visit_gap=args.smooth_visit_gap,
                                            smoother=settings.smoother)
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
