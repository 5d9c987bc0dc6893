"""Trajectory metrics of ONE run: final pose error, SE(2) alignment, ATE, RPE, pose NEES.

Alignments are SE(2) transforms written as a pose ``(x, y, theta)``: a point ``p`` maps to
``R(theta) p + (x, y)``. Padding is handled by boolean row masks; with no valid row every
function returns a finite value (documented on each), never NaN.
"""
from __future__ import annotations

import jax.numpy as jnp

from jaxslam.geometry import relative, wrap_angle


def final_pose_error(est_pose, true_pose):
    """Euclidean position error ||(x, y)_est - (x, y)_true|| [m]; poses (3,) or (2,); returns ()."""
    return jnp.hypot(est_pose[0] - true_pose[0], est_pose[1] - true_pose[1])


def heading_error(est_pose, true_pose):
    """Absolute wrapped heading error |wrap(theta_est - theta_true)| in [0, pi] [rad]; poses (3,)"""
    return jnp.abs(wrap_angle(est_pose[2] - true_pose[2]))


def transform_points(alignment, points):
    """Apply the SE(2) alignment pose (3,) to points (..., 2): R(theta) p + (x, y)."""
    cos_t, sin_t = jnp.cos(alignment[2]), jnp.sin(alignment[2])
    px, py = points[..., 0], points[..., 1]
    return jnp.stack(
        [cos_t * px - sin_t * py + alignment[0], sin_t * px + cos_t * py + alignment[1]], axis=-1
    )


def _row_mask(num_rows, valid):
    if valid is None:
        return jnp.ones((num_rows,), dtype=bool)
    return jnp.asarray(valid, dtype=bool)


def align_se2(est, truth, valid=None):
    """Closed-form least-squares SE(2) alignment of est onto truth (2D Kabsch/Umeyama, no scale).

    Minimises sum_i v_i ||R(theta) e_i + t - q_i||^2 over valid rows. With centred points
    e'_i = e_i - mean(e), q'_i = q_i - mean(q) and H = sum_i v_i e'_i q'_i^T (2, 2):

        theta = atan2(H01 - H10, H00 + H11),   t = mean(q) - R(theta) mean(e).

    Args:
      est: (T, 2+) estimated positions (only columns 0, 1 are used).
      truth: (T, 2+) true positions.
      valid: (T,) bool or None (all rows).
    Returns:
      (3,) alignment pose (x, y, theta). With no valid rows it is the identity (0, 0, 0); with
      one valid row (or all points coincident) theta = 0 and only the translation is fitted.
    """
    est, truth = jnp.asarray(est), jnp.asarray(truth)  # NumPy float64 -> JAX's float dtype
    weight = _row_mask(est.shape[0], valid).astype(est.dtype)
    count = jnp.maximum(weight.sum(), 1.0)
    est_xy, true_xy = est[:, :2], truth[:, :2]
    est_centre = (weight[:, None] * est_xy).sum(0) / count
    true_centre = (weight[:, None] * true_xy).sum(0) / count
    ex, ey = (est_xy - est_centre[None, :]).T
    qx, qy = (true_xy - true_centre[None, :]).T
    sin_part = (weight * (ex * qy - ey * qx)).sum()
    cos_part = (weight * (ex * qx + ey * qy)).sum()
    # atan2(0, 0) = 0 in XLA: degenerate inputs give theta = 0, never NaN.
    theta = jnp.arctan2(sin_part, cos_part)
    shift = true_centre - transform_points(jnp.stack([0.0, 0.0, theta]), est_centre)
    return jnp.stack([shift[0], shift[1], theta])


def ate_rmse(est, truth, valid=None, align: bool = False):
    """Absolute trajectory error: sqrt(mean_i ||p_est,i - p_true,i||^2) over valid rows [m].

    Args:
      est, truth: (T, 3) poses (or (T, 2) positions); only positions enter.
      valid: (T,) bool or None (all rows).
      align: static; if True est is first aligned onto truth by ``align_se2`` on valid rows.
    Returns:
      () RMSE; 0 when no row is valid.
    """
    mask = _row_mask(est.shape[0], valid)
    est_xy = est[:, :2]
    if align:
        est_xy = transform_points(align_se2(est, truth, mask), est_xy)
    diff = est_xy - truth[:, :2]
    sq_err = jnp.where(mask, diff[:, 0] ** 2 + diff[:, 1] ** 2, 0.0)
    return jnp.sqrt(sq_err.sum() / jnp.maximum(mask.sum(), 1))


def _rpe_pairs(num_poses: int, delta: int, all_pairs: bool):
    """Static index pairs (i, i + delta) as evo's ``filter_pairs_by_index`` builds them."""
    if all_pairs:
        first = jnp.arange(max(num_poses - delta, 0))
        return first, first + delta
    ids = jnp.arange(0, num_poses, delta)
    return ids[:-1], ids[1:]


def rpe(est, truth, delta: int = 1, valid=None, all_pairs: bool = False):
    """Relative pose error over a fixed step of ``delta`` frames, as evo's RPE (SE(2) here).

    For each pair (i, j = i + delta): E = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j) with Q truth, P estimate;
    translation error ||t(E)||, rotation error |theta(E)| (wrapped). Pairs as evo builds them:
    by default i = 0, delta, 2 delta, ... (consecutive, non-overlapping); ``all_pairs=True``
    takes every i with i + delta < T.

    Args:
      est, truth: (T, 3) poses.
      delta: static positive int, the step in frames.
      valid: (T,) bool or None; a pair counts only if both ends are valid.
      all_pairs: static, see above.
    Returns:
      (translation_rmse [m], rotation_rmse [rad]); both 0 when there is no valid pair.
    """
    if not isinstance(delta, int) or isinstance(delta, bool) or delta < 1:
        raise ValueError(f"rpe: delta={delta!r} is invalid; expected a positive int (frames)")
    mask = _row_mask(est.shape[0], valid)
    first, second = _rpe_pairs(est.shape[0], delta, all_pairs)
    error = relative(relative(truth[first], truth[second]), relative(est[first], est[second]))
    pair_valid = mask[first] & mask[second]
    count = jnp.maximum(pair_valid.sum(), 1)
    trans_sq = jnp.where(pair_valid, error[:, 0] ** 2 + error[:, 1] ** 2, 0.0)
    rot_sq = jnp.where(pair_valid, error[:, 2] ** 2, 0.0)
    return jnp.sqrt(trans_sq.sum() / count), jnp.sqrt(rot_sq.sum() / count)


def divergence_flag(final_pose_error_value, threshold):
    """True where the final pose error exceeds ``threshold`` [m] (or is NaN): ``~(e <= thr)``."""
    return ~(final_pose_error_value <= threshold)


# ---------------------------------------------------------------------------------------------
# Consistency


def pose_nees(est_mean, est_cov, truth):
    """Normalised estimation error squared e^T Sigma^-1 e, e = est - truth (heading wrapped).

    Args:
      est_mean: (3,); est_cov: (3, 3) symmetric positive definite; truth: (3,).
    Returns:
      (); for a consistent Gaussian estimate it is chi-square with 3 degrees of freedom.
      A singular covariance gives inf or NaN (no regularisation is added).
    """
    error = jnp.stack(
        [est_mean[0] - truth[0], est_mean[1] - truth[1], wrap_angle(est_mean[2] - truth[2])]
    )
    sym_cov = 0.5 * (est_cov + est_cov.T)
    return error @ jnp.linalg.solve(sym_cov, error)


def _normalised_weights(log_weight):
    """softmax(log_weight); uniform if every log-weight is -inf (never NaN)."""
    top = jnp.max(log_weight)
    top = jnp.where(jnp.isfinite(top), top, 0.0)
    weight = jnp.exp(log_weight - top)
    total = weight.sum()
    uniform = jnp.full_like(weight, 1.0 / weight.shape[0])
    return jnp.where(total > 0, weight / jnp.where(total > 0, total, 1.0), uniform)


def particle_pose_moments(pose, log_weight):
    """Weighted mean and covariance of particle poses, with a circular mean for the heading.

    w = softmax(log_weight); mean_xy = sum w p_xy; mean_theta = atan2(sum w sin, sum w cos);
    cov = sum w d d^T with d = (p_xy - mean_xy, wrap(theta - mean_theta)).

    Args:
      pose: (P, 3); log_weight: (P,) unnormalised (all -inf is read as uniform).
    Returns:
      (mean (3,), cov (3, 3)).
    """
    weight = _normalised_weights(log_weight)
    mean_xy = weight @ pose[:, :2]
    mean_theta = jnp.arctan2(weight @ jnp.sin(pose[:, 2]), weight @ jnp.cos(pose[:, 2]))
    deviation = jnp.concatenate(
        [pose[:, :2] - mean_xy[None, :], wrap_angle(pose[:, 2:3] - mean_theta)], axis=1
    )
    cov = (weight[:, None] * deviation).T @ deviation
    return jnp.concatenate([mean_xy, mean_theta[None]]), cov
