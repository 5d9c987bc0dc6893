"""The log pipeline: warnings, params files, filter_log (``jaxslam.pipeline``)."""
from __future__ import annotations

import types

import jax
import numpy as np
import pytest

from jaxslam import pipeline
from jaxslam.datasets.log_format import RobotLog
from jaxslam.filter import Trace
from jaxslam.types import FilterConfig, default_params

P = 10


def _trace(steps=20, ess=10.0, invalid=0, dropped=0, resets=0, landmarks=5):
    """A ``Trace`` of a healthy run, with the given fields changed."""
    zeros = np.zeros(steps)
    weights_reset = np.zeros(steps, bool)
    weights_reset[:resets] = True
    num_invalid = np.zeros(steps, int)
    num_invalid[0] = invalid
    num_dropped = np.zeros(steps, int)
    num_dropped[-1] = dropped
    return Trace(mean_pose=np.zeros((steps, 3)), best_pose=np.zeros((steps, 3)),
                 ess=np.full(steps, ess), num_landmarks=np.full(steps, landmarks),
                 resampled=np.zeros(steps, bool), weights_reset=weights_reset,
                 num_invalid_obs=num_invalid, num_dropped_births=num_dropped,
                 match_rounds=zeros, mixture_ratio=zeros, mean_log_likelihood=zeros)


VALID = np.ones((20, 3), bool)


def test_a_healthy_run_has_no_warning():
    assert pipeline.run_warnings(_trace(), VALID, 0.1, P, births=5) == []


@pytest.mark.parametrize("trace, share, births, words", [
    (_trace(invalid=7), 0.1, 5, "7 observations were masked as invalid"),
    (_trace(), 0.8, 5, "80% of the observations matched no landmark"),
    (_trace(dropped=12), 0.1, 5, "12 landmark births were dropped"),
    (_trace(ess=1.0), 0.1, 5, "collapsed"),
    (_trace(resets=3), 0.1, 5, "zero in 3 steps"),
    (_trace(landmarks=0), 0.1, 5, "the final map is empty"),
    (_trace(landmarks=4), 0.1, 13, "13 started; 4 kept"),
])
def test_each_warning(trace, share, births, words):
    warnings = pipeline.run_warnings(trace, VALID, share, P, births)
    assert len(warnings) == 1 and words in warnings[0]


def test_churn_counts_the_landmarks_started_beyond_the_expected_false_alarms():
    """60 valid observations at p_f 0.1: 6 one-off landmarks are the sensor model's own
    clutter, so with 4 kept the warning needs more than 3 * 4 + 6 = 18 started."""
    assert pipeline.run_warnings(_trace(landmarks=4), VALID, 0.1, P, births=18,
                                 false_alarm_probability=0.1) == []
    warnings = pipeline.run_warnings(_trace(landmarks=4), VALID, 0.1, P, births=19,
                                     false_alarm_probability=0.1)
    assert len(warnings) == 1
    assert ("19 started, about 6 of them expected as false alarms at false_alarm_probability "
            "0.1; 4 kept" in warnings[0])
    # without a clutter model every start counts, and the message says nothing of it
    warnings = pipeline.run_warnings(_trace(landmarks=4), VALID, 0.1, P, births=13)
    assert "13 started; 4 kept" in warnings[0]


@pytest.mark.parametrize("share, births, words", [
    (0.8, 5, "80% of the observations matched no landmark although the sensor noise was "
             "calibrated. Likely cause: the pose drifts"),
    (0.1, 13, "(13 started; 4 kept) although the sensor noise was calibrated. Likely causes: "
              "the pose drifts"),
])
def test_calibrated_runs_name_what_calibration_does_not_fix(share, births, words):
    """After a calibration the unmatched and churn warnings no longer advise to calibrate:
    they name the drift past the gate (and, for churn, the existence cap); uncalibrated they
    still do."""
    calibrated = pipeline.run_warnings(_trace(landmarks=4), VALID, share, P, births,
                                       calibrated=True)
    assert len(calibrated) == 1 and words in calibrated[0]
    assert "further than params.association_gate allows" in calibrated[0]
    assert "(calibrate" not in calibrated[0]
    assert ("params.existence_max" in calibrated[0]) == (births == 13)
    plain = pipeline.run_warnings(_trace(landmarks=4), VALID, share, P, births)
    assert len(plain) == 1 and "(calibrate" in plain[0] and "calibrated" not in plain[0]


def test_calibrated_unmatched_and_churn_name_the_drift_once():
    """Both warnings at once: the churn warning points back to the drift the unmatched
    one names instead of repeating it."""
    both = pipeline.run_warnings(_trace(landmarks=4), VALID, 0.8, P, births=13,
                                 calibrated=True)
    assert len(both) == 2
    assert sum(pipeline.DRIFT_PAST_GATE in warning for warning in both) == 1
    assert pipeline.DRIFT_PAST_GATE in both[0]
    assert "Likely causes: the drift named above; or the detector misses" in both[1]


def test_sensor_noise_calibrated_needs_a_sensor_fit_behind_the_settings():
    """Only a calibration whose returned settings rest on a fitted range or bearing group
    counts: none, or one that gave back its starting settings (no samples), does not."""
    info = types.SimpleNamespace
    assert not pipeline.sensor_noise_calibrated(None)
    assert not pipeline.sensor_noise_calibrated(info(samples={}))
    assert not pipeline.sensor_noise_calibrated(info(samples={"heading": 200}))
    assert not pipeline.sensor_noise_calibrated(info(samples={"radius": 40}))  # radius alone
    assert pipeline.sensor_noise_calibrated(info(samples={"range": 90, "bearing": 90}))


@pytest.mark.parametrize("marker, want", [(True, True), (False, False), (None, False)])
def test_a_params_file_says_whether_a_sensor_fit_lies_behind_it(tmp_path, marker, want):
    """``save_params``' [calibration] table round-trips; a file without it (by hand, or
    older), or one that cannot be read, counts as not calibrated; the [params] still load."""
    path = pipeline.save_params(tmp_path / "p.toml", default_params(max_range=9.0),
                                sensor_noise_calibrated=marker)
    assert pipeline.saved_sensor_calibration(path) is want
    assert float(pipeline.load_params(path).max_range) == 9.0
    assert pipeline.saved_sensor_calibration(tmp_path / "missing.toml") is False
    (tmp_path / "bad.toml").write_text("[calibration\n")
    assert pipeline.saved_sensor_calibration(tmp_path / "bad.toml") is False


def _spy_on_warnings(monkeypatch):
    """The ``calibrated`` flag of every ``run_warnings`` call ``filter_log`` makes."""
    seen, real = [], pipeline.run_warnings

    def spy(*args, **kwargs):
        seen.append(kwargs.get("calibrated", False))
        return real(*args, **kwargs)

    monkeypatch.setattr(pipeline, "run_warnings", spy)
    return seen


def test_edges_of_the_warning_thresholds():
    # Exactly at a threshold is no warning: half unmatched, a quarter of steps collapsed,
    # three births per kept landmark.
    assert pipeline.run_warnings(_trace(landmarks=4), VALID, 0.5, P, births=12) == []
    ess = np.full(20, 10.0)
    ess[:5] = 1.0
    assert pipeline.run_warnings(_trace()._replace(ess=ess), VALID, 0.1, P, 5) == []
    assert "no valid observation" in pipeline.run_warnings(
        _trace(landmarks=0), np.zeros((20, 3), bool), 0.0, P)[0]


def test_params_round_trip_through_toml(tmp_path):
    params = default_params(max_range=13.5, rot1_noise=(0.01, 0.02, 0.003))
    path = pipeline.save_params(tmp_path / "sub" / "p.toml", params, comment="a\nb")
    assert path.read_text().startswith("# a\n# b\n")
    back = pipeline.load_params(path)
    for name, value in params._asdict().items():
        np.testing.assert_array_equal(np.asarray(getattr(back, name)), np.asarray(value),
                                      err_msg=name)
    assert np.isinf(float(back.miss_range))  # +inf survives TOML


def _log(steps=30):
    trees = np.array([[2.0, 2.0], [4.0, -2.0], [6.0, 2.0], [8.0, -2.0], [10.0, 2.0]])
    truth = np.stack([0.4 * np.arange(1, steps + 1), np.zeros(steps), np.zeros(steps)], 1)
    offset = trees[None] - truth[:, None, :2]
    z = np.stack([np.hypot(offset[..., 0], offset[..., 1]),
                  np.arctan2(offset[..., 1], offset[..., 0])], -1)
    return RobotLog(time=np.arange(steps, dtype=float), motion_model="odometry",
                    controls=np.tile([0.0, 0.4, 0.0], (steps, 1)), obs_z=z,
                    obs_valid=z[..., 0] < 6.0, truth_pose=truth, truth_landmarks=trees)


@pytest.mark.slow  # 13 s; test_filter_log_calibrates_and_smooths keeps the pipeline
def test_filter_log_without_calibration_runs_the_given_params():
    config = FilterConfig(num_particles=8, max_landmarks=16)
    # The log's sensor sees 6 m: with the default 20 m, trees behind the robot would count
    # as missed and be deleted (that is what calibration's max_range is for).
    params = default_params(range_std_floor=0.05, bearing_std_floor=0.01, max_range=6.0)
    run = pipeline.filter_log(_log(), config, params, jax.random.PRNGKey(0), calibrate=False)
    assert run.calibration is None and run.params is params
    assert run.mean_pose.shape == (30, 3) and run.smoothed_pose is None
    # Exact odometry and observations: the estimate stays on the truth (cm) and maps
    # the five trees.
    assert run.metrics["final_pose_error"] < 0.1
    assert run.metrics["num_trees_mapped"] == 5
    assert run.metrics["valid_observations"] == int(_log().obs_valid.sum())
    assert run.warnings == ()


def test_filter_log_close_loops_needs_smoothing_without_visits():
    config = FilterConfig(num_particles=4, max_landmarks=16)
    for options in (dict(close_loops=True), dict(close_loops=True, smooth=True, visit_gap=3)):
        with pytest.raises(ValueError, match="close_loops needs smooth"):
            pipeline.filter_log(_log(), config, None, calibrate=False, **options)


def test_filter_log_smooth_rounds_reach_the_smoother_and_bad_counts_fail_early(monkeypatch):
    from jaxslam import lineage

    config = FilterConfig(num_particles=8, max_landmarks=16)
    seen = _spy_on_warnings(monkeypatch)
    for bad in (-1, 1.5, True, "2"):
        with pytest.raises(ValueError, match="smooth_rounds must be None"):
            pipeline.filter_log(_log(), config, None, calibrate=False, smooth=True,
                                smooth_rounds=bad)
    runs = {rounds: pipeline.filter_log(_log(40), config, None, jax.random.PRNGKey(0),
                                        calibrate=False, smooth=True, smooth_rounds=rounds)
            for rounds in (None, 0)}
    # The filter runs are the same; only the smoother's weighting differs.
    np.testing.assert_array_equal(runs[None].mean_pose, runs[0].mean_pose)
    assert seen == [False, False]  # not calibrated: the warnings may advise to calibrate
    run = runs[0]
    config_, controls, obs, start = pipeline.log_inputs(_log(40), config)
    history = lineage.trace_lineage(run.trace.lineage, run.estimate.best_particle)
    for rounds in (None, 0):
        path, _ = pipeline.offline_path(history, controls, obs, start, run.params,
                                        config_.motion_model, calibrate_rounds=rounds)
        np.testing.assert_array_equal(runs[rounds].smoothed_pose, path)
    with pytest.raises(ValueError, match="calibrate_rounds must be None"):
        pipeline.offline_path(history, controls, obs, start, run.params,
                              config_.motion_model, calibrate_rounds=-1)
    assert not np.array_equal(runs[None].smoothed_pose, runs[0].smoothed_pose)


def test_filter_log_calibrates_and_smooths(monkeypatch):
    config = FilterConfig(num_particles=8, max_landmarks=16)
    seen = _spy_on_warnings(monkeypatch)
    run = pipeline.filter_log(_log(40), config, None, jax.random.PRNGKey(0), smooth=True,
                              calibration_options=dict(iterations=2))
    assert run.calibration is not None and run.calibration.iterations >= 1
    assert run.smoothed_pose.shape == (40, 3)
    assert run.metrics["smoothed_ate_rmse"] < 0.1
    # The calibrated usable range is the log's 6 m (its largest range, +2 %), so trees left
    # behind are not deleted as missed: all five stay mapped.
    assert 5.5 <= float(run.params.max_range) <= 6.0 * 1.02 + 1e-6
    assert run.metrics["num_trees_mapped"] == 5
    assert seen == [True]  # the warnings know the settings came from this log


def _radius_log(radius_noise, with_radii=True):
    """3 observation rows, 30 steps: row k is born into slot k at step 0 and matched to it
    after; tree k has radius 0.1 + 0.1 k with scatter 0.02 m (fixed draws)."""
    from jaxslam.lineage import LineagePath
    from jaxslam.types import Observations

    steps = 30
    birth = np.full((steps, 3), -1)
    birth[0] = [0, 1, 2]
    match = np.tile(np.arange(3), (steps, 1))
    match[0] = -1
    history = LineagePath(np.zeros((steps, 3)), match, birth)
    scatter = np.random.default_rng(0).normal(0.0, 0.02, (steps, 3))
    radius = (0.1 + 0.1 * np.arange(3) + scatter) if with_radii else np.zeros((steps, 3))
    obs = Observations(z=np.ones((steps, 3, 2)), valid=np.ones((steps, 3), bool),
                       radius=radius, landmark_id=-np.ones((steps, 3), int))
    return history, obs, default_params(radius_noise=radius_noise)


def test_unused_radius_hint_names_the_scatter_only_when_the_radii_go_unused():
    """Radii measured and radius_noise 0: one warning with the count and the scatter that
    ``noise_fit.radius_noise_from_history`` gives for the same ids; no warning when the
    radius is in use or the log has none."""
    from jaxslam.noise_fit import radius_noise_from_history

    history, obs, params = _radius_log(0.0)
    hint, values = pipeline.unused_radius_hint(history, obs, params)
    ids = np.tile(np.arange(3), (30, 1))  # row k is tree k at every step
    want, used = radius_noise_from_history(ids, obs.radius, obs.valid)
    assert used == 90 and 0.01 < want < 0.04  # the 0.02 m scatter, widened for its tails
    assert values == {"radius_scatter": want}
    assert len(hint) == 1 and "90 observations carry a trunk radius" in hint[0]
    assert f"params.radius_noise={want:.3g}" in hint[0] and "16.27" in hint[0]
    assert pipeline.unused_radius_hint(*_radius_log(0.05)) == ([], {})
    assert pipeline.unused_radius_hint(*_radius_log(0.0, with_radii=False)) == ([], {})


@pytest.mark.slow  # 13 s, as the run above; the hint's own test keeps it in the default tier
def test_filter_log_warns_when_the_logs_radii_go_unused():
    """The log above with trunk radii (0.2 m, 1 cm scatter) and radius_noise 0: the run's
    warnings name them and metrics carry the within-tree scatter (about 0.01 m, within 50 %:
    about 30 samples); with radius_noise set, neither."""
    config = FilterConfig(num_particles=8, max_landmarks=16)
    params = default_params(range_std_floor=0.05, bearing_std_floor=0.01, max_range=6.0)
    log = _log()
    radius = 0.2 + np.random.default_rng(0).normal(0.0, 0.01, log.obs_valid.shape)
    log = log._replace(obs_radius=radius)
    run = pipeline.filter_log(log, config, params, jax.random.PRNGKey(0), calibrate=False)
    assert len(run.warnings) == 1 and "carry a trunk radius" in run.warnings[0]
    assert 0.005 < run.metrics["radius_scatter"] < 0.015
    used = pipeline.filter_log(log, config, params._replace(radius_noise=0.01),
                               jax.random.PRNGKey(0), calibrate=False)
    assert used.warnings == () and "radius_scatter" not in used.metrics
