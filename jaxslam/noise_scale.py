"""Noise scales chosen by the particle filter's marginal likelihood, after EM.

EM (``self_calibration``) fits each noise group to the residuals of the smoother on the best
particle's data association. When that association is poor (a tree split into several
landmarks, a loop that never closes), the smoothed path bends to fit each piece, its residuals
are small, the fitted noise is too small, and the next E-step run with it splits the trees
again: the loop is self-reinforcing, and on real logs (MRCLAM, Victoria Park) it ends with a
noise several times narrower than what the filter needs.

The filter's own estimate of the log marginal likelihood (``Trace.log_evidence`` summed: per
step, the log of the weighted mean over particles of each particle's incremental weight, its
observation likelihood with the proposal's correction, and for an observation that starts a
landmark the new-landmark credit of ``ekf.unexplained_log_likelihood``)

    log p(z_{1:T} | u_{1:T}, theta) ~= sum_t log sum_i w_{t-1}^i w_t^i(increment)

does not condition on one association: it averages over the histories the particles hold.
Maximising it over static parameters is the particle filter's maximum-likelihood estimate
(Kantas, Doucet, Singh, Maciejowski and Chopin, "On particle methods for parameter estimation
in state-space models", Statistical Science 2015). Here it only picks two multipliers of the
EM result:

    theta(s_m, s_o): Eq. (1)'s coefficients (Geiser et al., "Practical Implementation of
    FastSLAM for Forestry Robot", ICAROB 2023) of rot1, trans and rot2 times s_m, and with
    them ``association_heading_std`` (a typical heading std of that model); the range
    and bearing coefficients and floors (std = c_d d + c_0, Table 2's form) times s_o.

Coordinate ascent on a grid that contains 1 (EM's own result is always a candidate): first
s_m over ``motion_scales`` with s_o = 1, then s_o over ``observation_scales`` at the chosen
s_m; not a joint maximum. Every candidate that runs uses one key (common random numbers: the
candidates differ only in their settings, so the differences of their log likelihoods are
less noisy than each one), each once (the second stage's s_o = 1 is the first stage's
choice): at most len(motion_scales) + len(observation_scales) - 1 filter runs. Scales below 1
are not searched by default: EM's failure is the shrinking loop above.

Each stage walks its grid outward from 1 (upward through the larger scales, then downward
through the smaller ones) and, with ``stop_at_first_drop``, stops a direction at the first fair
candidate (dropped no birth, finite score; below) that scores lower than the best fair one met
so far on that walk; the candidates it did not use score NaN. For one Gaussian noise group
whose std is multiplied by s, the expected log likelihood -n log s - Q / (2 s^2) (n residuals
of summed squared whitened size Q at s = 1) has one maximum, at s^2 = Q / n, so a drop means
the peak is passed. The particle filter's estimate is noisy and the walk assumes it keeps that
shape; in every stage recorded in docs/results.md (MRCLAM robots 1 and 2, Victoria Park keys 0
and 1) the fair runs' scores rose to one peak and fell after it (runs whose map overflowed need
not: on Victoria Park they did not, and they never stop the walk). A stage whose runs all
overflow runs every candidate, as no run is fair. This saves the runs past the peak: on
MRCLAM's motion x2, observation x1, 3 of the 6 runs.

On a CPU the walk scores two candidates at a time (``workers``, ``default_workers``): when it
needs a candidate, that one and the next of its direction run together, each in its own thread,
on the one compiled filter; while no fair run has been met, the candidate after the one the
walk waits for is certainly needed and starts at once if a thread is free. A filter run of a
log does about one core's useful work (its steps are many small kernels), so on two cores the
pair takes the time of 1.1 runs (MRCLAM) to 1.3 runs (Victoria Park). The walk then reads the
scores in its own order, and a candidate scored ahead of a stop is not used: the choice and the
reported scores are those of the one-at-a-time walk, and only the time changes (a run past the
stop is spent, at little wall-clock cost on two cores).

The new-landmark credit is held fixed. The filter credits an observation that no landmark
explains with the density of a match at the gate under the observation's own noise
(``ekf.unexplained_log_likelihood``), -gate / 2 - log(sigma_r sigma_b) - log 2 pi + offset,
which rises by 2 log(1 / s) when every observation std is multiplied by s. Scored with that
credit, a narrow observation noise wins on any log where many observations start landmarks
(the split-tree case): the narrower the noise, the more it splits, and the more each split
is paid. A new landmark's proper marginal, p(z | new) = integral p(z | m) p(m) dm under a
prior p(m) spread over the sensor's footprint, does not depend on the sensor noise
(when p(m) is much wider than the noise).
So each candidate's ``new_landmark_log_offset`` is raised by 2 log s_o
(``scaled_noise``): every candidate credits a new landmark with EM's own density, and the
scores differ only in how the matched observations and the moves fit. The returned Params
carry that offset, so the filter run after the search is the run that was scored.

A run whose map overflowed is not a fair candidate. An observation no landmark explains is
credited as a new landmark whether or not a free slot takes it; when the map is full its
birth is dropped, the tree stays unmapped, and its next sighting is credited as new again:
the score of such a run counts the same trees over and over, and, broadly, the narrower the
noise, the more trees it splits and the sooner the map fills. On Victoria Park (320 slots,
twice the documented ~150 trees; motion x8) the observation scales x1, 2 and 4 all
overflowed (223 k, 355 k and 199 k births dropped, summed over the 100 particles) and
outscored x8, the only one that did not (log likelihood +70.8 k, +50.4 k and +46.1 k against
+34.9 k). So a stage ranks by likelihood only the candidates whose run dropped no birth
(``best_scale``). When none did, no score in that stage is a fair one:

- The observation stage takes the candidate whose map filled last (the latest first step
  with a dropped birth; ties go to the scale nearest 1, EM's own, then to the grid's order).
  The broader the sensor noise, the fewer observations of one tree fall outside its gate,
  so the map that lasts longest is the one that split the fewest trees. The fill step is a
  noisy sign of that: in five of the six observation stages recorded on Victoria Park on
  2026-12-05 it rose with the scale; in the sixth (after a widened EM start that was not
  kept) x8 filled before x2 and x4 (docs/results.md).
- The motion stage keeps 1 (EM's own estimate). It runs at s_o = 1, so when every one of its
  candidates overflows, the sensor noise is too narrow for this log, which this stage does
  not set; a broader motion noise delays the overflow only by widening every gate with the
  pose uncertainty, so taking it would make the motion noise absorb the sensor's misfit. The
  observation stage that follows has its own overflow test.

The run's warnings then say the map was full. Until 2026-12-05 both stages kept 1 then. That
rule was settled after seeing on Victoria Park the GPS error of the motion scale it kept (x1)
against the one the biased likelihood ranked first (x8), in-sample there. It failed on the
same log once every observation candidate overflowed: x1, whose map filled first, was kept,
and the run ended 101.5 m off (its x8 candidate dropped 6 births, at the step where its map
filled). The present rule uses no ground truth, but it was written after seeing GPS errors
on that log (the split between the stages after a second key's), so its Victoria Park
numbers are in-sample (docs/results.md).
An overflowed run's score never competes, and its fill step is known at the first step that
drops a birth, so a candidate's run stops there (``run_score``; ``filter.scan_filter``'s
``stop_at_dropped_birth``): the rest of it could not change the choice, so only the time
changes (on Victoria Park the candidates
that overflowed dropped their first birth 57-67 % into the log, measured on 2026-12-03).

Shapes: S candidates, T steps, K observations a step.
"""
from __future__ import annotations

import os
from concurrent.futures import Future, ThreadPoolExecutor
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxslam.filter import run_filter
from jaxslam.types import FilterConfig, Observations, Params

# ``association_heading_std`` moves with the motion noise: the calibration sets it to the
# motion model's typical heading std (``self_calibration``), which is linear in the coefficients.
MOTION_FIELDS = ("rot1_noise", "trans_noise", "rot2_noise", "association_heading_std")
OBSERVATION_FIELDS = ("range_noise", "bearing_noise", "range_std_floor", "bearing_std_floor")
DEFAULT_SCALES = (1.0, 2.0, 4.0, 8.0)


class ScaleSearch(NamedTuple):
    """What ``search_noise_scales`` found.

    motion_scale / observation_scale: the chosen multipliers s_m, s_o.
    motion_scales: (S_m,) candidates of the first stage; motion_objective: (S_m,) their log
    marginal likelihoods. observation_scales / observation_objective: the same for the second
    stage (at the chosen s_m). motion_dropped / observation_dropped: (S_m,) / (S_o,) the
    births each candidate's run dropped for want of a free slot (summed over particles and
    steps; ``best_scale``). motion_fill_step / observation_fill_step: (S_m,) / (S_o,) the
    first step (0-based) whose map dropped a birth, T (the log's steps) for a run that never
    did (``RunScore.fill_step``). A candidate the walk did not use (``walk_stage``: not run,
    or run ahead of its stop) has objective NaN, dropped -1 and fill step -1; one stopped at
    its first dropped birth (``run_score``) has objective NaN and the births dropped at that
    step (> 0). The x1 candidate given as ``known`` (EM's own run) is a whole run: its score
    and count are that run's, even when it overflowed.
    """

    motion_scale: float
    observation_scale: float
    motion_scales: np.ndarray
    motion_objective: np.ndarray
    observation_scales: np.ndarray
    observation_objective: np.ndarray
    motion_dropped: np.ndarray
    observation_dropped: np.ndarray
    motion_fill_step: np.ndarray
    observation_fill_step: np.ndarray


def scaled_noise(params: Params, motion_scale, observation_scale) -> Params:
    """``params`` with the motion-noise fields (and ``association_heading_std``) times
    ``motion_scale``, the observation noise fields times ``observation_scale`` = s_o and
    ``new_landmark_log_offset`` plus 2 log s_o, which keeps
    ``ekf.unexplained_log_likelihood`` at every range as it was (module docstring). Scalars
    or (S,) arrays: then every leaf gets a leading S axis, for ``jax.vmap`` over
    candidates."""
    motion_scale = jnp.asarray(motion_scale, params.rot1_noise.dtype)
    observation_scale = jnp.asarray(observation_scale, params.rot1_noise.dtype)
    batch = jnp.broadcast_shapes(motion_scale.shape, observation_scale.shape)

    def times(value, scale):
        value = jnp.asarray(value)
        scale = jnp.broadcast_to(scale, batch).reshape(batch + (1,) * value.ndim)
        return jnp.broadcast_to(value, (1,) * len(batch) + value.shape) * scale

    fields = {name: times(getattr(params, name), motion_scale) for name in MOTION_FIELDS}
    fields.update({name: times(getattr(params, name), observation_scale)
                   for name in OBSERVATION_FIELDS})
    fields["new_landmark_log_offset"] = (
        jnp.asarray(params.new_landmark_log_offset, observation_scale.dtype)
        + 2.0 * jnp.log(jnp.broadcast_to(observation_scale, batch)))
    if batch:
        rest = {name: jnp.broadcast_to(jnp.asarray(value), batch + jnp.shape(value))
                for name, value in params._asdict().items() if name not in fields}
        fields.update(rest)
    return params._replace(**fields)


class RunScore(NamedTuple):
    """A candidate's filter run: log_likelihood, the log marginal likelihood estimate
    (``Trace.log_evidence`` summed); dropped_births, the births it dropped because the map
    was full (``Trace.num_dropped_births`` summed over steps; each is summed over particles).
    A run stopped at its first dropped birth (``run_score``) has log_likelihood NaN (its
    partial sum would compare with nothing) and the births dropped at that step. fill_step,
    the first step (0-based) that dropped a birth, or the log's length T when none did: how
    long the map lasted (``best_scale`` ranks overflowed runs by it).
    """

    log_likelihood: float
    dropped_births: int
    fill_step: int


def score_trace(trace, stopped_at_dropped_birth: bool) -> RunScore:
    """``RunScore`` of a filter run's ``Trace`` (T steps): the summed ``log_evidence``
    (NaN when the run was stopped at a dropped birth and did drop one), the summed
    ``num_dropped_births`` and the first step with a dropped birth (T when none)."""
    per_step = np.asarray(trace.num_dropped_births)
    dropped = int(np.sum(per_step))
    log_likelihood = float(np.sum(np.asarray(trace.log_evidence)))  # as calibrate_params sums
    if stopped_at_dropped_birth and dropped > 0:
        log_likelihood = float("nan")
    full = np.flatnonzero(per_step > 0)
    return RunScore(log_likelihood, dropped, int(full[0]) if full.size else per_step.shape[0])


def run_score(config: FilterConfig, key, params: Params, controls,
              observations: Observations, initial_pose=None,
              stop_at_dropped_birth: bool = True) -> RunScore:
    """The filter's log marginal likelihood of the log under ``params`` with ``key``, and
    the births its run dropped (``RunScore``).

    One ``run_filter(..., record_lineage=True)`` call: the static arguments of the EM runs in
    ``calibrate_params``, so the search reuses their compiled filter (``Params`` and the stop
    flag are dynamic) instead of compiling a vmapped one. On the CPU that is the cheaper
    way: candidates run back to back cost what their runs cost, while one vmapped call over S
    candidates costs about S / 2 runs plus a compile of its own (a 250-step log: 0.65 s a
    run, ~10 s to compile).

    With ``stop_at_dropped_birth`` (default) the run stops after the first step whose map had
    no free slot for a birth: such a run is not a fair candidate (module docstring) whatever
    its remaining steps would score, so they are not run. The choice is the same as with the
    whole run; only the time differs (Victoria Park's overflowing candidates first dropped a
    birth 57-67 % into the log, measured on 2026-12-03).
    """
    _, trace = run_filter(config, key, params, controls, observations, initial_pose,
                          record_lineage=True, stop_at_dropped_birth=stop_at_dropped_birth)
    return score_trace(trace, stop_at_dropped_birth)


def best_scale(scales, objective, dropped=None, fill_step=None) -> float:
    """The scale (S,) of highest finite ``objective`` (S,), the first of ties; 1 (EM's own
    estimate) when no objective is finite (NaN or +-inf everywhere). With ``dropped`` (S,),
    the births each candidate's run dropped (-1: not run), only candidates that dropped none
    compete (module docstring: an overflowed run's score counts unmapped trees again and
    again). When none of them has a finite score: with ``fill_step`` (S,), each run's first
    step that dropped a birth (``RunScore.fill_step``), the overflowed run whose map filled
    last, ties to the scale nearest 1 (in log), then to the first (``latest_fill``);
    without it, or when no run overflowed, 1."""
    scales = np.asarray(scales)
    objective = np.asarray(objective, np.float64)
    competing = np.isfinite(objective) if dropped is None else fair(objective, dropped)
    if np.any(competing):
        return float(scales[int(np.argmax(np.where(competing, objective, -np.inf)))])
    if dropped is None or fill_step is None or not np.any(np.asarray(dropped) > 0):
        return 1.0
    # Rounded: 1/3 and 3 (say) must tie however the logs round.
    return float(scales[latest_fill(dropped, fill_step, np.round(np.abs(np.log(scales)), 12))])


def latest_fill(dropped, fill_step, tie_key=None) -> int:
    """Index of the overflowed run (``dropped`` (S,) > 0) whose map filled last (largest
    ``fill_step`` (S,)); ties go to the smallest ``tie_key`` (S,) (``best_scale``: |log s|,
    the scale nearest EM's own), then to the first; -1 when no run overflowed. The broader a
    noise, the fewer trees it splits and the later its map fills (module docstring). The
    births dropped do not break ties: a stopped run counts those of its fill step, a whole
    run (EM's) those of every step."""
    tie_key = np.zeros(np.shape(dropped)) if tie_key is None else tie_key
    return first_overflowed(dropped, -np.asarray(fill_step), tie_key)


def fair(objective, dropped) -> np.ndarray:
    """(S,) bool: the runs that dropped no birth and scored a finite log likelihood, the ones
    a likelihood may rank (module docstring; ``dropped`` -1 marks a run not made)."""
    return (np.asarray(dropped) == 0) & np.isfinite(np.asarray(objective, np.float64))


def first_overflowed(dropped, *keys) -> int:
    """Index of the overflowed run (``dropped`` (S,) > 0) that sorts first by ``keys`` (each
    (S,), the first the primary one; ties go to the next key, then to the run's order); -1
    when no run overflowed. ``latest_fill`` and EM's ``self_calibration._best_run`` rank
    overflowed runs with it."""
    overflowed = np.flatnonzero(np.asarray(dropped) > 0)
    if overflowed.size == 0:
        return -1
    # lexsort: the last key is the primary one; the stable sort keeps the given order.
    order = np.lexsort([np.asarray(key)[overflowed] for key in reversed(keys)])
    return int(overflowed[order[0]])


def default_workers() -> int:
    """Candidates ``search_noise_scales`` runs at once by default: 2 on a CPU when this process
    may use two or more cores, else 1. One filter run of a log keeps about one core busy
    with useful work (its steps are many small kernels), so two runs in two threads take
    1.1-1.3 runs' time: MRCLAM robot 2 (T 4179, P 100), two candidates back to back 6.9-7.1
    s, the same two in two threads 3.8 s; Victoria Park (T 7230, 320 slots), two whole runs
    29.1 s against 19.2 s; identical scores (docs/results.md, calibration_time). On an
    accelerator two calls share one device and would run one after the other."""
    cores = (len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity")
             else os.cpu_count() or 1)
    return 2 if jax.default_backend() == "cpu" and cores >= 2 else 1


def check_workers(workers, name: str = "workers") -> int:
    """``workers`` as a positive int (None: ``default_workers()``), else a ValueError that
    calls it ``name``."""
    if workers is None:
        return default_workers()
    if isinstance(workers, bool) or not isinstance(workers, (int, np.integer)) or workers < 1:
        raise ValueError(f"{name} must be a positive integer (search candidates run at once) "
                         f"or None for the default; got {workers!r}")
    return int(workers)


def walk_stage(scales, score, stop_at_first_drop: bool = True, workers: int = 1,
               known=None):
    """One stage's (objective (S,), dropped (S,), fill_step (S,)) over ``scales`` (S,)
    (contains 1), with ``score(scale) -> RunScore``: candidates run outward from 1, the larger
    scales upward and then the smaller downward. With ``stop_at_first_drop`` a direction stops
    after a fair run (dropped no birth, finite score) that scores below the best fair run met
    on that walk (1 included); candidates not run get NaN, -1 and -1 (module docstring).

    ``workers``: when a candidate is needed and not started, it and the next unscored ones
    of its direction start, each in its own thread (``score`` must be thread-safe), as many
    as leave at most ``workers`` running; the walk waits for each when it reads it, in walk
    order. While the walk has met no fair run (or without ``stop_at_first_drop``), the
    candidate it waits for cannot stop it, so the one after is certainly needed and starts at
    once if a thread is free (on Victoria Park, whose x1 run overflowed, a run that ends at
    its first dropped birth frees its thread early). A candidate scored ahead of a stop is
    not used and reads NaN, -1 and -1 as if not run, and an error it raised is not raised; at
    most ``workers`` - 1 are scored past a stop in each direction, and the stage returns
    after every started run has finished. So the result is the same for every ``workers``;
    only the time (and the memory: up to ``workers`` runs alive at once) differs. The
    threads see JAX's global settings, not a context manager of the calling thread
    (``jax.enable_x64`` and the like are per thread): inside one, use ``workers=1``.
    ``known``: {scale: RunScore} already scored (not scored again; scales not in the grid
    are ignored)."""
    scales = np.asarray(scales, np.float64)
    results = {int(np.flatnonzero(scales == scale)[0]): result
               for scale, result in (known or {}).items() if np.any(scales == scale)}

    pool = None
    used = set()

    def start_runs(indices, needed: bool) -> None:  # the first unscored of ``indices``
        todo = [index for index in indices if index not in results]
        running = sum(isinstance(r, Future) and not r.done() for r in results.values())
        for index in todo[:max(workers - running, 1 if needed else 0)]:
            results[index] = pool.submit(score, float(scales[index]))  # a Future until read

    def fair_score(walk, position, next_needed=False) -> float:  # -inf when not fair
        index = walk[position]
        if pool is None and index not in results:
            results[index] = score(float(scales[index]))
        elif pool is not None and index not in results:
            start_runs(walk[position:], needed=True)  # it and the next, ``workers`` at once
        elif pool is not None and next_needed:
            start_runs(walk[position + 1:position + 2], needed=False)
        used.add(index)
        result = results[index]
        if isinstance(result, Future):
            result = results[index] = result.result()
        ranked = fair(result.log_likelihood, result.dropped_births)
        return float(result.log_likelihood) if ranked else -np.inf

    first = int(np.flatnonzero(scales == 1.0)[0])
    up = [int(i) for i in np.argsort(scales, kind="stable") if scales[i] > 1.0]
    down = [int(i) for i in np.argsort(-scales, kind="stable") if scales[i] < 1.0]
    try:
        pool = ThreadPoolExecutor(workers) if workers > 1 else None
        for direction in (up, down):
            walk = [first] + direction
            best = fair_score(walk, 0)
            for position in range(1, len(walk)):
                # With no fair run met yet (or no stop) this candidate cannot stop the walk,
                # so the next one is needed: it starts now if a worker is free.
                next_needed = not stop_at_first_drop or best == -np.inf
                value = fair_score(walk, position, next_needed=next_needed)
                if stop_at_first_drop and np.isfinite(value) and value < best:
                    break
                best = max(best, value)
    finally:
        if pool is not None:
            pool.shutdown(wait=True)  # runs scored ahead of a stop finish before returning
    objective = np.full(scales.shape, np.nan)
    dropped = np.full(scales.shape, -1, np.int64)
    fill_step = np.full(scales.shape, -1, np.int64)
    for index in used:
        objective[index], dropped[index], fill_step[index] = results[index]
    return objective, dropped, fill_step


def any_fair(found: ScaleSearch) -> bool:
    """Whether any candidate of either stage was a fair one (``best_scale``): its run
    dropped no birth and scored a finite log likelihood. False means no likelihood ranked
    the search's choice (the observation stage fell back on the map that filled last)."""
    dropped = np.concatenate([found.motion_dropped, found.observation_dropped])
    objective = np.concatenate([found.motion_objective, found.observation_objective])
    return bool(np.any(fair(objective, dropped)))


def describe_search(found: ScaleSearch) -> str:
    """One line: each stage's candidates and scores, which were not run, and the births the
    runs dropped when any did (how the choice was made: ``best_scale``)."""
    dropped = np.concatenate([found.motion_dropped, found.observation_dropped])
    objective = np.concatenate([found.motion_objective, found.observation_objective])
    not_run = np.any(dropped < 0)
    stopped = np.any((dropped > 0) & np.isnan(objective))
    line = (f"motion {found.motion_scales.tolist()} -> "
            f"{np.round(found.motion_objective, 1).tolist()}, observation "
            f"{found.observation_scales.tolist()} -> "
            f"{np.round(found.observation_objective, 1).tolist()}")
    if not_run:
        line += " (nan where not run: the score had already fallen past its peak)"
    if stopped:
        line += (" (nan where a run stopped at its first dropped birth: the map was full, so "
                 "its score cannot compete; only its fill step counts)")
    if np.any(dropped > 0):
        line += (f" (births dropped, map full: motion {found.motion_dropped.tolist()}, "
                 f"observation {found.observation_dropped.tolist()}"
                 + ("; -1: not run" if not_run else "")
                 + ("; a stopped run counts the births of the step it stopped at"
                    if stopped else "")
                 + "; only runs that dropped none compete; when every run of a stage dropped "
                 "births, the motion stage keeps x1 and the observation stage takes the run "
                 "whose map filled last: first full at step motion "
                 f"{found.motion_fill_step.tolist()}, observation "
                 f"{found.observation_fill_step.tolist()})")
    return line


def check_scales(name: str, scales) -> np.ndarray:
    """``scales`` as a float64 (S,) array; ValueError unless it is a non-empty 1-D sequence of
    distinct finite positive multipliers that contains 1 (EM's own result)."""
    scales = np.asarray(scales, np.float64)
    if scales.ndim != 1 or scales.size == 0 or not np.all(np.isfinite(scales)) or np.any(
            scales <= 0) or not np.any(scales == 1.0) or np.unique(scales).size != scales.size:
        raise ValueError(f"{name} must be a non-empty 1-D sequence of distinct finite positive "
                         f"multipliers that contains 1; got {scales.tolist()}")
    return scales


def search_noise_scales(config: FilterConfig, key, params: Params, controls,
                        observations: Observations, initial_pose=None, *,
                        motion_scales=DEFAULT_SCALES,
                        observation_scales=DEFAULT_SCALES,
                        known: RunScore | None = None,
                        stop_at_first_drop: bool = True,
                        workers: int | None = None) -> tuple[Params, ScaleSearch]:
    """Multiply ``params``' motion and observation noise by the scales of highest filter log
    marginal likelihood (module docstring: coordinate ascent, motion first).

    Args:
      config, key, controls (T, 3), observations (T, K, ...), initial_pose (3,): as
        ``run_filter``; every candidate runs with ``key``.
      params: the settings to scale (EM's result).
      motion_scales / observation_scales: the candidate multipliers of each stage (each must
        contain 1; ``(1.0,)`` leaves that group as it is).
      known: the ``RunScore`` of ``params`` itself with ``key`` when the caller has it (EM's
        whole run of the settings it returns, ``score_trace``), so that candidate is not run
        again.
      stop_at_first_drop: walk each grid outward from 1 and stop a direction once a fair
        candidate scores below the best met on it (module docstring); False runs every
        candidate.
      workers: candidates scored at once, each in its own thread (``walk_stage``; the same
        result for every value); None: ``default_workers()``.
    Returns:
      (scaled ``Params``, ``ScaleSearch``; a candidate not run has objective NaN, dropped -1
      and fill step -1). A stage whose candidates all score a non-finite value keeps 1. When
      every candidate dropped births, the motion stage keeps 1 and the observation stage takes
      the run whose map filled last (``best_scale``, module docstring).
    """
    motion_scales = check_scales("motion_scales", motion_scales)
    observation_scales = check_scales("observation_scales", observation_scales)
    workers = check_workers(workers)
    if known is not None and not isinstance(known, RunScore):
        raise ValueError(f"known must be a RunScore (score_trace of EM's run) or None; got "
                         f"{known!r}")
    scored = {} if known is None else {(1.0, 1.0): known}

    def score(motion: float, observation: float) -> RunScore:  # one dict entry a thread
        scored[motion, observation] = run_score(
            config, key, scaled_noise(params, motion, observation), controls, observations,
            initial_pose)
        return scored[motion, observation]

    def known_of(motion: float) -> dict:  # the stage's x1, when it has run
        return {1.0: scored[motion, 1.0]} if (motion, 1.0) in scored else {}

    motion_objective, motion_dropped, motion_fill = walk_stage(
        motion_scales, lambda m: score(m, 1.0), stop_at_first_drop, workers,
        known_of(1.0))
    # Every motion candidate overflowed: keep 1 (no fill steps; module docstring).
    motion_scale = best_scale(motion_scales, motion_objective, motion_dropped)
    observation_objective, observation_dropped, observation_fill = walk_stage(
        observation_scales, lambda o: score(motion_scale, o), stop_at_first_drop, workers,
        known_of(motion_scale))
    observation_scale = best_scale(observation_scales, observation_objective,
                                   observation_dropped, observation_fill)
    return scaled_noise(params, motion_scale, observation_scale), ScaleSearch(
        motion_scale, observation_scale, motion_scales, motion_objective, observation_scales,
        observation_objective, motion_dropped, observation_dropped, motion_fill,
        observation_fill)
