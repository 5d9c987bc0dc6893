"""The paired t test of two runs' per-step log evidence (``jaxslam.score_comparison``)."""
import numpy as np
import pytest
from scipy import stats

from jaxslam import score_comparison as sc


def test_score_gain_by_hand():
    """Six steps in three blocks of two: block sums of d = c - i are 1, 3 and 5, so D = 9
    and se^2 = 3 / 2 ((1 - 3)^2 + 0 + (5 - 3)^2) = 12."""
    incumbent = np.zeros(6)
    candidate = np.array([0.0, 1.0, 1.0, 2.0, 2.0, 3.0])
    found = sc.score_gain(candidate, incumbent, num_blocks=3)
    assert found.gain == 9.0 and found.blocks == 3
    np.testing.assert_allclose(found.std_error, np.sqrt(12.0), rtol=1e-12)
    np.testing.assert_allclose(found.t, 9.0 / np.sqrt(12.0), rtol=1e-12)
    # Swapping the runs flips the sign of D and t, not se.
    swapped = sc.score_gain(incumbent, candidate, num_blocks=3)
    assert swapped.gain == -9.0 and swapped.std_error == found.std_error


def test_uneven_blocks_follow_array_split():
    """T = 7 in B = 3 blocks: 3, 2 and 2 steps (``numpy.array_split``)."""
    difference = np.arange(7.0)
    found = sc.score_gain(difference, np.zeros(7), num_blocks=3)
    sums = np.array([0 + 1 + 2, 3 + 4, 5 + 6], float)
    expected = np.sqrt(3 / 2 * np.sum((sums - sums.sum() / 3) ** 2))
    np.testing.assert_allclose(found.std_error, expected, rtol=1e-12)


def test_standard_error_of_independent_steps_is_sqrt_t_sigma():
    """For independent d_t with std sigma, se(D) estimates sqrt(T) sigma. With B = 20 blocks
    its relative error has std about 1 / sqrt(2 (B - 1)) = 0.16; the tolerance, 0.5, is three
    of those (fixed seed)."""
    rng = np.random.default_rng(0)
    difference = rng.normal(0.0, 2.0, 4000)
    found = sc.score_gain(difference, np.zeros(4000))
    np.testing.assert_allclose(found.std_error, np.sqrt(4000) * 2.0, rtol=0.5)


def test_false_alarm_rate_is_the_level():
    """Under the null (equal runs up to independent noise) the test says "better" in about
    5 % of pairs: 1000 pairs (fixed seed), binomial std 0.7 %, bounds 2.5-8 % (about four
    stds below, four above)."""
    rng = np.random.default_rng(1)
    hits = sum(sc.significantly_better(rng.normal(0, 1, 400), rng.normal(0, 1, 400))
               for _ in range(1000))
    assert 25 <= hits <= 80


def test_one_spike_does_not_decide_but_a_spread_gain_does():
    """A run with one step 1e5 nats lower loses the plain sum by 1e5 but the test calls the
    other run better only if its gain is spread over the log: with one outlying block t is
    about 1 (module docstring)."""
    rng = np.random.default_rng(2)
    base = rng.normal(-5.0, 1.0, 3800)
    spiked = base + rng.normal(0.0, 0.5, 3800)
    spiked[1234] -= 1e5
    assert np.sum(base) - np.sum(spiked) > 9e4
    found = sc.score_gain(base, spiked)
    assert 0.9 < found.t < 1.1
    assert not sc.significantly_better(base, spiked)
    better = base + 0.1 + rng.normal(0.0, 0.5, 3800)  # 0.1 nats a step, 380 in all
    assert sc.significantly_better(better, base)
    assert not sc.significantly_better(base, better)


def test_threshold_is_students_t_quantile():
    """D / se just above and just below the 95 % quantile of t with B - 1 = 2 dof."""
    quantile = stats.t.ppf(0.95, 2)
    incumbent = np.zeros(6)
    candidate = np.array([0.0, 1.0, 1.0, 2.0, 2.0, 3.0])  # t = 9 / sqrt(12) = 2.598
    assert 9 / np.sqrt(12) < quantile  # 2.920
    assert not sc.significantly_better(candidate, incumbent, num_blocks=3)
    assert sc.significantly_better(candidate + 0.2, incumbent, num_blocks=3)
    assert (sc.score_gain(candidate + 0.2, incumbent, 3).t > quantile)


def test_edges():
    same = np.ones(10)
    found = sc.score_gain(same, same)
    assert (found.gain, found.std_error, found.t, found.blocks) == (0.0, 0.0, 0.0, 10)
    assert not sc.significantly_better(same, same)
    # Every block gains the same: se 0 and t +inf.
    assert sc.score_gain(same + 1.0, same).t == np.inf
    assert sc.significantly_better(same + 1.0, same)
    # One step: no two blocks, so the sums decide.
    assert sc.significantly_better(np.array([2.0]), np.array([1.0]))
    assert not sc.significantly_better(np.array([1.0]), np.array([2.0]))
    assert np.isnan(sc.score_gain(np.array([2.0]), np.array([1.0])).std_error)
    # A broken run (a non-finite step) is better only than another broken one.
    broken = same.copy()
    broken[3] = -np.inf
    assert not sc.significantly_better(broken, same)
    assert sc.significantly_better(same, broken)
    assert not sc.significantly_better(broken, broken)
    assert np.isnan(sc.score_gain(same, broken).t)


@pytest.mark.parametrize("call, message", [
    (lambda: sc.score_gain(np.ones(5), np.ones(6)), "cover the same steps"),
    (lambda: sc.score_gain(np.ones((2, 3)), np.ones((2, 3))), r"non-empty \(T,\)"),
    (lambda: sc.score_gain(np.ones(0), np.ones(0)), r"non-empty \(T,\)"),
    (lambda: sc.score_gain(np.ones(5), np.ones(5), num_blocks=1), "num_blocks must be >= 2"),
    (lambda: sc.significantly_better(np.ones(5), np.ones(5), level=0.0), r"level must be in"),
    (lambda: sc.significantly_better(np.ones(5), np.ones(5), level=1.5), r"level must be in"),
])
def test_bad_input_is_named(call, message):
    with pytest.raises(ValueError, match=message):
        call()
