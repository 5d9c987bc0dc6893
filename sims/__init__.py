"""MuJoCo-MJX forest simulation: forest worlds, lidar scans, robot paths and scenarios.

``sims.scan_3d`` is ``sims.scan3d.scan_3d`` (a point cloud, with the per-beam ranges of
``sims.lidar.scan_3d`` kept as ``Cloud.ranges``); leaning-trunk forests on uneven ground are
``sims.forest3d``.

The names below are loaded lazily (PEP 562), and MuJoCo itself only when an MJX world, a lidar
scan or the wheeled robot is built (``sims.mujoco_loader``): analytic scenarios and
``import sims`` need no MuJoCo. The simulator's physics is installed with
``pip install "jaxslam[sim]"``.

Importing ``sims`` registers it as the study simulator "sims" (``jaxslam.simulators``): its
[scenario] settings are ``sims.config.ScenarioConfig``, its runs ``sims.batch.scenario_batch``
(imported at the first simulation; the MJX wheeled robot's runs are ``sims.robot_runs``). A
study config naming ``simulator = "sims"`` (the default) loads this package by that name.
"""
from __future__ import annotations

import importlib

from jaxslam.simulators import register_simulator
from sims.config import scenario_config, scenario_to_dict
from sims.mujoco_loader import lazy_functions

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
    "sample_forest": "sims.forest",
    "poisson_disc": "sims.forest",
    "sample_radii": "sims.forest",
    "world_from_forest": "sims.forest",
    "BLACK_CHERRY_DBH": "sims.forest3d",
    "Forest3D": "sims.forest3d",
    "Terrain": "sims.forest3d",
    "World3D": "sims.forest3d",
    "breast_height_points": "sims.forest3d",
    "flat_terrain": "sims.forest3d",
    "ground_height": "sims.forest3d",
    "make_world_3d": "sims.forest3d",
    "random_forest_3d": "sims.forest3d",
    "random_terrain": "sims.forest3d",
    "sample_dbh": "sims.forest3d",
    "TABLE2_RANGE_NOISE": "sims.lidar",
    "Scan": "sims.lidar",
    "add_range_noise": "sims.lidar",
    "beam_angles": "sims.lidar",
    "clip_3d_to_2d": "sims.lidar",
    "layer_elevations": "sims.lidar",
    "scan_2d": "sims.lidar",
    "scan_2d_full": "sims.lidar",
    "Cloud": "sims.scan3d",
    "beam_directions": "sims.scan3d",
    "scan_3d": "sims.scan3d",
    "lawnmower_path": "sims.paths",
    "loop_path": "sims.paths",
    "noisy_odometry": "sims.paths",
    "path_clearance": "sims.paths",
    "random_smooth_path": "sims.paths",
    "resample_polyline": "sims.paths",
    "true_moves": "sims.paths",
    "ScenarioConfig": "sims.config",
    "scenario_config": "sims.config",
    "Scenario": "sims.scenario",
    "analytic_observations": "sims.scenario",
    "with_start_scan": "sims.scenario",
    "build_scenario": "sims.scenario",
    "default_scenario": "sims.scenario",
}
_SUBMODULES = ("batch", "config", "forest", "lidar", "mujoco_loader", "paths", "robot",
               "robot_runs", "scenario")

__all__ = sorted(_PUBLIC)

register_simulator("sims", simulate=lazy_functions("sims.batch", "scenario_batch")[0],
                   settings=scenario_config, to_dict=scenario_to_dict)


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
