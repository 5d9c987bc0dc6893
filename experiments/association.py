"""Data association near the range limit in a dense forest: stable matching vs greedy nearest
neighbour vs optimal assignment, each with the hard and the loose boundary.

Run:  python experiments/association.py [--runs 200]
"""
from common import load_pipeline, parse_args, run_pipelines, write_comparison

METRICS = ["final_pose_error", "map_error", "redundant", "orphan", "gospa"]

if __name__ == "__main__":
    args = parse_args(__doc__, default_runs=200)
    pipelines = {f"{kind}_{boundary}": load_pipeline(
        "association", args, [f"filter.association='{kind}'", f"filter.boundary='{boundary}'"])
        for kind in ("stable", "greedy", "hungarian") for boundary in ("hard", "loose")}
    results = run_pipelines("association", pipelines, args)
    write_comparison("association", pipelines, results, METRICS, args, preamble=(
        "Dense forest (250 trunks in 60 m x 60 m), 10 m sensor range (many trunks cross the "
        "range limit), analytic observations, P=30."))
