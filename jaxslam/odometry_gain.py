"""The odometry's systematic error fitted from a smoothed solution: ``params.odometry_gain``.

Odometry that reads every move too long, or every turn too wide, errs in a way Eq. (1)'s
zero-mean noise cannot describe (Borenstein and Feng, "Measurement and correction of
systematic odometry errors in mobile robots", IEEE Transactions on Robotics and Automation,
1996): the error adds up along the drive. The filter's moves are the readings times the gains
g = (g_t, g_r) (``motion.control_to_odometry``), and like every other setting the gains come
from the log alone: each EM iteration of ``self_calibration.calibrate_params`` smooths the
log with the current moves u_t = g (x) reading_t and asks by what factor s the smoothed moves
v_t differ from them, the translation (x_t = trans) and the heading change (x_t = rot1 + rot2)
apart:

    v_t = s x_t + e_t,   s = sum x v / sum x^2   (least squares through the origin).

Its standard error is the jackknife's over blocks of consecutive moves (Kunsch, "The
jackknife and the bootstrap for general stationary observations", Annals of Statistics
1989): the slope s_(b) refitted without block b, se(s)^2 = (B - 1) / B sum_b (s_(b) -
mean s_(.))^2, over B blocks of about sqrt(n) moves. Blocks, because the smoother spreads one
correction over the moves between sightings, so neighbouring residuals are correlated. On the
draws of ``tests/test_odometry_gain.py`` (a tenth of the moves ten times wider) it states the
slope's spread within 10 % (0.0114 against 0.0126); with 5 % one-sided outliers of 20 stds
the spread doubles and the stated error does not follow (0.012 against 0.023).

Samples whose residual, in units of its Eq. (1) std, lies more than ``OUTLIER_MADS`` robust
scales (1.4826 times the median absolute standardised residual) from the fit are left out
and the fit repeated (``GUARD_ROUNDS`` passes): a re-sighting matched to the wrong landmark
can bend a smoothed move by metres, while a wide turn's residual is large only in metres.

Why the fit is not weighted by Eq. (1)'s 1 / sigma_t^2, as the noise is: the gain is the
factor by which the log's accumulated distance and turn are off, so the moves count by their
size. Weighted, the many short straight moves decide it; on UTIAS MRCLAM's commanded-velocity
odometry, whose deficit comes mostly in the moves that turn (a diagnostic against Vicon;
docs/results.md, mrclam, "Twenty-sixth session"), the weighted slope of the true moves on the
commanded ones is 1.01 for the translation where the drive's ratio is 0.89-0.92. (That choice
was made after seeing those Vicon moves.) The slope is unbiased under the filter's own model,
in which the true move scatters around the measured one (Eq. (1)); a log whose noise lies in
the reading instead biases it toward 0 by about sum sigma^2 / sum x^2 (for the rotation of a
nearly straight drive, the noise's share of the turns).

Each M-step repeats the fit with the association fixed (``self_calibration._fit_gain``):
smooth with the new gains, fit again, up to ``GAIN_ROUNDS`` fits or until the gains stop
moving (``GAIN_TOL``). One fit alone moves a gain only part of the way, as the smoother draws
its moves toward the measured ones: each round's remaining deviation is a fraction lambda of
the last one, the same pull that makes the gains at the rounds' fixed point vary 1 / (1 -
lambda) times as much as one slope does (``contraction``). Then each gain keeps its total
move only where the data call for it, by BIC for the one parameter it adds, ((g / g_0 - 1) /
se)^2 > log n with se = se(s) / (1 - lambda) (Schwarz, "Estimating the dimension of a
model", 1978; ``significant_gains``), else the given gain: a log whose odometry has no
systematic error keeps its gains in most cases. One M-step moves a gain by at most a factor
``MAX_STEP`` (an association that lost the map can propose any slope), and a fitted gain
never leaves ``GAIN_LIMITS`` (odometry more than a factor 2 off is broken, not
miscalibrated). The re-smoothings cost the smoother's time, no filter run.

Shapes: T moves.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from jaxslam.calibrate import MAD_TO_STD

OUTLIER_MADS = 5.0  # standardised residuals farther than this many robust scales: left out
GUARD_ROUNDS = 3  # guard passes; each refits with the previous pass's outliers left out
MAX_STEP = 1.2  # most one M-step moves a gain (factor either way)
GAIN_LIMITS = (0.5, 2.0)  # no fitted gain leaves these
MAX_CONTRACTION = 0.9  # most the rounds' lambda is taken as (se inflated at most 10x)
MIN_SAMPLES = 20  # fewer usable samples of a component: no fit
GAIN_ROUNDS = 4  # fits of the gains per M-step, each followed by a re-smoothing
GAIN_TOL = 0.002  # the rounds stop once no gain moved by more than this (relative)


class SlopeFit(NamedTuple):
    """One component's factor s = v / x by least squares through the origin."""

    factor: float  # s
    standard_error: float  # se(s), the delete-a-block jackknife's
    samples: int  # n, the samples of the final fit (outliers left out)


class GainFit(NamedTuple):
    """One round's gain update: translation and rotation fits, and the new gains."""

    translation: SlopeFit
    rotation: SlopeFit
    gain: tuple[float, float]  # the old gains times the fitted factors (each within MAX_STEP)
    change: float  # the largest relative move of a gain, |new / old - 1|


def _block_sums(values, samples: int) -> np.ndarray:
    """Sums (B,) of ``values`` (n,) over consecutive blocks of round(sqrt(n)) samples."""
    size = max(1, int(round(np.sqrt(samples))))
    return np.add.reduceat(values, np.arange(0, len(values), size))


def _jackknife_error(x, y) -> float:
    """The delete-a-block jackknife standard error of sum x y / sum x^2 (module docstring)."""
    sxy, sxx = _block_sums(x * y, len(x)), _block_sums(x * x, len(x))
    rest = sxx.sum() - sxx
    if len(sxx) < 2 or np.any(rest <= 0.0):
        return float("inf")
    slopes = (sxy.sum() - sxy) / rest
    return float(np.sqrt((len(slopes) - 1) / len(slopes)
                         * np.sum((slopes - slopes.mean()) ** 2)))


def drive_slope(measured, smoothed, std=None) -> SlopeFit:
    """The factor s of ``smoothed`` (n,) over ``measured`` (n,), both in time order, by
    least squares through the origin, outliers of the residual over ``std`` (n,; the Eq. (1)
    std of each move, default 1) left out, with its block jackknife standard error (module
    docstring). A factor of 1 and an infinite error from fewer than ``MIN_SAMPLES`` samples
    with a finite, non-zero measured component, a finite smoothed one and a positive std."""
    measured, smoothed = (np.asarray(a, np.float64).ravel() for a in (measured, smoothed))
    std = (np.ones_like(measured) if std is None
           else np.asarray(std, np.float64).ravel())
    usable = (np.isfinite(measured) & np.isfinite(smoothed) & (measured != 0.0)
              & np.isfinite(std) & (std > 0.0))
    x, y, sigma = measured[usable], smoothed[usable], std[usable]
    keep = np.ones(len(x), bool)
    for _ in range(GUARD_ROUNDS):
        if keep.sum() < MIN_SAMPLES:
            return SlopeFit(1.0, float("inf"), int(keep.sum()))
        slope = float(x[keep] @ y[keep] / (x[keep] @ x[keep]))
        white = (y - slope * x) / sigma
        scale = MAD_TO_STD * float(np.median(np.abs(white[keep])))
        if not scale > 0.0:  # an exact fit: every kept residual zero
            break
        keep = np.abs(white) <= OUTLIER_MADS * scale
    n = int(keep.sum())
    if n < MIN_SAMPLES:
        return SlopeFit(1.0, float("inf"), n)
    x, y = x[keep], y[keep]
    information = float(x @ x)
    slope = float(x @ y / information)
    return SlopeFit(slope, _jackknife_error(x, y), n)


def gain_update(gain, true_moves, measured_moves, move_std) -> GainFit:
    """One round's fit of ``odometry_gain`` (module docstring): the old gains times each
    fitted factor, the factor held within ``MAX_STEP`` and the gain within ``GAIN_LIMITS``
    (a component that could not be fitted keeps its gain).

    Args:
      gain: (2,) the gains (g_t, g_r) the measured moves were made with.
      true_moves: (T, 3) smoothed moves (rot1, trans, rot2), each in the decomposition
        nearest its measured move (``calibrate.motion_samples``); non-finite rows are left
        out. measured_moves: (T, 3) the moves u_t. move_std: (T, 3) their Eq. (1) stds (the
        guard's unit; the heading change's is the root sum of squares of rot1's and rot2's).
    """
    true_moves, measured_moves, move_std = (np.asarray(a, np.float64) for a in
                                            (true_moves, measured_moves, move_std))
    translation = drive_slope(measured_moves[:, 1], true_moves[:, 1], move_std[:, 1])
    rotation = drive_slope(measured_moves[:, 0] + measured_moves[:, 2],
                           true_moves[:, 0] + true_moves[:, 2],
                           np.hypot(move_std[:, 0], move_std[:, 2]))
    old = np.asarray(gain, np.float64)
    factor = np.array([np.clip(fit.factor, 1.0 / MAX_STEP, MAX_STEP) for fit in
                       (translation, rotation)])
    new = np.where(factor != 1.0, np.clip(old * factor, *GAIN_LIMITS), old)
    return GainFit(translation, rotation, (float(new[0]), float(new[1])),
                   float(np.max(np.abs(new / old - 1.0))))


def contraction(factors) -> np.ndarray:
    """(2,) lambda of each gain from the rounds' factors (R, 2): the ratio of the last two
    deviations |s - 1| (module docstring), within [0, ``MAX_CONTRACTION``]; 0 from fewer
    than two rounds (no pull measured) or a first deviation of 0."""
    factors = np.asarray(factors, np.float64).reshape(-1, 2)
    if len(factors) < 2:
        return np.zeros(2)
    before, after = np.abs(factors[-2] - 1.0), np.abs(factors[-1] - 1.0)
    ratio = np.divide(after, before, out=np.zeros(2), where=before > 0.0)
    return np.clip(ratio, 0.0, MAX_CONTRACTION)


def significant_gains(given, fitted, last: GainFit, pull=(0.0, 0.0)) -> tuple[float, float]:
    """``fitted`` (2,) where BIC keeps its move from ``given`` (2,), else ``given``, per
    component: ((fitted / given - 1) / se)^2 > log n, se the standard error of the last
    round's slope (``last``) over 1 - lambda (``pull``, from ``contraction``), n its
    samples; a component with fewer than ``MIN_SAMPLES`` samples keeps ``given``."""
    chosen = []
    for old, new, fit, lam in zip(np.asarray(given, np.float64), np.asarray(fitted, np.float64),
                                  (last.translation, last.rotation), np.asarray(pull)):
        move = new / old - 1.0
        error = fit.standard_error / (1.0 - lam)
        keep = fit.samples >= MIN_SAMPLES and np.isfinite(error) and (
            move != 0.0 if error == 0.0 else (move / error) ** 2 > np.log(fit.samples))
        chosen.append(float(new if keep else old))
    return chosen[0], chosen[1]
