"""The controls' time offset from the log alone: the smoother's profile likelihood.

Many logs stamp the controls and the sensor with a fixed lag between them: the odometry may be
the commanded velocities, which the robot follows some tenths of a second late (UTIAS MRCLAM's
is), or the two streams may pass through stages of different latency. A move integrated over
the wrong interval errs most where the robot turns, so the lag reads as heading noise that
is correlated from step to step, which a particle filter's white Eq. (1) noise (Geiser et al.
2023) does not model.

Method. One filter run on the log as it stands gives a best history, whose associations are
then held fixed (``calibration_bootstrap.log_solution``). For each candidate delay d the
controls are applied d seconds later on the same steps (the loader's ``log_at(d)``: the
observations, steps and start stay as they are, only the moves change), the path and the map
are smoothed with the four noise groups re-estimated from their residuals
(``smoothing.VARIANCE_ROUNDS`` rounds of variance components), and the robust -2 log L with
its normalisers (``smoothing.problem.neg2_log_likelihood``) is read at that solution:

    l(d) = -2 log p(z, u(d) | path, map, scales) at the smoothed path and map.

A profile criterion: the path, the map and the noise scales estimated out at each d. It is
not the likelihood of one data set, since each candidate scores other moves u(d) (and their
Eq. (1) covariances follow u(d)); it compares how well the log's observations and its
commands, applied d late, fit one path. The scales are the variance components' estimates
after ``VARIANCE_ROUNDS`` rounds (each group's chi-square over its redundancy, a REML-type
rule, not iterated to convergence), the same rule at every candidate. The delay is the
candidate with the least l(d), refined by the vertex of the parabola through it and its two
neighbours (left at the candidate when the minimum lies at the grid's edge, which
``DelayFit.at_edge`` flags: widen the grid). Nothing here looks at ground truth.

The associations come from one run at ``start_delay`` (0: the log as stamped). Where a large
lag makes that run split trees, the associations can bias the profile towards the start
delay; a second pass from the first fit (``start_delay`` and its calibrated ``Params``)
would show it. Not done by default: on simulated logs with a 0.27 s lag the first pass
lands within 0.01 s of it, and on MRCLAM's five robots at 0.19-0.24 s, where Vicon puts the lag
at about 0.2 s (docs/results.md, mrclam).

Everything here is host-side NumPy float64 (the filter run is JAX).
"""
from __future__ import annotations

from typing import Callable, NamedTuple

import numpy as np

from jaxslam import smoothing
from jaxslam.types import FilterConfig, Params

# Candidate delays [s]: -0.2 s to 0.6 s in 0.1 s steps (the commands late by up to 0.6 s,
# early by up to 0.2 s). MRCLAM's robots lag 0.2 s; most clocks and drives fall inside.
DEFAULT_DELAYS = tuple(round(0.1 * i, 10) for i in range(-2, 7))


class DelayFit(NamedTuple):
    """Result of ``fit_command_delay``.

    Attributes:
      delay: the fitted delay [s] (the controls apply this much later than stamped).
      delays: (D,) the candidates [s], increasing.
      neg2_log_likelihood: (D,) l(d) at each candidate (module docstring).
      noise_scales: (D, 4) the smoother's re-estimated scales (heading, translation, range,
        bearing) at each candidate, relative to the ``Params`` given.
      at_edge: the least l(d) is at the first or last candidate: the delay may lie outside.
    """

    delay: float
    delays: np.ndarray
    neg2_log_likelihood: np.ndarray
    noise_scales: np.ndarray
    at_edge: bool


def check_delays(delays) -> np.ndarray:
    """(D,) float64 candidates, or ValueError: at least three, finite, strictly increasing."""
    values = np.asarray(delays, np.float64)
    if values.ndim != 1 or values.size < 3 or not np.all(np.isfinite(values)) \
            or np.any(np.diff(values) <= 0.0):
        raise ValueError(f"delays {delays!r}: expected at least three finite candidate delays "
                         "[s] in increasing order")
    return values


def parabola_vertex(x, y) -> float:
    """Abscissa of the vertex of the parabola through three points (x (3,), y (3,)), x
    increasing. The middle x when the three are collinear or the parabola opens downwards
    (no interior minimum)."""
    x0, x1, x2 = (float(v) for v in x)
    y0, y1, y2 = (float(v) for v in y)
    slope_left = (y1 - y0) / (x1 - x0)
    slope_right = (y2 - y1) / (x2 - x1)
    curvature = (slope_right - slope_left) / (x2 - x0)
    if not curvature > 0.0:
        return x1
    # y = y0 + slope_left (x - x0) + curvature (x - x0) (x - x1): its derivative vanishes at
    # x = (x0 + x1) / 2 - slope_left / (2 curvature).
    vertex = 0.5 * (x0 + x1) - slope_left / (2.0 * curvature)
    return float(np.clip(vertex, x0, x2))


def profile_point(start, path, moves, z, landmark_of_obs, params: Params,
                  rounds: int = smoothing.VARIANCE_ROUNDS) -> smoothing.Smoothed:
    """The smoother on measured ``moves`` (T, 3) from ``path`` (T, 3) with the associations
    ``landmark_of_obs`` (T, K) of observations ``z`` (T, K, 2), its noise groups re-estimated
    ``rounds`` times; its ``neg2_log_likelihood`` is l(d) for the delay ``moves`` carry."""
    return smoothing.smooth_path(np.asarray(start, np.float64), path,
                                 np.asarray(moves, np.float64), np.asarray(z, np.float64),
                                 landmark_of_obs, params, calibrate_rounds=rounds)


def fit_command_delay(moves_at: Callable[[float], np.ndarray], start, path, z, landmark_of_obs,
                      params: Params, delays=DEFAULT_DELAYS) -> DelayFit:
    """``DelayFit`` of the profile likelihood over ``delays`` (module docstring).

    Args:
      moves_at: delay [s] -> (T, 3) measured moves (rot1, trans, rot2) with the controls
        applied that much later, on the log's own steps.
      start: (3,) start pose; path: (T, 3) the history the smoother starts from.
      z: (T, K, 2) observations; landmark_of_obs: (T, K) their landmark, -1 for none.
      params: the noise the scales multiply (the calibrated ``Params``).
      delays: (D,) candidates [s], D >= 3, increasing.
    """
    candidates = check_delays(delays)
    values, scales = [], []
    for delay in candidates:
        smoothed = profile_point(start, path, moves_at(float(delay)), z, landmark_of_obs,
                                 params)
        values.append(smoothed.neg2_log_likelihood)
        scales.append(np.asarray(smoothed.noise_scales, np.float64))
    values = np.asarray(values, np.float64)
    if not np.all(np.isfinite(values)):
        raise ValueError(f"the profile likelihood is not finite at delays "
                         f"{candidates[~np.isfinite(values)].tolist()} s: check the moves "
                         "moves_at returns there")
    best = int(np.argmin(values))
    at_edge = best in (0, len(candidates) - 1)
    delay = (float(candidates[best]) if at_edge else
             parabola_vertex(candidates[best - 1:best + 2], values[best - 1:best + 2]))
    return DelayFit(delay, candidates, values, np.stack(scales), at_edge)


def _check_odometry(log, delay) -> None:
    """ValueError unless ``log`` (``log_at(delay)``) holds odometry moves."""
    if log.motion_model != "odometry":
        raise ValueError(f"log_at({delay}) has motion_model={log.motion_model!r}; the fit "
                         "smooths odometry moves (rot1, trans, rot2): integrate the controls "
                         "(datasets.integrate_controls) and give motion_model='odometry'")


def fit_log_command_delay(log_at: Callable, config: FilterConfig, key, params: Params,
                          delays=DEFAULT_DELAYS, start_delay: float = 0.0) -> DelayFit:
    """``fit_command_delay`` of a log that its loader can rebuild at any delay.

    Args:
      log_at: delay [s] -> ``RobotLog`` of odometry moves (motion_model "odometry") with the
        controls applied that much later, on the same steps and with the same observations
        (``mrclam_log(..., command_delay=d)``); only its controls are read at each candidate.
      config: the ``FilterConfig`` of the run that gives the associations.
      key: its PRNG key; params: its ``Params`` (calibrated at ``start_delay``).
      delays: the candidates [s]; start_delay: the delay of the run that gives the
        associations (0: the log as stamped).
    """
    from jaxslam import pipeline
    from jaxslam.calibration_bootstrap import log_solution

    first = log_at(float(start_delay))
    _check_odometry(first, start_delay)
    config, controls, observations, start = pipeline.log_inputs(first, config)
    solution = log_solution(config, key, params, controls, observations, start)
    steps = np.asarray(controls).shape[0]

    def moves_at(delay: float) -> np.ndarray:
        log = log_at(delay)
        _check_odometry(log, delay)
        moves = np.asarray(log.controls, np.float64)
        if moves.shape != (steps, 3):
            raise ValueError(f"log_at({delay}) has {moves.shape[0]} steps, the log at "
                             f"{start_delay} s {steps}: a delayed log must keep the steps")
        return moves

    return fit_command_delay(moves_at, start, solution.path, observations.z,
                             solution.landmark_of_obs, params, delays)
