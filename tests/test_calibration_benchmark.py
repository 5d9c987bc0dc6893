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


def test_command_delay_auto_times_the_fit_and_the_calibration_at_the_lag(
        load_benchmark, tmp_path, monkeypatch, capsys):
    """``--command-delay auto``: per robot the stamped log's filter run (the unit), the lag fit
    with its default settings, the calibration at the fitted lag, and their sum over the unit
    (the data, the filter timing, the fit and ``bench`` stubbed: a 2 s filter run, a 10 s
    calibration)."""
    import numpy as np

    from jaxslam import command_delay, pipeline
    from jaxslam.datasets import mrclam, mrclam_convert

    benchmark = load_benchmark("calibration")
    calls, fits, timed = [], [], []
    # bench's own filter run (4 s) differs from the unit (2 s): the sum must use the unit
    monkeypatch.setattr(benchmark, "bench", lambda name, log, *args, **kwargs: (
        calls.append((name, log)) or (10.0, 4.0, f"params of {name}")))
    monkeypatch.setattr(benchmark, "filter_seconds", lambda *args: (
        timed.append(args[:3]) or (5.0, 2.0)))
    monkeypatch.setattr(benchmark, "starting_params", lambda config: "first settings")
    monkeypatch.setattr(mrclam, "read_mrclam", lambda folder, robot: robot)
    monkeypatch.setattr(mrclam_convert, "mrclam_steps", lambda raw, max_obs: raw)
    monkeypatch.setattr(mrclam_convert, "mrclam_log",
                        lambda raw, steps, command_delay: (raw, command_delay))
    monkeypatch.setattr(pipeline, "log_inputs", lambda log, config: (log, "inputs"))

    def fit(log_at, config, key):
        fits.append(log_at(0.5))
        return command_delay.DelayFit(0.25, np.array([0.0, 0.2, 0.4]), np.zeros(3),
                                      np.ones((3, 4)), False)

    monkeypatch.setattr(command_delay, "fit_log_command_delay", fit)
    benchmark.main(["--only", "mrclam", "--mrclam", str(tmp_path), "--robots", "3",
                    "--command-delay", "auto"])
    # the unit: a filter run of the log as stamped with the calibration's first settings
    assert timed == [((3, 0.0), "inputs", "first settings")]
    assert fits == [(3, 0.5)]
    assert calls == [("MRCLAM robot 3, commands +0.250 s late", (3, 0.25))]
    out = capsys.readouterr().out
    assert "lag fit 0.00 s (0.250 s from 3 candidates)" in out
    # the stub fit's few microseconds + 10 s over the 2 s filter run
    assert "fit 0.0 s (0.0x) + calibration at 0.250 s 5.0x = 10.0 s, " \
           "5.0x one filter run of the log as stamped" in out
