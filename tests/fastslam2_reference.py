"""Independent NumPy float64 reference of one FastSLAM 2.0 step for ONE particle (issue 23).

Plain loops over observations, no JAX, no import from ``jaxslam``: every formula is written
again here from the paper (Montemerlo et al. 2003, "FastSLAM 2.0: An Improved Particle
Filtering Algorithm for SLAM in which Landmark Estimates Converge Provably") and from
Thrun, Burgard, Fox, "Probabilistic Robotics" (2005), Table 13.2, with the data association
GIVEN (``match[k]`` = index of the landmark observation k belongs to, -1 for none).

Conventions (each one is a choice; those marked [jaxslam] are conventions of jaxslam that the
textbook leaves open or states differently, and the reference follows them so that the step
can be compared state by state; the textbook alternative is available where it matters):

Poses and angles
  pose = (x, y, theta); angles wrap to [-pi, pi) by a - 2 pi floor((a + pi) / (2 pi)).
  Every innovation bearing and every heading difference is wrapped.

Motion (Geiser et al. 2023, Eq. 1, odometry rot1-trans-rot2)
  x_hat = g(x_prev, u): x + t cos(theta + r1), y + t sin(theta + r1), theta + r1 + r2, with
  u = the MEASURED (r1, t, r2).
  Noise stds std = (a1 |t| + b1 |r1| + c1, a2 |t| + b2 (|r1| + |r2|) + c2, a3 |t| + b3 |r2| + c3)
  evaluated at the MEASURED odometry (the sampler draws the true move around the measured one
  with these stds, so the density must use them too).
  Pose-space motion covariance R = J diag(std^2) J^T with J = d g / d (r1, t, r2) at the
  measured odometry and the particle's previous heading:
      J = [[-t sin h, cos h, 0], [t cos h, sin h, 0], [1, 0, 1]],  h = theta + r1.
  [jaxslam] ``pose_jitter`` * I is added to R, with pose_jitter = 100 eps max(R_xx, R_yy) +
  1e-14, eps the float64 epsilon (``proposal.pose_jitter``): R is singular at t = 0 and badly
  conditioned for tiny moves.
  Textbook: jitter 0.
  Exact motion density over the pose (used by the importance weight): invert x -> (r1, t, r2)
  (r1 = atan2 of the displacement in the previous frame, 0 when t < min_translation;
  r2 = wrap(dtheta - r1)), Gaussian density in odometry space with the stds above, divided by
  |det J| = t, t clamped below by min_translation [jaxslam ``motion_log_density``].

Measurement (range, bearing), Geiser et al. 2023, Table 2
  h(x, m) = (|m - t|, wrap(atan2(dy, dx) - theta)).
  Hx = dh/dx = [[-dx/r, -dy/r, 0], [dy/r^2, -dx/r^2, -1]], Hm = dh/dm = [[dx/r, dy/r],
  [-dy/r^2, dx/r^2]].
  Noise Qt(r) = diag(max(cr r + dr, floor_r)^2, max(cb r + db, floor_b)^2) evaluated at the
  PREDICTED range r = |m - t| of the pose where h is evaluated [jaxslam; the textbook has a
  constant Qt]. Innovation covariance given the pose: Q = Hm P Hm^T + Qt.

Proposal (FastSLAM 2.0, Probabilistic Robotics Table 13.2, generalised to several features)
  Linearisation point: x_hat (the motion mean), NOT the previous pose or a sampled pose.
  Prior N(x_hat, R). The matched observations are fused one at a time in COVARIANCE (Kalman)
  form, each with the current Gaussian as its prior:
      S_k = Hx_k Sigma Hx_k^T + Q_k,  K_k = Sigma Hx_k^T S_k^-1,
      mu <- mu + K_k (z_k - h(x_lin, m_k) - Hx_k (mu - x_lin)),  Sigma <- (I - K_k Hx_k) Sigma
  (the heading of mu - x_lin wrapped)
  with ``relinearize=False`` (default): x_lin = x_hat for every k, Hx_k, Q_k and h at x_hat.
  Then the result is EXACTLY the batch information form jaxslam writes,
      Sigma = (R^-1 + sum_k Hx_k^T Q_k^-1 Hx_k)^-1,
      mu = x_hat + Sigma sum_k Hx_k^T Q_k^-1 (z_k - h(x_hat, m_k)),
  i.e. the single-feature proposal of Table 13.2 with the information of every matched
  feature added; the reference reaches it by a different algebraic route (sequential
  Kalman updates). With
  ``relinearize=True`` each observation is linearised at the current mean (an iterated /
  sequential EKF; what one gets by running the single-feature update once per observation):
  NOT what jaxslam does; kept to measure the difference. mu[2] is wrapped.
  No matched observation: fall back to the motion model (sample the odometry noise).

Sample
  x = mu + L eps, L = chol(Sigma), eps ~ N(0, I3) (the caller passes eps); heading wrapped.
  Fallback: true odometry = u + std * eps (r1, r2 wrapped), x = g(x_prev, true odometry).

Importance weight (two forms)
  * ``textbook_log_weight`` (the paper's importance weight, Table 13.2, generalised to several
    features): the linearised marginal p(z | x_prev, u, map) = N(z; h(x_hat), L) with the
    STACKED observations, L = Hx R Hx^T + blockdiag(Q_k), everything at x_hat. The pose
    uncertainty correlates the observations, so this is NOT the product of per-feature
    N(z_k; h_k, Hx_k R Hx_k^T + Q_k). It does not depend on the sampled pose.
  * ``importance_log_weight`` [jaxslam]: the generic importance weight of the pose actually
    drawn, p(z | x, map) p_motion(x | x_prev, u) / q(x), with the exact (nonlinear) likelihood
    N(z_k; h(x, m_k), Q_k(x)) at the sampled pose, the exact motion density above and the
    Gaussian proposal density q (the mixture q_mix = (1 - phi) p_motion + phi q_obs when
    ``ratio`` < 1). Without a match q = p_motion and the correction is 0. If h were linear
    in x, Q did not depend on x and p_motion were N(x_hat, R), both forms would be equal for
    every x (``linearised_importance_log_weight`` checks this identity).
  [jaxslam] Every valid unmatched observation adds the "unexplained" constant
  -gate/2 - log det Qt(z_r)/2 - log 2 pi + new_landmark_log_offset (the textbook credits a
  new feature with p0).

Landmark update (as in FastSLAM 1.0, conditioned on the drawn pose: AT THE SAMPLED POSE x)
  z_hat = h(x, m), Hm at x, S = Hm P Hm^T + Qt(r(x)), K = P Hm^T S^-1,
  m' = m + K (z - z_hat), P' = (I - K Hm) P (standard form; jaxslam uses the Joseph form,
  equal in exact arithmetic). New landmark: m = x + r (cos a, sin a), P = G Qt(r) G^T,
  a = theta + b, G = [[cos a, -r sin a], [sin a, r cos a]], Qt at the MEASURED range.

``params`` is any mapping/object with attributes named like ``jaxslam.types.Params``
(rot1_noise, trans_noise, rot2_noise, min_translation, range_noise, bearing_noise,
range_std_floor, bearing_std_floor, association_gate, new_landmark_log_offset); use
``params_from(obj)`` to turn a jaxslam ``Params`` into plain floats.
"""
from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np

LOG_2PI = math.log(2.0 * math.pi)
POSE_JITTER = "relative"  # jaxslam's proposal.pose_jitter, a convention (module docstring)

_FIELDS = ("rot1_noise", "trans_noise", "rot2_noise", "min_translation", "range_noise",
           "bearing_noise", "range_std_floor", "bearing_std_floor", "association_gate",
           "new_landmark_log_offset")


def params_from(params) -> SimpleNamespace:
    """Plain float64 NumPy copy of the fields the reference reads."""
    return SimpleNamespace(**{name: np.array(np.asarray(getattr(params, name)), np.float64)
                              for name in _FIELDS})


def wrap(angle):
    angle = np.asarray(angle, np.float64)
    return angle - 2.0 * np.pi * np.floor((angle + np.pi) / (2.0 * np.pi))


# ---------------------------------------------------------------------------------------------
# Motion


def odometry_std(odometry, params):
    r1, t, r2 = (abs(float(v)) for v in odometry)
    a, b, c = params.rot1_noise, params.trans_noise, params.rot2_noise
    return np.array([a[0] * t + a[1] * r1 + a[2],
                     b[0] * t + b[1] * (r1 + r2) + b[2],
                     c[0] * t + c[1] * r2 + c[2]])


def apply_odometry(pose, odometry):
    x, y, theta = pose
    r1, t, r2 = odometry
    heading = theta + r1
    return np.array([x + t * math.cos(heading), y + t * math.sin(heading),
                     float(wrap(heading + r2))])


def motion_jacobian(pose, odometry):
    """J = d g / d (r1, t, r2) at (pose, odometry)."""
    heading = pose[2] + odometry[0]
    t = odometry[1]
    s, c = math.sin(heading), math.cos(heading)
    return np.array([[-t * s, c, 0.0], [t * c, s, 0.0], [1.0, 0.0, 1.0]])


def motion_pose_covariance(pose, odometry, params, pose_jitter=POSE_JITTER):
    jac = motion_jacobian(pose, odometry)
    cov = jac @ np.diag(odometry_std(odometry, params) ** 2) @ jac.T
    if pose_jitter == "relative":
        pose_jitter = 100.0 * np.finfo(np.float64).eps * max(cov[0, 0], cov[1, 1]) + 1e-14
    return cov + pose_jitter * np.eye(3)


def odometry_between(pose_prev, pose_next, min_translation):
    """(r1, t, r2) that takes pose_prev to pose_next (r1 = 0 below min_translation)."""
    dx, dy = pose_next[0] - pose_prev[0], pose_next[1] - pose_prev[1]
    c, s = math.cos(pose_prev[2]), math.sin(pose_prev[2])
    fx, fy = c * dx + s * dy, -s * dx + c * dy  # displacement in the previous frame
    t = math.hypot(fx, fy)
    r1 = math.atan2(fy, fx) if t >= min_translation else 0.0
    dtheta = float(wrap(pose_next[2] - pose_prev[2]))
    return np.array([r1, t, float(wrap(dtheta - r1))])


def motion_log_density(pose_prev, pose_next, odometry, params):
    true = odometry_between(pose_prev, pose_next, float(params.min_translation))
    std = odometry_std(odometry, params)
    diff = true - np.asarray(odometry, np.float64)
    diff[0], diff[2] = wrap(diff[0]), wrap(diff[2])
    log_move = float(np.sum(-0.5 * (diff / std) ** 2 - np.log(std) - 0.5 * LOG_2PI))
    return log_move - math.log(max(true[1], float(params.min_translation)))


# ---------------------------------------------------------------------------------------------
# Measurement


def measurement_noise(distance, params):
    sr = max(params.range_noise[0] * distance + params.range_noise[1], params.range_std_floor)
    sb = max(params.bearing_noise[0] * distance + params.bearing_noise[1],
             params.bearing_std_floor)
    return np.diag([sr * sr, sb * sb])


def predict(pose, landmark):
    """h, Hx (2, 3), Hm (2, 2) at (pose, landmark)."""
    dx, dy = landmark[0] - pose[0], landmark[1] - pose[1]
    r2 = dx * dx + dy * dy
    r = math.sqrt(r2)
    z_hat = np.array([r, float(wrap(math.atan2(dy, dx) - pose[2]))])
    hm = np.array([[dx / r, dy / r], [-dy / r2, dx / r2]])
    hx = np.array([[-dx / r, -dy / r, 0.0], [dy / r2, -dx / r2, -1.0]])
    return z_hat, hx, hm


def innovation(z, z_hat):
    nu = np.asarray(z, np.float64) - z_hat
    nu[1] = wrap(nu[1])
    return nu


def landmark_innovation_cov(pose, landmark, landmark_cov, params):
    """Q = Hm P Hm^T + Qt(r) at the given pose (r: predicted range)."""
    z_hat, hx, hm = predict(pose, landmark)
    return z_hat, hx, hm, hm @ landmark_cov @ hm.T + measurement_noise(z_hat[0], params)


def gaussian_log_density(x, mean, cov):
    x = np.atleast_1d(x)
    d = x.shape[0]
    sign, log_det = np.linalg.slogdet(cov)
    assert sign > 0
    white = np.linalg.solve(cov, x - mean)
    return float(-0.5 * (x - mean) @ white - 0.5 * log_det - 0.5 * d * LOG_2PI)


def unexplained_log_likelihood(z_range, params):
    log_det = math.log(np.linalg.det(measurement_noise(z_range, params)))
    return (-0.5 * float(params.association_gate) - 0.5 * log_det - LOG_2PI
            + float(params.new_landmark_log_offset))


# ---------------------------------------------------------------------------------------------
# Proposal


def proposal(pose_prev, odometry, landmark_means, landmark_covs, z, match, params,
             relinearize=False, pose_jitter=POSE_JITTER, linearization_pose=None):
    """The FastSLAM 2.0 Gaussian of ONE particle.

    Args: pose_prev (3,); odometry (3,) measured (r1, t, r2); landmark_means (N, 2);
    landmark_covs (N, 2, 2); z (K, 2); match (K,) landmark index or -1;
    linearization_pose: (3,) x_l where every h, Hx and Q is evaluated instead of x_hat (the
    prior stays N(x_hat, R)); ignored with ``relinearize``.
    Returns a dict: x_hat, R, mean, cov, has_match.
    """
    x_hat = apply_odometry(pose_prev, odometry)
    cov_u = motion_pose_covariance(pose_prev, odometry, params, pose_jitter)
    mean, cov = x_hat.copy(), cov_u.copy()
    has_match = False
    for k, n in enumerate(match):
        if n < 0:
            continue
        has_match = True
        x_lin = mean if relinearize else (x_hat if linearization_pose is None
                                          else np.asarray(linearization_pose, float))
        z_hat, hx, _, q = landmark_innovation_cov(x_lin, landmark_means[n], landmark_covs[n],
                                                  params)
        s = hx @ cov @ hx.T + q
        gain = cov @ hx.T @ np.linalg.inv(s)
        offset = mean - x_lin
        offset[2] = wrap(offset[2])
        nu = innovation(z[k], z_hat) - hx @ offset
        mean = mean + gain @ nu
        cov = (np.eye(3) - gain @ hx) @ cov
        cov = 0.5 * (cov + cov.T)
    mean[2] = wrap(mean[2])
    return dict(x_hat=x_hat, R=cov_u, mean=mean, cov=cov, has_match=has_match)


def gauss_newton_proposal(pose_prev, odometry, landmark_means, landmark_covs, z, match,
                          params, iterations, pose_jitter=POSE_JITTER):
    """The FastSLAM 2.0 Gaussian relinearised ``iterations`` times at its own mean (batch
    Gauss-Newton on the pose posterior's mode, the association fixed): each round runs the
    sequential covariance-form fusion of ``proposal`` from the prior N(x_hat, R) with every
    observation linearised at the previous round's mean. ``iterations`` = 0 is ``proposal``.
    """
    prop = proposal(pose_prev, odometry, landmark_means, landmark_covs, z, match, params,
                    pose_jitter=pose_jitter)
    for _ in range(iterations):
        again = proposal(pose_prev, odometry, landmark_means, landmark_covs, z, match, params,
                         pose_jitter=pose_jitter, linearization_pose=prop["mean"])
        prop = dict(again, has_match=prop["has_match"])
    return prop


def sample_pose(pose_prev, odometry, prop, eps, params):
    """The drawn pose for the standard normal ``eps`` (3,) (see the module docstring)."""
    if prop["has_match"]:
        x = prop["mean"] + np.linalg.cholesky(prop["cov"]) @ eps
    else:
        true = np.asarray(odometry, np.float64) + odometry_std(odometry, params) * eps
        true[0], true[2] = wrap(true[0]), wrap(true[2])
        x = apply_odometry(pose_prev, true)
    x[2] = wrap(x[2])
    return x


def proposal_log_density(x, prop):
    diff = np.asarray(x, np.float64) - prop["mean"]
    diff[2] = wrap(diff[2])
    return gaussian_log_density(diff, np.zeros(3), prop["cov"])


# ---------------------------------------------------------------------------------------------
# Weights


def matching_covariance(x_hat, cov_u, landmark, landmark_cov, params):
    """The FastSLAM 2.0 matching/marginal covariance of one feature at x_hat:
    L = Hx R Hx^T + Hm P Hm^T + Qt. Returns (z_hat, L)."""
    z_hat, hx, _, q = landmark_innovation_cov(x_hat, landmark, landmark_cov, params)
    return z_hat, hx @ cov_u @ hx.T + q


def textbook_log_weight(prop, landmark_means, landmark_covs, z, match, params):
    """log N(z_matched; h(x_hat), Hx R Hx^T + blockdiag Q), stacked over matched features
    (0 without a match). Unexplained observations are not included."""
    rows = [(k, n) for k, n in enumerate(match) if n >= 0]
    if not rows:
        return 0.0
    x_hat, cov_u = prop["x_hat"], prop["R"]
    nus, hxs, qs = [], [], []
    for k, n in rows:
        z_hat, hx, _, q = landmark_innovation_cov(x_hat, landmark_means[n], landmark_covs[n],
                                                  params)
        nus.append(innovation(z[k], z_hat))
        hxs.append(hx)
        qs.append(q)
    nu = np.concatenate(nus)
    hx = np.concatenate(hxs, axis=0)
    big = hx @ cov_u @ hx.T
    for i, q in enumerate(qs):
        big[2 * i:2 * i + 2, 2 * i:2 * i + 2] += q
    return gaussian_log_density(nu, np.zeros_like(nu), big)


def observation_log_likelihood(x, landmark_means, landmark_covs, z, match, valid, params):
    """sum_k log N(z_k; h(x, m_k), Q_k(x)) over matched rows + the unexplained constant of
    every valid unmatched row, all at the pose x."""
    total = 0.0
    for k, n in enumerate(match):
        if not valid[k]:
            continue
        if n < 0:
            total += unexplained_log_likelihood(float(z[k][0]), params)
            continue
        z_hat, _, _, q = landmark_innovation_cov(x, landmark_means[n], landmark_covs[n], params)
        total += gaussian_log_density(innovation(z[k], z_hat), np.zeros(2), q)
    return total


def mixture_log_correction(pose_prev, x, odometry, prop, params, ratio=1.0):
    """log p_motion(x) - log((1 - phi) p_motion(x) + phi q_obs(x)); 0 without a match."""
    if not prop["has_match"]:
        return 0.0
    log_motion = motion_log_density(pose_prev, x, odometry, params)
    log_obs = proposal_log_density(x, prop)
    phi = min(max(float(ratio), 0.0), 1.0)
    if phi >= 1.0:
        return log_motion - log_obs
    if phi <= 0.0:
        return 0.0
    log_mix = np.logaddexp(math.log1p(-phi) + log_motion, math.log(phi) + log_obs)
    return float(log_motion - log_mix)


def importance_log_weight(pose_prev, x, odometry, prop, landmark_means, landmark_covs, z,
                          match, valid, params, ratio=1.0):
    """jaxslam's weight increment: log p(z | x, map) + log p_motion(x) - log q(x)."""
    return (observation_log_likelihood(x, landmark_means, landmark_covs, z, match, valid,
                                       params)
            + mixture_log_correction(pose_prev, x, odometry, prop, params, ratio))


def linearised_importance_log_weight(x, prop, landmark_means, landmark_covs, z, match,
                                     params):
    """p(z | x) p(x) / q(x) with h linearised at x_hat, Q fixed at x_hat and p(x) = N(x_hat, R)
    (matched rows only). Equals ``textbook_log_weight`` for EVERY x when q is the proposal
    built with ``relinearize=False``: a self-check of the reference."""
    x_hat = prop["x_hat"]
    dx = np.asarray(x, np.float64) - x_hat
    dx[2] = wrap(dx[2])
    total = gaussian_log_density(dx, np.zeros(3), prop["R"])
    for k, n in enumerate(match):
        if n < 0:
            continue
        z_hat, hx, _, q = landmark_innovation_cov(x_hat, landmark_means[n], landmark_covs[n],
                                                  params)
        total += gaussian_log_density(innovation(z[k], z_hat) - hx @ dx, np.zeros(2), q)
    return total - proposal_log_density(x, prop)


# ---------------------------------------------------------------------------------------------
# Landmarks


def landmark_update(x, landmark, landmark_cov, z, params):
    """EKF update at the sampled pose x. Returns (mean (2,), cov (2, 2))."""
    z_hat, _, hm, s = landmark_innovation_cov(x, landmark, landmark_cov, params)
    gain = landmark_cov @ hm.T @ np.linalg.inv(s)
    mean = np.asarray(landmark, np.float64) + gain @ innovation(z, z_hat)
    cov = (np.eye(2) - gain @ hm) @ landmark_cov
    return mean, 0.5 * (cov + cov.T)


def initialize_landmark(x, z, params):
    r, angle = float(z[0]), x[2] + float(z[1])
    c, s = math.cos(angle), math.sin(angle)
    g = np.array([[c, -r * s], [s, r * c]])
    return (np.array([x[0] + r * c, x[1] + r * s]),
            g @ measurement_noise(r, params) @ g.T)


# ---------------------------------------------------------------------------------------------
# One step


def step(pose_prev, odometry, landmark_means, landmark_covs, z, match, valid, params, eps,
         ratio=1.0, relinearize=False, pose_jitter=POSE_JITTER):
    """FastSLAM 2.0 step of ONE particle with known association (observation proposal).

    Returns a dict: the proposal fields, ``pose`` (the drawn pose for ``eps``),
    ``log_weight`` (``importance_log_weight``, jaxslam's form), ``textbook_log_weight``,
    ``landmark_means`` / ``landmark_covs`` after the updates of the matched landmarks, and
    ``born`` (list of (k, mean, cov)) for the valid unmatched observations.
    """
    match = [int(n) if valid[k] else -1 for k, n in enumerate(match)]
    prop = proposal(pose_prev, odometry, landmark_means, landmark_covs, z, match, params,
                    relinearize, pose_jitter)
    x = sample_pose(pose_prev, odometry, prop, eps, params)
    means = np.array(landmark_means, np.float64, copy=True)
    covs = np.array(landmark_covs, np.float64, copy=True)
    born = []
    for k, n in enumerate(match):
        if not valid[k]:
            continue
        if n < 0:
            born.append((k, *initialize_landmark(x, z[k], params)))
            continue
        means[n], covs[n] = landmark_update(x, landmark_means[n], landmark_covs[n], z[k],
                                            params)
    return dict(prop, pose=x,
                log_weight=importance_log_weight(pose_prev, x, odometry, prop, landmark_means,
                                                 landmark_covs, z, match, valid, params,
                                                 ratio),
                textbook_log_weight=textbook_log_weight(prop, landmark_means, landmark_covs,
                                                        z, match, params),
                landmark_means=means, landmark_covs=covs, born=born)
