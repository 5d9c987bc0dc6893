"""Box plots of a metric across the conditions of a sweep, labelled by the swept values."""
from __future__ import annotations

from typing import Sequence

import numpy as np

from jaxslam.plots import figure
from jaxslam.plots.inputs import column_units, table_columns
from jaxslam.plots.labels import (condition_labels, metric_label, sweep_table_columns,
                                  swept_columns)


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
    fig = figure.new_figure((max(6.0, 1.3 * len(conditions) + 2.0), 5))
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
    return figure.save_figure(sweep_boxes_figure(table, metric, sweep, title), out_png)
