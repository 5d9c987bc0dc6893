"""FastSLAM: ``make_filter(config) -> Filter(init, step)``, ``run_filter`` and ``estimate``.

One step (Geiser et al. 2023; Montemerlo et al. 2002), for every particle i in parallel:

1. propose a pose x_t^i (motion model, observation proposal or their mixture, ``proposal.py``);
2. predict every landmark's measurement, the squared Mahalanobis distance d2[k, m] of every
   observation to it, and apply the visibility boundary (hard or loose airlock); with
   ``Params.radius_noise`` > 0 the trunk radius adds d_r2[k, m] (``ekf.radius_distance_sq``)
   to what the gate, the associator and the weight see;
3. associate observations to landmarks (stable matching, greedy, optimal or known ids);
4. EKF-update matched landmarks; weight w_i *= prod_k p(z_k | x_t^i, m) where matched
   observations use N(nu; 0, S) and unexplained ones a constant (``ekf.py``);
5. evidence: matched landmarks gain, visible unmatched ones lose; delete below threshold;
   unexplained observations outside the airlock create landmarks in free slots;
6. normalise weights; resample when ESS < ess_threshold * P.

Observations are cleaned inside jit: rows with a NaN or infinite value, a negative range or a
bearing outside [-pi, pi] are masked out and counted in ``info.num_invalid_obs``. The public
``validate_observations`` raises instead (use it at the boundary of your program).

Controls are cleaned the same way (``sanitize_control``): a control row u_t (3,) of any motion
model with a NaN or infinite entry is missing odometry. The step then keeps every pose,

    x_t^i = x_{t-1}^i   (no motion noise, no observation draw, log-weight correction 0),

and still runs steps 2-6 (association, EKF update, weights, births, resampling) at the kept
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

from jaxslam import association, ekf, landmarks, proposal, resampling
from jaxslam.geometry import wrap_angle
from jaxslam.lineage import Lineage
from jaxslam.motion import predict_pose, sample_motion
from jaxslam.types import FilterConfig, FilterState, Observations, Params, Particles
from jaxslam.validation import cast_floating, check_controls, check_params


class StepInfo(NamedTuple):
    """Diagnostics of one step (returned, never carried).

    ess: () effective sample size before resampling. resampled: () bool.
    weights_reset: () bool, every weight was zero (-inf log) and they were reset to uniform.
    num_landmarks: (P,) int32 active slots per particle after the step.
    match: (P, K) int32 landmark slot of each observation, -1 when unmatched.
    match_rounds: () int32 most Gale-Shapley rounds used by any particle.
    num_invalid_obs: () int32 observations masked out as malformed (NaN, negative range...).
    num_dropped_births: (P,) int32 new landmarks dropped because the map was full.
    num_set_aside: (P,) int32 observations set aside in the airlock.
    mixture_ratio: () the phi used this step (0 for the motion proposal, 1 for observation).
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
    is the number of masked control rows of the run).
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


class _ObserveResult(NamedTuple):
    particle: Particles  # one particle (no P axis)
    log_likelihood: jnp.ndarray  # ()
    match: jnp.ndarray  # (K,)
    rounds: jnp.ndarray  # ()
    dropped: jnp.ndarray  # ()
    set_aside: jnp.ndarray  # ()
    birth_slot: jnp.ndarray  # (K,) slot created by each observation, -1 for none


# --------------------------------------------------------------------------------------------
# Observation cleaning


def sanitize_observations(obs: Observations):
    """Mask malformed rows inside jit. Returns (clean Observations, num_invalid ())."""
    z = obs.z
    finite = jnp.all(jnp.isfinite(z), axis=-1)
    well_formed = finite & (z[..., 0] >= 0.0) & (jnp.abs(z[..., 1]) <= jnp.pi)
    invalid = obs.valid & ~well_formed
    valid = obs.valid & well_formed
    z = jnp.where(valid[..., None], z, 0.0)
    # A radius that is not a finite positive number is unknown (0), whatever the row.
    radius = jnp.where(valid & jnp.isfinite(obs.radius) & (obs.radius > 0), obs.radius, 0.0)
    clean = obs._replace(z=z, valid=valid, radius=radius)
    return clean, jnp.sum(invalid).astype(jnp.int32)


def sanitize_control(control):
    """Mask a non-finite control inside jit. Returns (control (..., 3), invalid (...,) bool).

    invalid = any_j ~isfinite(u_j); the returned control is 0 where invalid (so nothing
    downstream, its gradient included, sees the NaN: the caller's ``where`` on the result of
    a zero control is the second half of a double where) and ``control`` elsewhere.
    """
    invalid = ~jnp.all(jnp.isfinite(control), axis=-1)
    return jnp.where(invalid[..., None], jnp.zeros_like(control), control), invalid


def validate_observations(obs: Observations, max_obs: int | None = None) -> None:
    """Raise ``ValueError`` for malformed observations (use outside jit, on concrete arrays).

    Checks shapes ((..., K, 2) with matching (..., K) masks), and, on valid rows, finite values,
    non-negative ranges and bearings within [-pi, pi].
    """
    import numpy as np

    z = np.asarray(obs.z)
    if z.ndim < 2 or z.shape[-1] != 2:
        raise ValueError(f"Observations.z must have shape (..., K, 2); got {z.shape}")
    if max_obs is not None and z.shape[-2] != max_obs:
        raise ValueError(
            f"Observations have K={z.shape[-2]} rows but FilterConfig.max_obs={max_obs}; "
            "pad or truncate to max_obs rows")
    valid = np.asarray(obs.valid, bool)
    for name in ("valid", "radius", "landmark_id"):
        shape = np.shape(getattr(obs, name))
        if shape != z.shape[:-1]:
            raise ValueError(f"Observations.{name} has shape {shape}; expected {z.shape[:-1]}")
    rows = z[valid]
    if not np.all(np.isfinite(rows)):
        raise ValueError(f"{int(np.sum(~np.isfinite(rows).all(-1)))} valid observation(s) "
                         "contain NaN or inf; mark them invalid or remove them")
    if np.any(rows[:, 0] < 0):
        raise ValueError(f"{int(np.sum(rows[:, 0] < 0))} valid observation(s) have a negative "
                         "range; ranges must be >= 0 metres")
    if np.any(np.abs(rows[:, 1]) > np.pi):
        raise ValueError("valid observation bearings must lie in [-pi, pi] radians; "
                         f"got values up to {np.abs(rows[:, 1]).max():.3f}")


# --------------------------------------------------------------------------------------------
# One particle


def _association_cost(config, obs, particle, mahalanobis, vis):
    """(K, M) cost the associator sees: +inf outside the usable/matchable sets."""
    allowed = vis.usable_obs[:, None] & vis.matchable[None, :]
    if config.association == "known":
        same = association.known_id_cost(obs.landmark_id, particle.landmark_id, particle.active)
        return jnp.where(allowed & jnp.isfinite(same), 0.0, jnp.inf)
    return jnp.where(allowed, mahalanobis, jnp.inf)


class _Association(NamedTuple):
    """Association of one particle's observations, computed at its matching pose."""

    match: jnp.ndarray  # (K,) landmark slot or -1
    rounds: jnp.ndarray  # () matching rounds
    visibility: landmarks.Visibility
    # At the matching pose, over the N landmarks of the association window (all M slots
    # without a window); local_match (K,) indexes it (-1: unmatched).
    predicted: ekf.PredictedMeasurement
    local_match: jnp.ndarray


def _to_slots(window_values, slots, num_slots: int):
    """(N,) bool flags of the windowed landmarks -> (M,) over all slots (False elsewhere)."""
    return jnp.zeros((num_slots,), bool).at[slots].set(window_values)


def _associate(config: FilterConfig, params: Params, particle: Particles, match_pose,
               obs: Observations, pose_cov=None) -> _Association:
    """Steps 2-3 of the module docstring at ``match_pose`` (3,): predictions, boundary, matching.

    ``match_pose`` is the sampled pose for the motion proposal and the motion prediction x_hat
    for the observation and mixture proposals (computed once, shared with the proposal).
    ``pose_cov`` (3, 3), when given, is added to the matching covariance
    (``ekf.add_pose_uncertainty``); the returned ``predicted`` keeps S without it. With an
    association window only its N landmarks are predicted (``_Association``).
    """
    window = config.association_window
    if 0 < window < config.max_landmarks:
        # Predictions and pair work on the N nearest active landmarks only; the match is
        # mapped back to slots.
        distance = jnp.hypot(particle.landmark_mean[:, 0] - match_pose[0],
                             particle.landmark_mean[:, 1] - match_pose[1])
        _, slots = jax.lax.top_k(-jnp.where(particle.active, distance, jnp.inf), window)
        local = particle._replace(landmark_mean=particle.landmark_mean[slots],
                                  landmark_cov=particle.landmark_cov[slots],
                                  landmark_radius=particle.landmark_radius[slots],
                                  radius_count=particle.radius_count[slots],
                                  active=particle.active[slots],
                                  landmark_id=particle.landmark_id[slots])
    else:
        slots, local = None, particle
    predicted = ekf.predict_measurements(match_pose, local.landmark_mean, local.landmark_cov,
                                         params)
    local_predicted = (predicted if pose_cov is None
                       else ekf.add_pose_uncertainty(predicted, pose_cov))
    mahalanobis = ekf.mahalanobis_sq(obs.z, local_predicted)
    mahalanobis = jnp.where(obs.valid[:, None] & local.active[None, :], mahalanobis, jnp.inf)
    vis = landmarks.visibility(obs.z, obs.valid, local.active, local_predicted, mahalanobis,
                               params, config.boundary)
    # The trunk radius, when used (params.radius_noise > 0), adds to what the gate and the
    # associator see; visibility (explained / airlock) stays on the position alone.
    radius_sq = ekf.radius_distance_sq(obs.radius[:, None], local.landmark_radius[None, :],
                                       local.radius_count[None, :], params)
    cost = _association_cost(config, obs, local, mahalanobis + radius_sq, vis)
    local_match, rounds = association.match(config.association, cost,
                                            params.association_gate, config.match_rounds)
    match = local_match
    if slots is not None:
        match = jnp.where(local_match >= 0, slots[jnp.clip(local_match, 0)],
                          -1).astype(jnp.int32)
        vis = vis._replace(**{name: _to_slots(getattr(vis, name), slots, config.max_landmarks)
                              for name in ("matchable", "explained", "expected")})
    return _Association(match, rounds, vis, predicted, local_match)


def _observe(config: FilterConfig, params: Params, particle: Particles, found: _Association,
             obs: Observations) -> _ObserveResult:
    """Steps 4-5 of the module docstring for one particle at pose ``particle.pose``, given
    its association ``found``."""
    num_slots = config.max_landmarks
    match, rounds, vis = found.match, found.rounds, found.visibility
    matched_obs = match >= 0
    slot_of_obs = jnp.where(matched_obs, match, num_slots)
    obs_of_slot = jnp.full((num_slots,), -1, jnp.int32).at[slot_of_obs].set(
        jnp.arange(match.shape[0], dtype=jnp.int32), mode="drop")
    matched_slot = obs_of_slot >= 0

    # Only the <= K matched landmarks are predicted again and updated: rows (K,) gathers each
    # observation's landmark (slot 0 for unmatched rows, whose results are dropped below).
    rows = jnp.clip(match, 0)
    mean_k, cov_k = particle.landmark_mean[rows], particle.landmark_cov[rows]
    if config.proposal == "motion":
        # The association was computed at this very pose.
        pred_k = jax.tree.map(lambda leaf: leaf[jnp.clip(found.local_match, 0)],
                              found.predicted)
    else:
        pred_k = ekf.predict_measurements(particle.pose, mean_k, cov_k, params)
    # Per-observation likelihood at the particle's pose.
    d_range = obs.z[:, 0] - pred_k.range
    d_bearing = wrap_angle(obs.z[:, 1] - pred_k.bearing)
    mahalanobis_k = (d_range**2 * pred_k.i_rr + 2.0 * d_range * d_bearing * pred_k.i_rb
                     + d_bearing**2 * pred_k.i_bb)
    radius_k = ekf.radius_distance_sq(obs.radius, particle.landmark_radius[rows],
                                      particle.radius_count[rows], params)
    matched_ll = ekf.gaussian_log_likelihood(mahalanobis_k + radius_k, pred_k.log_det)
    unexplained_ll = ekf.unexplained_log_likelihood(obs.z[:, 0], params)
    log_likelihood = jnp.sum(jnp.where(obs.valid, jnp.where(matched_obs, matched_ll,
                                                            unexplained_ll), 0.0))

    new_mean, new_cov = ekf.update_landmarks(mean_k, cov_k, pred_k, obs.z, params)
    # One-to-one matching: no two observations write the same slot.
    mean = particle.landmark_mean.at[slot_of_obs].set(new_mean, mode="drop")
    cov = particle.landmark_cov.at[slot_of_obs].set(new_cov, mode="drop")
    radius_obs = obs.radius[jnp.clip(obs_of_slot, 0)]
    count = particle.observation_count + matched_slot.astype(jnp.int32)
    # Running mean over the measured radii only (a landmark with none yet takes the first).
    has_radius = matched_slot & (radius_obs > 0)
    radius_count = particle.radius_count + has_radius.astype(jnp.int32)
    running = particle.landmark_radius + (radius_obs - particle.landmark_radius) / jnp.maximum(
        radius_count, 1)
    radius = jnp.where(has_radius, running, particle.landmark_radius)

    missed = vis.expected & ~matched_slot & ~vis.explained
    existence = landmarks.update_existence(particle.existence, matched_slot, missed, params)
    keep = particle.active & (existence >= params.existence_delete)
    empty_mean, empty_cov, empty_radius = landmarks.empty_slot_values(num_slots, mean.dtype)
    mean = jnp.where(keep[:, None], mean, empty_mean)
    cov = jnp.where(keep[:, None], cov, empty_cov)
    radius = jnp.where(keep, radius, empty_radius)
    count = jnp.where(keep, count, 0)
    radius_count = jnp.where(keep, radius_count, 0)
    landmark_id = jnp.where(keep, particle.landmark_id, -1)

    birth = vis.usable_obs & ~matched_obs
    if config.association == "known":
        # A tree already in the map (even outside the matchable region) is never born twice.
        in_map = jnp.any(particle.active[None, :]
                         & (particle.landmark_id[None, :] == obs.landmark_id[:, None]), axis=1)
        birth = birth & (obs.landmark_id >= 0) & ~in_map
    slot, dropped = landmarks.birth_slots(keep, birth)
    born_mean, born_cov = ekf.initialize_landmarks(particle.pose, obs.z, params)
    active = keep.at[slot].set(True, mode="drop")
    updated = particle._replace(
        landmark_mean=landmarks.scatter_rows(mean, slot, born_mean),
        landmark_cov=landmarks.scatter_rows(cov, slot, born_cov),
        landmark_radius=landmarks.scatter_rows(radius, slot, obs.radius),
        landmark_id=landmarks.scatter_rows(landmark_id, slot, obs.landmark_id),
        active=active,
        existence=landmarks.scatter_rows(
            jnp.where(keep, existence, 0.0), slot,
            jnp.broadcast_to(params.existence_init, slot.shape).astype(existence.dtype)),
        observation_count=landmarks.scatter_rows(count, slot, jnp.ones_like(slot)),
        radius_count=landmarks.scatter_rows(radius_count, slot,
                                            (obs.radius > 0).astype(jnp.int32)),
    )
    birth_slot = jnp.where(slot < num_slots, slot, -1).astype(jnp.int32)
    return _ObserveResult(updated, log_likelihood, match, rounds, dropped,
                          jnp.sum(vis.set_aside_obs).astype(jnp.int32), birth_slot)


# --------------------------------------------------------------------------------------------
# Proposal


def _propose(config, key, params, particles: Particles, control, obs, ratio, keep_pose):
    """Sample new poses and associate. Returns (poses (P, 3), association (P leading axis),
    log-weight corrections (P,), observation draws (P,) bool).

    ``keep_pose`` () bool (a masked control, ``sanitize_control``; ``control`` is then 0 and
    the caller passes ``ratio`` 0): every particle keeps its pose, is associated there and
    gets correction 0. The draws are still made (same keys) and dropped by ``where``.
    """
    num = config.num_particles
    key_motion, key_mixture = jax.random.split(key)
    motion = config.motion_model
    motion_draw = jax.vmap(lambda k, pose: sample_motion(k, pose, control, params, motion))(
        jax.random.split(key_motion, num), particles.pose)
    if config.anchor_empty_map:
        # A particle with no landmark yet: nothing observed can ever tell its pose error
        # from the map's frame, so it takes the motion mean (the map frame is that pose).
        mean = jax.vmap(lambda pose: predict_pose(pose, control, params, motion))(
            particles.pose)
        motion_draw = jnp.where(jnp.any(particles.active, axis=1)[:, None], motion_draw, mean)
    # Missing control: the "motion sample" is the previous pose. With ratio 0 no particle
    # takes the observation draw, so every proposal below returns these poses.
    motion_draw = jnp.where(keep_pose, particles.pose, motion_draw)
    if config.proposal == "motion":
        found = jax.vmap(lambda particle, pose: _associate(config, params, particle, pose, obs))(
            particles, motion_draw)
        return motion_draw, found, jnp.zeros((num,), motion_draw.dtype), jnp.zeros(num, bool)

    def one(k, particle, motion_sample):
        x_hat = predict_pose(particle.pose, control, params, motion)
        if config.burst_proposal:
            gaussian, found = _burst_pieces(config, params, particle, x_hat, control, obs)
        else:
            pose_cov = proposal.motion_pose_covariance(particle.pose, control, params, motion)
            found = _associate(config, params, particle, x_hat, obs,
                               pose_cov if config.match_pose_uncertainty else None)
            gaussian = proposal.observation_proposal(x_hat, pose_cov, obs.z,
                                                     found.local_match, found.predicted)
        pose, used_obs, piece = proposal.mixture_sample(k, motion_sample, gaussian, ratio)
        if config.burst_proposal:
            found = jax.tree.map(lambda leaf: leaf[piece], found)
        correction = proposal.mixture_log_correction(particle.pose, pose, control, params,
                                                     motion, gaussian, ratio)
        # The update and the weight use the association at the pose they are evaluated at:
        # a motion draw is matched at its own pose, exactly as the motion proposal does (so
        # phi = 0 is the motion proposal), and with ``associate_at_sample`` an observation
        # draw is matched again at its sample too (the association at x_hat only shaped q).
        again = ~used_obs | config.associate_at_sample
        at_sample = _associate(config, params, particle, pose, obs)
        found = jax.tree.map(lambda a, b: jnp.where(again, a, b), at_sample, found)
        # A kept pose was not proposed: there is no density ratio to correct (and the zero
        # control's p_motion at it is NaN when the constant noise terms are 0).
        correction = jnp.where(keep_pose, jnp.zeros_like(correction), correction)
        return pose, found, correction, used_obs

    return jax.vmap(one)(jax.random.split(key_mixture, num), particles, motion_draw)


def _burst_pieces(config, params, particle: Particles, x_hat, control, obs):
    """The pieces' proposal of a bursty motion prior (``FilterConfig.burst_proposal``).

    The prior (1 - eps) N(x_hat, Sigma) + eps N(x_hat, kappa^2 Sigma) gives two FastSLAM 2.0
    Gaussians, each with its own association at x_hat (the burst piece's wider matching
    covariance finds the landmarks a burst moved), mixed by prior mass x evidence
    (``proposal.piece_mixture``; an observation a piece leaves unmatched is credited the
    new-landmark likelihood). With ``burst_turn_pieces`` n > 0 the burst's mass is shared
    half and half between its Gaussian and the 2n + 1 turn pieces of ``proposal.turn_pieces``,
    each associated and linearised at its own centre. Returns (``PieceMixture``, the pieces'
    ``_Association`` stacked on a leading (J,) axis).
    """
    motion = config.motion_model

    def piece(centre, cov):
        found = _associate(config, params, particle, centre, obs,
                           cov if config.match_pose_uncertainty else None)
        gaussian = proposal.observation_proposal(centre, cov, obs.z, found.local_match,
                                                 found.predicted)
        unexplained = jnp.sum(jnp.where(obs.valid & (found.match < 0),
                                        ekf.unexplained_log_likelihood(obs.z[:, 0], params),
                                        0.0))
        return gaussian._replace(log_evidence=gaussian.log_evidence + unexplained), found

    pieces = [piece(x_hat, proposal.motion_pose_covariance(particle.pose, control, params,
                                                           motion, factor))
              for factor in (1.0, params.motion_outlier_scale**2)]
    eps = params.motion_outlier_probability
    log_burst = jnp.log(jnp.maximum(eps, 0.0))
    log_prior = jnp.stack([jnp.log1p(-eps), log_burst])
    gaussians = proposal.stack_proposals([g for g, _ in pieces])
    founds = jax.tree.map(lambda *leaves: jnp.stack(leaves), *[f for _, f in pieces])
    if config.burst_turn_pieces > 0:
        centres, covs, log_mass = proposal.turn_pieces(
            particle.pose, control, params, motion, config.burst_turn_pieces,
            config.burst_turn_span)
        turn_gaussians, turn_founds = jax.vmap(piece)(centres, covs)
        concat = lambda a, b: jnp.concatenate([a, b])
        gaussians = jax.tree.map(concat, gaussians, turn_gaussians)
        founds = jax.tree.map(concat, founds, turn_founds)
        half = log_burst + jnp.log(0.5)
        log_prior = jnp.concatenate([jnp.stack([log_prior[0], half]), half + log_mass])
    return proposal.piece_mixture(gaussians, log_prior), founds


def _mixture_ratio(config, params, state):
    if config.proposal == "motion":
        return jnp.zeros((), state.log_weight.dtype)
    if config.proposal == "observation":
        return jnp.ones((), state.log_weight.dtype)
    if config.mixture_mode == "adaptive":
        return proposal.adaptive_ratio(state.likelihood_fast, state.likelihood_slow, params)
    return jnp.asarray(params.mixture_ratio, state.log_weight.dtype)


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


def _step(config: FilterConfig, key, state: FilterState, params: Params, control,
          obs: Observations):
    # One float dtype, the state's: float64 params or observations with a float32 state
    # would otherwise change the type of the scan carry (a no-op when they already match).
    params, control, obs = cast_floating((params, control, obs), state.particles.pose.dtype)
    key_propose, key_resample = jax.random.split(key)
    obs, num_invalid = sanitize_observations(obs)
    control, invalid_control = sanitize_control(control)
    # A masked control draws nothing from the observation proposal (phi 0, poses kept).
    ratio = jnp.where(invalid_control, 0.0, _mixture_ratio(config, params, state)).astype(
        state.log_weight.dtype)
    poses, found, correction, used_obs = _propose(
        config, key_propose, params, state.particles, control, obs, ratio, invalid_control)
    moved = state.particles._replace(pose=poses)
    result = jax.vmap(lambda particle, association_: _observe(config, params, particle,
                                                              association_, obs))(moved, found)
    unnormalised = state.log_weight + result.log_likelihood + correction
    log_weight, reset = resampling.normalize_log_weights(unnormalised)
    # log p(z_t | z_1:t-1): the particle filter's estimate of the incremental evidence.
    log_evidence = jax.scipy.special.logsumexp(unnormalised)

    num_valid = jnp.sum(obs.valid)
    mean_ll = jnp.sum(jnp.exp(state.log_weight) * result.log_likelihood) / jnp.maximum(
        num_valid, 1)
    fast, slow = proposal.update_likelihood_averages(
        state.likelihood_fast, state.likelihood_slow, mean_ll, num_valid > 0, state.step == 0,
        params)

    ess = resampling.effective_sample_size(log_weight)
    do_resample = ess < params.ess_threshold * config.num_particles

    best_before = jnp.argmax(log_weight).astype(jnp.int32)

    def resample(operand):
        particles, weights, best, _ = operand
        indices = resampling.resample_indices(key_resample, weights, config.resampling)
        uniform = jnp.full_like(weights, -jnp.log(config.num_particles))
        # The highest-weight particle's first copy (kept unless the scheme dropped it).
        copies = indices == best
        best = jnp.where(jnp.any(copies), jnp.argmax(copies), 0).astype(jnp.int32)
        return resampling.gather(particles, indices), uniform, best, indices.astype(jnp.int32)

    particles, log_weight, best_particle, ancestor = jax.lax.cond(
        do_resample, resample, lambda operand: operand,
        (result.particle, log_weight, best_before,
         jnp.arange(config.num_particles, dtype=jnp.int32)))
    new_state = FilterState(particles, log_weight, fast, slow, state.step + 1)
    info = StepInfo(
        ess=ess, resampled=do_resample, weights_reset=reset,
        num_landmarks=jnp.sum(particles.active, axis=1).astype(jnp.int32),
        match=result.match, match_rounds=jnp.max(result.rounds).astype(jnp.int32),
        num_invalid_obs=num_invalid, num_dropped_births=result.dropped,
        num_set_aside=result.set_aside, mixture_ratio=ratio,
        num_observation_draws=jnp.sum(used_obs).astype(jnp.int32),
        mean_log_likelihood=mean_ll, best_particle=best_particle, ancestor=ancestor,
        birth_slot=result.birth_slot, log_evidence=log_evidence,
        invalid_control=invalid_control,
    )
    return new_state, info


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
    )


def _check_lineage_slots(config: FilterConfig) -> None:
    if config.max_landmarks > jnp.iinfo(jnp.int16).max:
        raise ValueError(f"record_lineage stores slots as int16; max_landmarks="
                         f"{config.max_landmarks} exceeds {jnp.iinfo(jnp.int16).max}")


def scan_filter(config: FilterConfig, key, state: FilterState, params: Params, controls,
                observations: Observations, record_lineage: bool = False):
    """``lax.scan`` of ``step`` over T steps (traceable; vmap it over runs or params).

    Step t uses key ``fold_in(key, t)``. Returns (final state, ``Trace``); with
    ``record_lineage`` the trace carries every particle's ancestry and association
    (``Lineage``, for ``smoothing.smooth_lineage``). ``controls`` (T, 3) are not checked: a
    row with a NaN or inf is masked (poses kept, module docstring) and flagged in
    ``trace.invalid_control`` (T,).
    """
    step = make_filter(config).step
    if record_lineage:
        _check_lineage_slots(config)

    def body(carry: FilterState, inputs):
        t, control, obs = inputs
        new_state, info = step(jax.random.fold_in(key, t), carry, params, control, obs)
        return new_state, _trace_row(new_state, info, record_lineage)

    steps = jnp.arange(controls.shape[0], dtype=jnp.int32)
    return jax.lax.scan(body, state, (steps, controls, observations))


@functools.partial(jax.jit, static_argnums=(0, 6))
def _run_filter_jit(config, key, params, controls, observations, initial_pose,
                    record_lineage=False):
    state = make_filter(config).init(initial_pose, dtype=controls.dtype)
    return scan_filter(config, key, state, params, controls, observations, record_lineage)


def run_filter(config: FilterConfig | Filter, key, params: Params, controls,
               observations: Observations, initial_pose=None, record_lineage: bool = False):
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
    Returns:
      (final ``FilterState``, ``Trace`` with leading axis T).
    Raises:
      ValueError: bad shapes, a non-finite control row (concrete controls only: under jit or
        vmap the row is masked as in ``scan_filter``), or ``Params`` that
        ``validation.check_params`` refuses. Float leaves of ``params`` and ``observations``
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
    return _run_filter_jit(config, key, params, controls, observations,
                           jnp.asarray(initial_pose, controls.dtype), bool(record_lineage))
