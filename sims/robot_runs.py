"""Study runs driven by the MJX wheeled robot (``scenario.robot = "mjx_wheeled"``).

The kinematic scenario moves the robot exactly along its path and draws the odometry from
Geiser et al. 2023, Eq. (1). Here the MJX differential-drive robot of ``sims.robot`` drives
instead: it starts at the scenario path's first pose and follows random diversified
wheel-speed commands (``random_commands``) with its wheels' friction drawn per run, so its
odometry errors come from wheel slip, contact softness and acceleration limits, not from a
noise model. Per run and step:

  controls      the encoder odometry (rot1, trans, rot2) of each interval (``encoder_step``
                dead reckoning, decomposed by ``jaxslam.motion.odometry_from_poses``), as
                ``experiments/noise_model.py`` feeds the filter;
  truth_pose    the true chassis poses, placed in the world frame at the path's first pose;
  observations  analytic range-bearing to trunk centres along that true path, with Table 2
                noise (``sims.scenario.analytic_observations``, as in the kinematic scenario).

The robot scans once at rest before it drives (``scenario.first_scan = "at_start"``, its
default; ``sims.scenario.with_start_scan``): row 0 is a zero move and a scan at the start pose,
and the truth repeats the start pose for it, so a run has T+1 filter steps (controls (T+1, 3),
truth (T+2, 3)). The first interval starts from rest and can slip by 0.1 rad; without the
start scan (``first_scan = "after_first_move"``: T steps, truth (T+1, 3), the other rows
identical) the filter's map would inherit that error for the whole run (docs/results.md,
noise_model).

The scenario's ``path`` only sets the start pose, and ``step_length`` the top speed
(step_length per interval); the forest keeps clear of the designed path, not of the robot's,
and the robot does not collide with trunks (its physics is a ground plane alone). Forest and
start come from the study's world (shared, or the run's own with ``world = "per_run"``).

Randomness: run i's key is ``fold_in(PRNGKey(seed), i)``; its commands and friction come from
the first half of ``split(fold_in(key, 0))`` and its observation noise from the second (the
kinematic scenario's odometry and observation keys): step t's scan from ``split(obs_key,
T)[t]``, the start scan from ``fold_in(obs_key, T)`` (a key no step uses; with JAX's default
partitionable threefry it is ``split(obs_key, T + 1)[T]``). So a run never depends on its neighbours or on the chunk size (runs are
simulated in groups of fixed width).

Shapes: R runs, T = ``num_steps`` intervals of ``STEP_SECONDS``, N trees, K = max_obs.
"""
from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from jaxslam.geometry import compose, relative
from jaxslam.simulators import RunBatch
from jaxslam.study_config import StudyConfig
from sims.batch import (observed_trees, run_world_arrays, simulate_in_groups,
                        simulation_params)
from sims.config import ScenarioConfig
from sims.mujoco_loader import require_mujoco

# A motor controller's ramp: about 1 m/s^2 at the wheel rim (0.1 m wheels), enough for the
# random commands' 0 <-> top-speed changes to slip in turns and on low friction.
ROBOT_SPEC_SETTINGS = dict(max_wheel_acceleration=10.0)
STEP_SECONDS = 0.5  # one filter step = one recording interval of the robot [s]
# Wheel-ground sliding friction, uniform per run: wet grass and leaf litter up to dry soil.
FRICTION_RANGE = (0.4, 1.0)


def robot_spec():
    """The ``sims.robot.RobotSpec`` of study robots (imports MuJoCo's robot module)."""
    from sims.robot import RobotSpec

    return RobotSpec(**ROBOT_SPEC_SETTINGS)


def draw_drive(key, num_steps: int, spec, top_speed: float, dtype):
    """A run's wheel-speed commands (T, 2) [rad/s] and wheel friction () from its ``key``."""
    from sims.robot import random_commands

    key_commands, key_friction = jax.random.split(key)
    commands = random_commands(key_commands, num_steps, spec, max_speed=top_speed)
    friction = jax.random.uniform(key_friction, (), dtype, *FRICTION_RANGE)
    return commands.astype(dtype), friction


def place_path(start, robot_poses):
    """Robot poses (T+1, 3), in the frame the robot started in, moved so that the first one
    is ``start`` (3,): start (+) (robot_poses[0]^-1 (+) robot_poses[t])."""
    return compose(start, relative(robot_poses[0], robot_poses))


@functools.lru_cache(maxsize=8)
def _robot_simulator(settings: ScenarioConfig, seed: int, max_obs: int):
    """jit(group of W robot runs): (run_ids (W,), start (W, 3), centres (W, N, 2),
    radii (W, N)) -> (controls (W, T+1, 3), observations (W, T+1, K, ...), tree_seen (W, N),
    truth_pose (W, T+2, 3)), all float32 poses (row 0: the start scan, module docstring; T
    and T+1 rows with ``first_scan = "after_first_move"``). Cached: one MJX model and compile
    per study."""
    from sims import robot as robot_lib
    from sims.scenario import analytic_observations, with_start_scan

    robot = robot_lib.make_robot(robot_spec())
    dtype = robot.model.geom_friction.dtype  # the physics' float type (float64 under x64)
    params = simulation_params(settings)
    top_speed = settings.step_length / STEP_SECONDS

    def run_keys(run_id):
        run_key = jax.random.fold_in(jax.random.PRNGKey(seed), run_id)
        return jax.random.split(jax.random.fold_in(run_key, 0))

    def scan(key, pose, centres, radii):
        return analytic_observations(key, pose, centres, radii, params, max_obs)

    def observe(key, start, robot_poses, odometry_moves, centres, radii):
        truth = place_path(start, robot_poses.astype(jnp.float32))
        controls = odometry_moves.astype(jnp.float32)
        observations = jax.vmap(scan, in_axes=(0, 0, None, None))(
            jax.random.split(key, settings.num_steps), truth[1:], centres, radii)
        if settings.first_scan == "at_start":
            controls, observations = with_start_scan(
                controls, observations,
                scan(jax.random.fold_in(key, settings.num_steps), truth[0], centres, radii))
            truth = jnp.concatenate([truth[:1], truth])  # the zero move stays at the start
        return controls, observations, observed_trees(observations, centres.shape[0]), truth

    def simulate(run_ids, start, centres, radii):
        keys = jax.vmap(run_keys)(run_ids)
        commands, friction = jax.vmap(lambda key: draw_drive(
            key, settings.num_steps, robot.spec, top_speed, dtype))(keys[:, 0])
        log = robot_lib.simulate_batch(robot, commands, friction, STEP_SECONDS,
                                       float(params.min_translation))
        return jax.vmap(observe)(keys[:, 1], start, log.true_poses, log.odometry_moves,
                                 centres, radii)

    return jax.jit(simulate)


def robot_batch(config: StudyConfig, run_ids: np.ndarray, width: int) -> RunBatch:
    """The runs ``run_ids`` (R,) driven by the MJX wheeled robot, in groups of ``width``.

    Returns a ``RunBatch`` whose leaves are all per run: controls (R, T+1, 3), observations
    (R, T+1, K, ...), truth_pose (R, T+2, 3) (row 0: the start scan, module docstring; one
    row fewer each with ``first_scan = "after_first_move"``),
    tree_centres (R, N, 2), tree_radii (R, N),
    tree_seen (R, N) (trees observed at least once). Raises ``SimulatorNotInstalled`` (an
    ImportError naming the install command) without MuJoCo.
    """
    require_mujoco('scenario.robot = "mjx_wheeled" (the MJX wheeled robot)')
    settings = config.scenario
    run_ids = np.asarray(run_ids, np.int64).reshape(-1)
    simulate = _robot_simulator(settings, config.seed, config.filter.max_obs)
    path, centres, radii = run_world_arrays(settings, config.seed, run_ids)
    controls, observations, seen, truth = simulate_in_groups(
        simulate, run_ids, width, path[:, 0], centres, radii)
    return RunBatch(controls, observations, truth, centres, radii, seen)
