"""The ``jaxslam`` command: demo, run, study, sweep, bench, export.

Only the standard library is imported at module level so that ``jaxslam --help`` answers fast;
JAX, the runner, pyarrow and matplotlib are imported inside the subcommands. Errors in what the
user gave (config keys and values, files) print one line naming the problem and exit with 2.
"""
from __future__ import annotations

import argparse
import importlib.util
import math
import os
import pathlib
import sys

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


def _out_dir(args, config) -> pathlib.Path:
    return pathlib.Path(args.out) if args.out else pathlib.Path("results") / config.name


def _write_plots(out_dir: pathlib.Path) -> list[str]:
    from jaxslam import plots

    return plots.plot_study(out_dir)


def _run_and_report(config, out_dir: pathlib.Path, quiet: bool) -> int:
    """Run (or resume) a study, print its summary, write its plots."""
    from jaxslam import studies

    enable_compilation_cache()
    print(f"study {config.name!r}: {config.num_runs} runs x {len(config.conditions)} "
          f"condition(s) -> {out_dir}", flush=True)
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
    out = pathlib.Path(args.out) if args.out else pathlib.Path("results") / "demo"
    return _run_and_report(demo_config(args.set), out, args.quiet)


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
    if args.smooth or args.visit_gap is not None or args.no_calibrate or args.params:
        raise UsageError("--smooth, --visit-gap, --no-calibrate and --params apply to a robot "
                         "log: pass --data FILE.npz too")
    config = _load_config(args.config, list(args.set or ())
                          + ["name=\"run\"", "num_runs=1", "chunk_size=1"])
    from jaxslam import plots, studies

    enable_compilation_cache()
    out = _out_dir(args, config)
    result = studies.run_study(config, out, progress=False)
    row = {name: values[0] for name, values in result.table.to_pydict().items()}
    _print_metrics({k: v for k, v in row.items() if k not in ("run_id", "condition", "seed")})
    print(f"wrote {plots.plot_map(out / 'example_run.npz', out / 'map.png')}")
    return 0


def _print_metrics(values: dict) -> None:
    width = max(len(name) for name in values)
    for name, value in values.items():
        text = f"{value:.6g}" if isinstance(value, float) else str(value)
        print(f"{name:<{width}}  {text}")


def _load_robot_log(path):
    from jaxslam.datasets.log_format import LogFormatError, load_log

    try:
        log = load_log(path)
        log.observations()
    except LogFormatError as error:
        raise UsageError(str(error)) from error
    return log


def _print_calibration(info) -> None:
    print(f"calibration: {info.verdict} ({info.iterations} iterations)")
    for name, value in info.values.items():
        text = (f"{value:.6g}" if isinstance(value, float)
                else "(" + ", ".join(f"{v:.6g}" for v in value) + ")")
        print(f"  {name:<24} {text}")


def _print_warnings(warnings) -> None:
    for line in warnings:
        print(f"WARNING: {line}")


def _run_log(args) -> int:
    """Filter a jaxslam .npz robot log; print the metrics its ground truth allows."""
    import json

    import numpy as np

    log = _load_robot_log(args.data)
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
        print("(the log has no truth_pose: no trajectory error to report)")
    np.savez(out / "example_run.npz", allow_pickle=False, **example)
    (out / "metrics.json").write_text(json.dumps(
        {"metrics": run.metrics, "warnings": list(run.warnings)}, indent=2) + "\n")
    from jaxslam import plots

    print(f"wrote {out / 'metrics.json'}")
    print(f"wrote {plots.plot_map(example, out / 'map.png', title=f'Map: {args.data}')}")
    return 0


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
    """Run the pipeline over a log. Returns (example_run arrays, ``pipeline.LogRun``)."""
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
                              map_match_threshold=study.map_match_threshold,
                              progress=print)
    est = run.estimate
    truth = np.zeros((0, 3)) if log.truth_pose is None else np.asarray(log.truth_pose)
    trees = np.zeros((0, 2)) if log.truth_landmarks is None else np.asarray(log.truth_landmarks)
    example = dict(truth_pose=truth, mean_pose=run.mean_pose,
                   landmark_mean=np.asarray(est.landmark_mean),
                   landmark_cov=np.asarray(est.landmark_cov), active=np.asarray(est.active),
                   tree_centres=trees, tree_radii=np.zeros(len(trees)))  # radii unknown: markers only
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


def cmd_bench(args) -> int:
    """Run ``benchmarks/filter_step.py`` (imported by path: it is not part of the package)."""
    if not BENCHMARK_PATH.is_file():
        raise UsageError(f"the benchmark script {BENCHMARK_PATH} is not here (it ships with the "
                         "source tree, not the installed package); run from a source checkout")
    spec = importlib.util.spec_from_file_location("jaxslam_benchmark_filter_step", BENCHMARK_PATH)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    enable_compilation_cache()
    if hasattr(module, "main"):
        result = module.main(list(args.bench_args))
        return int(result) if isinstance(result, int) else 0
    raise UsageError(f"{BENCHMARK_PATH} defines no main(argv) function; run it directly with "
                     f"python {BENCHMARK_PATH}")


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


def cmd_export(args) -> int:
    """Write the example run's true and estimated trajectories as TUM text (for evo)."""
    from jaxslam import plots

    results = pathlib.Path(args.results_dir)
    source = results / "example_run.npz" if results.is_dir() else results
    if not source.is_file():
        raise UsageError(f"{source} does not exist; expected a study folder holding "
                         "example_run.npz (run a study or `jaxslam run` first)")
    try:
        run = plots.load_example_run(source)
    except ValueError as error:
        raise UsageError(f"{source}: {error}") from error
    out = pathlib.Path(args.out) if args.out else source.parent
    out.mkdir(parents=True, exist_ok=True)
    # truth row k is the pose after k steps; estimate row t is the pose after step t + 1.
    offset = len(run.truth_pose) - len(run.mean_pose)
    written = []
    for name, poses, first in (("truth", run.truth_pose, 0), ("estimate", run.mean_pose, offset)):
        path = out / f"{name}.tum"
        times = (first + _arange(len(poses))) * args.dt
        path.write_text("\n".join([TUM_HEADER] + tum_lines(times, poses)) + "\n")
        written.append(path)
        print(f"wrote {path} ({len(poses)} poses)")
    print(f"compare with evo:  evo_ape tum {written[0]} {written[1]} --align")
    return 0


def _arange(count: int):
    import numpy as np

    return np.arange(count, dtype=np.float64)


# ------------------------------------------------------------------------------------------
# Parser


def _add_common(parser: argparse.ArgumentParser, config_required: bool) -> None:
    if config_required:
        parser.add_argument("config", help="study TOML file (sections: filter, scenario, "
                                           "params, sweep)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="override a config entry, e.g. --set filter.num_particles=50 "
                             "--set params.max_range=15 (repeatable)")
    parser.add_argument("--out", help="output folder (default: results/<study name>)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="jaxslam", description="Batched FastSLAM for forestry robots: Monte Carlo "
        "studies, sweeps and single runs.",
        epilog="Compiled functions are cached in " + str(cache_dir()) + ".")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    demo = sub.add_parser("demo", help="small study on the default simulated forest "
                                        "(a few minutes on a laptop CPU): table and plots")
    _add_common(demo, config_required=False)
    demo.set_defaults(func=cmd_demo)

    run = sub.add_parser("run", help="one run of the default scenario, or of a robot log "
                                      "(--data FILE.npz); prints metrics, writes map.png")
    run.add_argument("--data", help="a robot log in the jaxslam .npz format")
    run.add_argument("--config", help="study TOML whose filter/params/scenario to use")
    run.add_argument("--seed", type=int, default=0, help="PRNG seed for --data (default 0)")
    run.add_argument("--smooth", action="store_true",
                     help="with --data: also smooth the best particle's history (its "
                          "associations fixed; jaxslam.smoothing) and report its errors")
    run.add_argument("--visit-gap", type=int, default=None, metavar="STEPS",
                     help="with --smooth: split each landmark into visits separated by more "
                          "than STEPS steps, tied by robust links, so the smoother can drop "
                          "wrong loop closures (smooth_path(visit_gap=...); tried on "
                          "Victoria Park with 100 scans, about 20 s; see docs/results.md)")
    run.add_argument("--no-calibrate", action="store_true",
                     help="with --data: run with the config's params as given (default: "
                          "calibrate them from the log first and save calibrated_params.toml)")
    run.add_argument("--params", metavar="FILE",
                     help="with --data: a params TOML file (from `jaxslam calibrate` or a "
                          "previous run's calibrated_params.toml), used as it is")
    _add_common(run, config_required=False)
    run.set_defaults(func=cmd_run)

    calibrate = sub.add_parser("calibrate", help="estimate the filter's noise and sensor "
                                                 "settings from a robot log alone; write TOML")
    calibrate.add_argument("--data", required=True, help="a robot log in the jaxslam .npz "
                                                          "format")
    calibrate.add_argument("--out", required=True, help="params TOML file to write")
    calibrate.add_argument("--config", help="study TOML whose filter/params to start from")
    calibrate.add_argument("--seed", type=int, default=0, help="PRNG seed (default 0)")
    calibrate.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                           help="override a config entry (repeatable)")
    calibrate.set_defaults(func=cmd_calibrate)

    study = sub.add_parser("study", help="a Monte Carlo study from a TOML file")
    _add_common(study, config_required=True)
    study.set_defaults(func=cmd_study)

    sweep = sub.add_parser("sweep", help="a parameter sweep from a TOML file with a [sweep] "
                                          "section")
    _add_common(sweep, config_required=True)
    sweep.set_defaults(func=cmd_sweep)

    sub.add_parser("bench", help="filter speed benchmark (benchmarks/filter_step.py); the "
                                 "arguments after 'bench' go to the script (try: bench --help)")

    export = sub.add_parser("export", help="trajectories of a study's example run as TUM text")
    export.add_argument("results_dir", help="study folder (or an example_run.npz file)")
    export.add_argument("--format", choices=["tum"], default="tum", help="output format")
    export.add_argument("--dt", type=float, default=1.0,
                        help="seconds per filter step for the timestamps (default 1)")
    export.add_argument("--out", help="output folder (default: next to example_run.npz)")
    export.set_defaults(func=cmd_export)
    return parser


def main(argv=None) -> int:
    """Entry point of the ``jaxslam`` console script. Returns the exit status."""
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == ["bench"]:  # everything after "bench" belongs to the benchmark script
        args = argparse.Namespace(command="bench", func=cmd_bench, bench_args=argv[1:])
    else:
        args = build_parser().parse_args(argv)
    if getattr(args, "dt", 1.0) <= 0 or not math.isfinite(getattr(args, "dt", 1.0)):
        print(f"jaxslam {args.command}: error: --dt={args.dt}; expected a positive number of "
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
