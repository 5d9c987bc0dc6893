"""A chunk of runs on disk: its columns (one row per (run, condition)), its files, and the
finished chunks read back as one table. Layout and resume rules: ``jaxslam.study_store``.
"""
from __future__ import annotations

import json
import pathlib
import warnings
from typing import TYPE_CHECKING

import jax
import jax.numpy as jnp
import numpy as np

from jaxslam import study_store
from jaxslam.columns import column_unit
from jaxslam.simulators import RunBatch
from jaxslam.study_config import StudyConfig, study_config_to_dict
from jaxslam.study_store import StudyError, foreign_files

if TYPE_CHECKING:
    from jaxslam.studies.runner import ChunkOutput


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
    (condition, run_id).

    A chunk written by an earlier version may lack a column that later chunks have (a metric
    added since, such as ``num_window_cut_steps``): its rows hold null there (NaN in
    ``to_numpy()``), never a guessed value, and a warning names the columns and how many
    chunks lack them. Moving such a chunk and its traces file out of the folder lets a resume
    compute it again. Raises StudyError when a column's type differs between chunks.
    """
    import pyarrow as pa
    import pyarrow.parquet as pq

    paths = sorted((pathlib.Path(out_dir) / study_store.RUNS_DIR).glob("chunk-*.parquet"))
    if not paths:
        raise StudyError(f"no result chunks in {pathlib.Path(out_dir) / study_store.RUNS_DIR}")
    tables = [pq.read_table(p) for p in paths]
    _warn_missing_columns(out_dir, paths, tables)
    try:
        table = pa.concat_tables([t.replace_schema_metadata(tables[0].schema.metadata)
                                  for t in tables], promote_options="default")
    except pa.ArrowTypeError as error:
        raise StudyError(f"{pathlib.Path(out_dir)}: the chunks in runs/ store a column with "
                         f"different types ({error}); move the chunks of one version (and "
                         "their traces files) out of the folder to recompute them") from None
    return table.sort_by([("condition", "ascending"), ("run_id", "ascending")])


def _warn_missing_columns(out_dir, paths: list, tables: list) -> None:
    """Warn once for each set of columns that some chunks lack, with the count and the first
    and last such chunk."""
    every_column = set().union(*(t.column_names for t in tables))
    lacking: dict = {}
    for path, table in zip(paths, tables):
        missing = tuple(sorted(every_column - set(table.column_names)))
        if missing:
            lacking.setdefault(missing, []).append(path.name)
    for missing, names in lacking.items():
        which = names[0] if len(names) == 1 else f"{names[0]} ... {names[-1]}"
        warnings.warn(f"{pathlib.Path(out_dir)}: {len(names)} of {len(paths)} chunks ({which}) "
                      f"were written without {', '.join(missing)}, which are null in their "
                      "rows; move those chunks and their traces files out of the folder to "
                      "compute them again with these columns")
