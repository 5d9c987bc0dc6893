"""3D point clouds of a multi-layer lidar (a VLP-16 by default) from an MJX forest.

``scan_3d`` casts L layers x B beams with ``mjx.ray`` (``sims.lidar.scan_3d``: culled per
azimuth sector, so the cost does not grow with the forest) and returns the returns as points
in the sensor frame, what ``jaxslam.detect3d.fit_trunks_3d`` and a ROS PointCloud2 carry.

Beam (l, b): azimuth a_b = ``sims.lidar.beam_angles(B)[b]`` (from -pi in steps of 2 pi / B),
elevation e_l = ``sims.lidar.layer_elevations(L, *elevation_deg)[l]`` (a VLP-16: 16 layers
from -15 to +15 degrees, 2 degrees apart; 1800 beams = 0.2 degrees, its 10 Hz resolution).
Direction in the sensor frame d = (cos e cos a, cos e sin a, sin e); a return at range r is
the point r d, row-major over (l, b): point index l B + b.

Sensor frame: origin at the sensor, x along the heading theta, z up (the sensor is levelled,
as ``jaxslam.detect3d`` expects: on a slope a robot's IMU-levelled or gimballed lidar; a tilted
sensor would show every trunk leaning by the tilt). The sensor's world position is
(x, y, g(x, y) + ``mount_height``) on a ``sims.forest3d.World3D`` and
(x, y, ``sensor_height``) on a flat ``sims.forest.World``.

Range noise (with ``key``): ``sims.lidar.add_range_noise``, std = c_dist r + c_const along
each beam; the default (0, 0.015) m reads the VLP-16 datasheet's "+-3 cm typical" accuracy
as two standard deviations.
"""
from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from sims.forest3d import World3D, ground_height
from sims.lidar import beam_angles, layer_elevations
from sims.lidar import scan_3d as _scan_ranges

VLP16_RANGE_NOISE = (0.0, 0.015)  # (per metre, constant) [m/m, m]


class Cloud(NamedTuple):
    """One 3D scan.

    Attributes:
      points: (L B, 3) returns in the sensor frame [m] (zeros where not ``valid``).
      valid: (L B,) bool, a return within ``max_range``.
      ranges: (L, B) ranges along the beams [m] (``max_range`` = no return).
      geom: (L, B) int32 hit geom of the MJX model (-1: none).
      complete: () bool, no in-range geom was culled (``sims.lidar.Scan``).
      origin: (3,) the sensor's world position [m].
    """

    points: jnp.ndarray
    valid: jnp.ndarray
    ranges: jnp.ndarray
    geom: jnp.ndarray
    complete: jnp.ndarray
    origin: jnp.ndarray


def beam_directions(num_layers: int = 16, num_beams: int = 1800,
                    elevation_deg=(-15.0, 15.0)) -> np.ndarray:
    """(L, B, 3) unit beam directions in the sensor frame (module docstring)."""
    azimuth = beam_angles(num_beams)[None, :]
    elevation = layer_elevations(num_layers, *elevation_deg)[:, None]
    return np.stack(np.broadcast_arrays(np.cos(elevation) * np.cos(azimuth),
                                        np.cos(elevation) * np.sin(azimuth),
                                        np.sin(elevation)), -1)


def sensor_origin(world, pose):
    """(3,) world position of the sensor at ``pose`` (x, y, theta) (module docstring)."""
    pose = jnp.asarray(pose)
    if isinstance(world, World3D):
        z = ground_height(world.terrain, pose[:2].astype(world.terrain.slope.dtype))
        z = z + world.mount_height
    else:
        z = world.sensor_height
    return jnp.stack([pose[0], pose[1], jnp.asarray(z, pose.dtype)])


@functools.partial(jax.jit, static_argnames=("num_beams", "max_range", "num_layers",
                                             "elevation_deg", "range_noise", "cull",
                                             "num_sectors"))
def scan_3d(world, pose, num_beams: int = 1800, max_range: float = 20.0, *,
            num_layers: int = 16, elevation_deg=(-15.0, 15.0), key=None,
            range_noise=VLP16_RANGE_NOISE, cull: bool = True, num_sectors: int = 48) -> Cloud:
    """Multi-layer lidar point cloud from ``pose`` (3,) = (x, y, theta) (module docstring).

    Args:
      world: a ``sims.forest3d.World3D`` (uneven ground: the sensor rides ``mount_height``
        above it) or a flat ``sims.forest.World``.
      num_beams: B azimuth steps over the full circle; num_layers: L; elevation_deg: (low,
        high) elevations of the lowest and highest layer [deg].
      max_range: [m] returns at or beyond it are no return.
      key: PRNG key of the range noise ``range_noise`` (c_dist, c_const); None: noise-free.
      cull, num_sectors: culling (``sims.lidar``); ``Cloud.complete`` says if it was exact.
    Returns:
      ``Cloud``: points (L B, 3), valid (L B,), ranges (L, B), geom (L, B), complete, origin.

    Jitted (the sizes and settings static); ``jax.vmap`` over poses (and keys) for a path.
    """
    pose = jnp.asarray(pose)
    origin = sensor_origin(world, pose)
    flat = world.world if isinstance(world, World3D) else world
    flat = flat._replace(sensor_height=origin[2].astype(flat.sensor_height.dtype))
    scan = _scan_ranges(flat, pose, num_beams, max_range, num_layers=num_layers,
                        elevation_deg=tuple(elevation_deg), key=key, range_noise=range_noise,
                        cull=cull, num_sectors=num_sectors)
    directions = jnp.asarray(beam_directions(num_layers, num_beams, elevation_deg),
                             scan.ranges.dtype)
    valid = scan.ranges < max_range
    points = jnp.where(valid[..., None], scan.ranges[..., None] * directions, 0.0)
    return Cloud(points.reshape(-1, 3), valid.reshape(-1), scan.ranges, scan.geom,
                 scan.complete, origin)
