"""The mixture proposal in the divergence regime (Geiser et al. 2023, section 5.2; issue 5).

Accurate lidar (Table 2), odometry noise 5x Table 1, few particles. For each particle count:
the seed paper's motion proposal (a Gaussian motion prior, no bursts, the first pose
sampled), the mixture with fixed phi in {0, 0.1, 0.3, 1} and the adaptive phi (both with
the default flags and bursts), and the default proposal (``FilterConfig()``: observation).
Divergence = final pose error over 1 m.

Run:  python experiments/mixture_proposal.py [--runs 1000] [--particles 10 30]
"""
import argparse
import sys

from common import load_pipeline, parse_args, run_pipelines, write_comparison

METRICS = ["diverged", "final_pose_error", "ate_rmse", "map_error", "mean_mixture_ratio"]


def pipelines_for(particles, args):
    out = {}
    for count in particles:
        p = f"filter.num_particles={count}"
        out[f"P{count}_motion"] = load_pipeline(
            "mixture", args, [p, "filter.proposal='motion'", "filter.anchor_empty_map=false",
                              "params.motion_outlier_probability=0.0", "sweep={}"])
        out[f"P{count}_default"] = load_pipeline(
            "mixture", args, [p, "filter.proposal='observation'", "sweep={}"])
        out[f"P{count}_mixture"] = load_pipeline("mixture", args, [p])
        out[f"P{count}_adaptive"] = load_pipeline(
            "mixture", args, [p, "filter.mixture_mode='adaptive'", "sweep={}"])
    return out


if __name__ == "__main__":
    extra = argparse.ArgumentParser(add_help=False)
    extra.add_argument("--particles", type=int, nargs="+", default=[10, 30])
    known, rest = extra.parse_known_args()
    sys.argv = [sys.argv[0], *rest]
    args = parse_args(__doc__, default_runs=1000)
    pipelines = pipelines_for(known.particles, args)
    results = run_pipelines("mixture_proposal", pipelines, args)
    write_comparison("mixture_proposal", pipelines, results, METRICS, args, preamble=(
        "Divergence regime: Table 2 lidar, odometry noise 5x Table 1 (robot and filter), "
        "analytic observations in a 60 m random forest, loop of 150 steps. `diverged` is the "
        "fraction of runs whose final pose error exceeds 1 m; the throughput column (run-steps per "
        "second of the batched filter) gives the cost per step."))
