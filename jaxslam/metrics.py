"""Accuracy metrics for ONE run: pose errors, ATE/RPE, map error as Geiser et al. 2023, Table 3, NEES, GOSPA.

Every function is pure, jittable and has static output shapes; callers (``studies.py``) ``vmap``
over runs and sweep settings. Padding is handled by boolean masks, never by branches on values.
Empty inputs (no valid rows, no active landmarks, no true trees) give finite values, documented
on each function; none returns NaN for them.

Alignments are SE(2) transforms written as a pose ``(x, y, theta)``: a point ``p`` maps to
``R(theta) p + (x, y)``.
"""
from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import optax

from jaxslam.geometry import relative, wrap_angle


# ---------------------------------------------------------------------------------------------
# Poses and trajectories


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


# ---------------------------------------------------------------------------------------------
# Maps


class MapMetrics(NamedTuple):
    """Map accuracy counted as Geiser et al. 2023, Table 3 does (all scalars).

    map_error: mean over represented trees of the distance from the tree to the closest
      landmark matched to it [m]; 0 when no tree is represented (check num_trees_mapped).
    redundant: landmarks matched to a tree that another (closer) landmark already represents.
    orphan: active landmarks with no valid tree within the threshold.
    num_landmarks: active landmarks.
    num_trees_mapped: trees with at least one landmark matched to them.
    """

    map_error: jnp.ndarray
    redundant: jnp.ndarray
    orphan: jnp.ndarray
    num_landmarks: jnp.ndarray
    num_trees_mapped: jnp.ndarray


def _landmark_tree_distance(est_mean, true_centres, true_valid):
    """(M, N) Euclidean distances, +inf for invalid trees."""
    diff = est_mean[:, None, :2] - true_centres[None, :, :2]
    distance = jnp.hypot(diff[..., 0], diff[..., 1])
    return jnp.where(true_valid[None, :], distance, jnp.inf)


def _nearest_tree(distance, est_active, threshold):
    """(M,) nearest tree index within threshold (or -1) from (M, N) distances."""
    num_landmarks, num_trees = distance.shape
    if num_trees == 0:
        return jnp.full((num_landmarks,), -1, dtype=jnp.int32)
    nearest = jnp.argmin(distance, axis=1).astype(jnp.int32)
    within = jnp.min(distance, axis=1) <= threshold
    return jnp.where(est_active & within, nearest, -1)


def match_landmarks(est_mean, est_active, true_centres, true_valid, threshold):
    """Each active landmark to its nearest valid true tree within ``threshold`` [m], else -1.

    Several landmarks may match the same tree (they are counted as redundant by
    ``map_metrics``); ties in distance go to the lower tree index.

    Args:
      est_mean: (M, 2); est_active: (M,) bool; true_centres: (N, 2); true_valid: (N,) bool.
    Returns:
      (M,) int32 tree index or -1 (inactive or orphan).
    """
    distance = _landmark_tree_distance(est_mean, true_centres, jnp.asarray(true_valid, bool))
    return _nearest_tree(distance, jnp.asarray(est_active, bool), threshold)


def _closest_per_tree(distance, match):
    """(N,) distance of the closest landmark matched to each tree (+inf if none), and its index."""
    num_landmarks, num_trees = distance.shape
    if num_landmarks == 0:
        return jnp.full((num_trees,), jnp.inf, distance.dtype), jnp.zeros((num_trees,), jnp.int32)
    matched = match[:, None] == jnp.arange(num_trees)[None, :]
    masked = jnp.where(matched, distance, jnp.inf)
    return jnp.min(masked, axis=0, initial=jnp.inf), jnp.argmin(masked, axis=0)


def map_metrics(est_mean, est_active, true_centres, true_valid, threshold, alignment=None):
    """Final-map metrics of Geiser et al. 2023, Table 3 (see ``MapMetrics``).

    Args:
      est_mean: (M, 2) landmark means; est_active: (M,) bool.
      true_centres: (N, 2) tree centres; true_valid: (N,) bool.
      threshold: () match radius [m]; a landmark farther than this from every tree is an orphan.
      alignment: optional (3,) SE(2) pose applied to the landmarks first (e.g. ``align_se2`` of
        the trajectory).
    Returns:
      MapMetrics; with no active landmark or no tree: map_error 0 and counts 0 (orphans = all
      active landmarks when there is no tree).
    """
    est_active = jnp.asarray(est_active, bool)
    if alignment is not None:
        est_mean = transform_points(alignment, est_mean[:, :2])
    distance = _landmark_tree_distance(est_mean, true_centres, jnp.asarray(true_valid, bool))
    match = _nearest_tree(distance, est_active, threshold)
    closest, _ = _closest_per_tree(distance, match)
    represented = jnp.isfinite(closest)
    num_trees_mapped = represented.sum().astype(jnp.int32)
    num_matched = (match >= 0).sum().astype(jnp.int32)
    map_error = jnp.where(represented, closest, 0.0).sum() / jnp.maximum(num_trees_mapped, 1)
    return MapMetrics(
        map_error=map_error,
        redundant=num_matched - num_trees_mapped,
        orphan=(est_active & (match < 0)).sum().astype(jnp.int32),
        num_landmarks=est_active.sum().astype(jnp.int32),
        num_trees_mapped=num_trees_mapped,
    )


def _as_full_cov(landmark_cov):
    """(M, 2, 2) from (M, 2, 2) or the packed (M, 3) = (sxx, sxy, syy) of ``types.py``."""
    if landmark_cov.ndim == 2 and landmark_cov.shape[-1] == 3:
        sxx, sxy, syy = landmark_cov[:, 0], landmark_cov[:, 1], landmark_cov[:, 2]
        return jnp.stack([jnp.stack([sxx, sxy], -1), jnp.stack([sxy, syy], -1)], -2)
    if landmark_cov.ndim == 3 and landmark_cov.shape[-2:] == (2, 2):
        return landmark_cov
    raise ValueError(
        f"landmark covariance has shape {landmark_cov.shape}; expected (M, 2, 2) or packed (M, 3)"
    )


def _rotate_cov(theta, cov):
    """R(theta) Sigma R(theta)^T for (M, 2, 2) covariances."""
    cos_t, sin_t = jnp.cos(theta), jnp.sin(theta)
    rotation = jnp.stack([jnp.stack([cos_t, -sin_t]), jnp.stack([sin_t, cos_t])])
    return jnp.einsum("ij,mjk,lk->mil", rotation, cov, rotation)


def map_nees(est_mean, est_cov, est_active, true_centres, true_valid, threshold):
    """Mean landmark NEES over represented trees, using each tree's closest matched landmark.

    NEES_n = (l - t_n)^T Sigma_l^-1 (l - t_n), chi-square with 2 degrees of freedom when
    consistent. est_cov: (M, 2, 2) or packed (M, 3). Returns (); 0 when no tree is represented.
    """
    cov = _as_full_cov(est_cov)
    if est_mean.shape[0] == 0:
        return jnp.zeros((), est_mean.dtype)
    distance = _landmark_tree_distance(est_mean, true_centres, jnp.asarray(true_valid, bool))
    match = _nearest_tree(distance, jnp.asarray(est_active, bool), threshold)
    closest, landmark = _closest_per_tree(distance, match)
    represented = jnp.isfinite(closest)
    dx = est_mean[landmark, 0] - true_centres[:, 0]
    dy = est_mean[landmark, 1] - true_centres[:, 1]
    sxx, sxy, syy = cov[landmark, 0, 0], cov[landmark, 0, 1], cov[landmark, 1, 1]
    det = jnp.where(represented, sxx * syy - sxy * sxy, 1.0)
    nees = (syy * dx * dx - 2.0 * sxy * dx * dy + sxx * dy * dy) / det
    count = jnp.maximum(represented.sum(), 1)
    return jnp.where(represented, nees, 0.0).sum() / count


# ---------------------------------------------------------------------------------------------
# GOSPA


class GospaResult(NamedTuple):
    """GOSPA (alpha = 2) and its decomposition; distance^p = localisation + missed + false.

    distance: d_p^(c,2)(X, Y).
    localisation: sum over assigned pairs closer than c of d^p.
    missed: c^p / 2 times the number of unassigned true points.
    false: c^p / 2 times the number of unassigned estimated points.
    num_missed, num_false: those counts (int32); a pair at distance >= c counts as unassigned.
    """

    distance: jnp.ndarray
    localisation: jnp.ndarray
    missed: jnp.ndarray
    false: jnp.ndarray
    num_missed: jnp.ndarray
    num_false: jnp.ndarray


def _optimal_pairs(cost):
    """(rows, cols) of the optimal assignment of a (M, N) cost; static size min(M, N)."""
    return optax.assignment.hungarian_algorithm(cost)


def gospa(est, est_valid, truth, truth_valid, c, p=2.0, alpha=2.0):
    """GOSPA metric of Rahmathullah, Garcia-Fernandez and Svensson (2017), alpha = 2.

        d_p^(c,2)(X, Y) = ( min_gamma sum_{(i,j) in gamma} d(x_i, y_j)^p
                            + c^p / 2 (|X| + |Y| - 2 |gamma|) )^(1/p)

    over partial assignments gamma with d < c. Solved on the full (M, N) padded cost with the
    Hungarian algorithm: valid pairs cost min(d, c)^p, any pair touching padding costs c^p.
    Every assignment then costs sum_vv (min(d, c)^p - c^p) + const, so its optimum is the GOSPA
    optimum (padding pairs change nothing; valid pairs at d >= c are read as unassigned).

    Args:
      est: (M, 2); est_valid: (M,) bool; truth: (N, 2); truth_valid: (N,) bool.
      c: () cut-off distance > 0 [m]; p: () order >= 1; alpha: must be 2.
    Returns:
      GospaResult; two empty sets give 0; empty vs n points gives (n c^p / 2)^(1/p).
    """
    if alpha != 2:
        raise ValueError(f"gospa: alpha={alpha!r} is not supported; expected alpha=2")
    est_valid = jnp.asarray(est_valid, bool)
    truth_valid = jnp.asarray(truth_valid, bool)
    diff = est[:, None, :2] - truth[None, :, :2]
    distance = jnp.hypot(diff[..., 0], diff[..., 1])
    both_valid = est_valid[:, None] & truth_valid[None, :]
    dtype = jnp.result_type(est, truth)
    c = jnp.asarray(c, dtype)
    cut_cost = jnp.power(c, p)
    cost = jnp.where(both_valid, jnp.power(jnp.minimum(distance, c), p), cut_cost)
    rows, cols = _optimal_pairs(cost)
    close = both_valid[rows, cols] & (distance[rows, cols] < c)
    localisation = jnp.where(close, jnp.power(distance[rows, cols], p), 0.0).sum()
    num_close = close.sum().astype(jnp.int32)
    num_missed = truth_valid.sum().astype(jnp.int32) - num_close
    num_false = est_valid.sum().astype(jnp.int32) - num_close
    missed = 0.5 * cut_cost * num_missed.astype(dtype)
    false = 0.5 * cut_cost * num_false.astype(dtype)
    return GospaResult(
        distance=jnp.power(localisation + missed + false, 1.0 / p),
        localisation=localisation,
        missed=missed,
        false=false,
        num_missed=num_missed,
        num_false=num_false,
    )


# ---------------------------------------------------------------------------------------------
# Everything for one run


class RunMetrics(NamedTuple):
    """Every per-run metric (scalars). ``pose_nees`` and ``map_nees`` are None when the
    corresponding covariance was not given (None is an empty pytree node, so vmap keeps it)."""

    final_pose_error: jnp.ndarray
    final_heading_error: jnp.ndarray
    ate_rmse: jnp.ndarray
    ate_rmse_aligned: jnp.ndarray
    rpe_translation: jnp.ndarray
    rpe_rotation: jnp.ndarray
    map_error: jnp.ndarray
    redundant: jnp.ndarray
    orphan: jnp.ndarray
    num_landmarks: jnp.ndarray
    num_trees_mapped: jnp.ndarray
    gospa: jnp.ndarray
    gospa_localisation: jnp.ndarray
    gospa_missed: jnp.ndarray
    gospa_false: jnp.ndarray
    diverged: jnp.ndarray
    pose_nees: jnp.ndarray | None
    map_nees: jnp.ndarray | None


def summarize(
    est_poses,
    true_poses,
    landmark_mean,
    landmark_active,
    true_centres,
    true_valid,
    *,
    match_threshold,
    gospa_cutoff,
    divergence_threshold,
    landmark_cov=None,
    final_pose_cov=None,
    rpe_delta: int = 1,
    align_map: bool = False,
):
    """All per-run metrics of one run; the studies runner vmaps it over runs.

    Args:
      est_poses: (T+1, 3) estimated trajectory (e.g. ``estimate`` per step); true_poses: (T+1, 3).
      landmark_mean: (M, 2) final map; landmark_active: (M,) bool.
      true_centres: (N, 2) tree centres; true_valid: (N,) bool.
      match_threshold: () landmark-to-tree match radius [m] (Table 3 counts, map NEES).
      gospa_cutoff: () GOSPA cut-off c [m] (p = 2, alpha = 2).
      divergence_threshold: () final position error above which a run counts as diverged [m].
      landmark_cov: optional (M, 2, 2) or packed (M, 3) landmark covariances -> map_nees.
      final_pose_cov: optional (3, 3) covariance of the final pose estimate -> pose_nees.
      rpe_delta: static RPE step in frames.
      align_map: static; if True the map is aligned by the trajectory's SE(2) alignment first.
    Returns:
      RunMetrics.
    """
    final_error = final_pose_error(est_poses[-1], true_poses[-1])
    alignment = align_se2(est_poses, true_poses) if align_map else None
    map_result = map_metrics(
        landmark_mean, landmark_active, true_centres, true_valid, match_threshold, alignment
    )
    map_points, map_cov = landmark_mean, landmark_cov
    if alignment is not None:
        map_points = transform_points(alignment, landmark_mean)
        if landmark_cov is not None:
            map_cov = _rotate_cov(alignment[2], _as_full_cov(landmark_cov))
    gospa_result = gospa(map_points, landmark_active, true_centres, true_valid, gospa_cutoff)
    rpe_translation, rpe_rotation = rpe(est_poses, true_poses, rpe_delta)
    return RunMetrics(
        final_pose_error=final_error,
        final_heading_error=heading_error(est_poses[-1], true_poses[-1]),
        ate_rmse=ate_rmse(est_poses, true_poses),
        ate_rmse_aligned=ate_rmse(est_poses, true_poses, align=True),
        rpe_translation=rpe_translation,
        rpe_rotation=rpe_rotation,
        map_error=map_result.map_error,
        redundant=map_result.redundant,
        orphan=map_result.orphan,
        num_landmarks=map_result.num_landmarks,
        num_trees_mapped=map_result.num_trees_mapped,
        gospa=gospa_result.distance,
        gospa_localisation=gospa_result.localisation,
        gospa_missed=gospa_result.missed,
        gospa_false=gospa_result.false,
        diverged=divergence_flag(final_error, divergence_threshold),
        pose_nees=None if final_pose_cov is None
        else pose_nees(est_poses[-1], final_pose_cov, true_poses[-1]),
        map_nees=None if landmark_cov is None
        else map_nees(map_points, map_cov, landmark_active, true_centres, true_valid,
                      match_threshold),
    )
