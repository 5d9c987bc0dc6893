"""Geometry against plain NumPy float64 references: wrap, SE(2) compose/relative, range-bearing
and its Jacobian (vs jax.jacfwd and central finite differences), jit, vmap and edges."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam import geometry

RTOL = 1e-9
ATOL = 1e-9


# ---------------------------------------------------------------------------------------------
# NumPy float64 references


def ref_wrap(angle):
    """[-pi, pi) by Python's floored modulo."""
    return (np.asarray(angle, np.float64) + np.pi) % (2 * np.pi) - np.pi


def ref_se2(pose):
    c, s = np.cos(pose[2]), np.sin(pose[2])
    return np.array([[c, -s, pose[0]], [s, c, pose[1]], [0.0, 0.0, 1.0]])


def ref_pose(matrix):
    return np.array([matrix[0, 2], matrix[1, 2], np.arctan2(matrix[1, 0], matrix[0, 0])])


def ref_compose(pose, delta):
    return ref_pose(ref_se2(pose) @ ref_se2(delta))


def ref_relative(pose_a, pose_b):
    return ref_pose(np.linalg.inv(ref_se2(pose_a)) @ ref_se2(pose_b))


def ref_range_bearing(pose, point):
    dx, dy = point[0] - pose[0], point[1] - pose[1]
    return np.array([np.sqrt(dx * dx + dy * dy), ref_wrap(np.arctan2(dy, dx) - pose[2])])


def ref_jacobian_fd(pose, point, eps=1e-6):
    """Central finite differences of h w.r.t. the landmark point, (2, 2)."""
    columns = []
    for i in range(2):
        step = np.zeros(2)
        step[i] = eps
        diff = ref_range_bearing(pose, point + step) - ref_range_bearing(pose, point - step)
        diff[1] = ref_wrap(diff[1])
        columns.append(diff / (2 * eps))
    return np.stack(columns, axis=1)


def angle_close(actual, expected, atol=ATOL):
    np.testing.assert_allclose(ref_wrap(np.asarray(actual) - expected), 0.0, atol=atol)


@pytest.fixture(scope="module")
def rng():
    return np.random.default_rng(0)


# ---------------------------------------------------------------------------------------------
# wrap_angle


def test_wrap_angle_edges():
    pi = np.pi
    angles = np.array([0.0, pi, -pi, 3 * pi, -3 * pi, 2 * pi, -2 * pi, pi - 1e-12, -pi + 1e-12])
    out = np.asarray(geometry.wrap_angle(jnp.asarray(angles)))
    # Range is [-pi, pi): +pi and odd multiples map to -pi.
    np.testing.assert_allclose(out[[1, 2, 3, 4]], -pi, atol=1e-12)
    np.testing.assert_allclose(out[[0, 5, 6]], 0.0, atol=1e-12)
    np.testing.assert_allclose(out[7], pi - 1e-12, atol=1e-12)
    np.testing.assert_allclose(out[8], -pi + 1e-12, atol=1e-12)
    assert np.all(out >= -pi) and np.all(out < pi)


def test_wrap_angle_large_and_random(rng):
    angles = np.concatenate([rng.uniform(-1e3, 1e3, 1000), [1e4 + 0.3, -1e4 - 0.3, 123.456]])
    out = np.asarray(geometry.wrap_angle(jnp.asarray(angles)))
    assert np.all(out >= -np.pi) and np.all(out < np.pi)
    angle_close(out, ref_wrap(angles), atol=1e-9)
    # Same angle modulo 2 pi (relative to magnitude: floor arithmetic keeps ~1e-16 relative).
    np.testing.assert_allclose(np.sin(out), np.sin(angles), atol=1e-10)
    np.testing.assert_allclose(np.cos(out), np.cos(angles), atol=1e-10)


def test_wrap_angle_jit_float32():
    angles = jnp.asarray([0.5, 4.0, -4.0, 100.0], jnp.float32)
    out = jax.jit(geometry.wrap_angle)(angles)
    assert out.dtype == jnp.float32
    angle_close(np.asarray(out, np.float64), ref_wrap(np.asarray(angles, np.float64)), atol=1e-5)


# ---------------------------------------------------------------------------------------------
# compose / relative


def random_poses(rng, n):
    return np.stack([rng.uniform(-20, 20, n), rng.uniform(-20, 20, n),
                     rng.uniform(-np.pi, np.pi, n)], axis=1)


@pytest.mark.parametrize("use_jit", [False, True])
def test_compose_relative_vs_reference(rng, use_jit):
    a, b = random_poses(rng, 50), random_poses(rng, 50)
    compose = jax.jit(geometry.compose) if use_jit else geometry.compose
    relative = jax.jit(geometry.relative) if use_jit else geometry.relative
    out_c = np.asarray(compose(jnp.asarray(a), jnp.asarray(b)))  # batched (50, 3)
    out_r = np.asarray(relative(jnp.asarray(a), jnp.asarray(b)))
    ref_c = np.stack([ref_compose(p, d) for p, d in zip(a, b)])
    ref_r = np.stack([ref_relative(p, q) for p, q in zip(a, b)])
    np.testing.assert_allclose(out_c[:, :2], ref_c[:, :2], rtol=RTOL, atol=ATOL)
    angle_close(out_c[:, 2], ref_c[:, 2])
    np.testing.assert_allclose(out_r[:, :2], ref_r[:, :2], rtol=RTOL, atol=ATOL)
    angle_close(out_r[:, 2], ref_r[:, 2])


def test_compose_relative_inverse_pair(rng):
    a, b = jnp.asarray(random_poses(rng, 100)), jnp.asarray(random_poses(rng, 100))
    back = geometry.compose(a, geometry.relative(a, b))
    np.testing.assert_allclose(np.asarray(back[:, :2]), np.asarray(b[:, :2]), atol=1e-9)
    angle_close(np.asarray(back[:, 2]), np.asarray(b[:, 2]))
    delta = geometry.relative(a, geometry.compose(a, b))
    np.testing.assert_allclose(np.asarray(delta[:, :2]), np.asarray(b[:, :2]), atol=1e-9)
    angle_close(np.asarray(delta[:, 2]), np.asarray(b[:, 2]))
    # Heading stays wrapped.
    assert np.all(np.abs(np.asarray(back[:, 2])) <= np.pi)


def test_compose_vmap_matches_batched(rng):
    a, b = jnp.asarray(random_poses(rng, 8)), jnp.asarray(random_poses(rng, 8))
    np.testing.assert_allclose(np.asarray(jax.vmap(geometry.compose)(a, b)),
                               np.asarray(geometry.compose(a, b)), atol=1e-12)


# ---------------------------------------------------------------------------------------------
# range_bearing and its Jacobian


@pytest.mark.parametrize("use_jit", [False, True])
def test_range_bearing_vs_reference(rng, use_jit):
    poses, points = random_poses(rng, 60), rng.uniform(-30, 30, (60, 2))
    fn = jax.jit(geometry.range_bearing) if use_jit else geometry.range_bearing
    out = np.asarray(fn(jnp.asarray(poses), jnp.asarray(points)))
    ref = np.stack([ref_range_bearing(p, q) for p, q in zip(poses, points)])
    np.testing.assert_allclose(out[:, 0], ref[:, 0], rtol=RTOL, atol=ATOL)
    angle_close(out[:, 1], ref[:, 1])
    # vmap over pairs equals the batched call.
    np.testing.assert_allclose(
        np.asarray(jax.vmap(geometry.range_bearing)(jnp.asarray(poses), jnp.asarray(points))),
        out, atol=1e-12)


def test_inverse_range_bearing_round_trip(rng):
    poses, points = random_poses(rng, 40), rng.uniform(-30, 30, (40, 2))
    z = geometry.range_bearing(jnp.asarray(poses), jnp.asarray(points))
    back = geometry.inverse_range_bearing(jnp.asarray(poses), z)
    np.testing.assert_allclose(np.asarray(back), points, atol=1e-9)


def test_range_bearing_jacobian_vs_autodiff_and_fd(rng):
    poses, points = random_poses(rng, 30), rng.uniform(-30, 30, (30, 2))
    for pose, point in zip(poses, points):
        dx, dy = point - pose[:2]
        h00, h01, h10, h11 = (float(v) for v in geometry.range_bearing_jacobian_point(
            jnp.asarray(dx), jnp.asarray(dy)))
        closed = np.array([[h00, h01], [h10, h11]])
        auto = np.asarray(jax.jacfwd(geometry.range_bearing, argnums=1)(
            jnp.asarray(pose), jnp.asarray(point)))
        np.testing.assert_allclose(closed, auto, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(closed, ref_jacobian_fd(pose, point), rtol=1e-5, atol=1e-8)
        # Pose Jacobian: -H on (x, y), d bearing / d theta = -1, d range / d theta = 0.
        auto_pose = np.asarray(jax.jacfwd(geometry.range_bearing, argnums=0)(
            jnp.asarray(pose), jnp.asarray(point)))
        np.testing.assert_allclose(auto_pose[:, :2], -closed, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(auto_pose[:, 2], [0.0, -1.0], atol=1e-12)


def test_range_bearing_jacobian_vmap_and_jit(rng):
    d = jnp.asarray(rng.uniform(-10, 10, (2, 25)))
    eager = geometry.range_bearing_jacobian_point(d[0], d[1])
    jitted = jax.jit(geometry.range_bearing_jacobian_point)(d[0], d[1])
    mapped = jax.vmap(geometry.range_bearing_jacobian_point)(d[0], d[1])
    for e, j, m in zip(eager, jitted, mapped):
        np.testing.assert_allclose(np.asarray(j), np.asarray(e), rtol=1e-12)
        np.testing.assert_allclose(np.asarray(m), np.asarray(e), rtol=1e-12)


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_range_bearing_jacobian_zero_distance_finite(dtype):
    zero = jnp.zeros((), dtype)
    entries = geometry.range_bearing_jacobian_point(zero, zero)
    assert all(bool(jnp.isfinite(e)) for e in entries)
    tiny = jnp.asarray(1e-12, dtype)
    assert all(bool(jnp.isfinite(e)) for e in geometry.range_bearing_jacobian_point(tiny, zero))
