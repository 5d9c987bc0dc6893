"""Euclidean clusters of the height band's points on a grid (module docstring of
``jaxslam.detect3d``, step 4): 8-connected occupied cells, the nearest ``max_clusters`` kept,
and each cluster's fitted sample of at most ``cluster_points`` points.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxslam.detect3d.grid import grid_cells


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
