"""Monte Carlo studies and sweeps: chunked, seeded, resumable, one compiled program per study.

A study is R runs of a simulated scenario under one ``FilterConfig``, optionally over a grid of
``Params`` values (a sweep: G conditions). The runs come from the simulator the config names
(``jaxslam.simulators``: a plugin loaded by its module name, "sims" by default) or from a
``simulate`` function passed to ``run_study``; this module imports no simulator. Run i uses
``fold_in(PRNGKey(seed), i)`` for both its scenario and its filter, so every condition sees
the same forests, paths and noise (common random numbers). Every (run, condition) pair goes
through one compiled program of fixed width ``run_width`` (per device), so on one machine
type a run's numbers are bit-identical whatever
the chunk size, the number of runs or conditions, or the device count (``_ChunkRunner``).

The results folder (layout, integrity manifest, lock, resume rules) is described in
``jaxslam.study_store``: chunks of runs in ``runs/`` (Parquet, one row per (run, condition),
units and the resolved config in the schema metadata), per-step traces in ``traces/``, a
SHA-256 manifest checked on resume, and an exclusive lock while a process computes.
``num_runs`` can grow on resume (the new runs only are computed).
"""
from __future__ import annotations

import json
import pathlib
import time
import tomllib
import warnings
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxslam import metrics, study_store
from jaxslam.columns import COLUMN_UNITS, column_unit  # noqa: F401 (public here too)
from jaxslam.filter import estimate, make_filter, scan_filter
from jaxslam.simulators import (RunBatch, Simulator, SimulatorUnavailable,  # noqa: F401
                                 load_simulator, register_simulator)
from jaxslam.study_config import (StudyConfig, demo_study_config,  # noqa: F401
                                  load_study_config, study_config_from_dict,
                                  study_config_to_dict)
from jaxslam.study_store import StudyError, foreign_files  # noqa: F401 (public here too)
from jaxslam.types import Params, default_params

SUMMARY_METRICS = ("final_pose_error", "ate_rmse", "ate_rmse_aligned", "map_error",
                   "redundant", "orphan", "num_landmarks", "gospa", "pose_nees", "diverged")


def scenario_batch(config: StudyConfig, run_ids) -> RunBatch:
    """Simulate the runs ``run_ids`` (R,) with the simulator ``config.simulator`` names.

    Raises ``SimulatorUnavailable`` (an ImportError naming the install command) when the
    simulator, or a part of it these runs need (MuJoCo for "sims" lidar scans), is missing.
    """
    return load_simulator(config.simulator).simulate(config, run_ids)


# --------------------------------------------------------------------------------------------
# Filter + metrics of one run (traced)


def condition_params(config: StudyConfig) -> Params:
    """Stacked ``Params`` of the G sweep conditions (leading axis G)."""
    base = {"max_range": config.scenario.max_range, **dict(config.params)}  # sensor range
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
    truth = world.truth_pose[1:]
    est = estimate(final)
    position_error = jnp.hypot(trace.mean_pose[:, 0] - truth[:, 0],
                               trace.mean_pose[:, 1] - truth[:, 1])
    scores = metrics.summarize(
        trace.mean_pose, truth, est.landmark_mean, est.active, world.tree_centres,
        world.tree_seen, match_threshold=config.map_match_threshold,
        gospa_cutoff=config.gospa_cutoff, divergence_threshold=config.divergence_threshold,
        landmark_cov=est.landmark_cov, final_pose_cov=est.pose_cov + 1e-9 * jnp.eye(3))
    diameter_error, num_diameters = _diameter_error(est, world, config.map_match_threshold)
    values = dict(
        scores._asdict(),
        num_trees_seen=jnp.sum(world.tree_seen).astype(jnp.int32),
        diameter_error=diameter_error,
        num_diameters=num_diameters,
        min_ess=jnp.min(trace.ess),
        num_resampled=jnp.sum(trace.resampled).astype(jnp.int32),
        num_dropped_births=jnp.sum(trace.num_dropped_births).astype(jnp.int32),
        num_weight_resets=jnp.sum(trace.weights_reset).astype(jnp.int32),
        num_invalid_controls=jnp.sum(trace.invalid_control).astype(jnp.int32),
        peak_match_rounds=jnp.max(trace.match_rounds),
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


def _group_fn(config: StudyConfig, per_run_world: bool):
    """jit(vmap over a group of (run, condition) pairs) of ``_run_metrics``.

    Arguments: keys, params (leaves with the pair axis first), controls, observations,
    tree_seen (pair axis first), then truth_pose, tree_centres, tree_radii (one world shared
    by every run, or with the pair axis first when ``per_run_world``).
    """

    def per_pair(key, params, controls, observations, seen, truth_pose, centres, radii):
        world = RunBatch(None, None, truth_pose, centres, radii, seen)
        return _run_metrics(config, key, params, controls, observations, world)

    world_axis = 0 if per_run_world else None
    return jax.jit(jax.vmap(per_pair, in_axes=(0, 0, 0, 0, 0) + (world_axis,) * 3))


def _per_run_world(scenario: RunBatch) -> bool:
    """Whether each run of the batch has its own world (truth_pose (R, T+1, 3))."""
    return np.ndim(scenario.truth_pose) == 3


# --------------------------------------------------------------------------------------------
# Columns

def run_keys(seed: int, run_ids) -> np.ndarray:
    """(R,) uint64: run i's PRNG key ``fold_in(PRNGKey(seed), i)``, its two 32-bit words as
    one number (high word first), so a row names the exact randomness it came from."""
    words = np.asarray(jax.device_get(jax.vmap(
        lambda i: jax.random.key_data(jax.random.fold_in(jax.random.PRNGKey(seed), i)))(
            jnp.asarray(run_ids, jnp.uint32))), np.uint64)
    return (words[:, 0] << np.uint64(32)) | words[:, 1]


def _sweep_columns(config: StudyConfig) -> dict:
    """Swept setting -> (G,) column; a vector field gives one column per component,
    ``name[j]``."""
    out = {}
    for name, _ in config.sweep:
        values = np.asarray([c[name] for c in config.conditions], float)
        if values.ndim == 1:
            out[name] = values
        else:
            out.update({f"{name}[{j}]": values[:, j] for j in range(values.shape[1])})
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


def _chunk_rows(config, start, stop, values) -> dict:
    """Columns of the chunk [start, stop): one row per (condition, run), conditions outer."""
    num_runs, num_conditions = stop - start, len(config.conditions)
    run_ids = np.arange(start, stop)
    rows = {"run_id": np.tile(run_ids, num_conditions),
            "condition": np.repeat(np.arange(num_conditions), num_runs),
            "study_seed": np.full(num_runs * num_conditions, config.seed),
            "run_key": np.tile(run_keys(config.seed, run_ids), num_conditions)}
    for name, column in _sweep_columns(config).items():
        rows[name] = np.repeat(column, num_runs)
    for name, value in values.items():
        rows[name] = np.asarray(value).reshape(-1)
    return rows


def _chunk_table(config, start, stop, values, seconds, num_steps: int):
    """The chunk's pyarrow Table: units per field, and in the schema metadata the units, the
    resolved study config and the chunk's timing (timing lives here, not in a per-run column:
    it is one measurement of the whole chunk). num_steps: T, the filter steps of a run."""
    import pyarrow as pa
    import tomli_w

    rows = _chunk_rows(config, start, stop, values)
    fields = [pa.field(name, pa.array(column).type, metadata={"unit": column_unit(name)})
              for name, column in rows.items()]
    pairs = (stop - start) * len(config.conditions)
    metadata = {"jaxslam.units": json.dumps({n: column_unit(n) for n in rows}),
                "jaxslam.study": tomli_w.dumps(study_config_to_dict(config)),
                "jaxslam.filter_seconds": repr(float(seconds)),
                "jaxslam.update_rate_hz": repr(pairs * num_steps / max(seconds, 1e-9))}
    return pa.table(rows, schema=pa.schema(fields, metadata=metadata))


class ChunkOutput(NamedTuple):
    """What ``_ChunkRunner`` computes for the R runs [start, stop) under G conditions.

    scenario: the RunBatch of the chunk (leaves (R, ...)); values: metric name -> (G, R)
    numpy array; errors: (G, R, T) position error per step; example: run traces and final
    map, leaves (G, R, ...); seconds: wall time of the filter calls.
    """

    scenario: RunBatch
    values: dict
    errors: Any
    example: dict
    seconds: float


_COMPILED: dict = {}  # program key -> compiled study program (oldest first)
_MAX_COMPILED = 8


def _program_key(config: StudyConfig, device, args) -> tuple:
    """What a compiled group program depends on: the config (but not the number of runs or
    the chunk size), the device, the arguments' shapes and dtypes, and x64 mode."""
    identity = {k: v for k, v in study_config_to_dict(config).items()
                if k not in study_store.RESUMABLE_KEYS}
    identity = json.dumps(identity, sort_keys=True, default=repr)
    shapes = tuple((leaf.shape, str(leaf.dtype)) for leaf in jax.tree.leaves(args))
    return identity, str(device), shapes, bool(jax.config.jax_enable_x64)


class _ChunkRunner:
    """Simulates and filters chunks of runs with one compiled program of fixed width.

    Every (run, condition) pair goes through the same compiled call of width
    W = ``config.run_width``, whatever the chunk size, the number of runs or conditions, or
    the device count: a chunk's G x R pairs are cut into groups of W (the last one padded by
    repeating its last pair; padding dropped), and the simulator, too, runs in groups of W
    runs. On a CPU a pair's numbers do not depend on its position in the group or on its
    neighbours (measured, ``tests/test_study_determinism.py``), so they depend on its run
    id, its condition and W only.

    With D > 1 local devices the groups go round-robin to the devices, each running its own
    copy of the single-device program (compiled once per device, in parallel threads). A
    program sharded over a mesh instead (``shard_map``, one compile) was measured to differ
    from the single-device one in the last bit of rpe_translation for W = 3 on 2 CPU
    devices: XLA partitions and fuses it differently.
    """

    def __init__(self, config: StudyConfig, simulate=None):
        self.config = config
        self.simulate = simulate  # None: the config's simulator (``scenario_batch``)
        self.params = condition_params(config)
        self.width = config.run_width
        self.function = None  # built at the first chunk, for its kind of world
        self.devices = jax.local_devices()
        self.compiled: dict = {}  # device -> the compiled program placed on it
        self.compile_seconds = self.filter_seconds = self.simulator_seconds = 0.0

    def _compile(self, groups_args: list) -> None:
        """Compile the program for the devices of ``groups_args`` that lack it (lowered here,
        compiled in parallel threads: XLA releases the GIL while it compiles). Programs are
        kept per process (``_COMPILED``), so resuming or growing a study in the same process
        does not compile again."""
        from concurrent.futures import ThreadPoolExecutor

        lowered = {}
        for device, args in groups_args:
            if device in self.compiled or device in lowered:
                continue
            key = _program_key(self.config, device, args)
            if key in _COMPILED:
                self.compiled[device] = _COMPILED[key]
            else:
                lowered[device] = (key, self.function.lower(*args))
        if not lowered:
            return
        tick = time.perf_counter()
        compile_one = lambda item: item[1].compile()  # noqa: E731
        if len(lowered) == 1:  # one device: no thread needed
            programs = [compile_one(item) for item in lowered.values()]
        else:
            with ThreadPoolExecutor(len(lowered)) as pool:
                programs = list(pool.map(compile_one, lowered.values()))
        for (device, (key, _)), program in zip(lowered.items(), programs):
            self.compiled[device] = _COMPILED[key] = program
        while len(_COMPILED) > _MAX_COMPILED:
            _COMPILED.pop(next(iter(_COMPILED)))
        self.compile_seconds += time.perf_counter() - tick

    def __call__(self, start: int, stop: int) -> ChunkOutput:
        config = self.config
        run_ids = np.arange(start, stop)
        num_runs, num_conditions = run_ids.size, len(config.conditions)
        tick = time.perf_counter()
        simulate = scenario_batch if self.simulate is None else self.simulate
        scenario = jax.block_until_ready(simulate(config, run_ids))
        per_run_world = _per_run_world(scenario)
        if self.function is None:
            self.function = _group_fn(config, per_run_world)
        self.simulator_seconds += time.perf_counter() - tick
        keys = jax.vmap(lambda i: jax.random.fold_in(jax.random.PRNGKey(config.seed), i))(
            jnp.asarray(run_ids, jnp.uint32))
        # Groups are gathered on the host (numpy indexing: no eager device op per group).
        per_run = jax.device_get((keys, scenario.controls, scenario.observations,
                                  scenario.tree_seen))
        params_by_condition = jax.device_get(self.params)
        world = jax.device_get((scenario.truth_pose, scenario.tree_centres,
                                scenario.tree_radii))
        # Pairs in (condition, run) order, padded to whole groups with the last pair.
        num_pairs = num_conditions * num_runs
        padded = -(-num_pairs // self.width) * self.width
        pairs = np.minimum(np.arange(padded), num_pairs - 1)
        groups_args = []
        for index, first in enumerate(range(0, padded, self.width)):
            group = pairs[first:first + self.width]
            runs, conditions = group % num_runs, group // num_runs
            per_pair = jax.tree.map(lambda x: x[runs], per_run)
            params = jax.tree.map(lambda x: x[conditions], params_by_condition)
            device = self.devices[index % len(self.devices)]
            pair_world = jax.tree.map(lambda x: x[runs], world) if per_run_world else world
            args = jax.device_put((*per_pair[:1], params, *per_pair[1:], *pair_world), device)
            groups_args.append((device, args))
        self._compile(groups_args)
        tick = time.perf_counter()
        outputs = [self.compiled[device](*args) for device, args in groups_args]  # async
        outputs = jax.device_get(outputs)
        seconds = time.perf_counter() - tick
        self.filter_seconds += seconds

        def unpair(*groups):
            flat = np.concatenate(groups)[:num_pairs]
            return flat.reshape((num_conditions, num_runs) + flat.shape[1:])

        values, errors, example = jax.tree.map(unpair, *outputs)
        return ChunkOutput(scenario, values, errors, example, seconds)


def recompute_runs(config: StudyConfig, start: int, stop: int,
                   simulate=None) -> ChunkOutput:
    """Simulate and filter the runs [start, stop) of a study again, under every condition.

    The numbers equal the stored ones bit for bit (same run keys, same compiled width, the
    same simulator: ``simulate`` as in ``run_study``), so a run's full trajectory and map can
    be recovered without storing every run's.
    """
    return _ChunkRunner(config, simulate)(start, stop)


def open_study(config: StudyConfig, out_dir) -> list[tuple[int, int]]:
    """Create or check ``out_dir`` for ``config``, verify its finished chunks, warn about
    foreign files, and return the run ranges [start, stop) still to compute.

    Raises StudyError for a different study in the folder, before anything is computed or
    written. Chunks that fail verification are moved aside and recomputed
    (``study_store.finished_chunks``). The caller holds ``study_store.study_lock(out_dir)``.
    Every backend starts here, so chunk names and resume rules are shared.
    """
    out_dir = pathlib.Path(out_dir)
    study_store.prepare_out_dir(study_config_to_dict(config), out_dir)
    strangers = foreign_files(out_dir)
    if strangers:
        warnings.warn(f"{out_dir} holds files this study did not write (left untouched): "
                      f"{strangers}")
    done = study_store.finished_chunks(out_dir, config.num_runs)
    return study_store.pending_chunks(done, config.num_runs, config.chunk_size)


def write_chunk(out_dir, config: StudyConfig, start: int, stop: int,
                output: ChunkOutput) -> list[pathlib.Path]:
    """Write the files of the finished runs [start, stop): traces, the example run (the chunk
    holding run 0 only), then the chunk file, each atomically. Returns their paths, for the
    lock holder to record in the manifest (``study_store.record_files``); until then the
    chunk does not count as done."""
    import pyarrow.parquet as pq

    out_dir = pathlib.Path(out_dir)
    errors = np.asarray(output.errors)
    table = _chunk_table(config, start, stop, output.values, output.seconds, errors.shape[-1])
    traces = study_store.traces_path(out_dir, start, stop)
    study_store.atomic_write(traces, lambda p: _save_npz(
        p, run_id=table.column("run_id").to_numpy(),
        condition=table.column("condition").to_numpy(),
        pose_error=errors.reshape(-1, errors.shape[-1])))
    written = [traces]
    if start == 0:
        written.append(_write_example(out_dir, output.scenario, output.example))
    chunk = study_store.chunk_path(out_dir, start, stop)
    study_store.atomic_write(chunk, lambda p: pq.write_table(table, p))
    return written + [chunk]


def run_study(config: StudyConfig, out_dir, progress: bool = True,
              simulate=None) -> StudyResult:
    """Run (or resume) a study; see ``jaxslam.study_store`` for what lands in ``out_dir``.

    simulate: (config, run_ids (R,)) -> ``RunBatch``, the runs' inputs and truth; None (the
    default) uses the simulator the config names (``config.simulator``, loaded by name from
    the registry of ``jaxslam.simulators.register_simulator``). Run i must draw from
    ``fold_in(PRNGKey(config.seed), i)`` alone (``Simulator``) for chunks to resume.
    """
    from tqdm.auto import tqdm

    out_dir = pathlib.Path(out_dir)
    runner = _ChunkRunner(config, simulate)  # anything it refuses is refused before a file is written
    with study_store.study_lock(out_dir):
        pending = open_study(config, out_dir)
        bar = tqdm(pending, desc=f"study {config.name}", unit="chunk", disable=not progress)
        for start, stop in bar:
            study_store.record_files(out_dir, write_chunk(out_dir, config, start, stop,
                                                          runner(start, stop)))
            bar.set_postfix(runs=stop, filter_s=f"{runner.filter_seconds:.1f}")
        table = load_results(out_dir)
        summarize_study(out_dir, table)
    return StudyResult(out_dir, table, runner.compile_seconds, runner.filter_seconds,
                       runner.simulator_seconds)


def _save_npz(path: pathlib.Path, **arrays) -> None:
    with open(path, "wb") as handle:
        np.savez(handle, **arrays)


def run_world_of(scenario: RunBatch, index: int) -> tuple:
    """(truth_pose (T+1, 3), tree_centres (N, 2), tree_radii (N,)) of run ``index`` of a
    chunk's RunBatch: the shared world, or that run's own (leaves (R, ...))."""
    arrays = [np.asarray(x) for x in (scenario.truth_pose, scenario.tree_centres,
                                      scenario.tree_radii)]
    return tuple(a[index] for a in arrays) if arrays[0].ndim == 3 else tuple(arrays)


def _write_example(out_dir: pathlib.Path, scenario, example) -> pathlib.Path:
    first = {name: np.asarray(value)[0, 0] for name, value in example.items()}
    truth_pose, centres, radii = run_world_of(scenario, 0)
    path = out_dir / "example_run.npz"
    study_store.atomic_write(path, lambda p: _save_npz(
        p, truth_pose=truth_pose, tree_centres=centres, tree_radii=radii,
        tree_seen=np.asarray(scenario.tree_seen[0]), **first))
    return path


def load_results(out_dir):
    """All finished chunks of a study (``out_dir/runs``) as one pyarrow.Table, sorted by
    (condition, run_id)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    paths = sorted((pathlib.Path(out_dir) / study_store.RUNS_DIR).glob("chunk-*.parquet"))
    if not paths:
        raise StudyError(f"no result chunks in {pathlib.Path(out_dir) / study_store.RUNS_DIR}")
    tables = [pq.read_table(p) for p in paths]
    table = pa.concat_tables([t.replace_schema_metadata(tables[0].schema.metadata)
                              for t in tables])
    return table.sort_by([("condition", "ascending"), ("run_id", "ascending")])


def filter_throughput(out_dir) -> float:
    """Run-steps per second of the filter over the study's chunks (from their metadata)."""
    import pyarrow.parquet as pq

    steps = seconds = 0.0
    for path in sorted((pathlib.Path(out_dir) / study_store.RUNS_DIR).glob("chunk-*.parquet")):
        metadata = pq.read_schema(path).metadata or {}
        chunk_seconds = float(metadata.get(b"jaxslam.filter_seconds", b"nan"))
        seconds += chunk_seconds
        steps += float(metadata.get(b"jaxslam.update_rate_hz", b"nan")) * chunk_seconds
    return steps / seconds if seconds > 0 else float("nan")


def _mean_interval(values: np.ndarray) -> tuple[float, float]:
    """95% confidence interval of the mean: mean -/+ t_{0.975, n-1} s / sqrt(n) (Student t;
    NaN for fewer than 2 runs). It says how well the runs pin the mean, not their spread."""
    from scipy import stats

    n = len(values)
    if n < 2:
        return float("nan"), float("nan")
    half = stats.t.ppf(0.975, n - 1) * np.std(values, ddof=1) / np.sqrt(n)
    return float(np.mean(values) - half), float(np.mean(values) + half)


def summary_rows(config: StudyConfig, table) -> list[dict]:
    """Per condition and metric: unit, runs, mean with its 95% confidence interval, median,
    and the 2.5 and 97.5 percentiles of the runs."""
    rows = []
    columns = {name: table.column(name).to_numpy() for name in table.column_names}
    for index, condition in enumerate(config.conditions):
        mask = columns["condition"] == index
        for name in SUMMARY_METRICS:
            if name not in columns:
                continue
            values = columns[name][mask].astype(float)
            ci_low, ci_high = _mean_interval(values)
            rows.append(dict(condition=index, setting=_setting_label(condition), metric=name,
                             unit=column_unit(name), runs=int(mask.sum()),
                             mean=float(np.mean(values)), ci_low=ci_low, ci_high=ci_high,
                             median=float(np.median(values)),
                             p2_5=float(np.percentile(values, 2.5)),
                             p97_5=float(np.percentile(values, 97.5))))
    return rows


def _setting_label(condition: dict) -> str:
    return ", ".join(f"{k}={v}" for k, v in condition.items()) or "default"


def summarize_study(out_dir, table=None) -> str:
    """Write ``summary.md`` (a Markdown table with units) and the same rows as
    ``summary.json`` (for scripts), and return the Markdown."""
    out_dir = pathlib.Path(out_dir)
    with open(out_dir / "study.toml", "rb") as handle:
        config = study_config_from_dict(tomllib.load(handle))
    table = load_results(out_dir) if table is None else table
    lines = [f"# Study `{config.name}`", "",
             f"{config.num_runs} runs per condition; P={config.filter.num_particles}, "
             f"association={config.filter.association}, boundary={config.filter.boundary}, "
             f"proposal={config.filter.proposal}; filter throughput "
             f"{filter_throughput(out_dir):,.0f} run-steps/s.", "",
             "| setting | metric | unit | runs | mean | mean 95% CI | median | "
             "runs 2.5% | runs 97.5% |",
             "|---|---|---|---|---|---|---|---|---|"]
    for row in summary_rows(config, table):
        lines.append(f"| {row['setting']} | {row['metric']} | {row['unit']} | {row['runs']} | "
                     f"{row['mean']:.4g} | [{row['ci_low']:.4g}, {row['ci_high']:.4g}] | "
                     f"{row['median']:.4g} | {row['p2_5']:.4g} | {row['p97_5']:.4g} |")
    lines += ["", "mean 95% CI: Student-t confidence interval of the mean over runs; runs "
              "2.5% / 97.5%: percentiles of the runs themselves (their spread). pose_nees of "
              "a consistent filter averages 3 (chi-square, 3 degrees of freedom); far above "
              "means overconfident. Every metric is defined in docs/metrics.md."]
    text = "\n".join(lines) + "\n"
    study_store.atomic_write(out_dir / "summary.md", lambda p: p.write_text(text))
    rows = json.dumps({"study": config.name, "rows": summary_rows(config, table)}, indent=1)
    study_store.atomic_write(out_dir / "summary.json", lambda p: p.write_text(rows + "\n"))
    return text
