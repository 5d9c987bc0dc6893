"""The filter state of one run: per-particle maps and poses, weights and running averages.

Shapes use the glossary of ``jaxslam.types``: P particles, M landmark slots per particle.
"""
from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp


class Particles(NamedTuple):
    """Per-particle fields; every leaf has leading axis P, so resampling is one tree map.

    Attributes:
      pose: (P, 3) particle poses (x, y, theta).
      landmark_mean: (P, M, 2) landmark positions in the world frame.
      landmark_cov: (P, M, 3) landmark covariance components (sxx, sxy, syy).
      landmark_radius: (P, M) trunk radius estimate: the running mean of the ``radius_count``
        measured radii (0 while none was measured).
      landmark_id: (P, M) int32 true-tree id (``association="known"``); -1 when unknown.
      active: (P, M) bool slot occupancy.
      existence: (P, M) existence log-odds of each landmark.
      observation_count: (P, M) int32 number of updates since birth (1 at birth).
      radius_count: (P, M) int32 number of those updates (and the birth) that carried a
        measured radius (``Observations.radius`` > 0).
    Inactive slots hold finite values (zero mean, identity covariance) and are masked.
    """

    pose: jnp.ndarray
    landmark_mean: jnp.ndarray
    landmark_cov: jnp.ndarray
    landmark_radius: jnp.ndarray
    landmark_id: jnp.ndarray
    active: jnp.ndarray
    existence: jnp.ndarray
    observation_count: jnp.ndarray
    radius_count: jnp.ndarray


class FilterState(NamedTuple):
    """The filter state of ONE run.

    Attributes:
      particles: ``Particles`` with leading axis P.
      log_weight: (P,) normalised log-weights (logsumexp == 0).
      likelihood_fast / likelihood_slow: () short- and long-term running averages of the mean
        per-observation log-likelihood (drive the adaptive mixture ratio).
      step: () int32 steps taken.
    """

    particles: Particles
    log_weight: jnp.ndarray
    likelihood_fast: jnp.ndarray
    likelihood_slow: jnp.ndarray
    step: jnp.ndarray
