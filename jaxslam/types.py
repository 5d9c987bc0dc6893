"""Types shared by the whole library: static config, dynamic params, filter state, observations.

Dimension glossary (used in every docstring of the package):

    P   particles                     (``FilterConfig.num_particles``)
    M   landmark slots per particle   (``FilterConfig.max_landmarks``)
    K   padded observations per step  (``FilterConfig.max_obs``)
    B   lidar beams per scan
    T   time steps
    R   independent Monte Carlo runs
    N   true trees in a simulated forest
    C   motion control vector length (3 for every built-in motion model)
    L   landmark identities of one smoothed history (``smoothing``)
    V   visits of those landmarks, and E links between visits (``smoothing.split_visits``)

Conventions: poses are ``(x, y, theta)`` in metres and radians, theta wrapped to [-pi, pi);
observations are ``(range, bearing)`` in the robot frame; landmark covariances are stored as
their three distinct components ``(sxx, sxy, syy)`` in a trailing axis of size 3 so that the hot
code can do closed-form 2x2 arithmetic; ``estimate`` expands them.
"""
from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

MOTION_MODELS = ("odometry", "velocity", "ackermann")
ASSOCIATIONS = ("stable", "greedy", "hungarian", "known")
PROPOSALS = ("motion", "observation", "mixture")
RESAMPLINGS = ("systematic", "stratified", "multinomial", "residual")
BOUNDARIES = ("hard", "loose")
MIXTURE_MODES = ("fixed", "adaptive")


def _check_choice(name: str, value: str, allowed: tuple[str, ...]) -> None:
    if value not in allowed:
        raise ValueError(
            f"FilterConfig.{name}={value!r} is not supported; expected one of {list(allowed)}"
        )


def _check_positive_int(name: str, value) -> None:
    if not isinstance(value, (int, np.integer)) or isinstance(value, bool) or value < 1:
        raise ValueError(
            f"FilterConfig.{name}={value!r} is invalid; expected a positive integer (>= 1)"
        )


@dataclasses.dataclass(frozen=True)
class FilterConfig:
    """Static filter settings: everything that fixes array shapes or code paths.

    Changing a field recompiles; sweeps over numbers belong in ``Params`` instead.

    Attributes:
      num_particles: P, particles per run.
      max_landmarks: M, landmark slots per particle.
      max_obs: K, padded observations per step.
      motion_model: one of ``MOTION_MODELS``; fixes the meaning of the (3,) control vector.
      association: one of ``ASSOCIATIONS``.
      proposal: one of ``PROPOSALS``. The default is the observation proposal (FastSLAM 2.0,
        Montemerlo et al. 2003) with the four flags below on and the default bursts in
        ``Params``: on held-out logs with large turns or poor odometry it diverged far less
        than the motion proposal, and about as often on smooth ones (docs/results.md,
        proposal_defaults). The seed paper's FastSLAM is ``proposal="motion"``,
        ``anchor_empty_map=False`` and ``motion_outlier_probability=0``.
      mixture_mode: ``fixed`` ratio phi or ``adaptive`` (only used by the mixture proposal).
      resampling: one of ``RESAMPLINGS``.
      boundary: ``hard`` visibility limit or ``loose`` airlock (Geiser et al. 2023, section 3.1).
      association_window: 0 (default) matches observations against every slot; N > 0 only
        against each particle's N nearest active landmarks (by predicted range). Landmarks
        outside the window are neither matched nor penalised, so choose N above the number of
        trees the sensor can see at once. Cuts the (K, M) pair work to (K, N) for large maps.
      max_match_rounds: bound on Gale-Shapley rounds; 0 means K * (M + 1), a bound that is
        never reached (each round either forms a proposal or exhausts an observation's list),
        so a matching is never cut short; the rounds actually used are in ``info``.
      match_pose_uncertainty: with the observation or mixture proposal, observations are
        matched at the motion prediction x_hat; True adds the pose uncertainty of that
        prediction to the matching covariance, Z = Hx Sigma_u Hx^T + S (FastSLAM 2.0,
        Montemerlo et al. 2003), so an accurate sensor still matches when x_hat is off by
        the motion noise. False matches with S alone. Ignored by the motion proposal (each
        particle matches at its own sampled pose).
      anchor_empty_map: a particle whose map is still empty moves by the motion mean
        instead of a draw: no later observation can tell its pose error from the frame of
        the map it will build, so a draw only adds an error that rotates the whole map (the
        floor of every run's final error). False samples as usual.
      associate_at_sample: with the observation or mixture proposal, a particle drawn from
        the observation proposal is matched again at its drawn pose before the update and
        the weight (the match at x_hat only shapes the proposal). Particles drawn from the
        motion model are always matched at their own pose. Costs a second association.
      burst_proposal: with the observation or mixture proposal and bursts in the motion
        noise (``Params.motion_outlier_probability`` > 0), draw from the two FastSLAM 2.0
        Gaussians of the prior's core and burst pieces, mixed by prior mass x evidence
        (``filter._burst_pieces``). False uses one Gaussian with the mixture's covariance.
        Costs a second association and proposal per particle.
      burst_turn_pieces: n >= 0. With ``burst_proposal``, n > 0 adds 2n + 1 pieces that split
        the burst's first turn into Gaussians at offsets c_j = j (span/n) tau, j = -n..n
        (tau = kappa sigma_rot1; ``proposal.turn_pieces``), each linearised and associated at
        its own pose, so a turn far larger than the measured one is still proposed where the
        observations put it. Costs 2n + 1 more associations and proposals per particle.
      burst_turn_span: the pieces cover +-span tau (in burst standard deviations).
    """

    num_particles: int = 100
    max_landmarks: int = 64
    max_obs: int = 16
    motion_model: str = "odometry"
    association: str = "stable"
    proposal: str = "observation"
    mixture_mode: str = "fixed"
    resampling: str = "systematic"
    boundary: str = "loose"
    max_match_rounds: int = 0
    association_window: int = 0
    match_pose_uncertainty: bool = True
    anchor_empty_map: bool = True
    associate_at_sample: bool = True
    burst_proposal: bool = True
    burst_turn_pieces: int = 0
    burst_turn_span: float = 4.0

    def __post_init__(self):
        for name in ("num_particles", "max_landmarks", "max_obs"):
            _check_positive_int(name, getattr(self, name))
        if (not isinstance(self.max_match_rounds, (int, np.integer))
                or self.max_match_rounds < 0):
            raise ValueError(
                f"FilterConfig.max_match_rounds={self.max_match_rounds!r} is invalid; "
                "expected an integer >= 0 (0 means max_obs * (max_landmarks + 1))"
            )
        if (not isinstance(self.association_window, (int, np.integer))
                or self.association_window < 0):
            raise ValueError(
                f"FilterConfig.association_window={self.association_window!r} is invalid; "
                "expected an integer >= 0 (0 means every landmark slot)")
        if (not isinstance(self.burst_turn_pieces, (int, np.integer))
                or isinstance(self.burst_turn_pieces, bool) or self.burst_turn_pieces < 0):
            raise ValueError(
                f"FilterConfig.burst_turn_pieces={self.burst_turn_pieces!r} is invalid; "
                "expected an integer >= 0 (0: no turn pieces)")
        if (isinstance(self.burst_turn_span, bool)
                or not isinstance(self.burst_turn_span, (int, float, np.floating))
                or not self.burst_turn_span > 0 or not np.isfinite(self.burst_turn_span)):
            raise ValueError(
                f"FilterConfig.burst_turn_span={self.burst_turn_span!r} is invalid; "
                "expected a finite number > 0 (burst standard deviations)")
        for name in ("match_pose_uncertainty", "anchor_empty_map", "associate_at_sample",
                     "burst_proposal"):
            if not isinstance(getattr(self, name), (bool, np.bool_)):
                raise ValueError(f"FilterConfig.{name}={getattr(self, name)!r} is invalid; "
                                 "expected True or False")
        _check_choice("motion_model", self.motion_model, MOTION_MODELS)
        _check_choice("association", self.association, ASSOCIATIONS)
        _check_choice("proposal", self.proposal, PROPOSALS)
        _check_choice("mixture_mode", self.mixture_mode, MIXTURE_MODES)
        _check_choice("resampling", self.resampling, RESAMPLINGS)
        _check_choice("boundary", self.boundary, BOUNDARIES)

    @property
    def match_rounds(self) -> int:
        """The bound actually used for the Gale-Shapley loop."""
        return self.max_match_rounds or self.max_obs * (self.max_landmarks + 1)


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
      new_landmark_log_offset: an observation that no landmark explains (it starts a new
        landmark, or it is set aside in the airlock) is credited the log-likelihood of a match
        exactly at the gate under its own measurement noise, plus this offset. Every valid
        observation thus adds exactly one term to every particle's weight.
      detection_probability / false_alarm_probability: for existence log-odds updates.
      existence_init / existence_delete: log-odds at birth and the deletion threshold.
      existence_max: log-odds are clipped to [-existence_max, existence_max] so a long-seen
        landmark can still be deleted after a few misses.
      airlock_sigmas: the airlock width in standard deviations of the range (``boundary=
        "loose"``): w = airlock_sigmas * sigma_range. ``default_params`` derives it from the
        gate of the same call, sqrt(association_gate) (Geiser et al. 2023, section 3.1: "based
        on the correspondence threshold"): 5 for the default gate 25, 4 for a gate of 16; a
        value given explicitly wins.
    Resampling:
      ess_threshold: resample when ESS < ess_threshold * P.
    Mixture proposal (Geiser et al. 2023, section 5.2):
      mixture_ratio: phi, the probability of drawing a particle from the observation proposal.
      mixture_min / mixture_max: bounds of the adaptive phi.
      likelihood_rate_fast / likelihood_rate_slow: smoothing rates of the short- and long-term
        average observation likelihood that drive the adaptive phi.
    """

    rot1_noise: jnp.ndarray
    trans_noise: jnp.ndarray
    rot2_noise: jnp.ndarray
    motion_outlier_probability: jnp.ndarray
    motion_outlier_scale: jnp.ndarray
    min_translation: jnp.ndarray
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
    values = dict(
        rot1_noise=(0.0, 0.06, 0.0002),
        trans_noise=(0.02, 0.006, 0.00003),
        rot2_noise=(0.0, 0.06, 0.0003),
        motion_outlier_probability=0.05,
        motion_outlier_scale=8.0,
        min_translation=0.01,
        wheelbase=2.83,
        encoder_offset=0.76,
        laser_forward=3.78,
        laser_left=0.50,
        range_noise=(0.005, 0.0),
        bearing_noise=(0.0005, 0.0),
        range_std_floor=0.01,
        bearing_std_floor=0.001,
        radius_noise=0.0,
        max_range=20.0,
        min_range=0.1,
        miss_range=float("inf"),
        miss_bearing=float(np.pi),
        association_gate=25.0,
        new_landmark_log_offset=0.0,
        detection_probability=0.9,
        false_alarm_probability=0.05,
        existence_init=1.0,
        existence_delete=-1.5,
        existence_max=6.0,
        airlock_sigmas=None,  # derived below: sqrt(association_gate)
        ess_threshold=0.5,
        mixture_ratio=0.3,
        mixture_min=0.05,
        mixture_max=0.9,
        likelihood_rate_fast=0.5,
        likelihood_rate_slow=0.05,
    )
    unknown = set(overrides) - set(values)
    if unknown:
        raise ValueError(
            f"default_params got unknown field(s) {sorted(unknown)}; "
            f"expected fields of Params: {sorted(values)}"
        )
    values.update(overrides)
    derived = {"airlock_sigmas": ("association_gate", jnp.sqrt)}
    leaves = {k: jnp.asarray(v, dtype=dtype) for k, v in values.items() if k not in derived
              or k in overrides}
    for name, (source, rule) in derived.items():
        if name not in overrides:
            # A tracer gate (default_params inside vmap) gives a traced airlock. An invalid
            # gate (NaN, negative) gives a NaN here, but check_params names the gate first.
            leaves[name] = rule(leaves[source])
    params = Params(**{k: leaves[k] for k in Params._fields})
    from jaxslam.validation import check_params  # lazy: validation imports this module
    check_params(params, where="default_params", allow_batch=False)
    return params


class Particles(NamedTuple):
    """Per-particle fields; every leaf has leading axis P, so resampling is one tree map.

    Attributes:
      pose: (P, 3) particle poses (x, y, theta).
      landmark_mean: (P, M, 2) landmark positions in the world frame.
      landmark_cov: (P, M, 3) landmark covariance components (sxx, sxy, syy).
      landmark_radius: (P, M) trunk radius estimate: the running mean of the ``radius_count``
        measured radii (0 while none was measured).
      landmark_id: (P, M) int32 true-tree id (``association="known"``); -1 when unknown.
      active: (P, M) bool slot occupancy.
      existence: (P, M) existence log-odds of each landmark.
      observation_count: (P, M) int32 number of updates since birth (1 at birth).
      radius_count: (P, M) int32 number of those updates (and the birth) that carried a
        measured radius (``Observations.radius`` > 0).
    Inactive slots hold finite values (zero mean, identity covariance) and are masked.
    """

    pose: jnp.ndarray
    landmark_mean: jnp.ndarray
    landmark_cov: jnp.ndarray
    landmark_radius: jnp.ndarray
    landmark_id: jnp.ndarray
    active: jnp.ndarray
    existence: jnp.ndarray
    observation_count: jnp.ndarray
    radius_count: jnp.ndarray


class FilterState(NamedTuple):
    """The filter state of ONE run.

    Attributes:
      particles: ``Particles`` with leading axis P.
      log_weight: (P,) normalised log-weights (logsumexp == 0).
      likelihood_fast / likelihood_slow: () short- and long-term running averages of the mean
        per-observation log-likelihood (drive the adaptive mixture ratio).
      step: () int32 steps taken.
    """

    particles: Particles
    log_weight: jnp.ndarray
    likelihood_fast: jnp.ndarray
    likelihood_slow: jnp.ndarray
    step: jnp.ndarray


class Observations(NamedTuple):
    """Padded range-bearing observations of ONE step (add leading axes for T or R).

    Attributes:
      z: (K, 2) range [m] and bearing [rad] in the robot frame.
      valid: (K,) bool; padded rows are False and ignored.
      radius: (K,) trunk radius [m] (0 when unknown).
      landmark_id: (K,) int32 true-tree id (simulation truth, for ``association="known"``);
        -1 when unknown.
    """

    z: jnp.ndarray
    valid: jnp.ndarray
    radius: jnp.ndarray
    landmark_id: jnp.ndarray


def make_observations(z, valid=None, radius=None, landmark_id=None) -> Observations:
    """Build ``Observations`` with defaults for the optional fields.

    Args:
      z: (..., K, 2) range and bearing.
      valid: (..., K) bool, default all True.
      radius: (..., K) default zeros.
      landmark_id: (..., K) int, default -1.
    """
    z = jnp.asarray(z)
    if z.ndim < 2 or z.shape[-1] != 2:
        raise ValueError(f"observations z must have shape (..., K, 2); got {z.shape}")
    batch = z.shape[:-1]
    valid = jnp.ones(batch, bool) if valid is None else jnp.asarray(valid, bool)
    radius = jnp.zeros(batch, z.dtype) if radius is None else jnp.asarray(radius, z.dtype)
    landmark_id = (jnp.full(batch, -1, jnp.int32) if landmark_id is None
                   else jnp.asarray(landmark_id, jnp.int32))
    for name, arr in (("valid", valid), ("radius", radius), ("landmark_id", landmark_id)):
        if arr.shape != batch:
            raise ValueError(
                f"observations {name} must have shape {batch} to match z {z.shape}; "
                f"got {arr.shape}"
            )
    return Observations(z=z, valid=valid, radius=radius, landmark_id=landmark_id)


def empty_observations(max_obs: int, dtype=jnp.float32) -> Observations:
    """K padded, all-invalid observations (a step where nothing is seen)."""
    return make_observations(jnp.zeros((max_obs, 2), dtype), valid=jnp.zeros(max_obs, bool))
