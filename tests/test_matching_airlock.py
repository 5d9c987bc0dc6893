"""The loose boundary's ring when a particle matches at the motion prediction x_hat with the
motion prior's pose covariance added to S (``match_pose_uncertainty``).

The loose boundary is decided with S_m, the landmark's and the sensor's covariance alone: the
ring's width w_m = airlock_sigmas * sqrt(S_m[range, range]) and the gate that sets an
observation aside when it could match a ring landmark. The pose covariance added for matching
shapes only the matching gate. Before, it entered both: the burst piece of the motion prior
(kappa^2 Sigma_u, kappa = 8, at 6x Table 1 odometry) made w_m about 2 m, so every observation
of a tree in the outer metres of a 12 m range was set aside at that piece (and a ring
landmark's inflated gate reached observations far inside), the piece matched nothing, won the
piece mixture with the new-landmark credit of its unmatched observations, and the particle
drew from the bare burst prior and started a twin of every tree it saw (held-out log 6 of
the proposal study, step 152: every particle, 3 twins each).

The reference is plain NumPy float64: S_rr of a range-bearing landmark, its ring width and the
ring tests written out.
"""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam.proposal import motion_pose_covariance
from jaxslam.step_propose import _matching_cov, associate, propose
from jaxslam.types import FilterConfig, Observations, default_params
from mapped_state import mapped_state  # tests/ is on sys.path

MAX_RANGE = 12.0
# 6x Table 1 of Geiser et al. (ICAROB 2023): the mixture regime's odometry.
SIX_X = dict(rot1_noise=(0.0, 0.36, 0.0012), trans_noise=(0.12, 0.036, 0.00018),
             rot2_noise=(0.0, 0.36, 0.0018))
CONTROL = np.array([0.014, 0.449, 0.012])  # a measured move of held-out log 6, step 152
LANDMARK_VARIANCE = 1e-5


def _params(dtype=jnp.float64):
    return default_params(dtype=dtype, max_range=MAX_RANGE, range_noise=(0.0, 0.005),
                          bearing_noise=(0.0, 0.0005), range_std_floor=1e-4,
                          bearing_std_floor=1e-5, **SIX_X)


def _reference_matchable(ranges, params):
    """(N,) bool: a landmark at ``ranges`` (N,) (predicted at the pose, variance
    LANDMARK_VARIANCE I) takes part in matching: r >= min_range and
    r <= max_range - airlock_sigmas sqrt(S_rr), S_rr = sigma_r(r)^2 + LANDMARK_VARIANCE (the
    range Jacobian is a unit vector, so the landmark adds its isotropic variance)."""
    sigma_r = np.maximum(float(params.range_noise[0]) * ranges + float(params.range_noise[1]),
                         float(params.range_std_floor))
    width = float(params.airlock_sigmas) * np.sqrt(sigma_r**2 + LANDMARK_VARIANCE)
    return (ranges >= float(params.min_range)) & (ranges <= float(params.max_range) - width)


def _ring_case(ranges, factor, dtype=jnp.float64, window=0, boundary="loose"):
    """One particle with a landmark at each of ``ranges`` (N,) straight ahead-ish of x_hat
    (bearings spread over +-0.6 rad), each observed exactly; the matching covariance is the
    motion prior's times ``factor`` (plus the heading std). With ``window`` > 0 the map has
    one empty slot more and the association is windowed to the ``window`` nearest landmarks
    (``FilterConfig.association_window``). ``boundary``: the paper's ``loose`` unless a
    test says otherwise."""
    params = _params(dtype)
    ranges = np.asarray(ranges, np.float64)
    bearing = np.linspace(-0.6, 0.6, len(ranges))
    x_hat = np.array([0.0, 0.0, 0.0])
    trees = np.stack([ranges * np.cos(bearing), ranges * np.sin(bearing)], -1)
    config = FilterConfig(num_particles=1, max_landmarks=len(ranges) + (window > 0),
                          max_obs=len(ranges), association_window=window, boundary=boundary)
    state = mapped_state(config, trees, variance=LANDMARK_VARIANCE)
    particle = jax.tree.map(lambda a: a[0].astype(dtype) if a.dtype.kind == "f" else a[0],
                            state.particles)
    obs = Observations(jnp.asarray(np.stack([ranges, bearing], -1), dtype),
                       jnp.ones(len(ranges), bool), jnp.zeros(len(ranges), dtype),
                       jnp.full(len(ranges), -1, jnp.int32))
    pose_cov = motion_pose_covariance(jnp.asarray(x_hat, dtype), jnp.asarray(CONTROL, dtype),
                                      params, "odometry", factor)
    return config, params, particle, jnp.asarray(x_hat, dtype), obs, pose_cov


# Ranges across the ring of a 12 m sensor: the ring itself (w = 5 x 5.9 mm: the last 3 cm),
# well inside, and the outer metres a burst piece's pose covariance used to take away. The
# ring's landmark comes first, at the far end of the bearings (1.2 rad from the 11.9 m one):
# no other observation could match it, so none is set aside for it.
RANGES = [11.99, 3.0, 8.0, 9.8, 10.5, 11.3, 11.9]


@pytest.mark.parametrize("factor", [1.0, 64.0])
@pytest.mark.parametrize("transform", ["eager", "jit"])
@pytest.mark.parametrize("boundary", ["loose", "loose_match"])
def test_ring_widths_ignore_the_matching_pose_covariance(factor, transform, boundary):
    """``matchable`` equals the NumPy ring test without the pose covariance, for the core
    (factor 1) and the burst piece (factor kappa^2 = 64); every observation but the ring's is
    matched to its landmark (each lies exactly at its prediction), and the ring's is set aside
    (it lies within its own width of the range's end). With ``loose_match`` the same
    observation is set aside (never born) but matched, with the ring's landmark matchable."""
    config, params, particle, x_hat, obs, pose_cov = _ring_case(RANGES, factor,
                                                                boundary=boundary)

    def run(particle, x_hat, obs, pose_cov):
        return associate(config, params, particle, x_hat, obs,
                         _matching_cov(config, params, pose_cov))

    found = (run if transform == "eager" else jax.jit(run))(particle, x_hat, obs, pose_cov)
    want = _reference_matchable(np.asarray(RANGES), params)
    assert want[1:].all() and not want[0]  # the case spans the ring's edge
    ring_matched = boundary == "loose_match"
    np.testing.assert_array_equal(np.asarray(found.visibility.matchable), want | ring_matched)
    np.testing.assert_array_equal(np.asarray(found.match),
                                  [0 if ring_matched else -1, 1, 2, 3, 4, 5, 6])
    np.testing.assert_array_equal(np.asarray(found.visibility.set_aside_obs), ~want)


def test_ring_widths_under_vmap_over_the_pose_covariance():
    """One vmapped call over covariance factors 1 ... 400: the same matchable landmarks, the
    same observations set aside and the same matches whatever the factor (the boundary follows
    the sensor and the map only; each observation lies exactly at its landmark's prediction,
    d2 = 0, so the matching pairs them whatever the gates' overlap)."""
    factors = jnp.asarray([1.0, 4.0, 64.0, 400.0])
    config, params, particle, x_hat, obs, _ = _ring_case(RANGES, 1.0)

    def run(factor):
        pose_cov = motion_pose_covariance(x_hat, jnp.asarray(CONTROL), params, "odometry",
                                          factor)
        found = associate(config, params, particle, x_hat, obs,
                          _matching_cov(config, params, pose_cov))
        return found.visibility.matchable, found.visibility.set_aside_obs, found.match

    matchable, set_aside, match = jax.vmap(run)(factors)
    want = _reference_matchable(np.asarray(RANGES), params)
    for i in range(len(factors)):
        np.testing.assert_array_equal(np.asarray(matchable[i]), want)
        np.testing.assert_array_equal(np.asarray(set_aside[i]), ~want)
        np.testing.assert_array_equal(np.asarray(match[i]), [-1, 1, 2, 3, 4, 5, 6])


def test_a_turn_burst_at_the_range_edge_keeps_the_trees():
    """The held-out log's failure, rebuilt: three mapped trees 10.5-11.3 m away, a measured
    turn of 0.026 rad where the robot turned 0.106 rad (7.5 and 5.6 sigmas of Eq. (1) at
    the measured move, in rot1 and rot2). Every particle matches all three trees at its sample
    and ends within 10 mrad of the true heading; before the ring's fix every particle drew from
    the bare burst prior and started three twins."""
    params = _params(jnp.float32)
    config = FilterConfig(num_particles=16, max_landmarks=8, max_obs=3)
    true_move = np.array([0.059, 0.5, 0.047])
    truth = np.array([0.5 * np.cos(true_move[0]), 0.5 * np.sin(true_move[0]),
                      true_move[0] + true_move[2]])
    bearing = np.array([0.5, -0.3, -0.9])
    ranges = np.array([10.5, 11.1, 11.3])
    world = truth[2] + bearing  # bearings in the true pose's frame
    trees = truth[:2] + np.stack([ranges * np.cos(world), ranges * np.sin(world)], -1)
    state = mapped_state(config, trees, variance=LANDMARK_VARIANCE)
    obs = Observations(jnp.asarray(np.stack([ranges, bearing], -1), jnp.float32),
                       jnp.ones(3, bool), jnp.zeros(3, jnp.float32), jnp.full(3, -1, jnp.int32))
    proposed = jax.jit(lambda key: propose(config, key, params, state.particles,
                                           jnp.asarray(CONTROL, jnp.float32), obs,
                                           jnp.float32(1.0), jnp.asarray(False)))(
        jax.random.PRNGKey(0))
    np.testing.assert_array_equal(np.asarray(proposed.association.match),
                                  np.tile(np.arange(3), (config.num_particles, 1)))
    heading_error = np.angle(np.exp(1j * (np.asarray(proposed.pose[:, 2]) - truth[2])))
    # The three trees fix the heading to about 0.5 mrad / sqrt(3); 10 mrad is 35 such stds.
    assert np.max(np.abs(heading_error)) < 0.01, heading_error


def test_a_ring_landmark_does_not_reach_inner_observations_through_the_pose_covariance():
    """A landmark in the ring (11.99 m) 0.15 rad from a tree at 10.5 m, the burst piece's
    matching covariance: the observation of the inner tree is not set aside (the boundary's
    gate uses S alone, under which the two are 1.5 m apart in range) and matches its tree; the
    ring's own observation is set aside. With the pose covariance in the boundary's gate the
    inner observation was set aside and the piece matched nothing."""
    config, params, particle, x_hat, obs, pose_cov = _ring_case([11.99, 10.5], 64.0)
    # _ring_case spreads the bearings over +-0.6 rad; put the two 0.15 rad apart.
    bearing = jnp.asarray([0.0, 0.15], obs.z.dtype)
    ranges = jnp.asarray([11.99, 10.5], obs.z.dtype)
    trees = jnp.stack([ranges * jnp.cos(bearing), ranges * jnp.sin(bearing)], -1)
    particle = particle._replace(landmark_mean=trees)
    obs = obs._replace(z=jnp.stack([ranges, bearing], -1))
    found = jax.jit(lambda p: associate(config, params, p, x_hat, obs,
                                        _matching_cov(config, params, pose_cov)))(particle)
    np.testing.assert_array_equal(np.asarray(found.visibility.set_aside_obs), [True, False])
    np.testing.assert_array_equal(np.asarray(found.match), [-1, 1])


@pytest.mark.parametrize("factor", [1.0, 64.0])
def test_the_windowed_association_keeps_the_same_boundary(factor):
    """The same case through the association window (7 nearest of 8 slots, the 8th empty):
    the boundary's flags, mapped back to the slots, and the matches equal the unwindowed
    ones (the window only restricts which landmarks are predicted), and the matchable flags
    are the NumPy ring test's, so the windowed path also decides the boundary with S alone."""
    config, params, particle, x_hat, obs, pose_cov = _ring_case(RANGES, factor)
    plain = associate(config, params, particle, x_hat, obs,
                      _matching_cov(config, params, pose_cov))
    config_w, _, particle_w, _, _, _ = _ring_case(RANGES, factor, window=len(RANGES))
    windowed = jax.jit(lambda p: associate(config_w, params, p, x_hat, obs,
                                           _matching_cov(config_w, params, pose_cov)))(
        particle_w)
    np.testing.assert_array_equal(np.asarray(windowed.match), np.asarray(plain.match))
    want = _reference_matchable(np.asarray(RANGES), params)
    np.testing.assert_array_equal(np.asarray(windowed.visibility.matchable),
                                  np.append(want, False))
    np.testing.assert_array_equal(np.asarray(plain.visibility.matchable), want)
    np.testing.assert_array_equal(np.asarray(windowed.visibility.set_aside_obs),
                                  np.asarray(plain.visibility.set_aside_obs))
