"""Scaling of one filter step with particles P, landmark slots M and observations K, and of a
batched study with the number of runs R: time, temporary memory and throughput, and where the
throughput curve bends.

Run:  python experiments/scaling.py
"""
import importlib.util
import pathlib

import numpy as np

from common import ROOT, parse_args

spec = importlib.util.spec_from_file_location("filter_step", ROOT / "benchmarks" / "filter_step.py")
bench = importlib.util.module_from_spec(spec)
spec.loader.exec_module(bench)

GRIDS = {
    "P": [(p, 64, 16) for p in (10, 30, 100, 300, 1000, 3000)],
    "M": [(300, m, 16) for m in (16, 32, 64, 128, 256)],
    "K": [(300, 64, k) for k in (4, 8, 16, 32)],
}


def main():
    args = parse_args(__doc__, default_runs=0)
    out = pathlib.Path(args.out) / "scaling"
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for axis, shapes in GRIDS.items():
        for shape in shapes:
            compile_s, step_s, temp_mib = bench.bench_step(*shape, repeats=10)
            rows.append((axis, *shape, compile_s, step_s, temp_mib))
    lines = ["# scaling", "", "One `step` with every landmark slot active (stable matching, "
             "motion proposal, float32, this 2-core CPU). Pair evaluations = P K M per step.", "",
             "| varied | P | M | K | compile [s] | step [ms] | particle-steps/s | M pair-evals/s "
             "| temp memory [MiB] |", "|---|---|---|---|---|---|---|---|---|"]
    for axis, p, m, k, compile_s, step_s, temp in rows:
        lines.append(f"| {axis} | {p} | {m} | {k} | {compile_s:.1f} | {1e3 * step_s:.2f} | "
                     f"{p / step_s:,.0f} | {p * m * k / step_s / 1e6:.1f} | {temp:.1f} |")
    lines += ["", "Batched runs (one compiled vmap over R runs of T=50 steps, P=30, M=64, K=16, "
              "stable matching, the default forest; the simulator is timed apart):", "",
              "| runs R | compile [s] | filter [s] | run-steps/s | particle-steps/s |",
              "|---|---|---|---|---|"]
    for runs in (1, 8, 64, 256, 1024):
        compile_s, filter_s, _, _ = bench.bench_batch(runs, runs, 30, 64, 16, 50)
        lines.append(f"| {runs} | {compile_s:.1f} | {filter_s:.2f} | {runs * 50 / filter_s:,.0f} | "
                     f"{runs * 50 * 30 / filter_s:,.0f} |")
    text = "\n".join(lines) + "\n"
    (out / "table.md").write_text(text)
    print(text)
    _plot(rows, out / "throughput.png")


def _plot(rows, path):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(14, 4.2))
    for ax, (axis, index) in zip(axes, (("P", 1), ("M", 2), ("K", 3))):
        sel = [r for r in rows if r[0] == axis]
        x = np.array([r[index] for r in sel], float)
        rate = np.array([r[1] * r[2] * r[3] / r[5] / 1e6 for r in sel])
        ax.plot(x, rate, "o-")
        ax.set_xscale("log", base=2)
        ax.set_xlabel({"P": "particles P (M=64, K=16)", "M": "landmark slots M (P=300, K=16)",
                       "K": "observations K (P=300, M=64)"}[axis])
        ax.set_ylabel("throughput [M (particle, obs, landmark) / s]")
        ax.grid(alpha=0.3)
    fig.suptitle("FastSLAM step throughput on a 2-core CPU (higher is better)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


if __name__ == "__main__":
    main()
