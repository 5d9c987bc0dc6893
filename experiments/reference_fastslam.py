"""An independent NumPy float64 FastSLAM 2.0 particle filter, and a driver for the held-out logs.

Purpose: tell whether jaxslam's divergence at the hard point of ``experiments/proposal_study.py``
(wobble 0.3 m, odometry 6x Table 1 of Geiser et al. 2023, 5 mm / 0.5 mrad lidar, P = 20) is a
defect of jaxslam or a limit of FastSLAM 2.0 on those logs. The FILTER below imports nothing
from ``jaxslam``: every formula is written here from Montemerlo et al. 2003 ("FastSLAM 2.0: An
Improved Particle Filtering Algorithm for SLAM in which Landmark Estimates Converge Provably")
and Thrun, Burgard, Fox, "Probabilistic Robotics" (2005), Table 13.2, with unknown data
association. Only the LOG GENERATION (``load_logs``) calls the project's simulator (data).

Model (the simulator's, read from ``sims/scenario.py`` and ``jaxslam/motion.py``)
  pose (x, y, theta); angles wrapped to [-pi, pi) by a - 2 pi floor((a + pi) / (2 pi)).
  Move u = (r1, t, r2): x' = x + t cos(theta + r1), y' = y + t sin(theta + r1),
  theta' = theta + r1 + r2. The simulator draws the MEASURED move around the true one with
  std (Geiser et al. 2023, Eq. 1) = (a1|t| + b1|r1| + c1, a2|t| + b2(|r1|+|r2|) + c2,
  a3|t| + b3|r2| + c3) evaluated at the TRUE move; the filter knows only the measured move and
  evaluates the std there (so small measured turns get far too small a std: see ``bursts``).
  Measurement h(x, m) = (|m - p|, wrap(atan2(dy, dx) - theta)) with per-component std
  d * range + e (floored), evaluated at the predicted range.

Filter (one particle's step; vectorised over particles, and over burst pieces)
  motion prior  N(x_hat, R): x_hat = g(x_prev, u), R = J diag(std(u)^2) J^T + jitter I, J the
                Jacobian of g w.r.t. (r1, t, r2).
  association   at x_hat, squared Mahalanobis distance with S = Hx R Hx^T + Hm P Hm^T + Q
                (``pose_uncertainty``; else without Hx R Hx^T), chi-square gate (13.8: 99.9 %,
                2 dof), one-to-one by greedy smallest distance; an observation left without a
                landmark is a new landmark.
  proposal      FastSLAM 2.0 Gaussian, several features in information form:
                Sigma = (R^-1 + sum_k Hx_k^T D_k^-1 Hx_k)^-1, D_k = Hm P Hm^T + Q,
                mu = x_hat + Sigma sum_k Hx_k^T D_k^-1 v_k, with v_k = z_k - h(x_lin, m_k)
                + Hx_k (x_lin - x_hat) (bearing and heading wrapped). With ``iterations`` = n
                the proposal is linearised n times (Gauss-Newton / iterated EKF): x_lin = x_hat
                first, then x_lin = the previous mu, the observations associated AGAIN at the
                previous mu with the previous Sigma as pose uncertainty.
  weight        the marginal likelihood of the matched observations under the linearised
                model, STACKED (the features share the pose, so their product would count the
                pose uncertainty once per feature): log N(v; 0, H R H^T + blockdiag(D)) by the
                Woodbury / determinant lemma,
                  quad = sum_k v_k^T D_k^-1 v_k - g^T Sigma g,  g = sum_k Hx_k^T D_k^-1 v_k,
                  logdet = sum_k log|D_k| + log|R| + log|Sigma^-1|;
                times, for each valid observation left unmatched, a constant new-landmark
                density p0 (``new_landmark``): ``"field"`` (default) the uniform density of
                a new tree over the sensor's field in (range, bearing), 1 / (max_range 2 pi)
                (log p0 = -4.33 at 12 m); ``"gate"`` the density of a perfectly known
                landmark at the gate's edge, exp(-gate / 2) / (2 pi sqrt(det Q(z_range)))
                (log p0 = +4.16 for 5 mm / 0.5 mrad and gate 13.8). With so precise a sensor
                the gate-edge p0 is within a few nats per observation of a correct match
                after the pose's Occam factor, so "every observation is a new tree" pieces
                compete with the right association (seen in these logs); the field density
                is the Bayesian new-feature density. (``weight="product"``: Table 13.2's
                per-feature N(v_k; 0, Hx R Hx^T + D_k) multiplied instead, for ablation.)
  bursts        (``bursts``) the true move is often 5-50 sigma(u) from the measured one in
                these logs (in rot1 AND rot2; trans up to ~5 sigma), because Eq. (1)'s std is
                evaluated at the measured move. The move prior becomes a mixture. For each
                family in ``burst_families`` (default rot1, rot2, trans) the component's
                range is cut into cells of width delta (0.05 rad for turns up to +-0.5 rad
                = ``burst_span``; 0.1 m for trans up to +-0.4 m), with masses pi_j = the
                integral over cell j of a heavy-tailed density rho of the true value c:
                ``burst_prior="inverted"`` (default) rho(c) = N(u_i; c, s_i(c)^2), the
                Eq. (1) likelihood of the measured value given the true value c (flat prior
                on c; the std grows with |c|, hence the heavy tail); ``"mixture"``:
                0.95 N(c; u_i, s_i(u)^2) + 0.05 N(c; u_i, 0.15^2). The core piece (every
                component in its centre cell) is the ordinary prior N(x_hat, R); each
                off-centre piece moves ONE component to the centre of cell j with std
                delta / 2 (the others keep the core's std), mass pi_j x the other families'
                centre masses (two tails at once are neglected). A rot1-only family (the
                first design) cannot represent a rot2 burst: it shifts the heading only
                together with a lateral offset t * delta. Every piece is
                associated (with its own pose uncertainty), gets its own FastSLAM 2.0
                proposal N(mu_j, Sigma_j) and normaliser Z_j (stacked marginal x
                new-landmark credits); the particle draws piece j with probability
                pi_j Z_j / sum and samples from its proposal; its weight is sum_j pi_j Z_j
                (the marginal likelihood under the mixture prior). The pieces are evaluated
                only for TRIGGERED particles: those with at least one landmark for which the
                core association matched fewer than half of the observations "near the map"
                (a valid observation whose range is within ``burst_near`` = 0.5 m of an
                active landmark's range predicted at x_hat and whose bearing is within
                burst_span + 0.1 rad of its predicted bearing: the range hardly depends on
                the heading, so this counts the observations a burst could explain); with
                ``burst_always`` every particle with a map. An untriggered particle's weight
                is pi_0 Z_0 (the other pieces neglected), consistent with the mixture.
  first step    (``anchor_first``) while every particle's map is empty, every particle takes
                the motion prediction's mean (the map frame is not spread by sampling).
  sample        x ~ N(mu, Sigma) (Cholesky); then (``associate_at_sample``) the observations
                are associated again at x (no pose term) for the landmark update.
  landmarks     EKF update at x (Joseph form), Q at the predicted range; a new landmark by
                inverse observation, covariance G Q G^T, G = d(m)/d(range, bearing).
  existence     (``delete``) a counter per landmark: 1 when created, +1 when matched (at
                most 5), -1 when predicted at x in range (min_range < r < max_range - 0.25 m,
                and nearer than the farthest observation when K observations are reported,
                since the sensor keeps only the K nearest) but not matched; deleted below 0.
                The analytic sensor has no occlusion, so a missed landmark is a wrong one.
  resampling    systematic, when the effective sample size is below ``resample_threshold`` P.
  estimate      the weighted mean pose after the last step (circular mean heading); final error
                = |(x, y) - truth[-1, :2]|; diverged = final error > 1 m.

Driver (the logs of ``experiments/proposal_study.py``: seed 700, wobble 0.3 m, odometry 6x):

    python experiments/reference_fastslam.py --runs 1000 --forests 50 --first 40 --particles 20
"""
from __future__ import annotations

import argparse
import dataclasses
import math
import pathlib
import sys
import time

import numpy as np

LOG_2PI = math.log(2.0 * math.pi)
TWO_PI = 2.0 * math.pi


def wrap(angle):
    """Wrap to [-pi, pi)."""
    return angle - TWO_PI * np.floor((angle + math.pi) / TWO_PI)


# ------------------------------------------------------------------------------------------
# Noise model and configuration
# ------------------------------------------------------------------------------------------

@dataclasses.dataclass(frozen=True)
class Noise:
    """The filter's noise model (float64)."""

    rot1: tuple  # (a1, b1, c1) of Eq. (1)
    trans: tuple  # (a2, b2, c2)
    rot2: tuple  # (a3, b3, c3)
    range_noise: tuple  # (d, e): std = d * range + e
    bearing_noise: tuple
    range_floor: float
    bearing_floor: float
    max_range: float
    min_range: float

    @classmethod
    def from_params(cls, params) -> "Noise":
        """From a jaxslam ``Params`` (or any object with those fields): only numbers are read."""
        vec = lambda name: tuple(np.asarray(getattr(params, name), np.float64).tolist())
        num = lambda name: float(np.asarray(getattr(params, name), np.float64))
        return cls(vec("rot1_noise"), vec("trans_noise"), vec("rot2_noise"), vec("range_noise"),
                   vec("bearing_noise"), num("range_std_floor"), num("bearing_std_floor"),
                   num("max_range"), num("min_range"))

    def odometry_std(self, u):
        """Eq. (1) std (..., 3) of (r1, t, r2) at the move u (..., 3)."""
        r1, t, r2 = np.abs(u[..., 0]), np.abs(u[..., 1]), np.abs(u[..., 2])
        a = self.rot1, self.trans, self.rot2
        return np.stack([a[0][0] * t + a[0][1] * r1 + a[0][2],
                         a[1][0] * t + a[1][1] * (r1 + r2) + a[1][2],
                         a[2][0] * t + a[2][1] * r2 + a[2][2]], -1)

    def sensor_var(self, distance):
        """(var_range, var_bearing) at ``distance`` (any shape), floored stds squared."""
        sr = np.maximum(self.range_noise[0] * distance + self.range_noise[1], self.range_floor)
        sb = np.maximum(self.bearing_noise[0] * distance + self.bearing_noise[1],
                        self.bearing_floor)
        return sr * sr, sb * sb


@dataclasses.dataclass(frozen=True)
class Config:
    particles: int = 20
    max_landmarks: int = 96
    gate: float = 13.8  # chi-square 99.9 %, 2 dof
    pose_uncertainty: bool = True  # Hx R Hx^T in the association at x_hat
    iterations: int = 2  # proposal linearisations (>1: re-associate at the previous mu)
    bursts: bool = True
    burst_always: bool = False
    burst_families: tuple = ("rot1", "rot2", "trans")  # move components with tail pieces
    burst_span: float = 0.5  # rad each side of the measured turn (rot1, rot2)
    burst_spacing: float = 0.05  # rad between turn pieces
    burst_trans_span: float = 0.4  # m each side of the measured translation
    burst_trans_spacing: float = 0.1  # m between translation pieces
    burst_prior: str = "inverted"  # "inverted" or "mixture"
    burst_near: float = 0.5  # m: range tolerance of "an observation near a mapped landmark"
    anchor_first: bool = True
    associate_at_sample: bool = True
    weight: str = "stacked"  # "stacked" or "product"
    new_landmark: str = "field"  # "field" or "gate": the new-landmark density p0
    delete: bool = True
    existence_max: int = 5
    resample_threshold: float = 0.5
    jitter: float = 1e-12


# ------------------------------------------------------------------------------------------
# Small linear algebra helpers (batched)
# ------------------------------------------------------------------------------------------

def inv2(s):
    """Inverse and log-determinant of symmetric 2x2 matrices (..., 2, 2)."""
    a, b, c = s[..., 0, 0], 0.5 * (s[..., 0, 1] + s[..., 1, 0]), s[..., 1, 1]
    det = a * c - b * b
    inv = np.empty_like(s)
    inv[..., 0, 0] = c / det
    inv[..., 0, 1] = inv[..., 1, 0] = -b / det
    inv[..., 1, 1] = a / det
    return inv, np.log(det)


def symmetric(a):
    return 0.5 * (a + np.swapaxes(a, -1, -2))


def motion_mean(pose, u):
    """g(pose, u): (..., 3)."""
    heading = pose[..., 2] + u[..., 0]
    return np.stack([pose[..., 0] + u[..., 1] * np.cos(heading),
                     pose[..., 1] + u[..., 1] * np.sin(heading),
                     wrap(heading + u[..., 2])], -1)


def motion_cov(pose, u, std, jitter):
    """R = J diag(std^2) J^T + jitter I, J = dg / d(r1, t, r2) at (pose, u): (..., 3, 3)."""
    heading = pose[..., 2] + u[..., 0]
    t = u[..., 1]
    shape = np.broadcast_shapes(heading.shape, std.shape[:-1])
    jac = np.zeros(shape + (3, 3))
    jac[..., 0, 0] = -t * np.sin(heading)
    jac[..., 0, 1] = np.cos(heading)
    jac[..., 1, 0] = t * np.cos(heading)
    jac[..., 1, 1] = np.sin(heading)
    jac[..., 2, 0] = 1.0
    jac[..., 2, 2] = 1.0
    cov = np.einsum("...ij,...j,...kj->...ik", jac, std * std, jac)
    return symmetric(cov) + jitter * np.eye(3)


def geometry(x, m):
    """Predicted measurement (..., 2), Hx (..., 2, 3), Hm (..., 2, 2) of landmark m at pose x."""
    dx = m[..., 0] - x[..., 0]
    dy = m[..., 1] - x[..., 1]
    q = np.maximum(dx * dx + dy * dy, 1e-18)
    r = np.sqrt(q)
    zhat = np.stack([r, wrap(np.arctan2(dy, dx) - x[..., 2])], -1)
    hm = np.empty(dx.shape + (2, 2))
    hm[..., 0, 0] = dx / r
    hm[..., 0, 1] = dy / r
    hm[..., 1, 0] = -dy / q
    hm[..., 1, 1] = dx / q
    hx = np.zeros(dx.shape + (2, 3))
    hx[..., :, :2] = -hm
    hx[..., 1, 2] = -1.0
    return zhat, hx, hm


def innovation_cov(noise, zhat, hm, cov):
    """D = Hm P Hm^T + Q(predicted range): (..., 2, 2)."""
    d = np.einsum("...ij,...jk,...lk->...il", hm, cov, hm)
    var_r, var_b = noise.sensor_var(zhat[..., 0])
    d[..., 0, 0] += var_r
    d[..., 1, 1] += var_b
    return symmetric(d)


def log_new_landmark(noise, config, z):
    """log p0 (K,) of each observation z (K, 2) being a new landmark.

    ``new_landmark="gate"``: exp(-gate / 2) / (2 pi sqrt(det Q(z_range))), the density of a
    match exactly at the gate's edge under the sensor noise alone. ``"field"``: the uniform
    density 1 / (max_range 2 pi) over the sensor's field in (range, bearing)."""
    if config.new_landmark == "gate":
        var_r, var_b = noise.sensor_var(z[:, 0])
        return -0.5 * config.gate - LOG_2PI - 0.5 * np.log(var_r * var_b)
    if config.new_landmark == "field":
        return np.full(z.shape[0], -math.log(TWO_PI * noise.max_range))
    raise ValueError(f"new_landmark={config.new_landmark!r}")


# ------------------------------------------------------------------------------------------
# Association, proposal
# ------------------------------------------------------------------------------------------

def greedy_assign(d2):
    """One-to-one assignment (B, K) from distances (B, K, M) (inf = not allowed), greedily by
    the smallest distance: each observation and each landmark at most once; -1 = none."""
    b_count, k_count, m_count = d2.shape
    match = np.full((b_count, k_count), -1, np.int64)
    if m_count == 0:
        return match
    flat = d2.reshape(b_count, k_count * m_count).copy()
    view = flat.reshape(b_count, k_count, m_count)
    rows = np.arange(b_count)
    for _ in range(min(k_count, m_count)):
        idx = np.argmin(flat, axis=1)
        best = flat[rows, idx]
        ok = np.isfinite(best)
        if not ok.any():
            break
        b = rows[ok]
        k, m = idx[ok] // m_count, idx[ok] % m_count
        match[b, k] = m
        view[b, k, :] = np.inf
        view[b, :, m] = np.inf
    return match


def associate(noise, gate, x, pose_cov, mean, cov, active, z, valid):
    """Matches (B, K) of the observations z (K, 2), valid (K,) to the landmarks (B, M, ...)
    seen from x (B, 3); pose_cov (B, 3, 3) adds Hx pose_cov Hx^T to the innovation covariance
    (None: not). Also returns the predicted measurements (B, M, 2)."""
    zhat, hx, hm = geometry(x[:, None, :], mean)
    s = innovation_cov(noise, zhat, hm, cov)
    if pose_cov is not None:
        s = s + np.einsum("bmij,bjk,bmlk->bmil", hx, pose_cov, hx)
    s_inv, _ = inv2(s)
    nu = z[None, :, None, :] - zhat[:, None, :, :]  # (B, K, M, 2)
    nu[..., 1] = wrap(nu[..., 1])
    si = s_inv[:, None]
    d2 = (si[..., 0, 0] * nu[..., 0] ** 2 + 2.0 * si[..., 0, 1] * nu[..., 0] * nu[..., 1]
          + si[..., 1, 1] * nu[..., 1] ** 2)
    allowed = active[:, None, :] & valid[None, :, None] & (d2 < gate)
    return greedy_assign(np.where(allowed, d2, np.inf)), zhat


@dataclasses.dataclass
class Proposal:
    mu: np.ndarray  # (B, 3)
    sigma: np.ndarray  # (B, 3, 3)
    log_z: np.ndarray  # (B,) log evidence of the matched observations (no new-landmark term)
    matched: np.ndarray  # (B,) number of matched observations


def gaussian_proposal(noise, x_hat, r_cov, x_lin, mean, cov, match, z, weight="stacked"):
    """FastSLAM 2.0 proposal N(mu, Sigma) (information form) and the log marginal likelihood
    of the matched observations, linearised at x_lin (B, 3), prior N(x_hat, R) (B, 3) (B, 3, 3),
    matches (B, K) into the landmarks mean (B, M, 2), cov (B, M, 2, 2)."""
    b_count, k_count = match.shape
    has = match >= 0
    idx = np.where(has, match, 0)
    rows = np.arange(b_count)[:, None]
    mk, pk = mean[rows, idx], cov[rows, idx]  # (B, K, 2), (B, K, 2, 2)
    zhat, hx, hm = geometry(x_lin[:, None, :], mk)
    d = innovation_cov(noise, zhat, hm, pk)
    d_inv, logdet_d = inv2(d)
    d_inv = np.where(has[..., None, None], d_inv, 0.0)
    logdet_d = np.where(has, logdet_d, 0.0)
    e = z[None] - zhat
    e[..., 1] = wrap(e[..., 1])
    shift = x_lin - x_hat
    shift[:, 2] = wrap(shift[:, 2])
    v = e + np.einsum("bkij,bj->bki", hx, shift)
    v = np.where(has[..., None], v, 0.0)
    ht_dinv = np.einsum("bkji,bkjl->bkil", hx, d_inv)  # (B, K, 3, 2)
    r_inv = np.linalg.inv(r_cov)
    info = symmetric(r_inv + np.einsum("bkil,bklj->bij", ht_dinv, hx))
    sigma = symmetric(np.linalg.inv(info))
    g = np.einsum("bkil,bkl->bi", ht_dinv, v)
    step = np.einsum("bij,bj->bi", sigma, g)
    mu = x_hat + step
    mu[:, 2] = wrap(mu[:, 2])
    n = has.sum(1)
    if weight == "stacked":
        quad = np.einsum("bki,bkij,bkj->b", v, d_inv, v) - np.einsum("bi,bi->b", g, step)
        logdet = (logdet_d.sum(1) + np.linalg.slogdet(r_cov)[1] + np.linalg.slogdet(info)[1])
        log_z = -0.5 * quad - 0.5 * logdet - n * LOG_2PI
    elif weight == "product":
        c = d + np.einsum("bkij,bjl,bkml->bkim", hx, r_cov, hx)
        c_inv, logdet_c = inv2(c)
        terms = (-0.5 * np.einsum("bki,bkij,bkj->bk", v, c_inv, v) - 0.5 * logdet_c - LOG_2PI)
        log_z = np.where(has, terms, 0.0).sum(1)
    else:
        raise ValueError(f"weight={weight!r}")
    log_z = np.where(n > 0, log_z, 0.0)
    return Proposal(mu, sigma, log_z, n)


def propose(noise, config, x_hat, r_cov, mean, cov, active, z, valid, log_p0):
    """Associate at x_hat, then ``iterations`` linearisations (re-associating at each previous
    mu). Returns (Proposal with log_z including the new-landmark credits, matches (B, K),
    predicted measurements at x_hat (B, M, 2))."""
    match, zhat = associate(noise, config.gate, x_hat,
                            r_cov if config.pose_uncertainty else None, mean, cov, active, z,
                            valid)
    x_lin = x_hat
    for it in range(config.iterations):
        prop = gaussian_proposal(noise, x_hat, r_cov, x_lin, mean, cov, match, z, config.weight)
        if it + 1 < config.iterations:
            x_lin = prop.mu
            match, _ = associate(noise, config.gate, x_lin,
                                 prop.sigma if config.pose_uncertainty else None, mean, cov,
                                 active, z, valid)
    unmatched = valid[None, :] & (match < 0)
    prop.log_z = prop.log_z + np.where(unmatched, log_p0[None, :], 0.0).sum(1)
    return prop, match, zhat


def family_masses(noise, config, u, component, spacing, span):
    """Cells of one burst family: offsets (2J+1,) of move component ``component`` (0 rot1,
    1 trans, 2 rot2) from the measured u, log prior masses (2J+1,) of the cells (normalised
    over the family) under the heavy-tailed density rho of that component (module docstring).
    Trans cells whose true translation would be <= 0 get mass 0 (log -inf)."""
    count = int(round(span / spacing))
    offsets = spacing * np.arange(-count, count + 1)
    sub = spacing * ((np.arange(10) + 0.5) / 10.0 - 0.5)
    c = u[component] + offsets[:, None] + sub[None, :]  # true values inside each cell
    grid = np.broadcast_to(u, c.shape + (3,)).copy()
    if config.burst_prior == "inverted":
        grid[..., component] = c
        s = noise.odometry_std(grid)[..., component]
        dens = np.exp(-0.5 * ((u[component] - c) / s) ** 2) / s
    elif config.burst_prior == "mixture":
        s = noise.odometry_std(u)[component]
        wide = 0.15
        dens = (0.95 * np.exp(-0.5 * ((c - u[component]) / s) ** 2) / s
                + 0.05 * np.exp(-0.5 * ((c - u[component]) / wide) ** 2) / wide)
    else:
        raise ValueError(f"burst_prior={config.burst_prior!r}")
    if component == 1:
        dens = np.where(c > 0.0, dens, 0.0)
    mass = dens.mean(1)
    with np.errstate(divide="ignore"):
        return offsets, np.log(mass / mass.sum())


FAMILIES = {"rot1": 0, "trans": 1, "rot2": 2}


def piece_table(noise, config, u):
    """The off-centre burst pieces: shift (J, 3) of the move, the within-piece std (J, 3)
    (NaN: the core's Eq. (1) std), log prior masses (J,), and the core piece's log mass.
    Each piece moves ONE component off its centre cell (the others in their centre cells:
    combinations of two tails are neglected), so its mass is that component's cell mass
    times the centre-cell masses of the other families."""
    shifts, stds, logs, centre_logs = [], [], [], []
    for name in config.burst_families:
        comp = FAMILIES[name]
        spacing = config.burst_spacing if comp != 1 else config.burst_trans_spacing
        span = config.burst_span if comp != 1 else config.burst_trans_span
        offsets, log_mass = family_masses(noise, config, u, comp, spacing, span)
        centre = len(offsets) // 2
        centre_logs.append(log_mass[centre])
        keep = [j for j in range(len(offsets)) if j != centre and np.isfinite(log_mass[j])]
        shift = np.zeros((len(keep), 3))
        shift[:, comp] = offsets[keep]
        std = np.full((len(keep), 3), np.nan)
        std[:, comp] = 0.5 * spacing
        shifts.append(shift)
        stds.append(std)
        logs.append(log_mass[keep] - log_mass[centre])  # times the centre masses, below
    core = float(np.sum(centre_logs))
    return (np.concatenate(shifts), np.concatenate(stds), np.concatenate(logs) + core, core)


# ------------------------------------------------------------------------------------------
# The filter
# ------------------------------------------------------------------------------------------

@dataclasses.dataclass
class State:
    pose: np.ndarray  # (P, 3)
    mean: np.ndarray  # (P, M, 2)
    cov: np.ndarray  # (P, M, 2, 2)
    active: np.ndarray  # (P, M) bool
    count: np.ndarray  # (P, M) int existence counter
    log_w: np.ndarray  # (P,)

    @classmethod
    def initial(cls, start, config):
        p, m = config.particles, config.max_landmarks
        return cls(np.tile(np.asarray(start, np.float64), (p, 1)), np.zeros((p, m, 2)),
                   np.tile(np.eye(2), (p, m, 1, 1)), np.zeros((p, m), bool),
                   np.zeros((p, m), np.int64), np.full(p, -math.log(p)))

    def take(self, idx):
        return State(self.pose[idx], self.mean[idx], self.cov[idx], self.active[idx],
                     self.count[idx], np.full(len(idx), -math.log(len(idx))))


def sample_gaussian(rng, mu, sigma):
    """x ~ N(mu, Sigma) per row, heading wrapped."""
    noise = rng.standard_normal(mu.shape)
    try:
        chol = np.linalg.cholesky(sigma)
        step = np.einsum("bij,bj->bi", chol, noise)
    except np.linalg.LinAlgError:
        vals, vecs = np.linalg.eigh(sigma)
        step = np.einsum("bij,bj->bi", vecs * np.sqrt(np.maximum(vals, 0.0))[:, None, :], noise)
    x = mu + step
    x[:, 2] = wrap(x[:, 2])
    return x


def update_landmarks(noise, config, state, x, match, z, valid):
    """EKF update of the matched landmarks at the poses x (P, 3), new landmarks for the valid
    unmatched observations, existence counters and deletion."""
    rows, ks = np.nonzero(match >= 0)
    if rows.size:
        ms = match[rows, ks]
        m, pcov = state.mean[rows, ms], state.cov[rows, ms]
        zhat, _, hm = geometry(x[rows], m)
        d = innovation_cov(noise, zhat, hm, pcov)
        d_inv, _ = inv2(d)
        gain = np.einsum("nij,nkj,nkl->nil", pcov, hm, d_inv)  # P Hm^T D^-1 (n, 2, 2)
        nu = z[ks] - zhat
        nu[:, 1] = wrap(nu[:, 1])
        state.mean[rows, ms] = m + np.einsum("nij,nj->ni", gain, nu)
        a = np.eye(2) - np.einsum("nij,njk->nik", gain, hm)
        var_r, var_b = noise.sensor_var(zhat[:, 0])
        q = np.zeros((rows.size, 2, 2))
        q[:, 0, 0], q[:, 1, 1] = var_r, var_b
        state.cov[rows, ms] = symmetric(np.einsum("nij,njk,nlk->nil", a, pcov, a)
                                        + np.einsum("nij,njk,nlk->nil", gain, q, gain))
        state.count[rows, ms] = np.minimum(state.count[rows, ms] + 1, config.existence_max)
    if config.delete:
        matched = np.zeros_like(state.active)
        if rows.size:
            matched[rows, match[rows, ks]] = True
        zhat, _, _ = geometry(x[:, None, :], state.mean)
        r = zhat[..., 0]
        expected = (state.active & (r > noise.min_range) & (r < noise.max_range - 0.25))
        if valid.sum() >= valid.size:  # K reported: the sensor kept only the K nearest
            expected &= r < z[valid, 0].max()
        missed = expected & ~matched
        state.count[missed] -= 1
        state.active &= state.count >= 0
    # New landmarks.
    new_rows, new_ks = np.nonzero(valid[None, :] & (match < 0))
    if new_rows.size:
        for p in np.unique(new_rows):
            ks_p = new_ks[new_rows == p]
            free = np.flatnonzero(~state.active[p])[:ks_p.size]
            ks_p = ks_p[:free.size]
            if not free.size:
                continue
            rng_, brg = z[ks_p, 0], z[ks_p, 1]
            ang = x[p, 2] + brg
            cos_a, sin_a = np.cos(ang), np.sin(ang)
            state.mean[p, free, 0] = x[p, 0] + rng_ * cos_a
            state.mean[p, free, 1] = x[p, 1] + rng_ * sin_a
            g = np.empty((free.size, 2, 2))
            g[:, 0, 0], g[:, 0, 1] = cos_a, -rng_ * sin_a
            g[:, 1, 0], g[:, 1, 1] = sin_a, rng_ * cos_a
            var_r, var_b = noise.sensor_var(rng_)
            q = np.zeros((free.size, 2, 2))
            q[:, 0, 0], q[:, 1, 1] = var_r, var_b
            state.cov[p, free] = symmetric(np.einsum("nij,njk,nlk->nil", g, q, g))
            state.active[p, free] = True
            state.count[p, free] = 1


def systematic_resample(rng, weights):
    p = weights.size
    positions = (rng.random() + np.arange(p)) / p
    cumulative = np.cumsum(weights)
    cumulative[-1] = 1.0
    return np.searchsorted(cumulative, positions, side="right").clip(0, p - 1)


def weighted_mean_pose(pose, w):
    return np.array([w @ pose[:, 0], w @ pose[:, 1],
                     math.atan2(w @ np.sin(pose[:, 2]), w @ np.cos(pose[:, 2]))])


def normalise(log_w):
    w = np.exp(log_w - log_w.max())
    return w / w.sum()


def filter_step(noise, config, state, u, z, valid, rng, stats):
    """One FastSLAM 2.0 step (move u (3,), observations z (K, 2), valid (K,)), in place."""
    p_count = config.particles
    used = np.flatnonzero(state.active.any(0))
    m_used = used[-1] + 1 if used.size else 0
    empty = m_used == 0
    m_used = max(m_used, 1)  # at least one (inactive) slot, so that gathers have a target
    mean, cov, active = state.mean[:, :m_used], state.cov[:, :m_used], state.active[:, :m_used]
    std = noise.odometry_std(u)
    x_hat = motion_mean(state.pose, u)
    r_cov = motion_cov(state.pose, u, std, config.jitter)
    log_p0 = log_new_landmark(noise, config, z)

    if config.anchor_first and empty:
        # Empty map everywhere: every particle takes the motion mean; no weight change.
        match = np.full((p_count, z.shape[0]), -1)
        update_landmarks(noise, config, state, x_hat, match, z, valid)
        state.pose = x_hat
        return

    prop, match, zhat = propose(noise, config, x_hat, r_cov, mean, cov, active, z, valid,
                                log_p0)
    mu, sigma, match_final = prop.mu, prop.sigma, match
    log_evidence = prop.log_z.copy()
    if config.bursts:
        shifts, piece_std, log_mass, log_core = piece_table(noise, config, u)
        log_evidence += log_core
        has_map = active.any(1)
        if config.burst_always:
            trigger = has_map
        else:
            dr = np.abs(z[None, :, None, 0] - zhat[:, None, :, 0])
            db = np.abs(wrap(z[None, :, None, 1] - zhat[:, None, :, 1]))
            near = (active[:, None, :] & (dr < config.burst_near)
                    & (db < config.burst_span + 0.1)).any(2) & valid[None, :]
            trigger = has_map & (2 * prop.matched < near.sum(1))
        tp = np.flatnonzero(trigger)
        stats["burst_particle_steps"] += tp.size
        if tp.size:
            j_count = len(log_mass)
            u_j = np.broadcast_to(u + shifts, (tp.size, j_count, 3))
            std_j = np.where(np.isnan(piece_std), std, piece_std)
            std_j = np.broadcast_to(std_j, (tp.size, j_count, 3))
            pose_j = np.repeat(state.pose[tp][:, None, :], j_count, 1)
            xh = motion_mean(pose_j, u_j).reshape(-1, 3)
            rc = motion_cov(pose_j, u_j, std_j, config.jitter).reshape(-1, 3, 3)
            src = np.repeat(tp, j_count)
            prop_j, match_j, _ = propose(noise, config, xh, rc, mean[src], cov[src],
                                         active[src], z, valid, log_p0)
            # Column 0: the core piece; columns 1..J: the off-centre pieces.
            logits = np.empty((tp.size, j_count + 1))
            logits[:, 0] = log_evidence[tp]
            logits[:, 1:] = prop_j.log_z.reshape(tp.size, j_count) + log_mass[None, :]
            top = logits.max(1, keepdims=True)
            total = top[:, 0] + np.log(np.exp(logits - top).sum(1))
            probs = np.exp(logits - total[:, None])
            cdf = np.cumsum(probs, 1)
            choice = (rng.random(tp.size)[:, None] > cdf).sum(1).clip(0, j_count)
            log_evidence[tp] = total
            mu, sigma, match_final = mu.copy(), sigma.copy(), match_final.copy()
            for i, (p, j) in enumerate(zip(tp, choice)):
                if j == 0:
                    continue
                flat = i * j_count + j - 1
                mu[p], sigma[p] = prop_j.mu[flat], prop_j.sigma[flat]
                match_final[p] = match_j[flat]
                stats["burst_taken"] += 1
    x = sample_gaussian(rng, mu, sigma)
    if config.associate_at_sample:
        match_update, _ = associate(noise, config.gate, x, None, mean, cov, active, z, valid)
    else:
        match_update = match_final
    state.log_w = state.log_w + log_evidence
    state.pose = x
    update_landmarks(noise, config, state, x, match_update, z, valid)


def run_filter(controls, z, valid, start, noise, config, rng, truth=None):
    """Run the filter over one log: controls (T, 3), z (T, K, 2), valid (T, K), start (3,).
    Returns dict(final pose (3,), landmarks (weighted mean count), stats, errors (T,) if
    truth (T+1, 3) is given)."""
    controls = np.asarray(controls, np.float64)
    z = np.asarray(z, np.float64)
    valid = np.asarray(valid, bool)
    state = State.initial(start, config)
    stats = {"burst_particle_steps": 0, "burst_taken": 0, "resamples": 0}
    errors = []
    estimate = None
    for t in range(controls.shape[0]):
        filter_step(noise, config, state, controls[t], z[t], valid[t], rng, stats)
        w = normalise(state.log_w)
        estimate = weighted_mean_pose(state.pose, w)
        landmarks = float(w @ state.active.sum(1))
        if truth is not None:
            errors.append(math.hypot(*(estimate[:2] - truth[t + 1, :2])))
        state.log_w = np.log(np.maximum(w, 1e-300))
        if 1.0 / np.sum(w * w) < config.resample_threshold * config.particles:
            state = state.take(systematic_resample(rng, w))
            stats["resamples"] += 1
    out = dict(pose=estimate, landmarks=landmarks, stats=stats)
    if truth is not None:
        out["errors"] = np.asarray(errors)
    return out


# ------------------------------------------------------------------------------------------
# Logs (the project's simulator: data only) and the driver
# ------------------------------------------------------------------------------------------

def load_logs(seed, wobble, odometry, runs, forests, first=None, start=0):
    """The logs of ``experiments/proposal_study.py`` (``make_logs``), logs start..start+first-1
    of a set of ``runs`` over ``forests`` forests. Only the forests needed are simulated (forest
    f is drawn from fold_in(key, f), so they are identical to the full set's).
    Returns (noise params, controls, z, valid, landmark_id, truth, seen), all NumPy."""
    # Simulate with this checkout's code, as the other experiments do (first on sys.path).
    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
    from experiments.mixture_regime import regime_params
    from experiments.proposal_study import make_logs, point_keys

    if runs % forests:
        raise SystemExit("--runs must be a multiple of --forests")
    per_forest = runs // forests
    first = runs - start if first is None else first
    if start < 0 or first < 1 or start + first > runs:
        raise SystemExit(f"--start {start} --first {first} outside the {runs} logs")
    need = -(-(start + first) // per_forest)  # forests 0..need-1
    params = regime_params(odometry, "lidar")
    key_logs, _ = point_keys(seed, wobble, odometry)
    controls, obs, truth, seen = make_logs(key_logs, params, wobble, need * per_forest, need)
    sl = slice(start, start + first)
    return (params, np.asarray(controls[sl], np.float64), np.asarray(obs.z[sl], np.float64),
            np.asarray(obs.valid[sl], bool), np.asarray(obs.landmark_id[sl]),
            np.asarray(truth[sl], np.float64), np.asarray(seen[sl]))


def config_from_args(args) -> Config:
    return Config(particles=args.particles, gate=args.gate, bursts=not args.no_bursts,
                  burst_always=args.burst_always, burst_span=args.burst_span,
                  burst_families=tuple(args.burst_families.split(",")),
                  burst_prior=args.burst_prior, anchor_first=not args.sample_first,
                  associate_at_sample=not args.no_associate_at_sample,
                  pose_uncertainty=not args.no_pose_uncertainty, iterations=args.iterations,
                  weight=args.weight, delete=not args.no_delete, new_landmark=args.new_landmark)


def _one(job):
    index, controls, z, valid, truth, noise, config, seed = job
    tick = time.perf_counter()
    rng = np.random.default_rng([seed, index])
    out = run_filter(controls, z, valid, truth[0], noise, config, rng, truth)
    out["seconds"] = time.perf_counter() - tick
    out["index"] = index
    return out


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=200)
    parser.add_argument("--forests", type=int, default=10)
    parser.add_argument("--first", type=int, default=None, help="run only N logs")
    parser.add_argument("--start", type=int, default=0, help="first log index")
    parser.add_argument("--seed", type=int, default=700, help="logs' seed (held-out: 700)")
    parser.add_argument("--wobble", type=float, default=0.3)
    parser.add_argument("--odometry", type=float, default=6.0)
    parser.add_argument("--filter-seed", type=int, default=0)
    parser.add_argument("--particles", type=int, default=20)
    parser.add_argument("--workers", type=int, default=1)
    parser.add_argument("--gate", type=float, default=13.8)
    parser.add_argument("--iterations", type=int, default=2)
    parser.add_argument("--no-bursts", action="store_true")
    parser.add_argument("--burst-always", action="store_true")
    parser.add_argument("--burst-span", type=float, default=0.5)
    parser.add_argument("--burst-families", default="rot1,rot2,trans",
                        help="comma list of move components with tail pieces (rot1,rot2,trans)")
    parser.add_argument("--burst-prior", choices=("inverted", "mixture"), default="inverted")
    parser.add_argument("--sample-first", action="store_true",
                        help="sample the first pose instead of taking the motion mean")
    parser.add_argument("--no-associate-at-sample", action="store_true")
    parser.add_argument("--no-pose-uncertainty", action="store_true")
    parser.add_argument("--no-delete", action="store_true")
    parser.add_argument("--weight", choices=("stacked", "product"), default="stacked")
    parser.add_argument("--new-landmark", choices=("field", "gate"), default="field",
                        help="new-landmark density: uniform over the field, or the gate edge")
    parser.add_argument("--out", default=None, help=".npz for the per-run results")
    args = parser.parse_args(argv)

    tick = time.perf_counter()
    params, controls, z, valid, _, truth, seen = load_logs(
        args.seed, args.wobble, args.odometry, args.runs, args.forests, args.first, args.start)
    noise = Noise.from_params(params)
    config = config_from_args(args)
    print(f"{len(controls)} logs (from {args.start}) in {time.perf_counter() - tick:.1f} s; "
          f"{config}", flush=True)
    jobs = [(args.start + i, controls[i], z[i], valid[i], truth[i], noise, config,
             args.filter_seed) for i in range(len(controls))]
    results = []
    tick = time.perf_counter()
    if args.workers > 1:
        import multiprocessing  # spawn: the parent has JAX (log generation) loaded
        with multiprocessing.get_context("spawn").Pool(args.workers) as pool:
            iterator = pool.imap(_one, jobs)
            for out in iterator:
                results.append(out)
                _print(out, seen[out["index"] - args.start], tick)
    else:
        for job in jobs:
            out = _one(job)
            results.append(out)
            _print(out, seen[out["index"] - args.start], tick)
    error = np.array([r["errors"][-1] for r in results])
    landmarks = np.array([r["landmarks"] for r in results])
    seconds = np.array([r["seconds"] for r in results])
    from experiments.proposal_study import wilson  # the study's interval (driver only)

    n, k = error.size, int(np.sum(error > 1.0))
    low, high = wilson(k, n)
    print(f"runs {n}; diverged (> 1 m) {k} = {100 * k / n:.1f} % [{100 * low:.1f}, "
          f"{100 * high:.1f}]; median final error {np.median(error):.3f} m; median landmarks / "
          f"trees seen {np.median(landmarks / seen):.2f}; {seconds.mean():.2f} s per log",
          flush=True)
    if args.out:
        path = pathlib.Path(args.out)
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savez(path, index=np.array([r["index"] for r in results]), error=error,
                 landmarks=landmarks, seen=seen, seconds=seconds,
                 errors=np.stack([r["errors"] for r in results]),
                 burst_particle_steps=np.array([r["stats"]["burst_particle_steps"]
                                                for r in results]),
                 burst_taken=np.array([r["stats"]["burst_taken"] for r in results]),
                 resamples=np.array([r["stats"]["resamples"] for r in results]),
                 config=repr(config), argv=" ".join(sys.argv))
        print(f"wrote {path}", flush=True)


def _print(out, seen, tick):
    s = out["stats"]
    print(f"log {out['index']:4d}: final error {out['errors'][-1]:8.3f} m, landmarks "
          f"{out['landmarks']:5.1f} / {seen} seen, max error {out['errors'].max():7.3f} m, "
          f"bursts {s['burst_particle_steps']} (taken {s['burst_taken']}), resamples "
          f"{s['resamples']}, {out['seconds']:.1f} s (elapsed {time.perf_counter() - tick:.0f} s)",
          flush=True)


if __name__ == "__main__":
    main()
