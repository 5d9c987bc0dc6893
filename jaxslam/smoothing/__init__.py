"""Smoothing of a FastSLAM run: one particle's data association, re-solved over the whole path.

A FastSLAM particle is a whole path hypothesis with the map built along it. Once the run is
over, following the final best particle back through its ancestors (``Trace.lineage`` from
``run_filter(..., record_lineage=True)``) gives, for every observation z_{t,k}, the landmark
that particle associated it with (or created from it). With those associations fixed, the
maximum a-posteriori path and map are the nonlinear least squares of GraphSLAM (Thrun et al.,
Probabilistic Robotics, ch. 11):

    min_{x_{0:T-1}, m}  sum_t   || C_t^-1 (x_{t-1} (-) x_t - delta_t) ||^2
                      + sum_t,k rho(|| diag(sigma_r, sigma_b)^-1 (h(x_t, m_j(t,k)) - z_t,k) ||)

* x_{-1} is the fixed start pose; x_{t-1} (-) x_t is ``geometry.relative`` (the move in the
  frame of x_{t-1}) and delta_t the measured move of control t.
* C_t C_t^T = J_t diag(s_t^2) J_t^T + eps^2 diag(1, 1, 0): the motion noise of Geiser et al. 2023
  Eq. (1) (std s_t = ``motion.odometry_std``) carried from (rot1, trans, rot2) to the relative
  pose by J_t = d delta / d(rot1, trans, rot2). The floor eps (``MOVE_STD_FLOOR``) keeps C_t
  invertible for a pure turn.
* h is the range-bearing model and (sigma_r, sigma_b) = ``ekf.measurement_std`` at the
  measured range. rho is Huber's loss with threshold ``huber`` (whitened units), so a wrong
  association costs linearly rather than quadratically.

This undoes what a particle filter cannot: a heading error made where no landmark is seen is
spread back over that stretch when the loop closes, as EKF-SLAM's correlations do. The
associations are the filter's. With ``visit_gap`` the loop closures among them are revised:
each landmark is split into visits (its sightings with no long gap), each visit has its own
position, and visits of one landmark are tied by link factors

    sum_(a,b) rho_GM(|| (m_a - m_b) / sigma_link ||),   rho_GM(n) = c^2 n^2 / (c^2 + n^2),

a redescending (Geman-McClure) loss bounded by c^2, so a wrong loop closure, whose
observations agree among themselves and so escape Huber's loss, is switched off as a whole
(the switchable-constraint idea of Sunderhauf and Protzel, in closed form as in Agarwal et
al.'s dynamic covariance scaling).

The history comes from ``lineage.trace_lineage`` (JAX, jit/vmap over runs). The least squares is
solved on the host in float64 with Levenberg-Marquardt steps on the sparse normal equations
(``scipy.sparse``, a minimum-degree LU); its Jacobian is block sparse (3x3 move blocks on a
band, 2x3 and 2x2 observation blocks), and the associations fix its pattern, so the pattern
and the elimination order are found once per problem and reused by every step.

Modules: ``residuals`` (the factors: the library's JAX models in float64, Jacobians by
``jax.jacfwd``), ``problem`` (whitening, robust weights, the sparse Jacobian), ``solver``
(Levenberg-Marquardt, variance components), ``visits`` (visits and their links) and ``smooth``
(``smooth_path``, ``smooth_lineage``).
"""
from jaxslam.smoothing.problem import NoiseScales
from jaxslam.smoothing.residuals import (MOVE_STD_FLOOR, initial_landmarks, move_residual,
                                         move_residuals, move_whitening, observation_residual,
                                         observation_residuals, observation_std)
from jaxslam.smoothing.smooth import VARIANCE_ROUNDS, Smoothed, smooth_lineage, smooth_path
from jaxslam.smoothing.visits import Visits, check_visit_options, split_visits

__all__ = [
    "MOVE_STD_FLOOR",
    "NoiseScales",
    "Smoothed",
    "VARIANCE_ROUNDS",
    "Visits",
    "check_visit_options",
    "initial_landmarks",
    "move_residual",
    "move_residuals",
    "move_whitening",
    "observation_residual",
    "observation_residuals",
    "observation_std",
    "smooth_lineage",
    "smooth_path",
    "split_visits",
]
