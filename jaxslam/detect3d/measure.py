"""From a fitted cylinder to a trunk: where its axis meets the ground, its breast-height
position and DBH, and the rejection tests (module docstring of ``jaxslam.detect3d``, steps 6
and 7). C cluster slots, P points per cluster.
"""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxslam.detect3d.cylinders import cylinder_residual
from jaxslam.detect3d.grid import grid_cells
from jaxslam.detect3d.ground import Ground3D


class CylinderFits(NamedTuple):
    """The fit of every cluster slot (C,); slots without a cluster are not ``accepted``.

    Attributes:
      position: (C, 3) the axis at breast height (x, y, z) in the sensor frame [m].
      base: (C, 3) where the axis meets the ground [m].
      axis: (C, 3) unit axis direction, z component > 0.
      lean: (C,) angle of the axis from the vertical [rad].
      radius: (C,) cylinder radius (DBH / 2) [m].
      num_points: (C,) int32 band points in the cluster (all, not only the fitted sample).
      num_inliers: (C,) int32 fitted-sample points within ``inlier_tol`` of the cylinder.
      inlier_ratio: (C,) num_inliers / fitted-sample size.
      rms: (C,) RMS residual of the inliers [m].
      width: (C,) extent of the cross-section along its principal direction [m].
      flatness: (C,) second / first principal variance of the cross-section.
      enough_points, radius_ok, upright, cylindrical, not_wall, fit_ok: (C,) bool, the tests of
        the ``jaxslam.detect3d`` docstring (step 7); accepted: (C,) bool, all of them.
    """

    position: jnp.ndarray
    base: jnp.ndarray
    axis: jnp.ndarray
    lean: jnp.ndarray
    radius: jnp.ndarray
    num_points: jnp.ndarray
    num_inliers: jnp.ndarray
    inlier_ratio: jnp.ndarray
    rms: jnp.ndarray
    width: jnp.ndarray
    flatness: jnp.ndarray
    enough_points: jnp.ndarray
    radius_ok: jnp.ndarray
    upright: jnp.ndarray
    cylindrical: jnp.ndarray
    not_wall: jnp.ndarray
    fit_ok: jnp.ndarray
    accepted: jnp.ndarray


def axis_base(theta, z_ref, ground: Ground3D, cell, size: int, iterations: int = 3):
    """Where each axis meets the ground (step 6): (C, 3).

    With the plane (alpha, beta, gamma) of the ground cell (centre c) under the current
    crossing and the axis (x0 + a (z - z_ref), y0 + b (z - z_ref), z):
    z (1 - beta a - gamma b) = alpha + beta (x0 - a z_ref - c_x) + gamma (y0 - b z_ref - c_y);
    ``iterations`` times from z = z_ref (a crossing in another cell moves on to its plane).
    """
    x0, y0, a, b = theta[:, 0], theta[:, 1], theta[:, 2], theta[:, 3]

    def meet(z, _):
        q = jnp.stack([x0 + a * (z - z_ref), y0 + b * (z - z_ref)], -1)
        index, _ = grid_cells(q, cell, size)
        plane, centre = ground.planes[index], ground.centres[index]
        alpha, beta, gamma = plane[:, 0], plane[:, 1], plane[:, 2]
        denom = 1.0 - beta * a - gamma * b
        denom = jnp.where(jnp.abs(denom) > 1e-6, denom, 1e-6)
        z = (alpha + beta * (x0 - a * z_ref - centre[:, 0])
             + gamma * (y0 - b * z_ref - centre[:, 1])) / denom
        return z, None

    z, _ = jax.lax.scan(meet, z_ref, None, length=iterations)
    return jnp.stack([x0 + a * (z - z_ref), y0 + b * (z - z_ref), z], -1)


def cross_section(theta, pts, mask, z_ref):
    """Width (C,) along the principal direction and flatness (C,) (step 7) of the points moved
    along the axis onto z = z_ref: q = p_xy - (a, b) (p_z - z_ref)."""
    dz = pts[..., 2] - z_ref[:, None]
    q = pts[..., :2] - theta[:, None, 2:4] * dz[..., None]
    w = mask.astype(pts.dtype)
    n = jnp.maximum(jnp.sum(w, -1), 1.0)
    mean = jnp.sum(w[..., None] * q, -2) / n[:, None]
    d = q - mean[:, None, :]
    sxx = jnp.sum(w * d[..., 0] ** 2, -1) / n
    sxy = jnp.sum(w * d[..., 0] * d[..., 1], -1) / n
    syy = jnp.sum(w * d[..., 1] ** 2, -1) / n
    half = 0.5 * (sxx + syy)
    root = jnp.sqrt(jnp.maximum(0.25 * (sxx - syy) ** 2 + sxy * sxy, 0.0))
    big, small = half + root, jnp.maximum(half - root, 0.0)
    angle = 0.5 * jnp.arctan2(2.0 * sxy, sxx - syy)
    s = d[..., 0] * jnp.cos(angle)[:, None] + d[..., 1] * jnp.sin(angle)[:, None]
    huge = jnp.finfo(pts.dtype).max
    width = jnp.max(jnp.where(mask, s, -huge), -1) - jnp.min(jnp.where(mask, s, huge), -1)
    width = jnp.where(jnp.any(mask, -1), width, 0.0)
    return width, small / jnp.maximum(big, jnp.finfo(pts.dtype).tiny)


def measure_cylinders(theta, z_ref, found, pts, mask, count, ground: Ground3D, t: dict, *,
                      ground_cell, ground_size: int, max_range) -> tuple[CylinderFits, jnp.ndarray]:
    """Measure each fitted cylinder and run the rejection tests (steps 6 and 7).

    Args:
      theta: (C, 5) cylinders (x0, y0, a, b, r). z_ref: (C,) their reference heights.
      found: (C,) bool, a hypothesis was found. pts: (C, P, 3). mask: (C, P) bool.
      count: (C,) band points per cluster. ground: ``Ground3D`` on the grid of ``ground_cell``
      (G = ``ground_size`` cells a side). t: the traced thresholds of ``fit_trunks_3d``.
      max_range: () the grids' half-width [m]; a trunk beyond it is not ``fit_ok``.
    Returns:
      ``CylinderFits`` (C,) and the horizontal range (C,) of each breast-height point [m].
    """
    dtype = pts.dtype
    e = cylinder_residual(theta[:, None, :], pts, z_ref[:, None])
    inl = mask & (jnp.abs(e) < t["inlier_tol"])
    num_inliers = jnp.sum(inl, -1).astype(jnp.int32)
    sample = jnp.sum(mask, -1)
    inlier_ratio = num_inliers / jnp.maximum(sample, 1).astype(dtype)
    rms = jnp.sqrt(jnp.sum(jnp.where(inl, e * e, 0.0), -1)
                   / jnp.maximum(num_inliers, 1).astype(dtype))
    slope = jnp.hypot(theta[:, 2], theta[:, 3])
    lean = jnp.arctan(slope)
    norm = jnp.sqrt(1.0 + slope * slope)
    axis = jnp.stack([theta[:, 2], theta[:, 3], jnp.ones_like(slope)], -1) / norm[:, None]
    radius = jnp.abs(theta[:, 4])
    base = axis_base(theta, z_ref, ground, ground_cell, ground_size)
    z_bh = base[:, 2] + t["breast_height"]
    position = jnp.stack([theta[:, 0] + theta[:, 2] * (z_bh - z_ref),
                          theta[:, 1] + theta[:, 3] * (z_bh - z_ref), z_bh], -1)
    width, flatness = cross_section(theta, pts, mask, z_ref)

    # Rejections.
    w = mask.astype(dtype)
    centroid = jnp.sum(w[..., None] * pts[..., :2], -2) / jnp.maximum(sample, 1)[:, None]
    facing = jnp.hypot(theta[:, 0], theta[:, 1]) > jnp.hypot(centroid[:, 0], centroid[:, 1])
    horizontal = jnp.hypot(position[:, 0], position[:, 1])
    finite_fit = (jnp.all(jnp.isfinite(theta), -1) & jnp.all(jnp.isfinite(position), -1)
                  & jnp.isfinite(rms))
    enough_points = (count >= t["min_points"]) & (num_inliers >= t["min_points"])
    radius_ok = (radius >= t["min_radius"]) & (radius <= t["max_radius"])
    upright = lean <= t["max_lean"]
    cylindrical = inlier_ratio >= t["min_inlier_ratio"]
    not_wall = (width <= t["max_width"]) & (flatness >= t["min_flatness"])
    fit_ok = (found & finite_fit & facing & (horizontal > t["min_range"])
              & (horizontal < max_range))
    accepted = enough_points & radius_ok & upright & cylindrical & not_wall & fit_ok
    fits = CylinderFits(position=position, base=base, axis=axis, lean=lean, radius=radius,
                        num_points=count.astype(jnp.int32), num_inliers=num_inliers,
                        inlier_ratio=inlier_ratio, rms=rms, width=width, flatness=flatness,
                        enough_points=enough_points, radius_ok=radius_ok, upright=upright,
                        cylindrical=cylindrical, not_wall=not_wall, fit_ok=fit_ok,
                        accepted=accepted)
    return fits, horizontal
