"""Self-calibration: the filter's noise and sensor settings estimated from a log alone.

A user with a robot log has no ground truth to tune against. ``calibrate_params`` finds the
settings from the odometry and the observations only, by an expectation-maximisation of the
kind Probabilistic Robotics (Thrun, Burgard and Fox, sections 6.3 and 11) and GraphSLAM noise
estimation use, with the particle filter as the E-step's data associator:

    repeat (iteration i = 0, 1, ...):
      1. filter the log with Params_i (``run_filter``, one fixed key: common random numbers,
         so two iterations differ only by their settings), record the lineage;
      2. take the best particle's history: its data association j(t, k) (``trace_lineage``);
      3. smooth with that association fixed (``smoothing.smooth_path``): the maximum
         a-posteriori path x*_{0:T-1} and map m* of the log, Huber-robust;
      4. M-step on the residuals of that solution:
         * shape: fit Eq. (1) of Geiser et al., "Practical Implementation of FastSLAM for
           Forestry Robot" (ICAROB 2023), to the move residuals (x*_{t-1} (-) x*_t against the
           measured move) and Table 2's std = c_d range + c_0 to the observation residuals
           h(x*_t, m*_j) - z_tk, with the robust grouped fit of ``calibrate.fit_noise``
           (its NumPy twin ``_host_fit_noise``: see Cost);
         * scale: residuals of a least-squares solution are smaller than the noise (each
           group's residual sum of squares has r_g = n_g - tr(J_g H^-1 J_g^T) degrees of
           freedom, not n_g). The smoother's variance components (Helmert/Forstner,
           ``smooth_path(calibrate_rounds=...)``) give the unbiased factor of each noise group
           (heading, translation, range, bearing); the fitted shape is rescaled so that its
           mean variance over the group's samples equals that estimate. Without it, EM on MAP
           residuals shrinks the noise every iteration;
         * bursts: a two-scale mixture fitted to the whitened move residuals by EM
           (``fit_bursts``) sets ``motion_outlier_probability`` and ``motion_outlier_scale``
           when it beats one Gaussian by BIC (wheel slip, commanded-velocity odometry);
           without that evidence the burst proposal keeps its default tail
           (``defensive_bursts``);
         * tails: otherwise the std is widened, where needed, until 95 % of the group's residuals
           lie within its 95 % interval (``_tail_factor``; 1 for Gaussian errors). Real
           sensors are heavy-tailed, and a std fitted to the core alone makes the filter
           split tail observations into new landmarks, which leaves them out of the next fit:
           the estimate then shrinks from iteration to iteration;
         * sensor: ``max_range`` and ``miss_bearing`` (the field of view) from the observed
           ranges and bearings, ``miss_range`` and
           ``detection_probability`` from how often a smoothed landmark predicted in view has
           an observation within 3 std (``_detections``), ``false_alarm_probability`` from the share of observations no other
           observation confirms, ``association_gate`` from the innovations at the filter's
           own pose (so the gate covers the pose error a FastSLAM 1.0 innovation leaves out);
      5. monitor EM by the particle filter's own log marginal likelihood estimate (the sum
         of ``Trace.log_evidence``); when the iterations do not converge, return the
         settings whose run scored best (an iteration that broke the association scores
         low);
      6. limit each noise group's move to a factor ``TRUST_FACTOR`` an iteration
         (``_trust_region``), and stop when every group's typical std moved by less than
         ``tol`` (relative).

Why this and not a likelihood search over a population of Params: the filter's marginal
likelihood is a noisy, flat function of 9 motion and 4 sensor coefficients at the particle
counts users run, while the smoother's residuals measure each noise group directly, with
degrees of freedom in the thousands on a real log, and cost one filter run per iteration.

Uncertainty: a group's std estimated from r_g degrees of freedom has a relative standard
error of about 1 / sqrt(2 r_g) (chi-square); ``CalibrationInfo.relative_std`` reports it with
r_g taken as the group's sample count (an upper bound on r_g, so the interval is a lower bound).

Cost: one filter run per iteration, plus the smoother (0.15-0.35 of a run per iteration on
MRCLAM robot 1 and on the simulated loop of ``benchmarks/calibration.py``), plus a few per cent
for the rest. Between the filter runs everything runs on the host in NumPy/SciPy: the history
of the best particle (``_best_history``), the residual geometry and the noise fits are NumPy
twins of ``lineage.trace_lineage``, ``geometry``/``motion`` and ``calibrate.fit_noise``
(tested against them). The JAX versions compiled anew in every iteration, because the number
of associated observations changes with the association: 2-4 s a compile, which made a
calibration cost 32 filter runs on a 250-step log instead of 3.

Shapes: T steps, K observations per step, S associated observations, L smoothed landmarks.
"""
from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import numpy as np
import scipy.optimize

from jaxslam import calibrate, lineage, smoothing
from jaxslam.datasets.log_format import wrap_angle_np
from jaxslam.filter import run_filter
from jaxslam.motion import control_to_odometry
from jaxslam.types import FilterConfig, Observations, Params, default_params

CHI2_2DOF_999 = 13.8155  # chi-square quantile, 2 degrees of freedom, 99.9 %
# The estimated gate is clipped to [chi-square 99.9 %, the library's default gate 25]: above
# 25 the particles' own pose errors are better handled by the proposal than by the gate.
GATE_LIMITS = (CHI2_2DOF_999, 25.0)
MIN_MOVES = 30  # fewer moves than this: the motion noise is not fitted
MIN_OBSERVATIONS = 20  # fewer associated observations (in landmarks seen >= 3 times): none
MIN_SIGHTINGS = 3  # a landmark's observations enter the fits when it was seen this often
STD_FLOOR = 1e-5  # lower bound of every fitted constant term (keeps covariances invertible)
BURST_LIMITS = (0.25, 10.0)  # most burst probability, most burst scale (``fit_bursts``)
TRUST_FACTOR = 3.0  # most factor a noise group's typical std may move in one iteration
TAIL_QUANTILE = 0.95  # the share of errors the fitted std must cover (``_tail_factor``)
CHI2_1DOF = {0.95: 3.8415, 0.99: 6.6349}  # chi-square quantiles, 1 degree of freedom


class CalibrationInfo(NamedTuple):
    """What ``calibrate_params`` did.

    Attributes:
      iterations: EM iterations run.
      objective: (iterations,) the filter's estimate of the log marginal likelihood of the
        log with each iteration's Params (``Trace.log_evidence`` summed over steps).
      smoother_cost: (iterations,) the smoother's final robust cost per residual row.
      typical_std: (iterations + 1, 4) typical std of the four noise groups (heading [rad],
        translation [m], range [m], bearing [rad]: the mean over the log's samples) before
        each iteration and after the last.
      values: the final settings, a dict of floats or tuples (the fitted ``Params`` fields).
      relative_std: dict group -> relative standard error of its std (module docstring).
      samples: dict group -> number of samples the fit used.
      converged: whether the typical stds stopped moving (``tol``).
      verdict: one line in plain words.
      warnings: tuple of plain-word warnings (data too sparse, a group kept at its start).
    """

    iterations: int
    objective: np.ndarray
    smoother_cost: np.ndarray
    typical_std: np.ndarray
    values: dict
    relative_std: dict
    samples: dict
    converged: bool
    verdict: str
    warnings: tuple


class _Residuals(NamedTuple):
    """Samples of one smoothed solution (host NumPy, float64)."""

    true_moves: np.ndarray  # (T, 3) smoothed moves (rot1, trans, rot2)
    measured_moves: np.ndarray  # (T, 3)
    predicted_z: np.ndarray  # (S, 2) h(x*_t, m*_j)
    measured_z: np.ndarray  # (S, 2)
    filter_z: np.ndarray  # (S, 2) h(x_filter_t, m*_j), the filter's own pose
    obs_step: np.ndarray  # (S,) step of each sample
    obs_landmark: np.ndarray  # (S,) smoothed landmark index
    sightings: np.ndarray  # (L,) observations of each landmark


def starting_params(config: FilterConfig | None = None, dtype=jnp.float32, **overrides) -> Params:
    """The first iteration's settings when the user gives none: wide, so data associate.

    Seed Table 1 motion noise doubled, and a sensor noise floor of 10 cm and 0.02 rad (a
    2-20x wider sensor than Table 2): too tight a start makes every observation a new
    landmark and leaves nothing to calibrate on; too wide a start only costs an iteration.
    """
    base = default_params(config, dtype=dtype)
    values = dict(rot1_noise=2 * np.asarray(base.rot1_noise),
                  trans_noise=2 * np.asarray(base.trans_noise),
                  rot2_noise=2 * np.asarray(base.rot2_noise),
                  range_noise=(0.005, 0.0), bearing_noise=(0.0, 0.0),
                  range_std_floor=0.1, bearing_std_floor=0.02)
    values.update(overrides)
    return default_params(config, dtype=dtype, **values)


def _typical_stds(params: Params, odometry, z_range) -> np.ndarray:
    """(4,) mean std over the log of heading, translation, range, bearing (``CalibrationInfo``)."""
    move_std = _odometry_std(odometry, params)
    heading = np.sqrt(np.mean(move_std[:, 0] ** 2 + move_std[:, 2] ** 2))
    translation = np.sqrt(np.mean(move_std[:, 1] ** 2))
    obs_std = smoothing._observation_std(np.asarray(z_range, np.float64), params)
    return np.array([heading, translation, *np.sqrt(np.mean(obs_std**2, axis=0))])


def _residuals(start_pose, smoothed: smoothing.Smoothed, filter_path, odometry, z,
               min_translation: float) -> _Residuals:
    poses = np.concatenate([np.asarray(start_pose, np.float64)[None], smoothed.path])
    true_moves = _odometry_from_poses(poses[:-1], poses[1:], min_translation)
    ids = np.asarray(smoothed.landmark_of_obs)
    step, row = np.nonzero(ids >= 0)
    landmark = ids[step, row]
    point = smoothed.landmark[landmark]
    predicted = _range_bearing(smoothed.path[step], point)
    at_filter = _range_bearing(np.asarray(filter_path, np.float64)[step], point)
    sightings = np.bincount(landmark, minlength=len(smoothed.landmark))
    return _Residuals(true_moves, np.asarray(odometry, np.float64), predicted,
                      np.asarray(z, np.float64)[step, row], at_filter, step, landmark,
                      sightings)


def _rescale(coefficients, features, target_variance):
    """Coefficients scaled so that mean((features . c)^2) equals ``target_variance``."""
    fitted = features @ coefficients
    mean_variance = float(np.mean(fitted**2))
    if not mean_variance > 0.0:
        return None
    return coefficients * np.sqrt(target_variance / mean_variance)


def _tail_factor(errors, std, quantile: float = TAIL_QUANTILE) -> float:
    """max(1, q-quantile of (e / sigma)^2 over the chi-square-1 q-quantile), a variance factor.

    For Gaussian errors it is 1 up to sampling noise. For heavy-tailed ones (a camera's
    ranges, commanded-velocity odometry) it widens the std until the q share of the errors
    falls within the filter's q-interval: a std fitted to the core alone makes the filter
    split every tail observation into a new landmark, whose residual then leaves the fit,
    and the next iteration's std is tighter still.
    """
    ratio = (np.asarray(errors) / np.maximum(np.asarray(std), STD_FLOOR)) ** 2
    if ratio.size == 0:
        return 1.0
    return max(1.0, float(np.quantile(ratio, quantile)) / CHI2_1DOF[quantile])


def defensive_bursts(config: FilterConfig) -> tuple[float, float]:
    """(eps, kappa) kept when the log shows no bursts (``fit_bursts`` returns None).

    With the two-piece burst proposal (``FilterConfig.burst_proposal``, observation or
    mixture proposal) the default bursts stay: they are not a noise estimate but the tail
    that lets a particle follow a turn far from the measured one (Eq. (1)'s std is evaluated
    at the measured turn), which a log with few such turns cannot show. The motion proposal
    samples bursts blindly, so for it they are off.
    """
    defaults = default_params(config)
    if config.proposal != "motion" and config.burst_proposal:
        return float(defaults.motion_outlier_probability), float(defaults.motion_outlier_scale)
    return 0.0, float(defaults.motion_outlier_scale)


def _motion_update(res: _Residuals, params: Params, scales: smoothing.NoiseScales,
                   no_bursts: tuple[float, float]):
    """(coefficients (3, 3) of rot1, trans, rot2, burst probability, burst scale), or None
    when there are too few moves. Bursts (``fit_bursts``) or, without them, the tail factor
    and ``no_bursts`` (eps, kappa) (``defensive_bursts``)."""
    moving = np.all(np.isfinite(res.true_moves), axis=1)
    if int(moving.sum()) < MIN_MOVES:
        return None
    coefficients = list(_host_motion_fit(res.true_moves, res.measured_moves, moving,
                                         trans_bins=4, rot_bins=4, min_count=5))
    current = _odometry_std(res.measured_moves, params)[moving]
    _, features = _motion_samples(res.measured_moves, res.measured_moves)
    features = features[:, moving]
    # The heading group holds rot1 and rot2 together (its whitened row is their sum), so both
    # rows take one factor: the one that brings their summed variance to the estimate.
    heading_target = scales.heading**2 * np.mean(current[:, 0] ** 2 + current[:, 2] ** 2)
    heading_fit = np.mean((features[0] @ coefficients[0]) ** 2
                          + (features[2] @ coefficients[2]) ** 2)
    trans = _rescale(coefficients[1], features[1],
                     scales.translation**2 * np.mean(current[:, 1] ** 2))
    if not heading_fit > 0.0 or trans is None:
        return None
    factor = np.sqrt(heading_target / heading_fit)
    rows = [coefficients[0] * factor, trans, coefficients[2] * factor]
    errors, _ = _motion_samples(res.true_moves[moving], res.measured_moves[moving])
    std = [features[i] @ rows[i] for i in range(3)]
    heading_error, heading_std = errors[:, 0] + errors[:, 2], np.hypot(std[0], std[2])
    white = np.stack([heading_error / np.maximum(heading_std, STD_FLOOR),
                      errors[:, 1] / np.maximum(std[1], STD_FLOOR)], 1)
    bursts = fit_bursts(white)
    if bursts is not None:
        eps, core, kappa = bursts
        rows = [r * core for r in rows]
    else:
        eps, kappa = no_bursts
        heading_tail = _tail_factor(heading_error, heading_std)
        rows = [rows[0] * np.sqrt(heading_tail),
                rows[1] * np.sqrt(_tail_factor(errors[:, 1], std[1])),
                rows[2] * np.sqrt(heading_tail)]
    # A positive constant keeps every move's covariance invertible (smoothing, proposals).
    rows = np.stack([np.concatenate([r[:2], [max(r[2], STD_FLOOR)]]) for r in rows])
    return rows, eps, kappa


def fit_bursts(white, iterations: int = 50, min_share: float = 0.01, min_ratio: float = 2.0):
    """EM for the burst scale mixture of the whitened move residuals; None when not needed.

    Model: r_t (S, d) ~ (1 - eps) N(0, a^2 I) + eps N(0, b^2 I). E-step: each move's
    responsibility gamma_t of the burst component; M-step: eps = mean(gamma),
    a^2 = sum (1 - gamma) |r|^2 / (d sum (1 - gamma)), b^2 likewise with gamma. The mixture
    is kept when eps >= ``min_share``, b / a >= ``min_ratio`` and it beats one Gaussian by
    BIC (two more parameters: log-likelihood gain > log S). Returns (eps, a, b / a).
    """
    white = np.asarray(white, np.float64)
    count, dim = white.shape
    if count < MIN_MOVES:
        return None
    norm2 = np.sum(white**2, axis=1)

    def log_normal(scale):
        return -dim * np.log(scale) - 0.5 * norm2 / scale**2 - 0.5 * dim * np.log(2 * np.pi)

    single = np.sqrt(np.mean(norm2) / dim)
    eps, a, b = 0.1, 0.7 * single, 3.0 * single
    for _ in range(iterations):
        log_core = np.log1p(-eps) + log_normal(a)
        log_burst = np.log(eps) + log_normal(b)
        gamma = np.exp(log_burst - np.logaddexp(log_core, log_burst))
        eps = float(np.clip(np.mean(gamma), 1e-4, 0.5))
        a = float(np.sqrt(np.sum((1 - gamma) * norm2) / (dim * max(np.sum(1 - gamma), 1e-9))))
        b = float(np.sqrt(np.sum(gamma * norm2) / (dim * max(np.sum(gamma), 1e-9))))
        a, b = max(a, 1e-6), max(b, 1e-6)
    gain = (np.sum(np.logaddexp(np.log1p(-eps) + log_normal(a), np.log(eps) + log_normal(b)))
            - np.sum(log_normal(single)))
    if eps < min_share or b / a < min_ratio or gain <= np.log(count):
        return None
    # A burst wider than BURST_LIMITS' scale is an outlier no particle set of a few hundred
    # can sample, and a burst share above its limit is a mis-fit core: both are clipped.
    return min(eps, BURST_LIMITS[0]), a, min(b / a, BURST_LIMITS[1])


def _observation_update(res: _Residuals, params: Params, scales: smoothing.NoiseScales,
                        used: np.ndarray):
    """New (range_noise, bearing_noise) (2, 2), or None when there are too few samples."""
    if int(used.sum()) < MIN_OBSERVATIONS:
        return None
    fit = _host_observation_fit(res.predicted_z, res.measured_z, used, distance_bins=6,
                                min_count=5)
    z_range = res.measured_z[used, 0]
    current = smoothing._observation_std(z_range, params)
    features = np.stack([z_range, np.ones_like(z_range)], 1)
    new = []
    for group, (component, scale) in enumerate(zip(fit, (scales.range, scales.bearing))):
        row = _rescale(component, features, scale**2 * float(np.mean(current[:, group] ** 2)))
        if row is None:
            return None
        error = res.predicted_z[used, group] - res.measured_z[used, group]
        if group == 1:
            error = wrap_angle_np(error)
        row = row * np.sqrt(_tail_factor(error, features @ row))
        new.append(np.array([row[0], max(row[1], STD_FLOOR)]))
    return np.stack(new)


def _sensor_update(res: _Residuals, z, valid, used: np.ndarray, smoothed_path, landmark,
                   params: Params) -> dict:
    """max_range, miss_range, detection and false-alarm probabilities, gate (docstring)."""
    z_valid = np.asarray(z, np.float64)[np.asarray(valid)]
    max_range = float(np.quantile(z_valid[:, 0], 0.999) * 1.02) if len(z_valid) else None
    out = {}
    if max_range is not None:
        out["max_range"] = max_range
        # The field of view: a sensor that never reports a bearing past +-b does not miss
        # the landmarks out there. Below ~170 degrees of half-width, else all round.
        half_fov = float(np.quantile(np.abs(z_valid[:, 1]), 0.999) * 1.02)
        out["miss_bearing"] = half_fov if half_fov < 0.95 * np.pi else float(np.pi)
    confirmed = np.nonzero(res.sightings >= MIN_SIGHTINGS)[0]
    if confirmed.size and max_range is not None:
        predicted, detected = _detections(smoothed_path, landmark[confirmed], z, valid, params,
                                          max_range, out["miss_bearing"])
        edges = np.linspace(0.0, max_range, 11)
        bins = np.clip(np.digitize(predicted, edges) - 1, 0, 9)
        trials = np.bincount(bins, minlength=10)
        hits = np.bincount(bins[detected], minlength=10)
        rate = np.where(trials > 0, hits / np.maximum(trials, 1), np.nan)
        peak = np.nanmax(rate) if np.any(trials > 0) else np.nan
        if np.isfinite(peak) and peak > 0:
            # miss_range: the far edge of the last bin (from the sensor out) whose detection
            # rate is still half the best bin's; beyond it a missed landmark is no evidence.
            good = np.nonzero(np.nan_to_num(rate) >= 0.5 * peak)[0]
            out["miss_range"] = float(edges[good.max() + 1])
            near = predicted <= out["miss_range"]
            out["detection_probability"] = float(np.clip(
                np.sum(detected & near) / max(near.sum(), 1), 0.05, 0.99))
    if used.any():
        std = smoothing._observation_std(res.measured_z[used, 0], params)
        innovation = res.filter_z[used] - res.measured_z[used]
        innovation[:, 1] = wrap_angle_np(innovation[:, 1])
        nis = np.sum((innovation / std) ** 2, axis=1)
        # Inliers of the smoothed solution only: a wrong association must not widen the gate.
        smooth_err = res.predicted_z[used] - res.measured_z[used]
        smooth_err[:, 1] = wrap_angle_np(smooth_err[:, 1])
        inlier = np.sum((smooth_err / std) ** 2, axis=1) <= 9.0
        if inlier.sum() >= MIN_OBSERVATIONS:
            out["association_gate"] = float(np.clip(np.quantile(nis[inlier], 0.99),
                                                    *GATE_LIMITS))
    return out


def _single_share(ids):
    """Share of associated observations whose landmark no other observation confirms.

    The false-alarm estimate: a clutter detection starts a landmark that is never seen
    again. None when nothing is associated.
    """
    used = ids >= 0
    if not used.any():
        return None
    counts = np.bincount(ids[used])
    return float(np.mean(counts[ids[used]] == 1))


_GROUP_FIELDS = (("rot1_noise", "rot2_noise"), ("trans_noise",),
                 ("range_noise", "range_std_floor"), ("bearing_noise", "bearing_std_floor"))


def _trust_region(old: Params, new: Params, odometry, z_range) -> Params:
    """``new`` with each noise group's coefficients scaled back so that its typical std moves
    by at most ``TRUST_FACTOR`` from ``old``'s in one iteration.

    An iteration on a bad association (a filter that lost the map) can propose an absurd
    noise; the next filter run with it cannot recover. The limit lets real changes through
    in a few iterations (a factor 27 in three) and stops a single jump.
    """
    before = _typical_stds(old, odometry, z_range)
    after = _typical_stds(new, odometry, z_range)
    updates = {}
    for group, fields in enumerate(_GROUP_FIELDS):
        ratio = after[group] / max(before[group], 1e-12)
        limited = float(np.clip(ratio, 1.0 / TRUST_FACTOR, TRUST_FACTOR))
        if ratio > 0 and limited != ratio:
            for name in fields:
                updates[name] = np.asarray(getattr(new, name), np.float64) * (limited / ratio)
    return _with_values(new, updates)


def _confirmed_ids(ids):
    """(T, K) landmark ids with landmarks seen once dropped (-1) and the rest renumbered.

    A landmark seen once has no residual (its position fits its one observation exactly),
    so it carries nothing about the noise, and its unknowns would only enlarge the solve.
    """
    used = ids >= 0
    counts = np.bincount(ids[used], minlength=1)
    keep = used & (counts[np.where(used, ids, 0)] >= 2)
    out = np.full(ids.shape, -1, ids.dtype)
    if keep.any():
        _, out[keep] = np.unique(ids[keep], return_inverse=True)
    return out


def _detections(path, points, z, valid, params: Params, max_range: float, half_fov: float,
                chunk: int = 1024):
    """Predicted ranges (n,) of every (step, landmark) pair in view, and whether detected (n,).

    In view: min_range <= range <= max_range and |bearing| <= half_fov from the smoothed
    pose. Detected: some valid observation of that step lies within 3 std (squared whitened
    distance <= 9, about 99 % for 2 degrees of freedom) of the predicted measurement. The
    test uses positions, not the filter's landmark identities: a landmark the filter deleted
    and started again is still one tree here, so its misses count against the detector.

    Args: path (T, 3); points (L, 2); z (T, K, 2); valid (T, K).
    """
    ranges, hits = [], []
    for begin in range(0, len(path), chunk):
        pose = path[begin:begin + chunk]
        dx = points[None, :, 0] - pose[:, None, 0]
        dy = points[None, :, 1] - pose[:, None, 1]
        distance = np.hypot(dx, dy)  # (t, L)
        bearing = wrap_angle_np(np.arctan2(dy, dx) - pose[:, None, 2])
        in_view = ((distance >= float(params.min_range)) & (distance <= max_range)
                   & (np.abs(bearing) <= half_fov))
        # Only the pairs in view are tested (a few per cent of (t, L) on a long log).
        step, landmark = np.nonzero(in_view)
        distance, bearing = distance[step, landmark], bearing[step, landmark]  # (n,)
        std = smoothing._observation_std(distance, params)  # (n, 2)
        obs = z[begin + step]  # (n, K, 2)
        d_range = (obs[:, :, 0] - distance[:, None]) / std[:, None, 0]
        d_bearing = wrap_angle_np(obs[:, :, 1] - bearing[:, None]) / std[:, None, 1]
        close = (d_range**2 + d_bearing**2 <= 9.0) & valid[begin + step]
        ranges.append(distance)
        hits.append(np.any(close, axis=1))
    return np.concatenate(ranges), np.concatenate(hits)


# --------------------------------------------------------------------------------------------
# Host twins of the JAX code the EM loop used to call per iteration.
#
# Each EM iteration's fits see a few hundred to a few thousand samples, and their sample count
# changes from iteration to iteration (the association changes): the jitted ``calibrate``
# fits were recompiled every iteration (2-4 s each, several filter runs' worth on a short
# log) to run for 5 ms. The twins below are the same procedure in NumPy/SciPy, float64;
# ``tests/test_self_calibration.py`` checks them against ``calibrate`` and ``lineage``.


def _quantile_bins(values, num_bins: int, valid):
    """NumPy twin of ``calibrate.quantile_bins``."""
    probabilities = np.linspace(0.0, 1.0, num_bins + 1)[1:-1]
    edges = np.quantile(values[valid], probabilities)
    return np.clip(np.searchsorted(edges, values, side="right"), 0, num_bins - 1)


def _group_median(values, group, num_groups: int):
    """(G,) median of ``values`` per group (0 for an empty group); group G drops a sample."""
    out = np.zeros(num_groups)
    for g in range(num_groups):
        members = values[group == g]
        if members.size:
            out[g] = np.median(members)
    return out


def _nonnegative_fit(design, target, weight):
    """argmin_{c >= 0} sum_g w_g (design_g . c - target_g)^2 (``calibrate.fit_nonnegative``,
    solved exactly by ``scipy.optimize.nnls`` on columns scaled to unit weighted norm)."""
    weight = weight / max(float(np.sum(weight)), 1e-300)
    scale = np.sqrt(np.sum(weight[:, None] * design**2, axis=0))
    scale = np.where(scale > 0.0, scale, 1.0)
    root = np.sqrt(weight)[:, None]
    solution, _ = scipy.optimize.nnls(root * design / scale, root[:, 0] * target)
    return solution / scale


def _robust_keep_host(score, usable, threshold: float, floor: float):
    """NumPy twin of ``calibrate._robust_keep`` (the MAD rule with a floor)."""
    if not usable.any():
        return np.zeros_like(usable)
    median = np.median(score[usable])
    spread = calibrate._MAD_TO_STD * np.median(np.abs(score[usable] - median))
    limit = np.inf if np.isinf(threshold) else threshold * spread
    return usable & (np.abs(score - median) <= max(limit, floor))


def _host_fit_noise(features, errors, group, valid, num_groups: int, *, min_count: int,
                    sample_threshold: float = 5.0, group_threshold: float = 4.0,
                    min_group_ratio: float = 2.0):
    """(F,) coefficients of ``calibrate.fit_noise`` (zero-mean errors, steps 1-7 of that
    module's docstring) on host arrays: features (S, F), errors (S,), group (S,), valid (S,)."""
    features, errors = np.asarray(features, np.float64), np.asarray(errors, np.float64)
    valid = np.asarray(valid, bool)
    if not np.all(np.isfinite(features[valid])) or not np.all(np.isfinite(errors[valid])):
        raise ValueError("the noise fit got non-finite valid samples")
    if int(valid.sum()) < features.shape[1] * min_count:
        raise ValueError(f"the noise fit got {int(valid.sum())} valid samples; expected at "
                         f"least {features.shape[1] * min_count}")
    group = np.where(valid, group, num_groups)
    deviation = np.abs(errors)
    robust_std = calibrate._MAD_TO_STD * _group_median(deviation, group, num_groups)
    limit = (np.full(num_groups + 1, np.inf) if np.isinf(sample_threshold)
             else sample_threshold * np.append(robust_std, 0.0))
    kept_group = np.where(valid & (deviation <= limit[group]), group, num_groups)
    count = np.bincount(kept_group, minlength=num_groups + 1)[:num_groups].astype(np.float64)
    safe = np.maximum(count, 1.0)
    std = np.sqrt(np.bincount(kept_group, errors**2, num_groups + 1)[:num_groups] / safe)
    mean_features = np.stack([np.bincount(kept_group, column, num_groups + 1)[:num_groups]
                              for column in features.T], 1) / safe[:, None]
    used = count >= min_count
    safe_std = np.where(std > 0.0, std, 1.0)
    kept = used
    for _ in range(calibrate._GROUP_ROUNDS):
        coefficients = _nonnegative_fit(mean_features, std, np.where(kept, count, 0.0))
        fitted = np.maximum(mean_features @ coefficients, calibrate._TINY)
        new_kept = _robust_keep_host(np.log(safe_std) - np.log(fitted), used & (std > 0.0),
                                     group_threshold, np.log(min_group_ratio))
        kept = new_kept if new_kept.any() else used
    return _nonnegative_fit(mean_features, std, np.where(kept, count, 0.0))


def _motion_samples(true_moves, measured_moves):
    """NumPy twin of ``calibrate.motion_samples``: errors (S, 3), features (3, S, 3)."""
    errors = np.asarray(true_moves, np.float64) - measured_moves
    errors[:, 0], errors[:, 2] = wrap_angle_np(errors[:, 0]), wrap_angle_np(errors[:, 2])
    abs_rot1, abs_trans, abs_rot2 = np.abs(np.asarray(measured_moves, np.float64)).T
    ones = np.ones_like(abs_trans)
    features = np.stack([np.stack([abs_trans, abs_rot1, ones], -1),
                         np.stack([abs_trans, abs_rot1 + abs_rot2, ones], -1),
                         np.stack([abs_trans, abs_rot2, ones], -1)])
    return errors, features


def _host_motion_fit(true_moves, measured_moves, valid, *, trans_bins: int, rot_bins: int,
                     min_count: int):
    """(3, 3) coefficients of ``calibrate.fit_motion_noise`` (rows rot1, trans, rot2)."""
    valid = np.asarray(valid, bool)
    true_moves = np.where(valid[:, None], true_moves, 0.0)
    errors, features = _motion_samples(true_moves, np.asarray(measured_moves, np.float64))
    rows = []
    for i in range(3):
        group = (_quantile_bins(features[i][:, 0], trans_bins, valid) * rot_bins
                 + _quantile_bins(features[i][:, 1], rot_bins, valid))
        rows.append(_host_fit_noise(features[i], errors[:, i], group, valid,
                                    trans_bins * rot_bins, min_count=min_count))
    return np.stack(rows)


def _host_observation_fit(true_z, measured_z, valid, *, distance_bins: int, min_count: int):
    """(2, 2) coefficients of ``calibrate.fit_observation_noise`` (rows range, bearing)."""
    valid = np.asarray(valid, bool)
    true_z, measured_z = np.asarray(true_z, np.float64), np.asarray(measured_z, np.float64)
    errors = np.stack([true_z[:, 0] - measured_z[:, 0],
                       wrap_angle_np(true_z[:, 1] - measured_z[:, 1])], -1)
    features = np.stack([measured_z[:, 0], np.ones_like(measured_z[:, 0])], -1)
    group = _quantile_bins(measured_z[:, 0], distance_bins, valid)
    return np.stack([_host_fit_noise(features, errors[:, i], group, valid, distance_bins,
                                     min_count=min_count) for i in range(2)])


def _odometry_std(odometry, params: Params):
    """NumPy twin of ``motion.odometry_std``: Eq. (1) stds (N, 3) of (rot1, trans, rot2)."""
    abs_rot1, abs_trans, abs_rot2 = np.abs(np.asarray(odometry, np.float64)).T
    rot1, trans, rot2 = (np.asarray(c, np.float64) for c in (params.rot1_noise,
                                                            params.trans_noise,
                                                            params.rot2_noise))
    return np.stack([rot1[0] * abs_trans + rot1[1] * abs_rot1 + rot1[2],
                     trans[0] * abs_trans + trans[1] * (abs_rot1 + abs_rot2) + trans[2],
                     rot2[0] * abs_trans + rot2[1] * abs_rot2 + rot2[2]], 1)


def _odometry_from_poses(start, end, min_translation: float):
    """NumPy twin of ``motion.odometry_from_poses`` (N, 3) -> (rot1, trans, rot2) (N, 3)."""
    dx, dy = end[:, 0] - start[:, 0], end[:, 1] - start[:, 1]
    c, s = np.cos(start[:, 2]), np.sin(start[:, 2])
    along, across = c * dx + s * dy, -s * dx + c * dy
    trans = np.hypot(along, across)
    rot1 = np.where(trans >= min_translation, np.arctan2(across, along), 0.0)
    rot2 = wrap_angle_np(wrap_angle_np(end[:, 2] - start[:, 2]) - rot1)
    return np.stack([rot1, trans, rot2], 1)


def _range_bearing(pose, point):
    """NumPy twin of ``geometry.range_bearing`` for (N, 3) poses and (N, 2) points."""
    dx, dy = point[:, 0] - pose[:, 0], point[:, 1] - pose[:, 1]
    return np.stack([np.hypot(dx, dy), wrap_angle_np(np.arctan2(dy, dx) - pose[:, 2])], 1)


def _best_history(lineage_record: lineage.Lineage, log_weight) -> lineage.LineagePath:
    """NumPy twin of ``lineage.trace_lineage(lineage_record, estimate(final).best_particle)``.

    The best particle is the first of the highest final log weight (``filter.estimate``).
    """
    ancestor = np.asarray(lineage_record.ancestor)
    index = int(np.argmax(np.asarray(log_weight)))
    after = np.empty(ancestor.shape[0], np.int64)
    before = np.empty(ancestor.shape[0], np.int64)
    for t in range(ancestor.shape[0] - 1, -1, -1):
        after[t] = index
        index = int(ancestor[t, index])
        before[t] = index
    steps = np.arange(ancestor.shape[0])
    return lineage.LineagePath(pose=np.asarray(lineage_record.pose)[steps, after],
                               match=np.asarray(lineage_record.match)[steps, before],
                               birth_slot=np.asarray(lineage_record.birth_slot)[steps, before])


def _with_values(params: Params, values: dict) -> Params:
    return params._replace(**{name: jnp.asarray(value, getattr(params, name).dtype)
                              for name, value in values.items()})


def _plain(value):
    array = np.asarray(value, np.float64)
    return float(array) if array.ndim == 0 else tuple(float(v) for v in array)


def calibrate_params(config: FilterConfig, key, controls, observations: Observations,
                     initial_pose=None, params: Params | None = None, *,
                     motion_model: str | None = None, iterations: int = 6, tol: float = 0.05,
                     calibrate_sensor: bool = True, smoother_iterations: int = 15,
                     progress=None) -> tuple[Params, CalibrationInfo]:
    """Estimate the filter's settings from one log, with no ground truth (module docstring).

    Args:
      config: the ``FilterConfig`` the log will be filtered with (K = ``max_obs`` must match
        the observations). Its motion model is used unless ``motion_model`` is given.
      key: PRNG key of every iteration's filter run (the same one each time).
      controls: (T, 3) the log's controls. observations: ``Observations`` (T, K, ...).
      initial_pose: (3,) start pose (default zeros).
      params: the first iteration's settings; default ``starting_params(config)``. Fields the
        calibration does not estimate are kept from it.
      iterations: most EM iterations. tol: stop when every noise group's typical std moved
        by less than this fraction in one iteration.
      calibrate_sensor: also estimate max_range, miss_range, detection and false-alarm
        probabilities and the gate (else only the noise).
      smoother_iterations: most Levenberg-Marquardt steps of each smoothing.
      progress: optional callable(str) told of each iteration in one line.
    Returns:
      (params, info): the calibrated ``Params`` (dtype of ``params``) and ``CalibrationInfo``.
      A log too short or too sparse to calibrate returns the given ``params`` unchanged for
      the groups it could not fit, and says so in ``info.warnings`` and ``info.verdict``.
    """
    if iterations < 1 or not tol > 0:
        raise ValueError(f"calibrate_params needs iterations >= 1 and tol > 0; got "
                         f"{iterations}, {tol}")
    motion_model = motion_model or config.motion_model
    params = starting_params(config) if params is None else params
    controls = np.asarray(controls)
    if controls.ndim != 2 or controls.shape[1] != 3:
        raise ValueError(f"calibrate_params: controls must be (T, 3); got {controls.shape}")
    steps = controls.shape[0]
    if observations.z.shape[:1] != (steps,):
        raise ValueError(f"calibrate_params: observations have {observations.z.shape[0]} "
                         f"steps but controls {steps}; expected one row of each per step")
    start = np.zeros(3) if initial_pose is None else np.asarray(initial_pose, np.float64)
    dtype = params.rot1_noise.dtype
    z = np.asarray(observations.z, np.float64)
    valid = np.asarray(observations.valid) & np.all(np.isfinite(z), axis=-1)
    z = np.where(valid[..., None], z, 0.0)
    warnings: list[str] = []
    if valid.sum() < MIN_OBSERVATIONS:
        warnings.append(f"only {int(valid.sum())} valid observations in the log; the "
                        f"calibration needs at least {MIN_OBSERVATIONS} of landmarks seen "
                        f"{MIN_SIGHTINGS} or more times: the given settings are used")
        return params, CalibrationInfo(0, np.zeros(0), np.zeros(0), np.zeros((0, 4)),
                                       {}, {}, {}, False, "not calibrated: too few "
                                       "observations", tuple(warnings))
    objective, costs, typical = [], [], []
    relative_std, samples, values = {}, {}, {}
    converged = False
    done = 0
    motion = obs = None
    used = np.zeros(0, bool)
    evaluated = []  # the Params each filter run (objective entry) used
    for done in range(1, iterations + 1):
        odometry = np.asarray(control_to_odometry(jnp.asarray(controls, dtype), params,
                                                  motion_model), np.float64)
        typical.append(_typical_stds(params, odometry, z[valid][:, 0]))
        final, trace = run_filter(config, key, params, jnp.asarray(controls, dtype),
                                  observations, jnp.asarray(start, dtype), record_lineage=True)
        objective.append(float(np.sum(np.asarray(trace.log_evidence))))
        evaluated.append(params)
        history = _best_history(trace.lineage, final.log_weight)
        ids, _ = lineage.landmark_identities(history.match, history.birth_slot)
        ids = np.where(valid, np.asarray(ids), -1)
        single_share = _single_share(ids)
        ids = _confirmed_ids(ids)
        if not np.any(ids >= 0):
            warnings.append("no landmark was observed twice with the starting settings: "
                            "nothing to calibrate on, the given settings are used")
            break
        try:
            smoothed = smoothing.smooth_path(start, np.asarray(history.pose, np.float64),
                                             odometry, z, ids, params,
                                             iterations=smoother_iterations, tol=1e-4,
                                             calibrate_rounds=2)
        except (RuntimeError, np.linalg.LinAlgError, ValueError) as error:
            warnings.append(f"the smoother failed on this log ({error}); calibration stopped "
                            f"at iteration {done}")
            break
        costs.append(float(smoothed.cost[-1]) / max(3 * steps + 2 * int((ids >= 0).sum()), 1))
        res = _residuals(start, smoothed, np.asarray(history.pose, np.float64), odometry, z,
                         float(params.min_translation))
        used = res.sightings[res.obs_landmark] >= MIN_SIGHTINGS
        update = {}
        motion = _motion_update(res, params, smoothed.noise_scales,
                                defensive_bursts(config))
        if motion is not None:
            rows, eps, kappa = motion
            update.update(rot1_noise=rows[0], trans_noise=rows[1], rot2_noise=rows[2],
                          motion_outlier_probability=eps, motion_outlier_scale=kappa)
            samples["heading"] = samples["translation"] = steps
        obs = _observation_update(res, params, smoothed.noise_scales, used)
        if obs is not None:
            update.update(range_noise=obs[0], bearing_noise=obs[1],
                          range_std_floor=max(STD_FLOOR, 0.5 * obs[0][1]),
                          bearing_std_floor=max(STD_FLOOR, 0.5 * obs[1][1]))
            samples["range"] = samples["bearing"] = int(used.sum())
        if calibrate_sensor:
            update.update(_sensor_update(res, z, valid, used, smoothed.path, smoothed.landmark,
                                         params))
            if single_share is not None:
                update["false_alarm_probability"] = float(np.clip(single_share, 1e-3, 0.5))
        if "association_gate" in update:
            update["airlock_sigmas"] = float(np.sqrt(update["association_gate"]))
        new_params = _trust_region(params, _with_values(params, update), odometry,
                                   z[valid][:, 0])
        params = new_params
        values.update({name: _plain(getattr(params, name)) for name in update})
        new_typical = _typical_stds(params, odometry, z[valid][:, 0])
        change = np.max(np.abs(new_typical / typical[-1] - 1.0))
        if progress is not None:
            progress(f"calibration iteration {done}: log marginal likelihood "
                     f"{objective[-1]:.1f}, typical stds heading {new_typical[0]:.4g} rad, translation "
                     f"{new_typical[1]:.4g} m, range {new_typical[2]:.4g} m, bearing "
                     f"{new_typical[3]:.4g} rad (largest change {change:.1%})")
        if change < tol:
            converged = True
            break
    chosen = ""
    if not converged and evaluated:
        # EM raises the marginal likelihood while the E-step's association holds; when it
        # did not converge, the settings whose own filter run scored best are returned.
        # The first run used the starting settings, whose sensor fields (range, field of
        # view, detection) are guesses no M-step has seen: it is never the one returned.
        scores = np.asarray(objective, np.float64)
        scores[0] = -np.inf if len(scores) > 1 else scores[0]
        best = int(np.argmax(np.where(np.isfinite(scores), scores, -np.inf))
                   if np.any(np.isfinite(scores)) else len(evaluated) - 1)
        params = evaluated[best]
        values = {name: _plain(getattr(params, name)) for name in values}
        chosen = (f"; returned iteration {best + 1}'s settings (the highest log marginal "
                  f"likelihood of the {len(evaluated)} filter runs)")
    typical.append(_typical_stds(params, odometry, z[valid][:, 0]))
    if motion is None:
        warnings.append(f"too few moves ({steps}; need {MIN_MOVES}) to fit the motion noise: "
                        "kept the given motion noise")
    if obs is None:
        warnings.append(f"too few observations of landmarks seen {MIN_SIGHTINGS} or more "
                        f"times ({int(used.sum())}; need {MIN_OBSERVATIONS}) to fit the "
                        "sensor noise: kept the given sensor noise")
    relative_std = {group: 1.0 / np.sqrt(2.0 * n) for group, n in samples.items()}
    verdict = ("converged" if converged else f"not converged after {done} iterations "
               f"(the last moved a noise std by more than {tol:.0%})")
    verdict += chosen
    if warnings:
        verdict += "; partly calibrated (see warnings)"
    return params, CalibrationInfo(done, np.asarray(objective), np.asarray(costs),
                                   np.asarray(typical), values, relative_std, samples,
                                   converged, verdict, tuple(warnings))
