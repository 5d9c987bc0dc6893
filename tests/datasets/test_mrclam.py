"""MRCLAM loader: synthetic files in MRCLAM format against a hand-computed float64 reference,
robot-sighting removal, max_obs truncation, errors; plus a smoke test on the real dataset 1
(skipped when ``../shared/data/mrclam1`` next to the repository is absent).

The synthetic robot 1 drives 5 s at 50 Hz: v = 0.1 m/s straight for t < 2 s, v = 0.1 m/s and
omega = 0.5 rad/s for 2 <= t < 4 s, standing still from 4 s. Its Vicon pose is
(1 + 0.1 t, 2 - 0.05 t, wrap(3 + 0.1 t)), whose heading wraps at t = 1.4159 s.
"""
from pathlib import Path

import numpy as np
import pytest

from jaxslam.datasets import mrclam as mm
from jaxslam.datasets import mrclam_convert as mc
from jaxslam.datasets.log_format import LogFormatError, load_log, save_log, validate_log
from jaxslam.datasets.odometry import odometry_path

DATA_DIR = Path(__file__).resolve().parents[3] / "shared" / "data" / "mrclam1"

RATE = 50
ROWS = 250  # 0 .. 4.98 s
SPEED, TURN_RATE = 0.1, 0.5
BARCODES = {1: 5, 2: 14, 3: 41, 4: 32, 5: 23, 6: 72, 7: 27, 8: 54}
LANDMARKS = {8: (3.0, -1.0), 6: (1.0, 4.0), 7: (-2.0, 0.5)}  # written unsorted on purpose
# time, barcode, range, bearing. Subjects: 72 -> 6 (index 0), 27 -> 7 (1), 54 -> 8 (2);
# 5, 14, 41 are robots 1-3; 43 is no one's. The 2.0 row comes before the 1.41 row.
MEASUREMENTS = [
    (1.0, 72, 2.0, 0.1),
    (1.0, 5, 1.5, 0.2),     # robot 1: dropped
    (1.0, 27, 3.0, -0.2),
    (2.0, 54, 1.0, 0.0),
    (1.41, 54, 1.2, 0.05),  # off the 50 Hz grid, across the heading wrap
    (3.0, 72, 2.5, 0.3),
    (3.0, 14, 2.0, 0.0),    # robot 2: dropped
    (3.0, 27, 2.6, 0.31),
    (3.0, 54, 2.7, 0.32),   # third landmark at 3.0: truncated with max_obs = 2
    (3.0, 43, 1.0, 0.0),    # unknown barcode: dropped
    (3.5, 41, 1.0, 0.1),    # robot 3 only: no step at 3.5
    (4.6, 27, 1.1, -0.1),
    (5.2, 72, 0.9, 0.0),    # after the last odometry row: the last sample (v = 0) is held
]
TIMES = [1.0, 1.41, 2.0, 3.0, 4.6, 5.2]



def _wrap(angle):
    """Wrap to [-pi, pi) in NumPy float64 (the floor formula of jaxslam.geometry.wrap_angle)."""
    return angle - 2.0 * np.pi * np.floor((angle + np.pi) / (2.0 * np.pi))

def _commands(time):
    speed = np.where(time < 4.0, SPEED, 0.0)
    rate = np.where((time >= 2.0) & (time < 4.0), TURN_RATE, 0.0)
    return speed, rate


def _truth(time):
    time = np.minimum(time, (ROWS - 1) / RATE)  # held after the last Vicon row
    return np.stack([1.0 + 0.1 * time, 2.0 - 0.05 * time, _wrap(3.0 + 0.1 * time)], -1)


def _write(path, rows, header=""):
    path.write_text(header + "".join(" ".join(str(v) for v in row) + "\n" for row in rows))


def write_mrclam(root: Path, robot: int = 1, measurements=MEASUREMENTS) -> Path:
    """A small MRCLAM-format folder (tab / space separated, '#' headers on the tables)."""
    root.mkdir(parents=True, exist_ok=True)
    time = np.arange(ROWS) / RATE
    speed, rate = _commands(time)
    _write(root / f"Robot{robot}_Odometry.dat",
           [(f"{t:.2f}", repr(float(v)), repr(float(w))) for t, v, w in zip(time, speed, rate)])
    _write(root / f"Robot{robot}_Groundtruth.dat",
           [(f"{t:.2f}",) + tuple(repr(float(c)) for c in pose)
            for t, pose in zip(time, _truth(time))])
    _write(root / f"Robot{robot}_Measurement.dat", measurements)
    header = "# UTIAS Multi-Robot Cooperative Localization and Mapping Dataset\n# Format:\n"
    (root / mm.BARCODES_NAME).write_text(
        header + "".join(f"  {s} \t  {b} \n" for s, b in BARCODES.items()))
    (root / mm.LANDMARKS_NAME).write_text(
        header + "".join(f"  {s} \t {x} \t {y} \t 0.0001 \t 0.0002 \n"
                         for s, (x, y) in LANDMARKS.items()))
    return root


@pytest.fixture
def root(tmp_path):
    return write_mrclam(tmp_path / "mrclam")


# ------------------------------------------------------------------------- hand-computed reference


def euler_arc(steps: int, h: float = 1 / RATE, speed=SPEED, rate=TURN_RATE):
    """Explicit Euler from the zero pose, ``steps`` steps of h at constant (v, omega), closed form.

    heading_j = j h omega, p = sum_{j<n} h v e^{i j a} = h v (1 - e^{i n a}) / (1 - e^{i a}).
    """
    angle = h * rate
    total = h * speed * (1 - np.exp(1j * steps * angle)) / (1 - np.exp(1j * angle))
    return total.real, total.imag, steps * angle


def move(x, y, theta):
    """(rot1, trans, rot2) of the relative pose (x, y, theta)."""
    rot1 = np.arctan2(y, x) if np.hypot(x, y) > 0 else 0.0
    return np.array([rot1, np.hypot(x, y), theta - rot1])


ARC = move(*euler_arc(50))  # one second of turning: 2 -> 3 s, and 3 -> 4 s then standing
STRAIGHT = {dt: np.array([0.0, SPEED * dt, 0.0]) for dt in (1.0, 0.41, 0.59)}
STILL = np.zeros(3)


def test_euler_reference_is_close_to_the_exact_arc():
    x, y, theta = euler_arc(50)
    radius = SPEED / TURN_RATE
    exact = radius * np.sin(0.5), radius * (1 - np.cos(0.5))
    assert theta == pytest.approx(0.5)
    assert np.hypot(x - exact[0], y - exact[1]) < 5e-4  # Euler at 50 Hz: O(h v omega) per s


# ---------------------------------------------------------------------- synthetic: distinct times


def test_steps_at_distinct_measurement_times(root):
    run = mm.read_mrclam(root, 1)
    steps = mc.mrclam_steps(run, max_obs=2, max_gap=None)
    np.testing.assert_array_equal(steps.time, TIMES)
    assert (steps.num_robot_sightings, steps.num_unknown_barcodes) == (3, 1)
    assert (steps.num_truncated, steps.num_before_start, steps.num_filler_steps) == (1, 0, 0)
    np.testing.assert_array_equal(
        steps.obs_landmark, [[0, 1], [2, -1], [2, -1], [0, 1], [1, -1], [0, -1]])
    np.testing.assert_array_equal(steps.obs_valid, steps.obs_landmark >= 0)
    expected_z = np.zeros((6, 2, 2))
    expected_z[0] = [[2.0, 0.1], [3.0, -0.2]]
    expected_z[1, 0], expected_z[2, 0] = [1.2, 0.05], [1.0, 0.0]
    expected_z[3] = [[2.5, 0.3], [2.6, 0.31]]  # file order kept; the third (2.7) is dropped
    expected_z[4, 0], expected_z[5, 0] = [1.1, -0.1], [0.9, 0.0]
    np.testing.assert_array_equal(steps.obs_z, expected_z)


def test_log_matches_the_hand_computed_reference(root):
    log = mm.load_mrclam(root, robot=1, max_obs=2, max_gap=None)
    assert log.motion_model == "odometry"
    np.testing.assert_array_equal(log.time, TIMES)
    expected = np.stack([STRAIGHT[1.0], STRAIGHT[0.41], STRAIGHT[0.59], ARC, ARC, STILL])
    np.testing.assert_allclose(log.controls, expected, rtol=0, atol=1e-12)
    np.testing.assert_allclose(log.truth_pose, _truth(np.array(TIMES)), rtol=0, atol=1e-12)
    assert log.truth_pose[1, 2] == pytest.approx(3.141)  # interpolated across the wrap
    np.testing.assert_allclose(log.initial_pose, [1.0, 2.0, 3.0], rtol=0, atol=1e-15)
    np.testing.assert_array_equal(log.truth_landmarks, [LANDMARKS[s] for s in (6, 7, 8)])
    assert log.obs_z.shape == (6, 2, 2) and log.obs_valid.sum() == 8
    validate_log(log)


def test_command_delay_moves_only_the_moves(root):
    """Commands 1 s late: the robot stands for 1 s, drives straight 1 -> 3 s, turns 3 -> 5 s
    (the last turning sample, 3.98 s, acts at 4.98 s), then stands; steps, observations,
    start and truth are those of the log as stamped."""
    stamped = mm.load_mrclam(root, robot=1, max_obs=2, max_gap=None)
    late = mm.load_mrclam(root, robot=1, max_obs=2, max_gap=None, command_delay=1.0)
    expected = np.stack([STILL, STRAIGHT[0.41], STRAIGHT[0.59], STRAIGHT[1.0],
                         move(*euler_arc(80)), move(*euler_arc(20))])
    np.testing.assert_allclose(late.controls, expected, rtol=0, atol=1e-9)
    for field in ("time", "obs_z", "obs_valid", "truth_pose", "truth_landmarks",
                  "initial_pose"):
        np.testing.assert_array_equal(getattr(late, field), getattr(stamped, field))
    same = mm.load_mrclam(root, robot=1, max_obs=2, max_gap=None, command_delay=0.0)
    np.testing.assert_array_equal(same.controls, stamped.controls)
    for bad in (np.nan, np.inf):
        with pytest.raises(ValueError, match="command_delay=.*finite number of seconds"):
            mm.load_mrclam(root, robot=1, command_delay=bad)


def test_the_log_carries_its_commands(root, tmp_path):
    """The commanded velocities travel in the log (command_time, commands), through a saved
    .npz too, so ``at_command_delay`` rebuilds what the loader's ``command_delay`` gives."""
    from jaxslam.datasets.log_format import load_log, save_log

    run = mm.read_mrclam(root, 1)
    stamped = mm.load_mrclam(root, robot=1, max_obs=2, max_gap=None)
    np.testing.assert_array_equal(stamped.command_time, run.odometry_time)
    np.testing.assert_array_equal(stamped.commands, run.odometry)
    save_log(tmp_path / "robot1.npz", stamped)
    late = mm.load_mrclam(root, robot=1, max_obs=2, max_gap=None, command_delay=1.0)
    for log in (stamped, load_log(tmp_path / "robot1.npz")):
        # the default pure-turn threshold is the loader's: at 0 s the stored moves come back
        np.testing.assert_array_equal(log.at_command_delay(0.0).controls, stamped.controls)
        np.testing.assert_array_equal(log.at_command_delay(1.0).controls, late.controls)


def test_dead_reckoning_from_the_initial_pose(root):
    log = mm.load_mrclam(root, robot=1, max_gap=None)
    path = odometry_path(log.controls, log.initial_pose)
    x, y, theta = euler_arc(100)  # 2 s of turning in total, after 0.2 m along heading 3
    start = np.array([1.0 + 0.2 * np.cos(3.0), 2.0 + 0.2 * np.sin(3.0), 3.0])
    rotated = np.array([np.cos(3.0) * x - np.sin(3.0) * y, np.sin(3.0) * x + np.cos(3.0) * y])
    np.testing.assert_allclose(path[-1, :2], start[:2] + rotated, rtol=0, atol=1e-12)
    assert path[-1, 2] == pytest.approx(_wrap(3.0 + theta), abs=1e-12)


def test_filler_steps_cut_long_gaps(root):
    run = mm.read_mrclam(root, 1)
    steps = mc.mrclam_steps(run, max_gap=1.0)  # only 3.0 -> 4.6 is longer than 1 s
    np.testing.assert_allclose(steps.time, [1.0, 1.41, 2.0, 3.0, 3.8, 4.6, 5.2], atol=1e-12)
    assert steps.num_filler_steps == 1 and not steps.obs_valid[4].any()
    log = mc.mrclam_log(run, steps)
    # 3.0 -> 3.8: 40 Euler steps of turning; 3.8 -> 4.6: 10 more, then standing still.
    expected = np.stack([STRAIGHT[1.0], STRAIGHT[0.41], STRAIGHT[0.59], ARC,
                         move(*euler_arc(40)), move(*euler_arc(10)), STILL])
    np.testing.assert_allclose(log.controls, expected, rtol=0, atol=1e-12)
    np.testing.assert_allclose(log.truth_pose[4], _truth(np.array(3.8)), rtol=0, atol=1e-12)
    np.testing.assert_allclose(
        mc.fill_gaps(np.array([1.0, 2.0]), 0.0, 0.4), [1 / 3, 2 / 3, 4 / 3, 5 / 3], atol=1e-12)
    assert mc.fill_gaps(np.array([1.0, 2.0]), 0.0, None).shape == (0,)


# ---------------------------------------------------------------------------- synthetic: bins


def test_bins_of_step_dt(root):
    run = mm.read_mrclam(root, 1)
    steps = mc.mrclam_steps(run, max_obs=2, step_dt=1.0)
    np.testing.assert_allclose(steps.time, [1.0, 2.0, 3.0, 4.0, 5.0, 6.0], atol=1e-12)
    # (0,1]: 72, 27;  (1,2]: 54 at 1.41, 54 at 2.0 (time order);  (2,3]: 72, 27 (+54 cut);
    # (3,4]: only robot 3;  (4,5]: 27;  (5,6]: 72.
    np.testing.assert_array_equal(
        steps.obs_landmark, [[0, 1], [2, 2], [0, 1], [-1, -1], [1, -1], [0, -1]])
    assert steps.num_truncated == 1 and steps.num_filler_steps == 0
    log = mc.mrclam_log(run, steps)
    expected = np.stack([STRAIGHT[1.0], STRAIGHT[1.0], ARC, ARC, STILL, STILL])
    np.testing.assert_allclose(log.controls, expected, rtol=0, atol=1e-12)
    assert mc.mrclam_steps(run, max_obs=3, step_dt=1.0).num_truncated == 0


def test_round_trip_through_the_npz_format(root, tmp_path):
    log = mm.load_mrclam(root)
    save_log(tmp_path / "mrclam.npz", log)
    again = load_log(tmp_path / "mrclam.npz")
    np.testing.assert_array_equal(again.controls, log.controls)
    np.testing.assert_array_equal(again.obs_valid, log.obs_valid)


def test_printed_times_are_put_back_on_the_grid():
    grid = 999.0 + np.arange(200) / RATE  # past 1000 s, 5 digits print 0.1 s
    printed = np.array([float(f"{t:.5g}") for t in grid])
    assert (np.diff(printed) == 0).any()
    np.testing.assert_allclose(mm.regular_times(printed, RATE, "f"), grid, rtol=0, atol=1e-9)
    with pytest.raises(LogFormatError, match="not increase.*rate_hz"):
        mm.regular_times(printed, None, "f")
    with pytest.raises(LogFormatError, match="off the 50 Hz grid"):
        mm.regular_times(np.delete(grid, 10), RATE, "f")  # a missing row


# ------------------------------------------------------------------------------------- errors


def test_missing_folder_and_files(tmp_path, root):
    with pytest.raises(mm.MrclamFileError, match="folder not found.*Robot1_Odometry.dat"):
        mm.load_mrclam(tmp_path / "nowhere")
    with pytest.raises(FileNotFoundError):
        mm.load_mrclam(tmp_path / "nowhere")
    with pytest.raises(LogFormatError, match="Robot2_Odometry.dat: file not found"):
        mm.load_mrclam(root, robot=2)
    (root / mm.BARCODES_NAME).unlink()
    with pytest.raises(LogFormatError, match="Barcodes.dat: file not found.*subject, barcode"):
        mm.load_mrclam(root)


@pytest.mark.parametrize("robot", [0, 6, -1, 1.0, True, "1"])
def test_robot_number(root, robot):
    with pytest.raises(ValueError, match=r"robot=.*expected an integer in 1\.\.5"):
        mm.load_mrclam(root, robot=robot)


@pytest.mark.parametrize("name, index, line, match", [
    ("Robot1_Odometry.dat", 25, "0.5 0.1\n", r"line 26: 2 field\(s\).*expected 3 numbers"),
    ("Robot1_Odometry.dat", 25, "0.5 abc 0\n", "line 26: non-numeric"),
    ("Robot1_Groundtruth.dat", 25, "0.5 1 nan 0\n", "line 26: NaN or inf"),
    ("Robot1_Measurement.dat", 0, "1.0 72 -2.0 0.1\n", "negative range"),
    ("Robot1_Measurement.dat", 0, "1.0 72.5 2.0 0.1\n", "barcode 72.5.*not an integer"),
    (mm.LANDMARKS_NAME, 2, "6 1.0 4.0 0.1\n", "line 3: 4 field"),
])
def test_malformed_rows(root, name, index, line, match):
    path = root / name
    lines = path.read_text().splitlines(keepends=True)
    lines[index] = line
    path.write_text("".join(lines))
    with pytest.raises(LogFormatError, match=match):
        mm.load_mrclam(root)


def test_other_format_errors(root, tmp_path):
    (root / mm.BARCODES_NAME).write_text("1 5\n6 72\n7 72\n")
    with pytest.raises(LogFormatError, match="barcode 72 is listed more than once"):
        mm.load_mrclam(root)
    only_robots = write_mrclam(tmp_path / "robots", measurements=[(1.0, 5, 1.0, 0.0)])
    with pytest.raises(LogFormatError, match="no landmark measurement"):
        mm.load_mrclam(only_robots)
    (only_robots / "Robot1_Measurement.dat").write_text("# nothing\n")
    with pytest.raises(LogFormatError, match="no data rows"):
        mm.load_mrclam(only_robots)
    odometry = write_mrclam(tmp_path / "off_grid") / "Robot1_Odometry.dat"
    odometry.write_text(odometry.read_text().replace("0.50 ", "0.56 "))
    with pytest.raises(LogFormatError, match="off the 50 Hz grid"):
        mm.load_mrclam(odometry.parent)


@pytest.mark.parametrize("kwargs, match", [
    (dict(max_obs=0), "max_obs=0"), (dict(step_dt=0.0), "step_dt=0.0"),
    (dict(max_gap=-1.0), "max_gap=-1.0")])
def test_bad_parameters(root, kwargs, match):
    with pytest.raises(ValueError, match=match):
        mm.load_mrclam(root, **kwargs)


# ---------------------------------------------------------------------------------- real data


def test_real_dataset_robot_1():
    if not (DATA_DIR / "Robot1_Odometry.dat").is_file():
        pytest.skip(f"MRCLAM dataset 1 not found at {DATA_DIR}")
    import jax.numpy as jnp

    from jaxslam.metrics import ate_rmse

    run = mm.read_mrclam(DATA_DIR, 1)
    steps = mc.mrclam_steps(run)
    log = mc.mrclam_log(run, steps)
    counts = log.obs_valid.sum(1)
    assert run.odometry_time.shape == (75000,) and run.odometry_time[-1] == pytest.approx(1499.98)
    assert steps.num_robot_sightings == 952 and steps.num_truncated == 0
    assert counts.sum() == 4771 and (counts > 0).sum() == 3349  # distinct landmark times
    assert 3000 < log.num_steps < 5000
    assert np.diff(np.concatenate([[0.0], log.time])).max() <= mc.DEFAULT_MAX_GAP + 1e-9
    assert log.truth_landmarks.shape == (15, 2)
    ranges = log.obs_z[..., 0][log.obs_valid]
    bearings = log.obs_z[..., 1][log.obs_valid]
    assert 0.5 < ranges.min() and ranges.max() < 10.0
    assert np.abs(bearings).max() < 0.7  # the camera's field of view is about +-30 degrees
    assert np.abs(log.truth_pose[:, :2]).max() < 8.0  # the 15 m x 8 m arena
    path = odometry_path(log.controls, log.initial_pose)
    ate = float(ate_rmse(jnp.asarray(path), jnp.asarray(log.truth_pose)))
    final = np.hypot(*(path[-1, :2] - log.truth_pose[-1, :2]))
    # Commanded velocities drift by metres over 1,500 s (about 4.8 m ATE here), but the first
    # minute stays close to Vicon.
    assert np.isfinite(ate) and 0.1 < ate < 15.0 and np.isfinite(final)
    early = np.searchsorted(log.time, 60.0)
    assert np.hypot(*(path[early, :2] - log.truth_pose[early, :2])) < 1.0


def test_real_dataset_barcodes_of_subjects_11_and_17_read_each_other_s_position():
    """A fact of the shipped tables, stated in ``mrclam_convert``: every robot's readings
    of subject 11's barcode lie at subject 17's Vicon position and the other way round, so
    ``obs_landmark`` indices 5 and 11 name each other's ``truth_landmarks`` row. Per robot,
    the median range error of those readings against the listed landmark is over 1 m and
    against the other one under 0.2 m (the camera's robust range std is 0.09-0.15 m)."""
    if not (DATA_DIR / "Robot1_Odometry.dat").is_file():
        pytest.skip(f"MRCLAM dataset 1 not found at {DATA_DIR}")
    for robot in range(1, 6):
        run = mm.read_mrclam(DATA_DIR, robot)
        steps = mc.mrclam_steps(run)
        log = mc.mrclam_log(run, steps)
        step, row = np.nonzero(log.obs_valid)
        listed = steps.obs_landmark[step, row]
        sighted = mc.landmarks_as_sighted(log.truth_landmarks)
        a, b = mc.SWAPPED_LANDMARK_ROWS
        for index, other in ((a, b), (b, a)):
            seen = listed == index
            assert seen.sum() > 100, robot
            pose, measured = log.truth_pose[step[seen], :2], log.obs_z[step[seen], row[seen], 0]
            assert _median_range_error(pose, measured, log.truth_landmarks[index]) > 1.0, robot
            assert _median_range_error(pose, measured, log.truth_landmarks[other]) < 0.2, robot
            np.testing.assert_array_equal(sighted[index], log.truth_landmarks[other])


def _median_range_error(pose, measured, landmark):
    """Median |measured range - range from the true pose (n, 2) to ``landmark`` (2,)|."""
    delta = landmark - pose
    return np.median(np.abs(measured - np.hypot(delta[:, 0], delta[:, 1])))


def test_cli_converts_one_robot(root, tmp_path, capsys):
    """``jaxslam convert FOLDER --robot N``: the loader's log, command stream included, in a
    .npz that loads back; without --robot, with a robot outside 1-5, or with --robot on a
    path that is no MRCLAM folder, a one-line usage error."""
    from jaxslam import cli

    out = tmp_path / "robot1"
    assert cli.main(["convert", str(root), "--robot", "1", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert f"wrote {out}.npz" in printed and "commanded velocities" in printed
    assert "--command-delay auto" in printed
    loaded, direct = load_log(f"{out}.npz"), mm.load_mrclam(root, robot=1)
    for name in ("time", "controls", "obs_z", "obs_valid", "truth_pose", "initial_pose",
                 "command_time", "commands"):
        np.testing.assert_array_equal(getattr(loaded, name), getattr(direct, name),
                                      err_msg=name)
    assert cli.main(["convert", str(root), "--out", str(out)]) == 2
    assert "give --robot 1..5" in capsys.readouterr().err
    assert cli.main(["convert", str(root), "--robot", "6", "--out", str(out)]) == 2
    assert "(got 6)" in capsys.readouterr().err
    assert cli.main(["convert", f"{out}.npz", "--robot", "1", "--out", str(out)]) == 2
    assert "applies to a UTIAS MRCLAM folder" in capsys.readouterr().err
