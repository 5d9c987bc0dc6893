"""Does closing the missed loops by registration repair the first regime's divergence?

``experiments/lineage_check.py`` found that in the first regime (odometry 6x Table 1, large
turns, a 5 mm / 0.5 mrad lidar, P = 20) the filter's association has no wrong match but the
runs that diverge never close their loop, and that the batch MAP with the loop-return
re-sightings merged (an oracle) diverges in 0 %. This script puts a truth-free loop closure
in the oracle's place: on the same logs, filter, keys and settings (``lineage_check``'s
``regime_histories``), per log on the host

1. the batch MAP on the best particle's own association (``smoothing.smooth_path``, true
   noise, plain squares as lineage_check: Huber 1e6, tol 1e-10, up to 200 LM steps, the true
   start pose);
2. ``loop_closure.close_loops`` from there: candidate revisits registered by their shape,
   each verified by the smoother's cost rise, and split pieces merged under the same test.

The simulator's trees only SCORE: the final position error of each estimate, and the
association quality (``lineage_check.association_quality``) of the closed association:
purity 1.0 means no landmark holds two trees (no false closure).

    python experiments/loop_closure_study.py --seed 800 --runs 200 --forests 20 \\
        --out results/loop_closure/tuning
    python experiments/loop_closure_study.py --seed 700 --runs 1000 --forests 50 \\
        --first 200 --out results/loop_closure/first200

Seed 800 is where ``MAX_RISE_PER_DOF`` was read off (its first 40 logs); seed 700 is held out.
``--proposal`` runs another filter on the same logs (a ``proposal_study`` name with optional
``:field=value`` overrides), e.g. the mixture at phi = 0.5:

    python experiments/loop_closure_study.py --seed 700 --runs 1000 --forests 50 --first 200 \
        --proposal "default:proposal='mixture',mixture_ratio=0.5" --out results/loop_closure/mixture
"""
from __future__ import annotations

import argparse
import functools
import pathlib
import sys
import time

import jax
import numpy as np

# Run this checkout's jaxslam, also when an editable install points at another checkout
# (an experiment started from a git worktree of an older commit).
sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

from experiments.information_floor import (PURE_GAUSSIAN, RATE_HEADER, rate_row,
                                           write_outputs)
from experiments.lineage_check import (add_regime_arguments, association_quality, forests_of,
                                       position_error, regime_histories)
from jaxslam.lineage import LineagePath, landmark_identities
from jaxslam.loop_closure import MAX_RISE_PER_DOF, close_loops
from jaxslam.smoothing import smooth_path


def majority_tree(landmark_of_obs, true_id, valid) -> np.ndarray:
    """(L,) the true tree most of each landmark's valid observations belong to (ties: the
    lower id; -1 for a landmark with none). landmark_of_obs, true_id, valid (T, K)."""
    landmark_of_obs = np.asarray(landmark_of_obs, np.int64)
    used = np.asarray(valid, bool) & (landmark_of_obs >= 0) & (np.asarray(true_id) >= 0)
    count = int(landmark_of_obs.max()) + 1 if landmark_of_obs.size else 0
    out = np.full(count, -1, np.int64)
    for landmark in np.unique(landmark_of_obs[used]):
        out[landmark] = np.argmax(np.bincount(np.asarray(true_id)[used & (landmark_of_obs
                                                                           == landmark)]))
    return out


def close_log(history: LineagePath, controls, obs, truth, params, iterations: int):
    """Per-log numbers and per-tested-join numbers of one log.

    Returns (log, joins): log: own-association MAP and closed MAP final errors [m], closures
    made, landmarks joined, the closed association's quality fields (prefixed ``closed_``)
    and the seconds taken; joins: per join ``close_loops`` tested, kind (1 closure, 0 merge),
    rise per degree of freedom, accepted, and true (every proposed pair one tree: scored
    with the simulator's trees). history leaves (T, ...), controls (T, 3), obs leaves
    (T, K), truth (T+1, 3)."""
    tick = time.perf_counter()
    valid = np.asarray(obs.valid, bool)
    ids, _ = landmark_identities(np.asarray(history.match), np.asarray(history.birth_slot))
    ids = np.where(valid, np.asarray(ids), -1)
    z = np.where(valid[..., None], np.asarray(obs.z, np.float64), 0.0)
    solve = functools.partial(smooth_path, truth[0], odometry=np.asarray(controls, np.float64),
                              z=z, params=params, huber=PURE_GAUSSIAN, tol=1e-10)
    smooth = (lambda path, landmark_of_obs, steps=iterations:
              solve(path=path, landmark_of_obs=landmark_of_obs, iterations=steps))
    own = smooth(np.asarray(history.pose, np.float64), ids)
    result = close_loops(smooth, history.pose, ids)
    quality = association_quality(result.smoothed.landmark_of_obs, obs.landmark_id, valid)
    joins = {"kind": [], "rise_per_dof": [], "accepted": [], "true": []}
    for join in result.tested:
        tree = majority_tree(join.landmark_of_obs, obs.landmark_id, valid)
        joins["kind"].append(int(join.kind == "closure"))
        joins["rise_per_dof"].append(join.rise_per_dof)
        joins["accepted"].append(join.accepted)
        joins["true"].append(bool(np.all(tree[join.pairs[:, 0]] == tree[join.pairs[:, 1]])))
    log = dict({f"closed_{k}": v for k, v in quality._asdict().items()},
               own=float(position_error(own.path[-1], truth[-1])),
               closed=float(position_error(result.smoothed.path[-1], truth[-1])),
               closures=len(result.closures), landmarks_joined=result.landmarks_joined,
               seconds=time.perf_counter() - tick)
    return log, joins


def join_table(table: dict) -> str:
    """Markdown: the tested joins' cost rise per degree of freedom, by kind and by truth."""
    rows = []
    for kind, label in ((1, "closure (registration)"), (0, "merge (landmark_merge set)")):
        for truth, name in ((True, "true"), (False, "false (a pair of two trees)")):
            sel = (table["join_kind"] == kind) & (table["join_true"] == truth)
            rise = table["join_rise_per_dof"][sel]
            accepted = int(np.sum(table["join_accepted"][sel]))
            rows.append(f"| {label} | {name} | {rise.size} | {accepted} | " + (
                f"{np.min(rise):.3g} / {np.median(rise):.3g} / {np.max(rise):.3g}"
                if rise.size else "") + " |")
    return ("| join | scored | tested | accepted | cost rise per degree of freedom "
            "min / median / max (limit " f"{MAX_RISE_PER_DOF:g}) |\n|---|---|---|---|---|\n"
            + "\n".join(rows))


def tables(table: dict, forests: int) -> list[str]:
    """Markdown sections of the per-log arrays ``table`` of logs over ``forests`` forests."""
    runs = table["online"].size
    rows = [rate_row(label, table[name] > 1, table[name], forests) for name, label in (
        ("online", "online (weighted mean)"),
        ("own", "MAP on the best history's own association"),
        ("closed", "MAP after close_loops (registration + cost test + tested merges)"))]
    out = [RATE_HEADER + "\n|---|---|---|---|---|\n" + "\n".join(rows)]
    impure = table["closed_purity"] < 1
    ratio = table["closed_identities"] / np.maximum(table["closed_trees"], 1)
    all_loop = table["closed_loop_closed_trees"] == table["closed_loop_trees"]
    open_loop = (table["closed"] > 1) & ~all_loop
    out.append(
        f"Closed association (scored against the simulator's trees): purity 1.0 (no landmark "
        f"holds two trees) in {runs - int(np.sum(impure))} / {runs} logs (lowest "
        f"{np.min(table['closed_purity']):.4f}); identities per tree seen median "
        f"{np.median(ratio):.2f} (largest {np.max(ratio):.2f}); logs with every loop tree "
        f"re-identified {int(np.sum(all_loop))} / {runs}. Closures made: "
        f"{int(np.sum(table['closures']))} in "
        f"{int(np.sum(table['closures'] > 0))} logs; landmarks removed by joins "
        f"{int(np.sum(table['landmarks_joined']))}. Host time per log median "
        f"{np.median(table['seconds']):.1f} s (largest {np.max(table['seconds']):.1f} s).")
    diverged = table["online"] > 1
    rescued = diverged & (table["closed"] <= 1)
    worse = (table["online"] <= 1) & (table["closed"] > 1)
    out.append(f"Of the {int(np.sum(diverged))} logs whose online estimate ends > 1 m off, "
               f"{int(np.sum(rescued))} end <= 1 m after close_loops; of the "
               f"{int(np.sum(~diverged))} that end <= 1 m online, {int(np.sum(worse))} end "
               f"> 1 m after it. Still > 1 m after it: {int(np.sum(table['closed'] > 1))} logs, "
               f"of which {int(np.sum((table['closed'] > 1) & impure))} with a false join and "
               f"{int(np.sum(open_loop))} with a loop tree still not re-identified.")
    out.append(join_table(table))
    return out


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_regime_arguments(parser)
    parser.add_argument("--out", default="results/loop_closure/check",
                        help="prefix of the .npz (per-log arrays) and .md (tables)")
    args = parser.parse_args(argv)
    first, controls, obs, truth, params, online, histories, notes = regime_histories(args)
    per_log, joins = [], {name: [] for name in ("kind", "rise_per_dof", "accepted", "true",
                                                "log")}
    for r in range(first):
        log, tested = close_log(jax.tree.map(lambda a: a[r], histories), controls[r],
                                jax.tree.map(lambda a: a[r], obs),
                                np.asarray(truth[r], np.float64), params, args.iterations)
        per_log.append(log)
        for name, values in dict(tested, log=[r] * len(tested["kind"])).items():
            joins[name].extend(values)
        if (r + 1) % 25 == 0:
            print(f"{r + 1} logs closed, {sum(log['seconds'] for log in per_log):.0f} s",
                  flush=True)
    table = {name: np.asarray([log[name] for log in per_log]) for name in per_log[0]}
    table["online"] = online
    table.update({f"join_{name}": np.asarray(values, float if name == "rise_per_dof"
                                             else np.int64 if name in ("kind", "log")
                                             else bool)
                  for name, values in joins.items()})
    write_outputs("loop_closure_study.py", argv,
                  [" ".join(notes)] + tables(table, forests_of(args, first)), table, args.out)


if __name__ == "__main__":
    main()
