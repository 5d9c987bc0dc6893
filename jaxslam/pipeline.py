"""One pipeline for a robot log: calibrate, filter, smooth (optional), evaluate, warn.

``filter_log(log, config, params, key)`` is what ``jaxslam run --data`` and
``jaxslam calibrate`` call, and what a user importing jaxslam as a backend calls:

    0. optionally the controls rebuilt from the log's command stream with the commands late
       by a given lag or by the lag fitted from the log (``command_delay``:
       ``command_delay.log_at_command_delay``);
    1. observations and controls from the ``RobotLog`` (detected trunks: ``obs_z``);
    2. ``calibrate_params`` from the log alone, unless ``calibrate=False``;
    3. ``run_filter`` with the lineage recorded, so the best particle's data association is
       known (for the smoother and for the warnings);
    4. optionally ``smoothing.smooth_lineage`` of that particle's history, or with
       ``close_loops`` ``loop_closure.close_loops`` from it (loops the filter missed closed
       by registration, each closure tested by the smoother's cost rise), its noise groups
       weighed by their residuals' variance components (``offline_path``);
    5. metrics against the log's ground truth when it has any (truth only scores);
    6. ``run_warnings``: plain-word warnings about a run that went wrong.

``save_params`` / ``load_params`` store a ``Params`` as a TOML table of its fields, so a
calibration can be reused (``jaxslam run --data LOG --params FILE``).
"""
from __future__ import annotations

import pathlib
import tomllib
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxslam import lineage, metrics
from jaxslam.filter import Estimate, Trace, estimate, run_filter
from jaxslam.self_calibration import CalibrationInfo, calibrate_params
from jaxslam.types import FilterConfig, Params, default_params

UNMATCHED_WARNING = 0.5  # warn when more than this share of observations matched nothing
ESS_COLLAPSE = 0.05  # a step's ESS below this share of P counts as collapsed
ESS_WARNING = 0.25  # warn when more than this share of steps collapsed
# What calibration cannot fix when a tree's observations start new landmarks.
DRIFT_PAST_GATE = ("the pose drifts further than params.association_gate allows between "
                   "sightings of a tree, so its next sighting starts a new landmark (more "
                   "particles, filter.num_particles, may help)")
CHURN_WARNING = 3.0  # warn when more than this many landmarks were started per one kept
PLAIN_SQUARES = 1e6  # Huber threshold [whitened units] beyond any residual: least squares


class LogRun(NamedTuple):
    """The result of ``filter_log``.

    Attributes:
      params: the ``Params`` the filter ran with (calibrated unless told not to).
      calibration: ``CalibrationInfo``, or None when not calibrated.
      estimate: final ``Estimate`` (the best particle's map).
      trace: the filter's ``Trace`` (lineage included).
      mean_pose: (T, 3) the weighted mean pose after each step.
      smoothed_pose: (T, 3) the smoothed path, or None.
      metrics: dict of floats (truth-based ones only when the log has truth).
      warnings: tuple of plain-word warnings (``run_warnings``).
      delay_fit: the ``command_delay.DelayFit`` of ``command_delay="auto"``, else None.
    """

    params: Params
    calibration: CalibrationInfo | None
    estimate: Estimate
    trace: Trace
    mean_pose: np.ndarray
    smoothed_pose: np.ndarray | None
    metrics: dict
    warnings: tuple
    delay_fit: object = None


def run_warnings(trace: Trace, valid, unmatched_share: float, num_particles: int,
                 births: int = 0, false_alarm_probability: float = 0.0,
                 calibrated: bool = False) -> list[str]:
    """Plain-word warnings about a finished run (each names the number behind it).

    Churn: a false alarm starts a landmark that is never seen again and is deleted, so a run
    whose sensor model expects a share p_f of the N valid observations to be clutter starts
    about p_f N such landmarks by design. The warning counts the landmarks started beyond
    those, births - p_f N, against ``CHURN_WARNING`` times the landmarks kept.

    Args:
      trace: the run's ``Trace``. valid: (T, K) the log's valid observations.
      unmatched_share: share of valid observations the best particle matched to no existing
        landmark (they started landmarks or were set aside).
      num_particles: P.
      births: landmarks the best particle's history started (``history_counts``).
      false_alarm_probability: the run's ``Params.false_alarm_probability``, calibrated or
        as given (0: every landmark started counts as churn). Uncalibrated, the library
        default 0.05 forgives one start per 20 valid observations, so on a log with many
        observations a map's churn must be larger before this warns.
      calibrated: the run's sensor noise was calibrated (``sensor_noise_calibrated``, or a
        saved calibration reused). The unmatched and churn warnings then name the likely
        causes calibration does not fix (the pose drifting past the gate between sightings
        of a tree; a detector that misses a tree in view for longer than its detection
        probability allows) instead of advising to calibrate.
    """
    valid = np.asarray(valid)
    out = []
    total = int(valid.sum())
    invalid = int(np.sum(np.asarray(trace.num_invalid_obs)))
    if invalid:
        out.append(f"{invalid} observations were masked as invalid (NaN, negative "
                   "range, bearing outside [-pi, pi]); check the log's units (ranges in metres, "
                   "bearings in radians)")
    if total == 0:
        out.append("the log has no valid observation: the result is dead reckoning")
    elif unmatched_share > UNMATCHED_WARNING:
        out.append(f"{unmatched_share:.0%} of the observations matched no landmark"
                   + (f" although the sensor noise was calibrated. Likely cause: "
                      f"{DRIFT_PAST_GATE}" if calibrated else
                      ": the sensor noise or the gate is probably too tight for this log "
                      "(calibrate, or raise range_noise / bearing_noise / association_gate)"))
    drift_said = calibrated and total > 0 and unmatched_share > UNMATCHED_WARNING
    dropped = int(np.sum(np.asarray(trace.num_dropped_births)))
    if dropped:
        out.append(f"the map slots were full: {dropped} landmark births were dropped "
                   "(summed over particles); raise filter.max_landmarks")
    collapsed = np.asarray(trace.ess) < max(1.5, ESS_COLLAPSE * num_particles)
    if collapsed.mean() > ESS_WARNING:
        out.append(f"the effective sample size collapsed (below {ESS_COLLAPSE:.0%} of the "
                   f"particles) in {collapsed.mean():.0%} of the steps; the motion noise is "
                   "probably too small, or use more particles or the mixture proposal")
    cut = None if trace.window_cut is None else np.asarray(trace.window_cut)
    if cut is not None and cut.any():
        out.append(f"the association window left out landmarks that could have taken part in "
                   f"the association (matched or penalised) in {int(np.sum(cut > 0))} steps "
                   f"(up to {int(cut.max())} in one step); "
                   "raise filter.association_window above the landmarks in view, or set it "
                   "to 0")
    resets = int(np.sum(np.asarray(trace.weights_reset)))
    if resets:
        out.append(f"every particle's weight was zero in {resets} steps (weights reset)")
    kept = int(np.asarray(trace.num_landmarks)[-1])
    if total and kept == 0:
        out.append("the final map is empty although the log has observations")
    else:
        clutter = int(round(false_alarm_probability * total))
        if births - clutter > CHURN_WARNING * max(kept, 1):
            expected = (f", about {clutter} of them expected as false alarms at "
                        f"false_alarm_probability {false_alarm_probability:.3g}"
                        if clutter else "")
            drift = "the drift named above" if drift_said else DRIFT_PAST_GATE
            why = (f" although the sensor noise was calibrated. Likely causes: {drift}; or "
                   "the detector misses a tree in view for longer than "
                   "params.detection_probability allows, so its landmark is deleted (for "
                   "static landmarks raise params.existence_max, which also keeps the "
                   "duplicates that drift starts)" if calibrated else
                   ": observations of one tree are not being matched to it, so the sensor "
                   "noise or the gate is probably too tight (calibrate)")
            out.append(f"landmarks were started and deleted over and over ({births} started"
                       f"{expected}; {kept} kept){why}")
    return out


def sensor_noise_calibrated(calibration: CalibrationInfo | None) -> bool:
    """Whether ``calibration`` fitted the sensor noise behind the settings it returned (a
    range or bearing group in ``CalibrationInfo.samples``; False for None, or when it gave
    back its starting settings)."""
    return calibration is not None and any(group in calibration.samples
                                           for group in ("range", "bearing"))


def unused_radius_hint(history: lineage.LineagePath, obs, params: Params) -> tuple[list, dict]:
    """When the log's valid observations carry measured trunk radii (> 0) but
    ``params.radius_noise`` is 0, the radii take no part in the filter: one warning that says
    so, with the within-tree scatter of those radii along the best particle's ``history``
    (``noise_fit.radius_noise_from_history``: the std that covers 95 % of it) as a value to
    try, and {"radius_scatter": that std} for the run's values. ([], {}) otherwise, or when
    no landmark was seen often enough to measure the scatter."""
    from jaxslam.noise_fit import measured_radii, radius_noise_from_history

    measured = measured_radii(obs.radius, obs.valid)
    if float(np.asarray(params.radius_noise)) > 0.0 or not measured.any():
        return [], {}
    ids, _ = lineage.landmark_identities(history.match, history.birth_slot)
    std, used = radius_noise_from_history(np.asarray(ids), obs.radius, obs.valid)
    if not np.isfinite(std) or std <= 0.0:
        return [], {}
    return [f"{int(measured.sum())} observations carry a trunk radius, but the radius takes no "
            f"part in the filter while params.radius_noise is 0; the scatter of one tree's "
            f"radii along this run ({used} observations) is {std:.3g} m: try --set "
            f"params.radius_noise={std:.3g} with params.association_gate at least 16.27 (a "
            f"3-dof gate; docs/log_format.md)"], {"radius_scatter": std}


def history_counts(history: lineage.LineagePath, valid) -> tuple[float, int]:
    """(share of valid observations matched to no landmark, landmarks started) along one
    particle's history (``lineage.trace_lineage``); valid: (T, K)."""
    valid = np.asarray(valid)
    births = int(np.sum((np.asarray(history.birth_slot) >= 0) & valid))
    if not valid.any():
        return 0.0, births
    return float(np.mean(np.asarray(history.match)[valid] < 0)), births


def _truth_metrics(log, mean_pose, smoothed, est, map_match_threshold: float) -> dict:
    values = {}
    if log.truth_pose is not None:
        truth = np.asarray(log.truth_pose)
        values["final_pose_error"] = float(np.hypot(*(mean_pose[-1, :2] - truth[-1, :2])))
        values["ate_rmse"] = float(metrics.ate_rmse(mean_pose, truth))
        values["ate_rmse_aligned"] = float(metrics.ate_rmse(mean_pose, truth, align=True))
        if smoothed is not None:
            values["smoothed_ate_rmse"] = float(metrics.ate_rmse(smoothed, truth))
            values["smoothed_ate_rmse_aligned"] = float(metrics.ate_rmse(smoothed, truth,
                                                                         align=True))
    if log.truth_landmarks is not None and len(log.truth_landmarks):
        trees = np.asarray(log.truth_landmarks)
        scores = metrics.map_metrics(est.landmark_mean, est.active, trees,
                                     np.ones(len(trees), bool), map_match_threshold)
        values.update({name: float(value) for name, value in scores._asdict().items()})
    return values


def log_inputs(log, config: FilterConfig):
    """What ``run_filter`` and ``calibrate_params`` take from a ``RobotLog``: (``config`` with
    the log's observation width K and motion model, controls (T, 3) float32,
    ``Observations`` (T, K, ...), start pose (3,), the origin when the log has none)."""
    import dataclasses

    obs = log.observations()
    config = dataclasses.replace(config, max_obs=int(obs.z.shape[1]),
                                 motion_model=log.motion_model)
    controls = jnp.asarray(np.asarray(log.controls), jnp.float32)
    start = np.zeros(3) if log.initial_pose is None else np.asarray(log.initial_pose)
    return config, controls, obs, start


def filter_log(log, config: FilterConfig, params: Params | None = None, key=None, *,
               calibrate: bool = True, smooth: bool = False, visit_gap: int | None = None,
               close_loops: bool = False, smooth_rounds: int | None = None,
               map_match_threshold: float = 1.0,
               calibration_options: dict | None = None,
               command_delay: float | str | None = None,
               settings_calibrated: bool | None = None,
               progress: Callable[[str], None] | None = None) -> LogRun:
    """Calibrate (by default), filter and evaluate one ``RobotLog`` (module docstring).

    Args:
      log: a ``RobotLog`` with detected observations (``obs_z``).
      config: the ``FilterConfig``; ``max_obs`` and ``motion_model`` are taken from the log.
      params: the settings to run with (``calibrate=False``) or to start the calibration from
        (default ``starting_params``); with ``calibrate=False`` and None, ``default_params``.
      key: PRNG key (default ``PRNGKey(0)``), used by the calibration and the final run.
      calibrate: estimate the settings from the log first (``calibrate_params``).
      smooth / visit_gap: smooth the best particle's history (``smoothing.smooth_lineage``).
      close_loops: with ``smooth``, close the loops the filter missed before the final solve
        (``loop_closure.close_loops``, plain squares; the final solve of the closed
        association uses the smoother's default robust loss; not with ``visit_gap``);
        metrics gain ``loop_closures`` and ``landmarks_joined`` (landmarks removed).
      smooth_rounds: with ``smooth``, the smoother's rounds of variance components
        (``offline_path``'s ``calibrate_rounds``; None: ``smoothing.VARIANCE_ROUNDS``; 0
        smooths with the Params' noise as it is).
      map_match_threshold: [m] landmark-to-tree distance of a match in the map metrics.
      calibration_options: keyword arguments for ``calibrate_params``.
      command_delay: None (default): the log's controls as they are. A number [s] or "auto":
        the moves rebuilt from the log's command stream (``RobotLog.at_command_delay``) with
        the commands that much late, or at the lag ``fit_log_command_delay`` fits from the
        log (key ``key``, from ``params`` when given, else the calibration's start, also
        with ``calibrate=False``, where the run itself then uses ``default_params``);
        ``LogRun.delay_fit`` holds that fit and the metrics gain ``command_delay`` [s].
      settings_calibrated: whether the sensor noise the run uses was calibrated, for the
        warnings' advice (``run_warnings``' ``calibrated``): True for reused settings whose
        calibration fitted it (``saved_sensor_calibration``); None (default): whether this
        call's calibration fitted it (``sensor_noise_calibrated``).
      progress: optional callable(str) told of each stage.
    """
    check_offline_options(smooth, visit_gap, close_loops, smooth_rounds)
    key = jax.random.PRNGKey(0) if key is None else key
    delay_fit = None
    if command_delay is not None:
        from jaxslam.command_delay import log_at_command_delay

        log, delay_fit = log_at_command_delay(log, config, key, command_delay, params,
                                              progress)
    config, controls, obs, start = log_inputs(log, config)
    from jaxslam.validation import observation_units_warnings  # units guard (issue 18)
    units = observation_units_warnings(np.asarray(obs.z), np.asarray(obs.valid), max_range=(
        None if calibrate or params is None else float(np.max(np.asarray(params.max_range)))))
    calibration = None
    if calibrate:
        params, calibration = calibrate_params(config, key, controls, obs, start, params,
                                               progress=progress,
                                               **(calibration_options or {}))
    elif params is None:
        params = default_params(config)
    final, trace = run_filter(config, key, params, controls, obs,
                              jnp.asarray(start, jnp.float32), record_lineage=True)
    est = estimate(final)
    mean_pose = np.asarray(trace.mean_pose, np.float64)
    smoothed, closed = None, {}
    history = lineage.trace_lineage(trace.lineage, est.best_particle)  # traced once
    if smooth:
        smoothed, closed = offline_path(history, controls, obs, start, params,
                                        log.motion_model, visit_gap, close_loops,
                                        smooth_rounds)
    valid = np.asarray(obs.valid)
    share, births = history_counts(history, valid)
    values = {"steps": log.num_steps, "num_landmarks": int(np.sum(np.asarray(est.active))),
              "valid_observations": int(valid.sum()),
              "invalid_observations": int(np.sum(np.asarray(trace.num_invalid_obs))),
              "unmatched_share": share, "landmarks_started": births,
              "dropped_births": int(np.sum(np.asarray(trace.num_dropped_births))), **closed}
    values.update(_truth_metrics(log, mean_pose, smoothed, est, map_match_threshold))
    warnings = run_warnings(trace, valid, share, config.num_particles, births,
                            float(params.false_alarm_probability),
                            calibrated=(sensor_noise_calibrated(calibration)
                                        if settings_calibrated is None
                                        else settings_calibrated))
    hint, scatter = unused_radius_hint(history, obs, params)
    warnings += hint
    values.update(scatter)
    if calibration is not None:
        warnings = list(calibration.warnings) + warnings
    warnings = units + list(warnings)
    if command_delay is not None:
        values["command_delay"] = (delay_fit.delay if delay_fit is not None
                                   else float(command_delay))
    return LogRun(params, calibration, est, trace, mean_pose, smoothed, values, tuple(warnings),
                  delay_fit)


def check_offline_options(smooth: bool, visit_gap: int | None, close_loops: bool,
                          smooth_rounds: int | None = None,
                          rounds_name: str = "smooth_rounds") -> None:
    """Raise ValueError for ``close_loops`` without ``smooth`` or together with ``visit_gap``
    (visits are the smoother's own soft loop closures), or for ``smooth_rounds`` that is not
    None or a non-negative int (named ``rounds_name`` in the message), before any filter
    runs."""
    if smooth_rounds is not None and (isinstance(smooth_rounds, bool) or not isinstance(
            smooth_rounds, (int, np.integer)) or smooth_rounds < 0):
        raise ValueError(f"{rounds_name} must be None (the default, "
                         f"smoothing.VARIANCE_ROUNDS) or an int >= 0 (rounds of variance "
                         f"components in the smoother); got {smooth_rounds!r}")
    if close_loops and (not smooth or visit_gap is not None):
        raise ValueError("close_loops needs smooth=True and no visit_gap (visits are the "
                         "smoother's own soft loop closures; choose one)")


def offline_path(history, controls, obs, start, params: Params, motion_model: str,
                 visit_gap: int | None = None, close_loops: bool = False,
                 calibrate_rounds: int | None = None):
    """The smoothed path (T, 3) of the best particle's ``history`` (``LineagePath``) and,
    with ``close_loops``, the closure counts {loop_closures, landmarks_joined} (else {}):
    ``filter_log``'s step 4, for callers that ran the filter themselves.

    The smoother weighs its four noise groups (heading, translation, range, bearing) by the
    variance components of its own residuals, ``calibrate_rounds`` rounds (``smooth_path``;
    None: ``smoothing.VARIANCE_ROUNDS``, the calibration's M-step's count; 0 uses ``params``'
    noise as it is). ``params`` carry the noise the particle filter ran with, which is not the
    noise the log shows: the calibration's likelihood search multiplies EM's estimate for the
    filter's sake (``noise_scale``; observation x8 on Victoria Park), and a hand-set noise is
    usually widened for the same reason. Weighed with it, the least squares trusts the
    odometry too much or too little. On Victoria Park keys 0-3 the rounds took the smoothed
    RMSE from 2.8-3.2 m to 1.6-2.7 m (docs/results.md, victoria_park; in-sample for the
    count of rounds, which is the M-step's, kept over the fixed point after seeing two keys
    at both). ``calibrate_rounds`` must be None or an int >= 0. The loop-closure test
    (``close_loops``) keeps ``params`` as they are: its limit was measured so."""
    from jaxslam import loop_closure, smoothing
    from jaxslam.motion import control_to_odometry

    check_offline_options(True, visit_gap, close_loops, calibrate_rounds, "calibrate_rounds")
    history = jax.tree.map(np.asarray, history)
    odometry = np.asarray(control_to_odometry(controls, params, motion_model), np.float64)
    start = np.asarray(start, np.float64)
    rounds = smoothing.VARIANCE_ROUNDS if calibrate_rounds is None else calibrate_rounds
    if not close_loops:
        return smoothing.smooth_lineage(start, history, odometry, np.asarray(obs.z), params,
                                        visit_gap=visit_gap, calibrate_rounds=rounds).path, {}
    valid = np.asarray(obs.valid, bool)
    ids, _ = lineage.landmark_identities(history.match, history.birth_slot)
    ids = np.where(valid, np.asarray(ids), -1)
    z = np.where(valid[..., None], np.asarray(obs.z, np.float64), 0.0)

    def solve(path, landmark_of_obs, iterations: int = 100):
        # Plain squares and a tight tolerance: the closure test compares converged costs,
        # and its limit was measured with plain squares (loop_closure.close_loops).
        return smoothing.smooth_path(start, path, odometry, z, landmark_of_obs, params,
                                     iterations=iterations, huber=PLAIN_SQUARES, tol=1e-8)

    closed = loop_closure.close_loops(solve, history.pose, ids)
    # The reported path: the closed association solved with the smoother's robust default,
    # its noise groups weighed by the rounds.
    final = smoothing.smooth_path(start, closed.smoothed.path, odometry, z,
                                  closed.smoothed.landmark_of_obs, params,
                                  calibrate_rounds=rounds)
    return final.path, {"loop_closures": len(closed.closures),
                        "landmarks_joined": closed.landmarks_joined}


def params_to_dict(params: Params) -> dict:
    """``Params`` as {field: float or list of floats} (inf kept; TOML writes it as inf)."""
    out = {}
    for name, value in params._asdict().items():
        array = np.asarray(value, np.float64)
        out[name] = float(array) if array.ndim == 0 else [float(v) for v in array]
    return out


def save_params(path, params: Params, comment: str | None = None,
                sensor_noise_calibrated: bool | None = None) -> pathlib.Path:
    """Write ``params`` as a TOML table ``[params]`` (``load_params`` reads it back), and
    with ``sensor_noise_calibrated`` given a table ``[calibration]`` saying whether a fit
    of the sensor noise lies behind them (``saved_sensor_calibration`` reads it)."""
    import tomli_w

    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tables = {"params": params_to_dict(params)}
    if sensor_noise_calibrated is not None:
        tables["calibration"] = {"sensor_noise": bool(sensor_noise_calibrated)}
    text = tomli_w.dumps(tables)
    header = "".join(f"# {line}\n" for line in (comment or "").splitlines())
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(header + text)
    tmp.replace(path)
    return path


def saved_sensor_calibration(path) -> bool:
    """Whether the params file at ``path`` says a sensor-noise fit lies behind it (the
    ``[calibration]`` table ``save_params`` writes for a calibration); False for a file
    without one (written by hand, or before the table existed) or that cannot be read."""
    try:
        data = tomllib.loads(pathlib.Path(path).read_text())
    except (OSError, tomllib.TOMLDecodeError):
        return False
    table = data.get("calibration")
    return isinstance(table, dict) and table.get("sensor_noise") is True


def load_params(path, config: FilterConfig | None = None) -> Params:
    """``Params`` from a TOML file of ``save_params`` (or any ``[params]`` table of fields).

    Fields left out take ``default_params``; unknown fields are an error naming them.
    """
    path = pathlib.Path(path)
    try:
        data = tomllib.loads(path.read_text())
    except (OSError, tomllib.TOMLDecodeError) as error:
        raise ValueError(f"{path}: cannot read a params TOML file ({error}); expected a "
                         "[params] table as written by `jaxslam calibrate --out`") from error
    table = data.get("params")
    if not isinstance(table, dict):
        raise ValueError(f"{path}: no [params] table; expected one as written by "
                         "`jaxslam calibrate --out`")
    return default_params(config, **table)
