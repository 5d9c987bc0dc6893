"""The jaxslam robot log: a documented ``.npz`` layout, its validating loader, control integration.

The layout is specified in ``docs/log_format.md``. Shapes (glossary in ``jaxslam.types``):
T steps (one per observation time), K padded observations per step, B beams per raw scan,
N landmarks, G GPS fixes, C control components.

Everything here is host-side NumPy float64: logs are read once, then handed to the filter.
"""
from __future__ import annotations

import os
from typing import NamedTuple

import numpy as np

from jaxslam.types import MOTION_MODELS, Observations, make_observations

FORMAT_VERSION = 1
REQUIRED_KEYS = ("format_version", "time", "motion_model", "controls")
OPTIONAL_KEYS = ("obs_z", "obs_valid", "obs_radius", "scan_ranges", "scan_angles",
                 "truth_pose", "truth_landmarks", "gps_time", "gps_xy", "initial_pose")
EXTRA_PREFIX = "meta_"  # keys with this prefix are user metadata: kept out of RobotLog, ignored


class LogFormatError(ValueError):
    """A robot log that does not follow ``docs/log_format.md``; the message names file and fix."""


class RobotLog(NamedTuple):
    """One robot run in the jaxslam log format (all NumPy; optional fields are ``None``).

    Attributes:
      time: (T,) float64 seconds, strictly increasing: the observation (filter step) times.
      motion_model: "odometry" (rot1, trans, rot2), "velocity" (v, omega, dt) or
        "ackermann" (v, steering, dt).
      controls: (T, 3) float64; row t is the move from time[t-1] to time[t]; row 0 is the move
        into the first observation time (zeros when the robot starts there).
      obs_z: (T, K, 2) range [m] and bearing [rad] in the robot frame; padding finite.
      obs_valid: (T, K) bool; False marks padding.
      obs_radius: (T, K) trunk radius [m] or None.
      scan_ranges: (T, B) raw 2D scan ranges [m]; +inf means "no return". Or None.
      scan_angles: (B,) beam bearings [rad] in the robot frame (x forward, y left). Or None.
      truth_pose: (T, 3) true poses (x, y, theta) or None.
      truth_landmarks: (N, 2) true landmark positions or None.
      gps_time: (G,) seconds on the same clock as ``time``, strictly increasing, or None.
      gps_xy: (G, 2) GPS positions [m] in a local metric frame, or None.
      initial_pose: (3,) pose before row 0's move (so the pose at time[0] is
        ``initial_pose (+) controls[0]``), or None for zeros.
      format_version: int, ``FORMAT_VERSION`` when written by this library.
    """

    time: np.ndarray
    motion_model: str
    controls: np.ndarray
    obs_z: np.ndarray | None = None
    obs_valid: np.ndarray | None = None
    obs_radius: np.ndarray | None = None
    scan_ranges: np.ndarray | None = None
    scan_angles: np.ndarray | None = None
    truth_pose: np.ndarray | None = None
    truth_landmarks: np.ndarray | None = None
    gps_time: np.ndarray | None = None
    gps_xy: np.ndarray | None = None
    initial_pose: np.ndarray | None = None
    format_version: int = FORMAT_VERSION

    @property
    def num_steps(self) -> int:
        """T, the number of filter steps."""
        return int(self.time.shape[0])

    def observations(self, dtype=np.float32) -> Observations:
        """The padded range-bearing observations as ``Observations`` with (T, K, ...) leaves.

        Raises ``LogFormatError`` for a scans-only log: detect trunks first (``jaxslam.detect``)
        and store them as ``obs_z``/``obs_valid``.
        """
        if self.obs_z is None:
            raise LogFormatError(
                "this log has raw scans but no range-bearing observations (obs_z/obs_valid); "
                "expected detected landmarks: run trunk detection on scan_ranges first")
        return make_observations(
            np.asarray(self.obs_z, dtype), self.obs_valid,
            None if self.obs_radius is None else np.asarray(self.obs_radius, dtype))


# ----------------------------------------------------------------------------------------------
# Validation


def _fail(source: str, message: str) -> None:
    raise LogFormatError(f"{source}: {message}")


def _check_shape(source, name, array, expected):
    """``expected`` is a tuple of ints or None (any size); names the mismatch."""
    ok = array.ndim == len(expected) and all(
        e is None or e == s for e, s in zip(expected, array.shape))
    if not ok:
        want = "(" + ", ".join("*" if e is None else str(e) for e in expected) + (
            ",)" if len(expected) == 1 else ")")
        _fail(source, f"'{name}' has shape {array.shape}; expected {want}")


def _check_finite(source, name, array, allow_posinf=False):
    bad = np.isnan(array) | (np.isneginf(array) if allow_posinf else ~np.isfinite(array))
    if bad.any():
        where = tuple(int(i) for i in np.argwhere(bad)[0])
        what = "NaN or -inf" if allow_posinf else "NaN or inf"
        _fail(source, f"'{name}' contains {what} ({int(bad.sum())} entries, first at index "
                      f"{where}); expected finite values"
                      + (" (+inf marks no return)" if allow_posinf else ""))


def _check_increasing(source, name, times):
    steps = np.diff(times)
    if (steps <= 0).any():
        i = int(np.argmax(steps <= 0))
        later, earlier = float(times[i + 1]), float(times[i])
        _fail(source, f"'{name}' is not strictly increasing: {name}[{i + 1}]={later!r} <= "
                      f"{name}[{i}]={earlier!r}; expected sorted, distinct timestamps [s]")


def _as_float(source, name, value):
    """``value`` as float64; bool, complex, text and object arrays are refused by name (a
    bool or complex array would otherwise be cast silently: True -> 1.0, imaginary part lost)."""
    try:
        array = np.asarray(value)
    except (TypeError, ValueError) as error:  # e.g. a ragged list
        _fail(source, f"'{name}' is not an array ({error}); expected a float array")
    if array.dtype.kind not in "fiu":
        _fail(source, f"'{name}' is not numeric (dtype {array.dtype}); expected a float array "
                      "(float or integer values; not bool, complex or text)")
    return array.astype(np.float64)


def _check_version(source, value) -> int:
    """The integer scalar ``format_version`` (an integral float such as 1.0 is accepted)."""
    array = np.asarray(value)
    integral = array.dtype.kind in "iu" or (
        array.dtype.kind == "f" and array.ndim == 0 and bool(np.isfinite(array))
        and float(array).is_integer())
    if array.ndim != 0 or not integral:
        shown = f"{array.tolist()!r} " if array.size <= 6 else ""
        _fail(source, f"'format_version' is {shown}(shape {array.shape}, dtype {array.dtype}); "
                      f"expected the integer scalar {FORMAT_VERSION}")
    version = int(array)
    if version != FORMAT_VERSION:
        _fail(source, f"format_version {version} is not supported; expected {FORMAT_VERSION}")
    return version


def _check_pair(source, log, first, second):
    if (getattr(log, first) is None) != (getattr(log, second) is None):
        present, missing = (first, second) if getattr(log, first) is not None else (second, first)
        _fail(source, f"'{present}' is present but '{missing}' is missing; "
                      "expected both or neither")


def _check_core(source: str, log: RobotLog) -> dict:
    fields = {}
    version = _check_version(source, log.format_version)
    model = str(np.asarray(log.motion_model))
    if model not in MOTION_MODELS:
        _fail(source, f"unknown motion_model {model!r}; expected one of {list(MOTION_MODELS)}")
    time = _as_float(source, "time", log.time)
    _check_shape(source, "time", time, (None,))
    if time.shape[0] < 1:
        _fail(source, "'time' is empty; expected at least one step")
    _check_finite(source, "time", time)
    _check_increasing(source, "time", time)
    steps = time.shape[0]
    controls = _as_float(source, "controls", log.controls)
    _check_shape(source, "controls", controls, (steps, 3))
    _check_finite(source, "controls", controls)
    if model != "odometry" and (controls[:, 2] < 0).any():
        _fail(source, f"'controls' column 2 (dt) is negative for motion_model {model!r}; "
                      "expected dt >= 0 [s]")
    fields.update(format_version=version, motion_model=model, time=time, controls=controls)
    return fields


def _check_observations(source: str, log: RobotLog, steps: int) -> dict:
    if log.obs_z is None:
        if log.obs_radius is not None:
            _fail(source, "'obs_radius' is present without 'obs_z'; expected obs_z and obs_valid")
        return {}
    obs_z = _as_float(source, "obs_z", log.obs_z)
    _check_shape(source, "obs_z", obs_z, (steps, None, 2))
    _check_finite(source, "obs_z", obs_z)
    valid = np.asarray(log.obs_valid)
    if valid.dtype != np.bool_:
        _fail(source, f"'obs_valid' has dtype {valid.dtype}; expected bool")
    _check_shape(source, "obs_valid", valid, obs_z.shape[:2])
    negative = valid & (obs_z[..., 0] < 0)
    if negative.any():
        t, k = (int(i) for i in np.argwhere(negative)[0])
        _fail(source, f"'obs_z' has a negative range {float(obs_z[t, k, 0])!r} at valid "
                      f"observation (t={t}, k={k}); expected range >= 0 [m]")
    fields = dict(obs_z=obs_z, obs_valid=valid)
    if log.obs_radius is not None:
        radius = _as_float(source, "obs_radius", log.obs_radius)
        _check_shape(source, "obs_radius", radius, obs_z.shape[:2])
        _check_finite(source, "obs_radius", radius)
        if (radius < 0).any():
            t, k = (int(i) for i in np.argwhere(radius < 0)[0])
            _fail(source, f"'obs_radius' has a negative radius {float(radius[t, k])!r} at "
                          f"(t={t}, k={k}); expected radius >= 0 [m] (0 = unknown)")
        fields["obs_radius"] = radius
    return fields


def _check_scans(source: str, log: RobotLog, steps: int) -> dict:
    if log.scan_ranges is None:
        return {}
    angles = _as_float(source, "scan_angles", log.scan_angles)
    _check_shape(source, "scan_angles", angles, (None,))
    _check_finite(source, "scan_angles", angles)
    ranges = _as_float(source, "scan_ranges", log.scan_ranges)
    _check_shape(source, "scan_ranges", ranges, (steps, angles.shape[0]))
    _check_finite(source, "scan_ranges", ranges, allow_posinf=True)
    if (ranges < 0).any():
        t, b = (int(i) for i in np.argwhere(ranges < 0)[0])
        _fail(source, f"'scan_ranges' has a negative range {float(ranges[t, b])!r} at (t={t}, "
                      f"beam={b}); expected range >= 0 [m] or +inf for no return")
    return dict(scan_ranges=ranges, scan_angles=angles)


def _check_truth_and_gps(source: str, log: RobotLog, steps: int) -> dict:
    fields = {}
    for name, expected in (("truth_pose", (steps, 3)), ("truth_landmarks", (None, 2)),
                           ("initial_pose", (3,))):
        if getattr(log, name) is not None:
            array = _as_float(source, name, getattr(log, name))
            _check_shape(source, name, array, expected)
            _check_finite(source, name, array)
            fields[name] = array
    if log.gps_time is not None:
        gps_time = _as_float(source, "gps_time", log.gps_time)
        _check_shape(source, "gps_time", gps_time, (None,))
        _check_finite(source, "gps_time", gps_time)
        _check_increasing(source, "gps_time", gps_time)
        gps_xy = _as_float(source, "gps_xy", log.gps_xy)
        _check_shape(source, "gps_xy", gps_xy, (gps_time.shape[0], 2))
        _check_finite(source, "gps_xy", gps_xy)
        fields.update(gps_time=gps_time, gps_xy=gps_xy)
    return fields


def validate_log(log: RobotLog, source: str = "<RobotLog>") -> RobotLog:
    """Check ``log`` against ``docs/log_format.md``; return it with canonical dtypes.

    Raises:
      LogFormatError: naming ``source``, the offending array and what is expected.
    """
    for first, second in (("obs_z", "obs_valid"), ("scan_ranges", "scan_angles"),
                          ("gps_time", "gps_xy")):
        _check_pair(source, log, first, second)
    if log.obs_z is None and log.scan_ranges is None:
        _fail(source, "no observations: expected 'obs_z' + 'obs_valid' (range-bearing) or "
                      "'scan_ranges' + 'scan_angles' (raw 2D scans)")
    fields = _check_core(source, log)
    steps = fields["time"].shape[0]
    fields.update(_check_observations(source, log, steps))
    fields.update(_check_scans(source, log, steps))
    fields.update(_check_truth_and_gps(source, log, steps))
    return RobotLog(**fields)


# ----------------------------------------------------------------------------------------------
# Files


def save_log(path, log: RobotLog, compress: bool = False) -> None:
    """Validate ``log`` and write it to ``path`` (.npz); optional fields left None are omitted."""
    log = validate_log(log, source=os.fspath(path))
    arrays = {name: value for name, value in log._asdict().items() if value is not None}
    arrays["motion_model"] = np.asarray(log.motion_model)
    arrays["format_version"] = np.asarray(log.format_version, np.int64)
    (np.savez_compressed if compress else np.savez)(path, allow_pickle=False, **arrays)


_EXPECTED_FILE = ("expected a .npz archive written by numpy.savez / numpy.savez_compressed or "
                  "jaxslam.datasets.save_log (docs/log_format.md)")


def _read_npz(source: str) -> dict:
    """Every array of the .npz at ``source``; LogFormatError for anything unreadable.

    Pickle is never enabled (``allow_pickle=False``): object arrays are refused, by key.
    ``meta_*`` keys are listed but not read (``None``): they may hold anything.
    """
    if not os.path.exists(source):
        _fail(source, f"no such file; {_EXPECTED_FILE}")
    if os.path.isdir(source):
        _fail(source, f"is a directory, not a file; {_EXPECTED_FILE}")
    try:
        with open(source, "rb") as handle:
            magic = handle.read(6)
    except OSError as error:
        raise LogFormatError(f"{source}: cannot open ({error}); {_EXPECTED_FILE}") from error
    if not magic:
        _fail(source, f"the file is empty (0 bytes); {_EXPECTED_FILE}")
    if magic.startswith(b"\x93NUMPY"):
        _fail(source, "cannot read as a .npz archive: it is a single .npy array (numpy.save), "
                      f"not an archive of named arrays; {_EXPECTED_FILE}")
    if not magic.startswith(b"PK"):
        _fail(source, f"cannot read as a .npz archive: it is not a zip file (starts with "
                      f"{magic!r}; a .npz starts with b'PK'); {_EXPECTED_FILE}")
    try:
        loaded = np.load(source, allow_pickle=False)
    except Exception as error:  # noqa: BLE001 - any failure to parse means "not a .npz"
        raise LogFormatError(f"{source}: cannot read as a .npz archive, it is truncated or "
                             f"corrupt ({type(error).__name__}: {error}); "
                             f"{_EXPECTED_FILE}") from error
    if not isinstance(loaded, np.lib.npyio.NpzFile):  # the magic said zip; be safe anyway
        _fail(source, f"cannot read as a .npz archive (got a {type(loaded).__name__}); "
                      f"{_EXPECTED_FILE}")
    arrays = {}
    with loaded as npz:
        for name in list(npz.files):
            if name.startswith(EXTRA_PREFIX):  # user metadata is ignored: never read it
                arrays[name] = None
                continue
            try:
                arrays[name] = npz[name]
            except Exception as error:  # noqa: BLE001 - truncated, corrupt or pickled member
                what = ("an object array that needs pickle, which load_log never enables; "
                        "store numbers, bools or strings" if "pickle" in str(error)
                        else "a corrupt or truncated member")
                raise LogFormatError(
                    f"{source}: cannot read as a .npz archive: key '{name}' is {what} "
                    f"({type(error).__name__}: {error}); {_EXPECTED_FILE}") from error
            if not isinstance(arrays[name], np.ndarray):
                _fail(source, f"cannot read as a .npz archive: member '{name}' of the zip is "
                              f"not a .npy array; {_EXPECTED_FILE}")
    return arrays


def load_log(path) -> RobotLog:
    """Read and validate a jaxslam ``.npz`` log.

    Raises:
      LogFormatError: naming the file: it is missing, empty, truncated or corrupt, not a .npz
        (e.g. a single .npy array or a pickle), holds an array that needs pickle (never
        enabled), a required key is missing, a key is unknown (user metadata must start
        with ``meta_``), or ``validate_log`` fails.
    """
    source = os.fspath(path)
    arrays = _read_npz(source)
    missing = [name for name in REQUIRED_KEYS if name not in arrays]
    if missing:
        _fail(source, f"missing required key(s) {missing}; expected {list(REQUIRED_KEYS)}")
    unknown = sorted(name for name in arrays
                     if name not in REQUIRED_KEYS + OPTIONAL_KEYS
                     and not name.startswith(EXTRA_PREFIX))
    if unknown:
        _fail(source, f"unknown key(s) {unknown}; expected keys among "
                      f"{list(REQUIRED_KEYS + OPTIONAL_KEYS)} (prefix your own with "
                      f"'{EXTRA_PREFIX}')")
    fields = {name: value for name, value in arrays.items() if name in RobotLog._fields}
    if fields["motion_model"].dtype.kind != "U" or fields["motion_model"].ndim != 0:
        _fail(source, f"'motion_model' is {fields['motion_model']!r}; expected a string scalar "
                      f"among {list(MOTION_MODELS)}")
    fields["motion_model"] = str(fields["motion_model"])
    return validate_log(RobotLog(**fields), source=source)


# ----------------------------------------------------------------------------------------------
# Integrating high-rate controls into one odometry move per observation step


class AckermannVehicle(NamedTuple):
    """Ackermann geometry [m]; the pose is taken at the sensor (defaults: Victoria Park README).

    Attributes:
      wheelbase: L, rear axle to front axle.
      encoder_offset: H, lateral offset of the speed-encoder (rear-left) wheel.
      sensor_forward: a, sensor ahead of the rear axle.
      sensor_left: b, sensor left of the vehicle centre line.
    """

    wheelbase: float = 2.83
    encoder_offset: float = 0.76
    sensor_forward: float = 3.78
    sensor_left: float = 0.50


VICTORIA_PARK_VEHICLE = AckermannVehicle()


def wrap_angle_np(angle):
    """NumPy twin of ``jaxslam.geometry.wrap_angle``: wrap to [-pi, pi) by floor arithmetic."""
    return angle - 2.0 * np.pi * np.floor((angle + np.pi) / (2.0 * np.pi))


def interpolate_poses(times, pose_time, poses):
    """Poses (T, 3) at ``times`` (T,) from samples at ``pose_time`` (G,), ``poses`` (G, 3).

    x, y linearly; theta linearly on ``np.unwrap``-ed headings (no jump across +-pi), then
    wrapped to [-pi, pi). Outside [pose_time[0], pose_time[-1]] the end samples are held.
    """
    heading = np.unwrap(poses[:, 2])
    return np.stack([np.interp(times, pose_time, poses[:, 0]),
                     np.interp(times, pose_time, poses[:, 1]),
                     wrap_angle_np(np.interp(times, pose_time, heading))], axis=-1)


def body_rates(controls, motion_model: str, vehicle: AckermannVehicle | None = None):
    """Velocity of the pose's reference point in the body frame, and the yaw rate.

    velocity: u = (v, omega): body velocity (v, 0), yaw rate omega.
    ackermann: u = (v, alpha) with v measured at the encoder wheel (Victoria Park README):
      vc = v / (1 - tan(alpha) H / L), omega = vc tan(alpha) / L, and the sensor at (a, b)
      moves with body velocity (vc - omega b, omega a), which rotated by phi gives the README's
      x' = vc cos(phi) - omega (a sin(phi) + b cos(phi)),
      y' = vc sin(phi) + omega (a cos(phi) - b sin(phi)).

    Args:
      controls: (N, C) with C >= 2; columns (v, omega) or (v, steering); others ignored.
    Returns:
      (body_velocity (N, 2) [m/s], yaw_rate (N,) [rad/s]).
    """
    speed, second = controls[:, 0], controls[:, 1]
    if motion_model == "velocity":
        return np.stack([speed, np.zeros_like(speed)], axis=-1), second
    vehicle = VICTORIA_PARK_VEHICLE if vehicle is None else vehicle
    tan_steer = np.tan(second)
    centre_speed = speed / (1.0 - tan_steer * vehicle.encoder_offset / vehicle.wheelbase)
    yaw_rate = centre_speed * tan_steer / vehicle.wheelbase
    velocity = np.stack([centre_speed - yaw_rate * vehicle.sensor_left,
                         yaw_rate * vehicle.sensor_forward], axis=-1)
    return velocity, yaw_rate


def _euler_poses(duration, body_velocity, yaw_rate):
    """Explicit Euler from the zero pose: (J,), (J, 2), (J,) -> poses (J + 1, 3), heading unwrapped.

    phi_{j+1} = phi_j + h_j omega_j;  p_{j+1} = p_j + h_j R(phi_j) u_j. Headings are a cumsum,
    and since every position step depends only on phi_j, positions are a cumsum too.
    """
    heading = np.concatenate([[0.0], np.cumsum(duration * yaw_rate)])
    cos_h, sin_h = np.cos(heading[:-1]), np.sin(heading[:-1])
    step_x = duration * (cos_h * body_velocity[:, 0] - sin_h * body_velocity[:, 1])
    step_y = duration * (sin_h * body_velocity[:, 0] + cos_h * body_velocity[:, 1])
    return np.stack([np.concatenate([[0.0], np.cumsum(step_x)]),
                     np.concatenate([[0.0], np.cumsum(step_y)]), heading], axis=-1)


def _odometry_poses(increments):
    """Compose odometry moves (N, 3) (rot1, trans, rot2) from the zero pose: (N + 1, 3) poses.

    theta_{i+1} = theta_i + rot1_i + rot2_i; p_{i+1} = p_i + trans_i (cos, sin)(theta_i + rot1_i).
    """
    heading = np.concatenate([[0.0], np.cumsum(increments[:, 0] + increments[:, 2])])
    direction = heading[:-1] + increments[:, 0]
    return np.stack([np.concatenate([[0.0], np.cumsum(increments[:, 1] * np.cos(direction))]),
                     np.concatenate([[0.0], np.cumsum(increments[:, 1] * np.sin(direction))]),
                     heading], axis=-1)


def odometry_between(pose_a, pose_b, min_translation: float = 0.01):
    """The odometry move (rot1, trans, rot2) taking pose_a (..., 3) to pose_b (..., 3).

    rot1 = atan2(dy, dx) - theta_a, trans = |d|, rot2 = theta_b - theta_a - rot1 (wrapped).
    Below ``min_translation`` the move is a pure turn (rot1 = 0), matching
    ``Params.min_translation``: the direction of a sub-millimetre move is noise.
    """
    delta_x, delta_y = pose_b[..., 0] - pose_a[..., 0], pose_b[..., 1] - pose_a[..., 1]
    cos_a, sin_a = np.cos(pose_a[..., 2]), np.sin(pose_a[..., 2])
    forward, left = cos_a * delta_x + sin_a * delta_y, -sin_a * delta_x + cos_a * delta_y
    trans = np.hypot(forward, left)
    rot1 = np.where(trans >= min_translation, np.arctan2(left, forward), 0.0)
    rot2 = wrap_angle_np(pose_b[..., 2] - pose_a[..., 2] - rot1)
    return np.stack([rot1, trans, rot2], axis=-1)


def odometry_path(controls, initial_pose=None):
    """Dead-reckoned poses (T, 3) after each odometry move (T, 3), from ``initial_pose`` (3,)."""
    local = _odometry_poses(np.asarray(controls, np.float64))[1:]
    start = np.zeros(3) if initial_pose is None else np.asarray(initial_pose, np.float64)
    cos_s, sin_s = np.cos(start[2]), np.sin(start[2])
    return np.stack([start[0] + cos_s * local[:, 0] - sin_s * local[:, 1],
                     start[1] + sin_s * local[:, 0] + cos_s * local[:, 1],
                     wrap_angle_np(start[2] + local[:, 2])], axis=-1)


def _check_integration_inputs(control_time, controls, obs_time, motion_model):
    source = "integrate_controls"
    if motion_model not in MOTION_MODELS:
        _fail(source, f"unknown motion_model {motion_model!r}; expected one of "
                      f"{list(MOTION_MODELS)}")
    for name, times in (("control_time", control_time), ("obs_time", obs_time)):
        _check_shape(source, name, times, (None,))
        if times.shape[0] < 1:
            _fail(source, f"'{name}' is empty; expected at least one timestamp")
        _check_finite(source, name, times)
        _check_increasing(source, name, times)
    width = 3 if motion_model == "odometry" else None
    _check_shape(source, "controls", controls, (control_time.shape[0], width))
    if controls.shape[1] < 2:
        _fail(source, f"'controls' has {controls.shape[1]} column(s); expected (v, omega) or "
                      "(v, steering) first")
    _check_finite(source, "controls", controls)


def integrate_controls(control_time, controls, obs_time, motion_model: str,
                       vehicle: AckermannVehicle | None = None,
                       min_translation: float = 0.01) -> np.ndarray:
    """Compose high-rate controls between observation times into one odometry move per step.

    velocity / ackermann: sample i, (v, omega) or (v, steering), is held from control_time[i]
      to control_time[i+1] (the last one indefinitely; before control_time[0] the robot stands
      still). The kinematics (``body_rates``) are integrated by explicit Euler on the merged
      grid of control and observation times, and the relative pose over each observation
      interval becomes an odometry move (``odometry_between``), i.e. exactly what Euler
      integration from the zero pose at obs_time[t-1] to obs_time[t] gives.
    odometry: sample i (rot1, trans, rot2) is the move ending at control_time[i]; moves with
      obs_time[t-1] < control_time[i] <= obs_time[t] are composed into step t (moves after the
      last observation are dropped).
    Row 0 is the move from min(control_time[0], obs_time[0]) into obs_time[0].

    Args:
      control_time: (N,) seconds, strictly increasing.
      controls: (N, C) control samples (C = 3 for odometry, C >= 2 otherwise; a dt column
        is ignored: durations come from control_time).
      obs_time: (T,) seconds, strictly increasing, on the same clock.
      motion_model: "odometry", "velocity" or "ackermann".
      vehicle: Ackermann geometry; None means ``VICTORIA_PARK_VEHICLE``.
      min_translation: see ``odometry_between``.
    Returns:
      (T, 3) odometry controls (rot1, trans, rot2).
    """
    control_time = np.asarray(control_time, np.float64)
    controls = np.asarray(controls, np.float64)
    obs_time = np.asarray(obs_time, np.float64)
    _check_integration_inputs(control_time, controls, obs_time, motion_model)
    if motion_model == "odometry":
        poses = _odometry_poses(controls)
        at_obs = poses[np.searchsorted(control_time, obs_time, side="right")]
    else:
        grid = np.union1d(control_time, obs_time)
        held = np.searchsorted(control_time, grid[:-1], side="right") - 1
        velocity, yaw_rate = body_rates(controls[np.maximum(held, 0)], motion_model, vehicle)
        moving = held >= 0
        poses = _euler_poses(np.diff(grid), velocity * moving[:, None], yaw_rate * moving)
        at_obs = poses[np.searchsorted(grid, obs_time)]
    previous = np.concatenate([poses[:1], at_obs[:-1]], axis=0)
    return odometry_between(previous, at_obs, min_translation)
