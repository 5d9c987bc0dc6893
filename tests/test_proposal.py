"""Observation and mixture proposals (issue 5): importance sampling on a linear-Gaussian case
whose posterior is known (weighted mean and variance within Monte Carlo error for phi in
{0, 0.3, 1}), finite weights for every phi, the proposal against a NumPy reference, the
correction term, and the adaptive ratio (bounds, and a rise on an injected odometry fault)."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.stats import multivariate_normal

from jaxslam import ekf, motion, proposal
from jaxslam.filter import make_filter, run_filter
from jaxslam.types import FilterConfig, Observations, default_params

from test_filter import SENSOR_RANGE, simulate_circle  # noqa: E402  (tests/ is on sys.path)

# A linear-Gaussian-like case: constant noise stds (no distance or motion dependence), small
# enough that the linearisations are exact to ~1e-4 m.
SIGMA_MOVE = np.array([0.01, 0.05, 0.01])      # rot1 [rad], trans [m], rot2 [rad]
SIGMA_OBS = np.array([0.03, 0.003])            # range [m], bearing [rad]
PREV = np.array([1.0, 2.0, 0.3])
CONTROL = np.array([0.1, 1.0, -0.05])
LANDMARKS = np.array([[6.0, 4.0], [3.0, 8.0], [7.5, -1.0]])
TRUE_OFFSET = np.array([0.02, -0.01, 0.004])   # true pose - motion prediction
LANDMARK_COV = 1e-12                           # landmarks known exactly


def ref_wrap(angle):
    return (np.asarray(angle, np.float64) + np.pi) % (2 * np.pi) - np.pi


def ref_h(pose, point):
    d = point - pose[:2]
    return np.array([np.hypot(*d), ref_wrap(np.arctan2(d[1], d[0]) - pose[2])])


def ref_h_pose_jacobian(pose, point):
    dx, dy = point - pose[:2]
    r2 = dx * dx + dy * dy
    r = np.sqrt(r2)
    return np.array([[-dx / r, -dy / r, 0.0], [dy / r2, -dx / r2, -1.0]])


def ref_prediction():
    heading = PREV[2] + CONTROL[0]
    x_hat = np.array([PREV[0] + CONTROL[1] * np.cos(heading),
                      PREV[1] + CONTROL[1] * np.sin(heading), heading + CONTROL[2]])
    jac = np.array([[-CONTROL[1] * np.sin(heading), np.cos(heading), 0.0],
                    [CONTROL[1] * np.cos(heading), np.sin(heading), 0.0], [1.0, 0.0, 1.0]])
    return x_hat, jac @ np.diag(SIGMA_MOVE**2) @ jac.T


def ref_posterior(z, iterations=6):
    """Gaussian posterior of the pose: prior N(x_hat, Sigma_u) times prod_k N(z_k; h(x, m_k), R),
    h linearised at the current mean (iterated: Gauss-Newton to the mode). Returns mean, cov."""
    x_hat, prior_cov = ref_prediction()
    r_inv = np.diag(1.0 / SIGMA_OBS**2)
    mean = x_hat.copy()
    for _ in range(iterations):
        info = np.linalg.inv(prior_cov)
        vec = np.zeros(3)
        for m, z_k in zip(LANDMARKS, z):
            jac = ref_h_pose_jacobian(mean, m)
            nu = z_k - ref_h(mean, m)
            nu[1] = ref_wrap(nu[1])
            info += jac.T @ r_inv @ jac
            vec += jac.T @ r_inv @ (nu + jac @ (mean - x_hat))
        cov = np.linalg.inv(info)
        mean = x_hat + cov @ vec
    return mean, cov


def observations(offset=TRUE_OFFSET):
    x_hat, _ = ref_prediction()
    true_pose = x_hat + offset
    return np.stack([ref_h(true_pose, m) for m in LANDMARKS])


@pytest.fixture(scope="module")
def params():
    # One Gaussian motion prior (no bursts): the proposal under test is its FastSLAM 2.0 Gaussian.
    return default_params(dtype=jnp.float64, motion_outlier_probability=0.0,
                          rot1_noise=(0.0, 0.0, SIGMA_MOVE[0]),
                          trans_noise=(0.0, 0.0, SIGMA_MOVE[1]),
                          rot2_noise=(0.0, 0.0, SIGMA_MOVE[2]),
                          range_noise=(0.0, SIGMA_OBS[0]), bearing_noise=(0.0, SIGMA_OBS[1]),
                          range_std_floor=1e-6, bearing_std_floor=1e-6)


def log_likelihood(pose, z):
    """log prod_k N(z_k; h(pose, m_k), R) written in JAX (independent of ekf.py)."""
    d = jnp.asarray(LANDMARKS) - pose[None, :2]
    pred_range = jnp.hypot(d[:, 0], d[:, 1])
    pred_bearing = jnp.arctan2(d[:, 1], d[:, 0]) - pose[2]
    nu_b = pred_bearing - z[:, 1]
    nu_b = nu_b - 2 * jnp.pi * jnp.round(nu_b / (2 * jnp.pi))
    white = ((z[:, 0] - pred_range) / SIGMA_OBS[0]) ** 2 + (nu_b / SIGMA_OBS[1]) ** 2
    return jnp.sum(-0.5 * white - np.log(SIGMA_OBS).sum() - np.log(2 * np.pi))


def make_sampler(params):
    """jit(n keys, z, phi) -> (poses (n, 3), log-weights (n,), used_obs (n,)), compiled once."""
    prev, control = jnp.asarray(PREV), jnp.asarray(CONTROL)
    landmark_mean = jnp.asarray(LANDMARKS)
    landmark_cov = jnp.tile(jnp.asarray([LANDMARK_COV, 0.0, LANDMARK_COV]), (3, 1))

    def one(key, z, phi):
        key_motion, key_mixture = jax.random.split(key)
        motion_sample = motion.sample_motion(key_motion, prev, control, params)
        x_hat = motion.predict_pose(prev, control, params)
        pose_cov = proposal.motion_pose_covariance(prev, control, params, "odometry")
        predicted = ekf.predict_measurements(x_hat, landmark_mean, landmark_cov, params)
        gaussian = proposal.observation_proposal(x_hat, pose_cov, z, jnp.arange(3), predicted)
        pose, used, _ = proposal.mixture_sample(key_mixture, motion_sample, gaussian, phi)
        correction = proposal.mixture_log_correction(prev, pose, control, params, "odometry",
                                                     gaussian, phi)
        return pose, correction + log_likelihood(pose, z), used

    return jax.jit(jax.vmap(one, in_axes=(0, None, None)))


@pytest.fixture(scope="module")
def sampler(params):
    return make_sampler(params)


def weighted_moments(poses, log_weight):
    """Self-normalised IS mean and variance per axis and their delta-method standard errors."""
    w = np.exp(log_weight - log_weight.max())
    w /= w.sum()
    mean = w @ poses
    centred = poses - mean
    var = w @ centred**2
    mean_se = np.sqrt(w**2 @ centred**2)
    var_se = np.sqrt(w**2 @ (centred**2 - var) ** 2)
    return mean, var, mean_se, var_se, 1.0 / np.sum(w**2)


# ---------------------------------------------------------------------------------------------
# Linear-Gaussian posterior by importance sampling


@pytest.mark.parametrize("phi", [0.0, 0.3, 1.0])
def test_mixture_recovers_known_posterior(sampler, phi):
    """Tolerance per axis: 4 Monte Carlo standard errors plus 1e-4 (mean) / 3% (variance) for
    the linearisations (motion prior Gaussian in pose space, h linearised at the mode)."""
    n = 20_000
    z = observations()
    poses, log_weight, used = sampler(jax.random.split(jax.random.key(10), n), jnp.asarray(z),
                                      jnp.asarray(phi))
    poses, log_weight, used = np.asarray(poses), np.asarray(log_weight), np.asarray(used)
    assert np.all(np.isfinite(log_weight))
    # The observation proposal is chosen with probability phi (binomial, 4 SE).
    assert abs(used.mean() - phi) <= 4 * np.sqrt(phi * (1 - phi) / n) + 1e-12
    ref_mean, ref_cov = ref_posterior(z)
    mean, var, mean_se, var_se, ess = weighted_moments(poses, log_weight)
    assert ess > 200, ess
    mean_error = np.abs(mean - ref_mean)
    assert np.all(mean_error < 4 * mean_se + 1e-4), (phi, mean_error, mean_se)
    var_error = np.abs(var - np.diag(ref_cov))
    assert np.all(var_error < 4 * var_se + 0.03 * np.diag(ref_cov)), (phi, var, np.diag(ref_cov))
    # Sanity of the case: the posterior is much tighter than the motion prior.
    assert np.all(np.diag(ref_cov) < np.diag(ref_prediction()[1]))


def test_observation_proposal_is_efficient(sampler):
    """phi = 1 samples from (almost) the posterior itself: ESS close to n; phi = 0 is poor."""
    n = 4000
    z = jnp.asarray(observations())
    keys = jax.random.split(jax.random.key(11), n)
    ess = {phi: weighted_moments(*map(np.asarray, sampler(keys, z, jnp.asarray(phi))[:2]))[4]
           for phi in (0.0, 1.0)}
    assert ess[1.0] > 0.9 * n and ess[0.0] < 0.5 * ess[1.0], ess


@pytest.mark.parametrize("phi", [0.0, 0.3, 1.0])
def test_weights_finite_when_observations_disagree(sampler, phi):
    """Observations from a pose 20 motion sigmas away (an odometry fault): still finite."""
    z = observations(offset=np.array([1.0, -0.5, 0.2]))
    _, log_weight, _ = sampler(jax.random.split(jax.random.key(12), 2000), jnp.asarray(z),
                               jnp.asarray(phi))
    assert np.all(np.isfinite(np.asarray(log_weight))), phi


# ---------------------------------------------------------------------------------------------
# Kernels against NumPy


def test_observation_proposal_vs_reference(params):
    z = observations()
    x_hat, prior_cov = ref_prediction()
    pose_cov = proposal.motion_pose_covariance(jnp.asarray(PREV), jnp.asarray(CONTROL), params,
                                               "odometry")
    jitter = (100 * np.finfo(np.float64).eps * max(prior_cov[0, 0], prior_cov[1, 1])
              + 1e-14)  # proposal.pose_jitter's rule (float64)
    np.testing.assert_allclose(np.asarray(pose_cov), prior_cov + jitter * np.eye(3), rtol=1e-9,
                               atol=1e-15)
    landmark_cov = jnp.tile(jnp.asarray([LANDMARK_COV, 0.0, LANDMARK_COV]), (3, 1))
    predicted = ekf.predict_measurements(jnp.asarray(x_hat), jnp.asarray(LANDMARKS),
                                         landmark_cov, params)
    # Observation 1 unmatched: it must not contribute.
    match = jnp.asarray([0, -1, 2])
    gaussian = proposal.observation_proposal(jnp.asarray(x_hat), pose_cov, jnp.asarray(z),
                                             match, predicted)
    info = np.linalg.inv(prior_cov + jitter * np.eye(3))
    vec = np.zeros(3)
    for k in (0, 2):
        jac = ref_h_pose_jacobian(x_hat, LANDMARKS[k])
        s = np.diag(SIGMA_OBS**2) + LANDMARK_COV * np.eye(2) * 0  # landmark term ~1e-12
        nu = z[k] - ref_h(x_hat, LANDMARKS[k])
        nu[1] = ref_wrap(nu[1])
        info += jac.T @ np.linalg.inv(s) @ jac
        vec += jac.T @ np.linalg.inv(s) @ nu
    cov = np.linalg.inv(info)
    chol = np.asarray(gaussian.chol)
    np.testing.assert_allclose(chol @ chol.T, cov, rtol=1e-6, atol=1e-12)
    np.testing.assert_allclose(np.asarray(gaussian.mean), x_hat + cov @ vec, rtol=1e-6,
                               atol=1e-9)
    assert bool(gaussian.has_match)
    none = proposal.observation_proposal(jnp.asarray(x_hat), pose_cov, jnp.asarray(z),
                                         jnp.full(3, -1), predicted)
    assert not bool(none.has_match)
    np.testing.assert_allclose(np.asarray(none.mean), x_hat, atol=1e-12)


def _np_pose_jitter(cov, dtype):
    """proposal.pose_jitter's rule in plain NumPy: 100 eps of R's position block + 1e-14."""
    return 100.0 * float(np.finfo(dtype).eps) * max(cov[0, 0], cov[1, 1]) + 1e-14


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_pose_jitter_rule_eager_jit_vmap(dtype):
    """The jitter is 100 float epsilons of R's position block (plus 1e-14) in R's own dtype,
    eagerly, under jit and under vmap, and R's heading variance does not enter it (the old
    rule, 1e-5 of R's largest variance, was set by the heading for a creep). Tolerance: rtol
    1e-6, float32 rounding of a product of three numbers (the rules differ by >= 10x)."""
    rng = np.random.default_rng(5)
    covs = []
    for position, heading in ((1e-6, 0.04), (2.0, 1e-8), (1e-11, 3.4e-4), (0.0, 0.04)):
        a = rng.normal(size=(3, 3))
        cov = a @ a.T * 1e-3
        cov[0, 0], cov[1, 1], cov[2, 2] = position, 0.5 * position, heading
        covs.append(cov)
    covs = np.asarray(covs, dtype)
    want = np.array([_np_pose_jitter(c.astype(np.float64), dtype) for c in covs])
    eager = np.array([float(proposal.pose_jitter(jnp.asarray(c))) for c in covs])
    jitted = np.array([float(jax.jit(proposal.pose_jitter)(jnp.asarray(c))) for c in covs])
    mapped = np.asarray(jax.vmap(proposal.pose_jitter)(jnp.asarray(covs)))
    assert mapped.dtype == dtype
    for got in (eager, jitted, mapped):
        np.testing.assert_allclose(got, want, rtol=1e-6, atol=0)
    # The heading variance alone changes nothing; the position block does.
    moved = covs.copy()
    moved[:, 2, 2] *= 1e4
    np.testing.assert_array_equal(
        np.asarray(jax.vmap(proposal.pose_jitter)(jnp.asarray(moved))), mapped)
    # Above the 1e-14 floor, it scales with the position block (covs[1]: 2 m^2).
    excess = float(proposal.pose_jitter(jnp.asarray(covs[1] * 4))) - 1e-14
    np.testing.assert_allclose(excess, 4 * (float(mapped[1]) - 1e-14), rtol=1e-5)


def test_mixture_log_correction_vs_reference(params):
    x_hat, prior_cov = ref_prediction()
    mean = x_hat + np.array([0.01, 0.0, 0.002])
    cov = 0.3 * prior_cov
    gaussian = proposal.ObservationProposal(jnp.asarray(mean),
                                            jnp.asarray(np.linalg.cholesky(cov)),
                                            jnp.asarray(True))
    rng = np.random.default_rng(0)
    for phi in (0.0, 0.3, 1.0):
        for pose in x_hat + rng.normal(size=(5, 3)) * 0.02:
            got = float(proposal.mixture_log_correction(
                jnp.asarray(PREV), jnp.asarray(pose), jnp.asarray(CONTROL), params,
                "odometry", gaussian, jnp.asarray(phi)))
            log_motion = float(motion.motion_log_density(jnp.asarray(PREV), jnp.asarray(pose),
                                                         jnp.asarray(CONTROL), params))
            log_obs = multivariate_normal(mean, cov).logpdf(pose)
            want = log_motion - np.log((1 - phi) * np.exp(log_motion) + phi * np.exp(log_obs))
            np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-9)
    no_match = gaussian._replace(has_match=jnp.asarray(False))
    assert float(proposal.mixture_log_correction(jnp.asarray(PREV), jnp.asarray(x_hat),
                                                 jnp.asarray(CONTROL), params, "odometry",
                                                 no_match, jnp.asarray(0.5))) == 0.0


def test_mixture_sample_falls_back_without_match():
    gaussian = proposal.ObservationProposal(jnp.ones(3), jnp.eye(3), jnp.asarray(False))
    motion_sample = jnp.asarray([5.0, 6.0, 0.1])
    for seed in range(5):
        pose, used, _ = proposal.mixture_sample(jax.random.key(seed), motion_sample, gaussian,
                                             jnp.asarray(1.0))
        np.testing.assert_array_equal(np.asarray(pose), np.asarray(motion_sample))
        assert not bool(used)


# ---------------------------------------------------------------------------------------------
# Adaptive ratio


def ref_adaptive(fast, slow, lo, hi):
    drop = np.maximum(0.0, 1.0 - np.exp(fast - slow))
    return np.clip(lo + (hi - lo) * drop, lo, hi)


def test_adaptive_ratio_bounds_and_reference(params):
    values = np.array([-1e6, -50.0, -3.0, -1.0, 0.0, 0.5, 2.0, 40.0, 1e6])
    fast, slow = np.meshgrid(values, values)
    out = np.asarray(jax.jit(jax.vmap(proposal.adaptive_ratio, in_axes=(0, 0, None)))(
        jnp.asarray(fast.ravel()), jnp.asarray(slow.ravel()), params))
    assert np.all(np.isfinite(out))
    lo, hi = float(params.mixture_min), float(params.mixture_max)
    assert np.all(out >= lo) and np.all(out <= hi)
    with np.errstate(over="ignore"):
        np.testing.assert_allclose(out, ref_adaptive(fast.ravel(), slow.ravel(), lo, hi),
                                   rtol=1e-12)
    # At rest (fast >= slow) the ratio is the minimum; it rises as fast drops below slow.
    assert float(proposal.adaptive_ratio(jnp.asarray(1.0), jnp.asarray(0.0), params)) == 0.05
    ratios = [float(proposal.adaptive_ratio(jnp.asarray(-d), jnp.asarray(0.0), params))
              for d in (0.0, 0.1, 0.5, 1.0, 3.0)]
    assert np.all(np.diff(ratios) > 0), ratios


def test_update_likelihood_averages_vs_reference(params):
    fast, slow = jnp.asarray(-2.0), jnp.asarray(-1.0)
    new_fast, new_slow = proposal.update_likelihood_averages(
        fast, slow, jnp.asarray(-5.0), jnp.asarray(True), jnp.asarray(False), params)
    np.testing.assert_allclose([float(new_fast), float(new_slow)],
                               [-2.0 + 0.5 * (-3.0), -1.0 + 0.05 * (-4.0)], rtol=1e-12)
    same = proposal.update_likelihood_averages(fast, slow, jnp.asarray(-5.0),
                                               jnp.asarray(False), jnp.asarray(False), params)
    assert float(same[0]) == -2.0 and float(same[1]) == -1.0
    first = proposal.update_likelihood_averages(fast, slow, jnp.asarray(-5.0), jnp.asarray(True),
                                                jnp.asarray(True), params)
    assert float(first[0]) == -5.0 and float(first[1]) == -5.0


def _augmented_ratios(trace, obs, params):
    """(T,) the augmented-MCL phi each step started from: ``adaptive_ratio`` of the likelihood
    averages before the step, rebuilt on the host from ``trace.mean_log_likelihood`` with the
    library's own recursion (``update_likelihood_averages``)."""
    has_data = np.asarray(obs.valid).any(axis=1)
    fast = slow = jnp.asarray(0.0)
    ratios = []
    for t, mean_ll in enumerate(np.asarray(trace.mean_log_likelihood)):
        ratios.append(float(proposal.adaptive_ratio(fast, slow, params)))
        fast, slow = proposal.update_likelihood_averages(
            fast, slow, jnp.asarray(mean_ll), jnp.asarray(has_data[t]), jnp.asarray(t == 0),
            params)
    return np.asarray(ratios)


def test_adaptive_ratio_rises_on_odometry_fault():
    """Circle sim; the odometry of steps 30-32 over-reports the translation by 0.5 m (wheel
    slip, 23 motion sigmas, about 3 burst sigmas). A slip of 0.15 m (7 sigmas), the case until
    the loose boundary stopped using the matching pose covariance
    (``tests/test_matching_airlock.py``), is now matched by the burst piece of the default
    proposal (kappa 8: 0.17 m std), so the likelihood hardly drops and the augmented term
    rises by 0.05 only: explaining such slips is the bursts' job. Paired with the fault-free
    run under the same key (identical up to step 29; from step 30 the fault's own control
    enters phi through the motion draws' efficiency), the augmented-MCL phi at steps 31-33
    (from the likelihood averages before each step) is higher by at least 0.1 on average.
    The phi the particles used (their mean, ``trace.mixture_ratio``) never falls below that
    floor and stays in [mixture_min, mixture_max]; with this accurate lidar it sits near
    phi_max already without the fault (the efficiency term), and the fault takes it to
    within 1e-3 of phi_max.

    The single-run signal is weak: fault-free spikes reach 0.5-0.7 (likelihood_rate_fast=0.5),
    so the comparison is paired rather than against a threshold (see the report)."""
    controls, obs, truth, table = simulate_circle(seed=1)
    faulty = np.asarray(controls).copy()
    faulty[30:33, 1] += 0.5  # the augmented term rose by 0.19 when this was written
    config = FilterConfig(num_particles=32, max_landmarks=32, max_obs=8, proposal="mixture",
                          mixture_mode="adaptive")
    params = default_params(rot1_noise=tuple(table[0]), trans_noise=tuple(table[1]),
                            rot2_noise=tuple(table[2]), max_range=SENSOR_RANGE)
    ratios, floors = [], []
    for control_sequence in (controls, faulty):
        _, trace = run_filter(config, jax.random.key(0), params,
                              jnp.asarray(control_sequence, jnp.float32), obs,
                              initial_pose=jnp.asarray(truth[0], jnp.float32))
        ratio = np.asarray(trace.mixture_ratio)
        floor = _augmented_ratios(trace, obs, params)
        assert np.all(np.isfinite(ratio))
        assert np.all(ratio >= params.mixture_min - 1e-7)
        assert np.all(ratio <= params.mixture_max + 1e-7)
        assert np.all(ratio >= floor - 1e-6)
        assert np.all(np.isfinite(np.asarray(trace.mean_pose)))
        assert int(np.asarray(trace.weights_reset).sum()) == 0
        ratios.append(ratio)
        floors.append(floor)
    clean, fault = ratios
    np.testing.assert_array_equal(clean[:30], fault[:30])
    rise = floors[1][31:34].mean() - floors[0][31:34].mean()
    assert rise > 0.1, (rise, np.round(floors[0][28:36], 2), np.round(floors[1][28:36], 2))
    np.testing.assert_allclose(fault[30:33], float(params.mixture_max), atol=1e-3)


# ---------------------------------------------------------------------------------------------
# Matching at x_hat with the pose uncertainty (FastSLAM 2.0)


def _mapped_state(config, params):
    """One step's state: every particle at PREV with the three LANDMARKS mapped exactly."""
    state = make_filter(config).init(jnp.asarray(PREV), dtype=jnp.float64)
    slots = config.max_landmarks
    mean = np.zeros((config.num_particles, slots, 2))
    mean[:, :3] = LANDMARKS
    cov = np.tile([1.0, 0.0, 1.0], (config.num_particles, slots, 1))
    cov[:, :3] = [LANDMARK_COV, 0.0, LANDMARK_COV]
    active = np.zeros((config.num_particles, slots), bool)
    active[:, :3] = True
    particles = state.particles._replace(
        landmark_mean=jnp.asarray(mean), landmark_cov=jnp.asarray(cov),
        active=jnp.asarray(active), existence=jnp.where(jnp.asarray(active), 3.0, 0.0),
        observation_count=jnp.asarray(active, jnp.int32))
    return state._replace(particles=particles)


@pytest.mark.parametrize("with_pose_uncertainty", [False, True])
def test_matching_at_x_hat_uses_pose_uncertainty(params, with_pose_uncertainty):
    """x_hat 0.03 rad off in heading: 10 bearing sigmas (d2 ~ 100 > gate 25) but ~2 pose
    sigmas (Sigma_u heading std 0.014 rad, d2 ~ 5). With Z = Hx Sigma_u Hx^T + S every
    observation matches its landmark and the sampled poses move to the true heading; with S
    alone none matches at x_hat and every particle falls back to the motion model."""
    config = FilterConfig(num_particles=16, max_landmarks=8, max_obs=3,
                          proposal="observation", match_pose_uncertainty=with_pose_uncertainty)
    offset = np.array([0.0, 0.0, 0.03])
    z = observations(offset=offset)
    obs = Observations(z=jnp.asarray(z), valid=jnp.ones(3, bool), radius=jnp.zeros(3),
                       landmark_id=jnp.full(3, -1, jnp.int32))
    state, info = jax.jit(make_filter(config).step)(
        jax.random.key(3), _mapped_state(config, params), params, jnp.asarray(CONTROL), obs)
    match = np.asarray(info.match)
    heading = np.asarray(state.particles.pose[:, 2])
    x_hat, _ = ref_prediction()
    if with_pose_uncertainty:
        np.testing.assert_array_equal(match, np.tile(np.arange(3), (16, 1)))
        # Posterior heading within 4 posterior sigmas of the truth (sigma ~ 1e-3 rad here).
        ref_mean, ref_cov = ref_posterior(z)
        assert abs(ref_mean[2] - (x_hat[2] + offset[2])) < 0.005
        assert np.all(np.abs(heading - ref_mean[2]) < 4 * np.sqrt(ref_cov[2, 2]) + 1e-4)
        assert np.all(np.asarray(info.num_landmarks) == 3)
    else:
        # Nothing matches at x_hat with S alone, so no particle is drawn from the observation
        # proposal; each falls back to its motion draw and is matched at that pose, as the
        # motion proposal does: the few drawn near the true heading match their landmarks,
        # never a wrong one.
        assert int(info.num_observation_draws) == 0
        assert np.all((match == -1) | (match == np.arange(3)[None, :]))
        assert np.any(match == -1)


def test_match_pose_uncertainty_must_be_bool():
    with pytest.raises(ValueError, match="match_pose_uncertainty"):
        FilterConfig(match_pose_uncertainty="yes")
