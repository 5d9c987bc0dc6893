"""experiments/mrclam_diagnostics.py's counting helpers against hand-counted logs."""
import jax.numpy as jnp
import numpy as np
import pytest

import experiments.mrclam_diagnostics as diagnostics
from jaxslam.types import default_params
from jaxslam.validation import check_params


def test_resighting_gaps_counts_each_pause_once():
    """Barcode 0 seen at steps 0, 1, 3, 30, 200 with identities 5, 5, 5, 6, 6; barcode 1 at
    steps 1 and 9 as identities 7 and 8; an invalid row and an unassociated row are ignored.
    Gaps: 1 (kept), 2 (kept), 27 (new), 170 (kept); barcode 1: 8 (new)."""
    steps, rows = 201, 3
    ids = np.full((steps, rows), -1)
    barcode = np.full((steps, rows), -1)
    valid = np.zeros((steps, rows), bool)
    for t, identity in zip((0, 1, 3, 30, 200), (5, 5, 5, 6, 6)):
        ids[t, 0], barcode[t, 0], valid[t, 0] = identity, 0, True
    for t, identity in zip((1, 9), (7, 8)):
        ids[t, 1], barcode[t, 1], valid[t, 1] = identity, 1, True
    ids[5, 2], barcode[5, 2] = 9, 0          # not valid: ignored
    valid[6, 2], barcode[6, 2] = True, 0     # not associated (id -1): ignored
    rows_out = diagnostics.resighting_gaps(ids, barcode, valid)
    assert [bins for bins, _, _ in rows_out] == list(diagnostics.GAP_BINS)
    assert [(kept, new) for _, kept, new in rows_out] == [(1, 0), (1, 0), (0, 1), (0, 1),
                                                          (1, 0)]


def test_resighting_gaps_of_an_empty_log():
    empty = np.zeros((4, 2), int)
    rows = diagnostics.resighting_gaps(empty - 1, empty - 1, empty.astype(bool))
    assert [(kept, new) for _, kept, new in rows] == [(0, 0)] * len(diagnostics.GAP_BINS)


def test_camera_detection_rate_and_miss_runs():
    """A robot at the origin facing landmark 0 (3 m ahead) at steps 0-9 and 20-29 and
    landmark 1 (3 m behind) at steps 10-19 and 30-39. Landmark 0 is reported at steps 0, 1
    and 25, landmark 1 never: 3 detections in 40 in-region pairs. Runs of misses: landmark
    0's 8 (steps 2-9), 5 (20-24) and 4 (26-29), landmark 1's two of 10; four of the five
    last 5 steps or more."""
    steps = 40
    pose = np.zeros((steps, 3))
    pose[10:20, 2] = np.pi
    pose[30:, 2] = np.pi
    landmarks = np.array([[3.0, 0.0], [-3.0, 0.0]])
    barcode = np.full((steps, 1), -1)
    valid = np.zeros((steps, 1), bool)
    barcode[[0, 1, 25], 0] = 0
    valid[[0, 1, 25], 0] = True
    rate, long_runs, runs = diagnostics.camera_detection_rate(pose, landmarks, barcode, valid,
                                                             miss_range=4.0, miss_bearing=0.5)
    assert rate == pytest.approx(3 / 40)
    assert runs == 5 and long_runs == 4


@pytest.mark.parametrize("name", list(diagnostics.VARIANTS))
def test_each_variant_gives_valid_params(name):
    params = default_params()
    changed = params._replace(**{field: jnp.asarray(value, jnp.float32) for field, value
                                 in diagnostics.VARIANTS[name](params).items()})
    check_params(changed)
    if name == "calibrated":
        assert all(np.array_equal(np.asarray(a), np.asarray(b))
                   for a, b in zip(changed, params))
