"""Lidar scans of an MJX forest with ``mjx.ray``: 2D planar and 3D multi-layer, with culling.

Encoding: a beam with no return within ``max_range`` reads exactly ``max_range``; every
return reads strictly less. Ranges are measured from the sensor origin (x, y, sensor_height).

Culling: ``mjx.ray`` tests every ray against every geom, so a full scan costs B * G ray-geom
tests. The culled scan splits the field of view into S angular sectors; for each sector it
keeps the ``num_slots`` geoms of each type whose horizontal footprint reaches into the sector
within ``max_range`` (nearest first), writes them into the fixed slots of ``World.slot_model``
and casts that sector's beams against those slots only: B * slots tests, independent of the
forest size. ``Scan.complete`` is False when some sector had more candidates than slots (then
a geom in range may have been culled; raise ``num_slots`` in ``make_world``).
"""
from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxslam.detect import clip_points_by_height
from jaxslam.geometry import wrap_angle
from sims.forest import World
from sims.mujoco_loader import mjx, mujoco  # imported when first used

# Geiser et al. 2023, Table 2: range std = 0.005 * distance + 0.0 [m].
TABLE2_RANGE_NOISE = (0.005, 0.0)
_PLANE = int(mujoco.mjtGeom.mjGEOM_PLANE)
_FAR = -1000.0  # parking height of unused slots: no beam reaches it


class Scan(NamedTuple):
    """One scan. ranges: (..., B) [m] (max_range = no return); geom: (..., B) int32 index of the
    hit geom in ``World.model`` (-1 = none); complete: () bool, no in-range geom was culled."""

    ranges: jnp.ndarray
    geom: jnp.ndarray
    complete: jnp.ndarray


def beam_angles(num_beams: int, fov: float = 2.0 * np.pi) -> np.ndarray:
    """(B,) beam bearings in the sensor frame [rad]: a full circle starts at -pi and steps
    2 pi / B; a narrower field of view spans [-fov/2, fov/2] inclusive."""
    if num_beams < 1:
        raise ValueError(f"num_beams={num_beams}; expected a positive integer")
    if fov >= 2.0 * np.pi - 1e-9:
        return -np.pi + 2.0 * np.pi * np.arange(num_beams) / num_beams
    if num_beams == 1:
        return np.zeros(1)
    return np.linspace(-0.5 * fov, 0.5 * fov, num_beams)


def _sectors(angles: np.ndarray, num_sectors: int):
    """Static sector layout: sector of each beam (B,), sector centre (S,) and half-width (S,)."""
    num_beams = angles.shape[0]
    num_sectors = max(1, min(num_sectors, num_beams))
    sector = (np.arange(num_beams) * num_sectors) // num_beams
    lo = np.array([angles[sector == s].min() for s in range(num_sectors)])
    hi = np.array([angles[sector == s].max() for s in range(num_sectors)])
    return sector, 0.5 * (lo + hi), 0.5 * (hi - lo)


def _select(world: World, geom_ids: np.ndarray, num_slots: int, pose, sector_centre,
            sector_half, max_range):
    """Nearest ``num_slots`` geoms (from ``geom_ids``) reaching into each sector within range.

    Returns (S, L) indices into ``geom_ids``, (S, L) bool usable, (S,) bool complete.
    """
    xy = world.data.geom_xpos[geom_ids, :2]
    bound = world.geom_bound[geom_ids]
    delta = xy - pose[None, :2]
    dist = jnp.hypot(delta[:, 0], delta[:, 1])
    near = dist - bound
    half_angle = jnp.where(dist > bound, jnp.arcsin(jnp.clip(bound / jnp.maximum(dist, 1e-9),
                                                             0.0, 1.0)), jnp.pi)
    bearing = jnp.arctan2(delta[:, 1], delta[:, 0]) - pose[2]
    offset = jnp.abs(wrap_angle(bearing[None, :] - sector_centre[:, None]))  # (S, G_t)
    hits = (offset <= half_angle[None, :] + sector_half[:, None] + 1e-4) & (
        near[None, :] <= max_range)
    score = jnp.where(hits, near[None, :], jnp.inf)
    k = min(num_slots, len(geom_ids))
    neg_score, index = jax.lax.top_k(-score, k)
    complete = jnp.sum(hits, axis=1) <= k
    return index, jnp.isfinite(neg_score), complete


def _slot_tables(world: World, pose, sector_centre, sector_half, max_range):
    """Per-sector geom slots: xpos (S, Gs, 3), xmat (S, Gs, 3, 3), size (S, Gs, 3),
    full-model geom id (S, Gs) (-1 unused) and complete ()."""
    full_types = np.asarray(world.model.geom_type)
    slot_types = np.asarray(world.slot_model.geom_type)
    num_sectors = sector_centre.shape[0]
    xpos, xmat, size, geom, complete = [], [], [], [], []
    for geom_type in sorted(set(slot_types.tolist())):
        geom_ids = np.nonzero(full_types == geom_type)[0]
        num_slots = int(np.sum(slot_types == geom_type))
        if geom_type == _PLANE:  # never culled: copy the plane(s) as they are
            index = np.broadcast_to(np.arange(num_slots), (num_sectors, num_slots))
            usable = jnp.ones((num_sectors, num_slots), bool)
        else:
            index, usable, ok = _select(world, geom_ids, num_slots, pose, sector_centre,
                                        sector_half, max_range)
            complete.append(ok)
            pad = num_slots - index.shape[1]
            index = jnp.pad(index, ((0, 0), (0, pad)))
            usable = jnp.pad(usable, ((0, 0), (0, pad)))
        ids = jnp.asarray(geom_ids)[index]
        pos = world.data.geom_xpos[ids]
        xpos.append(jnp.where(usable[..., None], pos, pos.at[..., 2].set(_FAR)))
        xmat.append(world.data.geom_xmat[ids])
        size.append(world.model.geom_size[ids])
        geom.append(jnp.where(usable, ids, -1))
    complete = jnp.all(jnp.stack([jnp.all(c) for c in complete])) if complete else jnp.asarray(True)
    return (jnp.concatenate(xpos, 1), jnp.concatenate(xmat, 1), jnp.concatenate(size, 1),
            jnp.concatenate(geom, 1), complete)


def _ray_full(world: World, origin, vec):
    """mjx.ray against every geom of the full model: distance (-1 = none) and geom id."""
    return mjx.ray(world.model, world.data, origin, vec)


def cast_rays(world: World, pose, directions, sector, sector_centre, sector_half, max_range,
              cull: bool) -> Scan:
    """Cast rays from the sensor at ``pose`` (3,) along world ``directions`` (B, 3).

    ``sector`` (B,) static sector of each ray; the sector arrays are in the sensor frame.
    """
    origin = jnp.stack([pose[0], pose[1], world.sensor_height]).astype(
        world.data.geom_xpos.dtype)
    directions = directions.astype(origin.dtype)
    if cull:
        xpos, xmat, size, geom_of_slot, complete = _slot_tables(
            world, pose, jnp.asarray(sector_centre), jnp.asarray(sector_half), max_range)

        def one(slot_xpos, slot_xmat, slot_size, vec):
            model = world.slot_model.replace(geom_size=slot_size.astype(
                world.slot_model.geom_size.dtype))
            data = world.slot_data.replace(geom_xpos=slot_xpos, geom_xmat=slot_xmat)
            return mjx.ray(model, data, origin, vec)

        sector = jnp.asarray(sector)
        dist, slot = jax.vmap(one)(xpos[sector], xmat[sector], size[sector], directions)
        geom = jnp.where(slot >= 0, geom_of_slot[sector, jnp.maximum(slot, 0)], -1)
    else:
        dist, geom = jax.vmap(lambda vec: _ray_full(world, origin, vec))(directions)
        complete = jnp.asarray(True)
    hit = (dist >= 0.0) & (dist < max_range)
    ranges = jnp.where(hit, dist, max_range)
    return Scan(ranges, jnp.where(hit, geom, -1).astype(jnp.int32), complete)


def add_range_noise(key, ranges, max_range, coefficients=TABLE2_RANGE_NOISE, floor=0.0):
    """Range noise per Geiser et al. 2023, Table 2: r' = r + (c_dist r + c_const) eps, eps ~ N(0, 1),
    std floored at ``floor``; no-returns stay max_range and returns stay in [0, max_range)."""
    std = jnp.maximum(coefficients[0] * ranges + coefficients[1], floor)
    noisy = ranges + std * jax.random.normal(key, ranges.shape, ranges.dtype)
    below = jnp.nextafter(jnp.asarray(max_range, ranges.dtype), jnp.asarray(0, ranges.dtype))
    return jnp.where(ranges < max_range, jnp.clip(noisy, 0.0, below), max_range)


@functools.partial(jax.jit, static_argnames=("num_beams", "max_range", "fov", "cull",
                                             "num_sectors"))
def scan_2d_full(world: World, pose, num_beams: int = 720, max_range: float = 20.0,
                 fov: float = 2.0 * np.pi, cull: bool = True, num_sectors: int = 48) -> Scan:
    """Noise-free planar scan with hit geoms and the culling check.

    Args:
      pose: (3,) sensor pose (x, y, theta). Beams at ``beam_angles(num_beams, fov)`` + theta,
        horizontal, at ``world.sensor_height``.
    Returns:
      ``Scan`` with ranges (B,), geom (B,), complete ().
    """
    pose = jnp.asarray(pose)
    angles = beam_angles(num_beams, fov)
    sector, centre, half = _sectors(angles, num_sectors)
    world_angle = pose[2] + jnp.asarray(angles, pose.dtype)
    directions = jnp.stack([jnp.cos(world_angle), jnp.sin(world_angle),
                            jnp.zeros_like(world_angle)], -1)
    return cast_rays(world, pose, directions, sector, centre, half, max_range, cull)


def scan_2d(world: World, pose, num_beams: int = 720, max_range: float = 20.0, *,
            key=None, range_noise=TABLE2_RANGE_NOISE, fov: float = 2.0 * np.pi,
            cull: bool = True, num_sectors: int = 48):
    """Planar lidar ranges (B,) [m] from ``pose`` (3,); no return reads exactly ``max_range``.

    ``key``: when given, adds Table 2 range noise (``add_range_noise``); None = noise-free.
    """
    ranges = scan_2d_full(world, pose, num_beams, max_range, fov, cull, num_sectors).ranges
    if key is None:
        return ranges
    return add_range_noise(key, ranges, max_range, range_noise)


def layer_elevations(num_layers: int = 16, low_deg: float = -15.0, high_deg: float = 15.0):
    """(L,) evenly spaced beam elevations [rad] (a VLP-16 spans -15..15 degrees)."""
    return np.deg2rad(np.linspace(low_deg, high_deg, num_layers))


@functools.partial(jax.jit, static_argnames=("num_beams", "max_range", "num_layers",
                                             "elevation_deg", "range_noise", "cull",
                                             "num_sectors"))
def scan_3d(world: World, pose, num_beams: int = 360, max_range: float = 20.0, *,
            num_layers: int = 16, elevation_deg=(-15.0, 15.0), key=None,
            range_noise=TABLE2_RANGE_NOISE, cull: bool = True, num_sectors: int = 48) -> Scan:
    """Multi-layer 360-degree scan: ranges (L, B) along each 3D beam, geom (L, B).

    Beam (l, b) points at azimuth ``beam_angles(B)[b]`` + theta and elevation
    ``layer_elevations(L)[l]``. Culling uses horizontal footprints, which bound every 3D hit
    (the horizontal distance to a hit never exceeds its range).
    """
    pose = jnp.asarray(pose)
    angles = beam_angles(num_beams)
    elevations = layer_elevations(num_layers, *elevation_deg)
    sector, centre, half = _sectors(angles, num_sectors)
    azimuth = pose[2] + jnp.asarray(angles, pose.dtype)[None, :]
    elev = jnp.asarray(elevations, pose.dtype)[:, None]
    directions = jnp.stack(jnp.broadcast_arrays(
        jnp.cos(elev) * jnp.cos(azimuth), jnp.cos(elev) * jnp.sin(azimuth), jnp.sin(elev)), -1)
    scan = cast_rays(world, pose, directions.reshape(-1, 3), np.tile(sector, num_layers),
                     centre, half, max_range, cull)
    ranges = scan.ranges.reshape(num_layers, num_beams)
    if key is not None:
        ranges = add_range_noise(key, ranges, max_range, range_noise)
    return Scan(ranges, scan.geom.reshape(num_layers, num_beams), scan.complete)


def clip_3d_to_2d(ranges_3d, elevations, sensor_height, max_range, z_min: float = 0.2,
                  z_max: float = 2.0):
    """Height clipping then projection to (B,) planar ranges; see
    ``jaxslam.detect.clip_points_by_height``."""
    return clip_points_by_height(ranges_3d, elevations, sensor_height, max_range, z_min, z_max)
