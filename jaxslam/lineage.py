"""One particle's history out of a FastSLAM run: its poses and its landmarks' identities.

``run_filter(..., record_lineage=True)`` stores, per step, every particle's ancestor, the slot
each observation matched or created, and the poses (``Lineage``). A particle's history
is then a walk back through the ancestors (``trace_lineage``, JAX, jit/vmap-safe); within it a
slot names a landmark from a birth into it until the next birth (``landmark_identities``).
``smoothing`` re-solves such a history.
"""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["Lineage", "LineagePath", "landmark_identities", "trace_lineage"]


class Lineage(NamedTuple):
    """Every particle's ancestry and data association per step (``record_lineage=True``).

    ancestor: (T, P) int32, ``StepInfo.ancestor``; match / birth_slot: (T, P, K) int16,
    ``StepInfo.match`` / ``StepInfo.birth_slot`` (-1: none), indexed before resampling;
    pose: (T, P, 3) every particle's pose after the step (after resampling). Memory is
    4 T P K + 16 T P bytes (64 MB for Victoria Park's T = 7230, P = 100, K = 18).
    ``lineage.trace_lineage`` extracts one particle's history from it.
    """

    ancestor: jnp.ndarray
    match: jnp.ndarray
    birth_slot: jnp.ndarray
    pose: jnp.ndarray


class LineagePath(NamedTuple):
    """One particle's history, step by step.

    pose: (T, 3) its pose after each step; match: (T, K) slot each observation was matched to
    (-1: none); birth_slot: (T, K) slot each observation created (-1: none).
    """

    pose: jnp.ndarray
    match: jnp.ndarray
    birth_slot: jnp.ndarray


def trace_lineage(lineage: Lineage, final_particle) -> LineagePath:
    """The history of particle ``final_particle`` (index after the last step's resampling).

    With i_{T-1} = final_particle and i_{t-1} = ancestor[t, i_t], the particle at step t is
    i_t after resampling and ancestor[t, i_t] before it (where match and birth_slot live).

    Args:
      lineage: ``Lineage`` with leaves (T, P, ...). final_particle: () int.
    Returns:
      ``LineagePath`` with leaves (T, ...). Jit- and vmap-safe.
    """
    def back(index, ancestor_t):
        before = ancestor_t[index]
        return before, (index, before)

    _, (after, before) = jax.lax.scan(back, jnp.asarray(final_particle, jnp.int32),
                                      lineage.ancestor, reverse=True)
    steps = jnp.arange(lineage.ancestor.shape[0])
    return LineagePath(pose=lineage.pose[steps, after], match=lineage.match[steps, before],
                       birth_slot=lineage.birth_slot[steps, before])


def landmark_identities(match, birth_slot):
    """Landmark identity of every observation along one particle's history.

    A slot holds a new landmark each time an observation is born into it, so the identity is
    the birth: births are numbered 0..L-1 in (step, row) order, and a match at step t to
    slot s reads the last birth into s before step t (a step's births come after its
    matches, so a landmark is never matched in the step that creates it).

    Args:
      match, birth_slot: (T, K) int from ``trace_lineage`` (-1: none).
    Returns:
      (ids (T, K) int64 in [0, L) or -1, L). A match to a slot with no earlier birth (not
      produced by the filter) gets -1.
    """
    match, birth_slot = np.asarray(match, np.int64), np.asarray(birth_slot, np.int64)
    if match.shape != birth_slot.shape or match.ndim != 2:
        raise ValueError(f"match and birth_slot must both be (T, K); got {match.shape} and "
                         f"{birth_slot.shape}")
    if match.size and min(match.min(), birth_slot.min()) < -1:
        raise ValueError("match and birth_slot hold slots >= 0 or -1 (none); got "
                         f"{min(match.min(), birth_slot.min())}")
    stride = match.shape[0] + 1  # key = slot * stride + step orders births by slot, then time
    ids = np.full(match.shape, -1, np.int64)
    birth_t, birth_k = np.nonzero(birth_slot >= 0)
    num_births = birth_t.size
    if num_births == 0:
        return ids, 0
    ids[birth_t, birth_k] = np.arange(num_births)
    birth_key = birth_slot[birth_t, birth_k] * stride + birth_t
    order = np.argsort(birth_key, kind="stable")
    sorted_key = birth_key[order]
    match_t, match_k = np.nonzero(match >= 0)
    slot = match[match_t, match_k]
    last = np.searchsorted(sorted_key, slot * stride + match_t, side="left") - 1
    safe = np.maximum(last, 0)
    found = (last >= 0) & (sorted_key[safe] // stride == slot)
    ids[match_t, match_k] = np.where(found, order[safe], -1)
    return ids, num_births
