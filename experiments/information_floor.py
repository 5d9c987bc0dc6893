"""The information floor of the proposal study's logs: the batch MAP with the true association.

For each log of ``experiments/proposal_study.py`` (the same ``make_logs``, seed and settings,
so the logs are bit-identical) this solves GraphSLAM's least squares (Thrun et al.,
Probabilistic Robotics, ch. 11; ``jaxslam.smoothing.smooth_path``)

    min_{x_{0:T-1}, m}  sum_t || C_t^-1 (x_{t-1} (-) x_t - delta_t) ||^2
                      + sum_{t,k} || diag(sigma_r, sigma_b)^-1 (h(x_t, m_{j(t,k)}) - z_{t,k}) ||^2

with j(t, k) the simulator's TRUE tree of each valid observation, the TRUE noise (the
``Params`` the study gives the filter; the smoother's move model is Eq. (1)'s Gaussian, which
is how the simulator draws the odometry, so the filter's burst fields play no part), a pure
Gaussian cost (Huber threshold 1e6 whitened units: never reached) and no calibration rounds.
x_{-1} is the true start pose, as the filter's.

The last pose's filtering posterior p(x_T | z_{1:T}, u_{1:T}) is a marginal of the smoothing
posterior over the whole path, so the MAP path's last pose is (to the Laplace approximation)
the estimate an ideal filter approaches: if it ends more than 1 m off on X % of logs, no
filter can be expected to do better than about X % there.

The least squares is not convex. It is solved twice per log, from dead reckoning and from
the true path (an optimiser started at the truth is fair for a bound, never for an
estimate: the truth only picks a start, the cost picks the answer), and the solution with
the lower cost is kept. Landmarks start at the mean of their inverse observations from the
starting path (``initial_landmarks``).

Per log: the MAP's final position error, its first-step position error, the longest stretch
with <= 2 valid observations (``proposal_study.longest_sparse_stretch``), both starts'
costs and final errors, and the cost at the truth (true path and true tree centres).
Optionally the default filter (``FilterConfig()`` as the study runs it) at some particle
counts on the same logs (``proposal_study.run_point``, the study's keys).

    python experiments/information_floor.py --runs 1000 --forests 50 --seed 700 \
        --particles 20 --out results/information_floor/held_out
    python experiments/information_floor.py --runs 1000 --forests 50 --seed 700 --first 200 \
        --no-smooth --particles 20 100 --out results/information_floor/first200_p20_p100
"""
from __future__ import annotations

import argparse
import pathlib
import sys
import time
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

# Run this checkout's jaxslam, also when an editable install points at another checkout
# (an experiment started from a git worktree of an older commit).
sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

from experiments.mixture_regime import regime_params
from experiments.proposal_study import (clustered_interval, longest_sparse_stretch, make_logs,
                                        point_keys, proposal_settings, run_point, wilson)
from jaxslam.smoothing import move_whitening, observation_std, smooth_path
from jaxslam.smoothing import problem as least_squares
from jaxslam.types import FilterConfig, Params

PURE_GAUSSIAN = 1e6  # Huber threshold [whitened units] far beyond any residual: plain squares
SPARSE_BINS = ((0, 10), (10, 20), (20, 40), (40, 80), (80, 10**9))  # longest <= 2-obs stretch


class LogFloor(NamedTuple):
    """One log's MAP with the true association (errors [m] are final positions unless named).

    error: the kept (lower-cost) solution's; first_error: its first pose's; from_dead_reckoning,
    from_truth: each start's final error; cost_dead_reckoning, cost_truth: each start's final
    cost; cost_at_truth: the cost at the true path and true tree centres; chi2_at_truth: (4,)
    mean squared whitened residual there per group (heading, translation, range, bearing
    rows; 1 when the model's noise is the simulator's); dead_reckoning: the dead-reckoning
    path's own final error; converged: the kept solve converged (else it stopped at
    ``iterations``); iterations: the two solves' LM steps together.
    """

    error: float
    first_error: float
    from_dead_reckoning: float
    from_truth: float
    cost_dead_reckoning: float
    cost_truth: float
    cost_at_truth: float
    chi2_at_truth: np.ndarray
    dead_reckoning: float
    converged: bool
    iterations: int


def true_associations(landmark_id, valid):
    """Compact true landmark indices of one log's observations.

    Args:
      landmark_id: (T, K) the simulator's tree index of each observation; valid: (T, K).
    Returns:
      landmark_of_obs (T, K): index into ``trees`` of each valid observation, -1 for invalid
      ones; trees (L,): the tree index of each landmark (the trees seen, ascending).
    """
    landmark_id, valid = np.asarray(landmark_id), np.asarray(valid, bool)
    trees = np.unique(landmark_id[valid])
    index = np.searchsorted(trees, np.where(valid, landmark_id, trees[0] if trees.size else 0))
    return np.where(valid, index, -1), trees


def dead_reckoning(start, odometry):
    """(T, 3) poses after each measured move (rot1, trans, rot2) (T, 3) from ``start`` (3,),
    in float64 (``motion.apply_odometry`` step by step)."""
    pose = np.asarray(start, np.float64).copy()
    path = np.empty((len(odometry), 3))
    for t, (rot1, trans, rot2) in enumerate(np.asarray(odometry, np.float64)):
        heading = pose[2] + rot1
        pose = np.array([pose[0] + trans * np.cos(heading), pose[1] + trans * np.sin(heading),
                         np.angle(np.exp(1j * (heading + rot2)))])
        path[t] = pose
    return path


def gaussian_cost(start, path, landmark, odometry, z, landmark_of_obs, params: Params):
    """The smoother's least-squares cost (pure Gaussian, noise scales 1) at poses (T, 3) and
    landmark positions (L, 2), and the mean squared whitened residual (4,) of its heading,
    translation, range and bearing rows; the other arguments as ``smooth_path``'s."""
    delta, move_white = move_whitening(np.asarray(odometry, np.float64), params)
    obs_t, obs_k = np.nonzero(landmark_of_obs >= 0)
    z_obs = np.asarray(z, np.float64)[obs_t, obs_k]
    problem = least_squares.Problem(np.asarray(start, np.float64), delta, move_white, obs_t,
                                    landmark_of_obs[obs_t, obs_k], z_obs,
                                    observation_std(z_obs[:, 0], params), PURE_GAUSSIAN)
    white = least_squares.whitened(problem, np.asarray(path, np.float64),
                                   np.asarray(landmark, np.float64))
    groups = np.array([np.mean(white.move[:, 0] ** 2), np.mean(white.move[:, 1:] ** 2),
                       np.mean(white.obs[:, 0] ** 2), np.mean(white.obs[:, 1] ** 2)])
    return float(least_squares.robust_cost(problem, white)[0]), groups


def floor_of_log(start, odometry, z, landmark_id, valid, truth_path, trees_xy,
                 params: Params, iterations: int = 200, tol: float = 1e-10) -> LogFloor:
    """``LogFloor`` of one log: ``smooth_path`` from dead reckoning and from the truth.

    Args:
      start: (3,) true start pose; odometry: (T, 3) measured moves; z: (T, K, 2);
      landmark_id, valid: (T, K) the simulator's tree indices and validity; truth_path:
      (T, 3) true poses after each move; trees_xy: (N, 2) true tree centres;
      params: the true noise. iterations, tol: ``smooth_path``'s.
    """
    landmark_of_obs, trees = true_associations(landmark_id, valid)
    z = np.where(np.asarray(valid)[..., None], np.asarray(z, np.float64), 0.0)
    solve = lambda init: smooth_path(start, init, odometry, z, landmark_of_obs, params,
                                     iterations=iterations, huber=PURE_GAUSSIAN, tol=tol)
    reckoned = dead_reckoning(start, odometry)
    runs = [solve(reckoned), solve(np.asarray(truth_path, np.float64))]
    final = [float(np.hypot(*(r.path[-1, :2] - truth_path[-1, :2]))) for r in runs]
    costs = [float(r.cost[-1]) for r in runs]
    best = runs[int(costs[1] < costs[0])]
    cost_at_truth, chi2_at_truth = gaussian_cost(start, truth_path, np.asarray(trees_xy)[trees],
                                                 odometry, z, landmark_of_obs, params)
    return LogFloor(
        error=float(np.hypot(*(best.path[-1, :2] - truth_path[-1, :2]))),
        first_error=float(np.hypot(*(best.path[0, :2] - truth_path[0, :2]))),
        from_dead_reckoning=final[0], from_truth=final[1],
        cost_dead_reckoning=costs[0], cost_truth=costs[1],
        cost_at_truth=cost_at_truth, chi2_at_truth=chi2_at_truth,
        dead_reckoning=float(np.hypot(*(reckoned[-1, :2] - truth_path[-1, :2]))),
        converged=bool(best.converged),
        iterations=int(runs[0].iterations + runs[1].iterations))


def forest_centres(key, forests: int, wobble: float):
    """(F, 40, 2) the true tree centres of each forest of ``make_logs`` (same keys)."""
    from experiments.self_calibration import SIZE, wobbly_loop
    from sims.forest import random_forest

    dense = wobbly_loop(2000, amplitude=wobble)
    return np.stack([np.asarray(random_forest(
        jax.random.split(jax.random.fold_in(key, f))[0], 40, (SIZE, SIZE),
        keep_clear=dense[:, :2]).centres, np.float64) for f in range(forests)])


RATE_HEADER = ("| estimate | logs | final error > 1 m [Wilson 95 %] | forests' 95 % interval "
               "| median final error [m] |")


def rate_row(label: str, exceed, errors, forests: int) -> str:
    """'| label | n | k (p %) [Wilson 95 %] | [forest interval] | median |' of a > 1 m count
    ``exceed`` (n,) bool over n logs that come in ``forests`` equal blocks of one forest each
    (``make_logs``' order). The Wilson interval treats the logs as independent; the forests'
    interval (``proposal_study.clustered_interval``) treats the forests as the sampled units,
    the honest one when the rate depends on the forest. '-' with fewer than 2 forests."""
    total, k = np.size(exceed), int(np.sum(exceed))
    low, high = wilson(k, total)
    clustered = "-"
    if forests >= 2:
        c_low, c_high = clustered_interval(exceed, forests)
        clustered = f"[{100 * c_low:.1f}, {100 * c_high:.1f}]"
    return (f"| {label} | {total} | {k} ({100 * k / total:.1f} %) [{100 * low:.1f}, "
            f"{100 * high:.1f}] | {clustered} | {np.median(errors):.3f} |")


def sparse_rows(sparsest, columns: dict) -> list[str]:
    """Rows: runs and the > 1 m share of each named error array, per sparse-stretch bin."""
    rows = []
    for lo, hi in SPARSE_BINS:
        sel = (sparsest >= lo) & (sparsest < hi)
        if not np.any(sel):
            continue
        cells = " | ".join(f"{int(np.sum(e[sel] > 1.0))} ({100 * np.mean(e[sel] > 1.0):.1f} %)"
                           for e in columns.values())
        label = f"{lo}-{hi}" if hi < 10**9 else f">= {lo}"
        rows.append(f"| {label} | {int(np.sum(sel))} | {cells} |")
    return rows


def smooth_logs(controls, obs, truth, centres, params: Params, per_forest: int,
                iterations: int) -> dict:
    """Per-log ``LogFloor`` fields as arrays (R,) (``chi2_at_truth`` (R, 4)) of the logs
    (controls (R, T, 3), observations (R, T, K), truth (R, T+1, 3)); forest f's tree centres
    ``centres[f]`` (F, N, 2) serve logs f * per_forest ... (f + 1) * per_forest - 1."""
    floors, tick = [], time.perf_counter()
    for r in range(controls.shape[0]):
        floors.append(floor_of_log(
            truth[r, 0], controls[r], obs.z[r], obs.landmark_id[r], obs.valid[r],
            truth[r, 1:], centres[r // per_forest], params, iterations=iterations))
        if (r + 1) % 50 == 0:
            print(f"{r + 1} logs smoothed in {time.perf_counter() - tick:.0f} s; "
                  f"> 1 m so far {np.mean([f.error > 1 for f in floors]):.3f}", flush=True)
    return {name: np.asarray(values) for name, values in zip(LogFloor._fields, zip(*floors))}


def floor_tables(floor: dict, seconds: float, iterations: int, forests: int) -> list[str]:
    """The floor's table (each estimate's > 1 m rate and median; the logs over ``forests``
    forests) and a paragraph on the two starts, convergence, the cost at the truth and the
    first-step error."""
    runs = len(floor["error"])
    table = (RATE_HEADER + "\n|---|---|---|---|---|\n" + "\n".join(
                 rate_row(label, floor[name] > 1, floor[name], forests) for label, name in (
                     ("MAP, true association (lower cost of two starts)", "error"),
                     ("MAP from dead reckoning alone", "from_dead_reckoning"),
                     ("MAP from the truth alone", "from_truth"),
                     ("dead reckoning", "dead_reckoning"))))
    lower = np.minimum(floor["cost_dead_reckoning"], floor["cost_truth"])
    differ = np.abs(floor["cost_dead_reckoning"] - floor["cost_truth"]) > 1e-6 * lower
    truth_lower = floor["cost_truth"] < floor["cost_dead_reckoning"] - 1e-6 * lower
    moved = np.abs(floor["from_dead_reckoning"] - floor["from_truth"]) > 0.01
    verdict = (floor["from_dead_reckoning"] > 1) != (floor["from_truth"] > 1)
    below_truth = lower <= floor["cost_at_truth"] * (1 + 1e-9)
    chi2 = np.array2string(np.mean(floor["chi2_at_truth"], 0), precision=2)
    text = (f"Smoother: {seconds:.0f} s for {runs} logs (2 solves each, up to {iterations} LM "
            f"steps, Huber {PURE_GAUSSIAN:g}: pure Gaussian). The kept solve converged "
            f"(relative cost decrease < 1e-10) in {int(np.sum(floor['converged']))} / {runs} "
            f"logs. The two starts' final costs differ (relative > 1e-6) in "
            f"{int(np.sum(differ))} logs, the truth start lower in {int(np.sum(truth_lower))}; "
            f"their final positions differ by > 1 cm in {int(np.sum(moved))} and the > 1 m "
            f"verdict in {int(np.sum(verdict))}. MAP cost <= cost at the truth in "
            f"{int(np.sum(below_truth))} / {runs} logs. MAP first-step error: median "
            f"{1000 * np.median(floor['first_error']):.1f} mm, max "
            f"{1000 * np.max(floor['first_error']):.1f} mm; MAP final error: 95th percentile "
            f"{np.percentile(floor['error'], 95):.3f} m, max {np.max(floor['error']):.3f} m. "
            f"Mean squared whitened residual at the truth (heading, translation, range, "
            f"bearing rows; 1 if the model's noise is the simulator's): {chi2}.")
    return [table, text]


def filter_errors(particles: int, params: Params, key, controls, obs, truth, total_runs: int,
                  chunk: int):
    """The default filter's final errors (R,), compile [s] and run [s] on the first R logs
    of ``total_runs``, with the study's keys (``run_point``: one split of ``key`` a run)."""
    fields, _ = proposal_settings("default")
    config = FilterConfig(num_particles=particles, max_landmarks=96, max_obs=12, **fields)
    runs = controls.shape[0]
    # The first R keys of a split into total_runs must be the keys of a split into R (so
    # with JAX's partitionable threefry), else the filter's draws would not be the study's.
    if not np.array_equal(jax.random.key_data(jax.random.split(key, runs)),
                          jax.random.key_data(jax.random.split(key, total_runs)[:runs])):
        raise SystemExit("jax.random.split is not prefix-stable here (set "
                         "jax_threefry_partitionable=True)")
    chunk = min(chunk, runs)
    if runs % chunk:
        raise SystemExit(f"{runs} logs must be a multiple of the chunk {chunk}")
    error, _, _, _, _, compile_s, run_s = run_point(config, params, key, controls, obs, truth,
                                                    chunk)
    return error, compile_s, run_s


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=1000)
    parser.add_argument("--forests", type=int, default=50)
    parser.add_argument("--seed", type=int, default=700)
    parser.add_argument("--wobble", type=float, default=0.3)
    parser.add_argument("--odometry", type=float, default=6.0)
    parser.add_argument("--first", type=int, default=None,
                        help="use only the first N of the --runs logs (filter and smoother)")
    parser.add_argument("--no-smooth", action="store_true", help="skip the smoother")
    parser.add_argument("--iterations", type=int, default=200, help="LM steps per solve")
    parser.add_argument("--particles", type=int, nargs="*", default=[],
                        help="also run the default filter at these particle counts")
    parser.add_argument("--chunk", type=int, default=250, help="filter runs per vmap chunk")
    parser.add_argument("--out", default="results/information_floor/floor",
                        help="prefix of the .npz (per-log arrays) and .md (tables)")
    args = parser.parse_args(argv)
    if args.runs % args.forests:
        raise SystemExit("--runs must be a multiple of --forests")
    first = args.runs if args.first is None else args.first
    per_forest = args.runs // args.forests
    if first % per_forest or not 0 < first <= args.runs:
        raise SystemExit(f"--first must be a multiple of runs / forests = {per_forest}")
    truth_params = regime_params(args.odometry, "lidar")
    key_logs, key_filters = point_keys(args.seed, args.wobble, args.odometry)
    # make_logs draws forest f from fold_in(key_logs, f) and run i of a forest from its own key,
    # so the first N logs of --runs R are the logs of N runs over N / (R / F) forests.
    used_forests = first // per_forest
    controls, obs, truth, _ = make_logs(key_logs, truth_params, args.wobble, first, used_forests)
    _, param_fields = proposal_settings("default")
    params = truth_params._replace(**{k: jnp.asarray(v, jnp.float32)
                                      for k, v in param_fields.items()})
    out, tables, columns, filter_rows = {"sparsest": longest_sparse_stretch(obs.valid)}, [], {}, []
    if not args.no_smooth:
        tick = time.perf_counter()
        centres = forest_centres(key_logs, used_forests, args.wobble)
        floor = smooth_logs(controls, obs, truth, centres, params, per_forest, args.iterations)
        tables += floor_tables(floor, time.perf_counter() - tick, args.iterations,
                               used_forests)
        out.update({f"map_{k}": v for k, v in floor.items()})
        columns["MAP"] = floor["error"]
    for particles in args.particles:
        error, compile_s, run_s = filter_errors(particles, params, key_filters,
                                                controls, obs, truth, args.runs, args.chunk)
        out[f"filter_P{particles}"] = columns[f"filter P = {particles}"] = error
        filter_rows.append(rate_row(f"default filter, P = {particles}", error > 1, error,
                                    used_forests)
                           + f" {first * controls.shape[1] / run_s:.3g} | {compile_s:.0f} |")
        print(filter_rows[-1], flush=True)
    if filter_rows:
        tables.append(RATE_HEADER + " run-steps/s | compile [s] |\n|---|---|---|---|---|---|---|\n"
                      + "\n".join(filter_rows))
    if columns:
        tables.append("| longest stretch with <= 2 valid observations [steps] | logs | "
                      + " | ".join(f"{name} > 1 m" for name in columns) + " |\n|---|---|"
                      + "---|" * len(columns) + "\n"
                      + "\n".join(sparse_rows(out["sparsest"], columns)))
    write_outputs("information_floor.py", argv, tables, out, args.out)


def write_outputs(script: str, argv, sections: list[str], arrays: dict, out: str) -> None:
    """Print the command line and the markdown ``sections``; write them to ``out``.md and the
    per-log ``arrays`` to ``out``.npz (folders created)."""
    command = f"python experiments/{script} " + " ".join(sys.argv[1:] if argv is None else argv)
    text = f"`{command.strip()}`\n\n" + "\n\n".join(sections) + "\n"
    print(text)
    path = pathlib.Path(out)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path.with_suffix(".npz"), **arrays)
    path.with_suffix(".md").write_text(text)
    print(f"written to {path.with_suffix('.npz')} and {path.with_suffix('.md')}")


if __name__ == "__main__":
    main()
