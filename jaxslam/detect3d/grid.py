"""The square grids of the 3D detector: G x G cells covering |x|, |y| < max_range.

Cells are numbered row-major with x the slow index (flat index i G + j); the ground model
(``ground``) and the clusters (``clusters``) each use one such grid with their own cell size.
"""
from __future__ import annotations

import math

import jax.numpy as jnp


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
