"""experiments/proposal_study.py's keys: one per grid point, and the filter runs' keys never
one of the simulation's (the logs of information_floor, lineage_check and loop_closure_study
come from the same ``point_keys`` and ``make_logs``)."""
import jax
import numpy as np
import pytest

from experiments.proposal_study import (clustered_interval, main, point_keys, select_runs,
                                       wilson)


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


def test_clustered_interval_by_hand():
    """4 forests of 10 runs, exceeding in 1, 4, 7 and 4: rates 0.1, 0.4, 0.7, 0.4, mean 0.4,
    sample std sqrt((0.09 + 0 + 0.09 + 0) / 3) = 0.24495, SE 0.12247, Student t with 3
    degrees of freedom 3.18245: 0.4 +- 0.38977 = [0.0102, 0.7898], wider than Wilson's
    [0.2635, 0.5540] for 16 of 40 on both sides."""
    exceed = np.zeros((4, 10), bool)
    for forest, count in enumerate((1, 4, 7, 4)):
        exceed[forest, :count] = True
    low, high = clustered_interval(exceed.ravel(), 4)
    half = 3.182446305284263 * np.sqrt(0.06) / 2
    np.testing.assert_allclose([low, high], [0.4 - half, 0.4 + half], rtol=1e-9)


def test_clustered_interval_is_never_narrower_than_wilson():
    """Forests with equal rates (no spread) or no event at all: the binomial width stands
    (Wilson at the normal quantile of the level, 1.959964 for 95 %)."""
    z = 1.959963984540054
    even = np.tile(np.r_[np.ones(2, bool), np.zeros(8, bool)], 10)  # 2 of 10 in each forest
    np.testing.assert_allclose(clustered_interval(even, 10), wilson(20, 100, z), rtol=1e-9)
    low, high = clustered_interval(np.zeros(200, bool), 10)
    assert low == 0.0 and high == wilson(0, 200, z)[1] > 0.0


def test_clustered_interval_covers_when_the_rate_depends_on_the_forest():
    """Simulated studies like the proposal study's (50 forests x 20 runs), each forest's own
    rate drawn from Beta(1.2, 2.8) (mean 0.3; forest-to-forest spread like the default's at
    the hard point, design effect ~5): over 400 studies the forest-clustered interval holds
    the true mean in 90-99 % (nominal 95 %), the binomial Wilson interval over runs in
    under 70 %. And a rare event over few forests (10 x 20 runs, every forest at 1 %): the
    forest interval holds 1 % at least as often as Wilson's, in 90 % or more."""
    rng = np.random.default_rng(7)
    hold, hold_wilson = 0, 0
    for _ in range(400):
        rates = rng.beta(1.2, 2.8, size=50)
        exceed = rng.random((50, 20)) < rates[:, None]
        low, high = clustered_interval(exceed.ravel(), 50)
        hold += low <= 0.3 <= high
        low, high = wilson(int(exceed.sum()), exceed.size)
        hold_wilson += low <= 0.3 <= high
    assert 0.90 <= hold / 400 <= 0.99
    assert hold_wilson / 400 < 0.7
    rare, rare_wilson = 0, 0
    for _ in range(400):
        exceed = rng.random(200) < 0.01
        low, high = clustered_interval(exceed, 10)
        rare += low <= 0.01 <= high
        low, high = wilson(int(exceed.sum()), exceed.size)
        rare_wilson += low <= 0.01 <= high
    assert rare >= rare_wilson and rare / 400 >= 0.9


@pytest.mark.parametrize("runs, forests", [(10, 1), (10, 3), (0, 0)])
def test_clustered_interval_bad_shapes(runs, forests):
    with pytest.raises(ValueError, match="forests"):
        clustered_interval(np.zeros(runs, bool), forests)


def test_select_runs_picks_forests_in_study_order():
    """Forest f of a study of R runs in F forests holds runs f R / F onward: forests 1 and 3
    of 4 x 5 runs, first 2 of each, are runs 5, 6, 15, 16; bad forests or counts are refused
    with the flag's name."""
    np.testing.assert_array_equal(select_runs(20, 4, [1, 3], 2), [5, 6, 15, 16])
    np.testing.assert_array_equal(select_runs(20, 4), np.arange(20))
    with pytest.raises(ValueError, match=r"--only-forests \[4\]"):
        select_runs(20, 4, [4])
    with pytest.raises(ValueError, match="--per-forest 6"):
        select_runs(20, 4, None, 6)
    with pytest.raises(ValueError, match="names a forest twice"):
        select_runs(20, 4, [1, 1])


def test_a_subset_runs_with_the_keys_it_has_in_the_whole_study(tmp_path):
    """``--only-forests 1 --per-forest 1`` runs log 2 of a 4-log, 2-forest study with that
    log's own key: its final error equals the whole study's error of log 2 (rtol 1e-5: the
    same float32 program, vmapped over 1 log instead of 2)."""
    common = ["--runs", "4", "--forests", "2", "--wobble", "0.3", "--odometry", "6",
              "--particles", "5", "--proposals", "motion"]
    main(common + ["--chunk", "2", "--errors", str(tmp_path / "all.npz")])
    main(common + ["--chunk", "1", "--only-forests", "1", "--per-forest", "1",
                   "--errors", str(tmp_path / "one.npz")])
    whole = np.load(tmp_path / "all.npz")["0.3/6/5/motion"]
    one = np.load(tmp_path / "one.npz")["0.3/6/5/motion"]
    assert whole.shape == (4,) and one.shape == (1,)
    np.testing.assert_allclose(one[0], whole[2], rtol=1e-5)
    assert abs(one[0] - whole[3]) > 1e-3  # the neighbour's key would give another run
