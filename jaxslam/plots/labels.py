"""Words of the study plots: axis texts with units, condition labels from the swept settings,
and what a study folder's ``study.toml`` says (``StudyInfo``: titles and legend texts).
"""
from __future__ import annotations

import os
import tomllib
from typing import Mapping, NamedTuple, Sequence

import numpy as np

from jaxslam.columns import NON_SETTING_COLUMNS, column_unit
from jaxslam.plots.inputs import table_columns


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
                     observation_source=getattr(config.scenario, "observation_source", ""),
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
