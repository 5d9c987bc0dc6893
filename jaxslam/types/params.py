"""``Params``: the dynamic filter parameters, their defaults and ``default_params``."""
from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from jaxslam.types.config import FilterConfig


class Params(NamedTuple):
    """Dynamic filter parameters: a pytree of float arrays (scalars unless noted).

    A sweep over any field is a ``vmap`` over a stacked ``Params`` and compiles once.
    docs/parameters.md lists every field with its unit, default, the ``FilterConfig`` choices
    that read it, the equation it enters and how to estimate it without ground truth.

    Motion noise, Geiser et al. 2023, Eq. (1): each std is
    ``c_trans*|trans| + c_rot*|rot| + c_const``.
      rot1_noise: (3,) coefficients (trans, rot, const) of the first rotation's std
        [rad/m, rad/rad, rad]. Table 1 row 1.
      trans_noise: (3,) coefficients of the translation std [m/m, m/rad, m]; its rotation term
        multiplies |rot1| + |rot2|. Table 1 row 2.
      rot2_noise: (3,) coefficients of the second rotation's std. Table 1 row 3.
      motion_outlier_probability / motion_outlier_scale: bursts (``motion.py``): with
        probability eps a move's noise std is kappa times Eq. (1)'s. Default 0.05 / 8: the
        tail the default observation proposal needs when a turn is far from the measured one
        (chosen on tuning logs, docs/results.md, proposal_defaults).
      min_translation: below this translation [m] the move is a pure turn: rot1 = 0 and the
        whole heading change goes to rot2 (avoids the rot1 degeneracy of a stationary robot).
        Default 1 cm: above typical pose jitter of a parked robot (millimetres).
      odometry_gain: (2,) (translation gain, rotation gain) [-]: the systematic part of the
        odometry error (Borenstein and Feng, "Measurement and correction of systematic
        odometry errors in mobile robots", 1996). The move the models use is the reading's
        (g_r rot1, g_t trans, g_r rot2) (``motion.control_to_odometry``); Eq. (1)'s noise
        is then around that move. A robot that drives 9 % less than commanded has g_t
        0.91. Default (1, 1): the reading as it is.
      The velocity and Ackermann models integrate their control into the same
      (rot1, trans, rot2) move and reuse these coefficients (see ``motion.py``).
      wheelbase / encoder_offset / laser_forward / laser_left: Ackermann vehicle geometry [m]
        (Victoria Park defaults L=2.83, H=0.76, a=3.78, b=0.50); the pose is the laser's.
    Observation noise, Geiser et al. 2023, Table 2: std = c_dist * range + c_const.
      range_noise: (2,) (per metre of distance, constant) [m/m, m].
      bearing_noise: (2,) (per metre of distance, constant) [rad/m, rad].
      range_std_floor / bearing_std_floor: lower bounds on the two stds. Table 2's constants
        are zero, so without a floor the covariance is singular at distance 0.
      radius_noise: std [m] of one measured trunk radius (``Observations.radius``). When > 0,
        the radius joins the association and the weight (``ekf.radius_distance_sq``): pairs
        where both radii are known then have a third degree of freedom, so raise
        ``association_gate`` to match (chi-square 3 dof: 99.9 % 16.27 where 2 dof give 13.82;
        the default 25 becomes ~28); as the radius keeps wrong neighbours out, a wider gate
        may pay (Victoria Park: 13.8 without radii, 25 with them, GPS-tuned: docs/results.md).
        The same gate applies to pairs with an unknown radius (position only) and to the
        airlock's position tests. Default 0: radii are only averaged into
        ``Particles.landmark_radius``.
    Sensor:
      max_range / min_range: visibility limits [m].
      miss_range: landmarks predicted farther than this [m] are not counted as missed when
        no observation matches them (no existence penalty), though they still match and
        update up to ``max_range``. For detectors that find far trunks only now and then;
        default +inf (every matchable landmark inside the detection horizon can be missed).
      miss_bearing: the sensor's half field of view [rad]: landmarks predicted at
        |bearing| > miss_bearing are not counted as missed (a camera sees ~±30 degrees; a
        forward-facing lidar ±90). They still match and update. Default pi (all round).
    Association and map management:
      association_gate: squared Mahalanobis distance above which a pair is never formed.
        Default 25 (5 sigma), wider than the chi-square 99% quantile 9.21 because the
        innovation covariance leaves out the particle's own pose error (FastSLAM 1.0): on the
        default forest (8 runs, P=16, T=100) a gate of 9.21 left 3.6 twin landmarks per run,
        16 left 0.75, 25 left 0.4-0.6 and 49 left none, with equal pose and map errors.
      association_heading_std: a heading std [rad] added to the motion prior's pose
        covariance Sigma_u where the observation and mixture proposals match at the motion
        prediction x_hat (and at each turn piece's centre, ``FilterConfig.burst_turn_pieces``)
        with ``FilterConfig.match_pose_uncertainty``, for that matching only:
        the proposal, the update and the weight keep Sigma_u. A heading offset moves every
        predicted bearing by the same angle and no range, so Hx diag(0, 0, s^2) Hx^T adds
        s^2 to the bearing variance of every pair. Why: Eq. (1)'s std is evaluated at the
        measured turn, and when the true turn is larger (a burst) the bearing gate at x_hat
        refuses far trees the particle already mapped, which then start new landmarks and
        the loop is lost. Default 0.1 rad, chosen on simulated tuning logs with 0.15 rad
        turns (docs/results.md, proposal_study, "A heading std for matching at the
        prediction"); ``calibrate_params`` sets it from the log (the fitted motion model's
        typical heading std): as an angle it widens the gate with range.
      new_landmark_log_offset: an observation that no landmark explains (it starts a new
        landmark, or it is set aside in the airlock and, with ``boundary="loose_match"``,
        not matched either) is credited the log-likelihood of a match
        exactly at the gate under its own measurement noise, plus this offset. Every valid
        observation thus adds exactly one term to every particle's weight.
      detection_probability / false_alarm_probability: for existence log-odds updates.
      existence_init / existence_delete: log-odds at birth and the deletion threshold.
      existence_max: log-odds are clipped to [-existence_max, existence_max] so a long-seen
        landmark can still be deleted after a few misses.
      airlock_sigmas: the airlock width in standard deviations of the range (``boundary=
        "loose"`` or ``"loose_match"``): w = airlock_sigmas * sigma_range. ``default_params``
        derives it from the gate of the same call, sqrt(association_gate) (Geiser et al.
        2023, section 3.1: "based on the correspondence threshold"): 5 for the default gate
        25, 4 for a gate of 16; a value given explicitly wins.
    Resampling:
      ess_threshold: resample when ESS < ess_threshold * P.
    Mixture proposal (Geiser et al. 2023, section 5.2):
      mixture_ratio: phi, the probability of drawing a particle from the observation proposal.
      mixture_min / mixture_max: bounds of the adaptive phi (``step_propose.particle_ratio``).
      likelihood_rate_fast / likelihood_rate_slow: smoothing rates of the short- and long-term
        average observation likelihood that drive the adaptive phi.
    """

    rot1_noise: jnp.ndarray
    trans_noise: jnp.ndarray
    rot2_noise: jnp.ndarray
    motion_outlier_probability: jnp.ndarray
    motion_outlier_scale: jnp.ndarray
    min_translation: jnp.ndarray
    odometry_gain: jnp.ndarray
    wheelbase: jnp.ndarray
    encoder_offset: jnp.ndarray
    laser_forward: jnp.ndarray
    laser_left: jnp.ndarray
    range_noise: jnp.ndarray
    bearing_noise: jnp.ndarray
    range_std_floor: jnp.ndarray
    bearing_std_floor: jnp.ndarray
    radius_noise: jnp.ndarray
    max_range: jnp.ndarray
    min_range: jnp.ndarray
    miss_range: jnp.ndarray
    miss_bearing: jnp.ndarray
    association_gate: jnp.ndarray
    association_heading_std: jnp.ndarray
    new_landmark_log_offset: jnp.ndarray
    detection_probability: jnp.ndarray
    false_alarm_probability: jnp.ndarray
    existence_init: jnp.ndarray
    existence_delete: jnp.ndarray
    existence_max: jnp.ndarray
    airlock_sigmas: jnp.ndarray
    ess_threshold: jnp.ndarray
    mixture_ratio: jnp.ndarray
    mixture_min: jnp.ndarray
    mixture_max: jnp.ndarray
    likelihood_rate_fast: jnp.ndarray
    likelihood_rate_slow: jnp.ndarray

# The constant defaults (Geiser et al. 2023, Tables 1 and 2, and a 20 m forestry lidar), one
# group per part of the model; docs/parameters.md states each value. A field whose default
# follows another field of the same call is in ``DERIVED_DEFAULTS`` instead.
PARAM_DEFAULTS = {
    # Motion noise (Table 1) and its bursts.
    "rot1_noise": (0.0, 0.06, 0.0002),
    "trans_noise": (0.02, 0.006, 0.00003),
    "rot2_noise": (0.0, 0.06, 0.0003),
    "motion_outlier_probability": 0.05,
    "motion_outlier_scale": 8.0,
    "min_translation": 0.01,
    # Systematic odometry error (translation, rotation gain): none.
    "odometry_gain": (1.0, 1.0),
    # Ackermann vehicle geometry (Victoria Park).
    "wheelbase": 2.83,
    "encoder_offset": 0.76,
    "laser_forward": 3.78,
    "laser_left": 0.50,
    # Observation noise (Table 2).
    "range_noise": (0.005, 0.0),
    "bearing_noise": (0.0005, 0.0),
    "range_std_floor": 0.01,
    "bearing_std_floor": 0.001,
    "radius_noise": 0.0,
    # Sensor.
    "max_range": 20.0,
    "min_range": 0.1,
    "miss_range": float("inf"),
    "miss_bearing": float(np.pi),
    # Association.
    "association_gate": 25.0,
    "association_heading_std": 0.1,
    "new_landmark_log_offset": 0.0,
    # Landmark existence.
    "detection_probability": 0.9,
    "false_alarm_probability": 0.05,
    "existence_init": 1.0,
    "existence_delete": -1.5,
    "existence_max": 6.0,
    # Resampling.
    "ess_threshold": 0.5,
    # Mixture proposal.
    "mixture_ratio": 0.3,
    "mixture_min": 0.05,
    "mixture_max": 1.0,
    "likelihood_rate_fast": 0.5,
    "likelihood_rate_slow": 0.05,
}

# Derived default: field -> (the field it follows, the rule applied to that field's leaf).
DERIVED_DEFAULTS = {"airlock_sigmas": ("association_gate", jnp.sqrt)}


def default_params(config: FilterConfig | None = None, dtype=jnp.float32, **overrides) -> Params:
    """Geiser et al. 2023, Tables 1 and 2 and sensible defaults for a 20 m forestry lidar.

    Every field's default, unit and meaning: docs/parameters.md. Overrides are applied first;
    a derived default is then computed from the values of the SAME call, so overriding what
    it derives from carries over (an explicitly given derived field wins):

      airlock_sigmas = sqrt(association_gate)   (Geiser et al. 2023, section 3.1)

    The loose boundary's airlock is a ring inside R = max_range, w = airlock_sigmas * std
    wide (``landmarks.py``): an observation's own range std sigma_range(z_k), a landmark's
    predicted range std sqrt(S_rr). With airlock_sigmas = sqrt(gate), a landmark matched
    inside R - w_m is beyond the gate of every observation beyond R, since the squared
    Mahalanobis distance is at least its range part, d2 >= (z_r - r_m)^2 / S_rr > gate
    (and likewise for an observation inside R - w_k and an exactly known landmark beyond R).
    The square root is taken in ``dtype``, of the gate as stored: the default gate 25 gives
    exactly 5.0 (the value frozen before), ``association_gate=16.0`` gives 4.0, and
    ``p.airlock_sigmas == sqrt(p.association_gate)`` holds bit for bit. Every other default
    is a constant.

    Args:
      config: the ``FilterConfig`` the Params are meant for, or None. No default depends on
        it today, on purpose: ``Params`` hold numbers, ``FilterConfig`` code paths and shapes,
        and a field a config does not use (``wheelbase`` without ``motion_model=
        "ackermann"``, ``mixture_*`` without ``proposal="mixture"``, the airlock with
        ``boundary="hard"``) is simply not read by the compiled step, so one set of defaults
        serves every config and a sweep's stacked Params are the same whatever the config.
        It is accepted so that the signature stays stable: every entry point (studies, the
        CLI, ``pipeline.load_params``, ``calibrate_params``, ``victoria_park_params``)
        already passes its config, and a default that comes to depend on one needs no change
        in any caller. It must be a ``FilterConfig`` or None: a number given in its place
        (``default_params(15.0)`` for ``max_range=15.0``) is refused rather than ignored.
      dtype: float dtype of every leaf.
      **overrides: any ``Params`` field, e.g. ``max_range=30.0``.
    Raises:
      TypeError: ``config`` is neither a ``FilterConfig`` nor None.
      ValueError: an unknown field, or a value ``validation.check_params`` refuses (wrong
        shape, e.g. a scalar for a 3-vector noise field, NaN, out of range), naming it.
    """
    if config is not None and not isinstance(config, FilterConfig):
        raise TypeError(
            f"default_params(config={config!r}): config must be a FilterConfig or None; "
            "give Params fields by name, e.g. default_params(config, max_range=15.0)"
        )
    unknown = set(overrides) - set(Params._fields)
    if unknown:
        raise ValueError(
            f"default_params got unknown field(s) {sorted(unknown)}; "
            f"expected fields of Params: {sorted(Params._fields)}"
        )
    values = {**PARAM_DEFAULTS, **overrides}
    leaves = {k: jnp.asarray(v, dtype=dtype) for k, v in values.items()}
    for name, (source, rule) in DERIVED_DEFAULTS.items():
        if name not in overrides:
            # A tracer gate (default_params inside vmap) gives a traced airlock. An invalid
            # gate (NaN, negative) gives a NaN here, but check_params names the gate first.
            leaves[name] = rule(leaves[source])
    params = Params(**{k: leaves[k] for k in Params._fields})
    from jaxslam.validation import check_params  # lazy: validation imports this module
    check_params(params, where="default_params", allow_batch=False)
    return params
