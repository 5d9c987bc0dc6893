"""The smoother's least squares: its factors whitened, robustly weighted and linearised.

Unknowns: the poses x_0..x_{T-1} (3 columns each) then the landmark (or visit) positions
(2 columns each). Rows: 3 per move, 2 per observation, 2 per link, in that order. The
residuals and their Jacobian blocks come from ``residuals`` (the library's models in float64);
here they are whitened, weighted by the robust losses' IRLS weights and placed in a sparse
Jacobian whose pattern the associations fix once per problem.

Shapes: T moves, N observations, L positions, E links, R = 3 T + 2 N + 2 E rows.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
import scipy.sparse

from jaxslam.smoothing import residuals


class NoiseScales(NamedTuple):
    """Multipliers of the four noise groups' standard deviations (1: as in ``Params``).

    heading: moves' heading rows; translation: moves' translation rows (given the heading);
    range / bearing: the observations'. ``smooth_path(calibrate_rounds=n)`` estimates them.
    """

    heading: float = 1.0
    translation: float = 1.0
    range: float = 1.0
    bearing: float = 1.0


class Problem(NamedTuple):
    """One least squares: the fixed start, the measurements, their weights and the links."""

    start: np.ndarray  # (3,)
    delta: np.ndarray  # (T, 3)
    move_white: np.ndarray  # (T, 3, 3)
    obs_t: np.ndarray  # (N,)
    obs_id: np.ndarray  # (N,)
    obs_z: np.ndarray  # (N, 2)
    obs_std: np.ndarray  # (N, 2)
    huber: float
    links: np.ndarray = np.zeros((0, 2), np.int64)  # (E, 2) position indices tied together
    link_std: float = 1.0  # [m] std of a link's (l_a - l_b)
    link_threshold: float = 1.0  # Geman-McClure scale c on the whitened link norm


def rescaled(base: Problem, scales: NoiseScales) -> Problem:
    """``base`` (noise as in ``Params``) with the moves' whitening (T, 3, 3) divided and the
    observation stds (N, 2) multiplied by ``scales``."""
    move_scale = np.array([scales.heading, scales.translation, scales.translation])
    return base._replace(move_white=base.move_white / move_scale[None, :, None],
                         obs_std=base.obs_std * np.array([scales.range, scales.bearing]))


def geman_mcclure_weight(norm, threshold):
    """IRLS weight sqrt(rho'(n) / (2 n)) and rho(n) = c^2 n^2 / (c^2 + n^2) (c = threshold).

    A redescending loss: a link stretched far beyond c costs at most c^2 and pulls on nothing.
    """
    c2 = threshold**2
    return c2 / (c2 + norm**2), c2 * norm**2 / (c2 + norm**2)


def huber_weight(norm, threshold):
    """IRLS weight sqrt(rho'(n) / (2 n)) per whitened residual norm, and rho(n)."""
    inside = norm <= threshold
    rho = np.where(inside, norm**2, 2.0 * threshold * norm - threshold**2)
    weight = np.where(inside, 1.0, np.sqrt(threshold / np.maximum(norm, 1e-12)))
    return weight, rho


class Whitened(NamedTuple):
    """Whitened residuals and Jacobian blocks (before any robust weighting)."""

    move: np.ndarray  # (T, 3)
    move_start: np.ndarray  # (T, 3, 3) d move / d x_{t-1}
    move_end: np.ndarray  # (T, 3, 3) d move / d x_t
    obs: np.ndarray  # (N, 2)
    obs_pose: np.ndarray  # (N, 2, 3)
    obs_point: np.ndarray  # (N, 2, 2)
    link: np.ndarray  # (E, 2) (l_a - l_b) / link_std; Jacobians +-I / link_std


def whitened(problem: Problem, path, landmark) -> Whitened:
    """``Whitened`` at poses (T, 3) and landmark (or visit) positions (L, 2)."""
    previous = np.concatenate([problem.start[None], path[:-1]], axis=0)
    move, jac_start, jac_end = residuals.move_residuals(previous, path, problem.delta)
    white = problem.move_white
    obs, jac_pose, jac_point = residuals.observation_residuals(
        path[problem.obs_t], landmark[problem.obs_id], problem.obs_z)
    inverse_std = 1.0 / problem.obs_std
    # Links are linear in the positions: their residual and +-I / std blocks need no model.
    link = (landmark[problem.links[:, 0]] - landmark[problem.links[:, 1]]) / problem.link_std
    return Whitened(np.einsum("nij,nj->ni", white, move), white @ jac_start, white @ jac_end,
                    obs * inverse_std, jac_pose * inverse_std[:, :, None],
                    jac_point * inverse_std[:, :, None], link)


def robust_cost(problem: Problem, white: Whitened):
    """sum ||e_move||^2 + sum rho_Huber(||e_obs||) + sum rho_GM(||e_link||), and the IRLS
    weights of the observations (N,) and links (E,)."""
    weight, rho = huber_weight(np.linalg.norm(white.obs, axis=1), problem.huber)
    link_weight, link_rho = geman_mcclure_weight(np.linalg.norm(white.link, axis=1),
                                                 problem.link_threshold)
    return np.sum(white.move**2) + np.sum(rho) + np.sum(link_rho), weight, link_weight


def cost(problem: Problem, path, landmark):
    """The robust cost at poses (T, 3) and positions (L, 2)."""
    return robust_cost(problem, whitened(problem, path, landmark))[0]


def neg2_log_likelihood(problem: Problem, path, landmark) -> float:
    """-2 log L of poses (T, 3) and positions (L, 2) under ``problem``'s noise, up to a
    constant: the robust cost plus the Gaussian normalisers,

        cost + sum_t log det C_t + sum_n 2 log(sigma_r,n sigma_b,n),

    with C_t = (W_t^T W_t)^-1 from the moves' whitening W_t (``move_white``) and the
    observations' stds (``obs_std``). Huber's loss is read as a density proportional to
    exp(-rho / 2) in whitened units, whose normaliser depends on its threshold alone: a
    constant of the problem's rows. Links (``visit_gap``) count by their Geman-McClure loss
    alone (exp(-rho / 2) of a bounded loss has no finite normaliser), so compare problems
    with the same links. Two problems with the same rows, threshold and links, whose noise
    (scales) or measured moves differ, compare by this value.
    """
    _, log_abs_det_white = np.linalg.slogdet(problem.move_white)
    return float(cost(problem, path, landmark) - 2.0 * np.sum(log_abs_det_white)
                 + 2.0 * np.sum(np.log(problem.obs_std)))


class Pattern(NamedTuple):
    """The Jacobian's sparsity of one problem, built once and filled at every linearisation.

    indptr, indices: CSR structure; order: (nnz,) position in the concatenated block values
    (``linearize``) of each CSR entry; shape: (rows, columns). With a repeated (row, column)
    pair (a link from a position to itself) order is None and rows, cols (one per value)
    are summed at every linearisation instead.
    """

    indptr: np.ndarray | None
    indices: np.ndarray | None
    order: np.ndarray | None
    shape: tuple
    rows: np.ndarray | None = None
    cols: np.ndarray | None = None


def jacobian_pattern(problem: Problem, steps: int, num_positions: int) -> Pattern:
    """Rows and columns of every Jacobian entry (``linearize``'s layout), as CSR.

    Rows: 3 per move, 2 per observation, 2 per link. Columns: 3 per pose, then 2 per
    landmark (or visit) position. No (row, column) pair occurs twice (but in a link from a
    position to itself), so the CSR entries are a permutation of the block values.
    """
    t = np.arange(steps)
    move_rows = np.broadcast_to(3 * t[:, None, None] + np.arange(3)[None, :, None],
                                (steps, 3, 3))
    pose_cols = np.broadcast_to(3 * t[:, None, None] + np.arange(3)[None, None, :],
                                (steps, 3, 3))
    rows = [move_rows, move_rows[1:]]
    cols = [pose_cols, (pose_cols - 3)[1:]]  # x_{-1} is fixed: no column for it
    num_obs = len(problem.obs_t)
    obs_rows = 3 * steps + 2 * np.arange(num_obs)[:, None, None] + np.arange(2)[None, :, None]
    rows += [np.broadcast_to(obs_rows, (num_obs, 2, 3)),
             np.broadcast_to(obs_rows, (num_obs, 2, 2))]
    cols += [np.broadcast_to(3 * problem.obs_t[:, None, None] + np.arange(3)[None, None, :],
                             (num_obs, 2, 3)),
             np.broadcast_to(3 * steps + 2 * problem.obs_id[:, None, None]
                             + np.arange(2)[None, None, :], (num_obs, 2, 2))]
    num_links = len(problem.links)
    link_rows = (3 * steps + 2 * num_obs + 2 * np.arange(num_links)[:, None]
                 + np.arange(2)[None, :])
    for side in (0, 1):
        rows.append(link_rows)
        cols.append(3 * steps + 2 * problem.links[:, side, None] + np.arange(2)[None, :])
    rows = np.concatenate([r.ravel() for r in rows])
    cols = np.concatenate([c.ravel() for c in cols])
    shape = (3 * steps + 2 * num_obs + 2 * num_links, 3 * steps + 2 * num_positions)
    template = scipy.sparse.csr_matrix((np.arange(1, rows.size + 1, dtype=np.float64),
                                        (rows, cols)), shape=shape)
    if template.nnz != rows.size:  # a repeated entry: sum at every linearisation
        return Pattern(None, None, None, shape, rows, cols)
    return Pattern(template.indptr, template.indices,
                   template.data.astype(np.int64) - 1, shape)


def linearize(problem: Problem, path, landmark, pattern: Pattern | None = None):
    """Robustly weighted whitened residual (R,), Jacobian (R, n) CSR and robust cost.

    Rows: 3 per move, 2 per observation (Huber IRLS weight), 2 per link (Geman-McClure IRLS
    weight). Columns: 3 per pose, then 2 per landmark (or visit) position. ``pattern``:
    ``jacobian_pattern`` of this problem (built here when None).
    """
    steps = path.shape[0]
    if pattern is None:
        pattern = jacobian_pattern(problem, steps, landmark.shape[0])
    white = whitened(problem, path, landmark)
    total, weight, link_weight = robust_cost(problem, white)
    jac_pose = white.obs_pose * weight[:, None, None]
    jac_point = white.obs_point * weight[:, None, None]
    # Links: +I / std on landmark a and -I / std on landmark b, IRLS-weighted.
    link_value = (link_weight / problem.link_std)[:, None] * np.ones((1, 2))
    values = np.concatenate([white.move_end.ravel(), white.move_start[1:].ravel(),
                             jac_pose.ravel(), jac_point.ravel(), link_value.ravel(),
                             -link_value.ravel()])
    if pattern.order is None:
        jacobian = scipy.sparse.csr_matrix((values, (pattern.rows, pattern.cols)),
                                           shape=pattern.shape)
    else:
        jacobian = scipy.sparse.csr_matrix((values[pattern.order], pattern.indices,
                                            pattern.indptr), shape=pattern.shape)
    residual = np.concatenate([white.move.ravel(), (white.obs * weight[:, None]).ravel(),
                               (white.link * link_weight[:, None]).ravel()])
    return residual, jacobian, total
