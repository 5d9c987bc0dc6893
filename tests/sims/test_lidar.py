"""Lidar scans: mjx.ray against mujoco.mj_ray and analytic ray-circle hits; culling exactness."""
import chex
import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

import sims
from sims.lidar import beam_angles

MAX_RANGE = 20.0


def _ray_circle_ranges(origin, angles, centres, radii, max_range):
    """Float64 reference: nearest intersection of each horizontal ray with each circle."""
    d = np.stack([np.cos(angles), np.sin(angles)], -1)[:, None, :]  # (B, 1, 2)
    f = origin[None, None, :] - centres[None]  # (1, N, 2)
    b = np.sum(f * d, -1)
    c = np.sum(f * f, -1) - radii[None] ** 2
    disc = b * b - c
    t = -b - np.sqrt(np.where(disc >= 0, disc, 0.0))
    t = np.where((disc >= 0) & (t > 0), t, np.inf)
    out = t.min(1)
    return np.where(out < max_range, out, max_range)


@pytest.fixture(scope="module")
def small_world():
    forest = sims.random_forest(jax.random.PRNGKey(3), 40, (30.0, 30.0), num_bushes=4,
                                num_logs=3)
    return forest, sims.world_from_forest(forest)


@pytest.fixture(scope="module")
def trunk_world():
    forest = sims.random_forest(jax.random.PRNGKey(4), 60, (40.0, 40.0))
    return forest, sims.world_from_forest(forest)


def test_mjx_scan_matches_mujoco_mj_ray(small_world):
    forest, world = small_world
    mj_model = sims.mj_model_of(forest)
    mj_data = mujoco.MjData(mj_model)
    mujoco.mj_forward(mj_model, mj_data)
    pose = np.array([15.0, 14.0, 0.4])
    angles = beam_angles(180) + pose[2]
    scan = sims.scan_2d_full(world, jnp.asarray(pose), 180, MAX_RANGE, cull=False)
    geom_id = np.zeros(1, np.int32)
    for b, a in enumerate(angles):
        pnt = np.array([pose[0], pose[1], 0.5])
        vec = np.array([np.cos(a), np.sin(a), 0.0])
        dist = mujoco.mj_ray(mj_model, mj_data, pnt, vec, None, 1, -1, geom_id)
        expected = dist if 0 <= dist < MAX_RANGE else MAX_RANGE
        np.testing.assert_allclose(float(scan.ranges[b]), expected, rtol=1e-4, atol=1e-4)
        assert int(scan.geom[b]) == (int(geom_id[0]) if expected < MAX_RANGE else -1)
    hit_types = {int(mj_model.geom_type[g]) for g in np.asarray(scan.geom) if g >= 0}
    assert len(hit_types) >= 2, "the test scene should hit trunks and clutter"


def test_scan_matches_analytic_ray_circle(trunk_world):
    forest, world = trunk_world
    for pose in (np.array([20.0, 20.0, 0.0]), np.array([5.0, 33.0, -2.0])):
        ranges = sims.scan_2d(world, jnp.asarray(pose), 720, MAX_RANGE)
        expected = _ray_circle_ranges(pose[:2], beam_angles(720) + pose[2],
                                      np.asarray(forest.centres, float),
                                      np.asarray(forest.radii, float), MAX_RANGE)
        assert np.sum(expected < MAX_RANGE) > 20
        np.testing.assert_allclose(np.asarray(ranges), expected, atol=2e-3)


@pytest.mark.parametrize("seed", [0, pytest.param(1, marks=pytest.mark.slow)])
def test_culling_never_changes_a_scan(small_world, seed):
    forest, world = small_world
    poses = jnp.concatenate([jax.random.uniform(jax.random.PRNGKey(seed), (4, 2),
                                                minval=2.0, maxval=28.0),
                             jax.random.uniform(jax.random.PRNGKey(seed + 9), (4, 1),
                                                minval=-3.0, maxval=3.0)], -1)
    culled = jax.vmap(lambda p: sims.scan_2d_full(world, p, 240, MAX_RANGE, cull=True))(poses)
    full = jax.vmap(lambda p: sims.scan_2d_full(world, p, 240, MAX_RANGE, cull=False))(poses)
    assert bool(jnp.all(culled.complete))
    np.testing.assert_array_equal(np.asarray(culled.geom), np.asarray(full.geom))
    np.testing.assert_allclose(np.asarray(culled.ranges), np.asarray(full.ranges), atol=1e-3)


@pytest.mark.slow
def test_culling_flags_overflow():
    forest = sims.random_forest(jax.random.PRNGKey(5), 60, (20.0, 20.0), min_spacing=1.5)
    world = sims.world_from_forest(forest, num_slots=1)
    scan = sims.scan_2d_full(world, jnp.array([10.0, 10.0, 0.0]), 90, MAX_RANGE,
                             num_sectors=4)
    assert not bool(scan.complete)


def test_jit_and_vmap_agree(trunk_world):
    _, world = trunk_world
    poses = jnp.array([[20.0, 20.0, 0.0], [10.0, 12.0, 1.0], [30.0, 5.0, -2.5]])
    fn = lambda p: sims.scan_2d(world, p, 240, MAX_RANGE)
    batched = jax.jit(jax.vmap(fn))(poses)
    for i in range(3):
        chex.assert_trees_all_close(batched[i], fn(poses[i]), atol=1e-5)


def test_range_noise_statistics_and_no_return(trunk_world):
    _, world = trunk_world
    pose = jnp.array([20.0, 20.0, 0.0])
    clean = sims.scan_2d(world, pose, 720, MAX_RANGE)
    keys = jax.random.split(jax.random.PRNGKey(7), 50)
    noisy = jax.vmap(lambda k: sims.scan_2d(world, pose, 720, MAX_RANGE, key=k))(keys)
    hit = np.asarray(clean) < MAX_RANGE
    assert np.all(np.asarray(noisy)[:, ~hit] == MAX_RANGE)
    assert np.all(np.asarray(noisy)[:, hit] < MAX_RANGE)
    z = (np.asarray(noisy) - np.asarray(clean))[:, hit] / (0.005 * np.asarray(clean)[hit])
    # ~ 50 * (hits) standard normals: the sample std is within 5% of 1.
    assert z.size > 2000
    assert abs(z.std() - 1.0) < 0.05 and abs(z.mean()) < 0.05


@pytest.mark.slow
def test_3d_scan_clipped_matches_planar_scan(trunk_world):
    _, world = trunk_world
    pose = jnp.array([20.0, 20.0, 0.3])
    scan3 = sims.scan_3d(world, pose, 180, MAX_RANGE, num_layers=8)
    elevations = sims.layer_elevations(8)
    downward = np.asarray(scan3.ranges)[elevations < 0]
    assert np.sum(downward < MAX_RANGE) > 100, "the ground should be hit by downward layers"
    planar = sims.clip_3d_to_2d(scan3.ranges, elevations, 0.5, MAX_RANGE, z_min=0.2,
                                z_max=3.0)
    reference = sims.scan_2d(world, pose, 180, MAX_RANGE)
    both = (np.asarray(planar) < MAX_RANGE) & (np.asarray(reference) < MAX_RANGE)
    assert both.sum() > 10
    np.testing.assert_allclose(np.asarray(planar)[both], np.asarray(reference)[both], atol=2e-3)
    # No ground return survives the clipping: every kept return is a trunk range.
    assert np.all((np.asarray(planar) == MAX_RANGE) | both)


def test_make_world_validates_input():
    with pytest.raises(ValueError, match="centres"):
        sims.make_world(jnp.zeros((3, 3)), jnp.ones(3))
    with pytest.raises(ValueError, match="positive"):
        sims.make_world(jnp.zeros((2, 2)), jnp.array([0.1, -0.1]))


def _ray_ellipse_ranges(origin, angles, centre, axes, yaw, max_range):
    """Float64 reference: nearest hit of each horizontal ray with one rotated ellipse."""
    rotation = np.array([[np.cos(yaw), np.sin(yaw)], [-np.sin(yaw), np.cos(yaw)]])
    d = np.stack([np.cos(angles), np.sin(angles)], -1) @ rotation.T / axes  # body frame, scaled
    f = (rotation @ (origin - centre)) / axes
    a = np.sum(d * d, -1)
    b = np.sum(d * f, -1)
    c = np.sum(f * f) - 1.0
    disc = b * b - a * c
    t = (-b - np.sqrt(np.where(disc >= 0, disc, 0.0))) / a
    t = np.where((disc >= 0) & (t > 0), t, np.inf)
    return np.where(t < max_range, t, max_range)


def test_elliptical_trunk_scan_matches_analytic_ray_ellipse():
    """Non-circular trunks (ellipsoids): the scan-height cut is the requested ellipse, and
    mjx.ray agrees with an analytic float64 ray-ellipse intersection to 2 mm."""
    centre, axes, yaw = np.array([6.0, 1.0]), np.array([0.45, 0.25]), 0.6
    world = sims.make_world(jnp.asarray(centre[None]), jnp.asarray([0.35]),
                            trunk_axes=axes[None], trunk_heading=np.array([yaw]))
    assert int(world.model.geom_type[0]) == int(mujoco.mjtGeom.mjGEOM_ELLIPSOID)
    pose = np.array([0.0, 0.0, 0.0])
    ranges = np.asarray(sims.scan_2d(world, jnp.asarray(pose), 1440, MAX_RANGE))
    expected = _ray_ellipse_ranges(pose[:2], beam_angles(1440), centre, axes, yaw, MAX_RANGE)
    assert np.sum(expected < MAX_RANGE) >= 10
    np.testing.assert_allclose(ranges, expected, atol=2e-3)
