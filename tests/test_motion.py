"""Motion models against plain NumPy float64 references: the rot1-trans-rot2 decomposition,
Geiser et al. 2023, Eq. (1) with Table 1 numbers, sampling moments over many keys, the log-density, the
velocity (arc) and Ackermann models against fine-step Euler integration of their kinematics
(Victoria Park README), the stationary-robot degeneracy, jit and vmap."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam import motion
from jaxslam.types import default_params

# Geiser et al. 2023, Table 1: rows (rot1, trans, rot2), columns (translation, rotation, constant).
TABLE_1 = np.array([[0.0, 0.06, 0.0002], [0.02, 0.006, 0.00003], [0.0, 0.06, 0.0003]])
LOG_2PI = np.log(2 * np.pi)


# ---------------------------------------------------------------------------------------------
# NumPy float64 references


def ref_wrap(angle):
    return (np.asarray(angle, np.float64) + np.pi) % (2 * np.pi) - np.pi


def ref_odometry(pose_a, pose_b, min_translation):
    dx, dy = pose_b[0] - pose_a[0], pose_b[1] - pose_a[1]
    trans = np.hypot(dx, dy)
    rot1 = ref_wrap(np.arctan2(dy, dx) - pose_a[2]) if trans >= min_translation else 0.0
    rot2 = ref_wrap(pose_b[2] - pose_a[2] - rot1)
    return np.array([rot1, trans, rot2])


def ref_std(odometry, table=TABLE_1):
    """Geiser et al. 2023, Eq. (1): sigma = a |trans| + b |rot| + c; the translation's rot is |r1|+|r2|."""
    r1, t, r2 = np.abs(odometry)
    rots = (r1, r1 + r2, r2)
    return np.array([table[i, 0] * t + table[i, 1] * rots[i] + table[i, 2] for i in range(3)])


def ref_log_density(pose_prev, pose_next, odometry, min_translation, table=TABLE_1):
    true = ref_odometry(pose_prev, pose_next, min_translation)
    std = ref_std(odometry, table)
    diff = true - odometry
    diff[0], diff[2] = ref_wrap(diff[0]), ref_wrap(diff[2])
    log_move = np.sum(-0.5 * (diff / std) ** 2 - np.log(std) - 0.5 * LOG_2PI)
    return log_move - np.log(max(true[1], min_translation))


def euler_velocity(pose, speed, yaw_rate, dt, steps=200_000):
    """Explicit Euler of x' = v cos th, y' = v sin th, th' = w (vectorised over the steps)."""
    h = dt / steps
    theta = pose[2] + yaw_rate * h * np.arange(steps)
    return np.array([pose[0] + h * speed * np.sum(np.cos(theta)),
                     pose[1] + h * speed * np.sum(np.sin(theta)),
                     ref_wrap(pose[2] + yaw_rate * dt)])


def euler_ackermann(pose, speed, steering, dt, wheelbase=2.83, offset=0.76, fwd=3.78,
                    left=0.50, steps=200_000):
    """Victoria Park README equations (laser pose), explicit Euler."""
    vc = speed / (1.0 - np.tan(steering) * offset / wheelbase)
    rate = vc / wheelbase * np.tan(steering)
    h = dt / steps
    phi = pose[2] + rate * h * np.arange(steps)
    x_dot = vc * np.cos(phi) - rate * (fwd * np.sin(phi) + left * np.cos(phi))
    y_dot = vc * np.sin(phi) + rate * (fwd * np.cos(phi) - left * np.sin(phi))
    return np.array([pose[0] + h * np.sum(x_dot), pose[1] + h * np.sum(y_dot),
                     ref_wrap(pose[2] + rate * dt)])


@pytest.fixture(scope="module")
def params():
    # Eq. (1)'s Gaussian, the model these tests check: bursts off (their tests set them).
    return default_params(dtype=jnp.float64, motion_outlier_probability=0.0)


@pytest.fixture(scope="module")
def rng():
    return np.random.default_rng(1)


def angle_close(actual, expected, atol):
    np.testing.assert_allclose(ref_wrap(np.asarray(actual) - expected), 0.0, atol=atol)


# ---------------------------------------------------------------------------------------------
# Decomposition


def test_odometry_from_poses_vs_reference_and_round_trip(params, rng):
    prev = np.stack([rng.uniform(-5, 5, 50), rng.uniform(-5, 5, 50), rng.uniform(-3, 3, 50)], 1)
    nxt = prev + np.stack([rng.uniform(-1, 1, 50), rng.uniform(-1, 1, 50),
                           rng.uniform(-1, 1, 50)], 1)
    odo = np.asarray(motion.odometry_from_poses(jnp.asarray(prev), jnp.asarray(nxt),
                                                params.min_translation))
    min_translation = float(params.min_translation)
    ref = np.stack([ref_odometry(a, b, min_translation) for a, b in zip(prev, nxt)])
    np.testing.assert_allclose(odo[:, 1], ref[:, 1], rtol=1e-12)
    angle_close(odo[:, 0], ref[:, 0], 1e-12)
    angle_close(odo[:, 2], ref[:, 2], 1e-12)
    back = np.asarray(motion.apply_odometry(jnp.asarray(prev), jnp.asarray(odo)))
    np.testing.assert_allclose(back[:, :2], nxt[:, :2], atol=1e-12)
    angle_close(back[:, 2], nxt[:, 2], 1e-12)


def test_apply_odometry_jit_vmap(rng):
    pose = jnp.asarray(rng.normal(size=(7, 3)))
    odo = jnp.asarray(rng.normal(size=(7, 3)))
    eager = motion.apply_odometry(pose, odo)
    np.testing.assert_allclose(np.asarray(jax.jit(motion.apply_odometry)(pose, odo)),
                               np.asarray(eager), atol=1e-12)
    np.testing.assert_allclose(np.asarray(jax.vmap(motion.apply_odometry)(pose, odo)),
                               np.asarray(eager), atol=1e-12)


def _nearest_reference(move, reference):
    """NumPy float64: the backward form (rot1 + pi, -trans, rot2 + pi) where its rot1 is the
    nearer to the reference's (cos of the forward difference < 0)."""
    rot1, trans, rot2 = move
    if np.cos(rot1 - reference[0]) < 0:
        wrap = lambda a: (a + np.pi) % (2 * np.pi) - np.pi
        return np.array([wrap(rot1 + np.pi), -trans, wrap(rot2 + np.pi)])
    return np.array(move, np.float64)


def test_nearest_decomposition_vs_reference_jit_vmap_and_same_pose(rng):
    """Against a NumPy float64 reference (1e-12, x64 tests), eager / jit / vmap alike; both
    forms take a pose to the same pose (``apply_odometry``); a backward centimetre under a
    measured forward creep becomes a backward move with the measured rot1, not an error of
    pi; moves already near the reference, and a reference at exactly 90 degrees (cos = 0),
    are kept."""
    moves = np.stack([rng.uniform(-np.pi, np.pi, 64), rng.uniform(0, 0.5, 64),
                      rng.uniform(-np.pi, np.pi, 64)], 1)
    reference = np.stack([rng.uniform(-np.pi, np.pi, 64), rng.uniform(-0.5, 0.5, 64),
                          rng.uniform(-np.pi, np.pi, 64)], 1)
    expected = np.stack([_nearest_reference(m, r) for m, r in zip(moves, reference)])
    eager = np.asarray(motion.nearest_decomposition(jnp.asarray(moves), jnp.asarray(reference)))
    for found in (eager, np.asarray(jax.jit(motion.nearest_decomposition)(moves, reference)),
                  np.asarray(jax.vmap(motion.nearest_decomposition)(moves, reference))):
        np.testing.assert_allclose(found[:, 1], expected[:, 1], atol=1e-12)
        angle_close(found[:, 0], expected[:, 0], 1e-12)
        angle_close(found[:, 2], expected[:, 2], 1e-12)
    assert 0 < np.sum(eager[:, 1] < 0) < 64  # both branches taken
    pose = rng.normal(size=(64, 3))
    a = np.asarray(motion.apply_odometry(jnp.asarray(pose), jnp.asarray(moves)))
    b = np.asarray(motion.apply_odometry(jnp.asarray(pose), jnp.asarray(eager)))
    np.testing.assert_allclose(a[:, :2], b[:, :2], atol=1e-12)
    angle_close(a[:, 2], b[:, 2], 1e-12)
    # A robot that crept 2 cm forward (measured) while the true path went 1.5 cm back.
    true = motion.odometry_from_poses(jnp.zeros(3), jnp.array([-0.015, 0.0, 0.01]), 0.01)
    assert abs(abs(float(true[0])) - np.pi) < 1e-9  # the forward form: rot1 = pi
    near = np.asarray(motion.nearest_decomposition(true, jnp.array([0.0, 0.02, 0.0])))
    np.testing.assert_allclose(near, [0.0, -0.015, 0.01], atol=1e-12)
    kept = np.asarray(motion.nearest_decomposition(jnp.array([0.3, 0.5, -0.1]),
                                                   jnp.array([0.3 + np.pi / 2, 0.5, 0.0])))
    np.testing.assert_allclose(kept, [0.3, 0.5, -0.1], atol=1e-12)


def test_stationary_robot_jitter_is_a_pure_turn(params, rng):
    """Geiser et al. 2023 degeneracy: a parked robot whose pose jitters by millimetres (and a few mrad)
    must give rot1 = 0 (not the angle of the jitter) and small finite stds."""
    base = np.array([3.0, -2.0, 0.7])
    jitter = np.stack([rng.uniform(-3e-3, 3e-3, 200), rng.uniform(-3e-3, 3e-3, 200),
                       rng.uniform(-2e-3, 2e-3, 200)], 1)
    odo = motion.odometry_from_poses(jnp.asarray(np.broadcast_to(base, jitter.shape)),
                                     jnp.asarray(base + jitter), params.min_translation)
    odo = np.asarray(odo)
    np.testing.assert_array_equal(odo[:, 0], 0.0)
    angle_close(odo[:, 2], jitter[:, 2], 1e-12)
    std = np.asarray(motion.odometry_std(jnp.asarray(odo), params))
    assert np.all(np.isfinite(std))
    # With rot1 = 0: sigma_trans <= 0.02 * 4.3 mm + 0.006 * 2e-3 + 3e-5 < 0.2 mm, instead of
    # up to b2 * pi ~ 19 mm when rot1 is the angle of the jitter.
    assert np.all(std[:, 1] < 2e-4), std[:, 1].max()
    assert np.all(std[:, 0] < 1e-3) and np.all(std[:, 2] < 1e-3)


def test_moving_robot_keeps_rot1(params):
    odo = np.asarray(motion.odometry_from_poses(jnp.asarray([0.0, 0.0, 0.0]),
                                                jnp.asarray([0.0, 0.5, 0.0]),
                                                params.min_translation))
    np.testing.assert_allclose(odo, [np.pi / 2, 0.5, -np.pi / 2], atol=1e-12)


def test_odometry_from_relative_gradient_finite_at_zero(params):
    grad = jax.grad(lambda d: jnp.sum(motion.odometry_from_relative(d, params.min_translation)))(
        jnp.zeros(3))
    assert np.all(np.isfinite(np.asarray(grad)))


# ---------------------------------------------------------------------------------------------
# Eq. (1) and sampling


def test_default_params_are_table_1(params):
    np.testing.assert_array_equal(np.asarray(params.rot1_noise), TABLE_1[0])
    np.testing.assert_array_equal(np.asarray(params.trans_noise), TABLE_1[1])
    np.testing.assert_array_equal(np.asarray(params.rot2_noise), TABLE_1[2])


def test_odometry_std_is_eq_1(params, rng):
    odo = np.stack([rng.uniform(-np.pi, np.pi, 40), rng.uniform(-2, 2, 40),
                    rng.uniform(-np.pi, np.pi, 40)], 1)
    out = np.asarray(motion.odometry_std(jnp.asarray(odo), params))
    np.testing.assert_allclose(out, np.stack([ref_std(o) for o in odo]), rtol=1e-12)
    # A worked case by hand: rot1 = 0.1, trans = 1, rot2 = -0.2.
    np.testing.assert_allclose(
        np.asarray(motion.odometry_std(jnp.asarray([0.1, 1.0, -0.2]), params)),
        [0.06 * 0.1 + 0.0002, 0.02 + 0.006 * 0.3 + 0.00003, 0.06 * 0.2 + 0.0003], rtol=1e-12)


@pytest.mark.parametrize("odometry", [(0.3, 1.2, -0.4), (0.0, 0.0, 0.05)])
def test_sample_odometry_moments(params, odometry):
    """Mean within 4 standard errors (sigma / sqrt(n)); std within 4 standard errors of the
    sample std (sigma / sqrt(2 n))."""
    n = 40_000
    odo = jnp.asarray(odometry, jnp.float64)
    keys = jax.random.split(jax.random.key(7), n)
    draws = np.asarray(jax.jit(jax.vmap(motion.sample_odometry, in_axes=(0, None, None)))(
        keys, odo, params))
    sigma = ref_std(np.asarray(odometry))
    mean_err = np.abs(draws.mean(0) - np.asarray(odometry))
    assert np.all(mean_err < 4 * sigma / np.sqrt(n)), (mean_err, sigma)
    std_err = np.abs(draws.std(0) - sigma)
    assert np.all(std_err < 4 * sigma / np.sqrt(2 * n)), (std_err, sigma)


def test_sample_motion_pose_moments_and_vmap(params):
    """Poses from sample_motion: mean and covariance equal apply_odometry of the reference move
    samples (same keys would be implementation-dependent, so compare moments: 4 SE)."""
    n = 40_000
    pose = jnp.asarray([1.0, 2.0, 0.5])
    control = jnp.asarray([0.2, 1.0, -0.1])
    keys = jax.random.split(jax.random.key(3), n)
    draws = np.asarray(jax.vmap(motion.sample_motion, in_axes=(0, None, None, None))(
        keys, pose, control, params))
    rng = np.random.default_rng(5)
    sigma = ref_std(np.asarray(control))
    moves = np.asarray(control) + rng.normal(size=(n, 3)) * sigma
    ref = np.stack([1.0 + moves[:, 1] * np.cos(0.5 + moves[:, 0]),
                    2.0 + moves[:, 1] * np.sin(0.5 + moves[:, 0]),
                    0.5 + moves[:, 0] + moves[:, 2]], 1)
    se = draws.std(0) * np.sqrt(2.0 / n)  # standard error of a difference of two means
    assert np.all(np.abs(draws.mean(0) - ref.mean(0)) < 4 * se)
    np.testing.assert_allclose(draws.std(0), ref.std(0), rtol=4 * np.sqrt(1.0 / n))
    # Different keys give different draws; the same key the same draw.
    assert len(np.unique(draws[:, 0])) == n
    again = motion.sample_motion(keys[0], pose, control, params)
    np.testing.assert_array_equal(np.asarray(again), draws[0])


def test_motion_log_density_vs_reference(params, rng):
    control = np.array([0.25, 0.8, -0.3])
    prev = np.array([1.0, -1.0, 0.4])
    keys = jax.random.split(jax.random.key(11), 30)
    poses = np.asarray(jax.vmap(motion.sample_motion, in_axes=(0, None, None, None))(
        keys, jnp.asarray(prev), jnp.asarray(control), params))
    fn = jax.jit(jax.vmap(motion.motion_log_density, in_axes=(None, 0, None, None)))
    out = np.asarray(fn(jnp.asarray(prev), jnp.asarray(poses), jnp.asarray(control), params))
    min_translation = float(params.min_translation)
    ref = np.array([ref_log_density(prev, p, control, min_translation) for p in poses])
    np.testing.assert_allclose(out, ref, rtol=1e-9, atol=1e-9)
    eager = motion.motion_log_density(jnp.asarray(prev), jnp.asarray(poses[0]),
                                      jnp.asarray(control), params)
    np.testing.assert_allclose(float(eager), ref[0], rtol=1e-9)


def test_motion_log_density_integrates_to_one(params):
    """Importance sampling: E_q[p / q] = 1 with q a broad Gaussian over the pose. Tolerance:
    4 Monte Carlo standard errors of the estimate plus 1% (the linear-Gaussian move density
    neglects negative translations and angle wrap)."""
    n = 200_000
    control = np.array([0.2, 1.0, -0.1])
    prev = np.zeros(3)
    mean = np.array([np.cos(0.2), np.sin(0.2), 0.1])
    std = np.array([0.06, 0.06, 0.05])
    rng = np.random.default_rng(2)
    poses = mean + rng.normal(size=(n, 3)) * std
    log_q = np.sum(-0.5 * ((poses - mean) / std) ** 2 - np.log(std) - 0.5 * LOG_2PI, axis=1)
    log_p = np.asarray(jax.jit(jax.vmap(motion.motion_log_density,
                                        in_axes=(None, 0, None, None)))(
        jnp.asarray(prev), jnp.asarray(poses), jnp.asarray(control), params))
    ratio = np.exp(log_p - log_q)
    estimate, se = ratio.mean(), ratio.std() / np.sqrt(n)
    assert abs(estimate - 1.0) < 4 * se + 0.01, (estimate, se)


def test_motion_log_density_rejects_a_pose_behind_the_start(params):
    """The model's robot does not drive backwards (``motion_log_density``'s docstring): a
    robot measured to creep 5 cm forwards (0.007 rad rotation stds) has a pose 4 cm behind
    its start scored as the forward move (pi, 0.04, 0.002 - pi), about (pi / 0.007)^2 = 2e5
    (rot1 and rot2 together) below the same displacement ahead, as the reference writes it;
    the backward move (0, -0.04, 0.002), 3 translation stds off, is not counted."""
    creeping = params._replace(rot1_noise=jnp.asarray([0.0, 0.0, 0.007]),
                               trans_noise=jnp.asarray([0.0, 0.0, 0.03]),
                               rot2_noise=jnp.asarray([0.0, 0.0, 0.007]))
    table = np.asarray([creeping.rot1_noise, creeping.trans_noise, creeping.rot2_noise])
    control = np.array([0.0, 0.05, 0.0])
    prev = np.array([1.0, 2.0, 0.5])
    step = np.array([0.04 * np.cos(0.5), 0.04 * np.sin(0.5), 0.002])
    density = jax.jit(motion.motion_log_density)
    behind = float(density(jnp.asarray(prev), jnp.asarray(prev - step * [1, 1, -1]),
                           jnp.asarray(control), creeping))
    ahead = float(density(jnp.asarray(prev), jnp.asarray(prev + step), jnp.asarray(control),
                          creeping))
    np.testing.assert_allclose(behind, ref_log_density(prev, prev - step * [1, 1, -1], control,
                                                       0.01, table), rtol=1e-9)
    assert ahead - behind > 1.9e5


# ---------------------------------------------------------------------------------------------
# Velocity and Ackermann models against fine-step Euler


@pytest.mark.parametrize("speed,yaw_rate,dt", [(2.0, 0.5, 1.0), (1.0, -1.3, 0.5),
                                               (1.5, 1e-9, 0.8), (0.0, 0.4, 1.0)])
def test_velocity_model_vs_euler(params, speed, yaw_rate, dt):
    pose = np.array([0.5, -1.0, 2.9])
    control = jnp.asarray([speed, yaw_rate, dt])
    out = np.asarray(motion.predict_pose(jnp.asarray(pose), control, params, "velocity"))
    ref = euler_velocity(pose, speed, yaw_rate, dt)
    np.testing.assert_allclose(out[:2], ref[:2], atol=1e-4)  # Euler error ~ v w dt h / 2
    angle_close(out[2], ref[2], 1e-9)


@pytest.mark.parametrize("speed,steering,dt", [(3.0, 0.2, 0.5), (2.0, -0.35, 0.25),
                                               (1.0, 0.0, 1.0)])
def test_ackermann_model_vs_euler(params, speed, steering, dt):
    pose = np.array([10.0, 4.0, -0.8])
    control = jnp.asarray([speed, steering, dt])
    out = np.asarray(motion.predict_pose(jnp.asarray(pose), control, params, "ackermann"))
    ref = euler_ackermann(pose, speed, steering, dt)
    np.testing.assert_allclose(out[:2], ref[:2], atol=1e-4)
    angle_close(out[2], ref[2], 1e-9)


def test_motion_models_jit_vmap(params):
    poses = jnp.asarray([[0.0, 0.0, 0.0], [1.0, 2.0, 3.0], [-1.0, 0.5, -2.0]])
    controls = jnp.asarray([[2.0, 0.3, 0.5], [1.0, -0.1, 0.2], [0.5, 0.0, 1.0]])
    for model in ("velocity", "ackermann"):
        eager = np.stack([np.asarray(motion.predict_pose(p, c, params, model))
                          for p, c in zip(poses, controls)])
        mapped = jax.jit(jax.vmap(lambda p, c, m=model: motion.predict_pose(p, c, params, m)))(
            poses, controls)
        np.testing.assert_allclose(np.asarray(mapped), eager, atol=1e-12)
        batched = motion.predict_pose(poses, controls, params, model)
        np.testing.assert_allclose(np.asarray(batched), eager, atol=1e-12)


def test_unknown_motion_model_raises(params):
    with pytest.raises(ValueError, match="motion_model"):
        motion.control_to_odometry(jnp.zeros(3), params, "bicycle")


# ---------------------------------------------------------------------------------------------
# Bursts: the scale mixture (1 - eps) N(0, sigma^2) + eps N(0, kappa^2 sigma^2)


def _np_burst_log_density(true_odometry, odometry, std, eps, kappa):
    """float64 reference: log of the two-Gaussian mixture over the 3 components."""
    diff = np.asarray(true_odometry, np.float64) - np.asarray(odometry, np.float64)
    diff[..., [0, 2]] = (diff[..., [0, 2]] + np.pi) % (2 * np.pi) - np.pi

    def log_normal(scale):
        return np.sum(-0.5 * (diff / scale) ** 2 - np.log(scale) - 0.5 * np.log(2 * np.pi), -1)

    return np.logaddexp(np.log1p(-eps) + log_normal(std), np.log(eps) + log_normal(kappa * std))


@pytest.mark.parametrize("jit", [False, True])
def test_burst_density_matches_numpy(jit):
    from jaxslam.motion import odometry_log_density, odometry_std

    params = default_params(motion_outlier_probability=0.1, motion_outlier_scale=4.0)
    rng = np.random.default_rng(3)
    odometry = jnp.asarray(rng.normal(0, 0.3, (64, 3)), jnp.float32)
    true = odometry + jnp.asarray(rng.normal(0, 0.05, (64, 3)), jnp.float32)
    fn = jax.jit(odometry_log_density) if jit else odometry_log_density
    got = np.asarray(fn(true, odometry, params))
    std = np.asarray(odometry_std(odometry, params), np.float64)
    want = _np_burst_log_density(true, odometry, std, 0.1, 4.0)
    # float32 inputs: the log-density of a 3-vector agrees to ~1e-4 relative.
    np.testing.assert_allclose(got, want, rtol=2e-4, atol=2e-3)
    # Under vmap over stacked params (a sweep over eps) the same.
    stacked = jax.tree.map(lambda a, b: jnp.stack([a, b]), params,
                           params._replace(motion_outlier_probability=jnp.float32(0.3)))
    swept = jax.vmap(odometry_log_density, in_axes=(None, None, 0))(true, odometry, stacked)
    np.testing.assert_allclose(np.asarray(swept[1]),
                               _np_burst_log_density(true, odometry, std, 0.3, 4.0),
                               rtol=2e-4, atol=2e-3)


def test_no_bursts_is_eq1_bit_for_bit():
    from jaxslam.motion import odometry_log_density, odometry_std, sample_odometry

    params = default_params(motion_outlier_probability=0.0)
    odometry = jnp.array([0.1, 0.5, -0.2])
    key = jax.random.PRNGKey(5)
    plain = odometry + jax.random.normal(key, (3,)) * odometry_std(odometry, params)
    drawn = sample_odometry(key, odometry, params)
    np.testing.assert_array_equal(np.asarray(drawn[1]), np.asarray(plain[1]))
    true = odometry + 0.01
    std = odometry_std(odometry, params)
    gaussian = jnp.sum(-0.5 * ((true - odometry) / std) ** 2 - jnp.log(std)
                       - 0.5 * np.log(2 * np.pi))
    np.testing.assert_allclose(float(odometry_log_density(true, odometry, params)),
                               float(gaussian), rtol=1e-6)


def test_burst_draws_have_the_mixture_variance():
    from jaxslam.motion import odometry_std, sample_odometry

    eps, kappa, n = 0.2, 4.0, 20000
    params = default_params(motion_outlier_probability=eps, motion_outlier_scale=kappa)
    odometry = jnp.array([0.0, 1.0, 0.0])
    draws = jax.vmap(lambda k: sample_odometry(k, odometry, params))(
        jax.random.split(jax.random.PRNGKey(0), n))
    white = ((np.asarray(draws, np.float64) - np.asarray(odometry, np.float64)[None])
             / np.asarray(odometry_std(odometry, params), np.float64)[None])
    var = np.mean(white**2)
    expected = (1 - eps) + eps * kappa**2  # 4.0
    # The variance of white^2 for this mixture is E[s^4] 3 - E[s^2]^2 ~ 140; over 3n
    # components the standard error of the mean is ~0.07: 5 standard errors.
    assert abs(var - expected) < 0.35, var


def test_fit_bursts_recovers_a_mixture_and_rejects_a_gaussian():
    from jaxslam.noise_fit import fit_bursts

    rng = np.random.default_rng(0)
    n = 4000
    burst = rng.uniform(size=n) < 0.1
    white = rng.normal(size=(n, 2)) * np.where(burst, 5.0, 1.0)[:, None]
    eps, core, kappa = fit_bursts(white)
    # 4000 moves, 400 bursts: eps within +-0.03 (about 3 binomial std), kappa within 15 %.
    assert abs(eps - 0.1) < 0.03 and abs(core - 1.0) < 0.05 and abs(kappa - 5.0) < 0.75
    assert fit_bursts(rng.normal(size=(n, 2))) is None
    assert fit_bursts(rng.normal(size=(10, 2))) is None  # too few moves


# ---------------------------------------------------------------------------------------------
# Ackermann rates and the pose -> odometry inverse: NumPy float64, jit, vmap, edges


def ref_ackermann_rates(speed, steering, wheelbase, offset):
    """Victoria Park README: vc = v / (1 - tan(a) H / L), omega = vc tan(a) / L (float64)."""
    centre = speed / (1.0 - np.tan(steering) * offset / wheelbase)
    return centre, centre * np.tan(steering) / wheelbase


def test_ackermann_rates_vs_numpy_jit_vmap(rng):
    speed, steering = rng.uniform(-1, 6, 40), rng.uniform(-0.6, 0.6, 40)
    want = ref_ackermann_rates(speed, steering, 2.83, 0.76)
    eager = motion.ackermann_rates(jnp.asarray(speed), jnp.asarray(steering), 2.83, 0.76)
    jitted = jax.jit(motion.ackermann_rates)(jnp.asarray(speed), jnp.asarray(steering), 2.83,
                                             0.76)
    mapped = jax.vmap(motion.ackermann_rates, in_axes=(0, 0, None, None))(
        jnp.asarray(speed), jnp.asarray(steering), 2.83, 0.76)
    for got in (eager, jitted, mapped):  # the same float64 arithmetic: rounding only
        np.testing.assert_allclose(np.asarray(got[0]), want[0], rtol=1e-13, atol=1e-13)
        np.testing.assert_allclose(np.asarray(got[1]), want[1], rtol=1e-13, atol=1e-13)


def test_ackermann_rates_edges():
    centre, rate = motion.ackermann_rates(jnp.asarray([2.0, 0.0, -1.5]),
                                          jnp.asarray([0.0, 0.3, 0.0]), 2.83, 0.76)
    # Straight ahead the encoder wheel moves with the centre and nothing turns; standing still
    # nothing moves whatever the steering.
    np.testing.assert_array_equal(np.asarray(centre), [2.0, 0.0, -1.5])
    np.testing.assert_array_equal(np.asarray(rate), [0.0, 0.0, 0.0])
    # Turning left (a > 0) the rear-left encoder wheel is on the inside: the centre is faster.
    centre, rate = motion.ackermann_rates(jnp.asarray(2.0), jnp.asarray(0.2), 2.83, 0.76)
    assert float(centre) > 2.0 and float(rate) > 0.0


def test_ackermann_delta_uses_the_rates(params):
    """The Ackermann move turns by omega dt, omega from ``ackermann_rates`` (params' geometry)."""
    control = jnp.asarray([3.0, 0.25, 0.4])
    _, rate = motion.ackermann_rates(control[0], control[1], params.wheelbase,
                                     params.encoder_offset)
    delta = motion.ackermann_delta(control, params)
    np.testing.assert_allclose(float(delta[2]), float(rate) * 0.4, rtol=1e-12)


def test_odometry_from_poses_across_pi_jit_vmap(params):
    """Headings either side of +-pi: rot1 and rot2 are the short turns, wrapped; a pure turn
    across +-pi keeps rot1 = 0 and puts the whole (short) turn in rot2."""
    prev = np.array([[0.0, 0.0, np.pi - 0.05], [1.0, 1.0, -np.pi + 0.02],
                     [2.0, -1.0, np.pi - 0.01]])
    nxt = np.array([[-1.0, 0.02, -np.pi + 0.05], [0.0, 1.0, np.pi - 0.03],
                    [2.0 + 1e-4, -1.0, -np.pi + 0.01]])
    min_translation = float(params.min_translation)
    want = np.stack([ref_odometry(a, b, min_translation) for a, b in zip(prev, nxt)])
    eager = motion.odometry_from_poses(jnp.asarray(prev), jnp.asarray(nxt), min_translation)
    jitted = jax.jit(motion.odometry_from_poses)(jnp.asarray(prev), jnp.asarray(nxt),
                                                min_translation)
    mapped = jax.vmap(motion.odometry_from_poses, in_axes=(0, 0, None))(
        jnp.asarray(prev), jnp.asarray(nxt), min_translation)
    for got in (eager, jitted, mapped):
        got = np.asarray(got)
        np.testing.assert_allclose(got[:, 1], want[:, 1], rtol=1e-12)
        angle_close(got[:, [0, 2]], want[:, [0, 2]], 1e-12)
        assert np.all(np.abs(got[:, [0, 2]]) < 0.2)  # short turns, never ~2 pi
    assert np.asarray(eager)[2, 0] == 0.0  # 0.1 mm: a pure turn of 0.02 rad
    np.testing.assert_allclose(np.asarray(eager)[2, 2], 0.02, atol=1e-12)
