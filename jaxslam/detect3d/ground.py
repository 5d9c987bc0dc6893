"""The ground model of one cloud: robust local planes (module docstring of
``jaxslam.detect3d``, step 2).

Seeds at a height quantile per cell, a robust asymmetric LOWESS of the seeds (Cleveland,
"Robust Locally Weighted Regression and Smoothing Scatterplots", JASA 1979), then one more
local-plane fit of the ground points away from objects. S = G x G cells.
"""
from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxslam.detect3d.grid import cell_centres, grid_cells
from jaxslam.detect3d.solve import solve_sym3

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


def ground_seeds(points, usable, cell, size: int, quantile):
    """Each cell's point at the ``quantile`` of its heights (``jaxslam.detect3d``, step 2a).

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
    """The robust local-plane ground model of the ``jaxslam.detect3d`` docstring (step 2).

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
