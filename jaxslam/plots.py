"""Study plots (matplotlib, Agg backend, PNG): the map, error against time, sweep box plots.

Host-side NumPy only; matplotlib and pyarrow are imported inside the functions so that
``import jaxslam.plots`` stays cheap (the ``jaxslam`` command imports it lazily too).

Shapes (glossary in ``jaxslam.types``): T steps, M landmark slots, N true trees, R runs.
Inputs come from the files a study writes (``jaxslam.studies``):
  ``example_run.npz``: truth_pose (T+1, 3), mean_pose (T, 3), landmark_mean (M, 2),
    landmark_cov (M, 2, 2), active (M,), tree_centres (N, 2), tree_radii (N,).
  ``traces-*.npz``: run_id (R,), condition (R,), pose_error (R, T).
  ``chunk-*.parquet``: one row per run: run_id, condition, swept parameters, metrics.
"""
from __future__ import annotations

import glob
import os
from typing import Mapping, NamedTuple, Sequence

import numpy as np

# Columns of a study table that are never swept parameters.
_NON_PARAMETER_COLUMNS = frozenset({
    "run_id", "condition", "seed", "chunk", "final_pose_error", "final_heading_error",
    "ate_rmse", "ate_rmse_aligned", "rpe_translation", "rpe_rotation", "map_error",
    "redundant", "orphan", "num_landmarks", "num_trees_mapped", "pose_nees", "map_nees",
    "gospa", "gospa_localisation", "gospa_missed", "gospa_false", "diverged",
    "update_rate_hz", "wall_time_s",
})
# Plot units of the common metrics (for axis labels).
METRIC_UNITS = {
    "final_pose_error": "m", "final_heading_error": "rad", "ate_rmse": "m",
    "ate_rmse_aligned": "m", "rpe_translation": "m", "rpe_rotation": "rad", "map_error": "m",
    "redundant": "count", "orphan": "count", "num_landmarks": "count",
    "num_trees_mapped": "count", "pose_nees": "-", "map_nees": "-", "gospa": "m",
    "diverged": "fraction", "update_rate_hz": "Hz",
}
SIGMA_SCALE = 2.0  # ellipses are drawn at 2 standard deviations along each principal axis


class ExampleRun(NamedTuple):
    """One run's trajectories and map, validated (NumPy float64; see module docstring)."""

    truth_pose: np.ndarray
    mean_pose: np.ndarray
    landmark_mean: np.ndarray
    landmark_cov: np.ndarray
    active: np.ndarray
    tree_centres: np.ndarray
    tree_radii: np.ndarray


class Traces(NamedTuple):
    """Per-run error traces: run_id (R,) int, condition (R,) int, pose_error (R, T) [m]."""

    run_id: np.ndarray
    condition: np.ndarray
    pose_error: np.ndarray


# ------------------------------------------------------------------------------------------
# Input handling


def _as_mapping(source, what: str) -> Mapping:
    """A path to an .npz file, a mapping of arrays, or a NamedTuple -> a mapping of arrays."""
    if isinstance(source, (str, os.PathLike)):
        path = os.fspath(source)
        if not os.path.isfile(path):
            raise FileNotFoundError(f"{what}: no such file {path!r}; expected an .npz file")
        with np.load(path, allow_pickle=False) as npz:
            return {name: npz[name] for name in npz.files}
    if hasattr(source, "_asdict"):
        return source._asdict()
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

    Raises:
      ValueError naming the array whose key or shape is wrong and the shape expected.
    """
    arrays = _as_mapping(source, "example run")
    run = ExampleRun(**{name: _field(arrays, name, "example run", ExampleRun._fields,
                                     dtype=bool if name == "active" else np.float64)
                        for name in ExampleRun._fields})
    _check_shape("example run", "truth_pose", run.truth_pose, ("T+1", 3))
    _check_shape("example run", "mean_pose", run.mean_pose, ("T", 3))
    num_slots = run.landmark_mean.shape[0] if run.landmark_mean.ndim else -1
    _check_shape("example run", "landmark_mean", run.landmark_mean, ("M", 2))
    _check_shape("example run", "landmark_cov", run.landmark_cov, (num_slots, 2, 2))
    _check_shape("example run", "active", run.active, (num_slots,))
    num_trees = run.tree_centres.shape[0] if run.tree_centres.ndim else -1
    _check_shape("example run", "tree_centres", run.tree_centres, ("N", 2))
    _check_shape("example run", "tree_radii", run.tree_radii, (num_trees,))
    return run


def load_traces(source) -> Traces:
    """Per-run traces from a study folder (every ``traces-*.npz``, sorted by run id), one
    ``.npz`` file, or a mapping of arrays.

    Raises:
      FileNotFoundError if a folder holds no traces file; ValueError for inconsistent shapes.
    """
    if isinstance(source, (str, os.PathLike)) and os.path.isdir(source):
        files = sorted(glob.glob(os.path.join(os.fspath(source), "traces-*.npz")))
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


def format_value(value) -> str:
    """Compact text for a parameter value: 0.05, 100, (0.005, 0)."""
    if isinstance(value, (list, tuple, np.ndarray)):
        return "(" + ", ".join(format_value(v) for v in np.asarray(value).ravel()) + ")"
    if isinstance(value, (float, np.floating)):
        return f"{float(value):.4g}"
    return str(value)


def _hashable(value):
    return tuple(np.asarray(value).ravel().tolist()) if isinstance(
        value, (list, tuple, np.ndarray)) else value


def swept_columns(columns: Mapping[str, list]) -> list[str]:
    """Parameter columns that differ between conditions (constant within each condition)."""
    if "condition" not in columns:
        return []
    condition = columns["condition"]
    swept = []
    for name, values in columns.items():
        if name in _NON_PARAMETER_COLUMNS or len(values) != len(condition):
            continue
        by_condition: dict = {}
        for cond, value in zip(condition, values):
            by_condition.setdefault(cond, set()).add(_hashable(value))
        constant_within = all(len(seen) == 1 for seen in by_condition.values())
        varies = len({next(iter(seen)) for seen in by_condition.values()}) > 1
        if constant_within and varies:
            swept.append(name)
    return swept


def condition_labels(table, columns_to_show: Sequence[str] | None = None) -> dict[int, str]:
    """{condition: "name=value, ..."} from a study table (swept columns by default)."""
    columns = table_columns(table)
    if "condition" not in columns:
        raise ValueError(f"the table has no 'condition' column; columns: {sorted(columns)}")
    names = list(columns_to_show) if columns_to_show is not None else swept_columns(columns)
    single = len(set(columns["condition"])) == 1
    labels: dict[int, str] = {}
    for row, cond in enumerate(columns["condition"]):
        if int(cond) not in labels:
            parts = [f"{name}={format_value(columns[name][row])}" for name in names]
            fallback = "all runs" if single else f"condition {int(cond)}"
            labels[int(cond)] = ", ".join(parts) if parts else fallback
    return labels


# ------------------------------------------------------------------------------------------
# Geometry


def covariance_ellipses(cov, scale: float = SIGMA_SCALE):
    """Axis lengths and orientation of ``scale``-sigma ellipses of 2x2 covariances.

    cov: (M, 2, 2) symmetric. Returns (width (M,), height (M,), angle_deg (M,)): full axis
    lengths ``2 * scale * sqrt(eigenvalue)`` (major first) and the major axis angle from +x.
    """
    cov = np.asarray(cov, np.float64)
    cov = 0.5 * (cov + np.swapaxes(cov, -1, -2))
    eigenvalues, eigenvectors = np.linalg.eigh(cov)  # ascending
    eigenvalues = np.clip(eigenvalues, 0.0, None)
    major = eigenvectors[..., :, 1]
    angle = np.degrees(np.arctan2(major[..., 1], major[..., 0]))
    return (2.0 * scale * np.sqrt(eigenvalues[..., 1]),
            2.0 * scale * np.sqrt(eigenvalues[..., 0]), angle)


# ------------------------------------------------------------------------------------------
# Figures


def _pyplot():
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


def _save(fig, out_png) -> str:
    path = os.fspath(out_png)
    folder = os.path.dirname(path)
    if folder:
        os.makedirs(folder, exist_ok=True)
    fig.savefig(path, dpi=120, bbox_inches="tight")
    _pyplot().close(fig)
    return path


def plot_map(example, out_png, title: str = "Map: true trunks and estimated landmarks") -> str:
    """The map of one run: true trunks (circles of their radius, with a marker so thin trunks
    show; grey when the optional ``tree_seen`` (N,) mask says the run never saw them), active estimated landmarks with 2-sigma ellipses, the true and estimated paths.

    Args:
      example: path to ``example_run.npz`` or a mapping of its arrays (see ``ExampleRun``).
      out_png: output path.
    Returns:
      the PNG path.
    """
    from matplotlib.collections import EllipseCollection, PatchCollection
    from matplotlib.patches import Circle

    run = load_example_run(example)
    seen = _tree_seen(example, len(run.tree_radii))
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(8, 8))
    for mask, colour, label in ((seen, "saddlebrown", "true trunk, observed"),
                                (~seen, "darkgray", "true trunk, never in range")):
        if not mask.any() and label.endswith("range"):
            continue
        centres, radii = run.tree_centres[mask], run.tree_radii[mask]
        ax.add_collection(PatchCollection([Circle(tuple(c), r) for c, r in zip(centres, radii)],
                                          facecolor=colour, edgecolor="none", alpha=0.6))
        ax.scatter(centres[:, 0], centres[:, 1], s=14, marker="o", facecolor="none",
                   edgecolor=colour, linewidth=1.0, label=f"{label} ({int(mask.sum())})")
    mean, cov = run.landmark_mean[run.active], run.landmark_cov[run.active]
    if len(mean):
        width, height, angle = covariance_ellipses(cov)
        ax.add_collection(EllipseCollection(
            width, height, angle, units="xy", offsets=mean, offset_transform=ax.transData,
            facecolor="none", edgecolor="tab:blue", linewidth=1.0))
    ax.scatter(mean[:, 0], mean[:, 1], s=18, marker="+", color="tab:blue",
               label=f"estimated landmark ({len(mean)}), {SIGMA_SCALE:g}-sigma ellipse")
    ax.plot(run.truth_pose[:, 0], run.truth_pose[:, 1], color="black", linewidth=1.8,
            label="true path")
    ax.plot(run.mean_pose[:, 0], run.mean_pose[:, 1], color="tab:red", linewidth=1.4,
            linestyle="--", label="estimated path (weighted mean)")
    ax.plot(*run.truth_pose[0, :2], marker="s", color="black", markersize=7, linestyle="none",
            label="start")
    ax.set_aspect("equal", adjustable="datalim")
    ax.autoscale_view()
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(title)
    ax.grid(True, alpha=0.3)
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=9, framealpha=0.9)
    return _save(fig, out_png)


def _tree_seen(example, num_trees: int) -> np.ndarray:
    """The optional (N,) ``tree_seen`` mask of an example run (all True when absent)."""
    arrays = _as_mapping(example, "example run")
    if "tree_seen" not in arrays:
        return np.ones(num_trees, bool)
    seen = np.asarray(arrays["tree_seen"], bool)
    _check_shape("example run", "tree_seen", seen, (num_trees,))
    return seen


def plot_error_vs_time(traces, out_png, labels: Mapping[int, str] | None = None,
                       title: str = "Position error over time") -> str:
    """Median position error against step with a 5-95 % band across runs, per condition.

    Args:
      traces: a study folder, a ``traces-*.npz`` path or a mapping with run_id (R,),
        condition (R,), pose_error (R, T) [m].
      out_png: output path.
      labels: {condition: legend text}, e.g. from ``condition_labels(table)``.
    Returns:
      the PNG path.
    """
    data = load_traces(traces)
    if data.pose_error.shape[0] == 0:
        raise ValueError("traces: pose_error has no runs (R = 0); expected at least one")
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(9, 5))
    steps = np.arange(1, data.pose_error.shape[1] + 1)
    conditions = np.unique(data.condition)
    colours = plt.get_cmap("tab10" if len(conditions) <= 10 else "viridis")
    for index, cond in enumerate(conditions):
        errors = data.pose_error[data.condition == cond]
        low, median, high = np.nanpercentile(errors, [5.0, 50.0, 95.0], axis=0)
        colour = colours(index if len(conditions) <= 10 else index / max(len(conditions) - 1, 1))
        name = (labels or {}).get(int(cond), f"condition {int(cond)}")
        ax.fill_between(steps, low, high, color=colour, alpha=0.2, linewidth=0)
        ax.plot(steps, median, color=colour, linewidth=1.8,
                label=f"{name}  (median, 5-95 % band, {errors.shape[0]} runs)")
    ax.set_xlabel("time step")
    ax.set_ylabel("position error [m]")
    ax.set_xlim(steps[0], steps[-1])
    ax.set_ylim(bottom=0.0)
    ax.set_title(title)
    ax.grid(True, alpha=0.3)
    ax.legend(loc="upper left", fontsize=9, framealpha=0.9)
    return _save(fig, out_png)


def plot_sweep_boxes(table, metric: str, out_png, sweep: Sequence[str] | None = None,
                     title: str | None = None) -> str:
    """Box plots of one metric across sweep conditions, labelled by the swept values.

    Args:
      table: the study table (pyarrow.Table, mapping of columns or list of rows) with a
        ``condition`` column and the metric column.
      metric: the metric column, e.g. "final_pose_error".
      out_png: output path.
      sweep: the swept parameter columns to label with (default: inferred, ``swept_columns``).
    Returns:
      the PNG path.
    """
    columns = table_columns(table)
    for name in ("condition", metric):
        if name not in columns:
            raise ValueError(f"the table has no {name!r} column; available: {sorted(columns)}")
    sweep = list(sweep) if sweep is not None else swept_columns(columns)
    labels = condition_labels(columns, sweep)
    condition = np.asarray(columns["condition"], np.int64)
    values = np.asarray([np.nan if v is None else v for v in columns[metric]], np.float64)
    conditions = np.unique(condition)
    groups = [values[(condition == c) & np.isfinite(values)] for c in conditions]
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(max(6.0, 1.3 * len(conditions) + 2.0), 5))
    ax.boxplot(groups, whis=(5, 95), showmeans=True, widths=0.6)
    tick_labels = [labels[int(c)].replace(", ", "\n") + f"\n(n={len(g)})"
                   for c, g in zip(conditions, groups)]
    ax.set_xticks(np.arange(1, len(conditions) + 1), tick_labels, fontsize=9,
                  rotation=0 if len(conditions) <= 6 else 45)
    unit = METRIC_UNITS.get(metric)
    ax.set_ylabel(f"{metric.replace('_', ' ')}" + (f" [{unit}]" if unit else ""))
    ax.set_xlabel("sweep condition" + (f" ({', '.join(sweep)})" if sweep else ""))
    ax.set_title(title or f"{metric.replace('_', ' ')} across sweep conditions\n"
                          "box: quartiles, line: median, triangle: mean, whiskers: 5-95 %",
                 fontsize=11)
    ax.grid(True, axis="y", alpha=0.3)
    return _save(fig, out_png)


def read_study_table(out_dir):
    """Every ``chunk-*.parquet`` of a study folder as one pyarrow Table, sorted by run id."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    files = sorted(glob.glob(os.path.join(os.fspath(out_dir), "chunk-*.parquet")))
    if not files:
        raise FileNotFoundError(f"{os.fspath(out_dir)!r} holds no chunk-*.parquet file; "
                                "run the study first")
    table = pa.concat_tables([pq.read_table(path) for path in files], promote_options="default")
    return table.sort_by("run_id") if "run_id" in table.column_names else table


def plot_study(out_dir, metrics: Sequence[str] = ("final_pose_error", "ate_rmse", "map_error",
                                                  "gospa")) -> list[str]:
    """Every plot of a study folder that its files allow: map.png (example_run.npz),
    error_vs_time.png (traces-*.npz), and box_<metric>.png when it has several conditions."""
    folder = os.fspath(out_dir)
    written = []
    example = os.path.join(folder, "example_run.npz")
    if os.path.isfile(example):
        written.append(plot_map(example, os.path.join(folder, "map.png")))
    table = read_study_table(folder) if glob.glob(os.path.join(folder, "chunk-*.parquet")) \
        else None
    labels = condition_labels(table) if table is not None else None
    if glob.glob(os.path.join(folder, "traces-*.npz")):
        written.append(plot_error_vs_time(folder, os.path.join(folder, "error_vs_time.png"),
                                          labels))
    if table is not None and len(set(table.column("condition").to_pylist())) > 1:
        for metric in metrics:
            if metric in table.column_names:
                written.append(plot_sweep_boxes(table, metric,
                                                os.path.join(folder, f"box_{metric}.png")))
    return written
