"""Parametric bootstrap intervals for the calibrated noise: EM's bias and spread, measured.

``CalibrationInfo.relative_std`` states the sampling error of each noise group's residuals
(with the smoother's degrees of freedom). It leaves out what EM itself does to the
estimate: the association fixed by the filter, the smoother's shrinkage, the trust region.
On held-out simulated logs EM's heading std sat 0.79-0.86 of the truth on smooth loops,
outside that interval (docs/results.md, self_calibration). The parametric bootstrap
(Efron and Tibshirani, "An Introduction to the Bootstrap", 1993, chapters 6 and 10) measures
both bias and spread on logs drawn from the calibrated model itself:

  1. the log's own solution: filter it with the calibrated settings, take the best
     particle's history and smooth it with its association fixed (``smoothing.
     smooth_lineage`` with the M-step's variance rounds, as ``pipeline.offline_path``):
     start x_0, poses x_1..x_T after each step (observations z_t are taken at x_t),
     landmarks m_l, and the landmark l(t, k) of each associated observation;
  2. replicate b draws a log of the same design, at EM's own noise (the calibrated settings
     with the likelihood search's scales divided out: the estimate that is bootstrapped):
     each move u*_t around the smoothed move u(x_{t-1}, x_t) (written as the decomposition
     nearest the log's measured move, ``motion.nearest_decomposition``) by Eq. (1) of
     Geiser et al., "Practical Implementation of FastSLAM for Forestry Robot" (ICAROB
     2023) (``motion.sample_odometry``; the bursts only when the calibration fitted them, as
     the defensive ones are a proposal's tail, not a noise estimate), and each associated
     observation
     z*_tk = h(x_t, m_l(t,k)) + N(0, diag(sigma_r^2, sigma_b^2)) (``ekf.measurement_std``);
     observations the solution left unassociated and invalid rows stay as logged. The
     design (which landmark each step sees) is held fixed: a conditional bootstrap. The
     std of a draw is taken at the true move and range, as a simulator (and the world)
     makes it, while the calibration evaluates Eq. (1) at the measured ones: that
     difference is part of the bias the replicates measure;
  3. calibrate every replicate as the log was (same starting settings, key and options,
     without the likelihood's scale search, which does not change EM's estimate):
     theta*_b (B, 4), the typical std of each group (``total_typical_std``), against the
     typical std of the noise it was drawn with over its own moves and observations,
     tau_b (``replicate_truth``), so that the design's change from log to log is not read
     as bias;
  4. on the log scale, r_b = log(theta*_b / tau_b), bias = mean(r), s = std(r) (ddof 1); the
     interval for the truth is exp(log theta_hat - bias +- t s sqrt(1 + 1/B)) with t the
     Student quantile of B - 1 degrees of freedom: where the log's error log(theta_hat /
     theta) and the replicates' r_b share one normal law, it covers exactly its level
     (the bias estimate adds s^2 / B to the error's variance, the estimated s the Student
     quantile). Its limits need far fewer replicates than percentile limits: B = 20 gives s
     to about 1 / sqrt(2 (B - 1)) = 16 %.

The replicates are the cost: B calibrations (each several filter runs). The odometry motion
model only: the replicate moves are (rot1, trans, rot2) controls.

Shapes: T steps, K observations per step, L landmarks, B replicates.
"""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import scipy.stats

from jaxslam import ekf, lineage, smoothing
from jaxslam.calibration_residuals import NOISE_GROUPS, typical_stds
from jaxslam.filter import estimate, run_filter
from jaxslam.geometry import range_bearing, wrap_angle
from jaxslam.host import in_float64
from jaxslam.motion import (burst_variance_factor, control_to_odometry, nearest_decomposition,
                            odometry_from_poses, sample_odometry, with_gain)
from jaxslam.noise_scale import scaled_noise
from jaxslam.types import FilterConfig, Observations, Params, default_params

MIN_REPLICATES = 2  # a spread needs two; about 20 for the 16 % stated in the docstring
SMOOTHING_ERRORS = (RuntimeError, ValueError, np.linalg.LinAlgError)


class Solution(NamedTuple):
    """The log's smoothed solution a replicate is drawn around.

    path: (T, 3) poses after each step; start: (3,); landmark: (L, 2); landmark_of_obs:
    (T, K) int index into ``landmark`` (-1: not associated, left as logged); measured: (T, 3)
    the log's measured moves, whose decomposition the replicate moves take
    (``motion.nearest_decomposition``).
    """

    path: np.ndarray
    start: np.ndarray
    landmark: np.ndarray
    landmark_of_obs: np.ndarray
    measured: np.ndarray


class BootstrapIntervals(NamedTuple):
    """Bias-corrected bootstrap intervals of each noise group's typical std (module docstring).

    estimate: (4,) theta_hat, ``total_typical_std`` of the calibration (``NOISE_GROUPS``
    order); replicates: (B, 4) theta*_b (NaN where a replicate's calibration fitted
    nothing); replicate_truth: (B, 4) tau_b; bias: (4,) mean of log(theta*_b / tau_b);
    log_std: (4,) their std; lower / upper: (4,) the interval's limits for the true typical
    std over the log, (0, inf) for a group with a failed replicate or no estimate; level:
    its coverage; failed: (4,) int replicates that gave no estimate of the group.
    """

    estimate: np.ndarray
    replicates: np.ndarray
    replicate_truth: np.ndarray
    bias: np.ndarray
    log_std: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    level: float
    failed: np.ndarray


def burst_rms_factor(info) -> float:
    """sqrt(1 - eps + eps kappa^2) of the bursts a calibration fitted
    (``CalibrationInfo.bursts_fitted``; eps ``motion_outlier_probability``, kappa
    ``motion_outlier_scale`` from ``CalibrationInfo.values``), 1 when it fitted none."""
    if not info.bursts_fitted:
        return 1.0
    fitted = default_params(**{
        name: info.values[name] for name in ("motion_outlier_probability",
                                             "motion_outlier_scale")})
    return float(np.sqrt(burst_variance_factor(fitted)))


def total_typical_std(info) -> np.ndarray:
    """(4,) EM's typical std per group (``self_calibration.em_typical_std``), the motion
    groups times ``burst_rms_factor``: the std the whitened move residuals measure, and the
    one ``CalibrationInfo.relative_std`` describes."""
    from jaxslam.self_calibration import em_typical_std

    factor = burst_rms_factor(info)
    return em_typical_std(info) * np.array([factor, factor, 1.0, 1.0])


def log_solution(config: FilterConfig, key, params: Params, controls, observations:
                 Observations, initial_pose=None) -> Solution:
    """Step 1 of the module docstring: the smoothed best history of a filter run with
    ``params`` (controls (T, 3) of the odometry model)."""
    start = np.zeros(3) if initial_pose is None else np.asarray(initial_pose, np.float64)
    final, trace = run_filter(config, key, params, controls, observations,
                              jnp.asarray(start, jnp.float32), record_lineage=True)
    history = jax.tree.map(np.asarray, lineage.trace_lineage(
        trace.lineage, estimate(final).best_particle))
    measured = in_float64(control_to_odometry, controls, params, motion_model="odometry")
    try:
        smoothed = smoothing.smooth_lineage(start, history, measured,
                                            np.asarray(observations.z), params,
                                            calibrate_rounds=smoothing.VARIANCE_ROUNDS)
    except SMOOTHING_ERRORS as error:
        raise RuntimeError(f"bootstrap: smoothing the log with the calibrated settings "
                           f"failed ({error}); there is no solution to draw replicates "
                           f"around") from error
    return Solution(np.asarray(smoothed.path, np.float64), start,
                    np.asarray(smoothed.landmark, np.float64),
                    np.asarray(smoothed.landmark_of_obs), measured)


def replicate_log(key, solution: Solution, params: Params, observations: Observations,
                  bursts: bool):
    """Step 2: (controls (T, 3), ``Observations``) of one replicate log.

    Moves around u(x_{t-1}, x_t) by ``motion.sample_odometry`` (bursts off unless
    ``bursts``); associated observations redrawn around h(x_t, m) at ``ekf.
    measurement_std``; every other field and row as in ``observations``.
    """
    dtype = jnp.float64 if jax.config.jax_enable_x64 else jnp.float32
    key_motion, key_range, key_bearing = jax.random.split(key, 3)
    noise = params if bursts else params._replace(
        motion_outlier_probability=jnp.zeros_like(params.motion_outlier_probability))
    noise = jax.tree.map(lambda leaf: jnp.asarray(leaf, dtype), noise)
    poses = jnp.asarray(np.concatenate([solution.start[None], solution.path]), dtype)
    moves = nearest_decomposition(  # (T, 3), written as the log's measured moves are
        odometry_from_poses(poses[:-1], poses[1:], noise.min_translation),
        jnp.asarray(solution.measured, dtype))
    # The replicate's readings: its measured moves over the gains (``motion.with_gain``).
    controls = with_gain(sample_odometry(key_motion, moves, noise), 1.0 / noise.odometry_gain)
    ids = solution.landmark_of_obs
    points = jnp.asarray(solution.landmark[np.clip(ids, 0, None)] if len(solution.landmark)
                         else np.zeros(ids.shape + (2,)), dtype)  # (T, K, 2)
    predicted = range_bearing(jnp.asarray(solution.path, dtype)[:, None], points)  # (T, K, 2)
    sigma_range, sigma_bearing = ekf.measurement_std(predicted[..., 0], noise)
    drawn = jnp.stack([
        predicted[..., 0] + sigma_range * jax.random.normal(key_range, ids.shape, dtype),
        wrap_angle(predicted[..., 1]
                   + sigma_bearing * jax.random.normal(key_bearing, ids.shape, dtype))],
        axis=-1)
    associated = (ids >= 0) & np.asarray(observations.valid, bool)
    z = np.where(associated[..., None], np.asarray(drawn, np.float64),
                 np.asarray(observations.z, np.float64))
    return (np.asarray(controls, np.float64),
            observations._replace(z=jnp.asarray(z, jnp.asarray(observations.z).dtype)))


def replicate_truth(noise: Params, bursts: bool, controls, observations: Observations):
    """tau (4,): the typical std (``calibration_residuals.typical_stds``) of the noise a
    replicate was drawn with over its own moves (T, 3) and valid observations, the motion
    groups times the bursts' rms factor sqrt(1 - eps + eps kappa^2) when they were drawn
    (what ``total_typical_std`` estimates)."""
    z = np.asarray(observations.z, np.float64)
    valid = np.asarray(observations.valid, bool) & np.all(np.isfinite(z), axis=-1)
    measured = in_float64(control_to_odometry, controls, noise, motion_model="odometry")
    tau = np.asarray(typical_stds(noise, measured, z[valid][:, 0]))
    factor = float(np.sqrt(burst_variance_factor(noise))) if bursts else 1.0
    return tau * np.array([factor, factor, 1.0, 1.0])


def _check_level(level) -> float:
    if not 0.0 < float(level) < 1.0:
        raise ValueError(f"level must lie in (0, 1), the interval's coverage; got {level}")
    return float(level)


def intervals(estimate_std, replicates, truth, level: float = 0.95) -> BootstrapIntervals:
    """Step 4 of the module docstring from theta_hat (G,), theta* (B, G) and tau (B, G).

    A group whose estimate is not a positive finite number, or with a replicate that is
    not (its calibration fitted nothing: NaN), gets (0, inf): the bootstrap says nothing
    about it, and ``failed`` counts such replicates. ValueError for B < 2, shapes that do
    not match, or a level outside (0, 1).
    """
    estimate_std = np.asarray(estimate_std, np.float64)
    replicates = np.asarray(replicates, np.float64)
    truth = np.asarray(truth, np.float64)
    level = _check_level(level)
    if estimate_std.ndim != 1 or replicates.ndim != 2 or replicates.shape != truth.shape \
            or replicates.shape[1] != estimate_std.shape[0]:
        raise ValueError(f"intervals needs estimate (G,), replicates and truth (B, G); got "
                         f"{estimate_std.shape}, {replicates.shape}, {truth.shape}")
    count = replicates.shape[0]
    if count < MIN_REPLICATES:
        raise ValueError(f"bootstrap intervals need at least {MIN_REPLICATES} replicates; "
                         f"got {count}")
    positive = lambda x: np.isfinite(x) & (x > 0)
    failed = np.sum(~(positive(replicates) & positive(truth)), axis=0)
    usable = positive(estimate_std) & (failed == 0)
    ratio = np.log(np.where(usable, replicates, 1.0) / np.where(usable, truth, 1.0))
    bias = np.mean(ratio, axis=0)
    spread = np.std(ratio, axis=0, ddof=1)
    half = (scipy.stats.t.ppf(0.5 + level / 2.0, count - 1) * spread
            * np.sqrt(1.0 + 1.0 / count))
    centre = np.log(np.where(usable, estimate_std, 1.0)) - bias
    nan = np.full_like(bias, np.nan)
    return BootstrapIntervals(
        estimate_std, replicates, truth, np.where(usable, bias, nan),
        np.where(usable, spread, nan), np.where(usable, np.exp(centre - half), 0.0),
        np.where(usable, np.exp(centre + half), np.inf), level, failed)


def bootstrap_intervals(config: FilterConfig, key, controls, observations: Observations,
                        initial_pose, start_params: Params, calibrated: Params, info, *,
                        replicates: int = 20, level: float = 0.95, progress=None,
                        **calibrate_options) -> BootstrapIntervals:
    """The module docstring's intervals for a calibration of this log.

    Args:
      config, key, controls (T, 3), observations, initial_pose, start_params: what
        ``calibrate_params`` was given (its ``params`` argument: ``start_params``);
        ``calibrated``, ``info``: what it returned. ``calibrate_options``: the other options
        it was given (``scale_search`` is turned off for the replicates).
      replicates: B >= 2 (about 20 for the docstring's precision); level: coverage in (0, 1).
      progress: called with (b, B) after each replicate, or None.
    Raises:
      ValueError: a motion model other than ``"odometry"``; B not an int >= 2; a level
        outside (0, 1); a calibration that fitted nothing (``info.values`` empty: there is
        no estimate to bootstrap). RuntimeError: the log's solution could not be smoothed.
    """
    from jaxslam.self_calibration import calibrate_params, group_scales

    motion_model = calibrate_options.get("motion_model") or config.motion_model
    if motion_model != "odometry":
        raise ValueError(f"bootstrap_intervals draws (rot1, trans, rot2) moves: it needs the "
                         f"odometry motion model; got {motion_model!r}")
    if not isinstance(replicates, (int, np.integer)) or replicates < MIN_REPLICATES:
        raise ValueError(f"bootstrap_intervals needs an int replicates >= {MIN_REPLICATES}; "
                         f"got {replicates!r}")
    level = _check_level(level)
    if not info.values:
        raise ValueError("the calibration returned its starting settings (nothing fitted): "
                         "there is no estimate to bootstrap")
    solution = log_solution(config, key, calibrated, controls, observations, initial_pose)
    scales = group_scales(info)  # the likelihood search's, divided out: EM's own noise
    em_noise = scaled_noise(calibrated, 1.0 / scales[0], 1.0 / scales[2])
    bursts = bool(info.bursts_fitted)
    options = dict(calibrate_options, scale_search=False)
    draws, truths = [], []
    for b in range(replicates):
        replicate_controls, replicate_obs = replicate_log(
            jax.random.fold_in(key, 1_000_003 + b), solution, em_noise, observations, bursts)
        _, replicate_info = calibrate_params(config, key, replicate_controls, replicate_obs,
                                             initial_pose, start_params, **options)
        draws.append(total_typical_std(replicate_info) if replicate_info.values
                     else np.full(len(NOISE_GROUPS), np.nan))
        truths.append(replicate_truth(em_noise, bursts, replicate_controls, replicate_obs))
        if progress is not None:
            progress(b + 1, replicates)
    return intervals(total_typical_std(info), np.stack(draws), np.stack(truths), level)
