"""Padded range-bearing ``Observations`` of one step and their constructors.

K is the padded number of observations per step (``FilterConfig.max_obs``).
"""
from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp


class Observations(NamedTuple):
    """Padded range-bearing observations of ONE step (add leading axes for T or R).

    Attributes:
      z: (K, 2) range [m] and bearing [rad] in the robot frame.
      valid: (K,) bool; padded rows are False and ignored.
      radius: (K,) trunk radius [m] (0 when unknown).
      landmark_id: (K,) int32 true-tree id (simulation truth, for ``association="known"``);
        -1 when unknown.
    """

    z: jnp.ndarray
    valid: jnp.ndarray
    radius: jnp.ndarray
    landmark_id: jnp.ndarray


def make_observations(z, valid=None, radius=None, landmark_id=None) -> Observations:
    """Build ``Observations`` with defaults for the optional fields.

    Args:
      z: (..., K, 2) range and bearing.
      valid: (..., K) bool, default all True.
      radius: (..., K) default zeros.
      landmark_id: (..., K) int, default -1.
    """
    z = jnp.asarray(z)
    if z.ndim < 2 or z.shape[-1] != 2:
        raise ValueError(f"observations z must have shape (..., K, 2); got {z.shape}")
    batch = z.shape[:-1]
    valid = jnp.ones(batch, bool) if valid is None else jnp.asarray(valid, bool)
    radius = jnp.zeros(batch, z.dtype) if radius is None else jnp.asarray(radius, z.dtype)
    landmark_id = (jnp.full(batch, -1, jnp.int32) if landmark_id is None
                   else jnp.asarray(landmark_id, jnp.int32))
    for name, arr in (("valid", valid), ("radius", radius), ("landmark_id", landmark_id)):
        if arr.shape != batch:
            raise ValueError(
                f"observations {name} must have shape {batch} to match z {z.shape}; "
                f"got {arr.shape}"
            )
    return Observations(z=z, valid=valid, radius=radius, landmark_id=landmark_id)


def empty_observations(max_obs: int, dtype=jnp.float32) -> Observations:
    """K padded, all-invalid observations (a step where nothing is seen)."""
    return make_observations(jnp.zeros((max_obs, 2), dtype), valid=jnp.zeros(max_obs, bool))
