"""Every metric of ONE run in one call: ``summarize`` -> ``RunMetrics``, vmapped by studies."""
from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp

from jaxslam.metrics.gospa import gospa
from jaxslam.metrics.maps import _as_full_cov, _rotate_cov, map_metrics, map_nees
from jaxslam.metrics.trajectory import (align_se2, ate_rmse, divergence_flag, final_pose_error,
                                        heading_error, pose_nees, rpe, transform_points)


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
