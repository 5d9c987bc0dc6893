"""The Sydney Victoria Park dataset (Guivant and Nebot, 2001): raw files -> aligned NumPy arrays.

Files (read in place, never copied; described in the dataset's own README):
  victoria_park_ascii.zip/LASER.txt  S = 7230 scans: time [s] then B = 361 ranges over
                                     0..180 degrees (no line terminators: 362 floats a scan)
  aa3_dr.mat                         D = 61945 dead-reckoning samples at 40 Hz: time [ms],
                                     speed [m/s] (rear-left wheel), steering [rad]
  aa3_gpsx.mat                       G = 4466 GPS fixes: timeGps [ms], Lo_m, La_m [m]

Time base: everything is returned on the ascii clock, seconds = milliseconds / 1000 - 20.967.
Laser frame -> robot frame: bearing = beam angle - pi/2 (x forward, y left). A range of
81.91 m is "no return" and becomes +inf. GPS positions are (x, y) = (Lo_m, La_m) in metres:
that order is the one whose handedness agrees with the dead reckoning (the ascii GPS.txt
stores them swapped, a mirror image).
"""
from __future__ import annotations

import hashlib
import os
import zipfile
from pathlib import Path
from typing import NamedTuple

import numpy as np

from jaxslam.host import in_float64
from jaxslam.datasets.log_format import RobotLog
from jaxslam.datasets.odometry import VICTORIA_PARK_VEHICLE, integrate_controls, odometry_path
from jaxslam.metrics import align_se2, transform_points

ENV_DATA_DIR = "JAXSLAM_VICTORIA_PARK"
ENV_CACHE_DIR = "JAXSLAM_CACHE_DIR"
ZIP_NAME = "victoria_park_ascii.zip"
DR_NAME = "aa3_dr.mat"
GPS_NAME = "aa3_gpsx.mat"
MAT_CLOCK_OFFSET_S = 20.967  # ascii seconds = mat ms / 1000 - 20.967 (README "Time bases")
NO_RETURN_RANGE = 81.91
NUM_BEAMS = 361
CACHE_VERSION = 1


class VictoriaPark(NamedTuple):
    """The raw Victoria Park run on one clock (ascii seconds). All float64 NumPy.

    Attributes:
      laser_time: (S,) scan times [s], S = 7230.
      laser_ranges: (S, B) ranges [m], B = 361; +inf where the laser saw nothing (81.91 m).
      laser_angles: (B,) beam bearings [rad] in the robot frame, -pi/2 .. pi/2 in 0.5 deg steps.
      dr_time: (D,) dead-reckoning times [s] (``aa3_dr.mat``), D = 61945, 40 Hz.
      dr_speed: (D,) rear-left wheel speed v [m/s].
      dr_steering: (D,) steering angle alpha [rad].
      gps_time: (G,) GPS fix times [s], G = 4466 (all fixes, outliers included).
      gps_xy: (G, 2) GPS (Lo_m, La_m) [m], local metric frame.
    """

    laser_time: np.ndarray
    laser_ranges: np.ndarray
    laser_angles: np.ndarray
    dr_time: np.ndarray
    dr_speed: np.ndarray
    dr_steering: np.ndarray
    gps_time: np.ndarray
    gps_xy: np.ndarray


def default_victoria_park_dir() -> Path:
    """``$JAXSLAM_VICTORIA_PARK`` if set, else ``<repo root>/../shared/data/victoria_park``.

    The path is returned whether or not it exists (tests skip on a missing folder).
    """
    if os.environ.get(ENV_DATA_DIR):
        return Path(os.environ[ENV_DATA_DIR])
    repo_root = Path(__file__).resolve().parents[2]
    return repo_root.parent / "shared" / "data" / "victoria_park"


def default_cache_dir() -> Path:
    """``$JAXSLAM_CACHE_DIR``, else ``$XDG_CACHE_HOME/jaxslam``, else ``~/.cache/jaxslam``."""
    if os.environ.get(ENV_CACHE_DIR):
        return Path(os.environ[ENV_CACHE_DIR])
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "jaxslam"


def mat_ms_to_seconds(milliseconds):
    """The .mat clock [ms] on the ascii clock [s]: ms / 1000 - 20.967."""
    return np.asarray(milliseconds, np.float64) / 1000.0 - MAT_CLOCK_OFFSET_S


def laser_angles() -> np.ndarray:
    """(B,) = (361,) beam bearings [rad] in the robot frame: 0..180 deg in 0.5 deg, minus pi/2."""
    return np.deg2rad(np.arange(NUM_BEAMS) * 0.5) - np.pi / 2


def _read_zip_member(archive: Path, name: str) -> bytes:
    with zipfile.ZipFile(archive) as zipped:
        members = [m for m in zipped.namelist() if Path(m).name == name]
        if not members:
            raise ValueError(f"{archive}: no member {name!r}; found {zipped.namelist()}")
        return zipped.read(members[0])


def parse_laser(archive: Path):
    """LASER.txt -> (laser_time (S,), laser_ranges (S, B) with +inf for no return)."""
    values = np.array(_read_zip_member(archive, "LASER.txt").split(), dtype=np.float64)
    if values.size % (NUM_BEAMS + 1):
        raise ValueError(f"{archive}/LASER.txt holds {values.size} numbers; expected a "
                         f"multiple of {NUM_BEAMS + 1} (time + {NUM_BEAMS} ranges per scan)")
    table = values.reshape(-1, NUM_BEAMS + 1)
    ranges = table[:, 1:]
    # The no-return code is written as 81.91 exactly; anything at or past it is no return.
    return table[:, 0], np.where(ranges >= NO_RETURN_RANGE - 1e-6, np.inf, ranges)


def _load_mat(path: Path, keys: tuple[str, ...]) -> dict:
    import scipy.io  # scipy is a dependency; imported here to keep `import jaxslam` light

    contents = scipy.io.loadmat(path)
    missing = [key for key in keys if key not in contents]
    if missing:
        raise ValueError(f"{path}: missing variable(s) {missing}; expected {list(keys)}")
    return {key: np.asarray(contents[key], np.float64).ravel() for key in keys}


def parse_victoria_park(path) -> VictoriaPark:
    """Parse the three raw files in folder ``path`` (no cache): about 1 s."""
    path = Path(path)
    laser_time, laser_ranges = parse_laser(path / ZIP_NAME)
    dead_reckoning = _load_mat(path / DR_NAME, ("time", "speed", "steering"))
    gps = _load_mat(path / GPS_NAME, ("timeGps", "Lo_m", "La_m"))
    return VictoriaPark(
        laser_time=laser_time, laser_ranges=laser_ranges, laser_angles=laser_angles(),
        dr_time=mat_ms_to_seconds(dead_reckoning["time"]), dr_speed=dead_reckoning["speed"],
        dr_steering=dead_reckoning["steering"], gps_time=mat_ms_to_seconds(gps["timeGps"]),
        gps_xy=np.stack([gps["Lo_m"], gps["La_m"]], axis=-1))


def _cache_path(path: Path, cache_dir: Path) -> Path:
    """One cache file per (parser version, raw files' resolved path, size and mtime)."""
    key = [str(CACHE_VERSION)]
    for name in (ZIP_NAME, DR_NAME, GPS_NAME):
        info = (path / name).stat()
        key.append(f"{(path / name).resolve()}:{info.st_size}:{info.st_mtime_ns}")
    digest = hashlib.sha256("|".join(key).encode()).hexdigest()[:16]
    return cache_dir / f"victoria_park_{digest}.npz"


def _write_cache(cache_file: Path, data: VictoriaPark) -> None:
    """Atomic write (temporary file + rename) so parallel loaders never read half a file."""
    try:
        cache_file.parent.mkdir(parents=True, exist_ok=True)
        temporary = cache_file.with_name(f"{cache_file.name}.{os.getpid()}.tmp")
        with open(temporary, "wb") as handle:
            np.savez(handle, **data._asdict())
        os.replace(temporary, cache_file)
    except OSError:
        pass  # an unwritable cache only costs speed


def load_victoria_park(path=None, cache_dir=None, use_cache: bool = True) -> VictoriaPark:
    """Load Victoria Park from folder ``path`` (default ``default_victoria_park_dir()``).

    The parsed arrays are cached as one .npz in ``cache_dir`` (default ``default_cache_dir()``),
    keyed by the raw files' path, size and mtime: about 1 s to parse, about 0.1 s from cache.

    Raises:
      FileNotFoundError: a raw file is missing, naming the folder and the expected files.
    """
    path = default_victoria_park_dir() if path is None else Path(path)
    missing = [name for name in (ZIP_NAME, DR_NAME, GPS_NAME) if not (path / name).is_file()]
    if missing:
        raise FileNotFoundError(
            f"Victoria Park data not found in {path}: missing {missing}; expected "
            f"{[ZIP_NAME, DR_NAME, GPS_NAME]} (set ${ENV_DATA_DIR} to the folder)")
    if not use_cache:
        return parse_victoria_park(path)
    cache_file = _cache_path(path, default_cache_dir() if cache_dir is None else Path(cache_dir))
    if cache_file.is_file():
        try:
            with np.load(cache_file, allow_pickle=False) as cached:
                return VictoriaPark(**{name: cached[name] for name in VictoriaPark._fields})
        except (OSError, ValueError, KeyError):
            pass  # a stale or damaged cache is rebuilt below
    data = parse_victoria_park(path)
    _write_cache(cache_file, data)
    return data


# ----------------------------------------------------------------------------------------------
# GPS outliers, dead reckoning, and the filter log


def _implied_speeds(time, xy, keep):
    """Speeds [m/s] from each kept fix to the previous / next kept fix: (G,), (G,); inf at ends."""
    index = np.flatnonzero(keep)
    speed = np.linalg.norm(np.diff(xy[index], axis=0), axis=-1) / np.diff(time[index])
    before, after = np.full(time.shape, np.inf), np.full(time.shape, np.inf)
    before[index[1:]], after[index[:-1]] = speed, speed
    return before, after


def filter_gps(time, xy, max_speed: float = 10.0, jump_margin: float = 1.0,
               passes: int = 3) -> np.ndarray:
    """Mask (G,) of trustworthy GPS fixes.

    Spikes: a fix whose implied speed to BOTH neighbouring kept fixes exceeds ``max_speed``
    [m/s] is rejected; ``passes`` rounds, so a spike hidden behind another is found too.
    Jumps: where consecutive kept fixes imply more than ``max_speed``, one side is offset and
    we cannot tell which, so every fix within ``jump_margin`` seconds of either end of the
    jump is rejected.
    The vehicle never exceeds 6.7 m/s, so 10 m/s leaves room for GPS noise at 5 Hz.

    Args:
      time: (G,) seconds, strictly increasing.  xy: (G, 2) metres.
    """
    time, xy = np.asarray(time, np.float64), np.asarray(xy, np.float64)
    keep = np.ones(time.shape, bool)
    for _ in range(passes):  # a few whole-array passes, not a loop over fixes
        before, after = _implied_speeds(time, xy, keep)
        keep &= ~((before > max_speed) & (after > max_speed))
    index = np.flatnonzero(keep)
    jump = np.linalg.norm(np.diff(xy[index], axis=0), axis=-1) > max_speed * np.diff(time[index])
    jump_ends = np.sort(np.concatenate([time[index[:-1]][jump], time[index[1:]][jump]]))
    if jump_ends.size:
        nearest = np.searchsorted(jump_ends, time)
        gap_left = np.abs(time - jump_ends[np.maximum(nearest - 1, 0)])
        gap_right = np.abs(jump_ends[np.minimum(nearest, jump_ends.size - 1)] - time)
        keep &= np.minimum(gap_left, gap_right) > jump_margin
    return keep


# Pure-turn threshold for splitting the integrated dead-reckoning moves into (rot1, trans,
# rot2): 1 mm, not the filter's 1 cm default (these moves are integrated, not jittering poses;
# docs/results.md, section victoria_park, records the measured effect).
VP_MIN_TRANSLATION = 1e-3


def dead_reckoning_controls(data: VictoriaPark) -> np.ndarray:
    """(S, 3) odometry moves between laser times from the Ackermann dead reckoning."""
    return integrate_controls(data.dr_time, np.stack([data.dr_speed, data.dr_steering], -1),
                              data.laser_time, "ackermann", VICTORIA_PARK_VEHICLE,
                              min_translation=VP_MIN_TRANSLATION)


def dead_reckoning_path(data: VictoriaPark) -> np.ndarray:
    """(S, 3) dead-reckoned laser poses at the laser times, starting at the zero pose."""
    return odometry_path(dead_reckoning_controls(data))


def victoria_park_log(data: VictoriaPark, max_range: float = 75.0,
                      gps_filter: bool = True) -> RobotLog:
    """The run as a ``RobotLog``: one filter step per laser scan.

    Controls are odometry moves integrated from the 40 Hz Ackermann dead reckoning between
    laser times (row 0, before the first dead-reckoning sample, is zero). Beams at or beyond
    ``max_range`` [m] become +inf (no return; the classic detector uses 75 m). GPS fixes are
    those kept by ``filter_gps`` when ``gps_filter``. Observations are left to trunk detection.
    """
    ranges = np.where(data.laser_ranges >= max_range, np.inf, data.laser_ranges)
    keep = (filter_gps(data.gps_time, data.gps_xy) if gps_filter
            else np.ones(data.gps_time.shape, bool))
    return RobotLog(time=data.laser_time, motion_model="odometry",
                    controls=dead_reckoning_controls(data), scan_ranges=ranges,
                    scan_angles=data.laser_angles, gps_time=data.gps_time[keep],
                    gps_xy=data.gps_xy[keep], initial_pose=np.zeros(3))


class GpsError(NamedTuple):
    """Position error of a path against GPS after a rigid SE(2) fit (no scale,
    ``jaxslam.metrics.align_se2``).

    Attributes:
      mean / rmse / median / max: error statistics [m] over the G' GPS fixes used.
      rotation: () angle [rad] and translation: (2,) [m] of the fit, path -> GPS frame.
      aligned_xy: (G', 2) the path at the GPS times in the GPS frame.  gps_xy: (G', 2) the fixes.
    """

    mean: float
    rmse: float
    median: float
    max: float
    rotation: float
    translation: np.ndarray
    aligned_xy: np.ndarray
    gps_xy: np.ndarray


def rigid_transform_2d(points, angle, translation):
    """R(angle) p + translation for points (..., 2): rotation [rad], translation (2,).

    ``jaxslam.metrics.transform_points`` in float64, the alignment given as angle and shift.
    """
    alignment = np.append(np.broadcast_to(np.asarray(translation, np.float64), (2,)), angle)
    return in_float64(transform_points, alignment, points)


def gps_error(path_time, path_xy, gps_time, gps_xy, fit_until: float | None = None) -> GpsError:
    """Compare a path (T,), (T, 2) with GPS fixes (G,), (G, 2) inside the path's time span.

    The path is linearly interpolated at the GPS times. The rigid fit uses the fixes up to
    ``fit_until`` seconds (None: all of them; a short prefix mimics "aligned at the start").
    """
    inside = (gps_time >= path_time[0]) & (gps_time <= path_time[-1])
    times, targets = gps_time[inside], gps_xy[inside]
    at_gps = np.stack([np.interp(times, path_time, path_xy[:, i]) for i in range(2)], -1)
    fit = np.ones(times.shape, bool) if fit_until is None else times <= fit_until
    alignment = in_float64(align_se2, at_gps[fit], targets[fit])  # (x, y, angle)
    aligned = in_float64(transform_points, alignment, at_gps)
    angle, translation = float(alignment[2]), alignment[:2]
    error = np.linalg.norm(aligned - targets, axis=-1)
    return GpsError(mean=float(error.mean()), rmse=float(np.sqrt(np.mean(error ** 2))),
                    median=float(np.median(error)), max=float(error.max()), rotation=angle,
                    translation=translation, aligned_xy=aligned, gps_xy=targets)
