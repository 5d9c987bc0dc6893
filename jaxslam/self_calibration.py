"""Self-calibration: the filter's noise and sensor settings estimated from a log alone.

A user with a robot log has no ground truth to tune against. ``calibrate_params`` finds the
settings from the odometry and the observations only, by an expectation-maximisation of the
kind Probabilistic Robotics (Thrun, Burgard and Fox, sections 6.3 and 11) and GraphSLAM noise
estimation use, with the particle filter as the E-step's data associator:

    repeat (iteration i = 0, 1, ...):
      1. filter the log with Params_i (``run_filter``, one fixed key: common random numbers,
         so two iterations differ only by their settings), record the lineage;
      2. take the best particle's history: its data association j(t, k) (``trace_lineage``);
      3. smooth with that association fixed (``smoothing.smooth_path``): the maximum
         a-posteriori path x*_{0:T-1} and map m* of the log, Huber-robust, and the unbiased
         variance factor of each noise group (heading, translation, range, bearing:
         Helmert/Forstner variance components, ``smooth_path(calibrate_rounds=...)``);
         with ``merge_landmarks``, landmarks the filter split (never seen at one step, closer
         than half the distance of any two that were) are merged and the log smoothed again
         (``landmark_merge``);
      4. M-step on the residuals of that solution (``calibration_residuals``):
         * noise (``noise_fit``): Eq. (1) of Geiser et al., "Practical Implementation of
           FastSLAM for Forestry Robot" (ICAROB 2023), fitted to the move residuals and
           Table 2's std = c_d range + c_0 to the observation residuals, with the robust
           grouped fit of ``calibrate.fit_noise``, rescaled to the variance factors (without
           them, EM on MAP residuals shrinks the noise every iteration); bursts
           (``fit_bursts``: ``motion_outlier_probability`` and ``motion_outlier_scale``) when
           a two-scale mixture beats one Gaussian by BIC, else the default tail
           (``defensive_bursts``) and a std widened to cover 95 % of the residuals, both
           fitted to the move residuals at unit mean square (``noise_fit.unit_mean_square``:
           the variance factors set the scale, the residuals' shape sets core and bursts);
         * sensor (``detection_fit``): ``max_range``, ``miss_bearing``, ``miss_range``,
           ``detection_probability``, ``false_alarm_probability`` and ``association_gate``;
         * trunk radius, when the observations carry measured radii: ``radius_noise``, the
           std that covers 95 % of the scatter of the radii within each smoothed landmark
           (``noise_fit.radius_noise_from_history``). It is kept apart: EM's runs match
           without it, and only the returned settings get it (below), so that the std is
           fitted to an association the radius did not shape (a std fitted inside the
           loop narrows itself: a tight std splits a tree, and each piece's radii scatter
           less than the whole tree's);
         * ``odometry_gain`` (with the motion noise, when ``calibrate_gain=True``): the
           odometry's systematic error, the least-squares slope of the smoothed moves on
           the measured ones, kept where BIC calls for it (``odometry_gain``), fitted again
           on the log smoothed with the new gains until they settle (``_fit_gain``); the
           noise is fitted around those moves, and the next iteration's moves are the
           readings times the new gains;
         * ``association_heading_std`` (with the motion noise): the root-mean-square heading
           std that the fitted Eq. (1) gives over the log's own moves
           (``calibration_residuals.typical_stds``). It stands for a heading error of a
           typical move that Eq. (1), evaluated at a smaller measured turn, leaves out of the
           gate at the motion prediction. On a robot whose moves turn little (MRCLAM, Victoria
           Park) it is a few hundredths of a radian or less, not the library default's 0.1,
           which was chosen on simulated logs with 0.15 rad turns and whose matching of
           landmarks 0.7-2 m apart it would widen;
      5. monitor EM by the particle filter's own log marginal likelihood estimate (the sum
         of ``Trace.log_evidence``); when the iterations do not converge, return the
         settings whose run scored best (an iteration that broke the association scores
         low; with ``significance``, a later run counts as better only when its per-step
         log evidence beats the best's by a one-sided t test over blocks of steps,
         ``score_comparison``); stop once the last ``patience`` runs did not beat the best
         run before them
         (the first run never counts as best, and no stop while every run overflowed the map,
         as no likelihood ranks such runs; ``_stalled``): a Monte Carlo EM's likelihood
         need not rise every iteration, but on the logs measured (docs/results.md,
         calibration_time) it did not come back once it had fallen twice below its best,
         and each further iteration costs a filter run;
      6. limit each noise group's move to a factor ``TRUST_FACTOR`` an iteration
         (``_trust_region``), and stop when every group's typical std moved by less than
         ``tol`` (relative);
    then the returned settings get the radius std of the M-step behind them, with the fitted
    gate moved to 3 degrees of freedom at the same tail probability
    (``detection_fit.gate_with_radius``: the radius adds one to the matching distance; the
    airlock's position-only width keeps the 2-dof gate's root);
    then (``scale_search``) multiply the motion and the observation noise by the factors of a
    small grid whose filter log marginal likelihood is highest (``noise_scale``): on a log
    whose association EM could not get right (trees split, no loop closure) the M-step's
    noise is too narrow, and the likelihood, which does not condition on one association,
    says by how much (each candidate credits a new landmark with EM's density, so a narrow
    sensor noise is not paid for the trees it splits).

Why this and not a likelihood search over a population of Params: the filter's marginal
likelihood is a noisy, flat function of 9 motion and 4 sensor coefficients at the particle
counts users run, while the smoother's residuals measure each noise group directly, with
degrees of freedom in the thousands on a real log, and cost one filter run per iteration.
The likelihood is only asked for two multipliers of EM's result on a 2x grid (how stable that
choice is across keys was not measured).

Uncertainty: ``CalibrationInfo.relative_std`` is each group's relative standard error from
the spread of the residuals its fit used, whitened (``noise_fit.std_relative_error``: batch
means, so heavy tails and errors correlated across neighbouring steps widen it), never below
the chi-square figure 1 / sqrt(2 nu_g) of the smoother's degrees of freedom of the group's
variance factor (``smoothing.Smoothed.degrees_of_freedom``: nu_g = 1 / (S^-1)_gg of the four
groups' factors estimated together, at most its redundancy r_g,
``smoothing.solver.variance_factors``). The smoothed path absorbs most of a
move's error where the observations pin each pose loosely: the motion groups kept r_g of
34-50 of 250 heading rows and 41-72 of 500 translation rows at the first M-step on simulated
loops of ``experiments/self_calibration.py``. On Victoria Park the heading group kept about
2,500 of 7,230 at the first M-step, but in a calibration with 640 map slots it fell to its
clip of 1 at a later one, and the stated error to +-146 % (with r_g as the degrees of
freedom, before ``degrees_of_freedom``): once EM has made the heading
noise small against what the observations resolve, the odometry alone fixes each pose's
heading and the heading rows are all absorbed (a trace error of at most sqrt(2 r_g / 16),
``smoothing.solver.variance_factors``, so this is the smoother's answer, not the probe's
noise). It is still the sampling error only: a bias of EM's estimate (the path and
association EM converged to) is not in it (docs/results.md, self_calibration, "The
stated interval counts the smoother's degrees of freedom"). A fitted trunk-radius std gets its
error from a bootstrap over the landmarks whose radii it used
(``noise_fit.radius_noise_relative_error``): one tree's radii share its median and its
shape, so the trees, not the radii, are the independent samples.

Cost: one filter run per iteration, at most ``iterations`` (4 of at most 5 on MRCLAM robot 1
with ``patience``), plus the scale search's runs on the same compiled filter (at most 7 with the
default grid, 6 when EM did not converge and no radius std was fitted, fewer when a stage's
score falls past its peak;
on a CPU two at a time, in 1.1-1.3 runs' time: ``noise_scale.default_workers``),
plus the smoother (0.15-0.35 of a run per iteration on MRCLAM robot 1 and on the simulated
loop of ``benchmarks/calibration.py``), plus a few per cent for the rest. Between the filter
runs the library's models run on the host in float64 on shapes fixed for the log
(``host.in_float64``), and the noise fits in NumPy/SciPy (``noise_fit``): the number of
associated observations changes with every iteration's association, and jitted code of that
shape would compile anew each time.

Shapes: T steps, K observations per step, S associated observations, L smoothed landmarks.
"""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxslam import lineage, smoothing
from jaxslam.calibration_residuals import NOISE_GROUPS, smoothed_residuals, typical_stds
from jaxslam.detection_fit import gate_with_radius, sensor_update, single_share
from jaxslam.filter import run_filter
from jaxslam.host import in_float64
from jaxslam.landmark_merge import merge_split_landmarks, relabel
from jaxslam.motion import control_to_odometry, with_gain
from jaxslam.odometry_gain import (GAIN_ROUNDS, GAIN_TOL, MAX_STEP, GainFit, contraction,
                                   gain_update, significant_gains)
from jaxslam.noise_scale import (DEFAULT_SCALES, MOTION_FIELDS, OBSERVATION_FIELDS, ScaleSearch,
                                 any_fair, check_scales, check_workers, describe_search,
                                 fair, first_overflowed, score_trace, search_noise_scales)
from jaxslam.noise_fit import (MIN_MOVES, MIN_OBSERVATIONS, MIN_SIGHTINGS, STD_FLOOR,
                               group_relative_errors, measured_radii, motion_noise_update,
                               observation_noise_update, radius_noise_from_history,
                               radius_noise_relative_error)
from jaxslam.score_comparison import significantly_better
from jaxslam.types import FilterConfig, Observations, Params, default_params

START_DETECTION = 0.1  # the first iteration's detection probability (``starting_params``)
TRUST_FACTOR = 3.0  # most factor a noise group's typical std may move in one iteration
_GROUP_FIELDS = (("rot1_noise", "rot2_noise"), ("trans_noise",),
                 ("range_noise", "range_std_floor"), ("bearing_noise", "bearing_std_floor"))
_trace_lineage = jax.jit(lineage.trace_lineage)


class CalibrationInfo(NamedTuple):
    """What ``calibrate_params`` did.

    Attributes:
      iterations: EM iterations run.
      objective: (iterations,) the filter's estimate of the log marginal likelihood of the
        log with each iteration's Params (``Trace.log_evidence`` summed over steps).
      smoother_cost: (M,) the smoother's final robust cost per residual row of each M-step
        (M = iterations, or fewer when EM stopped before an M-step: ``patience``, a failed
        smoothing).
      typical_std: (iterations + 1, 4) typical std of the four noise groups (heading [rad],
        translation [m], range [m], bearing [rad]: the root mean square of the model's std over
        the log's moves and observations, ``calibration_residuals.typical_stds``) before
        each iteration and, last row, of the returned settings (after the scale search).
      values: the final settings, a dict of floats or tuples (the fitted ``Params`` fields).
      relative_std: dict group -> relative standard error of its std (module docstring),
        from the M-steps behind the returned settings: the sampling error of the group's
        residuals, with the smoother's degrees of freedom. On held-out simulated logs (32: 2
        regimes x 2 log sets x 8) the truth lay within 1 +- 1.96 relative_std in 56 of
        64 cases for the sensor groups and in 53 of 64 for the motion groups (with fitted
        bursts counted in the motion std; nominal about 61): on smooth loops EM's heading
        estimate can sit below the truth by more than that (docs/results.md,
        self_calibration, "Bursts fitted to the shrunk residuals").
        ``calibration_bootstrap.bootstrap_intervals`` states intervals that count EM's bias
        as well, at the cost of B more calibrations: on those logs they held the truth in
        62 of 64 (motion) and 62 of 64 (sensor) cases with B = 20 (rerun after the move
        errors took the nearest decomposition, 9184f50: the same counts). "radius": a fitted
        ``radius_noise``'s relative error, by a bootstrap over the landmarks whose radii it used
        (``noise_fit.radius_noise_relative_error``; inf with a single such landmark). Empty
        when the starting settings are returned.
      samples: dict group -> number of samples the fit used (the M-steps behind the
        returned settings, as ``relative_std``); "radius": the measured radii behind a
        fitted ``radius_noise``.
      converged: whether the typical stds stopped moving (``tol``).
      verdict: one line in plain words.
      warnings: tuple of plain-word warnings (data too sparse, a group kept at its start, a
        group the log barely determines: ``loose_interval_warnings``).
      noise_scales: ``noise_scale.ScaleSearch`` of the likelihood search after EM
        (``scale_search=True`` and something fitted), else None (the verdict says which).
      dropped_births: (iterations,) int64 births each iteration's filter run dropped because
        its map was full (summed over particles and steps). When EM does not converge, the
        settings returned are those of the best run after the first (``_best_run``), chosen
        among the runs that dropped none when any did (and scored a finite value), else the
        run that dropped the fewest.
      bursts_fitted: whether the motion fit behind the returned settings found bursts
        (``motion_outlier_probability`` and ``motion_outlier_scale`` fitted); False when it
        kept the defensive ones (``defensive_bursts``), None when no motion fit lies behind
        them.
      fill_steps: (iterations,) int64 each filter run's first step that dropped a birth (the
        log's length T when none did): ``_best_run`` breaks ties of the fewest dropped births
        with it when no later run kept every birth with a finite score.
    """

    iterations: int
    objective: np.ndarray
    smoother_cost: np.ndarray
    typical_std: np.ndarray
    values: dict
    relative_std: dict
    samples: dict
    converged: bool
    verdict: str
    warnings: tuple
    noise_scales: ScaleSearch | None = None
    dropped_births: np.ndarray | None = None
    bursts_fitted: bool | None = None
    fill_steps: np.ndarray | None = None


def starting_params(config: FilterConfig | None = None, dtype=jnp.float32, **overrides) -> Params:
    """The first iteration's settings when the user gives none: wide, so data associate.

    Seed Table 1 motion noise doubled, and a sensor noise floor of 10 cm and 0.02 rad (a
    2-20x wider sensor than Table 2): too tight a start makes every observation a new
    landmark and leaves nothing to calibrate on; too wide a start only costs an iteration.

    Existence: a detection probability of ``START_DETECTION`` (against the default false
    alarm probability 0.05) costs a missed landmark log(0.9 / 0.95) = -0.054 in log-odds, so
    a landmark born at ``existence_init`` 1 is deleted after 46 misses. The default 0.9
    deletes it after two: a detector that misses more often than that (a camera reading
    barcodes one step in three) has its landmarks deleted and started again, the smoother
    then sees each tree as many landmarks, and the detection fit (``detection_fit``), which
    counts a landmark's misses between its first and last sighting, sees only runs of
    misses too short to delete. Too slow a deletion only costs an iteration.
    """
    base = default_params(config, dtype=dtype)
    values = dict(rot1_noise=2 * np.asarray(base.rot1_noise),
                  trans_noise=2 * np.asarray(base.trans_noise),
                  rot2_noise=2 * np.asarray(base.rot2_noise),
                  range_noise=(0.005, 0.0), bearing_noise=(0.0, 0.0),
                  range_std_floor=0.1, bearing_std_floor=0.02,
                  detection_probability=START_DETECTION)
    values.update(overrides)
    return default_params(config, dtype=dtype, **values)


def defensive_bursts(config: FilterConfig) -> tuple[float, float]:
    """(eps, kappa) kept when the log shows no bursts (``fit_bursts`` returns None).

    With the two-piece burst proposal (``FilterConfig.burst_proposal``, observation or
    mixture proposal) the default bursts stay: they are not a noise estimate but the tail
    that lets a particle follow a turn far from the measured one (Eq. (1)'s std is evaluated
    at the measured turn), which a log with few such turns cannot show. The motion proposal
    samples bursts blindly, so for it they are off.
    """
    defaults = default_params(config)
    if config.proposal != "motion" and config.burst_proposal:
        return float(defaults.motion_outlier_probability), float(defaults.motion_outlier_scale)
    return 0.0, float(defaults.motion_outlier_scale)


def best_history(lineage_record: lineage.Lineage, log_weight) -> lineage.LineagePath:
    """``trace_lineage`` of the best particle: the first of the highest final log weight
    (``filter.estimate``)."""
    return _trace_lineage(lineage_record, int(np.argmax(np.asarray(log_weight))))


def history_associations(history: lineage.LineagePath, valid) -> np.ndarray:
    """(T, K) landmark ids of one particle's history (``lineage.landmark_identities``), -1
    where ``valid`` (T, K) marks no observation."""
    ids, _ = lineage.landmark_identities(history.match, history.birth_slot)
    return np.where(np.asarray(valid), np.asarray(ids), -1)


def confirmed_ids(ids):
    """(T, K) landmark ids with landmarks seen once dropped (-1) and the rest renumbered.

    A landmark seen once has no residual (its position fits its one observation exactly),
    so it carries nothing about the noise, and its unknowns would only enlarge the solve.
    """
    used = ids >= 0
    counts = np.bincount(ids[used], minlength=1)
    keep = used & (counts[np.where(used, ids, 0)] >= 2)
    out = np.full(ids.shape, -1, ids.dtype)
    if keep.any():
        _, out[keep] = np.unique(ids[keep], return_inverse=True)
    return out


def _with_values(params: Params, values: dict) -> Params:
    return params._replace(**{name: jnp.asarray(value, getattr(params, name).dtype)
                              for name, value in values.items()})


def with_typical_heading_std(params: Params, odometry, z_range) -> Params:
    """``params`` with ``association_heading_std`` = the root-mean-square heading std of its
    motion model over the log's moves (odometry (T, 3), z_range (N,); module docstring)."""
    heading = typical_stds(params, odometry, z_range)[0]
    return params._replace(association_heading_std=jnp.asarray(
        heading, params.association_heading_std.dtype))


def _plain(value):
    array = np.asarray(value, np.float64)
    return float(array) if array.ndim == 0 else tuple(float(v) for v in array)


def _trust_region(old: Params, new: Params, odometry, z_range) -> Params:
    """``new`` with each noise group's coefficients scaled back so that its typical std moves
    by at most ``TRUST_FACTOR`` from ``old``'s in one iteration.

    An iteration on a bad association (a filter that lost the map) can propose an absurd
    noise; the next filter run with it cannot recover. The limit lets real changes through
    in a few iterations (a factor 27 in three) and stops a single jump.
    """
    before = typical_stds(old, odometry, z_range)
    after = typical_stds(new, odometry, z_range)
    updates = {}
    for group, fields in enumerate(_GROUP_FIELDS):
        ratio = after[group] / max(before[group], 1e-12)
        limited = float(np.clip(ratio, 1.0 / TRUST_FACTOR, TRUST_FACTOR))
        if ratio > 0 and limited != ratio:
            for name in fields:
                updates[name] = np.asarray(getattr(new, name), np.float64) * (limited / ratio)
    return _with_values(new, updates)


class _Log(NamedTuple):
    """The log as the EM loop reads it (host arrays)."""

    controls: np.ndarray  # (T, 3)
    observations: Observations
    start: np.ndarray  # (3,) start pose
    z: np.ndarray  # (T, K, 2) float64, 0 where not valid
    valid: np.ndarray  # (T, K) valid and finite


def _check_patience(patience) -> None:
    if patience is None:
        return
    whole = isinstance(patience, (int, np.integer)) and not isinstance(patience, bool)
    if not whole or patience < 1:
        raise ValueError(f"calibrate_params needs patience >= 1 (an int) or None; got "
                         f"{patience!r}")


def _checked_log(controls, observations: Observations, initial_pose, iterations: int,
                 tol: float) -> _Log:
    if iterations < 1 or not tol > 0:
        raise ValueError(f"calibrate_params needs iterations >= 1 and tol > 0; got "
                         f"{iterations}, {tol}")
    controls = np.asarray(controls)
    if controls.ndim != 2 or controls.shape[1] != 3:
        raise ValueError(f"calibrate_params: controls must be (T, 3); got {controls.shape}")
    steps = controls.shape[0]
    if observations.z.shape[:1] != (steps,):
        raise ValueError(f"calibrate_params: observations have {observations.z.shape[0]} "
                         f"steps but controls {steps}; expected one row of each per step")
    start = np.zeros(3) if initial_pose is None else np.asarray(initial_pose, np.float64)
    z = np.asarray(observations.z, np.float64)
    valid = np.asarray(observations.valid) & np.all(np.isfinite(z), axis=-1)
    return _Log(controls, observations, start, np.where(valid[..., None], z, 0.0), valid)


class _MStep(NamedTuple):
    """One iteration's M-step (module docstring, step 4)."""

    update: dict  # the fitted ``Params`` fields
    cost: float  # the smoother's final robust cost per residual row
    motion_fitted: bool
    observation_fitted: bool
    used: int  # observations of landmarks seen ``MIN_SIGHTINGS`` times or more
    relative_std: dict  # group -> relative standard error of its fitted std
    bursts_fitted: bool  # the motion fit found bursts (else it kept the defensive ones)
    radius: dict | None = None  # {"radius_noise": std}, applied after EM (``_with_radius``)
    radius_used: int = 0  # measured radii of landmarks with ``MIN_SIGHTINGS`` of them
    radius_relative_std: float = float("inf")  # ``noise_fit.radius_noise_relative_error``
    gain: GainFit | None = None  # the odometry gains' fit (``odometry_gain``), when asked


def _merged(smoothed: smoothing.Smoothed, smooth) -> smoothing.Smoothed:
    """``smoothed`` re-solved by ``smooth(path, landmark_of_obs)`` from its own path with
    split landmarks merged (``landmark_merge``); ``smoothed`` itself when nothing merges."""
    ids = np.asarray(smoothed.landmark_of_obs)
    step, row = np.nonzero(ids >= 0)
    labels = merge_split_landmarks(smoothed.landmark, step, ids[step, row])
    if len(labels) == 0 or labels.max() + 1 == len(labels):
        return smoothed
    return smooth(smoothed.path, relabel(ids, labels))


def _log_has_radii(log: _Log) -> bool:
    """Whether any valid observation of the log carries a measured trunk radius."""
    return bool(measured_radii(log.observations.radius, log.valid).any())


def _radius_update(log: _Log, landmark_of_obs) -> tuple[dict, int, float]:
    """({"radius_noise": std} or {}, radii that qualify, relative standard error of the std):
    the trunk-radius std from the scatter of the measured radii within each landmark of the
    smoothed association (T, K) (``noise_fit.radius_noise_from_history``, landmarks with
    ``MIN_SIGHTINGS`` radii or more), and its error by a bootstrap over those landmarks
    (``noise_fit.radius_noise_relative_error``). Nothing (and an error of inf) when fewer
    than ``MIN_OBSERVATIONS`` radii qualify, or when the std comes out 0 (95 % of the radii
    equal their landmark's median, as exact simulated radii do: a std of 0 would make any
    difference infinitely unlikely)."""
    history = (np.asarray(landmark_of_obs), np.asarray(log.observations.radius, np.float64),
               log.valid)
    std, used = radius_noise_from_history(*history, min_sightings=MIN_SIGHTINGS)
    if used < MIN_OBSERVATIONS or not (np.isfinite(std) and std > 0.0):
        return {}, used, float("inf")
    return ({"radius_noise": float(std)}, used,
            radius_noise_relative_error(*history, min_sightings=MIN_SIGHTINGS))


def _fit_gain(log: _Log, params: Params, smoothed: smoothing.Smoothed, filter_path, odometry,
              smooth) -> tuple[smoothing.Smoothed, np.ndarray, GainFit | None]:
    """(smoothed, moves (T, 3), fit): ``odometry_gain`` for the association of ``smoothed``
    (module docstring, step 4; ``odometry_gain``): the gains' fit
    (``odometry_gain.gain_update``), the log smoothed again with the readings times the new
    gains, and so on, at most ``GAIN_ROUNDS`` fits or until no gain moves by more than
    ``GAIN_TOL`` (relative); the total move held within ``MAX_STEP``; then each gain keeps
    it only where BIC calls for it (``odometry_gain.significant_gains``, the slope's error
    inflated by the rounds' contraction), and the log is smoothed at the gains kept. Each
    re-smoothing starts from the last path; the association stays. ``smoothed`` and the
    given moves come back, with fit None, when the log has fewer than ``MIN_MOVES`` smoothed
    moves or a re-smoothing fails; ``fit`` is the last round's, with the gains kept and
    their change."""
    old = np.asarray(params.odometry_gain, np.float64)
    readings = in_float64(with_gain, odometry, 1.0 / old)
    first, gain, moves, factors = smoothed, old, odometry, []
    try:
        for _ in range(GAIN_ROUNDS):
            res = smoothed_residuals(log.start, smoothed, filter_path, moves, log.z, params)
            if int(np.all(np.isfinite(res.true_moves), axis=1).sum()) < MIN_MOVES:
                return first, odometry, None
            fit = gain_update(gain, res.measured_moves + res.move_error, res.measured_moves,
                              res.move_std)
            factors.append((fit.translation.factor, fit.rotation.factor))
            if fit.change == 0.0:
                break
            gain = old * np.clip(np.asarray(fit.gain) / old, 1.0 / MAX_STEP, MAX_STEP)
            moves = in_float64(with_gain, readings, gain)
            smoothed = smooth(smoothed.path, smoothed.landmark_of_obs, moves)
            if fit.change < GAIN_TOL:
                break
        kept = np.asarray(significant_gains(old, gain, fit, contraction(factors)))
        if np.array_equal(kept, old):
            smoothed, moves = first, odometry
        elif not np.array_equal(kept, gain):
            moves = in_float64(with_gain, readings, kept)
            smoothed = smooth(smoothed.path, smoothed.landmark_of_obs, moves)
    except (RuntimeError, np.linalg.LinAlgError, ValueError):
        return first, odometry, None
    return smoothed, moves, fit._replace(gain=(float(kept[0]), float(kept[1])),
                                         change=float(np.max(np.abs(kept / old - 1.0))))


def _m_step(config: FilterConfig, params: Params, log: _Log, odometry, history, iteration: int,
            calibrate_sensor: bool, smoother_iterations: int,
            merge_landmarks: bool = False, calibrate_radius: bool = False,
            calibrate_gain: bool = False) -> _MStep | str:
    """Smooth the best particle's association and fit the settings (module docstring, 3-4);
    a warning instead when there is nothing to fit or the smoother failed. With
    ``merge_landmarks`` the smoothed map's split landmarks are merged and the log smoothed
    again with the merged association before the fit (``landmark_merge``). With
    ``calibrate_radius`` also the trunk-radius std (``_radius_update``), kept apart: EM's
    runs match without it (``_with_radius`` applies it after EM). With ``calibrate_gain``
    also ``odometry_gain`` (``_fit_gain``); the noise is then fitted to the residuals of the
    log smoothed with the readings times the new gains."""
    ids = history_associations(history, log.valid)
    false_alarms = single_share(ids)
    ids = confirmed_ids(ids)
    if not np.any(ids >= 0):
        return ("no landmark was observed twice with the starting settings: nothing to "
                "calibrate on, the given settings are used")
    filter_path = np.asarray(history.pose, np.float64)

    def smooth(path, landmark_of_obs, moves=odometry):
        return smoothing.smooth_path(log.start, path, moves, log.z, landmark_of_obs, params,
                                     iterations=smoother_iterations, tol=1e-4,
                                     calibrate_rounds=smoothing.VARIANCE_ROUNDS)

    gain, moves = None, odometry
    try:
        smoothed = smooth(filter_path, ids)
        if merge_landmarks:
            smoothed = _merged(smoothed, smooth)
        if calibrate_gain:
            smoothed, moves, gain = _fit_gain(log, params, smoothed, filter_path, odometry,
                                              smooth)
    except (RuntimeError, np.linalg.LinAlgError, ValueError) as error:
        return (f"the smoother failed on this log ({error}); calibration stopped at "
                f"iteration {iteration}")
    rows = 3 * len(log.controls) + 2 * int((ids >= 0).sum())
    res = smoothed_residuals(log.start, smoothed, filter_path, moves, log.z, params)
    used = res.sightings[res.obs_landmark] >= MIN_SIGHTINGS
    update = {}
    motion = motion_noise_update(res, smoothed.noise_scales, defensive_bursts(config))
    bursts_fitted = False
    if motion is not None:
        (rot1, trans, rot2), eps, kappa, bursts_fitted = motion
        update.update(rot1_noise=rot1, trans_noise=trans, rot2_noise=rot2,
                      motion_outlier_probability=eps, motion_outlier_scale=kappa)
    if gain is not None:
        update["odometry_gain"] = gain.gain
    obs = observation_noise_update(res, smoothed.noise_scales, used)
    if obs is not None:
        update.update(range_noise=obs[0], bearing_noise=obs[1],
                      range_std_floor=max(STD_FLOOR, 0.5 * obs[0][1]),
                      bearing_std_floor=max(STD_FLOOR, 0.5 * obs[1][1]))
    if calibrate_sensor:
        update.update(sensor_update(res, log.z, log.valid, used, smoothed.path,
                                    smoothed.landmark, params))
        if false_alarms is not None:
            update["false_alarm_probability"] = float(np.clip(false_alarms, 1e-3, 0.5))
    if "association_gate" in update:
        # The airlock's tests are on the position alone: its width keeps the 2-dof gate.
        update["airlock_sigmas"] = float(np.sqrt(update["association_gate"]))
    radius, radius_used, radius_error = (_radius_update(log, smoothed.landmark_of_obs)
                                         if calibrate_radius else ({}, 0, float("inf")))
    return _MStep(update, float(smoothed.cost[-1]) / max(rows, 1), motion is not None,
                  obs is not None, int(used.sum()),
                  group_relative_errors(res, used, motion is not None, obs is not None,
                                        smoothed.degrees_of_freedom),
                  bursts_fitted, radius or None, radius_used, radius_error, gain)


LOOSE_INTERVAL = 0.5  # a noise group's stated 95 % half-width (relative) above which it is named


def loose_interval_warnings(relative_std: dict) -> list[str]:
    """Plain-word warnings for the noise groups (``NOISE_GROUPS``) whose stated 95 % interval,
    1 +- 1.96 ``relative_std``, is wider than +-``LOOSE_INTERVAL``: the log barely determines
    them, most often because the smoothed path absorbs the group's error (few degrees of
    freedom; Victoria Park's heading noise: +-92 %, docs/results.md, victoria_park). A
    group with no finite figure is not named (it was not fitted)."""
    out = []
    for group in NOISE_GROUPS:
        half = 1.96 * float(relative_std.get(group, float("inf")))
        if np.isfinite(half) and half > LOOSE_INTERVAL:
            out.append(f"the log barely determines the {group} noise (95 % interval "
                       f"+-{100.0 * half:.0f} % of the fitted std): if the run goes wrong, "
                       f"try a wider {group} noise than the fitted one")
    return out


def _behind(m_steps: list, source) -> int:
    """How many M-steps lie behind the returned settings: up to and including ``source``
    (0 when it is none of them: the starting settings were returned)."""
    return next((i + 1 for i, step in enumerate(m_steps) if step is source), 0)


def _with_radius(params: Params, radius: dict, gate_fitted: bool) -> Params:
    """``params`` with the trunk-radius std ``radius`` ({"radius_noise": std} or {}: keep
    theirs) and, when the calibration fitted the gate (``gate_fitted``) and the radius std
    in use is > 0, that gate moved to 3 degrees of freedom (``detection_fit.gate_with_radius``);
    ``airlock_sigmas`` keeps the 2-dof root (the airlock tests the position alone)."""
    params = _with_values(params, radius)
    if gate_fitted and _plain(params.radius_noise) > 0.0:
        gate = gate_with_radius(_plain(params.association_gate))
        params = _with_values(params, {"association_gate": float(gate)})
    return params


def interval_text(relative_std: float) -> str:
    """A relative standard error as its printed 95 % interval: "+- 9.8 %" (1.96 times it, two
    significant digits and no exponent: "+- 120 %", "+- 0.26 %"), or "no interval" when it
    is not finite (a trunk-radius std from a single landmark's radii; a figure not stated)."""
    percent = 196.0 * float(relative_std)
    if not np.isfinite(percent):
        return "no interval"
    return f"+- {percent:.0f} %" if percent >= 10 else f"+- {percent:.2g} %"


def _stated_errors(m_steps: list, source, steps: int) -> tuple[dict, dict, bool | None]:
    """(relative_std, samples, bursts_fitted) of ``CalibrationInfo``: each group as its
    latest fit among the M-steps up to ``source`` (the one behind the returned settings)
    stated it; ``steps`` moves for the motion groups; whether that latest motion fit found
    bursts (None without a motion fit); samples["radius"]: the radii behind ``source``'s
    radius std, when it fitted one. Nothing when ``source`` is none of them (the
    starting settings were returned: no fit lies behind them)."""
    behind = _behind(m_steps, source)
    relative_std, samples, bursts_fitted = {}, {}, None
    for step in m_steps[:behind]:
        relative_std.update(step.relative_std)
        if step.motion_fitted:
            samples["heading"] = samples["translation"] = steps
            bursts_fitted = step.bursts_fitted
        if step.observation_fitted:
            samples["range"] = samples["bearing"] = step.used
    if behind and m_steps[behind - 1].radius:  # a radius std is taken from ``source`` only
        samples["radius"] = m_steps[behind - 1].radius_used
        relative_std["radius"] = m_steps[behind - 1].radius_relative_std
    return relative_std, samples, bursts_fitted


def _best_run(objective, dropped, fill_step=None, evidence=None,
              level: float | None = None) -> int:
    """Index of the filter run with the highest log marginal likelihood; with ``evidence``
    and ``level``, of the first run a likelihood ranks or the last one whose per-step log
    evidence beat the best before it by the t test.

    EM raises the marginal likelihood while the E-step's association holds; when it did not
    converge, the settings whose own filter run scored best are returned. The first run used
    the starting settings, whose sensor fields (range, field of view, detection) are guesses
    no M-step has seen: it is never the one returned. Runs that dropped births (the map was
    full) compete only when every other run did too (or scored no finite value): their score
    counts unmapped trees again at each sighting (``noise_scale``), so among them the one
    that dropped the fewest births is returned (ties: the one whose map filled last, then the
    earlier), or, without ``fill_step``, the most likely. The births dropped, summed over
    particles and steps, count every landmark start the map had no slot for over the whole
    run: the more a run splits trees, the more it drops. The first step with a dropped birth
    (the scale search's measure, whose runs stop there) is one noisy point of that: on
    Victoria Park key 4 (2026-12-06) runs 2 and 5 filled at scans 4,182 and 4,094 while
    dropping 928,813 and 599,186 births, and run 2's settings, returned by the fill step,
    ran 34.8 m off GPS (in-sample: this rule was written after seeing it; docs/results.md).
    objective (R,), dropped (R,) births each run dropped, fill_step (R,) each run's first
    step that dropped one (T when none).

    With ``evidence`` (R arrays (T,), each run's ``Trace.log_evidence``) and ``level``, the
    fair runs with a finite score (after the first) are taken in order and a run replaces
    the best so far only when its per-step log evidence beats the best's by
    ``score_comparison.significantly_better`` at ``level`` (one-sided; a t test over blocks
    of steps): a higher sum that one or two steps make, or that the runs' chance could
    make, does not count. When no run kept every birth the rules above stand.
    """
    scores = np.asarray(objective, np.float64)
    scores[0] = -np.inf if len(scores) > 1 else scores[0]
    full = np.asarray(dropped) > 0
    if fill_step is not None and _no_fair_run(objective, dropped):
        first = 1 if len(scores) > 1 else 0  # the first run is never returned (above)
        later = np.asarray(dropped)[first:]
        # A run whose score is not finite (a broken run) is taken only if every one is.
        finite = np.isfinite(scores[first:])
        eligible = np.where(finite, later, 0) if np.any(finite & (later > 0)) else later
        return first + fewest_dropped(eligible, np.asarray(fill_step)[first:])
    if np.any(fair(scores, dropped)):
        scores = np.where(full, -np.inf, scores)
    if not np.any(np.isfinite(scores)):
        return len(scores) - 1
    if evidence is None or level is None or not np.any(fair(scores, dropped)):
        return int(np.argmax(np.where(np.isfinite(scores), scores, -np.inf)))
    ranked = np.flatnonzero(np.isfinite(scores))
    best = int(ranked[0])
    for run in ranked[1:]:
        if significantly_better(evidence[run], evidence[best], level):
            best = int(run)
    return best


def fewest_dropped(dropped, fill_step) -> int:
    """Index of the overflowed run (``dropped`` (R,) > 0) that dropped the fewest births;
    ties go to the latest ``fill_step`` (R,), then to the first; -1 when none overflowed."""
    return first_overflowed(dropped, dropped, -np.asarray(fill_step))


def _stalled(objective, dropped, patience: int | None, fill_step=None, evidence=None,
             level: float | None = None) -> bool:
    """Whether none of the last ``patience`` filter runs is the best so far by ``_best_run``'s
    rule (the first run never counts as best; a run whose map overflowed does not beat a
    lower fair one; a tie keeps the earlier run; with ``evidence`` (R arrays (T,)) and
    ``level``, a later run must beat the best by the t test). objective (R,), dropped (R,),
    fill_step (R,) or None. None patience: never. Nor
    while no run after the first kept every birth with a finite score (``_no_fair_run``):
    no likelihood ranks such runs, and EM's later iterations may still reach one that keeps
    its map (on Victoria Park every key's fifth run dropped the fewest births of runs 2-5).
    Can first hold after patience + 2 runs."""
    if patience is None or _no_fair_run(objective, dropped):
        return False
    best = _best_run(objective, dropped, fill_step, evidence, level)
    return len(objective) - 1 - best >= patience


def _fit_warnings(last: _MStep | None, steps: int, radius_step: _MStep | None = None,
                  radius_kept: float = 0.0) -> list[str]:
    """Plain-word warnings for the groups kept at their start; ``radius_step``: the M-step
    whose association the returned radius std comes from (None: no radius std to fit)."""
    out = []
    if radius_step is not None and radius_step.radius_used < MIN_OBSERVATIONS:
        out.append(f"the log carries trunk radii, but only {radius_step.radius_used} belong to "
                   f"landmarks with {MIN_SIGHTINGS} or more of them (need "
                   f"{MIN_OBSERVATIONS}) to fit the radius std: kept the given "
                   f"radius_noise ({radius_kept:g} m)")
    if last is None or not last.motion_fitted:
        out.append(f"too few moves ({steps}; need {MIN_MOVES}) to fit the motion noise: "
                   "kept the given motion noise")
    if last is None or not last.observation_fitted:
        out.append(f"too few observations of landmarks seen {MIN_SIGHTINGS} or more times "
                   f"({0 if last is None else last.used}; need {MIN_OBSERVATIONS}) to fit "
                   "the sensor noise: kept the given sensor noise")
    return out


def _progress_line(iteration: int, objective: float, typical, change: float,
                   dropped: int = 0, fill_step: int | None = None,
                   explain_overflow: bool = True) -> str:
    """One EM iteration in one line. A run whose map overflowed says so, and, with
    ``explain_overflow`` (the calibration's first such line only), what that means for the
    choice of the returned run."""
    at = "" if fill_step is None else f" from step {fill_step}"
    why = (" (if EM does not converge, the run whose settings are returned is chosen among "
           "the later runs that dropped none, when there are any, else it is the one that "
           "dropped the fewest births)" if explain_overflow else "")
    full = f", map full{at}: {dropped} births dropped{why}" if dropped else ""
    return (f"calibration iteration {iteration}: log marginal likelihood {objective:.1f}{full}, "
            f"typical stds heading {typical[0]:.4g} rad, translation {typical[1]:.4g} m, "
            f"range {typical[2]:.4g} m, bearing {typical[3]:.4g} rad (largest change of a std "
            f"or an odometry gain {change:.1%})")


def _no_fair_run(objective, dropped) -> bool:
    """Whether ``_best_run`` ranks EM's runs by the births they dropped (``fewest_dropped``;
    the fill step breaks ties), not by likelihood: no run it may return (every run after the
    first; the only one when there is one) kept every birth with a finite score, and one of
    them overflowed. objective (R,), dropped (R,)."""
    first = 1 if len(objective) > 1 else 0
    later = np.asarray(dropped)[first:]
    return not np.any(fair(np.asarray(objective)[first:], later)) and bool(np.any(later > 0))


def _unranked_warning(objective, dropped, found: ScaleSearch | None, slots: int) -> list[str]:
    """The plain-word warning for settings no likelihood ranked: every EM run ``_best_run``
    may return overflowed the map (``_no_fair_run``; objective (R,), dropped (R,)) and
    the scale search, when it ran (``found``), met no fair candidate either (``any_fair``).
    The returned settings are then a fallback (EM's run that dropped the fewest births,
    the search's map that filled last); on Victoria Park keys 4 and 6, under EM's earlier
    fallback (the map that filled last, with ``patience``), such settings ran 32-35 m off
    GPS (docs/results.md). Else []."""
    if not _no_fair_run(objective, dropped) or (found is not None and any_fair(found)):
        return []
    runs = "every EM run" + (" and every candidate of the noise-scale search"
                             if found is not None else "")
    return [f"no calibration run kept every landmark birth: {runs} filled the map's {slots} "
            "slots, so no likelihood ranked the settings returned; expect trees split into "
            "several landmarks and a poor run (too few map slots for this log, or "
            "observations of one tree that fail to match with every noise tried)"]


def _stalled_line(iteration: int, objective, dropped, patience: int, fill_step,
                  evidence=None, level: float | None = None) -> str:
    best = _best_run(objective, dropped, fill_step, evidence, level)  # a fair run (``_stalled``)
    by_test = "" if level is None else f" by the t test at the {level:g} level"
    return (f"calibration iteration {iteration}: log marginal likelihood {objective[-1]:.1f}; "
            f"none of the last {patience} runs beat iteration {best + 1}'s "
            f"{objective[best]:.1f}{by_test}: EM stops (not converged)")


def _scale_search(config, key, params, controls, observations, start, scales, last: _MStep,
                  progress, known=None, workers=None):
    """``search_noise_scales`` over the groups EM fitted (an unfitted group's grid is (1,)):
    (params, ``ScaleSearch``, a clause for the verdict). start: (3,) EM's runs' start pose
    (their dtype), so the search's runs are EM's compiled program."""
    unit = (1.0,)
    params, found = search_noise_scales(
        config, key, params, controls, observations, start,
        motion_scales=scales if last.motion_fitted else unit,
        observation_scales=scales if last.observation_fitted else unit,
        known=known, workers=workers)
    if progress is not None:
        progress(f"calibration: likelihood over noise scales: {describe_search(found)}")
    if found.motion_scale == 1.0 and found.observation_scale == 1.0:
        return params, found, "; the likelihood kept EM's noise (noise scales x1)"
    return params, found, (f"; noise scaled by the filter's likelihood: motion "
                           f"x{found.motion_scale:g}, observation x{found.observation_scale:g}")


def group_scales(info: CalibrationInfo) -> np.ndarray:
    """(4,) the likelihood search's multiplier of each noise group (``NOISE_GROUPS`` order:
    s_m on heading and translation, s_o on range and bearing; ones without a search)."""
    found = info.noise_scales
    motion, sensor = (1.0, 1.0) if found is None else (found.motion_scale,
                                                       found.observation_scale)
    return np.array([motion, motion, sensor, sensor], np.float64)


def em_typical_std(info: CalibrationInfo) -> np.ndarray:
    """(4,) EM's own typical std of each noise group, the estimate ``relative_std``
    describes: ``typical_std[-1]`` (the returned settings, after the search) divided by the
    search's scales (each scales every coefficient of its group, so the typical std scales
    with it)."""
    return np.asarray(info.typical_std[-1], np.float64) / group_scales(info)


def calibrate_params(config: FilterConfig, key, controls, observations: Observations,
                     initial_pose=None, params: Params | None = None, *,
                     motion_model: str | None = None, iterations: int = 5, tol: float = 0.05,
                     calibrate_sensor: bool = True, calibrate_radius: bool = True,
                     calibrate_gain: bool = False, smoother_iterations: int = 15,
                     merge_landmarks: bool = False, scale_search: bool = True,
                     scales=DEFAULT_SCALES, patience: int | None = 2,
                     search_workers: int | None = None, significance: float | None = None,
                     progress=None) -> tuple[Params, CalibrationInfo]:
    """Estimate the filter's settings from one log, with no ground truth (module docstring).

    Args:
      config: the ``FilterConfig`` the log will be filtered with (K = ``max_obs`` must match
        the observations). Its motion model is used unless ``motion_model`` is given.
      key: PRNG key of every iteration's filter run (the same one each time).
      controls: (T, 3) the log's controls. observations: ``Observations`` (T, K, ...).
      initial_pose: (3,) start pose (default zeros).
      params: the first iteration's settings; default ``starting_params(config)``. Fields the
        calibration does not estimate are kept from it. ``association_heading_std``, which
        it estimates from the motion noise, is set from their motion noise on this log for
        the EM runs too, and returned as given when no motion fit lies behind the result.
      iterations: most EM iterations (each one filter run). tol: stop when every noise
        group's typical std, and each odometry gain, moved by less than this fraction in one
        iteration. The default 5
        (6 until 2026-12-05) returns the same settings on every log whose EM likelihoods
        docs/results.md records (MRCLAM robots 1-5, Victoria Park, twelve simulated logs): none
        scored its best after its fifth run, and a sixth run cost a filter run on Victoria
        Park and MRCLAM robots 2 and 5. A log whose likelihood still rises at the fifth run
        is cut there (the verdict says "not converged").
      patience: also stop (not converged) once this many filter runs in a row did not beat
        the best run before them (a lower log marginal likelihood; with ``significance``,
        no significant gain by the test: ``_stalled``); the best run's
        settings are then returned, as when ``iterations`` runs out. None: run until
        ``tol`` or ``iterations``. Must be >= 1; can only stop EM when
        ``iterations >= patience + 2`` (the first run never counts as best), and never while
        every run after the first overflowed the map (then the run that dropped the fewest
        births is returned: ``_best_run``).
      calibrate_sensor: also estimate max_range, miss_range, detection and false-alarm
        probabilities and the gate (else only the noise).
      calibrate_radius: when the observations carry measured trunk radii (> 0), also
        estimate ``radius_noise`` (module docstring, step 4) from the association behind the
        returned settings. EM's runs then match without a radius std (0), the scale
        search's runs and the user's with the fitted one. When no std can be fitted
        (``_radius_update``: too few radii, with a warning, or radii that never differ
        within a landmark) the given ``radius_noise`` is returned. A log without radii, or
        ``calibrate_radius=False``, runs EM with the given ``radius_noise``. Whenever the
        returned settings match on a radius (std > 0) and the calibration fitted the gate,
        the gate is the 3-dof gate of ``detection_fit.gate_with_radius``; with
        ``calibrate_sensor=False`` the given gate is kept as it is.
      calibrate_gain: also estimate ``odometry_gain``, the odometry's systematic error
        (``odometry_gain``: each M-step's least-squares slope of the smoothed moves on the
        measured ones, kept only where BIC calls for it). Off by default (the given gains
        are kept): the gains come out right (within 1 % on simulated logs read with a
        known gain, within 0.02 of Vicon's drive ratios on MRCLAM robots 2, 3 and 5), but
        the online filter with them did no better on those simulated logs (median final
        error 0.87 against 0.38 m without the fit, 4 against 3 of 8 logs over 0.5 m: the
        runs flip log by log) nor on MRCLAM (docs/results.md, mrclam and self_calibration,
        "Twenty-sixth session"), and the fit costs smoothings.
      smoother_iterations: most Levenberg-Marquardt steps of each smoothing.
      merge_landmarks: in each M-step, merge the smoothed landmarks that were never observed
        at one step and lie closer than half the distance of any two that were
        (``landmark_merge``), and fit on the log smoothed again with the merged association:
        a filter that split its trees leaves the smoother no loop closure, and the noise
        fitted to such residuals shrinks. Off by default: on the simulated check of
        ``experiments/self_calibration.py`` (8 runs, seed 500, no wobble, odometry and sensor
        noise x2) it broke two runs' calibration (final error 0.07 -> 1.47 m and
        0.04 -> 1.00 m), and on MRCLAM dataset 1 (5 robots, one run each) the median ratio of
        dead-reckoning to filter ATE was 1.63 with it against 2.19 without.
      scale_search: after EM, multiply the motion and then the observation noise by the
        multipliers in ``scales`` (must contain 1) of highest filter log marginal likelihood
        among the runs whose map never overflowed (when every run of a stage overflowed, the
        motion stage keeps 1 and the observation stage takes the run whose map filled last;
        ``noise_scale.search_noise_scales``, EM's key; only the groups EM fitted): EM on
        a poor association shrinks the noise. ``converged`` and ``relative_std`` still describe
        EM's own estimate. Costs at most 2 len(scales) - 1 more filter runs (one fewer when
        EM did not converge and no radius std was fitted: its best run is reused), fewer
        when a stage's score falls past its peak (``noise_scale.walk_stage``).
      significance: None (default): the run with the highest summed log evidence is the
        best. A level in (0, 1): a later EM run replaces the best before it only when its
        per-step log evidence beats the best's by the one-sided test at that level
        (``score_comparison.significantly_better``: Diebold and Mariano's paired t test,
        batch means over 20 blocks of steps), for the returned iterate and for
        ``patience``; the scale search still compares sums. Made for MRCLAM, where one
        step can score -1e5 nats in one run and not in another (a creeping robot's
        particles all drawn behind it) and so decide the plain comparison. Measured mixed,
        so not the default (docs/results.md, mrclam, "Twenty-eighth session"): it kept
        EM's second run on all 20 MRCLAM calibrations; over four calibrations robot 1 went
        from 2.20x to 3.18x dead reckoning / ATE (in-sample: its runs suggested the test),
        robot 2 stayed level, robots 3, 4 and 5 got worse, and the simulated sensor-10x row went from 0.477 to 0.841 m (seed 700).
        A run with one outlying step stays the best against any gain smaller than about
        0.7 of that step (its block makes the standard error), and never becomes it.
      search_workers: candidates of the scale search run at once, each in its own thread
        (the same choice for every value; ``noise_scale.walk_stage``). None:
        ``noise_scale.default_workers()``, 2 on a CPU with two or more cores, where two
        runs in two threads take 1.1-1.3 runs' time.
      progress: optional callable(str) told of each iteration in one line.
    Returns:
      (params, info): the calibrated ``Params`` (dtype of ``params``) and ``CalibrationInfo``.
      A log too short or too sparse to calibrate returns the given ``params`` unchanged for
      the groups it could not fit, and says so in ``info.warnings`` and ``info.verdict``.
    """
    log = _checked_log(controls, observations, initial_pose, iterations, tol)
    _check_patience(patience)
    if significance is not None and not 0.0 < significance < 1.0:
        raise ValueError(f"calibrate_params needs significance in (0, 1) or None; got "
                         f"{significance!r}")
    scales = check_scales("scales", scales)
    search_workers = check_workers(search_workers, "search_workers")
    motion_model = motion_model or config.motion_model
    params = starting_params(config) if params is None else params
    steps, dtype = len(log.controls), params.rot1_noise.dtype
    z_range = log.z[log.valid][:, 0]
    if log.valid.sum() < MIN_OBSERVATIONS:
        warning = (f"only {int(log.valid.sum())} valid observations in the log; the "
                   f"calibration needs at least {MIN_OBSERVATIONS} of landmarks seen "
                   f"{MIN_SIGHTINGS} or more times: the given settings are used")
        return params, CalibrationInfo(0, np.zeros(0), np.zeros(0), np.zeros((0, 4)), {}, {},
                                       {}, False, "not calibrated: too few observations",
                                       (warning,), None, np.zeros(0, np.int64), None,
                                       np.zeros(0, np.int64))
    objective, dropped, costs, typical, evaluated, warnings = [], [], [], [], [], []
    runs, fill_steps = [], []  # each EM filter run's RunScore, and its fill step
    evidence = []  # each EM filter run's per-step log evidence (T,)
    values = {}
    converged, stalled, last, m_steps = False, False, None, []
    controls = jnp.asarray(log.controls, dtype)
    start = jnp.asarray(log.start, dtype)
    # The heading std for matching is a function of the motion noise (module docstring,
    # step 4): the first run's follows the starting motion noise on this log. The given
    # value comes back when no motion fit lies behind the returned settings.
    given_heading_std = params.association_heading_std
    odometry = np.asarray(control_to_odometry(controls, params, motion_model), np.float64)
    params = with_typical_heading_std(params, odometry, z_range)
    # EM's runs match without a radius std that is to be fitted (module docstring, step 4).
    given_radius = _plain(params.radius_noise)
    fit_radius = calibrate_radius and _log_has_radii(log)
    if fit_radius:
        params = _with_values(params, {"radius_noise": 0.0})
    for done in range(1, iterations + 1):
        odometry = np.asarray(control_to_odometry(controls, params, motion_model), np.float64)
        typical.append(typical_stds(params, odometry, z_range))
        final, trace = run_filter(config, key, params, controls, observations, start,
                                  record_lineage=True)
        runs.append(score_trace(trace, stopped_at_dropped_birth=False))
        objective.append(runs[-1].log_likelihood)
        dropped.append(runs[-1].dropped_births)
        fill_steps.append(runs[-1].fill_step)
        evidence.append(np.asarray(trace.log_evidence, np.float64))
        evaluated.append(params)
        if _stalled(objective, dropped, patience, fill_steps, evidence, significance):
            stalled = True
            if progress is not None:
                progress(_stalled_line(done, objective, dropped, patience, fill_steps,
                                       evidence, significance))
            break
        step = _m_step(config, params, log, odometry,
                       best_history(trace.lineage, final.log_weight), done, calibrate_sensor,
                       smoother_iterations, merge_landmarks, fit_radius, calibrate_gain)
        if isinstance(step, str):
            warnings.append(step)
            break
        last = step
        m_steps.append(step)  # m_steps[i] made the settings of filter run i + 1
        costs.append(step.cost)
        fitted = _with_values(params, step.update)
        # The new settings' moves (their gains), for the limits and the heading std below.
        odometry = np.asarray(control_to_odometry(controls, fitted, motion_model), np.float64)
        params = _trust_region(params, fitted, odometry, z_range)
        if step.motion_fitted:
            params = with_typical_heading_std(params, odometry, z_range)
        values.update({name: _plain(getattr(params, name)) for name in step.update})
        if step.motion_fitted:
            values["association_heading_std"] = _plain(params.association_heading_std)
        new_typical = typical_stds(params, odometry, z_range)
        change = max(np.max(np.abs(new_typical / typical[-1] - 1.0)),
                     step.gain.change if step.gain is not None else 0.0)
        if progress is not None:
            progress(_progress_line(done, objective[-1], new_typical, change, dropped[-1],
                                    fill_steps[-1],
                                    explain_overflow=not any(dropped[:-1])))
        if change < tol:
            converged = True
            break
    chosen, known, source = "", None, last  # source: the M-step behind ``params``
    if not converged:
        best = _best_run(objective, dropped, fill_steps, evidence, significance)
        source = m_steps[best - 1] if 1 <= best <= len(m_steps) else None
        params, known = evaluated[best], runs[best]
        values = {name: _plain(getattr(params, name)) for name in values}
        kept = int(np.sum(np.asarray(dropped[1:]) == 0))
        among = (f", among the {kept} whose map never overflowed"
                 if 0 < kept < len(evaluated) - 1 else "")
        why = (f"no later run kept every birth with a finite score; it dropped the fewest "
               f"births, {dropped[best]}, its map full from step {fill_steps[best]}"
               if _no_fair_run(objective, dropped) else
               f"the highest log marginal likelihood of the {len(evaluated)} filter "
               f"runs{among}" if significance is None else
               f"of the {len(evaluated)} filter runs{among}, the first a likelihood ranks "
               f"or a later one whose per-step log evidence beat the best before it by a "
               f"one-sided t test at the {significance:g} level")
        chosen = f"; returned iteration {best + 1}'s settings ({why})"
    behind = _behind(m_steps, source)
    fitted_radius = (source.radius if source is not None else None) or {}
    em_params = params
    # Without a fit the given std comes back (EM's runs matched with 0 when one was to be fitted).
    params = _with_radius(params, fitted_radius or {"radius_noise": given_radius},
                          any("association_gate" in step.update for step in m_steps[:behind]))
    values.update(fitted_radius)
    if fitted_radius:
        chosen += (f"; trunk-radius std {_plain(params.radius_noise):.3g} m "
                   f"({interval_text(source.radius_relative_std)}) from "
                   f"{source.radius_used} radii")
    if _plain(params.association_gate) != _plain(em_params.association_gate):
        values["association_gate"] = _plain(params.association_gate)
        chosen += f"; gate {_plain(params.association_gate):.3g} at 3 dof with the radius"
    if any(_plain(getattr(params, name)) != _plain(getattr(em_params, name))
           for name in ("radius_noise", "association_gate")):
        known = None  # EM's runs matched without this radius or gate: the search runs x1
    found = None
    if scale_search and source is not None and (source.motion_fitted
                                                 or source.observation_fitted):
        params, found, note = _scale_search(config, key, params, controls, observations,
                                            start, scales, source, progress, known,
                                            workers=search_workers)
        values.update({name: _plain(getattr(params, name)) for name in
                       (MOTION_FIELDS if source.motion_fitted else ())
                       + (OBSERVATION_FIELDS + ("new_landmark_log_offset",)
                          if source.observation_fitted else ())})
        chosen += note
    elif scale_search:
        chosen += "; no noise-scale search (no noise group was fitted)"
    if not any(step.motion_fitted for step in m_steps[:behind]):
        params = params._replace(association_heading_std=given_heading_std)
        values.pop("association_heading_std", None)
    # The returned settings' typical stds over their own moves (the readings times their gains).
    odometry = np.asarray(control_to_odometry(controls, params, motion_model), np.float64)
    typical.append(typical_stds(params, odometry, z_range))
    # The radius warning speaks of the M-step behind the returned settings (else the last).
    warnings += _fit_warnings(last, steps, (source or last) if fit_radius else None,
                              given_radius)
    if converged:
        verdict = "converged"
    elif stalled:
        best_run = ("the best run before them: the highest log marginal likelihood among "
                    "the runs that kept every birth" if significance is None else
                    "the best run before them among the runs that kept every birth, by a "
                    f"one-sided t test of the log evidence at the {significance:g} level")
        verdict = (f"not converged: stopped after {done} iterations (none of the last "
                   f"{patience} runs beat {best_run})")
    else:
        verdict = (f"not converged after {done} iterations (the last moved a noise std or "
                   f"an odometry gain by more than {tol:.0%})")
    verdict += chosen
    if warnings:
        verdict += "; partly calibrated (see warnings)"
    unranked = _unranked_warning(objective, dropped, found, config.max_landmarks)
    if unranked:
        verdict += "; no likelihood ranked the settings (see warnings)"
    warnings += unranked
    relative_std, samples, bursts_fitted = _stated_errors(m_steps, source, steps)
    warnings += loose_interval_warnings(relative_std)
    return params, CalibrationInfo(done, np.asarray(objective), np.asarray(costs),
                                   np.asarray(typical), values, relative_std, samples,
                                   converged, verdict, tuple(warnings), found,
                                   np.asarray(dropped, np.int64), bursts_fitted,
                                   np.asarray(fill_steps, np.int64))
