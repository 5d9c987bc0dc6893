"""Study plots (matplotlib, PNG): the map, error against time, sweep box plots.

Every plot has a builder that returns a ``matplotlib.figure.Figure`` (``map_figure``,
``error_vs_time_figure``, ``sweep_boxes_figure``: no pyplot state, so a test or a notebook
can inspect or restyle it) and a ``plot_*`` function that builds it and saves it as a PNG
(``save_figure``). ``plot_study`` writes every plot of a study folder, with titles that name
the study (the ``name`` in its ``study.toml``) and the run or conditions shown.

Host-side NumPy only; matplotlib, pyarrow and ``jaxslam.studies`` are imported inside the
functions so that ``import jaxslam.plots`` stays cheap (the ``jaxslam`` command imports it
lazily too).

Shapes (glossary in ``jaxslam.types``): T steps, M landmark slots, N true trees, R runs.
Inputs come from the files a study writes (``jaxslam.studies``):
  ``study.toml``: the resolved study config (name, [sweep], scenario), read by ``study_info``.
  ``example_run.npz``: run 0 / condition 0: truth_pose (T+1, 3), mean_pose (T, 3),
    landmark_mean (M, 2), landmark_cov (M, 2, 2), active (M,), tree_centres (N, 2),
    tree_radii (N,); optional tree_seen (N,) and smoothed_pose (T, 3).
  ``traces/traces-*.npz``: run_id (R,), condition (R,), pose_error (R, T) [m].
  ``runs/chunk-*.parquet``: one row per (run, condition): ids, swept settings, metrics (read
    only through ``jaxslam.studies.load_results``; every column is defined in
    docs/metrics.md).
"""
from __future__ import annotations

import glob
import os
import tomllib
import warnings
from typing import Mapping, NamedTuple, Sequence

import numpy as np

from jaxslam.columns import NON_SETTING_COLUMNS, column_unit

SIGMA_SCALE = 2.0  # ellipses are drawn at 2 standard deviations along each principal axis
# Scaled ellipses: the median full major axis is drawn at about this fraction of the map.
ELLIPSE_TARGET_FRACTION = 0.015
_INSET_GID = "true_scale_inset"
_ELLIPSES_GID = "landmark_ellipses"


class ExampleRun(NamedTuple):
    """One run's trajectories and map, validated (NumPy float64; see module docstring).

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


class StudyInfo(NamedTuple):
    """What the plots say about a study, from its ``study.toml`` (``study_info``).

    name: the config's name. sweep: the swept setting names (``[sweep]`` keys, in order).
    conditions: one label per condition G, "name=value, ..." ("no sweep" for the single
    condition of a study without one). num_runs: runs per condition. observation_source:
    "analytic" or "lidar". max_range: sensor range [m]. max_obs: K, observations per step.
    """

    name: str
    sweep: tuple
    conditions: tuple
    num_runs: int
    observation_source: str
    max_range: float
    max_obs: int


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


def metric_label(name: str, units: Mapping[str, str] | None = None) -> str:
    """Axis text for a column: its name as the table spells it (so it can be looked up in
    docs/metrics.md) and its unit, e.g. "final_pose_error [m]"."""
    unit = (units or {}).get(name) or column_unit(name)
    return f"{name} [{unit}]" if unit else name


def format_value(value) -> str:
    """Compact text for a parameter value: 0.05, 100, (0.005, 0)."""
    if isinstance(value, (list, tuple, np.ndarray)):
        return "(" + ", ".join(format_value(v) for v in np.asarray(value).ravel()) + ")"
    if isinstance(value, (float, np.floating)):
        return f"{float(value):.4g}"
    return str(value)


def setting_label(condition: Mapping) -> str:
    """"name=value, ..." of one sweep condition ({setting: value}); "no sweep" when empty."""
    return ", ".join(f"{name}={format_value(value)}" for name, value in condition.items()) \
        or "no sweep"


def _hashable(value):
    return tuple(np.asarray(value).ravel().tolist()) if isinstance(
        value, (list, tuple, np.ndarray)) else value


def swept_columns(columns: Mapping[str, list]) -> list[str]:
    """Parameter columns that differ between conditions (constant within each condition).

    A guess for tables without a ``study.toml`` (``plot_study`` reads the sweep keys from the
    study instead): ids and every known metric column are never returned.
    """
    if "condition" not in columns:
        return []
    condition = columns["condition"]
    swept = []
    for name, values in columns.items():
        if name in NON_SETTING_COLUMNS or len(values) != len(condition):
            continue
        by_condition: dict = {}
        for cond, value in zip(condition, values):
            by_condition.setdefault(cond, set()).add(_hashable(value))
        constant_within = all(len(seen) == 1 for seen in by_condition.values())
        varies = len({next(iter(seen)) for seen in by_condition.values()}) > 1
        if constant_within and varies:
            swept.append(name)
    return swept


def sweep_table_columns(columns: Mapping[str, list], sweep: Sequence[str]) -> list[str]:
    """The table columns of the swept settings ``sweep``: a scalar setting is its own column,
    a vector one is split into ``name[0]``, ``name[1]``, ...

    Raises:
      ValueError naming a setting the table has no column for.
    """
    found = []
    for name in sweep:
        if name in columns:
            found.append(name)
            continue
        parts = sorted((c for c in columns if c.startswith(f"{name}[") and c.endswith("]")),
                       key=lambda c: int(c[len(name) + 1:-1]) if c[len(name) + 1:-1].isdigit()
                       else 0)
        if not parts:
            raise ValueError(f"the table has no column for the swept setting {name!r}; "
                             f"columns: {sorted(columns)}")
        found += parts
    return found


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


def study_info(out_dir) -> StudyInfo | None:
    """The plots' view of a study folder's ``study.toml`` (None when it has none).

    Raises:
      ValueError / TypeError for a study.toml that ``studies.study_config_from_dict`` refuses.
    """
    path = os.path.join(os.fspath(out_dir), "study.toml")
    if not os.path.isfile(path):
        return None
    from jaxslam import studies

    with open(path, "rb") as handle:
        config = studies.study_config_from_dict(tomllib.load(handle))
    return StudyInfo(name=config.name, sweep=tuple(name for name, _ in config.sweep),
                     conditions=tuple(setting_label(c) for c in config.conditions),
                     num_runs=config.num_runs,
                     observation_source=config.scenario.observation_source,
                     max_range=float(config.scenario.max_range),
                     max_obs=int(config.filter.max_obs))


def tree_seen_labels(info: StudyInfo | None) -> tuple[str, str]:
    """Legend templates (seen, never seen) for the ``tree_seen`` mask of a study's example
    run; ``{n}`` stands for the count.

    What the mask means depends on the simulated sensor (``sims.batch``): with the analytic
    source a tree is seen when it gave a measurement at some step, i.e. it was within
    (min_range, max_range] and among the K = max_obs nearest such trees; with the lidar
    source when the true path passed within max_range of its centre at some step (it may
    still have been hidden or missed by the detector). Only seen trees are scored by the map
    metrics (docs/metrics.md).
    """
    if info is None:
        return ("true trunks seen at some step: {n}", "true trunks never seen: {n} (not scored)")
    if info.observation_source == "analytic":
        return ("true trunks measured at some step: {n}\n"
                f"(in range and among the {info.max_obs} nearest)",
                "true trunks never measured: {n} (not scored)")
    return (f"true trunks within {info.max_range:g} m of the path at some step: {{n}}",
            f"true trunks never within {info.max_range:g} m: {{n}} (not scored)")


def map_title(info: StudyInfo, condition: int = 0, run: int = 0) -> str:
    """Title of a study's example map: the study, the run and the condition's setting."""
    setting = info.conditions[condition] if condition < len(info.conditions) else "?"
    return (f"Study '{info.name}': example map, run {run} (of {info.num_runs}), "
            f"condition {condition} ({setting})\n"
            "true trunks and the estimated map (highest-weight particle)")


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


def ellipse_scale(widths, extent: float, target: float = ELLIPSE_TARGET_FRACTION) -> float:
    """Magnification of the landmark ellipses on a map of size ``extent`` [m].

    widths: (M,) full major axes [m]. Returns the largest of 1, 2, 5, 10, 20, 50, ... that
    keeps the median width times the factor at or below ``target * extent``; 1 when the
    ellipses are already that large (or there are none), so they are never shrunk.
    """
    widths = np.asarray(widths, np.float64)
    widths = widths[np.isfinite(widths) & (widths > 0)]
    if widths.size == 0 or not extent > 0:
        return 1.0
    wanted = target * extent / float(np.median(widths))
    if wanted < 2.0:
        return 1.0
    decade = 10.0 ** np.floor(np.log10(wanted))
    return float(decade * max(m for m in (1.0, 2.0, 5.0) if m * decade <= wanted))


def _map_extent(run: ExampleRun) -> float:
    """Side [m] of the bounding square of everything a map draws."""
    points = np.concatenate([run.truth_pose[:, :2], run.mean_pose[:, :2], run.tree_centres,
                             run.landmark_mean[run.active]])
    return float(np.max(np.ptp(points, axis=0))) if len(points) else 0.0


# ------------------------------------------------------------------------------------------
# Figures


def _new_figure(figsize):
    """A matplotlib Figure outside pyplot (no global state; garbage-collected)."""
    from matplotlib.figure import Figure

    return Figure(figsize=figsize)


def save_figure(fig, out_png) -> str:
    """Save ``fig`` as a PNG (folders created) and return the path."""
    path = os.fspath(out_png)
    folder = os.path.dirname(path)
    if folder:
        os.makedirs(folder, exist_ok=True)
    fig.savefig(path, dpi=120, bbox_inches="tight")
    return path


def _draw_map_layers(ax, run: ExampleRun, scale: float, seen_texts, legend: bool) -> list:
    """Trunks, landmarks with ``scale`` x 2-sigma ellipses and the paths on ``ax``.

    Returns the legend entries [(handle, text)] in reading order (empty if not ``legend``).
    """
    from matplotlib.collections import EllipseCollection, PatchCollection
    from matplotlib.patches import Circle, Ellipse

    entries = []
    seen = run.tree_seen if run.tree_seen is not None else np.ones(len(run.tree_radii), bool)
    groups = ((seen, "saddlebrown", seen_texts[0]), (~seen, "darkgray", seen_texts[1]))
    if run.tree_seen is None:
        groups = ((seen, "saddlebrown", "true trunks: {n}"),)
    for mask, colour, text in groups:
        if not mask.any():
            continue
        centres, radii = run.tree_centres[mask], run.tree_radii[mask]
        ax.add_collection(PatchCollection([Circle(tuple(c), r) for c, r in zip(centres, radii)],
                                          facecolor=colour, edgecolor="none", alpha=0.6))
        handle = ax.scatter(centres[:, 0], centres[:, 1], s=14, marker="o", facecolor="none",
                            edgecolor=colour, linewidth=1.0)
        entries.append((handle, text.format(n=int(mask.sum()))))
    mean, cov = run.landmark_mean[run.active], run.landmark_cov[run.active]
    if len(mean):
        width, height, angle = covariance_ellipses(cov)
        ellipses = EllipseCollection(scale * width, scale * height, angle, units="xy",
                                     offsets=mean, offset_transform=ax.transData,
                                     facecolor="none", edgecolor="tab:blue", linewidth=1.0)
        ellipses.set_gid(_ELLIPSES_GID)
        ax.add_collection(ellipses)
        handle = ax.scatter(mean[:, 0], mean[:, 1], s=18, marker="+", color="tab:blue")
        entries.append((handle, f"estimated landmarks: {len(mean)}"))
        proxy = Ellipse((0, 0), 1.0, 0.6, facecolor="none", edgecolor="tab:blue")
        entries.append((proxy, f"landmark {SIGMA_SCALE:g}σ ellipse" + (
            f" ×{scale:g} (enlarged to be visible)" if scale != 1 else " (true scale)")))
    if len(run.truth_pose):
        line, = ax.plot(run.truth_pose[:, 0], run.truth_pose[:, 1], color="black",
                        linewidth=1.8)
        entries.append((line, "true path"))
    line, = ax.plot(run.mean_pose[:, 0], run.mean_pose[:, 1], color="tab:red", linewidth=1.4,
                    linestyle="--")
    entries.append((line, "estimated path (weighted mean)"))
    if run.smoothed_pose is not None:
        line, = ax.plot(run.smoothed_pose[:, 0], run.smoothed_pose[:, 1], color="tab:green",
                        linewidth=1.4, linestyle="-.")
        entries.append((line, "smoothed path"))
    start = run.truth_pose[0, :2] if len(run.truth_pose) else (
        run.mean_pose[0, :2] if len(run.mean_pose) else None)
    if start is not None:
        line, = ax.plot(*start, marker="s", color="black", markersize=7, linestyle="none")
        entries.append((line, "start"))
    for handle, text in entries:
        handle.set_label(text)  # so the artists can be found by their legend text
    return entries if legend else []


def _inset_window(run: ExampleRun, index: int, half_major: float) -> float:
    """Half-side [m] of the inset around active landmark ``index``: its 2-sigma ellipse and
    its nearest true trunk (when that is within 1 m) fit with a margin."""
    centre = run.landmark_mean[index]
    reach = half_major
    if len(run.tree_centres):
        gaps = np.hypot(*(run.tree_centres - centre).T)
        nearest = int(np.argmin(gaps))
        reach = max(reach, min(gaps[nearest] + run.tree_radii[nearest], 1.0))
    return 1.5 * max(reach, 0.1)


def _add_true_scale_inset(ax, run: ExampleRun, seen_texts) -> None:
    """A zoom at true scale (unscaled 2-sigma ellipses) on the least certain active landmark
    (largest major axis), beside the map, its region outlined on the map."""
    active = np.flatnonzero(run.active)
    width, _, _ = covariance_ellipses(run.landmark_cov[active])
    pick = int(np.argmax(width))
    index = active[pick]
    half = _inset_window(run, index, 0.5 * width[pick])
    inset = ax.inset_axes([1.04, 0.0, 0.5, 0.5])
    inset.set_gid(_INSET_GID)
    _draw_map_layers(inset, run, 1.0, seen_texts, legend=False)
    cx, cy = run.landmark_mean[index]
    inset.set_xlim(cx - half, cx + half)
    inset.set_ylim(cy - half, cy + half)
    inset.set_aspect("equal", adjustable="box")
    inset.set_title(f"zoom at true scale ({SIGMA_SCALE:g}σ ellipse ×1):\n"
                    "the least certain landmark (outlined on the map)", fontsize=8)
    inset.set_xlabel("x [m]", fontsize=8)
    inset.set_ylabel("y [m]", fontsize=8)
    inset.tick_params(labelsize=7)
    inset.grid(True, alpha=0.3)
    ax.indicate_inset_zoom(inset, edgecolor="0.3")


def map_figure(example, title: str | None = None, *, info: StudyInfo | None = None,
               scale: float | None = None, inset: bool | None = None):
    """The map of one run as a Figure (not saved; ``plot_map`` saves it).

    Draws the true trunks (circles of their radius, with a marker so thin trunks show; grey
    when the optional ``tree_seen`` mask says the run never saw them, ``tree_seen_labels``),
    the active landmarks of the highest-weight particle with their 2-sigma ellipses, the true,
    estimated and (when given) smoothed paths, and the start.

    Uncertainty: landmark standard deviations are centimetres on a map of tens of metres, so
    true-scale ellipses vanish under their markers. Two views are drawn: on the map every
    ellipse is enlarged by one stated factor (``ellipse_scale``: 1, 2, 5, 10, ... chosen so
    the median ellipse is about 1.5 % of the map; the legend says e.g. "landmark 2σ ellipse
    ×10"), which shows where the map is uncertain and in which direction; beside it a zoom
    at true scale on the least certain landmark shows the real size against its trunk and
    the true centre, which an enlarged ellipse would misstate. The zoom is drawn only when
    the map's factor is above 1.

    Args:
      example: path to ``example_run.npz`` or a mapping of its arrays (see ``ExampleRun``).
      title: the title (default: ``map_title(info)`` for a study, else a generic one).
      info: the study (``study_info``) for the title and the ``tree_seen`` legend texts.
      scale: ellipse magnification (default: ``ellipse_scale``).
      inset: draw the true-scale zoom (default: when the magnification is above 1).
    Returns:
      matplotlib.figure.Figure; its first axes is the map.
    """
    run = load_example_run(example)
    seen_texts = tree_seen_labels(info)
    active_cov = run.landmark_cov[run.active]
    if scale is None:
        scale = ellipse_scale(covariance_ellipses(active_cov)[0], _map_extent(run))
    fig = _new_figure((8, 8))
    ax = fig.add_subplot()
    entries = _draw_map_layers(ax, run, scale, seen_texts, legend=True)
    ax.set_aspect("equal", adjustable="datalim")
    ax.autoscale_view()
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    if title is None:
        title = map_title(info) if info is not None else \
            "Map: true trunks and estimated landmarks"
    ax.set_title(title, fontsize=11)
    ax.grid(True, alpha=0.3)
    ax.legend([h for h, _ in entries], [t for _, t in entries], loc="upper left",
              bbox_to_anchor=(1.01, 1.0), fontsize=9, framealpha=0.9)
    if (scale > 1 if inset is None else inset) and run.active.any():
        _add_true_scale_inset(ax, run, seen_texts)
    return fig


def plot_map(example, out_png, title: str | None = None, *, info: StudyInfo | None = None,
             **options) -> str:
    """Build ``map_figure`` and save it as a PNG; returns the path.

    When ``example`` is a path and neither ``title`` nor ``info`` is given, the study of the
    folder holding the file (its ``study.toml``, if any) names the title.
    """
    if info is None and title is None and isinstance(example, (str, os.PathLike)):
        try:
            info = study_info(os.path.dirname(os.path.abspath(os.fspath(example))))
        except (ValueError, TypeError, tomllib.TOMLDecodeError) as error:
            warnings.warn(f"map title: the study.toml next to {os.fspath(example)} is not "
                          f"readable ({error}); using a generic title")
    return save_figure(map_figure(example, title, info=info, **options), out_png)


def error_vs_time_figure(traces, labels: Mapping[int, str] | None = None,
                         title: str = "Position error over time"):
    """Median position error against step with a 5-95 % band across runs, per condition.

    Args:
      traces: a study folder, a ``traces-*.npz`` path or a mapping with run_id (R,),
        condition (R,), pose_error (R, T) [m].
      labels: {condition: legend text}, e.g. from ``condition_labels(table)``.
      title: the title.
    Returns:
      matplotlib.figure.Figure.
    """
    data = load_traces(traces)
    if data.pose_error.shape[0] == 0:
        raise ValueError("traces: pose_error has no runs (R = 0); expected at least one")
    from matplotlib import colormaps

    fig = _new_figure((9, 5))
    ax = fig.add_subplot()
    steps = np.arange(1, data.pose_error.shape[1] + 1)
    conditions = np.unique(data.condition)
    colours = colormaps["tab10" if len(conditions) <= 10 else "viridis"]
    for index, cond in enumerate(conditions):
        errors = data.pose_error[data.condition == cond]
        low, median, high = np.nanpercentile(errors, [5.0, 50.0, 95.0], axis=0)
        colour = colours(index if len(conditions) <= 10 else index / max(len(conditions) - 1, 1))
        name = (labels or {}).get(int(cond), f"condition {int(cond)}")
        if errors.shape[0] == 1:  # one run: its error, no band to draw
            ax.plot(steps, median, color=colour, linewidth=1.8, label=name)
        else:
            ax.fill_between(steps, low, high, color=colour, alpha=0.2, linewidth=0)
            ax.plot(steps, median, color=colour, linewidth=1.8,
                    label=f"{name}  (median, 5-95 % band, {errors.shape[0]} runs)")
    ax.set_xlabel("time step (filter update) [steps]")
    ax.set_ylabel("position error [m]")
    ax.set_xlim(steps[0], steps[-1])
    ax.set_ylim(bottom=0.0)
    ax.set_title(title, fontsize=11)
    ax.grid(True, alpha=0.3)
    ax.legend(loc="upper left", fontsize=9, framealpha=0.9)
    return fig


def plot_error_vs_time(traces, out_png, labels: Mapping[int, str] | None = None,
                       title: str = "Position error over time") -> str:
    """Build ``error_vs_time_figure`` and save it as a PNG; returns the path."""
    return save_figure(error_vs_time_figure(traces, labels, title), out_png)


def _box_title(metric: str, study: str | None = None) -> str:
    where = f"Study '{study}': " if study else ""
    return (f"{where}{metric} across sweep conditions\n"
            "box: quartiles, line: median, triangle: mean, whiskers: 5-95 %")


def sweep_boxes_figure(table, metric: str, sweep: Sequence[str] | None = None,
                       title: str | None = None):
    """Box plots of one metric across sweep conditions, labelled by the swept values only.

    Args:
      table: the study table (pyarrow.Table, mapping of columns or list of rows) with a
        ``condition`` column and the metric column.
      metric: the metric column, e.g. "final_pose_error".
      sweep: the swept settings to label with: ``[sweep]`` keys of the study (a vector
        setting's ``name[j]`` columns are found) or any label columns (default: guessed by
        ``swept_columns``, which never returns a metric).
      title: the title (default: the metric and how to read a box).
    Returns:
      matplotlib.figure.Figure.
    """
    columns = table_columns(table)
    units = column_units(table)
    for name in ("condition", metric):
        if name not in columns:
            raise ValueError(f"the table has no {name!r} column; available: {sorted(columns)}")
    shown = sweep_table_columns(columns, sweep) if sweep is not None else swept_columns(columns)
    labels = condition_labels(columns, shown)
    condition = np.asarray(columns["condition"], np.int64)
    values = np.asarray([np.nan if v is None else v for v in columns[metric]], np.float64)
    conditions = np.unique(condition)
    groups = [values[(condition == c) & np.isfinite(values)] for c in conditions]
    fig = _new_figure((max(6.0, 1.3 * len(conditions) + 2.0), 5))
    ax = fig.add_subplot()
    ax.boxplot(groups, whis=(5, 95), showmeans=True, widths=0.6)
    tick_labels = [labels[int(c)].replace(", ", "\n") + f"\n(n={len(g)})"
                   for c, g in zip(conditions, groups)]
    ax.set_xticks(np.arange(1, len(conditions) + 1), tick_labels, fontsize=9,
                  rotation=0 if len(conditions) <= 6 else 45)
    ax.set_ylabel(metric_label(metric, units))
    ax.set_xlabel("sweep condition" + (": " + ", ".join(metric_label(n, units) for n in shown)
                                       if shown else " [index]"))
    ax.set_title(title or _box_title(metric), fontsize=11)
    ax.grid(True, axis="y", alpha=0.3)
    return fig


def plot_sweep_boxes(table, metric: str, out_png, sweep: Sequence[str] | None = None,
                     title: str | None = None) -> str:
    """Build ``sweep_boxes_figure`` and save it as a PNG; returns the path."""
    return save_figure(sweep_boxes_figure(table, metric, sweep, title), out_png)


# ------------------------------------------------------------------------------------------
# A study folder


def read_study_table(out_dir):
    """The study table: ``jaxslam.studies.load_results`` (every finished chunk of the folder
    as one pyarrow Table, sorted by (condition, run_id)); raises its StudyError without one."""
    from jaxslam import studies

    return studies.load_results(out_dir)


def _study_table_or_none(out_dir):
    from jaxslam import studies

    try:
        return studies.load_results(out_dir)
    except studies.StudyError:
        return None


def plot_study(out_dir, metrics: Sequence[str] = ("final_pose_error", "ate_rmse", "map_error",
                                                  "gospa")) -> list[str]:
    """Every plot of a study folder that its files allow: map.png (example_run.npz),
    error_vs_time.png (traces), and box_<metric>.png when it has several conditions.

    Titles name the study (``study.toml``); the conditions are labelled by the swept settings
    of its ``[sweep]`` (guessed from the table only when the folder has no study.toml).
    """
    folder = os.fspath(out_dir)
    info = study_info(folder)
    written = []
    example = os.path.join(folder, "example_run.npz")
    if os.path.isfile(example):
        written.append(plot_map(example, os.path.join(folder, "map.png"), info=info))
    table = _study_table_or_none(folder)
    if info is not None:
        labels = dict(enumerate(info.conditions)) if len(info.conditions) > 1 else {0: "all runs"}
        sweep = list(info.sweep)
    else:
        labels = condition_labels(table) if table is not None else None
        sweep = None
    if _trace_files(folder):
        title = (f"Study '{info.name}': position error over time" if info is not None
                 else "Position error over time")
        written.append(plot_error_vs_time(folder, os.path.join(folder, "error_vs_time.png"),
                                          labels, title))
    if table is not None and len(set(table.column("condition").to_pylist())) > 1:
        for metric in metrics:
            if metric in table.column_names:
                written.append(plot_sweep_boxes(
                    table, metric, os.path.join(folder, f"box_{metric}.png"), sweep=sweep,
                    title=_box_title(metric, info.name if info is not None else None)))
    return written
