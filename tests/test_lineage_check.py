"""The lineage check: association quality against a hand-worked example, and the script end to
end on two tiny logs (30 steps, 4 particles) with its bit-for-bit check of the online errors."""
import re

import numpy as np
import pytest

from experiments.lineage_check import (AssociationQuality, association_quality, loop_mismatch,
                                      loop_trees, main, merge_splits,
                                      split_geometry)

# Six steps, two rows. Trees 5, 9, 2; identities 0, 1, 2. Tree 9 is split (identity 1 at
# t = 0, 1, identity 2 from t = 2), tree 2 is wrongly matched to tree 5's identity 0 at t = 2,
# t = 3's second row is invalid (its id 3 and tree 7 must be ignored), t = 4's second row is
# valid but unassociated.
TRUE = np.array([[5, 9], [5, 9], [9, 2], [9, 7], [5, 9], [9, 5]])
IDS = np.array([[0, 1], [0, 1], [2, 0], [2, 3], [0, -1], [2, 0]])
VALID = np.ones_like(TRUE, bool)
VALID[3, 1] = False


def test_hand_example():
    """Worked by hand. Counts C[identity, tree]: 0 -> {5: 4, 2: 1}, 1 -> {9: 2}, 2 -> {9: 3};
    10 associated. purity = (4 + 2 + 3) / 10; consistency = (4 + 3 + 1) / 10; tree 9 holds two
    identities of >= 2 observations (split), tree 5 one. Early window t < 2 sees trees 5 (id 0)
    and 9 (id 1); late window t >= 4 sees 5 (id 0) and 9 (id 2): two loop trees, one closed.
    The first departure is t = 2 (tree 9 under a second identity, tree 2 under tree 5's)."""
    quality = association_quality(IDS, TRUE, VALID, early=2, late=2)
    expected = AssociationQuality(identities=3, trees=3, associated=10, unassociated=1,
                                  purity=0.9, consistency=0.8, split_trees=1, loop_trees=2,
                                  loop_closed_trees=1, first_error_step=2)
    for name, want in expected._asdict().items():
        assert getattr(quality, name) == pytest.approx(want), name


def test_loop_trees_and_split_steps_hand_example():
    """Same example: loop trees 5 (identity 0 early and late: closed) and 9 (1 early, 2 late:
    open); tree 9's identity 2 appears at t = 2, one step after its last sighting (gap 1);
    tree 5 keeps identity 0 and tree 2 is seen once (t = 4's unassociated row is no
    sighting)."""
    trees, closed = loop_trees(IDS, TRUE, VALID, early=2, late=2)
    np.testing.assert_array_equal(trees, [5, 9])
    np.testing.assert_array_equal(closed, [True, False])
    splits = split_geometry(np.zeros((TRUE.shape[0], 3)), np.ones(TRUE.shape + (2,)), IDS,
                            TRUE, VALID)
    np.testing.assert_array_equal(splits["step"], [2])
    np.testing.assert_array_equal(splits["gap"], [1])


def test_split_geometry_hand_example():
    """Same example. With every pose at (1, -2) facing +x, tree 9's split observation (t = 2,
    row 0) is read at (2.0 m, 0); its previous identity 1 was read at t = 0 and 1 as (1.9 m, 0)
    and (2.1 m, 0.1 rad): placed at (1, -2) + (1.9, 0) and (1, -2) + 2.1 (cos 0.1, sin 0.1), so
    the displacement is |(2, 0) - their mean| (the pose's translation cancels); gap 1, range
    2.0. With the pose at t = 2 moved to (1.5, -2, 0.1 rad) and ``last=1`` only t = 1's
    placement counts: |(0.5, 0) + (2 - 2.1) (cos 0.1, sin 0.1)|. A tree split nowhere gives empty
    arrays."""
    z = np.zeros(TRUE.shape + (2,))
    z[0, 1], z[1, 1], z[2, 0] = (1.9, 0.0), (2.1, 0.1), (2.0, 0.0)
    pose = np.zeros((TRUE.shape[0], 3))
    pose[:, :2] = (1.0, -2.0)
    out = split_geometry(pose, z, IDS, TRUE, VALID)
    before = np.mean([[1.9, 0.0], [2.1 * np.cos(0.1), 2.1 * np.sin(0.1)]], axis=0)
    np.testing.assert_array_equal(out["gap"], [1])
    np.testing.assert_array_equal(out["range"], [2.0])
    np.testing.assert_allclose(out["displacement"], [np.linalg.norm([2.0, 0.0] - before)],
                               rtol=1e-12)
    pose[2, :2], pose[2, 2] = (1.5, -2.0), 0.1  # x moved by 0.5 m, heading by 0.1 rad
    out = split_geometry(pose, z, IDS, TRUE, VALID, last=1)
    np.testing.assert_allclose(out["displacement"], [np.hypot(0.5 - 0.1 * np.cos(0.1),
                                                              -0.1 * np.sin(0.1))], rtol=1e-12)
    unsplit = np.where(TRUE == 9, 1, 0)
    empty = split_geometry(pose, z, unsplit, TRUE, VALID)
    assert all(value.shape == (0,) for value in empty.values())
    assert empty["step"].dtype == empty["gap"].dtype == np.int64
    assert empty["displacement"].dtype == np.float64


def test_merge_splits_hand_example():
    """Tree 9's identity 2 (in view: gap 1) merges into 1 with gaps (1, 2) and with (1, 1e9),
    not with (3, 1e9); tree 2's wrong match to identity 0 is no split and stays. Labels are
    renumbered: {0, 1} -> {0, 1} when 2 merges, invalid and unassociated rows stay -1."""
    for gaps in ((1, 2), (1, 10**9)):
        merged = merge_splits(IDS, TRUE, VALID, gaps)
        np.testing.assert_array_equal(
            merged, [[0, 1], [0, 1], [1, 0], [1, -1], [0, -1], [1, 0]])
        assert association_quality(merged, TRUE, VALID).split_trees == 0
    np.testing.assert_array_equal(merge_splits(IDS, TRUE, VALID, (3, 10**9)),
                                  np.where(VALID, IDS, -1))


def test_loop_mismatch_is_the_frame_shift():
    """A robot 1 m a step along x sees a tree at (5, 3) at t = 0, 1, 2 and again at 8, 9,
    with exact range-bearing. A history exact to t = 4 and shifted by d = (0.3, -0.4) from
    t = 5 on (its odometry the true moves) predicts the return pose shifted by d, so the
    return observation lands |d| = 0.5 m from the first visit's placements (exact
    arithmetic up to float64 rounding: 1e-12). With the exact history it is 0."""
    steps = 10
    truth = np.stack([np.arange(steps, dtype=float), np.zeros(steps), np.zeros(steps)], -1)
    odometry = np.tile([0.0, 1.0, 0.0], (steps, 1))
    tree = np.array([5.0, 3.0])
    seen = np.zeros((steps, 1), bool)
    seen[[0, 1, 2, 8, 9], 0] = True
    offset = tree - truth[:, :2]
    z = np.stack([np.hypot(*offset.T), np.arctan2(offset[:, 1], offset[:, 0])], -1)[:, None]
    true_id = np.where(seen, 4, -1)
    shifted = truth.copy()
    shifted[5:, :2] += [0.3, -0.4]
    # Only the return pose itself shifted: the prediction comes from the exact pose[7], so
    # the mismatch is 0 (reading pose[8] instead of predicting would give 0.5).
    corrected_at_return = truth.copy()
    corrected_at_return[8, :2] += [0.3, -0.4]
    for history, want in ((truth, 0.0), (shifted, 0.5), (corrected_at_return, 0.0)):
        mismatch, back = loop_mismatch(history, odometry, z, true_id, seen, np.array([4]))
        np.testing.assert_allclose(mismatch, [want], atol=1e-12)
        np.testing.assert_array_equal(back, [8])


def test_true_association_is_clean_and_labels_do_not_matter():
    """The truth as its own association (relabelled arbitrarily) is pure, consistent,
    unsplit, closes every loop tree and never departs."""
    relabel = {5: 11, 9: 0, 2: 4}
    ids = np.where(VALID, np.vectorize(lambda t: relabel.get(t, -1))(TRUE), -1)
    quality = association_quality(ids, TRUE, VALID, early=2, late=2)
    assert (quality.purity, quality.consistency, quality.split_trees) == (1.0, 1.0, 0)
    assert quality.loop_closed_trees == quality.loop_trees == 2
    assert quality.first_error_step == -1
    assert quality.identities == quality.trees == 3


def test_one_landmark_for_everything_is_impure_but_unsplit():
    """Edge: a single identity for all trees: purity is the largest tree's share, no tree is
    split, every loop tree 'closes' (the score does not reward that: purity does)."""
    ids = np.where(VALID, 0, -1)
    quality = association_quality(ids, TRUE, VALID, early=2, late=2)
    # Valid: tree 5 x 4, tree 9 x 6, tree 2 x 1 -> largest share 6 / 11.
    assert quality.purity == pytest.approx(6 / 11)
    assert quality.consistency == pytest.approx(1.0)
    assert quality.split_trees == 0 and quality.identities == 1
    assert quality.first_error_step == 0  # tree 9 at t = 0 under tree 5's identity


def test_nothing_associated():
    """Edge: no identity at all: nothing associated, no loop tree, no departure."""
    quality = association_quality(-np.ones_like(IDS), TRUE, VALID)
    assert quality.associated == 0 and quality.unassociated == int(VALID.sum())
    assert quality.identities == 0 and quality.trees == 3
    assert quality.loop_trees == 0 and quality.first_error_step == -1


def run_tiny(out, *extra):
    """The script on two 30-step logs at P = 4, 20 smoother steps; returns (md, npz)."""
    main(["--seed", "800", "--runs", "2", "--forests", "1", "--steps", "30", "--particles",
          "4", "--chunk", "2", "--iterations", "20", "--out", str(out), *extra])
    return out.with_suffix(".md").read_text(), np.load(out.with_suffix(".npz"))


def test_script_end_to_end(tmp_path):
    """Tables and per-log arrays are written, one entry a log, errors finite and >= 0 (under
    the test suite's rank-promotion errors)."""
    text, table = run_tiny(tmp_path / "tiny")
    assert "| online (weighted mean) | 2 |" in text
    for name in ("online", "best", "smoothed", "oracle_loop", "purity", "split_trees",
                 "sparsest"):
        assert table[name].shape == (2,), name
    for name in ("online", "best", "smoothed", "oracle_in_view", "oracle_loop", "oracle_all"):
        assert np.all(np.isfinite(table[name])) and np.all(table[name] >= 0), name
    assert np.all((table["purity"] > 0) & (table["purity"] <= 1))
    assert table["loop_mismatch"].shape == table["loop_closed"].shape == table["loop_log"].shape


def test_script_reproduces_information_floor_to_float32_rounding(tmp_path):
    """``--check``: the lineage run's online errors equal information_floor.filter_errors'
    (no lineage, same keys and chunk) to float32 rounding. They were equal bit for bit until
    the odometry gains' multiply (``motion.with_gain``, by 1 here) entered the step: XLA
    fuses the two programs differently since, and the final errors of these 30-step runs
    differ by 3.6e-5 m at most (measured); 1e-4 m is float32's spacing at 40 m times about
    25 rounding steps."""
    text, _ = run_tiny(tmp_path / "tiny", "--check")
    found = re.search(r"bit for bit in (\d+) / 2 logs \(largest difference ([0-9.e+-]+) m\)",
                      text)
    assert found, text
    assert float(found.group(2)) < 1e-4


def test_proposal_option_runs_another_filter(tmp_path):
    """``--proposal motion`` runs the seed paper's filter on the same logs: the per-log online
    errors differ from the default filter's (a filter that ignored the option would give the
    same numbers), and the notes name the filter."""
    text, motion = run_tiny(tmp_path / "motion", "--proposal", "motion")
    _, default = run_tiny(tmp_path / "default")
    assert "Filter motion, P = 4" in text
    assert not np.array_equal(motion["online"], default["online"])


def test_check_refuses_another_proposal(tmp_path):
    with pytest.raises(SystemExit, match="cannot check --proposal"):
        run_tiny(tmp_path / "x", "--check", "--proposal", "motion")
