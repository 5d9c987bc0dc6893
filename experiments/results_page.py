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
        "**Findings.** The 2 m target is reached at the median by the smoothed estimate "
        "(2.02 m) but not by the online filter (4.05 m), and not by most runs: 45 of 100 "
        "smoothed runs are at or under 2 m. The tree-count and speed targets are met. 100 runs "
        "of the whole log at P = 100 (keys independent of the tuning runs; 20 runs vmapped at "
        "a time because each records its lineage): online weighted mean, GPS RMSE median "
        "4.05 m, 10-90% 2.60-6.17 m, worst 17.5 m; the best particle's history smoothed "
        "(jaxslam.smoothing: its associations fixed, the path and map re-solved by sparse "
        "Levenberg-Marquardt with Huber loss, one round of noise calibration from its own "
        "residuals, no GPS), median 2.02 m, mean 2.85 m, 10-90% 1.58-3.92 m, best 1.53 m, "
        "worst 15.7 m; 86 runs at or under 3 m, 5 over 10 m; smoothing beat the online path in "
        "99 of 100 runs. Trees: median 180 (173-200). One run (the seed-0 run above, a bad "
        "one: 19.2 m online, 17.4 m smoothed) takes 17.9-18.2 s of filtering plus 8.5-9.4 s of "
        "smoothing after a 5.4 s compile when it has the machine to itself (the tables' "
        "24.0 + 10.6 s and the Monte Carlo times were taken while other jobs shared the two "
        "cores). What the smoother fixes: a particle filter cannot "
        "move an old pose once the loop closes; least squares spreads the closure over the "
        "stretch with no trunks. Measured on 16 runs (keys fold_in(key(0), r)): online median "
        "3.62 m, smoothed with the filter's noise 2.43 m, with one calibration round 2.04 m "
        "(three rounds 2.00 m at twice the time; the translation scale then keeps growing). "
        "What still limits it: the smoothed runs are bimodal. Of the 16, seven are 1.56-1.75 m "
        "with every 500-scan window under 3 m. In the others the first western leg (scans "
        "4,700-5,200) is turned ~5-9 degrees as a rigid body: the trunks seen there tie the "
        "leg together, and in one such run 14 of the 135 landmarks seen there were also "
        "matched from outside it; removing those cross-links (a diagnosis against GPS, not a "
        "method; smoothing without calibration) gave 1.55 m instead of 2.69 m, so some of "
        "those associations are wrong, and the smoother keeps the filter's associations. "
        "Merging landmark identities within 1 m after smoothing made 3 of 4 runs worse "
        "(2.42 -> 2.62, 2.05 -> 2.34, 3.25 -> 3.70 m; 6.64 -> 6.23 m); a smaller Huber "
        "threshold did not help (16 runs: 2.07 m). "
        "Revising those loop closures inside the smoother (smooth_path(visit_gap=100): each "
        "landmark split into visits, tied by links with a redescending Geman-McClure loss so "
        "a contradicted loop closure is switched off; python experiments/victoria_park.py "
        "--smooth-visit-gap 100, same 100 keys) improved 73 runs and worsened 27: mean "
        "2.85 -> 2.77 m, 10% 1.58 -> 1.49 m, worst 15.7 -> 13.9 m, 46 runs at or under 2 m, "
        "but median 2.02 -> 2.10 m and 90% 3.92 -> 4.23 m, at twice the smoothing time "
        "(21 s a run), so it is an option, not the default. On the 16 tuning runs it had cut "
        "the mean 2.37 -> 2.07 m and the worst 6.64 -> 3.02 m (a run whose last 700 scans "
        "were 18 m off, with ~90 of its ~1,050 links dropped): the tuning did not carry "
        "over. "
        "Earlier changes, kept: the steering bias profile fitted from the laser in 600-scan "
        "windows, matching out to 45 m with misses counted within 30 m (Params.miss_range)."),
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
