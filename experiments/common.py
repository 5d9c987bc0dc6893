"""Shared plumbing of the experiment scripts: run named study configs, compare them, plot.

Each experiment is a set of named pipelines, each a ``jaxslam study`` TOML in
``experiments/configs/`` (so ``jaxslam study experiments/configs/X.toml`` runs one alone).
Results land in ``results/<experiment>/<pipeline>/`` (resumable) and the comparison in
``results/<experiment>/table.md`` and ``box_<metric>.png``.
"""
from __future__ import annotations

import argparse
import pathlib
import sys
import time

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parent.parent
CONFIGS = ROOT / "experiments" / "configs"
# Run this checkout's jaxslam, also when an editable install points at another checkout
# (an experiment started from a git worktree of an older commit).
sys.path.insert(0, str(ROOT))


def add_em_significance(parser) -> None:
    """``--em-significance LEVEL``: ``calibrate_params``' significance (0: None)."""
    parser.add_argument("--em-significance", type=float, default=0.0, metavar="LEVEL",
                        help="calibrate_params' significance: a later EM run beats the best "
                             "before it only by a one-sided t test of the per-step log "
                             "evidence at this level; 0: the highest summed likelihood "
                             "(default: 0, as in the library)")


def em_significance(parser, args, calibrates: bool = True) -> float | None:
    """The checked ``--em-significance`` as ``calibrate_params`` takes it (None for 0);
    ``parser.error`` for a level outside [0, 1), or a level where nothing is calibrated."""
    level = args.em_significance
    if not 0.0 <= level < 1.0:
        parser.error(f"--em-significance {level}: expected a level in (0, 1), or 0")
    if level and not calibrates:
        parser.error("--em-significance ranks the calibration's EM runs: not without a "
                     "calibration (--no-calibrate)")
    return level or None


def parse_args(description: str, default_runs: int):
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--runs", type=int, default=default_runs,
                        help=f"Monte Carlo runs per pipeline and condition (default {default_runs})")
    parser.add_argument("--chunk", type=int, default=None, help="runs per compiled chunk")
    parser.add_argument("--out", default=str(ROOT / "results"), help="results root folder")
    parser.add_argument("--set", dest="overrides", action="append", default=[],
                        metavar="KEY=VALUE", help="extra study overrides for every pipeline")
    return parser.parse_args()


def load_pipeline(name: str, args, extra=()):
    from jaxslam.studies import load_study_config

    overrides = [f"num_runs={args.runs}", *extra, *args.overrides]
    if args.chunk:
        overrides.append(f"chunk_size={args.chunk}")
    return load_study_config(CONFIGS / f"{name}.toml", overrides)


def run_pipelines(experiment: str, pipelines: dict, args) -> dict:
    """Run each named StudyConfig into results/<experiment>/<name>/. Returns name -> result."""
    from jaxslam.studies import run_study

    out = pathlib.Path(args.out) / experiment
    results = {}
    for name, config in pipelines.items():
        tick = time.perf_counter()
        results[name] = run_study(config, out / name)
        result = results[name]
        print(f"[{experiment}] {name}: {config.num_runs} runs x {len(config.conditions)} "
              f"conditions in {time.perf_counter() - tick:.1f} s (compile "
              f"{result.compile_seconds:.1f} s, filter {result.filter_seconds:.1f} s, simulator "
              f"{result.simulator_seconds:.1f} s)")
    return results


def combined_rows(pipelines: dict, results: dict) -> dict:
    """One table across pipelines and their sweep conditions: a 'pipeline' label column and a
    global 'condition' index (the plots label boxes by the 'pipeline' column)."""
    columns: dict[str, list] = {}
    index = 0
    for name, config in pipelines.items():
        table = results[name].table
        local = table.column("condition").to_numpy()
        labels = []
        for condition in config.conditions:
            suffix = ", ".join(f"{k}={v}" for k, v in condition.items())
            labels.append(f"{name} ({suffix})" if suffix else name)
        for key in table.column_names:
            if key in ("condition",):
                continue
            columns.setdefault(key, [])
        count = len(local)
        columns.setdefault("pipeline", []).extend(labels[c] for c in local)
        columns.setdefault("condition", []).extend(int(index + c) for c in local)
        for key in table.column_names:
            if key in ("condition",):
                continue
            columns[key].extend(table.column(key).to_pylist())
        for key in columns:
            if key not in table.column_names and key not in ("pipeline", "condition"):
                columns[key].extend([None] * count)
        index += len(config.conditions)
    return columns


def summary_table(columns: dict, metrics: list[str], throughput: dict | None = None) -> str:
    """Markdown: per pipeline, mean / median / 95% interval of each metric, and the filter's
    throughput (run-steps/s, from the chunks' metadata) when ``throughput`` maps pipeline
    labels to it."""
    from jaxslam.columns import column_unit

    labels = list(dict.fromkeys(columns["pipeline"]))
    pipeline = np.asarray(columns["pipeline"])
    throughput = throughput or {}
    header = ("| pipeline | runs | " + " | ".join(f"{m} [{column_unit(m)}]" for m in metrics)
              + (" | run-steps/s |" if throughput else " |"))
    lines = [header, "|" + "---|" * (len(metrics) + 2 + bool(throughput))]
    for label in labels:
        mask = pipeline == label
        cells = []
        for metric in metrics:
            values = np.asarray([np.nan if v is None else v for v in columns[metric]], float)[mask]
            cells.append(f"{np.mean(values):.3g} / {np.median(values):.3g} "
                         f"[{np.percentile(values, 2.5):.3g}, {np.percentile(values, 97.5):.3g}]")
        if throughput:
            cells.append(f"{throughput.get(label, float('nan')):,.0f}")
        lines.append(f"| {label} | {int(mask.sum())} | " + " | ".join(cells) + " |")
    lines.append("")
    lines.append("Cells: mean / median [2.5%, 97.5% percentiles] across runs.")
    return "\n".join(lines) + "\n"


def write_comparison(experiment: str, pipelines: dict, results: dict, metrics: list[str],
                     args, preamble: str = "") -> str:
    """table.md and box plots of each metric across pipelines; returns the Markdown."""
    from jaxslam.plots import plot_sweep_boxes

    out = pathlib.Path(args.out) / experiment
    from jaxslam.studies import filter_throughput

    columns = combined_rows(pipelines, results)
    throughput = {}
    for name, config in pipelines.items():
        for condition in config.conditions:
            suffix = ", ".join(f"{k}={v}" for k, v in condition.items())
            label = f"{name} ({suffix})" if suffix else name
            throughput[label] = filter_throughput(results[name].out_dir)
    text = (f"# {experiment}\n\n{preamble}\n\n"
            + summary_table(columns, metrics, throughput))
    (out / "table.md").write_text(text)
    for metric in metrics:
        values = {v for v in columns[metric] if v is not None}
        if values <= {0, 1, 0.0, 1.0, True, False} or metric.startswith("mean_mixture"):
            continue  # a rate or a setting: the table says it better than a box plot
        plot_sweep_boxes(columns, metric, out / f"box_{metric}.png", sweep=["pipeline"],
                         title=f"{experiment}: {metric}")
    print(text)
    return text
