"""Monte Carlo studies and sweeps: chunked, seeded, resumable, one compiled call per chunk.

A study is R runs of a simulated scenario under one ``FilterConfig``, optionally over a grid of
``Params`` values (a sweep: G conditions). Run i uses ``fold_in(PRNGKey(seed), i)`` for both
its scenario and its filter, so every condition sees the same forests, paths and noise (common
random numbers), and results do not depend on the chunk size or the device count.

Output folder:
  study.toml            the resolved study config (a resumed study must match it)
  provenance.toml       package version, git revision, jax version, devices, start time
  chunk-AAAAAA-BBBBBB.parquet  one row per (run, condition) of runs [A, B): run_id, condition,
                        seed, each swept param, every metric
  traces-AAAAAA-BBBBBB.npz     per-step position error (rows, T), run_id, condition
  example_run.npz       run 0 / condition 0: truth, estimated path, final map
  summary.md            the results table (``summarize_study``)
Writes are atomic (temporary file + rename); a rerun skips every chunk already on disk.
"""
from __future__ import annotations

import dataclasses
import datetime
import functools
import itertools
import os
import pathlib
import subprocess
import time
import tomllib
import warnings
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxslam import metrics
from jaxslam.filter import estimate, make_filter, scan_filter
from jaxslam.types import FilterConfig, Params, default_params

_CHUNK_PREFIX = "chunk-"
# 1440 beams (0.25 degree): at 720, trunks beyond ~10 m get fewer than 4 points.
LIDAR_BEAMS = 1440
LIDAR_BEAM_NOISE = (0.0, 0.01)  # per-beam range std (per metre, constant) [m]
_KNOWN_FILES = {"study.toml", "provenance.toml", "summary.md", "example_run.npz"}
SUMMARY_METRICS = ("final_pose_error", "ate_rmse", "ate_rmse_aligned", "map_error",
                   "redundant", "orphan", "num_landmarks", "gospa", "pose_nees", "diverged",
                   "update_rate_hz")


class StudyError(RuntimeError):
    """A study cannot run or resume safely (foreign study in the folder, corrupt chunk...)."""


@dataclasses.dataclass(frozen=True)
class ScenarioConfig:
    """The simulated world of every run (see ``sims.scenario``).

    forest: "random" or "plantation"; num_trees; size: square side [m]; path: "loop",
    "lawnmower" or "random"; num_steps: T; step_length [m]; max_range [m] of the sensor;
    observation_source: "analytic" (range-bearing to trunk centres with Table 2 noise) or
    "lidar" (MJX scans + trunk detection); detection: centroid | kasa | geometric | ransac;
    odometry_noise_scale: multiplies the Table 1 noise of the simulated odometry.
    """

    forest: str = "random"
    num_trees: int = 80
    size: float = 60.0
    path: str = "loop"
    num_steps: int = 200
    step_length: float = 0.5
    max_range: float = 20.0
    observation_source: str = "analytic"
    detection: str = "kasa"
    odometry_noise_scale: float = 1.0


@dataclasses.dataclass(frozen=True)
class StudyConfig:
    """Everything that defines a study. ``params`` are overrides of ``default_params``;
    ``sweep`` maps Params fields to lists of values (cartesian grid of conditions)."""

    name: str = "study"
    num_runs: int = 100
    chunk_size: int = 50
    seed: int = 0
    filter: FilterConfig = FilterConfig()
    scenario: ScenarioConfig = ScenarioConfig()
    params: tuple = ()
    sweep: tuple = ()
    divergence_threshold: float = 2.0
    map_match_threshold: float = 1.0
    gospa_cutoff: float = 2.0

    def __post_init__(self):
        for name in ("num_runs", "chunk_size"):
            value = getattr(self, name)
            if not isinstance(value, int) or value < 1:
                raise ValueError(f"study {name}={value!r}; expected a positive integer")
        params_fields = set(Params._fields)
        for section, items in (("params", self.params), ("sweep", self.sweep)):
            for key, _ in items:
                if key not in params_fields:
                    raise ValueError(f"{section}.{key} is not a filter parameter; expected one "
                                     f"of {sorted(params_fields)}")

    @property
    def conditions(self) -> list[dict[str, Any]]:
        """The sweep grid as a list of {param: value} (one empty dict without a sweep)."""
        if not self.sweep:
            return [{}]
        names = [name for name, _ in self.sweep]
        values = [list(vals) for _, vals in self.sweep]
        return [dict(zip(names, combo)) for combo in itertools.product(*values)]


# --------------------------------------------------------------------------------------------
# Config files


def _as_tuple_items(mapping: dict) -> tuple:
    return tuple((k, tuple(v) if isinstance(v, list) else v) for k, v in mapping.items())


def study_config_to_dict(config: StudyConfig) -> dict:
    """Plain dict (TOML-ready) of a study config."""
    out = {f.name: getattr(config, f.name) for f in dataclasses.fields(config)
           if f.name not in ("filter", "scenario", "params", "sweep")}
    out["filter"] = dataclasses.asdict(config.filter)
    out["scenario"] = dataclasses.asdict(config.scenario)
    out["params"] = {k: list(v) if isinstance(v, tuple) else v for k, v in config.params}
    out["sweep"] = {k: list(v) for k, v in config.sweep}
    return out


def _check_keys(section: str, given: dict, cls) -> None:
    allowed = [f.name for f in dataclasses.fields(cls)]
    for key in given:
        if key not in allowed:
            where = f"{section}.{key}" if section else key
            raise ValueError(f"unknown study config key {where!r}; allowed keys"
                             f"{' in [' + section + ']' if section else ''}: {allowed}")


def study_config_from_dict(data: dict) -> StudyConfig:
    """Build and validate a ``StudyConfig``; errors name the key and the allowed values."""
    data = dict(data)
    filter_section = dict(data.pop("filter", {}))
    scenario_section = dict(data.pop("scenario", {}))
    params_section = dict(data.pop("params", {}))
    sweep_section = dict(data.pop("sweep", {}))
    _check_keys("", data, StudyConfig)
    _check_keys("filter", filter_section, FilterConfig)
    _check_keys("scenario", scenario_section, ScenarioConfig)
    _check_scenario(scenario_section)
    for key, values in sweep_section.items():
        if not isinstance(values, list) or not values:
            raise ValueError(f"sweep.{key} must be a non-empty list of values; got {values!r}")
    return StudyConfig(filter=FilterConfig(**filter_section),
                       scenario=ScenarioConfig(**scenario_section),
                       params=_as_tuple_items(params_section),
                       sweep=_as_tuple_items(sweep_section), **data)


_SCENARIO_CHOICES = {"forest": ("random", "plantation"), "path": ("loop", "lawnmower", "random"),
                     "observation_source": ("analytic", "lidar"),
                     "detection": ("centroid", "kasa", "geometric", "ransac")}


def _check_scenario(section: dict) -> None:
    for key, allowed in _SCENARIO_CHOICES.items():
        if key in section and section[key] not in allowed:
            raise ValueError(f"scenario.{key}={section[key]!r} is not supported; expected one of "
                             f"{list(allowed)}")


def _parse_value(text: str):
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text


def load_study_config(path=None, overrides=()) -> StudyConfig:
    """Read a study TOML (or start from the defaults) and apply "section.key=value" overrides.

    Example overrides: ``num_runs=20``, ``filter.num_particles=50``, ``params.max_range=15``,
    ``sweep.mixture_ratio=[0.0, 0.3]``.
    """
    data: dict = {}
    if path is not None:
        path = pathlib.Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"study config {str(path)!r} does not exist")
        with open(path, "rb") as handle:
            data = tomllib.load(handle)
    for item in overrides:
        if "=" not in item:
            raise ValueError(f"override {item!r} must look like section.key=value")
        dotted, text = item.split("=", 1)
        *sections, key = dotted.strip().split(".")
        target = data
        for section in sections:
            target = target.setdefault(section, {})
        target[key] = _parse_value(text.strip())
    return study_config_from_dict(data)


def demo_study_config() -> StudyConfig:
    """The README's main job: 64 runs on the default simulated forest, stable matching,
    the loose boundary, P=64 particles; a few minutes on a 2-core CPU."""
    return StudyConfig(name="demo", num_runs=64, chunk_size=32, seed=0,
                       filter=FilterConfig(num_particles=64, max_landmarks=96, max_obs=16),
                       scenario=ScenarioConfig(num_steps=150))


# --------------------------------------------------------------------------------------------
# Scenario batch (the simulator part)


class RunBatch(NamedTuple):
    """Scenarios of a chunk of runs. Run-dependent leaves have a leading axis R; the forest is
    shared by every run of a study (runs differ in odometry and observation noise).

    controls: (R, T, 3); observations: leaves (R, T, K, ...); truth_pose: (T+1, 3);
    tree_centres: (N, 2); tree_radii: (N,); tree_seen: (R, N) trees observed in each run.
    """

    controls: jnp.ndarray
    observations: Any
    truth_pose: jnp.ndarray
    tree_centres: jnp.ndarray
    tree_radii: jnp.ndarray
    tree_seen: jnp.ndarray


def simulation_params(scenario: ScenarioConfig) -> Params:
    """Noise of the simulated robot: Table 1 scaled by ``odometry_noise_scale``, Table 2."""
    base = default_params(max_range=scenario.max_range)
    scale = scenario.odometry_noise_scale
    return base._replace(rot1_noise=base.rot1_noise * scale,
                         trans_noise=base.trans_noise * scale,
                         rot2_noise=base.rot2_noise * scale)


@functools.lru_cache(maxsize=8)
def study_world(scenario: ScenarioConfig, seed: int):
    """The forest and true path of a study (built once, eagerly). Returns (forest, path)."""
    from sims import forest as forest_lib
    from sims import paths

    key_forest, key_path = jax.random.split(jax.random.fold_in(jax.random.PRNGKey(seed), 2**30))
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


def scenario_batch(config: StudyConfig, run_ids: np.ndarray) -> RunBatch:
    """Simulate the runs ``run_ids``: run i draws its noise from fold_in(PRNGKey(seed), i)."""
    simulate, world = _simulator(config.scenario, config.seed, config.filter.max_obs)
    controls, observations, seen = simulate(jnp.asarray(run_ids, jnp.uint32))
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
        observations = jax.vmap(observe)(jax.random.split(key_obs, moves.shape[0]), path[1:],
                                         steps)
        if settings.observation_source == "analytic":
            ids = jnp.where(observations.valid, observations.landmark_id, centres.shape[0])
            seen = jnp.zeros(centres.shape[0], bool).at[ids.ravel()].set(True, mode="drop")
        else:
            seen = in_range
        return controls, observations, seen

    world = RunBatch(None, None, path, centres, radii, in_range)
    return jax.jit(jax.vmap(one_run)), world


# --------------------------------------------------------------------------------------------
# Filter + metrics of one run (traced)


def condition_params(config: StudyConfig) -> Params:
    """Stacked ``Params`` of the G sweep conditions (leading axis G)."""
    base = {"max_range": config.scenario.max_range, **dict(config.params)}
    stacked = [default_params(config.filter, **{**base, **cond}) for cond in config.conditions]
    return jax.tree.map(lambda *leaves: jnp.stack(leaves), *stacked)


def _run_metrics(config: StudyConfig, key, params: Params, controls, observations,
                 world: RunBatch):
    """Filter one run and score it. Returns (metrics dict of (), error trace (T,), example).

    ``key`` is the run's key; the filter uses fold_in(key, 1) (the simulator used 0).
    """
    filter_config = config.filter
    state = make_filter(filter_config).init(world.truth_pose[0])
    final, trace = scan_filter(filter_config, jax.random.fold_in(key, 1), state, params,
                               controls, observations)
    scenario = world
    truth = world.truth_pose[1:]
    est = estimate(final)
    position_error = jnp.hypot(trace.mean_pose[:, 0] - truth[:, 0],
                               trace.mean_pose[:, 1] - truth[:, 1])
    final_error = position_error[-1]
    map_scores = metrics.map_metrics(est.landmark_mean, est.active, scenario.tree_centres,
                                     scenario.tree_seen, config.map_match_threshold)
    gospa = metrics.gospa(est.landmark_mean, est.active, scenario.tree_centres,
                          scenario.tree_seen, config.gospa_cutoff)
    rpe_translation, rpe_rotation = metrics.rpe(trace.mean_pose, truth, delta=1)
    diameter_error, num_diameters = _diameter_error(est, world, config.map_match_threshold)
    pose_mean, pose_cov = metrics.particle_pose_moments(final.particles.pose, final.log_weight)
    values = dict(
        final_pose_error=final_error,
        final_heading_error=jnp.abs(metrics.heading_error(trace.mean_pose[-1], truth[-1])),
        ate_rmse=metrics.ate_rmse(trace.mean_pose, truth),
        ate_rmse_aligned=metrics.ate_rmse(trace.mean_pose, truth, align=True),
        rpe_translation=rpe_translation,
        rpe_rotation=rpe_rotation,
        map_error=map_scores.map_error,
        redundant=map_scores.redundant,
        orphan=map_scores.orphan,
        num_landmarks=map_scores.num_landmarks,
        num_trees_mapped=map_scores.num_trees_mapped,
        num_trees_seen=jnp.sum(scenario.tree_seen).astype(jnp.int32),
        gospa=gospa.distance,
        pose_nees=metrics.pose_nees(pose_mean, pose_cov + 1e-9 * jnp.eye(3), truth[-1]),
        diverged=final_error > config.divergence_threshold,
        diameter_error=diameter_error,
        num_diameters=num_diameters,
        min_ess=jnp.min(trace.ess),
        num_resampled=jnp.sum(trace.resampled).astype(jnp.int32),
        num_dropped_births=jnp.sum(trace.num_dropped_births).astype(jnp.int32),
        num_weight_resets=jnp.sum(trace.weights_reset).astype(jnp.int32),
        max_match_rounds=jnp.max(trace.match_rounds),
        mean_mixture_ratio=jnp.mean(trace.mixture_ratio),
    )
    example = dict(mean_pose=trace.mean_pose, landmark_mean=est.landmark_mean,
                   landmark_cov=est.landmark_cov, landmark_radius=est.landmark_radius,
                   active=est.active)
    return values, position_error, example


def _diameter_error(est, world: RunBatch, threshold):
    """Mean |2 r_landmark - 2 r_tree| [m] over landmarks matched to a tree that carry a
    measured radius (> 0), and their count. 0 when there are none (check the count)."""
    tree = metrics.match_landmarks(est.landmark_mean, est.active, world.tree_centres,
                                   world.tree_seen, threshold)
    measured = (tree >= 0) & (est.landmark_radius > 0)
    error = 2.0 * jnp.abs(est.landmark_radius - world.tree_radii[jnp.clip(tree, 0)])
    count = jnp.sum(measured)
    return (jnp.sum(jnp.where(measured, error, 0.0)) / jnp.maximum(count, 1),
            count.astype(jnp.int32))


def _chunk_fn(config: StudyConfig):
    """jit(vmap over conditions (vmap over runs)) of ``_run_metrics``."""

    def per_run(key, params, controls, observations, world):
        return _run_metrics(config, key, params, controls, observations, world)

    world_axes = RunBatch(None, None, None, None, None, 0)
    over_runs = jax.vmap(per_run, in_axes=(0, None, 0, 0, world_axes))
    over_conditions = jax.vmap(over_runs, in_axes=(None, 0, None, None, None))
    return jax.jit(over_conditions)


# --------------------------------------------------------------------------------------------
# Files


def _chunk_name(start: int, stop: int) -> str:
    return f"{_CHUNK_PREFIX}{start:06d}-{stop:06d}.parquet"


def _atomic_write(path: pathlib.Path, write) -> None:
    tmp = path.with_name(f".tmp-{path.name}")
    write(tmp)
    os.replace(tmp, path)


def _git_revision() -> str:
    try:
        root = pathlib.Path(__file__).resolve().parent.parent
        return subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"], check=True,
                              capture_output=True, text=True, timeout=5).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def _provenance() -> dict:
    from jaxslam import __version__

    return dict(jaxslam_version=__version__, git_revision=_git_revision(),
                jax_version=jax.__version__, backend=jax.default_backend(),
                devices=[str(d) for d in jax.devices()],
                started=datetime.datetime.now(datetime.timezone.utc).isoformat())


def _prepare_out_dir(config: StudyConfig, out_dir: pathlib.Path) -> None:
    """Create or check the folder: a different study there is an error, never overwritten."""
    import tomli_w

    out_dir.mkdir(parents=True, exist_ok=True)
    resolved = tomli_w.dumps(study_config_to_dict(config))
    study_file = out_dir / "study.toml"
    if study_file.exists():
        if study_file.read_text() != resolved:
            raise StudyError(
                f"{study_file} holds a different study config; resume only the same study, or "
                "choose another output folder")
    else:
        _atomic_write(study_file, lambda p: p.write_text(resolved))
    for stale in out_dir.glob(".tmp-*"):
        stale.unlink()  # our own half-written file from an interrupted run
    _atomic_write(out_dir / "provenance.toml",
                  lambda p: p.write_text(tomli_w.dumps(_provenance())))


def _existing_chunk_ok(path: pathlib.Path, start: int, stop: int, num_conditions: int) -> bool:
    """True when a finished chunk file is on disk; StudyError when it is corrupt."""
    import pyarrow.parquet as pq

    if not path.exists():
        return False
    try:
        run_ids = pq.read_table(path, columns=["run_id"]).column("run_id").to_numpy()
    except Exception as error:  # pyarrow raises several types for a damaged file
        raise StudyError(f"{path} is not a readable Parquet chunk ({error}); move or delete it "
                         "to recompute those runs") from error
    expected = np.repeat(np.arange(start, stop)[None], num_conditions, 0).ravel()
    if not np.array_equal(np.sort(run_ids), np.sort(expected)):
        raise StudyError(f"{path} does not hold runs {start}..{stop - 1} x {num_conditions} "
                         "conditions; it belongs to another study: move or delete it")
    return True


def foreign_files(out_dir: pathlib.Path) -> list[str]:
    """Files in the output folder that a study did not write (reported, never touched)."""
    out = []
    for path in sorted(pathlib.Path(out_dir).iterdir()):
        name = path.name
        ours = (name in _KNOWN_FILES or name.endswith(".png")
                or (name.startswith(_CHUNK_PREFIX) and name.endswith(".parquet"))
                or (name.startswith("traces-") and name.endswith(".npz")))
        if not ours:
            out.append(name)
    return out


# --------------------------------------------------------------------------------------------
# Runner


class StudyResult(NamedTuple):
    """out_dir: the results folder; table: pyarrow.Table of every (run, condition) row;
    compile_seconds / filter_seconds / simulator_seconds: time spent this invocation."""

    out_dir: pathlib.Path
    table: Any
    compile_seconds: float
    filter_seconds: float
    simulator_seconds: float


def _pad_ids(run_ids: np.ndarray, size: int) -> np.ndarray:
    return np.concatenate([run_ids, np.full(size - run_ids.size, run_ids[-1])])


def _chunk_rows(config, start, stop, values, seconds) -> dict:
    num_runs = stop - start
    conditions = config.conditions
    rows = {"run_id": np.tile(np.arange(start, stop), len(conditions)),
            "condition": np.repeat(np.arange(len(conditions)), num_runs),
            "seed": np.full(num_runs * len(conditions), config.seed)}
    for name, _ in config.sweep:
        rows[name] = np.repeat([c[name] for c in conditions], num_runs).astype(float)
    for name, value in values.items():
        rows[name] = np.asarray(value)[:, :num_runs].reshape(-1)
    rate = num_runs * len(conditions) * config.scenario.num_steps / max(seconds, 1e-9)
    rows["update_rate_hz"] = np.full(num_runs * len(conditions), rate)
    return rows


class ChunkOutput(NamedTuple):
    """What ``_ChunkRunner`` computes for runs [start, stop), padded to its chunk size Rp.

    scenario: the RunBatch of the chunk; values: metric name -> (G, Rp); errors: (G, Rp, T)
    position error per step; example: run traces and final map, leaves (G, Rp, ...);
    seconds: wall time of the filter call.
    """

    scenario: RunBatch
    values: dict
    errors: Any
    example: dict
    seconds: float


class _ChunkRunner:
    """Simulates and filters one chunk of runs; compiles once; shards runs over devices.

    With D > 1 local devices the run axis is split over a 1-D mesh ("mc") with
    ``NamedSharding``; the chunk is padded to a multiple of D (padded runs repeat the last id
    and are dropped). Each run's numbers depend only on its id, never on D or the chunk size.
    """

    def __init__(self, config: StudyConfig):
        self.config = config
        self.params = condition_params(config)
        self.function = _chunk_fn(config)
        self.compiled = None
        self.compile_seconds = self.filter_seconds = self.simulator_seconds = 0.0
        devices = jax.devices()
        self.mesh = None
        if len(devices) > 1:
            self.mesh = jax.make_mesh((len(devices),), ("mc",),
                                      axis_types=(jax.sharding.AxisType.Auto,))
        multiple = len(devices)
        self.padded_size = -(-config.chunk_size // multiple) * multiple

    def _shard(self, tree):
        if self.mesh is None:
            return tree
        sharding = jax.sharding.NamedSharding(self.mesh, jax.sharding.PartitionSpec("mc"))
        return jax.device_put(tree, sharding)

    def __call__(self, start: int, stop: int):
        config = self.config
        run_ids = _pad_ids(np.arange(start, stop), self.padded_size)
        tick = time.perf_counter()
        scenario = jax.block_until_ready(scenario_batch(config, run_ids))
        self.simulator_seconds += time.perf_counter() - tick
        keys = jax.vmap(lambda i: jax.random.fold_in(jax.random.PRNGKey(config.seed), i))(
            jnp.asarray(run_ids, jnp.uint32))
        keys, controls, observations, seen = self._shard(
            (keys, scenario.controls, scenario.observations, scenario.tree_seen))
        args = (keys, self.params, controls, observations,
                scenario._replace(controls=None, observations=None, tree_seen=seen))
        if self.compiled is None:
            tick = time.perf_counter()
            self.compiled = self.function.lower(*args).compile()
            self.compile_seconds = time.perf_counter() - tick
        tick = time.perf_counter()
        values, errors, example = jax.block_until_ready(self.compiled(*args))
        seconds = time.perf_counter() - tick
        self.filter_seconds += seconds
        return ChunkOutput(scenario, values, errors, example, seconds)


def open_study(config: StudyConfig, out_dir) -> list[tuple[int, int]]:
    """Create or check ``out_dir`` for ``config``, warn about foreign files, and return the
    run ranges [start, stop) of the chunks not yet on disk.

    Raises StudyError for a different study in the folder or a damaged chunk, before anything
    is computed. Every backend starts here, so chunk names and resume rules are shared.
    """
    out_dir = pathlib.Path(out_dir)
    _prepare_out_dir(config, out_dir)
    strangers = foreign_files(out_dir)
    if strangers:
        warnings.warn(f"{out_dir} holds files this study did not write (left untouched): "
                      f"{strangers}")
    num_conditions = len(config.conditions)
    bounds = [(start, min(start + config.chunk_size, config.num_runs))
              for start in range(0, config.num_runs, config.chunk_size)]
    return [(start, stop) for start, stop in bounds
            if not _existing_chunk_ok(out_dir / _chunk_name(start, stop), start, stop,
                                      num_conditions)]


def write_chunk(out_dir, config: StudyConfig, start: int, stop: int,
                output: ChunkOutput) -> None:
    """Write the files of the finished runs [start, stop): traces, the example run (first
    chunk only), then the chunk file. Each write is atomic and the chunk file comes last, so
    its presence marks the chunk (and its traces) done; safe from any process or host that
    shares the folder."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    out_dir = pathlib.Path(out_dir)
    rows = _chunk_rows(config, start, stop, output.values, output.seconds)
    errors = np.asarray(output.errors)
    np_errors = errors[:, :stop - start].reshape(-1, errors.shape[-1])
    _atomic_write(out_dir / f"traces-{start:06d}-{stop:06d}.npz",
                  lambda p: _save_npz(p, run_id=rows["run_id"], condition=rows["condition"],
                                      pose_error=np_errors))
    if start == 0:
        _write_example(out_dir, output.scenario, output.example)
    _atomic_write(out_dir / _chunk_name(start, stop), lambda p: pq.write_table(pa.table(rows), p))


def run_study(config: StudyConfig, out_dir, progress: bool = True) -> StudyResult:
    """Run (or resume) a study; see the module docstring for what lands in ``out_dir``."""
    from tqdm.auto import tqdm

    out_dir = pathlib.Path(out_dir)
    pending = open_study(config, out_dir)
    runner = _ChunkRunner(config)
    bar = tqdm(pending, desc=f"study {config.name}", unit="chunk", disable=not progress)
    for start, stop in bar:
        write_chunk(out_dir, config, start, stop, runner(start, stop))
        bar.set_postfix(runs=stop, filter_s=f"{runner.filter_seconds:.1f}")
    table = load_results(out_dir)
    summarize_study(out_dir, table)
    return StudyResult(out_dir, table, runner.compile_seconds, runner.filter_seconds,
                       runner.simulator_seconds)


def _save_npz(path: pathlib.Path, **arrays) -> None:
    with open(path, "wb") as handle:
        np.savez(handle, **arrays)


def _write_example(out_dir: pathlib.Path, scenario, example) -> None:
    first = {name: np.asarray(value)[0, 0] for name, value in example.items()}
    _atomic_write(out_dir / "example_run.npz", lambda p: _save_npz(
        p, truth_pose=np.asarray(scenario.truth_pose),
        tree_centres=np.asarray(scenario.tree_centres),
        tree_radii=np.asarray(scenario.tree_radii),
        tree_seen=np.asarray(scenario.tree_seen[0]), **first))


def load_results(out_dir):
    """All finished chunks of a study as one pyarrow.Table, sorted by (condition, run_id)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    paths = sorted(pathlib.Path(out_dir).glob(f"{_CHUNK_PREFIX}*.parquet"))
    if not paths:
        raise StudyError(f"no result chunks in {out_dir}")
    table = pa.concat_tables([pq.read_table(p) for p in paths])
    return table.sort_by([("condition", "ascending"), ("run_id", "ascending")])


def summary_rows(config: StudyConfig, table) -> list[dict]:
    """Per condition and metric: mean, median and the 2.5-97.5 percentile interval."""
    rows = []
    columns = {name: table.column(name).to_numpy() for name in table.column_names}
    for index, condition in enumerate(config.conditions):
        mask = columns["condition"] == index
        for name in SUMMARY_METRICS:
            if name not in columns:
                continue
            values = columns[name][mask].astype(float)
            rows.append(dict(condition=index, setting=_setting_label(condition), metric=name,
                             runs=int(mask.sum()), mean=float(np.mean(values)),
                             median=float(np.median(values)),
                             low=float(np.percentile(values, 2.5)),
                             high=float(np.percentile(values, 97.5))))
    return rows


def _setting_label(condition: dict) -> str:
    return ", ".join(f"{k}={v}" for k, v in condition.items()) or "default"


def summarize_study(out_dir, table=None) -> str:
    """Write ``summary.md`` (a Markdown table) and return it."""
    out_dir = pathlib.Path(out_dir)
    with open(out_dir / "study.toml", "rb") as handle:
        config = study_config_from_dict(tomllib.load(handle))
    table = load_results(out_dir) if table is None else table
    lines = [f"# Study `{config.name}`", "",
             f"{config.num_runs} runs per condition; P={config.filter.num_particles}, "
             f"association={config.filter.association}, boundary={config.filter.boundary}, "
             f"proposal={config.filter.proposal}.", "",
             "| setting | metric | runs | mean | median | 95% interval |",
             "|---|---|---|---|---|---|"]
    for row in summary_rows(config, table):
        lines.append(f"| {row['setting']} | {row['metric']} | {row['runs']} | "
                     f"{row['mean']:.4g} | {row['median']:.4g} | "
                     f"[{row['low']:.4g}, {row['high']:.4g}] |")
    text = "\n".join(lines) + "\n"
    _atomic_write(out_dir / "summary.md", lambda p: p.write_text(text))
    return text
