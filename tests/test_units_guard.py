"""Units guard (issue 18): logs in degrees / millimetres / mostly malformed are named."""
from __future__ import annotations

import jax
import numpy as np
import pytest

from jaxslam import pipeline
from jaxslam.datasets.log_format import RobotLog
from jaxslam.types import FilterConfig, default_params
from jaxslam.validation import check_observation_units, observation_units_warnings

EXPECTED = "ranges in metres and bearings in radians in [-pi, pi]"


def _obs(steps=20, k=6, seed=0):
    """A good forestry-like log: ranges 5-40 m, bearings over the full circle [rad]."""
    rng = np.random.default_rng(seed)
    z = np.stack([rng.uniform(5.0, 40.0, (steps, k)),
                  rng.uniform(-np.pi, np.pi, (steps, k))], -1)
    valid = np.ones((steps, k), bool)
    valid[:, -1] = False  # padding rows, with junk that must be ignored
    z[:, -1] = [1e6, 1e3]
    return z, valid


def test_a_good_log_has_no_warning_and_passes():
    z, valid = _obs()
    assert observation_units_warnings(z, valid) == []
    assert observation_units_warnings(z, valid, max_range=20.0) == []
    check_observation_units(z, valid)
    # No valid row: nothing to judge (run_warnings says "no valid observation").
    assert observation_units_warnings(z, np.zeros_like(valid)) == []
    check_observation_units(z, np.zeros_like(valid))


def test_a_few_bad_rows_are_no_units_warning():
    z, valid = _obs()
    z[0, 0, 1] = 4.0   # one bearing beyond pi, one NaN: masked and counted by the filter,
    z[1, 0, 0] = np.nan  # but no sign of wrong units
    assert observation_units_warnings(z, valid) == []


def test_degrees_full_circle():
    z, valid = _obs()
    z[..., 1] = np.degrees(z[..., 1])
    w = observation_units_warnings(z, valid)
    assert "bearings look like degrees" in w[0] and EXPECTED in w[0]
    n = int(valid.sum())
    beyond = int((np.abs(z[valid][:, 1]) > np.pi).sum())
    assert f"{beyond} of {n}" in w[0]
    assert "are malformed" in w[1] and f"{beyond} with a bearing outside [-pi, pi]" in w[1]
    with pytest.raises(ValueError, match="degrees"):
        check_observation_units(z, valid)


def test_degrees_narrow_field_of_view_warns_and_refuses():
    z, valid = _obs()
    z[..., 1] = np.linspace(-30.0, 30.0, z.shape[1])[None]  # a +-30 degree camera, in degrees
    w = observation_units_warnings(z, valid)
    assert any("bearings look like degrees" in m for m in w)
    with pytest.raises(ValueError, match="refusing"):
        check_observation_units(z, valid)


def test_bearings_in_zero_to_two_pi():
    z, valid = _obs()
    z[..., 1] = np.mod(z[..., 1], 2 * np.pi)
    w = observation_units_warnings(z, valid)
    assert "radians in [0, 2 pi]" in w[0] and "none is negative" in w[0]
    check_observation_units(z, valid)  # a warning, not a refusal


def test_millimetres_warn_and_refuse():
    z, valid = _obs()
    z[..., 0] *= 1000.0
    w = observation_units_warnings(z, valid)
    assert len(w) == 1 and "ranges look wrong" in w[0] and "millimetres" in w[0]
    assert "centimetres" not in w[0] and EXPECTED in w[0]
    median = np.median(z[valid][:, 0])
    assert f"median valid range is {median:.4g} m" in w[0]
    with pytest.raises(ValueError, match="millimetres"):
        check_observation_units(z, valid)


def test_centimetres_warn_but_are_not_certain():
    z, valid = _obs()
    z[..., 0] = np.random.default_rng(1).uniform(2.0, 9.0, z.shape[:-1]) * 100.0  # cm
    w = observation_units_warnings(z, valid)
    assert len(w) == 1 and "centimetres" in w[0] and "millimetres" not in w[0]
    check_observation_units(z, valid)  # median under 1000: warned, not refused


def test_ranges_far_beyond_max_range():
    z, valid = _obs()
    z[..., 0] = 60.0  # plausible metres, but 20 times a 3 m max_range
    assert observation_units_warnings(z, valid) == []
    w = observation_units_warnings(z, valid, max_range=3.0)
    assert len(w) == 1 and "more than 10 times max_range 3 m" in w[0]
    assert observation_units_warnings(z, valid, max_range=np.inf) == []


def test_mostly_nan_names_the_count():
    z, valid = _obs()
    n = int(valid.sum())
    bad = np.zeros_like(valid)
    bad[:14, :5] = True  # 70 of 100 valid rows
    z[bad, 0] = np.nan
    w = observation_units_warnings(z, valid)
    assert len(w) == 1
    assert f"70 of {n} observations marked valid (70%) are malformed" in w[0]
    assert "70 NaN or inf, 0 with a range <= 0, 0 with a bearing" in w[0]
    check_observation_units(z, valid)  # some rows are usable: warned, not refused


def test_half_malformed_is_no_warning():
    z, valid = _obs()
    z[:10, :5, 0] = -1.0  # exactly 50 of 100
    assert observation_units_warnings(z, valid) == []


def test_all_invalid_warns_and_refuses():
    z, valid = _obs()
    z[..., 0] = np.where(np.arange(z.shape[1]) % 2 == 0, -3.0, 0.0)[None]  # <= 0 ranges
    w = observation_units_warnings(z, valid)
    assert len(w) == 1 and "all 100 observations marked valid are malformed" in w[0]
    assert "100 with a range <= 0" in w[0]
    with pytest.raises(ValueError, match="all 100 observations"):
        check_observation_units(z, valid)


def test_bad_shape_is_refused():
    with pytest.raises(ValueError, match="shape"):
        observation_units_warnings(np.zeros((4, 3)), np.ones(4, bool))


def _log(steps=20, degrees=False):
    trees = np.array([[2.0, 2.0], [4.0, -2.0], [6.0, 2.0], [8.0, -2.0]])
    truth = np.stack([0.4 * np.arange(1, steps + 1), np.zeros(steps), np.zeros(steps)], 1)
    offset = trees[None] - truth[:, None, :2]
    z = np.stack([np.hypot(offset[..., 0], offset[..., 1]),
                  np.arctan2(offset[..., 1], offset[..., 0])], -1)
    if degrees:
        z[..., 1] = np.degrees(z[..., 1])
    return RobotLog(time=np.arange(steps, dtype=float), motion_model="odometry",
                    controls=np.tile([0.0, 0.4, 0.0], (steps, 1)), obs_z=z,
                    obs_valid=z[..., 0] < 6.0, truth_pose=truth, truth_landmarks=trees)


@pytest.mark.slow  # 13 s; test_hostile_inputs keeps the degrees warning on filter_log
def test_filter_log_warns_about_a_log_in_degrees():
    log = _log(degrees=True)
    run = pipeline.filter_log(log, FilterConfig(num_particles=4, max_landmarks=16),
                              default_params(), jax.random.PRNGKey(0), calibrate=False)
    assert "bearings look like degrees" in run.warnings[0]
    assert EXPECTED in run.warnings[0]
    # The filter's own masked count still follows.
    assert any("masked as invalid" in m for m in run.warnings)
