"""How far back all particles share one ancestor, against how long a landmark goes unseen.

A diagnostic for UTIAS MRCLAM dataset 1 (Leung, Halpern, Barfoot and Liu, IJRR 2011); nothing
here sets a filter setting. For each robot the pipeline fits the commands' lag and calibrates
from the log (``pipeline.filter_log(..., command_delay="auto")``, key ``--seed``), as
``experiments/mrclam.py`` does. Then the filter runs with the lineage recorded, at each
particle count of ``--particles`` and with each filter key (100, 101, ...).

For each step t, ``common_ancestor_depth`` walks the ancestors back until every particle of
step t descends from one particle of an earlier step. The number of steps back is the depth of
the most recent common ancestor. When a landmark was last seen before that ancestor, every
particle's map of it descends from one map (changed since only by what each particle matched
to it). The cloud's spread against such a landmark then comes only from the steps since the
ancestor, not from the whole time the landmark was out of view.
FastSLAM's loss of path diversity is this depth being short.

``resighting_gaps`` lists each re-sighting of a barcode (a step that observes a barcode seen
before) with the steps since that barcode was last observed. The barcodes only diagnose here.
The script prints, per run, the depth's median and 90th percentile, and the share of the
re-sightings after a pause of over ``--pause`` steps whose landmark was last seen before the
common ancestor of the cloud that receives them (``beyond_depth_share``).

    python experiments/mrclam_ancestry.py [--robots 1 4] [--particles 100 1000] [--filter-keys 2]
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

from jaxslam import metrics, pipeline  # noqa: E402
from jaxslam.datasets.mrclam import read_mrclam  # noqa: E402
from jaxslam.datasets.mrclam_convert import DEFAULT_MAX_OBS, mrclam_log, mrclam_steps  # noqa: E402
from jaxslam.filter import run_filter  # noqa: E402
from jaxslam.types import FilterConfig  # noqa: E402

DATA = pathlib.Path(__file__).resolve().parents[2] / "shared" / "data" / "mrclam1"


def common_ancestor_depth(ancestor) -> np.ndarray:
    """(T,) int: for each step t, the smallest d >= 1 such that every particle after step t
    descends from one particle after step t - d; t + 1 when they do not share one (the
    start, before step 0, is one pose for all of them).

    Args:
      ancestor: (T, P) ints, ``Lineage.ancestor``: particle i after step t is a copy of
        particle ancestor[t, i] after step t - 1.
    """
    ancestor = np.asarray(ancestor)
    if ancestor.ndim != 2:
        raise ValueError(f"ancestor must be (T, P); got shape {ancestor.shape}")
    depth = np.empty(ancestor.shape[0], np.int64)
    for t in range(ancestor.shape[0]):
        lines = np.unique(ancestor[t])  # particles after step t - 1 with descendants at t
        back = 1
        while lines.size > 1 and t - back >= 0:
            lines = np.unique(ancestor[t - back][lines])
            back += 1
        depth[t] = back if lines.size == 1 else t + 1
    return depth


def resighting_gaps(landmark, valid) -> np.ndarray:
    """(N, 2) int rows (step, gap): each step that observes a landmark seen at an earlier
    step, with the steps since its last observation (a landmark seen twice in one step
    counts once). Steps are >= 1.

    Args:
      landmark: (T, K) landmark id of each observation (negative: none); valid: (T, K) bool.
    """
    landmark, valid = np.asarray(landmark), np.asarray(valid, bool)
    if landmark.shape != valid.shape or landmark.ndim != 2:
        raise ValueError(f"landmark and valid must be (T, K) alike; got {landmark.shape} and "
                         f"{valid.shape}")
    last, rows = {}, []
    for t in range(landmark.shape[0]):
        for seen in np.unique(landmark[t][valid[t] & (landmark[t] >= 0)]).tolist():
            if seen in last:
                rows.append((t, t - last[seen]))
            last[seen] = t
    return np.asarray(rows, np.int64).reshape(-1, 2)


def beyond_depth_share(gaps, depth, pause: int) -> tuple[float, float]:
    """(share of the re-sightings after a gap over ``pause``, share of those that come after
    the common ancestor of the cloud that receives them); NaN where there are none.

    A re-sighting at step t with gap g meets the cloud after step t - 1 (step t's own
    resampling is weighed by it, so ``depth[t]`` would be cut short by the re-sighting
    itself). That cloud's common ancestor is the particle after step t - 1 - depth[t - 1],
    which already holds the landmark's last sighting (step t - g) exactly when
    g > depth[t - 1].
    """
    gaps = np.asarray(gaps).reshape(-1, 2)
    if len(gaps) and gaps[:, 0].min() < 1:  # step 0 has no cloud before it to judge by
        raise ValueError(f"re-sighting steps must be >= 1 (``resighting_gaps``' rows); got "
                         f"{int(gaps[:, 0].min())}")
    paused = gaps[:, 1] > pause
    if not paused.any():
        return (float(np.mean(paused)) if len(gaps) else float("nan")), float("nan")
    beyond = gaps[paused, 1] > np.asarray(depth)[gaps[paused, 0] - 1]
    return float(np.mean(paused)), float(np.mean(beyond))


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", default=str(DATA),
                        help="the MRCLAM dataset 1 folder (default: ../shared/data/mrclam1 beside "
                             "the repository)")
    parser.add_argument("--robots", type=int, nargs="+", default=[1, 4],
                        help="robots 1-5 (default: 1 4)")
    parser.add_argument("--particles", type=int, nargs="+", default=[100, 1000],
                        help="particle counts of the filter runs (default: 100 1000); the "
                             "calibration runs at 100")
    parser.add_argument("--filter-keys", type=int, default=2,
                        help="filter keys 100, 101, ... per particle count (default: 2)")
    parser.add_argument("--pause", type=int, default=20,
                        help="re-sightings after more steps than this count as after a "
                             "pause (default: 20)")
    parser.add_argument("--seed", type=int, default=0,
                        help="the key of the lag fit and the calibration (default: 0)")
    args = parser.parse_args(argv)
    if min(args.particles) < 1 or args.filter_keys < 1 or args.pause < 0:
        parser.error("--particles needs counts of 1 or more, --filter-keys 1 or more and "
                     f"--pause 0 or more; got {args.particles}, {args.filter_keys} and "
                     f"{args.pause}")
    if not set(args.robots) <= {1, 2, 3, 4, 5}:
        parser.error(f"--robots {args.robots}: MRCLAM dataset 1 has robots 1-5")
    for robot in args.robots:
        raw = read_mrclam(args.data, robot)
        steps = mrclam_steps(raw, DEFAULT_MAX_OBS)
        log = mrclam_log(raw, steps)
        config = FilterConfig(num_particles=100, max_landmarks=64, max_obs=DEFAULT_MAX_OBS)
        run = pipeline.filter_log(log, config, key=jax.random.PRNGKey(args.seed),
                                  calibrate=True, command_delay="auto")
        log = log.at_command_delay(run.delay_fit.delay)
        gaps = resighting_gaps(steps.obs_landmark, log.obs_valid)
        truth = np.asarray(log.truth_pose)
        print(f"robot {robot}: lag {run.delay_fit.delay:.3f} s, {len(gaps)} re-sightings, "
              f"median gap {np.median(gaps[:, 1]):.0f} steps", flush=True)
        for particles in args.particles:
            inputs = pipeline.log_inputs(
                log, FilterConfig(num_particles=particles, max_landmarks=64,
                                  max_obs=DEFAULT_MAX_OBS))
            filter_config, controls, obs, start = inputs
            for key in range(100, 100 + args.filter_keys):
                _, trace = run_filter(filter_config, jax.random.PRNGKey(key), run.params,
                                      controls, obs, jnp.asarray(start, jnp.float32),
                                      record_lineage=True)
                depth = common_ancestor_depth(trace.lineage.ancestor)
                paused, beyond = beyond_depth_share(gaps, depth, args.pause)
                ate = metrics.ate_rmse(np.asarray(trace.mean_pose, np.float64), truth)
                print(f"  P = {particles}, key {key}: ATE {ate:.3f} m | common ancestor "
                      f"depth median {np.median(depth):.0f} steps (90th percentile "
                      f"{np.percentile(depth, 90):.0f}) | re-sightings after a pause of over "
                      f"{args.pause} steps {paused:.1%}, of those beyond the depth "
                      f"{beyond:.1%}", flush=True)


if __name__ == "__main__":
    main()
