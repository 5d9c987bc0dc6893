"""The self-calibration's noise M-step: Eq. (1) and Table 2 fitted to smoothed residuals.

Shape: the robust grouped fit of ``calibrate.fit_noise`` (steps 1-7 of that module's
docstring) of Geiser et al., "Practical Implementation of FastSLAM for Forestry Robot"
(ICAROB 2023), Eq. (1) to the move residuals and Table 2 to the observation residuals
(``calibration_residuals.Residuals``).

Scale: residuals of a least-squares solution are smaller than the noise (a group's residual
sum of squares has r_g = n_g - tr(J_g H^-1 J_g^T) degrees of freedom, not n_g); the fitted
shape is rescaled (``rescale``) so that its mean variance over the group's samples equals the
smoother's unbiased variance-component estimate (``smoothing.NoiseScales``).

Bursts and tails: a two-scale mixture of the whitened move residuals, brought to unit mean
square (``unit_mean_square``: the shape, not the scale, of the shrunk residuals), sets the
burst probability and scale when it beats one Gaussian by BIC (``fit_bursts``); otherwise
each std is widened until 95 % of the residuals lie in its 95 % interval (``tail_factor``).

Host code: each EM iteration fits a few hundred to a few thousand samples, and the count
changes with the association, so the jitted ``calibrate`` fits would compile anew every
iteration (seconds) to run for milliseconds. ``host_fit_noise`` is the same procedure in
NumPy/SciPy, float64; ``tests/test_self_calibration.py`` checks it against ``calibrate``.

Shapes: T moves, S samples, G groups, F features.
"""
from __future__ import annotations

import numpy as np
import scipy.optimize

from jaxslam import calibrate, smoothing
from jaxslam.calibration_residuals import Residuals

MIN_MOVES = 30  # fewer moves than this: the motion noise is not fitted
MIN_OBSERVATIONS = 20  # fewer associated observations (in landmarks seen >= 3 times): none
MIN_SIGHTINGS = 3  # a landmark's observations enter the fits when it was seen this often
STD_FLOOR = 1e-5  # lower bound of every fitted constant term (keeps covariances invertible)
BURST_LIMITS = (0.25, 10.0)  # most burst probability, most burst scale (``fit_bursts``)
TAIL_QUANTILE = 0.95  # the share of errors the fitted std must cover (``tail_factor``)
CHI2_1DOF = {0.95: 3.8415, 0.99: 6.6349}  # chi-square quantiles, 1 degree of freedom


# --------------------------------------------------------------------------------------------
# The grouped robust fit of ``calibrate.fit_noise`` on host arrays


def _quantile_bins(values, num_bins: int, valid):
    """Group index (S,) by quantile bins of the valid values (``calibrate.quantile_bins``)."""
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
    """argmin_{c >= 0} sum_g w_g (design_g . c - target_g)^2 (``nonnegative.fit_nonnegative``,
    solved exactly by ``scipy.optimize.nnls`` on columns scaled to unit weighted norm)."""
    weight = weight / max(float(np.sum(weight)), 1e-300)
    scale = np.sqrt(np.sum(weight[:, None] * design**2, axis=0))
    scale = np.where(scale > 0.0, scale, 1.0)
    root = np.sqrt(weight)[:, None]
    solution, _ = scipy.optimize.nnls(root * design / scale, root[:, 0] * target)
    return solution / scale


def _robust_keep(score, usable, threshold: float, floor: float):
    """The MAD rule with a floor of ``calibrate._robust_keep``."""
    if not usable.any():
        return np.zeros_like(usable)
    median = np.median(score[usable])
    spread = calibrate.MAD_TO_STD * np.median(np.abs(score[usable] - median))
    limit = np.inf if np.isinf(threshold) else threshold * spread
    return usable & (np.abs(score - median) <= max(limit, floor))


def host_fit_noise(features, errors, group, valid, num_groups: int, *, min_count: int,
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
    robust_std = calibrate.MAD_TO_STD * _group_median(deviation, group, num_groups)
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
    for _ in range(calibrate.GROUP_ROUNDS):
        coefficients = _nonnegative_fit(mean_features, std, np.where(kept, count, 0.0))
        fitted = np.maximum(mean_features @ coefficients, calibrate.TINY)
        new_kept = _robust_keep(np.log(safe_std) - np.log(fitted), used & (std > 0.0),
                                group_threshold, np.log(min_group_ratio))
        kept = new_kept if new_kept.any() else used
    return _nonnegative_fit(mean_features, std, np.where(kept, count, 0.0))


def host_motion_fit(errors, features, valid, *, trans_bins: int, rot_bins: int,
                    min_count: int):
    """(3, 3) coefficients of ``calibrate.fit_motion_noise`` (rows rot1, trans, rot2) from
    the errors (S, 3) and regressors (3, S, 3) of ``calibrate.motion_samples``."""
    valid = np.asarray(valid, bool)
    errors = np.where(valid[:, None], errors, 0.0)  # a move the smoother did not give
    rows = []
    for i in range(3):
        group = (_quantile_bins(features[i][:, 0], trans_bins, valid) * rot_bins
                 + _quantile_bins(features[i][:, 1], rot_bins, valid))
        rows.append(host_fit_noise(features[i], errors[:, i], group, valid,
                                   trans_bins * rot_bins, min_count=min_count))
    return np.stack(rows)


def host_observation_fit(errors, measured_range, valid, *, distance_bins: int,
                         min_count: int):
    """(2, 2) coefficients of ``calibrate.fit_observation_noise`` (rows range, bearing) from
    the errors (S, 2) (bearing wrapped) and the measured ranges (S,)."""
    valid = np.asarray(valid, bool)
    measured_range = np.asarray(measured_range, np.float64)
    features = np.stack([measured_range, np.ones_like(measured_range)], -1)
    group = _quantile_bins(measured_range, distance_bins, valid)
    return np.stack([host_fit_noise(features, errors[:, i], group, valid, distance_bins,
                                    min_count=min_count) for i in range(2)])


# --------------------------------------------------------------------------------------------
# Scale, bursts and tails


def rescale(coefficients, features, target_variance):
    """Coefficients scaled so that mean((features . c)^2) equals ``target_variance``."""
    fitted = features @ coefficients
    mean_variance = float(np.mean(fitted**2))
    if not mean_variance > 0.0:
        return None
    return coefficients * np.sqrt(target_variance / mean_variance)


def tail_factor(errors, std, quantile: float = TAIL_QUANTILE) -> float:
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
    # can sample, and a burst share above its limit is a mis-fit core: both are clipped, and
    # the core stays the fitted one. The mixture then carries less than the residuals' second
    # moment (a burst scale of 20 clipped to 10: 0.44 of it at eps = 0.05): the clipped part
    # is left to the filter as outliers, not spread over every move's core. A version that
    # moved it into the core made MRCLAM's five robots worse on both seeds run
    # (docs/results.md, self_calibration, "Bursts fitted to the shrunk residuals").
    return min(eps, BURST_LIMITS[0]), a, min(b / a, BURST_LIMITS[1])


# --------------------------------------------------------------------------------------------
# The M-step of the two noise models


def unit_mean_square(white):
    """(S, d) finite whitened residuals, each column divided by its root mean square (a
    column of zeros is kept).

    A smoothed path absorbs part of every move's error: group g's residuals keep a mean
    square of about r_g / n_g of the noise variance (``smoothing.solver.variance_factors``).
    The variance components have set each group's variance; the residuals still tell the
    shape of its distribution (a burst mixture, a tail), so the shape fits take them at unit
    mean square, and the mixture's core and bursts then share the variance components' total
    (``fit_bursts``; less what its limits clip). One factor a column corrects the average
    shrinkage, not each move's (row i keeps R_ii of its variance, R = I - J H^-1 J^T), so an
    uneven R_ii alone makes Gaussian residuals a scale mixture, which ``fit_bursts`` can read as
    bursts (half the moves at R_ii = 0.05 and half at 0.85: a share of 0.25 with a core of
    0.45; ``tests/test_motion_noise_shape.py``). Dividing each residual by sqrt(R_ii)
    removed them, and the calibrated filter did worse on every held-out row measured: the
    bursts give the motion proposal a tail it uses (docs/results.md, self_calibration,
    "Bursts fitted to the shrunk residuals").
    """
    white = np.asarray(white, np.float64)
    rms = np.sqrt(np.mean(white**2, axis=0)) if len(white) else np.ones(white.shape[1:])
    return white / np.where(rms > 0.0, rms, 1.0)


def motion_noise_update(res: Residuals, scales: smoothing.NoiseScales,
                        no_bursts: tuple[float, float]):
    """(coefficients (3, 3) of rot1, trans, rot2, burst probability, burst scale, whether
    the bursts were fitted), or None when there are too few moves. Bursts (``fit_bursts``)
    or, without them, the tail factor and ``no_bursts`` (eps, kappa)
    (``self_calibration.defensive_bursts``)."""
    moving = np.all(np.isfinite(res.true_moves), axis=1)
    if int(moving.sum()) < MIN_MOVES:
        return None
    coefficients = list(host_motion_fit(res.move_error, res.move_features, moving,
                                        trans_bins=4, rot_bins=4, min_count=5))
    current = res.move_std[moving]
    features = res.move_features[:, moving]
    # The heading group holds rot1 and rot2 together (its whitened row is their sum), so both
    # rows take one factor: the one that brings their summed variance to the estimate.
    heading_target = scales.heading**2 * np.mean(current[:, 0] ** 2 + current[:, 2] ** 2)
    heading_fit = np.mean((features[0] @ coefficients[0]) ** 2
                          + (features[2] @ coefficients[2]) ** 2)
    trans = rescale(coefficients[1], features[1],
                    scales.translation**2 * np.mean(current[:, 1] ** 2))
    if not heading_fit > 0.0 or trans is None:
        return None
    factor = np.sqrt(heading_target / heading_fit)
    rows = [coefficients[0] * factor, trans, coefficients[2] * factor]
    errors = res.move_error[moving]
    std = [features[i] @ rows[i] for i in range(3)]
    heading_error, heading_std = errors[:, 0] + errors[:, 2], np.hypot(std[0], std[2])
    white = unit_mean_square(np.stack([heading_error / np.maximum(heading_std, STD_FLOOR),
                                       errors[:, 1] / np.maximum(std[1], STD_FLOOR)], 1))
    bursts = fit_bursts(white)
    if bursts is not None:
        eps, core, kappa = bursts
        rows = [r * core for r in rows]
    else:
        eps, kappa = no_bursts
        heading_tail = tail_factor(white[:, 0], 1.0)
        rows = [rows[0] * np.sqrt(heading_tail),
                rows[1] * np.sqrt(tail_factor(white[:, 1], 1.0)),
                rows[2] * np.sqrt(heading_tail)]
    # A positive constant keeps every move's covariance invertible (smoothing, proposals).
    rows = np.stack([np.concatenate([r[:2], [max(r[2], STD_FLOOR)]]) for r in rows])
    return rows, eps, kappa, bursts is not None


def observation_noise_update(res: Residuals, scales: smoothing.NoiseScales, used: np.ndarray):
    """New (range_noise, bearing_noise) (2, 2), or None when there are too few samples.

    ``used`` (S,): the samples of landmarks seen often enough to enter the fit."""
    if int(used.sum()) < MIN_OBSERVATIONS:
        return None
    fit = host_observation_fit(res.observation_error, res.measured_z[:, 0], used,
                               distance_bins=6, min_count=5)
    z_range = res.measured_z[used, 0]
    current = res.observation_std[used]
    features = np.stack([z_range, np.ones_like(z_range)], 1)
    new = []
    for group, (component, scale) in enumerate(zip(fit, (scales.range, scales.bearing))):
        row = rescale(component, features, scale**2 * float(np.mean(current[:, group] ** 2)))
        if row is None:
            return None
        error = res.observation_error[used, group]
        row = row * np.sqrt(tail_factor(error, features @ row))
        new.append(np.array([row[0], max(row[1], STD_FLOOR)]))
    return np.stack(new)


def std_relative_error(white, degrees_of_freedom: float | None = None) -> float:
    """Relative standard error of a noise std estimated from the whitened residuals ``white``
    (S,) of its group, in time order (non-finite entries dropped).

    ``degrees_of_freedom``: nu, the degrees of freedom of the estimate (those of the
    smoother's variance factor of the group, ``group_relative_errors``), None for S; clipped
    to [1, S]. A
    least-squares solution absorbs part of each residual, so the residuals carry only nu
    independent squares and the Gaussian floor becomes 1 / sqrt(2 nu) (chi-square with nu
    degrees of freedom). The batch-means figure is left as it is: for Gaussian residuals
    e = R eps (R = I - H), a group's Var(sum e^2) = 2 tr(E_g R E_g R), which the batch means
    measure when the correlation is shorter than a batch, as a smoothed path's is; scaling
    it as well would count the correlation twice. Where the correlation is not local (a
    dense design) the batches miss it and the floor holds. The floor's nu is the variance
    factor's (``smoothing.solver.variance_factors``), at most tr(E_g R E_g R): a factor
    estimated together with the other groups' spreads more than its own sum of squares.

    The std is taken as the root mean square: s = sqrt(mean(w^2)), so by the delta method
    SE(s) / s = SE(mean(w^2)) / (2 mean(w^2)). For independent Gaussian residuals that is
    1 / sqrt(2 S) (chi-square), the figure the calibration stated before; heavy tails
    (kurtosis kappa: sqrt((kappa - 1) / (4 S)) for independent samples) and correlation
    between neighbouring steps (a bias or a burst spread over a few moves) make it larger.
    SE(mean(w^2)) is estimated by batch means: the squares cut into B = floor(sqrt(S))
    consecutive batches, SE = std(batch means) / sqrt(B), which holds for both when a batch
    is longer than the correlation (Flegal and Jones, "Batch means and spectral variance
    estimators in Markov chain Monte Carlo", Annals of Statistics 2010). With B about 15 the
    estimate is itself uncertain by about 20 %, so the result is never below the Gaussian
    figure. Fewer than 16 samples: the Gaussian figure (inf for none).
    """
    squares = np.asarray(white, np.float64) ** 2
    squares = squares[np.isfinite(squares)]
    count = squares.size
    if count == 0:
        return float("inf")
    nu = count if degrees_of_freedom is None else float(
        np.clip(degrees_of_freedom, 1.0, count))
    gaussian = 1.0 / np.sqrt(2.0 * nu)
    batches = int(np.sqrt(count))
    mean = float(np.mean(squares))
    if batches < 4 or not mean > 0.0:
        return gaussian
    length = count // batches
    batch_means = squares[:batches * length].reshape(batches, length).mean(axis=1)
    error_of_mean = np.std(batch_means, ddof=1) / np.sqrt(batches)
    return float(max(gaussian, 0.5 * error_of_mean / mean))


def group_relative_errors(res: Residuals, used: np.ndarray, motion: bool,
                          observation: bool, degrees_of_freedom=None) -> dict:
    """``std_relative_error`` of each fitted noise group (heading, translation, range,
    bearing) from ``res``' residuals whitened by their own Eq. (1) / Table 2 std (the shape
    of the settings the residuals were computed with; the relative error does not depend on
    the scale). The heading group's residual is rot1 + rot2, as in ``motion_noise_update``.
    ``used`` (S,): the observation samples that entered the fit.

    ``degrees_of_freedom``: None, or (4,) those of the smoother's variance factor of each
    group (``smoothing.Smoothed.degrees_of_freedom``, nu_g). The M-step scales each group's
    fit to that factor (``motion_noise_update``, ``observation_noise_update``), so nu_g is
    passed on (``std_relative_error``). Where the observations pin the path loosely, the
    smoothed path absorbs most of each move's error: on the simulated loops of
    ``experiments/self_calibration.py`` the heading group's redundancy r_g was 34-50 of 250
    rows and the translation group's 41-72 of 500 at the first M-step, and nu_g is smaller
    still (about half of r_g for the heading group at the true noise: the path shares the
    error with the bearings), while the observation groups keep about 0.9 of theirs. The
    translation group's two rows a move can leave nu_g above its S residuals;
    ``std_relative_error`` then clips it to S."""
    dof = ([None] * 4 if degrees_of_freedom is None
           else [float(r) for r in np.asarray(degrees_of_freedom)])

    out = {}
    if motion:
        moving = np.all(np.isfinite(res.true_moves), axis=1)
        error, std = res.move_error[moving], np.maximum(res.move_std[moving], STD_FLOOR)
        out["heading"] = std_relative_error((error[:, 0] + error[:, 2])
                                            / np.hypot(std[:, 0], std[:, 2]), dof[0])
        out["translation"] = std_relative_error(error[:, 1] / std[:, 1], dof[1])
    if observation:
        white = (res.observation_error[used]
                 / np.maximum(res.observation_std[used], STD_FLOOR))
        out["range"] = std_relative_error(white[:, 0], dof[2])
        out["bearing"] = std_relative_error(white[:, 1], dof[3])
    return out


def measured_radii(radius, valid) -> np.ndarray:
    """(T, K) bool: valid observations whose radius was measured (finite and > 0; otherwise
    "no radius", as ``sanitize`` reads it). radius, valid: (T, K)."""
    radius = np.asarray(radius, np.float64)
    return np.asarray(valid, bool) & np.isfinite(radius) & (radius > 0.0)


def radius_noise_from_history(ids, radius, valid, min_sightings: int = 3,
                              quantile: float = TAIL_QUANTILE) -> tuple[float, int]:
    """Std [m] of one detected trunk radius from the scatter within each tree, no ground truth.

    ids: (T, K) landmark identity of each observation along one particle's history
    (``lineage.landmark_identities``; -1: none); radius: (T, K) detected radii; valid:
    (T, K); a radius that is not finite or not positive means "no radius measured" (as in
    ``sanitize``) and is left out. Over the landmarks with at least ``min_sightings`` such
    sightings, the deviations e = r - median_j(r) of each radius from its tree's median are
    pooled. The core std is
    their median absolute deviation, s = 1.4826 median |e|, and it is then widened by
    ``tail_factor`` until the ``quantile`` share of the deviations lies within the filter's
    interval of that share: std = s sqrt(tail_factor(e, s)) = max(s, sqrt(q_quantile(e^2) /
    chi2_1(q))), about q_quantile(|e|) / 1.96 for 95 % (``quantile`` 0.95 or 0.99, the keys
    of ``CHI2_1DOF``). Computed as that maximum, so a core of 0 (most radii equal to their
    tree's median, as quantised radii can be) still gets the tail's width. The same rule as
    the motion and sensor noise (``tail_factor``): a trunk's detected radius is heavy-tailed
    (a partly occluded or grazed trunk gives a short chord), and a std fitted to the core
    alone makes the association's radius term reject those sightings, so the tree is split
    into a new landmark. For Gaussian scatter the two agree up to sampling noise. Returns
    (std, observations used); (nan, 0) when no landmark was seen often enough.
    """
    _check_quantile(quantile)
    deviations = _radius_deviations(ids, radius, valid, min_sightings)
    if not deviations:
        return float("nan"), 0
    pooled = np.concatenate(deviations)
    return _radius_std(pooled, quantile), int(pooled.size)


def radius_noise_relative_error(ids, radius, valid, min_sightings: int = 3,
                                quantile: float = TAIL_QUANTILE, replicates: int = 400,
                                seed: int = 0) -> float:
    """Relative standard error of ``radius_noise_from_history``'s std (same arguments), by a
    bootstrap over landmarks.

    The deviations of one tree share its median and its trunk's shape, so they are not
    independent samples; the landmarks are. Each of ``replicates`` replicates draws L of the
    L qualifying landmarks with replacement (``numpy.random.default_rng(seed)``: the same
    inputs give the same figure), pools their deviations (each tree's own, from its own
    median) and recomputes the std; the result is the replicates' standard deviation over the
    std of the data (Efron and Tibshirani, "An Introduction to the Bootstrap", 1993, ch. 6
    and 8.5 on resampling whole groups). As with ``std_relative_error`` it is the sampling
    error only: a landmark that merges two trees or splits one is not in it. inf when fewer
    than 2 landmarks qualify or the std is 0; nan inputs as ``radius_noise_from_history``.
    ``replicates`` below 2 is refused.
    """
    if isinstance(replicates, bool) or not isinstance(replicates, (int, np.integer)) \
            or replicates < 2:
        raise ValueError(f"replicates must be an integer >= 2; got {replicates!r}")
    _check_quantile(quantile)
    deviations = _radius_deviations(ids, radius, valid, min_sightings)
    std = _radius_std(np.concatenate(deviations), quantile) if deviations else 0.0
    if len(deviations) < 2 or not std > 0.0:
        return float("inf")
    rng = np.random.default_rng(seed)
    draws = rng.integers(0, len(deviations), size=(replicates, len(deviations)))
    stds = np.array([_radius_std(np.concatenate([deviations[j] for j in row]), quantile)
                     for row in draws])
    return float(np.std(stds, ddof=1) / std)


def _check_quantile(quantile: float) -> None:
    if quantile not in CHI2_1DOF:
        raise ValueError(f"quantile must be one of {sorted(CHI2_1DOF)}; got {quantile!r}")


def _radius_deviations(ids, radius, valid, min_sightings: int) -> list:
    """Per qualifying landmark (``min_sightings`` measured radii or more), its radii's
    deviations (n_j,) from its own median; [] when none qualifies."""
    ids = np.where(measured_radii(radius, valid), np.asarray(ids), -1).ravel()
    radius = np.asarray(radius, np.float64).ravel()
    keep = ids >= 0
    ids, radius = ids[keep], radius[keep]
    if ids.size == 0:
        return []
    order = np.argsort(ids, kind="stable")
    _, first, counts = np.unique(ids[order], return_index=True, return_counts=True)
    groups = np.split(radius[order], first[1:])
    return [group - np.median(group) for group, count in zip(groups, counts)
            if count >= min_sightings]


def _radius_std(deviation, quantile: float) -> float:
    """max(core, tail) std of pooled radius deviations (``radius_noise_from_history``)."""
    core = calibrate.MAD_TO_STD * np.median(np.abs(deviation))
    tail = np.sqrt(np.quantile(deviation**2, quantile) / CHI2_1DOF[quantile])  # tail_factor's
    return float(max(core, tail))
