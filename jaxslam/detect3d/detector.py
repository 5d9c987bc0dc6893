"""The 3D trunk detector: ``fit_trunks_3d`` (every fit and rejection) and ``detect_trunks_3d``
(the trunks as ``Observations``). Steps 1, 3 and 8 of the module docstring of
``jaxslam.detect3d``; the other steps are its sibling modules. N points, C cluster slots,
K output rows.
"""
from __future__ import annotations

import functools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxslam.detect3d.clusters import cluster_points_2d, gather_clusters
from jaxslam.detect3d.cylinders import fit_cylinders
from jaxslam.detect3d.grid import grid_cells, grid_size
from jaxslam.detect3d.ground import Ground3D, estimate_ground, plane_height
from jaxslam.detect3d.measure import CylinderFits, measure_cylinders
from jaxslam.types import Observations

class Trunks3D(NamedTuple):
    """Trunks of one cloud: K padded rows (the nearest accepted first) and the diagnostics.

    Attributes:
      observations: ``Observations`` with z (K, 2) = horizontal range [m] and bearing [rad] of
        the breast-height point, radius (K,) = DBH / 2 [m], valid (K,), landmark_id (K,) = -1.
      position, base, axis: (K, 3) as in ``CylinderFits``; lean, radius, inlier_ratio: (K,);
        num_points, num_inliers: (K,) int32; cluster: (K,) int32 slot in ``clusters``, -1 on
        padded rows (padded rows hold zeros).
      clusters: ``CylinderFits`` of the C cluster slots.
      ground: ``Ground3D``.
      num_clusters: () int32 clusters with at least ``min_points`` points, including the ones
        past ``max_clusters`` that were dropped.
    """

    observations: Observations
    position: jnp.ndarray
    base: jnp.ndarray
    axis: jnp.ndarray
    lean: jnp.ndarray
    radius: jnp.ndarray
    inlier_ratio: jnp.ndarray
    num_points: jnp.ndarray
    num_inliers: jnp.ndarray
    cluster: jnp.ndarray
    clusters: CylinderFits
    ground: Ground3D
    num_clusters: jnp.ndarray


def fit_trunks_3d(points, valid=None, *, key, max_obs: int = 16, max_clusters: int = 32,
                  max_range: float = 20.0, min_range: float = 0.1, ground_cell: float = 2.0,
                  ground_quantile: float = 0.1, ground_bandwidth: float = 3.0,
                  ground_tol: float = 0.15, ground_iterations: int = 4,
                  band_min: float = 0.5, band_max: float = 3.0, breast_height: float = 1.3,
                  cluster_cell: float = 0.15, min_points: int = 10, cluster_points: int = 512,
                  num_hypotheses: int = 64, ring_thickness: float = 0.1,
                  inlier_tol: float = 0.03, lm_iterations: int = 10, refine_rounds: int = 2,
                  min_radius: float = 0.03, max_radius: float = 0.5,
                  max_lean: float = math.radians(20.0), min_inlier_ratio: float = 0.6,
                  max_width: float = 1.5, min_flatness: float = 0.02) -> Trunks3D:
    """Trunks in a 3D point cloud with every fit and rejection (``jaxslam.detect3d`` docstring).

    Args:
      points: (N, 3) sensor frame, z up [m]; or (B, N, 3) for B clouds (vmapped inside).
      valid: (N,) or (B, N) bool, default all True; padded points are False.
      key: PRNG key (RANSAC draws); with a batch, one key (split into B) or B keys.
      max_obs: K, output rows. max_clusters: C, clusters fitted (the nearest; others dropped).
      max_range: half-width of the square covered by the grids [m] (static: fixes G).
      ground_cell, cluster_cell: grid cells [m] (static). cluster_points: P (static).
      num_hypotheses: H >= 2 (static). ground_iterations, lm_iterations, refine_rounds: static.
      Other arguments: the thresholds of the ``jaxslam.detect3d`` docstring (traced: no
        recompile per value), in metres and radians; min_points counts points.
    Returns:
      ``Trunks3D`` (with a leading B axis on every leaf for a batch).
    """
    points = jnp.asarray(points)
    if not jnp.issubdtype(points.dtype, jnp.floating):
        points = points.astype(jnp.float32)
    if points.ndim not in (2, 3) or points.shape[-1] != 3:
        raise ValueError(f"fit_trunks_3d expects points (N, 3) or (B, N, 3); got {points.shape}")
    if points.shape[-2] < 1:
        raise ValueError("fit_trunks_3d needs at least one point slot (N >= 1); pad with "
                         "valid=False for an empty cloud")
    valid = (jnp.ones(points.shape[:-1], bool) if valid is None else jnp.asarray(valid, bool))
    if valid.shape != points.shape[:-1]:
        raise ValueError(f"fit_trunks_3d valid must have shape {points.shape[:-1]}; "
                         f"got {valid.shape}")
    for name, value, low in (("max_obs", max_obs, 1), ("max_clusters", max_clusters, 1),
                             ("cluster_points", cluster_points, 3),
                             ("num_hypotheses", num_hypotheses, 2),
                             ("ground_iterations", ground_iterations, 1),
                             ("lm_iterations", lm_iterations, 0),
                             ("refine_rounds", refine_rounds, 0)):
        if not isinstance(value, int) or isinstance(value, bool) or value < low:
            raise ValueError(f"fit_trunks_3d {name}={value!r}; expected an integer >= {low}")
    for name, value in (("max_range", max_range), ("ground_cell", ground_cell),
                        ("cluster_cell", cluster_cell)):
        if not (isinstance(value, (int, float)) and value > 0 and math.isfinite(value)):
            raise ValueError(f"fit_trunks_3d {name}={value!r}; expected a positive number "
                             "(static: it fixes a grid's shape)")
    if key is None:
        raise ValueError("fit_trunks_3d needs a PRNG key for its RANSAC draws: pass key=...")
    statics = dict(max_obs=max_obs, max_clusters=max_clusters, max_range=float(max_range),
                   ground_cell=float(ground_cell), cluster_cell=float(cluster_cell),
                   cluster_points=cluster_points, num_hypotheses=num_hypotheses,
                   ground_iterations=ground_iterations, lm_iterations=lm_iterations,
                   refine_rounds=refine_rounds)
    thresholds = dict(min_range=min_range, ground_quantile=ground_quantile,
                      ground_bandwidth=ground_bandwidth, ground_tol=ground_tol,
                      band_min=band_min, band_max=band_max, breast_height=breast_height,
                      min_points=min_points, ring_thickness=ring_thickness,
                      inlier_tol=inlier_tol, min_radius=min_radius, max_radius=max_radius,
                      max_lean=max_lean, min_inlier_ratio=min_inlier_ratio,
                      max_width=max_width, min_flatness=min_flatness)
    thresholds = {k: jnp.asarray(v, points.dtype) for k, v in thresholds.items()}
    if points.ndim == 2:
        return _fit(points, valid, key, thresholds, **statics)
    if points.shape[0] == 0:  # an empty batch: the shapes of one cloud's result, nothing run
        single = jax.eval_shape(lambda p, v: _fit(p, v, jax.random.PRNGKey(0), thresholds,
                                                  **statics),
                                jax.ShapeDtypeStruct(points.shape[1:], points.dtype),
                                jax.ShapeDtypeStruct(valid.shape[1:], bool))
        return jax.tree.map(lambda s: jnp.zeros((0,) + s.shape, s.dtype), single)
    keys = _batch_keys(key, points.shape[0])
    return jax.vmap(lambda p, v, k: _fit(p, v, k, thresholds, **statics))(points, valid, keys)


def detect_trunks_3d(points, valid=None, *, key, **kwargs) -> Observations:
    """Trunks in a 3D point cloud as padded ``Observations`` (``fit_trunks_3d(...).observations``).

    Args:
      points: (N, 3) or (B, N, 3) sensor frame, z up [m]. valid: (N,) or (B, N) bool.
      key: PRNG key. kwargs: any setting of ``fit_trunks_3d``.
    Returns:
      ``Observations``: z (K, 2) horizontal range and bearing of each trunk at breast height,
      radius (K,) = DBH / 2, valid (K,), landmark_id (K,) = -1 (leading B axis for a batch).
    """
    return fit_trunks_3d(points, valid, key=key, **kwargs).observations


def _batch_keys(key, batch: int):
    """B keys: ``key`` itself when it is already a batch of B keys, else split(key, B)."""
    key = jnp.asarray(key) if not isinstance(key, jax.Array) else key
    typed = jnp.issubdtype(key.dtype, jax.dtypes.prng_key)
    if key.ndim == (1 if typed else 2):
        if key.shape[0] != batch:
            raise ValueError(f"fit_trunks_3d got {key.shape[0]} keys for {batch} clouds")
        return key
    return jax.random.split(key, batch)


@functools.partial(jax.jit, static_argnames=(
    "max_obs", "max_clusters", "max_range", "ground_cell", "cluster_cell", "cluster_points",
    "num_hypotheses", "ground_iterations", "lm_iterations", "refine_rounds"))
def _fit(points, valid, key, thresholds, *, max_obs, max_clusters, max_range, ground_cell,
         cluster_cell, cluster_points, num_hypotheses, ground_iterations, lm_iterations,
         refine_rounds) -> Trunks3D:
    """Jitted body of ``fit_trunks_3d`` for one cloud: points (N, 3), valid (N,)."""
    t = thresholds
    finite = jnp.all(jnp.isfinite(points), -1)
    points = jnp.where(finite[:, None], points, 0.0)
    dist = jnp.sqrt(jnp.sum(points * points, -1))
    usable = valid & finite & (dist > t["min_range"])

    # Ground and band.
    ground_size = grid_size(max_range, ground_cell)
    cluster_size = grid_size(max_range, cluster_cell)
    ground = estimate_ground(points, usable, cell=ground_cell, size=ground_size,
                             quantile=t["ground_quantile"], bandwidth=t["ground_bandwidth"],
                             tol=t["ground_tol"], iterations=ground_iterations,
                             object_height=t["band_max"], object_cell=cluster_cell,
                             object_size=cluster_size)
    index, inside = grid_cells(points[:, :2], ground_cell, ground_size)
    height = points[:, 2] - plane_height(ground.planes, ground.centres, index, points[:, :2])
    band = usable & inside & (height >= t["band_min"]) & (height <= t["band_max"])

    # Clusters.
    slot, num_clusters = cluster_points_2d(
        points[:, :2], band, cell=cluster_cell, size=cluster_size,
        max_clusters=max_clusters, min_points=t["min_points"])
    pts, h, mask, count = gather_clusters(points, height, slot, max_clusters, cluster_points)

    # Cylinders.
    theta, z_ref, found = fit_cylinders(
        key, pts, h, mask, num_hypotheses=num_hypotheses, ring_thickness=t["ring_thickness"],
        inlier_tol=t["inlier_tol"], max_radius=t["max_radius"], max_lean=t["max_lean"],
        lm_iterations=lm_iterations, refine_rounds=refine_rounds)
    fits, horizontal = measure_cylinders(theta, z_ref, found, pts, mask, count, ground, t,
                                         ground_cell=ground_cell, ground_size=ground_size,
                                         max_range=max_range)
    return _pack(fits, horizontal, max_obs, ground, num_clusters)


def _pack(fits: CylinderFits, horizontal, max_obs: int, ground: Ground3D,
          num_clusters) -> Trunks3D:
    """The ``max_obs`` nearest accepted fits as ``Trunks3D`` rows (padded with zeros)."""
    c = fits.accepted.shape[0]
    k = min(max_obs, c)
    neg, pick = jax.lax.top_k(-jnp.where(fits.accepted, horizontal, jnp.inf), k)
    ok = jnp.isfinite(neg)
    pad = max_obs - k

    def rows(values):
        values = values[pick]
        mask = ok.reshape(ok.shape + (1,) * (values.ndim - 1))
        values = jnp.where(mask, values, jnp.zeros_like(values))
        return jnp.pad(values, ((0, pad),) + ((0, 0),) * (values.ndim - 1))

    position = rows(fits.position)
    z = jnp.stack([jnp.hypot(position[:, 0], position[:, 1]),
                   jnp.arctan2(position[:, 1], position[:, 0])], -1)
    valid = jnp.pad(ok, (0, pad))
    obs = Observations(z=z, valid=valid, radius=rows(fits.radius),
                       landmark_id=jnp.full(max_obs, -1, jnp.int32))
    cluster = jnp.where(valid, jnp.pad(pick.astype(jnp.int32), (0, pad)), -1)
    return Trunks3D(observations=obs, position=position, base=rows(fits.base),
                    axis=rows(fits.axis), lean=rows(fits.lean), radius=rows(fits.radius),
                    inlier_ratio=rows(fits.inlier_ratio), num_points=rows(fits.num_points),
                    num_inliers=rows(fits.num_inliers), cluster=cluster, clusters=fits,
                    ground=ground, num_clusters=num_clusters)
