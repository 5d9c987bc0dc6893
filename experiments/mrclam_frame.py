"""In which frame the filter builds its map: the heading error over time, and the final map
fitted rigidly to the true landmarks.

A diagnostic for UTIAS MRCLAM dataset 1 (Leung, Halpern, Barfoot and Liu, IJRR 2011) with the
association known from the barcodes; nothing here sets a filter setting, and Vicon only
scores. Each robot's log, rebuilt with its commands ``--command-delay`` seconds late, is
calibrated with the barcodes and filtered with them (``experiments/mrclam.py``'s
``barcode_calibration``, existence cap ``--existence-max``, 1000 by default: the dataset's
15 tubes are static). Then for each filter key (100, 101, ...) the script prints:

- the online mean path's heading error against Vicon at the steps of ``--at`` (and dead
  reckoning's at the same steps);
- ``map_frame``: the best particle's final map against Vicon's landmarks, as it is and after
  the least-squares rigid transform (``metrics.align_se2``) that carries it onto them, with
  that transform's rotation and shift. A map whose error falls far with the fit has about
  the right shape in a rotated or shifted frame.

    python experiments/mrclam_frame.py --robots 4 --command-delay 0.224 [--keys 3]
"""
from __future__ import annotations

import argparse
import pathlib
import sys

import jax
import jax.numpy as jnp
import numpy as np

# Run this checkout's jaxslam, also when an editable install points at another checkout.
sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

from jaxslam import metrics  # noqa: E402
from jaxslam.datasets.mrclam import read_mrclam  # noqa: E402
from jaxslam.datasets.mrclam_convert import (DEFAULT_MAX_OBS, landmarks_as_sighted,  # noqa: E402
                                             mrclam_log, mrclam_steps)
from jaxslam.datasets.odometry import odometry_path  # noqa: E402
from jaxslam.filter import estimate, run_filter  # noqa: E402
from jaxslam.types import FilterConfig  # noqa: E402
from experiments.mrclam import barcode_calibration  # noqa: E402

DEFAULT_STEPS = (50, 100, 150, 200, 300, 425)


def heading_error_deg(pose, truth, steps) -> np.ndarray:
    """|wrap(theta - theta_true)| in degrees (float64, on the host) at ``steps`` (S,) of
    paths (T, 3)."""
    steps = np.asarray(steps, int)
    error = np.asarray(pose, np.float64)[steps, 2] - np.asarray(truth, np.float64)[steps, 2]
    return np.degrees(np.abs((error + np.pi) % (2.0 * np.pi) - np.pi))


def _rms(diff) -> float:
    """Root mean square length of the rows of ``diff`` (N, 2)."""
    return float(np.sqrt(np.mean(np.sum(diff**2, axis=1))))


def map_frame(landmark_mean, active, landmark_id, truth_landmarks) -> dict:
    """The map (M, 2) of one particle against the true landmarks (L, 2), pairing slot m with
    row ``landmark_id[m]`` (only active slots with an id >= 0): the rms error as it is
    (``error``), after the least-squares rigid fit of the map onto the truth (``fitted``), and
    that fit's rotation [deg] and shift [m] (``count`` landmarks paired). Needs two paired
    landmarks for a rotation; raises ValueError with fewer."""
    mean, ids = np.asarray(landmark_mean, np.float64), np.asarray(landmark_id)
    use = np.asarray(active, bool) & (ids >= 0)
    if use.sum() < 2:
        raise ValueError(f"map_frame needs at least 2 landmarks with a known id; got "
                         f"{int(use.sum())}")
    est, truth = mean[use], np.asarray(truth_landmarks, np.float64)[ids[use]]
    fit = np.asarray(metrics.align_se2(est, truth), np.float64)
    fitted = np.asarray(metrics.transform_points(fit, est), np.float64)
    return dict(count=int(use.sum()), error=_rms(est - truth), fitted=_rms(fitted - truth),
                rotation=float(np.degrees(fit[2])), shift=float(np.hypot(fit[0], fit[1])))


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", default="../shared/data/mrclam1",
                        help="the dataset folder (default: ../shared/data/mrclam1)")
    parser.add_argument("--robots", type=int, nargs="+", default=[4],
                        help="robots 1-5 (default: 4)")
    parser.add_argument("--command-delay", type=float, required=True,
                        help="[s] the commands' lag, e.g. the one experiments/mrclam.py "
                             "fits (robot 4: 0.224)")
    parser.add_argument("--keys", type=int, default=3,
                        help="filter keys 100, 101, ... (default: 3)")
    parser.add_argument("--seed", type=int, default=0,
                        help="the calibration's key (default: 0)")
    parser.add_argument("--existence-max", type=float, default=1000.0,
                        help="the existence cap (default: 1000, static tubes)")
    parser.add_argument("--at", type=int, nargs="+", default=list(DEFAULT_STEPS),
                        help=f"steps of the heading errors (default: {DEFAULT_STEPS})")
    args = parser.parse_args(argv)
    if args.keys < 1:
        parser.error(f"--keys {args.keys}: expected 1 or more")
    config = FilterConfig(num_particles=100, max_landmarks=64, max_obs=DEFAULT_MAX_OBS)
    for robot in args.robots:
        raw = read_mrclam(args.data, robot)
        steps = mrclam_steps(raw, DEFAULT_MAX_OBS)
        log = mrclam_log(raw, steps, command_delay=args.command_delay)
        truth = np.asarray(log.truth_pose)
        if max(args.at) >= len(truth) or min(args.at) < 0:
            parser.error(f"--at {args.at}: robot {robot}'s log has steps 0-{len(truth) - 1}")
        trees = landmarks_as_sighted(log.truth_landmarks)
        dead_reckoning = np.asarray(odometry_path(log.controls, log.initial_pose))[-len(truth):]
        _, known, params, _, (controls, obs, start) = barcode_calibration(
            log, steps.obs_landmark, config, args.seed, args.existence_max)
        print(f"robot {robot}: heading error [deg] at steps {args.at}: dead reckoning "
              f"{np.round(heading_error_deg(dead_reckoning, truth, args.at), 1).tolist()}",
              flush=True)
        for key in range(100, 100 + args.keys):
            final, trace = run_filter(known, jax.random.PRNGKey(key), params, controls, obs,
                                      jnp.asarray(start, jnp.float32))
            path = np.asarray(trace.mean_pose, np.float64)
            best = int(estimate(final).best_particle)
            particles = final.particles
            frame = map_frame(particles.landmark_mean[best], particles.active[best],
                              particles.landmark_id[best], trees)
            print(f"   key {key}: heading error "
                  f"{np.round(heading_error_deg(path, truth, args.at), 1).tolist()}; ATE "
                  f"{float(metrics.ate_rmse(path, truth)):.3f} m, aligned "
                  f"{float(metrics.ate_rmse(path, truth, align=True)):.3f} m; map of "
                  f"{frame['count']} landmarks: {frame['error']:.3f} m as it is, "
                  f"{frame['fitted']:.3f} m after a rigid fit (rotation "
                  f"{frame['rotation']:+.1f} deg, shift {frame['shift']:.2f} m)", flush=True)


if __name__ == "__main__":
    main()
