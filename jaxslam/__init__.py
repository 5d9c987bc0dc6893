"""jaxslam: JAX-accelerated, batched FastSLAM for forestry robots.

The public API is loaded lazily (PEP 562) so that ``import jaxslam.cli`` and ``jaxslam --help``
do not pay for importing JAX.
"""
from __future__ import annotations

import importlib

__version__ = "0.1.0"

_PUBLIC = {
    "FilterConfig": "jaxslam.types",
    "FilterState": "jaxslam.types",
    "Particles": "jaxslam.types",
    "Observations": "jaxslam.types",
    "Params": "jaxslam.types",
    "default_params": "jaxslam.types",
    "make_observations": "jaxslam.types",
    "empty_observations": "jaxslam.types",
    "make_filter": "jaxslam.filter",
    "run_filter": "jaxslam.filter",
    "scan_filter": "jaxslam.filter",
    "Trace": "jaxslam.filter",
    "Estimate": "jaxslam.filter",
    "estimate": "jaxslam.filter",
    "validate_observations": "jaxslam.filter",
    "Filter": "jaxslam.filter",
    "StepInfo": "jaxslam.filter",
    "stable_match": "jaxslam.association",
    "Lineage": "jaxslam.lineage",
    "trace_lineage": "jaxslam.lineage",
    "smooth_lineage": "jaxslam.smoothing",
    "smooth_path": "jaxslam.smoothing",
    "calibrate_params": "jaxslam.self_calibration",
    "CalibrationInfo": "jaxslam.self_calibration",
    "starting_params": "jaxslam.self_calibration",
    "fit_command_delay": "jaxslam.command_delay",
    "fit_log_command_delay": "jaxslam.command_delay",
    "DelayFit": "jaxslam.command_delay",
    "filter_log": "jaxslam.pipeline",
    "LogRun": "jaxslam.pipeline",
}

# Submodules a user reaches as ``jaxslam.NAME`` without importing them first.
_SUBMODULES = ("metrics",)

__all__ = sorted(_PUBLIC) + list(_SUBMODULES) + ["__version__"]


def __getattr__(name: str):
    if name in _PUBLIC:
        value = getattr(importlib.import_module(_PUBLIC[name]), name)
        globals()[name] = value
        return value
    if name in _SUBMODULES:
        return importlib.import_module(f"jaxslam.{name}")
    raise AttributeError(f"module 'jaxslam' has no attribute {name!r}")


def __dir__():
    return __all__
