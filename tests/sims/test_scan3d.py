"""3D lidar point clouds (sims.scan_3d) and leaning-trunk forests (sims.forest3d).

The geometry is checked against a NumPy float64 reference: exact ray intersections with
capsules (a finite cylinder plus two hemispheres) and with the tilted ground plane.

Tolerances: MJX casts in float32 in each geom's local frame; a range r then carries a
rounding error of a few eps * r^2 / (r sin(incidence)) (the quadratic's discriminant
cancels), about 0.1 mm at 10 m for a trunk hit well inside its silhouette, growing without
bound at a grazing hit. So ranges are compared to 1 mm on beams whose reference ray passes at
least 1 cm inside a trunk's silhouette or hits the ground, and hit/miss may differ only on
beams within 1 cm of a silhouette edge.
"""
import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import sims
from sims.forest import empty_clutter
from sims.forest3d import Forest3D, Terrain, lean_axes
from sims.scan3d import beam_directions

MAX_RANGE = 20.0
SLOPE = np.array([0.06, -0.04])
MOUNT = 1.0
TRUNK_LENGTH, SINK = 10.0, 0.6
# Trunks: base xy [m], radius [m], lean [deg], lean azimuth [deg].
TRUNKS = [((5.0, 1.0), 0.20, 12.0, 30.0), ((-3.0, 4.0), 0.15, 8.0, 200.0),
          ((1.0, -6.0), 0.30, 15.0, -90.0)]


def _forest(mounds=False) -> Forest3D:
    xy = np.array([t[0] for t in TRUNKS])
    radii = np.array([t[1] for t in TRUNKS])
    axis = np.asarray(lean_axes(np.radians([t[2] for t in TRUNKS]),
                                np.radians([t[3] for t in TRUNKS])), np.float64)
    if mounds:
        terrain = Terrain(jnp.asarray(SLOPE, jnp.float32), jnp.array([[-4.0, -3.0]]),
                          jnp.array([[2.5, 1.5, 0.4]]), jnp.array([0.7]))
    else:
        terrain = Terrain(jnp.asarray(SLOPE, jnp.float32), jnp.zeros((0, 2)),
                          jnp.zeros((0, 3)), jnp.zeros((0,)))
    base = np.column_stack([xy, xy @ SLOPE])
    return Forest3D(jnp.asarray(base, jnp.float32), jnp.asarray(axis, jnp.float32),
                    jnp.asarray(radii, jnp.float32), terrain, empty_clutter())


@pytest.fixture(scope="module")
def world():
    return sims.make_world_3d(_forest(), mount_height=MOUNT, trunk_length=TRUNK_LENGTH,
                              sink=SINK)


# ------------------------------------------------------------------ the float64 reference


def ray_capsule(origin, d, p0, p1, radius):
    """(B,) distance along unit rays d (B, 3) from origin (3,) to the capsule p0-p1 of
    ``radius`` (+inf: miss) and (B,) the distance between each ray's line and the axis line
    (for the silhouette-edge mask)."""
    axis = p1 - p0
    length = np.linalg.norm(axis)
    u = axis / length
    w = origin - p0
    # Infinite cylinder |(w + t d) x u| = r: quadratic in t on the components normal to u.
    dn = d - np.outer(d @ u, u)
    wn = w - (w @ u) * u
    a, b, c = np.sum(dn * dn, 1), 2.0 * dn @ wn, wn @ wn - radius ** 2
    disc = b * b - 4.0 * a * c
    with np.errstate(invalid="ignore", divide="ignore"):
        t = (-b - np.sqrt(np.maximum(disc, 0.0))) / (2.0 * a)
    s = w @ u + t * (d @ u)
    best = np.where((disc >= 0) & (t > 0) & (s >= 0) & (s <= length), t, np.inf)
    for centre in (p0, p1):  # the hemispherical caps (the sphere's first hit)
        f = origin - centre
        bb = d @ f
        disc_s = bb * bb - (f @ f - radius ** 2)
        ts = -bb - np.sqrt(np.maximum(disc_s, 0.0))
        best = np.minimum(best, np.where((disc_s >= 0) & (ts > 0), ts, np.inf))
    normal = np.cross(d, u)
    gap = np.abs(normal @ w) / np.linalg.norm(normal, axis=1)
    return best, gap


def ray_plane(origin, d, slope):
    """(B,) distance to the plane z = slope . (x, y) from above (+inf: miss)."""
    denom = d[:, 2] - d[:, :2] @ slope
    with np.errstate(divide="ignore"):
        t = (origin[:2] @ slope - origin[2]) / denom
    return np.where((denom < 0) & (t > 0), t, np.inf)


def reference_scan(pose, num_layers, num_beams, elevation_deg=(-15.0, 15.0)):
    """Ranges (L B,) (MAX_RANGE: none), hit index (L B,) (trunk i, N = ground, -1 none) and an
    edge mask (L B,) of beams within 1 cm of a trunk's silhouette."""
    local = beam_directions(num_layers, num_beams, elevation_deg).reshape(-1, 3)
    c, s = np.cos(pose[2]), np.sin(pose[2])
    d = local @ np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
    origin = np.array([pose[0], pose[1], pose[:2] @ SLOPE + MOUNT])
    forest = _forest()
    base, axis = np.asarray(forest.base, np.float64), np.asarray(forest.axis, np.float64)
    hits, edge = [], np.zeros(len(d), bool)
    ground = ray_plane(origin, d, SLOPE)
    for b, u, (_, radius, _, _) in zip(base, axis, TRUNKS):
        t, gap = ray_capsule(origin, d, b - SINK * u, b + TRUNK_LENGTH * u, radius)
        hits.append(t)
        # Edges: the silhouette, and where the trunk meets the ground (equal distances).
        with np.errstate(invalid="ignore"):  # inf - inf where both miss
            near_ground = np.abs(t - ground) < 0.01
        edge |= (np.abs(gap - radius) < 0.01) | near_ground
    hits = np.stack(hits + [ground], 1)
    which = np.argmin(hits, 1)
    ranges = hits[np.arange(len(d)), which]
    hit = ranges < MAX_RANGE
    return np.where(hit, ranges, MAX_RANGE), np.where(hit, which, -1), edge, local


# ------------------------------------------------------------------ geometry


POSE = np.array([0.5, -0.5, 0.4])


@pytest.fixture(scope="module")
def full_scan(world):
    return sims.scan_3d(world, jnp.asarray(POSE, jnp.float32))  # 16 x 1800, the default


def test_scan_matches_the_float64_reference(world, full_scan):
    cloud = full_scan
    chex.assert_shape(cloud.points, (16 * 1800, 3))
    chex.assert_shape(cloud.ranges, (16, 1800))
    assert bool(cloud.complete)
    ref, which, edge, local = reference_scan(POSE, 16, 1800)
    got = np.asarray(cloud.ranges, np.float64).ravel()
    geom = np.asarray(cloud.geom).ravel()
    num_trunks = len(TRUNKS)
    hit_tree = np.where(geom >= 0, np.asarray(world.world.geom_tree)[np.maximum(geom, 0)], -2)
    got_which = np.where(geom < 0, -1, np.where(hit_tree >= 0, hit_tree, num_trunks))
    # Hit/miss and the object hit agree except within 1 cm of a silhouette edge.
    disagree = (got_which != which) & ~edge
    assert disagree.sum() == 0, np.flatnonzero(disagree)[:10]
    trunk_beams = (which >= 0) & (which < num_trunks) & ~edge & (got_which == which)
    ground_beams = (which == num_trunks) & (got_which == which)
    assert trunk_beams.sum() > 500 and ground_beams.sum() > 5000
    for beams in (trunk_beams, ground_beams):
        np.testing.assert_allclose(got[beams], ref[beams], atol=1e-3)
    # Points: range times the sensor-frame direction; zeros without a return.
    valid = np.asarray(cloud.valid)
    np.testing.assert_array_equal(valid, got < MAX_RANGE)
    np.testing.assert_allclose(np.asarray(cloud.points)[valid],
                               got[valid, None] * local[valid], atol=1e-5)
    assert not np.asarray(cloud.points)[~valid].any()
    # The sensor rides MOUNT above the sloped ground.
    np.testing.assert_allclose(np.asarray(cloud.origin),
                               [POSE[0], POSE[1], POSE[:2] @ SLOPE + MOUNT], atol=1e-6)


def test_trunk_points_lie_on_the_leaning_cylinders(world, full_scan):
    """Each trunk return, moved to the world, is r from its trunk's axis (1 mm: float32)."""
    cloud = full_scan
    c, s = np.cos(POSE[2]), np.sin(POSE[2])
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    pts = np.asarray(cloud.points, np.float64) @ rot.T + np.asarray(cloud.origin, np.float64)
    tree = np.asarray(world.world.geom_tree)[np.maximum(np.asarray(cloud.geom).ravel(), 0)]
    tree = np.where(np.asarray(cloud.geom).ravel() >= 0, tree, -1)
    base, axis = np.asarray(world.base, np.float64), np.asarray(world.axis, np.float64)
    for i, (_, radius, _, _) in enumerate(TRUNKS):
        p = pts[tree == i] - base[i]
        assert len(p) > 50
        dist = np.linalg.norm(p - np.outer(p @ axis[i], axis[i]), axis=1)
        np.testing.assert_allclose(dist, radius, atol=1e-3)


SMALL = dict(num_beams=120, num_layers=4, num_sectors=8)  # one compile, shared by tests
SMALL_POSES = jnp.array([[0.5, -0.5, 0.4], [2.0, 2.0, -1.0], [-1.0, 0.0, 3.0]])


def test_vmap_equals_single_scans(world):
    """vmap over three poses and keys equals three single calls (1e-5 m: the same float32
    arithmetic, possibly fused differently)."""
    keys = jax.random.split(jax.random.PRNGKey(3), 3)
    single = [sims.scan_3d(world, p, key=k, **SMALL) for p, k in zip(SMALL_POSES, keys)]
    batched = jax.vmap(lambda p, k: sims.scan_3d(world, p, key=k, **SMALL))(SMALL_POSES, keys)
    chex.assert_shape(batched.points, (3, 480, 3))
    for i, one in enumerate(single):
        np.testing.assert_array_equal(np.asarray(batched.valid[i]), np.asarray(one.valid))
        np.testing.assert_allclose(np.asarray(batched.points[i]), np.asarray(one.points),
                                   atol=1e-5)
    # Noise: on the ranges only, 1.5 cm std (~200 returns: the sample std within 0.5-3 cm).
    clean = sims.scan_3d(world, SMALL_POSES[0], **SMALL)
    hit = np.asarray(clean.valid)
    delta = (np.asarray(single[0].ranges) - np.asarray(clean.ranges)).ravel()[hit]
    assert 0.005 < delta.std() < 0.03
    np.testing.assert_array_equal(np.asarray(single[0].valid), hit)


@pytest.mark.slow
def test_eager_equals_jit(world):
    """``jax.disable_jit`` runs the same code op by op (about 20 s on 2 cores): same cloud
    within 1e-5 m (float32, different fusion)."""
    key = jax.random.PRNGKey(3)
    jitted = sims.scan_3d(world, SMALL_POSES[0], key=key, **SMALL)
    with jax.disable_jit():
        eager = sims.scan_3d(world, SMALL_POSES[0], key=key, **SMALL)
    np.testing.assert_array_equal(np.asarray(eager.valid), np.asarray(jitted.valid))
    np.testing.assert_allclose(np.asarray(eager.points), np.asarray(jitted.points), atol=1e-5)


def test_no_trunk_in_range_and_all_beams_missing(world):
    far = jnp.array([40.0, 40.0, 0.0])  # every trunk is > 40 m away, beyond the 20 m range
    cloud = sims.scan_3d(world, far, **SMALL)
    assert np.asarray(cloud.valid).any()  # the ground still
    geom = np.asarray(cloud.geom)
    assert np.all(np.asarray(world.world.geom_tree)[geom[geom >= 0]] == -1)
    # Upward layers only: nothing at all is hit.
    up = sims.scan_3d(world, far, elevation_deg=(2.0, 10.0), **SMALL)
    assert not np.asarray(up.valid).any()
    assert not np.asarray(up.points).any()
    np.testing.assert_array_equal(np.asarray(up.ranges), MAX_RANGE)
    np.testing.assert_array_equal(np.asarray(up.geom), -1)


def test_flat_world_scan_keeps_the_old_ranges():
    """On a flat ``sims.forest.World`` the cloud's ranges are ``sims.lidar.scan_3d``'s."""
    from sims.lidar import scan_3d as ranges_3d

    forest = sims.random_forest(jax.random.PRNGKey(4), 6, (10.0, 10.0))
    flat = sims.world_from_forest(forest)
    pose = jnp.array([5.0, 5.0, 0.2])
    cloud = sims.scan_3d(flat, pose, 90, 15.0, num_layers=4)
    old = ranges_3d(flat, pose, 90, 15.0, num_layers=4)
    np.testing.assert_array_equal(np.asarray(cloud.ranges), np.asarray(old.ranges))
    np.testing.assert_allclose(np.asarray(cloud.origin), [5.0, 5.0, 0.5])


# ------------------------------------------------------------------ forests


def test_ground_hits_lie_on_the_ground_model():
    """Returns from the plane and a mound lie on ``ground_height`` (1 mm), so trunk bases
    and the sensor height use the surface the lidar sees."""
    world = sims.make_world_3d(_forest(mounds=True), mount_height=MOUNT)
    pose = jnp.array([-1.0, -1.0, 0.0])
    cloud = sims.scan_3d(world, pose, **SMALL)
    geom = np.asarray(cloud.geom).ravel()
    ground = (geom >= 0) & (np.asarray(world.world.geom_tree)[np.maximum(geom, 0)] == -1)
    types = np.asarray(world.world.model.geom_type)[np.maximum(geom, 0)]
    mound = ground & (types == 4)  # mjGEOM_ELLIPSOID
    assert mound.sum() > 5
    pts = np.asarray(cloud.points, np.float64)[ground] + np.asarray(cloud.origin)
    g = np.asarray(sims.ground_height(world.terrain, jnp.asarray(pts[:, :2], jnp.float32)))
    np.testing.assert_allclose(pts[:, 2], g, atol=1e-3)


def test_leaning_forest_is_deterministic_per_key():
    kwargs = dict(num_trees=12, size=(20.0, 20.0), num_bushes=3, num_logs=1,
                  keep_clear=np.array([[10.0, 10.0]]))
    a = sims.random_forest_3d(jax.random.PRNGKey(7), **kwargs)
    b = sims.random_forest_3d(jax.random.PRNGKey(7), **kwargs)
    other = sims.random_forest_3d(jax.random.PRNGKey(8), **kwargs)
    chex.assert_trees_all_equal(a, b)
    assert not np.allclose(np.asarray(a.base), np.asarray(other.base))
    lean = np.degrees(np.arccos(np.asarray(a.axis[:, 2])))
    assert lean.min() >= 2.0 - 1e-3 and lean.max() <= 15.0 + 1e-3
    np.testing.assert_allclose(np.linalg.norm(np.asarray(a.axis), axis=1), 1.0, atol=1e-6)
    # Bases stand on the ground; trunk bases stay clear of the kept point.
    g = sims.ground_height(a.terrain, a.base[:, :2])
    np.testing.assert_allclose(np.asarray(a.base[:, 2]), np.asarray(g), atol=1e-6)
    assert np.min(np.linalg.norm(np.asarray(a.base[:, :2]) - 10.0, axis=1)) >= 1.5
    # Breast height: 1.3 m vertically above the base, on the axis.
    bh = np.asarray(sims.breast_height_points(a.base, a.axis))
    np.testing.assert_allclose(bh[:, 2] - np.asarray(a.base[:, 2]), 1.3, atol=1e-5)
    off = bh - np.asarray(a.base)
    np.testing.assert_allclose(np.linalg.norm(np.cross(off, np.asarray(a.axis)), axis=1), 0.0,
                               atol=1e-5)


def test_measured_dbh_distributions():
    dbh = np.asarray(sims.sample_dbh(jax.random.PRNGKey(0), 400, "black_cherry"))
    table = np.asarray(sims.BLACK_CHERRY_DBH, np.float32)
    assert np.isin(dbh, table).all()
    assert abs(np.median(dbh) - 0.0254 * 12.9) < 0.03  # the stand's median: 12.9 in
    measured = np.array([0.21, 0.33, 0.40])
    own = np.asarray(sims.sample_dbh(jax.random.PRNGKey(1), 50, measured))
    assert set(np.round(own, 6)) <= set(np.round(measured.astype(np.float32), 6))
    forest = sims.random_forest_3d(jax.random.PRNGKey(2), 8, (20.0, 20.0), dbh="black_cherry")
    assert np.isin(2 * np.asarray(forest.radii), table).all()
    with pytest.raises(ValueError, match="expected one of"):
        sims.sample_dbh(jax.random.PRNGKey(0), 3, "weibull")
    with pytest.raises(ValueError, match="metres"):
        sims.sample_dbh(jax.random.PRNGKey(0), 3, [25.0])  # centimetres by mistake
