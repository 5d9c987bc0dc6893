"""What every ``jaxslam`` subcommand shares: the usage error and exit status, the compilation
cache, reading the study config, the output folder, one-line errors for a missing simulator.

Only the standard library is imported at module level (``jaxslam --help`` answers fast).
"""
from __future__ import annotations

import contextlib
import os
import pathlib
import sys


EXIT_USAGE = 2


class UsageError(ValueError):
    """Something the user asked for cannot be done; the message says what to change."""


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


@contextlib.contextmanager
def simulator_errors():
    """Run simulator code: a simulator, or a part of it, that is not installed
    (``jaxslam.simulators.SimulatorUnavailable``, e.g. MuJoCo for lidar scans, whose message
    names the install command) becomes a one-line ``UsageError``."""
    from jaxslam.simulators import SimulatorUnavailable

    try:
        yield
    except SimulatorUnavailable as error:
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


def _print_metrics(values: dict) -> None:
    width = max(len(name) for name in values)
    for name, value in values.items():
        text = f"{value:.6g}" if isinstance(value, float) else str(value)
        print(f"{name:<{width}}  {text}")
