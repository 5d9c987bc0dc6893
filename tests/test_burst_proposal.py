"""The bursty motion prior's proposal pieces, and the mixture's association at the sample.

Checks: ``ObservationProposal.log_evidence`` against the stacked Gaussian marginal in NumPy
float64; ``piece_mixture`` weights and density against NumPy; piece draws in proportion to
their weights; phi = 0 inside the mixture equals the motion proposal; a burst-free prior
(eps = 0) gives the same filter with and without ``burst_proposal``.
"""
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.stats import multivariate_normal

from jaxslam import ekf, proposal
from jaxslam.filter import run_filter
from jaxslam.types import FilterConfig, default_params

from test_filter import simulate_circle  # noqa: E402  (tests/ is on sys.path)

LANDMARKS = np.array([[6.0, 4.0], [3.0, 8.0], [7.5, -1.0]])
X_HAT = np.array([1.2, 2.1, 0.35])
POSE_COV = np.array([[4e-3, 1e-3, 2e-4], [1e-3, 3e-3, -1e-4], [2e-4, -1e-4, 1e-3]])


def _case(params, match=(0, -1, 2)):
    rng = np.random.default_rng(0)
    landmark_cov = jnp.tile(jnp.asarray([0.01, 0.002, 0.02]), (3, 1))
    predicted = ekf.predict_measurements(jnp.asarray(X_HAT), jnp.asarray(LANDMARKS),
                                         landmark_cov, params)
    z = np.stack([np.asarray(predicted.range), np.asarray(predicted.bearing)], 1)
    z = z + rng.normal(0, [0.05, 0.01], z.shape)
    return jnp.asarray(z), jnp.asarray(match), predicted


def _np_evidence(z, match, predicted):
    """float64: log N(nu; 0, Hx Sigma Hx^T + S) with the matched rows stacked (2n, 2n)."""
    rows = [k for k, j in enumerate(match) if j >= 0]
    nu, jac, blocks = [], [], []
    for k in rows:
        j = match[k]
        p = {name: float(np.asarray(getattr(predicted, name))[j]) for name in predicted._fields}
        bearing = (float(z[k, 1]) - p["bearing"] + np.pi) % (2 * np.pi) - np.pi
        nu += [float(z[k, 0]) - p["range"], bearing]
        jac += [[-p["h00"], -p["h01"], 0.0], [-p["h10"], -p["h11"], -1.0]]
        blocks.append(np.array([[p["s_rr"], p["s_rb"]], [p["s_rb"], p["s_bb"]]]))
    jac = np.asarray(jac)
    cov = jac @ POSE_COV @ jac.T + np.kron(np.eye(len(rows)), np.zeros((2, 2)))
    for i, block in enumerate(blocks):
        cov[2 * i:2 * i + 2, 2 * i:2 * i + 2] += block
    return multivariate_normal(np.zeros(2 * len(rows)), cov).logpdf(np.asarray(nu))


@pytest.fixture(scope="module")
def params():
    return default_params(dtype=jnp.float64, range_std_floor=0.05, bearing_std_floor=0.01)


@pytest.mark.parametrize("jit", [False, True])
def test_log_evidence_matches_the_stacked_marginal(params, jit):
    if True:  # x64 is on for the tests (conftest.py)
        z, match, predicted = _case(params)
        fn = jax.jit(proposal.observation_proposal) if jit else proposal.observation_proposal
        gaussian = fn(jnp.asarray(X_HAT), jnp.asarray(POSE_COV), z, match, predicted)
        want = _np_evidence(np.asarray(z), np.asarray(match), predicted)
        # float64 throughout: Woodbury and the determinant lemma agree with the direct
        # (2n x 2n) Gaussian to rounding (1e-9 relative).
        np.testing.assert_allclose(float(gaussian.log_evidence), want, rtol=1e-9)
        # No match: evidence 0 (an empty product).
        none = fn(jnp.asarray(X_HAT), jnp.asarray(POSE_COV), z, jnp.full(3, -1), predicted)
        assert abs(float(none.log_evidence)) < 1e-9 and not bool(none.has_match)


def test_piece_mixture_weights_density_and_draws(params):
    if True:  # x64 is on for the tests (conftest.py)
        z, match, predicted = _case(params)
        pieces = [proposal.observation_proposal(jnp.asarray(X_HAT), jnp.asarray(c), z, match,
                                                predicted) for c in (POSE_COV, 16 * POSE_COV)]
        log_prior = jnp.log(jnp.asarray([0.9, 0.1]))
        mixture = proposal.piece_mixture(pieces, log_prior)
        logits = np.log([0.9, 0.1]) + np.array([float(q.log_evidence) for q in pieces])
        weights = np.exp(logits - np.logaddexp.reduce(logits))
        np.testing.assert_allclose(np.exp(np.asarray(mixture.log_weights)), weights, rtol=1e-9)
        pose = jnp.asarray(X_HAT + np.array([0.01, -0.02, 0.005]))
        want = np.logaddexp.reduce([np.log(w) + multivariate_normal(
            np.asarray(q.mean), np.asarray(q.chol @ q.chol.T)).logpdf(np.asarray(pose))
            for w, q in zip(weights, pieces)])
        np.testing.assert_allclose(float(proposal.piece_mixture_log_density(pose, mixture)),
                                   want, rtol=1e-9)
        # Draws pick piece j with probability w_j: 4000 draws, 4 binomial standard errors.
        n = 4000
        keys = jax.random.split(jax.random.PRNGKey(1), n)
        _, _, piece = jax.vmap(lambda k: proposal.mixture_sample(
            k, jnp.asarray(X_HAT), mixture, 1.0))(keys)
        share = float(np.mean(np.asarray(piece) == 1))
        assert abs(share - weights[1]) < 4 * np.sqrt(weights[1] * (1 - weights[1]) / n) + 1e-3


def _filter(config, params, seed=3, motion_scale=3.0):
    controls, obs, poses, _ = simulate_circle(seed, num_steps=40, motion_scale=motion_scale)
    final, trace = run_filter(config, jax.random.PRNGKey(0), params, controls, obs,
                              jnp.asarray(poses[0], jnp.float32))
    return final, trace


def test_phi_zero_mixture_is_the_motion_proposal():
    base = dict(num_particles=16, max_landmarks=48, max_obs=8, anchor_empty_map=False,
                burst_proposal=False)
    params = default_params(mixture_ratio=0.0, motion_outlier_probability=0.0)
    motion_final, motion_trace = _filter(FilterConfig(proposal="motion", **base), params)
    for flags in (dict(associate_at_sample=False, match_pose_uncertainty=False),
                  dict(associate_at_sample=True, match_pose_uncertainty=True)):
        final, trace = _filter(FilterConfig(proposal="mixture", **base, **flags), params)
        # Same draws, same associations (each at its own pose), same weights: equal to
        # float32 rounding of the two code paths (the mixture re-predicts at the pose).
        np.testing.assert_allclose(np.asarray(trace.mean_pose), np.asarray(motion_trace.mean_pose),
                                   atol=1e-5)
        np.testing.assert_array_equal(np.asarray(trace.num_landmarks),
                                      np.asarray(motion_trace.num_landmarks))


@pytest.mark.slow  # 22 s: two more compiled filters
def test_burst_proposal_without_bursts_is_the_one_gaussian_proposal():
    base = dict(num_particles=16, max_landmarks=48, max_obs=8, proposal="mixture",
                match_pose_uncertainty=True)
    params = default_params(mixture_ratio=0.5, motion_outlier_probability=0.0)  # no burst mass
    _, plain = _filter(FilterConfig(burst_proposal=False, **base), params)
    _, pieces = _filter(FilterConfig(burst_proposal=True, **base), params)
    np.testing.assert_allclose(np.asarray(pieces.mean_pose), np.asarray(plain.mean_pose),
                               atol=1e-5)


@pytest.mark.slow  # 14 s
def test_burst_proposal_runs_under_vmap_with_finite_weights():
    config = FilterConfig(num_particles=8, max_landmarks=48, max_obs=8, proposal="mixture",
                          match_pose_uncertainty=True, burst_proposal=True,
                          associate_at_sample=True)
    params = default_params(motion_outlier_probability=0.1, motion_outlier_scale=8.0)
    controls, obs, poses, _ = simulate_circle(4, num_steps=30, motion_scale=4.0)
    keys = jax.random.split(jax.random.PRNGKey(2), 3)
    from jaxslam.filter import make_filter, scan_filter

    init = make_filter(config).init
    run = jax.vmap(lambda k: scan_filter(config, k, init(jnp.asarray(poses[0], jnp.float32)),
                                         params, controls, obs))
    finals, traces = run(keys)
    assert np.all(np.isfinite(np.asarray(traces.mean_pose)))
    assert np.all(np.isfinite(np.asarray(finals.log_weight)))
    # Normalised weights in every run (logsumexp 0, float32 rounding).
    np.testing.assert_allclose(np.asarray(jax.scipy.special.logsumexp(finals.log_weight, -1)),
                               0.0, atol=1e-4)
    # Three keys give three different runs (the vmapped axis is live, not broadcast).
    assert len({round(float(e), 6) for e in np.asarray(traces.mean_pose)[:, -1, 0]}) == 3
