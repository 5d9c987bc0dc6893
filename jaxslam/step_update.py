"""Stages 3-6 of one FastSLAM step: what the observations do to each particle.

Given each particle's proposed pose and its association (``step_propose.py``):

3. ``update_landmarks``: EKF update of the matched landmarks and the per-observation
   log-likelihood log p(z_k | x, m) -> ``LandmarkUpdate``;
4. ``weigh``: log w_i += sum_k log p(z_k | x_t^i, m) + the proposal's log correction,
   normalised -> ``Weights``;
5. ``manage_map``: existence evidence, deletion below ``existence_delete``, births of
   unexplained observations in free slots -> ``MapUpdate``;
6. ``resample`` when ESS < ess_threshold * P -> ``Resampled``.

Montemerlo et al., "FastSLAM: A Factored Solution to the Simultaneous Localization and
Mapping Problem", 2002; Geiser et al., "Practical Implementation of FastSLAM for Forestry
Robot", ICAROB 2023. Shapes: P particles, M landmark slots, K observation rows; stages 3 and
5 act on ONE particle and are vmapped over particles.
"""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxslam import association, ekf, landmarks, proposal, resampling
from jaxslam.geometry import wrap_angle
from jaxslam.step_propose import Association
from jaxslam.types import FilterConfig, FilterState, Observations, Params, Particles

# --------------------------------------------------------------------------------------------
# Stage 3: EKF update and per-observation likelihood (one particle)


class LandmarkUpdate(NamedTuple):
    """One particle after the EKF update of its matched landmarks.

    particle: ``Particles`` without the P axis: matched slots' mean (M, 2), cov (M, 3),
      radius (M,), observation_count and radius_count (M,) updated; the rest untouched.
    log_likelihood: (K,) log p(z_k | x, m): log N(nu_k; 0, S_k) (+ the radius term) for a
      matched observation, the new-landmark constant for an unmatched one, 0 for a padding
      or masked row.
    matched_slot: (M,) bool, the slot was matched by an observation this step.
    """

    particle: Particles
    log_likelihood: jnp.ndarray
    matched_slot: jnp.ndarray


def _matched_predictions(config, params, particle: Particles, found: Association):
    """Predicted measurement (K,) of each observation's matched landmark at ``particle.pose``
    (row 0's for an unmatched observation, whose results the caller drops)."""
    if config.proposal == "motion":
        # The association was computed at this very pose.
        return jax.tree.map(lambda leaf: leaf[jnp.clip(found.local_match, 0)], found.predicted)
    rows = jnp.clip(found.match, 0)
    return ekf.predict_measurements(particle.pose, particle.landmark_mean[rows],
                                    particle.landmark_cov[rows], params)


def _observation_log_likelihood(params, particle: Particles, obs, match, pred_k):
    """(K,) log p(z_k | x, m) of ``LandmarkUpdate``: with nu = (dr, wrap(db)) and
    S^-1 = [[i_rr, i_rb], [i_rb, i_bb]], d2 = nu^T S^-1 nu (+ d_r2 of the radius) and
    log N = -d2 / 2 - log det S / 2 - log 2 pi (``ekf.gaussian_log_likelihood``)."""
    rows = jnp.clip(match, 0)
    d_range = obs.z[:, 0] - pred_k.range
    d_bearing = wrap_angle(obs.z[:, 1] - pred_k.bearing)
    mahalanobis_k = ekf.innovation_mahalanobis_sq(d_range, d_bearing, pred_k.i_rr, pred_k.i_rb,
                                                  pred_k.i_bb)
    radius_k = ekf.radius_distance_sq(obs.radius, particle.landmark_radius[rows],
                                      particle.radius_count[rows], params)
    matched_ll = ekf.gaussian_log_likelihood(mahalanobis_k + radius_k, pred_k.log_det)
    unexplained_ll = ekf.unexplained_log_likelihood(obs.z[:, 0], params)
    return jnp.where(obs.valid, jnp.where(match >= 0, matched_ll, unexplained_ll), 0.0)


def _running_radius(particle: Particles, matched_slot, radius_obs):
    """Running mean (M,) of the measured radii r: r_bar += (r - r_bar) / n over the n > 0
    measured ones only (a landmark with none yet takes the first). Returns (radius, n)."""
    has_radius = matched_slot & (radius_obs > 0)
    radius_count = particle.radius_count + has_radius.astype(jnp.int32)
    running = particle.landmark_radius + (radius_obs - particle.landmark_radius) / jnp.maximum(
        radius_count, 1)
    return jnp.where(has_radius, running, particle.landmark_radius), radius_count


def update_landmarks(config: FilterConfig, params: Params, particle: Particles,
                     found: Association, obs: Observations) -> LandmarkUpdate:
    """Stage 3 for one particle at ``particle.pose``: EKF update of the <= K matched slots
    (``ekf.update_landmarks``: G = Sigma H^T S^-1, m' = m + G nu, Joseph-form Sigma') and
    the per-observation log-likelihood. Unmatched slots are not predicted again."""
    num_slots, match = config.max_landmarks, found.match
    slot_of_obs = jnp.where(match >= 0, match, num_slots)  # (K,), M: dropped by the scatter
    obs_of_slot = jnp.full((num_slots,), -1, jnp.int32).at[slot_of_obs].set(
        jnp.arange(match.shape[0], dtype=jnp.int32), mode="drop")  # (M,)
    matched_slot = obs_of_slot >= 0
    pred_k = _matched_predictions(config, params, particle, found)
    log_likelihood = _observation_log_likelihood(params, particle, obs, match, pred_k)
    rows = jnp.clip(match, 0)
    new_mean, new_cov = ekf.update_landmarks(particle.landmark_mean[rows],
                                             particle.landmark_cov[rows], pred_k, obs.z, params)
    radius, radius_count = _running_radius(particle, matched_slot,
                                           obs.radius[jnp.clip(obs_of_slot, 0)])
    # One-to-one matching: no two observations write the same slot.
    updated = particle._replace(
        landmark_mean=particle.landmark_mean.at[slot_of_obs].set(new_mean, mode="drop"),
        landmark_cov=particle.landmark_cov.at[slot_of_obs].set(new_cov, mode="drop"),
        landmark_radius=radius, radius_count=radius_count,
        observation_count=particle.observation_count + matched_slot.astype(jnp.int32))
    return LandmarkUpdate(updated, log_likelihood, matched_slot)


# --------------------------------------------------------------------------------------------
# Stage 4: weight


class Weights(NamedTuple):
    """The particles' weights after this step's evidence, before resampling.

    log_weight: (P,) normalised log w_i. reset: () bool, every weight was zero (-inf) and
      they were reset to uniform.
    log_evidence: () log sum_i w_{i,t-1} p(z_t | x_t^i) x correction_i, the particle
      filter's estimate of log p(z_t | z_1:t-1).
    mean_log_likelihood: () sum_i w_{i,t-1} log p(z_t | x_t^i) / max(#valid rows, 1).
    likelihood_fast, likelihood_slow: () running averages of it (``proposal``'s adaptive
      mixture ratio).
    """

    log_weight: jnp.ndarray
    reset: jnp.ndarray
    log_evidence: jnp.ndarray
    mean_log_likelihood: jnp.ndarray
    likelihood_fast: jnp.ndarray
    likelihood_slow: jnp.ndarray


def weigh(params: Params, state: FilterState, log_likelihood, log_correction,
          obs_valid) -> Weights:
    """Stage 4: log w_i = log w_{i,t-1} + log_likelihood[i] + log_correction[i], normalised.

    ``log_likelihood`` (P,) sums ``LandmarkUpdate.log_likelihood`` over observations,
    ``log_correction`` (P,) is ``Proposal.log_correction``, ``obs_valid`` (K,).
    """
    unnormalised = state.log_weight + log_likelihood + log_correction
    log_weight, reset = resampling.normalize_log_weights(unnormalised)
    log_evidence = jax.scipy.special.logsumexp(unnormalised)
    num_valid = jnp.sum(obs_valid)
    mean_ll = jnp.sum(jnp.exp(state.log_weight) * log_likelihood) / jnp.maximum(num_valid, 1)
    fast, slow = proposal.update_likelihood_averages(
        state.likelihood_fast, state.likelihood_slow, mean_ll, num_valid > 0, state.step == 0,
        params)
    return Weights(log_weight, reset, log_evidence, mean_ll, fast, slow)


# --------------------------------------------------------------------------------------------
# Stage 5: manage the map (one particle)


class MapUpdate(NamedTuple):
    """One particle's map after evidence, deletion and births.

    particle: ``Particles`` without the P axis.
    birth_slot: (K,) int32 slot of the landmark each observation created, -1 for none.
    num_dropped: () int32 births that found no free slot (the map was full).
    num_set_aside: () int32 observations set aside in the airlock (never born; with
      ``loose_match`` possibly matched).
    """

    particle: Particles
    birth_slot: jnp.ndarray
    num_dropped: jnp.ndarray
    num_set_aside: jnp.ndarray


def _surviving(params: Params, particle: Particles, matched_slot, vis: landmarks.Visibility):
    """Existence log-odds (M,) after this step's hits and misses, and the (M,) bool slots
    kept: active with log-odds >= ``existence_delete``. A miss is an expected landmark that
    was neither matched nor explained by a set-aside observation (``landmarks.py``)."""
    missed = vis.expected & ~matched_slot & ~vis.explained
    existence = landmarks.update_existence(particle.existence, matched_slot, missed, params)
    return existence, particle.active & (existence >= params.existence_delete)


def _clear_slots(particle: Particles, existence, keep) -> Particles:
    """The particle with every slot not in ``keep`` (M,) reset to the empty-slot values."""
    empty_mean, empty_cov, empty_radius = landmarks.empty_slot_values(
        keep.shape[0], particle.landmark_mean.dtype)
    return particle._replace(
        landmark_mean=jnp.where(keep[:, None], particle.landmark_mean, empty_mean),
        landmark_cov=jnp.where(keep[:, None], particle.landmark_cov, empty_cov),
        landmark_radius=jnp.where(keep, particle.landmark_radius, empty_radius),
        observation_count=jnp.where(keep, particle.observation_count, 0),
        radius_count=jnp.where(keep, particle.radius_count, 0),
        landmark_id=jnp.where(keep, particle.landmark_id, -1),
        active=keep,
        existence=jnp.where(keep, existence, 0.0))


def _give_birth(params: Params, particle: Particles, birth, obs: Observations):
    """Write a landmark for each ``birth`` (K,) observation into the first free slots:
    mean = x + r (cos(theta + b), sin(theta + b)), covariance G R G^T
    (``ekf.initialize_landmarks``), existence ``existence_init``, count 1.
    Returns (particle, slot (K,) int32 with M for none, dropped () int32)."""
    slot, dropped = landmarks.birth_slots(particle.active, birth)
    born_mean, born_cov = ekf.initialize_landmarks(particle.pose, obs.z, params)
    scatter = landmarks.scatter_rows
    born = particle._replace(
        landmark_mean=scatter(particle.landmark_mean, slot, born_mean),
        landmark_cov=scatter(particle.landmark_cov, slot, born_cov),
        landmark_radius=scatter(particle.landmark_radius, slot, obs.radius),
        landmark_id=scatter(particle.landmark_id, slot, obs.landmark_id),
        active=particle.active.at[slot].set(True, mode="drop"),
        existence=scatter(particle.existence, slot, jnp.broadcast_to(
            params.existence_init, slot.shape).astype(particle.existence.dtype)),
        observation_count=scatter(particle.observation_count, slot, jnp.ones_like(slot)),
        radius_count=scatter(particle.radius_count, slot, (obs.radius > 0).astype(jnp.int32)))
    return born, slot, dropped


def manage_map(config: FilterConfig, params: Params, updated: LandmarkUpdate,
               found: Association, obs: Observations) -> MapUpdate:
    """Stage 5 for one particle: matched landmarks gain log(p_d / p_f), expected unmatched
    ones gain log((1 - p_d) / (1 - p_f)); landmarks below ``existence_delete`` are deleted;
    usable unmatched observations are born in free slots (``association.birth_candidates``
    restricts them for known ids), never overwriting an active landmark."""
    particle, vis = updated.particle, found.visibility
    existence, keep = _surviving(params, particle, updated.matched_slot, vis)
    # Candidates are judged against the map before deletion.
    birth = association.birth_candidates(
        config.association, vis.usable_obs & (found.match < 0), obs.landmark_id,
        particle.landmark_id, particle.active)
    born, slot, dropped = _give_birth(params, _clear_slots(particle, existence, keep), birth,
                                      obs)
    birth_slot = jnp.where(slot < config.max_landmarks, slot, -1).astype(jnp.int32)
    return MapUpdate(born, birth_slot, dropped,
                     jnp.sum(vis.set_aside_obs).astype(jnp.int32))


# --------------------------------------------------------------------------------------------
# Stage 6: resample


class Resampled(NamedTuple):
    """The particles after the resampling decision.

    particles: ``Particles`` (P leading axis). log_weight: (P,) uniform when resampled.
    ess: () effective sample size 1 / sum_i w_i^2 before resampling. resampled: () bool.
    best_particle: () int32 index of a copy of the highest-weight particle before resampling.
    ancestor: (P,) int32 particle i is a copy of particle ancestor[i] (arange(P) if kept).
    """

    particles: Particles
    log_weight: jnp.ndarray
    ess: jnp.ndarray
    resampled: jnp.ndarray
    best_particle: jnp.ndarray
    ancestor: jnp.ndarray


def resample(config: FilterConfig, params: Params, key, particles: Particles,
             log_weight) -> Resampled:
    """Stage 6: draw P ancestors a_i ~ w (``config.resampling``) when
    ESS < ess_threshold * P, then uniform weights; otherwise keep everything."""
    num = config.num_particles
    ess = resampling.effective_sample_size(log_weight)
    do_resample = ess < params.ess_threshold * num
    best_before = jnp.argmax(log_weight).astype(jnp.int32)

    def draw(operand):
        particles, weights, best, _ = operand
        indices = resampling.resample_indices(key, weights, config.resampling)
        uniform = jnp.full_like(weights, -jnp.log(num))
        # The highest-weight particle's first copy (kept unless the scheme dropped it).
        copies = indices == best
        best = jnp.where(jnp.any(copies), jnp.argmax(copies), 0).astype(jnp.int32)
        return resampling.gather(particles, indices), uniform, best, indices.astype(jnp.int32)

    particles, log_weight, best, ancestor = jax.lax.cond(
        do_resample, draw, lambda operand: operand,
        (particles, log_weight, best_before, jnp.arange(num, dtype=jnp.int32)))
    return Resampled(particles, log_weight, ess, do_resample, best, ancestor)
