"""Collect every experiment's table and plots into docs/results.md (linked from the README).

Copies results/<study>/table.md (or results.md) and its PNGs into docs/results/<study>/ so the
page renders from a clean checkout, and writes the command that regenerates each study.

Run:  python experiments/results_page.py
"""
import pathlib
import shutil

ROOT = pathlib.Path(__file__).resolve().parent.parent
STUDIES = [
    ("demo", "jaxslam demo", "The README's main job: 64 runs on the default simulated forest."),
    ("table3", "python experiments/table3.py",
     "Seed 000 Table 3: centroids vs circle fits vs fits + loose boundary."),
    ("mixture_proposal", "python experiments/mixture_proposal.py",
     "The mixture proposal in the divergence regime (seed 000 section 5.2)."),
    ("association", "python experiments/association.py",
     "Stable matching vs greedy vs optimal assignment, hard vs loose boundary."),
    ("trunk_diameter", "python experiments/trunk_diameter.py",
     "Fitted trunk diameters in the final map against truth."),
    ("noise_model", "python experiments/noise_model.py",
     "Noise-model estimation (seed 000 section 4.1, Tables 1 and 2)."),
    ("scaling", "python experiments/scaling.py",
     "Step time, memory and throughput against P, M and K."),
    ("victoria_park", "python experiments/victoria_park.py",
     "FastSLAM on the Victoria Park dataset against GPS."),
]


FINDINGS = {
    "table3": (
        "**Findings.** Circle fits cut the final pose error about 12x (0.49 -> 0.042 m; paper "
        "~10x) and the map error about 7x (0.52 -> 0.078 m; paper >3x): the paper's direction "
        "is confirmed. The loose boundary did not halve the map error here (0.078 -> 0.075 m); "
        "it removes the last twins (0.027 -> 0.002 per run). Reason: the detector needs at "
        "least 4 beams per trunk, so trunks near the 20 m limit are rarely detected and the "
        "range-limit side effect the airlock guards against hardly occurs in this simulation."),
    "mixture_proposal": (
        "**Findings.** In the divergence regime the mixture beats the motion proposal: at P=10 "
        "divergence falls from 13.1% (motion) to 0.4% (phi=0.3) and 0.1% (phi=1), at P=30 from "
        "2.0% to 0.2%, for 1.7x the cost per step. phi=0 inside the mixture is worse than the "
        "plain motion proposal because it associates at the motion mean rather than at each "
        "sample. The adaptive ratio (mean phi ~0.16) sits between."),
    "association": (
        "**Findings.** Stable matching, greedy and optimal assignment give identical results "
        "on every run (well-separated trunks, accurate sensor), and stable matching is 4x "
        "faster than greedy and 7x faster than the Hungarian solver. The airlock halves "
        "redundant features (1.08 -> 0.54 per run) but leaves trees in the ring unmapped "
        "(GOSPA 2.1 -> 3.4)."),
    "trunk_diameter": (
        "**Findings.** Circle fits give 7.6-8.3 mm mean diameter error (seed 003: 5.7 mm on "
        "real trees with a 3D lidar); the centroid pipeline's chord/2 is off by 5.7 cm."),
    "victoria_park": (
        "**Findings.** The 2 m target is not reached; the tree-count and speed targets are. "
        "100 runs of the whole log at P = 100 (one vmapped call, 26 min here, keys "
        "independent of the tuning runs): GPS RMSE median 4.0 m, mean 4.8 m, 10-90% "
        "2.6-6.2 m, best 2.0 m, worst 17.5 m (8 runs over 10 m); final trees median 181 "
        "(174-200). The single run above (seed 0) is one of the bad ones (19.2 m: the second "
        "western leg swung out). A run takes 15-17 s after compilation. What changed from the "
        "previous 5.5 m median (10-90% 4.6-6.6 m), both measured on 16 runs with other keys "
        "first: (1) the steering bias varies along the log, and the default now fits it from "
        "the laser alone in 600-scan windows (steering_bias_profile): through the treeless "
        "corner into the first western leg (scans 4,650-5,300) it averages 2.2 mrad against "
        "the constant 4.1, and the filter follows the dead reckoning there for ~100 scans "
        "with almost no trunk turn estimates (16 runs: 5.8 -> 4.1 m; windows ending at each "
        "scan, usable online, 5.1 m); (2) trunks are matched out to 45 m instead of 30 m but "
        "only those within 30 m are penalised when unseen (new Params.miss_range): far trunks "
        "give heading, and counting their many misses had deleted the map (16 runs: 5.8 -> "
        "5.3 m alone, 3.6 m with (1)). Did not help (16 runs each, with (1) and (2)): motion "
        "noise halved again (6.9 m), windows of 400 / 900 scans (3.5 / 3.7 m), shifting the "
        "dead-reckoning clock by the laser-fitted 0.07 s (4.0 m); a random-walk bias smoothed "
        "by Kalman/RTS with a maximum-likelihood variance chose a constant. Checked and ruled "
        "out: a GPS antenna offset (fitted lever arm 0.3-0.7 m, RMSE change < 0.1 m) and a "
        "steering gain error (1.027, residual 4.38 -> 4.33 mrad). What still limits it: per "
        "500-scan window the error is 1.4-3.2 m (median over 16 runs) except around the two "
        "western legs (scans 4,500-5,500: 5.5-7.0 m; 5,500-6,500: 3.8-5.9 m), where the heading "
        "rests on dead reckoning and FastSLAM cannot bend the map built there back after the "
        "loop closes, as EKF-SLAM does through its correlations."),
    "scaling": (
        "**Findings.** Throughput grows with the batch (particles x runs) until about 25-30 k "
        "particles per step, then flattens near 150-180 M (particle, observation, landmark) "
        "evaluations per second; memory is linear in P M K."),
}


def main():
    docs = ROOT / "docs"
    lines = ["# Results", "",
             "Every table and plot below was produced on the project's 2-core CPU machine by the "
             "command shown (results land in `results/<study>/`; this page is rebuilt by "
             "`python experiments/results_page.py`). A study that has not been run yet says so.",
             ""]
    for study, command, about in STUDIES:
        source = ROOT / "results" / study
        lines += [f"## {study}", "", about, "", f"Regenerate: `{command}`", ""]
        table = next((source / name for name in ("table.md", "summary.md", "results.md")
                      if (source / name).exists()), None)
        if table is None:
            lines += ["_Not run in the current results._", ""]
            continue
        target = docs / "results" / study
        target.mkdir(parents=True, exist_ok=True)
        body = table.read_text().split("\n")
        body = [line for line in body if not line.startswith("# ")]
        lines += body + [""]
        if study in FINDINGS:
            lines += [FINDINGS[study], ""]
        for png in sorted(source.glob("*.png")):
            shutil.copy(png, target / png.name)
            lines += [f"![{study} {png.stem}](results/{study}/{png.name})", ""]
    (docs / "results.md").write_text("\n".join(lines))
    print(f"wrote {docs / 'results.md'}")


if __name__ == "__main__":
    main()
