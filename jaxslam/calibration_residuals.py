"""What the self-calibration's M-step reads: residuals of a smoothed solution, in float64.

Given the smoothed path x*_{0:T-1}, map m* and association j(t, k) of one EM iteration
(``smoothing.smooth_path``), the samples are

    moves:        the smoothed move  x*_{t-1} (-) x*_t  as (rot1, trans, rot2)
                  (``motion.odometry_from_poses``) against the measured one u_t, its error
                  (of the decomposition nearest u_t) and Eq. (1) regressors
                  (``calibrate.motion_samples``) and Eq. (1) std
                  (``motion.odometry_std``) of Geiser et al., "Practical Implementation of
                  FastSLAM for Forestry Robot" (ICAROB 2023);
    observations: h(x*_t, m*_j) - z_tk and h(x_t, m*_j) - z_tk at the filter's own pose x_t
                  (``geometry.range_bearing``, bearing wrapped), and the Table 2 std at the
                  measured range (``ekf.measurement_std``).

Every model is the library's JAX function, evaluated on the host in float64 (``host.in_float64``)
on arrays whose shapes do not change from one EM iteration to the next: the observation
residuals are computed on the whole (T, K) grid and the associated ones picked out after, so
each function compiles once per log rather than once per association.

Shapes: T steps, K observations per step, S associated observations, L smoothed landmarks.
"""
from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from jaxslam import calibrate, smoothing
from jaxslam.ekf import measurement_std
from jaxslam.geometry import range_bearing, wrap_angle
from jaxslam.motion import odometry_from_poses, odometry_std
from jaxslam.host import float64_on_host
from jaxslam.types import Params


NOISE_GROUPS = ("heading", "translation", "range", "bearing")  # ``typical_stds``' order
NOISE_GROUP_UNITS = ("rad", "m", "m", "rad")


class Residuals(NamedTuple):
    """Samples of one smoothed solution (host NumPy, float64).

    Attributes:
      true_moves: (T, 3) smoothed moves (rot1, trans, rot2); non-finite where the smoother
        gave no pose.
      measured_moves: (T, 3) the odometry u_t.
      move_error: (T, 3) true - measured, the true move in its decomposition nearest the
        measured one (``calibrate.motion_samples``), rotations wrapped.
      move_features: (3, T, 3) Eq. (1) regressors of rot1, trans, rot2 at the measured move.
      move_std: (T, 3) Eq. (1) std of the measured moves with the iteration's ``Params``.
      measured_z: (S, 2) the associated observations z_tk.
      observation_error: (S, 2) h(x*_t, m*_j) - z_tk, bearing wrapped.
      filter_error: (S, 2) h(x_t, m*_j) - z_tk at the filter's own pose.
      observation_std: (S, 2) Table 2 std (range, bearing) at the measured range.
      obs_step: (S,) step of each sample; obs_landmark: (S,) its smoothed landmark.
      sightings: (L,) observations of each landmark.
    """

    true_moves: np.ndarray
    measured_moves: np.ndarray
    move_error: np.ndarray
    move_features: np.ndarray
    move_std: np.ndarray
    measured_z: np.ndarray
    observation_error: np.ndarray
    filter_error: np.ndarray
    observation_std: np.ndarray
    obs_step: np.ndarray
    obs_landmark: np.ndarray
    sightings: np.ndarray


def _observation_residual(pose, point, z):
    """h(pose, point) - z, bearing wrapped; pose (..., 3), point and z (..., 2)."""
    error = range_bearing(pose, point) - z
    return error.at[..., 1].set(wrap_angle(error[..., 1]))


@float64_on_host
def _grid_residuals(start, path, filter_path, points, z, odometry, params: Params):
    """Move samples (T, ...) and observation samples on the whole (T, K) grid."""
    poses = jnp.concatenate([start[None], path])
    true_moves = odometry_from_poses(poses[:-1], poses[1:], params.min_translation)
    move_error, move_features = calibrate.motion_samples(true_moves, odometry)
    observation_error = _observation_residual(path[:, None], points, z)
    filter_error = _observation_residual(filter_path[:, None], points, z)
    observation_std = jnp.stack(measurement_std(z[..., 0], params), -1)
    return (true_moves, move_error, move_features, odometry_std(odometry, params),
            observation_error, filter_error, observation_std)


def smoothed_residuals(start_pose, smoothed: smoothing.Smoothed, filter_path, odometry, z,
                       params: Params) -> Residuals:
    """``Residuals`` of ``smoothed`` (module docstring).

    Args:
      start_pose: (3,); filter_path: (T, 3) the filter's poses of the associating particle;
      odometry: (T, 3) measured moves; z: (T, K, 2) observations (0 where not valid);
      params: the iteration's settings (``min_translation``, the noise of the stds).
    """
    ids = np.asarray(smoothed.landmark_of_obs)
    points = np.asarray(smoothed.landmark, np.float64)[np.maximum(ids, 0)]  # (T, K, 2)
    (true_moves, move_error, move_features, move_std, observation_error, filter_error,
     observation_std) = _grid_residuals(start_pose, smoothed.path, filter_path, points, z,
                                        odometry, params)
    step, row = np.nonzero(ids >= 0)
    landmark = ids[step, row]
    sightings = np.bincount(landmark, minlength=len(smoothed.landmark))
    return Residuals(true_moves, np.asarray(odometry, np.float64), move_error, move_features,
                     move_std, np.asarray(z, np.float64)[step, row],
                     observation_error[step, row], filter_error[step, row],
                     observation_std[step, row], step, landmark, sightings)


@float64_on_host
def _typical_stds(params: Params, odometry, z_range):
    move_std = odometry_std(odometry, params)
    heading = jnp.sqrt(jnp.mean(move_std[:, 0] ** 2 + move_std[:, 2] ** 2))
    translation = jnp.sqrt(jnp.mean(move_std[:, 1] ** 2))
    obs_std = jnp.stack(measurement_std(z_range, params), -1)
    return jnp.concatenate([jnp.stack([heading, translation]),
                            jnp.sqrt(jnp.mean(obs_std**2, axis=0))])


def typical_stds(params: Params, odometry, z_range) -> np.ndarray:
    """(4,) root-mean-square std over the log of heading [rad] (rot1 and rot2 together),
    translation [m], range [m] and bearing [rad]; odometry (T, 3), z_range (N,)."""
    return _typical_stds(params, odometry, z_range)
