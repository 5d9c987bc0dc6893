"""The ``jaxslam`` command: fast --help, lazy imports, bad configs exit 2, export, run, study."""
import subprocess
import sys
import time

import numpy as np
import pytest

from jaxslam import cli, plots

PYTHON = sys.executable
_HEAVY = ("jax", "matplotlib", "pyarrow", "jaxslam.studies", "jaxslam.filter", "jaxslam.plots",
          "sims.scenario", "tqdm")
_TINY_STUDY = ["--set", "num_runs=4", "--set", "chunk_size=2", "--set", "filter.num_particles=8",
               "--set", "filter.max_landmarks=24", "--set", "filter.max_obs=8",
               "--set", "scenario.num_steps=20", "--set", "scenario.num_trees=15",
               "--set", "scenario.size=30.0", "--set", "sweep.max_range=[10.0, 15.0]"]


def _python(code, **kwargs):
    return subprocess.run([PYTHON, "-c", code], capture_output=True, text=True, timeout=120,
                          **kwargs)


def _modules_after(statement):
    result = _python(f"import sys; {statement}; print(' '.join(sorted(sys.modules)))")
    assert result.returncode == 0, result.stderr
    return set(result.stdout.split())


def test_help_is_fast():
    tick = time.perf_counter()
    result = subprocess.run([PYTHON, "-m", "jaxslam.cli", "--help"], capture_output=True,
                            text=True, timeout=60)
    seconds = time.perf_counter() - tick
    assert result.returncode == 0, result.stderr
    for command in ("demo", "run", "study", "sweep", "bench", "export"):
        assert command in result.stdout
    # Issue 6 asks for < 2 s; 5 s leaves room for a loaded 2-core test machine while still
    # failing if --help imported the runner (JAX compile set-up, pyarrow, matplotlib: > 5 s).
    assert seconds < 5.0, f"jaxslam --help took {seconds:.2f} s"


def test_cli_module_imports_nothing_heavy_itself():
    baseline = _modules_after("import jaxslam")
    with_cli = _modules_after("import jaxslam.cli")
    added = {name for name in with_cli - baseline
             if any(name == h or name.startswith(h + ".") for h in _HEAVY)}
    assert not added, f"importing jaxslam.cli pulled in {sorted(added)}"


def test_cli_import_does_not_import_jax():
    if "jax" in _modules_after("import jaxslam"):
        pytest.skip("jaxslam/__init__.py imports JAX eagerly (via jaxslam.types); a lazy "
                    "module __getattr__ there is needed before --help can skip JAX")
    assert "jax" not in _modules_after("import jaxslam.cli")


@pytest.mark.parametrize("overrides, named", [
    (["filter.num_particle=8"], ["filter.num_particle", "num_particles"]),
    (["filter.association=foo"], ["association", "'foo'", "stable", "hungarian"]),
    (["scenario.path=spiral"], ["scenario.path", "lawnmower"]),
    (["params.not_a_param=3"], ["params.not_a_param", "max_range"]),
    (["num_run=3"], ["'num_run'", "num_runs"]),
])
def test_bad_config_exits_2_naming_the_key(tmp_path, capsys, overrides, named):
    config = tmp_path / "study.toml"
    config.write_text("num_runs = 4\n")
    args = ["study", str(config), "--out", str(tmp_path / "out")]
    for item in overrides:
        args += ["--set", item]
    assert cli.main(args) == 2
    err = capsys.readouterr().err
    for text in named:
        assert text in err
    assert "Traceback" not in err


def test_bad_config_file_key_in_subprocess_has_no_traceback(tmp_path):
    config = tmp_path / "study.toml"
    config.write_text("num_runs = 4\n[filter]\nnum_particle = 8\n")
    result = subprocess.run([PYTHON, "-m", "jaxslam.cli", "study", str(config)],
                            capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert result.returncode == 2
    assert "filter.num_particle" in result.stderr and "num_particles" in result.stderr
    assert "Traceback" not in result.stderr
    assert not (tmp_path / "results").exists()


def test_missing_config_and_sweep_without_sweep_section(tmp_path, capsys):
    assert cli.main(["study", str(tmp_path / "nope.toml")]) == 2
    assert "nope.toml" in capsys.readouterr().err
    config = tmp_path / "study.toml"
    config.write_text("num_runs = 4\n")
    assert cli.main(["sweep", str(config), "--out", str(tmp_path / "out")]) == 2
    assert "[sweep] section" in capsys.readouterr().err


def test_demo_config_overrides():
    from jaxslam import studies

    demo = studies.demo_study_config()
    assert cli.demo_config([]) == demo
    changed = cli.demo_config(["num_runs=8", "filter.num_particles=16",
                               "sweep.max_range=[10.0, 20.0]"])
    assert changed.num_runs == 8 and changed.filter.num_particles == 16
    assert changed.conditions == [{"max_range": 10.0}, {"max_range": 20.0}]
    # everything not overridden keeps the demo's value
    assert changed.filter.max_landmarks == demo.filter.max_landmarks
    assert changed.scenario == demo.scenario and changed.name == demo.name
    with pytest.raises(cli.UsageError, match="num_particle'.*num_particles"):
        cli.demo_config(["filter.num_particle=16"])


def _example_run(steps=25):
    angle = np.linspace(-3.0, 3.0, steps + 1)
    truth = np.stack([np.cos(angle), np.sin(angle), angle], 1)
    return dict(truth_pose=truth, mean_pose=truth[1:] + 0.01, landmark_mean=np.zeros((4, 2)),
                landmark_cov=np.tile(np.eye(2), (4, 1, 1)), active=np.ones(4, bool),
                tree_centres=np.zeros((3, 2)), tree_radii=np.full(3, 0.2))


def test_export_tum(tmp_path, capsys):
    example = _example_run()
    np.savez(tmp_path / "example_run.npz", **example)
    assert cli.main(["export", str(tmp_path), "--format", "tum", "--dt", "0.1",
                     "--out", str(tmp_path / "tum")]) == 0
    for name, poses, first_step in (("truth", example["truth_pose"], 0),
                                    ("estimate", example["mean_pose"], 1)):
        text = (tmp_path / "tum" / f"{name}.tum").read_text()
        lines = [line for line in text.splitlines() if not line.startswith("#")]
        rows = np.array([[float(v) for v in line.split()] for line in lines])
        assert rows.shape == (len(poses), 8)
        np.testing.assert_allclose(rows[:, 0], 0.1 * (first_step + np.arange(len(poses))),
                                   atol=1e-9)
        np.testing.assert_allclose(rows[:, 1:3], poses[:, :2], atol=1e-8)
        np.testing.assert_array_equal(rows[:, 3:6], 0.0)  # z, qx, qy
        np.testing.assert_allclose(np.hypot(rows[:, 6], rows[:, 7]), 1.0, atol=1e-8)
        yaw = 2.0 * np.arctan2(rows[:, 6], rows[:, 7])
        np.testing.assert_allclose(np.angle(np.exp(1j * (yaw - poses[:, 2]))), 0.0, atol=1e-8)
    assert "evo_ape" in capsys.readouterr().out


def test_export_errors(tmp_path, capsys):
    assert cli.main(["export", str(tmp_path)]) == 2
    assert "example_run.npz" in capsys.readouterr().err
    example = _example_run()
    example["mean_pose"] = example["mean_pose"][:, :2]
    np.savez(tmp_path / "example_run.npz", **example)
    assert cli.main(["export", str(tmp_path)]) == 2
    assert "mean_pose has shape (25, 2)" in capsys.readouterr().err
    with pytest.raises(SystemExit) as error:
        cli.main(["export", str(tmp_path), "--format", "csv"])
    assert error.value.code == 2


def test_bench_imports_script_by_path(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("JAXSLAM_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.setattr(cli.bench, "BENCHMARK_PATH", tmp_path / "missing.py")
    assert cli.main(["bench"]) == 2
    assert "missing.py" in capsys.readouterr().err
    script = tmp_path / "filter_step.py"
    script.write_text("def main(argv):\n    print('bench argv', argv)\n    return 0\n")
    monkeypatch.setattr(cli.bench, "BENCHMARK_PATH", script)
    try:
        assert cli.main(["bench", "--runs", "10"]) == 0
    finally:
        _reset_cache_config()
    assert "bench argv ['--runs', '10']" in capsys.readouterr().out


def _reset_cache_config():
    import jax

    jax.config.update("jax_compilation_cache_dir", None)


def test_enable_compilation_cache(tmp_path, monkeypatch):
    import jax

    monkeypatch.setenv("JAXSLAM_CACHE_DIR", str(tmp_path / "c"))
    try:
        path = cli.enable_compilation_cache()
        assert path == tmp_path / "c" and path.is_dir()
        assert jax.config.jax_compilation_cache_dir == str(tmp_path / "c")
    finally:
        _reset_cache_config()
    monkeypatch.delenv("JAXSLAM_CACHE_DIR")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert cli.cache_dir() == tmp_path / "xdg" / "jaxslam" / "jax"


def _straight_log(steps=15, num_obs=6):
    """A robot driving along +x at 0.5 m/step past six trees; noise-free observations."""
    from jaxslam.datasets.log_format import RobotLog

    trees = np.array([[1.0, 2.0], [3.0, -2.0], [5.0, 2.5], [7.0, -1.5], [9.0, 2.0], [4.0, 4.0]])
    truth = np.stack([0.5 * np.arange(1, steps + 1), np.zeros(steps), np.zeros(steps)], 1)
    offset = trees[None] - truth[:, None, :2]
    z = np.stack([np.hypot(offset[..., 0], offset[..., 1]),
                  np.arctan2(offset[..., 1], offset[..., 0])], -1)
    return RobotLog(time=np.arange(steps, dtype=float), motion_model="odometry",
                    controls=np.tile([0.0, 0.5, 0.0], (steps, 1)), obs_z=z[:, :num_obs],
                    obs_valid=z[:, :num_obs, 0] < 8.0, truth_pose=truth, truth_landmarks=trees)


def _run_on_straight_log(tmp_path, monkeypatch, capsys, *extra, log=None):
    """``jaxslam run --data`` on ``_straight_log`` with 8 particles: (status, printed metrics)."""
    from jaxslam.datasets.log_format import save_log

    monkeypatch.setenv("JAXSLAM_CACHE_DIR", str(tmp_path / "cache"))
    save_log(tmp_path / "log.npz", _straight_log() if log is None else log)
    try:
        status = cli.main(["run", "--data", str(tmp_path / "log.npz"), "--out",
                           str(tmp_path / "out"), *extra, "--set", "filter.num_particles=8",
                           "--set", "filter.max_landmarks=12"])
    finally:
        _reset_cache_config()
    out = capsys.readouterr().out
    return status, dict(line.split() for line in out.splitlines() if len(line.split()) == 2)


def test_run_on_a_log(tmp_path, monkeypatch, capsys):
    status, values = _run_on_straight_log(tmp_path, monkeypatch, capsys)
    assert status == 0
    # Noise-free observations and exact odometry: the filter must stay within a few cm.
    assert float(values["final_pose_error"]) < 0.2
    assert float(values["ate_rmse"]) < 0.2
    assert int(float(values["num_landmarks"])) >= 5
    assert (tmp_path / "out" / "map.png").stat().st_size > 10_000
    assert cli.main(["export", str(tmp_path / "out"), "--out", str(tmp_path / "tum")]) == 0
    assert "smoothed_ate_rmse" not in values


def test_run_on_a_log_with_smoothing(tmp_path, monkeypatch, capsys):
    status, values = _run_on_straight_log(tmp_path, monkeypatch, capsys, "--smooth",
                                          "--no-calibrate")
    assert status == 0
    # Exact odometry and noise-free observations: the smoothed history sits on the truth
    # (to the few cm the filter's sampled poses leave) like the online estimate.
    assert float(values["smoothed_ate_rmse"]) < 0.2
    saved = np.load(tmp_path / "out" / "example_run.npz")
    assert saved["smoothed_pose"].shape == saved["mean_pose"].shape
    assert cli.main(["run", "--smooth"]) == 2
    assert "--data" in capsys.readouterr().err


def test_run_on_a_log_with_visit_links(tmp_path, monkeypatch, capsys):
    from jaxslam import smoothing

    seen = {}
    smooth_lineage = smoothing.smooth_lineage

    def spy(*args, **options):
        seen.update(options)
        return smooth_lineage(*args, **options)

    monkeypatch.setattr(smoothing, "smooth_lineage", spy)
    status, values = _run_on_straight_log(tmp_path, monkeypatch, capsys, "--smooth",
                                          "--visit-gap", "3", "--no-calibrate")
    assert status == 0 and seen["visit_gap"] == 3  # the option reaches the smoother
    # The straight log's associations are right: the smoothed history stays within the same
    # few cm of the truth as without links.
    assert float(values["smoothed_ate_rmse"]) < 0.2
    log = str(tmp_path / "log.npz")
    assert cli.main(["run", "--data", log, "--visit-gap", "3"]) == 2
    assert "needs --smooth" in capsys.readouterr().err
    assert cli.main(["run", "--data", log, "--smooth", "--visit-gap", "0"]) == 2
    assert "at least 1 step" in capsys.readouterr().err


def test_run_on_a_log_with_loop_closure(tmp_path, monkeypatch, capsys):
    status, values = _run_on_straight_log(tmp_path, monkeypatch, capsys, "--smooth",
                                          "--close-loops", "--no-calibrate")
    assert status == 0
    # A straight drive never returns: no closure may be made, and the smoothed history stays
    # within the same few cm of the truth as without loop closure.
    assert float(values["loop_closures"]) == 0 and float(values["landmarks_joined"]) == 0
    assert float(values["smoothed_ate_rmse"]) < 0.2
    log, out = str(tmp_path / "log.npz"), str(tmp_path / "bad")
    assert cli.main(["run", "--data", log, "--close-loops", "--out", out]) == 2
    assert "needs --smooth" in capsys.readouterr().err
    assert cli.main(["run", "--data", log, "--smooth", "--close-loops", "--visit-gap",
                     "3", "--out", out]) == 2
    assert "choose one" in capsys.readouterr().err
    assert cli.main(["run", "--close-loops", "--out", out]) == 2
    assert "--data" in capsys.readouterr().err


def test_run_on_a_log_with_trunk_radii(tmp_path, monkeypatch, capsys):
    # docs/log_format.md: a log's obs_radius joins association when params.radius_noise is
    # set. The setting must reach the filter, and with radii that agree (each tree its own
    # constant radius) the run stays within the same few cm as without them.
    import jaxslam.pipeline

    seen = {}
    run_filter = jaxslam.pipeline.run_filter

    def spy(config, key, params, *args, **options):
        seen["radius_noise"] = float(params.radius_noise)
        seen["gate"] = float(params.association_gate)
        return run_filter(config, key, params, *args, **options)

    monkeypatch.setattr(jaxslam.pipeline, "run_filter", spy)
    log = _straight_log()
    radius = np.broadcast_to([0.1, 0.2, 0.3, 0.15, 0.25, 0.35], log.obs_valid.shape)
    status, values = _run_on_straight_log(
        tmp_path, monkeypatch, capsys, "--set", "params.radius_noise=0.07", "--set",
        "params.association_gate=25", "--no-calibrate",
        log=log._replace(obs_radius=np.array(radius)))
    assert status == 0
    assert seen == {"radius_noise": pytest.approx(0.07), "gate": pytest.approx(25.0)}
    assert float(values["ate_rmse"]) < 0.2
    assert int(float(values["num_landmarks"])) >= 5


def test_run_on_a_bad_log(tmp_path, capsys):
    np.savez(tmp_path / "log.npz", time=np.arange(3.0))
    assert cli.main(["run", "--data", str(tmp_path / "log.npz")]) == 2
    assert "missing required key" in capsys.readouterr().err


# ~28 s of CPU but 75-85 s of wall time on the shared 2-core machine (two compiles: simulator
# and the vmapped chunk), so it lives in the slow tier.
@pytest.mark.slow
def test_tiny_study_end_to_end_and_resume(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("JAXSLAM_CACHE_DIR", str(tmp_path / "cache"))
    config = tmp_path / "tiny.toml"
    config.write_text('name = "tiny"\n')
    out = tmp_path / "out"
    args = ["sweep", str(config), "--out", str(out), "--quiet"] + _TINY_STUDY
    try:
        assert cli.main(args) == 0
        printed = capsys.readouterr().out
        assert "| setting | metric |" in printed and "max_range=10.0" in printed
        for name in ("study.toml", "provenance.toml", "summary.md", "example_run.npz", "map.png",
                     "error_vs_time.png", "box_final_pose_error.png"):
            assert (out / name).is_file(), name
        table = plots.read_study_table(out).to_pydict()
        pairs = sorted(zip(table["condition"], table["run_id"]))
        assert pairs == [(c, r) for c in (0, 1) for r in range(4)]
        stamps = {p.name: p.stat().st_mtime_ns for p in out.glob("runs/chunk-*.parquet")}
        assert cli.main(args) == 0  # resume: every chunk is on disk, none rewritten
        assert stamps == {p.name: p.stat().st_mtime_ns for p in out.glob("runs/chunk-*.parquet")}
        # A different study into the same folder is refused, not overwritten.
        assert cli.main(args + ["--set", "seed=1"]) == 2
        assert "different study" in capsys.readouterr().err
    finally:
        _reset_cache_config()


@pytest.mark.slow
def test_run_default_scenario(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("JAXSLAM_CACHE_DIR", str(tmp_path / "cache"))
    small = [a for a in _TINY_STUDY if not a.startswith("sweep.")][:-1]  # drop the sweep pair
    try:
        assert cli.main(["run", "--out", str(tmp_path / "run")] + small) == 0
    finally:
        _reset_cache_config()
    values = dict(line.split() for line in capsys.readouterr().out.splitlines()
                  if len(line.split()) == 2)
    assert 0.0 <= float(values["final_pose_error"]) < 5.0
    assert (tmp_path / "run" / "map.png").stat().st_size > 10_000


def _noisy_log(steps=150, range_std=0.05, seed=3):
    """A user's own log: a loop past 24 trees, 5 cm range noise, noisy odometry, truth."""
    from jaxslam.datasets.log_format import RobotLog

    rng = np.random.default_rng(seed)
    angle = np.linspace(0.0, 2 * np.pi, 24, endpoint=False)
    trees = np.stack([(10 + 4 * (np.arange(24) % 2)) * np.cos(angle),
                      (10 + 4 * (np.arange(24) % 2)) * np.sin(angle)], 1)
    phi = 2 * np.pi * np.arange(steps + 1) / steps
    truth = np.stack([12 * np.cos(phi), 12 * np.sin(phi), phi + np.pi / 2], 1)
    truth[:, 2] = (truth[:, 2] + np.pi) % (2 * np.pi) - np.pi
    trans = np.full(steps, 2 * 12 * np.sin(np.pi / steps))
    turn = np.full(steps, 2 * np.pi / steps)
    controls = np.stack([0.5 * turn + rng.normal(0, 0.01, steps),
                         trans * (1 + rng.normal(0, 0.02, steps)),
                         0.5 * turn + rng.normal(0, 0.01, steps)], 1)
    offset = trees[None] - truth[1:, None, :2]
    distance = np.hypot(offset[..., 0], offset[..., 1])
    bearing = np.arctan2(offset[..., 1], offset[..., 0]) - truth[1:, None, 2]
    order = np.argsort(distance, axis=1)[:, :8]
    d = np.take_along_axis(distance, order, 1)
    b = np.take_along_axis(bearing, order, 1)
    z = np.stack([d + rng.normal(0, range_std, d.shape),
                  (b + rng.normal(0, 0.005, b.shape) + np.pi) % (2 * np.pi) - np.pi], -1)
    return RobotLog(time=np.arange(steps, dtype=float), motion_model="odometry",
                    controls=controls, obs_z=z, obs_valid=d < 8.0, truth_pose=truth[1:],
                    truth_landmarks=trees, initial_pose=truth[0])


def _run_noisy(tmp_path, monkeypatch, capsys, *extra):
    from jaxslam.datasets.log_format import save_log

    monkeypatch.setenv("JAXSLAM_CACHE_DIR", str(tmp_path / "cache"))
    save_log(tmp_path / "noisy.npz", _noisy_log())
    try:
        status = cli.main(["run", "--data", str(tmp_path / "noisy.npz"), "--out",
                           str(tmp_path / "out"), "--set", "filter.num_particles=16",
                           "--set", "filter.max_landmarks=48", *extra])
    finally:
        _reset_cache_config()
    out = capsys.readouterr().out
    return status, out, dict(line.split() for line in out.splitlines()
                             if len(line.split()) == 2)


def test_run_calibrates_a_user_log_by_default(tmp_path, monkeypatch, capsys):
    from jaxslam import pipeline

    # What each run tells its warnings: calibrated (or a saved calibration reused), or not.
    told, real_warnings = [], pipeline.run_warnings

    def spy(*args, **kwargs):
        told.append(kwargs["calibrated"])
        return real_warnings(*args, **kwargs)

    monkeypatch.setattr(pipeline, "run_warnings", spy)
    # The log's noise (5 cm range, 0.005 rad bearing, 1 cm / 2 % odometry) is given nowhere.
    status, out, calibrated = _run_noisy(tmp_path, monkeypatch, capsys)
    assert status == 0
    assert "calibration:" in out and "range_noise" in out
    saved = tmp_path / "out" / "calibrated_params.toml"
    assert saved.is_file() and (tmp_path / "out" / "metrics.json").is_file()
    # The same filter given the true noise by hand.
    status, _, given = _run_noisy(
        tmp_path, monkeypatch, capsys, "--no-calibrate", "--set", "params.range_noise=[0, 0.05]",
        "--set", "params.bearing_noise=[0, 0.005]", "--set", "params.rot1_noise=[0, 0, 0.01]",
        "--set", "params.rot2_noise=[0, 0, 0.01]", "--set", "params.trans_noise=[0.02, 0, 0]")
    assert status == 0
    # Acceptance of the calibration: within 1.5x of the result with the true noise (plus
    # 2 cm: both are a few cm, where one particle's luck moves the ratio).
    assert float(calibrated["ate_rmse"]) <= 1.5 * float(given["ate_rmse"]) + 0.02
    assert int(float(calibrated["num_landmarks"])) >= 0.8 * 24
    # --params reuses the saved calibration: same settings, same key, same run.
    status, out, reused = _run_noisy(tmp_path, monkeypatch, capsys, "--params", str(saved))
    assert status == 0 and "calibration:" not in out
    assert reused["ate_rmse"] == calibrated["ate_rmse"]
    # ... and at another particle count (docs/cli.md: calibrate small, filter large): the
    # later --set wins, the file's settings are used as they are, nothing is calibrated.
    status, out, larger = _run_noisy(tmp_path, monkeypatch, capsys, "--params", str(saved),
                                     "--set", "filter.num_particles=48")
    assert status == 0 and "calibration:" not in out
    assert larger["ate_rmse"] != calibrated["ate_rmse"]  # another filter: 48 particles
    # The file's settings, not the config's: the same 48 particles with the library's
    # defaults run another filter again.
    status, _, defaults = _run_noisy(tmp_path, monkeypatch, capsys, "--no-calibrate",
                                     "--set", "filter.num_particles=48")
    assert status == 0 and defaults["ate_rmse"] != larger["ate_rmse"]
    # A params file written by hand (no [calibration] table) is not taken as calibrated.
    by_hand = tmp_path / "by_hand.toml"
    by_hand.write_text("[params]\nrange_noise = [0.0, 0.05]\n")
    status, _, _ = _run_noisy(tmp_path, monkeypatch, capsys, "--params", str(by_hand))
    assert status == 0
    # calibrated, given by hand, reused twice, defaults, a hand-written file
    assert told == [True, False, True, True, False, False]


def test_defaults_on_a_user_log_warn_in_plain_words(tmp_path, monkeypatch, capsys):
    # The library defaults (1 cm floor at short range) are 5x too tight for this log:
    # observations of a tree keep starting new landmarks that are deleted again, and the
    # weights collapse; the run must say so.
    # The seed paper's motion proposal: its weights collapse here (the default observation
    # proposal keeps them, but the map churn warning below fires for both).
    status, out, values = _run_noisy(tmp_path, monkeypatch, capsys, "--no-calibrate",
                                     "--set", "filter.proposal='motion'")
    assert status == 0
    assert "WARNING: landmarks were started and deleted over and over" in out
    assert "WARNING: the effective sample size collapsed" in out
    assert int(values["landmarks_started"]) > 3 * int(float(values["num_landmarks"]))


def test_calibrate_command_writes_params_that_run_reads(tmp_path, monkeypatch, capsys):
    from jaxslam import pipeline
    from jaxslam.datasets.log_format import save_log

    monkeypatch.setenv("JAXSLAM_CACHE_DIR", str(tmp_path / "cache"))
    save_log(tmp_path / "noisy.npz", _noisy_log())
    try:
        status = cli.main(["calibrate", "--data", str(tmp_path / "noisy.npz"), "--out",
                           str(tmp_path / "p.toml"), "--set", "filter.num_particles=16",
                           "--set", "filter.max_landmarks=48"])
    finally:
        _reset_cache_config()
    assert status == 0
    out = capsys.readouterr().out
    assert "calibration: likelihood over noise scales" in out
    # Each fitted group's typical std with its stated 95 % interval, in percent.
    stated = {line.split()[0]: line.split() for line in out.splitlines()
              if line.startswith("    ") and "+-" in line}
    assert set(stated) == {"heading", "translation", "range", "bearing"}
    assert stated["range"][2] == "m" and stated["bearing"][2] == "rad"
    assert all(float(words[1]) > 0 and 0 < float(words[4]) < 100 and words[5] == "%"
               for words in stated.values())
    params = pipeline.load_params(tmp_path / "p.toml")
    # The true range std is 5 cm at every distance (2-8 m here); the fit's std at 5 m is
    # within 30 % (about 400 associated observations and a two-term fit).
    std_5m = float(params.range_noise[0]) * 5 + float(params.range_noise[1])
    assert 0.035 <= std_5m <= 0.065
    assert cli.main(["calibrate", "--data", str(tmp_path / "missing.npz"), "--out",
                     str(tmp_path / "q.toml")]) == 2


def test_calibrate_without_the_scale_search(tmp_path, monkeypatch, capsys):
    from jaxslam.datasets.log_format import save_log

    monkeypatch.setenv("JAXSLAM_CACHE_DIR", str(tmp_path / "cache"))
    save_log(tmp_path / "noisy.npz", _noisy_log())
    try:
        status = cli.main(["calibrate", "--data", str(tmp_path / "noisy.npz"), "--out",
                           str(tmp_path / "p.toml"), "--set", "filter.num_particles=16",
                           "--set", "filter.max_landmarks=48", "--no-scale-search"])
    finally:
        _reset_cache_config()
    out = capsys.readouterr().out
    assert status == 0 and (tmp_path / "p.toml").is_file()
    assert "likelihood over noise scales" not in out and "noise scale" not in out
    # The same flag on `run --data`: calibrated, no search.
    status, out, _ = _run_noisy(tmp_path, monkeypatch, capsys, "--no-scale-search")
    assert status == 0 and "calibration:" in out
    assert "likelihood over noise scales" not in out and "noise scale" not in out


def test_calibrate_with_bootstrap_intervals(tmp_path, monkeypatch, capsys):
    """``--bootstrap B`` prints, per noise group, EM's estimate, the replicates' median over
    it and an interval in the group's unit; B < 2 is refused before any work."""
    from jaxslam.datasets.log_format import save_log

    monkeypatch.setenv("JAXSLAM_CACHE_DIR", str(tmp_path / "cache"))
    save_log(tmp_path / "noisy.npz", _noisy_log())
    base = ["calibrate", "--data", str(tmp_path / "noisy.npz"), "--out",
            str(tmp_path / "p.toml"), "--set", "filter.num_particles=16", "--set",
            "filter.max_landmarks=48", "--no-scale-search"]
    try:
        assert cli.main(base + ["--bootstrap", "1"]) == 2
        assert "--bootstrap needs B >= 2" in capsys.readouterr().err
        status = cli.main(base + ["--bootstrap", "2"])
    finally:
        _reset_cache_config()
    out = capsys.readouterr().out
    assert status == 0 and (tmp_path / "p.toml").is_file()
    assert "replicate 2 of 2" in out
    # The settings are written before the replicates run (a long bootstrap never loses them).
    assert out.index("wrote ") < out.index("replicate 1 of 2")
    rows = {line.split()[0]: line.split() for line in out.splitlines()
            if line.startswith("    ") and "replicates x" in line}
    assert set(rows) == {"heading", "translation", "range", "bearing"}
    for words in rows.values():  # name, estimate, unit, "replicates", xR, [lo, hi], unit
        lower, upper = float(words[5].strip("[,")), float(words[6].strip("]"))
        assert float(words[1]) > 0 and 0 < lower <= upper and words[7] == words[2]


def test_params_file_errors(tmp_path):
    from jaxslam import pipeline

    (tmp_path / "bad.toml").write_text("[params]\nnot_a_field = 1.0\n")
    with pytest.raises(ValueError, match="not_a_field"):
        pipeline.load_params(tmp_path / "bad.toml")
    (tmp_path / "empty.toml").write_text("x = 1\n")
    with pytest.raises(ValueError, match=r"no \[params\] table"):
        pipeline.load_params(tmp_path / "empty.toml")
    with pytest.raises(ValueError, match="cannot read"):
        pipeline.load_params(tmp_path / "absent.toml")


def test_calibration_print_divides_the_search_scale_out(capsys):
    """The printed std is EM's (the interval describes it): the returned settings' typical
    std over the search's scale, with the factor and the std used beside it; an unscaled
    group prints alone, an unfitted one not at all."""
    import types

    from jaxslam.cli.logs import _print_calibration

    info = types.SimpleNamespace(
        verdict="converged", iterations=2, values={},
        typical_std=np.array([[9.0, 9.0, 9.0, 9.0], [0.04, 0.2, 0.05, 0.01]]),
        noise_scales=types.SimpleNamespace(motion_scale=2.0, observation_scale=1.0),
        relative_std={"heading": 0.05, "translation": 0.1, "range": 0.001})
    _print_calibration(info)
    lines = {line.split()[0]: line.split() for line in capsys.readouterr().out.splitlines()
             if line.startswith("    ") and "+-" in line}
    assert set(lines) == {"heading", "translation", "range"}
    assert lines["heading"][1:6] == ["0.02", "rad", "+-", "9.8", "%"]
    assert lines["heading"][6:] == ["(x2", "by", "the", "likelihood's", "search:", "0.04",
                                    "rad", "used)"]
    assert lines["translation"][1:6] == ["0.1", "m", "+-", "20", "%"]
    assert lines["range"][1:] == ["0.05", "m", "+-", "0.2", "%"]


def test_calibration_print_gives_the_radius_std_with_its_interval(capsys):
    """A fitted trunk-radius std is printed with its bootstrap interval and the radii behind
    it; without a fit (no "radius" in ``relative_std``) there is no such line."""
    import types

    from jaxslam.cli.logs import _print_calibration

    info = types.SimpleNamespace(
        verdict="converged", iterations=2, values={"radius_noise": 0.0503},
        samples={"radius": 2990}, typical_std=np.array([[0.02, 0.1, 0.05, 0.01]] * 2),
        noise_scales=None, relative_std={"range": 0.001, "radius": 0.05})
    _print_calibration(info)
    out = capsys.readouterr().out
    assert ("    radius       0.0503 m +- 9.8 %  (bootstrap over the landmarks of 2990 radii)"
            in out.splitlines())
    info.relative_std = {"range": 0.001, "radius": float("inf")}  # one landmark's radii
    _print_calibration(info)
    assert ("    radius       0.0503 m no interval  (bootstrap over the landmarks of 2990 "
            "radii)") in capsys.readouterr().out.splitlines()
    info.relative_std = {"range": 0.001}
    _print_calibration(info)
    assert "bootstrap" not in capsys.readouterr().out


def test_em_patience_option_reaches_the_calibration():
    """``--em-patience N`` is calibrate_params' patience, 0 is None (no early stop);
    ``--fit-gain`` also fits the odometry's gains (calibrate_gain=True);
    ``--search-workers N`` its search_workers (absent: None, the default);
    ``--em-significance LEVEL`` its significance (default and 0: None, the plain sums); a negative
    patience, a worker count below 1 or a level outside [0, 1) is refused with a message
    naming the flag."""
    import argparse

    from jaxslam.cli.common import UsageError
    from jaxslam.cli.logs import _calibration_options
    from jaxslam.cli.parser import build_parser

    parser = build_parser()
    for command in (["calibrate", "--data", "x.npz", "--out", "p.toml"], ["run", "--data", "x.npz"]):
        assert _calibration_options(parser.parse_args(command))["patience"] == 2
        given = parser.parse_args(command + ["--em-patience", "3"])
        assert _calibration_options(given) == {"scale_search": True, "calibrate_gain": False,
                                               "patience": 3, "search_workers": None,
                                               "significance": None}
        assert _calibration_options(parser.parse_args(command + ["--em-significance", "0.05"]))[
            "significance"] == 0.05
        assert _calibration_options(parser.parse_args(command + ["--em-significance", "0"]))[
            "significance"] is None
        assert _calibration_options(parser.parse_args(command + ["--fit-gain"]))[
            "calibrate_gain"]
        assert _calibration_options(parser.parse_args(command + ["--em-patience", "0"]))[
            "patience"] is None
        assert _calibration_options(parser.parse_args(command + ["--search-workers", "1"]))[
            "search_workers"] == 1
    with pytest.raises(UsageError, match="--em-patience must be 0"):
        _calibration_options(argparse.Namespace(em_patience=-1, no_scale_search=False))
    with pytest.raises(UsageError, match="--search-workers must be a positive number"):
        _calibration_options(argparse.Namespace(em_patience=2, search_workers=0))
    for bad in (-0.1, 1.0, 1.5):
        with pytest.raises(UsageError, match="--em-significance must be a level in"):
            _calibration_options(argparse.Namespace(em_patience=2, em_significance=bad))


def test_run_and_calibrate_with_the_commands_lag(tmp_path, monkeypatch, capsys):
    """``--command-delay``: a log that carries its commanded velocities (the simulated
    unicycle of tests/test_command_delay.py, 0.27 s late) is rebuilt at a given lag or at
    the lag fitted from it; the run records it in metrics.json and the params file names it.
    A log without a command stream is refused by name."""
    import json

    from jaxslam.datasets.log_format import save_log
    from tests.test_command_delay import TRUE_DELAY, DelayedWorld

    monkeypatch.setenv("JAXSLAM_CACHE_DIR", str(tmp_path / "cache"))
    save_log(tmp_path / "log.npz", DelayedWorld().stamped_log())
    small = ["--set", "filter.num_particles=30", "--set", "filter.max_landmarks=40"]
    try:
        status = cli.main(["run", "--data", str(tmp_path / "log.npz"), "--out",
                           str(tmp_path / "out"), "--command-delay", "auto",
                           "--no-calibrate", *small])
        out = capsys.readouterr().out
        assert status == 0 and "command delay fitted from the log" in out
        fitted = json.loads((tmp_path / "out" / "metrics.json").read_text())["metrics"][
            "command_delay"]
        # as tests/test_command_delay.py's end-to-end fit, from the default settings here
        assert abs(fitted - TRUE_DELAY) < 0.03, fitted
        status = cli.main(["calibrate", "--data", str(tmp_path / "log.npz"), "--out",
                           str(tmp_path / "params.toml"), "--command-delay", "0.27",
                           "--no-scale-search", *small])
        out = capsys.readouterr().out
        assert status == 0 and "commands +0.270 s late" in out
        assert "--command-delay 0.27)" in out  # how to reuse the file (the delay exactly)
        assert "run with --command-delay 0.27\n" in (tmp_path / "params.toml").read_text()
        # the saved settings reused at the lag they were calibrated at
        status = cli.main(["run", "--data", str(tmp_path / "log.npz"), "--out",
                           str(tmp_path / "again"), "--params", str(tmp_path / "params.toml"),
                           "--command-delay", "0.27", *small])
        assert status == 0 and "commands +0.270 s late" in capsys.readouterr().out
        metrics = json.loads((tmp_path / "again" / "metrics.json").read_text())["metrics"]
        assert metrics["command_delay"] == 0.27
        save_log(tmp_path / "plain.npz", _straight_log())
        status = cli.main(["run", "--data", str(tmp_path / "plain.npz"), "--out",
                           str(tmp_path / "plain"), "--command-delay", "0.2", "--no-calibrate",
                           *small])
        assert status == 2 and "has no command stream" in capsys.readouterr().err
        # a bad calibration option is refused before the lag is fitted
        status = cli.main(["run", "--data", str(tmp_path / "log.npz"), "--out",
                           str(tmp_path / "bad"), "--command-delay", "auto", "--em-patience",
                           "-1", *small])
        captured = capsys.readouterr()
        assert status == 2 and "--em-patience" in captured.err
        assert "fitting the commands' lag" not in captured.out
        assert cli.main(["run", "--command-delay", "0.2"]) == 2  # no --data
        assert "apply to a robot log" in capsys.readouterr().err
        # one second of log (3 steps, at most 12 sightings): too few to fit a lag from
        save_log(tmp_path / "short.npz", DelayedWorld(seconds=1.0).stamped_log())
        status = cli.main(["run", "--data", str(tmp_path / "short.npz"), "--out",
                           str(tmp_path / "short"), "--command-delay", "auto", *small])
        assert status == 2
        assert "lag cannot be fitted from it; give the lag" in capsys.readouterr().err
        with pytest.raises(SystemExit):
            cli.main(["run", "--data", str(tmp_path / "log.npz"), "--command-delay", "soon"])
        assert "expected 'auto' or a finite number of seconds" in capsys.readouterr().err
    finally:
        _reset_cache_config()


def test_the_saved_delay_note_carries_the_delay_to_the_last_digit():
    """The params file's note suggests ``--command-delay`` with the fitted delay exactly
    (``repr``), which the option reads back to the same float; none without a delay."""
    from jaxslam.cli.logs import _delay_note
    from jaxslam.command_delay import command_delay_argument

    delay = 0.23205342817306519
    note = _delay_note(delay)
    assert note.startswith("; at commands 0.232 s late: run with --command-delay ")
    assert command_delay_argument(note.rsplit(" ", 1)[-1]) == delay
    assert _delay_note(np.float32(0.25)).endswith("--command-delay 0.25")
    assert _delay_note(None) == ""
