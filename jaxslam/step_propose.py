"""Stages 1-2 of one FastSLAM step: where each particle goes and what it sees from there.

1. ``propose``: a pose x_t^i per particle from the motion model, the FastSLAM 2.0
   observation proposal (Montemerlo et al., "FastSLAM 2.0: An Improved Particle Filtering
   Algorithm for Simultaneous Localization and Mapping that Provably Converges", 2003) or
   their mixture, with the log density ratio log p(x | x_{t-1}, u) - log q(x) -> ``Proposal``;
2. ``associate``: at one pose, predict every landmark's measurement, gate and match the
   observations (visibility boundary of ``landmarks.py``, kernels of ``association.py``)
   -> ``Association``.

Stages 3-6 (EKF update, weight, map, resampling) are in ``step_update.py``; ``filter._step``
composes them. Shapes: P particles, M landmark slots, K observation rows; ``associate`` acts
on ONE particle and is vmapped over particles.
"""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxslam import association, ekf, landmarks, proposal
from jaxslam.motion import predict_pose, sample_motion
from jaxslam.types import FilterConfig, FilterState, Observations, Params, Particles

# --------------------------------------------------------------------------------------------
# Stage 1: propose


class Proposal(NamedTuple):
    """New poses and the association each particle is updated with.

    pose: (P, 3) proposed poses x_t^i.
    association: ``Association`` with a leading (P,) axis, computed at ``pose`` (or at x_hat
      for an observation draw without ``associate_at_sample``).
    log_correction: (P,) log p(x_t^i | x_{t-1}^i, u_t) - log q(x_t^i), 0 for the motion
      proposal and for kept poses.
    used_observation: (P,) bool, drawn from the observation proposal.
    ratio: (P,) the phi each particle was drawn with (``adaptive`` mixture: per particle).
    """

    pose: jnp.ndarray
    association: Association
    log_correction: jnp.ndarray
    used_observation: jnp.ndarray
    ratio: jnp.ndarray


def mixture_ratio(config: FilterConfig, params: Params, state: FilterState):
    """() phi, the probability of drawing from the observation proposal this step (for the
    ``adaptive`` mixture the floor under each particle's own phi, ``particle_ratio``)."""
    if config.proposal == "motion":
        return jnp.zeros((), state.log_weight.dtype)
    if config.proposal == "observation":
        return jnp.ones((), state.log_weight.dtype)
    if config.mixture_mode == "adaptive":
        return proposal.adaptive_ratio(state.likelihood_fast, state.likelihood_slow, params)
    return jnp.asarray(params.mixture_ratio, state.log_weight.dtype)


def particle_ratio(config: FilterConfig, params: Params, efficiency, ratio):
    """() phi of one particle: ``ratio`` () for the fixed mixture (and the other proposals);
    for the ``adaptive`` mixture

        phi_i = clip(max(phi_aug, phi_min + (phi_max - phi_min) (1 - eta_i)), phi_min, phi_max),

    phi_aug = ``ratio`` the augmented-MCL phi of the likelihood averages (Thrun, Burgard and
    Fox, Probabilistic Robotics, table 8.3: it rises after a sudden drop of the likelihood)
    and eta_i = ``efficiency`` () the expected effective-sample fraction of this particle's
    motion draws weighed toward its observation proposal (``_observation_gaussian``). The
    second term answers the regime of an accurate sensor and poor odometry, where the
    likelihood stays low at every step, so phi_aug stays at phi_min, while motion draws land
    far from where the observations put the pose (eta near 0). A particle without a match
    takes a motion draw whatever phi is.
    """
    if not (config.proposal == "mixture" and config.mixture_mode == "adaptive"):
        return ratio
    coverage = proposal.coverage_ratio(efficiency, params).astype(ratio.dtype)
    return jnp.clip(jnp.maximum(ratio, coverage), params.mixture_min, params.mixture_max)


def _motion_draws(config: FilterConfig, key, params: Params, particles: Particles, control,
                  keep_pose):
    """(P, 3) draws x ~ p(x | x_{t-1}, u_t); the motion mean for a particle with an empty
    map (``anchor_empty_map``), the previous pose when ``keep_pose``."""
    motion = config.motion_model
    draw = jax.vmap(lambda k, pose: sample_motion(k, pose, control, params, motion))(
        jax.random.split(key, config.num_particles), particles.pose)
    if config.anchor_empty_map:
        # Nothing observed can ever tell an empty-map particle's pose error from the map's
        # frame, so it takes the motion mean (the map frame is that pose).
        mean = jax.vmap(lambda pose: predict_pose(pose, control, params, motion))(
            particles.pose)
        draw = jnp.where(jnp.any(particles.active, axis=1)[:, None], draw, mean)
    # Missing control: with ratio 0 no particle takes the observation draw, so every
    # proposal returns these kept poses.
    return jnp.where(keep_pose, particles.pose, draw)


def _matching_cov(config, params, pose_cov):
    """The pose covariance (3, 3) that the association at the motion prediction (or at a
    turn piece's centre) adds to S, or None.

    Sigma_u + diag(0, 0, s^2), s = ``Params.association_heading_std``, with
    ``match_pose_uncertainty``; None (S alone) without. Only the matching sees s: the
    proposal, the update and the weight keep Sigma_u.
    """
    if not config.match_pose_uncertainty:
        return None
    heading_var = jnp.square(params.association_heading_std).astype(pose_cov.dtype)
    return pose_cov.at[2, 2].add(heading_var)


def _burst_pieces(config, params, particle: Particles, x_hat, control, obs):
    """The pieces' proposal of a bursty motion prior (``FilterConfig.burst_proposal``).

    The prior (1 - eps) N(x_hat, Sigma) + eps N(x_hat, kappa^2 Sigma) gives two FastSLAM 2.0
    Gaussians, each with its own association at x_hat (the burst piece's wider matching
    covariance finds the landmarks a burst moved), mixed by prior mass x evidence
    (``proposal.piece_mixture``; an observation a piece leaves unmatched is credited the
    new-landmark likelihood). With ``burst_turn_pieces`` n > 0 the burst's mass is shared
    half and half between its Gaussian and the 2n + 1 turn pieces of ``proposal.turn_pieces``,
    each associated and linearised at its own centre. Returns (``PieceMixture``, the pieces'
    ``Association`` stacked on a leading (J,) axis, the motion draws' efficiency () toward
    the mixture: ``proposal.mixture_draw_efficiency`` over the pieces, the burst mixture
    (with its turn pieces) standing for the motion draws).
    """
    motion = config.motion_model

    def piece(centre, cov):
        found = associate(config, params, particle, centre, obs, _matching_cov(config, params, cov))
        gaussian = _relinearised(config, params, particle, centre, cov, obs, found)
        unexplained = jnp.sum(jnp.where(obs.valid & (found.match < 0),
                                        ekf.unexplained_log_likelihood(obs.z[:, 0], params),
                                        0.0))
        return (gaussian._replace(log_evidence=gaussian.log_evidence + unexplained), found,
                proposal.piece_draw_efficiency(gaussian, centre, cov))

    pieces = [piece(x_hat, proposal.motion_pose_covariance(particle.pose, control, params,
                                                           motion, factor))
              for factor in (1.0, params.motion_outlier_scale**2)]
    eps = params.motion_outlier_probability
    log_burst = jnp.log(jnp.maximum(eps, 0.0))
    log_prior = jnp.stack([jnp.log1p(-eps), log_burst])
    gaussians = proposal.stack_proposals([g for g, _, _ in pieces])
    founds = jax.tree.map(lambda *leaves: jnp.stack(leaves), *[f for _, f, _ in pieces])
    efficiencies = jnp.stack([e for _, _, e in pieces])
    if config.burst_turn_pieces > 0:
        centres, covs, log_mass = proposal.turn_pieces(
            particle.pose, control, params, motion, config.burst_turn_pieces,
            config.burst_turn_span)
        turn_gaussians, turn_founds, turn_efficiencies = jax.vmap(piece)(centres, covs)
        concat = lambda a, b: jnp.concatenate([a, b])
        gaussians = jax.tree.map(concat, gaussians, turn_gaussians)
        founds = jax.tree.map(concat, founds, turn_founds)
        efficiencies = concat(efficiencies, turn_efficiencies)
        half = log_burst + jnp.log(0.5)
        log_prior = jnp.concatenate([jnp.stack([log_prior[0], half]), half + log_mass])
    mixture = proposal.piece_mixture(gaussians, log_prior)
    return mixture, founds, proposal.mixture_draw_efficiency(efficiencies, log_prior,
                                                             mixture.log_weights)


def _observation_gaussian(config, params, particle: Particles, x_hat, control, obs):
    """FastSLAM 2.0 proposal of one particle at x_hat (3,): (Gaussian or piece mixture, the
    association at x_hat (leading (J,) axis for the pieces), the expected effective-sample
    fraction () of motion draws weighed toward it (``proposal.piece_draw_efficiency``; without
    ``burst_proposal`` the motion prior is taken as the one Gaussian N(x_hat, Sigma_u) with the
    bursts' mean variance). Outputs nobody reads (the efficiency outside the adaptive
    mixture) are dropped by XLA."""
    if config.burst_proposal:
        return _burst_pieces(config, params, particle, x_hat, control, obs)
    pose_cov = proposal.motion_pose_covariance(particle.pose, control, params,
                                               config.motion_model)
    found = associate(config, params, particle, x_hat, obs,
                      _matching_cov(config, params, pose_cov))
    gaussian = _relinearised(config, params, particle, x_hat, pose_cov, obs, found)
    return gaussian, found, proposal.piece_draw_efficiency(gaussian, x_hat, pose_cov)


def _relinearised(config, params, particle: Particles, x_hat, pose_cov, obs, found):
    """The FastSLAM 2.0 Gaussian of one prior piece (centre x_hat (3,), Sigma_u (3, 3)) with
    the association ``found`` made at x_hat, relinearised ``config.proposal_iterations``
    times at its own mean (``proposal.relinearised_proposal``)."""
    gaussian = proposal.observation_proposal(x_hat, pose_cov, obs.z, found.local_match,
                                             found.predicted)
    if config.proposal_iterations == 0:
        return gaussian
    rows = jnp.clip(found.match, 0)
    return proposal.relinearised_proposal(
        gaussian, x_hat, pose_cov, obs.z, found.match >= 0, particle.landmark_mean[rows],
        particle.landmark_cov[rows], params=params, iterations=config.proposal_iterations)


def propose(config: FilterConfig, key, params: Params, particles: Particles, control,
            obs: Observations, ratio, keep_pose) -> Proposal:
    """Stage 1 (with stage 2 at the proposed poses): x_t^i ~ (1 - phi) p(x | x_{t-1}, u)
    + phi_i q(x | x_{t-1}, u, z) for every particle: phi_i = ``ratio`` (), or for the
    adaptive mixture each particle's own phi with ``ratio`` as its floor (``particle_ratio``).

    ``keep_pose`` () bool (a masked control: ``control`` is then 0 and ``ratio`` 0): every
    particle keeps its pose, is associated there and gets correction 0; the draws are still
    made (same keys) and dropped by ``where``.
    """
    num = config.num_particles
    key_motion, key_mixture = jax.random.split(key)
    motion_draw = _motion_draws(config, key_motion, params, particles, control, keep_pose)
    if config.proposal == "motion":
        found = jax.vmap(lambda particle, pose: associate(config, params, particle, pose, obs))(
            particles, motion_draw)
        return Proposal(motion_draw, found, jnp.zeros((num,), motion_draw.dtype),
                        jnp.zeros(num, bool), jnp.zeros((num,), motion_draw.dtype))

    def one(k, particle, motion_sample):
        x_hat = predict_pose(particle.pose, control, params, config.motion_model)
        gaussian, found, efficiency = _observation_gaussian(config, params, particle, x_hat,
                                                            control, obs)
        cut_at_x_hat = jnp.max(found.window_cut)  # every piece's association shaped q
        phi = jnp.where(keep_pose, ratio, particle_ratio(config, params, efficiency, ratio))
        pose, used_obs, piece = proposal.mixture_sample(k, motion_sample, gaussian, phi)
        if config.burst_proposal:
            found = jax.tree.map(lambda leaf: leaf[piece], found)
        correction = proposal.mixture_log_correction(particle.pose, pose, control, params,
                                                     config.motion_model, gaussian, phi)
        # The update and the weight use the association at the pose they are evaluated at:
        # a motion draw is matched at its own pose, exactly as the motion proposal does (so
        # phi = 0 is the motion proposal), and with ``associate_at_sample`` an observation
        # draw is matched again at its sample too (the association at x_hat only shaped q).
        again = ~used_obs | config.associate_at_sample
        at_sample = associate(config, params, particle, pose, obs)
        found = jax.tree.map(lambda a, b: jnp.where(again, a, b), at_sample, found)
        found = found._replace(window_cut=jnp.maximum(found.window_cut, cut_at_x_hat))
        # A kept pose was not proposed: there is no density ratio to correct (and the zero
        # control's p_motion at it is NaN when the constant noise terms are 0).
        correction = jnp.where(keep_pose, jnp.zeros_like(correction), correction)
        return pose, found, correction, used_obs, phi

    return Proposal(*jax.vmap(one)(jax.random.split(key_mixture, num), particles, motion_draw))


# --------------------------------------------------------------------------------------------
# Stage 2: predict and associate at one pose


class Association(NamedTuple):
    """Association of one particle's observations, computed at its matching pose.

    match: (K,) int32 landmark slot of each observation, -1 when unmatched.
    rounds: () int32 matching rounds used.
    visibility: ``landmarks.Visibility`` with (M,) landmark flags over all slots.
    predicted: ``ekf.PredictedMeasurement`` with (N,) leaves at the matching pose, over the
      N landmarks of the association window (all M slots without a window).
    local_match: (K,) int32 index into ``predicted`` (-1: unmatched).
    window_cut: () int32 landmarks that could have taken part but fell outside the
      association window (0 without one; ``_window``).
    """

    match: jnp.ndarray
    rounds: jnp.ndarray
    visibility: landmarks.Visibility
    predicted: ekf.PredictedMeasurement
    local_match: jnp.ndarray
    window_cut: jnp.ndarray


def _window(config: FilterConfig, params: Params, particle: Particles, pose, obs: Observations,
            pose_cov=None):
    """The N = ``association_window`` active landmarks nearest ``pose`` (3,).

    Returns (slots (N,) int32, the particle restricted to them, cut () int32), or
    (None, particle, 0) when the window covers every slot: predictions and pair costs then
    cost O(K N) instead of O(K M). ``cut`` counts the landmarks outside the window that could
    have taken part in the association with these observations (``landmarks.may_take_part``;
    for ``known`` ids the region alone): while it is 0 the window changes nothing but the
    order of the pairs.
    """
    window = config.association_window
    if not 0 < window < config.max_landmarks:
        return None, particle, jnp.zeros((), jnp.int32)
    distance = jnp.hypot(particle.landmark_mean[:, 0] - pose[0],
                         particle.landmark_mean[:, 1] - pose[1])
    _, slots = jax.lax.top_k(-jnp.where(particle.active, distance, jnp.inf), window)
    local = particle._replace(landmark_mean=particle.landmark_mean[slots],
                              landmark_cov=particle.landmark_cov[slots],
                              landmark_radius=particle.landmark_radius[slots],
                              radius_count=particle.radius_count[slots],
                              active=particle.active[slots],
                              landmark_id=particle.landmark_id[slots])
    outside = jnp.ones(config.max_landmarks, bool).at[slots].set(False)
    gated = config.association != "known"  # known ids are matched whatever the distance
    in_view = landmarks.may_take_part(pose, particle.landmark_mean, particle.landmark_cov,
                                      particle.active, params, config.boundary,
                                      *((obs.z, obs.valid, pose_cov) if gated else ()))
    return slots, local, jnp.sum(in_view & outside).astype(jnp.int32)


def _to_slots(window_values, slots, num_slots: int):
    """(N,) bool flags of the windowed landmarks -> (M,) over all slots (False elsewhere)."""
    return jnp.zeros((num_slots,), bool).at[slots].set(window_values)


def associate(config: FilterConfig, params: Params, particle: Particles, match_pose,
              obs: Observations, pose_cov=None) -> Association:
    """Predict, gate and match one particle's K observations at ``match_pose`` (3,).

    With z_hat_m, S_m the predicted measurement of landmark m (``ekf.predict_measurements``)
    the pair cost is d2[k, m] = nu^T S_m^-1 nu, nu = z_k - z_hat_m (bearing wrapped), plus
    d_r2[k, m] of the trunk radius when ``Params.radius_noise`` > 0; the visibility boundary
    (hard or loose airlock, position only) decides which pairs may be formed.

    ``match_pose`` is the sampled pose for the motion proposal and the motion prediction
    x_hat for the observation and mixture proposals. ``pose_cov`` (3, 3), when given, is
    added to S for the gate and the matching only (``ekf.add_pose_uncertainty``);
    ``predicted`` keeps S. The loose boundary is decided with S alone: its ring widths
    w_m = airlock_sigmas sqrt(S_m[range, range]) and the gate that sets aside an observation
    that could match a ring landmark (or keeps a landmark from penalties). So an observation
    nearer than R_max - w_k still cannot pair with a landmark beyond the ring, as
    ``landmarks`` states, whatever the pose covariance (``tests/test_matching_airlock.py``).
    """
    slots, local, cut = _window(config, params, particle, match_pose, obs, pose_cov)
    predicted = ekf.predict_measurements(match_pose, local.landmark_mean, local.landmark_cov,
                                         params)
    local_predicted = (predicted if pose_cov is None
                       else ekf.add_pose_uncertainty(predicted, pose_cov))
    pairs = obs.valid[:, None] & local.active[None, :]
    mahalanobis = jnp.where(pairs, ekf.mahalanobis_sq(obs.z, local_predicted), jnp.inf)
    boundary_distance = (mahalanobis if pose_cov is None
                         else jnp.where(pairs, ekf.mahalanobis_sq(obs.z, predicted), jnp.inf))
    vis = landmarks.visibility(obs.z, obs.valid, local.active, predicted, boundary_distance,
                               params, config.boundary)
    radius_sq = ekf.radius_distance_sq(obs.radius[:, None], local.landmark_radius[None, :],
                                       local.radius_count[None, :], params)
    allowed = vis.matching_obs[:, None] & vis.matchable[None, :]
    cost = association.association_cost(config.association, mahalanobis + radius_sq, allowed,
                                        obs.landmark_id, local.landmark_id, local.active)
    local_match, rounds = association.match(config.association, cost,
                                            params.association_gate, config.match_rounds)
    match = local_match
    if slots is not None:
        match = jnp.where(local_match >= 0, slots[jnp.clip(local_match, 0)],
                          -1).astype(jnp.int32)
        vis = vis._replace(**{name: _to_slots(getattr(vis, name), slots, config.max_landmarks)
                              for name in ("matchable", "explained", "expected")})
    return Association(match, rounds, vis, predicted, local_match, cut)
