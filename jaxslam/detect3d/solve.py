"""Small linear solves unrolled over their static size, for batched 3 x 3 and 5 x 5 systems.

Elementwise arithmetic instead of a batched LAPACK call: a few operations per entry, light to
compile and fast under ``vmap`` over thousands of tiny systems (ground planes, cylinder steps).
"""
from __future__ import annotations

import jax.numpy as jnp


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
