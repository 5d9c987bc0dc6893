"""experiments/mrclam_ancestry.py: the common ancestor's depth and the re-sighting gaps."""
import numpy as np
import pytest

from experiments import mrclam_ancestry as ancestry


def _depth_from_the_definition(ancestor):
    """Reference: for d = 1, 2, ..., follow every particle of step t back d steps on its own
    (particle i after step t -> ancestor[t][i] after t - 1 -> ...) and take the first d at
    which they all reach one particle; t + 1 when none does."""
    ancestor = np.asarray(ancestor)
    num_steps, num_particles = ancestor.shape
    depth = []
    for t in range(num_steps):
        found = t + 1
        for d in range(1, t + 1):
            reached = set()
            for i in range(num_particles):
                j = i
                for u in range(t, t - d, -1):
                    j = int(ancestor[u][j])
                reached.add(j)
            if len(reached) == 1:
                found = d
                break
        depth.append(found)
    return np.asarray(depth)


def test_depth_against_the_definition_on_random_ancestries():
    rng = np.random.default_rng(0)
    for num_particles in (1, 2, 5, 40):
        for keep in (0.0, 0.5, 0.95):  # share of particles that keep their own line a step
            steps = 30
            own = np.arange(num_particles)
            drawn = rng.integers(0, num_particles, size=(steps, num_particles))
            ancestor = np.where(rng.random((steps, num_particles)) < keep, own, drawn)
            depth = ancestry.common_ancestor_depth(ancestor)
            np.testing.assert_array_equal(depth, _depth_from_the_definition(ancestor))
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
    # A re-sighting at step t is judged by the cloud after step t - 1: depth[t - 1].
    gaps = np.array([[5, 1], [6, 30], [7, 25], [8, 40]])
    depth = np.array([1, 1, 1, 1, 1, 35, 20, 50, 1])
    paused, beyond = ancestry.beyond_depth_share(gaps, depth, pause=20)
    assert paused == 0.75  # gaps 30, 25, 40 of four
    assert beyond == pytest.approx(1 / 3)  # only step 7's 25 > depth[6] = 20
    # The boundary: last seen at the ancestor's own step (g = depth + 1) is beyond it;
    # last seen one step after it (g = depth) is not.
    depth = np.full(12, 4)
    assert ancestry.beyond_depth_share(np.array([[10, 5]]), depth, pause=0) == (1.0, 1.0)
    assert ancestry.beyond_depth_share(np.array([[10, 4]]), depth, pause=0) == (1.0, 0.0)
    paused, beyond = ancestry.beyond_depth_share(gaps[:1], depth, pause=20)
    assert paused == 0.0 and np.isnan(beyond)
    paused, beyond = ancestry.beyond_depth_share(np.zeros((0, 2), int), depth, pause=20)
    assert np.isnan(paused) and np.isnan(beyond)
    with pytest.raises(ValueError, match="steps must be >= 1"):  # not depth[-1], silently
        ancestry.beyond_depth_share(np.array([[0, 30]]), depth, pause=20)


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
