"""Noise scales chosen by the filter's marginal likelihood (``jaxslam.noise_scale``)."""
from __future__ import annotations

import functools

import chex
import jax
import numpy as np
import pytest

from jaxslam import noise_scale as ns
from jaxslam.filter import run_filter
from jaxslam.types import FilterConfig, default_params
from sims.forest import random_forest
from sims.paths import loop_path
from sims.scenario import build_scenario

CONFIG = FilterConfig(num_particles=16, max_landmarks=48, max_obs=10)


def _true_params():
    return default_params(rot1_noise=(0.0, 0.1, 0.002), trans_noise=(0.04, 0.0, 0.002),
                          rot2_noise=(0.0, 0.1, 0.002), range_noise=(0.01, 0.03),
                          bearing_noise=(0.001, 0.004), range_std_floor=1e-3,
                          bearing_std_floor=1e-4, max_range=12.0)


@functools.lru_cache(maxsize=1)
def _log():
    """A 120-step loop through 30 trees with ``_true_params``' noise."""
    key_forest, key_runs = jax.random.split(jax.random.PRNGKey(11))
    path = loop_path(120, (30.0, 30.0), (12.0, 12.0), 0.5)
    forest = random_forest(key_forest, 30, (60.0, 60.0), keep_clear=path[:, :2])
    scenario = build_scenario(key_runs, forest, path, 1, params=_true_params(), max_obs=10)
    return (scenario.controls[0], jax.tree.map(lambda a: a[0], scenario.observations),
            scenario.poses[0])


def test_scaled_noise_matches_numpy_for_scalars_and_batches():
    params = _true_params()
    one = ns.scaled_noise(params, 2.0, 3.0)
    for name in ns.MOTION_FIELDS:
        np.testing.assert_allclose(getattr(one, name), 2.0 * np.asarray(getattr(params, name)),
                                   rtol=1e-7)
    for name in ns.OBSERVATION_FIELDS:
        np.testing.assert_allclose(getattr(one, name), 3.0 * np.asarray(getattr(params, name)),
                                   rtol=1e-7)
    np.testing.assert_array_equal(one.max_range, params.max_range)
    batch = ns.scaled_noise(params, np.array([1.0, 4.0]), np.array([2.0, 1.0]))
    for name, leaf in batch._asdict().items():  # every leaf gets the leading S axis for vmap
        chex.assert_shape(leaf, (2,) + np.shape(getattr(params, name)))
        assert leaf.dtype == np.asarray(getattr(params, name)).dtype, name
    jitted = jax.jit(ns.scaled_noise)(params, np.array([1.0, 4.0]), np.array([2.0, 1.0]))
    chex.assert_trees_all_close(jitted, batch, rtol=1e-7)
    np.testing.assert_allclose(batch.trans_noise[1], 4.0 * np.asarray(params.trans_noise),
                               rtol=1e-7)
    np.testing.assert_allclose(batch.range_std_floor, 2.0 * np.array([1.0, 0.5]) *
                               float(params.range_std_floor), rtol=1e-7)


def test_vmapped_likelihoods_equal_one_run_each():
    controls, obs, poses = _log()
    key = jax.random.PRNGKey(3)
    candidates = ns.scaled_noise(_true_params(), np.array([1.0, 2.0]), np.array([1.0, 4.0]))
    batched = ns.log_likelihoods(CONFIG, key, candidates, controls, obs, poses[0])
    single = [float(np.sum(run_filter(CONFIG, key, jax.tree.map(lambda a: a[i], candidates),
                                      controls, obs, poses[0])[1].log_evidence))
              for i in range(2)]
    # The same float32 computation batched and one at a time: XLA may fuse and order the
    # float32 sums differently (a few ulps a step over 120 steps); a flipped discrete choice
    # (association, resampling) would move the sum by far more than 1e-4 relative.
    np.testing.assert_allclose(batched, single, rtol=1e-4)
    assert batched[0] != batched[1]


def test_search_widens_a_noise_that_is_too_narrow():
    controls, obs, poses = _log()
    narrow = ns.scaled_noise(_true_params(), 0.25, 0.25)
    scaled, found = ns.search_noise_scales(CONFIG, jax.random.PRNGKey(0), narrow, controls,
                                           obs, poses[0])
    # The log's noise is 4x the given one in both groups; the grid's step is 2x, so 2-8x is
    # the stated interval. Not a near tie: 1x must score at least 10 log units (a factor
    # e^10 in likelihood) below the chosen scale in both stages.
    assert found.motion_scale >= 2.0 and found.observation_scale >= 2.0
    assert np.max(found.motion_objective) - found.motion_objective[0] > 10.0
    assert np.max(found.observation_objective) - found.observation_objective[0] > 10.0
    chex.assert_shape(found.motion_objective, (4,))
    np.testing.assert_allclose(scaled.range_noise,
                               found.observation_scale * np.asarray(narrow.range_noise),
                               rtol=1e-6)


def test_search_keeps_the_true_noise_near_one():
    controls, obs, poses = _log()
    _, found = ns.search_noise_scales(CONFIG, jax.random.PRNGKey(0), _true_params(),
                                      controls, obs, poses[0])
    # Given the log's own noise the likelihood peaks at 1x or the next grid point for the
    # motion (the observation proposal's linearisation can favour a slightly wider motion
    # noise), and at 1x for the observations (a wider sensor noise only lowers the density).
    assert found.motion_scale <= 2.0 and found.observation_scale == 1.0


@pytest.mark.parametrize("objective, expected", [
    ([1.0, 3.0, 2.0, 3.0], 2.0),            # the first of ties
    ([np.nan, -np.inf, 0.5, np.inf], 4.0),  # non-finite scores never win
    ([np.nan, np.nan, np.inf, -np.inf], 1.0),  # nothing finite: keep 1
])
def test_best_scale(objective, expected):
    assert ns.best_scale(np.array([1.0, 2.0, 4.0, 8.0]), np.array(objective)) == expected


@pytest.mark.parametrize("bad", [[], [0.0, 1.0], [1.0, np.nan], [[1.0]], [2.0, 4.0]])
def test_bad_scales_are_refused_with_a_clear_error(bad):
    controls, obs, poses = _log()
    with pytest.raises(ValueError, match="motion_scales must be a non-empty 1-D .* contains 1"):
        ns.search_noise_scales(CONFIG, jax.random.PRNGKey(0), _true_params(), controls, obs,
                               poses[0], motion_scales=bad)
