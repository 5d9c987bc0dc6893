"""FastSLAM: ``make_filter(config) -> Filter(init, step)``, ``run_filter`` and ``estimate``.

One step (Montemerlo et al., "FastSLAM: A Factored Solution to the Simultaneous Localization
and Mapping Problem", 2002; Geiser et al., "Practical Implementation of FastSLAM for Forestry
Robot", ICAROB 2023) composes six named stages, for every particle i in parallel
(``step_propose.py`` holds 1-2, ``step_update.py`` 3-6):

1. ``propose`` a pose x_t^i (motion model, observation proposal or their mixture,
   ``proposal.py``), with the log density ratio that corrects the weight;
2. ``associate`` at one pose: predict every landmark's measurement, the squared Mahalanobis
   distance d2[k, m] of every observation to it, apply the visibility boundary (hard or
   loose airlock) and match (stable matching, greedy, optimal or known ids); with
   ``Params.radius_noise`` > 0 the trunk radius adds d_r2[k, m] (``ekf.radius_distance_sq``)
   to what the gate, the associator and the weight see;
3. ``update_landmarks``: EKF-update matched landmarks and compute the per-observation
   likelihood p(z_k | x_t^i, m): N(nu; 0, S) when matched, a constant when unexplained;
4. ``weigh``: w_i *= prod_k p(z_k | x_t^i, m) x correction, normalised;
5. ``manage_map``: matched landmarks gain evidence, visible unmatched ones lose; delete below
   threshold; unexplained observations outside the airlock create landmarks in free slots;
6. ``resample`` when ESS < ess_threshold * P.

Observations are cleaned inside jit (``sanitize.py``): rows with a NaN or infinite value, a
negative range or a bearing outside [-pi, pi] are masked out and counted in
``info.num_invalid_obs``. The public ``validate_observations`` raises instead (use it at the
boundary of your program).

Controls are cleaned the same way (``sanitize_control``): a control row u_t (3,) of any motion
model with a NaN or infinite entry is missing odometry. The step then keeps every pose,

    x_t^i = x_{t-1}^i   (no motion noise, no observation draw, log-weight correction 0),

and still runs stages 2-6 (association, EKF update, weights, births, resampling) at the kept
poses; ``info.invalid_control`` flags the step. No noise is added because nothing is known
about the move: a zero control's standstill noise (the constant terms c of Eq. (1)) would be
an invented move, while keeping the poses leaves the next valid control to move them (the
missed move then shows as a larger residual there). The public ``run_filter`` refuses
non-finite concrete controls instead (``validation.check_controls``); ``Filter.step``,
``scan_filter`` and ``run_filter`` called on tracers (under jit or vmap) mask them.
"""
from __future__ import annotations

import functools
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxslam import ekf, landmarks, step_propose, step_update
from jaxslam.geometry import wrap_angle
from jaxslam.lineage import Lineage
from jaxslam.sanitize import sanitize_control, sanitize_observations, validate_observations
from jaxslam.types import FilterConfig, FilterState, Observations, Params, Particles
from jaxslam.validation import cast_floating, check_controls, check_params

__all__ = ["Estimate", "Filter", "StepInfo", "Trace", "circular_weighted_mean_pose", "estimate",
           "make_filter", "run_filter", "sanitize_control", "sanitize_observations",
           "scan_filter", "validate_observations"]


class StepInfo(NamedTuple):
    """Diagnostics of one step (returned, never carried).

    ess: () effective sample size before resampling. resampled: () bool.
    weights_reset: () bool, every weight was zero (-inf log) and they were reset to uniform.
    num_landmarks: (P,) int32 active slots per particle after the step.
    match: (P, K) int32 landmark slot of each observation, -1 when unmatched.
    match_rounds: () int32 most Gale-Shapley rounds used by any particle.
    num_invalid_obs: () int32 observations masked out as malformed (NaN, negative range...).
    num_dropped_births: (P,) int32 new landmarks dropped because the map was full.
    num_set_aside: (P,) int32 observations set aside in the airlock (never born; with
      ``boundary="loose_match"`` they may still be matched, so this is not a count of
      observations the filter left unused).
    mixture_ratio: () the phi used this step, averaged over the particles (0 for the motion
      proposal, 1 for observation; the adaptive mixture's phi is per particle).
    num_observation_draws: () int32 particles drawn from the observation proposal.
    mean_log_likelihood: () weighted mean of the per-observation log-likelihood.
    best_particle: () int32 index (after resampling) of a copy of the particle that had the
      highest weight before resampling (all weights are equal right after resampling).
    ancestor: (P,) int32 particle i after the step is a copy of particle ancestor[i] before
      resampling (arange(P) when the step did not resample); ``match`` and ``birth_slot``
      are indexed before resampling.
    birth_slot: (P, K) int32 slot of the landmark each observation created, -1 when it
      created none. With ``match`` and ``ancestor`` it lets ``lineage.trace_lineage`` and
      ``lineage.landmark_identities`` follow one particle's data association back in time.
    log_evidence: () log sum_i w_i p(z_t | x_i) (with the proposal correction), the particle
      filter's estimate of log p(z_t | z_1:t-1); summed over steps it estimates the log
      marginal likelihood of the log (``self_calibration`` monitors its EM with it).
    invalid_control: () bool, the control held a NaN or inf and was masked: the poses were
      kept (module docstring), and ``mixture_ratio`` is 0 for the step.
    window_cut: () int32 the most landmarks any particle's ``association_window`` left out
      although they could have taken part in its association (``landmarks.may_take_part``);
      0 without a window. While it stays 0 the window gives the full association's matches,
      set-asides and misses (up to exactly equal pair costs).
    """

    ess: jnp.ndarray
    resampled: jnp.ndarray
    weights_reset: jnp.ndarray
    num_landmarks: jnp.ndarray
    match: jnp.ndarray
    match_rounds: jnp.ndarray
    num_invalid_obs: jnp.ndarray
    num_dropped_births: jnp.ndarray
    num_set_aside: jnp.ndarray
    mixture_ratio: jnp.ndarray
    num_observation_draws: jnp.ndarray
    mean_log_likelihood: jnp.ndarray
    best_particle: jnp.ndarray
    ancestor: jnp.ndarray
    birth_slot: jnp.ndarray
    log_evidence: jnp.ndarray
    invalid_control: jnp.ndarray
    window_cut: jnp.ndarray


class Filter(NamedTuple):
    """``init(initial_pose (3,)) -> FilterState``;
    ``step(key, state, params, control (3,), obs) -> (state, StepInfo)``; a control with a
    NaN or inf is masked (poses kept, ``StepInfo.invalid_control``, module docstring).

    Unpacks as ``init, step = make_filter(config)``; ``.config`` gives the config back.
    """

    init: Callable
    step: Callable

    @property
    def config(self) -> FilterConfig:
        return self.init.args[0]


class Estimate(NamedTuple):
    """Point estimate of one run.

    pose: (3,) weighted mean pose (circular mean heading); pose_cov: (3, 3);
    best_particle: () int32 index of the highest weight; the map is that particle's:
    landmark_mean (M, 2), landmark_cov (M, 2, 2), landmark_radius (M,), active (M,).
    """

    pose: jnp.ndarray
    pose_cov: jnp.ndarray
    best_particle: jnp.ndarray
    landmark_mean: jnp.ndarray
    landmark_cov: jnp.ndarray
    landmark_radius: jnp.ndarray
    active: jnp.ndarray


class Trace(NamedTuple):
    """Per-step record of ``run_filter``: every field has leading axis T.

    mean_pose (T, 3), best_pose (T, 3), ess (T,), num_landmarks (T,) of the best particle,
    resampled (T,), weights_reset (T,), num_invalid_obs (T,), num_dropped_births (T,) summed
    over particles, match_rounds (T,), mixture_ratio (T,), mean_log_likelihood (T,);
    lineage: ``Lineage`` with ``record_lineage=True``, else None; log_evidence (T,)
    (``StepInfo.log_evidence``; its sum is the log marginal likelihood estimate);
    invalid_control (T,) bool, ``StepInfo.invalid_control`` (``trace.invalid_control.sum()``
    is the number of masked control rows of the run); window_cut (T,) int32,
    ``StepInfo.window_cut`` (all 0: the association window changed no match, set-aside or
    miss).
    """

    mean_pose: jnp.ndarray
    best_pose: jnp.ndarray
    ess: jnp.ndarray
    num_landmarks: jnp.ndarray
    resampled: jnp.ndarray
    weights_reset: jnp.ndarray
    num_invalid_obs: jnp.ndarray
    num_dropped_births: jnp.ndarray
    match_rounds: jnp.ndarray
    mixture_ratio: jnp.ndarray
    mean_log_likelihood: jnp.ndarray
    lineage: Lineage | None = None
    log_evidence: jnp.ndarray | None = None
    invalid_control: jnp.ndarray | None = None
    window_cut: jnp.ndarray | None = None


# --------------------------------------------------------------------------------------------
# Public API


def _check_config(config) -> FilterConfig:
    if not isinstance(config, FilterConfig):
        raise TypeError(f"make_filter expects a FilterConfig; got {type(config).__name__}")
    return config


def _init(config: FilterConfig, initial_pose=None, dtype=jnp.float32) -> FilterState:
    num, slots = config.num_particles, config.max_landmarks
    pose = jnp.zeros(3, dtype) if initial_pose is None else jnp.asarray(initial_pose, dtype)
    if pose.shape != (3,):
        raise ValueError(f"initial_pose must have shape (3,) (x, y, theta); got {pose.shape}")
    mean, cov, radius = landmarks.empty_slot_values(slots, dtype)
    particles = Particles(
        pose=jnp.broadcast_to(pose, (num, 3)),
        landmark_mean=jnp.broadcast_to(mean, (num, slots, 2)),
        landmark_cov=jnp.broadcast_to(cov, (num, slots, 3)),
        landmark_radius=jnp.broadcast_to(radius, (num, slots)),
        landmark_id=jnp.full((num, slots), -1, jnp.int32),
        active=jnp.zeros((num, slots), bool),
        existence=jnp.zeros((num, slots), dtype),
        observation_count=jnp.zeros((num, slots), jnp.int32),
        radius_count=jnp.zeros((num, slots), jnp.int32),
    )
    return FilterState(particles, jnp.full((num,), -jnp.log(num), dtype),
                       jnp.zeros((), dtype), jnp.zeros((), dtype), jnp.zeros((), jnp.int32))


def _clean_inputs(state: FilterState, params: Params, control, obs: Observations):
    """Cast to the state's float dtype and mask malformed rows (``sanitize.py``).

    Returns (params, control (3,), obs, num_invalid_obs () int32, invalid_control () bool).
    """
    # One float dtype, the state's: float64 params or observations with a float32 state
    # would otherwise change the type of the scan carry (a no-op when they already match).
    params, control, obs = cast_floating((params, control, obs), state.particles.pose.dtype)
    obs, num_invalid = sanitize_observations(obs)
    control, invalid_control = sanitize_control(control)
    return params, control, obs, num_invalid, invalid_control


def _step_info(proposed, weights, mapped, resampled, num_invalid,
               invalid_control) -> StepInfo:
    """``StepInfo`` from the stages' results."""
    return StepInfo(
        ess=resampled.ess, resampled=resampled.resampled, weights_reset=weights.reset,
        num_landmarks=jnp.sum(resampled.particles.active, axis=1).astype(jnp.int32),
        match=proposed.association.match,
        match_rounds=jnp.max(proposed.association.rounds).astype(jnp.int32),
        num_invalid_obs=num_invalid, num_dropped_births=mapped.num_dropped,
        num_set_aside=mapped.num_set_aside,
        mixture_ratio=jnp.mean(proposed.ratio).astype(weights.log_weight.dtype),
        num_observation_draws=jnp.sum(proposed.used_observation).astype(jnp.int32),
        mean_log_likelihood=weights.mean_log_likelihood,
        best_particle=resampled.best_particle, ancestor=resampled.ancestor,
        birth_slot=mapped.birth_slot, log_evidence=weights.log_evidence,
        invalid_control=invalid_control,
        window_cut=jnp.max(proposed.association.window_cut).astype(jnp.int32))


def _step(config: FilterConfig, key, state: FilterState, params: Params, control,
          obs: Observations):
    """One step: the six stages of the module docstring in order. Returns (state, StepInfo)."""
    params, control, obs, num_invalid, invalid_control = _clean_inputs(state, params, control,
                                                                       obs)
    key_propose, key_resample = jax.random.split(key)
    # A masked control draws nothing from the observation proposal (phi 0, poses kept).
    ratio = jnp.where(invalid_control, 0.0, step_propose.mixture_ratio(
        config, params, state)).astype(state.log_weight.dtype)
    proposed = step_propose.propose(config, key_propose, params, state.particles, control, obs,
                                    ratio, invalid_control)

    def per_particle(stage):
        return jax.vmap(lambda one, found: stage(config, params, one, found, obs))

    moved = state.particles._replace(pose=proposed.pose)
    updated = per_particle(step_update.update_landmarks)(moved, proposed.association)
    weights = step_update.weigh(params, state, jnp.sum(updated.log_likelihood, axis=1),
                                proposed.log_correction, obs.valid)
    mapped = per_particle(step_update.manage_map)(updated, proposed.association)
    resampled = step_update.resample(config, params, key_resample, mapped.particle,
                                     weights.log_weight)
    new_state = FilterState(resampled.particles, resampled.log_weight, weights.likelihood_fast,
                            weights.likelihood_slow, state.step + 1)
    return new_state, _step_info(proposed, weights, mapped, resampled, num_invalid,
                                 invalid_control)


def make_filter(config: FilterConfig) -> Filter:
    """Build the filter for a static config. Cached: one Filter (and one trace) per config.

    Raises:
      TypeError / ValueError naming the offending field for an impossible config.
    """
    return _make_filter_cached(_check_config(config))


@functools.lru_cache(maxsize=None)
def _make_filter_cached(config: FilterConfig) -> Filter:
    return Filter(functools.partial(_init, config), functools.partial(_step, config))


def circular_weighted_mean_pose(pose, log_weight):
    """Weighted mean (3,) of poses (P, 3), heading by the circular mean."""
    weight = jnp.exp(log_weight)
    heading = jnp.arctan2(jnp.sum(weight * jnp.sin(pose[:, 2])),
                          jnp.sum(weight * jnp.cos(pose[:, 2])))
    return jnp.stack([jnp.sum(weight * pose[:, 0]), jnp.sum(weight * pose[:, 1]), heading])


def estimate(state: FilterState) -> Estimate:
    """Weighted mean pose and the map of the highest-weight particle.

    Right after a resampling step all weights are equal and the "best" particle is the first
    survivor: a draw from the posterior over maps rather than its mode.
    """
    particles, log_weight = state.particles, state.log_weight
    mean = circular_weighted_mean_pose(particles.pose, log_weight)
    diff = particles.pose - mean[None, :]
    diff = diff.at[:, 2].set(wrap_angle(diff[:, 2]))
    pose_cov = jnp.einsum("p,pi,pj->ij", jnp.exp(log_weight), diff, diff)
    best = jnp.argmax(log_weight).astype(jnp.int32)
    return Estimate(mean, pose_cov, best, particles.landmark_mean[best],
                    ekf.expand_covariance(particles.landmark_cov[best]),
                    particles.landmark_radius[best], particles.active[best])


def _trace_row(state: FilterState, info: StepInfo, record_lineage: bool = False) -> Trace:
    best = info.best_particle
    lineage = (Lineage(info.ancestor, info.match.astype(jnp.int16),
                       info.birth_slot.astype(jnp.int16), state.particles.pose)
               if record_lineage else None)
    return Trace(
        mean_pose=circular_weighted_mean_pose(state.particles.pose, state.log_weight),
        best_pose=state.particles.pose[best], ess=info.ess,
        num_landmarks=info.num_landmarks[best], resampled=info.resampled,
        weights_reset=info.weights_reset, num_invalid_obs=info.num_invalid_obs,
        num_dropped_births=jnp.sum(info.num_dropped_births), match_rounds=info.match_rounds,
        mixture_ratio=info.mixture_ratio, mean_log_likelihood=info.mean_log_likelihood,
        lineage=lineage, log_evidence=info.log_evidence, invalid_control=info.invalid_control,
        window_cut=info.window_cut,
    )


def _check_lineage_slots(config: FilterConfig) -> None:
    if config.max_landmarks > jnp.iinfo(jnp.int16).max:
        raise ValueError(f"record_lineage stores slots as int16; max_landmarks="
                         f"{config.max_landmarks} exceeds {jnp.iinfo(jnp.int16).max}")


def scan_filter(config: FilterConfig, key, state: FilterState, params: Params, controls,
                observations: Observations, record_lineage: bool = False,
                stop_at_dropped_birth=None):
    """``lax.scan`` of ``step`` over T steps (traceable; vmap it over runs or params).

    Step t uses key ``fold_in(key, t)``. Returns (final state, ``Trace``); with
    ``record_lineage`` the trace carries every particle's ancestry and association
    (``Lineage``, for ``smoothing.smooth_lineage``). ``controls`` (T, 3) are not checked: a
    row with a NaN or inf is masked (poses kept, module docstring) and flagged in
    ``trace.invalid_control`` (T,).

    ``stop_at_dropped_birth``: None (default) runs every step. A () bool (dynamic: one
    compiled program serves both values) that is True holds the state after the first step
    whose map had no free slot for a birth (``trace.num_dropped_births`` > 0): the steps
    after it are skipped (``lax.cond``: on a CPU or GPU only the taken branch runs, so they
    cost next to nothing unless the scan is vmapped, which turns the cond into a select of
    both branches), their trace rows are zeros (in a recorded lineage: each particle its own
    ancestor, match and birth_slot -1, as for a step with no observation), and the final
    state is the state after that step. ``noise_scale.run_score`` uses it: a run whose map
    overflowed cannot be chosen, so the rest of it need not be run.
    """
    step = make_filter(config).step
    if record_lineage:
        _check_lineage_slots(config)

    def advance(carry: FilterState, inputs):
        t, control, obs = inputs
        new_state, info = step(jax.random.fold_in(key, t), carry, params, control, obs)
        return new_state, _trace_row(new_state, info, record_lineage)

    steps = jnp.arange(controls.shape[0], dtype=jnp.int32)
    if stop_at_dropped_birth is None:
        return jax.lax.scan(advance, state, (steps, controls, observations))
    stop = jnp.asarray(stop_at_dropped_birth, bool)
    if stop.shape != ():
        raise ValueError(f"stop_at_dropped_birth must be a scalar bool; got shape {stop.shape}")
    one_step = jax.tree.map(lambda leaf: jax.ShapeDtypeStruct(leaf.shape[1:], leaf.dtype),
                            (steps, controls, observations))  # T = 0 has no row to index
    blank = jax.tree.map(lambda shape: jnp.zeros(shape.shape, shape.dtype),
                         jax.eval_shape(advance, state, one_step)[1])
    if record_lineage:  # a skipped step: no association, no birth, every particle its own
        blank = blank._replace(lineage=blank.lineage._replace(
            ancestor=jnp.arange(config.num_particles, dtype=blank.lineage.ancestor.dtype),
            match=jnp.full_like(blank.lineage.match, -1),
            birth_slot=jnp.full_like(blank.lineage.birth_slot, -1)))

    def body(carry, inputs):
        current, stopped = carry
        new_state, row = jax.lax.cond(stopped, lambda c, _: (c, blank), advance, current,
                                      inputs)
        return (new_state, stopped | (stop & (row.num_dropped_births > 0))), row

    (final, _), trace = jax.lax.scan(body, (state, jnp.asarray(False)),
                                     (steps, controls, observations))
    return final, trace


@functools.partial(jax.jit, static_argnums=(0, 6))
def _run_filter_jit(config, key, params, controls, observations, initial_pose,
                    record_lineage=False, stop_at_dropped_birth=False):
    state = make_filter(config).init(initial_pose, dtype=controls.dtype)
    return scan_filter(config, key, state, params, controls, observations, record_lineage,
                       stop_at_dropped_birth)


def run_filter(config: FilterConfig | Filter, key, params: Params, controls,
               observations: Observations, initial_pose=None, record_lineage: bool = False,
               stop_at_dropped_birth: bool = False):
    """Run a whole sequence in one compiled call.

    Args:
      config: a ``FilterConfig`` (or a ``Filter`` from ``make_filter``).
      key: PRNG key (required; step t uses ``fold_in(key, t)``).
      params: ``Params``.
      controls: (T, 3) controls of ``config.motion_model``.
      observations: ``Observations`` with leaves (T, K, ...).
      initial_pose: (3,) start pose of every particle (default origin).
      record_lineage: also record every particle's ancestry and association in
        ``trace.lineage`` (4 T P K + 16 T P bytes), for ``smoothing.smooth_lineage``.
      stop_at_dropped_birth: skip the steps after the first one that dropped a birth for
        want of a free slot (``scan_filter``): their trace rows are blank (zeros; no
        association or birth in the lineage), and the final state is the state after that
        step. A dynamic flag: both values share one compiled program.
    Returns:
      (final ``FilterState``, ``Trace`` with leading axis T).
    Raises:
      ValueError: bad shapes, a non-finite control row (concrete controls only: under jit or
        vmap the row is masked as in ``scan_filter``), ``Params`` that
        ``validation.check_params`` refuses, or a ``stop_at_dropped_birth`` that is not a
        0-d bool. Float leaves of ``params`` and ``observations``
        are cast to the controls' dtype (the filter's dtype).
    """
    if isinstance(config, Filter):
        config = config.config
    _check_config(config)
    controls = jnp.asarray(controls)
    check_controls(controls)  # shape (T, 3), float, finite (first bad row named)
    check_params(params)  # concrete leaves only; tracers are skipped
    params = cast_floating(params, controls.dtype)  # one dtype: the controls'
    observations = cast_floating(observations, controls.dtype)
    if observations.z.shape[:1] != controls.shape[:1] or observations.z.shape[1:] != (
            config.max_obs, 2):
        raise ValueError(
            f"observations.z must have shape (T, K, 2) = ({controls.shape[0]}, "
            f"{config.max_obs}, 2) to match controls and FilterConfig.max_obs; "
            f"got {observations.z.shape}")
    if initial_pose is None:
        initial_pose = jnp.zeros(3, controls.dtype)
    flag = (stop_at_dropped_birth if isinstance(stop_at_dropped_birth, jax.Array)
            else np.asarray(stop_at_dropped_birth))  # a traced flag stays traced
    if flag.shape != () or flag.dtype != np.bool_:
        raise ValueError("stop_at_dropped_birth must be True or False (a Python, NumPy or JAX "
                         f"0-d bool); got {stop_at_dropped_birth!r}")
    return _run_filter_jit(config, key, params, controls, observations,
                           jnp.asarray(initial_pose, controls.dtype), bool(record_lineage),
                           jnp.asarray(flag))
