"""The MJX differential-drive robot: encoder odometry and pose extraction against NumPy
references, odometry equal to the truth without slip, slip growing as friction falls and as
acceleration rises, command generation and bad input.

One batched simulation (5 robots x 6 intervals of 0.5 s, compiled once) serves the physics
tests."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sims import robot as rb

SPEC = rb.RobotSpec()
# Gentle: 0.2 m/s with +-0.3 rad/s turns. Aggressive: 0 <-> 1 m/s steps and 1.5 rad/s turns.
GENTLE = (np.array([0.2] * 6), np.array([0.0, 0.0, 0.3, 0.3, -0.3, -0.3]))
AGGRESSIVE = (np.array([1.0, 0.0, 1.0, 0.0, 1.0, 0.0]), np.array([0.0, 1.5, 0.0, -1.5, 1.0, 0.0]))
# Rows: gentle at friction 1.0, aggressive at 1.0, 0.3, 0.05, gentle at 0.05.
FRICTION = np.array([1.0, 1.0, 0.3, 0.05, 0.05])


@pytest.fixture(scope="module")
def logs():
    gentle = rb.wheel_speeds(jnp.asarray(GENTLE[0]), jnp.asarray(GENTLE[1]), SPEC)
    aggressive = rb.wheel_speeds(jnp.asarray(AGGRESSIVE[0]), jnp.asarray(AGGRESSIVE[1]), SPEC)
    commands = jnp.stack([gentle, aggressive, aggressive, aggressive, gentle])
    robot = rb.make_robot(SPEC)
    return jax.tree.map(np.asarray, rb.simulate_batch(robot, commands, FRICTION))


def drift(log_row):
    """Final position error [m] of the dead-reckoned pose."""
    return np.hypot(*(log_row.true_poses[-1, :2] - log_row.odometry_poses[-1, :2]))


def row(logs, i):
    return jax.tree.map(lambda a: a[i], logs)


def test_shapes_and_moves_consistent(logs):
    assert logs.true_poses.shape == (5, 7, 3) and logs.true_moves.shape == (5, 6, 3)
    assert np.all(np.isfinite(logs.true_poses)) and np.all(np.isfinite(logs.odometry_poses))
    # The robot starts at the origin facing +x, and both tracks start there.
    np.testing.assert_allclose(logs.true_poses[:, 0], 0.0, atol=1e-3)
    np.testing.assert_allclose(logs.odometry_poses[:, 0], logs.true_poses[:, 0])


def test_no_slip_odometry_matches_truth(logs):
    """Friction 1.0, 0.2 m/s: per 0.5 s interval |trans error| <= 2 mm (the first interval
    includes the start from rest) and |rot error| <= 0.02 rad; measured about 1.1 mm and
    0.012 rad (the heading transient when the turn starts)."""
    gentle = row(logs, 0)
    error = gentle.true_moves - gentle.odometry_moves
    assert np.max(np.abs(error[:, 1])) <= 2e-3
    assert np.max(np.abs(error[:, [0, 2]])) <= 0.02
    # The commanded 0.1 m per interval is driven (a sanity check of the wheel sign).
    np.testing.assert_allclose(gentle.true_moves[1:, 1], 0.1, rtol=0.02)
    assert drift(gentle) < 0.01


def test_slip_grows_as_friction_falls(logs):
    """Same aggressive commands at friction 1.0, 0.3, 0.05: the odometry drift and the mean
    |trans error| grow strictly; at 0.05 the robot covers less than 80% of the odometry."""
    drifts = [drift(row(logs, i)) for i in (1, 2, 3)]
    trans_error = [np.mean(np.abs(logs.true_moves[i, :, 1] - logs.odometry_moves[i, :, 1]))
                   for i in (1, 2, 3)]
    assert drifts[0] < drifts[1] < drifts[2], drifts
    assert trans_error[0] < trans_error[1] < trans_error[2], trans_error
    assert logs.true_moves[3, :, 1].sum() < 0.8 * logs.odometry_moves[3, :, 1].sum()


def test_slip_grows_with_acceleration(logs):
    """At friction 1.0 the aggressive commands (speed steps of 1 m/s) slip at least 10x
    more per interval than the gentle ones; so they do at 0.05."""
    def mean_trans_error(i):
        return np.mean(np.abs(logs.true_moves[i, :, 1] - logs.odometry_moves[i, :, 1]))
    assert mean_trans_error(1) > 10.0 * mean_trans_error(0)
    assert mean_trans_error(3) > 10.0 * mean_trans_error(4)


def test_encoder_step_matches_numpy():
    pose = np.array([1.0, -2.0, 0.3])
    delta = np.array([0.7, 1.1])
    travel = SPEC.wheel_radius * delta
    distance, turn = travel.mean(), (travel[1] - travel[0]) / SPEC.track_width
    expected = pose + np.array([distance * np.cos(0.3 + turn / 2),
                                distance * np.sin(0.3 + turn / 2), turn])
    np.testing.assert_allclose(rb.encoder_step(jnp.asarray(pose), jnp.asarray(delta), SPEC),
                               expected, rtol=1e-12)
    # wheel_speeds is the inverse: one second at those speeds gives back (v, w).
    speeds = np.asarray(rb.wheel_speeds(0.4, -0.5, SPEC))
    moved = np.asarray(rb.encoder_step(jnp.zeros(3), jnp.asarray(speeds) * 1e-3, SPEC)) * 1e3
    np.testing.assert_allclose([moved[0], moved[2]], [0.4, -0.5], rtol=1e-6)


@pytest.mark.parametrize("yaw", [0.0, 1.0, -2.5, 3.1])
def test_chassis_pose_yaw_from_quaternion(yaw):
    qpos = jnp.asarray([1.5, -0.5, 0.1, np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2), 0.0, 0.0])
    np.testing.assert_allclose(rb.chassis_pose(qpos), [1.5, -0.5, yaw], atol=1e-12)


def test_random_commands_diversified():
    commands = np.asarray(rb.random_commands(jax.random.key(0), 400, SPEC))
    assert commands.shape == (400, 2)
    assert np.all(np.abs(commands) <= SPEC.max_wheel_speed)
    speed = commands.mean(1) * SPEC.wheel_radius
    yaw_rate = (commands[:, 1] - commands[:, 0]) * SPEC.wheel_radius / SPEC.track_width
    # All four kinds occur: stops, pure turns, straight runs and arcs.
    stop = (speed == 0) & (yaw_rate == 0)
    turn = (np.abs(speed) < 1e-9) & (yaw_rate != 0)
    straight = (speed > 0) & (np.abs(yaw_rate) < 1e-9)
    arc = (speed > 0) & (np.abs(yaw_rate) > 1e-9)
    assert all(kind.sum() >= 40 for kind in (stop, turn, straight, arc))
    again = np.asarray(rb.random_commands(jax.random.key(0), 400, SPEC))
    np.testing.assert_array_equal(commands, again)


def test_bad_input_errors():
    robot = rb.make_robot(SPEC)
    with pytest.raises(ValueError, match=r"\(T, 2\)"):
        rb.simulate(robot, jnp.zeros((4, 3)), 1.0)
    with pytest.raises(ValueError, match="multiple of the physics timestep"):
        rb.simulate(robot, jnp.zeros((4, 2)), 1.0, interval=0.0123)
    with pytest.raises(ValueError, match=r"\(R, T, 2\)"):
        rb.simulate_batch(robot, jnp.zeros((4, 2)), 1.0)
