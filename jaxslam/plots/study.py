"""Every plot of a study folder (``plot_study``), titled and labelled from its study.toml."""
from __future__ import annotations

import os
from typing import Sequence

from jaxslam.plots import labels
from jaxslam.plots.inputs import _trace_files
from jaxslam.plots.labels import condition_labels
from jaxslam.plots.maps import plot_map
from jaxslam.plots.series import plot_error_vs_time
from jaxslam.plots.sweeps import _box_title, plot_sweep_boxes


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
    info = labels.study_info(folder)
    written = []
    example = os.path.join(folder, "example_run.npz")
    if os.path.isfile(example):
        written.append(plot_map(example, os.path.join(folder, "map.png"), info=info))
    table = _study_table_or_none(folder)
    if info is not None:
        names = dict(enumerate(info.conditions)) if len(info.conditions) > 1 else {0: "all runs"}
        sweep = list(info.sweep)
    else:
        names = condition_labels(table) if table is not None else None
        sweep = None
    if _trace_files(folder):
        title = (f"Study '{info.name}': position error over time" if info is not None
                 else "Position error over time")
        written.append(plot_error_vs_time(folder, os.path.join(folder, "error_vs_time.png"),
                                          names, title))
    if table is not None and len(set(table.column("condition").to_pylist())) > 1:
        for metric in metrics:
            if metric in table.column_names:
                written.append(plot_sweep_boxes(
                    table, metric, os.path.join(folder, f"box_{metric}.png"), sweep=sweep,
                    title=_box_title(metric, info.name if info is not None else None)))
    return written
