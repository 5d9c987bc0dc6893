"""The detection fit's trials limited to each landmark's sighting span
(``detection_fit.sighting_spans``, ``detections(span=...)``) and the first iteration's
existence settings (``self_calibration.starting_params``)."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam import detection_fit
from jaxslam import self_calibration as sc
from jaxslam.detection_fit import detections, sighting_spans
from jaxslam.types import default_params

PARAMS = default_params(range_noise=(0.01, 0.05), bearing_noise=(0.001, 0.01))


def _reference_block(pose, step, points, span, z, valid, params, max_range, half_fov):
    """NumPy float64 transcription of ``_detection_block`` (loops, no vectorisation)."""
    count, num_points = len(pose), len(points)
    distance = np.zeros((count, num_points))
    in_view = np.zeros((count, num_points), bool)
    detected = np.zeros((count, num_points), bool)
    c_range, c_bearing = np.asarray(params.range_noise, np.float64), np.asarray(
        params.bearing_noise, np.float64)
    for c in range(count):
        for j in range(num_points):
            dx, dy = points[j] - pose[c, :2]
            d = np.hypot(dx, dy)
            b = (np.arctan2(dy, dx) - pose[c, 2] + np.pi) % (2 * np.pi) - np.pi
            distance[c, j] = d
            in_view[c, j] = (span[j, 0] < step[c] <= span[j, 1]
                             and float(params.min_range) <= d <= max_range
                             and abs(b) <= half_fov)
            s_r = max(c_range[0] * d + c_range[1], float(params.range_std_floor))
            s_b = max(c_bearing[0] * d + c_bearing[1], float(params.bearing_std_floor))
            d_b = (z[c, :, 1] - b + np.pi) % (2 * np.pi) - np.pi
            close = ((z[c, :, 0] - d) / s_r) ** 2 + (d_b / s_b) ** 2 <= 9.0
            detected[c, j] = bool(np.any(close & valid[c]))
    return distance, in_view, detected


def _problem(seed=3, steps=12, rows=3, trees=5):
    rng = np.random.default_rng(seed)
    pose = np.concatenate([rng.uniform(-4, 4, (steps, 2)), rng.uniform(-3, 3, (steps, 1))], 1)
    points = rng.uniform(-6, 6, (trees, 2))
    z = np.stack([rng.uniform(0.5, 9, (steps, rows)), rng.uniform(-1, 1, (steps, rows))], -1)
    # one row of each step observes a tree within noise, so that detections occur
    seen = rng.integers(0, trees, steps)
    dx, dy = (points[seen] - pose[:, :2]).T
    z[:, 0, 0] = np.hypot(dx, dy) + rng.normal(0, 0.03, steps)
    z[:, 0, 1] = (np.arctan2(dy, dx) - pose[:, 2] + np.pi) % (2 * np.pi) - np.pi
    valid = rng.random((steps, rows)) < 0.8
    valid[:, 0] = True
    span = np.stack([rng.integers(-1, steps // 2, trees), rng.integers(steps // 2, steps, trees)],
                    1)
    return pose, np.arange(steps), points, span, z, valid


@pytest.mark.parametrize("jit", [True, False])
def test_detection_block_against_a_float64_loop(jit):
    """Distances to 1e-12 m (float64 rounding); in-view and detected flags exactly: the
    problem keeps every flag's inequality away from its threshold by more than rounding
    (checked: a stray flag would show as a mismatch)."""
    pose, step, points, span, z, valid = _problem()
    raw = detection_fit._detection_block.__wrapped__
    args = (pose, step, points, np.ones(len(points), bool), span, z, valid, PARAMS, 7.0, 1.1)
    with jax.enable_x64(True):
        arrays = jax.tree.map(jnp.asarray, args[:7])
        call = jax.jit(raw) if jit else raw
        if jit:
            got = call(*arrays, jax.tree.map(lambda v: jnp.asarray(v, jnp.float64), PARAMS),
                       7.0, 1.1)
        else:
            with jax.disable_jit():
                got = call(*arrays, jax.tree.map(lambda v: jnp.asarray(v, jnp.float64),
                                                 PARAMS), 7.0, 1.1)
    want = _reference_block(pose, step, points, span, z, valid, PARAMS, 7.0, 1.1)
    np.testing.assert_allclose(np.asarray(got[0]), want[0], atol=1e-12)
    np.testing.assert_array_equal(np.asarray(got[1]), want[1])
    np.testing.assert_array_equal(np.asarray(got[2]), want[2])
    assert 0 < want[1].sum() < want[1].size and 0 < (want[1] & want[2]).sum()


def test_detection_block_under_vmap():
    """Two blocks stacked on a leading axis give each block's own result (exact flags,
    distances to 1e-12 m)."""
    blocks = [_problem(seed) for seed in (3, 4)]
    raw = detection_fit._detection_block.__wrapped__
    params = jax.tree.map(lambda v: jnp.asarray(v, jnp.float64), PARAMS)
    with jax.enable_x64(True):
        stacked = [jnp.stack([jnp.asarray(b[i]) for b in blocks]) for i in range(6)]
        pose, step, points, span, z, valid = stacked
        real = jnp.ones(points.shape[:2], bool)
        got = jax.vmap(raw, in_axes=(0, 0, 0, 0, 0, 0, 0, None, None, None))(
            pose, step, points, real, span, z, valid, params, 7.0, 1.1)
    for b, block in enumerate(blocks):
        want = _reference_block(*block, PARAMS, 7.0, 1.1)
        np.testing.assert_allclose(np.asarray(got[0][b]), want[0], atol=1e-12)
        np.testing.assert_array_equal(np.asarray(got[1][b]), want[1])
        np.testing.assert_array_equal(np.asarray(got[2][b]), want[2])


@pytest.mark.parametrize("chunk", [1, 5, None])
def test_detections_with_spans_against_the_loop(chunk):
    """``detections(span=...)`` keeps exactly the reference's in-span, in-view pairs, in
    step-major order, whatever the block size (padding must not leak trials)."""
    pose, step, points, span, z, valid = _problem(seed=9, steps=17)
    ranges, hits = detections(pose, points, z, valid, PARAMS, 7.0, 1.1, chunk=chunk, span=span)
    distance, in_view, detected = _reference_block(pose, step, points, span, z, valid, PARAMS,
                                                   7.0, 1.1)
    t, j = np.nonzero(in_view)
    np.testing.assert_allclose(ranges, distance[t, j], atol=1e-12)
    np.testing.assert_array_equal(hits, detected[t, j])
    # span=None is every step: a superset of the spanned trials
    all_ranges, _ = detections(pose, points, z, valid, PARAMS, 7.0, 1.1, chunk=chunk)
    assert len(all_ranges) > len(ranges) > 0


def test_detections_span_edges():
    """A landmark seen once (first == last) or never ((-1, -1)) has no trial; a span of the
    whole log ((-1, T - 1)) equals span=None."""
    pose, step, points, _, z, valid = _problem(seed=11)
    steps = len(pose)
    once = np.tile([[4, 4]], (len(points), 1))
    never = np.tile([[-1, -1]], (len(points), 1))
    for span in (once, never):
        ranges, hits = detections(pose, points, z, valid, PARAMS, 7.0, 1.1, span=span)
        assert ranges.shape == (0,) and hits.shape == (0,)
    whole = np.tile([[-1, steps - 1]], (len(points), 1))
    a = detections(pose, points, z, valid, PARAMS, 7.0, 1.1, span=whole)
    b = detections(pose, points, z, valid, PARAMS, 7.0, 1.1)
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])


def test_sighting_spans_against_a_loop():
    rng = np.random.default_rng(2)
    obs_landmark = rng.integers(0, 6, 40)
    obs_landmark[obs_landmark == 4] = 5  # landmark 4 never observed
    obs_step = np.sort(rng.integers(0, 100, 40))
    got = sighting_spans(obs_step, obs_landmark, 7)  # landmark 6 never observed either
    for j in range(7):
        steps = obs_step[obs_landmark == j]
        want = (steps.min(), steps.max()) if steps.size else (-1, -1)
        assert tuple(got[j]) == want, j
    assert got.dtype == np.int64 and got.shape == (7, 2)
    assert sighting_spans(np.zeros(0, int), np.zeros(0, int), 2).tolist() == [[-1, -1]] * 2


def test_a_detector_that_misses_is_not_hidden_by_split_landmarks():
    """Spans against the whole log: a tree seen at steps 0-49 (detected every other step)
    and, after the path drifted, predicted at a place nobody observes during steps 50-199.
    Whole-log trials count the drift as 150 misses (rate 25/175 = 0.14); trials within the
    sighting span give the detector's own rate, 24 hits in 49 steps (0.49)."""
    steps = 200
    pose = np.zeros((steps, 3))
    point = np.array([[3.0, 0.0]])
    z = np.zeros((steps, 1, 2))
    z[:, 0, 0] = 3.0
    valid = np.zeros((steps, 1), bool)
    valid[0:50:2] = True  # 25 sightings, steps 0, 2, ..., 48
    ranges, hits = detections(pose, point, z, valid, PARAMS, 8.0, 1.0)
    assert len(ranges) == steps and hits.sum() == 25
    span = sighting_spans(np.arange(0, 50, 2), np.zeros(25, int), 1)
    ranges, hits = detections(pose, point, z, valid, PARAMS, 8.0, 1.0, span=span)
    assert len(ranges) == 48 and hits.sum() == 24  # steps 1..48: 24 even ones are hits


def test_starting_params_delete_landmarks_slowly():
    """The first run's existence rule deletes a newborn landmark only after dozens of
    misses: (existence_init - existence_delete) / |log((1 - p_d) / (1 - p_f))| >= 40."""
    params = sc.starting_params()
    p_d = float(params.detection_probability)
    p_f = float(params.false_alarm_probability)
    assert p_d == pytest.approx(sc.START_DETECTION)
    misses = (float(params.existence_init) - float(params.existence_delete)) / abs(
        np.log((1 - p_d) / (1 - p_f)))
    assert misses >= 40
    # a given value still wins
    assert float(sc.starting_params(detection_probability=0.7).detection_probability) == \
        pytest.approx(0.7)
