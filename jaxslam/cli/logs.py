"""Robot logs on the command line: ``run --data`` (filter a log, optionally calibrate and
smooth), ``calibrate`` and ``convert`` (a ROS bag into a jaxslam .npz log), and the ROS bag
options they share (``_TOPIC_OPTIONS``, ``_add_topic_options``).
"""
from __future__ import annotations

import argparse
import os
import pathlib

from jaxslam.cli import common
from jaxslam.cli.common import UsageError, _load_config, _print_metrics


_TOPIC_OPTIONS = (("--scan-topic", "scan_topic"), ("--cloud-topic", "cloud_topic"),
                  ("--odom-topic", "odom_topic"), ("--truth-topic", "truth_topic"),
                  ("--time-source", "time_source"), ("--cloud-detection", "cloud_detection"))


def _topic_options_given(args) -> list[str]:
    """The bag options (``_TOPIC_OPTIONS``) set on the command line, as flags."""
    return [flag for flag, name in _TOPIC_OPTIONS if getattr(args, name, None) is not None]


def _add_topic_options(parser: argparse.ArgumentParser, prefix: str = "") -> None:
    """The ROS bag options: --scan-topic, --cloud-topic, --odom-topic, --truth-topic,
    --time-source, --cloud-detection (``jaxslam.datasets.load_rosbag``)."""
    parser.add_argument("--scan-topic", metavar="TOPIC",
                        help=f"{prefix}the sensor_msgs/LaserScan topic (default: the bag's only "
                             "LaserScan topic)")
    parser.add_argument("--cloud-topic", metavar="TOPIC",
                        help=f"{prefix}a sensor_msgs/PointCloud2 topic instead (see "
                             "--cloud-detection) (default: the only PointCloud2 topic when "
                             "there is no "
                             "LaserScan)")
    parser.add_argument("--odom-topic", metavar="TOPIC",
                        help=f"{prefix}the nav_msgs/Odometry (or PoseStamped, TF odom -> "
                             "base_link) topic (default: the bag's only Odometry topic)")
    parser.add_argument("--truth-topic", metavar="TOPIC",
                        help=f"{prefix}a ground-truth pose topic (Odometry or PoseStamped) for "
                             "truth_pose (default: none: no truth)")
    parser.add_argument("--time-source", choices=["header", "bag"],
                        help=f"{prefix}time messages by their header stamps or by the times "
                             "the recorder received them (default: header)")
    parser.add_argument("--cloud-detection", choices=["cylinder", "slice"],
                        help=f"{prefix}trunks in a PointCloud2: 3D cylinder fits, or a "
                             "flattened height band with circle fits (default: cylinder)")


def _load_robot_log(path, args=None):
    """The ``RobotLog`` at ``path``: a ROS bag (``jaxslam.datasets.rosbag_reader.is_rosbag_path``:
    a .bag/.db3/.mcap name or a folder with metadata.yaml), read with the bag options of
    ``args``, else a jaxslam .npz log. Any problem with the file becomes a one-line
    ``UsageError``."""
    from jaxslam.datasets.log_format import LogFormatError, load_log
    from jaxslam.datasets.rosbag import load_rosbag
    from jaxslam.datasets.rosbag_reader import is_rosbag_path

    try:
        if is_rosbag_path(path):
            options = {name: getattr(args, name) for _, name in _TOPIC_OPTIONS
                       if getattr(args, name, None) is not None}
            log = load_rosbag(path, progress=print, **options)
        else:
            given = _topic_options_given(args)
            if given:
                raise UsageError(f"{given[0]} applies to a ROS bag (a .bag file or a ROS 2 "
                                 f"bag folder); {path} is read as a jaxslam .npz log")
            log = load_log(path)
        log.observations()
    except LogFormatError as error:
        hint = (" (nor a ROS 2 bag folder: it holds no metadata.yaml; docs/rosbag.md)"
                if os.path.isdir(path) else "")
        raise UsageError(f"{error}{hint}") from error
    return log


def _print_calibration(info) -> None:
    from jaxslam.calibration_residuals import NOISE_GROUP_UNITS, NOISE_GROUPS
    from jaxslam.self_calibration import em_typical_std, group_scales, interval_text

    print(f"calibration: {info.verdict} ({info.iterations} iterations)")
    for name, value in info.values.items():
        text = (f"{value:.6g}" if isinstance(value, float)
                else "(" + ", ".join(f"{v:.6g}" for v in value) + ")")
        print(f"  {name:<24} {text}")
    if not info.relative_std or not len(info.typical_std):
        return
    scales, fitted = group_scales(info), em_typical_std(info)
    print("  noise std fitted by EM (rms over this log) +- 95 % relative interval "
          "(sampling error only; docs/cli.md):")
    for group, (name, unit) in enumerate(zip(NOISE_GROUPS, NOISE_GROUP_UNITS)):
        if name not in info.relative_std:
            continue
        line = (f"    {name:<12} {fitted[group]:.4g} {unit} "
                f"{interval_text(info.relative_std[name])}")
        if scales[group] != 1.0:
            line += (f"  (x{scales[group]:g} by the likelihood's search: "
                     f"{info.typical_std[-1, group]:.4g} {unit} used)")
        print(line)
    if "radius" in info.relative_std and "radius_noise" in info.values:
        print(f"    {'radius':<12} {info.values['radius_noise']:.4g} m "
              f"{interval_text(info.relative_std['radius'])}  (bootstrap over the "
              f"landmarks of {info.samples.get('radius', 0)} radii)")


def _print_bootstrap(args, filter_config, log, start_params, params, info) -> None:
    """Print ``calibration_bootstrap.bootstrap_intervals`` of a ``jaxslam calibrate`` run."""
    import jax
    import numpy as np

    from jaxslam.calibration_bootstrap import bootstrap_intervals
    from jaxslam.calibration_residuals import NOISE_GROUP_UNITS, NOISE_GROUPS

    if not info.values:
        print("parametric bootstrap: skipped, the calibration fitted nothing")
        return
    print(f"parametric bootstrap: {args.bootstrap} replicate logs drawn from the calibrated "
          "model, each calibrated again ...")
    found = bootstrap_intervals(
        filter_config, jax.random.PRNGKey(args.seed), log.controls.astype("float32"),
        log.observations(), log.initial_pose, start_params, params, info,
        replicates=args.bootstrap,
        progress=lambda done, total: print(f"  replicate {done} of {total}", flush=True),
        **{k: v for k, v in _calibration_options(args).items() if k != "scale_search"})
    print("  noise std fitted by EM (rms over this log, before the likelihood's search, "
          "fitted bursts counted), the replicates' mean factor over the noise they were "
          "drawn with, and the 95 % interval for the log's true std:")
    for group, (name, unit) in enumerate(zip(NOISE_GROUPS, NOISE_GROUP_UNITS)):
        if name not in info.relative_std:
            continue
        line = f"    {name:<12} {found.estimate[group]:.4g} {unit}  "
        if found.failed[group]:
            line += (f"no interval: {found.failed[group]} of {args.bootstrap} replicates "
                     "fitted nothing")
        else:
            line += (f"replicates x{np.exp(found.bias[group]):.2f}  "
                     f"[{found.lower[group]:.4g}, {found.upper[group]:.4g}] {unit}")
        print(line)


def _print_warnings(lines) -> None:
    for line in lines:
        print(f"WARNING: {line}")


def _run_log(args) -> int:
    """Filter a jaxslam .npz robot log; print the metrics its ground truth allows; write
    example_run.npz (with the log's timestamps), metrics.json, map.png and, when the log has
    a truth_pose, error_vs_time.png."""
    import json

    import numpy as np

    log = _load_robot_log(args.data, args)
    out = pathlib.Path(args.out) if args.out else pathlib.Path("results") / "run"
    out.mkdir(parents=True, exist_ok=True)
    example, run = _filter_log(args, log)
    from jaxslam import pipeline

    if run.calibration is not None:
        _print_calibration(run.calibration)
        saved = pipeline.save_params(out / "calibrated_params.toml", run.params,
                                     comment=f"calibrated from {args.data} by jaxslam run "
                                     f"({run.calibration.verdict})"
                                     + _delay_note(run.metrics.get("command_delay")),
                                     sensor_noise_calibrated=pipeline.sensor_noise_calibrated(
                                         run.calibration))
        print(f"wrote {saved} (reuse it with --params {saved})")
    _print_metrics(run.metrics)
    _print_warnings(run.warnings)
    if log.truth_pose is None:
        print("(the log has no truth_pose: no trajectory error to report, no error_vs_time.png)")
    np.savez(out / "example_run.npz", allow_pickle=False, **example)
    (out / "metrics.json").write_text(json.dumps(
        {"metrics": run.metrics, "warnings": list(run.warnings)}, indent=2) + "\n")
    from jaxslam import plots

    print(f"wrote {out / 'example_run.npz'}")
    print(f"wrote {out / 'metrics.json'}")
    print(f"wrote {plots.plot_map(example, out / 'map.png', title=f'Map: {args.data}')}")
    error_plot = _plot_log_errors(example, out / "error_vs_time.png", args.data)
    if error_plot is not None:
        print(f"wrote {error_plot}")
    return 0


def log_error_traces(example: dict):
    """``plots.Traces`` of a log run's position error per step [m] against its truth_pose:
    condition 0 the filter's estimate, condition 1 the smoothed path when the run has one.
    None when the example holds no truth (truth_pose with no rows)."""
    import numpy as np

    from jaxslam import plots

    truth = np.asarray(example["truth_pose"], np.float64)
    if len(truth) == 0:
        return None
    paths = [example["mean_pose"]]
    if "smoothed_pose" in example:
        paths.append(example["smoothed_pose"])
    errors = [np.hypot(*(np.asarray(path, np.float64)[:, :2] - truth[:, :2]).T)
              for path in paths]
    return plots.Traces(run_id=np.zeros(len(errors), np.int64),
                        condition=np.arange(len(errors), dtype=np.int64),
                        pose_error=np.stack(errors))


def _plot_log_errors(example: dict, out_png: pathlib.Path, name) -> str | None:
    """error_vs_time.png of a log run (``log_error_traces``); None without truth."""
    from jaxslam import plots

    traces = log_error_traces(example)
    if traces is None:
        return None
    labels = {0: "filter estimate (weighted mean)", 1: "smoothed path"}
    return plots.plot_error_vs_time(traces, out_png, labels,
                                    title=f"Position error over time: {name}")


def _log_settings(args, log):
    """(study config, FilterConfig sized to the log, Params, calibrate?) for a log run.

    The Params are a ``--params`` file's (used as they are), the calibration's start
    (``starting_params`` with the config's [params]), or the config's values
    (``--no-calibrate``).
    """
    import dataclasses

    from jaxslam import pipeline
    from jaxslam.self_calibration import starting_params
    from jaxslam.types import default_params

    study = _load_config(args.config, args.set)
    obs = log.observations()
    filter_config = dataclasses.replace(study.filter, max_obs=int(obs.z.shape[1]),
                                        motion_model=log.motion_model)
    params_file = getattr(args, "params", None)
    calibrate = not getattr(args, "no_calibrate", False) and params_file is None
    if params_file is not None:
        try:
            params = pipeline.load_params(params_file, filter_config)
        except ValueError as error:
            raise UsageError(str(error)) from error
    elif calibrate:
        params = starting_params(filter_config, **dict(study.params))
    else:
        params = default_params(filter_config, **dict(study.params))
    return study, filter_config, params, calibrate


def _apply_command_delay(args, log):
    """(log, delay): ``log`` with its commands delayed by ``--command-delay`` (seconds, or
    "auto": fitted from the log, printed with its profile) and the delay [s]; (log, None)
    when the option was not given."""
    import jax

    from jaxslam.command_delay import DelayFitError, log_at_command_delay
    from jaxslam.self_calibration import starting_params

    choice = getattr(args, "command_delay", None)
    if choice is None:
        return log, None
    if log.command_time is None:
        raise UsageError(f"--command-delay {choice}: {args.data} has no command stream "
                         "('command_time' and 'commands', the commanded velocities its "
                         "controls were integrated from; docs/log_format.md; a ROS bag's "
                         "conversion keeps none)")
    study, filter_config, params, _ = _log_settings(args, log)
    if getattr(args, "params", None) is None:  # the calibration's start, also --no-calibrate
        params = starting_params(filter_config, **dict(study.params))
    try:
        delayed, fit = log_at_command_delay(log, filter_config, jax.random.PRNGKey(args.seed),
                                            choice, params, progress=print)
    except DelayFitError as error:  # a log that cannot give the lag: say why, in one line
        raise UsageError(f"--command-delay {choice}: {error}") from error
    return delayed, float(choice) if fit is None else fit.delay


def _filter_log(args, log):
    """Run the pipeline over a log. Returns (example_run arrays, ``pipeline.LogRun``).

    The example holds the log's ``time`` (T,) [s]: row t of mean_pose (and of truth_pose and
    smoothed_pose) is the pose at time[t], after the log's control row t.
    """
    import jax
    import numpy as np

    from jaxslam import pipeline

    common.enable_compilation_cache()
    smooth = bool(getattr(args, "smooth", False))
    visit_gap = getattr(args, "visit_gap", None)
    if visit_gap is not None and not smooth:
        raise UsageError(f"--visit-gap {visit_gap} needs --smooth (it splits the smoothed "
                         "history's landmarks into visits)")
    if visit_gap is not None and visit_gap < 1:
        raise UsageError(f"--visit-gap {visit_gap}: the gap must be at least 1 step")
    close = bool(getattr(args, "close_loops", False))
    if close and not smooth:
        raise UsageError("--close-loops needs --smooth (it closes loops in the smoothed "
                         "history)")
    if close and visit_gap is not None:
        raise UsageError("--close-loops and --visit-gap: choose one (visits are the "
                         "smoother's own soft loop closures)")
    options = _calibration_options(args)  # checked before the lag's fit
    log, delay = _apply_command_delay(args, log)
    study, filter_config, params, calibrate = _log_settings(args, log)
    # A --params file that a calibration saved with its sensor noise fitted: the warnings
    # then do not advise calibrating again (a hand-written file, or one whose calibration
    # fitted no sensor noise, still gets that advice).
    params_file = getattr(args, "params", None)
    reused = params_file is not None and pipeline.saved_sensor_calibration(params_file)
    run = pipeline.filter_log(log, filter_config, params, jax.random.PRNGKey(args.seed),
                              calibrate=calibrate, smooth=smooth, visit_gap=visit_gap,
                              close_loops=close, settings_calibrated=True if reused else None,
                              map_match_threshold=study.map_match_threshold, progress=print,
                              calibration_options=options)
    est = run.estimate
    truth = np.zeros((0, 3)) if log.truth_pose is None else np.asarray(log.truth_pose)
    trees = np.zeros((0, 2)) if log.truth_landmarks is None else np.asarray(log.truth_landmarks)
    example = dict(truth_pose=truth, mean_pose=run.mean_pose,
                   landmark_mean=np.asarray(est.landmark_mean),
                   landmark_cov=np.asarray(est.landmark_cov), active=np.asarray(est.active),
                   tree_centres=trees, tree_radii=np.zeros(len(trees)),  # radii unknown
                   time=np.asarray(log.time, np.float64))
    if run.smoothed_pose is not None:
        example["smoothed_pose"] = run.smoothed_pose
    if delay is not None:
        run.metrics["command_delay"] = delay
    return example, run


def _delay_note(delay) -> str:
    """The params file's note of the command delay they were calibrated at ("" for none).
    The command it suggests carries the delay to the last digit (``repr``): the moves are
    rebuilt from the commands at that delay, and a delay rounded to the millisecond gives
    slightly other moves, which a long run does not forgive."""
    return ("" if delay is None else
            f"; at commands {delay:.3f} s late: run with --command-delay {float(delay)!r}")


def _calibration_options(args) -> dict:
    """``calibrate_params`` keywords from the command line (``--no-scale-search``,
    ``--fit-gain``, ``--em-patience N``, 0 for none; ``--em-significance LEVEL``, 0 for
    none; ``--search-workers N``, absent for the default)."""
    patience = getattr(args, "em_patience", 2)
    if patience < 0:
        raise UsageError(f"--em-patience must be 0 (no early stop) or a positive number "
                         f"of filter runs; got {patience}")
    workers = getattr(args, "search_workers", None)
    if workers is not None and workers < 1:
        raise UsageError(f"--search-workers must be a positive number of filter runs at "
                         f"once; got {workers}")
    significance = getattr(args, "em_significance", 0.0)
    if not 0.0 <= significance < 1.0:
        raise UsageError(f"--em-significance must be a level in (0, 1), or 0 for the highest "
                         f"summed likelihood; got {significance}")
    return {"scale_search": not getattr(args, "no_scale_search", False),
            "calibrate_gain": getattr(args, "fit_gain", False),
            "patience": patience or None, "search_workers": workers,
            "significance": significance or None}


def cmd_calibrate(args) -> int:
    """Calibrate the filter's settings from a log alone and write them as TOML."""
    import jax

    from jaxslam import pipeline
    from jaxslam.self_calibration import calibrate_params

    common.enable_compilation_cache()
    log = _load_robot_log(args.data)
    if args.bootstrap and args.bootstrap < 2:
        raise UsageError(f"--bootstrap needs B >= 2 replicates (about 20); got "
                         f"{args.bootstrap}")
    options = _calibration_options(args)  # checked before the lag's fit
    log, delay = _apply_command_delay(args, log)
    if args.bootstrap and log.motion_model != "odometry":
        raise UsageError(f"--bootstrap draws odometry moves (rot1, trans, rot2); this log's "
                         f"motion model is {log.motion_model!r}")
    _, filter_config, start_params, _ = _log_settings(args, log)
    params, info = calibrate_params(
        filter_config, jax.random.PRNGKey(args.seed), log.controls.astype("float32"),
        log.observations(), log.initial_pose, start_params, progress=print,
        **options)
    _print_calibration(info)
    _print_warnings(info.warnings)
    saved = pipeline.save_params(args.out, params, comment=f"calibrated from {args.data} by "
                                 f"jaxslam calibrate ({info.verdict})" + _delay_note(delay),
                                 sensor_noise_calibrated=pipeline.sensor_noise_calibrated(info))
    again = "" if delay is None else f" --command-delay {float(delay)!r}"
    print(f"wrote {saved} (use it with: jaxslam run --data {args.data} --params {saved}"
          f"{again})")
    if args.bootstrap:
        _print_bootstrap(args, filter_config, log, start_params, params, info)
    return 0


def _mrclam_robot(args):
    """``convert``'s MRCLAM branch: the ``RobotLog`` of robot ``--robot`` when ``args.bag``
    is an MRCLAM folder (it holds ``Barcodes.dat``), else None (``--robot`` is then refused)."""
    from jaxslam.datasets.log_format import LogFormatError
    from jaxslam.datasets.mrclam import BARCODES_NAME, NUM_ROBOTS, load_mrclam

    robot = getattr(args, "robot", None)
    if not (pathlib.Path(args.bag) / BARCODES_NAME).is_file():
        if robot is not None:
            raise UsageError(f"--robot {robot} applies to a UTIAS MRCLAM folder (one holding "
                             f"{BARCODES_NAME}); {args.bag} is not one")
        return None
    if robot is None or not 1 <= robot <= NUM_ROBOTS:
        raise UsageError(f"{args.bag} is a UTIAS MRCLAM folder of {NUM_ROBOTS} robots: give "
                         f"--robot 1..{NUM_ROBOTS}" + ("" if robot is None else
                                                        f" (got {robot})"))
    try:
        return load_mrclam(args.bag, robot)
    except LogFormatError as error:
        raise UsageError(str(error)) from error


def cmd_convert(args) -> int:
    """Convert a ROS bag into a jaxslam .npz log (trunks detected per scan), check that the
    written file loads back, and print what it holds."""
    import numpy as np

    from jaxslam.datasets.log_format import LogFormatError, load_log, save_log
    from jaxslam.datasets.rosbag_reader import resolve_bag_path

    log = _mrclam_robot(args)
    if log is None:
        try:
            resolve_bag_path(args.bag)
        except LogFormatError as error:
            raise UsageError(str(error)) from error
        log = _load_robot_log(args.bag, args)
    out = pathlib.Path(args.out)
    if out.suffix != ".npz":  # numpy.savez would add it anyway; say the real name
        out = out.with_name(out.name + ".npz")
    out.parent.mkdir(parents=True, exist_ok=True)
    save_log(out, log, compress=args.compress)
    try:
        back = load_log(out)
    except LogFormatError as error:  # a bug, or a disk problem: say so plainly
        raise UsageError(f"{out} was written but does not load back: {error}") from error
    if back.num_steps != log.num_steps or not np.array_equal(back.obs_valid, log.obs_valid):
        raise UsageError(f"{out} was written but reads back differently ({back.num_steps} "
                         f"steps, expected {log.num_steps}); check the disk and rerun")
    valid = int(back.obs_valid.sum())
    span = float(back.time[-1] - back.time[0])
    commands = ("" if back.command_time is None else
                f", {back.command_time.shape[0]} commanded velocities")
    path_length = float(np.sum(back.controls[:, 1]))
    print(f"wrote {out}: {back.num_steps} steps over {span:.1f} s, {valid} landmark "
          f"detections ({valid / back.num_steps:.1f} per step), odometry path "
          f"{path_length:.1f} m{commands}, "
          + ("with" if back.truth_pose is not None else "without") + " truth_pose")
    print(f"run it with: jaxslam run --data {out}"
          + ("" if back.command_time is None else " (--command-delay auto: fit the "
             "commands' lag first)"))
    return 0
