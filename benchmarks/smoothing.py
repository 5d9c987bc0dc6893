"""Benchmark of ``jaxslam.smoothing.smooth_path`` (the smoothed Victoria Park runs).

The smoother's factors are the library's JAX models, jitted and run in float64; the least
squares runs on the host (scipy sparse LU). The first solve of a problem size compiles the
factors (batches padded to a power of two), so each size is solved twice: the first time
printed includes that compilation, the second is the solve alone.

A synthetic drive of T steps over laps of a 40 m circle among N trees, K nearest trees
observed per step (1 cm / 1 mrad noise), odometry with 0.01 rad heading noise per step; the
start path is dead reckoning. Victoria Park's size is T = 7230, K <= 18 (about 29,000
associated observations, 24,000 unknowns).

Usage:
  python benchmarks/smoothing.py                        # T = 1000 and 7230, K = 4
  python benchmarks/smoothing.py --steps 7230 --obs 6 --calibrate-rounds 1
  python benchmarks/smoothing.py --steps 7230 --visit-gap 100   # loop closures as links
"""
from __future__ import annotations

import argparse
import pathlib
import sys
import time

import numpy as np

# Time this checkout's code, also when an editable install points at another checkout.
sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

from jaxslam import metrics, smoothing  # noqa: E402
from jaxslam.datasets.odometry import odometry_path  # noqa: E402
from jaxslam.types import default_params  # noqa: E402


def synthetic_drive(steps: int, num_obs: int, num_trees: int, seed: int = 0):
    """(start (3,), truth (T, 3), odometry (T, 3), z (T, K, 2), ids (T, K))."""
    rng = np.random.default_rng(seed)
    laps = max(1.0, steps / 400)
    angle = 2 * np.pi * laps * np.arange(steps + 1) / steps
    truth = np.stack([40 * np.cos(angle), 40 * np.sin(angle), angle + np.pi / 2], 1)
    radius = rng.uniform(30, 50, num_trees)
    bearing = rng.uniform(-np.pi, np.pi, num_trees)
    trees = np.stack([radius * np.cos(bearing), radius * np.sin(bearing)], 1)
    start, poses = truth[0], truth[1:]
    delta = poses[:, :2] - truth[:-1, :2]
    heading = truth[:-1, 2]
    forward = np.cos(heading) * delta[:, 0] + np.sin(heading) * delta[:, 1]
    left = -np.sin(heading) * delta[:, 0] + np.cos(heading) * delta[:, 1]
    rot1 = np.arctan2(left, forward)
    odometry = np.stack([rot1, np.hypot(forward, left), np.diff(truth[:, 2]) - rot1], 1)
    odometry[:, [0, 2]] += 0.01 * rng.normal(size=(steps, 2))
    offset = trees[None] - poses[:, None, :2]
    distance = np.hypot(offset[..., 0], offset[..., 1])
    ids = np.argsort(distance, axis=1)[:, :num_obs]
    chosen = np.take_along_axis(offset, ids[..., None], axis=1)
    z = np.stack([np.hypot(chosen[..., 0], chosen[..., 1]),
                  np.arctan2(chosen[..., 1], chosen[..., 0]) - poses[:, None, 2]], -1)
    z[..., 1] = (z[..., 1] + np.pi) % (2 * np.pi) - np.pi
    z += rng.normal(size=z.shape) * [0.01, 0.001]
    return start, poses, odometry, z, ids


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, nargs="+", default=[1000, 7230])
    parser.add_argument("--obs", type=int, default=4, help="observations per step (K)")
    parser.add_argument("--trees", type=int, default=200)
    parser.add_argument("--calibrate-rounds", type=int, default=0)
    parser.add_argument("--visit-gap", type=int, default=None,
                        help="split landmarks into visits tied by robust links (steps)")
    args = parser.parse_args()
    params = default_params(rot1_noise=(0.0, 0.0, 0.01), rot2_noise=(0.0, 0.0, 0.01),
                            range_noise=(0.0, 0.01), bearing_noise=(0.0, 0.001))
    print(f"settings: K = {args.obs}, trees = {args.trees}, calibrate_rounds = "
          f"{args.calibrate_rounds}, visit_gap = {args.visit_gap}; JAX float64 factors + scipy "
          "sparse LU")
    for steps in args.steps:
        start, truth, odometry, z, ids = synthetic_drive(steps, args.obs, args.trees)
        initial = odometry_path(odometry, start)
        seconds = []
        for _ in range(2):  # the first includes compiling the factors for this size
            begin = time.perf_counter()
            out = smoothing.smooth_path(start, initial, odometry, z, ids, params,
                                        calibrate_rounds=args.calibrate_rounds,
                                        visit_gap=args.visit_gap)
            seconds.append(time.perf_counter() - begin)
        first, seconds = seconds
        positions = out.landmark if out.visits is None else out.visits.position
        unknowns = 3 * steps + 2 * positions.shape[0]
        # Rigidly aligned: the first move's heading noise turns the whole solution (gauge).
        error = float(metrics.ate_rmse(out.path.astype(np.float32), truth.astype(np.float32),
                                       align=True))
        drift = float(metrics.ate_rmse(initial.astype(np.float32), truth.astype(np.float32),
                                       align=True))
        if out.visits is None:
            solve = (f"{out.iterations} LM steps, {seconds:.2f} s "
                     f"({1e3 * seconds / max(out.iterations, 1):.0f} ms a step)")
        else:  # the merged solve, then the split one: time for both, steps of the last
            solve = (f"{len(out.visits.links)} links ({int(np.sum(out.visits.link_weight < 0.5))}"
                     f" dropped), {seconds:.2f} s for the merged and split solves "
                     f"({out.iterations} LM steps in the split one)")
        print(f"T = {steps:5d}: {unknowns} unknowns, {ids.size} observations, {solve} "
              f"(first call {first:.2f} s with compilation); aligned position RMSE "
              f"{error:.3f} m (dead reckoning {drift:.2f} m)")


if __name__ == "__main__":
    main()
