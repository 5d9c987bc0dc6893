"""Is one filter run's log evidence significantly higher than another's on the same log?

A particle filter's log marginal likelihood estimate is a sum over the log's steps of
one-step predictive log scores, ``Trace.log_evidence`` (T,):

    log p(z_{1:T} | theta) ~= sum_t e_t(theta).

Two settings theta_c (candidate) and theta_i (incumbent) run on one log give the paired
differences d_t = e_t(theta_c) - e_t(theta_i). Their sum D is the difference of the two
estimates; whether it says more than the runs' chance is the question of Diebold and Mariano,
"Comparing predictive accuracy" (Journal of Business and Economic Statistics 1995), asked of
log scores as in Amisano and Giacomini, "Comparing density forecasts via weighted likelihood
ratio tests" (JBES 2007): t = D / se(D), with se(D) robust to the serial correlation of d_t.
Here se(D) comes from batch means: the T steps are cut into B contiguous blocks with sums
S_b (sum_b S_b = D), and

    se(D)^2 = B / (B - 1) sum_b (S_b - D / B)^2,

which is T var(d) for independent d_t and stays right for correlation shorter than a block.
The candidate is significantly better when t exceeds Student's t quantile with B - 1
degrees of freedom at the one-sided level.

Why this matters for the calibration: on a log where the robot stands still or creeps, a
single step can score -1e5 nats in one run and not in another (the observation proposal
drew every particle behind the start, which the forward-only motion density rejects:
``motion.motion_log_density``). Such a step decides a plain comparison of sums. In the test
it sits in one block: with one outlying block of size A, se(D) is about A and t about 1,
so it decides nothing. A gain spread over the log does, unless one of the two runs has
such a step: then the gain must exceed about 0.7 A (t = 1 + G / A against the quantile,
1.73 at 19 degrees of freedom), so a run with one outlying step is never replaced by a
cleaner one, nor replaces it.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
from scipy import stats

NUM_BLOCKS = 20
LEVEL = 0.05


class ScoreGain(NamedTuple):
    """The candidate's log-evidence gain over the incumbent.

    gain: D, the summed differences. std_error: se(D) by batch means (NaN when it cannot be
    formed: fewer than 2 blocks, or a non-finite step). t: D / se(D) (+-inf when se is 0 and
    D is not; 0 when both are). blocks: B used.
    """

    gain: float
    std_error: float
    t: float
    blocks: int


def _evidence(name: str, values) -> np.ndarray:
    values = np.asarray(values, np.float64)
    if values.ndim != 1 or values.size == 0:
        raise ValueError(f"{name} must be a non-empty (T,) per-step log evidence; got shape "
                         f"{values.shape}")
    return values


def score_gain(candidate, incumbent, num_blocks: int = NUM_BLOCKS) -> ScoreGain:
    """``ScoreGain`` of ``candidate`` (T,) over ``incumbent`` (T,), each a run's per-step
    log evidence on the same log (module docstring). B = min(num_blocks, T) contiguous
    blocks of T // B or T // B + 1 steps (``numpy.array_split``)."""
    candidate = _evidence("candidate", candidate)
    incumbent = _evidence("incumbent", incumbent)
    if candidate.shape != incumbent.shape:
        raise ValueError(f"candidate and incumbent must cover the same steps; got "
                         f"{candidate.shape} and {incumbent.shape}")
    if num_blocks < 2:
        raise ValueError(f"num_blocks must be >= 2; got {num_blocks}")
    with np.errstate(invalid="ignore"):  # inf - inf: a broken run on both sides
        difference = candidate - incumbent
    gain = float(np.sum(difference))
    blocks = min(num_blocks, difference.size)
    if blocks < 2 or not np.all(np.isfinite(difference)):
        return ScoreGain(gain, float("nan"), float("nan"), blocks)
    sums = np.array([block.sum() for block in np.array_split(difference, blocks)])
    std_error = float(np.sqrt(blocks / (blocks - 1) * np.sum((sums - gain / blocks) ** 2)))
    if std_error > 0:
        t = gain / std_error
    else:
        t = 0.0 if gain == 0 else float(np.copysign(np.inf, gain))
    return ScoreGain(gain, std_error, float(t), blocks)


def significantly_better(candidate, incumbent, level: float = LEVEL,
                         num_blocks: int = NUM_BLOCKS) -> bool:
    """Whether ``candidate``'s per-step log evidence (T,) beats ``incumbent``'s (T,) by the
    one-sided test at ``level`` (module docstring). When a run has a non-finite step (a
    broken run) the candidate is better only if the incumbent alone has one; a log too
    short for two blocks compares the sums."""
    if not 0.0 < level < 1.0:
        raise ValueError(f"level must be in (0, 1); got {level}")
    found = score_gain(candidate, incumbent, num_blocks)
    candidate_ok = bool(np.all(np.isfinite(np.asarray(candidate, np.float64))))
    incumbent_ok = bool(np.all(np.isfinite(np.asarray(incumbent, np.float64))))
    if not (candidate_ok and incumbent_ok):
        return candidate_ok and not incumbent_ok
    if found.blocks < 2:
        return found.gain > 0
    return found.t > float(stats.t.ppf(1.0 - level, found.blocks - 1))
