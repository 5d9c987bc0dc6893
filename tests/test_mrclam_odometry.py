"""experiments/mrclam_odometry.py's helpers against hand values (the data runs in the
experiment; these check the arithmetic it reports)."""
import numpy as np

from experiments.mrclam_odometry import true_moves, weighted_slope
from jaxslam.datasets.odometry import odometry_path


def test_weighted_slope_by_hand():
    """w = 1/std^2: (1 * 1 * 2 + 0.25 * 2 * 3) / (1 * 1 + 0.25 * 4) = 3.5 / 2 = 1.75; the
    zero reading and the non-finite move are left out."""
    measured = np.array([1.0, 2.0, 0.0, 1.0])
    true = np.array([2.0, 3.0, 5.0, np.nan])
    std = np.array([1.0, 2.0, 1.0, 1.0])
    assert weighted_slope(measured, true, std) == 1.75


def test_true_moves_of_an_integrated_path_are_its_moves():
    """Poses integrated from moves give those moves back (the decomposition nearest the
    commanded one), to float64 rounding."""
    rng = np.random.default_rng(0)
    moves = np.stack([rng.uniform(-0.2, 0.2, 40), rng.uniform(0.05, 0.3, 40),
                      rng.uniform(-0.2, 0.2, 40)], 1)
    poses = np.asarray(odometry_path(moves, np.zeros(3)), np.float64)
    np.testing.assert_allclose(true_moves(poses, moves[1:], 0.01), moves[1:], atol=1e-9)
