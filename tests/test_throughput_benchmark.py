"""benchmarks/throughput.py at a tiny size: its rows are consistent (a step's time is the run
time over T, the ratio is PythonRobotics' 27.4 ms over it) and every time finite and positive.
The full-size figures are the script's own job (issue 20; docs/results.md)."""
import json
import math
from types import SimpleNamespace

import numpy as np
import pytest


def test_tiny_single_and_batched_rows(load_benchmark, tmp_path):
    throughput = load_benchmark("throughput")
    out = tmp_path / "rows.json"
    rows = throughput.main(["--proposal", "motion", "--cases", "single", "batched",
                            "--runs", "2", "--steps", "5", "--json", str(out)])
    assert json.loads(out.read_text()) == rows
    single, batched = rows
    assert (single["case"], single["T"], batched["case"], batched["R"]) == ("single", 5,
                                                                          "batched", 2)
    for row in rows:
        for name in ("compile_s", "run_s", "ratio"):
            assert math.isfinite(row[name]) and row[name] > 0, (name, row[name])
    reference = throughput.PYTHONROBOTICS_STEP_S
    assert math.isclose(single["step_ms"], 1e3 * single["run_s"] / 5)
    assert math.isclose(single["ratio"], reference / (single["run_s"] / 5))
    # The fastest of the timed calls can be no slower than their median.
    assert single["repeats"] == 5
    assert 0 < single["step_ms_fastest"] <= single["step_ms"]
    assert math.isclose(single["ratio_fastest"], reference / (single["step_ms_fastest"] / 1e3))
    assert math.isclose(batched["run_step_us"], 1e6 * batched["run_s"] / 10)
    assert math.isclose(batched["particle_steps_per_s"], 2 * 100 * 5 / batched["run_s"])


def test_tiny_study_row_with_a_window_reports_what_the_window_cut(load_benchmark):
    """The study case at R 2 x T 5 with a window of 2 landmarks, less than the trees a step
    sees (the default forest shows up to K = 16): the row must say that the window left
    landmarks out, so that its speed is not read as the full association's."""
    throughput = load_benchmark("throughput")
    (row,) = throughput.main(["--proposal", "motion", "--cases", "study", "--runs", "2",
                              "--chunk", "2", "--steps", "5", "--association-window", "2"])
    assert (row["case"], row["association_window"], row["R"], row["T"]) == ("study", 2, 2, 5)
    assert row["window_cut"] > 0
    for window in ("0", "64"):  # no window, or one of all M = 64 slots: none applied
        (plain,) = throughput.main(["--proposal", "motion", "--cases", "study", "--runs", "2",
                                    "--chunk", "2", "--steps", "5", "--association-window",
                                    window])
        assert plain["association_window"] == 0 and plain["window_cut"] is None
    assert math.isclose(row["particle_steps_per_s"], 2 * 100 * 5 / row["run_s"])


def test_tiny_single_and_batched_rows_with_a_window(load_benchmark):
    """``--association-window`` reaches the single and batched cases too: a window of 2 of
    the M = 16 slots on 8-tree forests seen out to 20 m leaves landmarks out, and the rows say
    so; without a window the rows carry no cut."""
    throughput = load_benchmark("throughput")
    arguments = ["--proposal", "motion", "--cases", "single", "batched", "--runs", "2",
                 "--steps", "5", "--repeats", "1"]
    for row in throughput.main(arguments + ["--association-window", "2"]):
        assert row["association_window"] == 2 and row["window_cut"] > 0, row
    # No window, or one of at least the M = 16 slots, which the filter does not apply: the
    # rows say no window was used.
    for window in ("0", "16"):
        for row in throughput.main(arguments + ["--association-window", window]):
            assert row["association_window"] == 0 and row["window_cut"] is None, row


def test_single_case_at_several_particle_counts(load_benchmark):
    """``--single-particles`` gives one single row per P, in order, each with its own P."""
    throughput = load_benchmark("throughput")
    rows = throughput.main(["--proposal", "motion", "--cases", "single", "--steps", "3",
                            "--single-particles", "1", "4"])
    assert [(row["case"], row["P"]) for row in rows] == [("single", 1), ("single", 4)]
    assert all(math.isfinite(row["step_ms"]) and row["step_ms"] > 0 for row in rows)


def test_single_row_takes_the_median_and_the_fastest_of_the_timed_calls(load_benchmark,
                                                                         monkeypatch):
    """With the calls' times fixed (0.5, 0.1, 0.3, 0.2 s for a 4-step run), the row's step
    time is their median over T (62.5 ms) and its fastest step the minimum over T (25 ms),
    and ``--repeats`` reaches the timer."""
    throughput = load_benchmark("throughput")
    asked = []

    def fixed_times(fn, *args, repeats=3):
        asked.append(repeats)
        return 2.0, np.array([0.5, 0.1, 0.3, 0.2]), SimpleNamespace(window_cut=None)

    monkeypatch.setattr(throughput, "_timed", fixed_times)
    (row,) = throughput.main(["--proposal", "motion", "--cases", "single", "--steps", "4",
                              "--repeats", "4", "--single-particles", "2"])
    assert asked == [4] and row["repeats"] == 4
    assert math.isclose(row["step_ms"], 62.5) and math.isclose(row["step_ms_fastest"], 25.0)
    assert math.isclose(row["ratio_fastest"], throughput.PYTHONROBOTICS_STEP_S / 0.025)
    assert math.isclose(row["compile_s"], 2.0)


@pytest.mark.parametrize("arguments, message", [
    (["--repeats", "0"], "--repeats must be positive integers"),
    (["--single-particles", "0"], "every particle count must be a positive integer"),
])
def test_bad_arguments_are_refused_by_name(load_benchmark, capsys, arguments, message):
    throughput = load_benchmark("throughput")
    with pytest.raises(SystemExit) as exit_:
        throughput.main(["--cases", "single", *arguments])
    assert exit_.value.code == 2
    assert message in capsys.readouterr().err
