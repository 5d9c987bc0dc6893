"""A small MJX differential-drive robot with wheel-ground contact and slip.

The robot: a box chassis on a free joint, two driven spherical wheels on hinge joints with
velocity actuators (torque = kv (set-point - wheel speed), clipped to +-``max_torque``) and two
frictionless spherical casters, front and back (one alone lets the chassis pitch over under
hard braking), on a ground plane. Friction acts only at the wheel contacts (the ground and the
casters have ``condim=1``; a contact takes the larger condim and the larger friction of its
two geoms), so the wheels' sliding friction coefficient alone sets
the traction; it is a traced parameter (``model.geom_friction``), so a vmap over friction
compiles once.

Odometry is encoder integration: at every physics step the wheel angle increments
d_phi_l, d_phi_r give the wheel travels d_l = r d_phi_l, d_r = r d_phi_r, and the dead-reckoned
pose moves by d = (d_l + d_r) / 2 along the mid-step heading and turns by (d_r - d_l) / w
(w: track width). Slip (wheel spin under acceleration, sliding in turns) makes it wrong; so
does, slightly, the contact softness (the wheel sinks a fraction of a millimetre, shortening
its effective radius: straight runs at friction 1 travel about 0.1% less than the encoders say).

Every ``interval`` s (about the filter's step) the true pose (from the free joint) and the
odometry pose are recorded, and each consecutive pair is decomposed into (rot1, trans, rot2)
with ``jaxslam.motion.odometry_from_poses``.

Shapes: T intervals, U = interval / timestep physics steps per interval.
"""
from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxslam.geometry import wrap_angle
from jaxslam.motion import odometry_from_poses
from sims.mujoco_loader import mjx, mujoco  # imported when first used


class RobotSpec(NamedTuple):
    """Geometry and drive settings (static: they build the MJCF).

    wheel_radius / track_width [m]; chassis_mass / wheel_mass [kg]; kv [N m s/rad] actuator
    gain; max_torque [N m]; timestep [s] physics step; max_wheel_speed [rad/s] command limit;
    max_wheel_acceleration [rad/s^2]: the speed set-point ramps towards each new command at
    most this fast (a motor controller's acceleration limit; inf = step changes).
    """

    wheel_radius: float = 0.1
    track_width: float = 0.4
    chassis_mass: float = 12.0
    wheel_mass: float = 1.0
    kv: float = 10.0
    max_torque: float = 20.0
    timestep: float = 0.005
    max_wheel_speed: float = 20.0
    max_wheel_acceleration: float = float("inf")


class Robot(NamedTuple):
    """An MJX robot: ``model`` and the initial ``data`` (after a forward pass), the wheel geom
    ids (whose friction ``set_friction`` writes) and the spec."""

    model: mjx.Model
    data: mjx.Data
    wheel_geoms: tuple
    spec: RobotSpec


class RobotLog(NamedTuple):
    """One simulation.

    Attributes:
      true_poses: (T+1, 3) true (x, y, yaw) of the chassis every interval.
      odometry_poses: (T+1, 3) encoder dead-reckoned poses (start = true start).
      true_moves: (T, 3) true (rot1, trans, rot2) of each interval.
      odometry_moves: (T, 3) odometry (rot1, trans, rot2) of each interval.
    """

    true_poses: jnp.ndarray
    odometry_poses: jnp.ndarray
    true_moves: jnp.ndarray
    odometry_moves: jnp.ndarray


def robot_mjcf(spec: RobotSpec) -> str:
    """MJCF of the robot on a plane (the chassis starts at the origin, facing +x)."""
    r, half_track = spec.wheel_radius, 0.5 * spec.track_width
    caster = 0.4 * r
    caster_z = -(r - caster)
    return f"""
<mujoco model="diff_drive">
  <option timestep="{spec.timestep}" integrator="implicitfast"/>
  <asset><material name="plain"/></asset>
  <worldbody>
    <geom name="ground" type="plane" size="0 0 1" friction="0 0 0" condim="1"
          contype="1" conaffinity="2" material="plain"/>
    <body name="chassis" pos="0 0 {r}">
      <freejoint name="root"/>
      <geom name="body" type="box" size="0.25 {half_track - 0.05} 0.05" pos="-0.08 0 0.02"
            mass="{spec.chassis_mass}" contype="0" conaffinity="0"/>
      <geom name="rear_caster" type="sphere" size="{caster}" pos="-0.22 0 {caster_z}"
            mass="0.2" condim="1" friction="0 0 0" contype="2" conaffinity="1"/>
      <geom name="front_caster" type="sphere" size="{caster}" pos="0.22 0 {caster_z}"
            mass="0.2" condim="1" friction="0 0 0" contype="2" conaffinity="1"/>
      <body name="left_wheel" pos="0 {half_track} 0">
        <joint name="left" type="hinge" axis="0 1 0"/>
        <geom name="left_tyre" type="sphere" size="{r}" mass="{spec.wheel_mass}" condim="3"
              friction="1 0 0" contype="2" conaffinity="1"/>
      </body>
      <body name="right_wheel" pos="0 {-half_track} 0">
        <joint name="right" type="hinge" axis="0 1 0"/>
        <geom name="right_tyre" type="sphere" size="{r}" mass="{spec.wheel_mass}" condim="3"
              friction="1 0 0" contype="2" conaffinity="1"/>
      </body>
    </body>
  </worldbody>
  <actuator>
    <velocity name="left" joint="left" kv="{spec.kv}" forcelimited="true"
              forcerange="{-spec.max_torque} {spec.max_torque}"/>
    <velocity name="right" joint="right" kv="{spec.kv}" forcelimited="true"
              forcerange="{-spec.max_torque} {spec.max_torque}"/>
  </actuator>
</mujoco>"""


def make_robot(spec: RobotSpec = RobotSpec()) -> Robot:
    """Build the MJX robot, settled on the ground by a CPU forward pass."""
    mj_model = mujoco.MjModel.from_xml_string(robot_mjcf(spec))
    mj_data = mujoco.MjData(mj_model)
    mujoco.mj_forward(mj_model, mj_data)
    wheels = tuple(mujoco.mj_name2id(mj_model, mujoco.mjtObj.mjOBJ_GEOM, name)
                   for name in ("left_tyre", "right_tyre"))
    return Robot(mjx.put_model(mj_model), mjx.put_data(mj_model, mj_data), wheels, spec)


def set_friction(model: mjx.Model, wheel_geoms: tuple, friction) -> mjx.Model:
    """``model`` with the wheels' sliding friction coefficient set to ``friction`` () (traced)."""
    ids = jnp.asarray(wheel_geoms)
    return model.replace(geom_friction=model.geom_friction.at[ids, 0].set(friction))


def wheel_speeds(speed, yaw_rate, spec: RobotSpec):
    """Wheel speeds (..., 2) [rad/s] (left, right) for a body speed [m/s] and yaw rate
    [rad/s]: omega_{l,r} = (v -+ w track / 2) / r."""
    half = 0.5 * spec.track_width * yaw_rate
    return jnp.stack([speed - half, speed + half], -1) / spec.wheel_radius


def random_commands(key, num_intervals: int, spec: RobotSpec, max_speed: float = 1.0,
                    max_yaw_rate: float = 1.5, hold_probability: float = 0.3):
    """Diversified wheel-speed commands (T, 2) [rad/s], one per interval.

    Each interval keeps the previous command with ``hold_probability``, else draws a new
    motion type uniformly among stop, pure turn, straight and arc, with speed ~ U(0, max_speed)
    and yaw rate ~ U(-max_yaw_rate, max_yaw_rate); the sudden changes between intervals are
    the accelerations that make the wheels slip.
    """
    key_kind, key_speed, key_rate, key_hold = jax.random.split(key, 4)
    kind = jax.random.randint(key_kind, (num_intervals,), 0, 4)
    speed = jax.random.uniform(key_speed, (num_intervals,), maxval=max_speed)
    rate = jax.random.uniform(key_rate, (num_intervals,), minval=-max_yaw_rate,
                              maxval=max_yaw_rate)
    speed = jnp.where((kind == 0) | (kind == 1), 0.0, speed)
    rate = jnp.where((kind == 0) | (kind == 2), 0.0, rate)
    fresh = wheel_speeds(speed, rate, spec)
    hold = jax.random.bernoulli(key_hold, hold_probability, (num_intervals,)).at[0].set(False)

    def carry_forward(previous, inputs):
        new, keep = inputs
        command = jnp.where(keep, previous, new)
        return command, command

    _, commands = jax.lax.scan(carry_forward, fresh[0], (fresh, hold))
    return jnp.clip(commands, -spec.max_wheel_speed, spec.max_wheel_speed)


def chassis_pose(qpos):
    """(x, y, yaw) (3,) of the free joint's qpos (x, y, z, qw, qx, qy, qz)."""
    w, x, y, z = qpos[3], qpos[4], qpos[5], qpos[6]
    yaw = jnp.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    return jnp.stack([qpos[0], qpos[1], yaw])


def encoder_step(pose, delta_angles, spec: RobotSpec):
    """Dead-reckoned pose (3,) after wheel angle increments (2,) (left, right) [rad]."""
    travel = spec.wheel_radius * delta_angles
    distance = 0.5 * (travel[0] + travel[1])
    turn = (travel[1] - travel[0]) / spec.track_width
    heading = pose[2] + 0.5 * turn
    return jnp.stack([pose[0] + distance * jnp.cos(heading),
                      pose[1] + distance * jnp.sin(heading), wrap_angle(pose[2] + turn)])


class _Carry(NamedTuple):
    data: mjx.Data
    odometry_pose: jnp.ndarray
    wheel_angles: jnp.ndarray
    set_point: jnp.ndarray


def _wheel_angles(data):
    # qpos: 7 free-joint coordinates, then the left and right hinges.
    return data.qpos[7:9]


@functools.partial(jax.jit, static_argnames=("spec", "substeps", "min_translation"))
def _simulate(model, data, wheel_geoms, commands, friction, spec, substeps, min_translation):
    model = set_friction(model, wheel_geoms, friction)
    # mjx.put_data stores contact indices as int32; under jax_enable_x64 mjx.step returns
    # int64. Cast to the step's output types so the scan carry keeps one type.
    step_types = jax.eval_shape(mjx.step, model, data)
    data = jax.tree.map(lambda leaf, like: leaf.astype(like.dtype), data, step_types)
    start_pose = chassis_pose(data.qpos)

    max_change = spec.max_wheel_acceleration * spec.timestep

    def physics_step(carry: _Carry, command):
        set_point = carry.set_point + jnp.clip(command - carry.set_point, -max_change,
                                               max_change)
        data = mjx.step(model, carry.data.replace(ctrl=set_point))
        angles = _wheel_angles(data)
        pose = encoder_step(carry.odometry_pose, angles - carry.wheel_angles, spec)
        return _Carry(data, pose, angles, set_point), None

    def interval(carry: _Carry, command):
        carry, _ = jax.lax.scan(lambda c, _: physics_step(c, command), carry, None, substeps)
        return carry, (chassis_pose(carry.data.qpos), carry.odometry_pose)

    start = _Carry(data, start_pose, _wheel_angles(data), jnp.zeros(2, commands.dtype))
    _, (true_poses, odometry_poses) = jax.lax.scan(interval, start, commands)
    true_poses = jnp.concatenate([start_pose[None], true_poses], 0)
    odometry_poses = jnp.concatenate([start_pose[None], odometry_poses], 0)
    return RobotLog(true_poses, odometry_poses,
                    odometry_from_poses(true_poses[:-1], true_poses[1:], min_translation),
                    odometry_from_poses(odometry_poses[:-1], odometry_poses[1:],
                                        min_translation))


def simulate(robot: Robot, commands, friction, interval: float = 0.5,
             min_translation: float = 0.01) -> RobotLog:
    """Drive ``robot`` with wheel-speed ``commands`` (T, 2) [rad/s], one per ``interval`` s.

    Args:
      friction: () wheel-ground sliding friction coefficient (traced; vmap for a sweep).
      interval: recording interval [s]; a whole number of physics steps.
      min_translation: below it a move is a pure turn (``motion.odometry_from_relative``).
    Returns:
      ``RobotLog`` of true and odometry poses and moves.
    """
    commands = jnp.asarray(commands)
    if commands.ndim != 2 or commands.shape[1] != 2:
        raise ValueError(f"simulate expects commands (T, 2) = (left, right) wheel speeds; "
                         f"got {commands.shape}")
    substeps = int(round(interval / robot.spec.timestep))
    if substeps < 1 or abs(substeps * robot.spec.timestep - interval) > 1e-9:
        raise ValueError(f"simulate interval={interval} s must be a positive multiple of the "
                         f"physics timestep {robot.spec.timestep} s")
    # MJX's own kernels broadcast implicitly; allow it even where rank promotion raises.
    with jax.numpy_rank_promotion("allow"):
        return _simulate(robot.model, robot.data, jnp.asarray(robot.wheel_geoms), commands,
                         jnp.asarray(friction, commands.dtype), robot.spec, substeps,
                         float(min_translation))


def simulate_batch(robot: Robot, commands, friction, interval: float = 0.5,
                   min_translation: float = 0.01) -> RobotLog:
    """``simulate`` vmapped over R robots: commands (R, T, 2), friction (R,) or ()."""
    commands = jnp.asarray(commands)
    if commands.ndim != 3 or commands.shape[2] != 2:
        raise ValueError(f"simulate_batch expects commands (R, T, 2); got {commands.shape}")
    friction = jnp.broadcast_to(jnp.asarray(friction, commands.dtype), commands.shape[:1])
    return jax.vmap(lambda c, f: simulate(robot, c, f, interval, min_translation))(
        commands, friction)
