"""Scenarios: everything ``run_filter`` needs for R Monte Carlo runs, plus the truth.

Run i draws its noise from ``jax.random.fold_in(key, i)``, so a run does not depend on how
many runs are built together. All runs share the forest and the true path; they differ in
odometry noise and observation noise. Time convention: ``controls[:, t]`` moves the robot
from ``poses[:, t]`` to ``poses[:, t + 1]`` and ``observations[:, t]`` is taken at
``poses[:, t + 1]`` (predict, then update); ``with_start_scan`` adds a scan at the start pose
(behind a zero move), so that the map is anchored at the known start.

Observation sources:
  analytic  exact range-bearing to every trunk centre with min_range < range <= max_range
            (no occlusion), plus Geiser et al. 2023, Table 2 noise (std = c_dist * range + c_const for
            range and bearing, floored by ``params.range_std_floor`` etc. only when
            ``floor_noise=True``); the K nearest are kept, ``landmark_id`` = true tree index.
  lidar     an ``mjx.ray`` scan with per-beam range noise, then ``detect_trunks``;
            ``landmark_id`` is -1 (the detector does not know tree identities).
"""
from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxslam.detect import detect_trunks
from jaxslam.ekf import measurement_std, sensor_std
from jaxslam.geometry import range_bearing, wrap_angle
from jaxslam.types import Observations, Params, default_params
from sims.forest import Forest, random_forest, world_from_forest
from sims.mujoco_loader import lazy_functions
from sims.paths import loop_path, noisy_odometry, true_moves

# sims.lidar needs MuJoCo: it is imported at the first lidar scan, so that analytic scenarios
# run without MuJoCo installed.
add_range_noise, beam_angles, scan_2d_full = lazy_functions(
    "sims.lidar", "add_range_noise", "beam_angles", "scan_2d_full")

SOURCES = ("analytic", "lidar")


class Scenario(NamedTuple):
    """R runs of T steps.

    Attributes:
      controls: (R, T, 3) noisy odometry readings (rot1, trans, rot2).
      observations: ``Observations`` with leaves (R, T, K, ...).
      poses: (R, T+1, 3) true poses, the initial pose first.
      moves: (R, T, 3) true moves (rot1, trans, rot2).
      centres: (N, 2) true trunk centres; radii: (N,) true trunk radii.
    """

    controls: jnp.ndarray
    observations: Observations
    poses: jnp.ndarray
    moves: jnp.ndarray
    centres: jnp.ndarray
    radii: jnp.ndarray


def analytic_observations(key, pose, centres, radii, params: Params, max_obs: int,
                          floor_noise: bool = False) -> Observations:
    """Noisy range-bearing (K, 2) of the K nearest trunks in range of ``pose`` (3,).

    z = h(pose, c_n) + (sigma_r eps_1, sigma_b eps_2), sigma = coeff[0] * range + coeff[1]
    (Geiser et al. 2023, Table 2: ``ekf.sensor_std``, floored with ``floor_noise``); trunks
    beyond ``params.max_range`` or nearer than ``min_range`` are not seen. With fewer than K in range the remaining rows are invalid.
    """
    truth = range_bearing(pose[None, :], centres)  # (N, 2)
    visible = (truth[:, 0] <= params.max_range) & (truth[:, 0] > params.min_range)
    k = min(max_obs, centres.shape[0])
    neg, pick = jax.lax.top_k(-jnp.where(visible, truth[:, 0], jnp.inf), k)
    valid = jnp.isfinite(neg)
    dist = truth[pick, 0]
    std_r, std_b = (measurement_std if floor_noise else sensor_std)(dist, params)
    eps = jax.random.normal(key, (k, 2), truth.dtype)
    z = jnp.stack([dist + std_r * eps[:, 0], wrap_angle(truth[pick, 1] + std_b * eps[:, 1])], -1)
    pad = max_obs - k
    return Observations(
        z=jnp.pad(jnp.where(valid[:, None], z, 0.0), ((0, pad), (0, 0))),
        valid=jnp.pad(valid, (0, pad)),
        radius=jnp.pad(jnp.where(valid, radii[pick], 0.0), (0, pad)),
        landmark_id=jnp.pad(jnp.where(valid, pick, -1).astype(jnp.int32), (0, pad),
                            constant_values=-1))


def lidar_observations(key, world, pose, max_obs: int, max_range: float, num_beams: int,
                       beam_noise, method: str, detect_kwargs: dict) -> Observations:
    """Scan at ``pose`` (3,) (culled, per-beam noise ``beam_noise``), then detect trunks."""
    key_scan, key_detect = jax.random.split(key)
    ranges = scan_2d_full(world, pose, num_beams, max_range).ranges
    ranges = add_range_noise(key_scan, ranges, max_range, beam_noise)
    angles = jnp.asarray(beam_angles(num_beams), ranges.dtype)
    return detect_trunks(ranges, angles, method, max_obs=max_obs, max_range=max_range,
                         key=key_detect if method == "ransac" else None, **detect_kwargs)


@functools.partial(jax.jit, static_argnames=(
    "num_runs", "source", "max_obs", "max_range", "num_beams", "beam_noise", "method",
    "detect_items", "floor_noise"))
def _build_runs(key, path, moves, centres, radii, params, world, *, num_runs, source, max_obs,
                max_range, num_beams, beam_noise, method, detect_items, floor_noise):
    """Controls (R, T, 3) and observations (R, T, K, ...) of runs 0..R-1 (compiled once per
    static setting; forests, paths and params are traced)."""
    detect_kwargs = dict(detect_items)

    def observe(obs_key, pose):
        if source == "analytic":
            return analytic_observations(obs_key, pose, centres, radii, params, max_obs,
                                         floor_noise)
        return lidar_observations(obs_key, world, pose, max_obs, max_range, num_beams,
                                  beam_noise, method, detect_kwargs)

    return jax.vmap(lambda run: simulate_run(jax.random.fold_in(key, run), moves, path[1:],
                                             params, observe))(jnp.arange(num_runs))


def simulate_run(key, moves, poses, params: Params, observe, sequential: bool = False):
    """One run along a known true path: the simulator every study and test scenario uses.

    controls = Eq. (1) noisy odometry of the true ``moves`` (T, 3); observations[t] =
    ``observe(key_t, poses[t])`` at the true poses (T, 3) after each move (or any pytree whose
    leaves have T rows, e.g. (poses, step indices)). ``key`` splits into
    the odometry key and the observation key, which splits into one key a step.
    ``sequential``: steps through ``lax.map`` instead of ``vmap`` (lidar detection holds large
    per-step work arrays). Returns (controls (T, 3), observations with leaves (T, K, ...)).
    """
    key_odometry, key_obs = jax.random.split(key)
    controls = noisy_odometry(key_odometry, moves, params)
    inputs = (jax.random.split(key_obs, moves.shape[0]), poses)
    if sequential:
        return controls, jax.lax.map(lambda args: observe(*args), inputs)
    return controls, jax.vmap(observe)(*inputs)


def with_start_scan(controls, observations: Observations, start_observations: Observations):
    """The log of a robot that scans once at rest before its first move.

    Row 0 becomes a zero move (rot1, trans, rot2) = 0 (the encoders read nothing) followed by
    ``start_observations``, a scan taken at the start pose; rows 1..T are the given ones. So
    ``controls[..., t]`` now ends at ``poses[..., t]`` and the filter's map is anchored at the
    known start pose. Without that scan the first landmarks are placed from the pose after
    the first move, and that move's error (a slip burst of the MJX robot can turn it by
    0.1 rad) tilts the whole map in a way no later scan can reveal.

    Args:
      controls: (..., T, 3); observations: leaves (..., T, K, ...); start_observations:
        leaves (..., K, ...), the same leading axes without T.
    Returns (controls (..., T+1, 3), observations with leaves (..., T+1, K, ...)).
    """
    time_axis = jnp.ndim(controls) - 2
    if time_axis < 0 or jnp.shape(controls)[-1] != 3:
        raise ValueError(f"with_start_scan: controls must have shape (..., T, 3); got "
                         f"{jnp.shape(controls)}")
    start_z = jnp.shape(start_observations.z)
    rest_z = jnp.shape(observations.z)
    if rest_z[:time_axis + 1] != jnp.shape(controls)[:-1]:
        raise ValueError(f"with_start_scan: observations.z has shape {rest_z}; its leading axes "
                         f"must be the controls' {jnp.shape(controls)[:-1]} (..., T)")
    if start_z != rest_z[:time_axis] + rest_z[time_axis + 1:]:
        raise ValueError(f"with_start_scan: start_observations.z has shape {start_z}; "
                         f"expected {rest_z[:time_axis] + rest_z[time_axis + 1:]} (the "
                         f"observations' {rest_z} without the time axis {time_axis})")
    shape = list(jnp.shape(controls))
    shape[time_axis] = 1
    zero_move = jnp.zeros(shape, jnp.result_type(controls))
    return (jnp.concatenate([zero_move, controls], axis=time_axis),
            jax.tree.map(lambda start, rest: jnp.concatenate(
                [jnp.expand_dims(start, time_axis), rest], axis=time_axis),
                start_observations, observations))


def build_scenario(key, forest: Forest, path, num_runs: int, *, source: str = "analytic",
                   params: Params | None = None, max_obs: int = 16, world=None,
                   num_beams: int = 1440, beam_noise=(0.0, 0.01), method: str = "kasa",
                   detect_kwargs: dict | None = None, floor_noise: bool = False) -> Scenario:
    """Build R = ``num_runs`` runs along ``path`` (T+1, 3) through ``forest``.

    Args:
      key: root key; run i uses ``fold_in(key, i)``.
      source: ``analytic`` or ``lidar`` (module docstring).
      params: noise and sensor settings (``default_params()``: Tables 1 and 2, 20 m range).
      world: a prebuilt ``make_world`` of the forest (lidar only; built when None).
      num_beams, beam_noise, method, detect_kwargs: lidar settings; beam_noise is
        (per metre, constant) of the per-beam range std.
    """
    if source not in SOURCES:
        raise ValueError(f"build_scenario source={source!r}; expected one of {list(SOURCES)}")
    if num_runs < 1:
        raise ValueError(f"build_scenario num_runs={num_runs}; expected >= 1")
    params = default_params() if params is None else params
    path = jnp.asarray(path, jnp.float32)
    moves = true_moves(path, params.min_translation)
    centres = jnp.asarray(forest.centres, jnp.float32)
    radii = jnp.asarray(forest.radii, jnp.float32)
    max_range = float(params.max_range)
    if source == "lidar" and world is None:
        world = world_from_forest(forest)
    detect_kwargs = {} if detect_kwargs is None else dict(detect_kwargs)
    detect_kwargs.setdefault("min_range", float(params.min_range))

    controls, observations = _build_runs(
        key, path, moves, centres, radii, params, world, num_runs=num_runs, source=source,
        max_obs=max_obs, max_range=max_range, num_beams=num_beams,
        beam_noise=tuple(float(v) for v in beam_noise), method=method,
        detect_items=tuple(sorted(detect_kwargs.items())), floor_noise=floor_noise)
    tile = (num_runs, 1, 1)
    return Scenario(controls, observations, jnp.tile(path[None], tile),
                    jnp.tile(moves[None], tile), centres, radii)


def default_scenario(key, num_runs: int, *, source: str = "analytic", num_trees: int = 80,
                     size: float = 60.0, num_steps: int = 200, step_length: float = 0.5,
                     max_obs: int = 16, params: Params | None = None, **kwargs) -> Scenario:
    """A small study: a ``size`` x ``size`` m random forest of ``num_trees`` trees (2 m
    spacing, trunks kept 1.5 m off the path), a circular loop of T = ``num_steps`` steps of
    ``step_length`` m about the forest centre, 20 m range, K = ``max_obs``.

    ``key`` splits into a forest key and the runs key (run i: ``fold_in(runs key, i)``).
    """
    key_forest, key_runs = jax.random.split(key)
    loop_radius = num_steps * step_length / (2.0 * np.pi)
    centre = (0.5 * size, 0.5 * size)
    path = loop_path(num_steps, centre, (loop_radius, loop_radius), step_length)
    dense = loop_path(720, centre, (loop_radius, loop_radius),
                      2.0 * np.pi * loop_radius / 720)
    forest = random_forest(key_forest, num_trees, (size, size), keep_clear=dense[:, :2])
    return build_scenario(key_runs, forest, path, num_runs, source=source, params=params,
                          max_obs=max_obs, **kwargs)
