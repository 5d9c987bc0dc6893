"""The ``jaxslam`` command: demo, run, calibrate, convert, study, sweep, config, bench, export.

Only the standard library is imported at module level so that ``jaxslam --help`` answers fast;
JAX, the runner, pyarrow and matplotlib are imported inside the subcommands. Errors in what the
user gave (config keys and values, files) print one line naming the problem and exit with 2.
"""
from __future__ import annotations

import argparse
import contextlib
import importlib.util
import math
import os
import pathlib
import sys

from jaxslam import __version__

EXIT_USAGE = 2
_REPO_ROOT = pathlib.Path(__file__).resolve().parent.parent
BENCHMARK_PATH = _REPO_ROOT / "benchmarks" / "filter_step.py"
TUM_HEADER = "# timestamp x y z qx qy qz qw"



class UsageError(ValueError):
    """Something the user asked for cannot be done; the message says what to change."""


# ------------------------------------------------------------------------------------------
# Helpers


def cache_dir() -> pathlib.Path:
    """Where the JAX persistent compilation cache lives: $JAXSLAM_CACHE_DIR, else
    $XDG_CACHE_HOME/jaxslam/jax, else ~/.cache/jaxslam/jax."""
    if os.environ.get("JAXSLAM_CACHE_DIR"):
        return pathlib.Path(os.environ["JAXSLAM_CACHE_DIR"])
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return pathlib.Path(base) / "jaxslam" / "jax"


def enable_compilation_cache() -> pathlib.Path:
    """Turn on JAX's persistent compilation cache (a rerun skips most compile time)."""
    import jax

    path = cache_dir()
    path.mkdir(parents=True, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", str(path))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
    return path


def import_mujoco_quietly() -> None:
    """Import MuJoCo MJX now if it is installed, without the two "Failed to import warp" lines
    it prints to stdout when the optional NVIDIA Warp backend is absent (anything else printed
    passes on). Does nothing when MuJoCo is not installed.

    The simulator imports MuJoCo this quietly by itself when it first needs it
    (``sims.mujoco_loader``); this is for code that imports ``mujoco`` directly.
    """
    from sims.mujoco_loader import import_quietly

    with contextlib.suppress(ImportError):
        import_quietly("mujoco.mjx")


@contextlib.contextmanager
def simulator_errors():
    """Run simulator code: MuJoCo missing (``sims.mujoco_loader.SimulatorNotInstalled``, whose
    message names the install command) becomes a one-line ``UsageError``."""
    from sims.mujoco_loader import SimulatorNotInstalled

    try:
        yield
    except SimulatorNotInstalled as error:
        raise UsageError(str(error)) from error


def _user_errors() -> tuple:
    """Exception types that mean "bad input" (reported in one line, exit 2). Anything else is
    a bug and keeps its traceback."""
    errors = [UsageError]
    studies = sys.modules.get("jaxslam.studies")
    if studies is not None and hasattr(studies, "StudyError"):
        errors.append(studies.StudyError)
    return tuple(errors)


def _load_config(path, overrides):
    """The study config; a bad key, value or file becomes a ``UsageError``."""
    from jaxslam import studies

    try:
        return studies.load_study_config(path, list(overrides or ()))
    except (ValueError, TypeError, FileNotFoundError) as error:
        raise UsageError(str(error)) from error


def _out_dir(args, config, reference=None) -> pathlib.Path:
    """``--out``, else ``results/<name>`` for the config as its file (or the demo) defines
    it, and ``results/<name>-<digest>`` once ``--set`` changes anything but num_runs or
    chunk_size (``study_store.default_out_dir``): a trial run never blocks the full study."""
    if args.out:
        return pathlib.Path(args.out)
    from jaxslam import studies, study_store

    if reference is None:
        reference = _load_config(getattr(args, "config", None), [])
    return study_store.default_out_dir(config.name, studies.study_config_to_dict(config),
                                       studies.study_config_to_dict(reference))


def _write_plots(out_dir: pathlib.Path) -> list[str]:
    from jaxslam import plots

    return plots.plot_study(out_dir)


def _run_and_report(config, out_dir: pathlib.Path, quiet: bool) -> int:
    """Run (or resume) a study, print its summary, write its plots."""
    from jaxslam import studies

    enable_compilation_cache()
    print(f"study {config.name!r}: {config.num_runs} runs x {len(config.conditions)} "
          f"condition(s) -> {out_dir}", flush=True)
    with simulator_errors():
        result = studies.run_study(config, out_dir, progress=not quiet)
    print((pathlib.Path(out_dir) / "summary.md").read_text())
    print(f"compile {result.compile_seconds:.1f} s, filter {result.filter_seconds:.1f} s, "
          f"simulator {result.simulator_seconds:.1f} s (this invocation)")
    for path in _write_plots(pathlib.Path(out_dir)):
        print(f"wrote {path}")
    return 0


# ------------------------------------------------------------------------------------------
# Subcommands


def demo_config(overrides=()):
    """``studies.demo_study_config()`` with "section.key=value" overrides applied on top."""
    from jaxslam import studies

    config = studies.demo_study_config()
    if not overrides:
        return config
    base = studies.study_config_to_dict(config)
    return _load_config(None, _flatten_overrides(base) + list(overrides))


def cmd_demo(args) -> int:
    """The small default study on the simulated forest: summary table and plots."""
    config = demo_config(args.set)
    return _run_and_report(config, _out_dir(args, config, reference=demo_config()), args.quiet)


def _flatten_overrides(data: dict, prefix: str = "") -> list[str]:
    """A config dict as "section.key=value" overrides (TOML value syntax)."""
    import json

    items = []
    for key, value in data.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            items += _flatten_overrides(value, name + ".")
        else:
            items.append(f"{name}={json.dumps(value)}")
    return items


def cmd_study(args) -> int:
    """A study from a TOML file with command-line overrides."""
    config = _load_config(args.config, args.set)
    return _run_and_report(config, _out_dir(args, config), args.quiet)


def cmd_sweep(args) -> int:
    """Like ``study`` but the config must hold a [sweep] section."""
    config = _load_config(args.config, args.set)
    if not config.sweep:
        raise UsageError(f"{args.config}: the sweep command needs a [sweep] section mapping "
                         "filter parameters to lists of values, e.g. [sweep] "
                         "mixture_ratio = [0.0, 0.3]; or pass --set sweep.NAME=[...]")
    return _run_and_report(config, _out_dir(args, config), args.quiet)


def cmd_run(args) -> int:
    """One run: of the default scenario (a one-run study), or of a robot log (--data)."""
    if args.data:
        return _run_log(args)
    given = _topic_options_given(args)
    if given:
        raise UsageError(f"{given[0]} applies to a ROS bag: pass --data BAG too")
    if args.smooth or args.visit_gap is not None or args.no_calibrate or args.params:
        raise UsageError("--smooth, --visit-gap, --no-calibrate and --params apply to a robot "
                         "log: pass --data FILE.npz too")
    one_run = ["name=\"run\"", "num_runs=1", "chunk_size=1"]
    config = _load_config(args.config, list(args.set or ()) + one_run)
    from jaxslam import plots, studies

    enable_compilation_cache()
    out = _out_dir(args, config, reference=_load_config(args.config, one_run))
    with simulator_errors():
        result = studies.run_study(config, out, progress=False)
    row = {name: values[0] for name, values in result.table.to_pydict().items()}
    _print_metrics({k: v for k, v in row.items()
                    if k not in ("run_id", "condition", "study_seed", "run_key")})
    print(f"wrote {plots.plot_map(out / 'example_run.npz', out / 'map.png')}")
    return 0


def _print_metrics(values: dict) -> None:
    width = max(len(name) for name in values)
    for name, value in values.items():
        text = f"{value:.6g}" if isinstance(value, float) else str(value)
        print(f"{name:<{width}}  {text}")


# The ROS bag options: (flag, attribute), the attribute being the load_rosbag keyword.
_TOPIC_OPTIONS = (("--scan-topic", "scan_topic"), ("--cloud-topic", "cloud_topic"),
                  ("--odom-topic", "odom_topic"), ("--truth-topic", "truth_topic"),
                  ("--time-source", "time_source"))


def _topic_options_given(args) -> list[str]:
    """The bag options (``_TOPIC_OPTIONS``) set on the command line, as flags."""
    return [flag for flag, name in _TOPIC_OPTIONS if getattr(args, name, None) is not None]


def _load_robot_log(path, args=None):
    """The ``RobotLog`` at ``path``: a ROS bag (``jaxslam.datasets.rosbag.is_rosbag_path``:
    a .bag/.db3/.mcap name or a folder with metadata.yaml), read with the bag options of
    ``args``, else a jaxslam .npz log. Any problem with the file becomes a one-line
    ``UsageError``."""
    from jaxslam.datasets.log_format import LogFormatError, load_log
    from jaxslam.datasets.rosbag import is_rosbag_path, load_rosbag

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
    print(f"calibration: {info.verdict} ({info.iterations} iterations)")
    for name, value in info.values.items():
        text = (f"{value:.6g}" if isinstance(value, float)
                else "(" + ", ".join(f"{v:.6g}" for v in value) + ")")
        print(f"  {name:<24} {text}")


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
                                     f"({run.calibration.verdict})")
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


def _filter_log(args, log):
    """Run the pipeline over a log. Returns (example_run arrays, ``pipeline.LogRun``).

    The example holds the log's ``time`` (T,) [s]: row t of mean_pose (and of truth_pose and
    smoothed_pose) is the pose at time[t], after the log's control row t.
    """
    import jax
    import numpy as np

    from jaxslam import pipeline

    enable_compilation_cache()
    smooth = bool(getattr(args, "smooth", False))
    visit_gap = getattr(args, "visit_gap", None)
    if visit_gap is not None and not smooth:
        raise UsageError(f"--visit-gap {visit_gap} needs --smooth (it splits the smoothed "
                         "history's landmarks into visits)")
    if visit_gap is not None and visit_gap < 1:
        raise UsageError(f"--visit-gap {visit_gap}: the gap must be at least 1 step")
    study, filter_config, params, calibrate = _log_settings(args, log)
    run = pipeline.filter_log(log, filter_config, params, jax.random.PRNGKey(args.seed),
                              calibrate=calibrate, smooth=smooth, visit_gap=visit_gap,
                              map_match_threshold=study.map_match_threshold, progress=print)
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
    return example, run


def cmd_calibrate(args) -> int:
    """Calibrate the filter's settings from a log alone and write them as TOML."""
    import jax

    from jaxslam import pipeline
    from jaxslam.self_calibration import calibrate_params

    enable_compilation_cache()
    log = _load_robot_log(args.data)
    _, filter_config, params, _ = _log_settings(args, log)
    params, info = calibrate_params(
        filter_config, jax.random.PRNGKey(args.seed), log.controls.astype("float32"),
        log.observations(), log.initial_pose, params, progress=print)
    _print_calibration(info)
    _print_warnings(info.warnings)
    saved = pipeline.save_params(args.out, params, comment=f"calibrated from {args.data} by "
                                 f"jaxslam calibrate ({info.verdict})")
    print(f"wrote {saved} (use it with: jaxslam run --data {args.data} --params {saved})")
    return 0


def cmd_convert(args) -> int:
    """Convert a ROS bag into a jaxslam .npz log (trunks detected per scan), check that the
    written file loads back, and print what it holds."""
    import numpy as np

    from jaxslam.datasets.log_format import LogFormatError, load_log, save_log
    from jaxslam.datasets.rosbag import resolve_bag_path

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
    path_length = float(np.sum(back.controls[:, 1]))
    print(f"wrote {out}: {back.num_steps} steps over {span:.1f} s, {valid} trunk detections "
          f"({valid / back.num_steps:.1f} per scan), odometry path {path_length:.1f} m, "
          + ("with" if back.truth_pose is not None else "without") + " truth_pose")
    print(f"run it with: jaxslam run --data {out}")
    return 0


def cmd_bench(args) -> int:
    """Run ``benchmarks/filter_step.py`` (imported by path: it is not part of the package)."""
    if not BENCHMARK_PATH.is_file():
        raise UsageError(f"the benchmark script {BENCHMARK_PATH} is not here (it ships with the "
                         "source tree, not the installed package); run from a source checkout")
    import_mujoco_quietly()
    spec = importlib.util.spec_from_file_location("jaxslam_benchmark_filter_step", BENCHMARK_PATH)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    enable_compilation_cache()
    if hasattr(module, "main"):
        with simulator_errors():
            result = module.main(list(args.bench_args))
        return int(result) if isinstance(result, int) else 0
    raise UsageError(f"{BENCHMARK_PATH} defines no main(argv) function; run it directly with "
                     f"python {BENCHMARK_PATH}")


# ------------------------------------------------------------------------------------------
# config show

from jaxslam.columns import CONFIG_UNITS, config_unit  # noqa: E402,F401 (units table)


def toml_value(value) -> str:
    """A config value in TOML syntax (what ``--set KEY=VALUE`` reads back): 64, 0.5, true,
    "loop", inf, [0.0, 0.06, 0.0002]. Floats keep 6 significant digits."""
    import json

    import numpy as np

    if hasattr(value, "__array__") and not isinstance(value, (list, tuple)):
        array = np.asarray(value)  # NumPy or JAX array: a scalar or a flat list
        value = array.item() if array.ndim == 0 else array.ravel().tolist()
    if isinstance(value, (bool, np.bool_)):
        return "true" if value else "false"
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(toml_value(v) for v in value) + "]"
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    number = float(value)
    if math.isnan(number):
        return "nan"
    if math.isinf(number):
        return "inf" if number > 0 else "-inf"
    text = f"{number:.6g}"
    return text if any(c in text for c in ".e") else text + ".0"


def config_rows(config) -> list[tuple[str, str, str, str]]:
    """(key, value, unit, note) of every entry of a resolved study config.

    Study, [filter] and [scenario] keys come from ``study_config_to_dict``; [params] lists
    every ``Params`` field with the value the filter runs with (note "set in the config",
    "= scenario.max_range" or "default"); [sweep] lists the swept values.
    """
    from jaxslam import studies
    from jaxslam.types import default_params

    data = studies.study_config_to_dict(config)
    rows = []
    for section in ("", "filter", "scenario"):
        items = data[section].items() if section else (
            (k, v) for k, v in data.items() if not isinstance(v, dict))
        for key, value in items:
            name = f"{section}.{key}" if section else key
            rows.append((name, toml_value(value), config_unit(name), ""))
    given, swept = dict(config.params), dict(config.sweep)
    resolved = default_params(config.filter, **{"max_range": config.scenario.max_range,
                                                **given})
    for key, value in resolved._asdict().items():
        note = (f"swept: see sweep.{key}" if key in swept else
                "set in the config" if key in given else
                "= scenario.max_range" if key == "max_range" else
                "= sqrt(association_gate)" if key == "airlock_sigmas" else "default")
        rows.append((f"params.{key}", toml_value(value), config_unit(f"params.{key}"), note))
    for key, values in data["sweep"].items():
        rows.append((f"sweep.{key}", toml_value(values), config_unit(f"sweep.{key}"),
                     "swept: one condition per value"))
    return rows


def format_config_rows(rows) -> list[str]:
    """Aligned "key  value  unit  # note" lines with a header."""
    header = ("# key", "value", "unit", "")
    widths = [max(len(row[i]) for row in [header, *rows]) for i in range(3)]
    lines = []
    for key, value, unit, note in [header, *rows]:
        line = f"{key:<{widths[0]}}  {value:<{widths[1]}}  {unit:<{widths[2]}}"
        lines.append((line + (f"  # {note}" if note else "")).rstrip())
    return lines


def cmd_config_show(args) -> int:
    """Print the resolved study config: every key, its value and its unit."""
    if args.file is None:
        config = demo_config(args.set)
        source = "the demo config (`jaxslam demo`)"
    else:
        config = _load_config(args.file, args.set)
        source = str(args.file)
    overrides = f" with {len(args.set)} --set override(s)" if args.set else ""
    print(f"# study config {config.name!r}: {source}{overrides}; "
          f"{len(config.conditions)} condition(s)")
    print("# values in TOML syntax: each line works as --set KEY=VALUE")
    for line in format_config_rows(config_rows(config)):
        print(line)
    return 0


# ------------------------------------------------------------------------------------------
# export


def yaw_to_quaternion(yaw):
    """(qx, qy, qz, qw) of a rotation by ``yaw`` about +z. yaw: (T,) -> four (T,) arrays."""
    import numpy as np

    half = 0.5 * np.asarray(yaw, np.float64)
    zero = np.zeros_like(half)
    return zero, zero, np.sin(half), np.cos(half)


def tum_lines(timestamps, poses) -> list[str]:
    """TUM trajectory lines ``timestamp x y z qx qy qz qw`` of planar poses (T, 3)."""
    import numpy as np

    poses = np.asarray(poses, np.float64)
    if poses.ndim != 2 or poses.shape[1] != 3:
        raise UsageError(f"poses have shape {poses.shape}; expected (T, 3) rows (x, y, theta)")
    qx, qy, qz, qw = yaw_to_quaternion(poses[:, 2])
    rows = np.stack([np.asarray(timestamps, np.float64), poses[:, 0], poses[:, 1],
                     np.zeros(len(poses)), qx, qy, qz, qw], axis=1)
    return [" ".join(f"{value:.9f}" for value in row) for row in rows]


def _step_times(truth, estimate, dt: float):
    """Timestamps on a step time base: truth row k is the pose after k steps when the truth
    has one more row than the estimate (a study: row 0 is the start), else after k + 1
    steps; estimate row t is the pose after step t + 1. Returns (truth times, estimate times).
    """
    import numpy as np

    first = 0 if len(truth) == len(estimate) + 1 else 1
    return ((first + np.arange(len(truth), dtype=np.float64)) * dt,
            (1 + np.arange(len(estimate), dtype=np.float64)) * dt)


def _example_tracks(source: pathlib.Path, dt) -> list[tuple[str, object, object]]:
    """(name, timestamps, poses) of an example_run.npz: truth (when it has rows), estimate,
    smoothed (when it holds smoothed_pose). A log run's own ``time`` is the time base, else
    ``dt`` seconds per step (default 1)."""
    import numpy as np

    from jaxslam import plots

    try:
        run = plots.load_example_run(source)
    except ValueError as error:
        raise UsageError(f"{source}: {error}") from error
    with np.load(source, allow_pickle=False) as arrays:
        extra = {name: arrays[name] for name in ("time", "smoothed_pose") if name in arrays}
    if "time" in extra:
        if dt is not None:
            raise UsageError(f"--dt {dt}: {source} holds its log's own timestamps (time), which "
                             "the export uses; leave --dt out")
        times = np.asarray(extra["time"], np.float64)
        if times.shape != (len(run.mean_pose),):
            raise UsageError(f"{source}: time has shape {times.shape}; expected "
                             f"({len(run.mean_pose)},), one timestamp per mean_pose row")
        if len(run.truth_pose) not in (0, len(times)):
            raise UsageError(f"{source}: truth_pose has {len(run.truth_pose)} rows; expected "
                             f"{len(times)}, one per timestamp (or none)")
        truth_times, estimate_times = times, times
    else:
        truth_times, estimate_times = _step_times(run.truth_pose, run.mean_pose,
                                                  1.0 if dt is None else dt)
    tracks = [("estimate", estimate_times, run.mean_pose)]
    if len(run.truth_pose):
        tracks.insert(0, ("truth", truth_times, run.truth_pose))
    if "smoothed_pose" in extra:
        smoothed = np.asarray(extra["smoothed_pose"], np.float64)
        if smoothed.shape != run.mean_pose.shape:
            raise UsageError(f"{source}: smoothed_pose has shape {smoothed.shape}; expected "
                             f"{run.mean_pose.shape} like mean_pose")
        tracks.append(("smoothed", estimate_times, smoothed))
    return tracks


def read_study_folder_config(folder: pathlib.Path):
    """The ``StudyConfig`` of a study folder (its study.toml); UsageError when there is none
    or it cannot be read."""
    import tomllib

    from jaxslam import studies

    path = folder / "study.toml"
    if not path.is_file():
        raise UsageError(f"{path} does not exist; --run and --condition need a study folder "
                         "(written by jaxslam demo, study or sweep)")
    try:
        with open(path, "rb") as handle:
            return studies.study_config_from_dict(tomllib.load(handle))
    except (tomllib.TOMLDecodeError, ValueError, TypeError) as error:
        raise UsageError(f"{path}: cannot read the study config ({error})") from error


def _check_run_and_condition(config, folder, run: int, condition: int) -> None:
    """UsageError naming the valid range when run or condition is outside the study."""
    if not 0 <= run < config.num_runs:
        raise UsageError(f"--run {run} is out of range: the study in {folder} has runs 0 to "
                         f"{config.num_runs - 1} (num_runs = {config.num_runs})")
    conditions = config.conditions
    if not 0 <= condition < len(conditions):
        listed = "; ".join(f"{i}: " + (", ".join(f"{k}={v}" for k, v in c.items()) or "default")
                           for i, c in enumerate(conditions))
        raise UsageError(f"--condition {condition} is out of range: the study in {folder} has "
                         f"conditions 0 to {len(conditions) - 1} ({listed})")


def _study_run_tracks(folder: pathlib.Path, run: int, condition: int, dt):
    """(name, timestamps, poses) of run ``run`` under condition ``condition`` of a study,
    simulated and filtered again (``studies.recompute_runs``: the same numbers as the stored
    ones). The time base is ``dt`` seconds per step (default 1): the simulated scenario has
    no clock of its own."""
    import numpy as np

    config = read_study_folder_config(folder)
    _check_run_and_condition(config, folder, run, condition)
    from jaxslam import studies

    enable_compilation_cache()
    print(f"recomputing run {run} of {folder} (all {len(config.conditions)} condition(s))",
          flush=True)
    with simulator_errors():
        output = studies.recompute_runs(config, run, run + 1)
    truth = np.asarray(output.scenario.truth_pose, np.float64)
    truth = truth[0] if truth.ndim == 3 else truth  # a per-run world: this run's own path
    estimate = np.asarray(output.example["mean_pose"], np.float64)[condition, 0]
    truth_times, estimate_times = _step_times(truth, estimate, 1.0 if dt is None else dt)
    return [("truth", truth_times, truth), ("estimate", estimate_times, estimate)]


def _write_tum(out: pathlib.Path, tracks) -> list[pathlib.Path]:
    """Write ``<name>.tum`` per (name, timestamps, poses); print each."""
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for name, times, poses in tracks:
        path = out / f"{name}.tum"
        path.write_text("\n".join([TUM_HEADER] + tum_lines(times, poses)) + "\n")
        written.append(path)
        print(f"wrote {path} ({len(poses)} poses)")
    return written


def cmd_export(args) -> int:
    """Write a run's true and estimated trajectories (and the smoothed one when the run has
    it) as TUM text for evo: the example run of a folder, or run I / condition C of a study."""
    import numpy as np

    results = pathlib.Path(args.results_dir)
    if args.run is not None or args.condition is not None:
        if not results.is_dir():
            raise UsageError(f"{results} is not a folder; --run and --condition need a study "
                             "folder holding study.toml")
        run, condition = args.run or 0, args.condition or 0
        tracks = _study_run_tracks(results, run, condition, args.dt)
        default_out = results / f"run-{run}-condition-{condition}"
    else:
        source = results / "example_run.npz" if results.is_dir() else results
        if not source.is_file():
            raise UsageError(f"{source} does not exist; expected a study folder holding "
                             "example_run.npz (run a study or `jaxslam run` first)")
        tracks = _example_tracks(source, args.dt)
        default_out = source.parent
    written = _write_tum(pathlib.Path(args.out) if args.out else default_out, tracks)
    poses = {name: pose for name, _, pose in tracks}
    if "truth" in poses:
        final = float(np.hypot(*(poses["estimate"][-1, :2] - poses["truth"][-1, :2])))
        print(f"final position error {final:.6g} m")
        print(f"compare with evo:  evo_ape tum {written[0]} {written[1]} --align")
    else:
        print("(the run has no truth poses: only the estimate is written)")
    return 0


# ------------------------------------------------------------------------------------------
# Parser


class HelpFormatter(argparse.RawDescriptionHelpFormatter):
    """Help that shows every option's default: "(default: X)" is added to each option's help
    unless the text already says "(default"; a flag says "(default: off)". An option whose
    default is None says in its own help text what happens without it."""

    def _get_help_string(self, action):
        text = action.help or ""
        if (not action.option_strings or action.required or "(default" in text
                or action.default is argparse.SUPPRESS or action.default is None):
            return text
        if isinstance(action, (argparse._StoreTrueAction, argparse._StoreFalseAction)):
            return f"{text} (default: {'on' if action.default else 'off'})"
        if action.default == []:
            return f"{text} (default: none)"
        return f"{text} (default: %(default)s)"


def _add_common(parser: argparse.ArgumentParser, config_required: bool,
                out_default: str = "results/<study name>") -> None:
    """The options every study-like subcommand takes: [config], --set, --out, --quiet."""
    if config_required:
        parser.add_argument("config", help="study TOML file (sections: filter, scenario, "
                                           "params, sweep)")
    _add_set(parser)
    parser.add_argument("--out", help=f"output folder (default: {out_default}; with --set "
                                      "changing anything but num_runs or chunk_size, "
                                      "<that folder>-<8-digit config digest>)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def _add_set(parser: argparse.ArgumentParser) -> None:
    """--set KEY=VALUE (repeatable)."""
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="override a config entry, e.g. --set filter.num_particles=50 "
                             "--set params.max_range=15 (repeatable; `jaxslam config show` "
                             "lists every key with its unit)")


def _add_run(sub) -> None:
    run = _subparser(sub, "run", help="one run of the default scenario, or of a robot log "
                                      "(--data FILE.npz or a ROS bag); prints metrics, writes "
                                      "map.png")
    run.add_argument("--data", help="a robot log: a jaxslam .npz file, a ROS 1 .bag file or a "
                                    "ROS 2 bag folder (docs/rosbag.md) (default: none: one "
                                    "run of the simulated default scenario)")
    run.add_argument("--config", help="study TOML whose filter/params/scenario to use "
                                      "(default: none: the built-in defaults)")
    run.add_argument("--seed", type=int, default=0, help="PRNG seed for --data")
    run.add_argument("--smooth", action="store_true",
                     help="with --data: also smooth the best particle's history (its "
                          "associations fixed; jaxslam.smoothing) and report its errors")
    run.add_argument("--visit-gap", type=int, default=None, metavar="STEPS",
                     help="with --smooth: split each landmark into visits separated by more "
                          "than STEPS steps, tied by robust links, so the smoother can drop "
                          "wrong loop closures (smooth_path(visit_gap=...); tried on "
                          "Victoria Park with 100 scans, about 20 s; see docs/results.md) "
                          "(default: none: one landmark per identity, no visits)")
    run.add_argument("--no-calibrate", action="store_true",
                     help="with --data: run with the config's params as given (default: off: "
                          "calibrate them from the log first and save calibrated_params.toml)")
    run.add_argument("--params", metavar="FILE",
                     help="with --data: a params TOML file (from `jaxslam calibrate` or a "
                          "previous run's calibrated_params.toml), used as it is (default: "
                          "none: calibrate, or the config's params with --no-calibrate)")
    _add_topic_options(run, "with --data BAG: ")
    _add_common(run, config_required=False, out_default="results/run")
    run.set_defaults(func=cmd_run)


def _add_topic_options(parser: argparse.ArgumentParser, prefix: str = "") -> None:
    """The ROS bag options: --scan-topic, --cloud-topic, --odom-topic, --truth-topic,
    --time-source (``jaxslam.datasets.load_rosbag``)."""
    parser.add_argument("--scan-topic", metavar="TOPIC",
                        help=f"{prefix}the sensor_msgs/LaserScan topic (default: the bag's only "
                             "LaserScan topic)")
    parser.add_argument("--cloud-topic", metavar="TOPIC",
                        help=f"{prefix}a sensor_msgs/PointCloud2 topic instead, flattened to a "
                             "scan (default: the only PointCloud2 topic when there is no "
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


def _add_convert(sub) -> None:
    convert = _subparser(sub, "convert", help="convert a ROS bag (LaserScan or PointCloud2 + "
                                              "odometry) into a jaxslam .npz log")
    convert.add_argument("bag", help="a ROS 1 .bag file or a ROS 2 bag folder (metadata.yaml "
                                     "with .db3 or .mcap files)")
    convert.add_argument("--out", required=True, help="the .npz log to write; .npz is added "
                                                      "when missing (required)")
    convert.add_argument("--compress", action="store_true",
                         help="write with numpy.savez_compressed")
    _add_topic_options(convert)
    convert.set_defaults(func=cmd_convert)


def _add_calibrate(sub) -> None:
    calibrate = _subparser(sub, "calibrate", help="estimate the filter's noise and sensor "
                                                  "settings from a robot log alone; write TOML")
    calibrate.add_argument("--data", required=True, help="a robot log in the jaxslam .npz "
                                                         "format (required)")
    calibrate.add_argument("--out", required=True, help="params TOML file to write (required)")
    calibrate.add_argument("--config", help="study TOML whose filter/params to start from "
                                            "(default: none: the built-in defaults)")
    calibrate.add_argument("--seed", type=int, default=0, help="PRNG seed")
    _add_set(calibrate)
    calibrate.set_defaults(func=cmd_calibrate)


def _add_config(sub) -> None:
    config = _subparser(sub, "config", help="show a study config: every key, its value and "
                                            "its unit")
    actions = config.add_subparsers(dest="config_command", metavar="ACTION", required=True)
    show = _subparser(actions, "show", help="print the resolved study config",
                      description="Print the resolved study config: every key (as --set "
                      "takes it), its value in TOML\nsyntax and its unit; [params] lists every "
                      "filter parameter with the value the filter\nruns with.")
    show.add_argument("file", nargs="?", metavar="FILE",
                      help="study TOML file (default: the demo config of `jaxslam demo`)")
    _add_set(show)
    show.set_defaults(func=cmd_config_show)


BENCH_EPILOG = """\
Everything after "bench" goes to the script unchanged, except a first -h/--help (this help).
Put "--" first to pass -h/--help or anything else through explicitly.

examples:
  jaxslam bench                               the step case at (P, M, K) = (100, 64, 16)
                                              and (1000, 128, 16)
  jaxslam bench --batch-runs 1000 --chunk 250 also R = 1000 batched runs, 250 per chunk
  jaxslam bench --association greedy --proposal mixture
  jaxslam bench -- --help                     the script's own options

The script ships with the source tree, not the installed package: run from a checkout."""


def _add_bench(sub) -> None:
    bench = _subparser(
        sub, "bench", help="filter speed benchmark (benchmarks/filter_step.py); arguments "
                           "pass through to the script (see bench --help)",
        usage="jaxslam bench [-h] [--] [SCRIPT_ARG ...]", epilog=BENCH_EPILOG,
        description="Run the filter speed benchmark benchmarks/filter_step.py: compile and "
                    "run time apart,\nfor one filter step and, optionally, batched runs.")
    bench.add_argument("script_args", nargs="*", metavar="SCRIPT_ARG",
                       help="arguments for benchmarks/filter_step.py (default: none: its "
                            "defaults; see `jaxslam bench -- --help`)")
    bench.set_defaults(func=cmd_bench)


def _add_export(sub) -> None:
    export = _subparser(sub, "export", help="trajectories of a run as TUM text (for evo)")
    export.add_argument("results_dir", help="a study or run folder (or an example_run.npz "
                                            "file)")
    export.add_argument("--format", choices=["tum"], default="tum", help="output format")
    export.add_argument("--run", type=int, metavar="I",
                        help="export run I of the study folder, simulated and filtered again "
                             "(default: none: the stored example run, run 0 / condition 0)")
    export.add_argument("--condition", type=int, metavar="C",
                        help="with --run: the sweep condition (default: 0)")
    export.add_argument("--dt", type=float, default=None,
                        help="seconds per filter step for the timestamps of a study run "
                             "(default: 1; a `jaxslam run --data` run uses its log's own "
                             "timestamps instead)")
    export.add_argument("--out", help="output folder (default: next to example_run.npz; "
                                      "with --run: STUDY/run-I-condition-C)")
    export.set_defaults(func=cmd_export)


def _subparser(sub, name: str, **options) -> argparse.ArgumentParser:
    """``sub.add_parser`` with the defaults-showing ``HelpFormatter``."""
    return sub.add_parser(name, formatter_class=HelpFormatter, **options)


def build_parser() -> argparse.ArgumentParser:
    """The ``jaxslam`` argument parser with every subcommand."""
    parser = argparse.ArgumentParser(
        prog="jaxslam", formatter_class=HelpFormatter,
        description="Batched FastSLAM for forestry robots: Monte Carlo studies, sweeps and "
                    "single runs.",
        epilog="Compiled functions are cached in " + str(cache_dir()) + ".")
    parser.add_argument("--version", action="version", version=f"jaxslam {__version__}",
                        help="print the version and exit")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    demo = _subparser(sub, "demo", help="small study on the default simulated forest "
                                        "(a few minutes on a laptop CPU): table and plots")
    _add_common(demo, config_required=False, out_default="results/demo")
    demo.set_defaults(func=cmd_demo)
    _add_run(sub)
    _add_calibrate(sub)
    _add_convert(sub)
    study = _subparser(sub, "study", help="a Monte Carlo study from a TOML file")
    _add_common(study, config_required=True)
    study.set_defaults(func=cmd_study)
    sweep = _subparser(sub, "sweep", help="a parameter sweep from a TOML file with a [sweep] "
                                          "section")
    _add_common(sweep, config_required=True)
    sweep.set_defaults(func=cmd_sweep)
    _add_config(sub)
    _add_bench(sub)
    _add_export(sub)
    return parser


def subcommand_parsers(parser: argparse.ArgumentParser, prefix: str = "") -> dict:
    """{"run": parser, "config show": parser, ...}: every (nested) subcommand's parser."""
    found = {}
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, child in action.choices.items():
                found[prefix + name] = child
                found.update(subcommand_parsers(child, prefix + name + " "))
    return found


def _bench_args(argv: list[str]):
    """Namespace for ``jaxslam bench ...`` (None after printing bench's own help): every
    argument goes to the script, a leading "--" dropped."""
    if argv[:1] in (["-h"], ["--help"]):
        subcommand_parsers(build_parser())["bench"].print_help()
        return None
    if argv[:1] == ["--"]:
        argv = argv[1:]
    return argparse.Namespace(command="bench", func=cmd_bench, bench_args=list(argv))


def main(argv=None) -> int:
    """Entry point of the ``jaxslam`` console script. Returns the exit status."""
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == ["bench"]:  # the script's own options are not declared here
        args = _bench_args(argv[1:])
        if args is None:
            return 0
    else:
        args = build_parser().parse_args(argv)
    dt = getattr(args, "dt", None)
    if dt is not None and not (math.isfinite(dt) and dt > 0):
        print(f"jaxslam {args.command}: error: --dt={dt}; expected a positive number of "
              "seconds", file=sys.stderr)
        return EXIT_USAGE
    try:
        return args.func(args)
    except KeyboardInterrupt:
        print(f"jaxslam {args.command}: interrupted; rerun the same command to resume",
              file=sys.stderr)
        return 130
    except _user_errors() as error:
        if os.environ.get("JAXSLAM_DEBUG"):
            raise
        print(f"jaxslam {args.command}: error: {error}", file=sys.stderr)
        print("(set JAXSLAM_DEBUG=1 for the traceback)", file=sys.stderr)
        return EXIT_USAGE


if __name__ == "__main__":
    sys.exit(main())
