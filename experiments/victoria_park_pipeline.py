"""Victoria Park FastSLAM runner: trunk detection, steering-bias calibration, settings sets,
filter / smoother runs and their GPS scores (the loader is ``jaxslam.datasets.victoria_park``).

Pipeline (one filter step per laser scan, T = 7230 for the whole run):
  1. ``detect_scans``: ``jaxslam.detect.detect_trunks`` on every raw scan at once (``jax.vmap``
     over the (T, B) ranges) -> ``Observations`` with (T, K) leaves, with the classic
     detector's limits from the dataset README (``CLASSIC_DETECTOR``) and the body mask
     (``BODY_RANGE``).
  2. ``victoria_park_controls``: (rot1, trans, rot2) moves integrated from the 40 Hz Ackermann
     dead reckoning between laser times (the pose is the laser's), the steering angle
     corrected by a bias b fitted to the scan-to-scan turns of the laser alone
     (``steering_bias_from_scans``: one constant; ``steering_bias_profile``: fits in windows).
     ``steering_bias_from_gps`` fits the same bias to the GPS course (a comparison only).
  3. Settings: a named set of ``experiments/configs/victoria_park.toml`` (``load_settings``):
     "calibrated" (every field from the documentation, the library default, or estimated
     from the log by ``calibrate_victoria_park``: ``jaxslam.pipeline.filter_log`` with
     ``calibrate=True`` on the log as a ``RobotLog``, the trunk-radius std included)
     or "legacy" (the earlier set chosen by GPS score, in-sample).
  4. ``run_victoria_park``: one compiled ``run_filter`` call; the weighted-mean path is scored
     against GPS by ``victoria_park.gps_error`` (outliers removed by ``filter_gps``, a rigid
     SE(2) fit, RMSE at the GPS times); the map is the best particle's. With ``smooth=True``
     the filter also records its lineage and the best particle's history is re-solved by
     ``smoothing.smooth_lineage`` (associations fixed) and scored the same way.
  5. ``run_victoria_park_batch``: R independent runs (keys ``fold_in(key, r)``) in one call
     (``jax.vmap`` over keys; with ``smooth=True``, ``chunk`` runs at a time).

GPS is used only to score (and by ``steering_bias_from_gps``, a comparison). Compile and run
times are measured apart (``block_until_ready`` after each).
"""
from __future__ import annotations

import functools
import pathlib
import sys
import time
import tomllib
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

# Run this checkout's jaxslam, also when an editable install points at another checkout
# (an experiment started from a git worktree of an older commit).
sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

from jaxslam import lineage, smoothing
from jaxslam.host import in_float64
from jaxslam.motion import control_to_odometry
from jaxslam.datasets.odometry import VICTORIA_PARK_VEHICLE, body_rates, integrate_controls
from jaxslam.datasets.victoria_park import (
    VP_MIN_TRANSLATION,
    VictoriaPark,
    filter_gps,
    gps_error,
    rigid_transform_2d,
    victoria_park_log,
)
from jaxslam.detect import detect_trunks
from jaxslam.filter import estimate, run_filter
from jaxslam.metrics import align_se2
from jaxslam.pipeline import check_offline_options, offline_path
from jaxslam.types import FilterConfig, Observations, Params, default_params

# The classic detector's figures (dataset README, "Known figures"): beams under 75 m, segments
# split at range jumps over 1.5 m, occluded and over-1-m-wide segments rejected, at most 18
# trunks a scan.
CLASSIC_DETECTOR = dict(max_range=75.0, range_jump=1.5, max_width=1.0)
CLASSIC_MAX_TRUNKS = 18
# Beams nearer than 1.5 m hit the vehicle itself (beams 0-11 of every scan read about 0.83 m).
BODY_RANGE = 1.5

# Ground strikes: when the vehicle pitches, the laser hits the grass at a nearly constant
# range (~25 m) over tens of degrees with a dropout every 2-4 beams (e.g. scans 4715-4730);
# split at every dropout, each piece passes as a trunk. Bridging up to 2 missing beams where
# the ranges agree within 0.3 m keeps such an arc one wide segment (rejected by the 1 m width
# limit); trunks beside a dropout and a neighbour at another range stay apart. Chosen from
# the scans (``test_ground_strike_is_not_a_row_of_trunks``); it removes 928 of 30,266
# detections.
GROUND_STRIKE_BRIDGING = dict(max_missing_beams=2, bridge_range_jump=0.3)

DETECTOR_DEFAULTS = dict(
    method="centroid", min_range=BODY_RANGE, min_points=3, min_width=0.04, max_radius=0.6,
    max_residual=0.1, **CLASSIC_DETECTOR, **GROUND_STRIKE_BRIDGING)

# Steering bias [rad] added to aa3_dr.mat's steering, from the laser alone:
# ``steering_bias_from_scans(data, detect_scans(...))`` = 0.0041 +- 0.0003 over the whole log.
STEERING_BIAS = 0.0041

SETTINGS_FILE = pathlib.Path(__file__).resolve().parent / "configs" / "victoria_park.toml"
SOURCES = ("documentation", "calibrated", "library default", "GPS-tuned (legacy)")
SETTINGS_SECTIONS = ("run", "filter", "params", "smoother")
LEGACY = "legacy"
CALIBRATED = "calibrated"


class Settings(NamedTuple):
    """One named settings set of ``SETTINGS_FILE``.

    Attributes:
      name / description: the TOML table's name and its one-line description.
      calibrate: whether the Params fields tagged "calibrated" are estimated from the log.
      run / filter / params / smoother: {field: value} of the entries that carry a value
        (run: steering_bias "constant" or "profile", bias_window; filter: FilterConfig
        fields; params: Params fields; smoother: ``smoothing.smooth_path`` keywords).
      sources: {"section.field": source tag} of every entry (``SOURCES``).
      calibrated: Params fields left to the calibration.
    """

    name: str
    description: str
    calibrate: bool
    run: dict
    filter: dict
    params: dict
    smoother: dict
    sources: dict
    calibrated: tuple


def parse_settings(table: dict, name: str) -> Settings:
    """A ``Settings`` from one TOML table {section: {field: {value, source, note}}}.

    Raises ValueError naming the entry for an unknown source tag, a missing value on an entry
    that is not "calibrated", or an unknown section or key.
    """
    unknown = set(table) - set(SETTINGS_SECTIONS) - {"description", "calibrate"}
    if unknown:
        raise ValueError(f"settings {name!r}: unknown section(s) {sorted(unknown)}; expected "
                         f"{list(SETTINGS_SECTIONS)}, description, calibrate")
    values, sources, calibrated = {}, {}, []
    for section in SETTINGS_SECTIONS:
        values[section] = {}
        for field, entry in table.get(section, {}).items():
            where = f"settings {name!r}, {section}.{field}"
            if not isinstance(entry, dict) or "source" not in entry:
                raise ValueError(f"{where}: expected a table {{value = ..., source = ...}}")
            extra = set(entry) - {"value", "source", "note"}
            if extra:
                raise ValueError(f"{where}: unknown key(s) {sorted(extra)}")
            if entry["source"] not in SOURCES:
                raise ValueError(f"{where}: source {entry['source']!r}; expected one of "
                                 f"{list(SOURCES)}")
            sources[f"{section}.{field}"] = entry["source"]
            if "value" in entry:
                value = entry["value"]
                values[section][field] = tuple(value) if isinstance(value, list) else value
            elif entry["source"] == "calibrated" and section == "params":
                calibrated.append(field)
            else:
                raise ValueError(f"{where}: no value (only calibrated Params may leave it out)")
    return Settings(name=name, description=str(table.get("description", name)),
                    calibrate=bool(table.get("calibrate", False)), run=values["run"],
                    filter=values["filter"], params=values["params"],
                    smoother=values["smoother"], sources=sources, calibrated=tuple(calibrated))


def load_settings(name: str = CALIBRATED, path=SETTINGS_FILE) -> Settings:
    """The settings set ``name`` ("calibrated" or "legacy") of the TOML file ``path``."""
    with open(path, "rb") as handle:
        tables = tomllib.load(handle)
    if name not in tables:
        raise ValueError(f"{path}: no settings set {name!r}; expected one of {sorted(tables)}")
    return parse_settings(tables[name], name)


def settings_config(settings: Settings, **fields) -> FilterConfig:
    """``FilterConfig`` of the set's filter fields, then ``fields`` (overrides)."""
    return FilterConfig(**{**settings.filter, **fields})


def settings_params(settings: Settings, config: FilterConfig | None = None,
                    dtype=jnp.float32, **overrides) -> Params:
    """``Params`` of the set's fixed values, then ``overrides``.

    A set with ``calibrate`` gives the calibration's starting point,
    ``self_calibration.starting_params`` with its fixed values (the fields tagged
    "calibrated" are then estimated by ``calibrate_victoria_park``); otherwise
    ``default_params`` with its values.
    """
    values = {**settings.params, **overrides}
    if settings.calibrate:
        from jaxslam.self_calibration import starting_params

        return starting_params(config, dtype=dtype, **values)
    return default_params(config, dtype=dtype, **values)


def victoria_park_controls(data: VictoriaPark, steering_bias=STEERING_BIAS,
                           speed_scale: float = 1.0) -> np.ndarray:
    """(S, 3) odometry moves between laser times, steering corrected by ``steering_bias``
    [rad]: a number, or a (D,) array over the dead-reckoning samples
    (``steering_bias_profile``).

    The Ackermann dead reckoning (v * speed_scale, alpha + steering_bias) is integrated by
    ``log_format.integrate_controls`` exactly as ``victoria_park.dead_reckoning_controls``
    (which is this with bias 0 and scale 1).

    Moves are split into (rot1, trans, rot2) with the loader's 1 mm pure-turn threshold
    (``victoria_park.VP_MIN_TRANSLATION``): these moves are integrated dead reckoning, not
    jittering poses.
    """
    steering_bias = np.asarray(steering_bias, np.float64)
    if steering_bias.ndim and steering_bias.shape != data.dr_steering.shape:
        raise ValueError(f"steering_bias has shape {steering_bias.shape}; expected a number or "
                         f"one value per dead-reckoning sample {data.dr_steering.shape}")
    inputs = np.stack([data.dr_speed * speed_scale, data.dr_steering + steering_bias], -1)
    return integrate_controls(data.dr_time, inputs, data.laser_time, "ackermann",
                              VICTORIA_PARK_VEHICLE, min_translation=VP_MIN_TRANSLATION)


def steering_bias_from_gps(data: VictoriaPark, until: float | None = None,
                           window: float = 3.0, min_speed: float = 2.0) -> float:
    """Steering bias [rad] that makes the dead-reckoned heading follow the GPS course.

    Course c_i = atan2 of the displacement between filtered GPS fixes ``window`` seconds
    apart (kept when faster than ``min_speed`` m/s). The offset c_i - heading(t_i; bias)
    (unwrapped) has a slope in time that is linear in a small bias; the two slopes at bias
    0 and 0.01 give the bias of zero slope. ``until``: use fixes up to this time [s] only.
    """
    keep = filter_gps(data.gps_time, data.gps_xy)
    times, xy = data.gps_time[keep], data.gps_xy[keep]
    later = np.searchsorted(times, times + window)
    ok = later < times.size
    first, later = np.flatnonzero(ok), later[ok]
    span = times[later] - times[first]
    shift = xy[later] - xy[first]
    use = ((np.linalg.norm(shift, axis=-1) > min_speed * span) & (span < window + 0.5)
           & (times[later] <= (np.inf if until is None else until)))
    if use.sum() < 10:
        raise ValueError(f"steering_bias_from_gps: only {int(use.sum())} GPS course samples "
                         f"before until={until}; expected at least 10 (drive longer)")
    course = np.arctan2(shift[use, 1], shift[use, 0])
    middle = 0.5 * (times[first][use] + times[later][use])

    def slope(bias):
        _, yaw_rate = body_rates(np.stack([data.dr_speed, data.dr_steering + bias], -1),
                                 "ackermann", VICTORIA_PARK_VEHICLE)
        heading = np.concatenate([[0.0], np.cumsum(np.diff(data.dr_time) * yaw_rate[:-1])])
        offset = np.unwrap(np.angle(np.exp(1j * (course - np.interp(middle, data.dr_time,
                                                                     heading)))))
        return np.polyfit(middle, offset, 1)[0]

    slope_0, slope_1 = slope(0.0), slope(0.01)
    return float(-slope_0 * 0.01 / (slope_1 - slope_0))


def scan_rotations(observations: Observations, match_radius: float = 1.5,
                   max_residual: float = 0.3, min_pairs: int = 3) -> np.ndarray:
    """(T - 1,) heading change [rad] between consecutive scans from their trunk detections.

    Detections of scans t and t+1 (sensor-frame points p_i, q_j) are paired by mutual nearest
    neighbour within ``match_radius`` [m]; the 2-D rigid fit q = R(-d) p + c (closed-form
    Kabsch) gives the vehicle's turn d. NaN where fewer than ``min_pairs`` pairs are found or
    the RMS residual of the fit exceeds ``max_residual`` [m] (a wrong pairing). Host NumPy: a
    calibration tool, about 1 s for the whole log.
    """
    valid = np.asarray(observations.valid, bool)
    z = np.asarray(observations.z, np.float64)
    points = np.stack([z[..., 0] * np.cos(z[..., 1]), z[..., 0] * np.sin(z[..., 1])], -1)
    turns = np.full(valid.shape[0] - 1, np.nan)
    for t in range(valid.shape[0] - 1):
        before, after = points[t][valid[t]], points[t + 1][valid[t + 1]]
        if min(len(before), len(after)) < min_pairs:
            continue
        distance = np.linalg.norm(before[:, None] - after[None], axis=-1)
        nearest, back = distance.argmin(1), distance.argmin(0)
        pair = ((back[nearest] == np.arange(len(before)))
                & (distance[np.arange(len(before)), nearest] < match_radius))
        if pair.sum() < min_pairs:
            continue
        source, target = before[pair], after[nearest[pair]]
        alignment = in_float64(align_se2, source, target)  # (x, y, angle)
        angle, shift = alignment[2], alignment[:2]
        residual = target - rigid_transform_2d(source, angle, shift)
        if np.sqrt(np.mean(np.sum(residual ** 2, -1))) <= max_residual:
            turns[t] = -angle  # the scene turns by -d when the vehicle turns by d
    return turns


def _dead_reckoned_turns(data: VictoriaPark, bias: float) -> np.ndarray:
    """(S - 1,) heading change [rad] between laser times of the dead reckoning with ``bias``."""
    _, yaw_rate = body_rates(np.stack([data.dr_speed, data.dr_steering + bias], -1),
                             "ackermann", VICTORIA_PARK_VEHICLE)
    heading = np.concatenate([[0.0], np.cumsum(np.diff(data.dr_time) * yaw_rate[:-1])])
    return np.diff(np.interp(data.laser_time, data.dr_time, heading))


def _turn_residuals(data: VictoriaPark, turns: np.ndarray, max_turn: float):
    """Per scan pair t (T - 1 of them): whether the laser turn d_t is usable, the sensitivity
    g_t = dD_t/db of the dead-reckoned turn to the steering bias, and d_t - D_t(0)."""
    base = _dead_reckoned_turns(data, 0.0)[:turns.size]
    slope = (_dead_reckoned_turns(data, 0.01)[:turns.size] - base) / 0.01
    use = np.isfinite(turns) & (np.abs(turns) < max_turn)
    return use, np.where(use, slope, 0.0), np.where(use, turns - base, 0.0)


def steering_bias_from_scans(data: VictoriaPark, observations: Observations,
                             max_turn: float = 0.3) -> tuple[float, float]:
    """Steering bias [rad] that makes the dead-reckoned turns match the laser's (no GPS).

    With d_t the scan-to-scan turns (``scan_rotations``) and D_t(b) the dead-reckoned turn
    between the same laser times with bias b (linear in a small b: D_t(b) = D_t(0) + b g_t,
    g_t = (D_t(0.01) - D_t(0)) / 0.01), least squares gives
    b = sum g_t (d_t - D_t(0)) / sum g_t^2 over the scans with a turn estimate below
    ``max_turn``. Returns (bias, standard error), both in rad.
    """
    use, x, y = _turn_residuals(data, scan_rotations(observations), max_turn)
    if use.sum() < 10:
        raise ValueError(f"steering_bias_from_scans: only {int(use.sum())} scan pairs with a "
                         "turn estimate; expected at least 10 (too few trunks matched)")
    x, y = x[use], y[use]
    bias = float(np.sum(x * y) / np.sum(x * x))
    error = float(np.std(y - bias * x) / np.sqrt(np.sum(x * x)))
    return bias, error


# Scans in each window of ``steering_bias_profile`` (about 2 minutes, 300 m of driving); the
# length was chosen by GPS score (the "legacy" set; docs/results.md, victoria_park).
BIAS_WINDOW = 600


def bias_profile_from_turns(data: VictoriaPark, turns: np.ndarray,
                            window: int = BIAS_WINDOW, max_turn: float = 0.3,
                            min_pairs: int = 20) -> np.ndarray:
    """(D,) steering bias [rad] at each dead-reckoning time from laser turns (T - 1,).

    The least-squares fit of ``steering_bias_from_scans`` over the scan pairs in
    [c - window/2, c + window/2), for centres c every window/4 scans; windows with fewer
    than ``min_pairs`` usable pairs (or no turning sensitivity) are skipped. The fits are
    linearly interpolated over the dead-reckoning times (held constant beyond the first and
    last centre). A calibration of the whole log from the laser alone (it looks up to
    window/2 scans ahead, so it is an offline step, not an online filter).
    """
    if window < 4:
        raise ValueError(f"window={window} scans is too short; expected at least 4")
    turns = np.asarray(turns, np.float64)
    use, x, y = _turn_residuals(data, turns, max_turn)
    centres, biases = [], []
    for centre in range(0, turns.size, window // 4):
        inside = slice(max(0, centre - window // 2), centre + window // 2)
        xw, yw = x[inside], y[inside]
        if use[inside].sum() >= min_pairs and np.sum(xw * xw) > 0.0:
            centres.append(centre)
            biases.append(np.sum(xw * yw) / np.sum(xw * xw))
    if not centres:
        raise ValueError(f"bias_profile_from_turns: no window of {window} scans has "
                         f"{min_pairs} scan pairs with a turn estimate (of {turns.size + 1} "
                         "scans); use a constant bias such as STEERING_BIAS")
    return np.interp(data.dr_time, np.asarray(data.laser_time)[centres], biases)


def steering_bias_profile(data: VictoriaPark, observations: Observations,
                          window: int = BIAS_WINDOW, max_turn: float = 0.3) -> np.ndarray:
    """(D,) time-varying steering bias [rad] from the scans alone (``scan_rotations`` of
    ``observations``, then ``bias_profile_from_turns``). On the whole log it runs -0.3 to
    6.6 mrad (10-90%: 2.2-5.8, median 4.2) around the constant 4.1; through the treeless
    corner into the western leg (scans 4,650-5,300) it averages 2.2 mrad, so the constant
    makes the dead reckoning turn too much there by about 2 mrad of steering."""
    return bias_profile_from_turns(data, scan_rotations(observations), window, max_turn)


def detector_settings(**overrides) -> dict:
    """Keyword arguments of ``detect_trunks`` used for Victoria Park (``DETECTOR_DEFAULTS``)."""
    unknown = set(overrides) - set(DETECTOR_DEFAULTS) - {
        "max_angle_gap", "min_radius", "geometric_iterations", "num_hypotheses", "inlier_tol"}
    if unknown:
        raise ValueError(f"detector_settings got unknown field(s) {sorted(unknown)}; expected "
                         f"keyword arguments of jaxslam.detect.detect_trunks")
    return {**DETECTOR_DEFAULTS, **overrides}


@functools.partial(jax.jit, static_argnames=("max_obs", "settings"))
def _detect_batch(ranges, angles, max_obs: int, settings: tuple):
    kwargs = dict(settings)
    method = kwargs.pop("method")
    return jax.vmap(lambda scan: detect_trunks(scan, angles, method, max_obs=max_obs,
                                               **kwargs))(ranges)


def detect_scans(ranges, angles, max_obs: int = CLASSIC_MAX_TRUNKS, dtype=jnp.float32,
                 to_centre: bool = False, **settings) -> Observations:
    """Trunks in every scan, batched with ``jax.vmap`` and compiled once per setting.

    Args:
      ranges: (T, B) ranges [m], +inf for no return (``detect_trunks`` treats anything at or
        beyond ``max_range`` or at or below ``min_range`` as no return, so +inf is safe).
      angles: (B,) beam bearings [rad] in the robot frame.
      max_obs: K, trunks kept per scan (the nearest ones).
      to_centre: with the centroid method, move ranges to the trunk centre
        (``centroid_to_centre``). Off by default (it did not help on prefixes of the
        log; docs/results.md).
      **settings: ``detect_trunks`` keywords overriding ``DETECTOR_DEFAULTS``.
    Returns:
      ``Observations`` with z (T, K, 2), valid (T, K), radius (T, K), landmark_id (T, K).
    """
    ranges = jnp.asarray(ranges, dtype)
    if ranges.ndim != 2:
        raise ValueError(f"detect_scans expects ranges (T, B); got shape {ranges.shape}")
    kwargs = detector_settings(**settings)
    obs = _detect_batch(ranges, jnp.asarray(angles, dtype), max_obs,
                        tuple(sorted(kwargs.items())))
    if to_centre and kwargs["method"] == "centroid":
        obs = centroid_to_centre(obs)
    return obs


def centroid_to_centre(obs: Observations) -> Observations:
    """Move centroid detections from the arc's centroid to the trunk centre.

    The points of the visible half circle, radius r, average 2 r / pi nearer the sensor than
    the centre; ``detect_trunks``' centroid method reports that centroid (radius = chord / 2),
    so the range gains 2 r / pi on valid rows. (The classic detector likewise reports the range
    to the trunk centre.)
    """
    offset = jnp.where(obs.valid, 2.0 / jnp.pi * obs.radius, 0.0)
    return obs._replace(z=obs.z.at[..., 0].add(offset))


class DetectionSummary(NamedTuple):
    """Detection figures over a run (compare with the classic detector's limits).

    total: trunks detected over all scans; per_scan_mean / per_scan_max: per scan;
    scans_at_cap: scans that filled all K rows (more trunks were seen than kept);
    range_percentiles: (5, 25, 50, 75, 95) percentiles of the detected ranges [m];
    radius_median: median fitted radius [m].
    """

    total: int
    per_scan_mean: float
    per_scan_max: int
    scans_at_cap: int
    range_percentiles: np.ndarray
    radius_median: float


def summarize_detections(observations: Observations) -> DetectionSummary:
    """Host-side counts and ranges of padded detections with (T, K) leaves."""
    valid = np.asarray(observations.valid, bool)
    per_scan = valid.sum(axis=1)
    ranges = np.asarray(observations.z)[..., 0][valid]
    radius = np.asarray(observations.radius)[valid]
    empty = ranges.size == 0
    return DetectionSummary(
        total=int(valid.sum()), per_scan_mean=float(per_scan.mean()),
        per_scan_max=int(per_scan.max()), scans_at_cap=int(np.sum(per_scan == valid.shape[1])),
        range_percentiles=(np.full(5, np.nan) if empty
                           else np.percentile(ranges, [5, 25, 50, 75, 95])),
        radius_median=float("nan") if empty else float(np.median(radius)))


def _settings(settings: str | Settings) -> Settings:
    return load_settings(settings) if isinstance(settings, str) else settings


def victoria_park_config(settings: str | Settings = LEGACY, **fields) -> FilterConfig:
    """``FilterConfig`` of a settings set (a name of ``SETTINGS_FILE`` or a ``Settings``;
    default "legacy", the set whose values need no calibration), then ``fields``."""
    return settings_config(_settings(settings), **fields)


def victoria_park_params(config: FilterConfig | None = None, dtype=jnp.float32,
                         settings: str | Settings = LEGACY, **overrides) -> Params:
    """``settings_params`` of a settings set (default "legacy"), then ``overrides``.

    Noise scales: ``motion_scale`` is not a field; scale the noise tuples yourself, e.g.
    ``trans_noise=tuple(2 * c for c in load_settings("legacy").params["trans_noise"])``.
    """
    return settings_params(_settings(settings), config, dtype, **overrides)


def smoother_options(settings: str | Settings = LEGACY) -> dict:
    """``smoothing.smooth_path`` keywords of a settings set (its ``smoother`` table)."""
    return dict(_settings(settings).smoother)


def steering_bias_of(settings: Settings, data: VictoriaPark, observations: Observations):
    """The set's steering bias [rad] from the scans alone: "constant" gives the number of
    ``steering_bias_from_scans``, "profile" the (D,) ``steering_bias_profile`` with the set's
    ``bias_window``; a number is used as it is."""
    mode = settings.run.get("steering_bias", "constant")
    if mode == "constant":
        return steering_bias_from_scans(data, observations)[0]
    if mode == "profile":
        return steering_bias_profile(data, observations,
                                     int(settings.run.get("bias_window", BIAS_WINDOW)))
    if isinstance(mode, (int, float)) and not isinstance(mode, bool):
        return float(mode)
    raise ValueError(f"settings {settings.name!r}: run.steering_bias={mode!r}; expected "
                     "'constant', 'profile' or a number [rad]")


def victoria_park_robot_log(data: VictoriaPark, observations: Observations, steering_bias,
                            num_scans: int | None = None):
    """The first T = ``num_scans`` scans as a ``RobotLog`` with detections: the input of
    ``jaxslam.pipeline.filter_log``.

    controls (T, 3): ``victoria_park_controls(data, steering_bias)``; obs_z (T, K, 2),
    obs_valid (T, K), obs_radius (T, K): ``observations``; GPS: the filtered fixes (the
    pipeline scores nothing with them: a RobotLog's truth is ``truth_pose``). No raw scans.
    """
    log = victoria_park_log(data)
    steps = _prefix(num_scans, log.num_steps)
    obs = jax.tree.map(lambda leaf: np.asarray(leaf)[:steps], observations)
    return log._replace(time=log.time[:steps],
                        controls=victoria_park_controls(data, steering_bias)[:steps],
                        obs_z=np.asarray(obs.z, np.float64), obs_valid=np.asarray(obs.valid),
                        obs_radius=np.asarray(obs.radius, np.float64), scan_ranges=None,
                        scan_angles=None)


class VictoriaParkCalibration(NamedTuple):
    """``calibrate_victoria_park``'s result.

    Attributes:
      params: the calibrated ``Params`` (``calibrate_params``, ``radius_noise`` included).
      info: ``self_calibration.CalibrationInfo`` of the EM.
      radius_noise / radius_samples: the fitted trunk-radius std and the radii behind it
        (nan / 0 when it was not fitted).
      steering_bias: the bias [rad] the controls were corrected with.
      seconds: wall time of the calibration (filter_log: EM iterations and one final run).
      path: (T, 3) the weighted-mean path of filter_log's final run (key of the calibration,
        calibrated Params); num_trees: its final map size.
      warnings: filter_log's warnings.
    """

    params: Params
    info: object
    radius_noise: float
    radius_samples: int
    steering_bias: object
    seconds: float
    path: np.ndarray
    num_trees: int
    warnings: tuple


def calibration_log(data: VictoriaPark, settings: Settings, config: FilterConfig,
                    observations: Observations | None = None, num_scans: int | None = None):
    """The log ``calibrate_victoria_park`` calibrates on: (``RobotLog`` of the first
    ``num_scans`` scans (default all) with their detected trunks (``detect_scans`` with
    ``config.max_obs`` unless ``observations`` are given) and the controls corrected by the
    set's steering bias, those observations, the bias)."""
    if observations is None:
        log = victoria_park_log(data)
        observations = detect_scans(log.scan_ranges, log.scan_angles, config.max_obs)
    steps = _prefix(num_scans, data.laser_time.shape[0])
    observations = _slice_obs(observations, steps)
    bias = steering_bias_of(settings, data, observations)
    return victoria_park_robot_log(data, observations, bias, steps), observations, bias


def calibrate_victoria_park(key, data: VictoriaPark, settings: str | Settings = CALIBRATED,
                            observations: Observations | None = None,
                            num_scans: int | None = None, progress=None,
                            config: FilterConfig | None = None) -> VictoriaParkCalibration:
    """The set's "calibrated" Params estimated from the log alone, GPS unused.

    1. controls corrected by the set's steering bias (``steering_bias_of``, from the laser);
    2. ``jaxslam.pipeline.filter_log(log, config, starting Params, key, calibrate=True)``
       on the log as a ``RobotLog`` (``victoria_park_robot_log``): EM with the smoother
       (``self_calibration.calibrate_params``) for the motion noise (Geiser et al. 2023,
       Eq. 1, with its burst tail), range/bearing noise, max_range, miss_range, field of
       view, detection / false-alarm probabilities, the trunk-radius std (from the scatter
       of the detected radii within each smoothed landmark, when the set lists
       ``radius_noise`` as calibrated) and the gate, then one run with them.

    Args: as ``run_victoria_park``; ``progress``: optional callable(str) for each EM step;
    ``config``: the FilterConfig to calibrate with (default ``settings_config(settings)``).
    """
    from jaxslam.pipeline import filter_log

    settings = _settings(settings)
    config = settings_config(settings) if config is None else config
    robot_log, observations, bias = calibration_log(data, settings, config, observations,
                                                    num_scans)
    start = time.perf_counter()
    options = {"calibrate_radius": "radius_noise" in settings.calibrated}
    run = filter_log(robot_log, config, settings_params(settings, config), key,
                     calibrate=settings.calibrate, smooth=False, progress=progress,
                     calibration_options=options)
    info = run.calibration
    fitted = info is not None and "radius_noise" in info.values
    seconds = time.perf_counter() - start
    return VictoriaParkCalibration(
        params=run.params, info=info,
        radius_noise=float(info.values["radius_noise"]) if fitted else float("nan"),
        radius_samples=int(info.samples.get("radius", 0)) if fitted else 0,
        steering_bias=bias, seconds=seconds, path=run.mean_pose,
        num_trees=int(np.sum(np.asarray(run.estimate.active))), warnings=run.warnings)


class VictoriaParkRun(NamedTuple):
    """One FastSLAM run over (a prefix of) Victoria Park.

    Attributes:
      time: (T,) scan times [s].  path: (T, 3) weighted-mean laser pose per scan.
      landmark_mean: (M, 2) best particle's map; active: (M,) its occupied slots.
      landmark_count: (M,) int32 updates of each slot since its birth.
      num_trees: () active landmarks of the best particle at the end.
      num_confirmed: () of those, landmarks updated at least ``confirm_count`` times.
      gps: ``GpsError`` of the path (None when no GPS fix falls in the time span).
      ess: (T,) effective sample size per step.  num_landmarks: (T,) map size per step.
      compile_s / run_s: seconds to compile and to run the filter (after compilation).
      smoothed_path: (T, 3) the best particle's history re-solved with its associations
        fixed (``smoothing``); smoothed_gps: its ``GpsError``; smooth_s: seconds it took
        (None / None / 0.0 with ``smooth=False``).
      closed_path: (T, 3) the same history smoothed with the loops the filter missed closed
        (``pipeline.offline_path(close_loops=True)``); closed_gps: its ``GpsError``;
        closures: {loop_closures, landmarks_joined}; close_s: seconds it took (None / None
        / None / 0.0 without ``close_loops``).
    """

    time: np.ndarray
    path: np.ndarray
    landmark_mean: np.ndarray
    active: np.ndarray
    landmark_count: np.ndarray
    num_trees: int
    num_confirmed: int
    gps: object
    ess: np.ndarray
    num_landmarks: np.ndarray
    compile_s: float
    run_s: float
    smoothed_path: np.ndarray | None = None
    smoothed_gps: object = None
    smooth_s: float = 0.0
    closed_path: np.ndarray | None = None
    closed_gps: object = None
    closures: dict | None = None
    close_s: float = 0.0


def _prefix(num_scans: int | None, total: int) -> int:
    if num_scans is None:
        return total
    if not 1 <= num_scans <= total:
        raise ValueError(f"num_scans={num_scans} is invalid; expected 1..{total} (the log's "
                         "scan count) or None for the whole run")
    return num_scans


def _slice_obs(observations: Observations, steps: int) -> Observations:
    return jax.tree.map(lambda leaf: leaf[:steps], observations)


@functools.partial(jax.jit, static_argnums=(0, 5))
def _run_one(config, key, params, controls, observations, smooth=False):
    state, trace = run_filter(config, key, params, controls, observations,
                              record_lineage=smooth)
    best = estimate(state)
    history = (lineage.trace_lineage(trace.lineage, best.best_particle) if smooth
               else None)
    return (trace.mean_pose, trace.ess, trace.num_landmarks, best.landmark_mean, best.active,
            state.particles.observation_count[best.best_particle], history)


def _smooth(params, controls, observations, history: lineage.LineagePath,
            visit_gap: int | None = None, options: dict | None = None):
    """``smoothing.smooth_lineage`` of one run from the origin (VP controls are odometry),
    with the ``smooth_path`` keywords ``options`` (default: the legacy set's smoother)."""
    options = smoother_options(LEGACY) if options is None else options
    return smoothing.smooth_lineage(np.zeros(3), jax.tree.map(np.asarray, history),
                                    in_float64(control_to_odometry, controls, params,
                                               motion_model="odometry"),
                                    np.asarray(observations.z), params,
                                    visit_gap=visit_gap, **options)


def _check_smoothing(smooth: bool, smooth_visit_gap, close_loops: bool = False):
    """Before the filter runs: a bad gap must not cost a finished run (or 100 of them)."""
    check_offline_options(smooth, smooth_visit_gap, close_loops)
    if smooth_visit_gap is None:
        return
    if not smooth:
        raise ValueError(f"smooth_visit_gap={smooth_visit_gap!r} needs smooth=True (it "
                         "configures the smoother)")
    smoothing.check_visit_options(smooth_visit_gap)


def _run_inputs(data, config, params, observations, num_scans, dtype, steering_bias):
    """Defaults filled in and everything cut to the first T = ``num_scans`` scans:
    (config, params, controls (T, 3), observations with (T, K) leaves, the log, T)."""
    if isinstance(steering_bias, str) and steering_bias not in ("laser", "constant"):
        raise ValueError(f"steering_bias={steering_bias!r}; expected 'laser' (the "
                         "steering_bias_profile of these scans), 'constant' (their "
                         "steering_bias_from_scans), a number [rad] or a (D,) array over the "
                         "dead-reckoning samples")
    config = victoria_park_config() if config is None else config
    params = victoria_park_params(config, dtype) if params is None else params
    log = victoria_park_log(data)
    steps = _prefix(num_scans, log.num_steps)
    if observations is None:
        observations = detect_scans(log.scan_ranges[:steps], log.scan_angles, config.max_obs,
                                    dtype)
    observations = _slice_obs(observations, steps)
    if isinstance(steering_bias, str) and steering_bias == "constant":
        steering_bias = steering_bias_from_scans(data, observations)[0]
    elif isinstance(steering_bias, str):
        steering_bias = steering_bias_profile(data, observations)
    controls = jnp.asarray(victoria_park_controls(data, steering_bias)[:steps], dtype)
    return config, params, controls, observations, log, steps


def run_victoria_park(key, data: VictoriaPark, config: FilterConfig | None = None,
                      params: Params | None = None, observations: Observations | None = None,
                      num_scans: int | None = None, confirm_count: int = 3,
                      dtype=jnp.float32,
                      steering_bias: float | np.ndarray | str = "laser",
                      smooth: bool = True,
                      smooth_visit_gap: int | None = None,
                      smoother: dict | None = None,
                      close_loops: bool = False) -> VictoriaParkRun:
    """FastSLAM over the first ``num_scans`` scans (None: all 7,230) and its GPS score.

    Args:
      key: PRNG key (step t uses ``fold_in(key, t)``).
      data: ``load_victoria_park()``.
      config / params: default ``victoria_park_config()`` / ``victoria_park_params(config)``
        (the "legacy" set; for the calibrated one pass ``calibrate_victoria_park``'s params).
      observations: detections with (T_all, K) leaves (default ``detect_scans`` of the log
        with K = config.max_obs); pass them to reuse one detection across runs.
      confirm_count: updates a landmark needs to count in ``num_confirmed``.
      steering_bias: added to the steering angle (``victoria_park_controls``): a number
        [rad], a (D,) array over the dead-reckoning samples, "laser" (default): the
        ``steering_bias_profile`` of the first ``num_scans`` scans' detections, or
        "constant": their ``steering_bias_from_scans``.
      smooth: also re-solve the best particle's history (``smoothing``; the filter then
        records every particle's lineage, 64 MB for the whole log at P=100, K=18).
      smooth_visit_gap: None (default), or let the smoother revise the loop closures with
        visits split at gaps of this many scans (``smoothing.smooth_path(visit_gap)``; 100
        is the tested value).
      smoother: ``smoothing.smooth_path`` keywords (``smoother_options``; default the legacy
        set's).
      close_loops: also smooth the history with the loops the filter missed closed
        (``pipeline.offline_path``: ``loop_closure.close_loops``, plain squares, then the
        smoother on the closed association with the ``smoother``'s rounds of variance
        components, as the smoothed path; needs ``smooth``).
    """
    _check_smoothing(smooth, smooth_visit_gap, close_loops)
    smoother = smoother_options(LEGACY) if smoother is None else smoother
    config, params, controls, observations, log, steps = _run_inputs(
        data, config, params, observations, num_scans, dtype, steering_bias)
    outputs, compile_s, run_s = _timed_run(config, key, params, controls, observations,
                                           bool(smooth))
    path, ess, num_landmarks, landmark_mean, active, count = (np.asarray(o)
                                                               for o in outputs[:6])
    smoothed, smoothed_gps, smooth_s = None, None, 0.0
    if smooth:
        start = time.perf_counter()
        smoothed = _smooth(params, controls, observations, outputs[6],
                           smooth_visit_gap, smoother).path
        smooth_s = time.perf_counter() - start
        smoothed_gps = _gps_score(log, smoothed, steps)
    closed, closed_gps, closures, close_s = None, None, None, 0.0
    if close_loops:
        start = time.perf_counter()
        # The set's own rounds (smooth_path's default 0 when it names none), as the
        # smoothed path's.
        closed, closures = offline_path(outputs[6], controls, observations, np.zeros(3),
                                        params, config.motion_model, close_loops=True,
                                        calibrate_rounds=smoother.get("calibrate_rounds", 0))
        close_s = time.perf_counter() - start
        closed_gps = _gps_score(log, closed, steps)
    return VictoriaParkRun(
        time=log.time[:steps], path=path, landmark_mean=landmark_mean, active=active,
        landmark_count=count, num_trees=int(active.sum()),
        num_confirmed=int(np.sum(active & (count >= confirm_count))),
        gps=_gps_score(log, path, steps), ess=ess, num_landmarks=num_landmarks,
        compile_s=compile_s, run_s=run_s, smoothed_path=smoothed, smoothed_gps=smoothed_gps,
        smooth_s=smooth_s, closed_path=closed, closed_gps=closed_gps, closures=closures,
        close_s=close_s)


_COMPILED: dict = {}


def _compiled(function, config, *args, static=()):
    """AOT-compiled ``function`` for this config, these argument shapes and the trailing
    static arguments ``static``, cached.

    Returns (executable, compile seconds; 0.0 when it came from the cache)."""
    signature = (function.__name__, config, static,
                 tuple((leaf.shape, leaf.dtype) for leaf in jax.tree.leaves(args)))
    if signature in _COMPILED:
        return _COMPILED[signature], 0.0
    start = time.perf_counter()
    executable = function.lower(config, *args, *static).compile()
    _COMPILED[signature] = executable
    return executable, time.perf_counter() - start


def _timed_run(config, key, params, controls, observations, smooth=False):
    """(outputs of ``_run_one``, compile seconds, run seconds after compilation)."""
    executable, compile_s = _compiled(_run_one, config, key, params, controls, observations,
                                      static=(smooth,))
    start = time.perf_counter()
    outputs = jax.block_until_ready(executable(key, params, controls, observations))
    return outputs, compile_s, time.perf_counter() - start


def _gps_score(log, path, steps: int):
    """``GpsError`` of the path's (x, y) against the filtered GPS, or None without fixes."""
    time_span = log.time[:steps]
    inside = (log.gps_time >= time_span[0]) & (log.gps_time <= time_span[-1])
    if inside.sum() < 3:
        return None
    return gps_error(time_span, np.asarray(path, np.float64)[:, :2], log.gps_time, log.gps_xy)


class BatchRuns(NamedTuple):
    """R independent runs of the same log in one compiled call.

    Attributes:
      path: (R, T, 3) weighted-mean paths.  num_trees: (R,) final map size (best particle).
      rmse: (R,) RMSE [m] against filtered GPS after a rigid fit of each path.
      compile_s / run_s: seconds to compile and to run the batched call.
      smoothed_path: (R, T, 3) and smoothed_rmse: (R,) of each run's smoothed history, and
      smooth_s: host seconds for all of them (None / None / 0.0 with ``smooth=False``).
    """

    path: np.ndarray
    num_trees: np.ndarray
    rmse: np.ndarray
    compile_s: float
    run_s: float
    smoothed_path: np.ndarray | None = None
    smoothed_rmse: np.ndarray | None = None
    smooth_s: float = 0.0


@functools.partial(jax.jit, static_argnums=(0, 5))
def _run_batch(config, keys, params, controls, observations, chunk=0):
    """All runs vmapped (``chunk`` = 0), or with lineage recording and ``chunk`` runs
    vmapped at a time (``lax.map``): the lineage is 4 T P K + 16 T P bytes a run."""
    smooth = chunk > 0

    def one(key):
        path, _, _, _, active, _, history = _run_one(config, key, params, controls,
                                                      observations, smooth)
        return path, jnp.sum(active).astype(jnp.int32), history

    if not smooth:
        return jax.vmap(one)(keys)
    return jax.lax.map(one, keys, batch_size=chunk)


def run_victoria_park_batch(key, data: VictoriaPark, num_runs: int,
                            config: FilterConfig | None = None, params: Params | None = None,
                            observations: Observations | None = None,
                            num_scans: int | None = None, dtype=jnp.float32,
                            steering_bias: float | np.ndarray | str = "laser",
                            smooth: bool = False, chunk: int = 20,
                            progress: bool = True,
                            smooth_visit_gap: int | None = None,
                            smoother: dict | None = None) -> BatchRuns:
    """``num_runs`` Monte Carlo runs (run r uses key ``fold_in(key, r)``) in one compiled call.

    Arguments as ``run_victoria_park``. Memory grows as R * P * M; on this CPU pick P so
    R * P stays within a few thousand. With ``smooth`` the filter records every particle's
    lineage, so runs go ``chunk`` at a time through the compiled call (64 MB a run for the
    whole log at P=100), and each run's best history is then smoothed on the host (a tqdm
    bar when ``progress``; ~5 s a run for the whole log with the legacy smoother settings).
    """
    if not isinstance(num_runs, (int, np.integer)) or num_runs < 1:
        raise ValueError(f"num_runs={num_runs!r} is invalid; expected a positive integer")
    if smooth and (not isinstance(chunk, (int, np.integer)) or chunk < 1):
        raise ValueError(f"chunk={chunk!r} is invalid; expected a positive integer (runs "
                         "per vmapped group when smoothing)")
    _check_smoothing(smooth, smooth_visit_gap)
    config, params, controls, observations, log, steps = _run_inputs(
        data, config, params, observations, num_scans, dtype, steering_bias)
    keys = jax.vmap(lambda run: jax.random.fold_in(key, run))(jnp.arange(num_runs))
    args = (keys, params, controls, observations)
    static = (int(min(chunk, num_runs)) if smooth else 0,)
    executable, compile_s = _compiled(_run_batch, config, *args, static=static)
    start = time.perf_counter()
    paths, num_trees, histories = jax.block_until_ready(executable(*args))
    run_s = time.perf_counter() - start
    paths = np.asarray(paths)
    rmse = np.array([_gps_score(log, path, steps).rmse for path in paths])
    smoothed, smoothed_rmse, smooth_s = None, None, 0.0
    if smooth:
        start = time.perf_counter()
        histories = jax.tree.map(np.asarray, histories)
        smoothed = np.stack([
            _smooth(params, controls, observations,
                    jax.tree.map(lambda leaf, run=run: leaf[run], histories),
                    smooth_visit_gap, smoother).path
            for run in tqdm(range(num_runs), desc="smoothing runs", disable=not progress)])
        smooth_s = time.perf_counter() - start
        smoothed_rmse = np.array([_gps_score(log, path, steps).rmse for path in smoothed])
    return BatchRuns(path=paths, num_trees=np.asarray(num_trees), rmse=rmse,
                     compile_s=compile_s, run_s=run_s, smoothed_path=smoothed,
                     smoothed_rmse=smoothed_rmse, smooth_s=smooth_s)
