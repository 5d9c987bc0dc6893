"""Trunk detection from a 3D lidar point cloud: ground, height band, clusters, cylinder fits.

The 3D counterpart of ``jaxslam.detect.detect_trunks``. Geiser et al., "Practical
Implementation of FastSLAM for Forestry Robot" (ICAROB 2023) clip the cloud in height to drop
ground and canopy, cluster the rest (Euclidean clustering) and fit a cylinder to each cluster by
RANSAC; the tree is where the cylinder's axis meets a horizontal plane. Yang et al., "A 3D Lidar
SLAM System Based on Semantic Segmentation for Rubber-Tapping Robot" (Forests 2023) fit cylinders
to trunk points the same way and report a DBH error of 0.57 cm. ``clip_points_by_height`` in
``jaxslam.detect`` instead flattens a height slice into a 2D scan; there a leaning trunk's centre
depends on the slice and its horizontal section is an ellipse of semi-axes r and r / cos(lean),
so circle fits get both the position and the diameter wrong.

Frame: the sensor frame with z up. A tilted sensor should be levelled upstream: the ground
model absorbs a tilt of a few degrees as a slope, but every trunk then leans by the tilt.
Every step keeps fixed shapes, so the whole pipeline runs under ``jit`` and ``vmap`` over scans
(B clouds of N points, padded with ``valid = False``). Dimensions: N points, S = G x G ground
cells, C cluster slots (``max_clusters``), P points per cluster (``cluster_points``), H
hypotheses per cluster (``num_hypotheses``), K output rows (``max_obs``).

Pipeline:
  1. Points. A point is used when ``valid``, finite, farther than ``min_range`` and inside the
     square |x|, |y| < ``max_range`` (the extent of both grids).
  2. Ground (``estimate_ground``): a robust local-plane smoother, not a flat-ground model.
     a. Seeds: on a G x G grid of ``ground_cell`` cells, each cell's point at the
        ``ground_quantile`` of its heights (sorted index floor(q (n - 1))); one seed per cell.
     b. Robust LOWESS (Cleveland, "Robust Locally Weighted Regression and Smoothing
        Scatterplots", JASA 1979) of the seeds: at a query q the local plane
        z = alpha + beta (x - q_x) + gamma (y - q_y) minimises
        sum_k K_k rho_k (z_k - alpha - beta dx_k - gamma dy_k)^2 with the Gaussian kernel
        K_k = exp(-|c_k - q|^2 / (2 h^2)), h = ``ground_bandwidth``. The robustness weights
        rho_k are refit ``ground_iterations`` times from the residual e_k = z_k - alpha(c_k) of
        each seed against the fit at its own place: rho_k = T(e_k / s) above the surface and
        T(e_k / (3 s)) below (T(u) = (1 - u^2)^2 for |u| < 1, else 0: Tukey's biweight), the
        scale s shrinking geometrically from 1 m to ``ground_tol``. The asymmetry makes the
        surface the lower envelope (seeds on trunks, bushes and walls sit above the ground;
        low outliers are rare in lidar data).
     c. Ground points: those within ``ground_tol`` of that surface, except under objects:
        points from ``ground_tol`` to ``band_max`` above it (trunks, bushes, walls; not the
        canopy) mark their cell of the cluster grid (step 4) and its 8 neighbours, and points
        there are not ground (a trunk's lowest ring, a few cm above the ground, would otherwise
        lift the ground at its base by millimetres). Their per-cell moments
        (count, sums of dx, dy, z, dx^2, dx dy, dy^2, dx z, dy z about the cell centre) feed the
        same smoother once more (kernel on the cell centres, rho = 1), which removes the low
        bias of the quantile seeds under noise. The ground model is this final local plane at
        each cell centre; a point's ground height is its cell's plane at its (x, y) (piecewise
        planar: exact on a plane, steps of the curvature bias between cells otherwise).
     Limits: the local plane is exact on planar ground (any slope) and biased on curved
     ground: on a bowl z = c (x^2 + y^2) by about c (sx^2 + sy^2), s the spread of the ground
     points in the kernel (at most ~h; lidar rings make it uneven). Measured with the test
     sensor (16 rings, 1 m above the ground): c = 0.005 /m (curvature 0.01 /m) puts the
     breast-height point 3 cm too high and 5 mm off horizontally for leans up to 15 degrees;
     c = 0.02 /m (slope 0.32 at 8 m), 25 cm and 4 cm; a local quadratic would remove this;
     cells are extrapolated from neighbours within ~2 h, so the ground under a robot whose
     lidar cannot see it nearby (a VLP-16 at 1 m sees no ground within 3.7 m) is the plane of
     the ground farther out; dense understory that hides the ground over more than ~h becomes
     the ground; overhangs (a cell's lowest return not on the ground anywhere nearby) bias it up.
  3. Height band: the points with height above their ground in [``band_min``, ``band_max``]
     (default 0.5-3 m: above the ground, stumps and low shrubs, below the crowns).
  4. Clusters (``cluster_points_2d``): the band's XY projection rasterised on a grid of
     ``cluster_cell`` cells; occupied cells that touch (8-neighbourhood) form a cluster, found by
     min-label propagation with pointer jumping until nothing changes (each cell's label ends as
     the smallest flat index in its component). Points less than one cell apart always join,
     points more than 2 sqrt(2) cells apart never. Clusters with at least ``min_points`` points
     are ranked by the horizontal range of their centroid and the ``max_clusters`` nearest are
     fitted; FARTHER CLUSTERS ARE DROPPED (``Trunks3D.num_clusters`` counts them all). Each
     cluster's fit uses at most ``cluster_points`` of its points: all of them when it has that
     many or fewer, otherwise the points at ranks floor(j n / P), j < P, of its points in input
     order (an even spread over the scan's rings).
  5. Cylinders (``fit_cylinders``). A cylinder is its axis crossing (x0, y0) of the plane
     z = z_ref (the cluster's mean height), the axis slopes (a, b) (direction
     u = (a, b, 1) / |(a, b, 1)|, lean = atan(|(a, b)|)) and its radius r; the residual of a
     point p is e = |(p - p0) x u| - r, p0 = (x0, y0, z_ref).
     a. Hypotheses (RANSAC: Fischler and Bolles, "Random Sample Consensus", CACM 1981): H per
        cluster. Two are deterministic: a vertical axis through the Kasa circle (Kasa, "A
        Circle Fitting Procedure and its Error Analysis", IEEE TIM 1976) of all points, and the
        axis through the Kasa centres of the lower and upper thirds of the cluster's height
        range. The other H - 2
        draw an anchor point in the lower third and two points within ``ring_thickness`` of its
        height (one lidar ring: a horizontal section of the cylinder, an ellipse close to a
        circle for small leans), the same in the upper third; the axis joins the two
        three-point circle centres, r is the mean distance of the six points to it. A
        hypothesis is kept when its radius is at most 2 ``max_radius`` and its lean at most
        3 ``max_lean`` (capped at 70 degrees), so that too wide and too leaning trunks still fit
        and are rejected below for the right reason; the one with the most inliers
        (|e| < ``inlier_tol``) wins (ties: the lower index, so the deterministic ones first).
     b. Refinement: ``refine_rounds`` rounds of taking the inliers of the current cylinder and
        ``lm_iterations`` Levenberg-Marquardt steps on sum_inliers e^2 (per-point gradients by
        ``jax.grad``; a step is kept when the cost does not rise, the damping mu is divided by
        10 on success and multiplied by 10 otherwise).
  6. Position. The axis meets the ground at its base: z_b solves z = g(x(z), y(z)) where
     (x(z), y(z)) is the axis at height z and g the plane of the ground cell under the current
     crossing (three line-plane intersections, exact on planar ground). The trunk's position
     is the axis at breast height z_b + ``breast_height`` (1.3 m vertically above the base,
     i.e. 1.3 / cos(lean) along the stem), reported as horizontal range and bearing in the
     sensor frame, and the radius r = DBH / 2 (perpendicular to the axis).
  7. Rejections (masks in ``CylinderFits``): too few points (fewer than ``min_points`` in the
     cluster or among the inliers), radius outside [``min_radius``, ``max_radius``], lean over
     ``max_lean``, bushes (inlier ratio below ``min_inlier_ratio``), walls (the cross-section,
     the points moved along the axis onto the plane z = z_ref, spans more than ``max_width`` along
     its principal direction, or is flat: its second-to-first principal variance ratio is below
     ``min_flatness``; a seen half-circle gives ~0.15, a plane only its noise), and fits that are
     not trunks seen from outside (no hypothesis, non-finite values, or the axis nearer the
     sensor than the points' centroid).
  8. The ``max_obs`` nearest accepted trunks become ``Observations`` (as ``detect_trunks``).
"""
from __future__ import annotations

import functools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxslam.types import Observations

# Moments of the points of one ground cell about its centre (dx, dy) and of their heights z.
_MOMENTS = ("count", "dx", "dy", "z", "dx_dx", "dx_dy", "dy_dy", "dx_z", "dy_z")


class Ground3D(NamedTuple):
    """The ground model of one cloud (S = G x G cells, row-major with x the slow index).

    Attributes:
      centres: (S, 2) cell centres (x, y) [m].
      planes: (S, 3) local plane (alpha, beta, gamma) at each centre: ground height
        z = alpha + beta (x - cx) + gamma (y - cy) [m, -, -].
      moments: (S, 9) moments of each cell's ground points about its centre (``_MOMENTS``).
      seeds: (S, 3) each cell's quantile point (x, y, z) [m].
      seed_weight: (S,) final robustness weight of each seed (0 for empty cells).
    """

    centres: jnp.ndarray
    planes: jnp.ndarray
    moments: jnp.ndarray
    seeds: jnp.ndarray
    seed_weight: jnp.ndarray


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
        the module docstring (step 7); accepted: (C,) bool, all of them.
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


# ----------------------------------------------------------------------------------------------
# Grids and the ground.


def grid_size(max_range: float, cell: float) -> int:
    """G, the cells per side of a square grid of ``cell`` [m] covering |x|, |y| < max_range."""
    return int(math.ceil(2.0 * max_range / cell - 1e-9))


def grid_cells(xy, cell, size: int):
    """Cell of each point on the G x G grid with lower-left corner (-G cell / 2, -G cell / 2).

    Args:
      xy: (N, 2) [m]. cell: () [m]. size: G.
    Returns:
      index (N,) int32 flat cell index i G + j (i from x, j from y; clipped into the grid) and
      inside (N,) bool.
    """
    ij = jnp.floor(xy / cell + 0.5 * size).astype(jnp.int32)
    inside = jnp.all((ij >= 0) & (ij < size), axis=-1)
    ij = jnp.clip(ij, 0, size - 1)
    return ij[:, 0] * size + ij[:, 1], inside


def cell_centres(cell, size: int, dtype=jnp.float32):
    """(G G, 2) centres of the grid of ``grid_cells``, in its flat order."""
    offset = (jnp.arange(size, dtype=dtype) + 0.5 - 0.5 * size) * cell
    cx, cy = jnp.meshgrid(offset, offset, indexing="ij")
    return jnp.stack([cx.ravel(), cy.ravel()], -1)


def ground_seeds(points, usable, cell, size: int, quantile):
    """Each cell's point at the ``quantile`` of its heights (module docstring, step 2a).

    Args:
      points: (N, 3). usable: (N,) bool. cell: () [m]. size: G. quantile: () in [0, 1].
    Returns:
      seeds (S, 3) and seed_ok (S,) bool (cells with at least one point).
    """
    num = size * size
    index, inside = grid_cells(points[:, :2], cell, size)
    used = usable & inside
    key = jnp.where(used, index, num)
    _, z, x, y = jax.lax.sort((key, points[:, 2], points[:, 0], points[:, 1]), num_keys=2)
    count = jax.ops.segment_sum(used.astype(jnp.int32), key, num_segments=num + 1)[:num]
    first = jnp.cumsum(count) - count
    rank = jnp.floor(quantile * jnp.maximum(count - 1, 0).astype(points.dtype))
    pick = jnp.clip(first + rank.astype(jnp.int32), 0, points.shape[0] - 1)
    seeds = jnp.stack([x[pick], y[pick], z[pick]], -1)
    ok = count > 0
    return jnp.where(ok[:, None], seeds, 0.0), ok


def point_moments(points, weight, centres, index, num_cells: int):
    """(S, 9) moments (``_MOMENTS``) of weighted points about their cells' centres.

    Args:
      points: (N, 3). weight: (N,). centres: (S, 2). index: (N,) int32 cell of each point.
    """
    d = points[:, :2] - centres[index]
    dx, dy, z = d[:, 0], d[:, 1], points[:, 2]
    columns = jnp.stack([jnp.ones_like(z), dx, dy, z, dx * dx, dx * dy, dy * dy, dx * z, dy * z],
                        -1)
    return jax.ops.segment_sum(weight[:, None] * columns, index, num_segments=num_cells)


def local_planes(query, centres, moments, weight, bandwidth):
    """Kernel-weighted least-squares planes about each query point (step 2b).

    Solves, per query q, sum_k K_k w_k sum_{i in k} (z_i - alpha - beta (x_i - q_x)
    - gamma (y_i - q_y))^2 -> min with K_k = exp(-|c_k - q|^2 / (2 h^2)), from each source's
    moments about its centre c_k shifted by o = c_k - q (e.g. sum (x - q_x)^2 =
    sum dx^2 + 2 o_x sum dx + n o_x^2): all the sums are one contraction of the kernel times
    (1, o_x, o_y, o_x^2, o_x o_y, o_y^2) with the moments. A ridge of 1e-12 trace(A) (1e-6 in
    float32) keeps empty or degenerate neighbourhoods finite (an empty one gives the plane 0).

    Args:
      query: (Q, 2). centres: (S, 2) source centres. moments: (S, 9). weight: (S,).
      bandwidth: () h [m].
    Returns:
      (Q, 3) planes (alpha, beta, gamma) about the queries.
    """
    o = centres[None, :, :] - query[:, None, :]
    ox, oy = o[..., 0], o[..., 1]
    kern = jnp.exp(-0.5 * (ox * ox + oy * oy) / (bandwidth * bandwidth)) * weight[None, :]
    basis = kern[..., None] * jnp.stack([jnp.ones_like(ox), ox, oy, ox * ox, ox * oy, oy * oy],
                                        -1)
    t = jnp.einsum("qsa,sm->qam", basis, moments)  # (Q, 6, 9)
    n, sx, sy, sz, sxx, sxy, syy, sxz, syz = range(9)
    one, px, py, pxx, pxy, pyy = range(6)
    count = t[:, one, n]
    x = t[:, one, sx] + t[:, px, n]
    y = t[:, one, sy] + t[:, py, n]
    xx = t[:, one, sxx] + 2.0 * t[:, px, sx] + t[:, pxx, n]
    xy = t[:, one, sxy] + t[:, px, sy] + t[:, py, sx] + t[:, pxy, n]
    yy = t[:, one, syy] + 2.0 * t[:, py, sy] + t[:, pyy, n]
    bz = t[:, one, sz]
    bx = t[:, one, sxz] + t[:, px, sz]
    by = t[:, one, syz] + t[:, py, sz]
    ridge = 1e-6 if query.dtype == jnp.float32 else 1e-12
    damp = ridge * (count + xx + yy) + jnp.finfo(query.dtype).tiny ** 0.5
    return solve_sym3(count + damp, x, y, xx + damp, xy, yy + damp, bz, bx, by)


def solve_sym3(a00, a01, a02, a11, a12, a22, b0, b1, b2):
    """(..., 3) solution of the symmetric 3 x 3 system by its adjugate (Cramer's rule); every
    argument (...). A singular system (det 0) gives zeros."""
    c00 = a11 * a22 - a12 * a12
    c01 = a02 * a12 - a01 * a22
    c02 = a01 * a12 - a02 * a11
    c11 = a00 * a22 - a02 * a02
    c12 = a01 * a02 - a00 * a12
    c22 = a00 * a11 - a01 * a01
    det = a00 * c00 + a01 * c01 + a02 * c02
    inv = jnp.where(det != 0.0, 1.0 / jnp.where(det != 0.0, det, 1.0), 0.0)
    return jnp.stack([c00 * b0 + c01 * b1 + c02 * b2, c01 * b0 + c11 * b1 + c12 * b2,
                      c02 * b0 + c12 * b1 + c22 * b2], -1) * inv[..., None]


def spd_solve(a, b):
    """x (..., n) solving a x = b for symmetric positive definite a (..., n, n), b (..., n).

    Cholesky a = L L^T unrolled over the (small, static) n, then two triangular solves: a few
    elementwise ops per entry, much lighter to compile than a batched LAPACK call. A pivot that
    is not positive (a singular a) is replaced by the largest finite float, which zeroes that
    component of x instead of returning NaN.
    """
    n = a.shape[-1]
    big = jnp.finfo(a.dtype).max
    low = [[None] * n for _ in range(n)]
    for j in range(n):
        pivot = a[..., j, j] - sum(low[j][k] * low[j][k] for k in range(j))
        pivot = jnp.sqrt(jnp.where(pivot > 0.0, pivot, big))
        low[j][j] = pivot
        for i in range(j + 1, n):
            low[i][j] = (a[..., i, j] - sum(low[i][k] * low[j][k] for k in range(j))) / pivot
    y = [None] * n
    for i in range(n):
        y[i] = (b[..., i] - sum(low[i][k] * y[k] for k in range(i))) / low[i][i]
    x = [None] * n
    for i in reversed(range(n)):
        x[i] = (y[i] - sum(low[k][i] * x[k] for k in range(i + 1, n))) / low[i][i]
    return jnp.stack(x, -1)


def _tukey(u):
    """Tukey's biweight (1 - u^2)^2 on |u| < 1, else 0; u any shape."""
    return jnp.where(jnp.abs(u) < 1.0, (1.0 - u * u) ** 2, 0.0)


def seed_planes(seeds, seed_ok, centres, bandwidth, tol, iterations: int):
    """Robust LOWESS of the seeds (step 2b): planes (S, 3) at the cell centres and the final
    robustness weights (S,) of the seeds.

    ``iterations`` asymmetric reweightings with scales s_i = 1 m (tol / 1 m)^(i / (n - 1)),
    i < n; a seed's residual is against the local plane at its own (x, y) fitted with the
    previous weights; the planes at the centres use the weights after the last reweighting.
    (One scan of n + 1 fits, each at the seeds and at the centres.)
    """
    dtype = seeds.dtype
    num = seeds.shape[0]
    moments = jnp.zeros((num, 9), dtype).at[:, 0].set(1.0).at[:, 3].set(seeds[:, 2])
    queries = jnp.concatenate([seeds[:, :2], centres], 0)
    steps = jnp.minimum(jnp.arange(iterations + 1, dtype=dtype), iterations - 1)
    scales = jnp.asarray(1.0, dtype) * (tol / 1.0) ** (steps / max(iterations - 1, 1))
    base = seed_ok.astype(dtype)

    def reweight(rho, scale):
        fit = local_planes(queries, seeds[:, :2], moments, rho, bandwidth)
        e = seeds[:, 2] - fit[:num, 0]
        new = base * _tukey(jnp.where(e >= 0.0, e / scale, e / (3.0 * scale)))
        return new, (rho, fit[num:])

    _, (rho, planes) = jax.lax.scan(reweight, base, scales)
    return planes[-1], rho[-1]


def plane_height(planes, centres, index, xy):
    """(N,) ground height of points xy (N, 2) from their cells' planes (S, 3) and centres."""
    d = xy - centres[index]
    p = planes[index]
    return p[:, 0] + p[:, 1] * d[:, 0] + p[:, 2] * d[:, 1]


def footprint(xy, member, cell, size: int):
    """(N,) bool: the point's cell on the G x G grid of ``cell``, or one of its 8 neighbours,
    holds a ``member`` (N,) point (the members' footprint dilated by one cell)."""
    num = size * size
    index, inside = grid_cells(xy, cell, size)
    occupied = jnp.zeros(num + 1, bool).at[jnp.where(member & inside, index, num)].set(True)
    grid = jnp.pad(occupied[:num].reshape(size, size), 1)
    dilated = functools.reduce(jnp.logical_or, [grid[i:i + size, j:j + size]
                                                for i in range(3) for j in range(3)])
    return dilated.ravel()[index] & inside


def estimate_ground(points, usable, *, cell, size: int, quantile, bandwidth, tol,
                    iterations: int, object_height, object_cell, object_size: int) -> Ground3D:
    """The robust local-plane ground model of the module docstring (step 2).

    Args:
      points: (N, 3) sensor frame [m]. usable: (N,) bool.
      cell: () ground cell [m]; size: G; quantile, bandwidth, tol: () as ``fit_trunks_3d``'s
        ``ground_quantile``, ``ground_bandwidth``, ``ground_tol``; iterations: reweightings.
      object_height: () points from ``tol`` to this height over the rough surface are objects
        (trunks, bushes, walls) whose footprint, on the grid of ``object_cell`` (G' cells a
        side), is not ground.
    """
    dtype = points.dtype
    num = size * size
    centres = cell_centres(cell, size, dtype)
    seeds, seed_ok = ground_seeds(points, usable, cell, size, quantile)
    rough, rho = seed_planes(seeds, seed_ok, centres, bandwidth, tol, iterations)
    index, inside = grid_cells(points[:, :2], cell, size)
    height = points[:, 2] - plane_height(rough, centres, index, points[:, :2])
    objects = usable & inside & (height >= tol) & (height <= object_height)
    below_object = footprint(points[:, :2], objects, object_cell, object_size)
    on_ground = usable & inside & (jnp.abs(height) < tol) & ~below_object
    moments = point_moments(points, on_ground.astype(dtype), centres, index, num)
    planes = local_planes(centres, centres, moments, jnp.ones(num, dtype), bandwidth)
    return Ground3D(centres=centres, planes=planes, moments=moments, seeds=seeds,
                    seed_weight=rho)


# ----------------------------------------------------------------------------------------------
# Clusters.


def connected_components(occupied):
    """Labels (G, G) int32 of the 8-connected components of ``occupied`` (G, G) bool.

    Each occupied cell ends with the smallest flat index of its component (min over the 3 x 3
    neighbourhood, then two pointer jumps label <- label[label], until nothing changes); empty
    cells hold G G.
    """
    g = occupied.shape[0]
    num = g * g
    labels = jnp.where(occupied, jnp.arange(num, dtype=jnp.int32).reshape(g, g), num)

    def neighbour_min(lab):
        padded = jnp.pad(lab, 1, constant_values=num)
        out = lab
        for di in range(3):
            for dj in range(3):
                out = jnp.minimum(out, padded[di:di + g, dj:dj + g])
        return jnp.where(occupied, out, num)

    def jump(lab):
        table = jnp.concatenate([lab.ravel(), jnp.full(1, num, jnp.int32)])
        return jnp.where(occupied, table[lab], num)

    def body(state):
        lab, _, step = state
        new = jump(jump(neighbour_min(lab)))
        return new, jnp.any(new != lab), step + 1

    labels, _, _ = jax.lax.while_loop(lambda s: s[1] & (s[2] < num), body,
                                      (labels, jnp.asarray(True), jnp.asarray(0)))
    return labels


def cluster_points_2d(xy, member, *, cell, size: int, max_clusters: int, min_points):
    """Cluster slot (N,) int32 of each band point (-1: none) and the candidate count (step 4).

    Args:
      xy: (N, 2) [m]. member: (N,) bool band points. cell: () [m]; size: G;
      max_clusters: C; min_points: () smallest cluster.
    Returns:
      slot (N,) int32 in [0, C) or -1, and num_clusters () int32 clusters with at least
      ``min_points`` points (before the cap).
    """
    num = size * size
    index, inside = grid_cells(xy, cell, size)
    member = member & inside
    occupied = jnp.zeros(num + 1, bool).at[jnp.where(member, index, num)].set(True)[:num]
    labels = connected_components(occupied.reshape(size, size)).ravel()
    root = jnp.where(member, labels[index], num)
    w = member.astype(xy.dtype)
    count = jax.ops.segment_sum(w, root, num_segments=num + 1)[:num]
    sx = jax.ops.segment_sum(w * xy[:, 0], root, num_segments=num + 1)[:num]
    sy = jax.ops.segment_sum(w * xy[:, 1], root, num_segments=num + 1)[:num]
    safe = jnp.maximum(count, 1.0)
    dist = jnp.hypot(sx / safe, sy / safe)
    candidate = count >= min_points
    k = min(max_clusters, num)
    neg, roots = jax.lax.top_k(jnp.where(candidate, -dist, -jnp.inf), k)
    chosen = jnp.isfinite(neg)
    table = jnp.full(num + 1, -1, jnp.int32).at[jnp.where(chosen, roots, num)].set(
        jnp.arange(k, dtype=jnp.int32))
    table = table.at[num].set(-1)
    return table[root], jnp.sum(candidate).astype(jnp.int32)


def gather_clusters(points, height, slot, max_clusters: int, cluster_points: int):
    """Each cluster's fitted sample (step 4: all points, or ranks floor(j n / P)).

    Args:
      points: (N, 3). height: (N,) above the ground. slot: (N,) int32 cluster or -1.
    Returns:
      pts (C, P, 3), h (C, P), mask (C, P) bool, count (C,) int32 points per cluster.
    """
    n = points.shape[0]
    key = jnp.where(slot >= 0, slot, max_clusters)
    order = jnp.argsort(key, stable=True)
    count = jax.ops.segment_sum(jnp.ones(n, jnp.int32), key,
                                num_segments=max_clusters + 1)[:max_clusters]
    first = jnp.cumsum(count) - count
    j = jnp.arange(cluster_points, dtype=jnp.int32)[None, :]
    rank = jnp.where(count[:, None] <= cluster_points, j, (j * count[:, None]) // cluster_points)
    pick = order[jnp.clip(first[:, None] + rank, 0, n - 1)]
    mask = j < count[:, None]
    return (jnp.where(mask[..., None], points[pick], 0.0), jnp.where(mask, height[pick], 0.0),
            mask, count)


# ----------------------------------------------------------------------------------------------
# Cylinders.


def cylinder_residual(theta, p, z_ref):
    """Signed distance e = |(p - p0) x u| - r of points to cylinders (step 5).

    Args:
      theta: (..., 5) (x0, y0, a, b, r). p: (..., 3). z_ref: (...). Shapes broadcast (same rank).
    Returns:
      (...) residuals [m].
    """
    wx, wy, wz = p[..., 0] - theta[..., 0], p[..., 1] - theta[..., 1], p[..., 2] - z_ref
    a, b = theta[..., 2], theta[..., 3]
    cx, cy, cz = wy - b * wz, a * wz - wx, wx * b - wy * a  # w x (a, b, 1)
    d2 = (cx * cx + cy * cy + cz * cz) / (1.0 + a * a + b * b)
    return jnp.sqrt(jnp.maximum(d2, jnp.finfo(p.dtype).tiny)) - theta[..., 4]


def _kasa_xy(xy, w):
    """Weighted Kasa circle of xy (..., P, 2): centre (..., 2), radius (...), ok (...)."""
    n = jnp.sum(w, -1)
    safe = jnp.maximum(n, 1e-12)
    mean = jnp.sum(w[..., None] * xy, -2) / safe[..., None]
    d = xy - mean[..., None, :]
    u, v = d[..., 0], d[..., 1]
    z = u * u + v * v
    sums = jnp.sum(w[..., None] * jnp.stack([u * u, u * v, v * v, z * u, z * v, z], -1), -2)
    suu, suv, svv, szu, szv, sz = (sums[..., i] for i in range(6))
    det = suu * svv - suv * suv
    ok = (det > 1e-12 * jnp.maximum(suu * svv, 1e-30)) & (n >= 3)
    safe_det = jnp.where(ok, det, 1.0)
    cu = 0.5 * (svv * szu - suv * szv) / safe_det
    cv = 0.5 * (suu * szv - suv * szu) / safe_det
    radius = jnp.sqrt(jnp.maximum(cu * cu + cv * cv + sz / safe, 0.0))
    return mean + jnp.stack([cu, cv], -1), radius, ok


def _circle_through(p):
    """Circle through the three points p (..., 3, 2): centre (..., 2), ok (...)."""
    ax, ay = p[..., 1, 0] - p[..., 0, 0], p[..., 1, 1] - p[..., 0, 1]
    bx, by = p[..., 2, 0] - p[..., 0, 0], p[..., 2, 1] - p[..., 0, 1]
    det = 2.0 * (ax * by - ay * bx)
    ok = jnp.abs(det) > 1e-12
    safe = jnp.where(ok, det, 1.0)
    a2, b2 = ax * ax + ay * ay, bx * bx + by * by
    return p[..., 0, :] + jnp.stack([(by * a2 - ay * b2) / safe, (ax * b2 - bx * a2) / safe],
                                    -1), ok


def _axis_theta(lower, upper, z_ref):
    """(x0, y0, a, b) of the line through points lower, upper (..., 3) at height z_ref (...)."""
    d = upper - lower
    ok = d[..., 2] > 0.0
    dz = jnp.where(ok, d[..., 2], 1.0)
    a, b = d[..., 0] / dz, d[..., 1] / dz
    t = z_ref - lower[..., 2]
    return jnp.stack([lower[..., 0] + a * t, lower[..., 1] + b * t, a, b], -1), ok


def _slices(h, mask):
    """Lower and upper thirds (C, P) bool of each cluster's height range."""
    big = jnp.finfo(h.dtype).max
    lo = jnp.min(jnp.where(mask, h, big), -1, keepdims=True)
    hi = jnp.max(jnp.where(mask, h, -big), -1, keepdims=True)
    third = (hi - lo) / 3.0
    return mask & (h <= lo + third), mask & (h >= hi - third), (hi - lo)[:, 0]


def _pick_ranks(allowed, ranks):
    """Index (...) of the point of rank ``ranks`` (...) among the ``allowed`` (..., P) points."""
    order = jnp.cumsum(allowed.astype(jnp.int32), -1) - 1
    return jnp.argmax(allowed & (order == ranks[..., None]), -1)


def _ring_samples(draws, z, candidate, ring):
    """Indices (C, M, 3) of three distinct points: an anchor uniform among ``candidate`` (C, P)
    and two more uniform among the candidates within ``ring`` of its height z (C, P), from the
    uniform ``draws`` (3, C, M) (rank = floor(u n)); ok (C, M) when there were enough."""
    p = z.shape[1]
    n_anchor = jnp.sum(candidate, -1)[:, None]
    rank = jnp.minimum(jnp.floor(draws[0] * n_anchor), n_anchor - 1).astype(jnp.int32)
    anchor = _pick_ranks(jnp.broadcast_to(candidate[:, None, :], draws.shape[1:] + (p,)), rank)
    z_anchor = jnp.take_along_axis(z, anchor, axis=1)
    near = (candidate[:, None, :] & (jnp.abs(z[:, None, :] - z_anchor[..., None]) <= ring)
            & (jnp.arange(p)[None, None, :] != anchor[..., None]))
    n_near = jnp.sum(near, -1)
    first = jnp.minimum(jnp.floor(draws[1] * n_near), n_near - 1).astype(jnp.int32)
    second = jnp.minimum(jnp.floor(draws[2] * (n_near - 1)), n_near - 2).astype(jnp.int32)
    second = second + (second >= first)  # a uniform second rank among the n - 1 others
    pair = jnp.stack([_pick_ranks(near, first), _pick_ranks(near, second)], -1)
    ok = (n_anchor >= 1) & (n_near >= 2)
    return jnp.concatenate([anchor[..., None], pair], -1), ok


def _mean_distance(theta4, pts, w, z_ref):
    """Mean distance (...) of points pts (..., P, 3) with weights w (..., P) to axes theta4
    (..., 4) at heights z_ref (...)."""
    theta = jnp.concatenate([theta4, jnp.zeros_like(theta4[..., :1])], -1)
    d = cylinder_residual(theta[..., None, :], pts, z_ref[..., None])
    return jnp.sum(w * d, -1) / jnp.maximum(jnp.sum(w, -1), 1e-12)


def cylinder_hypotheses(key, pts, h, mask, z_ref, *, num_hypotheses: int, ring_thickness):
    """RANSAC hypotheses (step 5a): theta (C, H, 5) and ok (C, H).

    Args:
      key: PRNG key. pts: (C, P, 3). h: (C, P) height above the ground. mask: (C, P) bool.
      z_ref: (C,) reference heights. num_hypotheses: H >= 2. ring_thickness: () [m].
    """
    c, p, _ = pts.shape
    dtype = pts.dtype
    w = mask.astype(dtype)
    lower, upper, _ = _slices(h, mask)
    # 0: vertical axis through the Kasa circle of all points; 1: the axis through the Kasa
    # centres of the lower and upper thirds (one stacked Kasa fit of the three point sets).
    sets = jnp.stack([mask, lower, upper]).astype(dtype)  # (3, C, P)
    centre, radius, ok_k = _kasa_xy(jnp.broadcast_to(pts[None, ..., :2], (3, c, p, 2)), sets)
    z_mean = jnp.sum(sets * pts[None, ..., 2], -1) / jnp.maximum(jnp.sum(sets, -1), 1e-12)
    theta0 = jnp.concatenate([centre[0], jnp.zeros((c, 2), dtype), radius[0][:, None]], -1)
    ok0 = ok_k[0]
    slice_c = jnp.concatenate([centre[1:], z_mean[1:, :, None]], -1)  # (2, C, 3)
    axis1, ok_axis = _axis_theta(slice_c[0], slice_c[1], z_ref)
    theta1 = jnp.concatenate([axis1, _mean_distance(axis1, pts, w, z_ref)[:, None]], -1)
    ok1 = ok_k[1] & ok_k[2] & ok_axis

    # 2..H-1: three points on a ring in each third (the two thirds vmapped, one draw).
    num = num_hypotheses - 2
    draws = jax.random.uniform(key, (2, 3, c, num), dtype)
    rows = jnp.arange(c)[:, None, None]

    def ring_circle(draw, sel):
        idx, ok = _ring_samples(draw, pts[..., 2], sel, ring_thickness)
        sample = pts[rows, idx]  # (C, M, 3, 3)
        centre, ok_c = _circle_through(sample[..., :2])
        z = jnp.mean(sample[..., 2], -1)
        return jnp.concatenate([centre, z[..., None]], -1), sample, ok & ok_c

    ring, sample, ok_ring = jax.vmap(ring_circle)(draws, jnp.stack([lower, upper]))
    z_rep = jnp.broadcast_to(z_ref[:, None], (c, num))
    axis_r, ok_ar = _axis_theta(ring[0], ring[1], z_rep)
    six = jnp.concatenate([sample[0], sample[1]], -2)
    theta_r = jnp.concatenate(
        [axis_r, _mean_distance(axis_r, six, jnp.ones(six.shape[:-1], dtype), z_rep)[..., None]],
        -1)
    theta = jnp.concatenate([theta0[:, None], theta1[:, None], theta_r], 1)
    ok = jnp.concatenate([ok0[:, None], ok1[:, None], ok_ring[0] & ok_ring[1] & ok_ar], 1)
    return theta, ok & jnp.all(jnp.isfinite(theta), -1)


def _inliers(theta, pts, mask, z_ref, tol):
    """Inlier mask (C, P) of the cylinders theta (C, 5)."""
    e = cylinder_residual(theta[:, None, :], pts, z_ref[:, None])
    return mask & (jnp.abs(e) < tol)


def levenberg_marquardt(theta, pts, weight, z_ref, iterations: int):
    """``iterations`` LM steps on sum_i w_i e_i(theta)^2 per cluster (step 5b).

    Normal equations (J^T W J + mu diag(J^T W J) + eps I) delta = -J^T W e with J (C, P, 5) the
    Jacobian of ``cylinder_residual`` (per-point ``jax.grad``); mu starts at 1e-3.

    Args:
      theta: (C, 5). pts: (C, P, 3). weight: (C, P). z_ref: (C,).
    Returns:
      theta (C, 5).
    """
    grad = jax.vmap(jax.vmap(jax.value_and_grad(cylinder_residual), in_axes=(None, 0, None)),
                    in_axes=(0, 0, 0))
    eye = jnp.eye(5, dtype=theta.dtype)

    def cost(th):
        e = cylinder_residual(th[:, None, :], pts, z_ref[:, None])
        return jnp.sum(weight * e * e, -1)

    def step(carry, _):
        th, mu, old = carry
        e, jac = grad(th, pts, z_ref)
        wj = weight[..., None] * jac
        a = jnp.einsum("cpi,cpj->cij", wj, jac)
        g = jnp.einsum("cpi,cp->ci", wj, e)
        diag = jnp.diagonal(a, axis1=-2, axis2=-1)
        eps = 1e-12 * jnp.sum(diag, -1) + jnp.finfo(th.dtype).tiny ** 0.5
        lhs = a + (mu[:, None] * diag + eps[:, None])[..., None] * eye[None]
        delta = spd_solve(lhs, -g)
        new = th + delta
        new_cost = cost(new)
        good = jnp.isfinite(new_cost) & (new_cost <= old) & jnp.all(jnp.isfinite(new), -1)
        th = jnp.where(good[:, None], new, th)
        return (th, jnp.where(good, mu * 0.1, mu * 10.0).clip(1e-12, 1e12),
                jnp.where(good, new_cost, old)), None

    mu = jnp.full(theta.shape[:1], 1e-3, theta.dtype)
    (theta, _, _), _ = jax.lax.scan(step, (theta, mu, cost(theta)), None, length=iterations)
    return theta


def fit_cylinders(key, pts, h, mask, *, num_hypotheses: int, ring_thickness, inlier_tol,
                  max_radius, max_lean, lm_iterations: int, refine_rounds: int):
    """RANSAC and refinement of one cylinder per cluster (step 5).

    Args:
      key: PRNG key. pts: (C, P, 3). h: (C, P). mask: (C, P) bool.
    Returns:
      theta (C, 5) (x0, y0, a, b, r), z_ref (C,), found (C,) bool (a hypothesis with 3+ inliers).
    """
    w = mask.astype(pts.dtype)
    z_ref = jnp.sum(w * pts[..., 2], -1) / jnp.maximum(jnp.sum(w, -1), 1.0)
    theta, ok = cylinder_hypotheses(key, pts, h, mask, z_ref, num_hypotheses=num_hypotheses,
                                    ring_thickness=ring_thickness)
    lean_cap = jnp.minimum(3.0 * max_lean, jnp.deg2rad(70.0))
    ok = (ok & (theta[..., 4] > 0.0) & (theta[..., 4] <= 2.0 * max_radius)
          & (jnp.hypot(theta[..., 2], theta[..., 3]) <= jnp.tan(lean_cap)))
    e = cylinder_residual(theta[:, :, None, :], pts[:, None], z_ref[:, None, None])
    votes = jnp.sum(mask[:, None, :] & (jnp.abs(e) < inlier_tol), -1)
    votes = jnp.where(ok, votes, -1)
    best = jnp.argmax(votes, -1)
    found = jnp.max(votes, -1) >= 3
    theta = jnp.take_along_axis(theta, best[:, None, None], axis=1)[:, 0]

    def refine(theta, _):
        inl = _inliers(theta, pts, mask, z_ref, inlier_tol)
        return levenberg_marquardt(theta, pts, inl.astype(pts.dtype), z_ref, lm_iterations), None

    theta, _ = jax.lax.scan(refine, theta, None, length=refine_rounds)
    return theta, z_ref, found


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


# ----------------------------------------------------------------------------------------------
# The detector.


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
    """Trunks in a 3D point cloud with every fit and rejection (module docstring).

    Args:
      points: (N, 3) sensor frame, z up [m]; or (B, N, 3) for B clouds (vmapped inside).
      valid: (N,) or (B, N) bool, default all True; padded points are False.
      key: PRNG key (RANSAC draws); with a batch, one key (split into B) or B keys.
      max_obs: K, output rows. max_clusters: C, clusters fitted (the nearest; others dropped).
      max_range: half-width of the square covered by the grids [m] (static: fixes G).
      ground_cell, cluster_cell: grid cells [m] (static). cluster_points: P (static).
      num_hypotheses: H >= 2 (static). ground_iterations, lm_iterations, refine_rounds: static.
      Other arguments: the thresholds of the module docstring (traced: no recompile per value),
        in metres and radians; min_points counts points.
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
    dtype = points.dtype
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
