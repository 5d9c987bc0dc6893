"""Control integration (``jaxslam.datasets.odometry``) against plain-Python float64 references:
per-sample explicit Euler of the velocity and Ackermann kinematics, composition of odometry
moves, the pose interpolation the loaders share. Tolerances: the library runs the same
arithmetic in float64 in another order, so results agree to rounding (1e-12 or 1e-10 after
hundreds of accumulated steps)."""
import math

import numpy as np
import pytest

from jaxslam.datasets import odometry as odo
from jaxslam.datasets.log_format import LogFormatError


def _wrap(angle):
    return (np.asarray(angle, np.float64) + np.pi) % (2 * np.pi) - np.pi


# ------------------------------------------------------------------------- control integration


def _euler_reference(control_time, controls, obs_time, motion_model, vehicle):
    """Plain-Python per-sample Euler from the zero pose over each observation interval."""
    length, offset, forward, left = (vehicle.wheelbase, vehicle.encoder_offset,
                                     vehicle.sensor_forward, vehicle.sensor_left)
    start = min(control_time[0], obs_time[0])
    moves = []
    for t, end in enumerate(obs_time):
        begin = start if t == 0 else obs_time[t - 1]
        x = y = phi = 0.0
        for i in range(len(control_time)):
            lo = max(begin, control_time[i])
            hi = min(end, control_time[i + 1]) if i + 1 < len(control_time) else end
            if hi <= lo:
                continue
            h = hi - lo
            v, u = controls[i][0], controls[i][1]
            if motion_model == "velocity":
                xd, yd, wd = v * math.cos(phi), v * math.sin(phi), u
            else:
                vc = v / (1 - math.tan(u) * offset / length)
                wd = vc / length * math.tan(u)
                xd = vc * math.cos(phi) - wd * (forward * math.sin(phi) + left * math.cos(phi))
                yd = vc * math.sin(phi) + wd * (forward * math.cos(phi) - left * math.sin(phi))
            x, y, phi = x + h * xd, y + h * yd, phi + h * wd
        trans = math.hypot(x, y)
        rot1 = math.atan2(y, x) if trans >= 1e-3 else 0.0
        rot2 = math.remainder(phi - rot1, 2 * math.pi)
        moves.append((rot1, trans, rot2))
    return np.array(moves)


def _irregular_times(rng, count, low, high, start):
    return start + np.cumsum(rng.uniform(low, high, count))


@pytest.mark.parametrize("motion_model", ["velocity", "ackermann"])
def test_integrate_controls_matches_per_sample_euler(motion_model):
    rng = np.random.default_rng(3)
    control_time = _irregular_times(rng, 300, 0.02, 0.03, 0.5)       # ~40 Hz from 0.5 s
    second = rng.uniform(-0.5, 0.5, 300) if motion_model == "ackermann" else rng.normal(0, 1, 300)
    controls = np.stack([rng.uniform(0, 5, 300), second, np.full(300, 0.025)], -1)
    controls[40:60, 0] = 0.0                                          # a stop
    obs_time = _irregular_times(rng, 34, 0.15, 0.25, 0.2)             # starts before controls
    obs_time[10] = control_time[np.searchsorted(control_time, obs_time[10])]  # shared stamp
    obs_time = np.append(obs_time, control_time[-1] + 0.3)            # past the last sample
    vehicle = odo.AckermannVehicle(2.5, 0.6, 3.0, 0.4)
    got = odo.integrate_controls(control_time, controls, obs_time, motion_model, vehicle)
    want = _euler_reference(control_time, controls, obs_time, motion_model, vehicle)
    assert got.shape == (35, 3) and obs_time[-2] < control_time[-1]
    np.testing.assert_allclose(got, want, atol=1e-10, rtol=0)
    np.testing.assert_array_equal(got[0], 0.0)  # before the first sample the robot stands


def test_integrate_controls_two_columns_equal_three():
    rng = np.random.default_rng(4)
    control_time = _irregular_times(rng, 50, 0.02, 0.03, 0.0)
    controls = np.stack([rng.uniform(0, 3, 50), rng.uniform(-0.3, 0.3, 50)], -1)
    obs_time = np.array([0.3, 0.6, 0.9, 1.1])
    two = odo.integrate_controls(control_time, controls, obs_time, "ackermann")
    three = odo.integrate_controls(control_time, np.c_[controls, np.ones(50)], obs_time,
                                  "ackermann")
    np.testing.assert_array_equal(two, three)


def test_integrate_straight_line_is_exact():
    control_time = np.arange(0.0, 2.0, 0.025)
    controls = np.stack([np.full(80, 2.0), np.zeros(80)], -1)
    moves = odo.integrate_controls(control_time, controls, np.array([0.5, 1.0, 1.7]),
                                  "ackermann")
    np.testing.assert_allclose(moves, [[0, 1.0, 0], [0, 1.0, 0], [0, 1.4, 0]], atol=1e-12)


def test_integrate_default_vehicle_is_victoria_park():
    assert odo.VICTORIA_PARK_VEHICLE == odo.AckermannVehicle(2.83, 0.76, 3.78, 0.50)
    rng = np.random.default_rng(5)
    control_time = np.arange(0.0, 1.0, 0.025)
    controls = np.stack([rng.uniform(1, 3, 40), rng.uniform(-0.3, 0.3, 40)], -1)
    obs_time = np.array([0.4, 0.9])
    np.testing.assert_allclose(
        odo.integrate_controls(control_time, controls, obs_time, "ackermann"),
        _euler_reference(control_time, controls, obs_time, "ackermann", odo.VICTORIA_PARK_VEHICLE),
        atol=1e-12)


def test_integrate_odometry_composes_moves():
    rng = np.random.default_rng(6)
    increments = np.stack([rng.normal(0, 0.1, 30), rng.uniform(0, 0.2, 30),
                           rng.normal(0, 0.1, 30)], -1)
    control_time = np.arange(1, 31) * 0.1
    obs_time = np.array([0.05, 0.5, 1.0, 2.55, 2.93])
    got = odo.integrate_controls(control_time, increments, obs_time, "odometry")
    # Reference: compose the moves ending in each interval with plain Python.
    pose = [0.0, 0.0, 0.0]
    poses = [tuple(pose)]
    for rot1, trans, rot2 in increments:
        pose = [pose[0] + trans * math.cos(pose[2] + rot1),
                pose[1] + trans * math.sin(pose[2] + rot1), pose[2] + rot1 + rot2]
        poses.append(tuple(pose))
    counts = [sum(ct <= t for ct in control_time) for t in obs_time]
    previous = [poses[0]] + [poses[c] for c in counts[:-1]]
    want = odo.odometry_between(np.array(previous), np.array([poses[c] for c in counts]))
    np.testing.assert_allclose(got, want, atol=1e-12)
    np.testing.assert_array_equal(got[0], 0.0)  # no move ends before 0.05 s
    # Composing the steps again lands where composing all samples lands.
    np.testing.assert_allclose(odo.odometry_path(got)[-1, :2], poses[counts[-1]][:2], atol=1e-12)


def test_odometry_path_and_between_are_inverse():
    rng = np.random.default_rng(7)
    moves = np.stack([rng.uniform(-1, 1, 20), rng.uniform(0.01, 1, 20), rng.uniform(-1, 1, 20)],
                     -1)
    initial = np.array([3.0, -1.0, 2.5])
    path = odo.odometry_path(moves, initial)
    back = odo.odometry_between(np.concatenate([initial[None], path[:-1]]), path)
    np.testing.assert_allclose(back[:, 1], moves[:, 1], atol=1e-12)
    np.testing.assert_allclose(_wrap(back[:, [0, 2]] - moves[:, [0, 2]]), 0,
                               atol=1e-12)
    assert np.all((path[:, 2] >= -np.pi) & (path[:, 2] < np.pi))


def test_tiny_translation_is_a_pure_turn():
    moves = odo.odometry_between(np.zeros((1, 3)), np.array([[-1e-5, 2e-5, 0.4]]))
    np.testing.assert_allclose(moves, [[0.0, math.hypot(1e-5, 2e-5), 0.4]], atol=1e-15)


@pytest.mark.parametrize("args, message", [
    ((np.array([0.0, 0.2, 0.1]), np.zeros((3, 2)), np.array([1.0]), "velocity"),
     r"integrate_controls: 'control_time' is not strictly increasing"),
    ((np.array([0.0, 0.1]), np.zeros((3, 2)), np.array([1.0]), "velocity"),
     r"'controls' has shape \(3, 2\); expected \(2, \*\)"),
    ((np.array([0.0, 0.1]), np.zeros((2, 2)), np.array([1.0]), "odometry"),
     r"'controls' has shape \(2, 2\); expected \(2, 3\)"),
    ((np.array([0.0, 0.1]), np.zeros((2, 1)), np.array([1.0]), "velocity"),
     r"'controls' has 1 column\(s\); expected \(v, omega\)"),
    ((np.array([0.0, 0.1]), np.zeros((2, 2)), np.array([1.0, np.nan]), "velocity"),
     r"'obs_time' contains NaN or inf"),
    ((np.array([0.0, 0.1]), np.zeros((2, 2)), np.array([1.0]), "tank"),
     r"unknown motion_model 'tank'"),
])
def test_integrate_controls_errors(args, message):
    with pytest.raises(LogFormatError, match=message):
        odo.integrate_controls(*args)


def test_interpolate_poses_unwraps_the_heading_and_holds_the_ends():
    """One interpolation serves the MRCLAM and ROS bag loaders: across +-pi the heading goes
    the short way round; outside the samples' span the end poses are held."""
    pose_time = np.array([0.0, 1.0])
    poses = np.array([[0.0, 0.0, np.pi - 0.1], [2.0, -4.0, -np.pi + 0.1]])
    got = odo.interpolate_poses(np.array([-1.0, 0.5, 2.0]), pose_time, poses)
    np.testing.assert_allclose(got[1, :2], [1.0, -2.0], rtol=0, atol=1e-12)
    np.testing.assert_allclose(abs(got[1, 2]), np.pi, rtol=0, atol=1e-12)  # not 0
    np.testing.assert_allclose(got[0], poses[0], rtol=0, atol=1e-12)
    np.testing.assert_allclose(got[2], poses[1], rtol=0, atol=1e-12)


def test_float64_whatever_the_global_x64_flag():
    """The loaders' numbers must not depend on ``jax_enable_x64`` (tests run with it on; users
    usually leave it off): ``in_float64`` switches 64-bit types on for the call, so the moves
    are float64 and bit-identical either way, and writable like NumPy results."""
    import jax

    rng = np.random.default_rng(8)
    control_time = _irregular_times(rng, 200, 0.02, 0.03, 0.0)
    controls = np.stack([rng.uniform(0, 4, 200), rng.uniform(-0.4, 0.4, 200)], -1)
    obs_time = _irregular_times(rng, 20, 0.15, 0.3, 0.1)
    with_x64 = odo.integrate_controls(control_time, controls, obs_time, "ackermann")
    with jax.enable_x64(False):
        without = odo.integrate_controls(control_time, controls, obs_time, "ackermann")
        path = odo.odometry_path(without, np.array([1.0, 2.0, 3.0]))
    assert without.dtype == np.float64 and path.dtype == np.float64
    np.testing.assert_array_equal(without, with_x64)
    without[0] = 1.0  # a plain writable array, as the loaders modify rows in place
