"""MRCLAM dataset 1: EM's calibrated settings against EM's times the likelihood's noise scales.

Leung, Halpern, Barfoot and Liu, "The UTIAS Multi-Robot Cooperative Localization and Mapping
Dataset" (IJRR 2011); barcodes dropped. Per robot: ``calibrate_params(scale_search=False)``
with key 0, then ``noise_scale.search_noise_scales`` on its result with key 0 (what
``calibrate_params`` does by default), then the final filter with each setting and keys
0..K-1. Vicon only scores: ATE of the online mean path, median over the keys. Key 0 is also
the search's key, so its column is the run the search ranked highest (in-sample).

    python experiments/mrclam_scales.py [--robots 1 2 3 4 5] [--keys 4]
"""
from __future__ import annotations

import argparse
import pathlib
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

# Run this checkout's jaxslam, also when an editable install points at another checkout
# (an experiment started from a git worktree of an older commit).
sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

from jaxslam import metrics
from jaxslam.datasets.mrclam import load_mrclam
from jaxslam.datasets.odometry import odometry_path
from jaxslam.filter import estimate, run_filter
from jaxslam.noise_scale import search_noise_scales
from jaxslam.self_calibration import calibrate_params
from jaxslam.types import FilterConfig

DATA = pathlib.Path(__file__).resolve().parents[2] / "shared" / "data" / "mrclam1"


def scores(config, params, controls, obs, start, truth, keys: int):
    """(ATE [m] (keys,), landmarks (keys,)) of the final filter with keys 0..keys-1."""
    ate, landmarks = [], []
    for k in range(keys):
        final, trace = run_filter(config, jax.random.PRNGKey(k), params, controls, obs, start)
        ate.append(float(metrics.ate_rmse(np.asarray(trace.mean_pose, np.float64), truth)))
        landmarks.append(int(np.sum(np.asarray(estimate(final).active))))
    return np.asarray(ate), np.asarray(landmarks)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", default=str(DATA))
    parser.add_argument("--robots", type=int, nargs="+", default=[1, 2, 3, 4, 5])
    parser.add_argument("--keys", type=int, default=4)
    parser.add_argument("--particles", type=int, default=100)
    args = parser.parse_args(argv)
    for robot in args.robots:
        log = load_mrclam(args.data, robot)
        truth = np.asarray(log.truth_pose)
        dead = np.asarray(odometry_path(log.controls, log.initial_pose))[-len(truth):]
        obs = log.observations()
        config = FilterConfig(num_particles=args.particles, max_landmarks=64,
                              max_obs=int(obs.z.shape[1]), motion_model=log.motion_model)
        controls = jnp.asarray(np.asarray(log.controls), jnp.float32)
        start = jnp.asarray(np.zeros(3) if log.initial_pose is None else log.initial_pose,
                            jnp.float32)
        tick = time.perf_counter()
        em, _ = calibrate_params(config, jax.random.PRNGKey(0), controls, obs, start,
                                 scale_search=False)
        scaled, found = search_noise_scales(config, jax.random.PRNGKey(0), em, controls, obs,
                                            start)
        seconds = time.perf_counter() - tick
        rows = {name: scores(config, p, controls, obs, start, truth, args.keys)
                for name, p in (("EM", em), ("scaled", scaled))}
        text = " | ".join(f"{name} ATE median {np.median(a):.2f} {np.round(a, 2).tolist()} "
                          f"landmarks {n.tolist()}" for name, (a, n) in rows.items())
        print(f"robot {robot}: dead reckoning {metrics.ate_rmse(dead, truth):.2f} m | scales "
              f"motion x{found.motion_scale:g}, observation x{found.observation_scale:g} "
              f"({seconds:.0f} s) | {text}", flush=True)


if __name__ == "__main__":
    main()
