"""benchmarks/calibration.py's choice of logs: ``--only`` runs just the named ones, and a log
whose data folder is missing is skipped with a line that names the option to give. The timings
themselves are the script's own job (issue 17; docs/results.md, calibration_time): a real run
takes from about 5 s (the simulated loop's calibration) to 4.5-5.5 minutes (Victoria Park's)."""


def test_missing_data_folders_are_skipped_by_name(load_benchmark, tmp_path, capsys,
                                                  monkeypatch):
    benchmark = load_benchmark("calibration")
    calls = []
    monkeypatch.setattr(benchmark, "bench", lambda *args, **kwargs: calls.append(args[0]))
    missing = tmp_path / "absent"
    benchmark.main(["--only", "mrclam", "victoria_park", "--mrclam", str(missing),
                    "--victoria-park", str(missing)])
    out = capsys.readouterr().out
    assert calls == []  # the simulated loop was not asked for, the others have no data
    assert "MRCLAM: skipped" in out and "--mrclam DIR" in out
    assert "Victoria Park: skipped" in out and "--victoria-park DIR" in out
    assert str(missing) in out


def test_only_simulated_runs_the_simulated_loop_alone(load_benchmark, capsys, monkeypatch):
    benchmark = load_benchmark("calibration")
    calls = []
    monkeypatch.setattr(benchmark, "bench", lambda *args, **kwargs: calls.append(args[0]))
    monkeypatch.setenv("JAXSLAM_MRCLAM", "/nonexistent")
    benchmark.main(["--only", "simulated", "--particles", "8"])
    assert calls == ["simulated loop"]
    assert "skipped" not in capsys.readouterr().out


def test_robots_option_benches_each_named_robot(load_benchmark, tmp_path, monkeypatch):
    """``--robots 2 4``: one line per robot, each robot's own log (the loader and the inputs
    stubbed: no data needed)."""
    from jaxslam import pipeline
    from jaxslam.datasets import mrclam

    benchmark = load_benchmark("calibration")
    calls = []
    monkeypatch.setattr(benchmark, "bench", lambda *args, **kwargs: calls.append(args[:2]))
    monkeypatch.setattr(mrclam, "load_mrclam", lambda folder, robot: f"log of robot {robot}")
    monkeypatch.setattr(pipeline, "log_inputs", lambda log, config: (log,))
    benchmark.main(["--only", "mrclam", "--mrclam", str(tmp_path), "--robots", "2", "4"])
    assert calls == [("MRCLAM robot 2", "log of robot 2"), ("MRCLAM robot 4", "log of robot 4")]
