"""``noise_fit.std_relative_error``: the stated relative error of a fitted noise std, against
the closed forms it must reproduce (independent Gaussian, Laplace, AR(1)), its coverage on
heavy-tailed samples, and its edges. NumPy, float64, fixed seeds."""
import numpy as np
import pytest

from jaxslam.noise_fit import std_relative_error


def _gaussian_figure(count: int) -> float:
    return 1.0 / np.sqrt(2.0 * count)


def test_independent_gaussian_gives_the_chi_square_figure():
    """n = 10,000: 100 batches of 100, so the batch estimate is within about 7 % (one sigma,
    1 / sqrt(2 x 99)) of 1 / sqrt(2 n); the result is never below it. Bound: 1.3x (4 sigma)."""
    white = np.random.default_rng(0).standard_normal(10_000)
    stated = std_relative_error(white)
    assert _gaussian_figure(10_000) <= stated <= 1.3 * _gaussian_figure(10_000)


def test_heavy_tails_widen_it_by_the_kurtosis():
    """Laplace samples (kurtosis 6): SE(s) / s = sqrt((6 - 1) / (4 n)), 1.58x the Gaussian
    figure. Tolerance 20 %: the batch estimate's own error, about 7 % x sqrt(kurtosis of a
    batch's mean of squares ~ 1), with margin."""
    white = np.random.default_rng(1).laplace(size=10_000)
    expected = np.sqrt(5.0 / (4 * 10_000))
    np.testing.assert_allclose(std_relative_error(white), expected, rtol=0.2)


def test_correlated_steps_widen_it():
    """Gaussian AR(1) with rho = 0.8: the squares are correlated with rho^2 at lag 1, so the
    variance of their mean grows by (1 + rho^2) / (1 - rho^2) = 4.56 and the relative error
    by its square root, 2.13x the Gaussian figure. Batches of 100 steps against a
    correlation length of about 3 steps; tolerance 20 %."""
    rng = np.random.default_rng(2)
    rho, n = 0.8, 10_000
    white = np.empty(n)
    white[0] = rng.standard_normal()
    for t in range(1, n):
        white[t] = rho * white[t - 1] + np.sqrt(1 - rho**2) * rng.standard_normal()
    expected = np.sqrt((1 + rho**2) / (1 - rho**2)) * _gaussian_figure(n)
    np.testing.assert_allclose(std_relative_error(white), expected, rtol=0.2)


def test_intervals_hold_the_truth_on_heavy_tailed_samples():
    """400 samples of 400 Student-t (5 degrees of freedom, kurtosis 9) scaled to unit
    variance; the rms is the estimate and 1 +- 1.96 x the stated error its interval. With
    20 batches the stated error is itself uncertain, and the rms of t samples is skewed, so
    coverage is checked in [85 %, 99 %] against 95 % nominal; the Gaussian figure's
    intervals, about half as wide, hold the truth in under 80 % (it is what the test must
    tell apart)."""
    rng = np.random.default_rng(3)
    samples = rng.standard_t(5, size=(400, 400)) / np.sqrt(5 / 3)
    estimate = np.sqrt(np.mean(samples**2, axis=1))
    stated = np.array([std_relative_error(row) for row in samples])
    inside = np.abs(estimate - 1.0) <= 1.96 * stated
    gaussian = np.abs(estimate - 1.0) <= 1.96 * _gaussian_figure(400)
    assert 0.85 <= inside.mean() <= 0.99
    assert gaussian.mean() < 0.8


def test_degrees_of_freedom_of_a_least_squares_fit_set_the_width():
    """Residuals of a least-squares fit keep only its redundancy nu of their n rows: with a
    random 400 x 340 design, e = (I - H) eps has nu = 60 degrees of freedom, and the variance
    estimate e^T e / nu is chi-square / nu. Over 400 draws (fixed seed) of eps ~ N(0, 1) the
    std's stated interval 1 +- 1.96 x std_relative_error(e, nu) must hold sigma = 1 in
    [88 %, 99 %] of them (binomial +-3 sigma around 95 % is [92 %, 98 %]; the batch means
    over correlated residuals add their own error); the same residuals counted as 400
    independent samples give intervals 2.6x too narrow, holding it in about 55 % (2 Phi(1.96
    x 0.035 / 0.091) - 1; asserted under 70 %, 6 binomial sigma above)."""
    rng = np.random.default_rng(6)
    rows, unknowns, draws = 400, 340, 400
    design = rng.standard_normal((rows, unknowns))
    q, _ = np.linalg.qr(design)
    noise = rng.standard_normal((draws, rows))
    residual = noise - (noise @ q) @ q.T  # (I - H) eps, H = Q Q^T
    nu = rows - unknowns
    estimate = np.sqrt(np.sum(residual**2, axis=1) / nu)
    stated = np.array([std_relative_error(e, nu) for e in residual])
    as_independent = np.array([std_relative_error(e) for e in residual])
    assert 0.88 <= np.mean(np.abs(estimate - 1.0) <= 1.96 * stated) <= 0.99
    assert np.mean(np.abs(estimate - 1.0) <= 1.96 * as_independent) < 0.7
    assert np.all(stated >= 1.0 / np.sqrt(2.0 * nu))  # never below chi-square with nu


def test_degrees_of_freedom_of_a_smoothed_path_are_not_counted_twice():
    """A path-like least squares: a 1-D random walk of 250 unit-noise moves with a position
    fix (std 0.5) every 10 steps; the move residuals keep nu of 250 degrees of freedom and
    are correlated over a few steps, which the batch means measure. Over 400 draws (fixed
    seed) the stated interval with nu must hold sigma in [90 %, 99 %] (binomial +-3 sigma
    around 95 % is [92 %, 98 %], with margin for the batch estimate's own error); scaling
    the batch figure by sqrt(250 / nu) as well would hold it in every draw."""
    rng = np.random.default_rng(8)
    steps, every, fix_std, draws = 250, 10, 0.5, 400
    moves = np.eye(steps) - np.eye(steps, k=-1)
    fixes = np.eye(steps)[every - 1::every] / fix_std
    design = np.vstack([moves, fixes])
    hat = design @ np.linalg.solve(design.T @ design, design.T)
    nu = steps - np.trace(hat[:steps, :steps])
    residual = (rng.standard_normal((draws, len(design))) @ (np.eye(len(design)) - hat).T)
    residual = residual[:, :steps]
    estimate = np.sqrt(np.sum(residual**2, axis=1) / nu)
    stated = np.array([std_relative_error(e, nu) for e in residual])
    inside = np.abs(estimate - 1.0) <= 1.96 * stated
    assert nu < 0.5 * steps  # the fixes leave most of each move's error to the path
    assert 0.90 <= inside.mean() <= 0.99
    twice = np.abs(estimate - 1.0) <= 1.96 * stated * np.sqrt(steps / nu)
    assert twice.mean() > inside.mean()


def test_degrees_of_freedom_edges():
    """nu >= n or None: the figure for n samples; nu below 1 counts as 1; nu sets the
    Gaussian floor 1 / sqrt(2 nu), below which the result never falls, and leaves the batch
    figure as it is."""
    white = np.random.default_rng(7).standard_normal(400)
    plain = std_relative_error(white)
    assert std_relative_error(white, None) == plain
    assert std_relative_error(white, 400.0) == plain
    assert std_relative_error(white, 1e6) == plain
    assert std_relative_error(white, 0.01) == std_relative_error(white, 1.0)
    assert std_relative_error(white, 100.0) == pytest.approx(1.0 / np.sqrt(200.0), rel=1e-12)
    heavy = np.random.default_rng(9).standard_t(3, size=400)  # batch figure above the floor
    assert std_relative_error(heavy, 390.0) == std_relative_error(heavy) > _gaussian_figure(390)
    assert std_relative_error(np.arange(1.0, 11.0), 2.5) == pytest.approx(
        1.0 / np.sqrt(2 * 2.5), rel=1e-12)


@pytest.mark.parametrize("white, expected", [
    (np.zeros(0), np.inf),                                   # nothing fitted
    (np.full(5, np.nan), np.inf),                           # nothing finite
    (np.arange(1.0, 11.0), _gaussian_figure(10)),            # under 16 samples
    (np.r_[np.ones(14), 30.0], _gaussian_figure(15)),        # 15: still the floor
    (np.zeros(100), _gaussian_figure(100)),                  # no spread at all
])
def test_edges(white, expected):
    assert std_relative_error(white) == expected


def test_sixteen_samples_use_the_batches():
    """At 16 samples (4 batches of 4) the batch estimate applies: one huge residual in the
    last batch puts the batch means at 1, 1, 1 and (3 + 900) / 4 = 225.75, far over the
    Gaussian figure (0.49 against 0.18)."""
    white = np.r_[np.ones(15), 30.0]
    means = np.array([1.0, 1.0, 1.0, (3.0 + 900.0) / 4])
    expected = 0.5 * np.std(means, ddof=1) / 2.0 / np.mean(white**2)
    np.testing.assert_allclose(std_relative_error(white), expected, rtol=1e-12)
    assert std_relative_error(white) > 2 * _gaussian_figure(16)


def test_non_finite_samples_are_dropped():
    """NaN and inf residuals (moves the smoother gave no pose) do not enter."""
    white = np.random.default_rng(4).standard_normal(400)
    padded = np.concatenate([white[:200], [np.nan, np.inf, -np.inf], white[200:]])
    assert std_relative_error(padded) == std_relative_error(white)


def _residuals(steps: int = 300, samples: int = 500, seed: int = 5):
    from jaxslam.calibration_residuals import Residuals

    rng = np.random.default_rng(seed)
    moves = np.ones((steps, 3))
    moves[7] = np.nan  # a move the smoother gave no pose: not a sample
    return Residuals(
        true_moves=moves, measured_moves=np.ones((steps, 3)),
        move_error=rng.standard_normal((steps, 3)) * [0.01, 0.05, 0.02],
        move_features=np.ones((3, steps, 3)),
        move_std=np.tile([0.01, 0.05, 0.02], (steps, 1)),
        measured_z=np.ones((samples, 2)),
        observation_error=rng.laplace(size=(samples, 2)) * [0.1, 0.01],
        filter_error=np.zeros((samples, 2)), observation_std=np.tile([0.1, 0.01], (samples, 1)),
        obs_step=np.arange(samples), obs_landmark=np.zeros(samples, int),
        sightings=np.array([samples]))


def test_group_errors_whiten_each_group_as_the_fit_does():
    """The heading group's residual is rot1 + rot2 over hypot of their stds, translation's
    its own, the sensor groups' the used observations'; moves without a smoothed pose and
    unused observations are left out; unfitted groups are absent."""
    from jaxslam.noise_fit import group_relative_errors

    res = _residuals()
    used = np.arange(500) % 5 != 0
    errors = group_relative_errors(res, used, motion=True, observation=True)
    keep = np.arange(300) != 7
    e, s = res.move_error[keep], res.move_std[keep]
    assert errors["heading"] == std_relative_error((e[:, 0] + e[:, 2]) / np.hypot(s[:, 0],
                                                                                  s[:, 2]))
    assert errors["translation"] == std_relative_error(e[:, 1] / s[:, 1])
    white = res.observation_error[used] / res.observation_std[used]
    assert errors["range"] == std_relative_error(white[:, 0])
    assert errors["bearing"] == std_relative_error(white[:, 1])
    # with the smoother's redundancies each group counts as that many degrees of freedom
    redundancy = np.array([40.0, 55.0, 350.0, 390.0])
    reduced = group_relative_errors(res, used, motion=True, observation=True,
                                    degrees_of_freedom=redundancy)
    assert reduced["heading"] == std_relative_error((e[:, 0] + e[:, 2]) / np.hypot(s[:, 0],
                                                                                   s[:, 2]), 40.0)
    assert reduced["translation"] == std_relative_error(e[:, 1] / s[:, 1], 55.0)
    assert reduced["range"] == std_relative_error(white[:, 0], 350.0)
    assert reduced["bearing"] == std_relative_error(white[:, 1], 390.0)
    assert reduced["heading"] > 2.5 * errors["heading"]  # sqrt(299 / 40) = 2.7
    assert set(group_relative_errors(res, used, motion=False, observation=True)) == {
        "range", "bearing"}
    assert group_relative_errors(res, used, motion=False, observation=False) == {}


def test_stated_errors_come_from_the_m_steps_behind_the_returned_settings():
    """Three M-steps; the settings returned are the second's: its motion error (0.2) and the
    first's sensor errors (the second fitted no sensor) are stated, not the third's; so is
    the second's burst verdict (none fitted), not the first's or the third's."""
    from jaxslam.self_calibration import _MStep, _stated_errors

    first = _MStep({}, 1.0, True, True, 400, {"heading": 0.1, "translation": 0.1,
                                              "range": 0.01, "bearing": 0.01}, True)
    second = _MStep({}, 1.0, True, False, 0, {"heading": 0.2, "translation": 0.2}, False)
    third = _MStep({}, 1.0, True, True, 500, {"heading": 0.3, "translation": 0.3,
                                              "range": 0.03, "bearing": 0.03}, True)
    errors, samples, bursts = _stated_errors([first, second, third], second, 250)
    assert errors == {"heading": 0.2, "translation": 0.2, "range": 0.01, "bearing": 0.01}
    assert samples == {"heading": 250, "translation": 250, "range": 400, "bearing": 400}
    assert bursts is False
    assert _stated_errors([first, second, third], third, 250)[0]["range"] == 0.03
    assert _stated_errors([first, second, third], third, 250)[2] is True
    # A sensor-only M-step says nothing of bursts: the latest motion fit's verdict stands.
    sensor_only = _MStep({}, 1.0, False, True, 300, {"range": 0.02, "bearing": 0.02}, False)
    assert _stated_errors([first, sensor_only], sensor_only, 250)[2] is True
    # The starting settings returned (no M-step behind them): nothing is stated.
    assert _stated_errors([first, second, third], None, 250) == ({}, {}, None)


def test_groups_the_log_barely_determines_are_named():
    """A group is named when 1.96 relative_std exceeds 0.5 (Victoria Park's heading: 0.467,
    +-92 %); 0.49 is not; unfitted (absent or inf) groups and the radius are not."""
    from jaxslam.self_calibration import LOOSE_INTERVAL, loose_interval_warnings

    assert LOOSE_INTERVAL == 0.5
    lines = loose_interval_warnings({"heading": 0.467, "translation": 0.25,
                                     "range": 0.019, "bearing": float("inf"), "radius": 3.0})
    assert len(lines) == 1
    assert "heading noise (95 % interval +-92 % of the fitted std)" in lines[0]
    assert "wider heading noise" in lines[0]
    assert loose_interval_warnings({}) == []
    assert len(loose_interval_warnings({"translation": 0.26, "range": 0.3})) == 2
