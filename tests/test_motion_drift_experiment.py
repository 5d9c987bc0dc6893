"""experiments/motion_drift.py's measures against plain loops and logs of known structure."""
import numpy as np
import pytest

import experiments.motion_drift as drift
from jaxslam.types import default_params


def test_robust_variance_of_a_normal_and_with_spikes():
    """20,000 draws of N(0, 0.3^2), seed 0: (1.4826 MAD)^2 within 5 % of 0.09 (the MAD
    variance's relative standard error is about 2.33 / sqrt(N) = 1.6 % here, so 5 % is 3 of
    them). With 1 % of the draws replaced by spikes of 30 (100 std), which raise the mean
    square about 100-fold, it stays within 10 % of 0.09."""
    rng = np.random.default_rng(0)
    draws = rng.normal(0.0, 0.3, 20_000)
    assert drift.robust_variance(draws) == pytest.approx(0.09, rel=0.05)
    spiked = draws.copy()
    spiked[::100] = 30.0
    assert drift.robust_variance(spiked) == pytest.approx(0.09, rel=0.10)
    assert np.isnan(drift.robust_variance([]))


def test_windowed_variance_against_a_plain_loop():
    """T = 100 (not a multiple of 3 or 7): the sums of consecutive windows, the last T mod n
    steps left out, then the robust variance; a window longer than the log gives nan."""
    errors = np.random.default_rng(1).normal(size=100)
    got = drift.windowed_variance(errors, (1, 3, 7, 101))
    for value, n in zip(got[:3], (1, 3, 7)):
        sums = [sum(errors[i * n + j] for j in range(n)) for i in range(100 // n)]
        median = np.median(sums)
        mad = np.median([abs(s - median) for s in sums])
        assert value == pytest.approx((1.4826 * mad) ** 2, rel=1e-12)
    assert np.isnan(got[3])


def test_windowed_variance_refuses_an_empty_window():
    with pytest.raises(ValueError, match="window 0: a window holds at least 1 step"):
        drift.windowed_variance(np.zeros(10), (1, 0))


def _ar1_growth(windows, rho: float, bias_variance: float) -> np.ndarray:
    """Closed-form g(n) of unit white noise plus a stationary AR(1) bias (coefficient rho,
    variance bias_variance): V(n) = n + bias_variance (n + 2 sum_k (n - k) rho^k)."""
    out = []
    for n in windows:
        lags = np.arange(1, n)
        bias = bias_variance * (n + 2.0 * np.sum((n - lags) * rho**lags))
        out.append((n + bias) / (n * (1.0 + bias_variance)))
    return np.asarray(out)


def test_growth_of_white_noise_plus_a_slow_bias_against_its_closed_form():
    """40,000 steps of N(0, 1) plus a stationary AR(1) bias (rho 0.9, variance 0.5; seed 3):
    g(n) is 1 at n = 1 by construction and within 25 % of the closed form (2.09, 4.36, 5.81 at
    n = 5, 20, 50; 7 in the limit) at n <= 50, where 800 or more windows give the MAD variance
    a relative standard error of 8 % or less (25 % is 3 of them). Shuffled, the same values
    are white and Gaussian: g within 25 % of 1, so the ratio g / shuffled g carries the bias."""
    rng = np.random.default_rng(3)
    rho, bias_variance, steps = 0.9, 0.5, 40_000
    innovation = rng.normal(0.0, np.sqrt(bias_variance * (1 - rho**2)), steps)
    bias = np.empty(steps)
    bias[0] = rng.normal(0.0, np.sqrt(bias_variance))
    for t in range(1, steps):
        bias[t] = rho * bias[t - 1] + innovation[t]
    errors = rng.normal(size=steps) + bias
    windows = (1, 5, 20, 50)
    expected = _ar1_growth(windows, rho, bias_variance)
    np.testing.assert_allclose(expected, [1.0, 2.086, 4.365, 5.806], atol=0.001)
    got = drift.growth(errors, windows)
    assert got[0] == pytest.approx(1.0, rel=1e-12)
    np.testing.assert_allclose(got, expected, rtol=0.25)
    np.testing.assert_allclose(drift.shuffled_growth(errors, windows), 1.0, rtol=0.25)


def test_spikes_raise_growth_but_not_its_ratio_to_the_shuffled_errors():
    """White errors with 5 % spikes of 10 std (20,000 steps, seed 4): g(20) exceeds 1.5 (the
    MAD of single steps sees the core, a 20-step sum holds a spike on average), and the
    shuffled twin, equally white, gives the same within 25 % at n <= 20 (1000 windows or
    more: relative standard error about 7 %)."""
    rng = np.random.default_rng(4)
    steps = 20_000
    errors = rng.normal(size=steps) * np.where(rng.uniform(size=steps) < 0.05, 10.0, 1.0)
    windows = (1, 2, 5, 10, 20)
    got = drift.growth(errors, windows)
    assert got[-1] > 1.5
    np.testing.assert_allclose(got / drift.shuffled_growth(errors, windows), 1.0, rtol=0.25)


def test_heading_errors_per_move_and_across_the_wrap():
    """True headings 3.0, 3.1, then -3.1 (a +0.083 rad step across pi): the measured moves
    turn 0.11 (split over rot1 and rot2) and 0.093, so the errors are 0.01 and 0.01, not
    2 pi off."""
    start = np.array([0.0, 0.0, 3.0])
    poses = np.array([[1.0, 0.0, 3.1], [2.0, 0.0, -3.1]])
    step = 2 * np.pi - 6.2
    controls = np.array([[0.05, 1.0, 0.06], [0.0, 1.0, step + 0.01]])
    np.testing.assert_allclose(drift.heading_errors(controls, start, poses), [0.01, 0.01],
                               atol=1e-12)
    with pytest.raises(ValueError, match=r"controls \(3, 3\) for 2 poses"):
        drift.heading_errors(np.zeros((3, 3)), start, poses)


def test_with_heading_scale_changes_only_the_heading_terms():
    params = default_params()
    scaled = drift.with_heading_scale(params, 2.0)
    np.testing.assert_allclose(scaled.rot1_noise, 2.0 * np.asarray(params.rot1_noise))
    np.testing.assert_allclose(scaled.rot2_noise, 2.0 * np.asarray(params.rot2_noise))
    assert float(scaled.association_heading_std) == pytest.approx(
        2.0 * float(params.association_heading_std))
    np.testing.assert_array_equal(scaled.trans_noise, params.trans_noise)
    np.testing.assert_array_equal(scaled.range_noise, params.range_noise)


@pytest.mark.parametrize("argv, message", [
    ([], "name --mrclam-robots and/or --victoria-park-params"),
    (["--mrclam-robots", "1", "--heading-scales", "1", "0"],
     "--heading-scales [1.0, 0.0]: positive factors"),
    (["--mrclam-robots", "1", "--heading-scales", "2", "--filter-keys", "0"],
     "--filter-keys 0: at least 1 with --heading-scales"),
    (["--mrclam-robots", "1", "--command-delay", "inf"],
     "--command-delay inf: a finite number of seconds"),
    (["--mrclam-robots", "1", "--replicates", "0"], "--replicates 0: at least 1"),
    (["--victoria-park-params", "x.toml", "--observation-scale", "0"],
     "--observation-scale 0.0: a positive factor"),
])
def test_main_refuses_what_it_cannot_run(argv, message, capsys):
    with pytest.raises(SystemExit):
        drift.main(argv)
    assert message in capsys.readouterr().err


@pytest.mark.slow  # 20 s: three filter runs and fifteen smoothings
def test_kappa_is_near_one_on_logs_drawn_from_the_model():
    """Three held-out simulated loops (``experiments/self_calibration.make_log``: 250 moves,
    40 trees, odometry 2x Table 1, sensor 2x Table 2, keys 7, 8, 9), the filter and the model
    both at the noise they were drawn with (no bursts, as the simulator draws none): the
    median of kappa(1) and of kappa(2) over the three lies within a factor 1.6 of 1. One log's
    MAD variance has a relative standard error of 15 % and 21 % at 250 and 125 windows
    (2.33 / sqrt(N)), four replicates add about half of that; single logs gave kappa(1) 0.62,
    0.84 and 1.08 when this test was written: the replicates, drawn around the smoothed
    solution with its association, do not carry the log's wrong matches, so kappa leans low
    (module docstring)."""
    import jax

    from experiments.self_calibration import make_log, true_params
    from jaxslam.types import FilterConfig

    params = true_params(2.0, 2.0)._replace(motion_outlier_probability=0.0)
    config = FilterConfig(num_particles=30, max_landmarks=96, max_obs=12)
    kappas = []
    for key in (7, 8, 9):
        controls, obs, truth, _ = make_log(jax.random.PRNGKey(key), params)
        result = drift.drift_against_model(config, params, params, controls, obs, truth[0],
                                           replicates=4, windows=(1, 2), bursts=False)
        assert result.replicate_variance.shape == (2, 4)
        kappas.append(result.kappa)
    median = np.median(kappas, axis=0)
    np.testing.assert_array_less(np.abs(np.log(median)), np.log(1.6))


def test_command_delay_is_the_loader_s(monkeypatch):
    """``mrclam_robot_log`` hands the delay to the loader (``load_mrclam(...,
    command_delay=)``, tested in tests/datasets/test_mrclam.py); a delay that is not finite
    is refused, as is the command-line flag."""
    from jaxslam.datasets import mrclam

    calls = []
    monkeypatch.setattr(mrclam, "load_mrclam", lambda *args, **kwargs: calls.append(
        (args, kwargs)) or "log")
    log, config = drift.mrclam_robot_log("DIR", 3, 0.2)
    assert log == "log" and config.num_particles == 100 and config.max_landmarks == 64
    assert calls == [(("DIR", 3, 8), {"command_delay": 0.2})]
