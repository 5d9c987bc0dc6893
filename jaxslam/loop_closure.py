"""Close the loops a filter missed: register a group of newer landmarks onto older ones.

A particle filter that returns to a place after drifting by about the spacing between trees
meets its old landmarks too far from where it expects them, starts new ones, and its best
particle's history holds the loop's trees twice. ``landmark_merge`` joins pieces closer than
half the smallest co-visible distance d_min; a loop's pieces are apart by the drift, metres,
and one tree's piece is then nearer another tree. What survives the drift is the SHAPE of
the group of trees in view: the trees seen together at the return keep their relative
positions (the drift between them is a few steps' worth), so the whole group maps onto its
old pieces by one rigid transform. This is the geometric verification of landmark-based
loop closure (the consensus of correspondences under one rigid transform, as in random
sample consensus: Fischler and Bolles, "Random sample consensus: a paradigm for model
fitting with applications to image analysis and automated cartography"), applied to the
smoothed map of the filter's own association; the smoother (Thrun, Burgard and Fox,
Probabilistic Robotics, ch. 11, GraphSLAM) then re-solves with the closure, which pulls the
loop shut.

Criterion (``find_revisits``). A landmark a is OLDER than b when a's last sighting precedes
b's first (so they were never seen together and b could be a's return). A hypothesis pairs
two newer landmarks b1, b2 seen together with two older ones a1, a2 seen together, a_i older
than b_i, whose distances agree: | |m_b1 - m_b2| - |m_a1 - m_a2| | < r. It fixes the rigid
transform (R, t) taking b1, b2 onto a1, a2 (rotation of b2 - b1 onto a2 - a1, centroids
matched). Its GROUP is b1, b2 and every landmark seen together with b1 or b2; a group member
g is an inlier when R m_g + t lies within r of a landmark older than g. Candidates are
ranked by the distinct older landmarks their group lands on (most first, then the smallest
summed distance) and need ``min_inliers`` of them. The radius is
r = f d_min with f = 1/2, the same radius and argument as ``landmark_merge``: within d_min / 2
of a tree, that tree is the nearest. With the default ``min_inliers`` = 3, one tree beyond the
two that define the transform must land on an old tree. That alone is weak evidence (a
random forest holds many such triples: on the tuning logs most candidates are false,
rotated by radians or shifted by tens of metres); the smoother's cost test decides.

Driver (``close_loops``). Smooth the filter's association; repeat: take the candidates in
order, join a candidate's matched pairs (``landmark_merge.join_groups``: never two landmarks
seen together), re-solve, and keep the first whose cost rise passes the test in
``close_loops``; then join the pieces now within d_min / 2 (``landmark_merge``), under the
same test (on a map that has not been closed yet, a piece drifted by about d_min / 2 can
sit nearest another tree); until neither joins anything or after ``rounds`` rounds.

All on the host in NumPy: the number of landmarks changes with every closure.

Shapes: L landmarks, N observations, H hypotheses, T steps, K observation rows.
"""
from __future__ import annotations

from typing import Callable, NamedTuple

import numpy as np
import scipy.spatial

from jaxslam.landmark_merge import (covisible_distance, covisible_pairs, join_groups,
                                    merge_split_landmarks, relabel)


class Closure(NamedTuple):
    """One registered revisit.

    pairs: (n, 2) int (older, newer) landmark ids proposed for joining, in the ids of the map
    it was found on (``join_groups`` skips a pair whose groups were seen together); angle:
    rotation [rad] and
    translation (2,) [m] of the transform taking the newer group onto the older landmarks;
    hypotheses: how many hypotheses were scored.
    """

    pairs: np.ndarray
    angle: float
    translation: np.ndarray
    hypotheses: int


def landmark_spans(obs_step, obs_landmark, num_landmarks: int):
    """(L,) first and (L,) last step each landmark was observed (-1 and -1 when never)."""
    obs_step = np.asarray(obs_step, np.int64).reshape(-1)
    obs_landmark = np.asarray(obs_landmark, np.int64).reshape(-1)
    first = np.full(num_landmarks, np.iinfo(np.int64).max)
    last = np.full(num_landmarks, -1, np.int64)
    np.minimum.at(first, obs_landmark, obs_step)
    np.maximum.at(last, obs_landmark, obs_step)
    return np.where(last >= 0, first, -1), last


def rigid_from_pairs(source, target):
    """The 2-D rigid transforms taking point pairs ``source`` onto ``target``.

    R rotates source[1] - source[0] onto the direction of target[1] - target[0]; t matches the
    centroids: t = mean(target) - R mean(source). source, target (H, 2, 2) [m]. Returns
    angle (H,) [rad] in (-pi, pi] and t (H, 2) [m].
    """
    source, target = np.asarray(source, np.float64), np.asarray(target, np.float64)
    ds, dt = source[:, 1] - source[:, 0], target[:, 1] - target[:, 0]
    angle = np.angle(np.exp(1j * (np.arctan2(dt[:, 1], dt[:, 0])
                                  - np.arctan2(ds[:, 1], ds[:, 0]))))
    return angle, target.mean(1) - rotate(source.mean(1), angle)


def rotate(points, angle):
    """points (..., 2) rotated by angle (...,) [rad]."""
    c, s = np.cos(angle), np.sin(angle)
    return np.stack([c * points[..., 0] - s * points[..., 1],
                     s * points[..., 0] + c * points[..., 1]], -1)


def _hypotheses(positions, together, older, radius):
    """(H, 2) newer and (H, 2) older landmark ids of the module docstring's hypotheses.

    The older pairs are sorted by length, so each newer pair finds the ones within
    ``radius`` of its length by bisection: memory O(H + pairs), not (pairs, pairs)."""
    b1, b2 = np.nonzero(np.triu(together, 1))
    a1, a2 = np.nonzero(together)  # ordered: both orientations of each older pair
    length = lambda i, j: np.linalg.norm(positions[i] - positions[j], axis=-1)
    order = np.argsort(length(a1, a2), kind="stable")
    a1, a2 = a1[order], a2[order]
    sorted_length = length(a1, a2)
    new_length = length(b1, b2)
    lo = np.searchsorted(sorted_length, new_length - radius, side="right")
    hi = np.searchsorted(sorted_length, new_length + radius, side="left")
    n = np.repeat(np.arange(len(b1)), hi - lo)
    o = np.arange(n.size) - np.repeat(np.cumsum(hi - lo) - (hi - lo), hi - lo) + lo[n]
    keep = older[a1[o], b1[n]] & older[a2[o], b2[n]]
    n, o = n[keep], o[keep]
    return np.stack([b1[n], b2[n]], -1), np.stack([a1[o], a2[o]], -1)


def _inliers(positions, together, older, radius, newer_pair, older_pair, tree=None):
    """Per hypothesis (H of them, groups padded to G members): distinct older landmarks hit
    (H,), the group's members (H, G) (-1: padding), the older landmark each member lands on
    (H, G) (-1: none), summed inlier distance (H,) [m], angle (H,) and translation (H, 2).

    A member lands on the nearest landmark older than it within ``radius`` of its moved
    position (the lowest id among equally near ones). The candidates are the landmarks a
    k-d tree over ``positions`` (``tree``) finds within a slightly larger radius (k is the
    most any moved member has there, so the nearest older one is always among them); their
    distances are then computed as hypot(dx, dy) and tested < ``radius``. Memory (H, L)
    int64 (the members' order), (H, G, k) floats, not (H, G, L)."""
    tree = scipy.spatial.cKDTree(positions) if tree is None else tree
    angle, shift = rigid_from_pairs(positions[newer_pair], positions[older_pair])
    in_group = together[newer_pair[:, 0]] | together[newer_pair[:, 1]]  # (H, L)
    in_group[np.arange(len(in_group))[:, None], newer_pair] = True
    size = int(in_group.sum(1).max())
    member = np.argsort(~in_group, axis=1, kind="stable")[:, :size]  # (H, G)
    real = np.take_along_axis(in_group, member, 1)
    moved = rotate(positions[member], angle[:, None]) + shift[:, None]  # (H, G, 2)
    points = moved[real]  # (M, 2) the real members' moved positions
    lands = np.full(member.shape, -1)
    gap = np.full(member.shape, np.inf)
    reach = radius * (1.0 + 1e-9) + 1e-12  # covers the tree's rounding of the distance
    neighbours = int(np.max(tree.query_ball_point(points, reach, return_length=True)))
    if neighbours > 0:
        _, index = tree.query(points, k=neighbours, distance_upper_bound=reach)
        index = index.reshape(len(points), -1)  # (M, k), len(positions) where none
        found = index < len(positions)
        index = np.where(found, index, 0)
        distance = np.hypot(points[:, 0, None] - positions[index, 0],
                            points[:, 1, None] - positions[index, 1])  # (M, k)
        candidate = found & older[index, member[real][:, None]] & (distance < radius)
        distance = np.where(candidate, distance, np.inf)
        hit = distance.min(-1)  # (M,)
        nearest = np.where(candidate & (distance == hit[:, None]), index, len(positions))
        lands[real] = np.where(np.isfinite(hit), nearest.min(-1), -1)
        gap[real] = hit
    hits = np.sort(lands, axis=1)
    first_of_value = np.ones_like(hits, bool)
    first_of_value[:, 1:] = hits[:, 1:] != hits[:, :-1]
    distinct = np.sum(first_of_value & (hits >= 0), 1)
    return (distinct, np.where(real, member, -1), lands,
            np.where(lands >= 0, gap, 0.0).sum(-1), angle, shift)


def find_revisits(positions, obs_step, obs_landmark, fraction: float = 0.5,
                  min_inliers: int = 3, candidates: int = 4,
                  chunk: int = 4096) -> list[Closure]:
    """The best-supported revisits of the map (module docstring), most distinct older
    landmarks hit first (then the smallest summed inlier distance). A candidate that shares
    a joined pair with a better one is a variant of the same registration and is left out,
    so the ``candidates`` returned are distinct registrations; none hits fewer than
    ``min_inliers`` older landmarks.

    Args:
      positions: (L, 2) landmark positions [m] (a smoothed map).
      obs_step: (N,) step of each observation; obs_landmark: (N,) its landmark in [0, L).
      fraction: f: the inlier radius is f d_min.
      min_inliers: the fewest distinct older landmarks the group must land on (the two that
        define the transform included).
      candidates: most candidates returned.
      chunk: hypotheses scored at once (memory (chunk, L) int64 and (chunk, G, k) floats, G
        the largest group, k the most landmarks within the radius of a moved member).
    """
    if min_inliers < 2:
        raise ValueError(f"min_inliers must be >= 2 (the two landmarks that define the "
                         f"transform always fit); got {min_inliers}")
    positions = np.asarray(positions, np.float64).reshape(-1, 2)
    count = len(positions)
    if count == 0:
        return []
    together = covisible_pairs(obs_step, obs_landmark, count)
    radius = fraction * covisible_distance(positions, together)
    if not (np.isfinite(radius) and radius > 0):  # two co-visible landmarks at one point:
        return []                                 # nothing lies within a zero radius
    first, last = landmark_spans(obs_step, obs_landmark, count)
    seen = last >= 0
    older = (last[:, None] < first[None]) & seen[:, None] & seen[None]  # older[a, b]
    newer_pair, older_pair = _hypotheses(positions, together, older, radius)
    tree = scipy.spatial.cKDTree(positions)
    found = []
    for lo in range(0, len(newer_pair), chunk):
        part = slice(lo, lo + chunk)
        distinct, member, lands, spread, angle, shift = _inliers(
            positions, together, older, radius, newer_pair[part], older_pair[part], tree)
        for h in np.nonzero(distinct >= min_inliers)[0]:
            hit = lands[h] >= 0
            pairs = np.stack([lands[h, hit], member[h, hit]], -1)
            found.append(((-int(distinct[h]), float(spread[h])),
                          Closure(pairs, float(angle[h]), shift[h], len(newer_pair))))
    kept, used = [], set()
    for _, closure in sorted(found, key=lambda item: item[0]):
        pairs = set(map(tuple, closure.pairs.tolist()))
        if pairs & used:
            continue
        used |= pairs
        kept.append(closure)
        if len(kept) == candidates:
            break
    return kept


MAX_RISE_PER_DOF = 100.0  # cost rise per removed unknown a join may add (close_loops)


class Tested(NamedTuple):
    """One join ``close_loops`` tested.

    kind: "closure" (a ``find_revisits`` candidate) or "merge" (``landmark_merge``'s set);
    pairs: (n, 2) (kept, joined) landmark ids proposed, in the ids of ``landmark_of_obs``;
    landmark_of_obs: (T, K) the association the ids refer to (the map before the join);
    rise_per_dof: the cost rise over the unknowns the join removes (2 per landmark);
    accepted: whether it passed.
    """

    kind: str
    pairs: np.ndarray
    landmark_of_obs: np.ndarray
    rise_per_dof: float
    accepted: bool


class ClosedLoops(NamedTuple):
    """Result of ``close_loops``: the last ``Smoothed``; the accepted ``Closure``s in order
    (ids of their round's map); every ``Tested`` join; landmarks_joined: landmarks before
    less landmarks after (each join that passed removes the landmarks it joins)."""

    smoothed: object
    closures: list
    tested: list
    landmarks_joined: int


def close_loops(smooth: Callable[..., object], path, landmark_of_obs, rounds: int = 8,
                max_rise_per_dof: float = MAX_RISE_PER_DOF, verify_iterations: int = 30,
                **find_options) -> ClosedLoops:
    """Smooth, then close verified loops and merge split pieces (module docstring).

    Each round takes ``find_revisits``' candidates in order, re-solves with a candidate's
    pairs joined (``join_groups``; at most ``verify_iterations`` Levenberg-Marquardt steps
    from the current path) and accepts the first whose least-squares cost rises by less than
    ``max_rise_per_dof`` x 2 n, n the landmarks the join removes (2 unknowns each). Under an
    exact Gaussian model a true join's rise is chi-square with 2 n degrees of freedom (about
    1 per degree of freedom); odometry whose errors are heavier-tailed than its model (large
    turns: the noise of Geiser et al. 2023, Eq. (1) is evaluated at the measured turn)
    makes it larger. A false registration has to bend the whole loop's odometry and raises
    the cost by orders of magnitude more. The distance merges of ``landmark_merge`` face the
    same test, as one set. The limit was read off the first 40 tuning logs of
    ``experiments/loop_closure_study.py`` (seed 800, true noise, plain squares): true
    candidates rose 0.4-17 per degree of freedom, false ones 6,500 or more; the study
    records every tested join's rise (``Tested``) for checking it on other logs. The cost
    must be comparable between solves: ``smooth`` must use fixed noise (no
    ``calibrate_rounds``, no ``visit_gap``), and plain squares are what the limit was
    measured with. The test needs a solved base (``_settled``): one that is not is solved
    again once, and if it still is not, nothing more is joined (a rise measured from a cost
    still falling would be too small).

    Args:
      smooth: (path (T, 3), landmark_of_obs (T, K), iterations) -> ``smoothing.Smoothed``
        (e.g. ``smoothing.smooth_path`` with its other arguments bound); called without
        ``iterations`` for the full solves.
      path: (T, 3) initial poses (the filter's history); landmark_of_obs: (T, K) its
        association (-1: none), ids 0..L-1 with none empty.
      rounds: most rounds (a round makes at most one closure and one merge).
      max_rise_per_dof: the test's limit (above).
      verify_iterations: the LM steps a candidate gets before the test.
      find_options: passed to ``find_revisits``.
    """
    if not max_rise_per_dof > 0 or verify_iterations < 1:
        raise ValueError(f"max_rise_per_dof must be > 0 and verify_iterations >= 1; got "
                         f"{max_rise_per_dof} and {verify_iterations}")
    tested = []

    def joined(smoothed, kind, pairs, labels):
        """``smoothed`` re-solved with ``labels`` (L,) joined when the rise passes, else None."""
        count = len(labels) - (labels.max() + 1) if len(labels) else 0
        if count == 0:
            return None
        ids = relabel(smoothed.landmark_of_obs, labels)
        trial = smooth(smoothed.path, ids, verify_iterations)
        rise = (trial.cost[-1] - smoothed.cost[-1]) / (2 * count)
        tested.append(Tested(kind, pairs, np.asarray(smoothed.landmark_of_obs), float(rise),
                             bool(rise < max_rise_per_dof)))
        return smooth(trial.path, ids) if tested[-1].accepted else None

    smoothed = smooth(np.asarray(path, np.float64), np.asarray(landmark_of_obs))
    before, closures = _count(smoothed), []
    for _ in range(rounds):
        if not _settled(smoothed, max_rise_per_dof):
            smoothed = smooth(smoothed.path, smoothed.landmark_of_obs)
            if not _settled(smoothed, max_rise_per_dof):
                break
        step, landmark = _observed(smoothed)
        together = covisible_pairs(step, landmark, len(smoothed.landmark))
        closed = None
        for closure in find_revisits(smoothed.landmark, step, landmark, **find_options):
            closed = joined(smoothed, "closure", closure.pairs,
                            join_groups(closure.pairs, together))
            if closed is not None:
                closures.append(closure)
                smoothed = closed
                break
        step, landmark = _observed(smoothed)
        labels = merge_split_landmarks(smoothed.landmark, step, landmark)
        merged = joined(smoothed, "merge", _label_pairs(labels), labels)
        smoothed = smoothed if merged is None else merged
        if closed is None and merged is None:
            break
    return ClosedLoops(smoothed, closures, tested, before - _count(smoothed))


SETTLED = 1e-4  # a base whose last step lowered the cost by < this x the limit counts as solved


def _settled(smoothed, max_rise_per_dof: float) -> bool:
    """Whether a ``Smoothed`` is solved well enough to test joins against: converged, or its
    last step lowered the cost by less than ``SETTLED`` x the limit (LM's slow tail on long
    logs; the descent still ahead is then small against one join's allowance of 2 x the
    limit)."""
    cost = np.asarray(smoothed.cost)
    return bool(smoothed.converged) or (
        cost.size > 1 and cost[-2] - cost[-1] < SETTLED * max_rise_per_dof)


def _count(smoothed) -> int:
    """Landmarks with an observation in a ``Smoothed``."""
    return int(np.unique(np.asarray(smoothed.landmark_of_obs)[
        np.asarray(smoothed.landmark_of_obs) >= 0]).size)


def _label_pairs(labels) -> np.ndarray:
    """(n, 2) (first member of its group, member) of every landmark a relabelling (L,)
    joins to an earlier one."""
    labels = np.asarray(labels, np.int64)
    _, first = np.unique(labels, return_index=True)
    lead = first[labels]
    joined = np.nonzero(lead != np.arange(len(labels)))[0]
    return np.stack([lead[joined], joined], -1)


def _observed(smoothed):
    """(N,) step and (N,) landmark of each associated observation of a ``Smoothed``."""
    ids = np.asarray(smoothed.landmark_of_obs)
    step, row = np.nonzero(ids >= 0)
    return step, ids[step, row]
