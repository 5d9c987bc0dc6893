"""experiments/self_calibration.py's recovery check against a hand-worked example."""
import types

import numpy as np
import jax.numpy as jnp

from experiments.self_calibration import GROUPS, recovery, true_params
from jaxslam.calibration_residuals import typical_stds
from jaxslam.types import make_observations


def test_recovery_hand_example():
    """Calibrated typical stds 1.0, 1.5, 0.9 and 1.02 times the truth's on the same log, with
    stated relative errors 1 %, 10 %, 5 % and 0.1 %: half-widths 0.0196, 0.196, 0.098 and
    0.00196, so only the heading (ratio 1) lies inside; a group the calibration did not fit
    (no relative_std) has an infinite half-width and counts as inside."""
    truth = true_params(2.0, 2.0)
    controls = jnp.asarray([[0.05, 0.5, -0.02], [0.0, 0.5, 0.1], [-0.1, 0.4, 0.0]])
    obs = make_observations(jnp.asarray([[[3.0, 0.1], [9.0, -0.4]]] * 3),
                            valid=jnp.asarray([[True, True], [True, False], [False, False]]))
    z_range = np.array([3.0, 9.0, 3.0])
    true = np.asarray(typical_stds(truth, np.asarray(controls, np.float64), z_range))
    factor = np.array([1.0, 1.5, 0.9, 1.02])
    info = types.SimpleNamespace(
        typical_std=np.stack([true * 3.0, true * factor]),
        relative_std={"heading": 0.01, "translation": 0.1, "range": 0.05, "bearing": 0.001})
    ratio, half, inside = recovery(truth, info, controls, obs)
    np.testing.assert_allclose(ratio, factor, rtol=1e-12)
    np.testing.assert_allclose(half, 1.96 * np.array([0.01, 0.1, 0.05, 0.001]), rtol=1e-12)
    np.testing.assert_array_equal(inside, [True, False, False, False])
    del info.relative_std["bearing"]
    _, half, inside = recovery(truth, info, controls, obs)
    assert np.isinf(half[3]) and inside[3]
    assert GROUPS == ("heading", "translation", "range", "bearing")
