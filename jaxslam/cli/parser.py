"""The ``jaxslam`` argument parser (every subcommand, help that shows defaults) and ``main``,
the console entry point."""
from __future__ import annotations

import argparse
import math
import os
import sys

from jaxslam import __version__
from jaxslam.cli.bench import BENCH_EPILOG, cmd_bench
from jaxslam.cli.common import EXIT_USAGE, _user_errors, cache_dir
from jaxslam.cli.config_show import cmd_config_show
from jaxslam.cli.export import cmd_export
from jaxslam.cli.logs import _add_topic_options, cmd_calibrate, cmd_convert
from jaxslam.cli.study import cmd_demo, cmd_run, cmd_study, cmd_sweep


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


def _subparser(sub, name: str, **options) -> argparse.ArgumentParser:
    """``sub.add_parser`` with the defaults-showing ``HelpFormatter``."""
    return sub.add_parser(name, formatter_class=HelpFormatter, **options)


def _add_set(parser: argparse.ArgumentParser) -> None:
    """--set KEY=VALUE (repeatable)."""
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="override a config entry, e.g. --set filter.num_particles=50 "
                             "--set params.max_range=15 (repeatable; `jaxslam config show` "
                             "lists every key with its unit)")


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
    run.add_argument("--close-loops", action="store_true",
                     help="with --smooth: close the loops the filter missed (register the "
                          "trees seen on a return onto the old landmarks, keep a closure only "
                          "if the smoother's cost accepts it; jaxslam.loop_closure)")
    run.add_argument("--visit-gap", type=int, default=None, metavar="STEPS",
                     help="with --smooth: split each landmark into visits separated by more "
                          "than STEPS steps, tied by robust links, so the smoother can drop "
                          "wrong loop closures (smooth_path(visit_gap=...); tried on "
                          "Victoria Park with 100 scans, about 20 s; see docs/results.md) "
                          "(default: none: one landmark per identity, no visits)")
    run.add_argument("--no-calibrate", action="store_true",
                     help="with --data: run with the config's params as given (default: off: "
                          "calibrate them from the log first and save calibrated_params.toml)")
    _add_no_scale_search(run, "with --data: ")
    _add_command_delay(run, "with --data: ")
    run.add_argument("--params", metavar="FILE",
                     help="with --data: a params TOML file (from `jaxslam calibrate` or a "
                          "previous run's calibrated_params.toml), used as it is (default: "
                          "none: calibrate, or the config's params with --no-calibrate)")
    _add_topic_options(run, "with --data BAG: ")
    _add_common(run, config_required=False, out_default="results/run")
    run.set_defaults(func=cmd_run)


def _add_convert(sub) -> None:
    convert = _subparser(sub, "convert", help="convert a ROS bag (LaserScan or PointCloud2 + "
                                              "odometry) or one robot of a UTIAS MRCLAM "
                                              "folder into a jaxslam .npz log")
    convert.add_argument("bag", metavar="source",
                         help="a ROS 1 .bag file, a ROS 2 bag folder (metadata.yaml with .db3 "
                              "or .mcap files) or a UTIAS MRCLAM dataset folder (Barcodes.dat, "
                              "RobotN_*.dat; give --robot)")
    convert.add_argument("--robot", type=int, default=None, metavar="N",
                         help="with an MRCLAM folder: the robot, 1-5 (the log keeps its "
                              "commanded velocities for --command-delay, and its Vicon path as "
                              "truth_pose) (default: none; required for an MRCLAM folder)")
    convert.add_argument("--out", required=True, help="the .npz log to write; .npz is added "
                                                      "when missing (required)")
    convert.add_argument("--compress", action="store_true",
                         help="write with numpy.savez_compressed")
    _add_topic_options(convert)
    convert.set_defaults(func=cmd_convert)


def _command_delay(text: str):
    """``--command-delay``'s value (``command_delay.command_delay_argument``; imported when
    the option is given: it loads jax)."""
    from jaxslam.command_delay import command_delay_argument

    return command_delay_argument(text)


def _add_command_delay(parser, prefix: str = "") -> None:
    parser.add_argument("--command-delay", type=_command_delay, default=None, metavar="S",
                        help=f"{prefix}the log's commands act S seconds later than stamped: "
                             "rebuild its moves from its command stream (command_time, "
                             "commands; docs/log_format.md) with that lag, or 'auto': fit the "
                             "lag from the log (jaxslam.fit_log_command_delay, no ground "
                             "truth) (default: none: the log's controls as they are)")


def _add_no_scale_search(parser, prefix: str = "") -> None:
    parser.add_argument("--no-scale-search", action="store_true",
                        help=f"{prefix}calibrate by EM alone, without multiplying the noise by "
                             "the scales of highest filter likelihood afterwards (faster: "
                             "up to 7 fewer filter runs) (default: off: search)")
    parser.add_argument("--fit-gain", action="store_true",
                        help=f"{prefix}also fit the odometry's systematic error, the gains "
                             "params.odometry_gain, from the log (right on the logs measured, "
                             "but the online filter did no better with them: docs/cli.md) "
                             "(default: off: the given gains)")
    parser.add_argument("--em-patience", type=int, default=2, metavar="N",
                        help=f"{prefix}stop the calibration's EM once N filter runs in a row "
                             "have not beaten the best log marginal likelihood before them, "
                             "and keep that best run's settings; 0: run until the noise stops "
                             "moving or 5 iterations (default: 2)")
    parser.add_argument("--em-significance", type=float, default=0.0, metavar="LEVEL",
                        help=f"{prefix}a later EM run replaces the best before it only when "
                             "its per-step log evidence is higher by a one-sided t test at "
                             "this level, e.g. 0.05 (over blocks of steps: one odd step does "
                             "not decide; measured mixed: docs/cli.md); 0: the highest "
                             "summed likelihood wins (default: 0)")
    parser.add_argument("--search-workers", type=int, default=None, metavar="N",
                        help=f"{prefix}filter runs of the noise-scale search run at once, each "
                             "in its own thread; the same choice for every N, only the time "
                             "and memory differ (default: 2 on a CPU with two or more cores, "
                             "else 1)")


def _add_calibrate(sub) -> None:
    calibrate = _subparser(sub, "calibrate", help="estimate the filter's noise and sensor "
                                                  "settings from a robot log alone; write TOML")
    calibrate.add_argument("--data", required=True, help="a robot log in the jaxslam .npz "
                                                         "format (required)")
    calibrate.add_argument("--out", required=True, help="params TOML file to write (required)")
    calibrate.add_argument("--config", help="study TOML whose filter/params to start from "
                                            "(default: none: the built-in defaults)")
    calibrate.add_argument("--seed", type=int, default=0, help="PRNG seed")
    calibrate.add_argument("--bootstrap", type=int, default=0, metavar="B",
                           help="also print each noise group's 95 %% interval from B "
                                "replicate logs drawn from the calibrated model and "
                                "calibrated again (parametric bootstrap: EM's bias and "
                                "spread, not only the sampling error; costs B calibrations; "
                                "odometry logs only; about 20) (default: 0: none)")
    _add_no_scale_search(calibrate)
    _add_command_delay(calibrate)
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
