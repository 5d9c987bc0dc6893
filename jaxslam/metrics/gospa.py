"""GOSPA of an estimated map against the true trees (Rahmathullah, Garcia-Fernandez and
Svensson, "Generalized optimal sub-pattern assignment metric", FUSION 2017), alpha = 2."""
from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import optax


class GospaResult(NamedTuple):
    """GOSPA (alpha = 2) and its decomposition; distance^p = localisation + missed + false.

    distance: d_p^(c,2)(X, Y).
    localisation: sum over assigned pairs closer than c of d^p.
    missed: c^p / 2 times the number of unassigned true points.
    false: c^p / 2 times the number of unassigned estimated points.
    num_missed, num_false: those counts (int32); a pair at distance >= c counts as unassigned.
    """

    distance: jnp.ndarray
    localisation: jnp.ndarray
    missed: jnp.ndarray
    false: jnp.ndarray
    num_missed: jnp.ndarray
    num_false: jnp.ndarray


def _optimal_pairs(cost):
    """(rows, cols) of the optimal assignment of a (M, N) cost; static size min(M, N)."""
    return optax.assignment.hungarian_algorithm(cost)


def gospa(est, est_valid, truth, truth_valid, c, p=2.0, alpha=2.0):
    """GOSPA metric of Rahmathullah, Garcia-Fernandez and Svensson (2017), alpha = 2.

        d_p^(c,2)(X, Y) = ( min_gamma sum_{(i,j) in gamma} d(x_i, y_j)^p
                            + c^p / 2 (|X| + |Y| - 2 |gamma|) )^(1/p)

    over partial assignments gamma with d < c. Solved on the full (M, N) padded cost with the
    Hungarian algorithm: valid pairs cost min(d, c)^p, any pair touching padding costs c^p.
    Every assignment then costs sum_vv (min(d, c)^p - c^p) + const, so its optimum is the GOSPA
    optimum (padding pairs change nothing; valid pairs at d >= c are read as unassigned).

    Args:
      est: (M, 2); est_valid: (M,) bool; truth: (N, 2); truth_valid: (N,) bool.
      c: () cut-off distance > 0 [m]; p: () order >= 1; alpha: must be 2.
    Returns:
      GospaResult; two empty sets give 0; empty vs n points gives (n c^p / 2)^(1/p).
    """
    if alpha != 2:
        raise ValueError(f"gospa: alpha={alpha!r} is not supported; expected alpha=2")
    est_valid = jnp.asarray(est_valid, bool)
    truth_valid = jnp.asarray(truth_valid, bool)
    diff = est[:, None, :2] - truth[None, :, :2]
    distance = jnp.hypot(diff[..., 0], diff[..., 1])
    both_valid = est_valid[:, None] & truth_valid[None, :]
    dtype = jnp.result_type(est, truth)
    c = jnp.asarray(c, dtype)
    cut_cost = jnp.power(c, p)
    cost = jnp.where(both_valid, jnp.power(jnp.minimum(distance, c), p), cut_cost)
    rows, cols = _optimal_pairs(cost)
    close = both_valid[rows, cols] & (distance[rows, cols] < c)
    localisation = jnp.where(close, jnp.power(distance[rows, cols], p), 0.0).sum()
    num_close = close.sum().astype(jnp.int32)
    num_missed = truth_valid.sum().astype(jnp.int32) - num_close
    num_false = est_valid.sum().astype(jnp.int32) - num_close
    missed = 0.5 * cut_cost * num_missed.astype(dtype)
    false = 0.5 * cut_cost * num_false.astype(dtype)
    return GospaResult(
        distance=jnp.power(localisation + missed + false, 1.0 / p),
        localisation=localisation,
        missed=missed,
        false=false,
        num_missed=num_missed,
        num_false=num_false,
    )
