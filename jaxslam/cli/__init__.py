"""The ``jaxslam`` command: demo, run, calibrate, convert, study, sweep, config, bench, export.

Only the standard library is imported at module level so that ``jaxslam --help`` answers fast;
JAX, the runner, pyarrow and matplotlib are imported inside the subcommands. Errors in what the
user gave (config keys and values, files) print one line naming the problem and exit with 2.

Modules: ``common`` (what every subcommand shares), ``study`` (demo, study, sweep, run),
``logs`` (robot logs and ROS bags: run --data, calibrate, convert), ``config_show``,
``export``, ``bench``, and ``parser`` (the argument parser and ``main``). Every name is
re-exported here, so ``from jaxslam.cli import main`` and ``python -m jaxslam.cli`` work.
"""
from __future__ import annotations

from jaxslam.cli.bench import BENCH_EPILOG, BENCHMARK_PATH, cmd_bench  # noqa: F401
from jaxslam.cli.common import (EXIT_USAGE, UsageError, _load_config, _out_dir,  # noqa: F401
                                _print_metrics, cache_dir, enable_compilation_cache,
                                simulator_errors)
from jaxslam.cli.config_show import (CONFIG_UNITS, cmd_config_show, config_rows,  # noqa: F401
                                     config_unit, format_config_rows, toml_value)
from jaxslam.cli.export import (TUM_HEADER, cmd_export, read_study_folder_config,  # noqa: F401
                                tum_lines, yaw_to_quaternion)
from jaxslam.cli.logs import (cmd_calibrate, cmd_convert, log_error_traces,  # noqa: F401
                              _filter_log, _load_robot_log, _log_settings)
from jaxslam.cli.parser import (HelpFormatter, build_parser, main,  # noqa: F401
                                subcommand_parsers)
from jaxslam.cli.study import cmd_demo, cmd_run, cmd_study, cmd_sweep, demo_config  # noqa: F401
