"""Batches of simulated runs for Monte Carlo studies: ``scenario_batch`` is the ``simulate``
function of the "sims" study simulator (registered by ``sims/__init__.py``; ``jaxslam.studies``
loads it by name, so the library itself never imports the simulator or MuJoCo).

Run i draws from its key ``fold_in(PRNGKey(seed), i)``: its odometry and observation noise
from ``fold_in(key, 0)`` (the filter uses ``fold_in(key, 1)``) and, with
``scenario.world = "per_run"``, its own forest and path from ``fold_in(key, 2)``. With
``world = "shared"`` every run follows one true path through one forest (drawn from the seed
alone), so runs differ only in noise: paired comparisons, but one world's luck.
"""
from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from jaxslam.simulators import RunBatch
from jaxslam.study_config import StudyConfig
from jaxslam.types import Params, default_params
from sims.config import ScenarioConfig
from sims.mujoco_loader import require_mujoco

# 1440 beams (0.25 degree): at 720, trunks beyond ~10 m get fewer than 4 points.
LIDAR_BEAMS = 1440
LIDAR_BEAM_NOISE = (0.0, 0.01)  # per-beam range std (per metre, constant) [m]


def simulation_params(scenario: ScenarioConfig) -> Params:
    """Noise of the simulated robot: Table 1 scaled by ``odometry_noise_scale``, Table 2."""
    base = default_params(max_range=scenario.max_range)
    scale = scenario.odometry_noise_scale
    return base._replace(rot1_noise=base.rot1_noise * scale,
                         trans_noise=base.trans_noise * scale,
                         rot2_noise=base.rot2_noise * scale)


@functools.lru_cache(maxsize=8)
def study_world(scenario: ScenarioConfig, seed: int):
    """The forest and true path of a shared-world study (built once, eagerly): (forest, path)."""
    return _draw_world(scenario, jax.random.fold_in(jax.random.PRNGKey(seed), 2**30))


def run_world(scenario: ScenarioConfig, seed: int, run_id: int):
    """The forest and true path of run ``run_id`` of a per-run-world study: (forest, path),
    drawn from ``fold_in(fold_in(PRNGKey(seed), run_id), 2)``."""
    run_key = jax.random.fold_in(jax.random.PRNGKey(seed), run_id)
    return _draw_world(scenario, jax.random.fold_in(run_key, 2))


def _draw_world(scenario: ScenarioConfig, key):
    """A forest (random or plantation) and a true path (loop, lawnmower or random) (T+1, 3)."""
    from sims import forest as forest_lib
    from sims import paths

    key_forest, key_path = jax.random.split(key)
    size = scenario.size
    centre = (0.5 * size, 0.5 * size)
    path = None
    if scenario.path == "loop":
        radius = scenario.num_steps * scenario.step_length / (2.0 * np.pi)
        path = paths.loop_path(scenario.num_steps, centre, (radius, radius),
                               scenario.step_length)
    elif scenario.path == "lawnmower":  # lanes midway between plantation rows
        path = paths.lawnmower_path(np.arange(3.5, size - 3.0, 7.0), 0.0, size,
                                    scenario.num_steps, scenario.step_length)
    if scenario.forest == "plantation":
        forest = forest_lib.plantation_forest(key_forest, num_rows=max(2, int(size // 7.0) + 1),
                                              trees_per_row=max(2, int(size // 3.0) + 1))
    else:
        keep_clear = None if path is None else np.asarray(path)[:, :2]
        forest = forest_lib.random_forest(key_forest, scenario.num_trees, (size, size),
                                          keep_clear=keep_clear)
    if path is None:
        path = paths.random_smooth_path(key_path, forest.centres, scenario.num_steps,
                                        (centre[0], centre[1], 0.0), scenario.step_length,
                                        bounds=((0.0, 0.0), (size, size)))
    return forest, path


def _world_arrays(forest, path):
    """(path (T+1, 3), centres (N, 2), radii (N,)) as float32 arrays."""
    return (jnp.asarray(path, jnp.float32), jnp.asarray(forest.centres, jnp.float32),
            jnp.asarray(forest.radii, jnp.float32))


def scenario_batch(config: StudyConfig, run_ids: np.ndarray, width: int | None = None
                   ) -> RunBatch:
    """Simulate the runs ``run_ids``: run i draws its noise from fold_in(PRNGKey(seed), i).

    The runs go through one compiled simulator of ``width`` runs (default
    ``config.run_width``) in groups, the last padded by repeating its last id, so a run's
    inputs never depend on how many runs are asked for at once. Leaves (R, ...) for the
    controls, observations and tree_seen; truth_pose (T+1, 3), tree_centres (N, 2) and
    tree_radii (N,) are the shared world's, or (R, ...) with ``scenario.world = "per_run"``.

    Lidar scans need MuJoCo: without it, ``SimulatorNotInstalled`` (an ImportError naming the
    install command) is raised before anything is simulated.
    """
    run_ids = np.asarray(run_ids, np.int64).reshape(-1)
    if run_ids.size == 0:
        raise ValueError("scenario_batch needs at least one run id")
    if config.scenario.observation_source == "lidar":
        require_mujoco('scenario.observation_source = "lidar" (MJX lidar scans)')
    width = config.run_width if width is None else int(width)
    if config.scenario.world == "per_run":
        return _per_run_batch(config, run_ids, width)
    simulate, world = _simulator(config.scenario, config.seed, config.filter.max_obs)
    padded = -(-run_ids.size // width) * width
    ids = np.concatenate([run_ids, np.full(padded - run_ids.size, run_ids[-1])])
    groups = [simulate(jnp.asarray(ids[first:first + width], jnp.uint32))
              for first in range(0, padded, width)]
    controls, observations, seen = jax.tree.map(
        lambda *parts: jnp.concatenate(parts)[:run_ids.size], *groups)
    return world._replace(controls=controls, observations=observations, tree_seen=seen)


@functools.lru_cache(maxsize=8)
def _simulator(settings: ScenarioConfig, seed: int, max_obs: int):
    """A compiled run simulator for one study world (cached: compiled once per study).

    Returns (simulate(run_ids (R,)) -> (controls, observations, tree_seen (R, N)), RunBatch of
    the shared world). A tree counts as seen in a run when it was observed at least once
    (analytic source, which knows tree ids) or passed within range of the path (lidar).
    """
    from sims import scenario as scenario_lib
    from sims.forest import world_from_forest
    from sims.paths import noisy_odometry, true_moves

    forest, path = study_world(settings, seed)
    params = simulation_params(settings)
    centres = jnp.asarray(forest.centres, jnp.float32)
    radii = jnp.asarray(forest.radii, jnp.float32)
    path = jnp.asarray(path, jnp.float32)
    moves = true_moves(path, params.min_translation)
    gap = path[:, None, :2] - centres[None]
    in_range = jnp.min(jnp.hypot(gap[..., 0], gap[..., 1]), axis=0) <= settings.max_range
    if settings.observation_source == "lidar":
        # Every run follows the same true path through the same forest, so the noise-free
        # scans are cast once (T scans) and each run only adds its own beam noise and detects.
        from jaxslam.detect import detect_trunks
        from sims.lidar import add_range_noise, beam_angles, scan_2d_full

        lidar_world = world_from_forest(forest)
        clean_scans = jax.lax.map(
            lambda pose: scan_2d_full(lidar_world, pose, LIDAR_BEAMS, settings.max_range).ranges,
            path[1:])
        angles = jnp.asarray(beam_angles(LIDAR_BEAMS), jnp.float32)

    def observe(key, pose, step):
        if settings.observation_source == "analytic":
            return scenario_lib.analytic_observations(key, pose, centres, radii, params, max_obs)
        key_noise, key_detect = jax.random.split(key)
        ranges = add_range_noise(key_noise, clean_scans[step], settings.max_range,
                                 LIDAR_BEAM_NOISE)
        return detect_trunks(ranges, angles, settings.detection, max_obs=max_obs,
                             max_range=settings.max_range, min_range=float(params.min_range),
                             key=key_detect if settings.detection == "ransac" else None)

    def one_run(run_id):
        run_key = jax.random.fold_in(jax.random.PRNGKey(seed), run_id)
        key_odometry, key_obs = jax.random.split(jax.random.fold_in(run_key, 0))
        controls = noisy_odometry(key_odometry, moves, params)
        steps = jnp.arange(moves.shape[0])
        inputs = (jax.random.split(key_obs, moves.shape[0]), path[1:], steps)
        if settings.observation_source == "analytic":
            observations = jax.vmap(observe)(*inputs)
        else:
            # Scan detection holds (segments x beams) work arrays (B x B for the geometric and
            # RANSAC fits): a vmap over all T steps of a 100-run chunk asked for 63 GB. Steps
            # go in sequence, runs stay vmapped.
            observations = jax.lax.map(lambda args: observe(*args), inputs)
        seen = (_observed_trees(observations, centres.shape[0])
                if settings.observation_source == "analytic" else in_range)
        return controls, observations, seen

    world = RunBatch(None, None, path, centres, radii, in_range)
    return jax.jit(jax.vmap(one_run)), world


def _observed_trees(observations, num_trees: int):
    """(N,) bool: trees observed at least once (analytic observations carry tree ids)."""
    ids = jnp.where(observations.valid, observations.landmark_id, num_trees)
    return jnp.zeros(num_trees, bool).at[ids.ravel()].set(True, mode="drop")


@functools.lru_cache(maxsize=8)
def _per_run_simulator(settings: ScenarioConfig, seed: int, max_obs: int):
    """jit(vmap(one run)) for per-run worlds: (run_ids (R,), path (R, T+1, 3), centres (R, N, 2),
    radii (R, N)) -> (controls (R, T, 3), observations, tree_seen (R, N)). Analytic observations
    (a lidar needs an MJX model of each run's forest, not built per run)."""
    from sims import scenario as scenario_lib
    from sims.paths import noisy_odometry, true_moves

    params = simulation_params(settings)

    def one_run(run_id, path, centres, radii):
        moves = true_moves(path, params.min_translation)
        run_key = jax.random.fold_in(jax.random.PRNGKey(seed), run_id)
        key_odometry, key_obs = jax.random.split(jax.random.fold_in(run_key, 0))
        controls = noisy_odometry(key_odometry, moves, params)
        observations = jax.vmap(lambda key, pose: scenario_lib.analytic_observations(
            key, pose, centres, radii, params, max_obs))(
                jax.random.split(key_obs, moves.shape[0]), path[1:])
        return controls, observations, _observed_trees(observations, centres.shape[0])

    return jax.jit(jax.vmap(one_run))


def _per_run_batch(config: StudyConfig, run_ids: np.ndarray, width: int) -> RunBatch:
    """``scenario_batch`` for ``world = "per_run"``: run i's forest and path from its own key
    (``run_world``, drawn on the host), simulated in groups of ``width`` runs."""
    settings = config.scenario
    simulate = _per_run_simulator(settings, config.seed, config.filter.max_obs)
    worlds = [_world_arrays(*run_world(settings, config.seed, int(i))) for i in run_ids]
    path, centres, radii = (jnp.stack(parts) for parts in zip(*worlds))
    padded = -(-run_ids.size // width) * width
    rows = np.minimum(np.arange(padded), run_ids.size - 1)
    groups = []
    for first in range(0, padded, width):
        group = rows[first:first + width]
        groups.append(simulate(jnp.asarray(run_ids[group], jnp.uint32), path[group],
                               centres[group], radii[group]))
    controls, observations, seen = jax.tree.map(
        lambda *parts: jnp.concatenate(parts)[:run_ids.size], *groups)
    return RunBatch(controls, observations, path, centres, radii, seen)
