"""High-rate controls -> one odometry move (rot1, trans, rot2) per observation step.

Logs store one move per filter step; robots record controls faster than they observe. This
module integrates the controls between observation times (explicit Euler for velocity and
Ackermann controls, composition for odometry moves) and splits each step's relative pose into
(rot1, trans, rot2). The kinematics are the library's own, evaluated in float64 on the host
(``jaxslam.host.in_float64``): Ackermann rates from ``jaxslam.motion.ackermann_rates``,
poses composed by ``jaxslam.geometry.compose``, moves decomposed by
``jaxslam.motion.odometry_from_poses``.

Shapes: N control samples, C control components, T observation times, J Euler intervals.
"""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxslam.host import in_float64
from jaxslam.datasets.log_format import check_finite, check_increasing, check_shape, fail
from jaxslam.geometry import compose, wrap_angle
from jaxslam.motion import ackermann_rates, apply_odometry, odometry_from_poses
from jaxslam.types import MOTION_MODELS


class AckermannVehicle(NamedTuple):
    """Ackermann geometry [m]; the pose is taken at the sensor (defaults: Victoria Park README).

    Attributes:
      wheelbase: L, rear axle to front axle.
      encoder_offset: H, lateral offset of the speed-encoder (rear-left) wheel.
      sensor_forward: a, sensor ahead of the rear axle.
      sensor_left: b, sensor left of the vehicle centre line.
    """

    wheelbase: float = 2.83
    encoder_offset: float = 0.76
    sensor_forward: float = 3.78
    sensor_left: float = 0.50


VICTORIA_PARK_VEHICLE = AckermannVehicle()


def interpolate_poses(times, pose_time, poses):
    """Poses (T, 3) at ``times`` (T,) from samples at ``pose_time`` (G,), ``poses`` (G, 3).

    x, y linearly; theta linearly on ``np.unwrap``-ed headings (no jump across +-pi), then
    wrapped to [-pi, pi). Outside [pose_time[0], pose_time[-1]] the end samples are held.
    """
    heading = np.unwrap(poses[:, 2])
    return np.stack([np.interp(times, pose_time, poses[:, 0]),
                     np.interp(times, pose_time, poses[:, 1]),
                     in_float64(wrap_angle, np.interp(times, pose_time, heading))], axis=-1)


def body_rates(controls, motion_model: str, vehicle: AckermannVehicle | None = None):
    """Velocity of the pose's reference point in the body frame, and the yaw rate.

    velocity: u = (v, omega): body velocity (v, 0), yaw rate omega.
    ackermann: u = (v, alpha) with v measured at the encoder wheel: the rear-axle centre moves
      at vc with yaw rate omega (``jaxslam.motion.ackermann_rates``), and the sensor at (a, b)
      moves with body velocity (vc - omega b, omega a), which rotated by phi gives the Victoria
      Park README's x' = vc cos(phi) - omega (a sin(phi) + b cos(phi)),
      y' = vc sin(phi) + omega (a cos(phi) - b sin(phi)).

    Args:
      controls: (N, C) with C >= 2; columns (v, omega) or (v, steering); others ignored.
    Returns:
      (body_velocity (N, 2) [m/s], yaw_rate (N,) [rad/s]).
    """
    speed, second = controls[:, 0], controls[:, 1]
    if motion_model == "velocity":
        return np.stack([speed, np.zeros_like(speed)], axis=-1), second
    vehicle = VICTORIA_PARK_VEHICLE if vehicle is None else vehicle
    centre_speed, yaw_rate = in_float64(ackermann_rates, speed, second,
                                        wheelbase=vehicle.wheelbase,
                                        encoder_offset=vehicle.encoder_offset)
    velocity = np.stack([centre_speed - yaw_rate * vehicle.sensor_left,
                         yaw_rate * vehicle.sensor_forward], axis=-1)
    return velocity, yaw_rate


@jax.jit
def compose_moves(moves):
    """Poses (J + 1, 3) visited from the zero pose by the relative moves (J, 3), in order.

    pose_0 = 0, pose_{j+1} = pose_j (+) move_j (``jaxslam.geometry.compose``). With
    move_j = h_j (u_j, omega_j) this is explicit Euler, p_{j+1} = p_j + h_j R(phi_j) u_j,
    phi_{j+1} = phi_j + h_j omega_j; with move_j the relative pose of an odometry move it
    chains the moves exactly. Headings are wrapped to [-pi, pi).
    """
    def step(pose, move):
        following = compose(pose, move)
        return following, following

    start = jnp.zeros(3, moves.dtype)
    _, poses = jax.lax.scan(step, start, moves)
    return jnp.concatenate([start[None], poses])


def odometry_between(pose_a, pose_b, min_translation: float = 0.01):
    """The odometry move (rot1, trans, rot2) (..., 3) taking pose_a (..., 3) to pose_b (..., 3).

    ``jaxslam.motion.odometry_from_poses`` in float64: rot1 = atan2(dy, dx) - theta_a,
    trans = |d|, rot2 = theta_b - theta_a - rot1 (wrapped), with d in pose_a's frame. Below
    ``min_translation`` the move is a pure turn (rot1 = 0), matching ``Params.min_translation``:
    the direction of a sub-millimetre move is noise.
    """
    return in_float64(odometry_from_poses, pose_a, pose_b, min_translation=min_translation)


def _path_after(moves, start):
    """Poses (T, 3) after each odometry move (T, 3) from ``start`` (3,)."""
    return compose(start, compose_moves(apply_odometry(jnp.zeros_like(moves), moves))[1:])


def odometry_path(controls, initial_pose=None):
    """Dead-reckoned poses (T, 3) after each odometry move (T, 3), from ``initial_pose`` (3,)."""
    start = np.zeros(3) if initial_pose is None else initial_pose
    return in_float64(_path_after, controls, start)


def _check_integration_inputs(control_time, controls, obs_time, motion_model):
    source = "integrate_controls"
    if motion_model not in MOTION_MODELS:
        fail(source, f"unknown motion_model {motion_model!r}; expected one of "
                      f"{list(MOTION_MODELS)}")
    for name, times in (("control_time", control_time), ("obs_time", obs_time)):
        check_shape(source, name, times, (None,))
        if times.shape[0] < 1:
            fail(source, f"'{name}' is empty; expected at least one timestamp")
        check_finite(source, name, times)
        check_increasing(source, name, times)
    width = 3 if motion_model == "odometry" else None
    check_shape(source, "controls", controls, (control_time.shape[0], width))
    if controls.shape[1] < 2:
        fail(source, f"'controls' has {controls.shape[1]} column(s); expected (v, omega) or "
                      "(v, steering) first")
    check_finite(source, "controls", controls)


def _euler_moves(control_time, controls, obs_time, motion_model, vehicle):
    """The merged time grid (J + 1,) and its Euler moves (J, 3) h_j (u_j, omega_j)."""
    grid = np.union1d(control_time, obs_time)
    held = np.searchsorted(control_time, grid[:-1], side="right") - 1
    velocity, yaw_rate = body_rates(controls[np.maximum(held, 0)], motion_model, vehicle)
    duration = np.diff(grid) * (held >= 0)  # before the first sample the robot stands still
    return grid, np.concatenate([velocity, yaw_rate[:, None]], axis=-1) * duration[:, None]


def integrate_controls(control_time, controls, obs_time, motion_model: str,
                       vehicle: AckermannVehicle | None = None,
                       min_translation: float = 0.01) -> np.ndarray:
    """Compose high-rate controls between observation times into one odometry move per step.

    velocity / ackermann: sample i, (v, omega) or (v, steering), is held from control_time[i]
      to control_time[i+1] (the last one indefinitely; before control_time[0] the robot stands
      still). The kinematics (``body_rates``) are integrated by explicit Euler on the merged
      grid of control and observation times, and the relative pose over each observation
      interval becomes an odometry move (``odometry_between``), i.e. exactly what Euler
      integration from the zero pose at obs_time[t-1] to obs_time[t] gives.
    odometry: sample i (rot1, trans, rot2) is the move ending at control_time[i]; moves with
      obs_time[t-1] < control_time[i] <= obs_time[t] are composed into step t (moves after the
      last observation are dropped).
    Row 0 is the move from min(control_time[0], obs_time[0]) into obs_time[0].

    Args:
      control_time: (N,) seconds, strictly increasing.
      controls: (N, C) control samples (C = 3 for odometry, C >= 2 otherwise; a dt column
        is ignored: durations come from control_time).
      obs_time: (T,) seconds, strictly increasing, on the same clock.
      motion_model: "odometry", "velocity" or "ackermann".
      vehicle: Ackermann geometry; None means ``VICTORIA_PARK_VEHICLE``.
      min_translation: see ``odometry_between``.
    Returns:
      (T, 3) odometry controls (rot1, trans, rot2).
    """
    control_time = np.asarray(control_time, np.float64)
    controls = np.asarray(controls, np.float64)
    obs_time = np.asarray(obs_time, np.float64)
    _check_integration_inputs(control_time, controls, obs_time, motion_model)
    if motion_model == "odometry":
        moves = in_float64(apply_odometry, np.zeros_like(controls), controls)
        at_obs = np.searchsorted(control_time, obs_time, side="right")
    else:
        grid, moves = _euler_moves(control_time, controls, obs_time, motion_model, vehicle)
        at_obs = np.searchsorted(grid, obs_time)
    poses = in_float64(compose_moves, moves)
    previous = np.concatenate([[0], at_obs[:-1]])
    return odometry_between(poses[previous], poses[at_obs], min_translation)
