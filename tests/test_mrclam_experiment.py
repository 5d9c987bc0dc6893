"""experiments/mrclam.py's barcode diagnostic (``with_barcodes``) on a tiny exact log."""
import numpy as np
import pytest

from experiments.mrclam import main, with_barcodes
from jaxslam.datasets.log_format import RobotLog
from jaxslam.types import FilterConfig


def _log_and_ids(steps=30):
    """A straight drive past five trees, exact odometry and observations, (T, K) tree ids."""
    trees = np.array([[2.0, 2.0], [4.0, -2.0], [6.0, 2.0], [8.0, -2.0], [10.0, 2.0]])
    truth = np.stack([0.4 * np.arange(1, steps + 1), np.zeros(steps), np.zeros(steps)], 1)
    offset = trees[None] - truth[:, None, :2]
    z = np.stack([np.hypot(offset[..., 0], offset[..., 1]),
                  np.arctan2(offset[..., 1], offset[..., 0])], -1)
    valid = z[..., 0] < 6.0
    log = RobotLog(time=np.arange(steps, dtype=float), motion_model="odometry",
                   controls=np.tile([0.0, 0.4, 0.0], (steps, 1)), obs_z=z, obs_valid=valid,
                   truth_pose=truth, truth_landmarks=trees)
    ids = np.where(valid, np.arange(5)[None], -1)
    return log, ids


@pytest.mark.slow  # two calibrations, ~40 s of compiling
@pytest.mark.parametrize("barcodes", ["both", "calibration"])
def test_with_barcodes_calibrates_and_filters_an_exact_log(barcodes):
    log, ids = _log_and_ids()
    config = FilterConfig(num_particles=8, max_landmarks=16)
    ate, landmarks, verdict = with_barcodes(log, ids, config, barcodes, seed=0)
    # Exact odometry and observations: whichever association runs, the path stays on the
    # truth (the observations' calibrated floor is centimetres) and the five trees seen are
    # mapped once each (the barcodes give exactly five identities).
    assert ate < 0.1
    assert landmarks == 5
    assert isinstance(verdict, str) and verdict


def test_barcodes_refuse_the_options_they_do_not_run(capsys):
    for extra in (["--no-calibrate"], ["--close-loops"]):
        with pytest.raises(SystemExit):
            main(["--barcodes", "both", "--robots", "1", *extra])
        assert "--barcodes calibrates and filters only" in capsys.readouterr().err
