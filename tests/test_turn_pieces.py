"""The burst's first turn split into pieces (``FilterConfig.burst_turn_pieces``).

Checks: ``proposal.turn_pieces`` (centres, covariances, masses) against a NumPy float64
reference, with and without jit, under vmap, and on its edges (pure turn, no turn noise, one
piece a side); with the pieces a turn 0.5 rad larger than the measured one is proposed at the
true pose while the two-piece proposal misses it; with them the filter step keeps finite,
normalised weights.
"""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam import proposal
from jaxslam.filter import _step
from jaxslam.step_propose import propose
from jaxslam.types import FilterConfig, Observations, default_params
from mapped_state import mapped_state  # tests/ is on sys.path

POSE = np.array([1.0, -2.0, 0.4])
CONTROL = np.array([0.05, 0.5, -0.02])  # odometry (rot1, trans, rot2)


@pytest.fixture(scope="module")
def params():
    return default_params(dtype=jnp.float64, rot1_noise=(0.002, 0.06, 0.01),
                          trans_noise=(0.02, 0.006, 0.001), rot2_noise=(0.001, 0.05, 0.01),
                          motion_outlier_probability=0.05, motion_outlier_scale=8.0)


def _np_turn_pieces(pose, odometry, p, num_side, span):
    """float64 reference of ``proposal.turn_pieces`` written from its docstring."""
    coeff = {name: np.asarray(getattr(p, name), np.float64)
             for name in ("rot1_noise", "trans_noise", "rot2_noise")}
    rot1, trans, rot2 = (abs(float(v)) for v in odometry)
    std = np.array([coeff["rot1_noise"] @ [trans, rot1, 1.0],
                    coeff["trans_noise"] @ [trans, rot1 + rot2, 1.0],
                    coeff["rot2_noise"] @ [trans, rot2, 1.0]])
    tau = float(p.motion_outlier_scale) * std[0]
    step = span * tau / num_side
    offsets = step * np.arange(-num_side, num_side + 1)
    centres, covs = [], []
    for c in offsets:
        heading = pose[2] + odometry[0] + c
        t = odometry[1]
        centre = [pose[0] + t * np.cos(heading), pose[1] + t * np.sin(heading),
                  (heading + odometry[2] + np.pi) % (2 * np.pi) - np.pi]
        jac = np.array([[-t * np.sin(heading), np.cos(heading), 0.0],
                        [t * np.cos(heading), np.sin(heading), 0.0], [1.0, 0.0, 1.0]])
        cov = jac @ np.diag([step**2, std[1] ** 2, std[2] ** 2]) @ jac.T
        # proposal.pose_jitter: 100 float64 epsilons of the position block, plus 1e-14.
        cov += (100 * np.finfo(np.float64).eps * max(cov[0, 0], cov[1, 1]) + 1e-14) * np.eye(3)
        centres.append(centre)
        covs.append(cov)
    logits = -0.5 * (offsets / max(tau, 1e-30)) ** 2
    log_mass = logits - np.log(np.sum(np.exp(logits - logits.max()))) - logits.max()
    return np.asarray(centres), np.asarray(covs), log_mass


@pytest.mark.parametrize("jit", [False, True])
@pytest.mark.parametrize("num_side,span,control", [
    (4, 4.0, CONTROL),
    (1, 2.0, CONTROL),                      # one piece a side
    (3, 6.0, np.array([0.0, 0.0, 0.3])),    # a pure turn: the pieces differ in heading only
])
def test_turn_pieces_match_numpy(params, jit, num_side, span, control):
    fn = lambda pose, ctl: proposal.turn_pieces(pose, ctl, params, "odometry", num_side, span)
    fn = jax.jit(fn) if jit else fn
    centres, covs, log_mass = fn(jnp.asarray(POSE), jnp.asarray(control))
    want = _np_turn_pieces(POSE, control, params, num_side, span)
    # float64 on both sides: agreement to 1e-12 relative (rounding of the same formulas).
    for got, ref in zip((centres, covs, log_mass), want):
        np.testing.assert_allclose(np.asarray(got), ref, rtol=1e-12, atol=1e-15)
    assert centres.shape == (2 * num_side + 1, 3) and covs.shape == (2 * num_side + 1, 3, 3)
    np.testing.assert_allclose(float(jax.scipy.special.logsumexp(log_mass)), 0.0, atol=1e-12)
    # The middle piece sits at the library's motion prediction (another code path).
    np.testing.assert_allclose(np.asarray(centres[num_side]), np.asarray(
        proposal.predict_pose(jnp.asarray(POSE), jnp.asarray(control), params, "odometry")),
        rtol=1e-12, atol=1e-15)


def test_turn_pieces_without_turn_noise_collapse_to_the_prediction(params):
    flat = params._replace(rot1_noise=jnp.zeros(3, jnp.float64))
    centres, covs, log_mass = proposal.turn_pieces(jnp.asarray(POSE), jnp.asarray(CONTROL),
                                                   flat, "odometry", 3, 4.0)
    # tau = 0: every offset is 0, every piece the prediction, the masses uniform and finite.
    np.testing.assert_allclose(np.asarray(centres), np.broadcast_to(centres[3], (7, 3)),
                               atol=1e-15)
    np.testing.assert_allclose(np.asarray(log_mass), np.full(7, -np.log(7)), atol=1e-12)
    assert np.all(np.isfinite(np.asarray(covs)))


def test_turn_pieces_under_vmap(params):
    poses = jnp.asarray(POSE + np.array([[0.0, 0.0, 0.0], [1.0, 2.0, -2.5], [-3.0, 0.5, 3.1]]))
    controls = jnp.asarray(np.array([CONTROL, [0.3, 0.2, 0.1], [-0.6, 1.0, 0.0]]))
    batched = jax.vmap(lambda pose, ctl: proposal.turn_pieces(pose, ctl, params, "odometry",
                                                              2, 4.0))(poses, controls)
    for i in range(3):
        want = _np_turn_pieces(np.asarray(poses[i]), np.asarray(controls[i]), params, 2, 4.0)
        for got, ref in zip(batched, want):
            np.testing.assert_allclose(np.asarray(got[i]), ref, rtol=1e-12, atol=1e-15)


# A particle whose map holds four trees; the robot turned 0.5 rad more than it measured.
TREES = np.array([[4.0, 3.0], [2.0, -4.0], [-3.0, 3.5], [6.0, -1.0]])
MEASURED = np.array([0.02, 0.5, 0.0])
TRUE_MOVE = MEASURED + np.array([0.5, 0.0, 0.0])


def _far_turn_case(turn_pieces):
    config = FilterConfig(num_particles=64, max_landmarks=8, max_obs=4,
                          burst_turn_pieces=turn_pieces, burst_turn_span=8.0)
    # rot1 std 0.01 rad at this move: tau = 0.08 rad, the true turn is 6.25 tau out.
    params = default_params(rot1_noise=(0.0, 0.0, 0.01), trans_noise=(0.02, 0.0, 0.002),
                            rot2_noise=(0.0, 0.0, 0.01), range_noise=(0.0, 0.01),
                            bearing_noise=(0.0, 0.002), range_std_floor=0.0,
                            bearing_std_floor=0.0)
    state = mapped_state(config, TREES)
    truth = np.array([0.5 * np.cos(0.52), 0.5 * np.sin(0.52), 0.52])
    d = TREES - truth[:2]
    z = np.stack([np.hypot(d[:, 0], d[:, 1]),
                  (np.arctan2(d[:, 1], d[:, 0]) - truth[2] + np.pi) % (2 * np.pi) - np.pi], 1)
    obs = Observations(jnp.asarray(z, jnp.float32), jnp.ones(4, bool), jnp.zeros(4, jnp.float32),
                       jnp.full(4, -1, jnp.int32))
    return config, params, state, jnp.asarray(MEASURED, jnp.float32), obs, truth


@pytest.mark.parametrize("turn_pieces", [0, 8])
def test_a_far_turn_is_proposed_at_the_truth_only_with_turn_pieces(turn_pieces):
    config, params, state, control, obs, truth = _far_turn_case(turn_pieces)
    poses, _, correction, used_obs, _ = jax.jit(
        lambda key: propose(config, key, params, state.particles, control, obs,
                             jnp.float32(1.0), jnp.asarray(False)))(jax.random.PRNGKey(0))
    near = np.hypot(*(np.asarray(poses[:, :2]) - truth[:2]).T) < 0.02
    assert np.all(np.isfinite(np.asarray(correction)))
    if turn_pieces:
        # The 0.48 rad piece (6 tau) holds the truth within 0.02 rad; its evidence from four
        # accurate trunks outweighs every other piece: nearly all 64 draws land there.
        assert near.mean() >= 0.9, near.mean()
    else:
        # Core and burst pieces sit at the measured turn (0.5 rad and 0.25 m away): the
        # trees fall outside their gates, so no draw comes near the truth.
        assert near.mean() <= 0.1, near.mean()


def test_filter_step_with_turn_pieces_keeps_normalised_weights():
    config, params, state, control, obs, _ = _far_turn_case(4)
    step = jax.jit(lambda key, st: _step(config, key, st, params, control, obs))
    new_state, _ = step(jax.random.PRNGKey(1), state)
    weights = np.asarray(new_state.log_weight)
    assert np.all(np.isfinite(weights))
    # Normalised (float32 rounding over 64 particles).
    np.testing.assert_allclose(float(jax.scipy.special.logsumexp(new_state.log_weight)), 0.0,
                               atol=1e-4)
    assert np.all(np.isfinite(np.asarray(new_state.particles.pose)))
