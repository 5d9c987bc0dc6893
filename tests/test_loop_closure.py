"""Loop closure by registration (jaxslam.loop_closure): transforms, candidates, the driver."""
import numpy as np
import pytest

from jaxslam.landmark_merge import covisible_pairs, join_groups
from jaxslam.loop_closure import (close_loops, find_revisits, landmark_spans,
                                  rigid_from_pairs, rotate)
from jaxslam.motion import apply_odometry
from jaxslam.smoothing import smooth_path
from jaxslam.types import default_params


def reference_rigid(source, target):
    """Plain float64 least-squares rigid fit (Kabsch in 2-D) of one point set onto another."""
    cs, ct = source.mean(0), target.mean(0)
    h = (source - cs).T @ (target - ct)
    angle = np.arctan2(h[0, 1] - h[1, 0], h[0, 0] + h[1, 1])
    rot = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    return angle, ct - rot @ cs


def test_rigid_from_pairs_matches_least_squares_fit_of_two_points():
    rng = np.random.default_rng(0)
    source = rng.normal(size=(50, 2, 2)) * 5
    angle = rng.uniform(-np.pi, np.pi, 50)
    shift = rng.normal(size=(50, 2)) * 10
    target = rotate(source, angle[:, None]) + shift[:, None]
    got_angle, got_shift = rigid_from_pairs(source, target)
    for i in range(50):
        ref_angle, ref_shift = reference_rigid(source[i], target[i])
        # Two exact points: both fits are the exact transform, to float64 rounding.
        np.testing.assert_allclose(np.cos(got_angle[i] - ref_angle), 1.0, atol=1e-12)
        np.testing.assert_allclose(got_shift[i], ref_shift, atol=1e-9)
    # Unequal pair lengths: the rotation aligns the directions and the centroids coincide.
    source = np.array([[[0.0, 0.0], [2.0, 0.0]]])
    target = np.array([[[1.0, 1.0], [1.0, 4.0]]])
    angle, shift = rigid_from_pairs(source, target)
    np.testing.assert_allclose(angle, [np.pi / 2])
    np.testing.assert_allclose(rotate(source.mean(1), angle) + shift, target.mean(1))


def test_landmark_spans():
    first, last = landmark_spans([3, 1, 7, 2], [0, 0, 2, 0], 4)
    np.testing.assert_array_equal(first, [1, -1, 7, -1])
    np.testing.assert_array_equal(last, [3, -1, 7, -1])


def revisit_map(angle=0.2, shift=(1.5, -2.0)):
    """Six old trees seen at steps 0-2 and a group of four re-seen at step 50 under a rigid
    drift. Other transforms also land three or four of the group on old trees (a false one,
    rotated by about 3 rad, lands four): the true one ranks first by its smaller summed
    distance (zero)."""
    old = np.array([[0.0, 0.0], [3.1, 0.4], [1.2, 2.7], [5.0, 3.3], [-2.2, 4.1], [8.0, -1.0]])
    back = [1, 2, 3, 4]
    new = rotate(old[back], -angle) - rotate(np.asarray(shift), -angle)  # inverse drift
    positions = np.concatenate([old, new])
    step = [0, 0, 0, 1, 1, 1, 2, 2, 50, 50, 50, 50]
    landmark = [0, 1, 2, 2, 3, 4, 4, 5, 6, 7, 8, 9]
    return positions, np.asarray(step), np.asarray(landmark), back


def test_close_loops_rejects_a_false_registration():
    """The loop log's candidates include false registrations (pairs of different trees);
    joining one bends the loop and its cost rise per degree of freedom is far above the limit,
    while the true one (the first) passes."""
    from jaxslam.landmark_merge import relabel
    from jaxslam.loop_closure import MAX_RISE_PER_DOF
    smooth, dead, ids, tree, _ = loop_smoother()
    base = smooth(dead, ids)
    landmark_of_obs = np.asarray(base.landmark_of_obs)
    step, row = np.nonzero(landmark_of_obs >= 0)
    landmark = landmark_of_obs[step, row]
    tree_of = np.zeros(landmark.max() + 1, int)
    tree_of[landmark] = tree[step, row]
    together = covisible_pairs(step, landmark, len(tree_of))
    rises = {}
    for closure in find_revisits(base.landmark, step, landmark, candidates=20):
        true = bool(np.all(tree_of[closure.pairs[:, 0]] == tree_of[closure.pairs[:, 1]]))
        labels = join_groups(closure.pairs, together)
        trial = smooth(base.path, relabel(landmark_of_obs, labels), 30)
        removed = len(labels) - labels.max() - 1
        rises.setdefault(true, []).append((trial.cost[-1] - base.cost[-1]) / (2 * removed))
    assert rises.get(True) and rises.get(False), "need both a true and a false candidate"
    assert max(rises[True]) < MAX_RISE_PER_DOF < min(rises[False])


def test_find_revisits_recovers_the_drifted_group():
    positions, step, landmark, back = revisit_map()
    found = find_revisits(positions, step, landmark)
    assert found, "the rigidly drifted group must be a candidate"
    best = found[0]
    np.testing.assert_array_equal(best.pairs, np.stack([back, [6, 7, 8, 9]], -1))
    np.testing.assert_allclose(best.angle, 0.2, atol=1e-9)
    np.testing.assert_allclose(best.translation, [1.5, -2.0], atol=1e-9)


def test_find_revisits_needs_the_older_landmark_to_be_gone_before_the_newer():
    positions, step, landmark, _ = revisit_map()
    # Seen together with the old trees: no landmark is older than another, no hypothesis.
    assert find_revisits(positions, np.zeros_like(step), landmark) == []


def test_find_revisits_edges_and_bad_input():
    assert find_revisits(np.zeros((0, 2)), np.zeros(0, int), np.zeros(0, int)) == []
    # No two landmarks ever seen together: d_min undefined, nothing to register.
    assert find_revisits(np.eye(2), [0, 1], [0, 1]) == []
    # Two landmarks seen together at one point: d_min = 0, the radius is 0 and nothing lies
    # within it (no error from the empty length window).
    assert find_revisits(np.array([[1.0, 2.0], [1.0, 2.0], [5.0, 2.0]]), [0, 0, 1, 1],
                         [0, 1, 1, 2]) == []
    positions, step, landmark, _ = revisit_map()
    with pytest.raises(ValueError, match="min_inliers"):
        find_revisits(positions, step, landmark, min_inliers=1)
    # A group shape no older pair has: the new pair's length matches nothing.
    far = positions.copy()
    far[6:] = np.array([[0.0, 0.0], [40.0, 0.0], [0.0, 40.0], [40.0, 40.0]]) + 100.0
    assert find_revisits(far, step, landmark) == []


def test_join_groups_skips_pairs_seen_together():
    together = covisible_pairs([0, 0, 5], [0, 1, 2], 3)
    np.testing.assert_array_equal(join_groups([[0, 2], [1, 2]], together), [0, 1, 0])
    np.testing.assert_array_equal(join_groups(np.zeros((0, 2)), together), [0, 1, 2])


def loop_log(seed=3, steps=90, drift=0.01, sensor_range=6.0, blind=(30, 45)):
    """A lap of a 10 m circle and a sixth more, trees in a ring around it, a sensor that sees
    6 m but nothing during the ``blind`` steps (a stretch with no trunk in view), when the
    odometry's first turn, biased by ``drift`` rad a step, turns the path away unobserved
    (the loop returns metres off); small Gaussian noise on every move and observation.
    Every tree seen in the first 20 steps gets a NEW identity
    when it is seen again after step 60: the filter's missed loop. Returns start (3,),
    odometry (T, 3), z (T, K, 2), landmark_of_obs (T, K), tree_of_obs (T, K), truth (T+1, 3)."""
    rng = np.random.default_rng(seed)
    angle = np.linspace(0, 2 * np.pi * steps / 75, steps + 1)
    truth = np.stack([10 * np.cos(angle), 10 * np.sin(angle), angle + np.pi / 2], 1)
    radius, around = rng.uniform(6.0, 14.0, 40), rng.uniform(-np.pi, np.pi, 40)
    trees = np.stack([radius * np.cos(around), radius * np.sin(around)], 1)
    keep = np.ones(len(trees), bool)
    for i in range(len(trees)):  # at least 1.5 m apart
        keep[i] = np.all(np.linalg.norm(trees[:i][keep[:i]] - trees[i], axis=1) > 1.5)
    trees = trees[keep]
    delta = truth[1:] - truth[:-1]
    rot1 = np.arctan2(delta[:, 1], delta[:, 0]) - truth[:-1, 2]
    odometry = np.stack([rot1, np.hypot(delta[:, 0], delta[:, 1]),
                         truth[1:, 2] - truth[:-1, 2] - rot1], 1)
    odometry[blind[0]:blind[1], 0] += drift
    odometry[:, 0] += rng.normal(0, 0.002, steps)
    odometry[:, 1] += rng.normal(0, 0.01, steps)
    max_obs = 10
    z = np.zeros((steps, max_obs, 2))
    tree_of_obs = np.full((steps, max_obs), -1)
    for t in range(steps):
        d = trees - truth[t + 1, :2]
        dist = np.hypot(d[:, 0], d[:, 1])
        seen = np.argsort(dist)[:max_obs]
        seen = seen[(dist[seen] < sensor_range) & (not blind[0] <= t < blind[1])]
        bearing = np.arctan2(d[seen, 1], d[seen, 0]) - truth[t + 1, 2]
        z[t, :len(seen)] = np.stack([dist[seen] + rng.normal(0, 0.01, len(seen)),
                                     np.angle(np.exp(1j * (bearing + rng.normal(0, 0.002,
                                                                              len(seen)))))], 1)
        tree_of_obs[t, :len(seen)] = seen
    early = np.unique(tree_of_obs[:20][tree_of_obs[:20] >= 0])
    split = np.where((np.arange(steps)[:, None] > 60) & np.isin(tree_of_obs, early),
                     tree_of_obs + len(trees), tree_of_obs)
    _, dense = np.unique(split, return_inverse=True)
    landmark_of_obs = np.where(tree_of_obs >= 0, dense.reshape(split.shape) - 1, -1)
    return truth[0], odometry, z, landmark_of_obs, tree_of_obs, truth


def same_partition(a, b):
    """True when labels a and b (N,) group the same items together."""
    pairs = lambda x: {(i, j) for i in range(len(x)) for j in range(i) if x[i] == x[j]}
    return pairs(a) == pairs(b)


def loop_smoother():
    """``loop_log``'s smoother (plain squares, noise of the log's order: first turn 0.01
    rad, distance 2 %, second turn 0.002 rad), its dead-reckoned path (T, 3), association,
    trees and truth."""
    start, odometry, z, ids, tree, truth = loop_log()
    params = default_params()._replace(rot1_noise=np.array([0.01, 0.0, 0.0]),
                                       trans_noise=np.array([0.0, 0.02, 0.0]),
                                       rot2_noise=np.array([0.002, 0.0, 0.0]))

    def smooth(path, landmark_of_obs, iterations=100):
        return smooth_path(start, path, odometry, z, landmark_of_obs, params,
                           iterations=iterations, huber=1e6, tol=1e-10)

    dead = [start]
    for move in odometry:
        dead.append(np.asarray(apply_odometry(dead[-1], move), np.float64))
    return smooth, np.array(dead[1:]), ids, tree, truth


def test_close_loops_rejoins_a_missed_loop_and_corrects_the_end_pose():
    smooth, dead, ids, tree, truth = loop_smoother()
    open_loop = smooth(dead, ids)
    open_error = np.hypot(*(open_loop.path[-1, :2] - truth[-1, :2]))
    # Precondition: the return is off by more than half a tree spacing, so merging by
    # distance alone (landmark_merge) cannot close this loop.
    assert open_error > 1.0, open_error
    result = close_loops(smooth, dead, ids)
    closed, closures = result.smoothed, result.closures
    assert len(closures) >= 1
    # Every tree seen in the first 20 steps and again after step 60 was split in two:
    # joining them all removes as many landmarks as there are such trees.
    split = np.intersect1d(tree[:20][tree[:20] >= 0], tree[61:][tree[61:] >= 0])
    assert split.size >= 5 and result.landmarks_joined == split.size
    assert any(t.accepted and t.kind == "closure" for t in result.tested)
    used = tree >= 0
    assert same_partition(closed.landmark_of_obs[used], tree[used])
    closed_error = np.hypot(*(closed.path[-1, :2] - truth[-1, :2]))
    # With the loop closed the end pose is fixed by the start's trees. Measured 0.04 m (the
    # observation noise is 1 cm / 2 mrad); 0.2 m is 5x that and a tenth of the open loop's.
    assert closed_error < 0.2, (open_error, closed_error)
    # The same candidates under a test no join can pass: nothing is joined, the loop stays
    # open, the association is the filter's.
    strict = close_loops(smooth, dead, ids, max_rise_per_dof=1e-9)
    assert strict.closures == [] and strict.landmarks_joined == 0
    assert strict.tested and not any(t.accepted for t in strict.tested)
    np.testing.assert_array_equal(strict.smoothed.landmark_of_obs, open_loop.landmark_of_obs)
    with pytest.raises(ValueError, match="max_rise_per_dof"):
        close_loops(smooth, dead, ids, max_rise_per_dof=0.0)


def test_loop_closure_study_end_to_end(tmp_path):
    """The study on four short logs (40 steps, 4 particles) writes every per-log field; where
    nothing was joined the closed MAP is the own-association MAP (the same solve)."""
    from experiments.loop_closure_study import main
    out = tmp_path / "lc"
    main(["--seed", "800", "--runs", "4", "--forests", "2", "--steps", "40", "--particles", "4",
          "--chunk", "4", "--out", str(out)])
    table = np.load(out.with_suffix(".npz"))
    for name in ("online", "own", "closed", "closures", "closed_purity", "seconds"):
        assert table[name].shape == (4,), name
    assert np.all(np.isfinite(table["closed"]))
    same = table["landmarks_joined"] == 0
    np.testing.assert_array_equal(table["closed"][same], table["own"][same])
    assert table["join_rise_per_dof"].shape == table["join_true"].shape
    assert "MAP after close_loops" in out.with_suffix(".md").read_text()


def reference_support(positions, step, landmark, radius):
    """Plain-loop float64 reference: for every hypothesis of the module docstring, the number
    of distinct older landmarks its group lands on; returns the largest and how many
    hypotheses there were."""
    count = len(positions)
    seen_at = [set(np.asarray(step)[np.asarray(landmark) == i]) for i in range(count)]
    together = [[i != j and bool(seen_at[i] & seen_at[j]) for j in range(count)]
                for i in range(count)]
    older = [[max(seen_at[a]) < min(seen_at[b]) for b in range(count)] for a in range(count)]
    best, hypotheses = 0, 0
    for b1 in range(count):
        for b2 in range(b1 + 1, count):
            if not together[b1][b2]:
                continue
            for a1 in range(count):
                for a2 in range(count):
                    if not (together[a1][a2] and older[a1][b1] and older[a2][b2]):
                        continue
                    lb = np.linalg.norm(positions[b1] - positions[b2])
                    la = np.linalg.norm(positions[a1] - positions[a2])
                    if not abs(lb - la) < radius:
                        continue
                    hypotheses += 1
                    da, db = positions[a2] - positions[a1], positions[b2] - positions[b1]
                    angle = np.arctan2(da[1], da[0]) - np.arctan2(db[1], db[0])
                    rot = np.array([[np.cos(angle), -np.sin(angle)],
                                    [np.sin(angle), np.cos(angle)]])
                    shift = (positions[a1] + positions[a2]) / 2 - rot @ (
                        positions[b1] + positions[b2]) / 2
                    hit = set()
                    for g in range(count):
                        if not (g in (b1, b2) or together[b1][g] or together[b2][g]):
                            continue
                        moved = rot @ positions[g] + shift
                        gaps = [np.linalg.norm(moved - positions[a]) if older[a][g] else np.inf
                                for a in range(count)]
                        if min(gaps) < radius:
                            hit.add(int(np.argmin(gaps)))
                    best = max(best, len(hit))
    return best, hypotheses


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("fraction", [0.5, 2.0, 4.0])
def test_find_revisits_against_the_plain_loop_reference(seed, fraction):
    """Random maps of 14 landmarks, 7 steps of 3-4 sightings each (a landmark seen in a few
    consecutive steps): the best candidate's support and the hypothesis count equal the
    reference's, for any chunk size (chunks only bound memory). Radii of 2 and 4 d_min put
    several landmarks within reach of a moved member, so the nearest OLDER one must be picked
    among them (the k-d tree query's k > 1)."""
    rng = np.random.default_rng(seed)
    positions = rng.uniform(0, 12, (14, 2))
    step = np.repeat(np.arange(7), 4)
    landmark = np.concatenate([[2 * t % 14, (2 * t + 1) % 14, (2 * t + 2) % 14,
                                (2 * t + 3) % 14] for t in range(7)])
    step, landmark = step[landmark < 14], landmark[landmark < 14]
    from jaxslam.landmark_merge import covisible_distance
    radius = fraction * covisible_distance(positions, covisible_pairs(step, landmark, 14))
    best, hypotheses = reference_support(positions, step, landmark, radius)
    for chunk in (1, 7, 512):
        found = find_revisits(positions, step, landmark, fraction=fraction, min_inliers=2,
                              candidates=1, chunk=chunk)
        assert found and found[0].hypotheses == hypotheses
        assert np.unique(found[0].pairs[:, 0]).size == best


def test_a_base_still_falling_is_not_tested_against():
    """``_settled``: converged, or a last step smaller than SETTLED x the limit (LM's slow
    tail); a base still falling by more is solved again before any join is tested."""
    from types import SimpleNamespace

    from jaxslam.loop_closure import SETTLED, _settled
    limit = 100.0
    tail = SETTLED * limit
    assert _settled(SimpleNamespace(converged=True, cost=np.array([5.0, 1.0])), limit)
    assert _settled(SimpleNamespace(converged=False, cost=np.array([9.0, 9.0 - tail / 2])),
                    limit)
    assert not _settled(SimpleNamespace(converged=False, cost=np.array([9.0, 9.0 - 2 * tail])),
                        limit)
    assert not _settled(SimpleNamespace(converged=False, cost=np.array([9.0])), limit)


def reference_lands(positions, together, older, radius, newer_pair, older_pair):
    """Plain-loop float64 reference of ``_inliers``: per hypothesis, the landmark each group
    member (ascending ids) lands on (-1: none; the nearest older one within ``radius``, the
    lowest id among equally near ones) and the summed inlier distance."""
    lands, spread = [], []
    for (b1, b2), (a1, a2) in zip(newer_pair, older_pair):
        da, db = positions[a2] - positions[a1], positions[b2] - positions[b1]
        angle = np.arctan2(da[1], da[0]) - np.arctan2(db[1], db[0])
        rot = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
        shift = (positions[a1] + positions[a2]) / 2 - rot @ (positions[b1] + positions[b2]) / 2
        row, total = [], 0.0
        for g in range(len(positions)):
            if not (g in (b1, b2) or together[b1, g] or together[b2, g]):
                continue
            moved = rot @ positions[g] + shift
            best, where = np.inf, -1
            for a in range(len(positions)):
                gap = float(np.hypot(moved[0] - positions[a, 0], moved[1] - positions[a, 1]))
                if older[a, g] and gap < radius and gap < best:
                    best, where = gap, a
            row.append(where)
            total += best if where >= 0 else 0.0
        lands.append(row)
        spread.append(total)
    return lands, np.array(spread)


@pytest.mark.parametrize("fraction", [0.5, 2.0, 4.0])
def test_inliers_per_hypothesis_against_the_plain_loop_reference(fraction):
    """Every hypothesis's landings and summed inlier distance equal the reference's, on
    random maps where three landmarks are exact copies of others (equally near candidates:
    the lowest id wins, as the reference's strict '<' keeps the first)."""
    from jaxslam.landmark_merge import covisible_distance
    from jaxslam.loop_closure import _hypotheses, _inliers
    ties = 0
    for seed in range(4):
        rng = np.random.default_rng(seed)
        positions = rng.uniform(0, 12, (16, 2))
        positions[[13, 14, 15]] = positions[[4, 6, 1]]  # never seen with their originals
        # Step t sees 2t, 2t + 1, 2t + 2 (mod 13); the copies 13, 14, 15 are seen once, at
        # steps 0, 1, 2, so a copy and its original are both older than later members.
        landmark = np.concatenate([[2 * t % 13, (2 * t + 1) % 13, (2 * t + 2) % 13]
                                   + ([13 + t] if t < 3 else []) for t in range(8)])
        step = np.concatenate([[t] * (4 if t < 3 else 3) for t in range(8)])
        together = covisible_pairs(step, landmark, 16)
        radius = fraction * covisible_distance(positions, together)
        first, last = landmark_spans(step, landmark, 16)
        older = (last[:, None] < first[None]) & (last >= 0)[:, None] & (last >= 0)[None]
        newer_pair, older_pair = _hypotheses(positions, together, older, radius)
        assert len(newer_pair) > 0
        distinct, member, lands, spread, _, _ = _inliers(positions, together, older, radius,
                                                         newer_pair, older_pair)
        want_lands, want_spread = reference_lands(positions, together, older, radius,
                                                  newer_pair, older_pair)
        for h, want in enumerate(want_lands):
            np.testing.assert_array_equal(lands[h][member[h] >= 0], want)
            assert distinct[h] == len({a for a in want if a >= 0})
        ties += int(np.isin(lands, [4, 6, 1]).sum())  # landings on an original with a copy
        # Same formula (hypot of the same moved point): equal to rounding of the sum.
        np.testing.assert_allclose(spread, want_spread, rtol=1e-12, atol=1e-12)
    assert ties > 0  # where the tie rule applies (a max-id tie rule fails this test)
