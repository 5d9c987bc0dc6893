"""Data association for ONE particle: match K observations to M landmark slots.

Every kernel takes a cost matrix ``cost`` of shape (K, M) (for instance the squared
Mahalanobis distance of observation k under landmark m's predicted measurement) and a scalar
``gate``. A pair (k, m) is *admissible* when ``cost[k, m]`` is finite and ``cost[k, m] <= gate``;
inadmissible pairs are never formed (``+inf`` marks impossible pairs: inactive slots, landmarks
outside the visible region, ...). Results are (K,) int32 arrays holding the landmark slot each
observation is matched to, or -1. The filter batches these kernels over particles with ``vmap``.

Tie rule: pairs are ordered lexicographically by ``(cost, k, m)``. An observation
prefers the cheaper landmark, then the lower slot index; a landmark prefers the cheaper
observation, then the lower observation index. Because both sides rank pairs by the same
total order, the stable matching is unique; it equals the greedy "cheapest pair first"
matching, which the tests use as a cross-check.

Kinds (``FilterConfig.association``): ``stable`` (vectorised Gale-Shapley), ``greedy``
(global nearest neighbour), ``hungarian`` (optimal assignment) and ``known`` (simulation truth,
stable matching on ``known_id_cost``).
"""
from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import lax
from optax import assignment as optax_assignment

from jaxslam.types import ASSOCIATIONS


def _as_cost_and_gate(cost, gate) -> tuple[jax.Array, jax.Array]:
    """Checks shapes and promotes ``cost`` to a float dtype; ``gate`` gets the same dtype."""
    cost = jnp.asarray(cost)
    if cost.ndim != 2:
        raise ValueError(
            f"cost has shape {cost.shape}; expected a (K, M) matrix (observations x landmark "
            "slots) for one particle; vmap over particles"
        )
    if jnp.ndim(gate) != 0:
        raise ValueError(f"gate has shape {jnp.shape(gate)}; expected a scalar threshold")
    cost = cost.astype(jnp.promote_types(cost.dtype, jnp.float32))
    return cost, jnp.asarray(gate, cost.dtype)


def _admissible(cost: jax.Array, gate: jax.Array) -> jax.Array:
    """(K, M) bool: finite and not above the gate (NaN counts as impossible)."""
    return jnp.isfinite(cost) & (cost <= gate)


def _masked(cost: jax.Array, gate: jax.Array) -> jax.Array:
    """``cost`` where admissible, +inf elsewhere; same shape."""
    return jnp.where(_admissible(cost, gate), cost, jnp.inf)


def _no_match(num_obs: int) -> jax.Array:
    return jnp.full((num_obs,), -1, jnp.int32)


class _ProposalState(NamedTuple):
    """Gale-Shapley loop carry; everything is per observation (no (M,) arrays).

    next_cost, next_slot: (K,) the observation's current proposal (held, or about to be made)
      or, when ``pending``, the proposal just rejected; ``+inf`` and M once its admissible
      landmarks are exhausted.
    pending: (K,) bool: rejected from ``next_slot``; the next choice is still to be looked up.
    match: (K,) int32 landmark slot the observation holds, -1 when free.
    rounds: () int32 rounds done.
    """

    next_cost: jax.Array
    next_slot: jax.Array
    pending: jax.Array
    match: jax.Array
    rounds: jax.Array


def _cheapest_in_rows(candidate: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Lexicographically smallest ``(candidate[r, m], m)`` of each row of an (R, M) matrix.

    Returns its cost (R,), +inf when the row is all +inf, and its slot (R,) int32, M then.
    Two minima, the slot one over float indices (exact below 2**24 slots): on CPU a plain
    argmin (a variadic reduction) is several times slower, an int minimum about twice, and a
    sort far slower still.
    """
    num_slots = candidate.shape[1]
    slot = jnp.arange(num_slots, dtype=candidate.dtype)[None, :]
    best = jnp.min(candidate, axis=1)
    first = jnp.min(jnp.where(candidate == best[:, None], slot, num_slots), axis=1)
    return best, jnp.where(jnp.isfinite(best), first, num_slots).astype(jnp.int32)


def _successor(masked: jax.Array, after_cost: jax.Array, after_slot: jax.Array):
    """Smallest ``(masked[r, m], m)`` above ``(after_cost[r], after_slot[r])`` in each row:
    the next choice of an observation rejected from ``after_slot``. (R, M), (R,), (R,) in."""
    slot = jnp.arange(masked.shape[1], dtype=jnp.int32)[None, :]
    later = (masked > after_cost[:, None]) | (
        (masked == after_cost[:, None]) & (slot > after_slot[:, None])
    )
    return _cheapest_in_rows(jnp.where(later, masked, jnp.inf))


def _refill(state: _ProposalState, cost, gate, rows_per_round: int) -> _ProposalState:
    """Looks up the next choice of at most ``rows_per_round`` pending observations (lowest
    index first); the others wait a round. Gale-Shapley's result does not depend on the order
    in which free observations propose, so waiting changes the round count, never the matching.
    Costs O(rows_per_round * M) instead of a full (K, M) pass."""
    num_obs = cost.shape[0]
    obs_index = jnp.arange(num_obs, dtype=jnp.int32)
    queue = jnp.cumsum(state.pending, dtype=jnp.int32) - 1                   # (K,)
    chosen = state.pending & (queue < rows_per_round)                          # (K,)
    place = jnp.arange(rows_per_round, dtype=jnp.int32)[:, None]               # (L, 1)
    rows = jnp.min(jnp.where(chosen[None, :] & (queue[None, :] == place), obs_index[None, :],
                             num_obs - 1), axis=1)                             # (L,)
    # Admissibility is re-derived on the L gathered rows so that the (K, M) masked matrix is
    # never written out: the first-choice pass then fuses into two reads of ``cost``.
    masked = _masked(cost[rows], gate)
    next_cost, slot = _successor(masked, state.next_cost[rows], state.next_slot[rows])
    place_of = jnp.clip(queue, 0, rows_per_round - 1)
    return state._replace(
        next_cost=jnp.where(chosen, next_cost[place_of], state.next_cost),
        next_slot=jnp.where(chosen, slot[place_of], state.next_slot),
        pending=state.pending & ~chosen,
    )


def _proposers(state: _ProposalState) -> jax.Array:
    """(K,) bool: free observations with a known next choice."""
    return (state.match < 0) & ~state.pending & jnp.isfinite(state.next_cost)


def _propose(state: _ProposalState) -> _ProposalState:
    """Every free observation proposes to its next choice; each landmark keeps the lowest
    ``(cost, observation index)`` among its holder and its proposers; the rejected become
    pending.

    Holders keep ``next_*`` equal to the pair they hold, so holders and proposers are resolved
    alike: contender k loses when another contender k' targets the same slot with
    ``(cost[k'], k') < (cost[k], k)``. A (K, K) comparison: cheaper on CPU than segment
    minima (scatters) over the M slots, and no (M,) state.
    """
    num_obs = state.match.shape[0]
    obs_index = jnp.arange(num_obs, dtype=jnp.int32)
    contending = _proposers(state) | (state.match >= 0)                    # (K,)
    cost, slot = state.next_cost, state.next_slot
    better = (cost[:, None] < cost[None, :]) | (
        (cost[:, None] == cost[None, :]) & (obs_index[:, None] < obs_index[None, :])
    )                                                                       # (K', K)
    beaten = jnp.any(contending[:, None] & (slot[:, None] == slot[None, :]) & better, axis=0)
    won = contending & ~beaten
    return state._replace(
        pending=state.pending | (contending & beaten),
        match=jnp.where(won, slot, -1),
    )


def _round(state: _ProposalState, cost, gate, rows_per_round: int) -> _ProposalState:
    state = _propose(_refill(state, cost, gate, rows_per_round))
    return state._replace(rounds=state.rounds + 1)


def _unfinished(state: _ProposalState) -> jax.Array:
    return jnp.any(state.pending | _proposers(state))


def stable_match(cost, gate, max_rounds=None, *, rows_per_round=4) -> tuple[jax.Array, jax.Array]:
    """Observation-optimal stable matching (vectorised Gale-Shapley) for one particle.

    Observations propose in increasing ``(cost, landmark index)`` order to admissible landmarks
    (finite cost <= gate); a landmark keeps the proposer with the lowest
    ``(cost, observation index)``. Every round all free observations with a known next choice
    propose in parallel; the first choices of all K come from one (K, M) pass, and after that
    each round looks up the next choice of at most ``rows_per_round`` rejected observations
    (lowest index first; the rest wait), so a round costs O(rows_per_round * M + K**2) and
    nothing of size (K, M, M). Each round makes a proposal or exhausts an observation, so
    ``K * (M + 1)`` rounds always finish; with a smaller ``max_rounds`` the loop stops early and
    observations still free are reported as unmatched (-1): the partial matching still uses
    each landmark at most once and respects the gate, but need not be stable.

    Args:
      cost: (K, M) pair costs, ``+inf`` where a pair is impossible.
      gate: () pairs with ``cost > gate`` are never formed.
      max_rounds: int (static or traced) bound on the rounds; None means ``K * (M + 1)``
        (``FilterConfig.match_rounds`` is the filter's bound, the same ``K (M + 1)`` unless
        ``FilterConfig.max_match_rounds`` sets one).
      rows_per_round: static, rejected observations whose next choice is found per round.

    Returns:
      match: (K,) int32 landmark slot of each observation, -1 when unmatched.
      num_rounds: () int32 rounds used (0 when nothing is admissible).
    """
    cost, gate = _as_cost_and_gate(cost, gate)
    num_obs, num_slots = cost.shape
    if num_obs == 0 or num_slots == 0:
        return _no_match(num_obs), jnp.zeros((), jnp.int32)
    if not isinstance(rows_per_round, int) or rows_per_round < 1:
        raise ValueError(f"rows_per_round={rows_per_round!r}; expected a positive int")
    bound = num_obs * (num_slots + 1) if max_rounds is None else max_rounds
    return _stable_match(cost, gate, jnp.asarray(bound, jnp.int32), min(rows_per_round, num_obs))


@functools.partial(jax.jit, static_argnums=3)
def _stable_match(cost, gate, bound, rows_per_round):
    """Jitted core of ``stable_match`` (one compile per shape, also for eager callers)."""
    num_obs = cost.shape[0]
    first_cost, first_slot = _cheapest_in_rows(_masked(cost, gate))
    init = _ProposalState(
        next_cost=first_cost,
        next_slot=first_slot,
        pending=jnp.zeros((num_obs,), bool),
        match=_no_match(num_obs),
        rounds=jnp.zeros((), jnp.int32),
    )
    final = lax.while_loop(
        lambda s: (s.rounds < bound) & _unfinished(s),
        lambda s: _round(s, cost, gate, rows_per_round),
        init,
    )
    return final.match, final.rounds


def _match_or_empty(core, cost, gate) -> jax.Array:
    """Check the inputs, answer an empty problem with no match, else run the jitted core."""
    cost, gate = _as_cost_and_gate(cost, gate)
    num_obs, num_slots = cost.shape
    if num_obs == 0 or num_slots == 0:
        return _no_match(num_obs)
    return core(cost, gate)


def greedy_match(cost, gate) -> jax.Array:
    """Global nearest neighbour: repeatedly form the cheapest remaining admissible pair.

    Ties go to the lower observation, then the lower landmark index (row-major argmin).
    K iterations of a (K, M) masked argmin.

    Args:
      cost: (K, M) pair costs, ``+inf`` where impossible.
      gate: () pairs with ``cost > gate`` are never formed.

    Returns:
      match: (K,) int32 landmark slot of each observation, -1 when unmatched.
    """
    return _match_or_empty(_greedy_match, cost, gate)


@jax.jit
def _greedy_match(cost, gate):
    """Jitted core of ``greedy_match``."""
    num_obs, num_slots = cost.shape
    masked = _masked(cost, gate)

    def take_cheapest(_, carry):
        remaining, match = carry
        # Row-major first minimum: lower observation, then lower slot.
        best, flat = _cheapest_in_rows(remaining.reshape(1, num_obs * num_slots))
        found = jnp.isfinite(best[0])
        obs = jnp.minimum(flat[0] // num_slots, num_obs - 1)   # flat is K * M when none left
        slot = flat[0] % num_slots
        match = match.at[obs].set(jnp.where(found, slot, match[obs]).astype(jnp.int32))
        taken = (jnp.arange(num_obs)[:, None] == obs) | (jnp.arange(num_slots)[None, :] == slot)
        return jnp.where(taken & found, jnp.inf, remaining), match

    _, match = lax.fori_loop(0, num_obs, take_cheapest, (masked, _no_match(num_obs)))
    return match


def hungarian_match(cost, gate) -> jax.Array:
    """Optimal assignment (``optax.assignment.hungarian_algorithm``) restricted by the gate.

    Inadmissible pairs get the finite penalty ``1 + 2 * min(K, M) * max|admissible cost|``,
    larger than any difference between sums of admissible costs, so the solver first
    maximises the number of admissible pairs and then minimises their total cost; assigned
    pairs that are inadmissible are dropped afterwards.

    Args:
      cost: (K, M) pair costs, ``+inf`` where impossible.
      gate: () pairs with ``cost > gate`` are never formed.

    Returns:
      match: (K,) int32 landmark slot of each observation, -1 when unmatched.
    """
    return _match_or_empty(_hungarian_match, cost, gate)


@jax.jit
def _hungarian_match(cost, gate):
    """Jitted core of ``hungarian_match``."""
    num_obs, num_slots = cost.shape
    admissible = _admissible(cost, gate)
    largest = jnp.max(jnp.where(admissible, jnp.abs(cost), 0.0))
    penalty = 1.0 + 2.0 * min(num_obs, num_slots) * largest
    rows, cols = optax_assignment.hungarian_algorithm(jnp.where(admissible, cost, penalty))
    cols = jnp.where(admissible[rows, cols], cols, -1).astype(jnp.int32)
    return _no_match(num_obs).at[rows].set(cols)


def known_id_cost(obs_ids, slot_ids, active) -> jax.Array:
    """Association by simulation truth: 0 where ids agree, +inf elsewhere.

    Args:
      obs_ids: (K,) int true-tree id of each observation; < 0 for unknown or padding.
      slot_ids: (M,) int true-tree id recorded in each landmark slot.
      active: (M,) bool slot holds a landmark.

    Returns:
      cost: (K, M) float32, ``0`` where ``obs_ids[k] == slot_ids[m] >= 0`` and slot m is
      active, ``+inf`` elsewhere.
    """
    obs_ids, slot_ids, active = jnp.asarray(obs_ids), jnp.asarray(slot_ids), jnp.asarray(active)
    if obs_ids.ndim != 1 or slot_ids.ndim != 1 or active.shape != slot_ids.shape:
        raise ValueError(
            f"got obs_ids {obs_ids.shape}, slot_ids {slot_ids.shape}, active {active.shape}; "
            "expected (K,), (M,) and (M,)"
        )
    same = (obs_ids[:, None] == slot_ids[None, :]) & (obs_ids[:, None] >= 0) & active[None, :]
    return jnp.where(same, 0.0, jnp.inf).astype(jnp.float32)


def known_id_births(candidates, obs_ids, slot_ids, active) -> jax.Array:
    """Births by simulation truth: a tree already in the map is never born twice.

    Observation k creates a landmark when it is a candidate, its id is known
    (``obs_ids[k] >= 0``) and no active slot holds that id, even one outside the matchable
    region (a landmark beyond the boundary would otherwise get a twin).

    Args:
      candidates: (K,) bool observations that would create a landmark (usable, unmatched).
      obs_ids: (K,) int true-tree id of each observation; < 0 for unknown or padding.
      slot_ids: (M,) int true-tree id recorded in each landmark slot.
      active: (M,) bool slot holds a landmark.

    Returns:
      (K,) bool, ``candidates & (obs_ids >= 0) & ~any_m(active[m] & slot_ids[m] == obs_ids)``.
    """
    in_map = jnp.any(active[None, :] & (slot_ids[None, :] == obs_ids[:, None]), axis=1)
    return candidates & (obs_ids >= 0) & ~in_map


def birth_candidates(kind: str, candidates, obs_ids, slot_ids, active) -> jax.Array:
    """(K,) bool observations allowed to create a landmark under association ``kind``:
    ``known_id_births`` for ``known``, ``candidates`` unchanged otherwise. Shapes as in
    ``known_id_births``."""
    if kind == "known":
        return known_id_births(candidates, obs_ids, slot_ids, active)
    return candidates


def association_cost(kind: str, distance, allowed, obs_ids, slot_ids, active) -> jax.Array:
    """(K, M) cost the matcher of ``kind`` sees: ``distance`` (K, M) where ``allowed``
    (K, M) bool, +inf elsewhere; for ``known``, 0 where allowed and the ids agree
    (``known_id_cost``), +inf elsewhere. ``obs_ids`` (K,), ``slot_ids`` (M,), ``active``
    (M,) are only read for ``known``."""
    if kind == "known":
        same = known_id_cost(obs_ids, slot_ids, active)
        return jnp.where(allowed & jnp.isfinite(same), 0.0, jnp.inf)
    return jnp.where(allowed, distance, jnp.inf)


def match(kind: str, cost, gate, max_rounds=None) -> tuple[jax.Array, jax.Array]:
    """Dispatches on the static association ``kind`` (``FilterConfig.association``).

    Args:
      kind: one of ``ASSOCIATIONS``: ``stable``, ``greedy``, ``hungarian``, ``known``.
        ``known`` expects ``cost`` from ``known_id_cost`` and ignores ``gate`` (truth is
        never gated).
      cost: (K, M) pair costs, ``+inf`` where impossible.
      gate: () threshold above which pairs are never formed.
      max_rounds: bound on Gale-Shapley rounds (``stable`` and ``known``); None means K * (M + 1).

    Returns:
      match: (K,) int32 landmark slot per observation, -1 when unmatched.
      num_rounds: () int32 Gale-Shapley rounds used; K for ``greedy`` (its fixed number of
        iterations), 0 for ``hungarian``.
    """
    if kind == "stable":
        return stable_match(cost, gate, max_rounds)
    if kind == "known":
        return stable_match(cost, jnp.inf, max_rounds)
    if kind == "greedy":
        return greedy_match(cost, gate), jnp.asarray(jnp.shape(cost)[0], jnp.int32)
    if kind == "hungarian":
        return hungarian_match(cost, gate), jnp.zeros((), jnp.int32)
    raise ValueError(
        f"association kind {kind!r} is not supported; expected one of {list(ASSOCIATIONS)}"
    )
