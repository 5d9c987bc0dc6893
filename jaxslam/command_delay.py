"""The controls' time offset from the log alone: the smoother's profile likelihood.

Many logs stamp the controls and the sensor with a fixed lag between them: the odometry may be
the commanded velocities, which the robot follows some tenths of a second late (UTIAS MRCLAM's
is), or the two streams may pass through stages of different latency. A move integrated over
the wrong interval errs most where the robot turns, so the lag reads as heading noise that
is correlated from step to step, which a particle filter's white Eq. (1) noise (Geiser et al.
2023) does not model.

Method. One filter run on the log as it stands gives a best history, whose associations are
then held fixed: the run ``self_calibration.calibrate_params`` starts its EM with (by default
``starting_params``, with the matching heading std of their motion noise on this log), so the
fit needs no calibration before it and the calibration runs once, on the log at the fitted
delay. For a candidate delay d the controls are applied d seconds later on the same steps
(the loader's ``log_at(d)``: the observations, steps and start stay as they are, only the
moves change), the path and the map are smoothed from the filter's path with the four noise
groups re-estimated from their residuals (``smoothing.VARIANCE_ROUNDS`` rounds of variance
components; the solver's settings of the calibration's M-step), and the robust -2 log L
with its normalisers (``smoothing.problem.neg2_log_likelihood``) is read at that solution:

    l(d) = -2 log p(z, u(d) | path, map, scales) at the smoothed path and map.

A profile criterion: the path, the map and the noise scales estimated out at each d. It is
not the likelihood of one data set, since each candidate scores other moves u(d) (and their
Eq. (1) covariances follow u(d)); it compares how well the log's observations and its
commands, applied d late, fit one path. The scales are the variance components' estimates
after ``VARIANCE_ROUNDS`` rounds (each group's chi-square over its redundancy, a REML-type
rule, not iterated to convergence), the same rule at every candidate.

Search (``search_minimum``). Each l(d) costs a smoothing, so the candidates are not a fixed
grid: from the start delay the search walks downhill in steps of ``step`` seconds until l
rises, halves the spacing ``refinements`` times around the least candidate (two more
smoothings each), and the delay is the vertex of the parabola through the least candidate
and its two neighbours. With the defaults (0.2 s, one halving) that is five smoothings for a
lag between about -0.1 and 0.3 s from the start, one more for each further 0.2 s. The walk
stops ``floor(max_shift / step)`` steps from the start, and ``DelayFit.at_edge`` flags a
least candidate there. On MRCLAM's five robots (docs/results.md, mrclam) the profile is
unimodal over -0.2..0.6 s. Nothing here looks at ground truth.

The associations come from one run at ``start_delay`` (0: the log as stamped). Where a large
lag makes that run split trees, the associations can bias the profile towards the start
delay; a second pass from the first fit (``start_delay`` and its calibrated ``Params``)
would show it. Not done by default: on simulated logs with a 0.27 s lag the first pass
lands within 0.03 s of it, and on MRCLAM, where Vicon puts the lag at about 0.2 s, a second
pass moved the twenty-second session's fits (a fixed grid, calibrated associations) by
0.00-0.03 s (docs/results.md, mrclam).

Everything here is host-side NumPy float64 (the filter run is JAX).
"""
from __future__ import annotations

import math
from typing import Callable, NamedTuple

import jax.numpy as jnp
import numpy as np

from jaxslam import smoothing
from jaxslam.filter import run_filter
from jaxslam.host import in_float64
from jaxslam.motion import control_to_odometry
from jaxslam.types import FilterConfig, Params

# The search's grid [s] and how far from the start it may walk [s]. MRCLAM's robots lag
# 0.2 s behind their commands; most clocks and drives lie within a second.
DEFAULT_STEP = 0.2
DEFAULT_MAX_SHIFT = 1.0
# Halvings of the bracket's spacing: 0.1 s between the candidates the parabola goes through.
# Its vertex through candidates 0.2 s apart sat 0.075-0.089 s short of a simulated 0.27 s lag
# (tests/test_command_delay.py's world, seeds 0-3: the profile is not a parabola over
# 0.4 s); 0.1 s apart, within 0.01 s.
DEFAULT_REFINEMENTS = 1
# The fewest observations of landmarks seen twice or more the fit accepts (``_check_revisits``):
# the count the calibration asks of its observation fits (``noise_fit.MIN_OBSERVATIONS``),
# here of landmarks seen twice, the least that ties the path to them.
MIN_REVISITS = 20

# The smoother's settings at each candidate: the calibration's M-step's (``calibrate_params``'
# ``smoother_iterations`` default and its tolerance). On MRCLAM robot 2 (as stamped, at 0,
# 0.2 and 0.4 s) they moved l(d) by 5-20 and its differences between those candidates
# (8,771 and 4,272) by under 0.4 %, against 30 steps at 1e-6, at 0.4 of the time.
PROFILE_ITERATIONS = 15
PROFILE_TOL = 1e-4


class DelayFit(NamedTuple):
    """Result of ``fit_command_delay``.

    Attributes:
      delay: the fitted delay [s] (the controls apply this much later than stamped).
      delays: (D,) the candidates the search evaluated [s], increasing: ``step`` apart where
        it walked, step / 2^refinements apart around the least one.
      neg2_log_likelihood: (D,) l(d) at each candidate (module docstring).
      noise_scales: (D, 4) the smoother's re-estimated scales (heading, translation, range,
        bearing) at each candidate, relative to the ``Params`` given.
      at_edge: the least l(d) lies at the search's bound (``floor(max_shift / step)`` steps
        from the start): the delay may lie beyond it.
    """

    delay: float
    delays: np.ndarray
    neg2_log_likelihood: np.ndarray
    noise_scales: np.ndarray
    at_edge: bool


def search_steps(start_delay, step, max_shift, refinements) -> int:
    """The most steps the walk may take from ``start_delay``, floor(max_shift / step), after
    checking the search's settings: ValueError unless they are finite, step > 0,
    max_shift >= step and refinements an integer >= 0."""
    values = (start_delay, step, max_shift)
    if not all(np.isfinite(v) for v in values) or not step > 0 or not max_shift >= step:
        raise ValueError(f"start_delay={start_delay!r}, step={step!r}, "
                         f"max_shift={max_shift!r}: expected finite values [s] with step > 0 "
                         "and max_shift >= step")
    if isinstance(refinements, bool) or not isinstance(refinements, (int, np.integer)) \
            or refinements < 0:
        raise ValueError(f"refinements={refinements!r}: expected an integer >= 0")
    return int(math.floor(max_shift / step + 1e-9))


class Search(NamedTuple):
    """Result of ``search_minimum``.

    Attributes:
      offsets: (D,) int the evaluated integers, increasing.
      values: (D,) the criterion there.
      best: index into ``offsets`` of the least value found (a tie goes to the point the
        walk or the refinement reached first).
      at_edge: the walk stopped at |i| = max_steps 2^refinements, not at a rise. Unless
        at_edge, offsets[best] - 1 and offsets[best] + 1 were evaluated.
    """

    offsets: np.ndarray
    values: np.ndarray
    best: int
    at_edge: bool


def search_minimum(criterion: Callable[[int], float], max_steps: int,
                   refinements: int) -> Search:
    """Bracket the least value of ``criterion`` on the integers i, |i| <= max_steps h, where
    h = 2^refinements is the coarse grid's spacing, and refine the bracket.

    Walk: evaluate 0 and h, then walk towards the lower side h at a time until the criterion
    does not fall (after h did not fall, -h first decides the side). Refine: ``refinements``
    times halve the spacing and evaluate the two points that far either side of the least
    one, which moves to the least of the three (a tie keeps it, then prefers the left one).
    Each point is evaluated once. A walk stopped at the bound is not refined. max_steps >= 1.
    """
    if max_steps < 1:
        raise ValueError(f"max_steps={max_steps}: the walk needs at least one step")
    values: dict[int, float] = {}

    def value(i: int) -> float:
        if i not in values:
            values[i] = float(criterion(i))
        return values[i]

    spacing = 2 ** refinements
    best, direction = 0, spacing
    value(0)  # the start first: a criterion that fails there is named at the start
    if not value(spacing) < value(0):
        direction = -spacing
    while abs(best + direction) <= max_steps * spacing and \
            value(best + direction) < value(best):
        best += direction
    at_edge = abs(best) == max_steps * spacing
    while not at_edge and spacing > 1:
        spacing //= 2
        best = min((best, best - spacing, best + spacing), key=value)
    offsets = sorted(values)
    return Search(np.asarray(offsets), np.asarray([values[i] for i in offsets], np.float64),
                  offsets.index(best), at_edge)


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
    ``rounds`` times (``PROFILE_ITERATIONS``, ``PROFILE_TOL``); its ``neg2_log_likelihood``
    is l(d) for the delay ``moves`` carry."""
    return smoothing.smooth_path(np.asarray(start, np.float64), path,
                                 np.asarray(moves, np.float64), np.asarray(z, np.float64),
                                 landmark_of_obs, params, iterations=PROFILE_ITERATIONS,
                                 tol=PROFILE_TOL, calibrate_rounds=rounds)


def fit_command_delay(moves_at: Callable[[float], np.ndarray], start, path, z, landmark_of_obs,
                      params: Params, step: float = DEFAULT_STEP, start_delay: float = 0.0,
                      max_shift: float = DEFAULT_MAX_SHIFT,
                      refinements: int = DEFAULT_REFINEMENTS) -> DelayFit:
    """``DelayFit`` of the profile likelihood, searched from ``start_delay`` (module docstring).

    Args:
      moves_at: delay [s] -> (T, 3) measured moves (rot1, trans, rot2) with the controls
        applied that much later, on the log's own steps.
      start: (3,) start pose; path: (T, 3) the history the smoother starts from.
      z: (T, K, 2) observations; landmark_of_obs: (T, K) their landmark, -1 for none.
      params: the noise the scales multiply.
      step: the walk's grid [s] (> 0); start_delay: where it starts [s]; max_shift: how
        far from the start it may walk [s] (>= step); refinements: how often the bracket's
        spacing is halved (>= 0).
    """
    max_steps = search_steps(start_delay, step, max_shift, refinements)
    _check_revisits(landmark_of_obs)
    spacing = step / 2 ** refinements  # [s] between the finest candidates
    scales = {}  # offset -> (4,) the smoother's scales there, filled by ``criterion``

    def criterion(offset: int) -> float:
        delay = float(start_delay) + offset * spacing
        smoothed = profile_point(start, path, moves_at(delay), z, landmark_of_obs, params)
        scales[offset] = np.asarray(smoothed.noise_scales, np.float64)
        if not np.isfinite(smoothed.neg2_log_likelihood):
            raise ValueError(f"the profile likelihood is not finite at delay {delay:.6g} s: "
                             "check the moves moves_at returns there")
        return smoothed.neg2_log_likelihood

    offsets, values, best, at_edge = search_minimum(criterion, max_steps, refinements)
    delays = float(start_delay) + offsets * spacing
    delay = (float(delays[best]) if at_edge else
             parabola_vertex(delays[best - 1:best + 2], values[best - 1:best + 2]))
    return DelayFit(delay, delays, values, np.stack([scales[i] for i in offsets]), at_edge)


class DelayFitError(ValueError):
    """A log that cannot give its commands' lag (too few landmarks seen again)."""


def _refuse(count: int, what: str = "observations belong to landmarks seen twice or more"):
    """Raise the ``DelayFitError`` of a log with only ``count`` ``what``."""
    raise DelayFitError(f"only {count} {what} (the fit needs at least {MIN_REVISITS} "
                        "observations of landmarks seen twice or more): the log's observations do "
                        "not tie its path down, so its commands' lag cannot be fitted from "
                        "it; give the lag (a number of seconds) or a longer log")


def _check_revisits(landmark_of_obs) -> None:
    """``DelayFitError`` unless at least ``MIN_REVISITS`` observations belong to landmarks
    seen twice or more: without landmarks seen again nothing ties the path to the
    observations, and l(d) would compare the moves' covariances alone."""
    ids = np.asarray(landmark_of_obs)
    counts = np.bincount(ids[ids >= 0], minlength=1)
    revisits = int(counts[counts >= 2].sum())
    if revisits < MIN_REVISITS:
        _refuse(revisits)


def _check_odometry(log, delay) -> None:
    """ValueError unless ``log`` (``log_at(delay)``) holds odometry moves."""
    if log.motion_model != "odometry":
        raise ValueError(f"log_at({delay}) has motion_model={log.motion_model!r}; the fit "
                         "smooths odometry moves (rot1, trans, rot2): integrate the controls "
                         "(datasets.integrate_controls) and give motion_model='odometry'")


def fit_log_command_delay(log_at: Callable, config: FilterConfig, key,
                          params: Params | None = None, step: float = DEFAULT_STEP,
                          start_delay: float = 0.0, max_shift: float = DEFAULT_MAX_SHIFT,
                          refinements: int = DEFAULT_REFINEMENTS) -> DelayFit:
    """``fit_command_delay`` of a log that its loader can rebuild at any delay.

    Args:
      log_at: delay [s] -> ``RobotLog`` of odometry moves (motion_model "odometry") with the
        controls applied that much later, on the same steps and with the same observations
        (``mrclam_log(..., command_delay=d)``); only its controls are read at each candidate.
      config: the ``FilterConfig`` of the run that gives the associations.
      key: its PRNG key.
      params: the calibration's starting point (default ``starting_params(config)``); the
        run takes them as ``calibrate_params``' first EM run on the log at ``start_delay``
        does, with ``association_heading_std`` from their motion noise on it
        (``with_typical_heading_std``), so no calibration is needed before the fit; their
        ``radius_noise`` is kept (the calibration's EM matches without one on logs with
        trunk radii). The smoother's scales multiply them. A second pass gives the
        ``Params`` calibrated at a first fit.
      step, max_shift, refinements: the search's grid and reach [s] and its refinements
        (``fit_command_delay``);
      start_delay: the delay of the run that gives the associations and where the search
        starts [s] (0: the log as stamped).
    """
    from jaxslam import pipeline
    from jaxslam.self_calibration import (best_history, confirmed_ids, history_associations,
                                          starting_params, with_typical_heading_std)

    search_steps(start_delay, step, max_shift, refinements)
    first = log_at(float(start_delay))
    _check_odometry(first, start_delay)
    config, controls, observations, start = pipeline.log_inputs(first, config)
    valid = np.asarray(observations.valid)
    if valid.sum() < MIN_REVISITS:  # refused before the filter run
        _refuse(int(valid.sum()), "valid observations in the log")
    params = starting_params(config) if params is None else params
    measured = in_float64(control_to_odometry, controls, params, motion_model="odometry")
    params = with_typical_heading_std(params, measured, np.asarray(observations.z)[valid][:, 0])
    final, trace = run_filter(config, key, params, controls, observations,
                              jnp.asarray(start, params.rot1_noise.dtype), record_lineage=True)
    history = best_history(trace.lineage, final.log_weight)
    landmark_of_obs = confirmed_ids(history_associations(history, valid))
    steps = np.asarray(controls).shape[0]

    def moves_at(delay: float) -> np.ndarray:
        log = log_at(delay)
        _check_odometry(log, delay)
        moves = np.asarray(log.controls, np.float64)
        if moves.shape != (steps, 3):
            raise ValueError(f"log_at({delay}) has {moves.shape[0]} steps, the log at "
                             f"{start_delay} s {steps}: a delayed log must keep the steps")
        return in_float64(control_to_odometry, moves, params, motion_model="odometry")

    return fit_command_delay(moves_at, start, np.asarray(history.pose, np.float64),
                             observations.z, landmark_of_obs, params, step, start_delay,
                             max_shift, refinements)


def profile_text(fit: DelayFit) -> str:
    """One line: the fitted delay, a flag at the search's bound, and l(d) above its least at
    each candidate."""
    profile = fit.neg2_log_likelihood - fit.neg2_log_likelihood.min()
    return (f"{fit.delay:.3f} s"
            + (" (at the search's bound: the lag may lie beyond; give it)" if fit.at_edge
               else "")
            + " | -2 log L above its least at "
            + ", ".join(f"{d:+.2f} s {v:.0f}" for d, v in zip(fit.delays, profile)))


def command_delay_argument(text: str):
    """``command_delay_choice`` as an argparse ``type``: ArgumentTypeError for bad text."""
    import argparse

    try:
        return command_delay_choice(text)
    except ValueError as error:
        raise argparse.ArgumentTypeError(str(error)) from error


def command_delay_choice(text: str):
    """A command-line command delay: "auto" (fit it from the log), or a finite number of
    seconds as a float; ValueError naming the expected forms otherwise."""
    if text == "auto":
        return text
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not np.isfinite(value):
        raise ValueError(f"{text!r}: expected 'auto' or a finite number of seconds")
    return value


def log_at_command_delay(log, config: FilterConfig, key, command_delay,
                         params: Params | None = None, progress=None):
    """(log, fit): a ``RobotLog`` that holds its command stream rebuilt with the commands
    ``command_delay`` seconds late (``RobotLog.at_command_delay``), or for "auto" at the
    delay ``fit_log_command_delay`` fits from it (key ``key``, starting point ``params``);
    fit is that ``DelayFit``, None for a number given. ``progress``: optional callable(str)
    told of the delay, and before a fit that one is under way."""
    if command_delay != "auto":
        if progress is not None:
            progress(f"commands {float(command_delay):+.3f} s late: moves rebuilt from the "
                     "command stream")
        return log.at_command_delay(float(command_delay)), None
    if progress is not None:
        progress("fitting the commands' lag from the log (a filter run and a few "
                 "smoothings) ...")
    fit = fit_log_command_delay(log.at_command_delay, config, key, params)
    if progress is not None:
        progress(f"command delay fitted from the log: {profile_text(fit)}")
    return log.at_command_delay(fit.delay), fit
