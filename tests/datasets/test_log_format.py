"""The jaxslam log format: round trips, every validation error."""
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
        command_time=np.linspace(0.0, 1.2, 9),
        commands=rng.normal(0.0, 0.3, (9, 2)),
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
     "initial_pose", "obs_radius", "command_time", "commands"),
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
    "commands alone": (_drop("command_time"),
                       r"'commands' is present but 'command_time' is missing"),
    "commands unsorted": (_poke("command_time", (3,), 0.0),
                          r"'command_time' is not strictly increasing"),
    "commands with dt": (_set("commands", lambda a: np.zeros((9, 3))),
                         r"'commands' has shape \(9, 3\); expected \(9, 2\)"),
    "commands NaN": (_poke("commands", (4, 1), np.nan), r"'commands' contains NaN or inf"),
    "command_time empty": (_set("command_time", lambda a: np.zeros(0)),
                           r"'command_time' is empty"),
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


# ------------------------------------------------------------------------------ command stream


def _commanded_log(commands, command_time, time) -> lf.RobotLog:
    steps = len(time)
    return lf.RobotLog(time=np.asarray(time, float), motion_model="velocity",
                       controls=np.zeros((steps, 3)), obs_z=np.ones((steps, 1, 2)),
                       obs_valid=np.ones((steps, 1), bool), truth_pose=np.zeros((steps, 3)),
                       initial_pose=np.array([1.0, 2.0, 0.5]),
                       command_time=np.asarray(command_time, float),
                       commands=np.asarray(commands, float))


def test_at_command_delay_against_hand_computed_moves():
    """1 m/s straight ahead from t = 0, steps at 0.5, 1.0, 1.5 s: 0.25 s late the robot stands
    still until 0.25 s, so it moves 0.25, 0.5, 0.5 m; 0.75 s late 0, 0.25, 0.5 m (the first
    step's 0 m is a pure turn of 0 rad, below min_translation)."""
    log = _commanded_log([[1.0, 0.0]], [0.0], [0.5, 1.0, 1.5])
    late = log.at_command_delay(0.25)
    assert late.motion_model == "odometry"
    np.testing.assert_allclose(late.controls, [[0, 0.25, 0], [0, 0.5, 0], [0, 0.5, 0]],
                               atol=1e-12)
    np.testing.assert_allclose(log.at_command_delay(0.75).controls[:, 1], [0.0, 0.25, 0.5],
                               atol=1e-12)
    for name in ("time", "obs_z", "obs_valid", "truth_pose", "initial_pose", "command_time",
                 "commands"):  # only the moves change
        np.testing.assert_array_equal(getattr(late, name), getattr(log, name), err_msg=name)


def test_at_command_delay_is_integrate_controls_of_the_shifted_stream():
    from jaxslam.datasets.odometry import integrate_controls

    rng = np.random.default_rng(5)
    command_time = np.arange(0.0, 6.0, 0.02)
    commands = np.stack([rng.uniform(0.2, 0.6, command_time.size),
                         rng.uniform(-0.8, 0.8, command_time.size)], -1)
    log = _commanded_log(commands, command_time, np.arange(0.25, 6.0, 0.25))
    for delay in (-0.1, 0.0, 0.23):
        expected = integrate_controls(command_time + delay, commands, log.time, "velocity",
                                      min_translation=1e-3)
        np.testing.assert_array_equal(log.at_command_delay(delay, 1e-3).controls, expected)


def test_at_command_delay_needs_a_stream_and_a_finite_delay():
    log = _commanded_log([[1.0, 0.0]], [0.0], [0.5, 1.0])
    with pytest.raises(lf.LogFormatError, match="no command stream"):
        log._replace(command_time=None, commands=None).at_command_delay(0.1)
    with pytest.raises(lf.LogFormatError, match="expected a finite number of seconds"):
        log.at_command_delay(float("nan"))
