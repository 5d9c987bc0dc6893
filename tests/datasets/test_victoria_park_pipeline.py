"""Victoria Park end to end (the runner ``experiments/victoria_park_pipeline.py``): batched
trunk detection, steering-bias calibration, the settings file, FastSLAM on a segment, GPS
evaluation.

The runner lives in experiments/ (not a library module); the project root is on pytest's
path (``pythonpath = ["."]``), so it imports as ``experiments.victoria_park_pipeline``.
Tests that need the data skip when ``default_victoria_park_dir()`` is absent; the full run is
``@pytest.mark.slow``. Tolerances are stated at each assertion.
"""
import inspect
import tomllib
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from experiments import victoria_park_pipeline as vps
from jaxslam.datasets import victoria_park as vpm
from jaxslam.detect import detect_trunks
from jaxslam.smoothing import VARIANCE_ROUNDS, smooth_path
from jaxslam.types import FilterConfig, Params, default_params
from jaxslam.validation import check_params

DATA_DIR = vpm.default_victoria_park_dir()
HAVE_DATA = (DATA_DIR / vpm.ZIP_NAME).is_file()
SKIP_REASON = (f"Victoria Park data not found at {DATA_DIR} (set ${vpm.ENV_DATA_DIR} to the "
               "folder holding victoria_park_ascii.zip, aa3_dr.mat and aa3_gpsx.mat)")
SEGMENT = 300


@pytest.fixture(scope="module")
def park(tmp_path_factory):
    if not HAVE_DATA:
        pytest.skip(SKIP_REASON)
    return vpm.load_victoria_park(DATA_DIR, cache_dir=tmp_path_factory.mktemp("vp_cache"))


@pytest.fixture(scope="module")
def segment_log(park):
    return vpm.victoria_park_log(park)


@pytest.fixture(scope="module")
def log_detections(segment_log):
    """``detect_scans`` of all 7,230 scans (about 10 s; shared by the calibration tests)."""
    return vps.detect_scans(segment_log.scan_ranges, segment_log.scan_angles)


# ------------------------------------------------------------------------------- no data needed


def _synthetic_scan(trunks, angles, wall=None):
    """Ranges (B,) of a 2D scan seeing circles (cx, cy, r); +inf where nothing is hit."""
    ranges = np.full(angles.shape, np.inf)
    direction = np.stack([np.cos(angles), np.sin(angles)], -1)
    for cx, cy, r in trunks:
        along = direction @ np.array([cx, cy])
        perp_sq = cx * cx + cy * cy - along ** 2
        hit = (perp_sq <= r * r) & (along > 0)
        distance = along - np.sqrt(np.maximum(r * r - perp_sq, 0.0))
        ranges = np.where(hit, np.minimum(ranges, distance), ranges)
    return ranges


@pytest.mark.parametrize("method", ["centroid", "kasa"])
def test_detect_scans_matches_per_scan_detection(method):
    angles = vpm.laser_angles()
    trunks = [[(8.0, 1.0, 0.3), (12.0, -4.0, 0.25)], [(5.0, 3.0, 0.2)], []]
    scans = np.stack([_synthetic_scan(t, angles) for t in trunks])
    scans[:, :12] = 0.83  # the vehicle body, as in the real log
    batched = vps.detect_scans(scans, angles, max_obs=4, dtype=jnp.float64, method=method)
    settings = vps.detector_settings(method=method)
    del settings["method"]
    for t in range(len(trunks)):
        single = detect_trunks(jnp.asarray(scans[t]), jnp.asarray(angles), method, max_obs=4,
                               **settings)
        np.testing.assert_array_equal(batched.valid[t], single.valid)
        np.testing.assert_allclose(batched.z[t], single.z, atol=1e-9)
        assert int(batched.valid[t].sum()) == len(trunks[t])
        # Noise-free arcs: Kasa centres to 1 cm; the centroid lies in front of the centre by
        # about 2 r / pi (within 0.3 r, beam quantisation).
        valid = np.asarray(batched.valid[t])
        for cx, cy, r in trunks[t]:
            gap = np.hypot(cx, cy) - np.asarray(batched.z[t, :, 0])[valid]
            best = gap[np.argmin(np.abs(gap - (0.0 if method == "kasa" else 2 * r / np.pi)))]
            if method == "kasa":
                assert abs(best) < 0.01
            else:
                assert abs(best - 2 * r / np.pi) < 0.3 * r
    summary = vps.summarize_detections(batched)
    assert summary.total == 3 and summary.per_scan_max == 2 and summary.scans_at_cap == 0


def test_centroid_to_centre_against_numpy():
    z = np.array([[[10.0, 0.1], [5.0, -0.2], [0.0, 0.0]]])
    valid = np.array([[True, True, False]])
    radius = np.array([[0.3, 0.2, 0.5]])
    obs = vps.Observations(z=jnp.asarray(z), valid=jnp.asarray(valid),
                           radius=jnp.asarray(radius), landmark_id=-jnp.ones((1, 3), jnp.int32))
    expected = z.copy()
    expected[..., 0] += np.where(valid, 2.0 / np.pi * radius, 0.0)
    for function in (vps.centroid_to_centre, jax.jit(vps.centroid_to_centre)):
        np.testing.assert_allclose(function(obs).z, expected, atol=1e-12)


def test_body_beams_never_become_trunks():
    angles = vpm.laser_angles()
    scan = np.full(angles.shape, np.inf)
    scan[:12] = 0.83  # a short, narrow, unoccluded segment: a "trunk" without the body mask
    obs = vps.detect_scans(scan[None], angles, max_obs=4, dtype=jnp.float64)
    assert not bool(obs.valid.any())


def test_bad_inputs_are_named():
    with pytest.raises(ValueError, match=r"ranges \(T, B\)"):
        vps.detect_scans(np.ones(361), vpm.laser_angles())
    with pytest.raises(ValueError, match="unknown field"):
        vps.detector_settings(range_jmp=1.0)
    with pytest.raises(ValueError, match="unknown field"):
        vps.victoria_park_params(None, motion_scale=2.0)


def test_config_and_params():
    config = vps.victoria_park_config(num_particles=8)
    assert config.motion_model == "odometry" and config.max_obs == vps.CLASSIC_MAX_TRUNKS
    params = vps.victoria_park_params(config, max_range=40.0)
    assert float(params.max_range) == 40.0
    assert float(params.min_range) == vps.BODY_RANGE


# ------------------------------------------------------------------------------- needs the data


@pytest.mark.skipif(not HAVE_DATA, reason=SKIP_REASON)
def test_detection_on_real_scans_respects_classic_limits(segment_log):
    obs = vps.detect_scans(segment_log.scan_ranges[:SEGMENT], segment_log.scan_angles)
    assert obs.z.shape == (SEGMENT, vps.CLASSIC_MAX_TRUNKS, 2)
    summary = vps.summarize_detections(obs)
    valid = np.asarray(obs.valid)
    ranges = np.asarray(obs.z[..., 0])[valid]
    # Classic limits: ranges inside (1.5 m body mask, 75 m), diameters <= 1 m plus fit slack.
    assert ranges.min() > vps.BODY_RANGE and ranges.max() < 75.0
    assert np.asarray(obs.radius)[valid].max() <= 0.6 + 1e-6
    # The park is a forest of trunks: on average at least one a scan, never more than K.
    assert 1.0 <= summary.per_scan_mean <= vps.CLASSIC_MAX_TRUNKS


@pytest.mark.skipif(not HAVE_DATA, reason=SKIP_REASON)
def test_controls_and_steering_bias(park, log_detections):
    # Bias 0 reproduces the loader's dead reckoning exactly.
    np.testing.assert_allclose(vps.victoria_park_controls(park, 0.0),
                               vpm.dead_reckoning_controls(park), atol=1e-12)
    # The laser-only calibration gives the module constant (to 0.2 mrad), and the corrected
    # dead reckoning is at least 2x closer to GPS than the raw one (91.8 -> 37.8 m).
    log = vpm.victoria_park_log(park)
    bias, _ = vps.steering_bias_from_scans(park, log_detections)
    assert abs(bias - vps.STEERING_BIAS) < 2e-4
    raw = vpm.gps_error(log.time, vpm.dead_reckoning_path(park)[:, :2], log.gps_time,
                        log.gps_xy)
    fixed = vpm.gps_error(log.time, vpm.odometry_path(vps.victoria_park_controls(park))[:, :2],
                          log.gps_time, log.gps_xy)
    assert fixed.rmse < 0.5 * raw.rmse
    with pytest.raises(ValueError, match="GPS course samples"):
        vps.steering_bias_from_gps(park, until=-1.0)


@pytest.mark.skipif(not HAVE_DATA, reason=SKIP_REASON)
def test_segment_end_to_end(park):
    config = vps.victoria_park_config(num_particles=16, max_landmarks=128)
    result = vps.run_victoria_park(jax.random.key(0), park, config, num_scans=SEGMENT)
    assert result.path.shape == (SEGMENT, 3) and np.all(np.isfinite(result.path))
    assert result.gps is not None and np.isfinite(result.gps.rmse)
    dead_reckoning = vpm.odometry_path(vps.victoria_park_controls(park))[:SEGMENT, :2]
    dr_error = vpm.gps_error(result.time, dead_reckoning, vpm.victoria_park_log(park).gps_time,
                             vpm.victoria_park_log(park).gps_xy)
    # 300 scans (about 64 s, the first loop): SLAM stays within 2 m RMSE of GPS and does not
    # do worse than dead reckoning by more than 0.5 m.
    assert result.gps.rmse < 2.0
    assert result.gps.rmse < dr_error.rmse + 0.5
    # A map forms: some trees, and not one landmark per detection.
    assert 5 <= result.num_trees <= 128
    assert result.compile_s > 0.0 and result.run_s > 0.0
    # The smoothed history (default smooth=True) is scored the same way; on this loop both
    # stay within the 2 m bound (measured: online 0.82 m, smoothed 0.92 m; on a loop this
    # short GPS noise, ~0.8 m, dominates both).
    assert result.smoothed_path.shape == (SEGMENT, 3)
    assert np.all(np.isfinite(result.smoothed_path))
    assert result.smoothed_gps.rmse < 2.0 and result.smooth_s > 0.0


@pytest.mark.skipif(not HAVE_DATA, reason=SKIP_REASON)
def test_segment_with_the_missed_loops_closed(park):
    """``close_loops`` adds the history smoothed with the loops the filter missed closed,
    scored like the others, with its closure counts; without it the fields stay empty, and
    it is refused before the filter runs when smoothing is off or visits are on."""
    config = vps.victoria_park_config(num_particles=16, max_landmarks=128)
    result = vps.run_victoria_park(jax.random.key(0), park, config, num_scans=SEGMENT,
                                   close_loops=True)
    assert result.closed_path.shape == (SEGMENT, 3)
    assert np.all(np.isfinite(result.closed_path))
    assert result.closed_gps is not None and np.isfinite(result.closed_gps.rmse)
    assert sorted(result.closures) == ["landmarks_joined", "loop_closures"]
    assert all(isinstance(v, int) and v >= 0 for v in result.closures.values())
    assert result.close_s > 0.0
    plain = vps.run_victoria_park(jax.random.key(0), park, config, num_scans=SEGMENT)
    assert plain.closed_path is None and plain.closures is None and plain.close_s == 0.0
    np.testing.assert_array_equal(plain.smoothed_path, result.smoothed_path)
    for options in (dict(smooth=False), dict(smooth_visit_gap=30)):
        with pytest.raises(ValueError, match="close_loops needs smooth=True"):
            vps.run_victoria_park(jax.random.key(0), park, config, num_scans=SEGMENT,
                                  close_loops=True, **options)


@pytest.mark.slow  # 37 s; the segment end-to-end test keeps smoothing in the default tier
@pytest.mark.skipif(not HAVE_DATA, reason=SKIP_REASON)
def test_batch_smoothing_shapes_and_options(park):
    config = vps.victoria_park_config(num_particles=8, max_landmarks=64)
    batch = vps.run_victoria_park_batch(jax.random.key(0), park, 3, config, num_scans=120,
                                        smooth=True, chunk=2, progress=False)
    assert batch.path.shape == batch.smoothed_path.shape == (3, 120, 3)
    assert batch.smoothed_rmse.shape == (3,) and np.all(np.isfinite(batch.smoothed_rmse))
    # 120 scans (26 s of driving): every path within 2 m of GPS (measured: online
    # 0.77-0.78 m, smoothed 0.82 m: the three runs share their associations).
    assert np.all(batch.rmse < 2.0) and np.all(batch.smoothed_rmse < 2.0)
    # The loop-closure revision (off by default) runs through the same path: 120 scans have
    # few revisits, so it must stay within the same 2 m bound.
    linked = vps.run_victoria_park_batch(jax.random.key(0), park, 2, config, num_scans=120,
                                         smooth=True, progress=False, smooth_visit_gap=30)
    assert np.all(np.isfinite(linked.smoothed_path)) and np.all(linked.smoothed_rmse < 2.0)
    plain = vps.run_victoria_park_batch(jax.random.key(0), park, 3, config, num_scans=120)
    assert plain.smoothed_path is None and plain.smoothed_rmse is None
    # Run r uses key fold_in(key, r) whether the runs go all at once or 2 at a time (with a
    # remainder of 1): the same paths up to float32 rounding of a differently batched
    # program (1 mm on poses ~30 m from the start).
    np.testing.assert_allclose(batch.path, plain.path, atol=1e-3)
    # A bad gap is refused before the filter runs, not after it (a 30-min study lost):
    # compiling the filter here fails the test.
    def no_filter(*args, **kwargs):
        raise AssertionError("the filter ran before the smoothing options were checked")

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(vps, "_compiled", no_filter)
        for bad in (0, 2.5):
            with pytest.raises(ValueError, match="visit_gap"):
                vps.run_victoria_park_batch(jax.random.key(0), park, 2, config,
                                            num_scans=120, smooth=True, smooth_visit_gap=bad)
            with pytest.raises(ValueError, match="visit_gap"):
                vps.run_victoria_park(jax.random.key(0), park, config, num_scans=120,
                                      smooth_visit_gap=bad)
        with pytest.raises(ValueError, match="smooth=True"):
            vps.run_victoria_park(jax.random.key(0), park, config, num_scans=120,
                                  smooth=False, smooth_visit_gap=30)
    with pytest.raises(ValueError, match="chunk"):
        vps.run_victoria_park_batch(jax.random.key(0), park, 3, config, num_scans=120,
                                    smooth=True, chunk=0)


@pytest.mark.slow
@pytest.mark.skipif(not HAVE_DATA, reason=SKIP_REASON)
def test_full_run_first_half(park):
    # What is reached: over the first 3,500 scans (before the long western legs) 8 runs at
    # P = 100 with the default settings follow GPS with RMSE 1.2-1.3 m, median 1.24 m
    # (measured with experiments/victoria_park_runs.py --runs 8 --scans 3500; 1.2-1.4 m,
    # median 1.32 m, before the trunk radius). Bounds with 0.7-1.2 m of slack (other CPUs
    # round differently, and the runs are chaotic): median below 2 m, every run below 2.5 m.
    config = vps.victoria_park_config(num_particles=100)
    batch = vps.run_victoria_park_batch(jax.random.key(0), park, 8, config, num_scans=3500)
    assert np.median(batch.rmse) < 2.0, batch.rmse
    assert np.all(batch.rmse < 2.5), batch.rmse


@pytest.mark.slow
@pytest.mark.skipif(not HAVE_DATA, reason=SKIP_REASON)
def test_full_run_targets(park):
    # Issue 7 targets with P = 100 on the key-0 run of the legacy (GPS-tuned, in-sample)
    # set, the runner's default (experiments/victoria_park.py --settings legacy reports it;
    # the time target is a benchmark figure, not asserted here). Measured: 1.74 m online,
    # 1.60 m smoothed, 173 trees (2.28 / 1.64 / 174 with an earlier library); 16 other keys
    # gave 1.55-1.67 m smoothed, so 2.0 m leaves 0.33 m for other CPUs' rounding of a
    # chaotic run. The calibrated set does not meet these targets (docs/results.md).
    result = vps.run_victoria_park(jax.random.key(0), park)
    assert result.path.shape == (7230, 3)
    assert result.smoothed_gps.rmse <= 2.0
    assert 130 <= result.num_trees <= 200


@pytest.mark.skipif(not HAVE_DATA, reason=SKIP_REASON)
def test_ground_strike_is_not_a_row_of_trunks(park):
    """Scans 4719-4729: the laser hits the grass at ~25 m over tens of degrees with a dropout
    every 2-4 beams. Split at every dropout this gave 3-8 'trunks' a scan within 1.5 m of
    25.5 m (56 in the 11 scans); with the default bridging at most 3 detections a scan remain,
    and at most 2 a scan in that band (7 in all: the arc ends and real trees at that range)."""
    log = vpm.victoria_park_log(park)
    scans = log.scan_ranges[4719:4730]
    split = vps.detect_scans(scans, log.scan_angles, max_missing_beams=0)
    bridged = vps.detect_scans(scans, log.scan_angles)

    def in_band(obs):
        return (np.asarray(obs.valid)
                & (np.abs(np.asarray(obs.z[..., 0]) - 25.5) < 1.5)).sum(1)

    assert in_band(split).min() >= 3 and in_band(split).sum() >= 50, in_band(split)
    assert np.asarray(bridged.valid.sum(1)).max() <= 3, bridged.valid.sum(1)
    assert in_band(bridged).max() <= 2 and in_band(bridged).sum() <= 10, in_band(bridged)


def _observations_from_points(points_per_scan, max_obs=6):
    """Padded Observations (T, max_obs) from lists of sensor-frame points."""
    z = np.zeros((len(points_per_scan), max_obs, 2))
    valid = np.zeros((len(points_per_scan), max_obs), bool)
    for t, points in enumerate(points_per_scan):
        for k, (x, y) in enumerate(points):
            z[t, k] = np.hypot(x, y), np.arctan2(y, x)
            valid[t, k] = True
    return vps.Observations(z=jnp.asarray(z), valid=jnp.asarray(valid),
                            radius=jnp.zeros(valid.shape), landmark_id=-jnp.ones(valid.shape,
                                                                                 jnp.int32))


def test_scan_rotations_recovers_known_turns():
    """Trunks 8-20 m away seen from poses that turn by known angles (up to 0.04 rad a scan,
    above the log's turns in a 0.2 s scan interval): the turn is recovered to 1e-9 (exact
    rigid motion, float64); too few trunks or a bad pairing give NaN."""
    rng = np.random.default_rng(4)
    world = np.array([[8.0, -6.0], [10.0, 5.0], [14.0, -1.0], [17.0, 9.0], [19.0, -8.0],
                      [20.0, 2.0]])
    turns = np.array([0.02, -0.04, 0.0, 0.03])
    poses = [np.zeros(3)]
    for turn in turns:
        x, y, h = poses[-1]
        poses.append(np.array([x + 0.5 * np.cos(h), y + 0.5 * np.sin(h), h + turn]))

    def seen_from(pose):
        c, s = np.cos(pose[2]), np.sin(pose[2])
        return (world - pose[:2]) @ np.array([[c, -s], [s, c]])

    obs = _observations_from_points([seen_from(p) for p in poses])
    np.testing.assert_allclose(vps.scan_rotations(obs), turns, atol=1e-9)
    sparse = _observations_from_points([seen_from(poses[0])[:2], seen_from(poses[1])[:2]])
    assert np.isnan(vps.scan_rotations(sparse)).all()
    shuffled = seen_from(poses[1]) + rng.normal(0, 0.6, (6, 2))  # pairs, but no rigid fit
    assert np.isnan(vps.scan_rotations(
        _observations_from_points([seen_from(poses[0]), shuffled]), match_radius=5.0)).all()


@pytest.mark.skipif(not HAVE_DATA, reason=SKIP_REASON)
def test_steering_bias_from_scans_agrees_with_gps(park, log_detections):
    """Laser-only calibration (no GPS): 4.1 +- 0.3 mrad measured; the GPS course fit gives 5.2.
    Both must agree within 2 mrad (the GPS course is noisy), and the laser estimate's standard
    error must be below 1 mrad."""
    bias, error = vps.steering_bias_from_scans(park, log_detections)
    assert error < 1e-3
    assert abs(bias - vps.steering_bias_from_gps(park)) < 2e-3


class _DeadReckoning(NamedTuple):
    """The fields of ``VictoriaPark`` that the steering-bias tools read."""

    dr_time: np.ndarray
    dr_speed: np.ndarray
    dr_steering: np.ndarray
    laser_time: np.ndarray


def _synthetic_drive(seconds=600.0):
    """40 Hz dead reckoning at 3 m/s, steering swinging +-0.1 rad every 40 s; 5 Hz scans."""
    dr_time = np.arange(0.0, seconds, 0.025)
    steering = 0.1 * np.sin(2 * np.pi * dr_time / 40.0)
    return _DeadReckoning(dr_time, np.full(dr_time.shape, 3.0), steering,
                          np.arange(0.1, seconds - 0.1, 0.2))


def test_bias_profile_recovers_a_bias_step():
    """The vehicle's true steering bias steps from 3 to 6 mrad halfway; the laser sees each
    scan-to-scan turn with 1 mrad noise and 30% of the pairs have no estimate. A 600-scan
    window holds ~420 usable pairs of sensitivity g ~ 0.21, so a window fit has a standard
    error of 1e-3 / sqrt(420 * 0.21^2) ~ 0.2 mrad: away from the step (more than half a
    window) the profile must be within 1 mrad (5 standard errors) of the truth, where the
    single constant fit is 1.5 mrad off on both sides."""
    drive = _synthetic_drive()
    true_bias = np.where(drive.dr_time < 300.0, 3e-3, 6e-3)
    rng = np.random.default_rng(0)
    turns = vps._dead_reckoned_turns(drive, true_bias) + rng.normal(0.0, 1e-3,
                                                                   drive.laser_time.size - 1)
    turns[rng.random(turns.size) < 0.3] = np.nan
    profile = vps.bias_profile_from_turns(drive, turns, window=600)
    assert profile.shape == drive.dr_time.shape
    before, after = drive.dr_time < 300.0 - 70.0, drive.dr_time > 300.0 + 70.0
    np.testing.assert_allclose(profile[before], 3e-3, atol=1e-3)
    np.testing.assert_allclose(profile[after], 6e-3, atol=1e-3)
    # The constant fit sits between the two levels.
    use, x, y = vps._turn_residuals(drive, turns, 0.3)
    constant = np.sum(x * y) / np.sum(x * x)
    assert 4e-3 < constant < 5e-3


def test_bias_profile_and_controls_name_bad_input():
    drive = _synthetic_drive(60.0)
    with pytest.raises(ValueError, match="no window"):
        vps.bias_profile_from_turns(drive, np.full(drive.laser_time.size - 1, np.nan))
    with pytest.raises(ValueError, match="too short"):
        vps.bias_profile_from_turns(drive, np.zeros(drive.laser_time.size - 1), window=2)
    with pytest.raises(ValueError, match="one value per dead-reckoning sample"):
        vps.victoria_park_controls(drive, np.zeros(7))
    # A constant and a constant array give the same moves.
    np.testing.assert_array_equal(
        vps.victoria_park_controls(drive, 0.004),
        vps.victoria_park_controls(drive, np.full(drive.dr_time.shape, 0.004)))


@pytest.mark.skipif(not HAVE_DATA, reason=SKIP_REASON)
def test_steering_bias_profile_on_the_log(park, log_detections):
    """Measured: the profile runs -0.3 to 6.6 mrad (10-90%: 2.2-5.8, median 4.17) around
    the constant 4.12, and through the treeless corner into the western leg (scans
    4,650-5,300) it averages 2.2 mrad.
    Asserted with 0.5 mrad of slack: the median within 0.5 mrad of the constant fit, the
    corner mean at least 1 mrad below it; and an unknown bias name is refused."""
    log, obs = vpm.victoria_park_log(park), log_detections
    profile = vps.steering_bias_profile(park, obs)
    constant, _ = vps.steering_bias_from_scans(park, obs)
    assert abs(np.median(profile) - constant) < 5e-4
    corner = ((park.dr_time >= log.time[4650]) & (park.dr_time <= log.time[5300]))
    assert profile[corner].mean() < constant - 1e-3, profile[corner].mean()
    with pytest.raises(ValueError, match="expected 'laser'"):
        vps.run_victoria_park(jax.random.key(0), park, num_scans=10, observations=obs,
                              steering_bias="gps")


# ------------------------------------------------------------------------------- settings file


def _entries():
    """(set, section, field, entry) of every entry of the settings file."""
    with open(vps.SETTINGS_FILE, "rb") as handle:
        tables = tomllib.load(handle)
    for name, table in tables.items():
        for section in vps.SETTINGS_SECTIONS:
            for field, entry in table.get(section, {}).items():
                yield name, section, field, entry


def _entries_of(name):
    return [entry for entry in _entries() if entry[0] == name]


def test_settings_file_has_both_sets_and_valid_sources():
    entries = list(_entries())
    assert {name for name, *_ in entries} == {vps.CALIBRATED, vps.LEGACY}
    for name, section, field, entry in entries:
        assert entry["source"] in vps.SOURCES, (name, section, field, entry)
        assert set(entry) <= {"value", "source", "note"}, (name, section, field)
        # A value may be left out only where the calibration sets it.
        assert "value" in entry or entry["source"] == "calibrated", (name, section, field)
    # GPS only scores the calibrated set: none of its settings was chosen by GPS score.
    assert not [e for e in entries if e[0] == vps.CALIBRATED
                and e[3]["source"] == "GPS-tuned (legacy)"]


@pytest.mark.parametrize("name", [vps.CALIBRATED, vps.LEGACY])
def test_settings_load_into_config_and_params(name):
    settings = vps.load_settings(name)
    config = vps.settings_config(settings)
    params = vps.settings_params(settings, config)
    assert isinstance(config, FilterConfig) and isinstance(params, Params)
    check_params(params)
    for field, value in settings.filter.items():
        assert getattr(config, field) == value, field
    for field, value in settings.params.items():
        np.testing.assert_allclose(np.asarray(getattr(params, field)), value, rtol=1e-6,
                                   err_msg=field)
    assert set(settings.sources) == {f"{section}.{field}" for _, section, field, _ in
                                     _entries_of(name)}
    assert config.max_obs == vps.CLASSIC_MAX_TRUNKS
    assert float(params.min_range) == vps.BODY_RANGE


def test_library_default_entries_are_the_library_defaults():
    """An entry tagged "library default" must state the default it claims."""
    config_defaults = FilterConfig()
    param_defaults = default_params()
    smoother_defaults = {name: parameter.default for name, parameter in
                         inspect.signature(smooth_path).parameters.items()}
    # A finished run is smoothed by pipeline.offline_path, whose rounds of variance
    # components default to smoothing.VARIANCE_ROUNDS (smooth_path's own default is 0).
    smoother_defaults["calibrate_rounds"] = VARIANCE_ROUNDS
    for name, section, field, entry in _entries():
        if entry["source"] != "library default":
            continue
        expected = {"filter": lambda f: getattr(config_defaults, f),
                    "params": lambda f: np.asarray(getattr(param_defaults, f)),
                    "smoother": lambda f: smoother_defaults[f]}[section](field)
        if isinstance(entry["value"], (str, bool)):
            assert entry["value"] == expected, f"{name}.{section}.{field}"
        else:
            np.testing.assert_allclose(np.asarray(entry["value"], np.float64),
                                       np.asarray(expected, np.float64), rtol=1e-6,
                                       err_msg=f"{name}.{section}.{field}")


def test_legacy_set_is_the_earlier_runner_settings():
    """The legacy set reproduces the settings the earlier runner hard-coded (its Monte Carlo
    figures in docs/results.md were measured with them)."""
    params = vps.victoria_park_params(settings=vps.LEGACY)
    assert float(params.radius_noise) == pytest.approx(0.07)
    assert float(params.max_range) == 45.0 and float(params.miss_range) == 30.0
    assert float(params.existence_max) == 30.0
    np.testing.assert_allclose(params.trans_noise, (0.01, 0.0025, 0.00125), rtol=1e-6)
    assert float(params.airlock_sigmas) == pytest.approx(np.sqrt(13.8), rel=1e-6)
    config = vps.victoria_park_config(settings=vps.LEGACY)
    assert config.association_window == 48 and not config.burst_proposal
    assert vps.smoother_options(vps.LEGACY)["calibrate_rounds"] == 1


def test_bad_settings_are_named():
    with pytest.raises(ValueError, match="source 'tuned'"):
        vps.parse_settings({"params": {"max_range": {"value": 1.0, "source": "tuned"}}}, "x")
    with pytest.raises(ValueError, match="no value"):
        vps.parse_settings({"params": {"max_range": {"source": "documentation"}}}, "x")
    with pytest.raises(ValueError, match="unknown section"):
        vps.parse_settings({"parms": {}}, "x")
    with pytest.raises(ValueError, match="no settings set"):
        vps.load_settings("tuned")
