"""experiments/proposal_study.py's keys: one per grid point, and the filter runs' keys never
one of the simulation's (the logs of information_floor, lineage_check and loop_closure_study
come from the same ``point_keys`` and ``make_logs``)."""
import jax
import numpy as np

from experiments.proposal_study import point_keys


def _as_tuples(keys) -> set:
    return {tuple(np.asarray(k).tolist()) for k in keys}


def _simulation_keys(key_logs, forests: int) -> set:
    """Every key ``make_logs`` draws from: fold_in(key_logs, f) and both halves of its split
    (the forest's and its runs')."""
    keys = set()
    for forest in range(forests):
        folded = jax.random.fold_in(key_logs, forest)
        keys |= _as_tuples([folded]) | _as_tuples(jax.random.split(folded))
    return keys


def test_point_keys_distinct_across_the_grid():
    """The study's grid (wobble 0 / 0.3 m x odometry 2 / 6, and 1-6 in between) and seeds
    700 / 800 give distinct logs' keys and distinct filter keys."""
    points = [(seed, w, o) for seed in (700, 800) for w in (0.0, 0.3)
              for o in (1.0, 2.0, 4.0, 6.0)]
    logs, filters = zip(*(point_keys(*p) for p in points))
    assert len(_as_tuples(logs)) == len(points)
    assert len(_as_tuples(filters)) == len(points)
    assert not _as_tuples(logs) & _as_tuples(filters)


def test_filter_keys_are_none_of_the_simulations():
    """``split(key_filters, R)`` (``run_point``: one key a run) shares no key with the
    simulation of 50 forests; the derivation it replaced (``fold_in(key, 1)``, forest 1's
    key) did: its runs 0 and 1 drew with forest 1's forest and noise keys."""
    key_logs, key_filters = point_keys(700, 0.3, 6.0)
    simulation = _simulation_keys(key_logs, 50)
    assert not _as_tuples(jax.random.split(key_filters, 1000)) & simulation
    old = _as_tuples(jax.random.split(jax.random.fold_in(key_logs, 1), 1000))
    assert old & simulation == _as_tuples(jax.random.split(jax.random.fold_in(key_logs, 1)))
