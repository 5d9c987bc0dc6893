"""experiments/mrclam.py's barcode diagnostic (``with_barcodes``) on a tiny exact log."""
import numpy as np
import pytest

from experiments.mrclam import main, with_barcodes
from jaxslam.types import FilterConfig
from test_pipeline import _log  # tests/ is on sys.path (no tests/__init__.py)


def _log_and_ids(steps=30):
    """test_pipeline's straight drive past five trees (exact odometry and observations) and
    its (T, K) tree ids: observation k of every step is tree k."""
    log = _log(steps)
    return log, np.where(log.obs_valid, np.arange(5)[None], -1)


@pytest.mark.slow  # two calibrations, about 20 s on this 2-core CPU
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
