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

Modules: ``inputs`` (loading and checking the files), ``labels`` (axis texts, condition labels,
``study_info``), ``figure`` (building and saving), ``maps``, ``series`` (error over time),
``sweeps`` (box plots) and ``study`` (a whole folder). Every name is re-exported here.
"""
from __future__ import annotations

from jaxslam.columns import NON_SETTING_COLUMNS, column_unit  # noqa: F401
from jaxslam.plots.figure import new_figure, save_figure  # noqa: F401
from jaxslam.plots.inputs import (ExampleRun, Traces, _trace_files,  # noqa: F401
                                  column_units, load_example_run, load_traces, table_columns)
from jaxslam.plots.labels import (StudyInfo, condition_labels, format_value,  # noqa: F401
                                  map_title, metric_label, setting_label, study_info,
                                  sweep_table_columns, swept_columns, tree_seen_labels)
from jaxslam.plots.maps import (ELLIPSE_TARGET_FRACTION, SIGMA_SCALE,  # noqa: F401
                                _map_extent, covariance_ellipses, ellipse_scale, map_figure,
                                plot_map)
from jaxslam.plots.series import error_vs_time_figure, plot_error_vs_time  # noqa: F401
from jaxslam.plots.study import plot_study, read_study_table  # noqa: F401
from jaxslam.plots.sweeps import plot_sweep_boxes, sweep_boxes_figure  # noqa: F401
