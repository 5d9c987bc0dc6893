"""Benchmark of ``jaxslam.calibrate_params``: its time as a multiple of one filter run.

One filter run is ``run_filter(..., record_lineage=True)`` after compiling (the calibration
runs it once an iteration, plus a smoothing of the best history). The calibration is timed
whole, with its compile already paid by the first timed filter run (same shapes), so the
ratio is run time over run time. Logs: a held-out simulated loop (the
``experiments/self_calibration.py`` generator: 250 steps, 40 trees) and UTIAS MRCLAM robot 1
(3,809 steps) when the data are present.

    python benchmarks/calibration.py [--particles 100] [--skip-mrclam]
"""
from __future__ import annotations

import argparse
import pathlib
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

from jaxslam.filter import run_filter  # noqa: E402
from jaxslam.self_calibration import calibrate_params, starting_params  # noqa: E402
from jaxslam.types import FilterConfig  # noqa: E402


def _time(function):
    start = time.perf_counter()
    out = function()
    jax.block_until_ready(jax.tree.leaves(out))
    return time.perf_counter() - start, out


def bench(name, config, controls, obs, start):
    key = jax.random.PRNGKey(0)
    params = starting_params(config)
    controls = jnp.asarray(controls, jnp.float32)
    start = jnp.asarray(start, jnp.float32)
    first, _ = _time(lambda: run_filter(config, key, params, controls, obs, start,
                                        record_lineage=True))
    run, _ = _time(lambda: run_filter(config, key, params, controls, obs, start,
                                      record_lineage=True))
    seconds, (_, info) = _time(lambda: calibrate_params(config, key, controls, obs, start,
                                                        params))
    print(f"{name}: T={controls.shape[0]} P={config.num_particles} K={config.max_obs} | "
          f"filter run {run:.2f} s (first call with compile {first:.2f} s) | calibration "
          f"{seconds:.2f} s, {info.iterations} iterations ({info.verdict}) | "
          f"{seconds / run:.1f}x one filter run, {seconds / info.iterations / run:.2f}x a run "
          f"per iteration")


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--particles", type=int, default=100)
    parser.add_argument("--skip-mrclam", action="store_true")
    args = parser.parse_args(argv)
    from experiments.self_calibration import make_log, true_params

    controls, obs, poses, _ = make_log(jax.random.PRNGKey(7), true_params(2.0, 2.0), 0.0)
    bench("simulated loop", FilterConfig(num_particles=args.particles, max_landmarks=96,
                                         max_obs=12), controls, obs, poses[0])
    data = pathlib.Path(__file__).resolve().parents[2] / "shared" / "data" / "mrclam1"
    if not args.skip_mrclam and data.is_dir():
        from jaxslam.datasets.mrclam import load_mrclam

        log = load_mrclam(data, 1)
        bench("MRCLAM robot 1", FilterConfig(num_particles=args.particles, max_landmarks=64,
                                             max_obs=int(log.obs_z.shape[1])),
              log.controls, log.observations(), log.initial_pose)


if __name__ == "__main__":
    main()
