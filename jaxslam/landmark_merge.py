"""Merge landmarks a filter split: one tree mapped as several identities, joined again.

A particle filter that loses its pose starts a new landmark where it meets an old one, so its
best particle's history can hold one tree under many identities and the smoother on that
history sees no loop closure. ``merge_split_landmarks`` relabels the smoothed map so that
identities that are plausibly one tree get one label.

Criterion. Landmarks a and b (positions m_a, m_b) are candidates when

    (1) they were never observed at the same step: a detector does not see one tree twice in
        one scan, so two landmarks seen in one scan are two trees; and
    (2) || m_a - m_b || < f d_min,  d_min = min { || m_c - m_d || : c, d observed at a common
        step },

d_min being the smallest distance between two landmarks the log itself shows to be distinct.
With the default f = 1/2 the merge is unambiguous: if distinct trees are at least d_min apart
and b lies within d_min / 2 of a's tree, every other tree is more than d_min / 2 from b
(triangle inequality), so a's tree is b's nearest. With f = 1 (the plain "closer than any two
co-visible landmarks") a split piece can sit between two trees and join the wrong one.

Why this threshold and not a chi-square gate on m_a - m_b with the smoother's covariances:
the pieces of a split tree lie apart by the drift the filter accumulated between the pieces'
sightings (metres on a long loop), and a gate needs the joint marginal covariance of the two
positions, which includes that drift only if it is computed from the full smoothed information
matrix (the positions' own observation noise, decimetres, would gate out every split tree).
The co-visible distance needs no covariance, and it adapts to the forest: dense trees give a
small d_min and few merges. It is only as good as its smallest co-visible pair: a false alarm
kept as a landmark beside a tree, or a tree detected twice in one scan, gives a small d_min,
which makes the merge cautious (fewer merges), not wrong.
With no co-visible pair, d_min is undefined and nothing is merged.

Merging is greedy, nearest pair first, single linkage with union-find: a pair's groups are
joined unless some member of one was observed at a step with some member of the other (the
same rule (1) lifted to groups). So a chain a-b, b-c of candidate pairs joins a, b, c even
when a and c are farther apart than f d_min, and two co-visible trees never share a label.

All on the host in NumPy: the number of landmarks changes with every EM iteration.

Shapes: L landmarks, N observations.
"""
from __future__ import annotations

import numpy as np
from scipy import sparse


def covisible_pairs(obs_step, obs_landmark, num_landmarks: int) -> np.ndarray:
    """(L, L) bool: landmarks a != b observed at a common step.

    Args:
      obs_step: (N,) step of each observation; obs_landmark: (N,) its landmark in [0, L).
    """
    obs_step = np.asarray(obs_step, np.int64).reshape(-1)
    obs_landmark = np.asarray(obs_landmark, np.int64).reshape(-1)
    steps, step = np.unique(obs_step, return_inverse=True)
    seen = sparse.csr_matrix((np.ones(len(step), np.int32), (obs_landmark, step.reshape(-1))),
                             shape=(num_landmarks, len(steps)))  # (L, steps with observations)
    together = (seen @ seen.T).toarray() > 0
    np.fill_diagonal(together, False)
    return together


def covisible_distance(positions, together) -> float:
    """d_min (module docstring): smallest distance between two co-visible landmarks; inf
    when no pair is co-visible. positions (L, 2), together (L, L) bool."""
    positions = np.asarray(positions, np.float64)
    if not together.any():
        return float("inf")
    distance = np.linalg.norm(positions[:, None] - positions[None], axis=-1)
    return float(distance[together].min())


def _find(parent, a):
    while parent[a] != a:
        parent[a] = parent[parent[a]]
        a = parent[a]
    return a


def merge_split_landmarks(positions, obs_step, obs_landmark,
                          fraction: float = 0.5) -> np.ndarray:
    """Relabelling (L,) of landmarks into merged ids 0..G-1 (module docstring).

    Args:
      positions: (L, 2) smoothed landmark positions [m].
      obs_step: (N,) step of each observation; obs_landmark: (N,) its landmark in [0, L).
        A landmark with no observation keeps a label of its own.
      fraction: f of the module docstring: candidates lie closer than f d_min.
    Returns:
      (L,) int64 merged id of each landmark, numbered in order of each group's first member
      (so with no merge it is arange(L)).
    """
    positions = np.asarray(positions, np.float64).reshape(-1, 2)
    count = len(positions)
    obs_landmark = np.asarray(obs_landmark, np.int64)
    if count == 0:
        return np.zeros(0, np.int64)
    together = covisible_pairs(obs_step, obs_landmark, count)
    threshold = fraction * covisible_distance(positions, together)
    observed = np.bincount(obs_landmark, minlength=count) > 0
    distance = np.linalg.norm(positions[:, None] - positions[None], axis=-1)
    candidate = (np.triu(~together, 1) & (distance < threshold) & np.isfinite(threshold)
                 & observed[:, None] & observed[None])
    a, b = np.nonzero(candidate)
    order = np.argsort(distance[a, b], kind="stable")
    return join_groups(np.stack([a[order], b[order]], -1), together)


def join_groups(pairs, together) -> np.ndarray:
    """Relabelling (L,) that joins the landmark pairs ``pairs`` (n, 2), taken in order,
    single linkage with union-find, skipping a pair whose groups hold two landmarks seen
    together (``together`` (L, L) bool, ``covisible_pairs``). Labels 0..G-1 are numbered in
    order of each group's first member (with no join, arange(L))."""
    count = len(together)
    parent = np.arange(count)
    group_together = np.array(together, bool)  # rows/columns of roots: co-visible with the group
    for i, j in np.asarray(pairs, np.int64).reshape(-1, 2):
        ri, rj = _find(parent, i), _find(parent, j)
        if ri == rj or group_together[ri, rj]:
            continue
        root, other = min(ri, rj), max(ri, rj)
        parent[other] = root
        group_together[root] |= group_together[other]
        group_together[:, root] |= group_together[:, other]
    roots = np.array([_find(parent, i) for i in range(count)], np.int64)
    _, labels = np.unique(roots, return_inverse=True)
    # Number groups by first member: np.unique sorts roots, and each root is its group's
    # smallest member, so the order is already by first member.
    return labels.astype(np.int64).reshape(count)


def relabel(landmark_of_obs, labels) -> np.ndarray:
    """(T, K) ``landmark_of_obs`` with each id >= 0 replaced by ``labels[id]`` (-1 kept)."""
    landmark_of_obs = np.asarray(landmark_of_obs)
    labels = np.asarray(labels, np.int64)
    out = np.full(landmark_of_obs.shape, -1, np.int64)
    associated = landmark_of_obs >= 0
    out[associated] = labels[landmark_of_obs[associated]]
    return out
