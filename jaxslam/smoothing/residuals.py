"""The smoother's factors: the odometry move and the range-bearing observation, in float64.

Every model here is the library's JAX one, evaluated per factor, vmapped over factors and
jitted once at import: the move residual is ``geometry.relative`` less the measured move, the
observation residual ``geometry.range_bearing`` less the measurement, the move covariance
propagates ``motion.odometry_std`` (Geiser et al. 2023, Eq. (1)) through
``motion.apply_odometry``, the observation noise is ``ekf.measurement_std`` and the landmarks'
first guess ``geometry.inverse_range_bearing``. Jacobians come from ``jax.jacfwd``.

The least squares lives on the host in float64 (its normal equations are badly conditioned:
a pure turn's move is pinned to a millimetre while a landmark sits tens of metres away), so
each host entry point runs in float64 for its call alone (``host.in_float64``), takes NumPy
arrays and returns writable NumPy arrays. The filter's own dtype is left untouched. A
compiled function is cached per input shape; batches are padded to a power of two, so one
problem compiles once, every Levenberg-Marquardt step reuses it and problems of similar size
share it.

Shapes: T moves, N observations, L landmarks.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jaxslam.ekf import measurement_std
from jaxslam.geometry import inverse_range_bearing, range_bearing, relative, wrap_angle
from jaxslam.host import in_float64
from jaxslam.motion import apply_odometry, odometry_std
from jaxslam.types import Params

MOVE_STD_FLOOR = 1e-3  # [m] added in x and y to every move covariance (a pure turn is singular)
MIN_RANGE = 1e-6  # [m] a landmark closer to the sensor has no bearing (see observation_residual)


def move_residual(start, end, delta):
    """Residual e = start (-) end - delta (3,) of one move, heading wrapped.

    Args:
      start, end: (3,) poses x_{t-1}, x_t; delta: (3,) measured move in start's frame.
    """
    error = relative(start, end) - delta
    return error.at[2].set(wrap_angle(error[2]))


def observation_residual(pose, point, z):
    """Residual e = h(pose, point) - z (2,) of one range-bearing observation, bearing wrapped.

    A point within ``MIN_RANGE`` of the sensor has no direction: h is then taken as
    (0, -theta), so the residual stays finite and its Jacobian is zero in the point and the
    position (the other observations place such a landmark). Elsewhere h is
    ``geometry.range_bearing``; the double ``where`` keeps its gradient finite at the sensor.

    Args:
      pose: (3,); point: (2,); z: (2,) measured range and bearing.
    """
    offset = point - pose[:2]
    at_sensor = jnp.dot(offset, offset) < MIN_RANGE**2
    ahead = pose[:2] + jnp.array([1.0, 0.0], pose.dtype)
    predicted = jnp.where(at_sensor, jnp.stack([jnp.zeros_like(pose[2]), -pose[2]]),
                          range_bearing(pose, jnp.where(at_sensor, ahead, point)))
    error = predicted - z
    return error.at[1].set(wrap_angle(error[1]))


def _with_jacobians(residual):
    """residual(a, b, measured) -> (residual, d residual / d a, d residual / d b)."""
    def evaluate(a, b, measured):
        jac_a, jac_b = jax.jacfwd(residual, argnums=(0, 1))(a, b, measured)
        return residual(a, b, measured), jac_a, jac_b

    return evaluate


def _move_covariance(odometry, params: Params, std_floor):
    """delta (3,) and its covariance C (3, 3) for one measured move (rot1, trans, rot2) (3,).

    C = J diag(s^2) J^T + std_floor^2 diag(1, 1, 0), J = d delta / d (rot1, trans, rot2).
    """
    def move(odo):
        return apply_odometry(jnp.zeros_like(odo), odo)

    jacobian = jax.jacfwd(move)(odometry)
    variance = odometry_std(odometry, params) ** 2
    floor = jnp.array([1.0, 1.0, 0.0], odometry.dtype) * std_floor**2
    return move(odometry), (jacobian * variance[None, :]) @ jacobian.T + jnp.diag(floor)


def _stacked_measurement_std(distance, params: Params):
    return jnp.stack(measurement_std(distance, params), axis=-1)


# Compiled once here: a jitted closure built per call would recompile at every call.
_move_factors = jax.jit(jax.vmap(_with_jacobians(move_residual)))
_observation_factors = jax.jit(jax.vmap(_with_jacobians(observation_residual)))
_move_covariances = jax.jit(jax.vmap(_move_covariance, in_axes=(0, None, None)))
_measurement_stds = jax.jit(_stacked_measurement_std)
_inverse_range_bearings = jax.jit(jax.vmap(inverse_range_bearing))
_wrap_angles = jax.jit(wrap_angle)


def _bucket(size: int) -> int:
    """The batch size compiled for ``size`` rows: the next power of two, at least 16."""
    return max(16, 1 << (int(size) - 1).bit_length())


def _batched(function, *arrays, shared=()):
    """``function(*arrays, *shared)`` in float64 (``host.in_float64``), as writable NumPy arrays.

    ``arrays`` (each (n, ...)) are taken in float64 (converted before the call, so no digit is
    lost) and padded with rows of zeros to ``_bucket(n)`` rows, so problems of similar size
    share one compilation; the outputs' padding rows are cut off. A zero row is a valid input
    of every factor here. ``shared``: unbatched arguments (NumPy float64 pytrees).
    """
    arrays = tuple(np.asarray(a, np.float64) for a in arrays)
    size = arrays[0].shape[0]
    padded = tuple(np.concatenate([a, np.zeros((_bucket(size) - size,) + a.shape[1:])])
                   for a in arrays)
    out = in_float64(function, *padded, *shared)  # x64 for this call only, on the CPU
    return jax.tree.map(lambda value: value[:size].copy(), out)


def _params_float64(params: Params) -> Params:
    return jax.tree.map(lambda value: np.asarray(value, np.float64), params)


def wrap(angle):
    """``geometry.wrap_angle`` of a NumPy array (n,), in float64."""
    return _batched(_wrap_angles, angle)


def move_residuals(start, end, delta):
    """Residual e = start (-) end - delta (3,) per move and its Jacobians.

    Args:
      start, end: (N, 3) poses; delta: (N, 3) measured relative poses.
    Returns:
      e (N, 3), d e / d start (N, 3, 3), d e / d end (N, 3, 3).
    """
    return _batched(_move_factors, start, end, delta)


def observation_residuals(pose, point, z):
    """Residual e = h(pose, point) - z (range, bearing) per observation and its Jacobians.

    Args:
      pose: (N, 3); point: (N, 2); z: (N, 2).
    Returns:
      e (N, 2), d e / d pose (N, 2, 3), d e / d point (N, 2, 2).
    """
    return _batched(_observation_factors, pose, point, z)


def observation_std(z_range, params: Params):
    """(N, 2) (sigma_range, sigma_bearing) of ``ekf.measurement_std`` at measured ranges (N,)."""
    return _batched(_measurement_stds, z_range, shared=(_params_float64(params),))


def move_whitening(odometry, params: Params, std_floor: float = MOVE_STD_FLOOR):
    """Measured moves delta (N, 3) and whitening W (N, 3, 3), W^T W = C^-1.

    C = J diag(s^2) J^T + std_floor^2 diag(1, 1, 0) with s = ``motion.odometry_std``
    (Geiser et al. 2023, Eq. (1)) and J = d delta / d (rot1, trans, rot2), the Jacobian of
    ``motion.apply_odometry`` from the origin. W is the inverse Cholesky factor of C taken in
    the order (theta, x, y), so whitened row 0 is the heading error alone,
    e_theta / sqrt(C_theta_theta), and rows 1-2 the translation error given it (the groups of
    ``NoiseScales``).

    Args:
      odometry: (N, 3) measured (rot1, trans, rot2).
    """
    delta, cov = _batched(_move_covariances, odometry,
                          shared=(_params_float64(params), np.float64(std_floor)))
    if np.any(cov[:, 2, 2] <= 0.0):
        raise ValueError(f"move {int(np.argmax(cov[:, 2, 2] <= 0.0))} has zero heading noise: "
                         "give rot1_noise or rot2_noise a positive constant term (c1 / c3)")
    order = np.array([2, 0, 1])  # (theta, x, y)
    white_ordered = np.linalg.inv(np.linalg.cholesky(cov[:, order][:, :, order]))
    return delta, white_ordered[:, :, np.argsort(order)]


def initial_landmarks(path, z, landmark_of_obs, num_landmarks: int):
    """(L, 2) mean over each landmark's observations of ``geometry.inverse_range_bearing``.

    Args:
      path: (T, 3) poses; z: (T, K, 2) observations; landmark_of_obs: (T, K) landmark index,
        -1 for none; num_landmarks: L (an index with no observation stays at the origin).
    """
    t, k = np.nonzero(landmark_of_obs >= 0)
    point = _batched(_inverse_range_bearings, np.asarray(path)[t], np.asarray(z)[t, k])
    ids = landmark_of_obs[t, k]
    total = np.zeros((num_landmarks, 2))
    np.add.at(total, ids, point)
    count = np.bincount(ids, minlength=num_landmarks)
    return total / np.maximum(count, 1)[:, None]
