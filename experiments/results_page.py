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
        for png in sorted(source.glob("*.png")):
            shutil.copy(png, target / png.name)
            lines += [f"![{study} {png.stem}](results/{study}/{png.name})", ""]
    (docs / "results.md").write_text("\n".join(lines))
    print(f"wrote {docs / 'results.md'}")


if __name__ == "__main__":
    main()
