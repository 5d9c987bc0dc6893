"""Accuracy metrics for ONE run: pose errors, ATE/RPE, map error as Geiser et al. 2023, Table 3, NEES, GOSPA.

Every function is pure, jittable and has static output shapes; callers (``jaxslam.studies``)
``vmap`` over runs and sweep settings. Padding is handled by boolean masks, never by branches on
values. Empty inputs (no valid rows, no active landmarks, no true trees) give finite values,
documented on each function; none returns NaN for them.

  ``trajectory``  final pose and heading error, SE(2) alignment, ATE, RPE, pose NEES.
  ``maps``        landmark-to-tree matching, map error, redundant and orphan counts, map NEES.
  ``gospa``       the GOSPA distance of the map to the true trees.
  ``run``         ``summarize``: all of them for one run (``RunMetrics``).
"""
from jaxslam.metrics.gospa import GospaResult, gospa
from jaxslam.metrics.maps import MapMetrics, map_metrics, map_nees, match_landmarks
from jaxslam.metrics.run import RunMetrics, summarize
from jaxslam.metrics.trajectory import (align_se2, ate_rmse, divergence_flag, final_pose_error,
                                        heading_error, particle_pose_moments, pose_nees, rpe,
                                        transform_points)

__all__ = [
    "GospaResult", "MapMetrics", "RunMetrics", "align_se2", "ate_rmse", "divergence_flag",
    "final_pose_error", "gospa", "heading_error", "map_metrics", "map_nees", "match_landmarks",
    "particle_pose_moments", "pose_nees", "rpe", "summarize", "transform_points",
]
