"""The settings of the simulated world of a study: the [scenario] section of a study config.

``scenario_config`` is this simulator's ``settings`` function (``jaxslam.simulators``): it turns
the plain mapping of the TOML section into a checked ``ScenarioConfig``; every error names the
key and the allowed values. Only the standard library and ``jaxslam.config_rules`` are imported
here, so that reading a study config needs neither JAX's simulator code nor MuJoCo.
"""
from __future__ import annotations

import dataclasses
from collections.abc import Mapping

from jaxslam.config_rules import (Rule, check_choices, check_fields, check_keys,
                                  normalise)

SECTION = "scenario"
SCENARIO_RULES = {
    "forest": Rule("str"),
    "num_trees": Rule("int", 1, True),
    "size": Rule("float", 0.0, False),
    "path": Rule("str"),
    "num_steps": Rule("int", 1, True),
    "step_length": Rule("float", 0.0, False),
    "max_range": Rule("float", 0.0, False),
    "observation_source": Rule("str"),
    "detection": Rule("str"),
    "odometry_noise_scale": Rule("float", 0.0, True),
    "world": Rule("str"),
    "robot": Rule("str"),
    "first_scan": Rule("str"),
}
SCENARIO_CHOICES = {"forest": ("random", "plantation"), "path": ("loop", "lawnmower", "random"),
                    "observation_source": ("analytic", "lidar"),
                    "detection": ("centroid", "kasa", "geometric", "ransac"),
                    "world": ("shared", "per_run"), "robot": ("kinematic", "mjx_wheeled"),
                    "first_scan": ("at_start", "after_first_move")}
# The robot's own first scan when ``first_scan`` is not given.
FIRST_SCAN_OF_ROBOT = {"kinematic": "after_first_move", "mjx_wheeled": "at_start"}


@dataclasses.dataclass(frozen=True)
class ScenarioConfig:
    """The simulated world of every run (see ``sims.scenario`` and ``sims.batch``).

    forest: "random" or "plantation"; num_trees; size: square side [m]; path: "loop",
    "lawnmower" or "random"; num_steps: T; step_length [m]; max_range [m] of the sensor;
    observation_source: "analytic" (range-bearing to trunk centres with Table 2 noise) or
    "lidar" (MJX scans + trunk detection); detection: centroid | kasa | geometric | ransac;
    odometry_noise_scale: multiplies the Table 1 noise of the simulated odometry.
    world: "per_run" (the default: run i draws its own forest and path from its run key, so
    the spread over worlds is part of every metric; with lidar, each run's trunks are written
    into one template MJX model, ``sims.batch``) or "shared" (every run follows one path
    through one forest, drawn from the seed: runs differ in noise only, for paired
    comparisons).
    robot: "kinematic" (the robot follows the path exactly; odometry = the true moves with
    Eq. (1) noise) or "mjx_wheeled" (the MJX differential-drive robot of ``sims.robot``,
    started at the path's first pose, driven by random wheel-speed commands with wheel slip,
    friction and acceleration limits; its encoder odometry is the controls and its chassis
    path the truth: ``sims.robot_runs``; analytic observations, odometry_noise_scale 1).
    first_scan: "at_start" (the robot scans at rest at its start pose before it drives, behind
    a zero move: a run has T + 1 filter steps, ``sims.scenario.with_start_scan``) or
    "after_first_move" (the first scan is taken after the first move). Default: the robot's
    own, ``FIRST_SCAN_OF_ROBOT`` ("at_start" for mjx_wheeled, whose first move from rest can
    slip; "after_first_move" for the kinematic robot, the seed paper's set-up, which has no
    "at_start" yet).
    """

    forest: str = "random"
    num_trees: int = 80
    size: float = 60.0
    path: str = "loop"
    num_steps: int = 200
    step_length: float = 0.5
    max_range: float = 20.0
    observation_source: str = "analytic"
    detection: str = "kasa"
    odometry_noise_scale: float = 1.0
    world: str = "per_run"
    robot: str = "kinematic"
    first_scan: str = ""

    def __post_init__(self):
        if self.first_scan == "":  # the robot's own (frozen: set once, here)
            own = FIRST_SCAN_OF_ROBOT.get(self.robot if isinstance(self.robot, str) else "",
                                          "after_first_move")
            object.__setattr__(self, "first_scan", own)
        check_fields(SECTION, self, SCENARIO_RULES)
        check_choices(SECTION, dataclasses.asdict(self), SCENARIO_CHOICES)
        if self.robot == "mjx_wheeled" and self.observation_source != "analytic":
            raise ValueError("scenario.robot='mjx_wheeled' needs scenario.observation_source="
                             "'analytic' (lidar scans along each robot's own path are not "
                             "simulated); use robot='kinematic' for lidar studies")
        if self.robot == "mjx_wheeled" and self.odometry_noise_scale != 1.0:
            raise ValueError(f"scenario.odometry_noise_scale={self.odometry_noise_scale!r} "
                             "has no effect with scenario.robot='mjx_wheeled' (its odometry "
                             "errors come from wheel slip, not Eq. (1) noise); leave it at 1.0")
        if self.robot == "kinematic" and self.first_scan == "at_start":
            raise ValueError("scenario.first_scan='at_start' is simulated for "
                             "scenario.robot='mjx_wheeled' only; the kinematic robot takes "
                             "its first scan after its first move (first_scan="
                             "'after_first_move', its default)")


def scenario_config(section) -> ScenarioConfig:
    """The ``ScenarioConfig`` of a [scenario] section (a mapping key -> TOML value; a
    ``ScenarioConfig`` passes through as it is).

    Keys and choices are checked first, then every value's type and range; a float given as
    an integer is stored as a float, so ``size = 30`` and ``size = 30.0`` are one study.
    """
    if isinstance(section, ScenarioConfig):
        return section
    if not isinstance(section, Mapping):
        raise ValueError(f"study scenario={section!r}; expected a ScenarioConfig or a "
                         "[scenario] section of key = value lines")
    section = dict(section)
    check_keys(SECTION, section, ScenarioConfig)
    check_choices(SECTION, section, SCENARIO_CHOICES)
    return ScenarioConfig(**normalise(SECTION, section, SCENARIO_RULES))


def scenario_to_dict(settings: ScenarioConfig) -> dict:
    """The [scenario] section written back (``Simulator.to_dict``): every key, except, for
    the kinematic robot, ``robot`` and ``first_scan`` (its only value, "after_first_move"), so
    that a kinematic study's study.toml, digest and resume check stay what they were before
    the keys existed. A robot study always writes ``first_scan``, so a robot study folder
    written before the key existed (its runs have ``num_steps`` rows, no start scan) differs
    from any robot config and is not resumed by mistake; adding ``first_scan =
    "after_first_move"`` to its study.toml resumes it as it was."""
    out = dataclasses.asdict(settings)
    if out["robot"] == "kinematic":
        del out["robot"], out["first_scan"]
    return out
