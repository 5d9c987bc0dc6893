"""Input cleaning of the filter: malformed observations and non-finite controls.

Inside jit (``sanitize_observations``, ``sanitize_control``) bad rows are masked, never raised
on: an observation row with a NaN or infinite value, a negative range or a bearing outside
[-pi, pi] is dropped and counted; a control row with a NaN or infinite entry is missing
odometry (the step keeps every pose, ``filter`` module docstring). At the boundary of a
program, ``validate_observations`` raises instead, on concrete arrays.
"""
from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from jaxslam.types import Observations


def sanitize_observations(obs: Observations):
    """Mask malformed rows inside jit. Returns (clean Observations, num_invalid ())."""
    z = obs.z
    finite = jnp.all(jnp.isfinite(z), axis=-1)
    well_formed = finite & (z[..., 0] >= 0.0) & (jnp.abs(z[..., 1]) <= jnp.pi)
    invalid = obs.valid & ~well_formed
    valid = obs.valid & well_formed
    z = jnp.where(valid[..., None], z, 0.0)
    # A radius that is not a finite positive number is unknown (0), whatever the row.
    radius = jnp.where(valid & jnp.isfinite(obs.radius) & (obs.radius > 0), obs.radius, 0.0)
    clean = obs._replace(z=z, valid=valid, radius=radius)
    return clean, jnp.sum(invalid).astype(jnp.int32)


def sanitize_control(control):
    """Mask a non-finite control inside jit. Returns (control (..., 3), invalid (...,) bool).

    invalid = any_j ~isfinite(u_j); the returned control is 0 where invalid (so nothing
    downstream, its gradient included, sees the NaN: the caller's ``where`` on the result of
    a zero control is the second half of a double where) and ``control`` elsewhere.
    """
    invalid = ~jnp.all(jnp.isfinite(control), axis=-1)
    return jnp.where(invalid[..., None], jnp.zeros_like(control), control), invalid


def validate_observations(obs: Observations, max_obs: int | None = None) -> None:
    """Raise ``ValueError`` for malformed observations (use outside jit, on concrete arrays).

    Checks shapes ((..., K, 2) with matching (..., K) masks), and, on valid rows, finite values,
    non-negative ranges and bearings within [-pi, pi].
    """
    z = np.asarray(obs.z)
    if z.ndim < 2 or z.shape[-1] != 2:
        raise ValueError(f"Observations.z must have shape (..., K, 2); got {z.shape}")
    if max_obs is not None and z.shape[-2] != max_obs:
        raise ValueError(
            f"Observations have K={z.shape[-2]} rows but FilterConfig.max_obs={max_obs}; "
            "pad or truncate to max_obs rows")
    valid = np.asarray(obs.valid, bool)
    for name in ("valid", "radius", "landmark_id"):
        shape = np.shape(getattr(obs, name))
        if shape != z.shape[:-1]:
            raise ValueError(f"Observations.{name} has shape {shape}; expected {z.shape[:-1]}")
    rows = z[valid]
    if not np.all(np.isfinite(rows)):
        raise ValueError(f"{int(np.sum(~np.isfinite(rows).all(-1)))} valid observation(s) "
                         "contain NaN or inf; mark them invalid or remove them")
    if np.any(rows[:, 0] < 0):
        raise ValueError(f"{int(np.sum(rows[:, 0] < 0))} valid observation(s) have a negative "
                         "range; ranges must be >= 0 metres")
    if np.any(np.abs(rows[:, 1]) > np.pi):
        raise ValueError("valid observation bearings must lie in [-pi, pi] radians; "
                         f"got values up to {np.abs(rows[:, 1]).max():.3f}")
