"""The smoother's entry points: ``smooth_path`` (a path and its associations) and
``smooth_lineage`` (one particle's history out of ``run_filter(..., record_lineage=True)``).

The least squares they solve is the package docstring's; ``problem`` assembles it from the
factors of ``residuals`` and ``solver`` runs Levenberg-Marquardt on it.

Shapes: T steps, K observation rows, N associated observations, L landmarks.
"""
from __future__ import annotations

import functools
from typing import NamedTuple

import numpy as np

from jaxslam.lineage import LineagePath, landmark_identities
from jaxslam.smoothing import solver
from jaxslam.smoothing.problem import (NoiseScales, Problem, geman_mcclure_weight, linearize,
                                       neg2_log_likelihood, rescaled, whitened)
from jaxslam.smoothing.residuals import initial_landmarks, move_whitening, observation_std
from jaxslam.smoothing.visits import Visits, check_visit_options, largest_visit, split_visits
from jaxslam.types import Params


class Smoothed(NamedTuple):
    """Result of ``smooth_path``.

    path: (T, 3) smoothed poses; landmark: (L, 2) smoothed landmark positions (L = the
    largest index in ``landmark_of_obs`` + 1; an index with no observation stays at 0);
    landmark_of_obs: (T, K) index into ``landmark`` of each observation (-1: none);
    cost: (I + 1,) robust cost before the first and after each accepted step;
    iterations: steps tried; converged: the last relative cost decrease was under ``tol``;
    noise_scales: the ``NoiseScales`` used (estimated ones with ``calibrate_rounds``);
    visits: ``Visits`` with ``visit_gap`` (each landmark is then at its largest visit), else None;
    redundancy: (4,) each noise group's redundancy r_g (``solver.variance_factors``) in the
    last ``calibrate_rounds`` round, else None; degrees_of_freedom: (4,) the degrees of
    freedom of each group's variance factor, the four estimated together (nu_g <= r_g,
    ``solver.variance_factors``), likewise; neg2_log_likelihood: -2 log L of the returned
    solution at the returned scales, normalisers included (``problem.neg2_log_likelihood``;
    with ``calibrate_rounds``, the profile likelihood of the moves and associations given).
    """

    path: np.ndarray
    landmark: np.ndarray
    landmark_of_obs: np.ndarray
    cost: np.ndarray
    iterations: int
    converged: bool
    noise_scales: NoiseScales = NoiseScales()
    visits: Visits | None = None
    redundancy: np.ndarray | None = None
    degrees_of_freedom: np.ndarray | None = None
    neg2_log_likelihood: float | None = None


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


# Rounds of variance components (``calibrate_rounds``) wherever the library smooths a filter
# run: the calibration's M-step (``self_calibration``) and the offline path of a finished run
# (``pipeline.offline_path``). Two rounds, not the fixed point: on Victoria Park the
# translation factor keeps growing for 8-12 rounds (x3-7 after two, x11-14 at the fixed
# point), absorbing errors the Gaussian move model does not describe; that choice was made
# after seeing the GPS errors of both on two keys (docs/results.md, victoria_park).
VARIANCE_ROUNDS = 2


def smooth_path(start_pose, path, odometry, z, landmark_of_obs, params: Params,
                iterations: int = 30, huber: float = 3.0, tol: float = 1e-6,
                damping: float = 1e-6, noise_scales: NoiseScales | None = None,
                calibrate_rounds: int = 0, visit_gap: int | None = None,
                link_std: float = 0.2, link_threshold: float = 2.5,
                link_neighbours: int = 2) -> Smoothed:
    """Levenberg-Marquardt on the package docstring's least squares.

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
        (``solver.variance_factors``: each group's chi-square over its redundancy) and solve
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
    scales = NoiseScales() if noise_scales is None else NoiseScales(*noise_scales)
    _check_options(iterations, calibrate_rounds, huber, scales, visit_gap, link_std,
                   link_threshold, link_neighbours)
    base = _base_problem(start_pose, odometry, z, landmark_of_obs, params, float(huber))
    landmark = initial_landmarks(path, z, landmark_of_obs,
                                 int(landmark_of_obs.max(initial=-1)) + 1)
    solve = functools.partial(solver.levenberg_marquardt, iterations=iterations, tol=tol,
                              damping=damping)
    problem, scales, components, (path, landmark, costs, step, converged) = (
        _solve_and_calibrate(base, scales, path, landmark, calibrate_rounds, solve))
    redundancy, dof = ((None, None) if components is None
                       else (components.redundancy, components.degrees_of_freedom))
    if visit_gap is None:
        return Smoothed(path, landmark, landmark_of_obs, costs, step, converged, scales,
                        redundancy=redundancy, degrees_of_freedom=dof,
                        neg2_log_likelihood=neg2_log_likelihood(problem, path, landmark))
    # Split from the merged solution: every link starts satisfied, at the least-squares
    # compromise, and the redescending loss then lets go of the ones that stay stretched.
    visit_of_obs, visit_landmark, links = split_visits(landmark_of_obs, visit_gap,
                                                      link_neighbours)
    # Boolean indexing keeps np.nonzero's row-major order: the observations' order in base.
    problem = problem._replace(obs_id=visit_of_obs[landmark_of_obs >= 0], links=links,
                               link_std=float(link_std), link_threshold=float(link_threshold))
    path, visit_position, costs, step, converged = solve(problem, path,
                                                         landmark[visit_landmark])
    link_weight = geman_mcclure_weight(
        np.linalg.norm(whitened(problem, path, visit_position).link, axis=1),
        problem.link_threshold)[0]
    return Smoothed(path, largest_visit(visit_position, visit_of_obs, visit_landmark),
                    landmark_of_obs, costs, step, converged, scales,
                    Visits(visit_position, visit_of_obs, visit_landmark, links, link_weight),
                    redundancy, dof, neg2_log_likelihood(problem, path, visit_position))


def _check_options(iterations, calibrate_rounds, huber, scales, visit_gap, link_std,
                   link_threshold, link_neighbours):
    """ValueError naming the first bad option of ``smooth_path``."""
    if iterations < 1 or calibrate_rounds < 0 or not huber > 0:
        raise ValueError(f"need iterations >= 1, calibrate_rounds >= 0 and huber > 0; got "
                         f"{iterations}, {calibrate_rounds}, {huber}")
    if visit_gap is not None:
        check_visit_options(visit_gap, link_neighbours)
        if not (link_std > 0 and link_threshold > 0):
            raise ValueError(f"need link_std > 0 and link_threshold > 0; got {link_std}, "
                             f"{link_threshold}")
    if not all(np.isfinite(v) and v > 0 for v in scales):
        raise ValueError(f"noise_scales must be positive and finite; got {scales}")


def _base_problem(start_pose, odometry, z, landmark_of_obs, params: Params,
                  huber: float) -> Problem:
    """The ``Problem`` of one position per landmark, noise as in ``params`` (scales 1)."""
    delta, move_white = move_whitening(odometry, params)
    obs_t, obs_k = np.nonzero(landmark_of_obs >= 0)
    return Problem(start_pose, delta, move_white, obs_t, landmark_of_obs[obs_t, obs_k],
                   z[obs_t, obs_k], observation_std(z[obs_t, obs_k, 0], params), huber)


def _solve_and_calibrate(base: Problem, scales: NoiseScales, path, landmark, rounds: int,
                         solve):
    """(problem, scales, components, ``solve``'s result): solve at ``scales``, then ``rounds``
    times re-estimate the scales from the residuals (``solver.variance_factors``) and solve
    again. components: the last round's ``VarianceComponents`` (None without rounds).

    One ``Factorizer`` serves every solve: the associations fix the sparsity pattern.
    """
    factorize = solver.Factorizer()
    problem = rescaled(base, scales)
    result = solve(problem, path, landmark, factorize=factorize)
    components = None
    for _ in range(rounds):
        path, landmark = result[:2]
        residual, jacobian, _ = linearize(problem, path, landmark)
        components = solver.variance_factors(residual, jacobian, len(path), len(base.obs_t),
                                             factorize=factorize)
        scales = NoiseScales(*(float(v) for v in
                               np.asarray(scales) * np.sqrt(components.factor)))
        problem = rescaled(base, scales)
        result = solve(problem, path, landmark, factorize=factorize)
    return problem, scales, components, result


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
