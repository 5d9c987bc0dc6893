"""Why the blind association splits MRCLAM's landmarks: three diagnostics, nothing chosen.

Vicon and the barcodes only look here; no setting printed is one the pipeline uses. For each
robot the pipeline calibrates from the log (``pipeline.filter_log``, P = 100, 64 slots, key
``--seed``), then:

1. **Re-sightings by the pause before them.** Along the best particle's history
   (``lineage.landmark_identities``), each observation of a barcode seen before either keeps
   the identity of that barcode's previous observation or has another (a new landmark, or
   rarely another tree's). Binned by the filter steps since the barcode was last observed
   (a step is a measurement time or a 1 s filler; ``mrclam_convert``). Also: identities
   whose observations carry more than one barcode, and their observations of another
   barcode than the identity's most frequent one.
2. **The detection rate per filter step in view.** From the Vicon poses and landmarks (rows
   as sighted, ``mrclam_convert.landmarks_as_sighted``), the share of (step, landmark) pairs
   inside the calibrated miss region (range <= ``miss_range``, |bearing| <=
   ``miss_bearing``, as the filter counts misses) whose barcode the robot reported that step,
   against the calibrated ``detection_probability``; the same share one step after a
   detection and one step after a miss (the filter's existence update takes misses as
   independent); and the runs of misses at least as long as the run that deletes a landmark
   at the existence cap under the calibrated settings (``misses_to_delete``).
3. **The filter with one group of the calibrated settings changed** (``--variants``), over
   ``--filter-keys`` filter keys (100, 101, ...): median ATE ratio (dead reckoning / filter),
   identities started along the best history, landmarks kept.

    python experiments/mrclam_diagnostics.py [--robots 1 2 3 4 5] [--seed 0] [--filter-keys 6]

Variants (each applied to the calibrated Params, nothing else changed):
  calibrated    as calibrated;
  no_delete     existence cap 50 and deletion at -49.9 (a landmark is practically never
                deleted);
  pd_0.4        detection_probability 0.4 (about the detection rate per step in view, item 2: a
                value read off Vicon, so a diagnostic only);
  pd_0.2        detection_probability 0.2, about the rate one step after a miss (item 2): in a
                run of misses each costs what a detection model with memory would charge
                after the first (a hit's log-odds gain changes less, p_f being 0.002-0.012);
  range_x3_no_delete  the range noise x3 and no deletion.
"""
from __future__ import annotations

import argparse
import pathlib
import sys
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

from jaxslam import metrics, pipeline  # noqa: E402
from jaxslam.datasets.mrclam import read_mrclam  # noqa: E402
from jaxslam.datasets.mrclam_convert import (  # noqa: E402
    DEFAULT_MAX_OBS,
    landmarks_as_sighted,
    mrclam_log,
    mrclam_steps,
)
from jaxslam.datasets.odometry import odometry_path  # noqa: E402
from jaxslam.filter import estimate, run_filter  # noqa: E402
from jaxslam.geometry import range_bearing  # noqa: E402
from jaxslam.lineage import landmark_identities, trace_lineage  # noqa: E402
from jaxslam.types import FilterConfig  # noqa: E402

DATA = pathlib.Path(__file__).resolve().parents[2] / "shared" / "data" / "mrclam1"
GAP_BINS = ((1, 2), (2, 5), (5, 20), (20, 100), (100, None))
NO_DELETE = dict(existence_max=50.0, existence_delete=-49.9)
VARIANTS = {
    "calibrated": lambda p: {},
    "no_delete": lambda p: NO_DELETE,
    "pd_0.4": lambda p: dict(detection_probability=0.4),
    "pd_0.2": lambda p: dict(detection_probability=0.2),
    "range_x3_no_delete": lambda p: dict(range_noise=np.asarray(p.range_noise) * 3.0,
                                         **NO_DELETE),
}


def resighting_gaps(ids, barcode, valid):
    """[(bin, kept, new)] over ``GAP_BINS``: re-sightings of a barcode that keep / change the
    identity of its previous observation, by steps since it.

    ids (T, K) identities (-1: none), barcode (T, K) (-1: none), valid (T, K); observations
    without both are skipped. A barcode read twice in one step (gap 0) is in no bin.
    """
    last_step, last_id = {}, {}
    gaps, changed = [], []
    for t, k in zip(*np.nonzero(valid & (ids >= 0) & (barcode >= 0))):
        b = int(barcode[t, k])
        if b in last_step:
            gaps.append(t - last_step[b])
            changed.append(ids[t, k] != last_id[b])
        last_step[b], last_id[b] = t, ids[t, k]
    gaps, changed = np.asarray(gaps), np.asarray(changed, bool)
    rows = []
    for low, high in GAP_BINS:
        inside = (gaps >= low) & (gaps < (np.inf if high is None else high))
        rows.append(((low, high), int(np.sum(inside & ~changed)), int(np.sum(inside & changed))))
    return rows


def mixed_identities(ids, barcode, valid):
    """(identities whose observations carry more than one barcode, observations of another
    barcode than their identity's most frequent one); ids, barcode, valid (T, K)."""
    used = valid & (ids >= 0) & (barcode >= 0)
    pairs = np.unique(np.stack([ids[used], barcode[used]], 1), axis=0, return_counts=True)
    identity, counts = pairs[0][:, 0], pairs[1]
    mixed, off_majority = 0, 0
    for value in np.unique(identity):
        mine = counts[identity == value]
        if len(mine) > 1:
            mixed += 1
            off_majority += int(mine.sum() - mine.max())
    return mixed, off_majority


def misses_to_delete(params) -> int:
    """Consecutive misses that take a landmark from the existence cap below the deletion
    threshold: ceil((cap - threshold) / -log((1 - p_d) / (1 - p_f))) (``landmarks``'
    existence update). ValueError when p_d <= p_f: a miss then never lowers the log-odds."""
    per_miss = -np.log((1.0 - float(params.detection_probability))
                       / (1.0 - float(params.false_alarm_probability)))
    if not per_miss > 0.0:
        raise ValueError(f"detection_probability={float(params.detection_probability)} <= "
                         f"false_alarm_probability={float(params.false_alarm_probability)}: "
                         "misses never delete a landmark")
    span = float(params.existence_max) - float(params.existence_delete)
    return int(np.ceil(span / per_miss))


class CameraRate(NamedTuple):
    """The camera's detections of the Vicon landmarks in a miss region.

    rate: share of in-region (step, landmark) pairs whose barcode was reported that step
      (nan with no such pair);
    after_detection / after_miss: the same share over the pairs whose landmark was also in
    the region the step before and was reported / not reported then (nan with no such pair);
    long_runs / runs: runs of consecutive in-region steps without the barcode, those of
    ``miss_run`` steps or more and all of them.
    """

    rate: float
    after_detection: float
    after_miss: float
    long_runs: int
    runs: int


def camera_detection_rate(truth_pose, landmarks, barcode, valid, miss_range, miss_bearing,
                          miss_run: int) -> CameraRate:
    """``CameraRate`` of Vicon poses (T, 3) and landmarks (N, 2) (row i where the readings
    of barcode index i lie), the reported barcodes (T, K) (-1 padding) and valid (T, K), in
    the region range <= miss_range and |bearing| <= miss_bearing."""
    predicted = np.asarray(range_bearing(jnp.asarray(truth_pose)[:, None],
                                         jnp.asarray(landmarks)[None]))
    in_view = (predicted[..., 0] <= miss_range) & (np.abs(predicted[..., 1]) <= miss_bearing)
    seen = np.zeros_like(in_view)
    t, k = np.nonzero(valid & (barcode >= 0))
    seen[t, barcode[t, k]] = True
    missed = in_view & ~seen
    runs = []
    for column in missed.T:
        edges = np.diff(np.concatenate([[0], column.astype(np.int8), [0]]))
        runs.extend(np.nonzero(edges == -1)[0] - np.nonzero(edges == 1)[0])
    runs = np.asarray(runs)
    both = in_view[1:] & in_view[:-1]

    def share(mask, outcomes=seen[1:]):
        return float(outcomes[mask].mean()) if mask.any() else float("nan")
    return CameraRate(share(in_view, seen), share(both & seen[:-1]),
                      share(both & ~seen[:-1]), int(np.sum(runs >= miss_run)), len(runs))


class VariantRuns(NamedTuple):
    """Filter runs of one setting over several PRNG keys (``filter_variant``).

    median: median ratio; ratios: dead reckoning's ATE over each run's online mean path's;
    identities: median identities started along the best history; kept: median landmarks
    kept at the end; smoothed: dead reckoning's ATE over each run's smoothed best history
    (``pipeline.offline_path``, as ``filter_log(..., smooth=True)``), () unless asked for.
    """

    median: float
    ratios: list
    identities: float
    kept: float
    smoothed: tuple = ()


def filter_variant(params, inputs, truth, dead_reckoning_ate, keys, smooth: bool = False,
                   close_loops: bool = False) -> VariantRuns:
    """``VariantRuns`` of filter runs with ``params`` over the PRNG keys ``keys``: inputs =
    ``pipeline.log_inputs``' (config, controls, observations, start); truth (T, 3) Vicon
    poses; ratio = dead reckoning's ATE over the run's. With ``smooth`` each run's best
    history is also smoothed as the pipeline smooths it (``pipeline.offline_path`` with the
    config's motion model, and ``close_loops`` as ``filter_log``'s; NaN for a run whose
    smoother fails)."""
    config, controls, obs, start = inputs
    ratios, identities, kept, smoothed = [], [], [], []
    for key in keys:
        final, trace = run_filter(config, jax.random.PRNGKey(key), params, controls, obs,
                                  jnp.asarray(start, jnp.float32), record_lineage=True)
        ate = metrics.ate_rmse(np.asarray(trace.mean_pose, np.float64), truth)
        path = trace_lineage(trace.lineage, estimate(final).best_particle)
        identities.append(landmark_identities(path.match, path.birth_slot)[1])
        kept.append(int(np.asarray(trace.num_landmarks)[-1]))
        ratios.append(float(dead_reckoning_ate / ate))
        if smooth:
            try:
                poses, _ = pipeline.offline_path(path, controls, obs, start, params,
                                                 config.motion_model, close_loops=close_loops)
            except (RuntimeError, np.linalg.LinAlgError, ValueError):  # e.g. a non-finite path
                smoothed.append(float("nan"))
                continue
            smoothed.append(float(dead_reckoning_ate
                                  / metrics.ate_rmse(np.asarray(poses, np.float64), truth)))
    return VariantRuns(float(np.median(ratios)), ratios, float(np.median(identities)),
                       float(np.median(kept)), tuple(smoothed))


def robot_report(data, robot, seed, filter_keys, variants):
    """Calibrate robot ``robot``'s log with key ``seed`` and print the three diagnostics
    (module docstring), each variant over ``filter_keys`` filter keys."""
    raw = read_mrclam(data, robot)
    steps = mrclam_steps(raw, DEFAULT_MAX_OBS)
    log = mrclam_log(raw, steps)
    config = FilterConfig(num_particles=100, max_landmarks=64, max_obs=DEFAULT_MAX_OBS)
    run = pipeline.filter_log(log, config, key=jax.random.PRNGKey(seed), calibrate=True)
    params = run.params
    truth = np.asarray(log.truth_pose)
    dead_reckoning = np.asarray(odometry_path(log.controls, log.initial_pose))
    dr_ate = metrics.ate_rmse(dead_reckoning, truth)
    barcode = np.asarray(steps.obs_landmark)
    valid = np.asarray(log.obs_valid)

    path = trace_lineage(run.trace.lineage, run.estimate.best_particle)
    ids, count = landmark_identities(path.match, path.birth_slot)
    print(f"robot {robot}: dead reckoning ATE {dr_ate:.3f} m; pipeline filter ATE "
          f"{run.metrics['ate_rmse']:.3f} m; {count} identities along the best history for "
          f"{len(np.unique(barcode[valid & (barcode >= 0)]))} barcodes", flush=True)
    mixed, off_majority = mixed_identities(ids, barcode, valid)
    print(f"  {mixed} identities carry more than one barcode ({off_majority} of "
          f"{int(valid.sum())} observations off their identity's most frequent barcode)")
    for (low, high), kept, new in resighting_gaps(ids, barcode, valid):
        span = f"{low}+" if high is None else f"{low}-{high - 1}"
        share = new / max(kept + new, 1)
        print(f"  re-sightings after {span:>6s} steps: {kept} kept the identity, {new} "
              f"did not ({share:.0%})")
    miss_run = misses_to_delete(params)
    camera = camera_detection_rate(truth, landmarks_as_sighted(log.truth_landmarks), barcode,
                                   valid, float(params.miss_range),
                                   float(params.miss_bearing), miss_run)
    print(f"  detection rate per step in the miss region {camera.rate:.2f} against "
          f"calibrated p_d {float(params.detection_probability):.2f} (after a detection "
          f"{camera.after_detection:.2f}, after a miss {camera.after_miss:.2f}); "
          f"{camera.long_runs} of {camera.runs} runs of misses last {miss_run} steps or more "
          f"(the run that deletes a landmark at the cap)")
    inputs = pipeline.log_inputs(log, config)
    keys = range(100, 100 + filter_keys)
    for name in variants if filter_keys > 0 else ():
        changed = params._replace(**{field: jnp.asarray(value, jnp.float32) for field, value
                                     in VARIANTS[name](params).items()})
        median, ratios, identities, kept, _ = filter_variant(changed, inputs, truth, dr_ate,
                                                             keys)
        print(f"  {name:20s} ratio median {median:.2f}x "
              f"({', '.join(f'{r:.2f}' for r in ratios)}); identities {identities:.0f}; "
              f"landmarks kept {kept:.0f}", flush=True)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", default=str(DATA))
    parser.add_argument("--robots", type=int, nargs="+", default=[1, 2, 3, 4, 5])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--filter-keys", type=int, default=6,
                        help="filter keys a variant runs with (0: no variant runs)")
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS),
                        choices=list(VARIANTS))
    args = parser.parse_args(argv)
    for robot in args.robots:
        robot_report(args.data, robot, args.seed, args.filter_keys, args.variants)


if __name__ == "__main__":
    main()
