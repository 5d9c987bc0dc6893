"""The relinearised FastSLAM 2.0 proposal (``FilterConfig.proposal_iterations``).

The kernel is checked against the NumPy float64 reference's Gauss-Newton rounds in
``tests/test_fastslam2_reference.py`` (eager, jit, vmap, no-match edge). Here: the option's
validation; what the rounds are for (a prior mean far off the true pose with near trees, where
one linearisation at x_hat leaves the proposal's mean off and the rounds converge to the
pose the observations fix); and the filter step with the rounds, under jit and vmap, with and
without the burst and turn pieces, keeping finite normalised weights.
"""
import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam import ekf, proposal
from jaxslam.filter import _step
from jaxslam.step_propose import propose
from jaxslam.types import FilterConfig, Observations, default_params
from mapped_state import mapped_state  # tests/ is on sys.path


@pytest.mark.parametrize("bad", [-1, True, 1.5, "2"])
def test_bad_iteration_counts_are_refused(bad):
    with pytest.raises(ValueError, match="proposal_iterations"):
        FilterConfig(proposal_iterations=bad)


# Trees 1.5-2.5 m from the true pose; the prior mean is 0.4 m and 0.15 rad off it, with a
# prior wide enough to hold the truth (std 0.5 m, 0.3 rad); exact observations, 1 mm / 1 mrad
# sensor. At 2 m a 0.4 m position error turns the bearings by ~0.2 rad, far from linear.
TREES = np.array([[1.5, 0.5], [0.5, 2.0], [-1.0, -1.2], [2.0, -1.5]])
TRUTH = np.array([0.0, 0.0, 0.1])
X_HAT = TRUTH + np.array([0.3, -0.25, 0.15])


def _kernel_case():
    params = default_params(dtype=jnp.float64, range_noise=(0.0, 0.001),
                            bearing_noise=(0.0, 0.001), range_std_floor=0.0,
                            bearing_std_floor=0.0)
    d = TREES - TRUTH[:2]
    z = np.stack([np.hypot(d[:, 0], d[:, 1]), np.arctan2(d[:, 1], d[:, 0]) - TRUTH[2]], 1)
    cov = np.tile([1e-8, 0.0, 1e-8], (4, 1))
    pose_cov = np.diag([0.5**2, 0.5**2, 0.3**2])
    return params, jnp.asarray(z), jnp.asarray(cov), jnp.asarray(pose_cov)


def _proposal(iterations):
    params, z, cov, pose_cov = _kernel_case()
    x_hat, trees = jnp.asarray(X_HAT), jnp.asarray(TREES)
    predicted = ekf.predict_measurements(x_hat, trees, cov, params)
    match = jnp.arange(4, dtype=jnp.int32)
    first = proposal.observation_proposal(x_hat, pose_cov, z, match, predicted)
    return proposal.relinearised_proposal(first, x_hat, pose_cov, z, match >= 0, trees, cov,
                                          params=params, iterations=iterations)


def test_rounds_converge_to_the_pose_the_trees_fix():
    """float64 (tests/conftest.py). Measured max abs error [m, m, rad] of the mean: 0.011
    at x_hat's linearisation, 1.1e-5 after one round, 5.5e-7 after two and after five (the
    MAP itself: the prior's pull on the exact observations)."""
    errors = [float(np.max(np.abs(np.asarray(_proposal(n).mean) - TRUTH))) for n in (0, 1, 2, 5)]
    assert errors[0] > 5e-3, errors
    assert errors[1] < errors[0] / 100 and errors[2] < errors[1] / 10, errors
    assert errors[3] < 2e-6, errors


def _step_case(turn_pieces, iterations):
    config = FilterConfig(num_particles=32, max_landmarks=8, max_obs=4,
                          burst_turn_pieces=turn_pieces, proposal_iterations=iterations)
    params = default_params(rot1_noise=(0.0, 0.3, 0.05), trans_noise=(0.1, 0.0, 0.02),
                            rot2_noise=(0.0, 0.3, 0.05), range_noise=(0.0, 0.005),
                            bearing_noise=(0.0, 0.002), range_std_floor=0.0,
                            bearing_std_floor=0.0)
    trees = TREES + np.array([2.0, 0.0])
    state = mapped_state(config, trees)
    truth = np.array([0.5 * np.cos(0.3), 0.5 * np.sin(0.3), 0.3])  # measured turn: 0.05 rad
    d = trees - truth[:2]
    z = np.stack([np.hypot(d[:, 0], d[:, 1]),
                  (np.arctan2(d[:, 1], d[:, 0]) - truth[2] + np.pi) % (2 * np.pi) - np.pi], 1)
    obs = Observations(jnp.asarray(z, jnp.float32), jnp.ones(4, bool),
                       jnp.zeros(4, jnp.float32), jnp.full(4, -1, jnp.int32))
    return config, params, state, jnp.asarray([0.05, 0.5, 0.0], jnp.float32), obs, truth


@pytest.mark.parametrize("turn_pieces", [0, 2])
def test_filter_step_with_rounds_under_jit_and_vmap(turn_pieces):
    config, params, state, control, obs, truth = _step_case(turn_pieces, 2)
    step = jax.jit(jax.vmap(lambda key, st: _step(config, key, st, params, control, obs),
                            in_axes=(0, None)))
    new_state, _ = step(jax.random.split(jax.random.PRNGKey(1), 2), state)
    weights = np.asarray(new_state.log_weight)
    assert weights.shape == (2, 32) and np.all(np.isfinite(weights))
    # Normalised per run (float32 rounding over 32 particles).
    np.testing.assert_allclose(np.asarray(jax.scipy.special.logsumexp(new_state.log_weight,
                                                                      axis=1)), 0.0, atol=1e-4)
    poses = np.asarray(new_state.particles.pose)
    assert np.all(np.isfinite(poses))
    # The four trees fix the pose: every particle lands within 5 cm of the truth (the
    # measured turn is 0.25 rad short of the true one, which puts x_hat 0.12 m off).
    assert np.max(np.hypot(*(poses[..., :2] - truth[:2]).transpose(2, 0, 1))) < 0.05


def _proposed_poses(turn_pieces, iterations, window=0):
    config, params, state, control, obs, _ = _step_case(turn_pieces, iterations)
    config = dataclasses.replace(config, association_window=window)
    poses = jax.jit(lambda key: propose(config, key, params, state.particles, control, obs,
                                        jnp.float32(1.0), jnp.asarray(False)).pose)
    return np.asarray(poses(jax.random.PRNGKey(3)))


@pytest.mark.parametrize("turn_pieces", [0, 2])
def test_the_filter_step_uses_the_rounds(turn_pieces):
    """Same key, same draws: the relinearised proposal moves the poses (the option reaches
    ``step_propose``); within the association window the same landmarks are gathered by
    their slots (window 4 = the four mapped trees: the same poses to float32 rounding)."""
    plain, once = _proposed_poses(turn_pieces, 0), _proposed_poses(turn_pieces, 1)
    assert np.max(np.abs(once - plain)) > 1e-4
    np.testing.assert_allclose(_proposed_poses(turn_pieces, 1, window=4), once, rtol=0,
                               atol=1e-5)
