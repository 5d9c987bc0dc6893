"""MuJoCo-MJX forest simulation: forest worlds, lidar scans, robot paths and scenarios.

The names below are loaded lazily (PEP 562), and MuJoCo itself only when an MJX world, a lidar
scan or the wheeled robot is built (``sims.mujoco_loader``): analytic scenarios and
``import sims`` need no MuJoCo. The simulator's physics is installed with
``pip install "jaxslam[sim]"``.
"""
from __future__ import annotations

import importlib

_PUBLIC = {
    "Clutter": "sims.forest",
    "Forest": "sims.forest",
    "World": "sims.forest",
    "forest_mjcf": "sims.forest",
    "make_world": "sims.forest",
    "mj_model_of": "sims.forest",
    "plantation_forest": "sims.forest",
    "random_clutter": "sims.forest",
    "random_forest": "sims.forest",
    "sample_radii": "sims.forest",
    "world_from_forest": "sims.forest",
    "TABLE2_RANGE_NOISE": "sims.lidar",
    "Scan": "sims.lidar",
    "add_range_noise": "sims.lidar",
    "beam_angles": "sims.lidar",
    "clip_3d_to_2d": "sims.lidar",
    "layer_elevations": "sims.lidar",
    "scan_2d": "sims.lidar",
    "scan_2d_full": "sims.lidar",
    "scan_3d": "sims.lidar",
    "lawnmower_path": "sims.paths",
    "loop_path": "sims.paths",
    "noisy_odometry": "sims.paths",
    "path_clearance": "sims.paths",
    "random_smooth_path": "sims.paths",
    "resample_polyline": "sims.paths",
    "true_moves": "sims.paths",
    "Scenario": "sims.scenario",
    "analytic_observations": "sims.scenario",
    "build_scenario": "sims.scenario",
    "default_scenario": "sims.scenario",
}
_SUBMODULES = ("batch", "forest", "lidar", "mujoco_loader", "paths", "robot", "scenario")

__all__ = sorted(_PUBLIC)


def __getattr__(name: str):
    if name in _PUBLIC:
        value = getattr(importlib.import_module(_PUBLIC[name]), name)
        globals()[name] = value
        return value
    if name in _SUBMODULES:
        return importlib.import_module(f"sims.{name}")
    raise AttributeError(f"module 'sims' has no attribute {name!r}")


def __dir__():
    return __all__ + list(_SUBMODULES)
