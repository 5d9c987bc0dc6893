"""experiments/mrclam_frame.py: the heading error and the map's rigid fit, against NumPy."""
import numpy as np
import pytest

from experiments import mrclam_frame as frame


def _reference_fit(est, truth):
    """Kabsch in plain NumPy float64: the rotation [deg] and shift of the rigid transform
    carrying ``est`` (N, 2) onto ``truth``, and the rms error after it."""
    ce, ct = est.mean(0), truth.mean(0)
    u, _, vt = np.linalg.svd((est - ce).T @ (truth - ct))
    d = np.sign(np.linalg.det(vt.T @ u.T))
    r = vt.T @ np.diag([1.0, d]) @ u.T
    shift = ct - r @ ce
    fitted = est @ r.T + shift
    return (np.degrees(np.arctan2(r[1, 0], r[0, 0])), np.hypot(*shift),
            np.sqrt(np.mean(np.sum((fitted - truth) ** 2, 1))))


def test_map_frame_recovers_a_rotated_map_and_pairs_by_id():
    """Twelve landmarks seen in a frame rotated by 20 degrees and shifted, with 3 cm noise,
    stored in shuffled slots among inactive and unknown ones: the fit recovers the rotation
    and agrees with Kabsch (float32 inside align_se2: 1e-3 deg, 1e-4 m)."""
    rng = np.random.default_rng(0)
    truth = rng.uniform(-6.0, 6.0, (12, 2))
    angle = np.radians(-20.0)
    rot = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    seen = (truth - [0.5, -1.0]) @ rot.T + rng.normal(0.0, 0.03, truth.shape)
    slots = 16
    order = rng.permutation(slots)[:12]
    mean = rng.normal(0.0, 50.0, (slots, 2))  # inactive or unknown slots must not count
    ids = np.full(slots, -1)
    active = np.zeros(slots, bool)
    mean[order], ids[order], active[order] = seen, np.arange(12), True
    active[[s for s in range(slots) if s not in order][0]] = True  # active, id unknown
    got = frame.map_frame(mean, active, ids, truth)
    rotation, shift, fitted = _reference_fit(seen, truth)
    assert got["count"] == 12
    assert got["rotation"] == pytest.approx(rotation, abs=1e-3)
    assert got["rotation"] == pytest.approx(20.0, abs=0.5)
    assert got["shift"] == pytest.approx(shift, abs=1e-4)
    assert got["fitted"] == pytest.approx(fitted, abs=1e-4)
    assert got["fitted"] < 0.05 < 1.0 < got["error"]


def test_map_frame_refuses_fewer_than_two_known_landmarks():
    with pytest.raises(ValueError, match="at least 2 landmarks with a known id; got 1"):
        frame.map_frame(np.zeros((4, 2)), np.array([1, 1, 0, 0], bool),
                        np.array([0, -1, 1, 2]), np.zeros((3, 2)))


def test_heading_error_wraps_and_picks_the_steps():
    truth = np.zeros((5, 3))
    pose = np.zeros((5, 3))
    pose[:, 2] = [0.0, np.pi - 0.1, -np.pi + 0.1, 0.2, -0.3]
    truth[2, 2] = np.pi - 0.1  # 0.2 rad apart across the wrap
    got = frame.heading_error_deg(pose, truth, [1, 2, 4])
    np.testing.assert_allclose(got, np.degrees([np.pi - 0.1, 0.2, 0.3]), atol=1e-4)


def test_bad_options_are_refused_before_any_data_is_read(capsys):
    for argv, words in ((["--keys", "0", "--command-delay", "0.2"], "--keys 0: expected 1"),
                        ([], "--command-delay")):
        with pytest.raises(SystemExit):
            frame.main(["--data", "/nonexistent", *argv])
        assert words in capsys.readouterr().err
