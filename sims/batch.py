"""Batches of simulated runs for Monte Carlo studies: ``scenario_batch`` is the ``simulate``
function of the "sims" study simulator (registered by ``sims/__init__.py``; ``jaxslam.studies``
loads it by name, so the library itself never imports the simulator or MuJoCo).

Run i draws from its key ``fold_in(PRNGKey(seed), i)``: its odometry and observation noise
from ``fold_in(key, 0)`` (the filter uses ``fold_in(key, 1)``) and, with
``scenario.world = "per_run"``, its own forest and path from ``fold_in(key, 2)``. With
``world = "shared"`` every run follows one true path through one forest (drawn from the seed
alone), so runs differ only in noise: paired comparisons, but one world's luck.

A per-run world is drawn inside the compiled, vmapped simulator (``draw_run_world``, static
shapes); its lidar scans are cast in a template MJX world whose trunk rows hold the run's
trunks (``run_lidar_world``), so per-run lidar runs stay one vmapped program. A run whose
forest cannot hold its trees is refused afterwards, on the host, with a ValueError naming
the runs and how many of those simulated were affected.
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
# Runs per compiled world-drawing call (``run_world_arrays``): one compile whatever R.
WORLD_WIDTH = 16
# A study of at most this many runs counts all its unbuildable worlds when one chunk has one.
STUDY_CHECK_RUNS = 20_000


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
    drawn from ``fold_in(fold_in(PRNGKey(seed), run_id), 2)`` as the study's simulator draws
    it (``draw_run_world``); ValueError when its forest cannot be placed."""
    from sims.forest import Forest, empty_clutter

    path, centres, radii = (part[0] for part in run_world_arrays(scenario, seed, [run_id]))
    return Forest(centres, radii, empty_clutter()), path


def _draw_world(scenario: ScenarioConfig, key):
    """A forest (random or plantation) and a true path (loop, lawnmower or random) (T+1, 3),
    drawn eagerly (a forest that cannot be placed raises ValueError)."""
    from sims import forest as forest_lib
    from sims import paths

    key_forest, key_path = jax.random.split(key)
    size = scenario.size
    path = _designed_path(scenario)
    if scenario.forest == "plantation":
        forest = forest_lib.plantation_forest(key_forest, *_plantation_shape(size))
    else:
        keep_clear = None if path is None else np.asarray(path)[:, :2]
        forest = forest_lib.random_forest(key_forest, scenario.num_trees, (size, size),
                                          keep_clear=keep_clear)
    if path is None:
        path = paths.random_smooth_path(key_path, forest.centres, scenario.num_steps,
                                        (0.5 * size, 0.5 * size, 0.0), scenario.step_length,
                                        bounds=((0.0, 0.0), (size, size)))
    return forest, path


def _designed_path(scenario: ScenarioConfig):
    """The loop or lawnmower path (T+1, 3) of a scenario (no key: every world has it), or None
    for a random path (drawn through each forest)."""
    from sims import paths

    size = scenario.size
    if scenario.path == "loop":
        radius = scenario.num_steps * scenario.step_length / (2.0 * np.pi)
        return paths.loop_path(scenario.num_steps, (0.5 * size, 0.5 * size), (radius, radius),
                               scenario.step_length)
    if scenario.path == "lawnmower":  # lanes midway between plantation rows
        return paths.lawnmower_path(np.arange(3.5, size - 3.0, 7.0), 0.0, size,
                                    scenario.num_steps, scenario.step_length)
    return None


def _plantation_shape(size: float) -> tuple[int, int]:
    """(rows 7 m apart, trees 3 m apart along a row) of a plantation filling the square."""
    return max(2, int(size // 7.0) + 1), max(2, int(size // 3.0) + 1)


def draw_run_world(settings: ScenarioConfig, key, designed_path=None):
    """One run's world as a pure function of its ``key`` (``jit``, ``vmap``): the world
    ``_draw_world`` draws, without raising.

    ``designed_path``: ``_designed_path(settings)`` (computed once by the caller).
    Returns (path (T+1, 3), centres (N, 2), radii (N,) float32, placed () int32 trees placed; a
    random forest with placed < N has zero rows and is refused by ``_check_placed``).
    """
    from sims import forest as forest_lib
    from sims import paths

    key_forest, key_path = jax.random.split(key)
    size = settings.size
    if settings.forest == "plantation":
        forest = forest_lib.plantation_forest(key_forest, *_plantation_shape(size))
        placed = jnp.asarray(forest.centres.shape[0], jnp.int32)
    else:
        keep_clear = None if designed_path is None else designed_path[:, :2]
        forest, placed = forest_lib.sample_forest(key_forest, settings.num_trees, (size, size),
                                                  keep_clear=keep_clear)
    path = designed_path
    if path is None:
        path = paths.random_smooth_path(key_path, forest.centres, settings.num_steps,
                                        (0.5 * size, 0.5 * size, 0.0), settings.step_length,
                                        bounds=((0.0, 0.0), (size, size)))
    return _world_arrays(forest, path) + (placed,)


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

    With ``scenario.robot = "mjx_wheeled"`` the MJX wheeled robot drives each run
    (``sims.robot_runs.robot_batch``): with ``scenario.first_scan = "at_start"`` (its
    default) it scans at rest before it drives, so controls are (R, T+1, 3), observations
    (R, T+1, K, ...) and truth_pose (R, T+2, 3), the start pose repeated for the zero move
    (with "after_first_move": T, T and T+1 rows); the world leaves are (R, ...) in both kinds
    of world.

    Lidar scans and the MJX robot need MuJoCo: without it, ``SimulatorNotInstalled`` (an
    ImportError naming the install command) is raised before anything is simulated.
    """
    run_ids = np.asarray(run_ids, np.int64).reshape(-1)
    if run_ids.size == 0:
        raise ValueError("scenario_batch needs at least one run id")
    if config.scenario.observation_source == "lidar":
        require_mujoco('scenario.observation_source = "lidar" (MJX lidar scans)')
    width = config.run_width if width is None else int(width)
    if config.scenario.robot == "mjx_wheeled":
        from sims.robot_runs import robot_batch

        return robot_batch(config, run_ids, width)
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
    from sims.paths import true_moves

    forest, path = study_world(settings, seed)
    params = simulation_params(settings)
    centres = jnp.asarray(forest.centres, jnp.float32)
    radii = jnp.asarray(forest.radii, jnp.float32)
    path = jnp.asarray(path, jnp.float32)
    moves = true_moves(path, params.min_translation)
    in_range = trees_in_range(path, centres, settings.max_range)
    if settings.observation_source == "lidar":
        # Every run follows the same true path through the same forest, so the noise-free
        # scans are cast once (T scans) and each run only adds its own beam noise and detects.
        lidar_world = world_from_forest(forest)
        clean_scans = jax.lax.map(lambda pose: clean_scan(settings, lidar_world, pose),
                                  path[1:])

    def observe(key, pose_and_step):
        pose, step = pose_and_step
        if settings.observation_source == "analytic":
            return scenario_lib.analytic_observations(key, pose, centres, radii, params, max_obs)
        return detect_in_scan(settings, params, max_obs, key, clean_scans[step])

    def one_run(run_id):
        run_key = jax.random.fold_in(jax.random.PRNGKey(seed), run_id)
        # Scan detection holds (segments x beams) work arrays (B x B for the geometric and
        # RANSAC fits): a vmap over all T steps of a 100-run chunk asked for 63 GB. Lidar
        # steps go in sequence, runs stay vmapped.
        controls, observations = scenario_lib.simulate_run(
            jax.random.fold_in(run_key, 0), moves, (path[1:], jnp.arange(moves.shape[0])),
            params, observe, sequential=settings.observation_source == "lidar")
        seen = (observed_trees(observations, centres.shape[0])
                if settings.observation_source == "analytic" else in_range)
        return controls, observations, seen

    world = RunBatch(None, None, path, centres, radii, in_range)
    return jax.jit(jax.vmap(one_run)), world


def trees_in_range(path, centres, max_range: float):
    """(N,) bool: trees whose centre comes within ``max_range`` of a pose of ``path``
    (T+1, 3): the lidar studies' "seen" (detections carry no tree ids)."""
    gap = path[:, None, :2] - centres[None]
    return jnp.min(jnp.hypot(gap[..., 0], gap[..., 1]), axis=0) <= max_range


def clean_scan(settings: ScenarioConfig, world, pose):
    """Noise-free culled planar scan (LIDAR_BEAMS,) [m] of ``world`` from ``pose`` (3,)."""
    from sims.lidar import scan_2d_full

    return scan_2d_full(world, pose, LIDAR_BEAMS, settings.max_range).ranges


def detect_in_scan(settings: ScenarioConfig, params: Params, max_obs: int, key, ranges):
    """A run's lidar observation of one step: per-beam noise (``LIDAR_BEAM_NOISE``, from
    ``split(key)[0]``) on the noise-free ``ranges`` (B,), then ``detect_trunks``
    (``split(key)[1]`` for RANSAC): ``Observations`` with leaves (K, ...)."""
    from jaxslam.detect import detect_trunks
    from sims.lidar import add_range_noise, beam_angles

    key_noise, key_detect = jax.random.split(key)
    noisy = add_range_noise(key_noise, ranges, settings.max_range, LIDAR_BEAM_NOISE)
    angles = jnp.asarray(beam_angles(LIDAR_BEAMS), jnp.float32)
    return detect_trunks(noisy, angles, settings.detection, max_obs=max_obs,
                         max_range=settings.max_range, min_range=float(params.min_range),
                         key=key_detect if settings.detection == "ransac" else None)


def observed_trees(observations, num_trees: int):
    """(N,) bool: trees observed at least once (analytic observations carry tree ids)."""
    ids = jnp.where(observations.valid, observations.landmark_id, num_trees)
    return jnp.zeros(num_trees, bool).at[ids.ravel()].set(True, mode="drop")


def _run_world_key(seed: int, run_id):
    """``fold_in(fold_in(PRNGKey(seed), run_id), 2)``: the key of run ``run_id``'s world."""
    return jax.random.fold_in(jax.random.fold_in(jax.random.PRNGKey(seed), run_id), 2)


@functools.lru_cache(maxsize=8)
def lidar_template(settings: ScenarioConfig):
    """The MJX world every per-run lidar world is refilled from (``sims.forest.trunk_template``
    with as many trunk slots as ``draw_run_world`` draws trees; the trunk height, sensor height
    and culling slots of ``world_from_forest``'s defaults, as the shared world's)."""
    from sims.forest import trunk_template

    with jax.ensure_compile_time_eval():  # concrete arrays even when first asked in a trace
        shapes = jax.eval_shape(
            lambda key: draw_run_world(settings, key, _designed_path(settings)),
            jax.random.PRNGKey(0))
        return trunk_template(shapes[1].shape[0])


def run_lidar_world(settings: ScenarioConfig, centres, radii):
    """Run's MJX lidar world: ``lidar_template(settings)`` with the run's trunks ``centres``
    (N, 2) and ``radii`` (N,) (``sims.forest.world_with_trunks``; ``jit`` and ``vmap``)."""
    from sims.forest import world_with_trunks

    return world_with_trunks(lidar_template(settings), centres, radii)


@functools.lru_cache(maxsize=8)
def _per_run_simulator(settings: ScenarioConfig, seed: int, max_obs: int):
    """jit(vmap(one run)) for per-run worlds: run_ids (R,) -> (controls (R, T, 3),
    observations, tree_seen (R, N), path (R, T+1, 3), centres (R, N, 2), radii (R, N),
    placed (R,)). Each run draws its world in the program (``draw_run_world``).

    Lidar: each run's trunks are written into the trunk rows of one template MJX world
    (``run_lidar_world``: arrays vmapped over runs, one compiled program) and its T scans are
    cast along its own path with the culled scan (sectors refilled from the run's trunks);
    steps go in sequence (``lax.map``, as the shared lidar path's detection), runs stay
    vmapped. Each scan then gets the run's beam noise and detection as in the shared path
    (``detect_in_scan``); "seen" is trees within range of the run's path."""
    from sims import scenario as scenario_lib
    from sims.paths import true_moves

    params = simulation_params(settings)
    designed_path = _designed_path(settings)
    lidar = settings.observation_source == "lidar"
    if lidar:
        lidar_template(settings)  # built eagerly, before tracing

    def one_run(run_id):
        path, centres, radii, placed = draw_run_world(
            settings, _run_world_key(seed, run_id), designed_path)
        moves = true_moves(path, params.min_translation)
        run_key = jax.random.fold_in(jax.random.PRNGKey(seed), run_id)
        if lidar:
            world = run_lidar_world(settings, centres, radii)

            def observe(key, pose):
                return detect_in_scan(settings, params, max_obs, key,
                                      clean_scan(settings, world, pose))
        else:
            def observe(key, pose):
                return scenario_lib.analytic_observations(key, pose, centres, radii, params,
                                                          max_obs)
        controls, observations = scenario_lib.simulate_run(
            jax.random.fold_in(run_key, 0), moves, path[1:], params, observe,
            sequential=lidar)
        seen = (trees_in_range(path, centres, settings.max_range) if lidar
                else observed_trees(observations, centres.shape[0]))
        return controls, observations, seen, path, centres, radii, placed

    return jax.jit(jax.vmap(one_run))


@functools.lru_cache(maxsize=8)
def _world_drawer(settings: ScenarioConfig, seed: int):
    """jit(vmap(run world)): run_ids (R,) -> (path, centres, radii, placed), leaves (R, ...)."""
    designed_path = _designed_path(settings)
    return jax.jit(jax.vmap(lambda run_id: draw_run_world(
        settings, _run_world_key(seed, run_id), designed_path)))


def _per_run_batch(config: StudyConfig, run_ids: np.ndarray, width: int) -> RunBatch:
    """``scenario_batch`` for ``world = "per_run"``: run i's forest and path drawn from its
    own key inside the compiled simulator, in groups of ``width`` runs."""
    settings = config.scenario
    simulate = _per_run_simulator(settings, config.seed, config.filter.max_obs)
    *outputs, placed = simulate_in_groups(simulate, run_ids, width)
    if _short_runs(settings, placed).size and config.num_runs <= STUDY_CHECK_RUNS:
        # Count the whole study's runs (worlds only), so the error says how many it loses.
        study_ids = np.arange(config.num_runs)
        study_placed = simulate_in_groups(_world_drawer(settings, config.seed), study_ids,
                                          WORLD_WIDTH)[3]
        _check_placed(settings, study_ids, study_placed, "runs of the study")
    _check_placed(settings, run_ids, placed)
    controls, observations, seen, path, centres, radii = outputs
    return RunBatch(controls, observations, path, centres, radii, seen)


def run_world_arrays(settings: ScenarioConfig, seed: int, run_ids, width: int = WORLD_WIDTH):
    """The worlds of runs ``run_ids`` (R,): (path (R, T+1, 3), centres (R, N, 2), radii (R, N))
    float32, each run's own (``draw_run_world``, in compiled groups of ``width`` runs) or the
    shared one repeated (``study_world``). ValueError names the runs whose forest cannot be
    placed."""
    run_ids = np.asarray(run_ids, np.int64).reshape(-1)
    if settings.world == "per_run":
        *world, placed = simulate_in_groups(_world_drawer(settings, seed), run_ids, width)
        _check_placed(settings, run_ids, placed)
        return tuple(world)
    return tuple(jnp.broadcast_to(part, (run_ids.size,) + part.shape)
                 for part in _world_arrays(*study_world(settings, seed)))


def _short_runs(settings: ScenarioConfig, placed) -> np.ndarray:
    """Indices of the runs whose forest holds fewer trees than ``settings.num_trees``."""
    if settings.forest != "random":  # a plantation places every tree
        return np.zeros(0, int)
    return np.flatnonzero(np.asarray(placed) < settings.num_trees)


def _check_placed(settings: ScenarioConfig, run_ids: np.ndarray, placed,
                  scope: str = "runs simulated") -> None:
    """Raise ValueError naming the runs ``run_ids`` (R,) whose forest is short of trees."""
    placed, short = np.asarray(placed), _short_runs(settings, placed)
    if short.size == 0:
        return
    listed = ", ".join(f"{run_ids[i]} ({placed[i]} placed)" for i in short[:5])
    clear = "" if settings.path == "random" else f" and 1.5 m off the {settings.path} path"
    raise ValueError(
        f"scenario.world='per_run': {short.size} of the {run_ids.size} {scope} "
        f"(run ids {run_ids.min()}..{run_ids.max()}) could not place scenario.num_trees="
        f"{settings.num_trees} trees 2.0 m apart{clear} in a scenario.size={settings.size} m "
        f"square: runs {listed}{', ...' if short.size > 5 else ''}; use a larger "
        "scenario.size or fewer scenario.num_trees (the 2.0 m spacing and 1.5 m path "
        "clearance are the defaults of sims.forest.sample_forest)")


def simulate_in_groups(simulate, run_ids: np.ndarray, width: int, *per_run):
    """``simulate(run_ids (W,), *leaves (W, ...))`` over groups of ``width`` runs, the last
    padded by repeating its last run (padding dropped), outputs concatenated to (R, ...).

    One compiled width whatever the number of runs asked: a run's inputs and outputs never
    depend on how many runs are simulated together."""
    padded = -(-run_ids.size // width) * width
    rows = np.minimum(np.arange(padded), run_ids.size - 1)
    groups = []
    for first in range(0, padded, width):
        group = rows[first:first + width]
        groups.append(simulate(jnp.asarray(run_ids[group], jnp.uint32),
                               *(leaves[group] for leaves in per_run)))
    return jax.tree.map(lambda *parts: jnp.concatenate(parts)[:run_ids.size], *groups)
