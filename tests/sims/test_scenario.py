"""Forests, paths, odometry and scenarios."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import sims
from jaxslam.geometry import range_bearing, wrap_angle
from jaxslam.motion import odometry_std
from jaxslam.types import default_params


def test_random_forest_spacing_and_radii():
    forest = sims.random_forest(jax.random.PRNGKey(0), 50, (40.0, 40.0), min_spacing=2.5)
    c = np.asarray(forest.centres)
    gaps = np.linalg.norm(c[:, None] - c[None], axis=-1) + np.eye(50) * 1e9
    assert gaps.min() >= 2.5 - 1e-5
    assert np.all((c >= 0) & (c <= 40))
    r = np.asarray(forest.radii)
    assert np.all((r >= 0.05 - 1e-6) & (r <= 0.35 + 1e-6)) and 0.1 < np.median(r) < 0.2
    with pytest.raises(ValueError, match="num_trees"):
        sims.random_forest(jax.random.PRNGKey(0), 500, (10.0, 10.0), min_spacing=2.0)


def test_plantation_rows_and_mjcf():
    forest = sims.plantation_forest(jax.random.PRNGKey(1), 3, 5, jitter=0.0, num_bushes=2)
    c = np.asarray(forest.centres)
    np.testing.assert_allclose(np.unique(np.round(c[:, 1], 6)), [0.0, 7.0, 14.0])
    np.testing.assert_allclose(np.unique(np.round(c[:, 0], 6)), [0.0, 3.0, 6.0, 9.0, 12.0])
    xml = sims.forest_mjcf(forest)
    assert "<material" in xml and xml.count('type="capsule"') == 15
    assert xml.count('contype="0" conaffinity="0"') == xml.count("<geom")


def test_paths_and_clearance():
    loop = sims.loop_path(100, (30.0, 30.0), (8.0, 8.0), 0.5)
    steps = np.linalg.norm(np.diff(np.asarray(loop[:, :2]), axis=0), axis=-1)
    np.testing.assert_allclose(steps, 0.5, atol=2e-3)
    lawn = sims.lawnmower_path([3.5, 10.5], 0.0, 20.0, 80, 0.5)
    assert abs(float(lawn[10, 1]) - 3.5) < 1e-5 and abs(float(lawn[10, 2])) < 1e-5
    forest = sims.random_forest(jax.random.PRNGKey(2), 60, (60.0, 60.0))
    path = sims.random_smooth_path(jax.random.PRNGKey(3), forest.centres, 300, (30.0, 30.0, 0.0),
                                   bounds=((0.0, 0.0), (60.0, 60.0)))
    assert float(sims.path_clearance(path, forest.centres, forest.radii)) > 0.5
    assert float(jnp.min(path[:, :2])) > -2.0 and float(jnp.max(path[:, :2])) < 62.0


@pytest.fixture(scope="module")
def scenario():
    return sims.default_scenario(jax.random.PRNGKey(0), 3, num_steps=120)


def test_scenario_shapes_and_run_seeding(scenario):
    assert scenario.controls.shape == (3, 120, 3)
    assert scenario.poses.shape == (3, 121, 3)
    assert scenario.observations.z.shape == (3, 120, 16, 2)
    fewer = sims.default_scenario(jax.random.PRNGKey(0), 2, num_steps=120)
    np.testing.assert_array_equal(np.asarray(fewer.controls), np.asarray(scenario.controls[:2]))
    np.testing.assert_array_equal(np.asarray(fewer.observations.z),
                                  np.asarray(scenario.observations.z[:2]))
    assert not np.allclose(scenario.controls[0], scenario.controls[1])


def test_analytic_observation_noise_is_table_2(scenario):
    obs = scenario.observations
    pose = scenario.poses[:, 1:, None, :]  # observation t is taken at pose t + 1
    truth = range_bearing(pose, scenario.centres[obs.landmark_id])
    valid = np.asarray(obs.valid)
    assert valid.sum() > 3000
    dist = np.asarray(truth[..., 0])[valid]
    z_r = (np.asarray(obs.z[..., 0])[valid] - dist) / (0.005 * dist)
    z_b = np.asarray(wrap_angle(obs.z[..., 1] - truth[..., 1]))[valid] / (0.0005 * dist)
    for z in (z_r, z_b):  # thousands of standard normals: mean and std within 5%
        assert abs(z.mean()) < 0.05 and abs(z.std() - 1.0) < 0.05
    assert np.all(dist <= 20.0)


def test_odometry_noise_is_eq_1(scenario):
    params = default_params(dtype=jnp.float64)
    std = odometry_std(scenario.moves, params)
    err = scenario.controls - scenario.moves
    err = err.at[..., 0].set(wrap_angle(err[..., 0])).at[..., 2].set(wrap_angle(err[..., 2]))
    z = np.asarray(err / std).reshape(-1, 3)
    assert np.all(np.abs(z.mean(0)) < 0.1) and np.all(np.abs(z.std(0) - 1.0) < 0.1)


@pytest.mark.slow
def test_lidar_scenario_detects_true_trees():
    forest = sims.random_forest(jax.random.PRNGKey(4), 40, (30.0, 30.0),
                                keep_clear=sims.loop_path(200, (15.0, 15.0), (8.0, 8.0),
                                                          0.25)[:, :2])
    path = sims.loop_path(4, (15.0, 15.0), (8.0, 8.0), 0.5)
    sc = sims.build_scenario(jax.random.PRNGKey(5), forest, path, 1, source="lidar")
    obs = jax.tree.map(lambda a: a[0], sc.observations)
    assert int(obs.valid.sum()) >= 8
    r, b = obs.z[..., 0], obs.z[..., 1]
    heading = path[1:, None, 2] + b
    xy = jnp.stack([path[1:, None, 0] + r * jnp.cos(heading),
                    path[1:, None, 1] + r * jnp.sin(heading)], -1)
    err = jnp.min(jnp.linalg.norm(xy[:, :, None] - forest.centres[None, None], axis=-1), -1)
    assert float(jnp.max(jnp.where(obs.valid, err, 0.0))) < 0.1
