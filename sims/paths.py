"""Robot paths through a forest, their true moves and noisy odometry (Geiser et al. 2023, Eq. 1).

A path is ``poses`` (T+1, 3): the initial pose first, then one pose per step, heading along
the direction of travel. ``true_moves`` gives the (rot1, trans, rot2) move of each step and
``noisy_odometry`` draws the odometry readings a robot would report, per Geiser et al. 2023, Eq. (1)
with Table 1 coefficients (``jaxslam.motion.sample_odometry``).
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jaxslam.geometry import wrap_angle
from jaxslam.motion import odometry_from_poses, sample_odometry
from jaxslam.types import Params


def resample_polyline(points, num_steps: int, step_length: float, closed: bool = False):
    """Poses (T+1, 3) every ``step_length`` metres of arc length along a polyline (Q, 2).

    A closed polyline wraps around; an open one stops at its end (the last moves are zero).
    Heading is the direction of the polyline segment containing each pose.
    """
    points = jnp.asarray(points, jnp.float32)
    if closed:
        points = jnp.concatenate([points, points[:1]], axis=0)
    seg = points[1:] - points[:-1]
    seg_len = jnp.hypot(seg[:, 0], seg[:, 1])
    cum = jnp.concatenate([jnp.zeros(1, points.dtype), jnp.cumsum(seg_len)])
    total = cum[-1]
    arc = jnp.arange(num_steps + 1, dtype=points.dtype) * step_length
    arc = jnp.mod(arc, total) if closed else jnp.minimum(arc, total)
    index = jnp.clip(jnp.searchsorted(cum, arc, side="right") - 1, 0, seg.shape[0] - 1)
    frac = (arc - cum[index]) / jnp.maximum(seg_len[index], 1e-12)
    xy = points[index] + frac[:, None] * seg[index]
    heading = jnp.arctan2(seg[index, 1], seg[index, 0])
    return jnp.concatenate([xy, heading[:, None]], axis=-1)


def loop_path(num_steps: int = 200, centre=(30.0, 30.0), radii=(16.0, 16.0),
              step_length: float = 0.5, num_vertices: int = 720):
    """Counter-clockwise elliptic loop (semi-axes ``radii``) about ``centre``: (T+1, 3)."""
    phi = 2.0 * np.pi * np.arange(num_vertices) / num_vertices
    points = np.stack([centre[0] + radii[0] * np.cos(phi), centre[1] + radii[1] * np.sin(phi)],
                      -1)
    return resample_polyline(points, num_steps, step_length, closed=True)


def lawnmower_path(row_ys, x_start: float, x_end: float, num_steps: int,
                   step_length: float = 0.5, turn_vertices: int = 24):
    """Back-and-forth along lanes at heights ``row_ys`` (e.g. midway between plantation rows),
    joined by semicircular U-turns beyond the row ends: (T+1, 3)."""
    row_ys = np.asarray(row_ys, float)
    pieces = []
    for lane, y in enumerate(row_ys):  # static geometry, built once in NumPy
        forward = lane % 2 == 0
        xs = (x_start, x_end) if forward else (x_end, x_start)
        pieces.append(np.array([[xs[0], y], [xs[1], y]]))
        if lane + 1 < len(row_ys):
            y_next = row_ys[lane + 1]
            radius = 0.5 * (y_next - y)
            phi = np.linspace(-0.5 * np.pi, 0.5 * np.pi, turn_vertices)[1:-1]
            side = 1.0 if forward else -1.0
            pieces.append(np.stack([xs[1] + side * abs(radius) * np.cos(phi),
                                    y + radius + radius * np.sin(phi)], -1))
    return resample_polyline(np.concatenate(pieces), num_steps, step_length, closed=False)


def random_smooth_path(key, centres, num_steps: int, start, step_length: float = 0.5,
                       bounds=((0.0, 0.0), (60.0, 60.0)), clearance: float = 1.5,
                       turn_std: float = 0.15, avoid_gain: float = 0.6):
    """A random smooth path that steers clear of trunks ``centres`` (N, 2): (T+1, 3).

    Heading follows theta' = theta + turn_std * eps + avoid_gain * (steer away from trunks
    within 2 * clearance, and back toward the box centre near ``bounds``), capped at 0.5 rad
    per step. Check the result with ``path_clearance``.
    """
    centres = jnp.asarray(centres, jnp.float32)
    low, high = jnp.asarray(bounds[0], jnp.float32), jnp.asarray(bounds[1], jnp.float32)
    middle = 0.5 * (low + high)

    def step(pose, noise):
        delta = pose[None, :2] - centres
        dist = jnp.maximum(jnp.hypot(delta[:, 0], delta[:, 1]), 1e-6)
        push = jnp.sum(delta / dist[:, None] * jnp.maximum(2.0 * clearance - dist, 0.0)[:, None],
                       axis=0)
        margin = jnp.minimum(jnp.min(pose[:2] - low), jnp.min(high - pose[:2]))
        home = (middle - pose[:2]) * jnp.maximum(5.0 - margin, 0.0)
        pull = push + home
        want = jnp.arctan2(pull[1], pull[0])
        strength = jnp.minimum(jnp.hypot(pull[0], pull[1]), 1.0)
        turn = turn_std * noise + avoid_gain * strength * wrap_angle(want - pose[2])
        theta = wrap_angle(pose[2] + jnp.clip(turn, -0.5, 0.5))
        new = jnp.stack([pose[0] + step_length * jnp.cos(theta),
                         pose[1] + step_length * jnp.sin(theta), theta])
        return new, new

    start = jnp.asarray(start, jnp.float32)
    _, poses = jax.lax.scan(step, start, jax.random.normal(key, (num_steps,), jnp.float32))
    return jnp.concatenate([start[None], poses], axis=0)


def path_clearance(poses, centres, radii):
    """Smallest distance [m] from any path position (T+1, 3) to any trunk surface."""
    delta = poses[:, None, :2] - jnp.asarray(centres)[None]
    return jnp.min(jnp.hypot(delta[..., 0], delta[..., 1]) - jnp.asarray(radii)[None])


def true_moves(poses, min_translation: float = 0.01):
    """(T, 3) true (rot1, trans, rot2) moves between consecutive poses (T+1, 3)."""
    return odometry_from_poses(poses[:-1], poses[1:], min_translation)


def noisy_odometry(key, moves, params: Params, bursts: bool = False):
    """(T, 3) odometry readings: each true move (T, 3) perturbed per Geiser et al. 2023, Eq. (1).

    The simulated robot's noise is Eq. (1)'s Gaussian: ``params``' bursts
    (``motion_outlier_probability``) are the filter's prior, a tail it allows for, not a
    property of this robot, and are ignored unless ``bursts`` (then drawn as
    ``sample_odometry`` does). Wheel slip with its own structure: ``sims.robot``.
    """
    if not bursts:
        params = params._replace(motion_outlier_probability=jnp.zeros_like(
            jnp.asarray(params.motion_outlier_probability)))
    keys = jax.random.split(key, moves.shape[0])
    return jax.vmap(sample_odometry, in_axes=(0, 0, None))(keys, moves, params)
