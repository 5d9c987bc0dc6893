"""A user's own log through the log pipeline: defaults, calibrated, and the true noise by hand.

The log: 300 steps on a 12 m circle past 30 trees (rings at 9 and 15 m), range noise 5 cm
and bearing noise 0.005 rad at every distance, 8 m sensor range, odometry noise 0.01 rad per
rotation and 2 % of the translation. Nothing about the noise is given to the calibrated run;
the "true noise" run is told it; "defaults" runs ``default_params`` (Geiser et al.'s Table 1
and 2 robot), which is what a user got before the pipeline calibrated.

    python experiments/user_log.py [--runs 4] [--particles 100]
"""
from __future__ import annotations

import argparse
import pathlib
import sys

import jax
import numpy as np

# Run this checkout's jaxslam, also when an editable install points at another checkout
# (an experiment started from a git worktree of an older commit).
sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

from jaxslam import pipeline
from jaxslam.datasets.log_format import RobotLog
from jaxslam.types import FilterConfig, default_params

RANGE_STD, BEARING_STD, TURN_STD, TRANS_FRACTION = 0.05, 0.005, 0.01, 0.02


def user_log(seed: int, steps: int = 300) -> RobotLog:
    rng = np.random.default_rng(seed)
    angle = rng.uniform(-np.pi, np.pi, 30)
    radius = np.where(np.arange(30) % 2 == 0, 9.0, 15.0) + rng.uniform(-0.5, 0.5, 30)
    trees = np.stack([radius * np.cos(angle), radius * np.sin(angle)], 1)
    phi = 2 * np.pi * np.arange(steps + 1) / steps
    truth = np.stack([12 * np.cos(phi), 12 * np.sin(phi), phi + np.pi / 2], 1)
    truth[:, 2] = (truth[:, 2] + np.pi) % (2 * np.pi) - np.pi
    trans = np.full(steps, 2 * 12 * np.sin(np.pi / steps))
    half_turn = np.full(steps, np.pi / steps)
    controls = np.stack([half_turn + rng.normal(0, TURN_STD, steps),
                         trans * (1 + rng.normal(0, TRANS_FRACTION, steps)),
                         half_turn + rng.normal(0, TURN_STD, steps)], 1)
    offset = trees[None] - truth[1:, None, :2]
    distance = np.hypot(offset[..., 0], offset[..., 1])
    bearing = np.arctan2(offset[..., 1], offset[..., 0]) - truth[1:, None, 2]
    order = np.argsort(distance, axis=1)[:, :10]
    d = np.take_along_axis(distance, order, 1)
    b = np.take_along_axis(bearing, order, 1)
    z = np.stack([d + rng.normal(0, RANGE_STD, d.shape),
                  (b + rng.normal(0, BEARING_STD, b.shape) + np.pi) % (2 * np.pi) - np.pi], -1)
    return RobotLog(time=np.arange(steps, dtype=float), motion_model="odometry",
                    controls=controls, obs_z=z, obs_valid=d < 8.0, truth_pose=truth[1:],
                    truth_landmarks=trees, initial_pose=truth[0])


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=4)
    parser.add_argument("--particles", type=int, default=100)
    args = parser.parse_args(argv)
    config = FilterConfig(num_particles=args.particles, max_landmarks=64)
    truth = default_params(range_noise=(0.0, RANGE_STD), bearing_noise=(0.0, BEARING_STD),
                           rot1_noise=(0.0, 0.0, TURN_STD), rot2_noise=(0.0, 0.0, TURN_STD),
                           trans_noise=(TRANS_FRACTION, 0.0, 0.0), max_range=8.0)
    rows = []
    for seed in range(args.runs):
        log = user_log(1000 + seed)
        key = jax.random.PRNGKey(seed)
        runs = {"defaults": pipeline.filter_log(log, config, default_params(), key,
                                                calibrate=False),
                "true noise": pipeline.filter_log(log, config, truth, key, calibrate=False),
                "calibrated": pipeline.filter_log(log, config, None, key)}
        row = []
        for name, run in runs.items():
            m = run.metrics
            row += [m["ate_rmse"], m["num_trees_mapped"]]
            print(f"log {seed} {name:<10}: ATE {m['ate_rmse']:.3f} m, final "
                  f"{m['final_pose_error']:.3f} m, {m['num_trees_mapped']:.0f} trees mapped of "
                  f"{len(log.truth_landmarks)}, {m['landmarks_started']} landmarks started, "
                  f"{len(run.warnings)} warnings", flush=True)
        rows.append(row)
    rows = np.asarray(rows)
    med = np.median(rows, axis=0)
    print(f"median ATE [m] / trees mapped: defaults {med[0]:.3f} / {med[1]:.0f}, true noise "
          f"{med[2]:.3f} / {med[3]:.0f}, calibrated {med[4]:.3f} / {med[5]:.0f}; calibrated / "
          f"true ATE (median of ratios) {np.median(rows[:, 4] / rows[:, 2]):.2f}")


if __name__ == "__main__":
    main()
