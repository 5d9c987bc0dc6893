"""Landmark EKF against a plain NumPy float64 EKF with explicit 2x2 matrices (1e-9 relative, in
float64), covariance health after 10^5 float32 updates, jit, vmap over landmarks and
particles, and the zero-distance edge."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.stats import multivariate_normal

from jaxslam import ekf
from jaxslam.types import default_params

RTOL = 1e-9
# Table 2 and the floors of default_params.
RANGE_NOISE, BEARING_NOISE = (0.005, 0.0), (0.0005, 0.0)
RANGE_FLOOR, BEARING_FLOOR = 0.01, 0.001


# ---------------------------------------------------------------------------------------------
# NumPy float64 reference EKF (explicit 2x2 matrices)


def ref_wrap(angle):
    return (np.asarray(angle, np.float64) + np.pi) % (2 * np.pi) - np.pi


def ref_noise(distance):
    sr = max(RANGE_NOISE[0] * distance + RANGE_NOISE[1], RANGE_FLOOR)
    sb = max(BEARING_NOISE[0] * distance + BEARING_NOISE[1], BEARING_FLOOR)
    return np.diag([sr**2, sb**2])


def ref_predict(pose, mean, cov):
    """Returns (z_hat (2,), H (2, 2), S (2, 2))."""
    dx, dy = mean[0] - pose[0], mean[1] - pose[1]
    r = np.hypot(dx, dy)
    z_hat = np.array([r, ref_wrap(np.arctan2(dy, dx) - pose[2])])
    jac = np.array([[dx / r, dy / r], [-dy / r**2, dx / r**2]])
    return z_hat, jac, jac @ cov @ jac.T + ref_noise(r)


def ref_innovation(z, z_hat):
    return np.array([z[0] - z_hat[0], ref_wrap(z[1] - z_hat[1])])


def ref_update(pose, mean, cov, z):
    z_hat, jac, s = ref_predict(pose, mean, cov)
    gain = cov @ jac.T @ np.linalg.inv(s)
    new_mean = mean + gain @ ref_innovation(z, z_hat)
    new_cov = (np.eye(2) - gain @ jac) @ cov  # textbook form (Joseph is equal in exact math)
    return new_mean, 0.5 * (new_cov + new_cov.T)


def ref_initialize(pose, z):
    angle = pose[2] + z[1]
    mean = pose[:2] + z[0] * np.array([np.cos(angle), np.sin(angle)])
    g = np.array([[np.cos(angle), -z[0] * np.sin(angle)], [np.sin(angle), z[0] * np.cos(angle)]])
    return mean, g @ ref_noise(z[0]) @ g.T


def components(cov):
    return np.array([cov[0, 0], cov[0, 1], cov[1, 1]])


def matrix(comp):
    return np.array([[comp[0], comp[1]], [comp[1], comp[2]]])


# ---------------------------------------------------------------------------------------------
# Fixtures: a particle with M landmarks of random covariance and K observations


@pytest.fixture(scope="module")
def params64():
    return default_params(dtype=jnp.float64)


def random_case(seed, num_slots=12, num_obs=5):
    rng = np.random.default_rng(seed)
    pose = np.array([rng.uniform(-5, 5), rng.uniform(-5, 5), rng.uniform(-np.pi, np.pi)])
    distance = rng.uniform(0.5, 25.0, num_slots)
    angle = rng.uniform(-np.pi, np.pi, num_slots)
    mean = pose[:2] + np.stack([distance * np.cos(angle), distance * np.sin(angle)], 1)
    covs = []
    for _ in range(num_slots):
        a = rng.normal(size=(2, 2)) * 0.3
        covs.append(a @ a.T + 1e-3 * np.eye(2))
    cov = np.stack([components(c) for c in covs])
    z = np.stack([rng.uniform(0.5, 25.0, num_obs), rng.uniform(-np.pi, np.pi, num_obs)], 1)
    return pose, mean, cov, z


def predict64(case, params):
    pose, mean, cov, _ = case
    return ekf.predict_measurements(jnp.asarray(pose), jnp.asarray(mean), jnp.asarray(cov),
                                    params)


# ---------------------------------------------------------------------------------------------
# Reference comparisons (float64, 1e-9 relative)


@pytest.mark.parametrize("use_jit", [False, True])
def test_predict_measurements_vs_reference(params64, use_jit):
    case = random_case(0)
    pose, mean, cov, _ = case
    fn = jax.jit(ekf.predict_measurements) if use_jit else ekf.predict_measurements
    p = fn(jnp.asarray(pose), jnp.asarray(mean), jnp.asarray(cov), params64)
    assert p.range.dtype == jnp.float64
    for m in range(mean.shape[0]):
        z_hat, jac, s = ref_predict(pose, mean[m], matrix(cov[m]))
        np.testing.assert_allclose(float(p.range[m]), z_hat[0], rtol=RTOL)
        np.testing.assert_allclose(ref_wrap(float(p.bearing[m]) - z_hat[1]), 0.0, atol=1e-12)
        np.testing.assert_allclose([p.h00[m], p.h01[m], p.h10[m], p.h11[m]], jac.ravel(),
                                   rtol=RTOL, atol=1e-15)
        np.testing.assert_allclose([p.s_rr[m], p.s_rb[m], p.s_bb[m]], components(s),
                                   rtol=RTOL, atol=1e-15)
        np.testing.assert_allclose([p.i_rr[m], p.i_rb[m], p.i_bb[m]],
                                   components(np.linalg.inv(s)), rtol=RTOL, atol=1e-12)
        np.testing.assert_allclose(float(p.log_det[m]), np.log(np.linalg.det(s)), rtol=RTOL)


@pytest.mark.parametrize("use_jit", [False, True])
def test_mahalanobis_and_log_likelihood_vs_reference(params64, use_jit):
    case = random_case(1)
    pose, mean, cov, z = case
    p = predict64(case, params64)
    maha = jax.jit(ekf.mahalanobis_sq) if use_jit else ekf.mahalanobis_sq
    loglik = jax.jit(ekf.gaussian_log_likelihood) if use_jit else ekf.gaussian_log_likelihood
    d2 = np.asarray(maha(jnp.asarray(z), p))
    ll = np.asarray(loglik(jnp.asarray(d2), p.log_det[None, :]))
    assert d2.shape == (z.shape[0], mean.shape[0])
    for k in range(z.shape[0]):
        for m in range(mean.shape[0]):
            z_hat, _, s = ref_predict(pose, mean[m], matrix(cov[m]))
            nu = ref_innovation(z[k], z_hat)
            np.testing.assert_allclose(d2[k, m], nu @ np.linalg.solve(s, nu), rtol=RTOL)
            np.testing.assert_allclose(ll[k, m], multivariate_normal(np.zeros(2), s).logpdf(nu),
                                       rtol=RTOL)


def test_mahalanobis_wraps_bearing(params64):
    """An observation at bearing pi - e and a landmark at -pi + e are 2e apart, not 2 pi."""
    pose = jnp.asarray([0.0, 0.0, 0.0])
    mean = jnp.asarray([[-10.0, -0.01]])  # bearing ~ -pi + 0.001
    cov = jnp.asarray([[0.01, 0.0, 0.01]])
    p = ekf.predict_measurements(pose, mean, cov, params64)
    z = jnp.stack([p.range, jnp.full_like(p.range, np.pi - 0.001)], -1)
    d2 = float(ekf.mahalanobis_sq(z, p)[0, 0])
    nu_b = ref_wrap(np.pi - 0.001 - float(p.bearing[0]))
    assert abs(nu_b) < 0.01
    np.testing.assert_allclose(d2, nu_b**2 * float(p.i_bb[0]), rtol=1e-9)


def test_unexplained_log_likelihood_vs_reference(params64):
    ranges = np.array([0.0, 1.0, 5.0, 19.9])
    out = np.asarray(ekf.unexplained_log_likelihood(jnp.asarray(ranges), params64))
    gate = float(params64.association_gate)
    ref = [-0.5 * gate - 0.5 * np.log(np.linalg.det(ref_noise(r))) - np.log(2 * np.pi)
           for r in ranges]
    np.testing.assert_allclose(out, ref, rtol=RTOL)


@pytest.mark.parametrize("use_jit", [False, True])
def test_initialize_landmarks_vs_reference(params64, use_jit):
    pose, _, _, z = random_case(2, num_obs=8)
    fn = jax.jit(ekf.initialize_landmarks) if use_jit else ekf.initialize_landmarks
    mean, cov = fn(jnp.asarray(pose), jnp.asarray(z), params64)
    for k in range(z.shape[0]):
        ref_mean, ref_cov = ref_initialize(pose, z[k])
        np.testing.assert_allclose(np.asarray(mean[k]), ref_mean, rtol=RTOL)
        np.testing.assert_allclose(np.asarray(cov[k]), components(ref_cov), rtol=RTOL,
                                   atol=1e-15)


@pytest.mark.parametrize("use_jit", [False, True])
def test_update_landmarks_vs_reference(params64, use_jit):
    case = random_case(3)
    pose, mean, cov, _ = case
    rng = np.random.default_rng(30)
    p = predict64(case, params64)
    # One observation per slot near the prediction (a plausible match), some bearings across pi.
    z = np.stack([np.asarray(p.range) + rng.normal(0, 0.05, mean.shape[0]),
                  ref_wrap(np.asarray(p.bearing) + rng.normal(0, 0.01, mean.shape[0]))], 1)
    fn = jax.jit(ekf.update_landmarks) if use_jit else ekf.update_landmarks
    new_mean, new_cov = fn(jnp.asarray(mean), jnp.asarray(cov), p, jnp.asarray(z), params64)
    for m in range(mean.shape[0]):
        ref_mean, ref_cov = ref_update(pose, mean[m], matrix(cov[m]), z[m])
        np.testing.assert_allclose(np.asarray(new_mean[m]), ref_mean, rtol=RTOL)
        np.testing.assert_allclose(np.asarray(new_cov[m]), components(ref_cov), rtol=1e-8,
                                   atol=1e-14 * np.abs(ref_cov).max())


def test_expand_covariance():
    comp = jnp.asarray([[1.0, 0.2, 3.0], [4.0, -1.0, 5.0]])
    np.testing.assert_array_equal(np.asarray(ekf.expand_covariance(comp)),
                                  [[[1.0, 0.2], [0.2, 3.0]], [[4.0, -1.0], [-1.0, 5.0]]])


# ---------------------------------------------------------------------------------------------
# vmap over particles and landmarks


def test_vmap_over_particles_matches_loop(params64):
    cases = [random_case(10 + i) for i in range(4)]
    poses = jnp.asarray(np.stack([c[0] for c in cases]))
    means = jnp.asarray(np.stack([c[1] for c in cases]))
    covs = jnp.asarray(np.stack([c[2] for c in cases]))
    z = jnp.asarray(cases[0][3])

    def one(pose, mean, cov):
        p = ekf.predict_measurements(pose, mean, cov, params64)
        z_slot = jnp.stack([p.range + 0.01, p.bearing - 0.002], -1)
        new_mean, new_cov = ekf.update_landmarks(mean, cov, p, z_slot, params64)
        return ekf.mahalanobis_sq(z, p), new_mean, new_cov

    mapped = jax.jit(jax.vmap(one))(poses, means, covs)
    for i in range(len(cases)):
        single = one(poses[i], means[i], covs[i])
        for got, want in zip(mapped, single):
            np.testing.assert_allclose(np.asarray(got[i]), np.asarray(want), rtol=1e-12)


def test_vmap_over_landmarks_matches_batched(params64):
    """The (M,) functions are elementwise over landmarks: M single-slot calls agree."""
    case = random_case(4)
    pose, mean, cov, _ = case
    batched = predict64(case, params64)
    mapped = jax.vmap(lambda m, c: ekf.predict_measurements(jnp.asarray(pose), m[None], c[None],
                                                            params64))(
        jnp.asarray(mean), jnp.asarray(cov))
    for got, want in zip(mapped, batched):
        np.testing.assert_allclose(np.asarray(got)[:, 0], np.asarray(want), rtol=1e-12)


# ---------------------------------------------------------------------------------------------
# Covariance health over 10^5 float32 updates


def test_covariance_spd_after_1e5_float32_updates():
    """A landmark at 10 m seen 10^5 times from poses circling it, float32, inside lax.scan.
    Every step: a > 0, c > 0, det > 0 (the components are symmetric by construction). At the
    end the covariance matches the float64 information-form answer
    (Sigma_0^-1 + sum_t H_t^T R_t^-1 H_t)^-1 within 5% (noise-free observations, so the EKF
    is linear up to float32 rounding)."""
    num = 100_000
    params = default_params(dtype=jnp.float32)
    landmark = np.array([3.0, -4.0])
    angle = np.linspace(0.0, 6 * np.pi, num)
    poses = np.stack([landmark[0] + 10 * np.cos(angle), landmark[1] + 10 * np.sin(angle),
                      angle + np.pi / 2], 1)  # facing along the circle: bearing +pi/2
    z = np.stack([np.full(num, 10.0), np.full(num, np.pi / 2)], 1)
    init_pose = np.array([landmark[0] + 10, landmark[1], np.pi])
    mean0, cov0 = ekf.initialize_landmarks(jnp.asarray(init_pose, jnp.float32),
                                           jnp.asarray([[10.0, 0.0]], jnp.float32), params)

    def body(carry, inputs):
        mean, cov = carry
        pose, z_t = inputs
        p = ekf.predict_measurements(pose, mean, cov, params)
        mean, cov = ekf.update_landmarks(mean, cov, p, z_t[None], params)
        det = cov[0, 0] * cov[0, 2] - cov[0, 1] ** 2
        health = jnp.minimum(jnp.minimum(cov[0, 0], cov[0, 2]), det)
        return (mean, cov), health

    run = jax.jit(lambda m, c, ps, zs: jax.lax.scan(body, (m, c), (ps, zs)))
    (mean, cov), health = run(mean0, cov0, jnp.asarray(poses, jnp.float32),
                              jnp.asarray(z, jnp.float32))
    health = np.asarray(health)
    assert np.all(np.isfinite(health)) and np.all(health > 0), health.min()
    np.testing.assert_allclose(np.asarray(mean[0]), landmark, atol=1e-3)

    info = np.linalg.inv(matrix(np.asarray(cov0[0], np.float64)))
    r_inv = np.linalg.inv(ref_noise(10.0))
    for pose in poses:
        dx, dy = landmark - pose[:2]
        jac = np.array([[dx / 10, dy / 10], [-dy / 100, dx / 100]])
        info += jac.T @ r_inv @ jac
    np.testing.assert_allclose(matrix(np.asarray(cov[0], np.float64)), np.linalg.inv(info),
                               rtol=0.05, atol=0.05 * np.abs(np.linalg.inv(info)).max())


# ---------------------------------------------------------------------------------------------
# Edges


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
@pytest.mark.parametrize("distance", [0.0, 1e-6])
def test_landmark_at_zero_distance_stays_finite(dtype, distance):
    params = default_params(dtype=dtype)
    pose = jnp.asarray([1.0, 2.0, 0.3], dtype)
    mean = jnp.asarray([[1.0 + distance, 2.0]], dtype)
    cov = jnp.asarray([[0.04, 0.0, 0.04]], dtype)
    p = jax.jit(ekf.predict_measurements)(pose, mean, cov, params)
    assert all(bool(jnp.all(jnp.isfinite(leaf))) for leaf in p), p
    z = jnp.asarray([[0.0, 0.0]], dtype)
    d2 = ekf.mahalanobis_sq(z, p)
    new_mean, new_cov = ekf.update_landmarks(mean, cov, p, z, params)
    born_mean, born_cov = ekf.initialize_landmarks(pose, z, params)
    for arr in (d2, new_mean, new_cov, born_mean, born_cov,
                ekf.gaussian_log_likelihood(d2, p.log_det[None, :])):
        assert bool(jnp.all(jnp.isfinite(arr))), arr
    # The born covariance at zero range is the floor's range variance along the beam.
    assert float(born_cov[0, 0] + born_cov[0, 2]) > 0


# ---------------------------------------------------------------------------------------------
# Pose uncertainty in the matching covariance (FastSLAM 2.0)


def ref_pose_jacobian(pose, mean):
    """dh/dpose (2, 3) by central differences of h in float64 (independent of the algebra)."""
    def h(p):
        dx, dy = mean[0] - p[0], mean[1] - p[1]
        return np.array([np.hypot(dx, dy), np.arctan2(dy, dx) - p[2]])

    step = 1e-6
    cols = [(h(pose + step * e) - h(pose - step * e)) / (2 * step) for e in np.eye(3)]
    return np.stack(cols, 1)


def random_pose_cov(seed):
    a = np.random.default_rng(seed).normal(size=(3, 3)) * np.array([0.3, 0.3, 0.05])[:, None]
    return a @ a.T + 1e-6 * np.eye(3)


@pytest.mark.parametrize("use_jit", [False, True])
def test_add_pose_uncertainty_vs_reference(params64, use_jit):
    case = random_case(7)
    pose, mean, cov, _ = case
    pose_cov = random_pose_cov(7)
    fn = jax.jit(ekf.add_pose_uncertainty) if use_jit else ekf.add_pose_uncertainty
    p = fn(predict64(case, params64), jnp.asarray(pose_cov))
    for m in range(mean.shape[0]):
        _, _, s = ref_predict(pose, mean[m], matrix(cov[m]))
        hx = ref_pose_jacobian(pose, mean[m])
        z_cov = s + hx @ pose_cov @ hx.T
        # Central differences with step 1e-6 are accurate to ~1e-9 relative here.
        np.testing.assert_allclose([p.s_rr[m], p.s_rb[m], p.s_bb[m]], components(z_cov),
                                   rtol=1e-7, atol=1e-12)
        np.testing.assert_allclose([p.i_rr[m], p.i_rb[m], p.i_bb[m]],
                                   components(np.linalg.inv(z_cov)), rtol=1e-6, atol=1e-9)
        np.testing.assert_allclose(float(p.log_det[m]), np.log(np.linalg.det(z_cov)),
                                   rtol=1e-7)


def test_add_pose_uncertainty_zero_cov_is_identity_and_vmaps(params64):
    cases = [random_case(seed) for seed in (8, 9)]
    predicted = [predict64(case, params64) for case in cases]
    same = ekf.add_pose_uncertainty(predicted[0], jnp.zeros((3, 3)))
    for name in ("s_rr", "s_rb", "s_bb", "i_rr", "i_rb", "i_bb", "log_det"):
        np.testing.assert_allclose(getattr(same, name), getattr(predicted[0], name), rtol=1e-12)
    pose_covs = jnp.stack([jnp.asarray(random_pose_cov(s)) for s in (8, 9)])
    stacked = jax.tree.map(lambda *leaves: jnp.stack(leaves), *predicted)
    batched = jax.vmap(ekf.add_pose_uncertainty)(stacked, pose_covs)
    for i in range(2):
        one = ekf.add_pose_uncertainty(predicted[i], pose_covs[i])
        np.testing.assert_allclose(batched.s_bb[i], one.s_bb, rtol=1e-12)
        np.testing.assert_allclose(batched.i_rb[i], one.i_rb, rtol=1e-12)


# ---------------------------------------------------------------------------------------------
# Trunk radius term


def ref_radius_distance_sq(obs_radius, landmark_radius, count, sigma):
    """Plain float64 loop: (r - r_bar)^2 / (sigma^2 (1 + 1/n)), 0 when a radius is unknown."""
    out = np.zeros((len(obs_radius), len(landmark_radius)))
    for k, r in enumerate(obs_radius):
        for m, (r_bar, n) in enumerate(zip(landmark_radius, count)):
            if sigma > 0 and r > 0 and r_bar > 0:
                out[k, m] = (r - r_bar) ** 2 / (sigma**2 * (1.0 + 1.0 / max(n, 1)))
    return out


@pytest.mark.parametrize("use_jit", [False, True])
def test_radius_distance_sq_vs_reference(use_jit):
    rng = np.random.default_rng(11)
    # Unknown radii (0, and a negative one) on both sides, and a never-updated count (0).
    obs_radius = np.r_[rng.uniform(0.05, 0.6, 5), 0.0, -0.1]
    landmark_radius = np.r_[rng.uniform(0.05, 0.6, 6), 0.0]
    count = np.r_[rng.integers(1, 40, 5), 0, 3]
    params = default_params(dtype=jnp.float64, radius_noise=0.05)
    fn = jax.jit(ekf.radius_distance_sq) if use_jit else ekf.radius_distance_sq
    got = np.asarray(fn(jnp.asarray(obs_radius)[:, None], jnp.asarray(landmark_radius)[None, :],
                        jnp.asarray(count)[None, :], params))
    assert got.shape == (7, 7) and got.dtype == np.float64
    np.testing.assert_allclose(got, ref_radius_distance_sq(obs_radius, landmark_radius, count,
                                                           0.05), rtol=RTOL, atol=0.0)
    assert np.all(got[5:] == 0.0) and np.all(got[:, 6] == 0.0)
    # Matched rows (K,) against (K,), and vmapped over particles, give the same numbers.
    rows = np.asarray(fn(jnp.asarray(obs_radius), jnp.asarray(landmark_radius),
                         jnp.asarray(count), params))
    np.testing.assert_allclose(rows, np.diag(got), rtol=RTOL)
    stacked = jnp.stack([jnp.asarray(landmark_radius), jnp.asarray(landmark_radius[::-1])])
    batched = np.asarray(jax.vmap(lambda lm: fn(jnp.asarray(obs_radius)[:, None], lm[None, :],
                                                jnp.asarray(count)[None, :], params))(stacked))
    np.testing.assert_allclose(batched[0], got, rtol=RTOL)
    np.testing.assert_allclose(batched[1], ref_radius_distance_sq(
        obs_radius, landmark_radius[::-1], count, 0.05), rtol=RTOL)


def test_radius_distance_sq_is_off_by_default():
    """default_params has radius_noise = 0: the radius changes nothing (finite zeros)."""
    params = default_params(dtype=jnp.float64)
    got = ekf.radius_distance_sq(jnp.asarray([0.1, 0.5])[:, None],
                                 jnp.asarray([0.3, 0.2])[None, :], jnp.asarray([1, 5])[None, :],
                                 params)
    np.testing.assert_array_equal(np.asarray(got), 0.0)


@pytest.mark.parametrize("use_jit", [False, True])
def test_sensor_std_and_floored_measurement_std_against_numpy(use_jit):
    """Table 2: sigma = c_dist d + c_const (the simulator's noise); the filter's std is that
    floored. Float64 NumPy reference; exact up to float64 rounding (rtol 1e-12). The floors
    bind at short range with these coefficients (d = 0: 0.002 < floor 0.01), not at 30 m."""
    params = default_params(dtype=jnp.float64, range_noise=(0.01, 0.002),
                            bearing_noise=(0.0002, 0.0005), range_std_floor=0.01,
                            bearing_std_floor=0.001)
    distance = np.array([0.0, 0.5, 5.0, 30.0])
    want_range = 0.01 * distance + 0.002
    want_bearing = 0.0002 * distance + 0.0005
    sensor = jax.jit(ekf.sensor_std) if use_jit else ekf.sensor_std
    floored = jax.jit(ekf.measurement_std) if use_jit else ekf.measurement_std
    got = sensor(jnp.asarray(distance), params)
    np.testing.assert_allclose(got[0], want_range, rtol=1e-12)
    np.testing.assert_allclose(got[1], want_bearing, rtol=1e-12)
    got = floored(jnp.asarray(distance), params)
    np.testing.assert_allclose(got[0], np.maximum(want_range, 0.01), rtol=1e-12)
    np.testing.assert_allclose(got[1], np.maximum(want_bearing, 0.001), rtol=1e-12)
    assert float(got[0][0]) == 0.01 and float(got[0][-1]) > 0.01  # the floor binds, then not
    batched = jax.vmap(ekf.sensor_std, in_axes=(0, None))(jnp.asarray(distance), params)
    np.testing.assert_allclose(batched[0], want_range, rtol=1e-12)
