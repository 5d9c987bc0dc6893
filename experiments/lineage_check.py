"""Is the first regime's divergence the filter's data association or its online estimate?

On the logs of ``experiments/information_floor.py`` (the same ``make_logs``, seed, keys and
settings: bit-identical logs, and the same per-run filter keys, so the online final errors are
information_floor's filter column), the default filter runs with ``record_lineage=True``
(``jaxslam.filter.scan_filter``, vmapped over runs in chunks as ``proposal_study.run_point``
does). Per log, on the host:

1. the online final error: the weighted mean pose's final position against the truth;
2. the best particle's history (``trace_lineage`` of the highest final log weight, the first
   of equals, as ``filter.estimate``) and its final position error;
3. that history's data association against the simulator's true tree of every valid
   observation (``association_quality``);
4. the batch MAP with the history's OWN association (``smoothing.smooth_lineage``: GraphSLAM's
   least squares, Thrun et al., Probabilistic Robotics, ch. 11) from the history's path, with
   information_floor's pure-Gaussian settings (true noise, Huber 1e6, no calibration rounds,
   the true start pose, up to 200 Levenberg-Marquardt steps, tol 1e-10) and its final error.

If a diverged run's association is clean (every identity one tree, no tree split, the loop
closed), the smoother on the filter's own association has the information the MAP floor has
and the online estimate is what failed; if it is broken, the smoother inherits the error.

Which break matters: every further identity a tree gets is a split event (``split_geometry``),
with the steps since the tree was last seen (1-2: lost while in view; > 40: a re-sighting,
on this 250-step loop the loop's return). The smoother is also run on the history's own
association with the in-view splits, the long-gap splits, or all splits undone
(``merge_splits``: an ORACLE, it reads the true trees; a diagnostic of what the filter's
association lacks, never an estimate). For each loop tree, ``loop_mismatch`` measures how
far the history's motion prediction at the return places it from its first visit: the drift
the filter's association has to bridge there. For each split, ``split_geometry`` gives the range
at which it happened and how far the history's own pose placed the tree from where its
previous identity stood: the pose-map misfit the association refused.

    python experiments/lineage_check.py --seed 800 --runs 200 --forests 20 \
        --out results/lineage_check/tuning
    python experiments/lineage_check.py --seed 700 --runs 1000 --forests 50 --first 200 \
        --out results/lineage_check/first200
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

from experiments.information_floor import (PURE_GAUSSIAN, RATE_HEADER, dead_reckoning,
                                           filter_errors, rate_row, sparse_rows, write_outputs)
from experiments.mixture_regime import regime_params
from experiments.proposal_study import (longest_sparse_stretch, make_logs, point_keys,
                                        proposal_settings, wilson)
from jaxslam.filter import make_filter, scan_filter
from jaxslam.lineage import LineagePath, landmark_identities, trace_lineage
from jaxslam.smoothing import smooth_lineage, smooth_path
from jaxslam.types import FilterConfig, Params

EARLY, LATE = 20, 30  # steps: the loop's start and end windows (a 250-step loop's 10 m, 15 m)


class AssociationQuality(NamedTuple):
    """One history's data association against the true trees (valid observations only).

    identities: distinct landmark identities the valid observations carry; trees: distinct
    true trees they see; associated: valid observations with an identity (the rest were set
    aside or dropped: ``unassociated``); purity: fraction of the associated whose identity's
    majority tree is their own tree (1: no wrong match); consistency: fraction of the
    associated whose identity is their tree's majority identity (1: no tree split);
    split_trees: trees with >= 2 identities of >= 2 observations each; loop_trees: trees seen
    in the first ``early`` steps and again in the last ``late``; loop_closed_trees: those of
    them with one identity on an early and on a late observation; first_error_step: the first
    step with an observation whose identity is not its tree's first identity or whose
    identity's first tree is not its tree (-1: none): where the association first departs
    from the truth.
    """

    identities: int
    trees: int
    associated: int
    unassociated: int
    purity: float
    consistency: float
    split_trees: int
    loop_trees: int
    loop_closed_trees: int
    first_error_step: int


def association_quality(ids, true_id, valid, early: int = EARLY,
                        late: int = LATE) -> AssociationQuality:
    """``AssociationQuality`` of identities ``ids`` (T, K) (``landmark_identities``, -1: none)
    against true tree indices ``true_id`` (T, K) of the valid observations ``valid`` (T, K).

    With C[i, j] the number of associated observations of identity i on tree j:
    purity = sum_i max_j C[i, j] / sum C (the argmax's share, ties to the lower index), and
    consistency = sum_j max_i C[i, j] / sum C.
    """
    ids, true_id = np.asarray(ids, np.int64), np.asarray(true_id, np.int64)
    valid = np.asarray(valid, bool)
    used = valid & (ids >= 0)
    obs_t, _ = np.nonzero(used)  # row-major: time order
    trees_seen = np.unique(true_id[valid])
    identity, ident = np.unique(ids[used], return_inverse=True)
    tree, tree_of = np.unique(true_id[used], return_inverse=True)
    count = np.zeros((identity.size, tree.size), np.int64)
    np.add.at(count, (ident, tree_of), 1)
    total = max(int(count.sum()), 1)
    majority_tree = np.argmax(count, 1) if identity.size else np.zeros(0, np.int64)
    majority_identity = np.argmax(count, 0) if tree.size else np.zeros(0, np.int64)
    # First identity of each tree and first tree of each identity, in time order.
    _, first_of_tree = np.unique(tree_of, return_index=True)
    _, first_of_ident = np.unique(ident, return_index=True)
    wrong = ((ident[first_of_tree][tree_of] != ident)
             | (tree_of[first_of_ident][ident] != tree_of)) if ident.size else np.zeros(0, bool)
    _, closed = loop_trees(ids, true_id, valid, early, late)
    return AssociationQuality(
        identities=int(identity.size), trees=int(trees_seen.size),
        associated=int(used.sum()), unassociated=int(valid.sum() - used.sum()),
        purity=float(np.sum(count[np.arange(identity.size), majority_tree]) / total),
        consistency=float(np.sum(count[majority_identity, np.arange(tree.size)]) / total),
        split_trees=int(np.sum(np.sum(count >= 2, 0) >= 2)),
        loop_trees=int(closed.size), loop_closed_trees=int(np.sum(closed)),
        first_error_step=int(obs_t[wrong][0]) if np.any(wrong) else -1)


def loop_trees(ids, true_id, valid, early: int = EARLY, late: int = LATE):
    """The loop trees of one history and whether it closed the loop on each.

    A loop tree has an associated valid observation in the first ``early`` steps and one in
    the last ``late``; the loop is closed on it when one identity is on both.

    Args: ids, true_id, valid (T, K) as ``association_quality``'s.
    Returns: trees (n,) the loop trees' true indices (ascending); closed (n,) bool.
    """
    ids, true_id = np.asarray(ids, np.int64), np.asarray(true_id, np.int64)
    used = np.asarray(valid, bool) & (ids >= 0)
    steps = ids.shape[0]
    step = np.broadcast_to(np.arange(steps)[:, None], ids.shape)
    trees, closed = [], []
    for tree in np.unique(true_id[used]):
        mine = used & (true_id == tree)
        first, last = set(ids[mine & (step < early)]), set(ids[mine & (step >= steps - late)])
        if first and last:
            trees.append(tree)
            closed.append(bool(first & last))
    return np.asarray(trees, np.int64), np.asarray(closed, bool)


def loop_mismatch(pose, odometry, z, true_id, valid, trees):
    """How far a history's predicted pose puts each loop tree on its return from where its
    first visit put it.

    A tree's placement by observation (t, k) from pose x is p = x_xy + r (cos(x_theta + b),
    sin(x_theta + b)), (r, b) = z[t, k]. The return is the tree's first observation after the
    longest gap between its observations (for a loop tree, the loop), at step t_r; its first
    visit, the observations before that gap, placed from the history's poses pose[t]. The
    mismatch is |p(x_hat, z_return) - mean of the first visit's placements| [m], with
    x_hat = pose[t_r - 1] moved by the measured odometry[t_r]: the motion prediction at
    which the filter matches (``FilterConfig.match_pose_uncertainty``), so the misfit its
    gate sees before the return observation corrects the pose, whatever the identities.

    Args: pose (T, 3) the history's poses; odometry (T, 3) measured moves; z (T, K, 2);
      true_id, valid (T, K); trees (n,) from ``loop_trees``.
    Returns: (n,) mismatch [m]; (n,) int the return step.
    """
    pose, z = np.asarray(pose, np.float64), np.asarray(z, np.float64)
    valid, true_id = np.asarray(valid, bool), np.asarray(true_id, np.int64)
    place = lambda x, zk: x[:2] + zk[0] * np.array([np.cos(x[2] + zk[1]), np.sin(x[2] + zk[1])])
    mismatch, back = np.zeros(len(trees)), np.zeros(len(trees), np.int64)
    for i, tree in enumerate(trees):
        t, k = np.nonzero(valid & (true_id == tree))
        if t.size < 2 or t[-1] == t[0]:  # no return: seen at one step only
            mismatch[i], back[i] = np.nan, t[0]
            continue
        ret = int(np.argmax(np.diff(t))) + 1
        visit = np.mean([place(pose[a], z[a, b]) for a, b in zip(t[:ret], k[:ret])], 0)
        back[i] = step = t[ret]
        predicted = dead_reckoning(pose[step - 1], np.asarray(odometry)[step:step + 1])[0]
        mismatch[i] = np.linalg.norm(place(predicted, z[step, k[ret]]) - visit)
    return mismatch, back


SPLIT_GAPS = ((1, 2), (3, 40), (41, 10**9))  # steps since the tree's previous observation


def _split_walk(ids, true_id, valid):
    """Yield (t, k, i) per split event: the tree's observations, t and k (n_tree,) int arrays
    in time order (``valid`` and associated), and the index i of the one that brought a
    further identity. ids, true_id, valid: (T, K)."""
    ids, true_id = np.asarray(ids, np.int64), np.asarray(true_id, np.int64)
    used = np.asarray(valid, bool) & (ids >= 0)
    for tree in np.unique(true_id[used]):
        t, k = np.nonzero(used & (true_id == tree))
        seen = {ids[t[0], k[0]]}
        for i in range(1, t.size):
            if ids[t[i], k[i]] not in seen:
                seen.add(ids[t[i], k[i]])
                yield t, k, i


def split_geometry(pose, z, ids, true_id, valid, last: int = 5):
    """Every time a tree gets a further identity (a split event): its step, the steps since
    that tree's previous associated observation (1: seen at the step before, a split while in
    view), the range of the observation that brought the further identity, and its
    displacement, |p(pose[t], z[t, k]) - mean of p over the last ``last``
    observations of the tree's previous identity| [m], with p(x, (r, b)) = x_xy + r (cos(x_theta
    + b), sin(x_theta + b)) placed from the history's own poses: the misfit between the
    history's pose and its map that the association refused.

    Args: pose (T, 3) the history's poses; z (T, K, 2); ids, true_id, valid (T, K).
    Returns: dict of (n,) arrays step, gap [steps], range [m], displacement [m], in time
      order per tree.
    """
    pose, z, ids = np.asarray(pose, np.float64), np.asarray(z, np.float64), np.asarray(ids)
    place = lambda a, b: pose[a, :2] + z[a, b, 0] * np.array([np.cos(pose[a, 2] + z[a, b, 1]),
                                                                np.sin(pose[a, 2] + z[a, b, 1])])
    step, gap, range_, displacement = [], [], [], []
    for t, k, i in _split_walk(ids, true_id, valid):
        step.append(t[i])
        previous = [j for j in range(i) if ids[t[j], k[j]] == ids[t[i - 1], k[i - 1]]][-last:]
        before = np.mean([place(t[j], k[j]) for j in previous], axis=0)
        gap.append(t[i] - t[i - 1])
        range_.append(z[t[i], k[i], 0])
        displacement.append(float(np.linalg.norm(place(t[i], k[i]) - before)))
    return dict(step=np.asarray(step, np.int64), gap=np.asarray(gap, np.int64), range=np.asarray(range_, np.float64),
                displacement=np.asarray(displacement, np.float64))


ORACLE_MERGES = {"in_view": (1, 2), "loop": (41, 10**9), "all": (1, 10**9)}  # gap ranges


def merge_splits(ids, true_id, valid, gaps=(1, 10**9)):
    """Diagnostic ORACLE (uses the true trees): undo the splits whose gap is in ``gaps``.

    Walking each tree's associated observations in time, a further identity that appears
    ``gaps[0]``..``gaps[1]`` steps after the tree's previous observation (``split_geometry``)
    is relabelled, for that tree's observations, to the label the previous observation got.
    Labels are then renumbered 0..L'-1 (the smoother wants no empty landmark).

    Args: ids, true_id, valid (T, K) as ``association_quality``'s; gaps: (lo, hi) steps.
    Returns: (T, K) int64 identities (-1 where ``ids`` is -1 or the row invalid).
    """
    ids, true_id = np.asarray(ids, np.int64), np.asarray(true_id, np.int64)
    used = np.asarray(valid, bool) & (ids >= 0)
    out = np.where(used, ids, -1)
    for tree in np.unique(true_id[used]):
        t, k = np.nonzero(used & (true_id == tree))
        seen, relabel, previous = set(), {}, None
        for i in range(t.size):
            label = ids[t[i], k[i]]
            if label not in seen and previous is not None and (
                    gaps[0] <= t[i] - t[i - 1] <= gaps[1]):
                relabel[label] = previous
            seen.add(label)
            out[t[i], k[i]] = previous = relabel.get(label, label)
    _, out[used] = np.unique(out[used], return_inverse=True)
    return out


def lineage_runs(config: FilterConfig, params: Params, key, controls, obs, truth, chunk: int):
    """The vmapped filter with ``record_lineage``: per run the online final pose (R, 3) and
    the best particle's ``LineagePath`` (leaves (R, T, ...)), with ``run_point``'s keys
    (``jax.random.split(key, R)``, one a run) and chunks. Also compile [s] and run [s]."""
    filt = make_filter(config)

    def one(key, controls, obs, start):
        state = filt.init(start, dtype=controls.dtype)
        final, trace = scan_filter(config, key, state, params, controls, obs,
                                   record_lineage=True)
        return trace.mean_pose[-1], trace_lineage(trace.lineage, jnp.argmax(final.log_weight))

    batched = jax.jit(jax.vmap(one))
    runs = controls.shape[0]
    keys = jax.random.split(key, runs)
    part = lambda lo: (keys[lo:lo + chunk], controls[lo:lo + chunk],
                       jax.tree.map(lambda a: a[lo:lo + chunk], obs), truth[lo:lo + chunk, 0])
    tick = time.perf_counter()
    compiled = batched.lower(*part(0)).compile()
    compile_s, run_s, finals, paths = time.perf_counter() - tick, 0.0, [], []
    for lo in range(0, runs, chunk):
        tick = time.perf_counter()
        final, path = jax.block_until_ready(compiled(*part(lo)))
        run_s += time.perf_counter() - tick
        finals.append(np.asarray(final))
        paths.append(jax.tree.map(np.asarray, path))
    return (np.concatenate(finals), jax.tree.map(lambda *xs: np.concatenate(xs), *paths),
            compile_s, run_s)


def position_error(pose, truth_pose):
    """Euclidean distance of the positions of poses (..., 3) and (..., 3) [m]."""
    return np.hypot(*np.moveaxis(np.asarray(pose)[..., :2] - np.asarray(truth_pose)[..., :2],
                                 -1, 0))


def check_log(history: LineagePath, controls, obs, truth, params: Params,
              iterations: int) -> tuple[dict, dict, dict]:
    """Per-loop-tree and per-log numbers of one history (leaves (T, ...)).

    Returns (loops, splits, log): loops, arrays (n,) over the loop trees (``loop_trees``,
    ``loop_mismatch``): tree, closed, mismatch, return_step; splits, arrays (n_s,) over the
    split events (``split_geometry``): gap, range, displacement; log, scalars: the
    ``AssociationQuality`` fields, the history's final position error (best), the smallest
    loop mismatch, the own-association smoother's final error and convergence, the
    smoother's final error on the ``ORACLE_MERGES`` repairs of the association
    (oracle_in_view, oracle_loop, oracle_all; from the history's path), the history's
    position error at the first association error, and its first step > 0.5 m off (-1:
    never). ``truth`` (T+1, 3), controls (T, 3), obs leaves (T, K).
    """
    history = LineagePath(*(np.asarray(a) for a in history))
    valid = np.asarray(obs.valid, bool)
    ids, _ = landmark_identities(history.match, history.birth_slot)
    if np.any(ids[~valid] >= 0):  # smooth_lineage would use their (zeroed) z
        raise ValueError("the filter associated an invalid observation")
    quality = association_quality(ids, obs.landmark_id, valid)
    z = np.where(valid[..., None], np.asarray(obs.z, np.float64), 0.0)
    smoothed = smooth_lineage(truth[0], history, controls, z, params, iterations=iterations,
                              huber=PURE_GAUSSIAN, tol=1e-10)
    along = position_error(history.pose, truth[1:])
    step = quality.first_error_step
    trees, closed = loop_trees(ids, obs.landmark_id, valid)
    mismatch, back = loop_mismatch(history.pose, controls, z, obs.landmark_id, valid,
                                   trees)
    loops = dict(tree=trees, closed=closed, mismatch=mismatch, return_step=back)
    oracle = {}
    for name, gaps in ORACLE_MERGES.items():
        merged = smooth_path(truth[0], history.pose, controls, z,
                             merge_splits(ids, obs.landmark_id, valid, gaps), params,
                             iterations=iterations, huber=PURE_GAUSSIAN, tol=1e-10)
        oracle[f"oracle_{name}"] = float(position_error(merged.path[-1], truth[-1]))
    geometry = split_geometry(history.pose, z, ids, obs.landmark_id, valid)
    gaps = geometry["gap"]
    splits = {f"splits_gap_{lo}_{hi}": int(np.sum((gaps >= lo) & (gaps <= hi)))
              for lo, hi in SPLIT_GAPS}
    return loops, geometry, dict(quality._asdict(), **splits, **oracle, best=float(along[-1]),
                loop_mismatch_min=float(np.nanmin(mismatch, initial=np.inf)),
                smoothed=float(position_error(smoothed.path[-1], truth[-1])),
                smoothed_converged=bool(smoothed.converged),
                error_at_first_association_error=float(along[step]) if step >= 0 else np.nan,
                first_step_over_half_metre=int(np.argmax(along > 0.5)) if np.any(along > 0.5)
                else -1)


def classes(table: dict) -> dict:
    """Boolean masks (R,) of the association classes of the per-log arrays ``table``."""
    loop_all = (table["loop_trees"] > 0) & (table["loop_closed_trees"] == table["loop_trees"])
    clean = (table["purity"] == 1.0) & (table["split_trees"] == 0) & loop_all
    return {
        "clean (purity 1, no split tree, loop closed on every loop tree)": clean,
        "not clean": ~clean,
        "purity 1": table["purity"] == 1.0,
        "purity < 1 (some wrong match)": table["purity"] < 1.0,
        "no split tree": table["split_trees"] == 0,
        ">= 1 split tree": table["split_trees"] > 0,
        "loop closed on every loop tree": loop_all,
        "loop closed on some, not all": (table["loop_closed_trees"] > 0) & ~loop_all,
        "loop not closed (no loop tree re-identified)": (table["loop_trees"] > 0)
        & (table["loop_closed_trees"] == 0),
        "no tree seen both early and late": table["loop_trees"] == 0,
    }


def share(mask) -> str:
    """'k / n (p %) [Wilson 95 %]' of a boolean array, '0 / 0' when empty."""
    k, n = int(np.sum(mask)), int(np.size(mask))
    if n == 0:
        return "0 / 0"
    low, high = wilson(k, n)
    return f"{k} / {n} ({100 * k / n:.1f} %) [{100 * low:.1f}, {100 * high:.1f}]"


MISMATCH_BINS = (0.0, 0.02, 0.05, 0.1, 0.2, 0.3, 0.5, 1.0, 2.0, np.inf)  # [m]


def loop_table(table: dict) -> str:
    """Markdown: per loop tree, the share the best history closed, by its loop mismatch bin,
    over all loop trees and over those of logs with online error > 1 m."""
    mismatch, closed = table["loop_mismatch"], table["loop_closed"]
    diverged = table["online"][table["loop_log"]] > 1
    rows = []
    for lo, hi in zip(MISMATCH_BINS[:-1], MISMATCH_BINS[1:]):
        sel = (mismatch >= lo) & (mismatch < hi)
        label = f"{lo:g}-{hi:g}" if np.isfinite(hi) else f">= {lo:g}"
        rows.append(f"| {label} | {int(np.sum(sel))} | {share(closed[sel])} | "
                    f"{int(np.sum(sel & diverged))} | {share(closed[sel & diverged])} |")
    return ("| loop mismatch of the tree (return placed from the motion prediction vs first "
            "visit) [m] | loop trees | closed (one identity early and late) | of them in "
            "online > 1 m logs | closed there |\n|---|---|---|---|---|\n" + "\n".join(rows))


RANGE_BINS = (0.0, 4.0, 8.0, 10.0, 11.0, np.inf)  # [m]


def split_table(table: dict) -> str:
    """Markdown: the in-view splits (gap <= 2 steps) by the range of the observation that
    brought the further identity, with their displacement (``split_geometry``), over all logs
    and over those with online error > 1 m."""
    in_view = table["split_gap"] <= 2
    diverged = table["online"][table["split_log"]] > 1
    rows = []
    for lo, hi in zip(RANGE_BINS[:-1], RANGE_BINS[1:]):
        sel = in_view & (table["split_range"] >= lo) & (table["split_range"] < hi)
        shift = table["split_displacement"][sel]
        label = f"{lo:g}-{hi:g}" if np.isfinite(hi) else f">= {lo:g}"
        rows.append(f"| {label} | {int(np.sum(sel))} | {int(np.sum(sel & diverged))} | "
                    + (" / ".join(f"{v:.3f}" for v in np.percentile(shift, [25, 50, 75]))
                       if shift.size else "") + " |")
    return ("| range of the split observation [m] | in-view splits (gap <= 2 steps) | of them in "
            "online > 1 m logs | displacement from the previous identity's placement, "
            "quartiles [m] |\n|---|---|---|---|\n" + "\n".join(rows))


def tables(table: dict, forests: int) -> list[str]:
    """The markdown tables of the per-log arrays ``table`` (``check_log``'s fields, ``online``
    and ``sparsest``) of logs over ``forests`` forests."""
    runs = table["online"].size
    errors = {"online": "online (weighted mean)", "best": "best particle's history",
              "smoothed": "MAP on the history's own association"}
    oracles = {"oracle_in_view": "ORACLE: MAP, own association with in-view splits "
               "(gap <= 2 steps) merged", "oracle_loop": "ORACLE: MAP, own association with "
               "re-sightings after > 40 steps merged (loop closure)",
               "oracle_all": "ORACLE: MAP, own association with every split merged"}
    out = [RATE_HEADER + "\n|---|---|---|---|---|\n" + "\n".join(
        rate_row(label, table[name] > 1, table[name], forests)
        for name, label in {**errors, **oracles}.items())]
    ratio = table["identities"] / np.maximum(table["trees"], 1)
    out.append(
        f"Association of the best history (medians over {runs} logs): {np.median(ratio):.2f} "
        f"identities per tree seen (largest {np.max(ratio):.2f}), purity "
        f"{np.median(table['purity']):.4f} (1.0 in {int(np.sum(table['purity'] == 1))} logs), "
        f"consistency {np.median(table['consistency']):.4f}, split trees "
        f"{np.median(table['split_trees']):.0f} (none in {int(np.sum(table['split_trees'] == 0))}"
        f" logs), loop trees {np.median(table['loop_trees']):.0f}, valid observations never "
        f"associated {np.median(table['unassociated']):.0f} of "
        f"{np.median(table['associated'] + table['unassociated']):.0f}. Smoother converged "
        f"(relative decrease < 1e-10 within 200 steps) in "
        f"{int(np.sum(table['smoothed_converged']))} / {runs}.")
    rows = []
    for label, mask in classes(table).items():
        n = int(np.sum(mask))
        if n == 0:
            rows.append(f"| {label} | 0 | | | | |")
            continue
        rows.append(f"| {label} | {n} | " + " | ".join(
            share(table[name][mask] > 1) for name in errors) + " | "
            + " / ".join(f"{np.median(table[name][mask]):.3f}" for name in errors) + " |")
    out.append("| best history's association | logs | online > 1 m [95 % CI] | best history "
               "> 1 m | own-association MAP > 1 m | medians online / best / MAP [m] |\n"
               "|---|---|---|---|---|---|\n" + "\n".join(rows))
    clean = next(iter(classes(table).values()))
    key_rows = []
    for label, sel in (("online > 1 m", table["online"] > 1), ("online <= 1 m",
                                                               table["online"] <= 1)):
        fixed = table["smoothed"] <= 1
        key_rows.append(
            f"| {label} | {int(np.sum(sel))} | {share(clean[sel])} | "
            f"{share(fixed[sel & clean])} | {share(fixed[sel & ~clean])} | "
            f"{share(table['purity'][sel] < 1)} | {share(table['split_trees'][sel] > 0)} | "
            f"{share((table['loop_closed_trees'] < table['loop_trees'])[sel])} |")
    out.append("| runs | logs | association clean | clean: own-association MAP <= 1 m | not "
               "clean: own-association MAP <= 1 m | purity < 1 | >= 1 split tree | some loop "
               "tree not re-identified |\n|---|---|---|---|---|---|---|---|\n"
               + "\n".join(key_rows))
    diverged = table["online"] > 1
    out.append("| online > 1 m logs | " + " | ".join(
        f"{label.split(', ', 1)[1]}: <= 1 m" for label in oracles.values())
        + " |\n|---|" + "---|" * len(oracles) + "\n| " + str(int(np.sum(diverged))) + " | "
        + " | ".join(share(table[name][diverged] <= 1) for name in oracles) + " |")
    broken = (table["online"] > 1) & (table["first_error_step"] >= 0)
    at_error = table["error_at_first_association_error"][broken]
    over_half = table["first_step_over_half_metre"][broken]
    first = table["first_error_step"][broken]
    if at_error.size:
        out.append(
            f"Order of events in the {at_error.size} online > 1 m logs whose best history "
            f"departs from the true association at some step: the history's position error at "
            f"that first departure is median {np.median(at_error):.3f} m ("
            f"{share(at_error > 0.5)} already > 0.5 m); the first departure comes at median "
            f"step {np.median(first):.0f}, the history first > 0.5 m off at median step "
            f"{np.median(np.where(over_half >= 0, over_half, np.nan)):.0f} (never in "
            f"{int(np.sum(over_half < 0))}); departure before the 0.5 m drift in "
            f"{share((first < over_half) | (over_half < 0))}.")
    out.append(loop_table(table))
    out.append(split_table(table))
    split_rows = []
    for label, sel in (("online > 1 m", table["online"] > 1), ("online <= 1 m",
                                                               table["online"] <= 1)):
        split_rows.append(f"| {label} | {int(np.sum(sel))} | " + " | ".join(
            f"{np.mean(table[f'splits_gap_{lo}_{hi}'][sel]):.2f}" if np.any(sel) else ""
            for lo, hi in SPLIT_GAPS) + " |")
    out.append("| runs | logs | " + " | ".join(
        f"further identities per log, tree last seen {lo}-{hi} steps before" if hi < 10**9
        else f"... > {lo - 1} steps before" for lo, hi in SPLIT_GAPS)
        + " |\n|---|---|" + "---|" * len(SPLIT_GAPS) + "\n" + "\n".join(split_rows))
    indicator = {name: table[name] for name in errors}
    indicator["not clean"] = np.where(clean, 0.0, 2.0)  # sparse_rows counts values > 1
    out.append("| longest stretch with <= 2 valid observations [steps] | logs | online > 1 m "
               "| best history > 1 m | own-association MAP > 1 m | association not clean |\n"
               "|---|---|---|---|---|---|\n" + "\n".join(sparse_rows(table["sparsest"],
                                                                    indicator)))
    return out


def add_regime_arguments(parser: argparse.ArgumentParser) -> None:
    """The logs' and the filter's options (``regime_histories``)."""
    parser.add_argument("--runs", type=int, default=1000)
    parser.add_argument("--forests", type=int, default=50)
    parser.add_argument("--seed", type=int, default=700)
    parser.add_argument("--wobble", type=float, default=0.3)
    parser.add_argument("--odometry", type=float, default=6.0)
    parser.add_argument("--first", type=int, default=None,
                        help="use only the first N of the --runs logs")
    parser.add_argument("--particles", type=int, default=20)
    parser.add_argument("--proposal", default="default",
                        help="the filter: a proposal_study name, optionally with :field=value "
                             "overrides (e.g. \"default:proposal='mixture',mixture_ratio=0.5\")")
    parser.add_argument("--chunk", type=int, default=250, help="filter runs per vmap chunk")
    parser.add_argument("--steps", type=int, default=None,
                        help="keep only the first N steps of each log (tests)")
    parser.add_argument("--iterations", type=int, default=200, help="LM steps of the smoother")
    parser.add_argument("--check", action="store_true",
                        help="also run information_floor.filter_errors (no lineage) and count "
                             "the logs whose online final error it reproduces bit for bit")


def forests_of(args: argparse.Namespace, first: int) -> int:
    """Forests behind the first ``first`` of ``args.runs`` logs (``make_logs``' order;
    ``regime_histories`` returns ``first``)."""
    return first // (args.runs // args.forests)


def regime_histories(args: argparse.Namespace):
    """information_floor.main's logs, keys and params (so its filter column is reproduced) and
    the filter's lineage runs on them. Returns (first: the logs used, controls (R, T, 3), obs
    leaves (R, T, K), truth (R, T+1, 3), params, online final error (R,), histories: the best
    particle's ``LineagePath`` per log (leaves (R, T, ...)), notes: list of str)."""
    if args.runs % args.forests:
        raise SystemExit("--runs must be a multiple of --forests")
    first = args.runs if args.first is None else args.first
    per_forest = args.runs // args.forests
    if first % per_forest or not 0 < first <= args.runs:
        raise SystemExit(f"--first must be a multiple of runs / forests = {per_forest}")
    proposal_name = args.proposal
    if args.check and proposal_name != "default":
        raise SystemExit("--check compares with information_floor's default filter; it cannot "
                         f"check --proposal {proposal_name!r}")
    chunk = min(args.chunk, first)
    if first % chunk:
        raise SystemExit(f"{first} logs must be a multiple of the chunk {chunk}")
    truth_params = regime_params(args.odometry, "lidar")
    key_logs, key_filters = point_keys(args.seed, args.wobble, args.odometry)
    controls, obs, truth, _ = make_logs(key_logs, truth_params, args.wobble, first,
                                        first // per_forest)
    if args.steps is not None:
        controls, truth = controls[:, :args.steps], truth[:, :args.steps + 1]
        obs = jax.tree.map(lambda a: a[:, :args.steps], obs)
    fields, param_fields = proposal_settings(proposal_name)
    params = truth_params._replace(**{k: jnp.asarray(v, jnp.float32)
                                      for k, v in param_fields.items()})
    config = FilterConfig(num_particles=args.particles, max_landmarks=96, max_obs=12, **fields)
    final, histories, compile_s, run_s = lineage_runs(config, params, key_filters,
                                                      controls, obs, truth, chunk)
    online = position_error(final, truth[:, -1])
    print(f"filter with lineage: compile {compile_s:.0f} s, run {run_s:.0f} s; online > 1 m "
          f"{np.mean(online > 1):.3f}", flush=True)
    notes = [f"Filter {proposal_name}, P = {args.particles}, with lineage: compile "
             f"{compile_s:.0f} s, run {run_s:.0f} s ({first * controls.shape[1] / run_s:.3g} "
             "run-steps/s, loaded)."]
    if args.check:
        reference, _, _ = filter_errors(args.particles, params, key_filters,
                                        controls, obs, truth, args.runs, chunk)
        same = int(np.sum(reference == online))
        notes.append(f"information_floor.filter_errors (no lineage, same keys and chunk) "
                     f"reproduces the online final error bit for bit in {same} / {first} logs "
                     f"(largest difference {np.max(np.abs(reference - online)):.3g} m).")
        print(notes[-1], flush=True)
    return first, controls, obs, truth, params, online, histories, notes


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_regime_arguments(parser)
    parser.add_argument("--out", default="results/lineage_check/check",
                        help="prefix of the .npz (per-log arrays) and .md (tables)")
    args = parser.parse_args(argv)
    first, controls, obs, truth, params, online, histories, notes = regime_histories(args)
    tick, per_log, per_loop, per_split = time.perf_counter(), [], [], []
    for r in range(first):
        loops, splits, log = check_log(jax.tree.map(lambda a: a[r], histories), controls[r],
                               jax.tree.map(lambda a: a[r], obs),
                               np.asarray(truth[r], np.float64), params, args.iterations)
        per_log.append(log)
        per_loop.append(dict(loops, log=np.full(loops["tree"].size, r)))
        per_split.append(dict(splits, log=np.full(splits["gap"].size, r)))
        if (r + 1) % 50 == 0:
            print(f"{r + 1} logs checked in {time.perf_counter() - tick:.0f} s", flush=True)
    notes.append(f"Host checks (lineage, association, smoother): "
                 f"{time.perf_counter() - tick:.0f} s.")
    table = {name: np.asarray([log[name] for log in per_log]) for name in per_log[0]}
    table.update(online=online, sparsest=longest_sparse_stretch(obs.valid))
    table.update({f"loop_{name}": np.concatenate([loop[name] for loop in per_loop])
                  for name in per_loop[0]})
    table.update({f"split_{name}": np.concatenate([split[name] for split in per_split])
                  for name in per_split[0]})
    write_outputs("lineage_check.py", argv,
                  [" ".join(notes)] + tables(table, forests_of(args, first)), table, args.out)


if __name__ == "__main__":
    main()
