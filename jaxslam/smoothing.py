"""Smoothing of a FastSLAM run: one particle's data association, re-solved over the whole path.

A FastSLAM particle is a whole path hypothesis with the map built along it. Once the run is
over, following the final best particle back through its ancestors (``Trace.lineage`` from
``run_filter(..., record_lineage=True)``) gives, for every observation z_{t,k}, the landmark
that particle associated it with (or created from it). With those associations fixed, the
maximum a-posteriori path and map are the nonlinear least squares of GraphSLAM (Thrun et al.,
Probabilistic Robotics, ch. 11):

    min_{x_{0:T-1}, m}  sum_t   || C_t^-1 (x_{t-1} (-) x_t - delta_t) ||^2
                      + sum_t,k rho(|| diag(sigma_r, sigma_b)^-1 (h(x_t, m_j(t,k)) - z_t,k) ||)

* x_{-1} is the fixed start pose; x_{t-1} (-) x_t is ``geometry.relative`` (the move in the
  frame of x_{t-1}) and delta_t the measured move of control t.
* C_t C_t^T = J_t diag(s_t^2) J_t^T + eps^2 diag(1, 1, 0): the motion noise of Geiser et al. 2023
  Eq. (1) (std s_t = ``motion.odometry_std``) carried from (rot1, trans, rot2) to the relative
  pose by J_t = d delta / d(rot1, trans, rot2). The floor eps (``MOVE_STD_FLOOR``) keeps C_t
  invertible for a pure turn.
* h is the range-bearing model and (sigma_r, sigma_b) = ``ekf.measurement_std`` at the
  measured range. rho is Huber's loss with threshold ``huber`` (whitened units), so a wrong
  association costs linearly rather than quadratically.

This undoes what a particle filter cannot: a heading error made where no landmark is seen is
spread back over that stretch when the loop closes, as EKF-SLAM's correlations do. The
associations are the filter's. With ``visit_gap`` the loop closures among them are revised:
each landmark is split into visits (its sightings with no long gap), each visit has its own
position, and visits of one landmark are tied by link factors

    sum_(a,b) rho_GM(|| (m_a - m_b) / sigma_link ||),   rho_GM(n) = c^2 n^2 / (c^2 + n^2),

a redescending (Geman-McClure) loss bounded by c^2, so a wrong loop closure, whose
observations agree among themselves and so escape Huber's loss, is switched off as a whole
(the switchable-constraint idea of Sunderhauf and Protzel, in closed form as in Agarwal et
al.'s dynamic covariance scaling).

The history comes from ``lineage.trace_lineage`` (JAX, jit/vmap over runs). The least squares is
solved on the host in float64 with Levenberg-Marquardt steps on the sparse normal equations
(``scipy.sparse``, a minimum-degree LU); its Jacobian is block sparse (3x3 move blocks on a
band, 2x3 and 2x2 observation blocks), so one step on the 7,230-scan Victoria Park log (24k
unknowns) takes 0.2-0.4 s on this CPU (benchmarks/smoothing.py: 379-419 ms a step at T = 7230).
The associations fix the sparsity pattern, so the Jacobian's pattern (``_jacobian_pattern``) and
the elimination order (``_Factorizer``) are found once per problem and reused by every LM step,
every damping retry and every calibration round.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
import scipy.sparse
import scipy.sparse.linalg

from jaxslam.lineage import LineagePath, landmark_identities
from jaxslam.types import Params

MOVE_STD_FLOOR = 1e-3  # [m] added in x and y to every move covariance (a pure turn is singular)


class NoiseScales(NamedTuple):
    """Multipliers of the four noise groups' standard deviations (1: as in ``Params``).

    heading: moves' heading rows; translation: moves' translation rows (given the heading);
    range / bearing: the observations'. ``smooth_path(calibrate_rounds=n)`` estimates them.
    """

    heading: float = 1.0
    translation: float = 1.0
    range: float = 1.0
    bearing: float = 1.0


class Visits(NamedTuple):
    """The visits of ``smooth_path(visit_gap=...)`` (``split_visits``) and their links.

    position: (V, 2) smoothed position of each visit; visit_of_obs: (T, K) (-1: none);
    landmark: (V,) the landmark of each visit; links: (E, 2) linked visit pairs;
    link_weight: (E,) final IRLS weight of each link, 1 kept ... 0 dropped (a loop closure
    the data contradict).
    """

    position: np.ndarray
    visit_of_obs: np.ndarray
    landmark: np.ndarray
    links: np.ndarray
    link_weight: np.ndarray


def _largest_visit(position, visit_of_obs, visit_landmark):
    """(L, 2): each landmark at its visit with the most observations."""
    count = np.bincount(visit_of_obs[visit_of_obs >= 0], minlength=len(visit_landmark))
    order = np.lexsort((-count, visit_landmark))  # by landmark, largest visit first
    first = np.ones(len(order), bool)
    first[1:] = visit_landmark[order][1:] != visit_landmark[order][:-1]
    landmark = np.zeros((int(visit_landmark.max(initial=-1)) + 1, 2))
    landmark[visit_landmark[order][first]] = position[order][first]
    return landmark


class Smoothed(NamedTuple):
    """Result of ``smooth_path``.

    path: (T, 3) smoothed poses; landmark: (L, 2) smoothed landmark positions (L = the
    largest index in ``landmark_of_obs`` + 1; an index with no observation stays at 0);
    landmark_of_obs: (T, K) index into ``landmark`` of each observation (-1: none);
    cost: (I + 1,) robust cost before the first and after each accepted step;
    iterations: steps tried; converged: the last relative cost decrease was under ``tol``;
    noise_scales: the ``NoiseScales`` used (estimated ones with ``calibrate_rounds``);
    visits: ``Visits`` with ``visit_gap`` (each landmark is then at its largest visit), else None.
    """

    path: np.ndarray
    landmark: np.ndarray
    landmark_of_obs: np.ndarray
    cost: np.ndarray
    iterations: int
    converged: bool
    noise_scales: NoiseScales = NoiseScales()
    visits: Visits | None = None


# --------------------------------------------------------------------------------------------
# Least squares (host, float64)


def _wrap(angle):
    return (angle + np.pi) % (2.0 * np.pi) - np.pi


def move_residuals(start, end, delta):
    """Residual e = start (-) end - delta (3,) per move and its Jacobians.

    Args:
      start, end: (N, 3) poses; delta: (N, 3) measured relative poses.
    Returns:
      e (N, 3), d e / d start (N, 3, 3), d e / d end (N, 3, 3).
    """
    dx, dy = end[:, 0] - start[:, 0], end[:, 1] - start[:, 1]
    c, s = np.cos(start[:, 2]), np.sin(start[:, 2])
    rel = np.stack([c * dx + s * dy, -s * dx + c * dy, end[:, 2] - start[:, 2]], axis=1)
    error = rel - delta
    error[:, 2] = _wrap(error[:, 2])
    zero, one = np.zeros_like(c), np.ones_like(c)
    jac_start = np.stack([np.stack([-c, -s, -s * dx + c * dy], 1),
                          np.stack([s, -c, -c * dx - s * dy], 1),
                          np.stack([zero, zero, -one], 1)], axis=1)
    jac_end = np.stack([np.stack([c, s, zero], 1), np.stack([-s, c, zero], 1),
                        np.stack([zero, zero, one], 1)], axis=1)
    return error, jac_start, jac_end


def observation_residuals(pose, point, z):
    """Residual e = h(pose, point) - z (range, bearing) per observation and its Jacobians.

    Args:
      pose: (N, 3); point: (N, 2); z: (N, 2).
    Returns:
      e (N, 2), d e / d pose (N, 2, 3), d e / d point (N, 2, 2).
    """
    dx, dy = point[:, 0] - pose[:, 0], point[:, 1] - pose[:, 1]
    q = np.maximum(dx**2 + dy**2, 1e-12)
    r = np.sqrt(q)
    error = np.stack([r - z[:, 0], _wrap(np.arctan2(dy, dx) - pose[:, 2] - z[:, 1])], axis=1)
    jac_point = np.stack([np.stack([dx / r, dy / r], 1), np.stack([-dy / q, dx / q], 1)],
                         axis=1)
    jac_pose = np.concatenate([-jac_point, np.array([0.0, -1.0])[None, :, None]
                               * np.ones((len(r), 1, 1))], axis=2)
    return error, jac_pose, jac_point


def move_whitening(odometry, params: Params, std_floor: float = MOVE_STD_FLOOR):
    """Measured moves delta (N, 3) and whitening W (N, 3, 3), W^T W = C^-1 (module docstring).

    W is the inverse Cholesky factor of C taken in the order (theta, x, y), so whitened row 0
    is the heading error alone, e_theta / sqrt(C_theta_theta), and rows 1-2 the translation
    error given it (the groups of ``NoiseScales``).

    Args:
      odometry: (N, 3) measured (rot1, trans, rot2).
    """
    odometry = np.asarray(odometry, np.float64)
    rot1, trans, rot2 = odometry.T
    heading = rot1
    delta = np.stack([trans * np.cos(heading), trans * np.sin(heading), _wrap(rot1 + rot2)], 1)
    coef = [np.asarray(c, np.float64) for c in (params.rot1_noise, params.trans_noise,
                                                params.rot2_noise)]
    std = np.stack([coef[0][0] * abs(trans) + coef[0][1] * abs(rot1) + coef[0][2],
                    coef[1][0] * abs(trans) + coef[1][1] * (abs(rot1) + abs(rot2))
                    + coef[1][2],
                    coef[2][0] * abs(trans) + coef[2][1] * abs(rot2) + coef[2][2]], 1)
    zero, one = np.zeros_like(trans), np.ones_like(trans)
    jac = np.stack([np.stack([-trans * np.sin(heading), np.cos(heading), zero], 1),
                    np.stack([trans * np.cos(heading), np.sin(heading), zero], 1),
                    np.stack([one, zero, one], 1)], axis=1)
    cov = np.einsum("nij,nj,nkj->nik", jac, std**2, jac)
    cov[:, 0, 0] += std_floor**2
    cov[:, 1, 1] += std_floor**2
    if np.any(cov[:, 2, 2] <= 0.0):
        raise ValueError(f"move {int(np.argmax(cov[:, 2, 2] <= 0.0))} has zero heading noise: "
                         "give rot1_noise or rot2_noise a positive constant term (c1 / c3)")
    order = np.array([2, 0, 1])  # (theta, x, y)
    white_ordered = np.linalg.inv(np.linalg.cholesky(cov[:, order][:, :, order]))
    return delta, white_ordered[:, :, np.argsort(order)]


def _observation_std(z_range, params: Params):
    range_noise = np.asarray(params.range_noise, np.float64)
    bearing_noise = np.asarray(params.bearing_noise, np.float64)
    sigma_r = np.maximum(range_noise[0] * z_range + range_noise[1],
                         float(params.range_std_floor))
    sigma_b = np.maximum(bearing_noise[0] * z_range + bearing_noise[1],
                         float(params.bearing_std_floor))
    return np.stack([sigma_r, sigma_b], axis=1)


def initial_landmarks(path, z, landmark_of_obs, num_landmarks: int):
    """(L, 2) mean over each landmark's observations of pose (+) inverse range-bearing."""
    t, k = np.nonzero(landmark_of_obs >= 0)
    pose, obs = path[t], z[t, k]
    heading = pose[:, 2] + obs[:, 1]
    point = pose[:, :2] + obs[:, :1] * np.stack([np.cos(heading), np.sin(heading)], 1)
    ids = landmark_of_obs[t, k]
    total = np.zeros((num_landmarks, 2))
    np.add.at(total, ids, point)
    count = np.bincount(ids, minlength=num_landmarks)
    return total / np.maximum(count, 1)[:, None]


def split_visits(landmark_of_obs, visit_gap: int, link_neighbours: int = 2):
    """Split each landmark's observations into visits and pair the visits of one landmark.

    A visit is a run of a landmark's observations with no gap of more than ``visit_gap``
    steps. Each visit gets its own position in the least squares; a link factor ties it to
    the ``link_neighbours`` visits of the same landmark before it (so one wrong visit in the
    middle does not cut the chain). A link is a loop closure the filter decided on; giving
    it a redescending loss lets the smoother drop the ones the rest of the data contradict.

    Args:
      landmark_of_obs: (T, K) landmark index per observation, -1 for none.
      visit_gap: steps without an observation of a landmark that end a visit (>= 1).
      link_neighbours: earlier visits each visit is linked to (>= 1).
    Returns:
      visit_of_obs (T, K) visit index (-1 where ``landmark_of_obs`` is -1),
      visit_landmark (V,) the landmark of each visit, links (E, 2) visit pairs (a < b).
    """
    check_visit_options(visit_gap, link_neighbours)
    landmark_of_obs = np.asarray(landmark_of_obs)
    if landmark_of_obs.ndim != 2:
        raise ValueError(f"landmark_of_obs must be (T, K); got shape {landmark_of_obs.shape}")
    t, k = np.nonzero(landmark_of_obs >= 0)
    ids = landmark_of_obs[t, k]
    order = np.lexsort((t, ids))  # by landmark, then time
    ids_sorted, t_sorted = ids[order], t[order]
    starts = np.ones(len(order), bool)
    starts[1:] = (ids_sorted[1:] != ids_sorted[:-1]) | (np.diff(t_sorted) > visit_gap)
    visit_sorted = np.cumsum(starts) - 1
    visit_of_obs = np.full(landmark_of_obs.shape, -1, np.int64)
    visit_of_obs[t[order], k[order]] = visit_sorted
    visit_landmark = ids_sorted[starts]
    # Visits of one landmark are consecutive indices: pair v with v - j when same landmark.
    visit = np.arange(len(visit_landmark))
    links = [np.stack([visit[:-j], visit[j:]], 1)[visit_landmark[:-j] == visit_landmark[j:]]
             for j in range(1, link_neighbours + 1) if j < len(visit)]
    links = np.concatenate(links) if links else np.zeros((0, 2), np.int64)
    return visit_of_obs, visit_landmark, links


def check_visit_options(visit_gap, link_neighbours=2):
    """ValueError unless ``visit_gap`` and ``link_neighbours`` are integers >= 1 (callers
    that smooth after a long filter run check first, so a bad value costs no run)."""
    for name, value in (("visit_gap", visit_gap), ("link_neighbours", link_neighbours)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
            raise ValueError(f"{name} must be an integer >= 1 (steps / visits); got {value!r}")


def _geman_mcclure_weight(norm, threshold):
    """IRLS weight sqrt(rho'(n) / (2 n)) and rho(n) = c^2 n^2 / (c^2 + n^2) (c = threshold).

    A redescending loss: a link stretched far beyond c costs at most c^2 and pulls on nothing.
    """
    c2 = threshold**2
    return c2 / (c2 + norm**2), c2 * norm**2 / (c2 + norm**2)


def _huber_weight(norm, threshold):
    """IRLS weight sqrt(rho'(n) / (2 n)) per whitened residual norm, and rho(n)."""
    inside = norm <= threshold
    rho = np.where(inside, norm**2, 2.0 * threshold * norm - threshold**2)
    weight = np.where(inside, 1.0, np.sqrt(threshold / np.maximum(norm, 1e-12)))
    return weight, rho


class _Problem(NamedTuple):
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


def _rescaled(problem: _Problem, base_white, base_std, scales: NoiseScales) -> _Problem:
    move_scale = np.array([scales.heading, scales.translation, scales.translation])
    return problem._replace(move_white=base_white / move_scale[None, :, None],
                            obs_std=base_std * np.array([scales.range, scales.bearing]))


def _group_rows(steps: int, num_obs: int):
    """Row indices of the whitened residual per ``NoiseScales`` group."""
    move = 3 * np.arange(steps)
    obs = 3 * steps + 2 * np.arange(num_obs)
    return (move, np.concatenate([move + 1, move + 2]), obs, obs + 1)


def _variance_factors(residual, jacobian, steps: int, num_obs: int, probes: int = 16,
                      factorize=None):
    """Helmert/Forstner variance components: per group g, (e_g^T e_g) / r_g.

    e are the whitened residuals at the solution and r_g = n_g - tr(J_g H^-1 J_g^T) the
    group's redundancy (H = J^T J), the trace by Hutchinson's estimator with ``probes``
    fixed-seed Rademacher vectors. A factor of 1 means the group's noise is as assumed.
    ``factorize``: the problem's ``_Factorizer`` (a new one when None).
    """
    hessian = jacobian.T @ jacobian
    # A landmark index no observation uses has an empty column; the tiny ridge keeps H
    # invertible and leaves the traces unchanged (those columns never meet a probe).
    hessian = (hessian + scipy.sparse.diags(
        np.full(hessian.shape[0], 1e-12 * float(np.mean(hessian.diagonal()))))).tocsc()
    solve = (_Factorizer() if factorize is None else factorize)(hessian)
    rng = np.random.default_rng(0)
    factors = []
    for rows in _group_rows(steps, num_obs):
        probe = np.zeros((jacobian.shape[0], probes))
        probe[rows] = rng.choice([-1.0, 1.0], size=(rows.size, probes))
        projected = jacobian.T @ probe  # (n, probes), one solve for all probes
        trace = float(np.sum(projected * solve(projected))) / probes
        redundancy = max(rows.size - trace, 1.0)
        factors.append(float(np.sum(residual[rows] ** 2) / redundancy))
    return np.asarray(factors)


class _Whitened(NamedTuple):
    """Whitened residuals and Jacobian blocks (before any robust weighting)."""

    move: np.ndarray  # (T, 3)
    move_start: np.ndarray  # (T, 3, 3) d move / d x_{t-1}
    move_end: np.ndarray  # (T, 3, 3) d move / d x_t
    obs: np.ndarray  # (N, 2)
    obs_pose: np.ndarray  # (N, 2, 3)
    obs_point: np.ndarray  # (N, 2, 2)
    link: np.ndarray  # (E, 2) (l_a - l_b) / link_std; Jacobians +-I / link_std


def _whitened(problem: _Problem, path, landmark) -> _Whitened:
    """``_Whitened`` at poses (T, 3) and landmark (or visit) positions (L, 2)."""
    previous = np.concatenate([problem.start[None], path[:-1]], axis=0)
    error, jac_start, jac_end = move_residuals(previous, path, problem.delta)
    white = problem.move_white
    obs_err, jac_pose, jac_point = observation_residuals(
        path[problem.obs_t], landmark[problem.obs_id], problem.obs_z)
    inverse_std = 1.0 / problem.obs_std
    link_res = (landmark[problem.links[:, 0]] - landmark[problem.links[:, 1]]) / problem.link_std
    return _Whitened(np.einsum("nij,nj->ni", white, error), white @ jac_start,
                     white @ jac_end, obs_err * inverse_std, jac_pose * inverse_std[:, :, None],
                     jac_point * inverse_std[:, :, None], link_res)


def _robust_cost(problem: _Problem, white: _Whitened):
    """sum ||e_move||^2 + sum rho_Huber(||e_obs||) + sum rho_GM(||e_link||), and the IRLS
    weights of the observations (N,) and links (E,)."""
    weight, rho = _huber_weight(np.linalg.norm(white.obs, axis=1), problem.huber)
    link_weight, link_rho = _geman_mcclure_weight(np.linalg.norm(white.link, axis=1),
                                                  problem.link_threshold)
    return np.sum(white.move**2) + np.sum(rho) + np.sum(link_rho), weight, link_weight


def _cost(problem: _Problem, path, landmark):
    return _robust_cost(problem, _whitened(problem, path, landmark))[0]


class _Pattern(NamedTuple):
    """The Jacobian's sparsity of one problem, built once and filled at every linearisation.

    indptr, indices: CSR structure; order: (nnz,) position in the concatenated block values
    (``_linearize``) of each CSR entry; shape: (rows, columns). With a repeated (row, column)
    pair (a link from a position to itself) order is None and rows, cols (one per value)
    are summed at every linearisation instead.
    """

    indptr: np.ndarray | None
    indices: np.ndarray | None
    order: np.ndarray | None
    shape: tuple
    rows: np.ndarray | None = None
    cols: np.ndarray | None = None


def _jacobian_pattern(problem: _Problem, steps: int, num_positions: int) -> _Pattern:
    """Rows and columns of every Jacobian entry (``_linearize``'s layout), as CSR.

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
        return _Pattern(None, None, None, shape, rows, cols)
    return _Pattern(template.indptr, template.indices,
                    template.data.astype(np.int64) - 1, shape)


def _linearize(problem: _Problem, path, landmark, pattern: _Pattern | None = None):
    """Robustly weighted whitened residual (R,), Jacobian (R, n) CSR and robust cost.

    Rows: 3 per move, 2 per observation (Huber IRLS weight), 2 per link (Geman-McClure IRLS
    weight). Columns: 3 per pose, then 2 per landmark (or visit) position. ``pattern``:
    ``_jacobian_pattern`` of this problem (built here when None).
    """
    steps = path.shape[0]
    if pattern is None:
        pattern = _jacobian_pattern(problem, steps, landmark.shape[0])
    white = _whitened(problem, path, landmark)
    cost, weight, link_weight = _robust_cost(problem, white)
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
    return residual, jacobian, cost


class _Factorizer:
    """Sparse LU solves of the symmetric matrices of one problem (one sparsity pattern).

    The first matrix is factorised with SuperLU's minimum-degree order on the symmetric
    pattern (0.2 s for Victoria Park's 24k unknowns where spsolve's default column order
    took 2.2 s); its order is kept and every later matrix (each damping, each LM step, the
    variance components) is factorised in it directly. The matrices are symmetric positive
    definite (J^T J plus a positive diagonal), so the pivots are taken on the diagonal
    (``diag_pivot_thresh=0``: LU without pivoting is stable there, as Cholesky is), which
    keeps the order's fill. Together a third less time per factorisation than a
    minimum-degree search and threshold pivoting at every step (MRCLAM robot 1, 12k
    unknowns: 13 ms against 19.5 ms). A matrix of another size gets a new order.
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


def _levenberg_marquardt(problem: _Problem, path, landmark, iterations: int, tol: float,
                         damping: float, factorize: _Factorizer | None = None):
    """(path, landmark, costs, steps tried, converged) from the given start.

    ``factorize``: the problem's ``_Factorizer`` (its order is reused; a new one when None).
    """
    steps = path.shape[0]
    factorize = _Factorizer() if factorize is None else factorize
    pattern = _jacobian_pattern(problem, steps, landmark.shape[0])
    costs = [_cost(problem, path, landmark)]
    lam, converged, step = None, False, 0
    for step in range(1, iterations + 1):
        residual, jacobian, cost = _linearize(problem, path, landmark, pattern)
        hessian = (jacobian.T @ jacobian).tocsc()
        gradient = jacobian.T @ residual
        diagonal = hessian.diagonal()
        if lam is None:
            lam = damping * float(np.mean(diagonal))
        while True:
            damped = hessian + scipy.sparse.diags(lam * np.maximum(diagonal, 1e-9))
            update = factorize(damped)(-gradient)
            new_path = path + update[:3 * steps].reshape(steps, 3)
            new_path[:, 2] = _wrap(new_path[:, 2])
            new_landmark = landmark + update[3 * steps:].reshape(-1, 2)
            new_cost = _cost(problem, new_path, new_landmark)
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


def _check_inputs(start_pose, path, odometry, z, landmark_of_obs, steps: int):
    """ValueError naming the first bad input of ``smooth_path`` (shapes, NaN)."""
    if steps < 1 or path.shape != (steps, 3) or odometry.shape != (steps, 3):
        raise ValueError(f"path and odometry must both be (T, 3) with T >= 1; got {path.shape} "
                         f"and {odometry.shape}")
    if start_pose.shape != (3,) or not np.all(np.isfinite(start_pose)):
        raise ValueError(f"start_pose must be a finite (3,) pose; got {start_pose}")
    if not np.all(np.isfinite(odometry)):
        raise ValueError(f"odometry has {np.sum(~np.isfinite(odometry))} NaN/inf entries "
                         f"(first at step {np.argwhere(~np.isfinite(odometry))[0, 0]})")
    if z.shape[:1] != (steps,) or z.shape[2:] != (2,) or landmark_of_obs.shape != z.shape[:2]:
        raise ValueError(f"z must be (T, K, 2) and landmark_of_obs (T, K) with T = {steps}; "
                         f"got {z.shape} and {landmark_of_obs.shape}")
    if not np.all(np.isfinite(z[landmark_of_obs >= 0])) or not np.all(np.isfinite(path)):
        raise ValueError("smooth_path needs finite poses and finite associated observations")


def smooth_path(start_pose, path, odometry, z, landmark_of_obs, params: Params,
                iterations: int = 30, huber: float = 3.0, tol: float = 1e-6,
                damping: float = 1e-6, noise_scales: NoiseScales | None = None,
                calibrate_rounds: int = 0, visit_gap: int | None = None,
                link_std: float = 0.2, link_threshold: float = 2.5,
                link_neighbours: int = 2) -> Smoothed:
    """Levenberg-Marquardt on the module docstring's least squares.

    Args:
      start_pose: (3,) fixed pose x_{-1} before the first move.
      path: (T, 3) initial poses x_0..x_{T-1} (e.g. ``trace_lineage(...).pose``).
      odometry: (T, 3) measured moves (rot1, trans, rot2) (``motion.control_to_odometry``).
      z: (T, K, 2) range-bearing observations; landmark_of_obs: (T, K) landmark index
        (``landmark_identities``), -1 for observations to leave out (invalid, unassociated).
      params: ``Params`` (the motion and measurement noise).
      iterations: most LM steps; huber: Huber threshold on the whitened residual norm;
      tol: stop when a step lowers the cost by less than this fraction; damping: the first
        lambda is damping * mean(diag(J^T J)) and each step solves
        (J^T J + lambda diag(J^T J)) dx = -J^T e; lambda / 10 after a step that lowers the
        cost, x 10 (retry) after one that does not.
      noise_scales: ``NoiseScales`` multiplying the four groups' stds (default all 1).
      calibrate_rounds: after solving, re-estimate the scales from the residuals
        (``_variance_factors``: each group's chi-square over its redundancy) and solve
        again, this many times. The noise that suits a particle filter is rarely the one
        the data show; this lets the data set the weights, with no ground truth.
      visit_gap: None (default) keeps one position per landmark. Else, after the solve (and
        calibration rounds) with one position per landmark, each landmark's
        observations are split into visits (``split_visits``: a gap of more than this many
        steps starts a new one), each visit gets its own position, and a link factor
        rho_GM(|| (l_a - l_b) / link_std ||) ties it to the ``link_neighbours`` previous visits
        of that landmark. rho_GM is Geman-McClure's redescending loss with scale
        ``link_threshold``: a loop closure the filter made that the rest of the data
        contradict stops pulling (its weight in ``Smoothed.visits.link_weight`` falls to ~0)
        instead of bending the map around it, as a Huber-weighted observation still does.
        The split problem is solved from the merged solution (all links satisfied there),
        with the calibrated scales; its cost history is the one returned.
      link_std: [m] std of a link; link_threshold: Geman-McClure scale (whitened units; a
        link stretched link_std * link_threshold metres has ``link_weight`` 1/2). The
        defaults, 0.2 m and half weight at 0.5 m, were tuned on 16 Victoria Park runs
        (docs/results.md, section victoria_park, records the measured effect): trunk
        centres seen on two visits agree to a few decimetres, a wrong tree is metres away.
      link_neighbours: earlier visits each visit is linked to.
    Returns:
      ``Smoothed`` (its cost history is the last solve's).
    """
    path = np.asarray(path, np.float64)
    odometry = np.asarray(odometry, np.float64)
    z = np.asarray(z, np.float64)
    start_pose = np.asarray(start_pose, np.float64)
    landmark_of_obs = np.asarray(landmark_of_obs)
    steps = path.shape[0] if path.ndim else 0
    _check_inputs(start_pose, path, odometry, z, landmark_of_obs, steps)
    if iterations < 1 or calibrate_rounds < 0 or not huber > 0:
        raise ValueError(f"need iterations >= 1, calibrate_rounds >= 0 and huber > 0; got "
                         f"{iterations}, {calibrate_rounds}, {huber}")
    if visit_gap is not None:
        check_visit_options(visit_gap, link_neighbours)
        if not (link_std > 0 and link_threshold > 0):
            raise ValueError(f"need link_std > 0 and link_threshold > 0; got {link_std}, "
                             f"{link_threshold}")
    used = landmark_of_obs >= 0
    scales = NoiseScales() if noise_scales is None else NoiseScales(*noise_scales)
    if not all(np.isfinite(v) and v > 0 for v in scales):
        raise ValueError(f"noise_scales must be positive and finite; got {scales}")
    num_landmarks = int(landmark_of_obs.max(initial=-1)) + 1
    delta, move_white = move_whitening(odometry, params)
    obs_t, obs_k = np.nonzero(used)
    obs_std = _observation_std(z[obs_t, obs_k, 0], params)
    base = _Problem(start_pose, delta, move_white, obs_t, landmark_of_obs[obs_t, obs_k],
                    z[obs_t, obs_k], obs_std, float(huber))
    problem = _rescaled(base, move_white, obs_std, scales)
    landmark = initial_landmarks(path, z, landmark_of_obs, num_landmarks)
    factorize = _Factorizer()  # one sparsity pattern for every solve with these associations
    path, landmark, costs, step, converged = _levenberg_marquardt(
        problem, path, landmark, iterations, tol, damping, factorize)
    for _ in range(calibrate_rounds):
        residual, jacobian, _ = _linearize(problem, path, landmark)
        factors = _variance_factors(residual, jacobian, steps, len(obs_t),
                                    factorize=factorize)
        scales = NoiseScales(*(float(v) for v in np.asarray(scales) * np.sqrt(factors)))
        problem = _rescaled(base, move_white, obs_std, scales)
        path, landmark, costs, step, converged = _levenberg_marquardt(
            problem, path, landmark, iterations, tol, damping, factorize)
    if visit_gap is None:
        return Smoothed(path, landmark, landmark_of_obs, costs, step, converged, scales)
    # Split from the merged solution: every link starts satisfied, at the least-squares
    # compromise, and the redescending loss then lets go of the ones that stay stretched.
    visit_of_obs, visit_landmark, links = split_visits(landmark_of_obs, visit_gap,
                                                      link_neighbours)
    problem = problem._replace(obs_id=visit_of_obs[obs_t, obs_k], links=links,
                               link_std=float(link_std), link_threshold=float(link_threshold))
    path, visit_position, costs, step, converged = _levenberg_marquardt(
        problem, path, landmark[visit_landmark], iterations, tol, damping)
    link_weight = _geman_mcclure_weight(
        np.linalg.norm(_whitened(problem, path, visit_position).link, axis=1),
        problem.link_threshold)[0]
    return Smoothed(path, _largest_visit(visit_position, visit_of_obs, visit_landmark),
                    landmark_of_obs, costs, step, converged, scales,
                    Visits(visit_position, visit_of_obs, visit_landmark, links, link_weight))


def smooth_lineage(start_pose, lineage_path: LineagePath, odometry, z, params: Params,
                   **options) -> Smoothed:
    """``smooth_path`` of one particle's history (``trace_lineage``), its associations fixed.

    The callers in this package trace ``estimate(final_state).best_particle``: the highest
    final weight, or after a resampling last step (equal weights) the first survivor, a draw
    from the posterior over histories.

    Args:
      start_pose: (3,) the filter's initial pose. lineage_path: ``LineagePath`` (T leading).
      odometry: (T, 3) measured moves (rot1, trans, rot2): the controls of the odometry
        model, else ``motion.control_to_odometry(controls, params, model)``.
      z: (T, K, 2) the observations the filter saw. options: passed to ``smooth_path``.
    """
    ids, _ = landmark_identities(lineage_path.match, lineage_path.birth_slot)
    return smooth_path(start_pose, lineage_path.pose, odometry, z, ids, params, **options)
