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

Measurements. Barcodes are dropped (unknown data association): rows whose barcode belongs to a
robot (subjects 1-5, sightings of the other robots) are removed, and so are rows whose barcode
is in no table (dataset 1 has 3 reads of barcode 43, which no subject carries). The rest
keep only (range, bearing). The true landmark of each kept observation is returned separately
(``MrclamSteps.obs_landmark``, an index into ``truth_landmarks``) for scoring or for known
association; ``RobotLog`` has no field for it.

Steps (``mrclam_step_times``). With ``step_dt=None`` (default) there is one filter step per
distinct measurement time (readings that share a time stamp are taken as one camera image).
With ``step_dt`` the run is cut into bins (start + (b-1) step_dt, start + b step_dt],
b = 1..B, and every bin is a step at its end time, empty or not; the last bin holds the last
measurement. In both cases the start is the first odometry time. Where steps (or the
start and the first step) are more than ``max_gap`` seconds apart (robot 4 drives up to 78 s
without reading a landmark), the gap is cut into equal parts of at most ``max_gap`` by steps
without observations, so that no single odometry move spans a long curved stretch (the
odometry noise model is meant for short moves). Observations are assigned to the first step at
or after their time, in time order (file order among equal times); past ``max_obs`` per step
the later ones are dropped and counted.

Controls. The commanded (v, omega) are integrated with ``integrate_controls(...,
"velocity")`` (unicycle kinematics, explicit Euler on the merged 50 Hz + step grid; each
sample is held until the next) into one odometry move (rot1, trans, rot2) per step, so the log's
motion_model is "odometry". Row 0 is the move from the first odometry time to ``time[0]``.

Ground truth. ``truth_pose`` is the Vicon pose interpolated at the step times (x and y
linearly, theta linearly on the unwrapped heading, then wrapped to [-pi, pi)).
``initial_pose`` is the Vicon pose at the first odometry time (the start of row 0's move):
the filter starts at the true pose, so its map frame is the Vicon frame and estimates compare
with ``truth_pose`` and ``truth_landmarks`` without alignment (the usual practice on MRCLAM).
``truth_landmarks`` are the 15 Vicon landmark positions, sorted by subject (6..20).

Shapes of the returned log (``load_mrclam``): T steps, K = ``max_obs``, N = 15 landmarks.
  time (T,), controls (T, 3) odometry moves, obs_z (T, K, 2) (range [m], bearing [rad]),
  obs_valid (T, K) bool, truth_pose (T, 3), truth_landmarks (N, 2), initial_pose (3,).
Robot 1 with the defaults: T = 3,809 steps (3,349 with observations, 460 fillers), 4,771
observations (952 robot sightings removed, none truncated).

Everything here is host-side NumPy float64, in small pure functions.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import NamedTuple

import numpy as np

from jaxslam.datasets.log_format import (
    LogFormatError,
    RobotLog,
    integrate_controls,
    interpolate_poses,
    validate_log,
)

NUM_ROBOTS = 5
ROBOT_SUBJECTS = tuple(range(1, NUM_ROBOTS + 1))  # Barcodes.dat subjects 1-5 are the robots
RATE_HZ = 50.0
PRINTED_DIGITS = 5  # significant digits of the times in this copy's files
BARCODES_NAME = "Barcodes.dat"
LANDMARKS_NAME = "Landmark_Groundtruth.dat"
DEFAULT_MAX_OBS = 8  # the most landmark readings at one time in dataset 1 (robot 5)
DEFAULT_MAX_GAP = 1.0  # [s]: at most 8.6 cm and 0.57 rad of commanded motion
TIME_SLACK = 1e-9  # [s], float rounding allowance when comparing times
# Pure-turn threshold of the integrated moves: 1 mm, as for Victoria Park. The moves are
# integrated commanded velocities, so even short ones have a meaningful direction (a median
# step is 0.24 s, 2 cm). Measured: dead-reckoning ATE of every robot changes by < 1 mm
# between 0, 1 mm and 1 cm.
MRCLAM_MIN_TRANSLATION = 1e-3


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


class MrclamSteps(NamedTuple):
    """Measurements grouped into filter steps, and what was dropped on the way.

    Attributes:
      time: (T,) step times [s], strictly increasing.
      obs_z: (T, K, 2) range and bearing; zeros where padding.
      obs_valid: (T, K) bool.
      obs_landmark: (T, K) int64 index of the observed landmark into ``truth_landmarks``
        (the subject-sorted rows of Landmark_Groundtruth.dat); -1 where padding.
      num_robot_sightings: measurements of robots (subjects 1-5), removed.
      num_unknown_barcodes: measurements of barcodes no landmark carries, removed.
      num_before_start: landmark measurements before the first odometry time, removed.
      num_truncated: landmark measurements past ``max_obs`` in their step, removed.
      num_filler_steps: steps added by ``max_gap`` (no observations by construction).
    """

    time: np.ndarray
    obs_z: np.ndarray
    obs_valid: np.ndarray
    obs_landmark: np.ndarray
    num_robot_sightings: int
    num_unknown_barcodes: int
    num_before_start: int
    num_truncated: int
    num_filler_steps: int


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


# ----------------------------------------------------------------------------------------------
# Measurements -> steps


def measurement_landmarks(barcode, table_barcode, table_subject, landmark_subject):
    """Landmark index (M,) int64 of each measured barcode (M,): into ``landmark_subject`` (N,).

    -1 marks a robot (subjects 1-5), -2 a barcode no landmark carries (not in the
    (S,) barcode -> subject table, or its subject is not in ``landmark_subject``).
    """
    lookup = dict(zip(table_barcode.tolist(), table_subject.tolist()))
    position = {int(s): i for i, s in enumerate(landmark_subject.tolist())}
    subject = [lookup.get(int(b), 0) for b in barcode]
    return np.array([-1 if s in ROBOT_SUBJECTS else position.get(s, -2) for s in subject],
                    np.int64).reshape(np.shape(barcode))


def fill_gaps(times, start: float, max_gap: float | None) -> np.ndarray:
    """Extra times (E,) that cut every gap of (start, *times) (T,) longer than ``max_gap``.

    A gap of length L > max_gap gets ceil(L / max_gap) - 1 equally spaced times inside it.
    None or inf: no extra times.
    """
    times = np.asarray(times, np.float64)
    if max_gap is None or not np.isfinite(max_gap):
        return np.zeros(0)
    previous = np.concatenate([[start], times[:-1]])
    gap = times - previous
    parts = np.maximum(np.ceil(gap / max_gap - TIME_SLACK), 1).astype(np.int64)
    extra = parts - 1
    owner = np.repeat(np.arange(times.shape[0]), extra)
    within = np.arange(owner.shape[0]) - np.repeat(np.cumsum(extra) - extra, extra) + 1
    return previous[owner] + gap[owner] * within / parts[owner]


def mrclam_step_times(measurement_time, start: float, step_dt: float | None = None,
                      max_gap: float | None = DEFAULT_MAX_GAP):
    """Step times (T,) and the number of filler steps among them.

    ``step_dt=None``: the distinct measurement times (M,) (all >= ``start``).
    ``step_dt``: the bin ends start + b step_dt, b = 1..B, B = ceil((last - start) / step_dt)
    (at least 1), every bin a step.
    Then ``fill_gaps`` adds steps so that no two consecutive steps (nor ``start`` and the first)
    are more than ``max_gap`` apart. Raises LogFormatError when there is no measurement.
    """
    measurement_time = np.asarray(measurement_time, np.float64)
    if measurement_time.shape[0] < 1:
        raise LogFormatError("no landmark measurement at or after the first odometry time; "
                             "expected at least one to build filter steps")
    if step_dt is None:
        base = np.unique(measurement_time)
    else:
        if not step_dt > 0:
            raise ValueError(f"step_dt={step_dt!r}; expected a positive bin width [s] or None")
        bins = max(int(math.ceil((measurement_time.max() - start) / step_dt - TIME_SLACK)), 1)
        base = start + step_dt * np.arange(1, bins + 1)
    if max_gap is not None and not max_gap > 0:
        raise ValueError(f"max_gap={max_gap!r}; expected a positive time [s] or None")
    extra = fill_gaps(base, start, max_gap)
    return np.sort(np.concatenate([base, extra])), int(extra.shape[0])


def pad_observations(step, z, landmark, num_steps: int, max_obs: int):
    """Scatter observations into padded steps, in order, keeping the first ``max_obs`` a step.

    Args:
      step: (M,) int64 step of each observation, non-decreasing.
      z: (M, 2) range and bearing.  landmark: (M,) int64 landmark index.
    Returns:
      obs_z (T, K, 2), obs_valid (T, K) bool, obs_landmark (T, K) int64 (-1 padding), and
      the number of observations dropped past ``max_obs``.
    """
    rank = np.arange(step.shape[0]) - np.searchsorted(step, step, side="left")
    keep = rank < max_obs
    obs_z = np.zeros((num_steps, max_obs, 2))
    obs_valid = np.zeros((num_steps, max_obs), bool)
    obs_landmark = np.full((num_steps, max_obs), -1, np.int64)
    obs_z[step[keep], rank[keep]] = z[keep]
    obs_valid[step[keep], rank[keep]] = True
    obs_landmark[step[keep], rank[keep]] = landmark[keep]
    return obs_z, obs_valid, obs_landmark, int((~keep).sum())


def mrclam_steps(run: MrclamRun, max_obs: int = DEFAULT_MAX_OBS, step_dt: float | None = None,
                 max_gap: float | None = DEFAULT_MAX_GAP) -> MrclamSteps:
    """Drop robot sightings and unknown barcodes, build the steps, pad the observations."""
    if isinstance(max_obs, bool) or not isinstance(max_obs, (int, np.integer)) or max_obs < 1:
        raise ValueError(f"max_obs={max_obs!r}; expected a positive integer (K, the padded "
                         "observations per step)")
    landmark = measurement_landmarks(run.measurement_barcode, run.barcode, run.barcode_subject,
                                     run.landmark_subject)
    start = float(run.odometry_time[0])
    seen = landmark >= 0
    kept = seen & (run.measurement_time >= start)
    time, filler = mrclam_step_times(run.measurement_time[kept], start, step_dt, max_gap)
    # The first step at or after each measurement; the 1 ns slack keeps a measurement on a
    # bin's end in that bin despite float rounding of start + b step_dt.
    step = np.searchsorted(time, run.measurement_time[kept] - TIME_SLACK, side="left")
    step = np.minimum(step, time.shape[0] - 1)
    obs_z, obs_valid, obs_landmark, truncated = pad_observations(
        step, run.measurement_z[kept], landmark[kept], time.shape[0], int(max_obs))
    return MrclamSteps(time=time, obs_z=obs_z, obs_valid=obs_valid, obs_landmark=obs_landmark,
                       num_robot_sightings=int((landmark == -1).sum()),
                       num_unknown_barcodes=int((landmark == -2).sum()),
                       num_before_start=int((seen & ~kept).sum()), num_truncated=truncated,
                       num_filler_steps=filler)


# ----------------------------------------------------------------------------------------------
# Ground truth, controls, the log


def mrclam_log(run: MrclamRun, steps: MrclamSteps,
               min_translation: float = MRCLAM_MIN_TRANSLATION) -> RobotLog:
    """The validated ``RobotLog`` of ``steps``: odometry moves, Vicon truth, start pose."""
    controls = integrate_controls(run.odometry_time, run.odometry, steps.time, "velocity",
                                  min_translation=min_translation)
    start = run.odometry_time[:1]
    log = RobotLog(time=steps.time, motion_model="odometry", controls=controls,
                   obs_z=steps.obs_z, obs_valid=steps.obs_valid,
                   truth_pose=interpolate_poses(steps.time, run.truth_time, run.truth_pose),
                   truth_landmarks=run.landmark_xy,
                   initial_pose=interpolate_poses(start, run.truth_time, run.truth_pose)[0])
    return validate_log(log, source=f"MRCLAM robot {run.robot}")


def load_mrclam(root, robot: int = 1, max_obs: int = DEFAULT_MAX_OBS,
                step_dt: float | None = None, max_gap: float | None = DEFAULT_MAX_GAP,
                rate_hz: float | None = RATE_HZ,
                min_translation: float = MRCLAM_MIN_TRANSLATION) -> RobotLog:
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
    Returns:
      RobotLog with time (T,), controls (T, 3) odometry, obs_z (T, K, 2), obs_valid (T, K),
      truth_pose (T, 3), truth_landmarks (15, 2), initial_pose (3,) (Vicon at the start).
    Raises:
      ValueError: robot not in 1..5, or max_obs / step_dt / max_gap not positive.
      MrclamFileError: the folder or a file is missing.
      LogFormatError: a malformed file (names file and line) or no landmark measurement.
    """
    run = read_mrclam(root, robot, rate_hz)
    return mrclam_log(run, mrclam_steps(run, max_obs, step_dt, max_gap), min_translation)
