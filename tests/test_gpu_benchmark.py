"""benchmarks/gpu_study.py at a tiny size on the CPU: it runs the study machinery in chunks and
writes compile time, run time and throughput to its JSON file, every number finite and
positive. The accelerator-size run is the script's own job."""
import json
import math

import pytest

TINY = ["--runs", "8", "--particles", "8", "--steps", "10", "--landmarks", "16",
        "--max-obs", "8", "--lidar-runs", "0"]
TIMES = ("first_chunk_s", "compile_s", "filter_compile_s", "run_s", "simulator_s", "filter_s")
RATES = ("runs_per_s", "particle_steps_per_s", "filter_runs_per_s",
         "filter_particle_steps_per_s")


@pytest.fixture(scope="module")
def gpu_study(load_benchmark):
    return load_benchmark("gpu_study")


def test_tiny_study_writes_finite_positive_timings(gpu_study, tmp_path):
    out = tmp_path / "gpu_study.json"
    returned = gpu_study.main(TINY + ["--chunk", "4", "--out", str(out)])
    written = json.loads(out.read_text())
    assert written["chunk_source"] == "--chunk" and written["backend"] == "cpu"
    case = written["cases"]["analytic"]
    assert list(written["cases"]) == ["analytic"]  # --lidar-runs 0 skips the lidar case
    assert (case["runs"], case["chunk"], case["chunks"], case["particles"], case["steps"]) \
        == (8, 4, 2, 8, 10)
    for name in TIMES + RATES:
        assert math.isfinite(case[name]) and case[name] > 0, (name, case[name])
    # The rates follow from the times: R P T particle-steps in run_s.
    assert math.isclose(case["particle_steps_per_s"], 8 * 8 * 10 / case["run_s"])
    assert case["filter_s"] <= case["run_s"] and case["compile_s"] < case["first_chunk_s"]
    assert returned["cases"]["analytic"] == case


def test_chunk_comes_from_the_flag_or_a_fallback_on_the_cpu(gpu_study):
    assert gpu_study.choose_chunk(gpu_study.parse_args(TINY + ["--chunk", "3", "--out", "x"]))[:2] \
        == (3, "--chunk")
    chunk, source, per_run = gpu_study.choose_chunk(gpu_study.parse_args(TINY + ["--out", "x"]))
    assert (chunk, per_run) == (8, None) and source.startswith("fallback")


def test_bad_sizes_are_refused(gpu_study):
    with pytest.raises(SystemExit):
        gpu_study.parse_args(["--runs", "0", "--out", "x"])


@pytest.mark.slow
def test_chunk_from_device_memory_uses_the_measured_program_size(gpu_study, monkeypatch):
    """Where the device reports its memory, the chunk is the largest multiple of the probe
    width whose measured filter program takes half of it."""
    monkeypatch.setattr(gpu_study, "device_memory_bytes", lambda: 2**30)
    args = gpu_study.parse_args(TINY + ["--runs", "100000", "--out", "x"])
    chunk, source, per_run = gpu_study.choose_chunk(args)
    assert source == "device memory" and per_run > 0
    assert chunk % gpu_study.PROBE_WIDTH == 0
    assert chunk * per_run <= 0.5 * 2**30 < (chunk + gpu_study.PROBE_WIDTH) * per_run
