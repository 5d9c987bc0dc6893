"""The inputs of the study plots, validated: a run's map and paths (``example_run.npz``), the
per-run error traces (``traces/traces-*.npz``) and the study table's columns and units.

Shapes: T steps, M landmark slots, N true trees, R runs (see ``jaxslam.plots``).
"""
from __future__ import annotations

import glob
import os
from typing import Mapping, NamedTuple, Sequence

import numpy as np


class ExampleRun(NamedTuple):
    """One run's trajectories and map, validated (NumPy float64; shapes in ``jaxslam.plots``).

    tree_seen: (N,) bool or None (absent: every tree is drawn alike); smoothed_pose: (T, 3)
    or None.
    """

    truth_pose: np.ndarray
    mean_pose: np.ndarray
    landmark_mean: np.ndarray
    landmark_cov: np.ndarray
    active: np.ndarray
    tree_centres: np.ndarray
    tree_radii: np.ndarray
    tree_seen: np.ndarray | None = None
    smoothed_pose: np.ndarray | None = None


_REQUIRED_EXAMPLE = ("truth_pose", "mean_pose", "landmark_mean", "landmark_cov", "active",
                     "tree_centres", "tree_radii")


class Traces(NamedTuple):
    """Per-run error traces: run_id (R,) int, condition (R,) int, pose_error (R, T) [m]."""

    run_id: np.ndarray
    condition: np.ndarray
    pose_error: np.ndarray


def _as_mapping(source, what: str) -> Mapping:
    """A path to an .npz file, a mapping of arrays, or a NamedTuple -> a mapping of arrays."""
    if isinstance(source, (str, os.PathLike)):
        path = os.fspath(source)
        if not os.path.isfile(path):
            raise FileNotFoundError(f"{what}: no such file {path!r}; expected an .npz file")
        with np.load(path, allow_pickle=False) as npz:
            return {name: npz[name] for name in npz.files}
    if hasattr(source, "_asdict"):
        return {k: v for k, v in source._asdict().items() if v is not None}
    if isinstance(source, Mapping) or hasattr(source, "files"):
        return source
    raise TypeError(f"{what}: expected a path to an .npz file or a mapping of arrays; "
                    f"got {type(source).__name__}")


def _field(arrays: Mapping, name: str, what: str, expected: tuple, dtype=np.float64):
    if name not in arrays:
        raise ValueError(f"{what}: missing array {name!r}; expected keys {list(expected)}")
    return np.asarray(arrays[name], dtype=dtype)


def _check_shape(what: str, name: str, array: np.ndarray, expected: tuple) -> None:
    """``expected`` holds ints (exact) and strings (named free dimensions, matched by name)."""
    ok = array.ndim == len(expected)
    ok = ok and all(not isinstance(e, int) or e == s for e, s in zip(expected, array.shape))
    if not ok:
        shown = "(" + ", ".join(str(e) for e in expected) + ("," if len(expected) == 1 else "") + ")"
        raise ValueError(f"{what}: {name} has shape {array.shape}; expected {shown}")


def load_example_run(source) -> ExampleRun:
    """Read and check an example run (path to ``example_run.npz`` or a mapping of arrays).

    The optional ``tree_seen`` (N,) and ``smoothed_pose`` (T, 3) are read when present.

    Raises:
      ValueError naming the array whose key or shape is wrong and the shape expected.
    """
    arrays = _as_mapping(source, "example run")
    fields = {name: _field(arrays, name, "example run", _REQUIRED_EXAMPLE,
                           dtype=bool if name == "active" else np.float64)
              for name in _REQUIRED_EXAMPLE}
    run = ExampleRun(**fields)
    _check_shape("example run", "truth_pose", run.truth_pose, ("T+1", 3))
    _check_shape("example run", "mean_pose", run.mean_pose, ("T", 3))
    num_slots = run.landmark_mean.shape[0] if run.landmark_mean.ndim else -1
    _check_shape("example run", "landmark_mean", run.landmark_mean, ("M", 2))
    _check_shape("example run", "landmark_cov", run.landmark_cov, (num_slots, 2, 2))
    _check_shape("example run", "active", run.active, (num_slots,))
    num_trees = run.tree_centres.shape[0] if run.tree_centres.ndim else -1
    _check_shape("example run", "tree_centres", run.tree_centres, ("N", 2))
    _check_shape("example run", "tree_radii", run.tree_radii, (num_trees,))
    if arrays.get("tree_seen") is not None:
        seen = np.asarray(arrays["tree_seen"], bool)
        _check_shape("example run", "tree_seen", seen, (num_trees,))
        run = run._replace(tree_seen=seen)
    if arrays.get("smoothed_pose") is not None:
        smoothed = np.asarray(arrays["smoothed_pose"], np.float64)
        _check_shape("example run", "smoothed_pose", smoothed, (run.mean_pose.shape[0], 3))
        run = run._replace(smoothed_pose=smoothed)
    return run


def _trace_files(folder: str) -> list[str]:
    """The ``traces-*.npz`` files of a study folder: in ``traces/`` (the study layout), else
    in the folder itself (a folder of traces files)."""
    for where in (os.path.join(folder, "traces"), folder):
        files = sorted(glob.glob(os.path.join(where, "traces-*.npz")))
        if files:
            return files
    return []


def load_traces(source) -> Traces:
    """Per-run traces from a study folder (every ``traces/traces-*.npz``, sorted by run id),
    one ``.npz`` file, or a mapping of arrays.

    Raises:
      FileNotFoundError if a folder holds no traces file; ValueError for inconsistent shapes.
    """
    if isinstance(source, (str, os.PathLike)) and os.path.isdir(source):
        files = _trace_files(os.fspath(source))
        if not files:
            raise FileNotFoundError(f"{os.fspath(source)!r} holds no traces-*.npz file; "
                                    "run the study first")
        parts = [load_traces(path) for path in files]
        traces = Traces(*(np.concatenate(arrays) for arrays in zip(*parts)))
        order = np.argsort(traces.run_id, kind="stable")
        return Traces(*(array[order] for array in traces))
    arrays = _as_mapping(source, "traces")
    traces = Traces(_field(arrays, "run_id", "traces", Traces._fields, np.int64),
                    _field(arrays, "condition", "traces", Traces._fields, np.int64),
                    _field(arrays, "pose_error", "traces", Traces._fields))
    _check_shape("traces", "pose_error", traces.pose_error, ("R", "T"))
    num_runs = traces.pose_error.shape[0]
    _check_shape("traces", "run_id", traces.run_id, (num_runs,))
    _check_shape("traces", "condition", traces.condition, (num_runs,))
    return traces


def table_columns(table) -> dict[str, list]:
    """A pyarrow Table, a mapping of columns or a list of row dicts -> {name: list of values}."""
    if hasattr(table, "to_pydict"):
        return table.to_pydict()
    if isinstance(table, Mapping):
        return {name: list(np.asarray(values).tolist()) if isinstance(values, np.ndarray)
                else list(values) for name, values in table.items()}
    if isinstance(table, Sequence) and table and isinstance(table[0], Mapping):
        return {name: [row[name] for row in table] for name in table[0]}
    raise TypeError(f"expected a pyarrow.Table, a mapping of columns or a list of rows; "
                    f"got {type(table).__name__}")


def column_units(table) -> dict[str, str]:
    """{column: unit} that a pyarrow Table carries (each field's ``unit`` metadata entry);
    empty for a mapping or a list of rows."""
    schema = getattr(table, "schema", None)
    if schema is None:
        return {}
    units = {}
    for field in schema:
        unit = (field.metadata or {}).get(b"unit")
        if unit is not None:
            units[field.name] = unit.decode()
    return units
