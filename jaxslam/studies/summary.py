"""Per-condition statistics of a study's runs, written as ``summary.md`` and ``summary.json``."""
from __future__ import annotations

import json
import pathlib
import tomllib
from typing import NamedTuple

import numpy as np

from jaxslam import study_store
from jaxslam.columns import column_unit
from jaxslam.studies.chunks import load_results
from jaxslam.study_config import StudyConfig, study_config_from_dict

SUMMARY_METRICS = ("final_pose_error", "ate_rmse", "ate_rmse_aligned", "map_error",
                   "redundant", "orphan", "num_landmarks", "gospa", "pose_nees", "diverged")


def filter_throughput(out_dir) -> float:
    """Run-steps per second of the filter over the study's chunks (from their metadata)."""
    import pyarrow.parquet as pq

    steps = seconds = 0.0
    for path in sorted((pathlib.Path(out_dir) / study_store.RUNS_DIR).glob("chunk-*.parquet")):
        metadata = pq.read_schema(path).metadata or {}
        chunk_seconds = float(metadata.get(b"jaxslam.filter_seconds", b"nan"))
        seconds += chunk_seconds
        steps += float(metadata.get(b"jaxslam.update_rate_hz", b"nan")) * chunk_seconds
    return steps / seconds if seconds > 0 else float("nan")


def _mean_interval(values: np.ndarray) -> tuple[float, float]:
    """95% confidence interval of the mean: mean -/+ t_{0.975, n-1} s / sqrt(n) (Student t;
    NaN for fewer than 2 runs). It says how well the runs pin the mean, not their spread."""
    from scipy import stats

    n = len(values)
    if n < 2:
        return float("nan"), float("nan")
    half = stats.t.ppf(0.975, n - 1) * np.std(values, ddof=1) / np.sqrt(n)
    return float(np.mean(values) - half), float(np.mean(values) + half)


def summary_rows(config: StudyConfig, table) -> list[dict]:
    """Per condition and metric: unit, runs, mean with its 95% confidence interval, median,
    and the 2.5 and 97.5 percentiles of the runs."""
    rows = []
    columns = {name: table.column(name).to_numpy() for name in table.column_names}
    for index, condition in enumerate(config.conditions):
        mask = columns["condition"] == index
        for name in SUMMARY_METRICS:
            if name not in columns:
                continue
            values = columns[name][mask].astype(float)
            ci_low, ci_high = _mean_interval(values)
            rows.append(dict(condition=index, setting=_setting_label(condition), metric=name,
                             unit=column_unit(name), runs=int(mask.sum()),
                             mean=float(np.mean(values)), ci_low=ci_low, ci_high=ci_high,
                             median=float(np.median(values)),
                             p2_5=float(np.percentile(values, 2.5)),
                             p97_5=float(np.percentile(values, 97.5))))
    return rows


class _RunCheck(NamedTuple):
    """A per-run count that should be 0 (``column`` > 0 flags the run), the words for it and
    what to do. ``what`` is formatted with the study config as ``config``."""

    column: str
    what: str
    unit: str
    advice: str
    only_if: str = ""  # a FilterConfig field that must be non-zero for the check to apply


RUN_CHECKS = (
    _RunCheck("num_dropped_births", "the map's {config.filter.max_landmarks} slots were full "
              "and new landmarks were dropped", "births",
              "raise filter.max_landmarks above the landmarks a run maps"),
    _RunCheck("num_weight_resets", "every particle's weight was zero at some step and the "
              "weights were reset", "steps",
              "the noise settings are likely too small for the data"),
    _RunCheck("num_invalid_controls", "control rows held NaN or infinity and were masked",
              "steps", "check the simulator's controls"),
    _RunCheck("num_window_cut_steps", "the association window (filter.association_window = "
              "{config.filter.association_window}) left out landmarks that could have taken "
              "part", "steps", "raise it until no run is flagged, or set 0 for the full "
              "association", only_if="association_window"),
)


def warning_lines(config: StudyConfig, table) -> list[str]:
    """Markdown lines naming, per condition, the runs that a ``RUN_CHECKS`` count flags
    (dropped births: map full; weight resets; masked controls; an association window that
    left out landmarks that could have taken part): how many runs, the most in one run, and
    what to do. Runs whose chunk was written before a column existed (null there) are named
    as not checked when the check applies. Empty when nothing was flagged."""
    condition = table.column("condition").to_numpy()
    lines = []
    for check in RUN_CHECKS:
        if check.column not in table.column_names:
            continue
        if check.only_if and not getattr(config.filter, check.only_if):
            continue
        counts = table.column(check.column).to_numpy().astype(float)  # NaN: null
        what = check.what.format(config=config)
        for index, setting in enumerate(config.conditions):
            mine = condition == index
            checked = mine & ~np.isnan(counts)
            flagged = checked & (np.nan_to_num(counts) > 0)
            label = _setting_label(setting)
            if flagged.any():
                lines.append(f"- {label}: in {int(flagged.sum())} of {int(checked.sum())} runs "
                             f"{what} (up to {int(counts[flagged].max())} {check.unit} in one "
                             f"run, `{check.column}`); {check.advice}.")
            unchecked = int(mine.sum() - checked.sum())
            if unchecked:
                lines.append(f"- {label}: {unchecked} runs were written before "
                             f"`{check.column}` existed (null there): not checked.")
    return ["", "Warnings:", ""] + lines if lines else []


def _setting_label(condition: dict) -> str:
    return ", ".join(f"{k}={v}" for k, v in condition.items()) or "default"


def summarize_study(out_dir, table=None) -> str:
    """Write ``summary.md`` (a Markdown table with units) and the same rows as
    ``summary.json`` (for scripts), and return the Markdown."""
    out_dir = pathlib.Path(out_dir)
    with open(out_dir / "study.toml", "rb") as handle:
        config = study_config_from_dict(tomllib.load(handle))
    table = load_results(out_dir) if table is None else table
    lines = [f"# Study `{config.name}`", "",
             f"{config.num_runs} runs per condition; P={config.filter.num_particles}, "
             f"association={config.filter.association}, boundary={config.filter.boundary}, "
             f"proposal={config.filter.proposal}; filter throughput "
             f"{filter_throughput(out_dir):,.0f} run-steps/s.", "",
             "| setting | metric | unit | runs | mean | mean 95% CI | median | "
             "runs 2.5% | runs 97.5% |",
             "|---|---|---|---|---|---|---|---|---|"]
    for row in summary_rows(config, table):
        lines.append(f"| {row['setting']} | {row['metric']} | {row['unit']} | {row['runs']} | "
                     f"{row['mean']:.4g} | [{row['ci_low']:.4g}, {row['ci_high']:.4g}] | "
                     f"{row['median']:.4g} | {row['p2_5']:.4g} | {row['p97_5']:.4g} |")
    lines += ["", "mean 95% CI: Student-t confidence interval of the mean over runs; runs "
              "2.5% / 97.5%: percentiles of the runs themselves (their spread). pose_nees of "
              "a consistent filter averages 3 (chi-square, 3 degrees of freedom); far above "
              "means overconfident. Every metric is defined in docs/metrics.md."]
    warned = warning_lines(config, table)
    lines += warned
    text = "\n".join(lines) + "\n"
    study_store.atomic_write(out_dir / "summary.md", lambda p: p.write_text(text))
    warnings = [line[2:] for line in warned if line.startswith("- ")]
    rows = json.dumps({"study": config.name, "rows": summary_rows(config, table),
                       "warnings": warnings}, indent=1)
    study_store.atomic_write(out_dir / "summary.json", lambda p: p.write_text(rows + "\n"))
    return text
