"""The systematic error of UTIAS MRCLAM's commanded-velocity odometry, measured against Vicon.

A diagnostic for dataset 1 (Leung, Halpern, Barfoot and Liu, IJRR 2011): nothing here sets a
filter setting. For each robot the log is rebuilt with its commands ``--command-delay``
seconds late (the lag ``experiments/mrclam.py`` fits from the log), and the moves Vicon saw
at the filter's steps (``motion.odometry_from_poses`` of consecutive truth poses, in the
decomposition nearest the commanded move) are regressed on the commanded ones, translation
and heading change apart:

- the drive's ratio, the unweighted least-squares slope through the origin with its
  block-jackknife error (``odometry_gain.drive_slope``, what the calibration fits from the
  smoothed moves);
- the same slope weighted by Eq. (1)'s 1 / sigma^2 at ``--noise`` (default: Table 1 of
  Geiser et al., "Practical Implementation of FastSLAM for Forestry Robot", ICAROB 2023),
  as a noise fit would weigh the moves;
- the dead-reckoning ATE of the commands as they are and times the drive's ratios (the
  gains ``params.odometry_gain`` would carry).

    python experiments/mrclam_odometry.py [--robots 1 2 3 4 5] [--command-delay 0.228]
"""
from __future__ import annotations

import argparse
import pathlib
import sys

import numpy as np

# Run this checkout's jaxslam, also when an editable install points at another checkout.
sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

from jaxslam import metrics  # noqa: E402
from jaxslam.datasets.mrclam import read_mrclam  # noqa: E402
from jaxslam.datasets.mrclam_convert import DEFAULT_MAX_OBS, mrclam_log, mrclam_steps  # noqa: E402
from jaxslam.datasets.odometry import odometry_path  # noqa: E402
from jaxslam.host import in_float64  # noqa: E402
from jaxslam.motion import (nearest_decomposition, odometry_from_poses,  # noqa: E402
                            odometry_std, with_gain)
from jaxslam.odometry_gain import drive_slope  # noqa: E402
from jaxslam.types import default_params  # noqa: E402

DEFAULT_DATA = pathlib.Path(__file__).resolve().parents[2] / "shared" / "data" / "mrclam1"


def true_moves(truth, commanded, min_translation: float) -> np.ndarray:
    """(T - 1, 3) the moves between consecutive truth poses (T, 3), each written in the
    decomposition nearest the commanded move of the same step (``commanded`` (T - 1, 3))."""
    moves = in_float64(odometry_from_poses, truth[:-1], truth[1:],
                       min_translation=min_translation)
    return in_float64(nearest_decomposition, moves, commanded)


def weighted_slope(measured, true, std) -> float:
    """sum w x v / sum w x^2 with w = 1 / std^2 over the finite samples with x != 0."""
    usable = np.isfinite(true) & (measured != 0.0) & (std > 0.0)
    w = 1.0 / std[usable] ** 2
    return float(np.sum(w * measured[usable] * true[usable])
                 / np.sum(w * measured[usable] ** 2))


def robot_row(data, robot: int, delay: float, noise) -> dict:
    """The drive's ratios, the weighted slopes and the dead-reckoning ATEs of one robot."""
    raw = read_mrclam(data, robot)
    log = mrclam_log(raw, mrclam_steps(raw, DEFAULT_MAX_OBS), command_delay=delay)
    truth = np.asarray(log.truth_pose, np.float64)
    commanded = np.asarray(log.controls, np.float64)[-len(truth):][1:]
    true = true_moves(truth, commanded, float(noise.min_translation))
    std = in_float64(odometry_std, commanded, noise)
    heading, true_heading = commanded[:, 0] + commanded[:, 2], true[:, 0] + true[:, 2]
    heading_std = np.hypot(std[:, 0], std[:, 2])
    translation = drive_slope(commanded[:, 1], true[:, 1], std[:, 1])
    rotation = drive_slope(heading, true_heading, heading_std)
    controls = np.asarray(log.controls, np.float64)
    gained = in_float64(with_gain, controls, np.array([translation.factor, rotation.factor]))
    ate = [float(metrics.ate_rmse(np.asarray(odometry_path(moves, log.initial_pose))
                                  [-len(truth):], truth)) for moves in (controls, gained)]
    return {"translation": translation, "rotation": rotation,
            "weighted": (weighted_slope(commanded[:, 1], true[:, 1], std[:, 1]),
                         weighted_slope(heading, true_heading, heading_std)),
            "ate": ate}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", type=pathlib.Path, default=DEFAULT_DATA,
                        help=f"the dataset folder (default: {DEFAULT_DATA})")
    parser.add_argument("--robots", type=int, nargs="+", default=[1, 2, 3, 4, 5],
                        choices=range(1, 6), help="robots (default: all five)")
    parser.add_argument("--command-delay", type=float, default=0.228,
                        help="seconds the commands act late (default: 0.228, robot 2's "
                             "fitted lag; the five fitted 0.224-0.234 s)")
    args = parser.parse_args(argv)
    noise = default_params()
    print("robot | drive's ratio: translation, heading change (+- 1 se) | weighted by "
          "Eq. (1) 1/sigma^2 (Table 1) | dead reckoning ATE: as commanded, times the ratios")
    for robot in args.robots:
        row = robot_row(args.data, robot, args.command_delay, noise)
        t, r = row["translation"], row["rotation"]
        print(f"{robot} | {t.factor:.3f} +- {t.standard_error:.3f}, {r.factor:.3f} +- "
              f"{r.standard_error:.3f} | {row['weighted'][0]:.3f}, {row['weighted'][1]:.3f} | "
              f"{row['ate'][0]:.2f} m, {row['ate'][1]:.2f} m", flush=True)


if __name__ == "__main__":
    main()
