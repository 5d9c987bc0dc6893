"""Levenberg-Marquardt on the sparse normal equations, and the noise groups' variance factors.

Both run on the host in float64 with ``scipy.sparse``. The associations fix the Jacobian's
sparsity, so its pattern (``problem.jacobian_pattern``) and the elimination order
(``Factorizer``) are found once per problem and reused by every step, every damping retry
and every calibration round.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
import scipy.sparse
import scipy.sparse.linalg

from jaxslam.smoothing import problem as least_squares
from jaxslam.smoothing.residuals import wrap


class Factorizer:
    """Sparse LU solves of the symmetric matrices of one problem (one sparsity pattern).

    The first matrix is factorised with SuperLU's minimum-degree order on the symmetric
    pattern (an order of magnitude faster than ``spsolve``'s default column order on
    Victoria Park's 24k unknowns); its order is kept and every later matrix (each damping,
    each LM step, the variance components) is factorised in it directly. The matrices are
    symmetric positive definite (J^T J plus a positive diagonal), so the pivots are taken on
    the diagonal (``diag_pivot_thresh=0``: LU without pivoting is stable there, as Cholesky
    is), which keeps the order's fill and spares a minimum-degree search and threshold
    pivoting at every step. A matrix of another size gets a new order.
    """

    def __init__(self):
        self.order = None  # (n,) the column order of the first factorisation

    def __call__(self, matrix):
        """A function rhs (n,) or (n, m) -> matrix^-1 rhs."""
        matrix = scipy.sparse.csc_matrix(matrix)
        if self.order is None or len(self.order) != matrix.shape[0]:
            lu = scipy.sparse.linalg.splu(matrix, permc_spec="MMD_AT_PLUS_A",
                                          diag_pivot_thresh=0.0,
                                          options=dict(SymmetricMode=True))
            self.order = np.argsort(lu.perm_c)  # A[:, order] is the factorised A Pc
            return lu.solve
        order = self.order
        lu = scipy.sparse.linalg.splu(matrix[order][:, order].tocsc(), permc_spec="NATURAL",
                                      diag_pivot_thresh=0.0, options=dict(SymmetricMode=True))

        def solve(rhs):
            out = np.empty_like(rhs)
            out[order] = lu.solve(np.ascontiguousarray(rhs[order]))
            return out

        return solve


def levenberg_marquardt(problem: least_squares.Problem, path, landmark, iterations: int,
                        tol: float, damping: float, factorize: Factorizer | None = None):
    """(path (T, 3), landmark (L, 2), costs, steps tried, converged) from the given start.

    Each step solves (J^T J + lambda diag(J^T J)) dx = -J^T e; lambda starts at
    damping * mean(diag(J^T J)), falls 10x after a step that lowers the cost and rises 10x
    (retry) after one that does not. ``factorize``: the problem's ``Factorizer`` (its order
    is reused; a new one when None).
    """
    steps = path.shape[0]
    factorize = Factorizer() if factorize is None else factorize
    pattern = least_squares.jacobian_pattern(problem, steps, landmark.shape[0])
    costs = [least_squares.cost(problem, path, landmark)]
    lam, converged, step = None, False, 0
    for step in range(1, iterations + 1):
        residual, jacobian, cost = least_squares.linearize(problem, path, landmark, pattern)
        hessian = (jacobian.T @ jacobian).tocsc()
        gradient = jacobian.T @ residual
        diagonal = hessian.diagonal()
        if lam is None:
            lam = damping * float(np.mean(diagonal))
        while True:
            damped = hessian + scipy.sparse.diags(lam * np.maximum(diagonal, 1e-9))
            update = factorize(damped)(-gradient)
            new_path = path + update[:3 * steps].reshape(steps, 3)
            new_path[:, 2] = wrap(new_path[:, 2])
            new_landmark = landmark + update[3 * steps:].reshape(-1, 2)
            new_cost = least_squares.cost(problem, new_path, new_landmark)
            if new_cost < cost or lam > 1e8:
                break
            lam *= 10.0
        if not new_cost < cost:  # also a NaN cost: never take that step
            converged = True  # no damping lowers the cost: a minimum to working precision
            break
        path, landmark = new_path, new_landmark
        costs.append(new_cost)
        lam = max(lam / 10.0, 1e-15)
        if (cost - new_cost) <= tol * cost:
            converged = True
            break
    return path, landmark, np.asarray(costs), step, converged


def group_rows(steps: int, num_obs: int):
    """Row indices of the whitened residual per ``NoiseScales`` group (heading, translation,
    range, bearing)."""
    move = 3 * np.arange(steps)
    obs = 3 * steps + 2 * np.arange(num_obs)
    return (move, np.concatenate([move + 1, move + 2]), obs, obs + 1)


class VarianceComponents(NamedTuple):
    """Per noise group (heading, translation, range, bearing): factor (4,), the variance
    factor (e_g^T e_g) / r_g; redundancy (4,), r_g; degrees_of_freedom (4,), nu_g =
    1 / (S^-1)_gg, those of the factor with all four estimated from the same residuals
    (``variance_factors``)."""

    factor: np.ndarray
    redundancy: np.ndarray
    degrees_of_freedom: np.ndarray


def variance_factors(residual, jacobian, steps: int, num_obs: int, probes: int = 16,
                     factorize=None) -> VarianceComponents:
    """Helmert/Forstner variance components: per group g, (e_g^T e_g) / r_g.

    e are the whitened residuals (R,) at the solution, J (R, n) their Jacobian and
    r_g = n_g - tr(J_g H^-1 J_g^T) the group's redundancy (H = J^T J), the trace by
    Hutchinson's estimator with ``probes`` fixed-seed Rademacher vectors. A factor of 1 means
    the group's noise is as assumed. r_g, not n_g, is what the residuals keep: E[e_g^T e_g] =
    r_g sigma_g^2 at the assumed scales (the factor's degrees of freedom are fewer still,
    below). The path absorbs the rest: where the
    observations pin each pose less well than one move's odometry does, most of a move's
    error is explained by the path and r_g is a small part of n_g. The trace's own error:
    with Rademacher probes z (z^T z = n_g exactly) the estimate is n_g - mean(z^T P_g z) =
    mean(z^T (I - P_g) z), P_g = J_g H^-1 J_g^T, whose variance is 2 sum_{i != j} (P_g)_ij^2
    / probes <= 2 ||I - P_g||_F^2 / probes <= 2 r_g / probes (the eigenvalues of I - P_g lie
    in [0, 1], as H >= J_g^T J_g). So the error is at most sqrt(2 r_g / probes) however
    large n_g is: a redundancy of 2 is resolved to +-0.5 or better with 16 probes, not lost in
    the noise of n_g (Victoria Park's first M-step: 2,531.9 of 7,230 heading rows with 16
    probes, 2,529.6 with 256). It is clipped at 1.

    The factors' degrees of freedom. With R = I - J H^-1 J^T (the residuals are e = R eps)
    and E_g the rows of group g, Cov(e^T E_g e, e^T E_h e) = 2 S_gh for Gaussian noise at the
    assumed scales, S_gh = tr(E_g R E_h R); the variance components at their fixed point solve
    S theta = q (q_g = e^T E_g e; sum_h S_gh = r_g, so at theta = 1 this is the factor above),
    hence Cov(theta) = 2 S^-1 (Koch, "Parameter Estimation and Hypothesis Testing in Linear
    Models", section 3.6; Forstner 1979). nu_g = 1 / (S^-1)_gg, so that the factor's relative
    error is sqrt(2 / nu_g): nu_g <= S_gg <= r_g, smaller where the path shares a move's
    error with the observations (on the simulated smooth loops of
    ``experiments/self_calibration.py`` at the true noise: heading r_g 79-83, S_gg 41-45,
    nu_g about 40, and the chi-square figure 0.08 becomes 0.11). S comes from the same probes:
    for z on the rows of g, E[|E_h R z|^2] = S_hg (error at most sqrt(2 S_hg / probes), as
    above), averaged with S_gh. Groups without rows get nu_g = r_g = 1. ``factorize``: the
    problem's ``Factorizer`` (a new one when None). Returns ``VarianceComponents``.
    """
    hessian = jacobian.T @ jacobian
    # A landmark index no observation uses has an empty column; the tiny ridge keeps H
    # invertible and leaves the traces unchanged (those columns never meet a probe).
    hessian = (hessian + scipy.sparse.diags(
        np.full(hessian.shape[0], 1e-12 * float(np.mean(hessian.diagonal()))))).tocsc()
    solve = (Factorizer() if factorize is None else factorize)(hessian)
    rng = np.random.default_rng(0)
    groups = group_rows(steps, num_obs)
    factors, redundancies = [], []
    coupling = np.zeros((len(groups), len(groups)))  # S_hg, probes on g
    for g, rows in enumerate(groups):
        probe = np.zeros((jacobian.shape[0], probes))
        probe[rows] = rng.choice([-1.0, 1.0], size=(rows.size, probes))
        projected = jacobian.T @ probe  # (n, probes), one solve for all probes
        solved = solve(projected)
        trace = float(np.sum(projected * solved)) / probes
        redundancy = max(rows.size - trace, 1.0)
        factors.append(float(np.sum(residual[rows] ** 2) / redundancy))
        redundancies.append(redundancy)
        kept = probe - jacobian @ solved  # R z, (R, probes)
        coupling[:, g] = [float(np.sum(kept[other] ** 2)) / probes for other in groups]
    redundancies = np.asarray(redundancies)
    return VarianceComponents(np.asarray(factors), redundancies,
                              factor_degrees_of_freedom(0.5 * (coupling + coupling.T),
                                                        redundancies))


def factor_degrees_of_freedom(coupling, redundancy, max_condition: float = 1e10):
    """(G,) nu_g = 1 / (S^-1)_gg of the groups with a positive S_gg (``variance_factors``),
    within [1, r_g]; r_g for the others (no rows). coupling: (G, G) S; redundancy: (G,) r_g.

    An S that is singular or nearly so (condition number over ``max_condition``, or not
    finite) has groups the residuals cannot tell apart: their factors' variance is unbounded,
    so every group with rows gets the least, nu = 1."""
    coupling, redundancy = np.asarray(coupling, np.float64), np.asarray(redundancy, np.float64)
    present = np.diag(coupling) > 0.0
    dof = redundancy.copy()
    block = coupling[np.ix_(present, present)]
    if present.any():
        dof[present] = 1.0
        if np.all(np.isfinite(block)) and np.linalg.cond(block) < max_condition:
            diagonal = np.diag(np.linalg.inv(block))
            positive = diagonal > 0.0
            dof[np.flatnonzero(present)[positive]] = 1.0 / diagonal[positive]
    return np.clip(dof, 1.0, np.maximum(redundancy, 1.0))
