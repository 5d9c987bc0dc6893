"""Closed-form algebra of 3x3 symmetric positive-definite matrices (pose covariances).

The FastSLAM 2.0 proposal inverts, factors and takes the determinant of 3x3 pose covariances
for every particle and every motion piece. XLA's CPU backend runs ``jnp.linalg`` on such tiny
matrices as batched LAPACK-style calls (LU, triangular solves) whose fixed cost per call is
far larger than the arithmetic; these closed forms are plain elementwise arithmetic that XLA
fuses with the surrounding work. The Cholesky factor is the backward-stable route (no pivoting
is needed for an SPD matrix), so the accuracy is that of ``jnp.linalg.cholesky``.

For A = L L^T with L lower triangular (Golub and Van Loan, Matrix Computations, 4.2):

    l00 = sqrt(a00),  l10 = a10 / l00,  l20 = a20 / l00,
    l11 = sqrt(a11 - l10^2),  l21 = (a21 - l20 l10) / l11,
    l22 = sqrt(a22 - l20^2 - l21^2);

    L^-1 = [[1/l00, 0, 0], [-l10 / (l00 l11), 1/l11, 0],
            [(l10 l21 - l11 l20) / (l00 l11 l22), -l21 / (l11 l22), 1/l22]],

    A^-1 = L^-T L^-1,   log det A = 2 (log l00 + log l11 + log l22).

Only the lower triangle of A is read. A matrix that is not positive definite gives NaN (the
square root of a negative pivot), as ``jnp.linalg.cholesky`` does. Every function works on
(..., 3, 3) arrays, inside jit and vmap.
"""
from __future__ import annotations

import jax.numpy as jnp


def cholesky3(a):
    """Lower Cholesky factor L of an SPD (..., 3, 3) matrix: A = L L^T. Returns (..., 3, 3)."""
    l00 = jnp.sqrt(a[..., 0, 0])
    l10 = a[..., 1, 0] / l00
    l20 = a[..., 2, 0] / l00
    l11 = jnp.sqrt(a[..., 1, 1] - l10**2)
    l21 = (a[..., 2, 1] - l20 * l10) / l11
    l22 = jnp.sqrt(a[..., 2, 2] - l20**2 - l21**2)
    zero = jnp.zeros_like(l00)
    return jnp.stack([jnp.stack([l00, zero, zero], -1),
                      jnp.stack([l10, l11, zero], -1),
                      jnp.stack([l20, l21, l22], -1)], -2)


def lower_inverse3(chol):
    """Inverse of a lower-triangular (..., 3, 3) matrix with a positive diagonal."""
    l00, l11, l22 = chol[..., 0, 0], chol[..., 1, 1], chol[..., 2, 2]
    l10, l20, l21 = chol[..., 1, 0], chol[..., 2, 0], chol[..., 2, 1]
    zero = jnp.zeros_like(l00)
    return jnp.stack([
        jnp.stack([1.0 / l00, zero, zero], -1),
        jnp.stack([-l10 / (l00 * l11), 1.0 / l11, zero], -1),
        jnp.stack([(l10 * l21 - l11 * l20) / (l00 * l11 * l22), -l21 / (l11 * l22),
                   1.0 / l22], -1)], -2)


def solve_lower3(chol, b):
    """x with L x = b, by forward substitution. chol (..., 3, 3), b (..., 3) -> (..., 3)."""
    x0 = b[..., 0] / chol[..., 0, 0]
    x1 = (b[..., 1] - chol[..., 1, 0] * x0) / chol[..., 1, 1]
    x2 = (b[..., 2] - chol[..., 2, 0] * x0 - chol[..., 2, 1] * x1) / chol[..., 2, 2]
    return jnp.stack([x0, x1, x2], -1)


def log_det_from_cholesky3(chol):
    """log det(L L^T) = 2 sum_i log l_ii. (..., 3, 3) -> (...)."""
    return 2.0 * jnp.sum(jnp.log(jnp.diagonal(chol, axis1=-2, axis2=-1)), -1)


def spd_inverse3(a):
    """(A^-1, log det A) of an SPD (..., 3, 3) matrix through its Cholesky factor.

    The inverse L^-T L^-1 is symmetric by construction.
    """
    chol = cholesky3(a)
    inv_chol = lower_inverse3(chol)
    return (jnp.einsum("...ki,...kj->...ij", inv_chol, inv_chol),
            log_det_from_cholesky3(chol))
