"""A filter state whose every particle has already mapped some trees (shared test helper)."""
import jax.numpy as jnp
import numpy as np

from jaxslam.filter import _init


def mapped_state(config, trees, variance=1e-4, existence=3.0, count=5):
    """``filter._init(config, 0)`` with ``trees`` (N, 2) in the first N landmark slots of
    every particle: covariance ``variance`` I, existence log-odds ``existence``, seen
    ``count`` times; float32 as the filter's state."""
    p, m = config.num_particles, config.max_landmarks
    state = _init(config, jnp.zeros(3))
    slots = np.zeros((m, 2))
    slots[:len(trees)] = trees
    active = np.arange(m) < len(trees)
    cov = np.tile([variance, 0.0, variance], (m, 1))
    particles = state.particles._replace(
        landmark_mean=jnp.broadcast_to(jnp.asarray(slots, jnp.float32), (p, m, 2)),
        landmark_cov=jnp.broadcast_to(jnp.asarray(cov, jnp.float32), (p, m, 3)),
        active=jnp.broadcast_to(jnp.asarray(active), (p, m)),
        existence=jnp.broadcast_to(jnp.where(active, existence, 0.0).astype(jnp.float32),
                                   (p, m)),
        observation_count=jnp.broadcast_to(jnp.where(active, count, 0).astype(jnp.int32),
                                           (p, m)))
    return state._replace(particles=particles)
