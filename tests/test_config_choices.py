"""Every FilterConfig choice runs through make_filter / run_filter: finite state, right shapes.

The kernels behind each choice have their own reference tests; this checks the wiring (one tiny
compiled run per choice: P=4, M=8, K=4, T=3).
"""
import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxslam
from jaxslam.filter import Filter

BASE = dict(num_particles=4, max_landmarks=8, max_obs=4)
CHOICES = [
    dict(proposal="observation"),
    dict(proposal="mixture", mixture_mode="adaptive"),
    dict(association="greedy"),
    dict(association="hungarian"),
    dict(association="known", boundary="hard"),
    dict(motion_model="velocity"),
    dict(motion_model="ackermann"),
    dict(resampling="stratified"),
    dict(resampling="multinomial"),
    dict(resampling="residual"),
]
# A robot standing still (each model's zero move) seeing the same three trunks every step.
CONTROLS = {"odometry": [0.0, 0.0, 0.0], "velocity": [0.0, 0.0, 0.5],
            "ackermann": [0.0, 0.0, 0.5]}


@pytest.mark.parametrize("choice", CHOICES, ids=lambda c: "-".join(f"{v}" for v in c.values()))
def test_config_choice_runs(choice):
    config = jaxslam.FilterConfig(**BASE, **choice)
    params = jaxslam.default_params(config, max_range=15.0)
    controls = jnp.tile(jnp.asarray(CONTROLS[config.motion_model], jnp.float32), (3, 1))
    z = jnp.tile(jnp.asarray([[5.0, 0.3], [7.0, -0.4], [9.0, 1.2], [0.0, 0.0]], jnp.float32),
                 (3, 1, 1))
    valid = jnp.tile(jnp.asarray([True, True, True, False]), (3, 1))
    ids = jnp.tile(jnp.asarray([0, 1, 2, -1], jnp.int32), (3, 1))
    obs = jaxslam.make_observations(z, valid, landmark_id=ids)
    state, trace = jaxslam.run_filter(config, jax.random.PRNGKey(0), params, controls, obs)
    chex.assert_shape(state.particles.pose, (4, 3))
    chex.assert_shape(trace.mean_pose, (3, 3))
    chex.assert_tree_all_finite((state.particles.pose, state.log_weight, trace.mean_pose))
    assert np.isclose(float(jax.nn.logsumexp(state.log_weight)), 0.0, atol=1e-5)
    estimate = jaxslam.estimate(state)
    # Three trunks seen three times: the best particle holds exactly three landmarks.
    assert int(np.sum(estimate.active)) == 3


def test_filter_unpacks_as_init_step():
    config = jaxslam.FilterConfig(**BASE)
    init, step = jaxslam.make_filter(config)
    assert jaxslam.make_filter(config).config == config
    assert isinstance(jaxslam.make_filter(config), Filter)
    state = init(jnp.zeros(3))
    chex.assert_shape(state.log_weight, (4,))
    del step


@pytest.mark.parametrize("proposal,pose_uncertainty", [
    ("motion", False),
    # 19 s; the motion case keeps the window logic in the default tier
    pytest.param("observation", True, marks=pytest.mark.slow)])
def test_association_window_matches_full_association_when_it_covers_the_map(
        proposal, pose_uncertainty):
    """With more window places than active landmarks, windowed association is exact: the
    same keys give the same particles, weights and maps as matching against every slot.
    The window's rows are in distance order, not slot order, so the observation proposal
    (which indexes the window by ``local_match``) is checked too."""
    rng = np.random.default_rng(0)
    trees = rng.uniform(-8.0, 8.0, (6, 2))
    steps = 6
    poses = np.stack([0.3 * np.arange(steps + 1), np.zeros(steps + 1), np.zeros(steps + 1)], -1)
    z = np.zeros((steps, 8, 2), np.float32)
    valid = np.zeros((steps, 8), bool)
    for t in range(steps):
        delta = trees - poses[t + 1, :2]
        z[t, :6] = np.stack([np.hypot(*delta.T), np.arctan2(delta[:, 1], delta[:, 0])], -1)
        valid[t, :6] = True
    obs = jaxslam.make_observations(jnp.asarray(z), jnp.asarray(valid))
    controls = jnp.tile(jnp.asarray([0.0, 0.3, 0.0], jnp.float32), (steps, 1))
    outs = []
    for window in (0, 10):
        config = jaxslam.FilterConfig(num_particles=4, max_landmarks=16, max_obs=8,
                                      association_window=window, proposal=proposal,
                                      match_pose_uncertainty=pose_uncertainty)
        params = jaxslam.default_params(config, max_range=15.0)
        outs.append(jaxslam.run_filter(config, jax.random.PRNGKey(3), params, controls, obs))
    (full, _), (windowed, _) = outs
    assert int(np.sum(np.asarray(full.particles.active[0]))) == 6
    chex.assert_trees_all_close(full, windowed, atol=1e-6)


def test_association_window_rejects_negative():
    with pytest.raises(ValueError, match="association_window"):
        jaxslam.FilterConfig(association_window=-1)


def test_best_particle_survives_resampling():
    """After a resampling step all weights are equal; info.best_particle still points to a
    copy of the particle that had the highest weight (here 0.6 of the mass: 3 of 5 copies)."""
    # Motion draws (not the empty-map anchor, which would give every particle the same pose).
    config = jaxslam.FilterConfig(num_particles=5, max_landmarks=4, max_obs=2, proposal="motion",
                                  anchor_empty_map=False)
    params = jaxslam.default_params(config, ess_threshold=1.0)  # always resample
    init, step = jaxslam.make_filter(config)
    state = init(jnp.zeros(3))
    weights = jnp.asarray([0.1, 0.1, 0.6, 0.1, 0.1])
    state = state._replace(log_weight=jnp.log(weights))
    obs = jaxslam.empty_observations(2)
    new_state, info = jax.jit(step)(jax.random.PRNGKey(0), state, params,
                                    jnp.asarray([0.1, 0.5, 0.0]), obs)
    assert bool(info.resampled)
    pose = np.asarray(new_state.particles.pose)
    best = pose[int(info.best_particle)]
    assert int(np.sum(np.all(pose == best, axis=1))) == 3
