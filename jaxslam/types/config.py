"""``FilterConfig``: the static filter settings (shapes and code paths) and their choices."""
from __future__ import annotations

import dataclasses

import numpy as np

MOTION_MODELS = ("odometry", "velocity", "ackermann")
ASSOCIATIONS = ("stable", "greedy", "hungarian", "known")
PROPOSALS = ("motion", "observation", "mixture")
RESAMPLINGS = ("systematic", "stratified", "multinomial", "residual")
BOUNDARIES = ("hard", "loose", "loose_match")
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
      mixture_mode: ``fixed`` ratio phi or ``adaptive`` (only used by the mixture proposal):
        a phi per particle that rises after a drop of the observation likelihood and where
        the motion draws would rarely land where the observations put the pose
        (``step_propose.particle_ratio``).
      resampling: one of ``RESAMPLINGS``.
      boundary: ``hard`` visibility limit, ``loose`` airlock (Geiser et al. 2023, section 3.1)
        or ``loose_match`` (default): the airlock for births and deaths only, its
        observations and ring landmarks still matched (``landmarks`` module docstring). The
        paper's ``loose`` throws away every observation in a ring 5 range stds wide (22 % of
        them at 5x Table 2's range noise, 10 % at 2x). On fresh simulated logs run after the
        switch (seed 900, true noise given), ``loose_match`` cut the median final error
        from 1.45 to 0.58 m at 5x and from 3.59 to 1.62 m at 10x; at 2x the rows were mixed
        (0.23 -> 0.32 m wobbly, 0.41 -> 0.30 m smooth, 0.57 -> 0.12 m with 4x odometry).
        The default was chosen on seeds 500 and 700 (docs/results.md, "Matching across the
        airlock").
      association_window: 0 (default) matches observations against every slot; N > 0 only
        against each particle's N nearest active landmarks (by predicted range). Landmarks
        outside the window are neither matched nor penalised, so choose N above the number of
        trees the sensor can see at once. Cuts the (K, M) pair work to (K, N) for large maps.
        ``StepInfo.window_cut`` / ``Trace.window_cut`` count the landmarks the window left out
        although they could have taken part (``landmarks.may_take_part``), and the run
        warnings say so: while the count stays 0 the window gives the full association's
        matches, set-asides and misses (up to exactly equal pair costs). Studies report it
        per run (columns ``num_window_cut_steps`` and ``peak_window_cut``).
      max_match_rounds: bound on Gale-Shapley rounds; 0 means K * (M + 1), a bound that is
        never reached (each round either forms a proposal or exhausts an observation's list),
        so a matching is never cut short; the rounds actually used are in ``info``.
      match_pose_uncertainty: with the observation or mixture proposal, observations are
        matched at the motion prediction x_hat; True adds the pose uncertainty of that
        prediction to the matching covariance, Z = Hx Sigma_u Hx^T + S (FastSLAM 2.0,
        Montemerlo et al. 2003), so an accurate sensor still matches when x_hat is off by
        the motion noise, with diag(0, 0, s^2) added to Sigma_u for the matching only
        (s = ``Params.association_heading_std``). False matches with S alone. Ignored by the
        motion proposal (each particle matches at its own sampled pose).
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
        (``step_propose._burst_pieces``). False uses one Gaussian with the mixture's covariance.
        Costs a second association and proposal per particle.
      burst_turn_pieces: n >= 0. With ``burst_proposal``, n > 0 adds 2n + 1 pieces that split
        the burst's first turn into Gaussians at offsets c_j = j (span/n) tau, j = -n..n
        (tau = kappa sigma_rot1; ``proposal.turn_pieces``), each linearised and associated at
        its own pose, so a turn far larger than the measured one is still proposed where the
        observations put it. Costs 2n + 1 more associations and proposals per particle.
      burst_turn_span: the pieces cover +-span tau (in burst standard deviations).
      proposal_iterations: n >= 0 Gauss-Newton relinearisations of each FastSLAM 2.0
        Gaussian (``proposal.relinearised_proposal``): the matched landmarks are predicted
        again at the proposal's mean and the Gaussian is solved again, keeping the
        association made at x_hat. 0 (default) linearises at x_hat only (FastSLAM 2.0 as
        published); on held-out logs with 6x Table 1 odometry and large turns one round
        changed the divergence by less than its interval (docs/results.md, proposal_study).
        Costs n predictions of the K matched landmarks per piece.
    """

    num_particles: int = 100
    max_landmarks: int = 64
    max_obs: int = 16
    motion_model: str = "odometry"
    association: str = "stable"
    proposal: str = "observation"
    mixture_mode: str = "fixed"
    resampling: str = "systematic"
    boundary: str = "loose_match"
    max_match_rounds: int = 0
    association_window: int = 0
    match_pose_uncertainty: bool = True
    anchor_empty_map: bool = True
    associate_at_sample: bool = True
    burst_proposal: bool = True
    burst_turn_pieces: int = 0
    burst_turn_span: float = 4.0
    proposal_iterations: int = 0

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
        if (not isinstance(self.proposal_iterations, (int, np.integer))
                or isinstance(self.proposal_iterations, bool) or self.proposal_iterations < 0):
            raise ValueError(
                f"FilterConfig.proposal_iterations={self.proposal_iterations!r} is invalid; "
                "expected an integer >= 0 (0: linearise at the motion prediction only)")
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
