"""Merging split landmarks (``jaxslam.landmark_merge``) and its use in the M-step."""
from __future__ import annotations

import numpy as np
import pytest

from jaxslam import self_calibration as sc
from jaxslam.landmark_merge import (covisible_distance, covisible_pairs,
                                    merge_split_landmarks, relabel)
from jaxslam.smoothing import Smoothed


def _reference(positions, obs_step, obs_landmark, fraction=0.5):
    """Plain reference: groups as lists with sets of steps; merge the globally nearest
    non-co-visible pair of groups (single linkage) below fraction * d_min until none is
    left."""
    positions = np.asarray(positions, np.float64)
    count = len(positions)
    steps = [set() for _ in range(count)]
    for t, j in zip(obs_step, obs_landmark):
        steps[j].add(int(t))
    d_min = np.inf
    for a in range(count):
        for b in range(a + 1, count):
            if steps[a] & steps[b]:
                d_min = min(d_min, float(np.hypot(*(positions[a] - positions[b]))))
    groups = [[i] for i in range(count) if steps[i]]
    lonely = [[i] for i in range(count) if not steps[i]]
    while True:
        best = None
        for g in range(len(groups)):
            for h in range(g + 1, len(groups)):
                seen_g = set().union(*(steps[i] for i in groups[g]))
                seen_h = set().union(*(steps[i] for i in groups[h]))
                if seen_g & seen_h:
                    continue
                d = min(float(np.hypot(*(positions[a] - positions[b])))
                        for a in groups[g] for b in groups[h])
                if np.isfinite(d_min) and d < fraction * d_min and (best is None or d < best[0]):
                    best = (d, g, h)
        if best is None:
            break
        _, g, h = best
        groups[g] = groups[g] + groups.pop(h)
    labels = np.empty(count, np.int64)
    for label, group in enumerate(sorted(groups + lonely, key=min)):
        labels[group] = label
    return labels


def test_split_tree_is_merged():
    # Trees A (0) and B (1) seen together at step 0; A seen again later as landmark 2, 0.3 m
    # from A: one tree split in two. d_min = |A - B| = 5 m.
    positions = np.array([[0.0, 0.0], [5.0, 0.0], [0.3, 0.0]])
    labels = merge_split_landmarks(positions, [0, 0, 7, 8], [0, 1, 2, 2])
    np.testing.assert_array_equal(labels, [0, 1, 0])


def test_covisible_trees_are_never_merged():
    # 0 and 1 are 1 cm apart but seen at one step: two trees, whatever the distance.
    positions = np.array([[0.0, 0.0], [0.01, 0.0], [0.004, 0.0]])
    labels = merge_split_landmarks(positions, [0, 0, 3], [0, 1, 2])
    assert labels[0] != labels[1]
    # 2 joins 0 (4 mm, under d_min / 2 = 5 mm); at fraction 1, 2 is also a candidate of 1
    # (6 mm), but the group {0, 2} is then co-visible with 1, so it does not join 1 as well.
    np.testing.assert_array_equal(labels, [0, 1, 0])
    np.testing.assert_array_equal(
        merge_split_landmarks(positions, [0, 0, 3], [0, 1, 2], fraction=1.0), [0, 1, 0])


def test_group_covisibility_blocks_a_merge():
    # 0 and 2 are near, 1 and 2 are near; 0 and 1 co-visible (step 0) but 5 m apart.
    # 2 is merged with the nearer of 0 and 1; never both, since 0 and 1 are two trees.
    positions = np.array([[0.0, 0.0], [5.0, 0.0], [0.2, 0.0], [4.9, 0.0]])
    labels = merge_split_landmarks(positions, [0, 0, 4, 5, 9], [0, 1, 2, 3, 3])
    np.testing.assert_array_equal(labels, [0, 1, 0, 1])


def test_chain_is_merged_by_single_linkage():
    # d_min = 10 m (0 and 4 seen together). 1-2-3 are a chain with 4 m links: 1 and 3 are
    # 8 m apart, beyond d_min / 2, and still one group through 2.
    positions = np.array([[0.0, 0.0], [0.0, 20.0], [4.0, 20.0], [8.0, 20.0], [10.0, 0.0]])
    labels = merge_split_landmarks(positions, [0, 0, 1, 2, 3], [0, 4, 1, 2, 3])
    np.testing.assert_array_equal(labels, [0, 1, 1, 1, 2])


def test_no_covisible_pair_merges_nothing():
    positions = np.array([[0.0, 0.0], [0.1, 0.0]])
    np.testing.assert_array_equal(merge_split_landmarks(positions, [0, 1], [0, 1]), [0, 1])
    assert covisible_distance(positions, covisible_pairs([0, 1], [0, 1], 2)) == np.inf


def test_empty_input():
    labels = merge_split_landmarks(np.zeros((0, 2)), np.zeros(0, int), np.zeros(0, int))
    assert labels.shape == (0,) and labels.dtype == np.int64
    np.testing.assert_array_equal(relabel(np.full((3, 2), -1), labels), np.full((3, 2), -1))


def test_unobserved_landmark_keeps_its_own_label():
    # Landmark 1 has no observation (a smoothed index with none stays at the origin).
    positions = np.array([[0.0, 0.0], [0.0, 0.0], [5.0, 0.0], [0.1, 0.0]])
    labels = merge_split_landmarks(positions, [0, 0, 3], [0, 2, 3])
    np.testing.assert_array_equal(labels, [0, 1, 2, 0])


def test_covisible_pairs_against_loops():
    rng = np.random.default_rng(0)
    step, landmark = rng.integers(0, 30, 80), rng.integers(0, 12, 80)
    expected = np.zeros((12, 12), bool)
    for a in range(12):
        for b in range(12):
            expected[a, b] = a != b and bool(set(step[landmark == a]) & set(step[landmark == b]))
    np.testing.assert_array_equal(covisible_pairs(step, landmark, 12), expected)


@pytest.mark.parametrize("fraction", [0.5, 1.0])
@pytest.mark.parametrize("seed", range(12))
def test_matches_the_reference_on_random_maps(seed, fraction):
    # Trees on a 20 m square, each split into 1-3 pieces at 0.5 m scatter, each piece seen
    # on its own run of steps with a few co-visible neighbours per step. Labels are exact
    # integers: no tolerance (ties have probability 0 with continuous positions).
    rng = np.random.default_rng(seed)
    trees = rng.uniform(0, 20, (8, 2))
    pieces = np.repeat(np.arange(8), rng.integers(1, 4, 8))
    positions = trees[pieces] + 0.5 * rng.normal(size=(len(pieces), 2))
    steps, landmarks = [], []
    for piece in range(len(pieces)):
        start = rng.integers(0, 200)
        t = np.arange(start, start + rng.integers(2, 10))
        steps.append(t)
        landmarks.append(np.full(len(t), piece))
    step, landmark = np.concatenate(steps), np.concatenate(landmarks)
    labels = merge_split_landmarks(positions, step, landmark, fraction)
    np.testing.assert_array_equal(labels, _reference(positions, step, landmark, fraction))
    together = covisible_pairs(step, landmark, len(pieces))
    assert not np.any(together & (labels[:, None] == labels[None]))


def test_relabel_keeps_unassociated():
    ids = np.array([[0, -1], [2, 1]])
    np.testing.assert_array_equal(relabel(ids, np.array([0, 1, 0])), [[0, -1], [0, 1]])


def test_m_step_resmooths_with_merged_labels():
    # The split tree of ``test_split_tree_is_merged`` as a smoothed solution: ``_merged``
    # smooths again from the smoothed path with landmark 2 relabelled 0, and leaves a
    # solution with nothing to merge alone.
    ids = np.array([[0, 1], [-1, -1], [2, -1], [2, -1]])
    smoothed = Smoothed(np.zeros((4, 3)), np.array([[0.0, 0.0], [5.0, 0.0], [0.3, 0.0]]), ids,
                        np.zeros(1), 1, True)
    calls = []

    def smooth(path, landmark_of_obs):
        calls.append((path, landmark_of_obs))
        return smoothed._replace(landmark_of_obs=landmark_of_obs)

    merged = sc._merged(smoothed, smooth)
    assert len(calls) == 1 and calls[0][0] is smoothed.path
    np.testing.assert_array_equal(merged.landmark_of_obs, [[0, 1], [-1, -1], [0, -1], [0, -1]])
    apart = smoothed._replace(landmark=np.array([[0.0, 0.0], [5.0, 0.0], [-9.0, 0.0]]))
    assert sc._merged(apart, smooth) is apart and len(calls) == 1


def test_calibrate_params_merge_is_off_by_default():
    """Documented off by default (it broke two simulated calibrations and lowered the MRCLAM
    ratio): the keyword exists and defaults to False."""
    assert sc.calibrate_params.__kwdefaults__["merge_landmarks"] is False
