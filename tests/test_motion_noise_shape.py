"""The motion M-step fits the shape of the smoothed residuals, not their shrunk scale.

A smoothed path absorbs part of each move's error (a group's residuals keep a mean square of
about r_g / n_g of the noise variance), and the variance components set the scale; the burst
mixture and the tail factor must not shrink the std a second time (``noise_fit``,
``unit_mean_square``).
"""
import numpy as np
import pytest

from jaxslam import smoothing
from jaxslam.calibration_residuals import Residuals
from jaxslam.noise_fit import BURST_LIMITS, fit_bursts, motion_noise_update, unit_mean_square

CORE = np.array([0.01, 0.04, 0.01])  # core std of rot1, trans, rot2
EPS, KAPPA = 0.1, 4.0  # burst share and scale of the simulated moves
NO_BURSTS = (0.0, 5.0)


def test_unit_mean_square_scales_each_column_to_one():
    """Each column ends at mean square 1 whatever its scale, and the result does not depend
    on the input's scale (the shape fits see the shape only)."""
    rng = np.random.default_rng(0)
    white = rng.standard_normal((50, 2)) * [0.3, 2.0]
    out = unit_mean_square(white)
    np.testing.assert_allclose(np.mean(out**2, axis=0), 1.0, rtol=1e-12)
    np.testing.assert_allclose(unit_mean_square(white * [7.0, 0.01]), out, rtol=1e-12)
    # float64 reference of one entry
    assert out[3, 1] == pytest.approx(white[3, 1] / np.sqrt(np.mean(white[:, 1] ** 2)),
                                      rel=1e-12)


def test_unit_mean_square_edges():
    """A column of zeros stays zero (no NaN); no rows at all stay no rows. (The moves it gets
    are finite: ``motion_noise_update`` keeps only moves with a smoothed pose.)"""
    white = np.c_[np.zeros(10), np.arange(10.0)]
    out = unit_mean_square(white)
    assert np.all(out[:, 0] == 0.0) and np.all(np.isfinite(out))
    assert unit_mean_square(np.zeros((0, 2))).shape == (0, 2)


def test_a_clipped_burst_scale_keeps_the_fitted_core():
    """Bursts 20x a unit core (share 0.05) are clipped to the limit's scale 10, and the core
    stays the fitted one: the clipped variance is left to the filter as outliers, not spread
    over every move (``fit_bursts``). 4000 moves: the core's sampling error is about 1.2 %;
    5 % is four of those."""
    rng = np.random.default_rng(3)
    scale = np.where(rng.random(4000) < 0.05, 20.0, 1.0)
    white = rng.standard_normal((4000, 2)) * scale[:, None]
    eps, core, kappa = fit_bursts(white)
    assert kappa == BURST_LIMITS[1]
    assert core == pytest.approx(1.0, rel=0.05)
    assert eps == pytest.approx(0.05, abs=0.015)


def _shrunk_residuals(shrink: float, bursts: bool, moves: int = 3000, seed: int = 1):
    """Residuals of moves whose error is (optionally) a burst mixture, multiplied by
    ``shrink`` as a smoothed path's are, with ``move_std`` at the true total std (the variance
    components' scale 1 then states the truth)."""
    rng = np.random.default_rng(seed)
    scale = np.where(rng.random(moves) < EPS, KAPPA, 1.0) if bursts else np.ones(moves)
    error = rng.standard_normal((moves, 3)) * CORE * scale[:, None]
    total = CORE * np.sqrt(1 - EPS + EPS * KAPPA**2) if bursts else CORE
    return Residuals(
        true_moves=np.ones((moves, 3)), measured_moves=np.ones((moves, 3)),
        move_error=shrink * error, move_features=np.ones((3, moves, 3)),
        move_std=np.tile(total, (moves, 1)), measured_z=np.ones((0, 2)),
        observation_error=np.zeros((0, 2)), filter_error=np.zeros((0, 2)),
        observation_std=np.zeros((0, 2)), obs_step=np.zeros(0, int),
        obs_landmark=np.zeros(0, int), sightings=np.zeros(0, int)), total


@pytest.mark.parametrize("shrink", [1.0, 0.5, 0.2])
def test_bursts_and_core_do_not_depend_on_the_shrinkage(shrink):
    """Burst-mixture moves (eps 0.1, kappa 4) with their residuals shrunk to 1, 1/4 and 1/25
    of the variance: the fitted core std, share and scale are those of the noise. Spread of
    the three over 20 seeds of 3000 moves (shrink 0.5, measured): core std 3.6 %, share
    0.008, scale 0.12; the bounds 12 %, 0.03 and 0.4 are 3.3-3.8 of them. Fitted to the
    shrunk residuals themselves, the core came out at ``shrink`` times the truth."""
    res, _ = _shrunk_residuals(shrink, bursts=True)
    rows, eps, kappa, fitted = motion_noise_update(res, smoothing.NoiseScales(), NO_BURSTS)
    assert fitted
    std = rows.sum(axis=1)  # features are ones: each std is its row's sum
    np.testing.assert_allclose(std, CORE, rtol=0.12)
    assert abs(eps - EPS) < 0.03
    assert abs(kappa - KAPPA) < 0.4


@pytest.mark.parametrize("shrink", [1.0, 0.3])
def test_gaussian_moves_keep_the_variance_components_scale(shrink):
    """Gaussian moves, shrunk evenly: no bursts, and the std is the scale the variance
    components state (here the truth). The tail factor max(1, q95 / 3.84) can only widen:
    its 95 % quantile of 3000 chi-square-1 samples has a sampling error of about 3.5 % in
    variance, 1.7 % in std, so 5 % is three of those. (This guards the no-burst branch
    against widening; the old code passed it too, as an even shrink leaves the shape.)"""
    res, total = _shrunk_residuals(shrink, bursts=False)
    rows, eps, kappa, fitted = motion_noise_update(res, smoothing.NoiseScales(), NO_BURSTS)
    assert not fitted and (eps, kappa) == NO_BURSTS
    np.testing.assert_allclose(rows.sum(axis=1), total, rtol=0.05)


@pytest.mark.xfail(strict=True, reason="behaviour kept: one mean-square factor a column "
                   "corrects the average shrinkage, not each move's (noise_fit."
                   "unit_mean_square; docs/results.md, self_calibration)")
def test_uneven_shrinkage_is_not_read_as_bursts():
    """Gaussian moves whose residuals keep uneven shares R_ii of their variance are a scale
    mixture once shrunk, and the fit reads bursts in them. Half the moves at 0.05 and half
    at 0.85 (a path whose observations are dense on some stretches and absent on others):
    bursts on 10 of 10 seeds (share 0.25, scale 4.1, core 0.45 of the truth; shares uniform
    in 0.05-0.85: none of 10). Dividing each residual by sqrt(R_ii) removed them but made the
    calibrated filter's final error worse on every held-out row measured (the bursts give
    the motion proposal a tail it uses), so the behaviour is kept and recorded here."""
    res, _ = _shrunk_residuals(1.0, bursts=False)
    share = np.where(np.random.default_rng(7).random(len(res.move_error)) < 0.5, 0.05, 0.85)
    res = res._replace(move_error=res.move_error * np.sqrt(share)[:, None])
    _, _, _, fitted = motion_noise_update(res, smoothing.NoiseScales(), NO_BURSTS)
    assert not fitted
