"""Forest layouts, their MJCF models and ground truth.

A forest is a table of trunks (centres (N, 2), radii (N,)) plus optional clutter that trunk
detection must reject: bushes (ellipsoids) and fallen logs (horizontal capsules). ``make_world``
turns it into an MJX model whose trunks are vertical capsules (``mjx.ray`` does not hit
cylinders; a vertical capsule cut by a horizontal beam is a circle of the trunk radius), with a
``<material>`` (``mjx.ray`` crashes without one), static geoms that never collide
(``contype="0" conaffinity="0"``) and one slide-joint sensor body so ``mjx.forward`` has a
degree of freedom.

Layout generators take a key first and return ``Forest``. ``random_forest`` and clutter run
eagerly (they check the count placed); ``sample_forest`` (its trunks), ``poisson_disc`` and
``plantation_forest`` without clutter are pure functions of the key, for ``jit`` and ``vmap``.
"""
from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from sims.mujoco_loader import mjx, mujoco  # imported when first used

# Diameter at breast height: a right-skewed log-normal (median 0.28 m, log-sd 0.35), typical of
# managed conifer / rubber stands, clipped to [0.10, 0.70] m.
DBH_MEDIAN = 0.28
DBH_LOG_SD = 0.35
DBH_MIN, DBH_MAX = 0.10, 0.70


class Clutter(NamedTuple):
    """Non-trunk objects. Bushes: ellipsoids; logs: horizontal capsules lying on the ground.

    Attributes:
      bush_centres: (Nb, 2) xy centre [m].
      bush_sizes: (Nb, 3) semi-axes (a, b, c) [m]; the ellipsoid centre sits at height c * 0.7.
      log_starts, log_ends: (Nl, 2) xy end points of each log's axis [m].
      log_radii: (Nl,) log radius [m]; the axis lies at height ``log_height``.
    """

    bush_centres: jnp.ndarray
    bush_sizes: jnp.ndarray
    log_starts: jnp.ndarray
    log_ends: jnp.ndarray
    log_radii: jnp.ndarray


class Forest(NamedTuple):
    """Ground truth of a forest: trunks (N,) and clutter."""

    centres: jnp.ndarray
    radii: jnp.ndarray
    clutter: Clutter


class World(NamedTuple):
    """An MJX forest ready for ``mjx.ray`` plus its ground truth (a pytree; ``jit``-friendly).

    Attributes:
      model, data: the full MJX model (every geom) after ``mjx.forward``.
      slot_model, slot_data: a small model with ``num_slots`` geoms of each geom type present,
        refilled per lidar sector with the nearest geoms (culling, see ``sims.lidar``).
      centres: (N, 2) true trunk centres [m]; radii: (N,) true trunk radii [m].
      geom_tree: (G,) tree index of each geom of ``model``, -1 for clutter and ground.
      geom_bound: (G,) horizontal bounding radius of each geom about its xy position [m].
      sensor_height: () height of the 2D scan plane [m].
    """

    model: mjx.Model
    data: mjx.Data
    slot_model: mjx.Model
    slot_data: mjx.Data
    centres: jnp.ndarray
    radii: jnp.ndarray
    geom_tree: jnp.ndarray
    geom_bound: jnp.ndarray
    sensor_height: jnp.ndarray


def empty_clutter() -> Clutter:
    """No bushes, no logs."""
    return Clutter(jnp.zeros((0, 2)), jnp.zeros((0, 3)), jnp.zeros((0, 2)), jnp.zeros((0, 2)),
                   jnp.zeros((0,)))


def sample_radii(key, num_trees: int) -> jnp.ndarray:
    """Trunk radii (N,) [m]: DBH ~ LogNormal(log 0.28, 0.35) clipped to [0.10, 0.70] m, r = DBH/2."""
    dbh = DBH_MEDIAN * jnp.exp(DBH_LOG_SD * jax.random.normal(key, (num_trees,)))
    return 0.5 * jnp.clip(dbh, DBH_MIN, DBH_MAX)


def _candidates(key, num_points: int, low, high):
    """(30 * num_points + 50, 2) darts uniform in the box [low, high) (default float type)."""
    return jax.random.uniform(key, (30 * num_points + 50, 2), minval=low, maxval=high)


@functools.partial(jax.jit, static_argnums=1)
def poisson_disc(key, num_points: int, low, high, min_spacing: float, keep_clear=None,
                 clear_dist: float = 0.0):
    """Dart throwing, a pure function of ``key`` (``jit`` and ``vmap`` friendly).

    Candidates c (C = 30 N + 50 of them, uniform in the box, from ``key``) are taken in order;
    c is accepted when fewer than N = ``num_points`` are placed, ||c - q|| >= ``clear_dist``
    for every row q of ``keep_clear`` (Q, 2), and ||c - p|| >= ``min_spacing`` for every
    accepted p. A ``lax.scan`` over the candidates carries (points (N, 2), count ()), so the
    shapes are static and a short count is returned, never raised. Distances are in the
    candidates' float type (float32, float64 under x64): in float32 only a distance within
    about 1e-6 relative of its threshold could be decided otherwise than in float64.

    Args:
      low, high: (2,) box corners [m]; keep_clear: (Q, 2) points to keep ``clear_dist`` from.
    Returns:
      (points (N, 2) float32, unfilled rows zero; placed () int32, the number accepted).
    """
    candidates = _candidates(key, num_points, low, high)
    clear = jnp.ones(candidates.shape[0], bool)
    if keep_clear is not None and keep_clear.shape[0] > 0:
        clear = jnp.min(_squared_distances(candidates, keep_clear), axis=1) >= jnp.square(
            clear_dist)
    rows = jnp.arange(num_points)
    spacing_sq = jnp.square(jnp.asarray(min_spacing, candidates.dtype))

    def throw(carry, dart):
        points, count = carry
        candidate, is_clear = dart
        far = (_squared_distances(candidate[None], points)[0] >= spacing_sq) | (rows >= count)
        accept = is_clear & jnp.all(far) & (count < num_points)
        points = jnp.where((accept & (rows == count))[:, None], candidate, points)
        return (points, count + accept.astype(jnp.int32)), None

    start = (jnp.zeros((num_points, 2), candidates.dtype), jnp.zeros((), jnp.int32))
    (points, placed), _ = jax.lax.scan(throw, start, (candidates, clear))
    return points.astype(jnp.float32), placed


def _squared_distances(a, b):
    """(A, B) squared distances between rows of a (A, 2) and b (B, 2), in a's float type.
    Per coordinate: a (A, B, 2) gap summed over its last axis runs many times slower on CPU."""
    b = jnp.asarray(b, a.dtype)
    dx = a[:, None, 0] - b[None, :, 0]
    dy = a[:, None, 1] - b[None, :, 1]
    return dx * dx + dy * dy


def random_forest(key, num_trees: int, size=(60.0, 60.0), min_spacing: float = 2.0,
                  num_bushes: int = 0, num_logs: int = 0, keep_clear=None,
                  clearance: float = 1.5) -> Forest:
    """Trees uniformly at random in [0, sx] x [0, sy] with a minimum trunk spacing (eager).

    ``keep_clear`` (Q, 2): points (e.g. a planned path) no trunk centre comes within
    ``clearance`` m of. Under ``jit``: ``sample_forest``.

    Raises ValueError when the area cannot hold ``num_trees`` at ``min_spacing``.
    """
    forest, placed = sample_forest(key, num_trees, size, min_spacing, keep_clear, clearance)
    if int(placed) < num_trees:
        raise ValueError(
            f"random_forest placed only {int(placed)} of num_trees={num_trees} trees in a "
            f"{tuple(np.asarray(size, np.float32))} m area with min_spacing={min_spacing} m; "
            "expected a larger area, fewer trees or a smaller spacing"
        )
    avoid = forest.centres
    if keep_clear is not None:
        avoid = jnp.concatenate([avoid, jnp.asarray(keep_clear, jnp.float32)[:, :2]], 0)
    clutter = random_clutter(jax.random.split(key, 3)[2], avoid, num_bushes, num_logs,
                             jnp.zeros(2), jnp.asarray(size, jnp.float32))
    return forest._replace(clutter=clutter)


def sample_forest(key, num_trees: int, size=(60.0, 60.0), min_spacing: float = 2.0,
                  keep_clear=None, clearance: float = 1.5):
    """``random_forest`` without clutter as a pure JAX function of ``key`` (``jit``, ``vmap``).

    Same key use as ``random_forest`` (trunk positions by ``poisson_disc``, radii by
    ``sample_radii``). Nothing is raised under ``jit``: the caller checks ``placed``.

    Returns:
      (Forest with centres (N, 2) (rows >= placed are zero) and radii (N,), placed () int32).
    """
    key_pos, key_rad, _ = jax.random.split(key, 3)
    keep = None if keep_clear is None else jnp.asarray(keep_clear, jnp.float32)[:, :2]
    centres, placed = poisson_disc(key_pos, num_trees, jnp.zeros(2),
                                   jnp.asarray(size, jnp.float32), min_spacing, keep, clearance)
    return Forest(centres, sample_radii(key_rad, num_trees), empty_clutter()), placed


def plantation_forest(key, num_rows: int = 8, trees_per_row: int = 20,
                      row_spacing: float = 7.0, tree_spacing: float = 3.0,
                      jitter: float = 0.15, num_bushes: int = 0, num_logs: int = 0) -> Forest:
    """Plantation rows (rubber plantation: about 3 m along a row, 7 m between rows).

    Rows run along x; row j sits at y = j * row_spacing; tree i of a row at x = i * tree_spacing;
    each position is jittered by N(0, jitter^2) per axis. N = num_rows * trees_per_row.
    """
    key_jit, key_rad, key_clutter = jax.random.split(key, 3)
    along, across = jnp.meshgrid(jnp.arange(trees_per_row) * tree_spacing,
                                 jnp.arange(num_rows) * row_spacing)
    grid = jnp.stack([along.ravel(), across.ravel()], axis=-1)
    centres = grid + jitter * jax.random.normal(key_jit, grid.shape)
    high = jnp.array([(trees_per_row - 1) * tree_spacing, (num_rows - 1) * row_spacing])
    clutter = random_clutter(key_clutter, centres, num_bushes, num_logs, jnp.zeros(2), high)
    return Forest(centres, sample_radii(key_rad, centres.shape[0]), clutter)


def random_clutter(key, centres, num_bushes: int, num_logs: int, low, high,
                   clearance: float = 1.8) -> Clutter:
    """Bushes (semi-axes 0.6-1.2 m wide, 0.5-0.9 m tall) and logs (2-6 m long, radius
    0.12-0.3 m) placed at least ``clearance`` m from every trunk centre."""
    if num_bushes == 0 and num_logs == 0:  # traceable: no count to read back
        return empty_clutter()
    key_b, key_bs, key_l, key_la, key_ll, key_lr = jax.random.split(key, 6)
    bushes, nb = poisson_disc(key_b, num_bushes, low, high, 2.5, centres, clearance)
    logs, nl = poisson_disc(key_l, num_logs, low, high, 4.0, centres, clearance + 1.5)
    nb, nl = int(nb), int(nl)
    bushes, logs = bushes[:nb], logs[:nl]
    widths = jax.random.uniform(key_bs, (nb, 2), minval=0.6, maxval=1.2)
    heights = jax.random.uniform(key_bs, (nb, 1), minval=0.5, maxval=0.9)
    heading = jax.random.uniform(key_la, (nl,), minval=0.0, maxval=jnp.pi)
    half_length = 0.5 * jax.random.uniform(key_ll, (nl,), minval=2.0, maxval=6.0)
    # Shorten logs so they stay clear of trunks: clearance + 1.5 m around the log centre.
    half_length = jnp.minimum(half_length, clearance + 1.0)
    axis = jnp.stack([jnp.cos(heading), jnp.sin(heading)], -1) * half_length[:, None]
    radii = jax.random.uniform(key_lr, (nl,), minval=0.12, maxval=0.3)
    return Clutter(bushes, jnp.concatenate([widths, heights], -1), logs - axis, logs + axis, radii)


def forest_mjcf(forest: Forest, trunk_height: float = 6.0, sensor_height: float = 0.5,
                ground: bool = True, trunk_axes=None, trunk_heading=None) -> str:
    """MJCF text of a forest: capsule trunks standing on z = 0, bushes, logs, ground plane.

    Non-circular trunks: with ``trunk_axes`` (N, 2) (cross-section semi-axes [m] at the scan
    height) and ``trunk_heading`` (N,) (rotation of the first axis about z [rad]) the trunks
    are vertical ellipsoids of half-height trunk_height / 2 centred at that height, scaled so
    the horizontal cut at ``sensor_height`` is exactly that ellipse.

    Geom order (relied on by ``World.geom_tree``): trunks 0..N-1, bushes, logs, then the
    ground plane. Logs lie with their axis at ``sensor_height`` - 0.3 * radius so a planar scan
    at ``sensor_height`` hits them. The sensor body (slide joint along z, no geom) is last.
    """
    centres, radii = np.asarray(forest.centres, float), np.asarray(forest.radii, float)
    clutter = forest.clutter
    half = 0.5 * trunk_height
    lines = ['<mujoco model="forest">', "<asset>",
             '<material name="bark" rgba="0.45 0.3 0.2 1"/>',
             '<material name="leaf" rgba="0.2 0.5 0.2 1"/>',
             '<material name="soil" rgba="0.4 0.35 0.3 1"/>', "</asset>", "<worldbody>"]
    static = 'contype="0" conaffinity="0"'
    if trunk_axes is None:
        for (x, y), r in zip(centres, radii):
            lines.append(f'<geom type="capsule" size="{r:.6f} {half - r:.6f}" '
                         f'pos="{x:.6f} {y:.6f} {half:.6f}" material="bark" {static}/>')
    else:
        axes = np.asarray(trunk_axes, float)
        heading = (np.zeros(len(centres)) if trunk_heading is None
                   else np.asarray(trunk_heading, float))
        # Cut of an ellipsoid (a, b, c) centred at height c by the plane z = h:
        # semi-axes (a, b) * sqrt(1 - ((h - c) / c)^2).
        shrink = np.sqrt(1.0 - ((sensor_height - half) / half) ** 2)
        for (x, y), (a, b), yaw in zip(centres, axes / shrink, heading):
            lines.append(f'<geom type="ellipsoid" size="{a:.6f} {b:.6f} {half:.6f}" '
                         f'pos="{x:.6f} {y:.6f} {half:.6f}" euler="0 0 {np.degrees(yaw):.6f}" '  # MJCF: degrees
                         f'material="bark" {static}/>')
    for (x, y), (a, b, c) in zip(np.asarray(clutter.bush_centres, float),
                                 np.asarray(clutter.bush_sizes, float)):
        lines.append(f'<geom type="ellipsoid" size="{a:.6f} {b:.6f} {c:.6f}" '
                     f'pos="{x:.6f} {y:.6f} {0.7 * c:.6f}" material="leaf" {static}/>')
    for s, e, r in zip(np.asarray(clutter.log_starts, float), np.asarray(clutter.log_ends, float),
                       np.asarray(clutter.log_radii, float)):
        z = sensor_height - 0.3 * r
        lines.append(f'<geom type="capsule" size="{r:.6f}" fromto="{s[0]:.6f} {s[1]:.6f} {z:.6f} '
                     f'{e[0]:.6f} {e[1]:.6f} {z:.6f}" material="bark" {static}/>')
    if ground:
        lines.append(f'<geom type="plane" size="0 0 1" material="soil" {static}/>')
    lines += [f'<body name="sensor" pos="0 0 {sensor_height}">',
              '<joint name="lift" type="slide" axis="0 0 1"/>',
              '<inertial mass="1" pos="0 0 0" diaginertia="0.01 0.01 0.01"/>',
              "</body>", "</worldbody>", "</mujoco>"]
    return "\n".join(lines)


def _slot_mjcf(geom_types: list[int], num_slots: int) -> str:
    """A model with ``num_slots`` placeholder geoms per type (filled per scan by culling)."""
    names = {int(mujoco.mjtGeom.mjGEOM_CAPSULE): 'type="capsule" size="0.1 0.1"',
             int(mujoco.mjtGeom.mjGEOM_ELLIPSOID): 'type="ellipsoid" size="0.1 0.1 0.1"',
             int(mujoco.mjtGeom.mjGEOM_PLANE): 'type="plane" size="0 0 1"'}
    lines = ['<mujoco model="slots">', '<asset><material name="m" rgba="1 1 1 1"/></asset>',
             "<worldbody>"]
    for geom_type in geom_types:
        count = 1 if geom_type == int(mujoco.mjtGeom.mjGEOM_PLANE) else num_slots
        lines += [f'<geom {names[geom_type]} pos="0 0 -1000" material="m" '
                  'contype="0" conaffinity="0"/>'] * count
    lines += ['<body name="sensor"><joint type="slide" axis="0 0 1"/>',
              '<inertial mass="1" pos="0 0 0" diaginertia="0.01 0.01 0.01"/></body>',
              "</worldbody></mujoco>"]
    return "\n".join(lines)


def _geom_bounds(mj_model) -> np.ndarray:
    """(G,) horizontal bounding radius about each geom's xy position (plane: 0, never culled)."""
    size = mj_model.geom_size
    geom_type = mj_model.geom_type
    capsule = geom_type == mujoco.mjtGeom.mjGEOM_CAPSULE
    # Capsule axis is local z; its horizontal extent is half_length * |horizontal part|.
    quat = mj_model.geom_quat
    axis_z = 1.0 - 2.0 * (quat[:, 1] ** 2 + quat[:, 2] ** 2)  # z of the rotated local z axis
    sin_tilt = np.sqrt(np.clip(1.0 - axis_z ** 2, 0.0, 1.0))
    capsule_bound = size[:, 0] + size[:, 1] * sin_tilt
    bound = np.where(capsule, capsule_bound, size.max(axis=-1))
    return np.where(geom_type == mujoco.mjtGeom.mjGEOM_PLANE, 0.0, bound)


def _put(mj_model):
    """MJX model and data after a forward pass. The CPU ``mj_forward`` gives the same geom
    poses as ``mjx.forward`` but avoids seconds of eager JAX dispatch."""
    mj_data = mujoco.MjData(mj_model)
    mujoco.mj_forward(mj_model, mj_data)
    return mjx.put_model(mj_model), mjx.put_data(mj_model, mj_data)


def make_world(centres, radii, clutter: Clutter | None = None, trunk_height: float = 6.0,
               sensor_height: float = 0.5, num_slots: int = 6, ground: bool = True,
               trunk_axes=None, trunk_heading=None) -> World:
    """Build the MJX forest for trunks ``centres`` (N, 2) [m] and ``radii`` (N,) [m].

    Args:
      clutter: optional bushes and logs (``random_clutter``).
      trunk_height: capsule trunk height [m] (the trunk is a cylinder from 0 to
        trunk_height - 2 r with rounded caps).
      sensor_height: height of the 2D scan plane [m].
      num_slots: culling slots per lidar sector and geom type (see ``sims.lidar``).
      ground: add a ground plane (hit only by downward 3D beams).
      trunk_axes, trunk_heading: non-circular trunks as ellipsoids (see ``forest_mjcf``);
        ``radii`` stays the ground-truth radius (e.g. the mean of the two semi-axes).
    """
    centres = jnp.asarray(centres, jnp.float32)
    radii = jnp.asarray(radii, jnp.float32)
    if centres.ndim != 2 or centres.shape[1] != 2 or radii.shape != centres.shape[:1]:
        raise ValueError(f"make_world expects centres (N, 2) and radii (N,); got "
                         f"{centres.shape} and {radii.shape}")
    if radii.shape[0] and float(jnp.min(radii)) <= 0.0:
        raise ValueError("make_world expects positive trunk radii")
    if float(trunk_height) <= 2.0 * float(jnp.max(radii, initial=0.0)) + sensor_height:
        raise ValueError(f"trunk_height={trunk_height} is too low for sensor_height="
                         f"{sensor_height}; expected > sensor_height + 2 * max radius")
    clutter = empty_clutter() if clutter is None else clutter
    forest = Forest(centres, radii, clutter)
    mj_model = mujoco.MjModel.from_xml_string(forest_mjcf(forest, trunk_height, sensor_height,
                                                          ground, trunk_axes, trunk_heading))
    model, data = _put(mj_model)
    num_geoms = mj_model.ngeom
    geom_tree = np.full(num_geoms, -1, np.int32)
    geom_tree[:centres.shape[0]] = np.arange(centres.shape[0])
    geom_types = sorted(set(int(t) for t in mj_model.geom_type))
    slot_mj = mujoco.MjModel.from_xml_string(_slot_mjcf(geom_types, num_slots))
    slot_model, slot_data = _put(slot_mj)
    return World(model, data, slot_model, slot_data, centres, radii, jnp.asarray(geom_tree),
                 jnp.asarray(_geom_bounds(mj_model), jnp.float32),
                 jnp.asarray(sensor_height, jnp.float32))


def world_from_forest(forest: Forest, **kwargs) -> World:
    """``make_world(forest.centres, forest.radii, forest.clutter, **kwargs)``."""
    return make_world(forest.centres, forest.radii, forest.clutter, **kwargs)


def mj_model_of(forest: Forest, trunk_height: float = 6.0, sensor_height: float = 0.5,
                ground: bool = True):
    """The CPU ``mujoco.MjModel`` of a forest (same geoms and order as ``make_world``)."""
    return mujoco.MjModel.from_xml_string(forest_mjcf(forest, trunk_height, sensor_height,
                                                      ground))


def mjcf_document(geom_lines: list[str], sensor_height: float = 0.5) -> str:
    """An MJCF model around ``geom_lines`` (``<geom .../>`` strings of the worldbody): the
    materials of ``forest_mjcf`` (bark, leaf, soil; ``mjx.ray`` crashes without one) and its
    sensor body (slide joint along z, no geom: the degree of freedom ``mjx.forward`` needs)
    at ``sensor_height`` [m], after the geoms. Used by ``sims.forest3d``."""
    lines = ['<mujoco model="forest">', "<asset>",
             '<material name="bark" rgba="0.45 0.3 0.2 1"/>',
             '<material name="leaf" rgba="0.2 0.5 0.2 1"/>',
             '<material name="soil" rgba="0.4 0.35 0.3 1"/>', "</asset>", "<worldbody>"]
    lines += list(geom_lines)
    lines += [f'<body name="sensor" pos="0 0 {sensor_height}">',
              '<joint name="lift" type="slide" axis="0 0 1"/>',
              '<inertial mass="1" pos="0 0 0" diaginertia="0.01 0.01 0.01"/>',
              "</body>", "</worldbody>", "</mujoco>"]
    return "\n".join(lines)


def trunk_template(num_trees: int, trunk_height: float = 6.0, sensor_height: float = 0.5,
                   num_slots: int = 6, ground: bool = True) -> World:
    """A ``make_world`` of ``num_trees`` placeholder capsule trunks (no clutter), built once
    (eagerly) and refilled per run by ``world_with_trunks``: its geoms are those
    ``world_from_forest`` builds for any clutter-free forest of ``num_trees`` trunks (trunks
    0..N-1, then the ground plane), so only the trunk rows of the arrays differ.

    The placeholders stand on a 10 m grid with radius 0.1 m (the values never reach a scan:
    ``world_with_trunks`` replaces every trunk row).
    """
    if num_trees < 1:
        raise ValueError(f"trunk_template num_trees={num_trees}; expected >= 1")
    side = int(np.ceil(np.sqrt(num_trees)))
    index = np.arange(num_trees)
    centres = 10.0 * np.stack([index % side, index // side], -1).astype(np.float32)
    return make_world(centres, np.full(num_trees, 0.1, np.float32), trunk_height=trunk_height,
                      sensor_height=sensor_height, num_slots=num_slots, ground=ground)


def world_with_trunks(template: World, centres, radii) -> World:
    """``template`` (``trunk_template``) with its N capsule trunks moved to ``centres``
    (N, 2) [m] with ``radii`` (N,) [m]: a pure function (``jit``, ``vmap`` over runs).

    A vertical capsule trunk n of a forest of trunk height h is (``forest_mjcf``): geom
    position = geom xpos = (x_n, y_n, h/2), identity orientation, size = (r_n, h/2 - r_n, 0),
    horizontal bound r_n (``_geom_bounds``). The template's trunk rows of the model
    (geom_pos, geom_size), the data (geom_xpos; geom_xmat stays identity: the trunks are
    static world geoms, so no ``mjx.forward`` is needed), ``geom_bound``, ``centres`` and
    ``radii`` are replaced; h/2 is read from the template's trunk heights. Every other geom
    (the ground plane) and the slot model are the template's. The result scans as
    ``world_from_forest(Forest(centres, radii, empty_clutter()))`` of the same trunk height
    (the MJCF route rounds positions and sizes to 1e-6 m).

    Radii must be positive and below h/2 (not checked under ``jit``).
    """
    num = template.centres.shape[0]
    centres = jnp.asarray(centres, template.data.geom_xpos.dtype)
    radii = jnp.asarray(radii, template.model.geom_size.dtype)
    if centres.shape != (num, 2) or radii.shape != (num,):
        raise ValueError(f"world_with_trunks: the template has {num} trunks; got centres "
                         f"{centres.shape} and radii {radii.shape}, expected ({num}, 2) and "
                         f"({num},)")
    types = np.asarray(template.model.geom_type)[:num]  # static under jit
    if not np.all(types == mujoco.mjtGeom.mjGEOM_CAPSULE):
        raise ValueError("world_with_trunks expects a template of capsule trunks "
                         "(trunk_template); got geom types " + str(sorted(set(types.tolist()))))
    half = template.data.geom_xpos[:num, 2]
    xpos = jnp.concatenate([centres, half[:, None]], -1)
    size = jnp.stack([radii, half - radii, jnp.zeros_like(radii)], -1)
    model = template.model.replace(
        geom_pos=template.model.geom_pos.at[:num].set(xpos.astype(template.model.geom_pos.dtype)),
        geom_size=template.model.geom_size.at[:num].set(size))
    data = template.data.replace(geom_xpos=template.data.geom_xpos.at[:num].set(xpos))
    bound = template.geom_bound.at[:num].set(radii.astype(template.geom_bound.dtype))
    return template._replace(model=model, data=data, centres=centres.astype(jnp.float32),
                             radii=radii.astype(jnp.float32), geom_bound=bound)
