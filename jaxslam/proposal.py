"""Pose proposals: the motion model, an observation-based proposal, and their mixture.

Geiser et al. 2023, section 5.2: when the lidar is far more accurate than odometry, particles drawn from
the motion model alone can all miss the true pose. The observation proposal (FastSLAM 2.0,
Montemerlo et al. 2003) linearises the measurements of the matched landmarks around the motion
prediction x_hat and samples from

    Lambda = Sigma_u^-1 + sum_k Hx_k^T S_k^-1 Hx_k,     mu = x_hat + Lambda^-1 sum_k Hx_k^T S_k^-1 nu_k

where Sigma_u = J diag(sigma_odometry^2) J^T is the motion noise mapped to the pose,
Hx_k = dh/dx at x_hat, S_k the innovation covariance of landmark m(k), nu_k = z_k - h(x_hat, m).
Without any match it falls back to the motion model. ``relinearised_proposal`` repeats the
solve with h linearised at the previous mean (Gauss-Newton on the pose posterior's mode, the
association held), for priors wide enough that x_hat is a poor linearisation point.

The mixture draws each particle from q_obs with probability phi and from p_motion otherwise,
and the importance weight is corrected by

    log w += log p_motion(x) - log((1 - phi) p_motion(x) + phi q_obs(x))

evaluated at the sampled pose, so the filter targets the same posterior for every phi.
The adaptive phi is per particle: it rises after a drop of the short-term average of the
observation log-likelihood below the long-term one (as in augmented MCL,
``adaptive_ratio``), and where the particle's motion draws would rarely land where its
observation proposal puts the pose (``motion_draw_efficiency``, ``coverage_ratio``;
``step_propose.particle_ratio`` combines them).

Shapes are for ONE particle: pose (3,), landmark arrays (M,), observations (K,).
"""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxslam.ekf import PredictedMeasurement, predict_measurements
from jaxslam.geometry import LOG_2PI, wrap_angle
from jaxslam.motion import (apply_odometry, burst_variance_factor, control_to_odometry,
                            motion_log_density, odometry_std, predict_pose)
from jaxslam.types import Params
from jaxslam.spd3 import cholesky3, log_det_from_cholesky3, solve_lower3, spd_inverse3

# Sigma_u is singular for a pure turn and badly conditioned for a short move (``pose_jitter``).
_POSE_JITTER_EPS = 100.0  # the jitter in units of the float type's epsilon
_POSE_JITTER_ABSOLUTE = 1e-14


class ObservationProposal(NamedTuple):
    """Gaussian proposal over the pose of one particle.

    mean: (3,); chol: (3, 3) lower Cholesky factor of the covariance;
    has_match: () bool, False means fall back to the motion model;
    log_evidence: () log N(nu; 0, Hx Sigma_u Hx^T + S) of the matched observations, the
      linearised marginal likelihood of this prior piece (``piece_mixture``).
    """

    mean: jnp.ndarray
    chol: jnp.ndarray
    has_match: jnp.ndarray
    log_evidence: jnp.ndarray = None


class PieceMixture(NamedTuple):
    """A mixture of J Gaussian pose proposals (one per piece of the motion prior).

    means: (J, 3); chols: (J, 3, 3); log_weights: (J,) normalised (logsumexp 0);
    has_match: () bool, some piece matched an observation.
    """

    means: jnp.ndarray
    chols: jnp.ndarray
    log_weights: jnp.ndarray
    has_match: jnp.ndarray


def motion_pose_covariance(pose, control, params: Params, motion_model: str,
                           variance_factor=None):
    """Sigma_u = J diag(sigma^2) J^T (3, 3): Eq. (1) noise mapped to the pose at x_hat.

    With bursts (``motion.burst_variance_factor``) sigma^2 is the mixture's E[s^2] sigma^2;
    ``variance_factor`` replaces that factor (1: the core piece, kappa^2: the burst piece).

    J = d pose' / d (rot1, trans, rot2) = [[-t sin h, cos h, 0], [t cos h, sin h, 0],
    [1, 0, 1]], h = theta + rot1.
    """
    odometry = control_to_odometry(control, params, motion_model)
    factor = burst_variance_factor(params) if variance_factor is None else variance_factor
    return odometry_pose_covariance(pose, odometry, odometry_std(odometry, params) ** 2 * factor)


def odometry_pose_covariance(pose, odometry, variance):
    """J diag(variance) J^T + jitter (3, 3) of the move ``odometry`` (3,) from ``pose`` (3,),
    ``variance`` (3,) of (rot1, trans, rot2) (``motion_pose_covariance``)."""
    heading = pose[2] + odometry[0]
    trans = odometry[1]
    zero = jnp.zeros_like(trans)
    jac = jnp.array([[-trans * jnp.sin(heading), jnp.cos(heading), zero],
                     [trans * jnp.cos(heading), jnp.sin(heading), zero],
                     [1.0 + zero, zero, 1.0 + zero]])
    cov = (jac * variance[None, :]) @ jac.T
    return cov + pose_jitter(cov) * jnp.eye(3, dtype=pose.dtype)


def turn_pieces(pose, control, params: Params, motion_model: str, num_side: int,
                span: float):
    """The burst's first turn split into J = 2n + 1 Gaussian pieces (``burst_turn_pieces``).

    The burst moves by (rot1, trans, rot2) + kappa sigma * N(0, I). Its first turn is
    replaced by sum_j w_j N(c_j, h^2) with c_j = j h, h = span tau / n, tau = kappa sigma_rot1,
    w_j proportional to exp(-c_j^2 / (2 tau^2)) (the burst's density at c_j); translation and
    second turn keep the core std. Piece j's centre is the odometry move with c_j added to
    rot1 and its covariance J_j diag(h^2, sigma_trans^2, sigma_rot2^2) J_j^T at that centre, so
    a piece far out along the turn is linearised where it lies.

    Args: pose (3,); control (3,); n = ``num_side`` > 0; ``span`` > 0.
    Returns: (centres (J, 3), covariances (J, 3, 3), log masses (J,), normalised over J).
    """
    odometry = control_to_odometry(control, params, motion_model)
    std = odometry_std(odometry, params)
    tau = params.motion_outlier_scale * std[0]
    step = span * tau / num_side
    offsets = step * jnp.arange(-num_side, num_side + 1, dtype=pose.dtype)
    moves = odometry[None, :] + jnp.stack(
        [offsets, jnp.zeros_like(offsets), jnp.zeros_like(offsets)], -1)
    variance = jnp.stack([step**2, std[1] ** 2, std[2] ** 2])
    centres = jax.vmap(lambda move: apply_odometry(pose, move))(moves)
    covs = jax.vmap(lambda move: odometry_pose_covariance(pose, move, variance))(moves)
    log_mass = jax.nn.log_softmax(-0.5 * (offsets / jnp.maximum(tau, 1e-30)) ** 2)
    return centres, covs, log_mass


def pose_jitter(cov):
    """The diagonal jitter () added to a motion covariance R (3, 3):

        jitter = 100 eps max(R_xx, R_yy) + 1e-14,   eps = the float type's epsilon.

    R = J diag(sigma^2) J^T has determinant trans^2 prod(sigma^2): singular for a pure turn,
    and for a creep its lateral variance trans^2 sigma_rot1^2 is many orders below the
    heading's (a 0.02 m move with a 0.3 rad turn: 1.6e-11 m^2 against 3.4e-4 rad^2). Rounding
    J diag(sigma^2) J^T perturbs each entry of the position block by about eps times that
    block's own size, and the lateral variance is what is left after the position block and
    its correlation with the heading cancel; so a jitter of 100 eps of the position block
    keeps R positive definite without widening it. A jitter relative to R's
    largest variance (the heading's, for a creep) was ~200x the creep's lateral variance and
    made the observation proposal far wider than the posterior (ESS/N 0.10 against 0.98
    without it, ``tests/test_fastslam2_reference.py``). The floor covers a move with no noise.
    """
    eps = jnp.finfo(cov.dtype).eps
    return _POSE_JITTER_EPS * eps * jnp.maximum(cov[0, 0], cov[1, 1]) + _POSE_JITTER_ABSOLUTE


def observation_proposal(predicted_pose, pose_cov, z, match, predicted: PredictedMeasurement,
                         linearization_pose=None):
    """FastSLAM 2.0 Gaussian (module docstring) from the matched observations.

    With ``linearization_pose`` x_l, h is linearised at x_l instead of x_hat (one
    Gauss-Newton step towards the pose posterior's mode from x_l) and the innovation is the
    linear model's about the prior mean,

        nu_k = z_k - h_k(x_l) - Hx_k (x_hat - x_l),

    so the formulas of the module docstring stand with Hx_k, S_k at x_l; x_l = x_hat is
    the published proposal.

    Args:
      predicted_pose: (3,) x_hat; pose_cov: (3, 3) Sigma_u; z: (K, 2);
      match: (K,) int32 row of ``predicted`` matched by each observation, or -1;
      predicted: at x_l (x_hat when not given), (N,) fields (the particle's landmarks, or a
        window of them, or the K matched ones).
      linearization_pose: (3,) x_l, or None for x_hat.
    """
    matched = match >= 0
    slot = jnp.clip(match, 0, predicted.range.shape[0] - 1)
    p = jax.tree.map(lambda leaf: leaf[slot], predicted)
    weight = matched.astype(z.dtype)
    nu_range = (z[:, 0] - p.range) * weight
    nu_bearing = wrap_angle(z[:, 1] - p.bearing) * weight
    # Hx = [[-h00, -h01, 0], [-h10, -h11, -1]]: rows (range, bearing), columns (x, y, theta).
    zero = jnp.zeros_like(p.h00)
    hx = jnp.stack([jnp.stack([-p.h00, -p.h01, zero], -1),
                    jnp.stack([-p.h10, -p.h11, zero - 1.0], -1)], -2)  # (K, 2, 3)
    s_inv = jnp.stack([jnp.stack([p.i_rr, p.i_rb], -1),
                       jnp.stack([p.i_rb, p.i_bb], -1)], -2) * weight[:, None, None]
    info_obs = jnp.einsum("kai,kab,kbj->ij", hx, s_inv, hx)
    nu = jnp.stack([nu_range, nu_bearing], -1)
    if linearization_pose is not None:
        offset = predicted_pose - linearization_pose
        offset = offset.at[2].set(wrap_angle(offset[2]))
        nu = nu - jnp.einsum("kai,i->ka", hx, offset) * weight[:, None]
    info_vec = jnp.einsum("kai,kab,kb->i", hx, s_inv, nu)
    pose_info, pose_log_det = spd_inverse3(pose_cov)
    precision = pose_info + info_obs
    cov, precision_log_det = spd_inverse3(precision)
    mean = predicted_pose + cov @ info_vec
    mean = mean.at[2].set(wrap_angle(mean[2]))
    # log N(nu; 0, Hx Sigma_u Hx^T + S) by Woodbury and the determinant lemma:
    # nu^T (.)^-1 nu = nu^T S^-1 nu - b^T Lambda^-1 b, log det (.) = log det S
    # + log det Sigma_u + log det Lambda, with b = Hx^T S^-1 nu and Lambda the precision.
    quad = jnp.einsum("ka,kab,kb->", nu, s_inv, nu) - info_vec @ cov @ info_vec
    log_det = (jnp.sum(jnp.where(matched, p.log_det, 0.0)) + pose_log_det + precision_log_det)
    log_evidence = -0.5 * (quad + log_det) - jnp.sum(weight) * LOG_2PI
    return ObservationProposal(mean, cholesky3(cov), jnp.any(matched), log_evidence)


def relinearised_proposal(first: ObservationProposal, predicted_pose, pose_cov, z, matched,
                          landmark_mean, landmark_cov, *, params: Params, iterations: int):
    """``first`` (the FastSLAM 2.0 Gaussian linearised at x_hat) relinearised ``iterations``
    times at its own mean: Gauss-Newton on the mode of p(x | x_prev, u) prod_k p(z_k | x, m_k)
    with the association held fixed,

        x_{i+1} = mean of ``observation_proposal``(x_hat, Sigma_u, linearization_pose = x_i),

    x_0 the mean of ``first``; Hx_k, S_k and h_k are evaluated at x_i for the matched
    landmarks only. The last solve's mean, covariance and evidence are the proposal (the
    importance weight stays exact for any Gaussian: ``mixture_log_correction``); its
    ``has_match`` (any observation matched) is ``first``'s, as ``matched`` marks the rows
    ``first`` used. No damping: a round that overshoots costs proposal efficiency only.

    Args:
      first: at x_hat; predicted_pose: (3,) x_hat; pose_cov: (3, 3) Sigma_u; z: (K, 2);
      matched: (K,) bool; landmark_mean: (K, 2), landmark_cov: (K, 3) components, row k the
        landmark observation k matched (ignored where not matched); iterations: static >= 0.
    """
    local = jnp.where(matched, jnp.arange(matched.shape[0]), -1)
    gaussian = first
    for _ in range(iterations):
        at_mean = predict_measurements(gaussian.mean, landmark_mean, landmark_cov, params)
        gaussian = observation_proposal(predicted_pose, pose_cov, z, local, at_mean,
                                        linearization_pose=gaussian.mean)
    return gaussian


def stack_proposals(pieces) -> ObservationProposal:
    """J ``ObservationProposal`` as one with a leading (J,) axis on every field; an
    ``ObservationProposal`` whose fields already have that axis passes through."""
    if isinstance(pieces, ObservationProposal):
        return pieces
    return jax.tree.map(lambda *leaves: jnp.stack(leaves), *pieces)


def piece_mixture(pieces, log_prior) -> PieceMixture:
    """Proposals of the J motion-prior pieces mixed by prior mass x linearised evidence.

    For a motion prior sum_j pi_j N(x; x_hat, Sigma_j), the linearised optimal proposal is
    sum_j w_j N(x; mu_j, C_j) with w_j proportional to pi_j p_j(z), p_j(z) each piece's
    ``log_evidence`` (the observations it left unmatched credited as a new landmark's, so
    pieces with different matches compare; that credit is in ``log_evidence`` already when
    the caller adds it).

    Args:
      pieces: J ``ObservationProposal`` (their ``log_evidence`` set), as a list or stacked
        with a leading (J,) axis (``stack_proposals``).
      log_prior: (J,) log pi_j (-inf for a piece of mass 0).
    """
    stacked = stack_proposals(pieces)
    logits = jnp.asarray(log_prior) + stacked.log_evidence
    logits = jnp.where(stacked.has_match, logits, jnp.asarray(log_prior))
    return PieceMixture(stacked.mean, stacked.chol, jax.nn.log_softmax(logits),
                        jnp.any(stacked.has_match))


def piece_mixture_log_density(pose, mixture: PieceMixture):
    """log sum_j w_j N(pose; mu_j, C_j), heading differences wrapped. (3,) -> ()."""
    densities = jax.vmap(lambda mean, chol: gaussian_pose_log_density(
        pose, ObservationProposal(mean, chol, jnp.asarray(True))))(mixture.means, mixture.chols)
    return jax.scipy.special.logsumexp(mixture.log_weights + densities)


def sample_piece_mixture(key, mixture: PieceMixture):
    """x ~ sum_j w_j N(mu_j, C_j). Returns (pose (3,), piece () int32)."""
    key_piece, key_draw = jax.random.split(key)
    piece = jax.random.categorical(key_piece, mixture.log_weights)
    return sample_gaussian_pose(key_draw, ObservationProposal(
        mixture.means[piece], mixture.chols[piece], jnp.asarray(True))), piece


def gaussian_pose_log_density(pose, proposal: ObservationProposal):
    """log N(pose; mean, L L^T) with the heading difference wrapped. (3,) -> ()."""
    diff = pose - proposal.mean
    diff = diff.at[2].set(wrap_angle(diff[2]))
    white = solve_lower3(proposal.chol, diff)
    log_det = log_det_from_cholesky3(proposal.chol)
    return -0.5 * jnp.sum(white**2) - 0.5 * log_det - 1.5 * LOG_2PI


def sample_gaussian_pose(key, proposal: ObservationProposal):
    """x ~ N(mean, L L^T), heading wrapped. Returns (3,)."""
    draw = proposal.mean + proposal.chol @ jax.random.normal(key, (3,), proposal.mean.dtype)
    return draw.at[2].set(wrap_angle(draw[2]))


def _piece(proposal, key):
    """The Gaussian to draw from: ``proposal`` itself, or one piece of a ``PieceMixture``
    chosen by its weights with a key folded from ``key`` (so one piece draws as before)."""
    if not isinstance(proposal, PieceMixture):
        return proposal, jnp.zeros((), jnp.int32)
    piece = jax.random.categorical(jax.random.fold_in(key, 1), proposal.log_weights)
    return ObservationProposal(proposal.means[piece], proposal.chols[piece],
                               proposal.has_match), piece.astype(jnp.int32)


def mixture_sample(key, motion_sample, proposal, ratio):
    """Pick q_obs with probability ``ratio`` (and a match), else the motion sample.

    ``proposal``: an ``ObservationProposal`` or a ``PieceMixture``.
    Returns (pose (3,), used_observation () bool, piece () int32 drawn from).
    """
    key_choice, key_draw = jax.random.split(key)
    use_obs = (jax.random.uniform(key_choice, (), motion_sample.dtype) < ratio)
    use_obs = use_obs & proposal.has_match
    gaussian, piece = _piece(proposal, key_draw)
    pose = jnp.where(use_obs, sample_gaussian_pose(key_draw, gaussian), motion_sample)
    return pose, use_obs, piece


def mixture_log_correction(pose_prev, pose, control, params: Params, motion_model: str,
                           proposal, ratio):
    """log p_motion(x) - log((1 - phi) p_motion(x) + phi q_obs(x)); 0 without a match.

    q_obs is the Gaussian of an ``ObservationProposal`` or the mixture of a ``PieceMixture``.
    """
    log_motion = motion_log_density(pose_prev, pose, control, params, motion_model)
    if isinstance(proposal, PieceMixture):
        log_obs = piece_mixture_log_density(pose, proposal)
    else:
        log_obs = gaussian_pose_log_density(pose, proposal)
    ratio = jnp.clip(ratio, 0.0, 1.0)
    log_mix = jnp.logaddexp(jnp.log1p(-ratio) + log_motion,
                            jnp.log(jnp.maximum(ratio, 1e-30)) + log_obs)
    log_mix = jnp.where(ratio >= 1.0, log_obs, log_mix)
    return jnp.where(proposal.has_match, log_motion - log_mix, 0.0)


def adaptive_ratio(likelihood_fast, likelihood_slow, params: Params):
    """phi = clip(phi_min + (phi_max - phi_min) * max(0, 1 - exp(fast - slow)))."""
    drop = jnp.maximum(0.0, 1.0 - jnp.exp(likelihood_fast - likelihood_slow))
    ratio = params.mixture_min + (params.mixture_max - params.mixture_min) * drop
    return jnp.clip(ratio, params.mixture_min, params.mixture_max)


def motion_draw_efficiency(delta, prior_cov, posterior_cov):
    """eta in [0, 1]: the expected effective-sample fraction of draws from a Gaussian motion
    prior p = N(0, A) weighed toward the proposal's posterior q = N(delta, B) (all (3,) /
    (3, 3)).

    eta = 1 / E_p[(q / p)^2] (Kong's ESS of importance weights w = q / p, whose mean is 1).
    Completing the square in int q^2 / p, with C^-1 = 2 B^-1 - A^-1 = B^-1 (2A - B) A^-1:

        log E_p[(q / p)^2] = log det A - (log det B + log det(2A - B)) / 2
                             + delta^T (2A - B)^-1 delta,

    a form that needs no inverse of the (often tiny) B. eta = 1 when B = A and delta = 0
    (the observations add nothing); eta -> 0 when B is much tighter than A or delta far out
    in A's tail: motion draws then rarely land where the observations put the pose. Where
    2A - B is not positive definite (B wider than 2A in some direction) E_p[(q / p)^2] is
    infinite and eta = 0.
    """
    chol_wide = cholesky3(2.0 * prior_cov - posterior_cov)
    white = solve_lower3(chol_wide, delta)
    log_second_moment = (log_det_from_cholesky3(cholesky3(prior_cov))
                         - 0.5 * log_det_from_cholesky3(cholesky3(posterior_cov))
                         - 0.5 * log_det_from_cholesky3(chol_wide) + jnp.sum(white**2))
    eta = jnp.exp(-jnp.maximum(log_second_moment, 0.0))
    return jnp.where(jnp.isfinite(log_second_moment), eta, 0.0)


def piece_draw_efficiency(gaussian: ObservationProposal, centre, prior_cov):
    """eta () of one prior piece N(centre (3,), prior_cov (3, 3)) toward its own FastSLAM 2.0
    Gaussian: ``motion_draw_efficiency`` with delta = mean - centre (heading wrapped) and
    B = L L^T."""
    delta = gaussian.mean - centre
    delta = delta.at[2].set(wrap_angle(delta[2]))
    return motion_draw_efficiency(delta, prior_cov, gaussian.chol @ gaussian.chol.T)


def mixture_draw_efficiency(piece_efficiency, log_prior, log_weights):
    """A lower bound on eta () for draws from the motion prior p = sum_j pi_j p_j weighed
    toward the piece mixture q = sum_j w_j q_j, q_j the Gaussian of prior piece j.

    By (sum_j a_j)^2 / sum_j b_j <= sum_j a_j^2 / b_j (Cauchy-Schwarz), q^2 / p <=
    sum_j (w_j q_j)^2 / (pi_j p_j), so E_p[(q / p)^2] <= sum_j (w_j^2 / pi_j) / eta_j and

        eta >= 1 / sum_j exp(2 log w_j - log pi_j - log eta_j),

    exact for one piece; a piece of weight 0 adds nothing. When the observations add nothing
    (q_j = p_j, w = pi) the bound is 1.

    Args: piece_efficiency (J,) eta_j (``piece_draw_efficiency``); log_prior (J,) log pi_j;
      log_weights (J,) log w_j (``PieceMixture.log_weights``).
    """
    terms = 2.0 * log_weights - log_prior - jnp.log(piece_efficiency)
    terms = jnp.where(jnp.isneginf(log_weights), -jnp.inf, terms)
    return jnp.minimum(jnp.exp(-jax.scipy.special.logsumexp(terms)), 1.0)


def coverage_ratio(efficiency, params: Params):
    """() phi = phi_min + (phi_max - phi_min) (1 - eta) from eta (): the observation proposal
    takes the share of draws that the motion prior would waste (``motion_draw_efficiency``)."""
    return params.mixture_min + (params.mixture_max - params.mixture_min) * (1.0 - efficiency)


def update_likelihood_averages(fast, slow, mean_log_likelihood, has_data, first_step, params):
    """Exponential averages of the per-observation log-likelihood (unchanged without data)."""
    new_fast = jnp.where(first_step, mean_log_likelihood,
                         fast + params.likelihood_rate_fast * (mean_log_likelihood - fast))
    new_slow = jnp.where(first_step, mean_log_likelihood,
                         slow + params.likelihood_rate_slow * (mean_log_likelihood - slow))
    return jnp.where(has_data, new_fast, fast), jnp.where(has_data, new_slow, slow)


__all__ = [
    "ObservationProposal",
    "PieceMixture",
    "piece_mixture",
    "piece_mixture_log_density",
    "adaptive_ratio",
    "coverage_ratio",
    "gaussian_pose_log_density",
    "mixture_log_correction",
    "mixture_draw_efficiency",
    "mixture_sample",
    "motion_draw_efficiency",
    "motion_pose_covariance",
    "observation_proposal",
    "piece_draw_efficiency",
    "predict_pose",
    "relinearised_proposal",
    "sample_gaussian_pose",
    "stack_proposals",
    "turn_pieces",
    "update_likelihood_averages",
]
