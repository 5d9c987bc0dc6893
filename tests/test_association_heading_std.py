"""``Params.association_heading_std``: a heading std added to the motion prior's pose covariance
where the observation and mixture proposals match at the motion prediction, for matching only.

The reference is plain NumPy float64: the pose Jacobian Hx of (range, bearing) written out and
S_match = S + Hx (Sigma_u + diag(0, 0, s^2)) Hx^T formed as a matrix product.
"""
import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam import ekf
from jaxslam.step_propose import _matching_cov, propose
from jaxslam.types import FilterConfig, Observations, default_params
from mapped_state import mapped_state  # tests/ is on sys.path

LANDMARKS = np.array([[11.0, 0.4], [3.0, -2.0], [-4.0, 6.0], [0.5, 0.2]])
LANDMARK_COV = np.array([[1e-4, 2e-5, 3e-4], [4e-4, -1e-4, 2e-4], [1e-3, 0.0, 1e-3],
                         [5e-6, 0.0, 5e-6]])
X_HAT = np.array([0.3, -0.2, 0.4])
SIGMA_U = np.array([[4e-3, 1e-3, 2e-4], [1e-3, 3e-3, -1e-4], [2e-4, -1e-4, 2e-3]])


def _reference_matching_s(s):
    """(M, 2, 2) float64: S of the library at x_hat plus Hx (Sigma_u + diag(0, 0, s^2)) Hx^T,
    Hx = d(range, bearing) / d(x, y, theta) = [[-dx/r, -dy/r, 0], [dy/q, -dx/q, -1]]."""
    params = default_params(dtype=jnp.float64)
    pred = ekf.predict_measurements(jnp.asarray(X_HAT), jnp.asarray(LANDMARKS),
                                    jnp.asarray(LANDMARK_COV), params)
    s_plain = np.stack([np.stack([pred.s_rr, pred.s_rb], -1),
                        np.stack([pred.s_rb, pred.s_bb], -1)], -2)
    d = LANDMARKS - X_HAT[:2]
    q = np.sum(d**2, axis=1)
    r = np.sqrt(q)
    hx = np.stack([np.stack([-d[:, 0] / r, -d[:, 1] / r, np.zeros(4)], -1),
                   np.stack([d[:, 1] / q, -d[:, 0] / q, -np.ones(4)], -1)], -2)
    sigma = SIGMA_U + np.diag([0.0, 0.0, s**2])
    return s_plain + hx @ sigma @ np.swapaxes(hx, -1, -2)


def _library_matching_s(s, match_pose_uncertainty=True):
    config = FilterConfig(match_pose_uncertainty=match_pose_uncertainty)
    params = default_params(dtype=jnp.float64, association_heading_std=s)
    pred = ekf.predict_measurements(jnp.asarray(X_HAT), jnp.asarray(LANDMARKS),
                                    jnp.asarray(LANDMARK_COV), params)
    matched = ekf.add_pose_uncertainty(pred, _matching_cov(config, params, jnp.asarray(SIGMA_U)))
    return jnp.stack([jnp.stack([matched.s_rr, matched.s_rb], -1),
                      jnp.stack([matched.s_rb, matched.s_bb], -1)], -2)


@pytest.mark.parametrize("s", [0.0, 0.01, 0.1, 0.5])
@pytest.mark.parametrize("transform", ["eager", "jit"])
def test_matching_covariance_against_reference(s, transform):
    """float64; tolerance 1e-12 relative to the largest entry (a few roundings of products
    of entries up to ~0.25)."""
    fn = _library_matching_s if transform == "eager" else jax.jit(_library_matching_s)
    got = np.asarray(fn(s))
    want = _reference_matching_s(s)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12 * np.abs(want).max())


def test_the_heading_std_adds_to_the_bearing_variance_only_under_vmap():
    """A heading offset turns every predicted bearing by the same angle and moves no range:
    s_bb grows by s^2 exactly (to float64 rounding), s_rr and s_rb stay as at s = 0."""
    stds = jnp.asarray([0.0, 0.05, 0.1, 0.3])
    batched = np.asarray(jax.vmap(_library_matching_s)(stds))
    for i, s in enumerate(np.asarray(stds)):
        np.testing.assert_allclose(batched[i], _reference_matching_s(float(s)), rtol=0,
                                   atol=1e-12)
        np.testing.assert_array_equal(batched[i, :, 0, 0], batched[0, :, 0, 0])
        np.testing.assert_array_equal(batched[i, :, 0, 1], batched[0, :, 0, 1])
        np.testing.assert_allclose(batched[i, :, 1, 1] - batched[0, :, 1, 1], s**2, rtol=1e-9)


def test_zero_std_and_no_pose_uncertainty_edges():
    """s = 0 leaves Sigma_u bit for bit; without ``match_pose_uncertainty`` the matching takes
    S alone (None), whatever s is."""
    cov = jnp.asarray(SIGMA_U, jnp.float32)
    config = FilterConfig()
    same = _matching_cov(config, default_params(association_heading_std=0.0), cov)
    np.testing.assert_array_equal(np.asarray(same), np.asarray(cov))
    off = dataclasses.replace(config, match_pose_uncertainty=False)
    assert _matching_cov(off, default_params(association_heading_std=0.3), cov) is None


# One mapped tree 11 m ahead; 6x Table 1 motion noise (the mixture regime's odometry). The
# odometry measures a straight 0.5 m move, but the robot turned by 0.08 rad: the tree's
# bearing is 0.08 rad off its prediction at x_hat (0.84 m sideways). Eq. (1) at the measured
# turn gives a heading std of 1.7 mrad, 14 mrad in a burst (kappa 8): 5.9 burst sigmas, past
# the gate of 25; with s = 0.1 rad the pair's d2 is 0.6.
TURN = 0.08


def _burst_case(s):
    config = FilterConfig(num_particles=16, max_landmarks=4, max_obs=2)
    params = default_params(association_heading_std=s, rot1_noise=(0.0, 0.36, 0.0012),
                            trans_noise=(0.12, 0.036, 0.00018),
                            rot2_noise=(0.0, 0.36, 0.0018))
    tree = np.array([[11.0, 0.0]])
    state = mapped_state(config, tree, variance=1e-5)
    truth = np.array([0.5, 0.0, TURN])
    d = tree[0] - truth[:2]
    z = np.array([[np.hypot(*d), np.arctan2(d[1], d[0]) - TURN], [0.0, 0.0]])
    obs = Observations(jnp.asarray(z, jnp.float32), jnp.array([True, False]),
                       jnp.zeros(2, jnp.float32), jnp.full(2, -1, jnp.int32))
    control = jnp.asarray([0.0, 0.5, 0.0], jnp.float32)
    return config, params, state, control, obs, truth


def _proposed(s):
    config, params, state, control, obs, truth = _burst_case(s)
    run = jax.jit(lambda key, p: propose(config, key, p, state.particles, control, obs,
                                         jnp.float32(1.0), jnp.asarray(False)))
    return run(jax.random.PRNGKey(0), params), truth


def test_a_burst_turn_keeps_the_far_tree_matched():
    """At s = 0 the core piece of the motion prior cannot match the tree; unmatched, it is
    credited the new-landmark likelihood, which outweighs the burst piece's match (measured
    log weights -7e-5 against -9.5), so every particle keeps the measured heading (error
    0.074-0.082 rad) and leaves the tree unmatched: it would start a second landmark for it.
    At the default s = 0.1 rad the core piece matches too, its evidence is then that of a
    0.08 rad miss (log weight -83), the burst piece wins, and every particle matches the tree
    with its heading turned to within 0.015 rad of the truth (bound 0.02 rad, a quarter of
    the turn)."""
    plain, truth = _proposed(0.0)
    assert np.all(np.asarray(plain.association.match)[:, 0] == -1)
    assert np.abs(np.asarray(plain.pose)[:, 2] - truth[2]).min() > 0.06
    wide, _ = _proposed(0.1)
    assert np.all(np.asarray(wide.association.match)[:, 0] == 0)
    heading_error = np.abs(np.asarray(wide.pose)[:, 2] - truth[2])
    assert heading_error.max() < 0.02, heading_error


def test_the_std_is_a_dynamic_parameter_swept_under_vmap():
    """One compiled call over stacked Params: the same outcome per value as one call each."""
    config, params, state, control, obs, _ = _burst_case(0.0)
    stacked = jax.tree.map(lambda a, b: jnp.stack([a, b]), params,
                           params._replace(association_heading_std=jnp.float32(0.1)))
    run = jax.jit(jax.vmap(lambda p: propose(config, jax.random.PRNGKey(0), p, state.particles,
                                             control, obs, jnp.float32(1.0),
                                             jnp.asarray(False))))
    out = run(stacked)
    for i, s in enumerate((0.0, 0.1)):
        single, _ = _proposed(s)
        np.testing.assert_array_equal(np.asarray(out.association.match[i]),
                                      np.asarray(single.association.match))
        np.testing.assert_allclose(np.asarray(out.pose[i]), np.asarray(single.pose), rtol=0,
                                   atol=1e-5)


def test_matching_only_the_proposal_and_weight_keep_sigma_u():
    """When every observation matches either way, s changes nothing: same key, the same
    poses, corrections and associations (four near trees, exact observations)."""
    config = FilterConfig(num_particles=16, max_landmarks=8, max_obs=4)
    trees = np.array([[2.0, 1.0], [3.0, -1.0], [1.5, -2.0], [2.5, 2.5]])
    state = mapped_state(config, trees)
    d = trees - np.array([0.5, 0.0])
    z = np.stack([np.hypot(d[:, 0], d[:, 1]), np.arctan2(d[:, 1], d[:, 0])], 1)
    obs = Observations(jnp.asarray(z, jnp.float32), jnp.ones(4, bool),
                       jnp.zeros(4, jnp.float32), jnp.full(4, -1, jnp.int32))
    control = jnp.asarray([0.0, 0.5, 0.0], jnp.float32)
    out = [propose(config, jax.random.PRNGKey(2), default_params(association_heading_std=s),
                   state.particles, control, obs, jnp.float32(1.0), jnp.asarray(False))
           for s in (0.0, 0.1)]
    np.testing.assert_array_equal(np.asarray(out[0].association.match),
                                  np.asarray(out[1].association.match))
    assert np.all(np.asarray(out[0].association.match) >= 0)
    np.testing.assert_array_equal(np.asarray(out[0].pose), np.asarray(out[1].pose))
    np.testing.assert_array_equal(np.asarray(out[0].log_correction),
                                  np.asarray(out[1].log_correction))
    # Matched at x_hat only (no match again at the sample): the association the update reads
    # carries S without s (the update's innovation covariance).
    at_x_hat = dataclasses.replace(config, associate_at_sample=False)
    kept = [propose(at_x_hat, jax.random.PRNGKey(2), default_params(association_heading_std=s),
                    state.particles, control, obs, jnp.float32(1.0), jnp.asarray(False))
            for s in (0.0, 0.1)]
    np.testing.assert_array_equal(np.asarray(kept[0].association.predicted.s_bb),
                                  np.asarray(kept[1].association.predicted.s_bb))
