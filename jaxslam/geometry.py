"""Planar geometry: angle wrap, SE(2) composition, the range-bearing model and its Jacobians.

All functions work elementwise on any leading shape (written for scalars or component
arrays); none loops.
"""
from __future__ import annotations

import jax.numpy as jnp

TWO_PI = 2.0 * jnp.pi
LOG_2PI = 1.8378770664093453  # log(2 pi), for Gaussian log-densities


def wrap_angle(angle):
    """Wrap to [-pi, pi) by floor arithmetic: a - 2 pi floor((a + pi) / (2 pi)).

    About 9x faster than arctan2(sin, cos) on XLA:CPU.
    """
    return angle - TWO_PI * jnp.floor((angle + jnp.pi) / TWO_PI)


def compose(pose, delta):
    """SE(2) composition ``pose (+) delta``, both (..., 3): delta expressed in pose's frame."""
    x, y, theta = pose[..., 0], pose[..., 1], pose[..., 2]
    dx, dy, dtheta = delta[..., 0], delta[..., 1], delta[..., 2]
    cos_t, sin_t = jnp.cos(theta), jnp.sin(theta)
    return jnp.stack(
        [x + cos_t * dx - sin_t * dy, y + sin_t * dx + cos_t * dy, wrap_angle(theta + dtheta)],
        axis=-1,
    )


def relative(pose_a, pose_b):
    """SE(2) ``pose_a^-1 (+) pose_b``, both (..., 3): pose_b expressed in pose_a's frame."""
    dx = pose_b[..., 0] - pose_a[..., 0]
    dy = pose_b[..., 1] - pose_a[..., 1]
    cos_t, sin_t = jnp.cos(pose_a[..., 2]), jnp.sin(pose_a[..., 2])
    return jnp.stack(
        [cos_t * dx + sin_t * dy, -sin_t * dx + cos_t * dy,
         wrap_angle(pose_b[..., 2] - pose_a[..., 2])],
        axis=-1,
    )


def range_bearing(pose, point):
    """Measurement model h(pose, point) = (|p - t|, atan2(dy, dx) - theta), wrapped.

    Args:
      pose: (..., 3) sensor pose; point: (..., 2) landmark; broadcastable.
    Returns:
      (..., 2) range and bearing.
    """
    dx = point[..., 0] - pose[..., 0]
    dy = point[..., 1] - pose[..., 1]
    return jnp.stack(
        [jnp.hypot(dx, dy), wrap_angle(jnp.arctan2(dy, dx) - pose[..., 2])], axis=-1
    )


def inverse_range_bearing(pose, z):
    """Inverse model g(pose, z) = t + r (cos(theta + b), sin(theta + b)).

    Args:
      pose: (..., 3); z: (..., 2) range and bearing. Returns (..., 2) world point.
    """
    angle = pose[..., 2] + z[..., 1]
    return jnp.stack(
        [pose[..., 0] + z[..., 0] * jnp.cos(angle), pose[..., 1] + z[..., 0] * jnp.sin(angle)],
        axis=-1,
    )


def range_bearing_jacobian_point(dx, dy):
    """Jacobian of h with respect to the landmark, from dx = px - x, dy = py - y.

        H = [[ dx/r,    dy/r  ],
             [-dy/r^2,  dx/r^2]]

    The Jacobian with respect to the pose (x, y) is -H, and d bearing / d theta = -1.
    Returns the four entries (h00, h01, h10, h11), each of dx's shape. A zero distance is
    clamped to 1e-9 so the entries stay finite.
    """
    range_sq = jnp.maximum(dx * dx + dy * dy, 1e-18)
    range_ = jnp.sqrt(range_sq)
    return dx / range_, dy / range_, -dy / range_sq, dx / range_sq
