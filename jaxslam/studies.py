"""Monte Carlo studies and sweeps: chunked, seeded, resumable, one compiled program per study.

A study is R runs of a simulated scenario under one ``FilterConfig``, optionally over a grid of
``Params`` values (a sweep: G conditions). Run i uses ``fold_in(PRNGKey(seed), i)`` for both
its scenario and its filter, so every condition sees the same forests, paths and noise (common
random numbers). Every (run, condition) pair goes through one compiled program of fixed width
``run_width`` (per device), so on one machine type a run's numbers are bit-identical whatever
the chunk size, the number of runs or conditions, or the device count (``_ChunkRunner``).

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

import datetime
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
from jaxslam.study_config import (RunBatch, ScenarioConfig, StudyConfig,  # noqa: F401
                                  demo_study_config, load_study_config,
                                  study_config_from_dict, study_config_to_dict)
from jaxslam.types import Params, default_params

_CHUNK_PREFIX = "chunk-"
_KNOWN_FILES = {"study.toml", "provenance.toml", "summary.md", "example_run.npz"}
SUMMARY_METRICS = ("final_pose_error", "ate_rmse", "ate_rmse_aligned", "map_error",
                   "redundant", "orphan", "num_landmarks", "gospa", "pose_nees", "diverged",
                   "update_rate_hz")


class StudyError(RuntimeError):
    """A study cannot run or resume safely (foreign study in the folder, corrupt chunk...)."""


def scenario_batch(config: StudyConfig, run_ids):
    """Simulate the runs ``run_ids`` (``sims.batch.scenario_batch``; imports MuJoCo lazily)."""
    from sims.batch import scenario_batch as simulate

    return simulate(config, run_ids)


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


def _group_fn(config: StudyConfig):
    """jit(vmap over a group of (run, condition) pairs) of ``_run_metrics``.

    Arguments: keys, params (leaves with the pair axis first), controls, observations,
    tree_seen (pair axis first), then truth_pose, tree_centres, tree_radii (shared by every
    run of a study).
    """

    def per_pair(key, params, controls, observations, seen, truth_pose, centres, radii):
        world = RunBatch(None, None, truth_pose, centres, radii, seen)
        return _run_metrics(config, key, params, controls, observations, world)

    return jax.jit(jax.vmap(per_pair, in_axes=(0, 0, 0, 0, 0, None, None, None)))


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


def _flatten(data: dict, prefix: str = "") -> dict:
    out = {}
    for key, value in data.items():
        if isinstance(value, dict):
            out.update(_flatten(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value
    return out


def _config_differences(old: dict, new: dict) -> list[str]:
    """"key: folder X, this config Y" for every key whose value differs."""
    old, new = _flatten(old), _flatten(new)
    lines = []
    for key in sorted(set(old) | set(new)):
        if old.get(key, _MISSING) != new.get(key, _MISSING):
            show = lambda v: "(absent)" if v is _MISSING else repr(v)  # noqa: E731
            lines.append(f"{key}: folder {show(old.get(key, _MISSING))}, "
                         f"this config {show(new.get(key, _MISSING))}")
    return lines


_MISSING = object()


def _prepare_out_dir(config: StudyConfig, out_dir: pathlib.Path) -> None:
    """Create or check the folder: a different study there is an error, never overwritten.

    ``config`` has been validated when it was built (``StudyConfig`` refuses a bad value),
    so study.toml is only ever written for a config that can run.
    """
    import tomli_w

    resolved_dict = study_config_to_dict(config)
    resolved = tomli_w.dumps(resolved_dict)
    study_file = out_dir / "study.toml"
    if study_file.exists():
        text = study_file.read_text()
        if text != resolved:
            try:
                differences = _config_differences(tomllib.loads(text), resolved_dict)
            except tomllib.TOMLDecodeError as error:
                differences = [f"(the folder's study.toml is not readable TOML: {error})"]
            if differences:
                raise StudyError(_refusal(out_dir, study_file, differences))
    out_dir.mkdir(parents=True, exist_ok=True)
    if not study_file.exists():
        _atomic_write(study_file, lambda p: p.write_text(resolved))
    for stale in out_dir.glob(".tmp-*"):
        stale.unlink()  # our own half-written file from an interrupted run
    _atomic_write(out_dir / "provenance.toml",
                  lambda p: p.write_text(tomli_w.dumps(_provenance())))


def _refusal(out_dir: pathlib.Path, study_file: pathlib.Path, differences: list[str]) -> str:
    chunks = sorted(out_dir.glob(f"{_CHUNK_PREFIX}*.parquet"))
    if chunks:
        start_over = (f"it holds {len(chunks)} finished chunk(s) of that study: resume it with "
                      f"the config in {study_file}, or choose another output folder (to start "
                      f"over here, delete {out_dir} first)")
    else:
        start_over = (f"it holds no finished chunk yet: delete {study_file} to start this "
                      "study over here, or choose another output folder")
    return (f"{study_file} holds a different study config; resume only the same study. "
            f"Keys that differ:\n  " + "\n  ".join(differences) + f"\n{start_over}")


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


def _chunk_rows(config, start, stop, values, seconds) -> dict:
    num_runs = stop - start
    conditions = config.conditions
    rows = {"run_id": np.tile(np.arange(start, stop), len(conditions)),
            "condition": np.repeat(np.arange(len(conditions)), num_runs),
            "seed": np.full(num_runs * len(conditions), config.seed)}
    for name, _ in config.sweep:
        rows[name] = np.repeat([c[name] for c in conditions], num_runs).astype(float)
    for name, value in values.items():
        rows[name] = np.asarray(value).reshape(-1)
    rate = num_runs * len(conditions) * config.scenario.num_steps / max(seconds, 1e-9)
    rows["update_rate_hz"] = np.full(num_runs * len(conditions), rate)
    return rows


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

    def __init__(self, config: StudyConfig):
        self.config = config
        self.params = condition_params(config)
        self.width = config.run_width
        self.function = _group_fn(config)
        self.devices = jax.local_devices()
        self.compiled: dict = {}  # device -> the compiled program placed on it
        self.compile_seconds = self.filter_seconds = self.simulator_seconds = 0.0

    def _compile(self, groups_args: list) -> None:
        """Compile the program for the devices of ``groups_args`` that lack it (lowered here,
        compiled in parallel threads: XLA releases the GIL while it compiles)."""
        from concurrent.futures import ThreadPoolExecutor

        lowered = {}
        for device, args in groups_args:
            if device not in self.compiled and device not in lowered:
                lowered[device] = self.function.lower(*args)
        if not lowered:
            return
        tick = time.perf_counter()
        if len(lowered) == 1:  # one device: no thread needed
            self.compiled.update({device: low.compile() for device, low in lowered.items()})
        else:
            with ThreadPoolExecutor(len(lowered)) as pool:
                self.compiled.update(zip(lowered, pool.map(lambda low: low.compile(),
                                                           lowered.values())))
        self.compile_seconds += time.perf_counter() - tick

    def __call__(self, start: int, stop: int) -> ChunkOutput:
        config = self.config
        run_ids = np.arange(start, stop)
        num_runs, num_conditions = run_ids.size, len(config.conditions)
        tick = time.perf_counter()
        scenario = jax.block_until_ready(scenario_batch(config, run_ids))
        self.simulator_seconds += time.perf_counter() - tick
        keys = jax.vmap(lambda i: jax.random.fold_in(jax.random.PRNGKey(config.seed), i))(
            jnp.asarray(run_ids, jnp.uint32))
        # Groups are gathered on the host (numpy indexing: no eager device op per group).
        per_run = jax.device_get((keys, scenario.controls, scenario.observations,
                                  scenario.tree_seen))
        params_by_condition = jax.device_get(self.params)
        shared = jax.device_get((scenario.truth_pose, scenario.tree_centres,
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
            args = jax.device_put((*per_pair[:1], params, *per_pair[1:], *shared), device)
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


def recompute_runs(config: StudyConfig, start: int, stop: int) -> ChunkOutput:
    """Simulate and filter the runs [start, stop) of a study again, under every condition.

    The numbers equal the stored ones bit for bit (same run keys, same compiled width),
    so a run's full trajectory and map can be recovered without storing every run's.
    """
    return _ChunkRunner(config)(start, stop)


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
    np_errors = errors.reshape(-1, errors.shape[-1])
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
    runner = _ChunkRunner(config)  # anything it refuses is refused before a file is written
    pending = open_study(config, out_dir)
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
