"""Victoria Park: raw parse, time bases, GPS filtering, dead reckoning, the filter log.

Tests that need the data skip when ``default_victoria_park_dir()`` is absent. The data are
parsed once per module (about 1 s) into a per-session cache folder.
"""
import zipfile
from pathlib import Path

import numpy as np
import pytest

from jaxslam.datasets import log_format as lf
from jaxslam.datasets import victoria_park as vpm
from jaxslam.host import in_float64
from jaxslam.datasets.odometry import odometry_path
from jaxslam.metrics import align_se2

DATA_DIR = vpm.default_victoria_park_dir()
needs_data = pytest.mark.skipif(
    not (DATA_DIR / vpm.ZIP_NAME).is_file(),
    reason=f"Victoria Park data not found at {DATA_DIR} (set ${vpm.ENV_DATA_DIR} to the folder "
           "holding victoria_park_ascii.zip, aa3_dr.mat and aa3_gpsx.mat)")


@pytest.fixture(scope="module")
def cache_dir(tmp_path_factory):
    return tmp_path_factory.mktemp("vp_cache")


@pytest.fixture(scope="module")
def park(cache_dir):
    if not (DATA_DIR / vpm.ZIP_NAME).is_file():
        pytest.skip(f"Victoria Park data not found at {DATA_DIR}")
    return vpm.load_victoria_park(DATA_DIR, cache_dir=cache_dir)


# ------------------------------------------------------------------------------- no data needed


def test_default_dir_env_override(monkeypatch, tmp_path):
    monkeypatch.setenv(vpm.ENV_DATA_DIR, str(tmp_path))
    assert vpm.default_victoria_park_dir() == tmp_path
    monkeypatch.delenv(vpm.ENV_DATA_DIR)
    default = vpm.default_victoria_park_dir()
    assert default.parts[-3:] == ("shared", "data", "victoria_park")
    repo_root = Path(vpm.__file__).resolve().parents[2]
    assert default == repo_root.parent / "shared" / "data" / "victoria_park"


def test_missing_folder_names_the_files(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"missing \['victoria_park_ascii.zip', "
                                                r"'aa3_dr.mat', 'aa3_gpsx.mat'\].*JAXSLAM_"):
        vpm.load_victoria_park(tmp_path / "nowhere")


def test_clock_conversion():
    np.testing.assert_allclose(vpm.mat_ms_to_seconds([20967, 21940]), [0.0, 0.973], atol=1e-12)


def test_laser_angles_robot_frame():
    angles = vpm.laser_angles()
    assert angles.shape == (361,)
    np.testing.assert_allclose(angles[[0, 180, 360]], [-np.pi / 2, 0.0, np.pi / 2], atol=1e-15)
    np.testing.assert_allclose(np.diff(angles), np.deg2rad(0.5), atol=1e-15)


def _clean_track(count=200):
    time = np.arange(count) * 0.2
    xy = np.stack([3.0 * time, 5.0 * np.sin(0.1 * time)], -1)  # at most ~3.1 m/s
    return time, xy


def test_filter_gps_keeps_a_clean_track():
    assert vpm.filter_gps(*_clean_track()).all()


def test_filter_gps_rejects_spikes():
    time, xy = _clean_track()
    xy[50] += [40.0, 0.0]                   # isolated spike
    xy[120] += [0.0, 30.0]                  # two neighbouring spikes in different directions
    xy[121] += [-25.0, 0.0]
    keep = vpm.filter_gps(time, xy, jump_margin=0.0)
    assert np.flatnonzero(~keep).tolist() == [50, 120, 121]


def test_filter_gps_rejects_fixes_around_a_jump():
    time, xy = _clean_track()
    xy[100:] += [5.0, 0.0]                  # a 5 m offset from fix 100 on (25 m/s implied)
    keep = vpm.filter_gps(time, xy, jump_margin=0.5)
    rejected = np.flatnonzero(~keep)
    # fixes within 0.5 s of t[99] = 19.8 s or t[100] = 20.0 s
    assert rejected.tolist() == [97, 98, 99, 100, 101, 102]


def test_float64_se2_alignment_recovers_a_known_transform():
    rng = np.random.default_rng(1)
    source = rng.normal(0, 10, (50, 2))
    angle, shift = 2.5, np.array([4.0, -7.0])
    rotation = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    target = source @ rotation.T + shift + rng.normal(0, 0.01, (50, 2))
    alignment = in_float64(align_se2, source, target)  # what gps_error fits
    got_angle, got_shift = alignment[2], alignment[:2]
    # Reference: SVD Kabsch in float64.
    centred_s, centred_t = source - source.mean(0), target - target.mean(0)
    u, _, vt = np.linalg.svd(centred_s.T @ centred_t)
    reference = vt.T @ np.diag([1.0, np.linalg.det(vt.T @ u.T)]) @ u.T
    assert got_angle == pytest.approx(np.arctan2(reference[1, 0], reference[0, 0]), abs=1e-12)
    np.testing.assert_allclose(got_shift, target.mean(0) - reference @ source.mean(0),
                               atol=1e-10)
    assert got_angle == pytest.approx(angle, abs=1e-3)
    # The transform helper is the same rotation matrix plus the shift (float64, 1e-12).
    np.testing.assert_allclose(vpm.rigid_transform_2d(source, angle, shift),
                               source @ rotation.T + shift, atol=1e-12)


def test_gps_error_of_a_transformed_copy_is_zero():
    path_time = np.linspace(0, 10, 101)
    path_xy = np.stack([path_time, np.sin(path_time)], -1)
    rotation = np.array([[0.0, -1.0], [1.0, 0.0]])
    gps_time = np.linspace(-1, 11, 25)      # fixes outside the path's span are ignored
    truth = np.stack([gps_time, np.sin(gps_time)], -1) @ rotation.T + [10.0, 3.0]
    error = vpm.gps_error(path_time, path_xy, gps_time, truth)
    assert len(error.gps_xy) == 21
    assert error.max < 0.05 and error.rotation == pytest.approx(np.pi / 2, abs=1e-2)


# ------------------------------------------------------------------------------ with the data


@needs_data
def test_parse_shapes(park):
    assert park.laser_time.shape == (7230,)
    assert park.laser_ranges.shape == (7230, 361)
    assert park.laser_angles.shape == (361,)
    assert park.dr_time.shape == park.dr_speed.shape == park.dr_steering.shape == (61945,)
    assert park.gps_time.shape == (4466,) and park.gps_xy.shape == (4466, 2)
    for name, value in park._asdict().items():
        assert value.dtype == np.float64, name
    for times in (park.laser_time, park.dr_time, park.gps_time):
        assert np.all(np.diff(times) > 0)


@needs_data
def test_no_return_is_inf(park):
    ranges = park.laser_ranges
    assert np.isinf(ranges).any() and not np.isnan(ranges).any()
    finite = ranges[np.isfinite(ranges)]
    assert finite.min() >= 0 and finite.max() < vpm.NO_RETURN_RANGE
    assert park.laser_time[0] == pytest.approx(0.852) and park.laser_ranges[0, 0] == 0.83


@needs_data
def test_time_bases_aligned(park):
    assert park.dr_time[0] == pytest.approx(0.973, abs=1e-9)    # README: 21940 ms is 0.973 s
    assert park.gps_time[0] == pytest.approx(0.0, abs=1e-9)     # first GPS fix is ascii 0
    # laser and dead-reckoning clocks overlap over the whole run
    assert park.dr_time[0] < park.laser_time[1] and park.dr_time[-1] > park.laser_time[-1]
    # the converted .mat clock is the ascii clock: DRS.txt shares the laser's clock
    with zipfile.ZipFile(DATA_DIR / vpm.ZIP_NAME) as archive:
        drs = np.array(archive.read("DRS.txt").split(), np.float64).reshape(-1, 3)
    # DRS.txt stops at the last scan (61763 rows); each row is a .mat sample on the same clock
    assert drs.shape[0] > 61000 and drs[-1, 0] < park.laser_time[-1]
    same = np.searchsorted(park.dr_time, drs[:, 0] - 1e-6)
    np.testing.assert_allclose(park.dr_time[same], drs[:, 0], atol=1e-6)
    np.testing.assert_allclose(park.dr_speed[same], drs[:, 1], atol=6e-4)  # 3 decimals printed
    assert np.std(park.dr_steering[same] - drs[:, 2]) < 0.02  # README: std 0.01 rad apart


@needs_data
def test_cache_round_trip(park, cache_dir):
    files = list(cache_dir.glob("victoria_park_*.npz"))
    assert len(files) == 1
    again = vpm.load_victoria_park(DATA_DIR, cache_dir=cache_dir)
    fresh = vpm.load_victoria_park(DATA_DIR, use_cache=False)
    for name in vpm.VictoriaPark._fields:
        np.testing.assert_array_equal(getattr(again, name), getattr(park, name), err_msg=name)
        np.testing.assert_array_equal(getattr(fresh, name), getattr(park, name), err_msg=name)


@needs_data
def test_gps_filter_on_park(park):
    keep = vpm.filter_gps(park.gps_time, park.gps_xy)
    assert 0.9 < keep.mean() < 1.0
    spike = np.argmax(np.linalg.norm(park.gps_xy - np.median(park.gps_xy, 0), axis=-1))
    assert not keep[spike]                  # the 140 m spike near 1223 s
    kept_t, kept_xy = park.gps_time[keep], park.gps_xy[keep]
    speed = np.linalg.norm(np.diff(kept_xy, axis=0), axis=-1) / np.diff(kept_t)
    assert speed.max() <= 10.0


@needs_data
def test_dead_reckoning_drift_matches_readme(park):
    path = vpm.dead_reckoning_path(park)
    assert path.shape == (7230, 3)
    length = np.sum(np.linalg.norm(np.diff(path[:, :2], axis=0), axis=-1))
    assert 3500 < length < 4500             # README: about 4 km
    keep = vpm.filter_gps(park.gps_time, park.gps_xy)
    # README: about 130 m mean drift; aligned on the first minute we measure ~129 m.
    start = vpm.gps_error(park.laser_time, path[:, :2], park.gps_time[keep], park.gps_xy[keep],
                          fit_until=60.0)
    assert 100 < start.mean < 160
    best = vpm.gps_error(park.laser_time, path[:, :2], park.gps_time[keep], park.gps_xy[keep])
    assert best.rmse <= start.rmse and 50 < best.mean < 110


@needs_data
def test_gps_handedness_agrees_with_dead_reckoning(park):
    # Over a 150 s stretch (small drift) the (Lo, La) order fits far better than its mirror.
    path = vpm.dead_reckoning_path(park)
    window = (park.gps_time > 300) & (park.gps_time < 450)
    args = (park.laser_time, path[:, :2], park.gps_time[window])
    direct = vpm.gps_error(*args, park.gps_xy[window]).median
    mirrored = vpm.gps_error(*args, park.gps_xy[window][:, ::-1]).median
    assert direct < 0.5 * mirrored


@needs_data
def test_victoria_park_log(park, tmp_path):
    log = vpm.victoria_park_log(park, max_range=30.0)
    assert log.motion_model == "odometry" and log.num_steps == 7230
    np.testing.assert_array_equal(log.controls[0], 0.0)     # laser starts before DR
    assert np.all(log.controls[:, 1] >= 0) and log.controls[:, 1].max() < 6.7 * 0.5
    assert np.all(np.isinf(log.scan_ranges[park.laser_ranges >= 30.0]))
    assert log.obs_z is None and log.scan_ranges.shape == (7230, 361)
    np.testing.assert_allclose(odometry_path(log.controls), vpm.dead_reckoning_path(park))
    lf.save_log(tmp_path / "vp.npz", log)
    loaded = lf.load_log(tmp_path / "vp.npz")
    for name in ("time", "controls", "scan_ranges", "scan_angles", "gps_time", "gps_xy"):
        np.testing.assert_array_equal(getattr(loaded, name), getattr(log, name), err_msg=name)
