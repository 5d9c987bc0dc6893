"""Which proposal should be the default? The candidates on three kinds of held-out logs.

Regimes (the wobbly loop of ``experiments/self_calibration.py``, 40 trees, 12 m range, 250
steps, the filter given the true noise):
  smooth:  odometry 2x Table 1, sensor 2x Table 2, no wobble, P = 100 (the easy case)
  lidar:   odometry 6x, 5 mm / 0.5 mrad lidar, wobble 0.3 m (~0.15 rad a step), P = 20
  coarse:  odometry 4x, 2 cm / 10 mrad sensor, wobble 0.3 m, P = 100
Candidates are (proposal, eps, kappa, anchor_empty_map) as in ``experiments/mixture_regime.py``.

    python experiments/proposal_defaults.py --regime smooth --runs 8 --seed 200
"""
from __future__ import annotations

import argparse
import ast
import pathlib
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

# Run this checkout's jaxslam, also when an editable install points at another checkout
# (an experiment started from a git worktree of an older commit).
sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

from experiments.mixture_regime import DEFAULT_VARIANTS, regime_params, variant_config
from experiments.self_calibration import make_log, score, true_params

REGIMES = {"smooth": (lambda: true_params(2.0, 2.0), 0.0, 100),
           "lidar": (lambda: regime_params(6.0, "lidar"), 0.3, 20),
           "coarse": (lambda: regime_params(4.0, "coarse"), 0.3, 100)}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--regime", choices=sorted(REGIMES), default="smooth")
    parser.add_argument("--runs", type=int, default=8)
    parser.add_argument("--seed", type=int, default=200)
    parser.add_argument("--particles", type=int, default=None)
    parser.add_argument("--variants", default=repr(DEFAULT_VARIANTS))
    args = parser.parse_args(argv)
    make_truth, wobble, particles = REGIMES[args.regime]
    particles = args.particles or particles
    truth = make_truth()
    variants = [tuple(v) for v in ast.literal_eval(args.variants)]
    results = {v: [] for v in variants}
    seconds = {v: 0.0 for v in variants}
    for run in range(args.runs):
        key_log, key_filter = jax.random.split(jax.random.fold_in(jax.random.PRNGKey(args.seed),
                                                                  run))
        controls, obs, poses, trees = make_log(key_log, truth, wobble)
        for v in variants:
            params = truth._replace(motion_outlier_probability=jnp.float32(v[1]),
                                    motion_outlier_scale=jnp.float32(v[2]))
            start = time.perf_counter()
            error, size, seen, _, _ = score(variant_config(v, particles), key_filter, params,
                                            controls, obs, poses, trees)
            if run > 0:
                seconds[v] += time.perf_counter() - start
            results[v].append((error, size, seen))
    print(f"regime {args.regime}, P = {particles}, {args.runs} runs, seed {args.seed}")
    for v, rows in results.items():
        rows = np.asarray(rows)
        print(f"{v}: median final error {np.median(rows[:, 0]):.3f} m, diverged (> 1 m) "
              f"{int(np.sum(rows[:, 0] > 1))}/{len(rows)}, map {np.median(rows[:, 1]):.0f} "
              f"landmarks for {np.median(rows[:, 2]):.0f} trees seen, "
              f"{seconds[v] / max(args.runs - 1, 1):.2f} s a run; errors "
              + " ".join(f"{e:.2f}" for e in rows[:, 0]))


if __name__ == "__main__":
    main()
