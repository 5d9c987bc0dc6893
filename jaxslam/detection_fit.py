"""The self-calibration's sensor M-step: range, field of view, detection, false alarms, gate.

From one EM iteration's smoothed solution (``calibration_residuals.Residuals``) and the log:

    max_range       the 99.9 % quantile of the observed ranges, plus 2 %;
    miss_bearing    the half field of view: the 99.9 % quantile of |bearing|, plus 2 %
                    (pi, all round, above about 170 degrees);
    miss_range and detection_probability
                    how often a smoothed landmark predicted in view is observed within 3 std
                    (``detections``), binned by predicted range: misses beyond the last bin
                    still detected half as often as the best one are no evidence. The
                    trials of a landmark are the steps after its first sighting up to its
                    last (``sighting_spans``): outside that span the smoothed path and the
                    landmark are not tied by any observation, so a drifted path predicts the
                    landmark where the detector never saw it, and a map with the trees split
                    into many landmarks (the filter deleted and restarted them) would count
                    each split-off landmark's whole log as misses. With the whole log as
                    trials, MRCLAM robot 1 gave p_d 0.05-0.07 against a detector that reads
                    a barcode in view about one step in three; the low p_d keeps every
                    false landmark alive (a miss then costs log(0.95) in log-odds);
    false_alarm_probability
                    the share of observations no other observation confirms
                    (``single_share``): a clutter detection starts a landmark never seen again;
    association_gate
                    the 99 % quantile of the squared whitened innovations at the filter's own
                    pose, so the gate covers the pose error a FastSLAM 1.0 innovation leaves
                    out (Montemerlo et al., "FastSLAM: A Factored Solution to the
                    Simultaneous Localization and Mapping Problem", AAAI 2002); when the
                    trunk radius joins the distance (``radius_noise`` > 0), that gate moved to
                    three degrees of freedom at the same tail probability
                    (``gate_with_radius``).

The predicted measurements are ``geometry.range_bearing`` and their std ``ekf.measurement_std``,
evaluated in float64 on the host (``host.in_float64``) on blocks of fixed
shape, so that they compile once per landmark count's power of two.

Shapes: T steps, K observations per step, L smoothed landmarks, n (step, landmark) pairs.
"""
from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import scipy.stats

from jaxslam.calibration_residuals import Residuals
from jaxslam.host import float64_on_host
from jaxslam.ekf import measurement_std
from jaxslam.geometry import range_bearing, wrap_angle
from jaxslam.noise_fit import MIN_OBSERVATIONS, MIN_SIGHTINGS
from jaxslam.types import Params

CHI2_2DOF_999 = 13.8155  # chi-square quantile, 2 degrees of freedom, 99.9 %
# The estimated gate is clipped to [chi-square 99.9 %, the library's default gate 25]: above
# 25 the particles' own pose errors are better handled by the proposal than by the gate.
GATE_LIMITS = (CHI2_2DOF_999, 25.0)
DETECTION_RADIUS_SQ = 9.0  # a landmark is detected by an observation within 3 std
BLOCK_ELEMENTS = 1 << 22  # (steps, landmarks, rows) evaluated at once by ``detections``


@float64_on_host
def _detection_block(pose, step, points, real, span, z, valid, params: Params, max_range,
                     half_fov):
    """Predicted range (C, L), in view (C, L) and detected (C, L) of every (step, landmark).

    pose (C, 3) at the log steps ``step`` (C,) int; points (L, 2) with ``real`` (L,) marking
    the landmarks that exist and ``span`` (L, 2) int: a (step, landmark) pair is a trial only
    when span[l, 0] < step <= span[l, 1]; z (C, K, 2); valid (C, K).
    """
    predicted = range_bearing(pose[:, None], points[None])  # (C, L, 2)
    distance, bearing = predicted[..., 0], predicted[..., 1]
    in_span = (step[:, None] > span[None, :, 0]) & (step[:, None] <= span[None, :, 1])
    in_view = (real[None] & in_span & (distance >= params.min_range) & (distance <= max_range)
               & (jnp.abs(bearing) <= half_fov))
    sigma_range, sigma_bearing = measurement_std(distance, params)  # (C, L)
    d_range = (z[:, None, :, 0] - distance[..., None]) / sigma_range[..., None]  # (C, L, K)
    d_bearing = wrap_angle(z[:, None, :, 1] - bearing[..., None]) / sigma_bearing[..., None]
    close = (d_range**2 + d_bearing**2 <= DETECTION_RADIUS_SQ) & valid[:, None]
    return distance, in_view, jnp.any(close, axis=-1)


def detections(path, points, z, valid, params: Params, max_range: float, half_fov: float,
               chunk: int | None = None, span=None):
    """Predicted ranges (n,) of every (step, landmark) pair in view, and whether detected (n,).

    In view: min_range <= range <= max_range and |bearing| <= half_fov from the smoothed
    pose. Detected: some valid observation of that step lies within 3 std (squared whitened
    distance <= 9, about 99 % for 2 degrees of freedom) of the predicted measurement. The
    test uses positions, not the filter's landmark identities: a landmark the filter deleted
    and started again is still one tree here, so its misses count against the detector.

    Args: path (T, 3); points (L, 2); z (T, K, 2); valid (T, K). chunk: steps a block
      (default: ``BLOCK_ELEMENTS`` elements of (steps, landmarks, rows)). span: None (every
      step is a trial), or (L, 2) int first and last step of each landmark's sightings
      (``sighting_spans``): only steps t with span[l, 0] < t <= span[l, 1] are trials.
    """
    path, z = np.asarray(path, np.float64), np.asarray(z, np.float64)
    valid = np.asarray(valid, bool)
    steps, rows = valid.shape
    count_points = len(points)
    # Padded to a power of two so that a changing landmark count rarely recompiles.
    padded = max(64, 1 << int(np.ceil(np.log2(max(count_points, 1)))))
    real = np.arange(padded) < count_points
    points = np.concatenate([points, np.zeros((padded - count_points, 2))])
    span = (np.tile([-1, steps], (count_points, 1)) if span is None
            else np.asarray(span, np.int64).reshape(count_points, 2))
    span = np.concatenate([span, np.zeros((padded - count_points, 2), np.int64)])
    chunk = min(chunk or max(1, BLOCK_ELEMENTS // (padded * max(rows, 1))), steps)
    ranges, hits = [], []
    for begin in range(0, steps, chunk):
        count = min(chunk, steps - begin)
        block = slice(begin, begin + count)
        pad = ((0, chunk - count),)
        distance, in_view, detected = _detection_block(
            np.pad(path[block], pad + ((0, 0),)), np.arange(begin, begin + chunk), points,
            real, span, np.pad(z[block], pad + ((0, 0), (0, 0))),
            np.pad(valid[block], pad + ((0, 0),)), params, max_range, half_fov)
        step, landmark = np.nonzero(in_view[:count])
        ranges.append(distance[step, landmark])
        hits.append(detected[step, landmark])
    return np.concatenate(ranges), np.concatenate(hits)


def sighting_spans(obs_step, obs_landmark, num_landmarks: int):
    """(L, 2) int first and last step at which each landmark was observed; (-1, -1) for a
    landmark never observed. obs_step (S,), obs_landmark (S,) of the associated samples
    (``calibration_residuals.Residuals``)."""
    obs_step = np.asarray(obs_step, np.int64)
    obs_landmark = np.asarray(obs_landmark, np.int64)
    first = np.full(num_landmarks, np.iinfo(np.int64).max)
    last = np.full(num_landmarks, -1, np.int64)
    np.minimum.at(first, obs_landmark, obs_step)
    np.maximum.at(last, obs_landmark, obs_step)
    return np.stack([np.where(last >= 0, first, -1), last], 1)


def single_share(ids):
    """Share of associated observations whose landmark no other observation confirms.

    The false-alarm estimate: a clutter detection starts a landmark that is never seen
    again. ids: (T, K) landmark identities (-1: none). None when nothing is associated.
    """
    used = ids >= 0
    if not used.any():
        return None
    counts = np.bincount(ids[used])
    return float(np.mean(counts[ids[used]] == 1))


def _detection_settings(predicted, detected, max_range: float) -> dict:
    """miss_range and detection_probability from predicted ranges (n,) and detections (n,)."""
    edges = np.linspace(0.0, max_range, 11)
    bins = np.clip(np.digitize(predicted, edges) - 1, 0, 9)
    trials = np.bincount(bins, minlength=10)
    hits = np.bincount(bins[detected], minlength=10)
    rate = np.where(trials > 0, hits / np.maximum(trials, 1), np.nan)
    peak = np.nanmax(rate) if np.any(trials > 0) else np.nan
    if not (np.isfinite(peak) and peak > 0):
        return {}
    # miss_range: the far edge of the last bin (from the sensor out) whose detection
    # rate is still half the best bin's; beyond it a missed landmark is no evidence.
    good = np.nonzero(np.nan_to_num(rate) >= 0.5 * peak)[0]
    miss_range = float(edges[good.max() + 1])
    near = predicted <= miss_range
    return {"miss_range": miss_range, "detection_probability": float(np.clip(
        np.sum(detected & near) / max(near.sum(), 1), 0.05, 0.99))}


def _association_gate(res: Residuals, used: np.ndarray) -> dict:
    """association_gate from the innovations at the filter's pose of the ``used`` samples."""
    std = res.observation_std[used]
    nis = np.sum((res.filter_error[used] / std) ** 2, axis=1)
    # Inliers of the smoothed solution only: a wrong association must not widen the gate.
    inlier = np.sum((res.observation_error[used] / std) ** 2, axis=1) <= DETECTION_RADIUS_SQ
    if inlier.sum() < MIN_OBSERVATIONS:
        return {}
    return {"association_gate": float(np.clip(np.quantile(nis[inlier], 0.99), *GATE_LIMITS))}


def gate_with_radius(gate):
    """The association gate for distances that carry the trunk radius too.

    With ``Params.radius_noise`` > 0 the filter adds the radius term d_r2 (one degree of
    freedom, ``ekf.radius_distance_sq``) to the position's squared distance (two), so an
    exactly modelled correct pair's distance is chi-square with 3 degrees of freedom instead
    of 2. The 3-dof gate with the 2-dof gate's tail probability solves P(chi2_3 > g3) =
    P(chi2_2 > g) = exp(-g / 2): g3 = chi2_3.isf(exp(-g / 2)) (13.82 -> 16.27, 25 -> 27.95).
    A convention, not an exact equivalence: the calibrated 2-dof gate is an empirical
    quantile of innovations widened by the pose error and clipped (``_association_gate``),
    and the radius, which the pose error does not widen, gets the chi-square share on top
    (about 2.9 at 25, 1.7 radius stds at the position's gate). ``gate``: a scalar or array
    of 2-dof gates in (0, 1400] (beyond, exp(-g / 2) underflows); returns the same shape,
    float64.
    """
    gate = np.asarray(gate, np.float64)
    if not np.all((gate > 0) & (gate <= 1400.0)):
        raise ValueError(f"gate_with_radius needs chi-square gates in (0, 1400]; got {gate}")
    return scipy.stats.chi2.isf(np.exp(-0.5 * gate), 3)


def sensor_update(res: Residuals, z, valid, used: np.ndarray, smoothed_path, landmark,
                  params: Params) -> dict:
    """max_range, miss_bearing, miss_range, detection probability and gate (module docstring).

    z (T, K, 2), valid (T, K): the log; used (S,): the samples of landmarks seen often
    enough; smoothed_path (T, 3), landmark (L, 2): the smoothed solution.
    """
    z_valid = np.asarray(z, np.float64)[np.asarray(valid)]
    out = {}
    if len(z_valid):
        max_range = float(np.quantile(z_valid[:, 0], 0.999) * 1.02)
        out["max_range"] = max_range
        # The field of view: a sensor that never reports a bearing past +-b does not miss
        # the landmarks out there. Below ~170 degrees of half-width, else all round.
        half_fov = float(np.quantile(np.abs(z_valid[:, 1]), 0.999) * 1.02)
        out["miss_bearing"] = half_fov if half_fov < 0.95 * np.pi else float(np.pi)
        confirmed = np.nonzero(res.sightings >= MIN_SIGHTINGS)[0]
        if confirmed.size:
            span = sighting_spans(res.obs_step, res.obs_landmark, len(res.sightings))
            predicted, detected = detections(smoothed_path, landmark[confirmed], z, valid,
                                             params, max_range, out["miss_bearing"],
                                             span=span[confirmed])
            out.update(_detection_settings(predicted, detected, max_range))
    if used.any():
        out.update(_association_gate(res, used))
    return out
