"""The jaxslam log format: round trips, every validation error, control integration."""
import math

import numpy as np
import pytest

from jaxslam.datasets import log_format as lf
from jaxslam.types import Observations, make_observations

T, K, B = 5, 3, 7


def _full_arrays(rng=None) -> dict:
    """Every key of the format, valid, as a plain dict of arrays (what np.savez writes)."""
    rng = np.random.default_rng(0) if rng is None else rng
    obs_z = np.stack([rng.uniform(0.5, 20.0, (T, K)), rng.uniform(-1.5, 1.5, (T, K))], -1)
    return dict(
        format_version=np.asarray(lf.FORMAT_VERSION),
        time=np.cumsum(rng.uniform(0.1, 0.3, T)),
        motion_model=np.asarray("odometry"),
        controls=rng.normal(0.0, 0.2, (T, 3)),
        obs_z=obs_z,
        obs_valid=rng.uniform(size=(T, K)) < 0.7,
        obs_radius=rng.uniform(0.05, 0.4, (T, K)),
        scan_ranges=np.where(rng.uniform(size=(T, B)) < 0.2, np.inf, rng.uniform(1, 30, (T, B))),
        scan_angles=np.linspace(-np.pi / 2, np.pi / 2, B),
        truth_pose=rng.normal(size=(T, 3)),
        truth_landmarks=rng.normal(size=(4, 2)),
        gps_time=np.linspace(0.0, 1.0, 6),
        gps_xy=rng.normal(size=(6, 2)),
        initial_pose=np.array([1.0, -2.0, 0.3]),
    )


def _log_from(arrays: dict) -> lf.RobotLog:
    fields = {k: v for k, v in arrays.items() if k in lf.RobotLog._fields}
    fields["motion_model"] = str(fields["motion_model"])
    fields["format_version"] = int(fields["format_version"])
    return lf.RobotLog(**fields)


def _assert_logs_equal(got: lf.RobotLog, want: lf.RobotLog):
    for name in lf.RobotLog._fields:
        a, b = getattr(got, name), getattr(want, name)
        if b is None:
            assert a is None, name
        else:
            np.testing.assert_array_equal(a, b, err_msg=name)


# ---------------------------------------------------------------------------------- round trips


@pytest.mark.parametrize("compress", [False, True])
def test_round_trip_all_fields(tmp_path, compress):
    log = _log_from(_full_arrays())
    lf.save_log(tmp_path / "run.npz", log, compress=compress)
    loaded = lf.load_log(tmp_path / "run.npz")
    _assert_logs_equal(loaded, log)
    assert loaded.motion_model == "odometry" and isinstance(loaded.motion_model, str)
    assert loaded.obs_valid.dtype == np.bool_ and loaded.num_steps == T


@pytest.mark.parametrize("drop", [
    ("scan_ranges", "scan_angles", "truth_pose", "truth_landmarks", "gps_time", "gps_xy",
     "initial_pose", "obs_radius"),
    ("obs_z", "obs_valid", "obs_radius"),  # scans only
])
def test_round_trip_minimal(tmp_path, drop):
    arrays = {k: v for k, v in _full_arrays().items() if k not in drop}
    log = _log_from(arrays)
    lf.save_log(tmp_path / "run.npz", log)
    loaded = lf.load_log(tmp_path / "run.npz")
    _assert_logs_equal(loaded, log)
    for name in drop:
        assert getattr(loaded, name) is None


def test_meta_keys_are_ignored(tmp_path):
    arrays = _full_arrays()
    np.savez(tmp_path / "run.npz", meta_robot=np.asarray("harvester-3"), **arrays)
    _assert_logs_equal(lf.load_log(tmp_path / "run.npz"), _log_from(arrays))


def test_velocity_and_ackermann_logs_load(tmp_path):
    for model in ("velocity", "ackermann"):
        arrays = _full_arrays()
        arrays["motion_model"] = np.asarray(model)
        arrays["controls"][:, 2] = np.abs(arrays["controls"][:, 2])
        np.savez(tmp_path / f"{model}.npz", **arrays)
        assert lf.load_log(tmp_path / f"{model}.npz").motion_model == model


def test_observations():
    arrays = _full_arrays()
    obs = _log_from(arrays).observations(dtype=np.float64)
    want = make_observations(arrays["obs_z"], arrays["obs_valid"], arrays["obs_radius"])
    assert isinstance(obs, Observations)
    assert obs.z.shape == (T, K, 2) and obs.valid.shape == (T, K)
    for got, expected in zip(obs, want):
        np.testing.assert_array_equal(np.asarray(got), np.asarray(expected))
    assert np.all(np.asarray(obs.landmark_id) == -1)


def test_observations_of_scans_only_log_raise():
    arrays = {k: v for k, v in _full_arrays().items() if k not in ("obs_z", "obs_valid",
                                                                  "obs_radius")}
    with pytest.raises(lf.LogFormatError, match="raw scans but no range-bearing"):
        _log_from(arrays).observations()


def test_save_refuses_invalid_log(tmp_path):
    arrays = _full_arrays()
    arrays["time"] = arrays["time"][::-1].copy()
    with pytest.raises(lf.LogFormatError, match="not strictly increasing"):
        lf.save_log(tmp_path / "bad.npz", _log_from(arrays))
    assert not (tmp_path / "bad.npz").exists()


# ---------------------------------------------------------------------------- validation errors


def _set(name, value_fn):
    def edit(arrays):
        arrays[name] = value_fn(arrays)
    return edit


def _drop(*names):
    def edit(arrays):
        for name in names:
            del arrays[name]
    return edit


def _poke(name, index, value):
    def edit(arrays):
        arrays[name] = arrays[name].copy()
        arrays[name][index] = value
    return edit


def _negative_valid_range(arrays):
    arrays["obs_valid"] = np.ones((T, K), bool)
    arrays["obs_z"] = arrays["obs_z"].copy()
    arrays["obs_z"][2, 1, 0] = -0.5


INVALID = {
    "missing controls": (_drop("controls"),
                         r"missing required key\(s\) \['controls'\]; expected \['format_version'"),
    "missing time": (_drop("time"), r"missing required key\(s\) \['time'\]"),
    "unknown key": (_set("obs_vaild", lambda a: a["obs_valid"]),
                    r"unknown key\(s\) \['obs_vaild'\]; expected keys among .*prefix .*'meta_'"),
    "bad version": (_set("format_version", lambda a: np.asarray(7)),
                    r"format_version 7 is not supported; expected 1"),
    "version not a number": (_set("format_version", lambda a: np.asarray("one")),
                             r"'format_version' is 'one' \(shape \(\), dtype <U3\); expected "
                             r"the integer scalar 1"),
    "version a vector": (_set("format_version", lambda a: np.asarray([1, 1])),
                         r"'format_version' is \[1, 1\] \(shape \(2,\), dtype int64\); "
                         r"expected the integer scalar 1"),
    "version fractional": (_set("format_version", lambda a: np.asarray(1.5)),
                           r"'format_version' is 1.5 .*expected the integer scalar 1"),
    "time complex": (_set("time", lambda a: a["time"] + 1j),
                     r"'time' is not numeric \(dtype complex128\); expected a float array "
                     r"\(float or integer values; not bool, complex or text\)"),
    "controls bool": (_set("controls", lambda a: np.ones((T, 3), bool)),
                      r"'controls' is not numeric \(dtype bool\); expected a float array"),
    "obs_z text": (_set("obs_z", lambda a: np.full((T, K, 2), "1.0")),
                   r"'obs_z' is not numeric \(dtype <U3\); expected a float array"),
    "unknown motion model": (_set("motion_model", lambda a: np.asarray("bicycle")),
                             r"unknown motion_model 'bicycle'; expected one of \['odometry', "
                             r"'velocity', 'ackermann'\]"),
    "motion model not a string": (_set("motion_model", lambda a: np.asarray(3)),
                                  r"'motion_model' is .*expected a string scalar"),
    "time 2-D": (_set("time", lambda a: a["time"][:, None]),
                 r"'time' has shape \(5, 1\); expected \(\*,\)"),
    "time empty": (lambda a: a.update(time=np.zeros(0), controls=np.zeros((0, 3)),
                                      obs_z=np.zeros((0, K, 2)), obs_valid=np.zeros((0, K), bool),
                                      obs_radius=np.zeros((0, K)),
                                      scan_ranges=np.zeros((0, B)), truth_pose=np.zeros((0, 3))),
                   r"'time' is empty; expected at least one step"),
    "time unsorted": (_set("time", lambda a: a["time"][[0, 2, 1, 3, 4]]),
                      r"'time' is not strictly increasing: time\[2\]=.* <= time\[1\]=.*; "
                      r"expected sorted, distinct timestamps"),
    "time repeated": (_set("time", lambda a: np.array([0.0, 0.1, 0.2, 0.2, 0.3])),
                      r"time\[3\]=0.2 <= time\[2\]=0.2"),
    "time NaN": (_poke("time", 4, np.nan),
                 r"'time' contains NaN or inf \(1 entries, first at index \(4,\)\); "
                 r"expected finite"),
    "controls wrong width": (_set("controls", lambda a: a["controls"][:, :2]),
                             r"'controls' has shape \(5, 2\); expected \(5, 3\)"),
    "controls mismatched T": (_set("controls", lambda a: np.zeros((T + 1, 3))),
                              r"'controls' has shape \(6, 3\); expected \(5, 3\)"),
    "controls NaN": (_poke("controls", (1, 2), np.nan),
                     r"'controls' contains NaN or inf \(1 entries, first at index \(1, 2\)\)"),
    "controls inf": (_poke("controls", (0, 0), np.inf), r"'controls' contains NaN or inf"),
    "negative dt": (lambda a: a.update(motion_model=np.asarray("velocity"),
                                       controls=np.tile([1.0, 0.1, -0.2], (T, 1))),
                    r"column 2 \(dt\) is negative for motion_model 'velocity'; expected dt >= 0"),
    "obs_z mismatched T": (_set("obs_z", lambda a: np.zeros((T + 1, K, 2))),
                           r"'obs_z' has shape \(6, 3, 2\); expected \(5, \*, 2\)"),
    "obs_z wrong trailing": (_set("obs_z", lambda a: np.zeros((T, K, 3))),
                             r"'obs_z' has shape \(5, 3, 3\); expected \(5, \*, 2\)"),
    "obs_z inf in padding": (_poke("obs_z", (0, 0, 1), np.inf),
                             r"'obs_z' contains NaN or inf .*index \(0, 0, 1\)"),
    "obs_valid not bool": (_set("obs_valid", lambda a: a["obs_valid"].astype(np.int64)),
                           r"'obs_valid' has dtype int64; expected bool"),
    "obs_valid mismatched K": (_set("obs_valid", lambda a: np.ones((T, K + 1), bool)),
                               r"'obs_valid' has shape \(5, 4\); expected \(5, 3\)"),
    "obs_z without obs_valid": (_drop("obs_valid"),
                                r"'obs_z' is present but 'obs_valid' is missing; expected both"),
    "negative valid range": (_negative_valid_range,
                             r"'obs_z' has a negative range -0.5 at valid observation "
                             r"\(t=2, k=1\); expected range >= 0"),
    "obs_radius mismatched": (_set("obs_radius", lambda a: np.zeros((T, K + 2))),
                              r"'obs_radius' has shape \(5, 5\); expected \(5, 3\)"),
    "obs_radius negative": (_poke("obs_radius", (4, 2), -0.1),
                            r"'obs_radius' has a negative radius -0.1 at \(t=4, k=2\); "
                            r"expected radius >= 0 \[m\] \(0 = unknown\)"),
    "obs_radius without obs_z": (_drop("obs_z", "obs_valid"),
                                 r"'obs_radius' is present without 'obs_z'"),
    "no observations": (_drop("obs_z", "obs_valid", "obs_radius", "scan_ranges", "scan_angles"),
                        r"no observations: expected 'obs_z' \+ 'obs_valid' .* or "
                        r"'scan_ranges' \+ 'scan_angles'"),
    "scans without angles": (_drop("scan_angles"),
                             r"'scan_ranges' is present but 'scan_angles' is missing"),
    "scan beams mismatched": (_set("scan_angles", lambda a: np.zeros(B + 1)),
                              r"'scan_ranges' has shape \(5, 7\); expected \(5, 8\)"),
    "scan NaN": (_poke("scan_ranges", (3, 4), np.nan),
                 r"'scan_ranges' contains NaN or -inf .*\(3, 4\).*\+inf marks no return"),
    "scan negative": (_poke("scan_ranges", (1, 0), -2.0),
                      r"'scan_ranges' has a negative range -2.0 at \(t=1, beam=0\)"),
    "truth_pose mismatched T": (_set("truth_pose", lambda a: np.zeros((T - 1, 3))),
                                r"'truth_pose' has shape \(4, 3\); expected \(5, 3\)"),
    "truth_landmarks wrong": (_set("truth_landmarks", lambda a: np.zeros((4, 3))),
                              r"'truth_landmarks' has shape \(4, 3\); expected \(\*, 2\)"),
    "initial_pose wrong": (_set("initial_pose", lambda a: np.zeros(2)),
                           r"'initial_pose' has shape \(2,\); expected \(3,\)"),
    "gps unsorted": (_set("gps_time", lambda a: a["gps_time"][::-1].copy()),
                     r"'gps_time' is not strictly increasing"),
    "gps mismatched": (_set("gps_xy", lambda a: np.zeros((5, 2))),
                       r"'gps_xy' has shape \(5, 2\); expected \(6, 2\)"),
    "gps NaN": (_poke("gps_xy", (2, 1), np.nan), r"'gps_xy' contains NaN or inf"),
    "gps_time alone": (_drop("gps_xy"), r"'gps_time' is present but 'gps_xy' is missing"),
}


@pytest.mark.parametrize("case", sorted(INVALID))
def test_every_validation_error(tmp_path, case):
    edit, message = INVALID[case]
    arrays = _full_arrays()
    edit(arrays)
    path = tmp_path / "bad_log.npz"
    np.savez(path, **arrays)
    with pytest.raises(lf.LogFormatError, match=message) as error:
        lf.load_log(path)
    assert str(error.value).startswith(f"{path}: "), "the message names the file"
    assert isinstance(error.value, ValueError)


def test_negative_range_in_padding_is_allowed(tmp_path):
    arrays = _full_arrays()
    arrays["obs_valid"][2, 1] = False
    arrays["obs_z"][2, 1, 0] = -1.0
    np.savez(tmp_path / "run.npz", **arrays)
    assert lf.load_log(tmp_path / "run.npz").obs_z[2, 1, 0] == -1.0


def test_not_an_npz(tmp_path):
    path = tmp_path / "run.npz"
    path.write_text("time,x,y\n")
    with pytest.raises(lf.LogFormatError, match=r"run.npz: cannot read as a .npz archive"):
        lf.load_log(path)


# ------------------------------------------------------------------------- control integration


def _euler_reference(control_time, controls, obs_time, motion_model, vehicle):
    """Plain-Python per-sample Euler from the zero pose over each observation interval."""
    length, offset, forward, left = (vehicle.wheelbase, vehicle.encoder_offset,
                                     vehicle.sensor_forward, vehicle.sensor_left)
    start = min(control_time[0], obs_time[0])
    moves = []
    for t, end in enumerate(obs_time):
        begin = start if t == 0 else obs_time[t - 1]
        x = y = phi = 0.0
        for i in range(len(control_time)):
            lo = max(begin, control_time[i])
            hi = min(end, control_time[i + 1]) if i + 1 < len(control_time) else end
            if hi <= lo:
                continue
            h = hi - lo
            v, u = controls[i][0], controls[i][1]
            if motion_model == "velocity":
                xd, yd, wd = v * math.cos(phi), v * math.sin(phi), u
            else:
                vc = v / (1 - math.tan(u) * offset / length)
                wd = vc / length * math.tan(u)
                xd = vc * math.cos(phi) - wd * (forward * math.sin(phi) + left * math.cos(phi))
                yd = vc * math.sin(phi) + wd * (forward * math.cos(phi) - left * math.sin(phi))
            x, y, phi = x + h * xd, y + h * yd, phi + h * wd
        trans = math.hypot(x, y)
        rot1 = math.atan2(y, x) if trans >= 1e-3 else 0.0
        rot2 = math.remainder(phi - rot1, 2 * math.pi)
        moves.append((rot1, trans, rot2))
    return np.array(moves)


def _irregular_times(rng, count, low, high, start):
    return start + np.cumsum(rng.uniform(low, high, count))


@pytest.mark.parametrize("motion_model", ["velocity", "ackermann"])
def test_integrate_controls_matches_per_sample_euler(motion_model):
    rng = np.random.default_rng(3)
    control_time = _irregular_times(rng, 300, 0.02, 0.03, 0.5)       # ~40 Hz from 0.5 s
    second = rng.uniform(-0.5, 0.5, 300) if motion_model == "ackermann" else rng.normal(0, 1, 300)
    controls = np.stack([rng.uniform(0, 5, 300), second, np.full(300, 0.025)], -1)
    controls[40:60, 0] = 0.0                                          # a stop
    obs_time = _irregular_times(rng, 34, 0.15, 0.25, 0.2)             # starts before controls
    obs_time[10] = control_time[np.searchsorted(control_time, obs_time[10])]  # shared stamp
    obs_time = np.append(obs_time, control_time[-1] + 0.3)            # past the last sample
    vehicle = lf.AckermannVehicle(2.5, 0.6, 3.0, 0.4)
    got = lf.integrate_controls(control_time, controls, obs_time, motion_model, vehicle)
    want = _euler_reference(control_time, controls, obs_time, motion_model, vehicle)
    assert got.shape == (35, 3) and obs_time[-2] < control_time[-1]
    np.testing.assert_allclose(got, want, atol=1e-10, rtol=0)
    np.testing.assert_array_equal(got[0], 0.0)  # before the first sample the robot stands


def test_integrate_controls_two_columns_equal_three():
    rng = np.random.default_rng(4)
    control_time = _irregular_times(rng, 50, 0.02, 0.03, 0.0)
    controls = np.stack([rng.uniform(0, 3, 50), rng.uniform(-0.3, 0.3, 50)], -1)
    obs_time = np.array([0.3, 0.6, 0.9, 1.1])
    two = lf.integrate_controls(control_time, controls, obs_time, "ackermann")
    three = lf.integrate_controls(control_time, np.c_[controls, np.ones(50)], obs_time,
                                  "ackermann")
    np.testing.assert_array_equal(two, three)


def test_integrate_straight_line_is_exact():
    control_time = np.arange(0.0, 2.0, 0.025)
    controls = np.stack([np.full(80, 2.0), np.zeros(80)], -1)
    moves = lf.integrate_controls(control_time, controls, np.array([0.5, 1.0, 1.7]),
                                  "ackermann")
    np.testing.assert_allclose(moves, [[0, 1.0, 0], [0, 1.0, 0], [0, 1.4, 0]], atol=1e-12)


def test_integrate_default_vehicle_is_victoria_park():
    assert lf.VICTORIA_PARK_VEHICLE == lf.AckermannVehicle(2.83, 0.76, 3.78, 0.50)
    rng = np.random.default_rng(5)
    control_time = np.arange(0.0, 1.0, 0.025)
    controls = np.stack([rng.uniform(1, 3, 40), rng.uniform(-0.3, 0.3, 40)], -1)
    obs_time = np.array([0.4, 0.9])
    np.testing.assert_allclose(
        lf.integrate_controls(control_time, controls, obs_time, "ackermann"),
        _euler_reference(control_time, controls, obs_time, "ackermann", lf.VICTORIA_PARK_VEHICLE),
        atol=1e-12)


def test_integrate_odometry_composes_moves():
    rng = np.random.default_rng(6)
    increments = np.stack([rng.normal(0, 0.1, 30), rng.uniform(0, 0.2, 30),
                           rng.normal(0, 0.1, 30)], -1)
    control_time = np.arange(1, 31) * 0.1
    obs_time = np.array([0.05, 0.5, 1.0, 2.55, 2.93])
    got = lf.integrate_controls(control_time, increments, obs_time, "odometry")
    # Reference: compose the moves ending in each interval with plain Python.
    pose = [0.0, 0.0, 0.0]
    poses = [tuple(pose)]
    for rot1, trans, rot2 in increments:
        pose = [pose[0] + trans * math.cos(pose[2] + rot1),
                pose[1] + trans * math.sin(pose[2] + rot1), pose[2] + rot1 + rot2]
        poses.append(tuple(pose))
    counts = [sum(ct <= t for ct in control_time) for t in obs_time]
    previous = [poses[0]] + [poses[c] for c in counts[:-1]]
    want = lf.odometry_between(np.array(previous), np.array([poses[c] for c in counts]))
    np.testing.assert_allclose(got, want, atol=1e-12)
    np.testing.assert_array_equal(got[0], 0.0)  # no move ends before 0.05 s
    # Composing the steps again lands where composing all samples lands.
    np.testing.assert_allclose(lf.odometry_path(got)[-1, :2], poses[counts[-1]][:2], atol=1e-12)


def test_odometry_path_and_between_are_inverse():
    rng = np.random.default_rng(7)
    moves = np.stack([rng.uniform(-1, 1, 20), rng.uniform(0.01, 1, 20), rng.uniform(-1, 1, 20)],
                     -1)
    initial = np.array([3.0, -1.0, 2.5])
    path = lf.odometry_path(moves, initial)
    back = lf.odometry_between(np.concatenate([initial[None], path[:-1]]), path)
    np.testing.assert_allclose(back[:, 1], moves[:, 1], atol=1e-12)
    np.testing.assert_allclose(lf.wrap_angle_np(back[:, [0, 2]] - moves[:, [0, 2]]), 0,
                               atol=1e-12)
    assert np.all((path[:, 2] >= -np.pi) & (path[:, 2] < np.pi))


def test_tiny_translation_is_a_pure_turn():
    moves = lf.odometry_between(np.zeros((1, 3)), np.array([[-1e-5, 2e-5, 0.4]]))
    np.testing.assert_allclose(moves, [[0.0, math.hypot(1e-5, 2e-5), 0.4]], atol=1e-15)


@pytest.mark.parametrize("args, message", [
    ((np.array([0.0, 0.2, 0.1]), np.zeros((3, 2)), np.array([1.0]), "velocity"),
     r"integrate_controls: 'control_time' is not strictly increasing"),
    ((np.array([0.0, 0.1]), np.zeros((3, 2)), np.array([1.0]), "velocity"),
     r"'controls' has shape \(3, 2\); expected \(2, \*\)"),
    ((np.array([0.0, 0.1]), np.zeros((2, 2)), np.array([1.0]), "odometry"),
     r"'controls' has shape \(2, 2\); expected \(2, 3\)"),
    ((np.array([0.0, 0.1]), np.zeros((2, 1)), np.array([1.0]), "velocity"),
     r"'controls' has 1 column\(s\); expected \(v, omega\)"),
    ((np.array([0.0, 0.1]), np.zeros((2, 2)), np.array([1.0, np.nan]), "velocity"),
     r"'obs_time' contains NaN or inf"),
    ((np.array([0.0, 0.1]), np.zeros((2, 2)), np.array([1.0]), "tank"),
     r"unknown motion_model 'tank'"),
])
def test_integrate_controls_errors(args, message):
    with pytest.raises(lf.LogFormatError, match=message):
        lf.integrate_controls(*args)


def test_interpolate_poses_unwraps_the_heading_and_holds_the_ends():
    """One interpolation serves the MRCLAM and ROS bag loaders: across +-pi the heading goes
    the short way round; outside the samples' span the end poses are held."""
    from jaxslam.datasets.log_format import interpolate_poses

    pose_time = np.array([0.0, 1.0])
    poses = np.array([[0.0, 0.0, np.pi - 0.1], [2.0, -4.0, -np.pi + 0.1]])
    got = interpolate_poses(np.array([-1.0, 0.5, 2.0]), pose_time, poses)
    np.testing.assert_allclose(got[1, :2], [1.0, -2.0], rtol=0, atol=1e-12)
    np.testing.assert_allclose(abs(got[1, 2]), np.pi, rtol=0, atol=1e-12)  # not 0
    np.testing.assert_allclose(got[0], poses[0], rtol=0, atol=1e-12)
    np.testing.assert_allclose(got[2], poses[1], rtol=0, atol=1e-12)
