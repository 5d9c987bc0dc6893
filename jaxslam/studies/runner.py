"""The run loop: chunks of runs through one compiled program of fixed width, and ``run_study``.

Every (run, condition) pair goes through one compiled program of width ``run_width`` (per
device), so on one machine type a run's numbers are bit-identical whatever the chunk size, the
number of runs or conditions, or the device count (``_ChunkRunner``).
"""
from __future__ import annotations

import json
import pathlib
import time
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxslam import study_store
from jaxslam.simulators import RunBatch
from jaxslam.studies.chunks import load_results, open_study, write_chunk
from jaxslam.studies.scoring import _group_fn, _per_run_world, condition_params, scenario_batch
from jaxslam.studies.summary import summarize_study
from jaxslam.study_config import StudyConfig, study_config_to_dict


class StudyResult(NamedTuple):
    """out_dir: the results folder; table: pyarrow.Table of every (run, condition) row;
    compile_seconds / filter_seconds / simulator_seconds: time spent this invocation."""

    out_dir: pathlib.Path
    table: Any
    compile_seconds: float
    filter_seconds: float
    simulator_seconds: float


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
    the chunk size), the device, the arguments' shapes and dtypes, and the JAX settings that
    change its numbers (``study_store.NUMERIC_JAX_SETTINGS``: x64, XLA's optimisation)."""
    identity = {k: v for k, v in study_config_to_dict(config).items()
                if k not in study_store.RESUMABLE_KEYS}
    identity = json.dumps(identity, sort_keys=True, default=repr)
    shapes = tuple((leaf.shape, str(leaf.dtype)) for leaf in jax.tree.leaves(args))
    return (identity, str(device), shapes,
            tuple(sorted(study_store.numeric_jax_settings().items())))


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
