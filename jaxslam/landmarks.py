"""Landmark life cycle in masked slots: visibility, the loose-boundary airlock, evidence, birth,
death. All functions act on ONE particle's map; the filter vmaps them over particles.

Loose boundary (Geiser et al. 2023, section 3.1, Fig. 3). Near the lidar's maximum range R_max, noise
can put a particle's landmark just inside the range while its tree is just beyond (the hard
boundary then deletes the landmark), or the reverse (the hard boundary creates a twin). The
airlock is a ring inside R_max whose width follows from the correspondence threshold:

    observation k:  w_k = airlock_sigmas * sigma_range(z_k)        (its own range noise)
    landmark m:     w_m = airlock_sigmas * sqrt(S_m[range, range]) (predicted range std)

With airlock_sigmas = sqrt(gate), no observation closer than R_max - w_k can be associated
with an invisible landmark, and vice versa. An observation is set aside when
z_k > R_max - w_k or when it could match (d2 <= gate) a landmark in the ring
(R_max - w_m < r_m <= R_max + w_m). Only landmarks inside R_max - w_m take part in matching.
Unmatched observations that were not set aside create landmarks; unmatched matchable
landmarks that no set-aside observation could explain lose evidence. Landmarks in the ring
keep their evidence. When all K observation rows are used, the sensor may have dropped farther
trunks (detectors keep the K nearest): landmarks beyond the farthest observation are then not
penalised either. The hard boundary uses R_max alone: every observation within range is
matched or creates a landmark, every unmatched landmark within range loses evidence.

Matching across the airlock (``boundary="loose_match"``). The paper calls the loose boundary
"wasteful but safe": the set-aside observations carry no information to the filter. Their only
danger is at birth and death, so ``loose_match`` keeps the airlock's rules for those (a
set-aside observation never creates a landmark, a landmark in the ring or explained by a
set-aside observation is never penalised) but lets every valid observation take part in the
matching, against the landmarks inside R_max - w_m and those in the ring. A matched pair must
still pass the gate and win the stable matching, as anywhere; what changes is that an
observation near the range limit of a tree already mapped updates that landmark and the
particle's weight instead of being thrown away. With a noisy range the ring is wide (w_k =
5 sigma_r(z_k): 1.6 m at 12 m for a range std of 0.025 d + 0.01) and holds a large share of
the observations (docs/results.md, "Matching across the airlock").

Existence evidence in log-odds (detection probability p_d, false alarm probability p_f):
hit += log(p_d / p_f), miss += log((1 - p_d) / (1 - p_f)), clipped to +-existence_max;
a landmark is deleted when its log-odds fall below ``existence_delete``.
"""
from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp

from jaxslam.ekf import PredictedMeasurement, measurement_std, pose_share_terms, sandwich
from jaxslam.geometry import range_bearing_jacobian_point
from jaxslam.types import BOUNDARIES, Params


class Visibility(NamedTuple):
    """Which observations and landmarks take part in matching (one particle).

    usable_obs: (K,) valid observations that take part in matching and create a landmark
      when unmatched.
    set_aside_obs: (K,) valid observations set aside in the airlock (never create landmarks;
      with ``loose_match`` they still take part in matching).
    matchable: (M,) active landmarks that take part in matching (``loose_match``: the ring's
      too).
    explained: (M,) landmarks a set-aside observation could explain (kept from penalties).
    expected: (M,) matchable landmarks the sensor should have reported: when all K
      observation rows are valid the detector may have dropped farther trunks (detectors and
      simulators keep the K nearest), so only landmarks up to the farthest observation count;
      and only those predicted within ``params.miss_range`` and ``params.miss_bearing``;
      never a landmark in the ring.
    matching_obs: (K,) valid observations that take part in matching: ``usable_obs``, and
      with ``loose_match`` the set-aside ones too.
    """

    usable_obs: jnp.ndarray
    set_aside_obs: jnp.ndarray
    matchable: jnp.ndarray
    explained: jnp.ndarray
    expected: jnp.ndarray
    matching_obs: jnp.ndarray


def visibility(z, obs_valid, active, predicted: PredictedMeasurement, mahalanobis,
               params: Params, boundary: str) -> Visibility:
    """Hard, loose or loose_match visibility boundary (module docstring).

    Args:
      z: (K, 2); obs_valid: (K,); active: (M,); predicted: (M,) fields;
      mahalanobis: (K, M) squared distances (+inf for impossible pairs) under the same S as
        ``predicted`` (no pose covariance added for matching: the ring's guarantee, that an
        observation nearer than R_max - w_k cannot gate with a landmark beyond the ring,
        needs the widths and the distances from one S; ``step_propose.associate``).
    """
    in_min_range = predicted.range >= params.min_range
    saturated = jnp.all(obs_valid)
    horizon = jnp.where(saturated, jnp.max(jnp.where(obs_valid, z[:, 0], 0.0)), jnp.inf)
    may_be_missed = ((predicted.range <= horizon) & (predicted.range <= params.miss_range)
                     & (jnp.abs(predicted.bearing) <= params.miss_bearing))
    # Observations nearer than min_range could never match (no landmark there is matchable)
    # and would create a twin every step.
    obs_valid = obs_valid & (z[:, 0] >= params.min_range)
    if boundary == "hard":
        usable = obs_valid & (z[:, 0] <= params.max_range)
        matchable = active & in_min_range & (predicted.range <= params.max_range)
        no_obs = jnp.zeros_like(usable)
        return Visibility(usable, no_obs, matchable, jnp.zeros_like(matchable),
                          matchable & may_be_missed, usable)
    if boundary not in ("loose", "loose_match"):
        raise ValueError(f"boundary={boundary!r}; expected one of {BOUNDARIES}")
    obs_width = params.airlock_sigmas * measurement_std(z[:, 0], params)[0]
    obs_in_ring = z[:, 0] > params.max_range - obs_width
    landmark_width = params.airlock_sigmas * jnp.sqrt(predicted.s_rr)
    landmark_in_ring = (active & (predicted.range > params.max_range - landmark_width)
                        & (predicted.range <= params.max_range + landmark_width))
    gated = mahalanobis <= params.association_gate
    near_ring_landmark = jnp.any(gated & landmark_in_ring[None, :], axis=1)
    set_aside = obs_valid & (obs_in_ring | near_ring_landmark)
    inside = active & in_min_range & (predicted.range <= params.max_range - landmark_width)
    explained = jnp.any(gated & set_aside[:, None], axis=0)
    usable = obs_valid & ~set_aside
    if boundary == "loose":
        return Visibility(usable, set_aside, inside, explained, inside & may_be_missed, usable)
    return Visibility(usable, set_aside, inside | (landmark_in_ring & in_min_range), explained,
                      inside & may_be_missed, obs_valid)


SLACK = 1e-4  # may_take_part's widening for rounding: relative on margins, absolute on cosines


def may_take_part(pose, landmark_mean, landmark_cov, active, params: Params, boundary: str,
                  z=None, obs_valid=None, pose_cov=None):
    """(M,) bool: a superset of the landmarks that take part in an association made at
    ``pose``, in O(M + K) (the window's guard, ``StepInfo.window_cut``).

    With h the unit vector from the pose to landmark m at range r_m, S_rr = h^T Sigma_m h +
    sigma_r(r_m)^2 (the range entry of ``ekf``'s innovation covariance, computed by the same
    functions) and w_m = a sqrt(S_rr), a = ``airlock_sigmas``, a landmark takes part only in
    the region of ``visibility``: matchable (r_m <= R_max; r_m <= R_max - w_m when loose) or,
    loose, in the ring (r_m <= R_max + w_m, where it may set an observation aside, and with
    ``loose_match`` also be matched):

        hard:  r_m <= R_max
        loose, loose_match: r_m <= R_max + w_m

    Given the step's observations (``z`` (K, 2), ``obs_valid`` (K,); for the gated
    associations, not ``known``), a landmark in that region takes part only if an
    observation could gate with it or a miss could be counted against it. Let Z be the
    matching covariance (S plus the pose's share when the matching adds ``pose_cov``
    (3, 3), as ``ekf.add_pose_uncertainty`` does) and b_m the predicted bearing. For a
    symmetric positive definite Z, nu^T Z^-1 nu >= nu_i^2 / Z_ii for each component i (the
    trunk radius only adds to d2), and the wrapped bearing difference obeys
    |wrap(z_b - b_m)| >= |b_m| - |z_b|. So no observation gates with a landmark farther than
    the farthest valid observation z_max by more than sqrt(g Z_rr) (g the gate), nor with
    one whose |b_m| exceeds the widest valid |z_b| = beta_max by more than
    delta_m = sqrt(g Z_bb); a miss needs r_m <= min(horizon, miss_range) and
    |b_m| <= miss_bearing (``visibility``). The bearings are tested by their cosines, which
    need no arctangent per landmark: cos b_m = h . (cos theta, sin theta) (theta the pose's
    heading), |b| <= x <=> cos b >= cos x on [0, pi], and, cos being 1-Lipschitz,
    cos(beta_max + delta_m) >= cos(beta_max) - delta_m. The landmark is kept when

        (r_m <= z_max + sqrt(g Z_rr)  and  cos b_m >= cos(beta_max) - delta_m)
        or (r_m <= min(horizon, miss_range)  and  cos b_m >= cos(miss_bearing)).

    This is loose for landmarks inside that range and bearing (kept) but catches the usual
    cases: a saturated sensor (its K nearest trunks) leaves the trees behind them out, and a
    sensor with a limited field of view leaves out the landmarks behind the robot. The
    margins are widened by ``SLACK`` (relative on the range margin and on delta_m, absolute
    on the cosines) so that rounding in the association's own float32 distances and bearings
    cannot put a pair inside the gate or the field of view that the bound left out.

    Args:
      pose: (3,); landmark_mean: (M, 2); landmark_cov: (M, 3) components (sxx, sxy, syy);
      active: (M,) bool; z, obs_valid: None (the region alone) or the step's observations;
      pose_cov: None or the (3, 3) pose covariance the matching adds.
    """
    dx = landmark_mean[:, 0] - pose[0]
    dy = landmark_mean[:, 1] - pose[1]
    range_ = jnp.hypot(dx, dy)
    h00, h01, h10, h11 = range_bearing_jacobian_point(dx, dy)
    sigma_range, sigma_bearing = measurement_std(range_, params)
    s_rr, _, s_bb = sandwich(h00, h01, h10, h11, landmark_cov[:, 0], landmark_cov[:, 1],
                             landmark_cov[:, 2])
    s_rr, s_bb = s_rr + sigma_range**2, s_bb + sigma_bearing**2
    if boundary == "hard":
        region = range_ <= params.max_range
    elif boundary in ("loose", "loose_match"):
        region = range_ <= params.max_range + params.airlock_sigmas * jnp.sqrt(s_rr)
    else:
        raise ValueError(f"boundary={boundary!r}; expected one of {BOUNDARIES}")
    if z is None:
        return active & region
    z_rr, z_bb = s_rr, s_bb
    if pose_cov is not None:  # ekf.add_pose_uncertainty's diagonal
        (xy_rr, _, xy_bb), (_, v1) = pose_share_terms(h00, h01, h10, h11, pose_cov)
        z_rr = s_rr + xy_rr
        z_bb = s_bb + xy_bb + 2.0 * v1 + pose_cov[2, 2]
    ahead = dx * jnp.cos(pose[2]) + dy * jnp.sin(pose[2])
    # cos b_m; a landmark on the pose has bearing 0, as atan2(0, 0) gives the association
    cos_bearing = jnp.where(range_ > 0.0, ahead / jnp.where(range_ > 0.0, range_, 1.0), 1.0)
    farthest = jnp.max(jnp.where(obs_valid, z[:, 0], -jnp.inf))
    widest = jnp.max(jnp.where(obs_valid, jnp.abs(z[:, 1]), -jnp.inf))
    margin = 1.0 + SLACK
    could_gate = ((range_ <= farthest + margin * jnp.sqrt(params.association_gate * z_rr))
                  & (cos_bearing >= jnp.cos(jnp.clip(widest, 0.0, jnp.pi))
                     - margin * jnp.sqrt(params.association_gate * z_bb) - SLACK))
    horizon = jnp.where(jnp.all(obs_valid), farthest, jnp.inf)  # visibility's horizon
    could_miss = ((range_ <= jnp.minimum(horizon, params.miss_range))
                  & (cos_bearing >= jnp.cos(jnp.minimum(params.miss_bearing, jnp.pi)) - SLACK))
    return active & region & (could_gate | could_miss)


def update_existence(existence, matched, missed, params: Params):
    """Log-odds evidence update of (M,) slots: + hit for matched, + miss for missed."""
    hit = jnp.log(params.detection_probability / params.false_alarm_probability)
    miss = jnp.log((1.0 - params.detection_probability) / (1.0 - params.false_alarm_probability))
    updated = existence + jnp.where(matched, hit, 0.0) + jnp.where(missed, miss, 0.0)
    return jnp.clip(updated, -params.existence_max, params.existence_max)


def birth_slots(active, birth):
    """Slot index for each observation that creates a landmark: the first free slots in order.

    Args:
      active: (M,) bool occupancy; birth: (K,) bool observations that create landmarks.
    Returns:
      slot: (K,) int32 in [0, M) for a placed birth and M (out of bounds, dropped by scatter)
        otherwise; dropped: () int32 births that found no free slot (a full map never
        overwrites an active landmark).
    """
    num_slots = active.shape[0]
    free_count = jnp.cumsum((~active).astype(jnp.int32))  # (M,) free slots among 0..m
    rank = jnp.cumsum(birth.astype(jnp.int32)) - 1  # (K,) rank of each birth among births
    placed = birth & (rank < jnp.sum(~active))
    # The free slot of rank r is the first m with free_count[m] = r + 1: a binary search
    # (log2 M gathers a birth). Alone, vmapped over 20,000 particles (M 64, K 16, 2-core CPU),
    # it takes 7.5 ms against 38 ms for a (K, M) one-hot sum; inside a whole batched step the
    # gain was within the timing noise (benchmarks/throughput.py, study case).
    picked = jnp.searchsorted(free_count, rank + 1, side="left", method="scan")
    slot = jnp.where(placed, picked, num_slots)
    return slot.astype(jnp.int32), jnp.sum(birth & ~placed).astype(jnp.int32)


def scatter_rows(slot_values, slot, new_values):
    """Write new_values[k] into slot_values[slot[k]]; out-of-range slots are dropped."""
    return slot_values.at[slot].set(new_values, mode="drop")


def empty_slot_values(num_slots: int, dtype):
    """Finite placeholder values of an empty slot: mean, cov components, radius."""
    return (jnp.zeros((num_slots, 2), dtype),
            jnp.tile(jnp.array([1.0, 0.0, 1.0], dtype), (num_slots, 1)),
            jnp.zeros((num_slots,), dtype))
