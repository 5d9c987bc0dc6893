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
from jaxslam.noise_fit import motion_noise_update, unit_mean_square

CORE = np.array([0.01, 0.04, 0.01])  # core std of rot1, trans, rot2
EPS, KAPPA = 0.1, 4.0  # burst share and scale of the simulated moves
NO_BURSTS = (0.0, 5.0)


def test_unit_mean_square_against_numpy():
    rng = np.random.default_rng(0)
    white = rng.standard_normal((50, 2)) * [0.3, 2.0]
    out = unit_mean_square(white)
    expected = white / np.sqrt(np.mean(white**2, axis=0))
    np.testing.assert_allclose(out, expected, rtol=1e-12)
    np.testing.assert_allclose(np.mean(out**2, axis=0), 1.0, rtol=1e-12)


def test_unit_mean_square_keeps_a_zero_column():
    """A column of zeros (no residual left) stays zero instead of turning into NaN."""
    white = np.c_[np.zeros(10), np.arange(10.0)]
    out = unit_mean_square(white)
    assert np.all(out[:, 0] == 0.0)
    assert np.all(np.isfinite(out))


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
    of the variance: the fitted core std, share and scale are those of the noise. 3000 moves:
    the core std's sampling error is about 1.5 %, the share's about 0.006; 10 % and 0.03 are
    over five of them (the mixture fit adds little at a 4x scale ratio). Fitted to the shrunk
    residuals themselves, the core came out at ``shrink`` times the truth."""
    res, _ = _shrunk_residuals(shrink, bursts=True)
    rows, eps, kappa, fitted = motion_noise_update(res, smoothing.NoiseScales(), NO_BURSTS)
    assert fitted
    std = rows.sum(axis=1)  # features are ones: each std is its row's sum
    np.testing.assert_allclose(std, CORE, rtol=0.10)
    assert abs(eps - EPS) < 0.03
    assert abs(kappa - KAPPA) < 0.4


@pytest.mark.parametrize("shrink", [1.0, 0.3])
def test_gaussian_moves_keep_the_variance_components_scale(shrink):
    """Gaussian moves: no bursts, and the std is the scale the variance components state
    (here the truth) within the tail factor's sampling error (its 95 % quantile of 3000
    chi-square-1 samples: about 4 % in variance; 5 % in std)."""
    res, total = _shrunk_residuals(shrink, bursts=False)
    rows, eps, kappa, fitted = motion_noise_update(res, smoothing.NoiseScales(), NO_BURSTS)
    assert not fitted and (eps, kappa) == NO_BURSTS
    np.testing.assert_allclose(rows.sum(axis=1), total, rtol=0.05)
