"""Leaning trunks on uneven ground: forests for 3D lidar and cylinder trunk detection.

``sims.forest`` stands vertical capsule trunks on the plane z = 0, which is all a planar scan
needs. A 3D detector (``jaxslam.detect3d``; Geiser et al., "Practical Implementation of FastSLAM
for Forestry Robot", ICAROB 2023, fit RANSAC cylinders to clipped 3D clouds) has to cope with
what a flat world hides: trunks that lean, ground that is not level, undergrowth. Here:

  trunks      capsules of radius r = DBH / 2 along a unit axis u leaning ``lean`` from the
              vertical toward azimuth ``psi`` (u = (sin lean cos psi, sin lean sin psi,
              cos lean)), from ``sink`` below their base b (where the axis meets the ground,
              so the rounded end is buried) to ``trunk_length`` above it. The breast-height
              point is b + u 1.3 / u_z (1.3 m vertically above the base, the convention of
              ``jaxslam.detect3d``): the tree's true position, ``World.centres``.
  ground      a tilted plane z = s . (x, y) (slope s (2,)) plus low mounds: ellipsoids whose
              equator lies in the plane, semi-axes (a, b) in the plane and c along its normal.
              The ground height g(x, y) = max(plane, mound tops) (``ground_height``).
  undergrowth ``sims.forest.random_clutter`` bushes (ellipsoids sunk 0.3 c into the ground at
              their centre) and logs (capsules lying on the ground).
  DBH         ``sample_dbh``: the log-normal of ``sims.forest.sample_radii``, or a measured
              stand: the 31 black cherry trees (Prunus serotina, Allegheny National Forest,
              Pennsylvania) of Ryan, Joiner and Ryan, "Minitab Student Handbook" (1976), the
              ``trees`` data set of R (diameters at 4 ft 6 in = 1.37 m, 8.3-20.6 in), drawn
              with replacement; or any array of measured DBHs.

Why not a heightfield: ``mjx.ray`` in MuJoCo 3.17 (``mujoco/mjx/_src/ray.py``, ``_RAY_FUNC``)
intersects planes, spheres, capsules, ellipsoids, boxes and meshes, not hfields, and tests a
ray against every triangle of a mesh (no culling inside a mesh): a terrain mesh fine enough to
matter would cost thousands of triangle tests per beam. A tilted plane plus ellipsoid mounds
is continuous, cheap, and culled like every other geom (``sims.lidar``).

Model rules (as in ``sims.forest``): every geom has a ``<material>`` (``mjx.ray`` crashes
without one), static geoms never collide (``contype="0" conaffinity="0"``), and the sensor body
carries one slide joint (``mjx.forward`` needs a degree of freedom). Geom order: trunks
0..N-1, bushes, logs, mounds, the ground plane.

Generators take a key first and run eagerly (NumPy on the result), not under ``jit``.
"""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from sims.forest import (
    Clutter,
    World,
    _geom_bounds,
    _put,
    _slot_mjcf,
    mjcf_document,
    poisson_disc,
    random_clutter,
    sample_radii,
)
from sims.mujoco_loader import mujoco  # imported when first used

BREAST_HEIGHT = 1.3  # [m] above the trunk's base
# Ryan, Joiner and Ryan (1976), R datasets::trees, column Girth (a diameter despite the name) [in].
BLACK_CHERRY_DBH_IN = (8.3, 8.6, 8.8, 10.5, 10.7, 10.8, 11.0, 11.0, 11.1, 11.2, 11.3, 11.4, 11.4,
                       11.7, 12.0, 12.9, 12.9, 13.3, 13.7, 13.8, 14.0, 14.2, 14.5, 16.0, 16.3,
                       17.3, 17.5, 17.9, 18.0, 18.0, 20.6)
BLACK_CHERRY_DBH = tuple(0.0254 * d for d in BLACK_CHERRY_DBH_IN)  # [m]
DBH_CHOICES = ("lognormal", "black_cherry")


class Terrain(NamedTuple):
    """Uneven ground: a tilted plane through the origin plus M mounds.

    Attributes:
      slope: (2,) plane gradient (dz/dx, dz/dy) [-]; the plane is z = slope . (x, y).
      mound_centres: (M, 2) xy of each mound's centre, which lies on the plane [m].
      mound_axes: (M, 3) semi-axes (a, b) in the plane and c along its normal [m].
      mound_yaw: (M,) heading of the a axis (its xy projection's angle) [rad].
    """

    slope: jnp.ndarray
    mound_centres: jnp.ndarray
    mound_axes: jnp.ndarray
    mound_yaw: jnp.ndarray


class Forest3D(NamedTuple):
    """Ground truth of a leaning-trunk forest.

    Attributes:
      base: (N, 3) where each trunk's axis meets the ground [m].
      axis: (N, 3) unit axis directions, z > 0.
      radii: (N,) trunk radii r = DBH / 2, perpendicular to the axis [m].
      terrain: ``Terrain``. clutter: bushes and logs (``sims.forest.Clutter``; xy only, they
        are set on the ground).
    """

    base: jnp.ndarray
    axis: jnp.ndarray
    radii: jnp.ndarray
    terrain: Terrain
    clutter: Clutter


class World3D(NamedTuple):
    """An MJX leaning-trunk forest and its truth (a pytree; ``jit``-friendly).

    Attributes:
      world: the ``sims.forest.World`` (model, culling slots, ``centres`` (N, 2) = the
        breast-height xy, ``radii`` (N,), ``sensor_height`` = ``mount_height``).
      terrain: ``Terrain``: the sensor rides ``mount_height`` above g(x, y).
      mount_height: () sensor height above the ground under it [m].
      breast: (N, 3) breast-height points [m]. base, axis: (N, 3) as in ``Forest3D``.
    """

    world: World
    terrain: Terrain
    mount_height: jnp.ndarray
    breast: jnp.ndarray
    base: jnp.ndarray
    axis: jnp.ndarray


def flat_terrain() -> Terrain:
    """Level ground (z = 0), no mounds."""
    return Terrain(jnp.zeros(2), jnp.zeros((0, 2)), jnp.zeros((0, 3)), jnp.zeros((0,)))


def plane_normal(slope):
    """(3,) upward unit normal (-s_x, -s_y, 1) / |.| of the plane z = s . (x, y)."""
    slope = jnp.asarray(slope)
    n = jnp.concatenate([-slope, jnp.ones(1, slope.dtype)])
    return n / jnp.linalg.norm(n)


def mound_frames(terrain: Terrain):
    """(M, 3, 3) rotations whose columns are each mound's a, b and c axes in the world.

    a = the in-plane direction above heading ``mound_yaw`` (xy (cos, sin), rising with the
    plane), c = the plane normal, b = c x a.
    """
    yaw = terrain.mound_yaw
    s = terrain.slope
    a = jnp.stack([jnp.cos(yaw), jnp.sin(yaw), s[0] * jnp.cos(yaw) + s[1] * jnp.sin(yaw)], -1)
    a = a / jnp.linalg.norm(a, axis=-1, keepdims=True)
    c = jnp.broadcast_to(plane_normal(s), a.shape)
    b = jnp.cross(c, a)
    return jnp.stack([a, b, c], -1)


def mound_tops(terrain: Terrain, xy):
    """(..., M) height of each mound's upper surface above xy (..., 2); -inf off the mound.

    Vertical line p(z) = (x, y, z) in the mound frame (R, centre q, semi-axes s):
    l(z) = A + z B with A = R^T ((x, y, 0) - q) / s, B = R^T e_z / s; |l|^2 = 1 gives
    z = (-A.B + sqrt((A.B)^2 - |B|^2 (|A|^2 - 1))) / |B|^2, the upper root.
    """
    xy = jnp.asarray(xy)
    flat = xy.reshape(-1, 1, 2)  # (Q, 1, 2)
    frames = mound_frames(terrain)  # (M, 3, 3)
    centres = terrain.mound_centres
    q = jnp.concatenate([centres, (centres @ terrain.slope)[:, None]], -1)[None]  # (1, M, 3)
    offset = jnp.concatenate([flat - q[..., :2], jnp.broadcast_to(
        -q[..., 2:], (flat.shape[0],) + q.shape[1:2] + (1,))], -1)  # (Q, M, 3)
    a = jnp.einsum("mij,qmi->qmj", frames, offset) / terrain.mound_axes[None]
    b = frames[:, 2, :] / terrain.mound_axes  # row z of R = R^T e_z, (M, 3)
    ab = jnp.sum(a * b[None], -1)
    bb = jnp.sum(b * b, -1)[None]
    disc = ab * ab - bb * (jnp.sum(a * a, -1) - 1.0)
    top = (-ab + jnp.sqrt(jnp.maximum(disc, 0.0))) / bb
    top = jnp.where(disc >= 0.0, top, -jnp.inf)
    return top.reshape(xy.shape[:-1] + (centres.shape[0],))


def ground_height(terrain: Terrain, xy):
    """(...,) ground height g(x, y) = max(plane, mound tops) at xy (..., 2) [m]."""
    xy = jnp.asarray(xy)
    plane = xy @ jnp.asarray(terrain.slope, xy.dtype)
    if terrain.mound_centres.shape[0] == 0:
        return plane
    return jnp.maximum(plane, jnp.max(mound_tops(terrain, xy), axis=-1))


def lean_axes(lean, azimuth):
    """(N, 3) unit axes leaning ``lean`` (N,) [rad] from the vertical toward ``azimuth`` (N,)."""
    return jnp.stack([jnp.sin(lean) * jnp.cos(azimuth), jnp.sin(lean) * jnp.sin(azimuth),
                      jnp.cos(lean)], -1)


def breast_height_points(base, axis, breast_height: float = BREAST_HEIGHT):
    """(N, 3) points of the axes ``breast_height`` [m] vertically above the bases (N, 3):
    base + axis * breast_height / axis_z."""
    return base + axis * (breast_height / axis[:, 2:3])


def sample_dbh(key, num_trees: int, dbh="lognormal") -> jnp.ndarray:
    """(N,) diameters at breast height [m].

    ``dbh``: "lognormal" (``sims.forest.sample_radii``: median 0.28 m, log-sd 0.35, clipped to
    0.10-0.70 m), "black_cherry" (``BLACK_CHERRY_DBH``, drawn with replacement), or an array
    of measured DBHs [m] drawn with replacement.
    """
    if isinstance(dbh, str):
        if dbh not in DBH_CHOICES:
            raise ValueError(f"sample_dbh dbh={dbh!r}; expected one of {list(DBH_CHOICES)} or "
                             "an array of measured DBHs [m]")
        if dbh == "lognormal":
            return 2.0 * sample_radii(key, num_trees)
        dbh = BLACK_CHERRY_DBH
    table = jnp.asarray(dbh, jnp.float32).reshape(-1)
    if table.shape[0] == 0 or not bool(jnp.all((table > 0) & (table < 3.0))):
        raise ValueError("sample_dbh expects measured DBHs in metres, each in (0, 3)")
    return table[jax.random.randint(key, (num_trees,), 0, table.shape[0])]


def random_terrain(key, size=(40.0, 40.0), max_slope: float = 0.08, num_mounds: int = 6,
                   mound_width=(1.5, 4.0), mound_height=(0.15, 0.5)) -> Terrain:
    """A plane of gradient |s| ~ U(0, max_slope) in a uniform direction, and ``num_mounds``
    mounds centred uniformly in [0, sx] x [0, sy] with semi-axes a, b ~ U(mound_width) and
    c ~ U(mound_height) [m], heading uniform."""
    k_slope, k_dir, k_pos, k_axes, k_height, k_yaw = jax.random.split(key, 6)
    grade = jax.random.uniform(k_slope, (), maxval=max_slope)
    direction = jax.random.uniform(k_dir, (), maxval=2.0 * jnp.pi)
    slope = grade * jnp.stack([jnp.cos(direction), jnp.sin(direction)])
    centres = jax.random.uniform(k_pos, (num_mounds, 2)) * jnp.asarray(size, jnp.float32)[None]
    widths = jax.random.uniform(k_axes, (num_mounds, 2), minval=mound_width[0],
                                maxval=mound_width[1])
    heights = jax.random.uniform(k_height, (num_mounds, 1), minval=mound_height[0],
                                 maxval=mound_height[1])
    yaw = jax.random.uniform(k_yaw, (num_mounds,), maxval=jnp.pi)
    return Terrain(slope, centres, jnp.concatenate([widths, heights], -1), yaw)


def random_forest_3d(key, num_trees: int, size=(40.0, 40.0), min_spacing: float = 2.5, *,
                     lean_deg=(2.0, 15.0), dbh="lognormal", terrain: Terrain | None = None,
                     max_slope: float = 0.08, num_mounds: int = 6, num_bushes: int = 0,
                     num_logs: int = 0, keep_clear=None, clearance: float = 1.5) -> Forest3D:
    """Leaning trees uniformly at random in [0, sx] x [0, sy] on uneven ground.

    Bases are ``min_spacing`` apart (Poisson-disc darts, as ``sims.forest.random_forest``) and
    ``clearance`` m from ``keep_clear`` (Q, 2) points; leans ~ U(lean_deg) [degrees] toward a
    uniform azimuth; DBH by ``sample_dbh(dbh)``; terrain ``random_terrain(max_slope,
    num_mounds)`` unless given; bushes and logs by ``sims.forest.random_clutter``. The same
    key gives the same forest.

    Raises ValueError when the area cannot hold ``num_trees`` at ``min_spacing``.
    """
    k_pos, k_lean, k_az, k_dbh, k_ground, k_clutter = jax.random.split(key, 6)
    size = jnp.asarray(size, jnp.float32)
    if keep_clear is not None:
        keep_clear = jnp.asarray(keep_clear, jnp.float32)[:, :2]
    xy, placed = poisson_disc(k_pos, num_trees, jnp.zeros(2), size, min_spacing, keep_clear,
                              clearance)
    placed = int(placed)
    if placed < num_trees:
        raise ValueError(
            f"random_forest_3d placed only {placed} of num_trees={num_trees} trees in a "
            f"{tuple(np.asarray(size))} m area with min_spacing={min_spacing} m; expected a "
            "larger area, fewer trees or a smaller spacing")
    if terrain is None:
        terrain = random_terrain(k_ground, size, max_slope, num_mounds)
    lean = jnp.deg2rad(jax.random.uniform(k_lean, (num_trees,), minval=lean_deg[0],
                                          maxval=lean_deg[1]))
    azimuth = jax.random.uniform(k_az, (num_trees,), minval=-jnp.pi, maxval=jnp.pi)
    base = jnp.concatenate([xy, ground_height(terrain, xy)[:, None]], -1)
    avoid = xy if keep_clear is None else jnp.concatenate([xy, keep_clear], 0)
    clutter = random_clutter(k_clutter, avoid, num_bushes, num_logs, jnp.zeros(2), size)
    return Forest3D(base, lean_axes(lean, azimuth), 0.5 * sample_dbh(k_dbh, num_trees, dbh),
                    terrain, clutter)


def _vec(v) -> str:
    return " ".join(f"{float(x):.6f}" for x in v)


def forest3d_mjcf(forest: Forest3D, trunk_length: float = 10.0, sink: float = 0.6,
                  sensor_height: float = 1.0) -> str:
    """MJCF text of a ``Forest3D`` (module docstring; geom order trunks, bushes, logs, mounds,
    plane). Trunks run from base - sink u to base + trunk_length u [m]; bushes stand with
    their centre 0.7 c above the ground there, logs with their axis 0.7 r above it."""
    static = 'contype="0" conaffinity="0"'
    base, axis = np.asarray(forest.base, float), np.asarray(forest.axis, float)
    lines = []
    for b, u, r in zip(base, axis, np.asarray(forest.radii, float)):
        lines.append(f'<geom type="capsule" size="{r:.6f}" fromto="{_vec(b - sink * u)} '
                     f'{_vec(b + trunk_length * u)}" material="bark" {static}/>')
    terrain, clutter = forest.terrain, forest.clutter
    bushes = np.asarray(clutter.bush_centres, float).reshape(-1, 2)
    if len(bushes):
        ground = np.asarray(ground_height(terrain, jnp.asarray(bushes, jnp.float32)), float)
        for (x, y), z, (a, b_, c) in zip(bushes, ground, np.asarray(clutter.bush_sizes, float)):
            lines.append(f'<geom type="ellipsoid" size="{a:.6f} {b_:.6f} {c:.6f}" '
                         f'pos="{x:.6f} {y:.6f} {z + 0.7 * c:.6f}" material="leaf" {static}/>')
    starts = np.asarray(clutter.log_starts, float).reshape(-1, 2)
    if len(starts):
        ends = np.asarray(clutter.log_ends, float).reshape(-1, 2)
        zs = np.asarray(ground_height(terrain, jnp.asarray(starts, jnp.float32)), float)
        ze = np.asarray(ground_height(terrain, jnp.asarray(ends, jnp.float32)), float)
        for s, e, z0, z1, r in zip(starts, ends, zs, ze, np.asarray(clutter.log_radii, float)):
            lines.append(f'<geom type="capsule" size="{r:.6f}" fromto="{s[0]:.6f} {s[1]:.6f} '
                         f'{z0 + 0.7 * r:.6f} {e[0]:.6f} {e[1]:.6f} {z1 + 0.7 * r:.6f}" '
                         f'material="bark" {static}/>')
    frames = np.asarray(mound_frames(terrain), float)
    slope = np.asarray(terrain.slope, float)
    for (x, y), axes, frame in zip(np.asarray(terrain.mound_centres, float),
                                   np.asarray(terrain.mound_axes, float), frames):
        z = slope[0] * x + slope[1] * y
        lines.append(f'<geom type="ellipsoid" size="{_vec(axes)}" pos="{x:.6f} {y:.6f} '
                     f'{z:.6f}" xyaxes="{_vec(frame[:, 0])} {_vec(frame[:, 1])}" '
                     f'material="soil" {static}/>')
    lines.append(f'<geom type="plane" size="0 0 1" zaxis="{_vec(plane_normal(slope))}" '
                 f'material="soil" {static}/>')
    return mjcf_document(lines, sensor_height)


def make_world_3d(forest: Forest3D, mount_height: float = 1.0, trunk_length: float = 10.0,
                  num_slots: int = 12, sink: float = 0.6) -> World3D:
    """The MJX model of ``forest`` for ``sims.scan3d.scan_3d``.

    Args:
      mount_height: sensor height above the ground under it [m] (a VLP-16 on a small
        forestry robot: about 1 m).
      trunk_length: trunk length above the base along its axis [m].
      num_slots: culling slots per lidar sector and geom type (``sims.lidar``); mounds and
        bushes share the ellipsoid slots, so more than ``make_world``'s 6 by default.
      sink: trunk length buried below the base [m]; keeps the rounded end underground on a
        slope (at least r sin(lean) + slope r + the mound slope under the trunk).
    """
    base = jnp.asarray(forest.base, jnp.float32)
    axis = jnp.asarray(forest.axis, jnp.float32)
    radii = jnp.asarray(forest.radii, jnp.float32)
    if base.ndim != 2 or base.shape[1] != 3 or axis.shape != base.shape or radii.shape != (
            base.shape[0],):
        raise ValueError(f"make_world_3d expects base (N, 3), axis (N, 3) and radii (N,); got "
                         f"{base.shape}, {axis.shape} and {radii.shape}")
    if radii.shape[0] and (float(jnp.min(radii)) <= 0.0 or float(jnp.min(axis[:, 2])) <= 0.1):
        raise ValueError("make_world_3d expects positive radii and axes leaning less than "
                         "84 degrees (axis z > 0.1)")
    mj_model = mujoco.MjModel.from_xml_string(forest3d_mjcf(forest, trunk_length, sink,
                                                            mount_height))
    model, data = _put(mj_model)
    geom_tree = np.full(mj_model.ngeom, -1, np.int32)
    geom_tree[:base.shape[0]] = np.arange(base.shape[0])
    geom_types = sorted(set(int(t) for t in mj_model.geom_type))
    slot_model, slot_data = _put(mujoco.MjModel.from_xml_string(_slot_mjcf(geom_types,
                                                                           num_slots)))
    breast = breast_height_points(base, axis)
    world = World(model, data, slot_model, slot_data, breast[:, :2], radii,
                  jnp.asarray(geom_tree), jnp.asarray(_geom_bounds(mj_model), jnp.float32),
                  jnp.asarray(mount_height, jnp.float32))
    terrain = jax.tree.map(lambda v: jnp.asarray(v, jnp.float32), forest.terrain)
    return World3D(world, terrain, jnp.asarray(mount_height, jnp.float32), breast, base, axis)
