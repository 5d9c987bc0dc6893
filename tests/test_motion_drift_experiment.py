"""experiments/motion_drift.py's measures against plain loops and logs of known structure."""
import numpy as np
import pytest

import experiments.motion_drift as drift
from jaxslam.types import default_params


def test_robust_variance_of_a_normal_and_with_spikes():
    """20,000 draws of N(0, 0.3^2), seed 0: (1.4826 MAD)^2 within 5 % of 0.09 (the MAD
    variance's relative standard error is about 1.6 % at this N, so 5 % is 3 of them); 1 % of
    the draws replaced by spikes of 30 (100 std) move it by less than 10 %, while the
    mean square grows 100-fold."""
    rng = np.random.default_rng(0)
    draws = rng.normal(0.0, 0.3, 20_000)
    assert drift.robust_variance(draws) == pytest.approx(0.09, rel=0.05)
    spiked = draws.copy()
    spiked[::100] = 30.0
    assert drift.robust_variance(spiked) == pytest.approx(0.09, rel=0.10)
    assert np.mean(spiked**2) > 50 * 0.09
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


def test_growth_is_one_for_white_errors_and_grows_with_a_drift():
    """White errors (20,000 steps, seed 2): g(n) within 25 % of 1 for n <= 20 (at n = 20, 1000
    windows: the MAD variance's relative standard error is about 7 %, so 25 % is over 3 of
    them). Adding a slowly varying bias (a random walk with steps of 0.05 of the white std)
    makes g grow: above 2 at n = 50 and larger at n = 200 than at n = 20; g(1) = 1 by
    construction."""
    rng = np.random.default_rng(2)
    white = rng.normal(size=20_000)
    g_white = drift.growth(white, (1, 2, 5, 10, 20))
    assert g_white[0] == pytest.approx(1.0, rel=1e-12)
    np.testing.assert_allclose(g_white, 1.0, rtol=0.25)
    drifting = white + np.cumsum(rng.normal(0.0, 0.05, white.size))
    g_drift = drift.growth(drifting, (1, 20, 50, 200))
    assert g_drift[0] == pytest.approx(1.0, rel=1e-12)
    assert g_drift[2] > 2.0
    assert g_drift[3] > g_drift[1]


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
    (["--mrclam-robots", "1", "--replicates", "0"], "--replicates 0: at least 1"),
    (["--victoria-park-params", "x.toml", "--observation-scale", "0"],
     "--observation-scale 0.0: a positive factor"),
])
def test_main_refuses_what_it_cannot_run(argv, message, capsys):
    with pytest.raises(SystemExit):
        drift.main(argv)
    assert message in capsys.readouterr().err
