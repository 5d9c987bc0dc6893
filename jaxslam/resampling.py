"""Resampling schemes on log-weights, and the effective sample size.

Each scheme maps (key, log_weight (P,)) to ancestor indices (P,) int32 such that the expected
number of copies of particle i is P w_i (unbiased). Systematic and residual schemes also keep
every count within floor(P w_i) and floor(P w_i) + 1 (systematic) or at least floor(P w_i)
(residual).
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
from jax.scipy.special import logsumexp

from jaxslam.types import RESAMPLINGS


def normalize_log_weights(log_weight):
    """Normalise (P,) log-weights to logsumexp 0.

    When every weight is -inf or NaN (no particle explains the data) the weights are reset to
    uniform; the returned flag says so (``info.weights_reset``), never a NaN.
    Returns (normalised (P,), reset ()).
    """
    finite = jnp.isfinite(log_weight)
    log_weight = jnp.where(finite | (log_weight == jnp.inf), log_weight, -jnp.inf)
    total = logsumexp(log_weight)
    reset = ~jnp.isfinite(total)
    uniform = jnp.full_like(log_weight, -jnp.log(log_weight.shape[0]))
    return jnp.where(reset, uniform, log_weight - jnp.where(reset, 0.0, total)), reset


def effective_sample_size(log_weight):
    """ESS = 1 / sum w_i^2 for normalised log-weights (P,)."""
    return jnp.exp(-logsumexp(2.0 * log_weight))


def _sorted_search(cumulative, positions):
    """Ancestor index of each position in [0, 1) on the cumulative weights (P,)."""
    indices = jnp.searchsorted(cumulative, positions, side="right")
    return jnp.clip(indices, 0, cumulative.shape[0] - 1).astype(jnp.int32)


def _cumulative(log_weight):
    cumulative = jnp.cumsum(jnp.exp(log_weight))
    return cumulative / cumulative[-1]


def systematic(key, log_weight):
    """One uniform offset u ~ U[0, 1/P): positions (i + u) / P."""
    num = log_weight.shape[0]
    offset = jax.random.uniform(key, (), log_weight.dtype)
    positions = (jnp.arange(num, dtype=log_weight.dtype) + offset) / num
    return _sorted_search(_cumulative(log_weight), positions)


def stratified(key, log_weight):
    """One uniform per stratum: positions (i + u_i) / P."""
    num = log_weight.shape[0]
    offsets = jax.random.uniform(key, (num,), log_weight.dtype)
    positions = (jnp.arange(num, dtype=log_weight.dtype) + offsets) / num
    return _sorted_search(_cumulative(log_weight), positions)


def multinomial(key, log_weight):
    """P independent draws from the categorical distribution of the weights."""
    return jax.random.categorical(key, log_weight, shape=log_weight.shape).astype(jnp.int32)


def residual(key, log_weight):
    """floor(P w_i) deterministic copies, the remainder drawn multinomially from the residuals.

    The deterministic copies are laid out with a cumulative-count search (static shapes): slot
    j < sum floor(P w) belongs to the particle whose cumulative count first exceeds j.
    """
    num = log_weight.shape[0]
    expected = num * jnp.exp(log_weight)
    copies = jnp.floor(expected)
    cumulative_copies = jnp.cumsum(copies)
    slots = jnp.arange(num, dtype=expected.dtype)
    deterministic = jnp.searchsorted(cumulative_copies, slots, side="right").astype(jnp.int32)
    remainder = expected - copies
    log_remainder = jnp.where(remainder > 0, jnp.log(jnp.maximum(remainder, 1e-30)), -jnp.inf)
    # If floor(P w) already fills every slot, the residual draw is never used; keep it finite.
    log_remainder = jnp.where(jnp.all(remainder <= 0), 0.0, log_remainder)
    drawn = jax.random.categorical(key, log_remainder, shape=(num,)).astype(jnp.int32)
    return jnp.where(slots < cumulative_copies[-1], jnp.clip(deterministic, 0, num - 1), drawn)


_SCHEMES = {
    "systematic": systematic,
    "stratified": stratified,
    "multinomial": multinomial,
    "residual": residual,
}


def resample_indices(key, log_weight, kind: str):
    """Ancestor indices (P,) from normalised log-weights (P,) by scheme ``kind``."""
    if kind not in _SCHEMES:
        raise ValueError(f"resampling={kind!r}; expected one of {list(RESAMPLINGS)}")
    return _SCHEMES[kind](key, log_weight)


def gather(tree, indices):
    """Gather every leaf (leading axis P) of a pytree at ``indices`` (P,): one tree map."""
    return jax.tree.map(lambda leaf: jnp.take(leaf, indices, axis=0), tree)
