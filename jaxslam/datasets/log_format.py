"""The jaxslam robot log: a documented ``.npz`` layout and its validating loader and writer.

The layout is specified in ``docs/log_format.md``. Shapes (glossary in ``jaxslam.types``):
T steps (one per observation time), K padded observations per step, B beams per raw scan,
N landmarks, G GPS fixes, C control components, U command samples.

Everything here is host-side NumPy float64: logs are read once, then handed to the filter.
Controls recorded faster than the observations are turned into one move per step by
``jaxslam.datasets.odometry.integrate_controls``.
"""
from __future__ import annotations

import os
from typing import NamedTuple

import numpy as np

from jaxslam.types import MOTION_MODELS, Observations, make_observations

FORMAT_VERSION = 1
REQUIRED_KEYS = ("format_version", "time", "motion_model", "controls")
OPTIONAL_KEYS = ("obs_z", "obs_valid", "obs_radius", "scan_ranges", "scan_angles",
                 "truth_pose", "truth_landmarks", "gps_time", "gps_xy", "initial_pose",
                 "command_time", "commands")
EXTRA_PREFIX = "meta_"  # keys with this prefix are user metadata: kept out of RobotLog, ignored
# Pure-turn threshold [m] of moves rebuilt from a command stream: 1 mm, as the MRCLAM and
# Victoria Park loaders integrate theirs (a short commanded move still has a direction).
COMMAND_MIN_TRANSLATION = 1e-3


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
      command_time: (U,) seconds on the same clock as ``time``, strictly increasing: the
        stamps of the commanded velocities the controls were integrated from, or None.
      commands: (U, 2) commanded (v [m/s], omega [rad/s]), sample i held from
        command_time[i] to command_time[i + 1], or None. With them the log can be rebuilt
        with the commands acting later than stamped (``at_command_delay``), and the lag
        fitted (``jaxslam.fit_log_command_delay``).
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
    command_time: np.ndarray | None = None
    commands: np.ndarray | None = None

    @property
    def num_steps(self) -> int:
        """T, the number of filter steps."""
        return int(self.time.shape[0])

    def at_command_delay(self, delay: float,
                         min_translation: float = COMMAND_MIN_TRANSLATION) -> "RobotLog":
        """This log with the commands acting ``delay`` seconds later than stamped.

        controls become the odometry moves (motion_model "odometry") that
        ``datasets.integrate_controls`` integrates from ``commands``, sample i held from
        command_time[i] + delay to the next (the last one for ever; before the first the
        robot stands still), over this log's steps; moves shorter than ``min_translation``
        [m] are written as pure turns. The stored controls are replaced; the steps,
        observations, start and truth stay. At delay 0 that is the command stream
        integrated as stamped, which may differ from the stored controls if they were made
        another way (the MRCLAM loader's are made this way: they agree to the bit).

        Raises ``LogFormatError`` when the log has no command stream or ``delay`` is not a
        finite number of seconds.
        """
        from jaxslam.datasets.odometry import integrate_controls

        if self.command_time is None or self.commands is None:
            raise LogFormatError(
                "this log has no command stream ('command_time' and 'commands'): a command "
                "delay needs the commanded velocities the controls were integrated from "
                "(docs/log_format.md)")
        if not np.isfinite(delay):
            raise LogFormatError(f"command delay {delay!r}: expected a finite number of "
                                 "seconds")
        moves = integrate_controls(np.asarray(self.command_time, np.float64) + float(delay),
                                   self.commands, self.time, "velocity",
                                   min_translation=min_translation)
        return self._replace(controls=moves, motion_model="odometry")

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


def fail(source: str, message: str) -> None:
    """Raise ``LogFormatError`` with ``message`` prefixed by ``source`` (the file or caller)."""
    raise LogFormatError(f"{source}: {message}")


def check_shape(source, name, array, expected):
    """``expected`` is a tuple of ints or None (any size); names the mismatch."""
    ok = array.ndim == len(expected) and all(
        e is None or e == s for e, s in zip(expected, array.shape))
    if not ok:
        want = "(" + ", ".join("*" if e is None else str(e) for e in expected) + (
            ",)" if len(expected) == 1 else ")")
        fail(source, f"'{name}' has shape {array.shape}; expected {want}")


def check_finite(source, name, array, allow_posinf=False):
    bad = np.isnan(array) | (np.isneginf(array) if allow_posinf else ~np.isfinite(array))
    if bad.any():
        where = tuple(int(i) for i in np.argwhere(bad)[0])
        what = "NaN or -inf" if allow_posinf else "NaN or inf"
        fail(source, f"'{name}' contains {what} ({int(bad.sum())} entries, first at index "
                      f"{where}); expected finite values"
                      + (" (+inf marks no return)" if allow_posinf else ""))


def check_increasing(source, name, times):
    steps = np.diff(times)
    if (steps <= 0).any():
        i = int(np.argmax(steps <= 0))
        later, earlier = float(times[i + 1]), float(times[i])
        fail(source, f"'{name}' is not strictly increasing: {name}[{i + 1}]={later!r} <= "
                      f"{name}[{i}]={earlier!r}; expected sorted, distinct timestamps [s]")


def _as_float(source, name, value):
    """``value`` as float64; bool, complex, text and object arrays are refused by name (a
    bool or complex array would otherwise be cast silently: True -> 1.0, imaginary part lost)."""
    try:
        array = np.asarray(value)
    except (TypeError, ValueError) as error:  # e.g. a ragged list
        fail(source, f"'{name}' is not an array ({error}); expected a float array")
    if array.dtype.kind not in "fiu":
        fail(source, f"'{name}' is not numeric (dtype {array.dtype}); expected a float array "
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
        fail(source, f"'format_version' is {shown}(shape {array.shape}, dtype {array.dtype}); "
                      f"expected the integer scalar {FORMAT_VERSION}")
    version = int(array)
    if version != FORMAT_VERSION:
        fail(source, f"format_version {version} is not supported; expected {FORMAT_VERSION}")
    return version


def _check_pair(source, log, first, second):
    if (getattr(log, first) is None) != (getattr(log, second) is None):
        present, missing = (first, second) if getattr(log, first) is not None else (second, first)
        fail(source, f"'{present}' is present but '{missing}' is missing; "
                      "expected both or neither")


def _stamps(source, name, value, what: str) -> np.ndarray:
    """(N,) float64 time stamps [s]: one axis, at least one ``what``, finite, increasing."""
    stamps = _as_float(source, name, value)
    check_shape(source, name, stamps, (None,))
    if stamps.shape[0] < 1:
        fail(source, f"'{name}' is empty; expected at least one {what}")
    check_finite(source, name, stamps)
    check_increasing(source, name, stamps)
    return stamps


def _check_core(source: str, log: RobotLog) -> dict:
    fields = {}
    version = _check_version(source, log.format_version)
    model = str(np.asarray(log.motion_model))
    if model not in MOTION_MODELS:
        fail(source, f"unknown motion_model {model!r}; expected one of {list(MOTION_MODELS)}")
    time = _stamps(source, "time", log.time, "step")
    steps = time.shape[0]
    controls = _as_float(source, "controls", log.controls)
    check_shape(source, "controls", controls, (steps, 3))
    check_finite(source, "controls", controls)
    if model != "odometry" and (controls[:, 2] < 0).any():
        fail(source, f"'controls' column 2 (dt) is negative for motion_model {model!r}; "
                      "expected dt >= 0 [s]")
    fields.update(format_version=version, motion_model=model, time=time, controls=controls)
    return fields


def _check_observations(source: str, log: RobotLog, steps: int) -> dict:
    if log.obs_z is None:
        if log.obs_radius is not None:
            fail(source, "'obs_radius' is present without 'obs_z'; expected obs_z and obs_valid")
        return {}
    obs_z = _as_float(source, "obs_z", log.obs_z)
    check_shape(source, "obs_z", obs_z, (steps, None, 2))
    check_finite(source, "obs_z", obs_z)
    valid = np.asarray(log.obs_valid)
    if valid.dtype != np.bool_:
        fail(source, f"'obs_valid' has dtype {valid.dtype}; expected bool")
    check_shape(source, "obs_valid", valid, obs_z.shape[:2])
    negative = valid & (obs_z[..., 0] < 0)
    if negative.any():
        t, k = (int(i) for i in np.argwhere(negative)[0])
        fail(source, f"'obs_z' has a negative range {float(obs_z[t, k, 0])!r} at valid "
                      f"observation (t={t}, k={k}); expected range >= 0 [m]")
    fields = dict(obs_z=obs_z, obs_valid=valid)
    if log.obs_radius is not None:
        radius = _as_float(source, "obs_radius", log.obs_radius)
        check_shape(source, "obs_radius", radius, obs_z.shape[:2])
        check_finite(source, "obs_radius", radius)
        if (radius < 0).any():
            t, k = (int(i) for i in np.argwhere(radius < 0)[0])
            fail(source, f"'obs_radius' has a negative radius {float(radius[t, k])!r} at "
                          f"(t={t}, k={k}); expected radius >= 0 [m] (0 = unknown)")
        fields["obs_radius"] = radius
    return fields


def _check_scans(source: str, log: RobotLog, steps: int) -> dict:
    if log.scan_ranges is None:
        return {}
    angles = _as_float(source, "scan_angles", log.scan_angles)
    check_shape(source, "scan_angles", angles, (None,))
    check_finite(source, "scan_angles", angles)
    ranges = _as_float(source, "scan_ranges", log.scan_ranges)
    check_shape(source, "scan_ranges", ranges, (steps, angles.shape[0]))
    check_finite(source, "scan_ranges", ranges, allow_posinf=True)
    if (ranges < 0).any():
        t, b = (int(i) for i in np.argwhere(ranges < 0)[0])
        fail(source, f"'scan_ranges' has a negative range {float(ranges[t, b])!r} at (t={t}, "
                      f"beam={b}); expected range >= 0 [m] or +inf for no return")
    return dict(scan_ranges=ranges, scan_angles=angles)


def _check_truth_and_gps(source: str, log: RobotLog, steps: int) -> dict:
    fields = {}
    for name, expected in (("truth_pose", (steps, 3)), ("truth_landmarks", (None, 2)),
                           ("initial_pose", (3,))):
        if getattr(log, name) is not None:
            array = _as_float(source, name, getattr(log, name))
            check_shape(source, name, array, expected)
            check_finite(source, name, array)
            fields[name] = array
    if log.gps_time is not None:
        gps_time = _as_float(source, "gps_time", log.gps_time)
        check_shape(source, "gps_time", gps_time, (None,))
        check_finite(source, "gps_time", gps_time)
        check_increasing(source, "gps_time", gps_time)
        gps_xy = _as_float(source, "gps_xy", log.gps_xy)
        check_shape(source, "gps_xy", gps_xy, (gps_time.shape[0], 2))
        check_finite(source, "gps_xy", gps_xy)
        fields.update(gps_time=gps_time, gps_xy=gps_xy)
    return fields


def _check_commands(source: str, log: RobotLog) -> dict:
    if log.command_time is None:
        return {}
    command_time = _stamps(source, "command_time", log.command_time, "command")
    commands = _as_float(source, "commands", log.commands)
    check_shape(source, "commands", commands, (command_time.shape[0], 2))
    check_finite(source, "commands", commands)
    return dict(command_time=command_time, commands=commands)


def validate_log(log: RobotLog, source: str = "<RobotLog>") -> RobotLog:
    """Check ``log`` against ``docs/log_format.md``; return it with canonical dtypes.

    Raises:
      LogFormatError: naming ``source``, the offending array and what is expected.
    """
    for first, second in (("obs_z", "obs_valid"), ("scan_ranges", "scan_angles"),
                          ("gps_time", "gps_xy"), ("command_time", "commands")):
        _check_pair(source, log, first, second)
    if log.obs_z is None and log.scan_ranges is None:
        fail(source, "no observations: expected 'obs_z' + 'obs_valid' (range-bearing) or "
                      "'scan_ranges' + 'scan_angles' (raw 2D scans)")
    fields = _check_core(source, log)
    steps = fields["time"].shape[0]
    fields.update(_check_observations(source, log, steps))
    fields.update(_check_scans(source, log, steps))
    fields.update(_check_truth_and_gps(source, log, steps))
    fields.update(_check_commands(source, log))
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
        fail(source, f"no such file; {_EXPECTED_FILE}")
    if os.path.isdir(source):
        fail(source, f"is a directory, not a file; {_EXPECTED_FILE}")
    try:
        with open(source, "rb") as handle:
            magic = handle.read(6)
    except OSError as error:
        raise LogFormatError(f"{source}: cannot open ({error}); {_EXPECTED_FILE}") from error
    if not magic:
        fail(source, f"the file is empty (0 bytes); {_EXPECTED_FILE}")
    if magic.startswith(b"\x93NUMPY"):
        fail(source, "cannot read as a .npz archive: it is a single .npy array (numpy.save), "
                      f"not an archive of named arrays; {_EXPECTED_FILE}")
    if not magic.startswith(b"PK"):
        fail(source, f"cannot read as a .npz archive: it is not a zip file (starts with "
                      f"{magic!r}; a .npz starts with b'PK'); {_EXPECTED_FILE}")
    try:
        loaded = np.load(source, allow_pickle=False)
    except Exception as error:  # noqa: BLE001 - any failure to parse means "not a .npz"
        raise LogFormatError(f"{source}: cannot read as a .npz archive, it is truncated or "
                             f"corrupt ({type(error).__name__}: {error}); "
                             f"{_EXPECTED_FILE}") from error
    if not isinstance(loaded, np.lib.npyio.NpzFile):  # the magic said zip; be safe anyway
        fail(source, f"cannot read as a .npz archive (got a {type(loaded).__name__}); "
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
                fail(source, f"cannot read as a .npz archive: member '{name}' of the zip is "
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
        fail(source, f"missing required key(s) {missing}; expected {list(REQUIRED_KEYS)}")
    unknown = sorted(name for name in arrays
                     if name not in REQUIRED_KEYS + OPTIONAL_KEYS
                     and not name.startswith(EXTRA_PREFIX))
    if unknown:
        fail(source, f"unknown key(s) {unknown}; expected keys among "
                      f"{list(REQUIRED_KEYS + OPTIONAL_KEYS)} (prefix your own with "
                      f"'{EXTRA_PREFIX}')")
    fields = {name: value for name, value in arrays.items() if name in RobotLog._fields}
    if fields["motion_model"].dtype.kind != "U" or fields["motion_model"].ndim != 0:
        fail(source, f"'motion_model' is {fields['motion_model']!r}; expected a string scalar "
                      f"among {list(MOTION_MODELS)}")
    fields["motion_model"] = str(fields["motion_model"])
    return validate_log(RobotLog(**fields), source=source)
