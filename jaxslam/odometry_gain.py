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

    v_t = s x_t + e_t,   s = sum x v / sum x^2   (least squares through the origin),

with the standard error of the heteroscedasticity-consistent "sandwich" form (White, "A
heteroskedasticity-consistent covariance matrix estimator and a direct test for
heteroskedasticity", Econometrica 1980): se(s)^2 = sum x^2 r^2 / (sum x^2)^2, r = v - s x.
Samples whose residual lies more than ``OUTLIER_MADS`` robust scales (1.4826 times the median
absolute residual) from the fit are left out and the fit repeated (``GUARD_ROUNDS``): a
re-sighting matched to the wrong landmark can bend a smoothed move by metres.

Why not weighted by Eq. (1)'s 1 / sigma_t^2, as the noise is: the gain is the factor by which
the log's accumulated distance and turn are off, so the moves count by their size. Weighted,
the many short straight moves decide it; on UTIAS MRCLAM's commanded-velocity odometry, whose
deficit comes mostly in the moves that turn (a diagnostic against Vicon; docs/results.md,
mrclam), the weighted slope of the true moves on the commanded ones is 1.01 for the
translation where the drive's ratio is 0.89-0.92. (That choice was made after seeing those
Vicon moves.)

The new gain is g s (a generalised EM: the next iteration smooths with the new moves, so s
moves toward 1 as EM converges). A factor is kept only when the data call for it, by BIC for
the one parameter it adds: ((s - 1) / se)^2 > log n, n the samples it was fitted to
(Schwarz, "Estimating the dimension of a model", 1978); else s = 1, so a log whose odometry
has no systematic error keeps its gains. One iteration moves a gain by at most ``MAX_STEP``
(an association that lost the map can propose any slope), and no gain leaves
``GAIN_LIMITS`` (odometry more than a factor 2 off is broken, not miscalibrated).

The smoothed moves are drawn toward the measured ones by the smoother's motion factors, so
one fit's s is biased toward 1. EM often returns the settings after its first M-step, so
each M-step repeats the fit with the association fixed (``self_calibration._fit_gain``):
smooth with the new gains, fit again, up to ``GAIN_ROUNDS`` fits or until the gains stop
moving (``GAIN_TOL``), each round's factor applied untested; BIC then tests the total move
of each gain (``significant_gains``). The re-smoothings cost the smoother's time, no filter
run.

Shapes: T moves.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

OUTLIER_MADS = 5.0  # residuals farther than this many robust scales are left out
GUARD_ROUNDS = 3  # fits, each leaving out the previous fit's outliers
MAD_TO_STD = 1.4826  # the MAD of a Gaussian times this is its std
MAX_STEP = 1.2  # most one iteration moves a gain (factor either way)
GAIN_LIMITS = (0.5, 2.0)  # no gain leaves these
MIN_SAMPLES = 20  # fewer usable samples of a component: no fit
GAIN_ROUNDS = 4  # fits of the gains per M-step, each followed by a re-smoothing
GAIN_TOL = 0.002  # the rounds stop once no gain moved by more than this (relative)


class SlopeFit(NamedTuple):
    """One component's factor s = v / x by least squares through the origin."""

    factor: float  # s
    standard_error: float  # se(s), the sandwich form
    samples: int  # n, the samples of the last fit (outliers left out)
    kept: bool  # BIC kept s (else the factor applied is 1)


class GainFit(NamedTuple):
    """The M-step's gain update: translation and rotation fits, and the new gains."""

    translation: SlopeFit
    rotation: SlopeFit
    gain: tuple[float, float]  # the new (g_t, g_r): the old gains times the kept factors
    change: float  # the largest relative move of a gain, |new / old - 1|


def drive_slope(measured, smoothed) -> SlopeFit:
    """The factor s of ``smoothed`` (n,) over ``measured`` (n,) by least squares through the
    origin, outliers left out (module docstring); a factor of 1, never kept, from fewer than
    ``MIN_SAMPLES`` samples with a finite, non-zero measured component and a finite smoothed
    one."""
    measured, smoothed = (np.asarray(a, np.float64).ravel() for a in (measured, smoothed))
    usable = np.isfinite(measured) & np.isfinite(smoothed) & (measured != 0.0)
    x, y = measured[usable], smoothed[usable]
    keep = np.ones(len(x), bool)
    for _ in range(GUARD_ROUNDS):
        if keep.sum() < MIN_SAMPLES:
            return SlopeFit(1.0, float("inf"), int(keep.sum()), False)
        slope = float(x[keep] @ y[keep] / (x[keep] @ x[keep]))
        residual = y - slope * x
        scale = MAD_TO_STD * float(np.median(np.abs(residual[keep])))
        if not scale > 0.0:  # an exact fit: every kept residual zero
            break
        keep = np.abs(residual) <= OUTLIER_MADS * scale
    n = int(keep.sum())
    if n < MIN_SAMPLES:
        return SlopeFit(1.0, float("inf"), n, False)
    x, y = x[keep], y[keep]
    information = float(x @ x)
    slope = float(x @ y / information)
    error = float(np.sqrt(np.sum(x**2 * (y - slope * x) ** 2)) / information)
    kept = slope != 1.0 if error == 0.0 else ((slope - 1.0) / error) ** 2 > np.log(n)
    return SlopeFit(slope, error, n, bool(kept))


def gain_update(gain, true_moves, measured_moves, test: bool = True) -> GainFit:
    """The M-step's new ``odometry_gain`` (module docstring).

    Args:
      gain: (2,) the gains (g_t, g_r) the measured moves were made with.
      true_moves: (T, 3) smoothed moves (rot1, trans, rot2), each in the decomposition
        nearest its measured move (``calibrate.motion_samples``); non-finite rows are left
        out. measured_moves: (T, 3) the moves u_t.
      test: apply a factor only where BIC keeps it; False: wherever it could be fitted
        (the rounds of ``self_calibration._fit_gain``, which test the total with
        ``significant_gains``).
    """
    true_moves, measured_moves = (np.asarray(a, np.float64) for a in (true_moves, measured_moves))
    translation = drive_slope(measured_moves[:, 1], true_moves[:, 1])
    rotation = drive_slope(measured_moves[:, 0] + measured_moves[:, 2],
                           true_moves[:, 0] + true_moves[:, 2])
    old = np.asarray(gain, np.float64)
    factor = np.array([np.clip(fit.factor, 1.0 / MAX_STEP, MAX_STEP)
                       if (fit.kept or not test and np.isfinite(fit.standard_error)) else 1.0
                       for fit in (translation, rotation)])
    new = np.clip(old * factor, *GAIN_LIMITS)
    return GainFit(translation, rotation, (float(new[0]), float(new[1])),
                   float(np.max(np.abs(new / old - 1.0))))


def significant_gains(given, fitted, last: GainFit) -> tuple[float, float]:
    """``fitted`` (2,) where BIC keeps its move from ``given`` (2,), else ``given``, per
    component: ((fitted / given - 1) / se)^2 > log n with the standard error and samples of
    the last fit ``last`` (at the fitted gains the slope's relative error is the gain's)."""
    chosen = []
    for old, new, fit in zip(np.asarray(given, np.float64), np.asarray(fitted, np.float64),
                             (last.translation, last.rotation)):
        move = new / old - 1.0
        keep = fit.samples >= MIN_SAMPLES and (
            move != 0.0 if fit.standard_error == 0.0
            else (move / fit.standard_error) ** 2 > np.log(fit.samples))
        chosen.append(float(new if keep else old))
    return chosen[0], chosen[1]
