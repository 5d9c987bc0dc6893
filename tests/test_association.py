"""Tests for jaxslam.association: stable, greedy, Hungarian and known-id matching.

References are plain Python / NumPy float64 (Gale-Shapley, greedy) and SciPy
(``linear_sum_assignment``). Random instances use small integer costs so that ties are common.
"""
import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.optimize import linear_sum_assignment

from jaxslam import association
from jaxslam.association import (
    greedy_match,
    hungarian_match,
    known_id_cost,
    match,
    stable_match,
)
from jaxslam.types import ASSOCIATIONS


# ----------------------------------------------------------------------------- references
def _admissible(cost, gate):
    return np.isfinite(cost) & (cost <= gate)


def gale_shapley_reference(cost, gate):
    """Sequential Gale-Shapley, observations propose; ties to the lower index on both sides."""
    cost = np.asarray(cost, np.float64)
    num_obs, num_slots = cost.shape
    ok = _admissible(cost, gate)
    prefs = [sorted((cost[k, m], m) for m in range(num_slots) if ok[k, m]) for k in range(num_obs)]
    nxt = [0] * num_obs
    match = [-1] * num_obs
    holder = [-1] * num_slots
    free = list(range(num_obs))
    while free:
        k = free.pop()
        if nxt[k] >= len(prefs[k]):
            continue
        _, m = prefs[k][nxt[k]]
        nxt[k] += 1
        h = holder[m]
        if h < 0:
            holder[m], match[k] = k, m
        elif (cost[k, m], k) < (cost[h, m], h):
            holder[m], match[k], match[h] = k, m, -1
            free.append(h)
        else:
            free.append(k)
    return np.array(match, np.int32)


def greedy_reference(cost, gate):
    """Cheapest admissible pair first; ties to the lower observation, then the lower slot."""
    cost = np.asarray(cost, np.float64)
    pairs = sorted(
        (cost[k, m], k, m) for k, m in zip(*np.nonzero(_admissible(cost, gate)))
    )
    match = np.full(cost.shape[0], -1, np.int32)
    used = set()
    for _, k, m in pairs:
        if match[k] < 0 and m not in used:
            match[k] = m
            used.add(m)
    return match


def hungarian_reference(cost, gate):
    """SciPy on the finite sub-problem: inadmissible pairs cost 1e6 and are dropped after."""
    cost = np.asarray(cost, np.float64)
    ok = _admissible(cost, gate)
    rows, cols = linear_sum_assignment(np.where(ok, cost, 1e6))
    match = np.full(cost.shape[0], -1, np.int32)
    keep = ok[rows, cols]
    match[rows[keep]] = cols[keep]
    return match


def blocking_pairs(cost, gate, match):
    """Admissible pairs (k, m) that both prefer each other to their partners."""
    cost = np.asarray(cost, np.float64)
    holder = {int(m): k for k, m in enumerate(match) if m >= 0}
    blocking = []
    for k, m in zip(*np.nonzero(_admissible(cost, gate))):
        mine = match[k]
        obs_prefers = mine < 0 or (cost[k, m], m) < (cost[k, mine], mine)
        h = holder.get(int(m), -1)
        slot_prefers = h < 0 or (cost[k, m], k) < (cost[h, m], h)
        if mine != m and obs_prefers and slot_prefers:
            blocking.append((k, m))
    return blocking


def check_valid_matching(cost, gate, match):
    """Each landmark at most once, every formed pair admissible."""
    formed = match[match >= 0]
    assert len(set(formed.tolist())) == formed.size, f"landmark used twice: {match}"
    k = np.nonzero(match >= 0)[0]
    assert np.all(_admissible(np.asarray(cost, np.float64), gate)[k, match[k]]), match


# ----------------------------------------------------------------------------- instances
def random_instances(seed, batch, num_obs, num_slots):
    """Integer costs 0..4 (many ties), 0-100% impossible (+inf) entries, gates 0.5..inf."""
    rng = np.random.default_rng(seed)
    cost = rng.integers(0, 5, size=(batch, num_obs, num_slots)).astype(np.float64)
    impossible_rate = rng.choice([0.0, 0.3, 0.7, 0.95, 1.0], size=(batch, 1, 1))
    cost[rng.random(cost.shape) < impossible_rate] = np.inf
    gate = rng.choice([0.5, 1.0, 2.0, 3.5, np.inf], size=batch)
    return cost, gate


# (K, M) -> instances; 10,400 in all, K > M, K < M, K = M, K or M = 1.
STABLE_SHAPES = {(1, 1): 500, (1, 7): 1000, (7, 1): 1000, (3, 3): 2000, (4, 9): 2500,
                 (9, 4): 2500, (16, 24): 500}


_batched_stable = jax.jit(jax.vmap(stable_match))
_batched_greedy = jax.jit(jax.vmap(greedy_match))
_batched_hungarian = jax.jit(jax.vmap(hungarian_match))


@pytest.mark.parametrize("shape", list(STABLE_SHAPES))
def test_stable_match_equals_gale_shapley_reference(shape):
    cost, gate = random_instances(sum(shape), STABLE_SHAPES[shape], *shape)
    got, rounds = jax.device_get(_batched_stable(cost, gate))
    chex.assert_shape(got, (len(cost), shape[0]))
    assert got.dtype == np.int32 and rounds.dtype == np.int32
    for b in range(len(cost)):
        want = gale_shapley_reference(cost[b], gate[b])
        np.testing.assert_array_equal(got[b], want, err_msg=f"instance {b}: {cost[b]} {gate[b]}")
    # The stability property and validity, checked on the result itself.
    for b in range(0, len(cost), 7):
        check_valid_matching(cost[b], gate[b], got[b])
        assert blocking_pairs(cost[b], gate[b], got[b]) == []
    # Rounds: zero exactly when nothing is admissible, never above the default bound.
    any_admissible = _admissible(cost, gate[:, None, None]).any(axis=(1, 2))
    np.testing.assert_array_equal(rounds > 0, any_admissible)
    assert rounds.max() <= shape[0] * (shape[1] + 1)


def test_reference_finds_blocking_pair_in_unstable_matching():
    # Guards the property checker itself: swapping a stable matching creates a blocking pair.
    cost = np.array([[0.0, 1.0], [1.0, 0.0]])
    assert blocking_pairs(cost, np.inf, np.array([0, 1])) == []
    assert blocking_pairs(cost, np.inf, np.array([1, 0])) != []
    assert blocking_pairs(cost, np.inf, np.array([0, -1])) == [(1, 1)]


def test_stable_match_all_impossible_and_gated():
    cost = np.full((4, 5), np.inf)
    got, rounds = stable_match(cost, 1.0)
    np.testing.assert_array_equal(got, -np.ones(4))
    assert int(rounds) == 0
    got, rounds = stable_match(np.full((4, 5), 2.0), 1.0)   # every pair above the gate
    np.testing.assert_array_equal(got, -np.ones(4))
    assert int(rounds) == 0
    got, _ = stable_match(np.full((4, 5), 1.0), 1.0)        # exactly at the gate: formed
    np.testing.assert_array_equal(got, [0, 1, 2, 3])


def test_stable_match_ties_go_to_lower_index():
    # All costs equal: observation k gets slot k (lower slot first, lower observation wins).
    got, _ = stable_match(np.zeros((3, 5)), 1.0)
    np.testing.assert_array_equal(got, [0, 1, 2])
    got, _ = stable_match(np.zeros((5, 3)), 1.0)
    np.testing.assert_array_equal(got, [0, 1, 2, -1, -1])
    # Two observations tie for slot 1: the lower index keeps it, the other takes slot 0.
    cost = np.array([[5.0, 1.0], [4.0, 1.0]])
    np.testing.assert_array_equal(stable_match(cost, 9.0)[0], [1, 0])


def test_stable_match_empty_shapes():
    for shape in [(0, 4), (3, 0), (0, 0)]:
        got, rounds = stable_match(np.zeros(shape), 1.0)
        np.testing.assert_array_equal(got, -np.ones(shape[0]))
        assert got.dtype == jnp.int32 and int(rounds) == 0


def test_stable_match_jit_and_eager_agree():
    cost, gate = random_instances(1, 6, 5, 7)
    jitted = jax.jit(stable_match)
    for b in range(len(cost)):
        want = gale_shapley_reference(cost[b], gate[b])
        eager, eager_rounds = stable_match(cost[b], gate[b])
        traced, traced_rounds = jitted(cost[b], gate[b])
        np.testing.assert_array_equal(eager, want)
        np.testing.assert_array_equal(traced, want)
        assert int(eager_rounds) == int(traced_rounds)


def test_stable_match_vmap_batch_zero():
    empty = np.zeros((0, 4, 6))
    for fn in (jax.vmap(stable_match, in_axes=(0, None)),
               jax.jit(jax.vmap(stable_match, in_axes=(0, None)))):
        got, rounds = fn(empty, 1.0)
        chex.assert_shape(got, (0, 4))
        chex.assert_shape(rounds, (0,))


def test_stable_match_float32_costs():
    cost, gate = random_instances(3, 100, 4, 9)
    got, _ = _batched_stable(cost.astype(np.float32), gate.astype(np.float32))
    for b in range(len(cost)):
        np.testing.assert_array_equal(got[b], gale_shapley_reference(cost[b], gate[b]))


@pytest.mark.parametrize("rows_per_round", [1, 16])
def test_stable_match_rows_per_round_changes_rounds_not_result(rows_per_round):
    cost, gate = random_instances(4, 300, 8, 10)
    base, base_rounds = _batched_stable(cost, gate)
    fn = jax.jit(jax.vmap(lambda c, g: stable_match(c, g, rows_per_round=rows_per_round)))
    got, rounds = fn(cost, gate)
    np.testing.assert_array_equal(got, base)
    if rows_per_round == 16:   # every rejected observation re-proposes at once
        assert np.all(rounds <= base_rounds)


def test_stable_match_max_rounds_truncates_to_a_valid_partial_matching():
    cost, gate = random_instances(5, 300, 8, 8)
    fn = jax.jit(jax.vmap(lambda c, g: stable_match(c, g, 2)))
    got, rounds = jax.device_get(fn(cost, gate))
    assert rounds.max() <= 2
    full, full_rounds = jax.device_get(_batched_stable(cost, gate))
    assert np.any(full_rounds > 2), "instances too easy to exercise truncation"
    for b in range(len(cost)):
        check_valid_matching(cost[b], gate[b], got[b])
        if full_rounds[b] <= 2:
            np.testing.assert_array_equal(got[b], full[b])


def test_stable_match_rounds_on_conflict_free_and_chain_instances():
    # Distinct first choices: one round.
    cost = np.array([[0.0, 5.0, 5.0], [5.0, 0.0, 5.0], [5.0, 5.0, 0.0]])
    assert int(stable_match(cost, 9.0)[1]) == 1
    # A displacement chain: everyone prefers slot 0, then 1, ...; each slot prefers the
    # higher observation index. Round r settles exactly one more observation.
    k = 6
    chain = 10.0 * (np.arange(k)[None, :] + 1) - np.arange(k)[:, None]
    got, rounds = stable_match(chain, 100.0, rows_per_round=k)
    np.testing.assert_array_equal(got, np.arange(k)[::-1])
    assert int(rounds) == k
    got, rounds = stable_match(chain, 100.0, k, rows_per_round=k)   # bound exactly reached
    np.testing.assert_array_equal(got, np.arange(k)[::-1])
    got, rounds = stable_match(chain, 100.0, k - 1, rows_per_round=k)
    np.testing.assert_array_equal(got, [-1, 4, 3, 2, 1, 0])
    assert int(rounds) == k - 1


def test_stable_match_round_distribution_on_sparse_costs():
    # Realistic: each observation is within the gate of 1-3 landmarks, a few others > gate.
    rng = np.random.default_rng(7)
    batch, num_obs, num_slots, gate = 400, 16, 128, 9.21
    cost = np.full((batch, num_obs, num_slots), np.inf)
    far = rng.random(cost.shape) < 0.1
    cost[far] = gate + 1.0 + rng.random(far.sum()) * 20
    for n in range(3):
        b, k = np.nonzero(rng.integers(1, 4, size=(batch, num_obs)) > n)
        cost[b, k, rng.integers(0, num_slots, size=b.size)] = rng.random(b.size) * gate
    got, rounds = jax.device_get(
        jax.jit(jax.vmap(lambda c: stable_match(c, gate, num_obs + num_slots)))(cost)
    )
    np.testing.assert_array_equal(got, jax.device_get(_batched_greedy(cost, np.full(batch, gate))))
    # Tolerances: with ~1.3 collisions per particle, >= 25% finish in one round, all within 8.
    assert rounds.min() >= 1 and rounds.max() <= 8, np.bincount(rounds)
    assert np.mean(rounds == 1) >= 0.25, np.bincount(rounds)
    assert np.mean(got >= 0) > 0.9


def test_stable_match_rejects_bad_shapes():
    with pytest.raises(ValueError, match=r"\(K, M\)"):
        stable_match(np.zeros(4), 1.0)
    with pytest.raises(ValueError, match="scalar"):
        stable_match(np.zeros((2, 3)), np.ones(2))
    with pytest.raises(ValueError, match="rows_per_round"):
        stable_match(np.zeros((2, 3)), 1.0, rows_per_round=0)


# ----------------------------------------------------------------------------- greedy
@pytest.mark.parametrize("shape", [(1, 1), (1, 5), (5, 1), (4, 6), (6, 4)])
def test_greedy_match_equals_reference(shape):
    cost, gate = random_instances(10 + sum(shape), 300, *shape)
    got = jax.device_get(_batched_greedy(cost, gate))
    for b in range(len(cost)):
        want = greedy_reference(cost[b], gate[b])
        np.testing.assert_array_equal(got[b], want)
        # Both sides rank pairs by the same (cost, k, m) order, so the stable matching is
        # unique and equals the greedy one.
        np.testing.assert_array_equal(want, gale_shapley_reference(cost[b], gate[b]))


def test_greedy_match_eager_jit_vmap_zero_and_edges():
    cost, gate = random_instances(11, 3, 4, 5)
    for b in range(3):
        want = greedy_reference(cost[b], gate[b])
        np.testing.assert_array_equal(greedy_match(cost[b], gate[b]), want)
        np.testing.assert_array_equal(jax.jit(greedy_match)(cost[b], gate[b]), want)
    chex.assert_shape(jax.vmap(greedy_match, in_axes=(0, None))(np.zeros((0, 3, 4)), 1.0), (0, 3))
    chex.assert_shape(
        jax.jit(jax.vmap(greedy_match, in_axes=(0, None)))(np.zeros((0, 3, 4)), 1.0), (0, 3)
    )
    np.testing.assert_array_equal(greedy_match(np.full((3, 2), np.inf), 1.0), [-1, -1, -1])
    np.testing.assert_array_equal(greedy_match(np.zeros((0, 2)), 1.0), np.zeros(0))
    np.testing.assert_array_equal(greedy_match(np.zeros((2, 0)), 1.0), [-1, -1])


# ----------------------------------------------------------------------------- hungarian
def _assignment_cost(cost, match):
    k = np.nonzero(match >= 0)[0]
    return np.asarray(cost, np.float64)[k, match[k]].sum()


@pytest.mark.parametrize("shape", [(1, 6), (6, 1), (4, 7), (7, 4)])
def test_hungarian_match_equals_scipy(shape):
    rng = np.random.default_rng(20 + sum(shape))
    batch = 150
    cost = rng.random((batch,) + shape) * 10.0          # continuous: a unique optimum
    cost[rng.random(cost.shape) < rng.choice([0.0, 0.4, 0.8], size=(batch, 1, 1))] = np.inf
    gate = rng.choice([3.0, 7.0, np.inf], size=batch)
    got = jax.device_get(_batched_hungarian(cost, gate))
    for b in range(batch):
        want = hungarian_reference(cost[b], gate[b])
        check_valid_matching(cost[b], gate[b], got[b])
        assert np.sum(got[b] >= 0) == np.sum(want >= 0), (cost[b], gate[b], got[b], want)
        np.testing.assert_allclose(_assignment_cost(cost[b], got[b]),
                                   _assignment_cost(cost[b], want), rtol=1e-9, atol=1e-9)
        np.testing.assert_array_equal(got[b], want)


def test_hungarian_prefers_more_pairs_then_lower_cost():
    # Greedy takes (0, 0) and strands observation 1; the optimal assignment matches both.
    cost = np.array([[1.0, 2.0], [1.5, np.inf]])
    np.testing.assert_array_equal(greedy_match(cost, 9.0), [0, -1])
    np.testing.assert_array_equal(hungarian_match(cost, 9.0), [1, 0])
    np.testing.assert_array_equal(jax.jit(hungarian_match)(cost, 9.0), [1, 0])


def test_hungarian_edges_and_vmap_zero():
    np.testing.assert_array_equal(hungarian_match(np.array([[0.5]]), 1.0), [0])
    np.testing.assert_array_equal(hungarian_match(np.array([[1.5]]), 1.0), [-1])
    square = np.random.default_rng(29).random((5, 5)) * 10.0
    square[square > 8.0] = np.inf
    np.testing.assert_array_equal(hungarian_match(square, 6.0), hungarian_reference(square, 6.0))
    np.testing.assert_array_equal(hungarian_match(np.full((3, 2), np.inf), 1.0), [-1, -1, -1])
    np.testing.assert_array_equal(hungarian_match(np.full((2, 3), 5.0), 1.0), [-1, -1])
    np.testing.assert_array_equal(hungarian_match(np.zeros((2, 0)), 1.0), [-1, -1])
    for fn in (jax.vmap(hungarian_match, in_axes=(0, None)),
               jax.jit(jax.vmap(hungarian_match, in_axes=(0, None)))):
        chex.assert_shape(fn(np.zeros((0, 3, 4)), 1.0), (0, 3))


# ----------------------------------------------------------------------------- known ids
def test_known_id_cost_matches_numpy():
    obs_ids = np.array([3, -1, 7, 3, 9])
    slot_ids = np.array([7, 3, 3, -1, 9, 2])
    active = np.array([True, True, False, True, False, True])
    want = np.where(
        (obs_ids[:, None] == slot_ids[None, :]) & (obs_ids[:, None] >= 0) & active[None, :],
        0.0, np.inf,
    )
    got = known_id_cost(obs_ids, slot_ids, active)
    chex.assert_shape(got, (5, 6))
    np.testing.assert_array_equal(got, want)
    np.testing.assert_array_equal(jax.jit(known_id_cost)(obs_ids, slot_ids, active), want)
    m, _ = match("known", got, 1.0, None)
    np.testing.assert_array_equal(m, [1, -1, 0, -1, -1])   # obs 3 shares tree 3: lower obs wins
    with pytest.raises(ValueError, match=r"\(K,\), \(M,\) and \(M,\)"):
        known_id_cost(obs_ids, slot_ids, active[:3])


def known_id_births_reference(candidates, obs_ids, slot_ids, active):
    """Loop over observations: born when a candidate with a known id no active slot holds."""
    return np.array([bool(candidates[k]) and obs_ids[k] >= 0
                     and not any(active[m] and slot_ids[m] == obs_ids[k]
                                 for m in range(len(slot_ids)))
                     for k in range(len(obs_ids))], bool).reshape(len(obs_ids))


def random_births(seed, batch, num_obs, num_slots):
    """Ids in [-1, 4) so that repeats, unknown ids and inactive twins are common."""
    rng = np.random.default_rng(seed)
    return (rng.random((batch, num_obs)) < 0.7, rng.integers(-1, 4, (batch, num_obs)),
            rng.integers(-1, 4, (batch, num_slots)), rng.random((batch, num_slots)) < 0.5)


@pytest.mark.parametrize("jit", [False, True])
def test_known_id_births_matches_numpy(jit):
    fn = jax.jit(association.known_id_births) if jit else association.known_id_births
    for candidates, obs_ids, slot_ids, active in zip(*random_births(4, 40, 6, 5)):
        got = fn(candidates, obs_ids, slot_ids, active)
        chex.assert_shape(got, (6,))
        assert got.dtype == jnp.bool_
        np.testing.assert_array_equal(
            got, known_id_births_reference(candidates, obs_ids, slot_ids, active))


def test_known_id_births_under_vmap():
    batch = random_births(5, 16, 7, 9)
    got = jax.jit(jax.vmap(association.known_id_births))(*batch)
    chex.assert_shape(got, (16, 7))
    want = np.stack([known_id_births_reference(*row) for row in zip(*batch)])
    np.testing.assert_array_equal(got, want)
    assert want.any() and not want.all()   # the instances exercise both outcomes


def test_known_id_births_edges():
    # No observations: an empty answer, eagerly, jitted and under vmap.
    none = (np.zeros(0, bool), np.zeros(0, np.int32), np.array([1, 2]), np.array([True, True]))
    chex.assert_shape(association.known_id_births(*none), (0,))
    chex.assert_shape(jax.jit(association.known_id_births)(*none), (0,))
    chex.assert_shape(jax.vmap(association.known_id_births)(
        *(np.broadcast_to(a, (3,) + a.shape) for a in none)), (3, 0))
    # All slots full: only trees not yet in the map are born (capacity is the map's concern,
    # ``landmarks.birth_slots``); an unknown id (-1) is never born, even if a slot says -1.
    slot_ids, active = np.array([0, 1, -1]), np.ones(3, bool)
    obs_ids, candidates = np.array([1, 2, -1, 5, 0]), np.array([True, True, True, True, False])
    got = association.known_id_births(candidates, obs_ids, slot_ids, active)
    np.testing.assert_array_equal(got, [False, True, False, True, False])
    # A deleted (inactive) slot still holding the id does not block a rebirth.
    got = association.known_id_births(np.array([True]), np.array([4]), np.array([4]),
                                      np.array([False]))
    np.testing.assert_array_equal(got, [True])


def test_birth_candidates_restricts_known_ids_only():
    candidates, obs_ids, slot_ids, active = (a[0] for a in random_births(6, 1, 8, 6))
    for kind in ASSOCIATIONS:
        got = association.birth_candidates(kind, candidates, obs_ids, slot_ids, active)
        want = (known_id_births_reference(candidates, obs_ids, slot_ids, active)
                if kind == "known" else candidates)
        np.testing.assert_array_equal(got, want)
    assert not np.array_equal(known_id_births_reference(candidates, obs_ids, slot_ids, active),
                              candidates)


def test_association_cost_matches_numpy():
    rng = np.random.default_rng(8)
    distance = rng.random((5, 6)) * 4.0
    allowed = rng.random((5, 6)) < 0.7
    obs_ids, slot_ids = rng.integers(-1, 4, 5), rng.integers(-1, 4, 6)
    active = rng.random(6) < 0.8
    same = (obs_ids[:, None] == slot_ids[None, :]) & (obs_ids[:, None] >= 0) & active[None, :]
    for kind in ASSOCIATIONS:
        got = jax.jit(association.association_cost, static_argnums=0)(
            kind, distance, allowed, obs_ids, slot_ids, active)
        want = (np.where(allowed & same, 0.0, np.inf) if kind == "known"
                else np.where(allowed, distance, np.inf))
        np.testing.assert_array_equal(got, want)


# ----------------------------------------------------------------------------- dispatch
def test_match_dispatches_every_kind():
    cost, gate = random_instances(30, 1, 6, 8)
    cost, gate = cost[0], gate[0]
    for kind in ASSOCIATIONS:
        got, rounds = jax.jit(match, static_argnums=0)(kind, cost, gate, 14)
        chex.assert_shape(got, (6,))
        assert rounds.dtype == jnp.int32
        if kind == "stable":
            np.testing.assert_array_equal(got, gale_shapley_reference(cost, gate))
        elif kind == "greedy":
            np.testing.assert_array_equal(got, greedy_reference(cost, gate))
            assert int(rounds) == 6
        elif kind == "hungarian":
            check_valid_matching(cost, gate, np.asarray(got))
            assert int(rounds) == 0
        else:   # known ignores the gate
            np.testing.assert_array_equal(got, gale_shapley_reference(cost, np.inf))


def test_match_rejects_unknown_kind():
    with pytest.raises(ValueError, match="'stable', 'greedy', 'hungarian', 'known'"):
        match("nearest", np.zeros((2, 2)), 1.0, None)


def test_top_level_exports_stable_match():
    """``jaxslam.stable_match`` (the lazy top-level export) is the association kernel."""
    import jaxslam

    assert jaxslam.stable_match is association.stable_match
    match, _ = jaxslam.stable_match(jnp.array([[1.0, 2.0], [0.5, 3.0]]), 10.0)
    np.testing.assert_array_equal(match, [1, 0])  # row 1 takes slot 0 (0.5 < 1.0)
