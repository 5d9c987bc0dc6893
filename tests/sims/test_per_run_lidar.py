"""Per-run lidar worlds: each run's trunks written into one template MJX world (vmapped over
runs), checked against an MJX world built from that run's forest by ``world_from_forest``.

One tiny study config (15 trees in 30 m, T=10, K=8, run_width=3) for every test, so the
per-run lidar simulator compiles once for the module (~30 s on the shared 2-core CPU).
"""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam import studies
from sims.batch import run_lidar_world, run_world, run_world_arrays, scenario_batch
from sims.forest import world_from_forest, world_with_trunks
from sims.lidar import scan_2d_full

TINY = ["num_runs=3", "chunk_size=3", "run_width=3", "filter.num_particles=8",
        "filter.max_landmarks=24", "filter.max_obs=8", "scenario.num_steps=10",
        "scenario.num_trees=15", "scenario.size=30.0", "scenario.path='random'",
        "scenario.world='per_run'", "scenario.observation_source='lidar'",
        "filter.proposal='motion'", "filter.anchor_empty_map=false",
        "params.motion_outlier_probability=0.0"]
BEAMS = 1440
# Interior beams (both neighbours hit the same trunk): the two worlds' trunk positions and
# radii differ by the MJCF's 6-decimal rounding and float32 (<= 1e-6 m), which moves a
# non-grazing return by about as much; 1e-4 m leaves room for float32 ray arithmetic at 20 m
# (ulp 2e-6 m). Edge beams graze a trunk: a ray passing eps inside a circle of radius r
# travels a chord of half-length sqrt(2 r eps), so a shift delta of the circle moves the
# return by up to sqrt(2 r delta) = sqrt(2 * 0.35 * 1e-6) = 8.4e-4 m for the largest trunk.
INTERIOR_TOL = 1e-4
EDGE_TOL = 1e-4 + np.sqrt(2 * 0.35 * 1e-6)


@pytest.fixture(scope="module")
def config():
    return studies.load_study_config(None, TINY)


@pytest.fixture(scope="module")
def batch(config):
    return scenario_batch(config, np.arange(3))


def test_per_run_world_scans_match_worlds_built_from_each_run_forest(config):
    """Runs 0 and 1: the template refilled (jit(vmap) over both runs) scans as the MJX world
    built from the run's own forest, at two poses of its path and one with no trunk in range
    (every beam reads max_range); hit geoms agree beam by beam."""
    settings, max_range = config.scenario, config.scenario.max_range
    ids = np.array([0, 1])
    paths, centres, radii = run_world_arrays(settings, config.seed, ids)
    worlds = jax.jit(jax.vmap(lambda c, r: run_lidar_world(settings, c, r)))(centres, radii)
    eager_world = run_lidar_world(settings, centres[0], radii[0])  # no jit, no vmap
    for leaf, eager in zip(jax.tree.leaves(worlds), jax.tree.leaves(eager_world)):
        np.testing.assert_array_equal(np.asarray(leaf)[0], np.asarray(eager))
    far = jnp.array([settings.size + 25.0, settings.size + 25.0, 0.3])
    for i, run_id in enumerate(ids):
        forest, path = run_world(settings, config.seed, int(run_id))
        reference = world_from_forest(forest)
        world = jax.tree.map(lambda leaf, i=i: leaf[i], worlds)
        np.testing.assert_allclose(world.data.geom_xpos, reference.data.geom_xpos, atol=2e-6)
        np.testing.assert_allclose(world.model.geom_size, reference.model.geom_size, atol=1e-6)
        np.testing.assert_allclose(world.geom_bound, reference.geom_bound, atol=1e-6)
        np.testing.assert_array_equal(world.data.geom_xmat, reference.data.geom_xmat)
        for pose in (path[3], path[8], far):
            got = scan_2d_full(world, pose, BEAMS, max_range)
            want = scan_2d_full(reference, pose, BEAMS, max_range)
            geom = np.asarray(want.geom)
            np.testing.assert_array_equal(np.asarray(got.geom), geom)
            assert bool(got.complete) and bool(want.complete)
            error = np.abs(np.asarray(got.ranges) - np.asarray(want.ranges))
            interior = (np.roll(geom, 1) == geom) & (np.roll(geom, -1) == geom)
            assert np.max(error[interior], initial=0.0) <= INTERIOR_TOL, (run_id, pose)
            assert np.max(error) <= EDGE_TOL, (run_id, pose)
            if pose is far:
                np.testing.assert_array_equal(np.asarray(got.ranges), max_range)
            else:
                assert np.sum(geom >= 0) > 20  # trunks in view: the comparison has hits


def test_world_with_trunks_refuses_a_wrong_trunk_count(config):
    template_world = run_lidar_world(config.scenario, jnp.zeros((15, 2)), jnp.full(15, 0.2))
    with pytest.raises(ValueError, match="template has 15 trunks"):
        world_with_trunks(template_world, jnp.zeros((14, 2)), jnp.full(14, 0.2))


def detected_points(batch, run):
    """(T, K, 2) world positions of run ``run``'s detections (true pose + z), (T, K) valid."""
    obs = jax.tree.map(lambda leaf: np.asarray(leaf)[run], batch.observations)
    poses = np.asarray(batch.truth_pose)[run, 1:]
    heading = poses[:, None, 2] + obs.z[..., 1]
    points = poses[:, None, :2] + obs.z[..., :1] * np.stack([np.cos(heading),
                                                             np.sin(heading)], -1)
    return points, obs.valid


def test_per_run_lidar_worlds_differ_by_run_and_do_not_depend_on_the_chunk(config, batch):
    """Each run scans its own forest: its detections sit on its own trunks (not on another
    run's), its worlds differ from the others', and run 1 alone (padded to the width of 3)
    gives bit-identical outputs to run 1 among runs 0..2."""
    centres = np.asarray(batch.tree_centres)
    assert centres.shape == (3, config.scenario.num_trees, 2)
    assert not np.allclose(centres[0], centres[1]) and not np.allclose(centres[1], centres[2])
    for run in range(3):
        points, valid = detected_points(batch, run)
        assert valid.sum() >= 20, run
        for other in range(3):
            gap = np.linalg.norm(points[..., None, :] - centres[other][None, None], axis=-1)
            nearest = gap.min(-1)[valid]
            if other == run:  # kasa fits of 1 cm beam noise: centimetres off the true centre
                assert np.quantile(nearest, 0.9) < 0.1, run
            else:
                assert np.median(nearest) > 0.3, (run, other)
        seen = np.asarray(batch.tree_seen)[run]
        gap = np.asarray(batch.truth_pose)[run][:, None, :2] - centres[run][None]
        np.testing.assert_array_equal(
            seen, np.min(np.hypot(gap[..., 0], gap[..., 1]), 0) <= config.scenario.max_range)
    alone = scenario_batch(config, np.array([1]))
    for whole, part in zip(jax.tree.leaves(batch), jax.tree.leaves(alone)):
        np.testing.assert_array_equal(np.asarray(whole)[1], np.asarray(part)[0])


def test_small_per_run_lidar_study_runs(config, batch, tmp_path):
    """``run_study`` on per-run lidar worlds: one row a run, finite errors, and the example
    run carries run 0's own forest."""
    result = studies.run_study(config, tmp_path / "study", progress=False)
    table = result.table
    assert table.num_rows == 3
    errors = np.asarray(table.column("final_pose_error").to_numpy(), float)
    assert np.all(np.isfinite(errors)) and np.all(errors < 2.0)
    with np.load(tmp_path / "study" / "example_run.npz") as example:
        np.testing.assert_array_equal(example["tree_centres"],
                                      np.asarray(batch.tree_centres)[0])
