"""Noise-model estimation from data (Geiser et al. 2023, section 4.1, Tables 1 and 2).

Input: S recorded pairs of a true and a measured quantity. For motion, moves (rot1, trans,
rot2) from the true poses and from the odometry; for observations, (range, bearing) of a trunk
from the truth and from the detector. The model to fit is Geiser et al. 2023, Eq. (1): the error
``e = true - measured`` is Gaussian with zero mean and a std linear in the measured move,

    sigma_rot1  = a1 |trans| + b1 |rot1|           + c1      (Params.rot1_noise)
    sigma_trans = a2 |trans| + b2 (|rot1| + |rot2|) + c2      (Params.trans_noise)
    sigma_rot2  = a3 |trans| + b3 |rot2|           + c3      (Params.rot2_noise)
    sigma_range = d_r distance + e_r,   sigma_bearing = d_b distance + e_b   (Table 2)

The std is a function of the MEASURED value because the filter evaluates it there
(``motion.odometry_std`` of the odometry reading; the observation noise at the measured range).

Procedure (one error component at a time, ``fit_noise``):
  1. Group similar samples: quantile bins over the two magnitudes (|trans|, |rot|) of the
     component (motion, an n_t x n_r grid) or over distance (observations). G groups.
  2. Sample outliers: in each group, a sample whose absolute deviation exceeds
     ``sample_threshold`` robust stds is removed; the robust std is 1.4826 * median absolute
     deviation (about the median when ``estimate_mean``, about zero otherwise), the MAD rule.
     When more than half of a group's errors are exactly zero the robust std is 0 and only
     the zeros are kept (the group's std is then 0 and it is left out of the fit, step 6).
  3. Per-group maximum-likelihood variance of the kept samples. Default: the mean is KNOWN to be
     zero (Eq. (1) centres the true value on the measured one), sigma^2 = mean(e^2), so a bias
     of the sensor (wheel slip shortens every move) is counted as noise, as the filter needs.
     With ``estimate_mean=True`` the ML pair is used: mu = mean(e), sigma^2 = mean((e - mu)^2)
     (the ML variance, biased by (n-1)/n).
  4. Groups with fewer than ``min_count`` kept samples are dropped.
  5. A first non-negative weighted least-squares fit of sigma_g against the group's mean
     features (|trans|, |rot|, 1) or (distance, 1), weights = kept sample counts n_g.
  6. Group outliers: log ratios z_g = log(sigma_g / fit_g) of the group std to the fitted one;
     a group with |z_g - median z| > max(``group_threshold`` * 1.4826 * MAD(z),
     log(``min_group_ratio``)) is removed (the MAD rule, with a floor: a removed group's std
     is also off by more than a factor ``min_group_ratio``, default 2). A ratio, not a residual scaled by the group's precision sqrt(2 n_g) / sigma_g:
     when the linear model is only approximate, a precision-scaled rule would throw out the
     largest (best measured) groups first. Groups with sigma_g = 0 (e.g. rot1 of pure turns,
     0 by convention in both the truth and the odometry) are not used in the fit.
     Three rounds: refit on the kept groups, re-judge all used groups against the refit.
  7. The final non-negative fit on the kept groups.

The non-negative least squares of steps 5-7 is ``nonnegative.fit_nonnegative`` (optax).

Shapes: S samples, G groups, F features (3 for motion, 2 for observations).
"""
from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxslam.geometry import wrap_angle
from jaxslam.motion import nearest_decomposition
from jaxslam.nonnegative import fit_nonnegative
from jaxslam.types import Params

GROUP_ROUNDS = 3  # fit / re-judge rounds of the group outlier rule (step 6)
TINY = 1e-12  # floor of a fitted std before its log
MAD_TO_STD = 1.4826  # 1 / Phi^-1(3/4): MAD of a Gaussian times this is its std


class GroupStats(NamedTuple):
    """Per-group statistics.

    Attributes:
      features: (G, F) mean features of the kept samples of each group.
      std: (G,) maximum-likelihood std of the kept samples (0 for empty groups).
      mean: (G,) mean error of the kept samples (reported; 0 is assumed unless estimated).
      count: (G,) kept samples.
      removed: (G,) samples removed as outliers.
    """

    features: jnp.ndarray
    std: jnp.ndarray
    mean: jnp.ndarray
    count: jnp.ndarray
    removed: jnp.ndarray


class NoiseFit(NamedTuple):
    """One error component's fit.

    Attributes:
      coefficients: (F,) non-negative std coefficients, e.g. (trans, rot, const).
      groups: ``GroupStats`` of the G groups.
      used: (G,) bool, groups with at least ``min_count`` samples.
      kept: (G,) bool, used groups that survived the group outlier rule (the final fit's).
    """

    coefficients: jnp.ndarray
    groups: GroupStats
    used: jnp.ndarray
    kept: jnp.ndarray


class MotionNoiseFit(NamedTuple):
    """Fits of the three motion error components; coefficients as ``Params`` rows."""

    rot1: NoiseFit
    trans: NoiseFit
    rot2: NoiseFit


class ObservationNoiseFit(NamedTuple):
    """Fits of range and bearing errors; coefficients (distance, const) as ``Params``."""

    range: NoiseFit
    bearing: NoiseFit


# ---------------------------------------------------------------------------------------------
# Grouping and per-group maximum likelihood


def quantile_bins(values, num_bins: int, valid=None):
    """Group index (S,) in [0, num_bins) of each value (S,) by quantile bins of the valid ones.

    Ties (many equal values, e.g. |rot| = 0 on straight moves) can leave bins empty.
    """
    valid = jnp.ones(values.shape, bool) if valid is None else valid
    probabilities = jnp.linspace(0.0, 1.0, num_bins + 1)[1:-1]
    edges = jnp.nanquantile(jnp.where(valid, values, jnp.nan), probabilities)
    return jnp.clip(jnp.searchsorted(edges, values, side="right"), 0, num_bins - 1)


def grid_bins(first, second, num_first: int, num_second: int, valid=None):
    """Group index (S,) of an ``num_first`` x ``num_second`` grid of quantile bins."""
    return (quantile_bins(first, num_first, valid) * num_second
            + quantile_bins(second, num_second, valid))


def _segment_median(values, group, num_groups):
    """Median (G,) of ``values`` (S,) per group; a group index of G drops the sample."""
    order = jnp.lexsort((values, group))
    sorted_values = values[order]
    count = jax.ops.segment_sum(jnp.ones_like(values), group, num_groups + 1)[:num_groups]
    count = count.astype(jnp.int32)
    start = jnp.cumsum(count) - count
    last = values.shape[0] - 1
    low = jnp.clip(start + (count - 1) // 2, 0, last)
    high = jnp.clip(start + count // 2, 0, last)
    return jnp.where(count > 0, 0.5 * (sorted_values[low] + sorted_values[high]), 0.0)


@functools.partial(jax.jit, static_argnames=("num_groups", "estimate_mean"))
def group_stats(features, errors, group, valid, num_groups: int, estimate_mean: bool = False,
                sample_threshold=5.0) -> GroupStats:
    """Per-group ML std after removing sample outliers (module docstring, steps 2 and 3).

    Args:
      features: (S, F); errors: (S,); group: (S,) int in [0, G); valid: (S,) bool.
      sample_threshold: robust stds beyond which a sample is an outlier (inf keeps all).
    """
    group = jnp.where(valid, group, num_groups)
    centre = (_segment_median(errors, group, num_groups) if estimate_mean
              else jnp.zeros(num_groups, errors.dtype))
    centre_of = jnp.append(centre, 0.0)[group]
    deviation = jnp.abs(errors - centre_of)
    robust_std = MAD_TO_STD * _segment_median(deviation, group, num_groups)
    keep = valid & (deviation <= _limit(sample_threshold, jnp.append(robust_std, 0.0)[group]))
    kept_group = jnp.where(keep, group, num_groups)

    def total(values):
        return jax.ops.segment_sum(values, kept_group, num_groups + 1)[:num_groups]

    count = total(jnp.ones_like(errors))
    safe = jnp.maximum(count, 1.0)
    mean = total(errors) / safe if estimate_mean else jnp.zeros(num_groups, errors.dtype)
    residual = errors - jnp.append(mean, 0.0)[kept_group]
    variance = total(residual**2) / safe
    group_features = jax.vmap(total, in_axes=1, out_axes=1)(features) / safe[:, None]
    removed = jax.ops.segment_sum((valid & ~keep).astype(jnp.int32), group,
                                  num_groups + 1)[:num_groups]
    return GroupStats(group_features, jnp.sqrt(variance), jnp.where(count > 0, mean, 0.0),
                      count.astype(jnp.int32), removed)


def _robust_keep(score, usable, threshold, floor=0.0):
    """MAD rule: keep usable entries with |score - median| <= max(threshold * 1.4826 * MAD,
    floor)."""
    masked = jnp.where(usable, score, jnp.nan)
    median = jnp.nanmedian(masked)
    spread = MAD_TO_STD * jnp.nanmedian(jnp.abs(masked - median))
    return usable & (jnp.abs(score - median) <= jnp.maximum(_limit(threshold, spread), floor))


def _limit(threshold, spread):
    """threshold * spread, with inf * 0 = inf (an infinite threshold keeps everything)."""
    return jnp.where(jnp.isinf(threshold), jnp.inf, threshold * spread)


@functools.partial(jax.jit, static_argnames=("num_groups", "estimate_mean", "num_steps"))
def _fit_noise(features, errors, group, valid, num_groups, estimate_mean, sample_threshold,
               group_threshold, min_group_ratio, min_count, num_steps):
    stats = group_stats(features, errors, group, valid, num_groups, estimate_mean,
                        sample_threshold)
    count = stats.count.astype(errors.dtype)
    used = stats.count >= min_count
    safe_std = jnp.where(stats.std > 0.0, stats.std, 1.0)

    def refine(kept, _):
        coefficients = fit_nonnegative(stats.features, stats.std, jnp.where(kept, count, 0.0),
                                       num_steps)
        fitted = jnp.maximum(stats.features @ coefficients, TINY)
        score = jnp.log(safe_std) - jnp.log(fitted)
        new_kept = _robust_keep(score, used & (stats.std > 0.0), group_threshold,
                                jnp.log(min_group_ratio))
        return jnp.where(jnp.any(new_kept), new_kept, used), None

    # The first fit sees the outlier groups and is pulled towards them, so good groups can
    # look bad against it: re-judge every used group against the refit, a few times.
    kept, _ = jax.lax.scan(refine, used, None, GROUP_ROUNDS)
    final = fit_nonnegative(stats.features, stats.std, jnp.where(kept, count, 0.0), num_steps)
    return NoiseFit(final, stats, used, kept)


def fit_noise(features, errors, group, num_groups: int, valid=None, *,
              estimate_mean: bool = False, sample_threshold: float = 5.0,
              group_threshold: float = 4.0, min_group_ratio: float = 2.0,
              min_count: int = 10, num_steps: int = 3000) -> NoiseFit:
    """Fit std = features . c, c >= 0, for one error component (module docstring, 1-7).

    Args:
      features: (S, F) per-sample features, e.g. (|trans|, |rot|, 1).
      errors: (S,) true - measured (angles already wrapped).
      group: (S,) int group index in [0, num_groups).
      num_groups: G.
      valid: (S,) bool mask of real samples (default all).
      estimate_mean: ML with an estimated mean instead of the known zero mean.
      sample_threshold / group_threshold: MAD-rule thresholds (inf disables).
      min_group_ratio: a group is an outlier only if its std is also off the fit by more
        than this factor (guards the MAD rule when the groups are precise and the linear
        model only approximate; 1 disables the guard).
      min_count: groups with fewer kept samples are dropped.
    """
    features, errors = jnp.asarray(features), jnp.asarray(errors)
    if features.ndim != 2 or errors.shape != features.shape[:1]:
        raise ValueError(f"fit_noise expects features (S, F) and errors (S,); got "
                         f"{features.shape} and {errors.shape}")
    group = jnp.asarray(group)
    if group.shape != errors.shape or not jnp.issubdtype(group.dtype, jnp.integer):
        raise ValueError(f"fit_noise expects an integer group index of shape {errors.shape}; "
                         f"got {group.dtype} {group.shape}")
    valid = jnp.ones(errors.shape, bool) if valid is None else jnp.asarray(valid, bool)
    if valid.shape != errors.shape:
        raise ValueError(f"fit_noise valid must have shape {errors.shape}; got {valid.shape}")
    if num_groups < 1 or min_count < 1:
        raise ValueError(f"fit_noise num_groups={num_groups}, min_count={min_count}; "
                         "expected both >= 1")
    _check_finite("features", features, valid[:, None])
    _check_finite("errors", errors, valid)
    if int(jnp.sum(valid)) < features.shape[1] * min_count:
        raise ValueError(f"fit_noise got {int(jnp.sum(valid))} valid samples; expected at "
                         f"least {features.shape[1] * min_count} (F * min_count) to fit "
                         f"{features.shape[1]} coefficients")
    if min_group_ratio < 1.0:
        raise ValueError(f"fit_noise min_group_ratio={min_group_ratio}; expected >= 1")
    return _fit_noise(features, errors, group, valid, num_groups, estimate_mean,
                      sample_threshold, group_threshold, min_group_ratio, min_count, num_steps)


def _check_finite(name, values, valid):
    if isinstance(values, jax.core.Tracer):
        return
    bad = ~np.isfinite(np.asarray(values)) & np.asarray(valid)
    if bad.any():
        raise ValueError(f"{name} has {int(bad.sum())} non-finite valid entries; expected "
                         "finite numbers (mask bad samples with valid=False)")


# ---------------------------------------------------------------------------------------------
# Motion and observation front ends


def _check_pairs(name, true, measured, width, valid):
    """(true, measured, valid) as JAX arrays after the shape and finiteness checks."""
    true, measured = jnp.asarray(true), jnp.asarray(measured)
    if true.ndim != 2 or true.shape[1] != width or true.shape != measured.shape:
        raise ValueError(f"{name} expects true and measured arrays of shape (S, {width}); got "
                         f"{true.shape} and {measured.shape}")
    valid = jnp.ones(true.shape[:1], bool) if valid is None else jnp.asarray(valid, bool)
    _check_finite("true", true, valid[:, None])
    _check_finite("measured", measured, valid[:, None])
    return true, measured, valid


def motion_samples(true_moves, measured_moves):
    """Errors (S, 3) = true - measured (rotations wrapped) and features (3, S, 3).

    Each true move is first written as its decomposition nearest the measured one
    (``motion.nearest_decomposition``): a true move that went a centimetre backwards while
    the measured one crept forwards is an error of a few centimetres, not of pi in rot1 and
    rot2 (``odometry_from_poses`` always writes trans >= 0).

    features[i] are the Eq. (1) regressors of component i at the measured move:
    rot1 (|trans|, |rot1|, 1); trans (|trans|, |rot1| + |rot2|, 1); rot2 (|trans|, |rot2|, 1).
    """
    errors = nearest_decomposition(true_moves, measured_moves) - measured_moves
    errors = errors.at[:, 0].set(wrap_angle(errors[:, 0])).at[:, 2].set(wrap_angle(errors[:, 2]))
    abs_rot1, abs_trans, abs_rot2 = (jnp.abs(measured_moves[:, i]) for i in range(3))
    ones = jnp.ones_like(abs_trans)
    features = jnp.stack([
        jnp.stack([abs_trans, abs_rot1, ones], -1),
        jnp.stack([abs_trans, abs_rot1 + abs_rot2, ones], -1),
        jnp.stack([abs_trans, abs_rot2, ones], -1)])
    return errors, features


@functools.partial(jax.jit, static_argnames=("trans_bins", "rot_bins"))
def _motion_groups(true_moves, measured_moves, valid, trans_bins, rot_bins):
    """Errors (S, 3), features (3, S, 3) and grid group indices (3, S) of each component."""
    errors, features = motion_samples(true_moves, measured_moves)
    groups = jax.vmap(lambda f: grid_bins(f[:, 0], f[:, 1], trans_bins, rot_bins, valid))(
        features)
    return errors, features, groups


def fit_motion_noise(true_moves, measured_moves, valid=None, *, trans_bins: int = 8,
                     rot_bins: int = 8, **kwargs) -> MotionNoiseFit:
    """Table 1 from S move pairs (rot1, trans, rot2), each (S, 3).

    Each component is grouped on a ``trans_bins`` x ``rot_bins`` grid of quantile bins of its
    own (|trans|, |rot|) features; ``kwargs`` go to ``fit_noise``.
    """
    true_moves, measured_moves, valid = _check_pairs("fit_motion_noise", true_moves,
                                                     measured_moves, 3, valid)
    errors, features, groups = _motion_groups(true_moves, measured_moves, valid, trans_bins,
                                              rot_bins)
    fits = [fit_noise(features[i], errors[:, i], groups[i], trans_bins * rot_bins, valid,
                      **kwargs) for i in range(3)]  # the three Eq. (1) components
    return MotionNoiseFit(*fits)


def fit_observation_noise(true_z, measured_z, valid=None, *, distance_bins: int = 12,
                          **kwargs) -> ObservationNoiseFit:
    """Table 2 from S (range, bearing) pairs, each (S, 2); std against the measured range."""
    true_z, measured_z, valid = _check_pairs("fit_observation_noise", true_z, measured_z, 2,
                                             valid)
    errors, features, group = _observation_groups(true_z, measured_z, valid, distance_bins)
    return ObservationNoiseFit(*(fit_noise(features, errors[:, i], group, distance_bins, valid,
                                           **kwargs) for i in range(2)))


@functools.partial(jax.jit, static_argnames=("distance_bins",))
def _observation_groups(true_z, measured_z, valid, distance_bins):
    """Errors (S, 2), features (S, 2) = (measured range, 1) and distance bins (S,)."""
    errors = jnp.stack([true_z[:, 0] - measured_z[:, 0],
                        wrap_angle(true_z[:, 1] - measured_z[:, 1])], -1)
    features = jnp.stack([measured_z[:, 0], jnp.ones_like(measured_z[:, 0])], -1)
    return errors, features, quantile_bins(measured_z[:, 0], distance_bins, valid)


def with_fitted_noise(params: Params, motion: MotionNoiseFit | None = None,
                      observation: ObservationNoiseFit | None = None) -> Params:
    """``params`` with the fitted coefficients written in (dtype kept), via ``_replace``."""
    updates = {}
    if motion is not None:
        updates.update(rot1_noise=motion.rot1.coefficients, trans_noise=motion.trans.coefficients,
                       rot2_noise=motion.rot2.coefficients)
    if observation is not None:
        updates.update(range_noise=observation.range.coefficients,
                       bearing_noise=observation.bearing.coefficients)
    return params._replace(**{name: jnp.asarray(value, getattr(params, name).dtype)
                              for name, value in updates.items()})
