"""Per-landmark EKF in closed-form 2x2 arithmetic: prediction, initialisation, update, weight.

Symmetric 2x2 matrices are carried as their components ``(a, b, c)`` = [[a, b], [b, c]];
general 2x2 Jacobians as ``(h00, h01, h10, h11)``. Nothing here calls ``jnp.linalg``: on this
CPU the written-out form runs 4-8x faster.

Model (Geiser et al. 2023, section 4, Table 2): z = h(x, m) + v, h = (range, bearing),
v ~ N(0, R(r)), R(r) = diag(sigma_r(r)^2, sigma_b(r)^2), sigma = max(c_dist r + c_const, floor).

Shapes: ``pose`` (3,) for one particle; landmark arrays (M,); observation arrays (K,); pair
arrays (K, M). Functions are vmapped over particles by the filter.
"""
from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp

from jaxslam.geometry import LOG_2PI, range_bearing_jacobian_point, wrap_angle
from jaxslam.types import Params


class PredictedMeasurement(NamedTuple):
    """Predicted measurement of every landmark slot of one particle, each field (M,).

    range, bearing: h(pose, landmark). h00..h11: Jacobian of h w.r.t. the landmark.
    s_rr, s_rb, s_bb: innovation covariance S = H Sigma H^T + R(range).
    i_rr, i_rb, i_bb: S^-1. log_det: log det S.
    noise_rr, noise_bb: R(range), the measurement noise variances inside S (kept for the
      update's Joseph form, so they are computed once per landmark).
    """

    range: jnp.ndarray
    bearing: jnp.ndarray
    h00: jnp.ndarray
    h01: jnp.ndarray
    h10: jnp.ndarray
    h11: jnp.ndarray
    s_rr: jnp.ndarray
    s_rb: jnp.ndarray
    s_bb: jnp.ndarray
    i_rr: jnp.ndarray
    i_rb: jnp.ndarray
    i_bb: jnp.ndarray
    log_det: jnp.ndarray
    noise_rr: jnp.ndarray
    noise_bb: jnp.ndarray


def sensor_std(distance, params: Params):
    """(sigma_range, sigma_bearing) of the sensor at ``distance`` (any shape), Geiser et al.
    2023, Table 2: sigma = c_dist * distance + c_const, without the filter's floors (the noise
    a simulator draws)."""
    return (params.range_noise[0] * distance + params.range_noise[1],
            params.bearing_noise[0] * distance + params.bearing_noise[1])


def measurement_std(distance, params: Params):
    """(sigma_range, sigma_bearing) at ``distance`` (any shape): ``sensor_std`` floored at
    ``range_std_floor`` and ``bearing_std_floor`` (the noise the filter assumes)."""
    sigma_range, sigma_bearing = sensor_std(distance, params)
    return (jnp.maximum(sigma_range, params.range_std_floor),
            jnp.maximum(sigma_bearing, params.bearing_std_floor))


def sandwich(h00, h01, h10, h11, a, b, c):
    """H [[a, b], [b, c]] H^T as components (rr, rb, bb)."""
    t00 = h00 * a + h01 * b
    t01 = h00 * b + h01 * c
    t10 = h10 * a + h11 * b
    t11 = h10 * b + h11 * c
    return t00 * h00 + t01 * h01, t00 * h10 + t01 * h11, t10 * h10 + t11 * h11


def inverse_symmetric(a, b, c):
    """Inverse and log-determinant of [[a, b], [b, c]] (positive definite)."""
    det = a * c - b * b
    return c / det, -b / det, a / det, jnp.log(det)


def predict_measurements(pose, landmark_mean, landmark_cov, params: Params):
    """h, its landmark Jacobian and the innovation covariance for every slot.

    Args:
      pose: (3,); landmark_mean: (M, 2); landmark_cov: (M, 3) components.
    Returns:
      ``PredictedMeasurement`` with (M,) fields. The bearing is computed once per landmark
      (never per observation-landmark pair).
    """
    dx = landmark_mean[:, 0] - pose[0]
    dy = landmark_mean[:, 1] - pose[1]
    range_ = jnp.hypot(dx, dy)
    bearing = wrap_angle(jnp.arctan2(dy, dx) - pose[2])
    h00, h01, h10, h11 = range_bearing_jacobian_point(dx, dy)
    s_rr, s_rb, s_bb = sandwich(h00, h01, h10, h11,
                                landmark_cov[:, 0], landmark_cov[:, 1], landmark_cov[:, 2])
    sigma_range, sigma_bearing = measurement_std(range_, params)
    noise_rr, noise_bb = sigma_range**2, sigma_bearing**2
    s_rr = s_rr + noise_rr
    s_bb = s_bb + noise_bb
    i_rr, i_rb, i_bb, log_det = inverse_symmetric(s_rr, s_rb, s_bb)
    return PredictedMeasurement(range_, bearing, h00, h01, h10, h11,
                                s_rr, s_rb, s_bb, i_rr, i_rb, i_bb, log_det, noise_rr, noise_bb)


def pose_share_terms(h00, h01, h10, h11, pose_cov):
    """The terms of Hx Sigma_u Hx^T (``add_pose_uncertainty``) for the landmark Jacobian H
    (h.. any shape) and the pose covariance Sigma_u = [[Sxy, c], [c^T, s_tt]] (3, 3):
    ((rr, rb, bb) of H Sxy H^T, (v0, v1) = H c). The share is
    [[rr, rb + v0], [rb + v0, bb + 2 v1 + s_tt]]; callers add it in their own order."""
    xy = sandwich(h00, h01, h10, h11, pose_cov[0, 0], pose_cov[0, 1], pose_cov[1, 1])
    v0 = h00 * pose_cov[0, 2] + h01 * pose_cov[1, 2]
    v1 = h10 * pose_cov[0, 2] + h11 * pose_cov[1, 2]
    return xy, (v0, v1)


def add_pose_uncertainty(predicted: PredictedMeasurement, pose_cov):
    """Innovation covariance with the pose uncertainty added (FastSLAM 2.0 association).

    Matching at the motion prediction x_hat, the innovation of landmark m has covariance
    Z = Hx Sigma_u Hx^T + H Sigma_m H^T + R, where Hx = dh/dpose = [-H, (0, -1)^T]
    (H = dh/dm, the landmark Jacobian). With Sigma_u = [[Sxy, c], [c^T, s_tt]] and
    v = H c, Hx Sigma_u Hx^T = H Sxy H^T + [[0, v0], [v0, 2 v1 + s_tt]].

    Args:
      predicted: (M,) fields at x_hat; pose_cov: (3, 3) Sigma_u.
    Returns:
      ``PredictedMeasurement`` whose s_*, i_* and log_det describe Z (R and H unchanged).
    """
    p = predicted
    (xy_rr, xy_rb, xy_bb), (v0, v1) = pose_share_terms(p.h00, p.h01, p.h10, p.h11, pose_cov)
    s_rr = p.s_rr + xy_rr
    s_rb = p.s_rb + xy_rb + v0
    s_bb = p.s_bb + xy_bb + 2.0 * v1 + pose_cov[2, 2]
    i_rr, i_rb, i_bb, log_det = inverse_symmetric(s_rr, s_rb, s_bb)
    return p._replace(s_rr=s_rr, s_rb=s_rb, s_bb=s_bb, i_rr=i_rr, i_rb=i_rb, i_bb=i_bb,
                      log_det=log_det)


def innovation_mahalanobis_sq(d_range, d_bearing, i_rr, i_rb, i_bb):
    """Squared Mahalanobis distance nu^T S^-1 nu of innovations nu = (d_range, d_bearing)
    (bearing already wrapped) with S^-1 = [[i_rr, i_rb], [i_rb, i_bb]]; all arguments
    broadcast together, elementwise."""
    return (d_range * d_range * i_rr + 2.0 * d_range * d_bearing * i_rb
            + d_bearing * d_bearing * i_bb)


def mahalanobis_sq(z, predicted: PredictedMeasurement):
    """Squared Mahalanobis distance d2[k, m] of observation k under landmark m's prediction.

    d2 = nu^T S^-1 nu, nu = (z_r - r_m, wrap(z_b - b_m)). Args: z (K, 2). Returns (K, M).
    """
    d_range = z[:, 0:1] - predicted.range[None, :]
    d_bearing = wrap_angle(z[:, 1:2] - predicted.bearing[None, :])
    return innovation_mahalanobis_sq(d_range, d_bearing, predicted.i_rr[None, :],
                                     predicted.i_rb[None, :], predicted.i_bb[None, :])


def radius_distance_sq(obs_radius, landmark_radius, landmark_count, params: Params):
    """Squared standardised difference of a measured trunk radius and a landmark's radius.

    d_r2 = (r_obs - r_bar)^2 / (sigma_r^2 (1 + 1/n)), sigma_r = ``params.radius_noise``:
    r_bar is the landmark's running mean of n measured radii, each with std sigma_r, so the
    difference has variance sigma_r^2 + sigma_r^2 / n. It is 0 (the radius says nothing) when
    sigma_r <= 0 (the default: radii unused) or either radius is unknown (<= 0). The filter adds
    it to the (range, bearing) Mahalanobis distance, so the gate and the weight see a third
    degree of freedom: a trunk of the wrong thickness is matched only if the position agrees
    well enough to pay for it. The weight gets exp(-d_r2 / 2) with no normaliser, a factor of 1
    at agreement: a radius can only count against a match, never for it. (The normaliser
    -log(1 + 1/n) / 2, up to 0.35 at n = 1, is left out on purpose: it would make every match
    of a young landmark cost more than its position alone, whatever its radius.)

    Args (broadcast together): obs_radius, landmark_radius [m]; landmark_count (int) radii
    averaged into the landmark's (``Particles.radius_count``). Pairs: obs (K, 1) with
    landmarks (1, M) -> (K, M); matched rows: (K,) with (K,) -> (K,).
    """
    sigma = params.radius_noise
    count = jnp.maximum(landmark_count, 1).astype(sigma.dtype)
    variance = jnp.maximum(sigma * sigma, 1e-30) * (1.0 + 1.0 / count)
    diff = obs_radius - landmark_radius
    known = (sigma > 0) & (obs_radius > 0) & (landmark_radius > 0)
    return jnp.where(known, diff * diff / variance, 0.0)


def gaussian_log_likelihood(mahalanobis, log_det):
    """log N(nu; 0, S) = -d2/2 - log det S / 2 - log(2 pi) for 2-vectors."""
    return -0.5 * mahalanobis - 0.5 * log_det - LOG_2PI


def unexplained_log_likelihood(z_range, params: Params):
    """Log-likelihood credited to an observation no landmark explains, (K,).

    The density of a match exactly at the gate under the observation's own noise R(z_r),
    plus ``params.new_landmark_log_offset``.
    """
    sigma_range, sigma_bearing = measurement_std(z_range, params)
    log_det = 2.0 * (jnp.log(sigma_range) + jnp.log(sigma_bearing))
    return (gaussian_log_likelihood(params.association_gate, log_det)
            + params.new_landmark_log_offset)


def initialize_landmarks(pose, z, params: Params):
    """Landmarks from observations through the inverse model, one per row.

    m = t + r (cos(theta + b), sin(theta + b)); Sigma = G R G^T with
    G = d m / d z = [[cos a, -r sin a], [sin a, r cos a]], a = theta + b.

    Args:
      pose: (3,); z: (K, 2). Returns mean (K, 2) and covariance components (K, 3).
    """
    range_, angle = z[:, 0], pose[2] + z[:, 1]
    cos_a, sin_a = jnp.cos(angle), jnp.sin(angle)
    mean = jnp.stack([pose[0] + range_ * cos_a, pose[1] + range_ * sin_a], axis=-1)
    sigma_range, sigma_bearing = measurement_std(range_, params)
    var_range, var_bearing = sigma_range**2, sigma_bearing**2
    lateral_sq = range_ * range_ * var_bearing
    cov = jnp.stack(
        [cos_a * cos_a * var_range + sin_a * sin_a * lateral_sq,
         cos_a * sin_a * (var_range - lateral_sq),
         sin_a * sin_a * var_range + cos_a * cos_a * lateral_sq],
        axis=-1,
    )
    return mean, cov


def update_landmarks(landmark_mean, landmark_cov, predicted: PredictedMeasurement, z, params):
    """EKF update of every slot with its assigned observation (the caller masks the result).

    K = Sigma H^T S^-1, m' = m + K nu, Sigma' = (I - K H) Sigma (I - K H)^T + K R K^T
    (Joseph form: stays symmetric positive definite in float32 after 10^5 updates).

    Args:
      landmark_mean: (M, 2); landmark_cov: (M, 3); predicted: (M,) fields; z: (M, 2) the
        observation assigned to each slot (any finite value for unassigned slots).
    Returns:
      mean (M, 2), covariance components (M, 3).
    """
    del params  # R(range) comes precomputed in ``predicted``; kept for a stable signature
    p = predicted
    a, b, c = landmark_cov[:, 0], landmark_cov[:, 1], landmark_cov[:, 2]
    # Sigma H^T (2x2): rows = landmark axes, columns = (range, bearing).
    pht00 = a * p.h00 + b * p.h01
    pht01 = a * p.h10 + b * p.h11
    pht10 = b * p.h00 + c * p.h01
    pht11 = b * p.h10 + c * p.h11
    gain00 = pht00 * p.i_rr + pht01 * p.i_rb
    gain01 = pht00 * p.i_rb + pht01 * p.i_bb
    gain10 = pht10 * p.i_rr + pht11 * p.i_rb
    gain11 = pht10 * p.i_rb + pht11 * p.i_bb
    nu_range = z[:, 0] - p.range
    nu_bearing = wrap_angle(z[:, 1] - p.bearing)
    mean = landmark_mean + jnp.stack(
        [gain00 * nu_range + gain01 * nu_bearing, gain10 * nu_range + gain11 * nu_bearing],
        axis=-1)
    # Joseph form with A = I - K H.
    a00 = 1.0 - (gain00 * p.h00 + gain01 * p.h10)
    a01 = -(gain00 * p.h01 + gain01 * p.h11)
    a10 = -(gain10 * p.h00 + gain11 * p.h10)
    a11 = 1.0 - (gain10 * p.h01 + gain11 * p.h11)
    j00, j01, j11 = sandwich(a00, a01, a10, a11, a, b, c)
    r00, r01, r11 = sandwich(gain00, gain01, gain10, gain11,
                             p.noise_rr, jnp.zeros_like(a), p.noise_bb)
    cov = jnp.stack([j00 + r00, j01 + r01, j11 + r11], axis=-1)
    return mean, cov


def expand_covariance(components):
    """(..., 3) components (a, b, c) -> (..., 2, 2) matrices."""
    a, b, c = components[..., 0], components[..., 1], components[..., 2]
    return jnp.stack([jnp.stack([a, b], -1), jnp.stack([b, c], -1)], -2)
