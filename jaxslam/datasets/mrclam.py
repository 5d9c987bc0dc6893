"""The UTIAS MRCLAM dataset 1 (resampled at 50 Hz): raw files -> a ``RobotLog`` per robot.

Dataset: K. Y. K. Leung, Y. Halpern, T. D. Barfoot and H. H. T. Liu, "The UTIAS Multi-Robot
Cooperative Localization and Mapping Dataset", International Journal of Robotics Research
30(8), 2011, pp. 969-974. Five iRobot Create robots, 15 landmark tubes with barcodes, about
1,500 s, Vicon ground truth for everything (the dataset's own README describes its files).

Files (read in place; whitespace separated; ``#`` lines are comments; robot files have no
header). N is the robot number 1..5:

  RobotN_Odometry.dat       O rows: time [s], v [m/s], omega [rad/s]; commanded, 50 Hz
  RobotN_Measurement.dat    M rows: time [s], barcode, range [m], bearing [rad] (robot frame,
                            counter-clockwise)
  RobotN_Groundtruth.dat    G rows: time [s], x [m], y [m], theta [rad]; Vicon, 50 Hz
  Landmark_Groundtruth.dat  15 rows: subject, x [m], y [m], x std [m], y std [m]
  Barcodes.dat              20 rows: subject, barcode; subjects 1-5 are robots, 6-20 landmarks

Time stamps. This copy prints times with 5 significant digits, so after 1000 s they are rounded
to 0.1 s and five consecutive 50 Hz rows share one time. With ``rate_hz`` (default 50) the
odometry and ground-truth rows are put back on their grid, row i at ``t_0 + i / rate_hz``,
after checking that every printed time agrees with it to its printed precision (a file that
does not is an error; ``rate_hz=None`` takes the printed times, which must then increase).
Measurement times keep their printed value (up to 0.05 s off after 1000 s; measurements that
print the same time become one step).

Measurement grouping into filter steps, the odometry moves and the ground truth of the log are
``jaxslam.datasets.mrclam_convert``'s.

Shapes of the returned log (``load_mrclam``): T steps, K = ``max_obs``, N = 15 landmarks.
  time (T,), controls (T, 3) odometry moves, obs_z (T, K, 2) (range [m], bearing [rad]),
  obs_valid (T, K) bool, truth_pose (T, 3), truth_landmarks (N, 2), initial_pose (3,).
Robot 1 with the defaults: T = 3,809 steps (3,349 with observations, 460 fillers), 4,771
observations (952 robot sightings removed, none truncated).

Everything here is host-side NumPy float64, in small pure functions.
"""
from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import numpy as np

from jaxslam.datasets.log_format import LogFormatError, RobotLog
from jaxslam.datasets.mrclam_convert import (
    DEFAULT_MAX_GAP,
    DEFAULT_MAX_OBS,
    MRCLAM_MIN_TRANSLATION,
    ROBOT_SUBJECTS,
    TIME_SLACK,
    mrclam_log,
    mrclam_steps,
)

NUM_ROBOTS = len(ROBOT_SUBJECTS)
RATE_HZ = 50.0
PRINTED_DIGITS = 5  # significant digits of the times in this copy's files
BARCODES_NAME = "Barcodes.dat"
LANDMARKS_NAME = "Landmark_Groundtruth.dat"


class MrclamFileError(LogFormatError, FileNotFoundError):
    """A missing MRCLAM folder or file: both a ``LogFormatError`` and a ``FileNotFoundError``."""


class MrclamRun(NamedTuple):
    """One robot's raw files, parsed (float64 unless noted; times in seconds).

    Attributes:
      robot: the robot number, 1..5.
      odometry_time: (O,) strictly increasing.  odometry: (O, 2) commanded (v [m/s], omega
        [rad/s]).
      measurement_time: (M,) non-decreasing (file order kept among equal times).
      measurement_barcode: (M,) int64 barcode numbers.
      measurement_z: (M, 2) range [m], bearing [rad].
      truth_time: (G,) strictly increasing.  truth_pose: (G, 3) Vicon (x, y, theta).
      landmark_subject: (N,) int64 subjects, ascending.  landmark_xy: (N, 2) Vicon positions.
      barcode_subject: (S,) int64 and barcode: (S,) int64, the Barcodes.dat table.
    """

    robot: int
    odometry_time: np.ndarray
    odometry: np.ndarray
    measurement_time: np.ndarray
    measurement_barcode: np.ndarray
    measurement_z: np.ndarray
    truth_time: np.ndarray
    truth_pose: np.ndarray
    landmark_subject: np.ndarray
    landmark_xy: np.ndarray
    barcode_subject: np.ndarray
    barcode: np.ndarray



# ----------------------------------------------------------------------------------------------
# Raw files


def robot_file_names(robot: int) -> tuple[str, str, str]:
    """(odometry, measurement, ground-truth) file names of robot 1..5."""
    return (f"Robot{robot}_Odometry.dat", f"Robot{robot}_Measurement.dat",
            f"Robot{robot}_Groundtruth.dat")


def check_robot(robot) -> int:
    """``robot`` as an int in 1..5, else ValueError."""
    if (isinstance(robot, bool) or not isinstance(robot, (int, np.integer))
            or not 1 <= robot <= NUM_ROBOTS):
        raise ValueError(f"robot={robot!r} is not an MRCLAM robot; expected an integer in "
                         f"1..{NUM_ROBOTS}")
    return int(robot)


def parse_table(text: str, source: str, columns: tuple[str, ...]) -> np.ndarray:
    """A whitespace-separated numeric table -> (R, len(columns)) float64.

    Blank lines and lines starting with ``#`` are skipped. Raises ``LogFormatError`` naming
    ``source`` and the line for a row with the wrong number of fields, a non-numeric field or
    a NaN / inf, and for a table without rows.
    """
    expected = f"{len(columns)} numbers ({', '.join(columns)})"
    numbered = [(number, line.split()) for number, line in enumerate(text.splitlines(), 1)
                if line.strip() and not line.lstrip().startswith("#")]
    for number, fields in numbered:
        if len(fields) != len(columns):
            raise LogFormatError(f"{source}, line {number}: {len(fields)} field(s) "
                                 f"{' '.join(fields)!r}; expected {expected}")
    try:
        values = np.array([field for _, fields in numbered for field in fields], np.float64)
    except ValueError:
        for number, fields in numbered:
            try:
                [float(field) for field in fields]
            except ValueError:
                raise LogFormatError(f"{source}, line {number}: non-numeric field in "
                                     f"{' '.join(fields)!r}; expected {expected}") from None
        raise
    table = values.reshape(len(numbered), len(columns))
    if not table.size:
        raise LogFormatError(f"{source}: no data rows; expected rows of {expected}")
    bad = ~np.isfinite(table)
    if bad.any():
        row = int(np.argwhere(bad)[0, 0])
        raise LogFormatError(f"{source}, line {numbered[row][0]}: NaN or inf in "
                             f"{' '.join(numbered[row][1])!r}; expected finite {expected}")
    return table


def _read_table(path: Path, columns: tuple[str, ...]) -> np.ndarray:
    if not path.is_file():
        raise MrclamFileError(f"{path}: file not found; expected an MRCLAM table of "
                              f"{len(columns)} columns ({', '.join(columns)})")
    return parse_table(path.read_text(), str(path), columns)


def _as_integers(values, source: str, name: str) -> np.ndarray:
    """A float column that must hold integers -> int64, else LogFormatError."""
    rounded = np.round(values)
    if (rounded != values).any():
        row = int(np.argmax(rounded != values))
        raise LogFormatError(f"{source}: {name} {float(values[row])!r} in data row {row + 1} "
                             f"is not an integer; expected integer {name}s")
    return rounded.astype(np.int64)


def print_tolerance(time, digits: int = PRINTED_DIGITS):
    """Half a unit of the last of ``digits`` significant digits of |time| (>= 1 s): (...,)."""
    magnitude = np.floor(np.log10(np.maximum(np.abs(time), 1.0)))
    return 0.5 * 10.0 ** (magnitude - (digits - 1)) + TIME_SLACK


def regular_times(printed, rate_hz: float | None, source: str) -> np.ndarray:
    """Row times (R,) of a regularly sampled file from its printed times (R,).

    With ``rate_hz``: ``printed[0] + i / rate_hz`` for row i, checked against the printed
    times to their precision (``print_tolerance``). With None: the printed times, which must
    be strictly increasing. Raises ``LogFormatError`` otherwise.
    """
    printed = np.asarray(printed, np.float64)
    if rate_hz is None:
        steps = np.diff(printed)
        if (steps <= 0).any():
            row = int(np.argmax(steps <= 0)) + 1
            raise LogFormatError(f"{source}: time {printed[row]!r} in data row {row + 1} does "
                                 f"not increase; expected strictly increasing times (or pass "
                                 f"rate_hz for files sampled at a fixed rate)")
        return printed
    grid = printed[0] + np.arange(printed.shape[0]) / rate_hz
    off = np.abs(printed - grid) > print_tolerance(grid)
    if off.any():
        row = int(np.argmax(off))
        raise LogFormatError(f"{source}: time {printed[row]!r} in data row {row + 1} is off "
                             f"the {rate_hz:g} Hz grid ({grid[row]!r} expected); expected one "
                             f"row every 1/{rate_hz:g} s (pass rate_hz=None to use the "
                             f"printed times)")
    return grid


def read_mrclam(root, robot: int = 1, rate_hz: float | None = RATE_HZ) -> MrclamRun:
    """Parse robot ``robot``'s three files and the two shared tables in folder ``root``.

    Raises:
      ValueError: ``robot`` is not 1..5.
      MrclamFileError: the folder or a file is missing (names the expected files).
      LogFormatError: a malformed row (names the file and line), a negative range, a
        non-integer barcode or subject, a duplicated barcode or landmark, or off-grid times.
    """
    robot = check_robot(robot)
    root = Path(root)
    names = robot_file_names(robot) + (LANDMARKS_NAME, BARCODES_NAME)
    if not root.is_dir():
        raise MrclamFileError(f"{root}: MRCLAM folder not found; expected a folder holding "
                              f"{list(names)}")
    odometry = _read_table(root / names[0], ("time", "v", "omega"))
    measured = _read_table(root / names[1], ("time", "barcode", "range", "bearing"))
    truth = _read_table(root / names[2], ("time", "x", "y", "theta"))
    landmarks = _read_table(root / names[3], ("subject", "x", "y", "x std", "y std"))
    barcodes = _read_table(root / names[4], ("subject", "barcode"))
    if (measured[:, 2] < 0).any():
        row = int(np.argmax(measured[:, 2] < 0))
        raise LogFormatError(f"{root / names[1]}: negative range {measured[row, 2]!r} in data "
                             f"row {row + 1}; expected range >= 0 [m]")
    order = np.argsort(measured[:, 0], kind="stable")
    subject = _as_integers(landmarks[:, 0], str(root / names[3]), "subject")
    barcode_table = _as_integers(barcodes, str(root / names[4]), "subject/barcode")
    for values, name, path in ((subject, "subject", names[3]),
                               (barcode_table[:, 1], "barcode", names[4])):
        unique, counts = np.unique(values, return_counts=True)
        if (counts > 1).any():
            raise LogFormatError(f"{root / path}: {name} {int(unique[counts > 1][0])} is "
                                 f"listed more than once; expected each {name} once")
    by_subject = np.argsort(subject, kind="stable")
    return MrclamRun(
        robot=robot,
        odometry_time=regular_times(odometry[:, 0], rate_hz, str(root / names[0])),
        odometry=odometry[:, 1:],
        measurement_time=measured[order, 0],
        measurement_barcode=_as_integers(measured[order, 1], str(root / names[1]), "barcode"),
        measurement_z=measured[order][:, 2:],
        truth_time=regular_times(truth[:, 0], rate_hz, str(root / names[2])),
        truth_pose=truth[:, 1:],
        landmark_subject=subject[by_subject], landmark_xy=landmarks[by_subject, 1:3],
        barcode_subject=barcode_table[:, 0], barcode=barcode_table[:, 1])



def load_mrclam(root, robot: int = 1, max_obs: int = DEFAULT_MAX_OBS,
                step_dt: float | None = None, max_gap: float | None = DEFAULT_MAX_GAP,
                rate_hz: float | None = RATE_HZ,
                min_translation: float = MRCLAM_MIN_TRANSLATION,
                command_delay: float = 0.0) -> RobotLog:
    """Robot ``robot`` of the MRCLAM folder ``root`` as a validated ``RobotLog``.

    Args:
      root: the folder with RobotN_*.dat, Landmark_Groundtruth.dat and Barcodes.dat.
      robot: 1..5.
      max_obs: K, padded observations per step; more in one step are dropped (counted in
        ``mrclam_steps(...).num_truncated``).
      step_dt: None for one step per distinct measurement time, else the bin width [s].
      max_gap: the longest time [s] between steps; longer gaps get empty steps. None: no limit.
      rate_hz: the odometry / ground-truth sampling rate used to rebuild their times; None
        takes the printed times.
      min_translation: pure-turn threshold of the integrated moves (``odometry_between``).
      command_delay: [s] the commands take effect this much later than stamped (``mrclam_log``;
        fitted from the log by ``jaxslam.command_delay.fit_log_command_delay``).
    Returns:
      RobotLog with time (T,), controls (T, 3) odometry, obs_z (T, K, 2), obs_valid (T, K),
      truth_pose (T, 3), truth_landmarks (15, 2), initial_pose (3,) (Vicon at the start).
    Raises:
      ValueError: robot not in 1..5, or max_obs / step_dt / max_gap not positive.
      MrclamFileError: the folder or a file is missing.
      LogFormatError: a malformed file (names file and line) or no landmark measurement.
    """
    run = read_mrclam(root, robot, rate_hz)
    return mrclam_log(run, mrclam_steps(run, max_obs, step_dt, max_gap), min_translation,
                      command_delay)
