"""The simulated-study subcommands: ``demo``, ``study``, ``sweep`` and ``run`` (one run of the
default scenario, or of a robot log with --data: ``jaxslam.cli.logs``).
"""
from __future__ import annotations

import pathlib

from jaxslam.cli import common
from jaxslam.cli.common import (UsageError, _flatten_overrides, _load_config, _out_dir,
                                _print_metrics, simulator_errors)
from jaxslam.cli.logs import _run_log, _topic_options_given


def _write_plots(out_dir: pathlib.Path) -> list[str]:
    from jaxslam import plots

    return plots.plot_study(out_dir)


def _run_and_report(config, out_dir: pathlib.Path, quiet: bool) -> int:
    """Run (or resume) a study, print its summary, write its plots."""
    from jaxslam import studies

    common.enable_compilation_cache()
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
    if (args.smooth or args.visit_gap is not None or args.close_loops or args.no_calibrate
            or args.params or args.command_delay is not None or args.no_scale_search):
        raise UsageError("--smooth, --visit-gap, --close-loops, --no-calibrate, --params, "
                         "--command-delay and --no-scale-search apply to a robot log: pass "
                         "--data FILE.npz too")
    one_run = ["name=\"run\"", "num_runs=1", "chunk_size=1"]
    config = _load_config(args.config, list(args.set or ()) + one_run)
    from jaxslam import plots, studies

    common.enable_compilation_cache()
    out = _out_dir(args, config, reference=_load_config(args.config, one_run))
    with simulator_errors():
        result = studies.run_study(config, out, progress=False)
    row = {name: values[0] for name, values in result.table.to_pydict().items()}
    _print_metrics({k: v for k, v in row.items()
                    if k not in ("run_id", "condition", "study_seed", "run_key")})
    print(f"wrote {plots.plot_map(out / 'example_run.npz', out / 'map.png')}")
    return 0
