"""experiments/mrclam_ancestry.py: the common ancestor's depth and the re-sighting gaps."""
import numpy as np
import pytest

from experiments import mrclam_ancestry as ancestry


def _depth_by_composition(ancestor):
    """Reference: compose each particle's ancestry step by step (an (P,) array of the
    ancestor every particle of step t has after step t - d) until all are one."""
    ancestor = np.asarray(ancestor)
    num_steps = ancestor.shape[0]
    depth = []
    for t in range(num_steps):
        line = ancestor[t].copy()  # each particle's ancestor after step t - 1
        d = 1
        while len(set(line.tolist())) > 1 and t - d >= 0:
            line = ancestor[t - d][line]
            d += 1
        depth.append(d if len(set(line.tolist())) == 1 else t + 1)
    return np.asarray(depth)


def test_depth_against_a_composition_reference_on_random_ancestries():
    rng = np.random.default_rng(0)
    for num_particles in (1, 2, 5, 40):
        for keep in (0.0, 0.5, 0.95):  # share of particles that keep their own line a step
            steps = 60
            own = np.arange(num_particles)
            drawn = rng.integers(0, num_particles, size=(steps, num_particles))
            ancestor = np.where(rng.random((steps, num_particles)) < keep, own, drawn)
            depth = ancestry.common_ancestor_depth(ancestor)
            np.testing.assert_array_equal(depth, _depth_by_composition(ancestor))
            assert depth.shape == (steps,)
            assert np.all((depth >= 1) & (depth <= np.arange(1, steps + 1)))


def test_depth_edges():
    # One particle is always its own common ancestor one step back.
    np.testing.assert_array_equal(ancestry.common_ancestor_depth(np.zeros((4, 1), int)), [1] * 4)
    # Never resampled: the lines never meet after step 0, so the depth is t + 1 (the start).
    identity = np.tile(np.arange(3), (5, 1))
    np.testing.assert_array_equal(ancestry.common_ancestor_depth(identity), [1, 2, 3, 4, 5])
    # Everyone copies particle 2 at step 3: depth 1 there, and 1 + steps since after it.
    ancestor = np.tile(np.arange(3), (6, 1))
    ancestor[3] = 2
    np.testing.assert_array_equal(ancestry.common_ancestor_depth(ancestor), [1, 2, 3, 1, 2, 3])
    with pytest.raises(ValueError, match=r"ancestor must be \(T, P\)"):
        ancestry.common_ancestor_depth(np.zeros(5, int))


def test_resighting_gaps_by_hand():
    landmark = np.array([[3, -1], [7, 3], [3, 3], [-1, -1], [7, 9], [9, 3]])
    valid = np.array([[True, False], [True, True], [True, True], [False, False],
                      [True, False], [True, True]])
    # Step 2 sees 3 twice (counted once); step 4's 9 is invalid, so step 5's 9 is its first.
    np.testing.assert_array_equal(ancestry.resighting_gaps(landmark, valid),
                                  [[1, 1], [2, 1], [4, 3], [5, 3]])
    assert ancestry.resighting_gaps(np.full((3, 2), -1), np.ones((3, 2), bool)).shape == (0, 2)
    with pytest.raises(ValueError, match=r"\(T, K\) alike"):
        ancestry.resighting_gaps(np.zeros((3, 2), int), np.ones((3, 3), bool))


def test_beyond_depth_share():
    gaps = np.array([[5, 1], [6, 30], [7, 25], [8, 40]])
    depth = np.array([1, 1, 1, 1, 1, 1, 35, 20, 50])
    paused, beyond = ancestry.beyond_depth_share(gaps, depth, pause=20)
    assert paused == 0.75  # gaps 30, 25, 40 of four
    assert beyond == pytest.approx(1 / 3)  # only 25 > 20 at step 7
    paused, beyond = ancestry.beyond_depth_share(gaps[:1], depth, pause=20)
    assert paused == 0.0 and np.isnan(beyond)
    paused, beyond = ancestry.beyond_depth_share(np.zeros((0, 2), int), depth, pause=20)
    assert np.isnan(paused) and np.isnan(beyond)


@pytest.mark.parametrize("extra, message", [
    (["--particles", "0"], "--particles needs counts of 1 or more"),
    (["--filter-keys", "0"], "--filter-keys 1 or more"),
    (["--pause", "-1"], "--pause 0 or more"),
    (["--robots", "6"], "has robots 1-5"),
])
def test_bad_options_are_refused_before_any_data_is_read(extra, message, capsys):
    with pytest.raises(SystemExit):
        ancestry.main(["--data", "/nonexistent", *extra])
    assert message in capsys.readouterr().err
