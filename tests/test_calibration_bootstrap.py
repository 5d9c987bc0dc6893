"""Parametric bootstrap intervals of the calibrated noise (``jaxslam.calibration_bootstrap``).

``intervals`` is NumPy float64 on the host and is checked against the formula written out
here; ``replicate_log`` is host code around three JAX kernels that have their own jit / vmap
tests (``motion.sample_odometry`` in test_motion.py, ``geometry.range_bearing`` in
test_geometry.py, ``ekf.measurement_std`` in test_ekf.py): here its rows are checked against
a NumPy float64 reference at zero noise and statistically with fixed keys.
"""
from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.stats

from jaxslam import calibration_bootstrap as cb
from jaxslam import self_calibration as sc
from jaxslam.motion import odometry_from_poses, odometry_std
from jaxslam.types import FilterConfig, default_params, make_observations


# ------------------------------------------------------------------------------------------
# intervals


def _reference_interval(estimate, replicates, truth, level):
    """exp(log theta_hat - bias +- t_{B-1} s sqrt(1 + 1/B)), r_b = log(theta*_b / tau_b),
    written out per group in float64."""
    count = len(replicates)
    t = scipy.stats.t.ppf(0.5 + level / 2.0, count - 1)
    lower, upper = [], []
    for g in range(len(estimate)):
        logs = [math.log(replicates[b, g] / truth[b, g]) for b in range(count)]
        mean = sum(logs) / count
        sd = math.sqrt(sum((v - mean) ** 2 for v in logs) / (count - 1))
        centre = math.log(estimate[g]) - mean
        half = t * sd * math.sqrt(1.0 + 1.0 / count)
        lower.append(math.exp(centre - half))
        upper.append(math.exp(centre + half))
    return np.array(lower), np.array(upper)


def test_intervals_against_the_formula():
    rng = np.random.default_rng(3)
    estimate = np.array([0.02, 0.05, 0.1, 0.003])
    truth = estimate * rng.uniform(0.9, 1.1, (12, 4))  # each replicate's own design
    replicates = truth * np.exp(rng.normal(0.2, 0.1, (12, 4)))
    for level in (0.95, 0.5):
        found = cb.intervals(estimate, replicates, truth, level)
        lower, upper = _reference_interval(estimate, replicates, truth, level)
        np.testing.assert_allclose(found.lower, lower, rtol=1e-12)
        np.testing.assert_allclose(found.upper, upper, rtol=1e-12)
        np.testing.assert_allclose(found.bias, np.mean(np.log(replicates / truth), 0),
                                   rtol=1e-12)
        assert found.level == level and np.all(found.failed == 0)
    # The replicates came out about 22 % above their truth, so the interval's centre (its
    # geometric mean) sits about 18 % below the estimate.
    found = cb.intervals(estimate, replicates, truth)
    assert np.all(np.sqrt(found.lower * found.upper) < 0.87 * estimate)


def test_intervals_edges():
    estimate = np.array([1.0, 2.0, 3.0, 4.0])
    same = np.tile(estimate, (3, 1))
    found = cb.intervals(estimate, same, same)
    np.testing.assert_allclose(found.lower, estimate, rtol=1e-12)  # no bias, no spread
    np.testing.assert_allclose(found.upper, estimate, rtol=1e-12)
    replicates = np.tile(estimate, (4, 1)) * np.array([[1.1], [0.9], [1.0], [1.2]])
    replicates[2, 1] = np.nan  # a replicate whose calibration fitted nothing
    replicates[0, 3] = 0.0
    found = cb.intervals(estimate, replicates, np.tile(estimate, (4, 1)))
    assert found.lower[1] == 0.0 and found.upper[1] == np.inf and np.isnan(found.bias[1])
    assert found.lower[3] == 0.0 and found.upper[3] == np.inf
    np.testing.assert_array_equal(found.failed, [0, 1, 0, 1])
    assert np.all(np.isfinite(found.upper[[0, 2]]))
    with pytest.raises(ValueError, match="at least 2 replicates"):
        cb.intervals(estimate, estimate[None], estimate[None])
    with pytest.raises(ValueError, match="level"):
        cb.intervals(estimate, same, same, level=1.0)
    with pytest.raises(ValueError, match=r"replicates and truth \(B, G\)"):
        cb.intervals(estimate, same, same[:, :3])
    with pytest.raises(ValueError, match=r"replicates and truth \(B, G\)"):
        cb.intervals(estimate, estimate, estimate)


def test_intervals_cover_a_biased_estimator_at_their_level():
    """An estimator log theta_hat = log theta + beta + sigma e whose bootstrap world repeats
    the bias and spread (log(theta*_b / tau_b) = beta + sigma e_b): the case the interval is
    exact for, so it covers 95 %. 4000 trials of 4 independent groups: 16,000 draws,
    binomial sd 0.0017; the rate must lie within 4 sd, [0.943, 0.957]. The same width
    centred on theta_hat, without the bias correction, must cover far less (so the bias
    here matters): its error 0.2 - 0.1 e against a half-width near 2.09 x 0.1 x 1.02 = 0.215
    covers e in [-0.15, 4.15], about 56 %; bound 62 %."""
    rng = np.random.default_rng(11)
    trials, replicates, beta, sigma = 4000, 20, -0.2, 0.1
    truth = np.array([0.05, 0.1, 0.2, 0.01])
    hat = truth * np.exp(beta + sigma * rng.normal(size=(trials, 4)))
    covered, naive = 0, 0
    for t in range(trials):
        tau = truth * rng.uniform(0.8, 1.2, (replicates, 4))  # the replicates' own designs
        stars = tau * np.exp(beta + sigma * rng.normal(size=(replicates, 4)))
        found = cb.intervals(hat[t], stars, tau)
        covered += np.sum((found.lower <= truth) & (truth <= found.upper))
        half = np.log(found.upper / found.lower) / 2.0
        naive += np.sum(np.abs(np.log(truth / hat[t])) <= half)
    rate = covered / (4 * trials)
    assert 0.943 <= rate <= 0.957, rate
    assert naive / (4 * trials) < 0.62


# ------------------------------------------------------------------------------------------
# replicate_log


def _solution(num_steps=400, rng_seed=5):
    rng = np.random.default_rng(rng_seed)
    heading = np.cumsum(rng.uniform(-0.1, 0.1, num_steps))
    xy = np.cumsum(0.5 * np.stack([np.cos(heading), np.sin(heading)], 1), 0)
    path = np.column_stack([xy, heading])
    landmark = rng.uniform(-20.0, 20.0, (30, 2)) + xy.mean(0)
    ids = rng.integers(-1, 30, (num_steps, 6))
    poses = np.vstack([np.zeros(3), path])
    measured = np.asarray(odometry_from_poses(jnp.asarray(poses[:-1]), jnp.asarray(poses[1:]),
                                              0.01))
    return cb.Solution(path, np.zeros(3), landmark, ids, measured)


def _observations(solution, valid_share=0.9, seed=2):
    rng = np.random.default_rng(seed)
    shape = solution.landmark_of_obs.shape
    z = np.column_stack([rng.uniform(1, 10, shape).ravel(),
                         rng.uniform(-1, 1, shape).ravel()]).reshape(shape + (2,))
    return make_observations(jnp.asarray(z, jnp.float32),
                             valid=jnp.asarray(rng.uniform(size=shape) < valid_share))


def _range_bearing_reference(pose, point):
    dx, dy = point[0] - pose[0], point[1] - pose[1]
    bearing = math.atan2(dy, dx) - pose[2]
    return math.hypot(dx, dy), math.atan2(math.sin(bearing), math.cos(bearing))


def _quiet():
    """Every noise std zero (``default_params`` refuses a zero sensor std, which the filter
    could not use; a replicate draw can)."""
    zero = lambda n: jnp.zeros(n, jnp.float64)
    return default_params(dtype=jnp.float64)._replace(
        rot1_noise=zero(3), trans_noise=zero(3), rot2_noise=zero(3), range_noise=zero(2),
        bearing_noise=zero(2), range_std_floor=zero(()), bearing_std_floor=zero(()))


def test_replicate_log_without_noise_is_the_solution_itself():
    """Zero noise: the moves are those of the smoothed path (NumPy float64 reference, 1e-5
    absolute: float32 without x64) and each associated observation its predicted measurement
    (1e-4 absolute: float32 ranges up to about 50 m); other rows as logged, bit for bit."""
    solution = _solution(60)
    obs = _observations(solution)
    controls, replicate = cb.replicate_log(jax.random.PRNGKey(0), solution, _quiet(), obs,
                                           bursts=True)
    poses = np.vstack([solution.start, solution.path])
    for t in range(60):
        dx, dy = poses[t + 1, :2] - poses[t, :2]
        rot1 = math.atan2(dy, dx) - poses[t, 2]
        rot1 = math.atan2(math.sin(rot1), math.cos(rot1))
        rot2 = poses[t + 1, 2] - poses[t, 2] - rot1
        rot2 = math.atan2(math.sin(rot2), math.cos(rot2))
        np.testing.assert_allclose(controls[t], [rot1, math.hypot(dx, dy), rot2], atol=1e-5)
    valid = np.asarray(obs.valid)
    z, logged = np.asarray(replicate.z, np.float64), np.asarray(obs.z, np.float64)
    for t, k in zip(*np.nonzero(valid & (solution.landmark_of_obs >= 0))):
        expected = _range_bearing_reference(solution.path[t],
                                            solution.landmark[solution.landmark_of_obs[t, k]])
        np.testing.assert_allclose(z[t, k], expected, atol=1e-4)
    kept = ~(valid & (solution.landmark_of_obs >= 0))
    np.testing.assert_array_equal(z[kept], logged[kept])
    np.testing.assert_array_equal(np.asarray(replicate.valid), valid)
    assert replicate.z.dtype == obs.z.dtype


def test_replicate_log_noise_has_the_model_std():
    """Fixed keys, 12,000 move components and about 20,000 observations: the standardised
    move and observation errors have mean square 1 within 8 % (its relative sd sqrt(2 / n)
    is 1.3 % for the moves and 1 % for the observations: 6 sd or more); bursts only when
    asked for, then with the mixture's mean square 1 - eps + eps kappa^2 = 1.6 (eps 0.2,
    kappa 2) within 12 % (its heavier tail about doubles the sd). The mean range error is
    within 0.05 std (about 5 sd of a mean of 20,000)."""
    solution = _solution(4000, rng_seed=8)
    obs = _observations(solution, valid_share=1.0)
    params = default_params(dtype=jnp.float64, rot1_noise=(0.0, 0.05, 0.01),
                            trans_noise=(0.02, 0.0, 0.01), rot2_noise=(0.0, 0.05, 0.01),
                            range_noise=(0.01, 0.02), bearing_noise=(0.001, 0.003),
                            range_std_floor=0.0, bearing_std_floor=0.0,
                            motion_outlier_probability=0.2, motion_outlier_scale=2.0)
    poses = np.vstack([solution.start, solution.path])
    moves = np.asarray(odometry_from_poses(jnp.asarray(poses[:-1]), jnp.asarray(poses[1:]),
                                           params.min_translation))
    std = np.asarray(odometry_std(jnp.asarray(moves), params))
    for bursts, variance in ((False, 1.0), (True, 1.6)):
        controls, replicate = cb.replicate_log(jax.random.PRNGKey(4), solution, params, obs,
                                               bursts)
        error = np.asarray(controls) - moves
        error[:, [0, 2]] = np.arctan2(np.sin(error[:, [0, 2]]), np.cos(error[:, [0, 2]]))
        np.testing.assert_allclose(np.mean((error / std) ** 2), variance,
                                   rtol=0.08 if not bursts else 0.12)
    ids = solution.landmark_of_obs
    t, k = np.nonzero(ids >= 0)
    predicted = np.array([_range_bearing_reference(solution.path[a], solution.landmark[ids[a, b]])
                          for a, b in zip(t, k)])
    z = np.asarray(replicate.z, np.float64)[t, k]
    sigma_range = 0.01 * predicted[:, 0] + 0.02
    sigma_bearing = 0.001 * predicted[:, 0] + 0.003
    offset = z[:, 1] - predicted[:, 1]
    bearing_error = np.arctan2(np.sin(offset), np.cos(offset))
    np.testing.assert_allclose(np.mean(((z[:, 0] - predicted[:, 0]) / sigma_range) ** 2), 1.0,
                               rtol=0.08)
    np.testing.assert_allclose(np.mean((bearing_error / sigma_bearing) ** 2), 1.0, rtol=0.08)
    assert abs(np.mean((z[:, 0] - predicted[:, 0]) / sigma_range)) < 0.05


# ------------------------------------------------------------------------------------------
# bootstrap_intervals end to end

CONFIG = FilterConfig(num_particles=16, max_landmarks=64, max_obs=10, association="known")


@functools.lru_cache(maxsize=1)
def _calibrated_log():
    """A 120-step loop through 30 trees (the sims scenario), calibrated as a user would."""
    from loop_log import loop_log, loop_noise  # tests/ is on sys.path

    truth = loop_noise()
    controls, obs, poses = loop_log(21, 120, 30, 12.0, truth)
    start = poses[0]
    params, info = sc.calibrate_params(CONFIG, jax.random.PRNGKey(0), controls, obs, start,
                                       iterations=3, scale_search=False)
    return controls, obs, start, params, info


def test_bootstrap_intervals_end_to_end():
    """Three replicates of a known-association calibration. Each replicate's world has EM's
    own noise as its truth. The sensor groups (about 1,000 observations, 1 / sqrt(2 n)
    near 2 %) come back within 10 % of the estimate (0.96-1.05 when written). The motion
    groups rest on 120 moves and three EM iterations: their replicates spread far more
    (heading 0.55-0.95 of the estimate when written, the spread the bootstrap exists to
    measure), so they are only held within a factor 2. The interval is finite, ordered and
    brackets the bias-corrected centre."""
    controls, obs, start, params, info = _calibrated_log()
    found = cb.bootstrap_intervals(CONFIG, jax.random.PRNGKey(0), controls, obs, start,
                                   sc.starting_params(CONFIG), params, info, replicates=3,
                                   iterations=3)
    assert found.replicates.shape == (3, 4)
    np.testing.assert_allclose(found.estimate, cb.total_typical_std(info), rtol=1e-12)
    assert found.replicate_truth.shape == (3, 4) and np.all(found.failed == 0)
    # tau_b is EM's noise over replicate b's own design: near the estimate itself.
    np.testing.assert_allclose(found.replicate_truth / found.estimate, 1.0, rtol=0.1)
    ratio = found.replicates / found.replicate_truth
    assert np.all(np.abs(np.log(ratio[:, 2:])) < np.log(1.1)), ratio
    assert np.all(np.abs(np.log(ratio[:, :2])) < np.log(2.0)), ratio
    assert np.all(np.isfinite(found.lower) & np.isfinite(found.upper))
    assert np.all((0 < found.lower) & (found.lower <= found.upper))
    centre = found.estimate * np.exp(-found.bias)  # the interval's centre on the log scale
    assert np.all((found.lower <= centre * (1 + 1e-12)) & (centre <= found.upper * (1 + 1e-12)))


def test_bootstrap_intervals_refuses_what_it_cannot_do():
    controls, obs, start, params, info = _calibrated_log()
    start_params = sc.starting_params(CONFIG)
    with pytest.raises(ValueError, match="odometry motion model"):
        cb.bootstrap_intervals(CONFIG, jax.random.PRNGKey(0), controls, obs, start,
                               start_params, params, info, motion_model="ackermann")
    with pytest.raises(ValueError, match="replicates >= 2"):
        cb.bootstrap_intervals(CONFIG, jax.random.PRNGKey(0), controls, obs, start,
                               start_params, params, info, replicates=1)
    with pytest.raises(ValueError, match="nothing fitted"):
        cb.bootstrap_intervals(CONFIG, jax.random.PRNGKey(0), controls, obs, start,
                               start_params, params, info._replace(values={}))


def test_total_typical_std_counts_fitted_bursts_only():
    _, _, _, _, info = _calibrated_log()
    plain = sc.em_typical_std(info)
    kept = info._replace(bursts_fitted=False)
    np.testing.assert_allclose(cb.total_typical_std(kept), plain, rtol=1e-12)
    fitted = info._replace(bursts_fitted=True, values=dict(
        info.values, motion_outlier_probability=0.2, motion_outlier_scale=2.0))
    np.testing.assert_allclose(cb.total_typical_std(fitted),
                               plain * np.array([1.6**0.5, 1.6**0.5, 1.0, 1.0]), rtol=1e-6)


def test_replicates_are_drawn_at_ems_own_noise(monkeypatch):
    """The likelihood search's scales (motion x2, observation x4 here) are divided out of
    the noise the replicates are drawn with, and bursts are drawn only when the calibration
    fitted them; the replicates are calibrated without the search, with the caller's other
    options."""
    import types

    controls, obs, start, params, info = _calibrated_log()
    searched = info._replace(noise_scales=types.SimpleNamespace(motion_scale=2.0,
                                                                observation_scale=4.0))
    seen = []

    def fake_replicate(key, solution, noise, observations, bursts):
        seen.append((noise, bursts))
        return np.asarray(controls, np.float64), observations

    def fake_calibrate(*args, **options):
        seen.append(options)
        return params, info

    monkeypatch.setattr(cb, "replicate_log", fake_replicate)
    monkeypatch.setattr(sc, "calibrate_params", fake_calibrate)
    for fitted in (False, True):
        seen.clear()
        found = cb.bootstrap_intervals(CONFIG, jax.random.PRNGKey(0), controls, obs, start,
                                       sc.starting_params(CONFIG), params,
                                       searched._replace(bursts_fitted=fitted), replicates=2,
                                       iterations=3)
        noise, bursts = seen[0]
        assert bursts is fitted
        np.testing.assert_allclose(noise.rot1_noise, np.asarray(params.rot1_noise) / 2,
                                   rtol=1e-6)
        np.testing.assert_allclose(noise.range_noise, np.asarray(params.range_noise) / 4,
                                   rtol=1e-6)
        assert seen[1] == {"iterations": 3, "scale_search": False}
        assert found.replicates.shape == (2, 4)
