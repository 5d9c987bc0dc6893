"""Map metrics of ONE run, counted as Geiser et al. 2023, Table 3 does, and the map NEES.

Each active landmark is matched to its nearest valid true tree within a threshold; a tree's
closest matched landmark represents it, the other landmarks matched to it are redundant, and a
landmark with no tree in reach is an orphan. Landmark covariances come full (M, 2, 2) or packed
(M, 3) = (sxx, sxy, syy) as ``jaxslam.types`` stores them.
"""
from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp

from jaxslam.metrics.trajectory import transform_points


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
    """(M, 2, 2) from (M, 2, 2) or the packed (M, 3) = (sxx, sxy, syy) of ``jaxslam.types``."""
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
