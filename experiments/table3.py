"""Geiser et al. 2023, Table 3 on simulated forests: three pipelines on the same forests, paths and noise.

  centroid       trunk positions from cluster centroids, hard visibility boundary
  fits           trunk positions from circle fits (Kasa), hard boundary
  fits_boundary  circle fits plus the loose-boundary airlock (Geiser et al. 2023, section 3.1)

Run:  python experiments/table3.py [--runs 1000] [--world shared|per_run]
  --world shared   (default) one forest and loop path for every run: runs differ in noise only
  --world per_run  run i draws its own forest (scenario.world = "per_run"; lidar scans of each
                   run's own MJX forest); results in results/table3_per_run/
One pipeline alone:  jaxslam study experiments/configs/table3.toml \
        --set scenario.detection=centroid --set filter.boundary=hard
"""
import argparse
import sys

from common import load_pipeline, parse_args, run_pipelines, write_comparison

METRICS = ["final_pose_error", "map_error", "redundant", "orphan", "num_landmarks",
           "diameter_error"]
PIPELINES = {
    "centroid": ["scenario.detection='centroid'", "filter.boundary='hard'"],
    "fits": ["scenario.detection='kasa'", "filter.boundary='hard'"],
    "fits_boundary": ["scenario.detection='kasa'", "filter.boundary='loose'"],
}
PREAMBLE = (
    "Geiser et al. 2023, Table 3 (paper: final pose error 2.39 / 0.21 / 0.24 m, map error "
    "0.81 / 0.25 / 0.14 m, redundant 5 / 0 / 0, orphan 1 / 0 / 0 for centroid / "
    "cylinder fits / fits + boundary). Simulated 2D lidar (1440 beams, 20 m, 1 cm beam "
    "noise) in a 60 m random forest of 80 trunks, loop path of 200 steps; P=30, stable "
    "matching. The throughput column counts run-steps per second of the batched filter.")
PER_RUN = (" Per-run worlds: run i draws its own forest (scenario.world = \"per_run\"), so "
           "the spread across runs includes the spread across forests.")


def parse_world() -> str:
    """``--world`` (removed from ``sys.argv`` before the common options are parsed)."""
    parser = argparse.ArgumentParser(add_help=False)
    parser.add_argument("--world", choices=("shared", "per_run"), default="shared")
    known, rest = parser.parse_known_args()
    sys.argv = sys.argv[:1] + rest
    return known.world


if __name__ == "__main__":
    world = parse_world()
    args = parse_args(__doc__, default_runs=1000)
    experiment = "table3" if world == "shared" else "table3_per_run"
    pipelines = {name: load_pipeline("table3", args, extra + [f"scenario.world='{world}'"])
                 for name, extra in PIPELINES.items()}
    results = run_pipelines(experiment, pipelines, args)
    write_comparison(experiment, pipelines, results, METRICS, args,
                     preamble=PREAMBLE + (PER_RUN if world == "per_run" else ""))
