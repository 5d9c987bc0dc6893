"""experiments/self_calibration.py's recovery check against hand-worked examples."""
import types

import numpy as np
import jax.numpy as jnp

from experiments.self_calibration import recovery, true_params
from jaxslam.calibration_residuals import typical_stds
from jaxslam.types import make_observations

ODOMETRY = jnp.asarray([[0.05, 0.5, -0.02], [0.0, 0.5, 0.1], [-0.1, 0.4, 0.0]])
# Rows (0, 0), (0, 1), (1, 0) valid: ranges 3, 9, 3; (1, 1) valid but NaN (not counted).
OBS = make_observations(jnp.asarray([[[3.0, 0.1], [9.0, -0.4]], [[3.0, 0.2], [jnp.nan, 0.0]],
                                     [[5.0, 0.0], [6.0, 0.0]]]),
                        valid=jnp.asarray([[True, True], [True, True], [False, False]]))


def _true_typical(truth):
    return np.asarray(typical_stds(truth, np.asarray(ODOMETRY, np.float64),
                                   np.array([3.0, 9.0, 3.0])))


def test_recovery_hand_example():
    """EM's typical stds 1.0, 1.5, 0.9 and 1.02 times the truth's on the same log, with
    stated relative errors 1 %, 10 %, 5 % and 0.1 %: half-widths 0.0196, 0.196, 0.098 and
    0.00196, so only the heading (ratio 1) lies inside; a group the calibration did not fit
    (no relative_std) has an infinite half-width and counts as inside."""
    truth = true_params(2.0, 2.0)
    true = _true_typical(truth)
    factor = np.array([1.0, 1.5, 0.9, 1.02])
    info = types.SimpleNamespace(
        typical_std=np.stack([true * 3.0, true * factor]), noise_scales=None,
        relative_std={"heading": 0.01, "translation": 0.1, "range": 0.05, "bearing": 0.001})
    found = recovery(truth, info, ODOMETRY, OBS)
    np.testing.assert_allclose(found.ratio, factor, rtol=1e-12)
    np.testing.assert_allclose(found.half_width, 1.96 * np.array([0.01, 0.1, 0.05, 0.001]),
                               rtol=1e-12)
    np.testing.assert_array_equal(found.inside, [True, False, False, False])
    assert not found.scaled
    del info.relative_std["bearing"]
    found = recovery(truth, info, ODOMETRY, OBS)
    assert np.isinf(found.half_width[3]) and found.inside[3]


def test_recovery_divides_out_the_search_scales():
    """Returned settings with motion x2 and observation x4 on top of an EM estimate equal to
    the truth: the ratio is EM's (1 everywhere, inside any interval) and the run is flagged."""
    truth = true_params(4.0, 2.0)
    true = _true_typical(truth)
    info = types.SimpleNamespace(
        typical_std=np.stack([true, true * np.array([2.0, 2.0, 4.0, 4.0])]),
        noise_scales=types.SimpleNamespace(motion_scale=2.0, observation_scale=4.0),
        relative_std={"heading": 0.01, "translation": 0.01, "range": 0.01, "bearing": 0.01})
    found = recovery(truth, info, ODOMETRY, OBS)
    np.testing.assert_allclose(found.ratio, np.ones(4), rtol=1e-12)
    assert found.inside.all() and found.scaled
