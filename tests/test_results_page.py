"""experiments/results_page.py: a rebuild of docs/results.md never drops, unasked, a line that
no source it reads holds."""
import importlib.util
import pathlib

import pytest

SCRIPT = pathlib.Path(__file__).resolve().parent.parent / "experiments" / "results_page.py"


@pytest.fixture(scope="module")
def results_page():
    spec = importlib.util.spec_from_file_location("results_page_script", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _tree(root: pathlib.Path):
    """A checkout with the demo study's results (a table and a plot) and one page."""
    (root / "results" / "demo").mkdir(parents=True)
    (root / "results" / "demo" / "table.md").write_text("# demo\n| a | b |\n|---|---|\n| 1 | 2 |\n")
    (root / "results" / "demo" / "final.png").write_bytes(b"png")
    (root / "docs" / "results").mkdir(parents=True)
    (root / "docs" / "results" / "notes.md").write_text("## notes\n\nA hand-written page.\n")


def test_rebuild_keeps_hand_written_lines_unless_forced(results_page, tmp_path, capsys):
    _tree(tmp_path)
    page = tmp_path / "docs" / "results.md"
    assert results_page.main([], root=tmp_path) == 0
    built = page.read_text()
    assert "| 1 | 2 |" in built and "A hand-written page." in built
    assert "_Not run in the current results._" in built  # the studies without results
    assert (tmp_path / "docs" / "results" / "demo" / "final.png").read_bytes() == b"png"
    assert results_page.main([], root=tmp_path) == 0 and page.read_text() == built
    # A line written by hand under a generated section: the rebuild refuses and names it.
    edited = built.replace("| 1 | 2 |\n", "| 1 | 2 |\n\nA finding added by hand.\n")
    page.write_text(edited)
    (tmp_path / "docs" / "results" / "demo" / "final.png").unlink()
    capsys.readouterr()
    assert results_page.main([], root=tmp_path) == 1
    err = capsys.readouterr().err
    assert "not rebuilt. 1 line of" in err and "is in no source" in err and "by section: demo (1)" in err and "--force" in err
    assert page.read_text() == edited  # nothing written, nothing copied
    assert not (tmp_path / "docs" / "results" / "demo" / "final.png").exists()
    assert results_page.main(["--force"], root=tmp_path) == 0
    assert page.read_text() == built


def test_lost_lines_counts_by_section(results_page):
    old = "# Results\nintro\n## a\nkept\ngone 1\n\n## b\ngone 2\ngone 3\n"
    new = "# Results\nintro\n## a\nkept\n## b\n"
    assert results_page.lost_lines(old, new) == {"a": 1, "b": 2}
    assert results_page.lost_lines(old, old) == {}
    assert results_page.lost_lines("", new) == {}


def test_a_study_without_results_keeps_its_section(results_page, tmp_path):
    """table3 has no results in this checkout: its section of the current page (up to the
    next study or to a page's first line) comes back verbatim, hand-written lines and all,
    and the page that followed it is not taken into it."""
    _tree(tmp_path)
    page = tmp_path / "docs" / "results.md"
    results_page.main([], root=tmp_path)
    section = ["## table3", "", "Table 3.", "", "| old | table |", "", "A note by hand.", ""]
    built = page.read_text()
    start = built.index("## table3")
    end = built.index("## mixture_proposal")
    page.write_text(built[:start] + "\n".join(section) + "\n" + built[end:])
    edited = page.read_text()
    assert results_page.main([], root=tmp_path) == 0
    assert page.read_text() == edited
    sections = results_page.earlier_sections(edited, {"## notes"})
    assert sections["table3"] == section
    assert "A hand-written page." not in "\n".join(sections["victoria_park"])
