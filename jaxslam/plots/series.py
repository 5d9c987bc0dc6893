"""Position error against time: the median and 5-95 % band across runs, per condition."""
from __future__ import annotations

from typing import Mapping

import numpy as np

from jaxslam.plots import figure
from jaxslam.plots.inputs import load_traces


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

    fig = figure.new_figure((9, 5))
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
    return figure.save_figure(error_vs_time_figure(traces, labels, title), out_png)
