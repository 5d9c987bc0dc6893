"""experiments/mrclam_diagnostics.py's counting helpers against hand-counted logs."""
import jax.numpy as jnp
import numpy as np
import pytest

import experiments.mrclam_diagnostics as diagnostics
from jaxslam.datasets.mrclam_convert import SWAPPED_LANDMARK_ROWS, landmarks_as_sighted
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
    ids[7, 2], valid[7, 2] = 4, True         # no barcode (-1): ignored
    rows_out = diagnostics.resighting_gaps(ids, barcode, valid)
    assert [bins for bins, _, _ in rows_out] == list(diagnostics.GAP_BINS)
    assert [(kept, new) for _, kept, new in rows_out] == [(1, 0), (1, 0), (0, 1), (0, 1),
                                                          (1, 0)]


def test_resighting_gap_bins_edges():
    """Gaps of 4, 5, 19, 20, 99 and 100 steps fall in bins 2-4, 5-19, 5-19, 20-99, 20-99
    and 100+ (each bin's lower edge included, its upper excluded)."""
    steps = np.cumsum([0, 4, 5, 19, 20, 99, 100])
    ids = np.full((steps[-1] + 1, 1), -1)
    barcode = np.full_like(ids, -1)
    valid = np.zeros(ids.shape, bool)
    ids[steps, 0], barcode[steps, 0], valid[steps, 0] = 3, 2, True
    counts = [kept for _, kept, _ in diagnostics.resighting_gaps(ids, barcode, valid)]
    assert counts == [0, 1, 2, 2, 1]


def test_mixed_identities():
    """Identity 0 sees barcode 3 four times and barcode 4 once; identity 1 barcode 4 only;
    identity 2 barcodes 5, 6, 6: two mixed identities, 1 + 1 observations off majority."""
    pairs = [(0, 3)] * 4 + [(0, 4), (1, 4), (1, 4), (2, 5), (2, 6), (2, 6)]
    ids = np.array([[i] for i, _ in pairs])
    barcode = np.array([[b] for _, b in pairs])
    valid = np.ones(ids.shape, bool)
    assert diagnostics.mixed_identities(ids, barcode, valid) == (2, 2)
    valid[4] = False  # identity 0's one reading of barcode 4
    assert diagnostics.mixed_identities(ids, barcode, valid) == (1, 1)


def test_misses_to_delete():
    """cap 6, threshold -1.5: 7.5 log-odds; p_d 0.8, p_f 0.0117 lose 1.598 a miss (5
    misses), p_d 0.45 lose 0.586 (13 misses)."""
    params = default_params(existence_max=6.0, existence_delete=-1.5,
                            false_alarm_probability=0.0117, detection_probability=0.8)
    assert diagnostics.misses_to_delete(params) == 5
    params = params._replace(detection_probability=jnp.asarray(0.45, jnp.float32))
    assert diagnostics.misses_to_delete(params) == 13
    with pytest.raises(ValueError, match="never delete"):
        diagnostics.misses_to_delete(params._replace(
            detection_probability=jnp.asarray(0.0117, jnp.float32)))


def test_landmarks_as_sighted_swaps_only_the_two_rows():
    listed = np.arange(30.0).reshape(15, 2)
    sighted = landmarks_as_sighted(listed)
    a, b = SWAPPED_LANDMARK_ROWS
    np.testing.assert_array_equal(sighted[a], listed[b])
    np.testing.assert_array_equal(sighted[b], listed[a])
    others = np.setdiff1d(np.arange(15), [a, b])
    np.testing.assert_array_equal(sighted[others], listed[others])
    assert listed[a, 0] == 2 * a  # the input is not changed


def test_resighting_gaps_of_an_empty_log():
    empty = np.zeros((4, 2), int)
    rows = diagnostics.resighting_gaps(empty - 1, empty - 1, empty.astype(bool))
    assert [(kept, new) for _, kept, new in rows] == [(0, 0)] * len(diagnostics.GAP_BINS)
    assert diagnostics.mixed_identities(empty - 1, empty - 1, empty.astype(bool)) == (0, 0)


def test_camera_detection_rate_and_miss_runs():
    """A robot at the origin facing landmark 0 (3 m ahead) at steps 0-9 and 20-29 and
    landmark 1 (3 m behind) at steps 10-19 and 30-39. Landmark 0 is reported at steps 0, 1
    and 25, landmark 1 never: 3 detections in 40 in-region pairs. Runs of misses: landmark
    0's 8 (steps 2-9), 5 (20-24) and 4 (26-29), landmark 1's two of 10; four of the five
    last 5 steps or more. Of the 36 pairs of consecutive in-region steps, 3 follow a
    detection (steps 0, 1, 25) and one of those is detected (step 1); of the 33 after a
    miss, one is (step 25)."""
    steps = 40
    pose = np.zeros((steps, 3))
    pose[10:20, 2] = np.pi
    pose[30:, 2] = np.pi
    landmarks = np.array([[3.0, 0.0], [-3.0, 0.0]])
    barcode = np.full((steps, 1), -1)
    valid = np.zeros((steps, 1), bool)
    barcode[[0, 1, 25], 0] = 0
    valid[[0, 1, 25], 0] = True
    camera = diagnostics.camera_detection_rate(pose, landmarks, barcode, valid,
                                               miss_range=4.0, miss_bearing=0.5, miss_run=5)
    assert camera.rate == pytest.approx(3 / 40)
    assert camera.after_detection == pytest.approx(1 / 3)
    assert camera.after_miss == pytest.approx(1 / 33)
    assert camera.runs == 5 and camera.long_runs == 4
    longer = diagnostics.camera_detection_rate(pose, landmarks, barcode, valid, 4.0, 0.5,
                                               miss_run=9)
    assert longer.long_runs == 2  # only the two runs of 10
    # 3 m is outside a 2.9 m region and on the edge of a 3 m one (counted, as the filter's
    # ``<=``): no pair / the same pairs
    assert np.isnan(diagnostics.camera_detection_rate(pose, landmarks, barcode, valid, 2.9,
                                                      0.5, 5).rate)
    assert diagnostics.camera_detection_rate(pose, landmarks, barcode, valid, 3.0, 0.5,
                                             5) == camera


def test_camera_detection_rate_without_consecutive_pairs():
    """One in-region step only: the shares after a detection / miss have no pair (nan)."""
    pose = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, np.pi]])
    camera = diagnostics.camera_detection_rate(pose, np.array([[3.0, 0.0]]),
                                               np.array([[0], [-1]]), np.array([[True], [False]]),
                                               miss_range=4.0, miss_bearing=0.5, miss_run=5)
    assert camera.rate == 1.0 and camera.runs == 0 and camera.long_runs == 0
    assert np.isnan(camera.after_detection) and np.isnan(camera.after_miss)


@pytest.mark.parametrize("name", list(diagnostics.VARIANTS))
def test_each_variant_gives_valid_params(name):
    params = default_params()
    changed = params._replace(**{field: jnp.asarray(value, jnp.float32) for field, value
                                 in diagnostics.VARIANTS[name](params).items()})
    check_params(changed)
    differ = {field for field, a, b in zip(params._fields, changed, params)
              if not np.array_equal(np.asarray(a), np.asarray(b))}
    assert differ == {"calibrated": set(),
                      "no_delete": {"existence_max", "existence_delete"},
                      "pd_0.4": {"detection_probability"},
                      "pd_0.2": {"detection_probability"},
                      "range_x3_no_delete": {"range_noise", "existence_max",
                                             "existence_delete"}}[name]


def test_filter_variant_smooths_each_key_as_the_pipeline_does():
    """With ``smooth``, ``filter_variant`` also smooths each key's best history:
    the same ratio as ``pipeline.filter_log(..., smooth=True)`` gives for that key with the
    same settings (one code path, ``pipeline.offline_path``); without it, no smoothing."""
    import jax

    from jaxslam import pipeline
    from jaxslam.types import FilterConfig
    from test_pipeline import _log  # tests/ is on sys.path (no tests/__init__.py)

    log = _log(30)
    config = FilterConfig(num_particles=8, max_landmarks=16)
    params = default_params(range_std_floor=0.05, bearing_std_floor=0.01, max_range=6.0)
    truth = np.asarray(log.truth_pose)
    runs = diagnostics.filter_variant(params, pipeline.log_inputs(log, config), truth, 1.0,
                                      (3, 4), smooth=True)
    assert len(runs.ratios) == len(runs.smoothed) == 2
    for key, smoothed_ratio in zip((3, 4), runs.smoothed):
        run = pipeline.filter_log(log, config, params, jax.random.PRNGKey(key),
                                  calibrate=False, smooth=True)
        # The same run and the same smoother: equal up to float64 rounding.
        np.testing.assert_allclose(smoothed_ratio, 1.0 / run.metrics["smoothed_ate_rmse"],
                                   rtol=1e-9)
    # Exact odometry and observations: both paths stay within centimetres of the truth.
    assert min(runs.ratios) > 10 and min(runs.smoothed) > 10
    plain = diagnostics.filter_variant(params, pipeline.log_inputs(log, config), truth, 1.0,
                                       (3,))
    assert plain.smoothed == () and plain.ratios[0] == runs.ratios[0]
