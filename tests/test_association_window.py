"""The association window's guard: ``landmarks.may_take_part`` (which landmarks could take
part in an association, found without predicting a measurement) against a NumPy float64
reference and against the visibility rule it bounds; the count of such landmarks a window
leaves out (``StepInfo.window_cut``, ``Trace.window_cut``) in the filter; the run warning."""
import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxslam
from jaxslam import ekf, landmarks, pipeline
from jaxslam.types import FilterConfig, default_params

CONFIG = FilterConfig(num_particles=1, max_landmarks=40, max_obs=8)


def _params(dtype=jnp.float64, **overrides):
    fields = dict(max_range=12.0, range_noise=(0.01, 0.02), range_std_floor=0.005)
    fields.update(overrides)
    params = default_params(CONFIG, **fields)
    return jax.tree.map(lambda leaf: jnp.asarray(leaf, dtype), params)


def ref_may_take_part(distance, cov, active, params, boundary):
    """Plain NumPy float64: r <= R_max (hard); r <= R_max + a sqrt(sxx + syy + s_r(r)^2),
    s_r(r) = max(c_d r + c_0, floor) (loose)."""
    distance, cov = np.asarray(distance, np.float64), np.asarray(cov, np.float64)
    max_range = float(params.max_range)
    if boundary == "hard":
        return np.asarray(active) & (distance <= max_range)
    slope, const = (float(v) for v in np.asarray(params.range_noise))
    sigma = np.maximum(slope * distance + const, float(params.range_std_floor))
    width = float(params.airlock_sigmas) * np.sqrt(cov[:, 0] + cov[:, 2] + sigma**2)
    return np.asarray(active) & (distance <= max_range + width)


def _random_map(rng, num=40, spread=15.0):
    mean = rng.uniform(-spread, spread, (num, 2))
    a = rng.uniform(0.0, 0.5, num) ** 2
    c = rng.uniform(0.0, 0.5, num) ** 2
    b = rng.uniform(-1.0, 1.0, num) * np.sqrt(a * c)  # positive semi-definite
    active = rng.random(num) < 0.8
    return mean, np.stack([a, b, c], -1), active


@pytest.mark.parametrize("boundary", ["hard", "loose"])
@pytest.mark.parametrize("jit", [False, True])
def test_may_take_part_matches_the_numpy_reference(boundary, jit):
    rng = np.random.default_rng(0)
    params = _params()
    mean, cov, active = _random_map(rng)
    distance = np.hypot(mean[:, 0], mean[:, 1])
    fn = lambda d, s, a: landmarks.may_take_part(d, s, a, params, boundary)
    fn = jax.jit(fn) if jit else fn
    got = np.asarray(fn(jnp.asarray(distance), jnp.asarray(cov), jnp.asarray(active)))
    want = ref_may_take_part(distance, cov, active, params, boundary)
    np.testing.assert_array_equal(got, want)
    assert 0 < want.sum() < active.sum()  # the case holds landmarks on both sides


def test_may_take_part_under_vmap_equals_each_map_alone():
    rng = np.random.default_rng(1)
    params = _params()
    maps = [_random_map(rng) for _ in range(3)]
    distance = np.stack([np.hypot(m[:, 0], m[:, 1]) for m, _, _ in maps])
    cov = np.stack([c for _, c, _ in maps])
    active = np.stack([a for _, _, a in maps])
    got = jax.vmap(lambda d, s, a: landmarks.may_take_part(d, s, a, params, "loose"))(
        jnp.asarray(distance), jnp.asarray(cov), jnp.asarray(active))
    for i in range(3):
        np.testing.assert_array_equal(
            np.asarray(got[i]), ref_may_take_part(distance[i], cov[i], active[i], params,
                                                  "loose"))


def test_may_take_part_edges():
    params = _params()
    zero_cov = jnp.zeros((3, 3))
    at_max = jnp.asarray([12.0, 12.0, 0.0])
    # hard: exactly at R_max takes part, inactive never does
    np.testing.assert_array_equal(
        landmarks.may_take_part(at_max, zero_cov, jnp.asarray([True, False, True]), params,
                                "hard"), [True, False, True])
    # loose with zero covariance: r <= 12 + a (0.01 r + 0.02), so the last r in is
    # (12 + 0.02 a) / (1 - 0.01 a)
    a = float(params.airlock_sigmas)
    last = (12.0 + 0.02 * a) / (1.0 - 0.01 * a)
    distance = jnp.asarray([0.999 * last, 1.001 * last, 0.0])
    np.testing.assert_array_equal(
        landmarks.may_take_part(distance, zero_cov, jnp.ones(3, bool), params, "loose"),
        [True, False, True])
    with pytest.raises(ValueError, match="boundary"):
        landmarks.may_take_part(distance, zero_cov, jnp.ones(3, bool), params, "soft")


@pytest.mark.parametrize("boundary", ["hard", "loose"])
def test_may_take_part_holds_every_landmark_the_visibility_rule_uses(boundary):
    """The bound's claim: a landmark matchable or in the loose ring at some pose (from the
    predicted measurement's S, ``landmarks.visibility``) is always in ``may_take_part``.
    2,000 random landmarks and poses (fixed seed), covariances up to 0.25 m^2, ranges
    around R_max."""
    rng = np.random.default_rng(2)
    params = _params()
    pose = jnp.asarray([0.3, -0.2, 0.7])
    mean, cov, _ = _random_map(rng, num=2000, spread=14.0)
    active = jnp.ones(2000, bool)
    predicted = ekf.predict_measurements(pose, jnp.asarray(mean), jnp.asarray(cov), params)
    width = params.airlock_sigmas * jnp.sqrt(predicted.s_rr)
    if boundary == "hard":
        used = predicted.range <= params.max_range
    else:
        used = predicted.range <= params.max_range + width
    bound = landmarks.may_take_part(predicted.range, jnp.asarray(cov), active, params,
                                    boundary)
    used, bound = np.asarray(used), np.asarray(bound)
    assert used.sum() > 500  # enough landmarks in view to mean something
    assert not np.any(used & ~bound)


def _line_of_trees(num_trees, steps=4):
    """Trees on a line ahead of a robot that stands still; every tree observed exactly."""
    trees = np.stack([np.linspace(2.0, 9.0, num_trees), np.full(num_trees, 0.5)], -1)
    z = np.zeros((steps, 8, 2), np.float32)
    valid = np.zeros((steps, 8), bool)
    z[:, :num_trees] = np.stack([np.hypot(*trees.T), np.arctan2(trees[:, 1], trees[:, 0])], -1)
    valid[:, :num_trees] = True
    obs = jaxslam.make_observations(jnp.asarray(z), jnp.asarray(valid))
    return jnp.zeros((steps, 3), jnp.float32), obs


@pytest.mark.parametrize("proposal", ["motion", "observation"])
def test_window_cut_is_zero_when_the_window_holds_the_view(proposal):
    controls, obs = _line_of_trees(6)
    config = FilterConfig(num_particles=4, max_landmarks=16, max_obs=8, association_window=10,
                          proposal=proposal)
    params = default_params(config, max_range=15.0)
    _, trace = jaxslam.run_filter(config, jax.random.PRNGKey(0), params, controls, obs)
    np.testing.assert_array_equal(np.asarray(trace.window_cut), 0)
    np.testing.assert_array_equal(np.asarray(trace.num_landmarks), 6)


@pytest.mark.parametrize("proposal", ["motion", "observation"])
def test_window_cut_counts_the_landmarks_in_view_left_out(proposal):
    """Six trees in view, a window of four: at the second step (the map holds the six from
    the first) each particle's window leaves out exactly two landmarks in view."""
    controls, obs = _line_of_trees(6)
    config = FilterConfig(num_particles=4, max_landmarks=16, max_obs=8, association_window=4,
                          proposal=proposal)
    params = default_params(config, max_range=15.0)
    step = jax.jit(jaxslam.make_filter(config).step)
    state = jaxslam.make_filter(config).init(jnp.zeros(3, jnp.float32))
    row = lambda t: jax.tree.map(lambda leaf: leaf[t], obs)
    state, first = step(jax.random.PRNGKey(0), state, params, controls[0], row(0))
    assert int(first.window_cut) == 0  # an empty map
    state, second = step(jax.random.PRNGKey(1), state, params, controls[1], row(1))
    chex.assert_shape(second.window_cut, ())
    assert int(second.window_cut) == 2
    _, trace = jaxslam.run_filter(config, jax.random.PRNGKey(0), params, controls, obs)
    assert int(trace.window_cut[0]) == 0 and np.all(np.asarray(trace.window_cut[1:]) >= 2)
    warnings = pipeline.run_warnings(trace, obs.valid, 0.1, config.num_particles)
    assert any("association window left out landmarks" in w and "in 3 steps" in w
               for w in warnings), warnings


def test_no_window_reports_no_cut():
    controls, obs = _line_of_trees(6)
    config = FilterConfig(num_particles=4, max_landmarks=16, max_obs=8)
    _, trace = jaxslam.run_filter(config, jax.random.PRNGKey(0),
                                  default_params(config, max_range=15.0), controls, obs)
    np.testing.assert_array_equal(np.asarray(trace.window_cut), 0)
    assert not any("window" in w for w in pipeline.run_warnings(trace, obs.valid, 0.1, 4))
