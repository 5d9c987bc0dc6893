"""MRCLAM measurements and commands -> filter steps, odometry moves and the ``RobotLog``.

The conversion half of the MRCLAM loader (``jaxslam.datasets.mrclam`` reads the files into a
``MrclamRun``; see it for the dataset and its files).

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
``truth_landmarks`` are the 15 Vicon landmark positions, sorted by subject (6..20). In
dataset 1 as shipped, every robot's readings of subject 11's barcode (18) lie at subject 17's
listed position and those of subject 17's barcode (61) at subject 11's (median range error
over 1 m against the listed landmark, under 0.2 m against the other; checked in
``tests/datasets/test_mrclam.py``): ``obs_landmark`` indices 5 and 11 name each other's
row. The tables are returned as they are. Scores that compare the map with the set of
positions (``metrics``) do not depend on it, and a known-association run with these ids
builds each landmark where the other's row lies; only per-id comparisons with
``truth_landmarks`` must swap the two rows (``landmarks_as_sighted``).

Everything here is host-side NumPy float64, in small pure functions.
"""
from __future__ import annotations

import math
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from jaxslam.datasets.log_format import (COMMAND_MIN_TRANSLATION, LogFormatError, RobotLog,
                                         validate_log)
from jaxslam.datasets.odometry import interpolate_poses

if TYPE_CHECKING:  # only for annotations: mrclam imports this module
    from jaxslam.datasets.mrclam import MrclamRun

ROBOT_SUBJECTS = (1, 2, 3, 4, 5)  # Barcodes.dat subjects 1-5 are the robots
DEFAULT_MAX_OBS = 8  # the most landmark readings at one time in dataset 1 (robot 5)
DEFAULT_MAX_GAP = 1.0  # [s]: at most 8.6 cm and 0.57 rad of commanded motion
TIME_SLACK = 1e-9  # [s], float rounding allowance when comparing times
# Pure-turn threshold of the integrated moves: 1 mm, as for Victoria Park. The moves are
# integrated commanded velocities, so even short ones have a meaningful direction (a median
# step is 0.24 s, 2 cm). Measured: dead-reckoning ATE of every robot changes by < 1 mm
# between 0, 1 mm and 1 cm.
MRCLAM_MIN_TRANSLATION = COMMAND_MIN_TRANSLATION
# obs_landmark indices whose readings lie at each other's listed position (module docstring)
SWAPPED_LANDMARK_ROWS = (5, 11)


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
               min_translation: float = MRCLAM_MIN_TRANSLATION,
               command_delay: float = 0.0) -> RobotLog:
    """The validated ``RobotLog`` of ``steps``: odometry moves, Vicon truth, start pose, and
    the commanded velocities as its command stream (``command_time``, ``commands``).

    ``command_delay`` [s]: each commanded velocity takes effect that much later than its
    time stamp (the robots answer their commands with a lag, which
    ``command_delay.fit_log_command_delay`` fits from the log): the moves of
    ``RobotLog.at_command_delay``. Only the moves change: the steps, the observations, the
    start time and pose and the truth stay as they are (before its first, delayed, command
    the robot stands still; a negative delay moves the first commands before the start).
    """
    if not np.isfinite(command_delay):
        raise ValueError(f"command_delay={command_delay!r}: expected a finite number of "
                         "seconds")
    start = run.odometry_time[:1]
    log = RobotLog(time=steps.time, motion_model="odometry",
                   controls=np.zeros((steps.time.shape[0], 3)),
                   obs_z=steps.obs_z, obs_valid=steps.obs_valid,
                   truth_pose=interpolate_poses(steps.time, run.truth_time, run.truth_pose),
                   truth_landmarks=run.landmark_xy,
                   initial_pose=interpolate_poses(start, run.truth_time, run.truth_pose)[0],
                   command_time=run.odometry_time, commands=run.odometry)
    return validate_log(log.at_command_delay(command_delay, min_translation),
                        source=f"MRCLAM robot {run.robot}")


def landmarks_as_sighted(truth_landmarks):
    """``truth_landmarks`` (15, 2) with rows ``SWAPPED_LANDMARK_ROWS`` exchanged: row i is
    where the readings with ``obs_landmark`` i lie (module docstring). A copy."""
    landmarks = np.array(truth_landmarks, dtype=np.float64, copy=True)
    a, b = SWAPPED_LANDMARK_ROWS
    landmarks[[a, b]] = landmarks[[b, a]]
    return landmarks
