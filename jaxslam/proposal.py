"""Pose proposals: the motion model, an observation-based proposal, and their mixture.

Seed 000 section 5.2: when the lidar is far more accurate than odometry, particles drawn from
the motion model alone can all miss the true pose. The observation proposal (FastSLAM 2.0,
Montemerlo et al. 2003) linearises the measurements of the matched landmarks around the motion
prediction x_hat and samples from

    Lambda = Sigma_u^-1 + sum_k Hx_k^T S_k^-1 Hx_k,     mu = x_hat + Lambda^-1 sum_k Hx_k^T S_k^-1 nu_k

where Sigma_u = J diag(sigma_odometry^2) J^T is the motion noise mapped to the pose,
Hx_k = dh/dx at x_hat, S_k the innovation covariance of landmark m(k), nu_k = z_k - h(x_hat, m).
Without any match it falls back to the motion model.

The mixture draws each particle from q_obs with probability phi and from p_motion otherwise,
and the importance weight is corrected by

    log w += log p_motion(x) - log((1 - phi) p_motion(x) + phi q_obs(x))

evaluated at the sampled pose, so the filter targets the same posterior for every phi.
Adaptive phi follows short- and long-term averages of the observation log-likelihood
(as in augmented MCL): phi = clip(phi_min + (phi_max - phi_min)(1 - exp(fast - slow))).

Shapes are for ONE particle: pose (3,), landmark arrays (M,), observations (K,).
"""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxslam.ekf import PredictedMeasurement
from jaxslam.geometry import LOG_2PI, wrap_angle
from jaxslam.motion import control_to_odometry, motion_log_density, odometry_std, predict_pose
from jaxslam.types import Params

_POSE_JITTER = 1e-8


class ObservationProposal(NamedTuple):
    """Gaussian proposal over the pose of one particle.

    mean: (3,); chol: (3, 3) lower Cholesky factor of the covariance;
    has_match: () bool, False means fall back to the motion model.
    """

    mean: jnp.ndarray
    chol: jnp.ndarray
    has_match: jnp.ndarray


def motion_pose_covariance(pose, control, params: Params, motion_model: str):
    """Sigma_u = J diag(sigma^2) J^T (3, 3): Eq. (1) noise mapped to the pose at x_hat.

    J = d pose' / d (rot1, trans, rot2) = [[-t sin h, cos h, 0], [t cos h, sin h, 0],
    [1, 0, 1]], h = theta + rot1.
    """
    odometry = control_to_odometry(control, params, motion_model)
    variance = odometry_std(odometry, params) ** 2
    heading = pose[2] + odometry[0]
    trans = odometry[1]
    zero = jnp.zeros_like(trans)
    jac = jnp.array([[-trans * jnp.sin(heading), jnp.cos(heading), zero],
                     [trans * jnp.cos(heading), jnp.sin(heading), zero],
                     [1.0 + zero, zero, 1.0 + zero]])
    return (jac * variance[None, :]) @ jac.T + _POSE_JITTER * jnp.eye(3, dtype=pose.dtype)


def observation_proposal(predicted_pose, pose_cov, z, match, predicted: PredictedMeasurement):
    """FastSLAM 2.0 Gaussian (module docstring) from the matched observations.

    Args:
      predicted_pose: (3,) x_hat; pose_cov: (3, 3) Sigma_u; z: (K, 2);
      match: (K,) int32 row of ``predicted`` matched by each observation, or -1;
      predicted: at x_hat, (N,) fields (the particle's landmarks, or a window of them).
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
    info_vec = jnp.einsum("kai,kab,kb->i", hx, s_inv, nu)
    precision = jnp.linalg.inv(pose_cov) + info_obs
    cov = jnp.linalg.inv(precision)
    cov = 0.5 * (cov + cov.T)
    mean = predicted_pose + cov @ info_vec
    mean = mean.at[2].set(wrap_angle(mean[2]))
    return ObservationProposal(mean, jnp.linalg.cholesky(cov), jnp.any(matched))


def gaussian_pose_log_density(pose, proposal: ObservationProposal):
    """log N(pose; mean, L L^T) with the heading difference wrapped. (3,) -> ()."""
    diff = pose - proposal.mean
    diff = diff.at[2].set(wrap_angle(diff[2]))
    white = jax.scipy.linalg.solve_triangular(proposal.chol, diff, lower=True)
    log_det = 2.0 * jnp.sum(jnp.log(jnp.diag(proposal.chol)))
    return -0.5 * jnp.sum(white**2) - 0.5 * log_det - 1.5 * LOG_2PI


def sample_gaussian_pose(key, proposal: ObservationProposal):
    """x ~ N(mean, L L^T), heading wrapped. Returns (3,)."""
    draw = proposal.mean + proposal.chol @ jax.random.normal(key, (3,), proposal.mean.dtype)
    return draw.at[2].set(wrap_angle(draw[2]))


def mixture_sample(key, motion_sample, proposal: ObservationProposal, ratio):
    """Pick q_obs with probability ``ratio`` (and a match), else the motion sample.

    Returns (pose (3,), used_observation () bool).
    """
    key_choice, key_draw = jax.random.split(key)
    use_obs = (jax.random.uniform(key_choice, (), motion_sample.dtype) < ratio)
    use_obs = use_obs & proposal.has_match
    pose = jnp.where(use_obs, sample_gaussian_pose(key_draw, proposal), motion_sample)
    return pose, use_obs


def mixture_log_correction(pose_prev, pose, control, params: Params, motion_model: str,
                           proposal: ObservationProposal, ratio):
    """log p_motion(x) - log((1 - phi) p_motion(x) + phi q_obs(x)); 0 without a match."""
    log_motion = motion_log_density(pose_prev, pose, control, params, motion_model)
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


def update_likelihood_averages(fast, slow, mean_log_likelihood, has_data, first_step, params):
    """Exponential averages of the per-observation log-likelihood (unchanged without data)."""
    new_fast = jnp.where(first_step, mean_log_likelihood,
                         fast + params.likelihood_rate_fast * (mean_log_likelihood - fast))
    new_slow = jnp.where(first_step, mean_log_likelihood,
                         slow + params.likelihood_rate_slow * (mean_log_likelihood - slow))
    return jnp.where(has_data, new_fast, fast), jnp.where(has_data, new_slow, slow)


__all__ = [
    "ObservationProposal",
    "adaptive_ratio",
    "gaussian_pose_log_density",
    "mixture_log_correction",
    "mixture_sample",
    "motion_pose_covariance",
    "observation_proposal",
    "predict_pose",
    "sample_gaussian_pose",
    "update_likelihood_averages",
]
