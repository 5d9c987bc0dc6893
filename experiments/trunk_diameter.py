"""Trunk diameter in the final map against truth, per circle-fit method (Yang et al. 2023 reports
0.57 cm on real trees). Uses the Table 3 world with the loose boundary.

Run:  python experiments/trunk_diameter.py [--runs 200]
"""
from common import load_pipeline, parse_args, run_pipelines, write_comparison

METRICS = ["diameter_error", "num_diameters", "map_error", "final_pose_error"]

if __name__ == "__main__":
    args = parse_args(__doc__, default_runs=200)
    pipelines = {method: load_pipeline("table3", args, [f"scenario.detection='{method}'",
                                                        "name='trunk_diameter'"])
                 for method in ("centroid", "kasa", "geometric", "ransac")}
    results = run_pipelines("trunk_diameter", pipelines, args)
    write_comparison("trunk_diameter", pipelines, results, METRICS, args, preamble=(
        "diameter_error: mean |2 r_landmark - 2 r_tree| [m] over the best particle's landmarks "
        "matched to a tree (within 1 m) that carry a measured radius. The landmark radius is the "
        "running mean of the per-scan fitted radii. Centroid detection reports chord/2."))
