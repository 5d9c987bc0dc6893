"""UTIAS MRCLAM dataset 1, five robots, unknown association, settings calibrated from each log.

Leung, Halpern, Barfoot and Liu, "The UTIAS Multi-Robot Cooperative Localization and Mapping
Dataset" (IJRR 2011). Barcodes are dropped: the filter does not know which landmark it sees.
For each robot the pipeline (``jaxslam.pipeline.filter_log``) calibrates the noise and the
sensor settings from that robot's odometry and measurements alone, then filters; Vicon only
scores (ATE of the online mean path and of the smoothed one, against dead reckoning).

    python experiments/mrclam.py [--robots 1 2 3 4 5] [--particles 100] [--close-loops]

With ``--close-loops`` the smoothed path is ``loop_closure.close_loops``' (loops the filter
missed closed by registration, each tested by the smoother's cost rise).
"""
from __future__ import annotations

import argparse
import pathlib
import time

import jax
import numpy as np

from jaxslam import metrics, pipeline
from jaxslam.datasets.odometry import odometry_path
from jaxslam.datasets.mrclam import load_mrclam
from jaxslam.types import FilterConfig

DATA = pathlib.Path(__file__).resolve().parents[2] / "shared" / "data" / "mrclam1"


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", default=str(DATA))
    parser.add_argument("--robots", type=int, nargs="+", default=[1, 2, 3, 4, 5])
    parser.add_argument("--particles", type=int, default=100)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--no-calibrate", action="store_true")
    parser.add_argument("--close-loops", action="store_true")
    args = parser.parse_args(argv)
    config = FilterConfig(num_particles=args.particles, max_landmarks=64, max_obs=8)
    rows = []
    for robot in args.robots:
        log = load_mrclam(args.data, robot)
        truth = np.asarray(log.truth_pose)
        dr = np.asarray(odometry_path(log.controls, log.initial_pose))[-len(truth):]
        dr_ate = float(metrics.ate_rmse(dr, truth))
        start = time.perf_counter()
        run = pipeline.filter_log(log, config, None, jax.random.PRNGKey(args.seed),
                                  calibrate=not args.no_calibrate, smooth=True,
                                  close_loops=args.close_loops)
        seconds = time.perf_counter() - start
        m = run.metrics
        rows.append((dr_ate, m["ate_rmse"], m["smoothed_ate_rmse"], m["num_landmarks"],
                     m["num_trees_mapped"]))
        verdict = run.calibration.verdict if run.calibration is not None else "not calibrated"
        print(f"robot {robot}: T={log.num_steps} | dead reckoning ATE {dr_ate:.3f} m | "
              f"filter ATE {m['ate_rmse']:.3f} m, smoothed {m['smoothed_ate_rmse']:.3f} m | "
              f"{m['num_landmarks']:.0f} landmarks, {m['num_trees_mapped']:.0f} of 15 mapped "
              f"(map error {m['map_error']:.3f} m) | {seconds:.1f} s | {verdict}"
              + (f" | {m['loop_closures']} closures, {m['landmarks_joined']} landmarks joined"
                 if args.close_loops else ""),
              flush=True)
        if run.calibration is not None:
            print("   fitted:", {k: (np.round(v, 5).tolist() if isinstance(v, tuple)
                                    else round(v, 5)) for k, v in run.calibration.values.items()})
        for line in run.warnings:
            print("   WARNING:", line)
    rows = np.asarray(rows)
    print(f"median: dead reckoning {np.median(rows[:, 0]):.3f} m, filter "
          f"{np.median(rows[:, 1]):.3f} m, smoothed {np.median(rows[:, 2]):.3f} m; ratio dead "
          f"reckoning / filter "
          f"{np.median(rows[:, 0] / rows[:, 1]):.2f}; landmarks {np.median(rows[:, 3]):.0f}")


if __name__ == "__main__":
    main()
