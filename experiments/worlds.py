"""Shared world against per-run worlds: the same filter on one forest and path for every run,
and on a forest and path drawn per run (scenario.world). The per-run spread includes the
worlds' luck; the shared one only the noise's.

Run:  python experiments/worlds.py [--runs 1000]
Writes results/worlds/table.md (mean, median, percentiles, and the standard deviation across
runs of each metric) and box plots.
"""
import numpy as np
from common import load_pipeline, parse_args, run_pipelines, write_comparison

METRICS = ["final_pose_error", "ate_rmse", "map_error", "redundant", "orphan",
           "num_trees_seen", "diverged"]
WORLD = ["scenario.path='random'"]


def spread_table(pipelines: dict, results: dict) -> str:
    """Markdown: standard deviation across runs (and the interquartile range) per metric."""
    lines = ["| pipeline | " + " | ".join(f"{m} std [IQR]" for m in METRICS) + " |",
             "|" + "---|" * (len(METRICS) + 1)]
    for name in pipelines:
        table = results[name].table
        cells = []
        for metric in METRICS:
            values = table.column(metric).to_numpy().astype(float)
            low, high = np.percentile(values, [25, 75])
            cells.append(f"{np.std(values, ddof=1):.3g} [{high - low:.3g}]")
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    args = parse_args(__doc__, default_runs=1000)
    pipelines = {world: load_pipeline("demo", args, WORLD + [f"scenario.world='{world}'"])
                 for world in ("shared", "per_run")}
    results = run_pipelines("worlds", pipelines, args)
    spread = spread_table(pipelines, results)
    write_comparison("worlds", pipelines, results, METRICS, args, preamble=(
        "The demo study's filter and scenario (random path) with one shared world and with a "
        "world drawn per run. Spread across runs:\n\n" + spread))
    print(spread)
