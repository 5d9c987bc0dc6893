"""Per-run worlds drawn inside the compiled simulator: dart throwing, run ids, bad input."""
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam import studies
from sims.batch import (WORLD_WIDTH, _designed_path, _world_drawer, run_world,
                        run_world_arrays, scenario_batch)
from sims.forest import poisson_disc, sample_forest

TINY = ["num_runs=5", "filter.num_particles=8", "filter.max_landmarks=24", "filter.max_obs=8",
        "scenario.num_steps=20", "scenario.num_trees=15", "scenario.size=30.0",
        "scenario.world='per_run'"]


def tiny_config(*overrides):
    return studies.load_study_config(None, TINY + list(overrides))


def reference_poisson_disc(key, num_points, low, high, min_spacing, keep_clear=None,
                           clear_dist=0.0):
    """The host dart throwing ``poisson_disc`` replaced: a sequential NumPy pass in float64
    over the same candidates (30 N + 50 uniform draws of ``key``, default float type)."""
    candidates = np.asarray(jax.random.uniform(key, (30 * num_points + 50, 2), minval=low,
                                               maxval=high), np.float64)
    clear = np.ones(len(candidates), bool)
    if keep_clear is not None and keep_clear.shape[0] > 0:
        keep = np.asarray(keep_clear, np.float64)
        nearest = np.min(np.linalg.norm(candidates[:, None] - keep[None], axis=-1), axis=1)
        clear = nearest >= clear_dist
    points, count = np.zeros((num_points, 2)), 0
    for candidate in candidates[clear]:
        if count == num_points:
            break
        if count == 0 or np.min(np.sum((points[:count] - candidate) ** 2, -1)) >= min_spacing ** 2:
            points[count] = candidate
            count += 1
    return points.astype(np.float32), count


def ring(num=60, centre=10.0, radius=5.0):
    phi = np.linspace(0.0, 2.0 * np.pi, num, endpoint=False)
    return np.stack([centre + radius * np.cos(phi), centre + radius * np.sin(phi)], -1)


CASES = {  # name: (num_points, box side [m], spacing [m], keep_clear, clear_dist [m])
    "free": (25, 20.0, 2.0, None, 0.0),
    "ring kept clear": (25, 20.0, 2.0, ring(), 1.5),
    "too small": (40, 8.0, 2.0, None, 0.0),  # about 16 fit: placed < N
    "none": (0, 20.0, 2.0, None, 0.0),
    "all kept clear": (5, 4.0, 1.0, ring(40, 2.0, 1.0), 10.0),
}


def run_case(fn, key, case):
    num, side, spacing, keep, clear = case
    keep = None if keep is None else jnp.asarray(keep, jnp.float32)
    return fn(key, num, jnp.zeros(2), jnp.full(2, side), spacing, keep, clear)


@pytest.mark.parametrize("name", list(CASES))
def test_poisson_disc_matches_the_numpy_reference(name):
    """Same points and count as the float64 host pass, under x64 (the tests' mode: exact)
    and in float32 (decisions can differ only for a distance within ~1e-6 relative of its
    threshold; none of these keys has one), jitted and under vmap."""
    case = CASES[name]
    keys = jax.random.split(jax.random.PRNGKey(7), 4)
    for x64 in (True, False):
        with jax.enable_x64(x64):
            points, placed = jax.vmap(lambda k: run_case(poisson_disc, k, case))(keys)
            for i, key in enumerate(keys):
                expected, count = run_case(reference_poisson_disc, key, case)
                assert int(placed[i]) == count, (x64, i)
                np.testing.assert_array_equal(np.asarray(points[i]), expected)
                assert points.dtype == jnp.float32
            if x64:  # the same without vmap
                single = run_case(poisson_disc, keys[0], case)
                np.testing.assert_array_equal(single[0], points[0])
    if name == "too small":
        assert 0 < count < case[0]
    if name in ("none", "all kept clear"):
        assert count == 0 and points.shape == (4, case[0], 2) and not np.any(points)


def test_poisson_disc_without_jit_matches():
    """The function itself, called eagerly (not through its ``jax.jit`` wrapper)."""
    case = (6, 10.0, 2.0, ring(12, 5.0, 3.0), 1.0)
    points, placed = run_case(poisson_disc.__wrapped__, jax.random.PRNGKey(3), case)
    expected, count = run_case(reference_poisson_disc, jax.random.PRNGKey(3), case)
    assert int(placed) == count == 6
    np.testing.assert_array_equal(np.asarray(points), expected)


def test_sample_forest_keeps_spacing_and_clearance():
    keep = ring(80, 15.0, 8.0)
    forest, placed = jax.jit(lambda k: sample_forest(k, 40, (30.0, 30.0), keep_clear=keep))(
        jax.random.PRNGKey(1))
    c = np.asarray(forest.centres, np.float64)
    gaps = np.linalg.norm(c[:, None] - c[None], axis=-1) + np.eye(40) * 1e9
    assert int(placed) == 40 and gaps.min() >= 2.0 - 1e-6
    assert np.linalg.norm(c[:, None] - keep[None], axis=-1).min() >= 1.5 - 1e-6


# A dense forest (37 trees 2 m apart in 14 m x 14 m): some runs' forests fit, some do not.
# One config (one compiled simulator) serves both tests below.
DENSE = ("scenario.num_trees=37", "scenario.size=14.0", "scenario.path='random'",
         "num_runs=8")


def placed_trees(config, num_runs=8):
    """(num_runs,) trees placed in runs 0.. (the drawer ``run_world_arrays`` compiles)."""
    drawer = _world_drawer(config.scenario, config.seed)
    return np.asarray(drawer(jnp.arange(WORLD_WIDTH))[3])[:num_runs]


def test_per_run_worlds_differ_by_run_and_not_by_width():
    """Run i's world (and every input) is the same whatever runs share its group; its world
    is the same drawn alone, in groups of 1 or WORLD_WIDTH runs (run_world_arrays) or in the
    simulator's groups of 3; different runs draw different worlds."""
    config = tiny_config(*DENSE)
    ids = np.flatnonzero(placed_trees(config) == 37)[:5]  # runs whose forest fits
    assert ids.size == 4
    batch = jax.tree.map(np.asarray, scenario_batch(config, ids, width=3))
    alone = jax.tree.map(np.asarray, scenario_batch(config, ids[-1:], width=3))
    for whole, part in zip(jax.tree.leaves(batch), jax.tree.leaves(alone)):
        np.testing.assert_array_equal(whole[-1], part[0])
    centres = batch.tree_centres
    assert centres.shape == (4, 37, 2)
    for a in range(4):
        for b in range(a):
            assert not np.allclose(centres[a], centres[b])
            assert not np.allclose(batch.truth_pose[a], batch.truth_pose[b])
    forest, path = run_world(config.scenario, config.seed, ids[2])
    np.testing.assert_array_equal(np.asarray(forest.centres), centres[2])
    np.testing.assert_array_equal(np.asarray(path), batch.truth_pose[2])
    for width in (1, WORLD_WIDTH):
        world = run_world_arrays(config.scenario, config.seed, ids[[3, 1]], width=width)
        for part, whole in zip(world, (batch.truth_pose, centres, batch.tree_radii)):
            np.testing.assert_array_equal(np.asarray(part), whole[[3, 1]])


@pytest.mark.parametrize("forest, path", [("plantation", "lawnmower"), ("random", "loop")])
def test_designed_paths_are_shared_and_forests_are_not(forest, path):
    config = tiny_config(f"scenario.forest='{forest}'", f"scenario.path='{path}'")
    paths, centres, radii = map(np.asarray, run_world_arrays(config.scenario, config.seed,
                                                             np.arange(3)))
    designed = np.asarray(_designed_path(config.scenario), np.float32)
    for run in range(3):
        np.testing.assert_array_equal(paths[run], designed)
    assert not np.allclose(centres[0], centres[1]) and not np.allclose(radii[0], radii[1])
    if path == "loop":
        gap = np.linalg.norm(centres[:, :, None] - designed[None, None, :, :2], axis=-1)
        assert gap.min() >= 1.5 - 1e-6  # trunks keep clear of the loop


def test_a_world_that_cannot_be_built_names_its_runs():
    """Too many trees for the area: the runs are named (with the trees placed) and counted,
    before any filter runs; nothing hangs (the dart throwing has a fixed length)."""
    config = tiny_config(*DENSE)
    settings = config.scenario
    placed = placed_trees(config)
    short = np.flatnonzero(placed < 37)
    assert 0 < short.size < 8, placed  # some runs fit, some do not: the ids matter
    for draw, scope in ((lambda: scenario_batch(config, np.arange(3), width=3),
                         "runs of the study"),  # a chunk of the study: its 8 runs counted
                        (lambda: run_world_arrays(settings, config.seed, np.arange(8)),
                         "runs simulated")):
        with pytest.raises(ValueError) as error:
            draw()
        message = str(error.value)
        assert f"{short.size} of the 8 {scope}" in message
        named = [int(i) for i in re.findall(r"(\d+) \(\d+ placed\)", message)]
        assert named == list(short[:5])
        assert "scenario.size" in message and "scenario.num_trees" in message
