"""Divergence of the motion and the default proposal over turn rate, odometry noise and P.

Each point of the grid (wobble amplitude: the turn per step; odometry noise x Table 1 of
Geiser et al., ICAROB 2023; particle count P) runs R logs: ``--forests`` forests, each with
its own wobbly loop logs (``experiments/self_calibration.py``: 40 trees, 12 m range, 250 steps
of 0.5 m, a 5 mm / 0.5 mrad lidar, as in ``experiments/mixture_regime.py``), R / forests noise
draws each. The filter is given the true noise. All runs of a point are one ``jax.vmap`` of
``scan_filter`` (in chunks). Reported: the divergence rate (final position error > 1 m) with
its 95 % Wilson interval, the median final error, the landmarks per tree seen, and the cost
(run-steps per second of the batched filter after compilation; compile time apart).

    python experiments/proposal_study.py --runs 1000 --forests 50 --out docs/results/proposal_study.md
"""
from __future__ import annotations

import argparse
import ast
import dataclasses
import itertools
import sys
import pathlib
import time

import jax
import jax.numpy as jnp
import numpy as np
import scipy.stats

# Run this checkout's jaxslam, also when an editable install points at another checkout
# (an experiment started from a git worktree of an older commit).
sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

from experiments.mixture_regime import regime_params
from experiments.self_calibration import SIZE, wobbly_loop
from jaxslam.filter import make_filter, scan_filter
from jaxslam.geometry import compose, relative
from jaxslam.types import FilterConfig, default_params
from sims.forest import random_forest
from sims.scenario import build_scenario

CHI2_2DOF_95 = 5.991  # 95 % quantile of chi-square with 2 degrees of freedom
PROPOSALS = {
    # The seed paper's FastSLAM: motion proposal, Gaussian prior, first pose sampled.
    "motion": (dict(proposal="motion", anchor_empty_map=False),
               dict(motion_outlier_probability=0.0)),
    # FilterConfig() as shipped (observation proposal with its flags and default bursts).
    "default": ({}, {k: getattr(default_params(), k) for k in (
        "motion_outlier_probability", "motion_outlier_scale")}),
}


def proposal_settings(name: str) -> tuple[dict, dict]:
    """(FilterConfig fields, Params fields) of ``name``: a key of ``PROPOSALS``, optionally
    followed by ``:field=value,...`` overrides (FilterConfig fields when FilterConfig has
    them, else Params fields), e.g. ``default:motion_outlier_scale=16``."""
    base, _, extra = name.partition(":")
    if base not in PROPOSALS:
        raise SystemExit(f"unknown proposal {base!r}; expected one of {sorted(PROPOSALS)}")
    fields, param_fields = dict(PROPOSALS[base][0]), dict(PROPOSALS[base][1])
    for pair in filter(None, extra.split(",")):
        key, _, value = pair.partition("=")
        target = fields if key in {f.name for f in dataclasses.fields(FilterConfig)} else param_fields
        target[key] = ast.literal_eval(value)
    return fields, param_fields


def wilson(k: int, n: int, z: float = 1.96):
    """95 % Wilson score interval of a binomial rate k / n."""
    p = k / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * np.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return max(0.0, centre - half), min(1.0, centre + half)


def point_keys(seed: int, wobble: float, odometry: float):
    """(logs' key, filter runs' key) of one grid point: ``PRNGKey(seed)`` folded with
    round(1000 wobble + odometry), split once. ``make_logs`` draws forest f from
    ``fold_in(logs' key, f)``; the filter runs split the other key once a run, so no filter
    run reuses a key of the simulation (an earlier version took ``fold_in(key, 1)``, forest
    1's key, for the filters: their runs 0 and 1 drew with forest 1's forest and noise keys).
    """
    key = jax.random.fold_in(jax.random.PRNGKey(seed), int(round(1000 * wobble + odometry)))
    key_logs, key_filters = jax.random.split(key)
    return key_logs, key_filters


def clustered_interval(exceed, forests: int, level: float = 0.95):
    """Interval of a rate over R runs that come in ``forests`` equal blocks of runs on one
    forest each (``make_logs``' order), the forests as the sampled units.

    Runs on one forest share its trees and path, so they are not independent and a binomial
    interval (``wilson``) over runs is too narrow when the rate depends on the forest. With
    p_f the rate of forest f, p = mean_f p_f and SE = std_f(p_f) / sqrt(F) (the cluster
    sample's standard error; Cochran, "Sampling Techniques", 1977, ch. 9): p +- t SE, t the
    Student quantile with F - 1 degrees of freedom, clipped to [0, 1]. Never narrower than
    the Wilson interval on either side: with few forests and a rare event (no forest with a
    divergence, or one) the forests' spread says little, and the binomial width is the
    least uncertainty 1000 runs can have. exceed: (R,) bool, R a multiple of ``forests``
    (>= 2).
    """
    exceed = np.asarray(exceed, bool)
    if forests < 2 or exceed.size % forests:
        raise ValueError(f"need >= 2 forests dividing the {exceed.size} runs; got {forests}")
    rates = exceed.reshape(forests, -1).mean(axis=1)
    centre, error = rates.mean(), rates.std(ddof=1) / np.sqrt(forests)
    quantile = scipy.stats.t.ppf(0.5 + level / 2, forests - 1)
    low, high = wilson(int(exceed.sum()), exceed.size, scipy.stats.norm.ppf(0.5 + level / 2))
    return (max(0.0, min(low, centre - quantile * error)),
            min(1.0, max(high, centre + quantile * error)))


def make_logs(key, params, wobble: float, runs: int, forests: int):
    """Stacked logs of ``runs`` runs: controls (R, T, 3), observations (R, T, K), truth
    (R, T+1, 3), trees seen (R,)."""
    path = wobbly_loop(amplitude=wobble)
    dense = wobbly_loop(2000, amplitude=wobble)
    per_forest = runs // forests
    controls, obs, truth, seen = [], [], [], []
    for f in range(forests):
        key_forest, key_runs = jax.random.split(jax.random.fold_in(key, f))
        forest = random_forest(key_forest, 40, (SIZE, SIZE), keep_clear=dense[:, :2])
        scenario = build_scenario(key_runs, forest, path, per_forest, params=params, max_obs=12)
        controls.append(np.asarray(scenario.controls))
        obs.append(jax.tree.map(np.asarray, scenario.observations))
        truth.append(np.broadcast_to(np.asarray(scenario.poses), (per_forest,) +
                                     np.asarray(scenario.poses).shape[-2:]))
        ids = np.asarray(scenario.observations.landmark_id)
        valid = np.asarray(scenario.observations.valid)
        seen += [len(np.unique(ids[r][valid[r]])) for r in range(per_forest)]
    stack = lambda *xs: np.concatenate(xs)
    return (np.concatenate(controls), jax.tree.map(stack, *obs), np.concatenate(truth),
            np.asarray(seen))


def run_point(config, params, key, controls, obs, truth, chunk: int, run_ids=None,
              total_runs: int | None = None):
    """Final errors (R,), landmark counts (R,), final position NEES (R,), the first-step floor
    and the error with it removed (R,) each (``first_step_errors``), compile [s] and run [s]
    of the vmapped filter. Run r's key is ``split(key, R)[r]``; with ``run_ids`` (R,) the logs
    are a subset of a study of ``total_runs`` logs and log i takes that study's key
    ``split(key, total_runs)[run_ids[i]]`` (``select_runs``: a subset runs with the keys it
    has in the whole study; the split must be of the whole study's size, as a split's keys
    depend on its size unless ``jax_threefry_partitionable`` is on)."""
    filt = make_filter(config)

    def one(key, controls, obs, start, end):
        state = filt.init(start, dtype=controls.dtype)
        final, trace = scan_filter(config, key, state, params, controls, obs)
        w = jax.nn.softmax(final.log_weight)
        count = jnp.sum(w * jnp.sum(final.particles.active, -1))
        return (trace.mean_pose[-1], count, position_nees(final.particles.pose, w, end),
                trace.mean_pose[0])

    batched = jax.jit(jax.vmap(one))
    runs = controls.shape[0]
    keys = (jax.random.split(key, runs) if run_ids is None
            else jax.random.split(key, total_runs)[np.asarray(run_ids)])
    tick = time.perf_counter()
    sl = slice(0, chunk)
    compiled = batched.lower(keys[sl], controls[sl], jax.tree.map(lambda a: a[sl], obs),
                             truth[sl, 0], truth[sl, -1]).compile()
    compile_s = time.perf_counter() - tick
    finals, counts, nees, firsts, run_s = [], [], [], [], 0.0
    for lo in range(0, runs, chunk):
        sl = slice(lo, lo + chunk)
        tick = time.perf_counter()
        final, count, run_nees, first = compiled(keys[sl], controls[sl],
                                          jax.tree.map(lambda a: a[sl], obs), truth[sl, 0],
                                          truth[sl, -1])
        jax.block_until_ready(final)
        run_s += time.perf_counter() - tick
        finals.append(np.asarray(final))
        counts.append(np.asarray(count))
        nees.append(np.asarray(run_nees))
        firsts.append(np.asarray(first))
    final = np.concatenate(finals)
    error = np.hypot(*(final[:, :2] - truth[:, -1, :2]).T)
    floor, removed = first_step_errors(np.concatenate(firsts), final, truth)
    return (error, np.concatenate(counts), np.concatenate(nees), floor, removed, compile_s,
            run_s)


def select_runs(runs: int, forests: int, only_forests=None, per_forest=None) -> np.ndarray:
    """Ids (R',) of the logs of ``only_forests`` (default all), the first ``per_forest`` of
    each (default all ``runs // forests``), in ``make_logs``' order (forest f holds runs
    f * runs / forests onward)."""
    each = runs // forests
    chosen = range(forests) if only_forests is None else only_forests
    bad = [f for f in chosen if not 0 <= f < forests]
    if bad:
        raise ValueError(f"--only-forests {bad}: the study has forests 0..{forests - 1}")
    if len(set(chosen)) < len(chosen):
        raise ValueError(f"--only-forests {list(chosen)} names a forest twice; name each once")
    first = each if per_forest is None else per_forest
    if not 1 <= first <= each:
        raise ValueError(f"--per-forest {first}: each forest has {each} logs; expected 1..{each}")
    return np.concatenate([np.arange(f * each, f * each + first) for f in chosen])


def longest_sparse_stretch(valid, most: int = 2):
    """(R,) the longest run of consecutive steps of each log with at most ``most`` valid
    observations (``valid`` (R, T, K)): where the map holds the pose only weakly."""
    sparse = np.asarray(valid).sum(-1) <= most
    longest = np.zeros(sparse.shape[0], int)
    current = np.zeros(sparse.shape[0], int)
    for column in sparse.T:
        current = np.where(column, current + 1, 0)
        longest = np.maximum(longest, current)
    return longest


def first_step_errors(first, final, truth):
    """The part of the final error that the first step's pose error fixes, and the rest.

    The map's frame is the first estimated pose e_1 (R, 3) (the weighted mean after step 1;
    with ``anchor_empty_map`` every particle's, the motion mean): a perfect filter from there
    ends at e_1 (+) (x_1^-1 (+) x_T), x_1, x_T the true poses. Returns that floor's final
    position error (R,) and the filter's final error with the first-step error removed,
    |x_1 (+) (e_1^-1 (+) final) - x_T| (R,) (for the motion proposal, whose particles start
    from different poses, only the weighted mean's first-step error is removed).
    """
    first, final, true_first, true_final = (jnp.asarray(a) for a in (
        first, final, truth[:, 1], truth[:, -1]))
    perfect = compose(first, relative(true_first, true_final))
    removed = compose(true_first, relative(first, final))
    distance = lambda a: np.hypot(*np.asarray(a[:, :2] - true_final[:, :2]).T)
    return distance(perfect), distance(removed)


def position_nees(pose, weight, truth):
    """(e^T C^-1 e) () of the final position: e = truth - weighted mean, C the particles'
    weighted position covariance (P, 3) poses, (P,) weights, (3,) truth, plus 1 mm^2 so a
    collapsed particle set stays invertible. Under a consistent filter it is chi-square with
    2 degrees of freedom: the 95 % ellipse holds the truth when it is <= 5.991."""
    mean = weight @ pose[:, :2]
    diff = pose[:, :2] - mean[None, :]
    cov = (diff * weight[:, None]).T @ diff + 1e-6 * jnp.eye(2, dtype=pose.dtype)
    error = truth[:2] - mean
    return error @ jnp.linalg.solve(cov, error)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=1000)
    parser.add_argument("--forests", type=int, default=50)
    parser.add_argument("--chunk", type=int, default=250)
    parser.add_argument("--seed", type=int, default=700)
    parser.add_argument("--wobble", type=float, nargs="+", default=[0.0, 0.3])
    parser.add_argument("--odometry", type=float, nargs="+", default=[2.0, 6.0])
    parser.add_argument("--particles", type=int, nargs="+", default=[20])
    parser.add_argument("--proposals", nargs="+", default=list(PROPOSALS))
    parser.add_argument("--out", default=None, help="markdown file for the table")
    parser.add_argument("--errors", default=None,
                        help=".npz file for the per-run final errors of every row")
    parser.add_argument("--only-forests", type=int, nargs="+", default=None,
                        help="run only these forests' logs (0-based), with the keys they have "
                             "in the whole study")
    parser.add_argument("--per-forest", type=int, default=None,
                        help="run only the first N logs of each forest")
    args = parser.parse_args(argv)
    if args.runs % args.forests:
        raise SystemExit("--runs must be a multiple of --forests")
    try:
        run_ids = select_runs(args.runs, args.forests, args.only_forests, args.per_forest)
    except ValueError as error:
        raise SystemExit(str(error))
    subset = not np.array_equal(run_ids, np.arange(args.runs))
    forests = len(args.only_forests) if args.only_forests is not None else args.forests
    runs = run_ids.size
    if runs % min(args.chunk, runs):
        raise SystemExit(f"--chunk must divide the {runs} logs run (--runs, or the "
                         f"--only-forests / --per-forest subset)")
    rows, per_run = [], {}
    for wobble, odometry in itertools.product(args.wobble, args.odometry):
        truth_params = regime_params(odometry, "lidar")
        key_logs, key_filters = point_keys(args.seed, wobble, odometry)
        tick = time.perf_counter()
        controls, obs, truth, seen = make_logs(key_logs, truth_params, wobble, args.runs,
                                               args.forests)
        if subset:
            controls, truth, seen = controls[run_ids], truth[run_ids], seen[run_ids]
            obs = jax.tree.map(lambda a: a[run_ids], obs)
        per_run[f"{wobble:g}/{odometry:g}/sparsest"] = longest_sparse_stretch(obs.valid)
        print(f"wobble {wobble} m, odometry {odometry}x: {runs} logs in "
              f"{time.perf_counter() - tick:.0f} s", flush=True)
        for particles, name in itertools.product(args.particles, args.proposals):
            fields, param_fields = proposal_settings(name)
            config = FilterConfig(num_particles=particles, max_landmarks=96, max_obs=12,
                                  **fields)
            params = truth_params._replace(**{k: jnp.asarray(v, jnp.float32)
                                              for k, v in param_fields.items()})
            error, count, nees, floor, removed, compile_s, run_s = run_point(
                config, params, key_filters, controls, obs, truth,
                min(args.chunk, runs), run_ids if subset else None, args.runs)
            diverged = int(np.sum(error > 1.0))
            low, high = wilson(diverged, runs)
            forest_text = ("n/a (one forest)" if forests < 2 else
                           "[{:.1f}, {:.1f}]".format(*(100 * np.asarray(
                               clustered_interval(error > 1.0, forests)))))
            rate = runs * controls.shape[1] / run_s
            row = (f"| {wobble:g} | {odometry:g} | {particles} | {name} | {runs} | "
                   f"{100 * diverged / runs:.1f} % [{100 * low:.1f}, {100 * high:.1f}] | "
                   f"{forest_text} | "
                   f"{np.median(error):.3f} | {100 * np.mean(floor > 1.0):.1f} % | "
                   f"{100 * np.mean(removed > 1.0):.1f} % | {np.median(removed):.3f} | "
                   f"{np.median(count / np.maximum(seen, 1)):.2f} | "
                   f"{np.median(nees):.3g} | {100 * np.mean(nees <= CHI2_2DOF_95):.1f} % | "
                   f"{rate:.3g} | {compile_s:.1f} |")
            print(row, flush=True)
            rows.append(row)
            per_run[f"{wobble:g}/{odometry:g}/{particles}/{name}"] = error
    if args.errors:
        np.savez(args.errors, **per_run)
    table = ("| wobble [m] | odometry x Table 1 | P | proposal | runs | diverged [95 % CI, "
             "runs independent] | 95 % CI, forests as units | "
             "median final error [m] | floor: first-step error alone > 1 m | diverged, "
             "first-step error removed | median, first-step error removed [m] | landmarks / "
             "trees seen (median) | final position NEES (median) | 95 % ellipse holds the "
             "truth | run-steps/s | compile [s] |\n"
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|\n"
             + "\n".join(rows))
    print(table)
    if args.out:
        command = "python experiments/proposal_study.py " + " ".join(argv or sys.argv[1:])
        pathlib.Path(args.out).write_text(table + "\n")
        print(f"written to {args.out} ({command.strip()})")


if __name__ == "__main__":
    main()
