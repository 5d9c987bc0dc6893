"""Self-calibration from the log alone (``jaxslam.self_calibration``)."""
from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam import self_calibration as sc
from jaxslam.types import FilterConfig, default_params, make_observations
from sims.forest import random_forest
from sims.paths import loop_path
from sims.scenario import build_scenario

CONFIG = FilterConfig(num_particles=16, max_landmarks=64, max_obs=10, association="known")


def _true_params():
    return default_params(rot1_noise=(0.0, 0.1, 0.001), trans_noise=(0.04, 0.0, 0.001),
                          rot2_noise=(0.0, 0.1, 0.001), range_noise=(0.01, 0.03),
                          bearing_noise=(0.001, 0.004), range_std_floor=1e-4,
                          bearing_std_floor=1e-5, max_range=12.0)


@functools.lru_cache(maxsize=1)
def _log():
    """A 200-step loop through 40 trees, sensor and odometry noise as ``_true_params``."""
    key_forest, key_runs = jax.random.split(jax.random.PRNGKey(7))
    path = loop_path(200, (30.0, 30.0), (16.0, 16.0), 0.5)
    forest = random_forest(key_forest, 40, (60.0, 60.0), keep_clear=path[:, :2])
    scenario = build_scenario(key_runs, forest, path, 1, params=_true_params(), max_obs=10)
    return (scenario.controls[0], jax.tree.map(lambda a: a[0], scenario.observations),
            scenario.poses[0])


@functools.lru_cache(maxsize=1)
def _calibrated():
    controls, obs, poses = _log()
    return sc.calibrate_params(CONFIG, jax.random.PRNGKey(0), controls, obs, poses[0],
                               iterations=4)


def test_recovers_the_noise_groups_within_stated_intervals():
    controls, obs, _ = _log()
    params, info = _calibrated()
    z_range = np.asarray(obs.z)[np.asarray(obs.valid)][:, 0]
    odometry = np.asarray(controls, np.float64)
    truth = sc._typical_stds(_true_params(), odometry, z_range)
    fitted = sc._typical_stds(params, odometry, z_range)
    # Tolerance: 1/sqrt(2 n) is 5 % for the 200 moves and under 2 % for the ~1,700
    # observations; the rot1/rot2 split and the Eq. (1) shape are fitted on 16 and 6 groups,
    # which adds about as much again. 4 sigma of the moves' interval: 20 %, sensor 15 %.
    np.testing.assert_allclose(fitted[:2], truth[:2], rtol=0.20)
    np.testing.assert_allclose(fitted[2:], truth[2:], rtol=0.15)
    assert info.iterations >= 1 and info.objective.shape == (info.iterations,)
    assert info.typical_std.shape == (info.iterations + 1, 4)
    assert set(info.relative_std) == {"heading", "translation", "range", "bearing"}


def test_calibration_moves_a_wrong_start_towards_the_truth():
    controls, obs, _ = _log()
    params, info = _calibrated()
    start = info.typical_std[0]
    truth = sc._typical_stds(_true_params(), np.asarray(controls, np.float64),
                             np.asarray(obs.z)[np.asarray(obs.valid)][:, 0])
    # The wide start's sensor noise is off by 15-45 % (range, bearing); the result is within
    # a third of that distance (the 15 % tolerance above is the stated interval).
    start_off = np.abs(np.log(start[2:] / truth[2:]))
    assert np.all(start_off > 0.1)
    assert np.all(np.abs(np.log(info.typical_std[-1][2:] / truth[2:])) < start_off / 3)


def test_sensor_settings_from_the_log():
    params, info = _calibrated()
    # The simulated sensor sees every trunk within 12 m: the usable range is its largest
    # observed range, which the range noise (std 0.15 m at 12 m) moves by at most 4 std,
    # plus the 2 % margin; every landmark in range is detected (the
    # estimate is clipped at 0.99) and there are no false alarms (clipped at 1e-3 .. 0.5).
    assert 11.5 <= float(params.max_range) <= (12.0 + 4 * 0.15) * 1.02
    assert float(params.detection_probability) >= 0.9
    assert float(params.false_alarm_probability) <= 0.05
    lo, hi = sc.GATE_LIMITS
    assert lo <= float(params.association_gate) <= hi
    np.testing.assert_allclose(float(params.airlock_sigmas),
                               np.sqrt(float(params.association_gate)), rtol=1e-6)


def test_calibrated_values_are_finite_and_non_negative():
    params, info = _calibrated()
    for name, value in params._asdict().items():
        value = np.asarray(value)
        if name == "miss_range":
            assert np.all(value > 0)
            continue
        assert np.all(np.isfinite(value)), name
        if "noise" in name or "floor" in name or "probability" in name:
            assert np.all(value >= 0), name
    assert info.values and all(np.all(np.isfinite(v)) for v in info.values.values())


def test_too_few_observations_keeps_the_given_params_and_says_so():
    controls = jnp.tile(jnp.array([[0.0, 0.5, 0.0]]), (40, 1))
    obs = make_observations(jnp.zeros((40, 4, 2)), jnp.zeros((40, 4), bool))
    given = default_params()
    config = FilterConfig(num_particles=4, max_landmarks=8, max_obs=4)
    params, info = sc.calibrate_params(config, jax.random.PRNGKey(0), controls, obs,
                                       params=given)
    assert params is given
    assert info.iterations == 0 and not info.converged
    assert "too few observations" in info.verdict
    assert any("valid observations" in w for w in info.warnings)


def test_sparse_landmarks_keep_the_sensor_noise_and_warn():
    # Every observation is a distinct landmark (seen once): nothing to fit the sensor on.
    steps = 60
    controls = jnp.tile(jnp.array([[0.0, 0.5, 0.0]]), (steps, 1))
    z = jnp.stack([jnp.full((steps, 1), 3.0), jnp.full((steps, 1), 1.5)], -1)
    obs = make_observations(z, jnp.ones((steps, 1), bool))
    config = FilterConfig(num_particles=4, max_landmarks=64, max_obs=1)
    given = default_params(association_gate=1e-3)  # nothing ever matches
    params, info = sc.calibrate_params(config, jax.random.PRNGKey(0), controls, obs,
                                       params=given, iterations=1)
    np.testing.assert_array_equal(np.asarray(params.range_noise), np.asarray(given.range_noise))
    assert any("sensor noise" in w for w in info.warnings)
    assert "partly calibrated" in info.verdict


@pytest.mark.parametrize("bad, message", [
    (dict(iterations=0), "iterations >= 1"),
    (dict(tol=0.0), "tol > 0"),
])
def test_bad_options(bad, message):
    controls, obs, _ = _log()
    with pytest.raises(ValueError, match=message):
        sc.calibrate_params(CONFIG, jax.random.PRNGKey(0), controls, obs, **bad)


def test_bad_shapes():
    controls, obs, _ = _log()
    with pytest.raises(ValueError, match=r"controls must be \(T, 3\)"):
        sc.calibrate_params(CONFIG, jax.random.PRNGKey(0), controls[:, :2], obs)
    with pytest.raises(ValueError, match="one row of each per step"):
        sc.calibrate_params(CONFIG, jax.random.PRNGKey(0), controls[:-1], obs)


def test_rescale_matches_a_float64_reference():
    rng = np.random.default_rng(0)
    features = np.stack([rng.uniform(0, 10, 50), np.ones(50)], 1)
    coefficients = np.array([0.02, 0.1])
    target = 0.3**2
    scaled = sc._rescale(coefficients, features, target)
    np.testing.assert_allclose(np.mean((features @ scaled) ** 2), target, rtol=1e-12)
    np.testing.assert_allclose(scaled / coefficients, scaled[0] / coefficients[0])
    assert sc._rescale(np.zeros(2), features, target) is None


def test_exported_at_top_level():
    import jaxslam

    assert jaxslam.calibrate_params is sc.calibrate_params
    assert jaxslam.CalibrationInfo is sc.CalibrationInfo
