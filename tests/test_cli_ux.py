"""What a new user meets: --version, defaults in every --help, `config show` with units, bench's
own help, a quiet console, TUM export on the log's own clock or of any study run, and the error
plot of a log run."""
import argparse
import pathlib
import os
import re
import subprocess
import sys
import tomllib
import types

import numpy as np
import pytest

import jaxslam
from jaxslam import cli

import test_cli  # the log builders and cache reset of the other CLI tests

PYTHON = sys.executable
NOISE = ("Failed to import warp", "Failed to import mujoco_warp", "float64", "Warning")


def _assert_quiet(result):
    """No import warning or stray warning on either stream of a finished subprocess."""
    for stream, text in (("stdout", result.stdout), ("stderr", result.stderr)):
        for noise in NOISE:
            assert noise not in text, f"{stream} holds {noise!r}:\n{text}"


# ------------------------------------------------------------------------------------------
# --version and --help


def test_version_prints_the_package_version():
    result = subprocess.run([PYTHON, "-m", "jaxslam.cli", "--version"], capture_output=True,
                            text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    assert result.stdout == f"jaxslam {jaxslam.__version__}\n"


def _option_blocks(help_text: str) -> dict[str, str]:
    """{"--seed": "--seed SEED  PRNG seed (default: 0)", ...} from an argparse help text:
    each option's lines joined (its help may wrap over several)."""
    blocks, current = {}, None
    for line in help_text.splitlines():
        match = re.match(r"^  (-[-\w]+|[A-Za-z_]\w*)(,| |$)", line)
        if match:
            current = match.group(1)
            blocks[current] = line.strip()
        elif current and line.startswith("    "):
            blocks[current] += " " + line.strip()
        else:
            current = None
    return {name: re.sub(r"\s+", " ", text) for name, text in blocks.items()}


def _subcommands():
    return cli.subcommand_parsers(cli.build_parser())


@pytest.mark.parametrize("name", sorted(_subcommands()))
def test_every_option_shows_its_default(name):
    parser = _subcommands()[name]
    blocks = _option_blocks(parser.format_help())
    for action in parser._actions:
        if (not action.option_strings or action.help == argparse.SUPPRESS
                or isinstance(action, (argparse._HelpAction, argparse._VersionAction))):
            continue
        text = blocks[action.option_strings[-1]]
        assert "(default:" in text or "(required)" in text, f"jaxslam {name}: {text}"


def test_help_shows_the_actual_default_values():
    commands = _subcommands()
    run = _option_blocks(commands["run"].format_help())
    assert "(default: 0)" in run["--seed"]
    assert "(default: off)" in run["--smooth"]
    assert "(default: results/run;" in run["--out"]
    assert "(default: results/demo;" in _option_blocks(commands["demo"].format_help())["--out"]
    assert "(default: none" in run["--data"] and "simulated" in run["--data"]
    export = _option_blocks(commands["export"].format_help())
    assert "(default: tum)" in export["--format"]
    assert "(default: 1;" in export["--dt"]
    demo = _option_blocks(commands["demo"].format_help())
    assert "(default: none)" in demo["--set"] and "(default: off)" in demo["--quiet"]
    assert "(required)" in _option_blocks(commands["calibrate"].format_help())["--data"]


def test_top_level_help_lists_config_and_version():
    help_text = cli.build_parser().format_help()
    assert "--version" in help_text and "config" in help_text


# ------------------------------------------------------------------------------------------
# config show


def _flat_keys(data: dict, prefix="") -> list[str]:
    keys = []
    for key, value in data.items():
        if isinstance(value, dict):
            keys += _flat_keys(value, f"{prefix}{key}.")
        else:
            keys.append(f"{prefix}{key}")
    return keys


def test_every_config_key_and_param_has_a_unit():
    from jaxslam import studies
    from jaxslam.types import Params

    data = studies.study_config_to_dict(studies.demo_study_config())
    keys = _flat_keys({k: v for k, v in data.items() if k not in ("params", "sweep")})
    keys += [f"params.{name}" for name in Params._fields]
    keys += ["scenario.robot"]  # written out only when it is not the default, "kinematic"
    keys += ["scenario.first_scan"]  # written out for robot studies only
    missing = [key for key in keys if key not in cli.CONFIG_UNITS]
    assert not missing, f"add the units of {missing} to cli.CONFIG_UNITS"
    stale = sorted(set(cli.CONFIG_UNITS) - set(keys))
    assert not stale, f"cli.CONFIG_UNITS names keys the config does not have: {stale}"
    expected = {"scenario.size": "m", "scenario.step_length": "m", "filter.num_particles":
                "count", "params.bearing_noise": "rad/m, rad", "params.miss_bearing": "rad",
                "params.detection_probability": "probability", "params.existence_init":
                "log-odds", "filter.association": "-", "sweep.max_range": "m"}
    assert {key: cli.config_unit(key) for key in expected} == expected


def _show(capsys, *args):
    """``jaxslam config show ARGS``: {key: (value, unit, note)} of its table."""
    assert cli.main(["config", "show", *args]) == 0
    out = capsys.readouterr().out
    rows = {}
    for line in out.splitlines():
        if line.startswith("#"):
            continue
        body, _, note = line.partition("  # ")
        key, value, unit = re.match(r"^(\S+)\s+(.+?)\s{2,}(\S.*?)\s*$", body).groups()
        rows[key] = (value, unit, note.strip())
    return out, rows


def test_config_show_defaults_to_the_demo_config(capsys):
    from jaxslam import studies

    demo = studies.demo_study_config()
    out, rows = _show(capsys)
    assert "the demo config" in out
    assert rows["name"][0] == '"demo"'
    assert rows["filter.num_particles"] == (str(demo.filter.num_particles), "count", "")
    assert rows["scenario.num_steps"][0] == str(demo.scenario.num_steps)
    assert rows["params.max_range"] == ("20.0", "m", "= scenario.max_range")
    assert rows["params.range_noise"] == ("[0.005, 0.0]", "m/m, m", "default")


def test_config_show_round_trips_through_set(tmp_path, capsys):
    from jaxslam import studies
    from jaxslam.types import Params, default_params

    config_file = tmp_path / "study.toml"
    config_file.write_text('name = "mine"\nnum_runs = 7\n[filter]\nproposal = "mixture"\n'
                           '[params]\nrange_noise = [0.01, 0.02]\n')
    sets = ["--set", "scenario.size=45", "--set", "sweep.mixture_ratio=[0.1, 0.5]"]
    _, rows = _show(capsys, str(config_file), *sets)
    config = studies.load_study_config(config_file, ["scenario.size=45",
                                                     "sweep.mixture_ratio=[0.1, 0.5]"])
    # Every non-[params] line, given back as --set, rebuilds the same config.
    overrides = [f"{key}={value}" for key, (value, _, _) in rows.items()
                 if not key.startswith("params.")]
    overrides += [f"params.range_noise={rows['params.range_noise'][0]}"]
    assert studies.load_study_config(None, overrides) == config
    assert rows["scenario.size"][:2] == ("45.0", "m")
    assert rows["params.range_noise"] == ("[0.01, 0.02]", "m/m, m", "set in the config")
    assert rows["params.mixture_ratio"][2] == "swept: see sweep.mixture_ratio"
    assert rows["sweep.mixture_ratio"][:2] == ("[0.1, 0.5]", "probability")
    # [params] lists every field with the value the filter runs with.
    assert sorted(k[len("params."):] for k in rows if k.startswith("params.")) == sorted(
        Params._fields)
    resolved = default_params(config.filter, max_range=config.scenario.max_range,
                              range_noise=(0.01, 0.02))
    for name in Params._fields:
        shown = tomllib.loads(f"v = {rows['params.' + name][0]}")["v"]
        np.testing.assert_allclose(shown, np.asarray(getattr(resolved, name)), rtol=1e-5,
                                   err_msg=name)


def test_config_show_errors_name_the_key(tmp_path, capsys):
    assert cli.main(["config", "show", "--set", "filter.num_particle=3"]) == 2
    err = capsys.readouterr().err
    assert "filter.num_particle" in err and "num_particles" in err
    assert cli.main(["config", "show", str(tmp_path / "absent.toml")]) == 2
    assert "absent.toml" in capsys.readouterr().err


# ------------------------------------------------------------------------------------------
# bench


def _fake_bench(tmp_path, monkeypatch):
    script = tmp_path / "filter_step.py"
    script.write_text("def main(argv):\n    print('bench argv', argv)\n    return 0\n")
    monkeypatch.setattr(cli.bench, "BENCHMARK_PATH", script)
    monkeypatch.setenv("JAXSLAM_CACHE_DIR", str(tmp_path / "cache"))


def test_bench_help_describes_bench_itself(tmp_path, monkeypatch, capsys):
    _fake_bench(tmp_path, monkeypatch)
    assert cli.main(["bench", "--help"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("usage: jaxslam bench")
    assert "bench argv" not in out  # the script did not run
    assert "jaxslam bench -- --help" in out and "--batch-runs" in out


def test_bench_passes_arguments_through(tmp_path, monkeypatch, capsys):
    _fake_bench(tmp_path, monkeypatch)
    try:
        assert cli.main(["bench", "--", "--help"]) == 0
        assert "bench argv ['--help']" in capsys.readouterr().out
        assert cli.main(["bench", "--steps", "5", "--skip-step"]) == 0
        assert "bench argv ['--steps', '5', '--skip-step']" in capsys.readouterr().out
    finally:
        test_cli._reset_cache_config()


# ------------------------------------------------------------------------------------------
# A quiet console


def test_mujoco_import_prints_no_warp_lines():
    code = ("from sims.mujoco_loader import import_quietly; import_quietly('mujoco.mjx'); "
            "import sims.forest, sims.lidar, mujoco.mjx; print('imported')")
    result = subprocess.run([PYTHON, "-c", code], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert result.stdout == "imported\n"
    _assert_quiet(result)


def test_study_export_imports_mujoco_quietly(tmp_path):
    # The export of a study run simulates it again (MuJoCo): the command must import MuJoCo
    # quietly before the simulator does. recompute_runs is stubbed to import the simulator.
    folder = _study_folder(tmp_path)
    code = f"""
import sys, types, numpy as np
from jaxslam import cli, studies
def recompute(config, start, stop):
    import sims.forest, sims.lidar
    return types.SimpleNamespace(scenario=types.SimpleNamespace(truth_pose=np.zeros((4, 3))),
                                 example=dict(mean_pose=np.zeros((1, 1, 3, 3))))
studies.recompute_runs = recompute
sys.exit(cli.main(["export", {str(folder)!r}, "--run", "0"]))
"""
    result = subprocess.run([PYTHON, "-c", code], capture_output=True, text=True, timeout=120,
                            env=_env(tmp_path))
    assert result.returncode == 0, result.stderr
    assert "estimate.tum (3 poses)" in result.stdout
    _assert_quiet(result)


def _env(tmp_path):
    """The environment of a subprocess run, with its own compilation cache."""
    return {**os.environ, "JAXSLAM_CACHE_DIR": str(tmp_path / "cache")}


# ------------------------------------------------------------------------------------------
# A log run: its own timestamps in the TUM files, the error plot


def _read_tum(path):
    lines = [line for line in path.read_text().splitlines() if not line.startswith("#")]
    rows = np.array([[float(v) for v in line.split()] for line in lines])
    return rows[:, 0], np.stack([rows[:, 1], rows[:, 2], 2 * np.arctan2(rows[:, 6],
                                                                        rows[:, 7])], 1)


def _same_angle(a, b, atol):
    np.testing.assert_allclose(np.angle(np.exp(1j * (a - b))), 0.0, atol=atol)


@pytest.mark.slow  # 20 s: a whole log run; the export tests above keep the TUM format
def test_log_run_exports_with_the_logs_timestamps(tmp_path):
    # One subprocess (a console as the user sees it): no warp lines, no float64 warning.
    from jaxslam.datasets.log_format import save_log

    log = test_cli._straight_log()
    log = log._replace(time=100.25 + 0.25 * np.arange(log.num_steps))
    save_log(tmp_path / "log.npz", log)
    out = tmp_path / "out"
    result = subprocess.run(
        [PYTHON, "-m", "jaxslam.cli", "run", "--data", str(tmp_path / "log.npz"), "--out",
         str(out), "--smooth", "--no-calibrate", "--set", "filter.num_particles=8", "--set",
         "filter.max_landmarks=12"], capture_output=True, text=True, timeout=300,
        env=_env(tmp_path))
    assert result.returncode == 0, result.stderr
    _assert_quiet(result)
    assert (out / "error_vs_time.png").stat().st_size > 10_000
    assert f"wrote {out / 'error_vs_time.png'}" in result.stdout
    saved = np.load(out / "example_run.npz")
    np.testing.assert_array_equal(saved["time"], log.time)

    assert cli.main(["export", str(out), "--out", str(tmp_path / "tum")]) == 0
    for name, poses in (("truth", log.truth_pose), ("estimate", saved["mean_pose"]),
                        ("smoothed", saved["smoothed_pose"])):
        times, read = _read_tum(tmp_path / "tum" / f"{name}.tum")
        np.testing.assert_allclose(times, log.time, atol=1e-9, err_msg=name)
        np.testing.assert_allclose(read[:, :2], poses[:, :2], atol=1e-8, err_msg=name)
        _same_angle(read[:, 2], poses[:, 2], atol=1e-8)
    # The estimate at 100.25 s is the pose after the first control, near truth row 0.
    _, estimate = _read_tum(tmp_path / "tum" / "estimate.tum")
    assert np.hypot(*(estimate[0, :2] - log.truth_pose[0, :2])) < 0.1


def test_export_refuses_dt_for_a_run_with_its_own_clock(tmp_path, capsys):
    example = test_cli._example_run()
    example["truth_pose"] = example["truth_pose"][1:]  # a log run: one truth row per step
    example["time"] = 7.0 + np.arange(len(example["mean_pose"]))
    np.savez(tmp_path / "example_run.npz", **example)
    assert cli.main(["export", str(tmp_path), "--dt", "0.1"]) == 2
    assert "leave --dt out" in capsys.readouterr().err
    example["time"] = example["time"][:-1]
    np.savez(tmp_path / "example_run.npz", **example)
    assert cli.main(["export", str(tmp_path)]) == 2
    assert "one timestamp per mean_pose row" in capsys.readouterr().err


def test_export_of_a_run_without_truth_writes_the_estimate_only(tmp_path, capsys):
    example = test_cli._example_run()
    example["truth_pose"] = np.zeros((0, 3))
    example["time"] = 3.5 + 0.5 * np.arange(len(example["mean_pose"]))
    np.savez(tmp_path / "example_run.npz", **example)
    assert cli.main(["export", str(tmp_path)]) == 0
    assert "no truth poses" in capsys.readouterr().out
    assert not (tmp_path / "truth.tum").exists()
    times, poses = _read_tum(tmp_path / "estimate.tum")
    np.testing.assert_allclose(times, example["time"], atol=1e-9)
    np.testing.assert_allclose(poses[:, :2], example["mean_pose"][:, :2], atol=1e-8)


def test_log_error_traces():
    truth = np.stack([np.arange(5.0), np.zeros(5), np.zeros(5)], 1)
    example = dict(truth_pose=truth, mean_pose=truth + [[0.3, 0.4, 0.0]])
    traces = cli.log_error_traces(example)
    np.testing.assert_allclose(traces.pose_error, np.full((1, 5), 0.5))
    smoothed = truth.copy()
    smoothed[-1, 1] = 2.0
    traces = cli.log_error_traces(dict(example, smoothed_pose=smoothed))
    np.testing.assert_array_equal(traces.condition, [0, 1])
    np.testing.assert_allclose(traces.pose_error[1], [0, 0, 0, 0, 2.0])
    assert cli.log_error_traces(dict(example, truth_pose=np.zeros((0, 3)))) is None


def test_log_run_without_truth_says_there_is_no_error_plot(tmp_path, monkeypatch, capsys):
    log = test_cli._straight_log()._replace(truth_pose=None)
    status, _ = test_cli._run_on_straight_log(tmp_path, monkeypatch, capsys,
                                              "--no-calibrate", log=log)
    assert status == 0
    assert not (tmp_path / "out" / "error_vs_time.png").exists()
    assert (tmp_path / "out" / "map.png").is_file()


# ------------------------------------------------------------------------------------------
# Export of any run of a study


_TINY = ["num_runs=3", "chunk_size=3", "filter.num_particles=4", "filter.max_landmarks=16",
         "filter.max_obs=8", "scenario.num_steps=10", "scenario.num_trees=10",
         "scenario.size=20.0", "sweep.max_range=[10.0, 15.0]"]


def _study_folder(tmp_path, overrides=_TINY):
    """A folder holding only the study.toml of a tiny 2-condition study."""
    import tomli_w

    from jaxslam import studies

    folder = tmp_path / "study"
    folder.mkdir()
    config = studies.load_study_config(None, list(overrides))
    (folder / "study.toml").write_text(tomli_w.dumps(studies.study_config_to_dict(config)))
    return folder


def test_study_export_picks_the_run_and_condition(tmp_path, monkeypatch, capsys):
    from jaxslam import studies

    folder = _study_folder(tmp_path)
    calls = []
    truth = np.stack([np.arange(11.0), np.ones(11), np.full(11, 0.1)], 1)
    # (G=2, R=1, T=10, 3): condition c's estimate is the truth shifted by c + 1 in y.
    mean = np.stack([truth[1:] + [0.0, c + 1.0, 0.0] for c in range(2)])[:, None]

    def recompute(config, start, stop):
        calls.append((config.num_runs, len(config.conditions), start, stop))
        return types.SimpleNamespace(scenario=types.SimpleNamespace(truth_pose=truth),
                                     example=dict(mean_pose=mean))

    monkeypatch.setattr(studies, "recompute_runs", recompute)
    monkeypatch.setattr(cli.common, "enable_compilation_cache", lambda: None)
    assert cli.main(["export", str(folder), "--run", "2", "--condition", "1",
                     "--dt", "0.5"]) == 0
    assert calls == [(3, 2, 2, 3)]
    assert "final position error 2 m" in capsys.readouterr().out
    target = folder / "run-2-condition-1"
    times, poses = _read_tum(target / "truth.tum")
    np.testing.assert_allclose(times, 0.5 * np.arange(11))
    np.testing.assert_allclose(poses, truth, atol=1e-8)
    times, poses = _read_tum(target / "estimate.tum")
    np.testing.assert_allclose(times, 0.5 * np.arange(1, 11))  # row t: after step t + 1
    np.testing.assert_allclose(poses, mean[1, 0], atol=1e-8)


@pytest.mark.parametrize("option, message", [
    (["--run", "3"], "--run 3 is out of range: the study in {folder} has runs 0 to 2"),
    (["--run", "-1"], "--run -1 is out of range"),
    (["--run", "0", "--condition", "2"],
     "--condition 2 is out of range: the study in {folder} has conditions 0 to 1 "
     "(0: max_range=10.0; 1: max_range=15.0)"),
])
def test_study_export_out_of_range(tmp_path, monkeypatch, capsys, option, message):
    from jaxslam import studies

    folder = _study_folder(tmp_path)
    monkeypatch.setattr(studies, "recompute_runs", lambda *a: pytest.fail("ran the study"))
    assert cli.main(["export", str(folder), *option]) == 2
    assert message.format(folder=folder) in capsys.readouterr().err


def test_study_export_needs_a_study_folder(tmp_path, capsys):
    assert cli.main(["export", str(tmp_path), "--run", "0"]) == 2
    assert "study.toml does not exist" in capsys.readouterr().err
    np.savez(tmp_path / "example_run.npz", **test_cli._example_run())
    assert cli.main(["export", str(tmp_path / "example_run.npz"), "--run", "0"]) == 2
    assert "is not a folder" in capsys.readouterr().err


# Two study compiles (simulator and filter) and a recompute: ~40-60 s on the shared 2-core CPU.
@pytest.mark.slow
def test_study_export_matches_the_table(tmp_path):
    from jaxslam import studies

    config = tmp_path / "tiny.toml"
    config.write_text('name = "tiny"\n')
    out = tmp_path / "out"
    sets = [a for item in _TINY for a in ("--set", item)]
    for command in (["study", str(config), "--out", str(out), "--quiet", *sets],
                    ["export", str(out), "--run", "1", "--condition", "0"]):
        result = subprocess.run([PYTHON, "-m", "jaxslam.cli", *command], capture_output=True,
                                text=True, timeout=600, env=_env(tmp_path))
        assert result.returncode == 0, result.stderr
        _assert_quiet(result)
    _, truth = _read_tum(out / "run-1-condition-0" / "truth.tum")
    _, estimate = _read_tum(out / "run-1-condition-0" / "estimate.tum")
    assert len(truth) == 11 and len(estimate) == 10
    table = studies.load_results(out).to_pydict()
    row = [i for i, (r, c) in enumerate(zip(table["run_id"], table["condition"]))
           if (r, c) == (1, 0)]
    assert len(row) == 1
    final = np.hypot(*(estimate[-1, :2] - truth[-1, :2]))
    np.testing.assert_allclose(final, table["final_pose_error"][row[0]], rtol=1e-5, atol=1e-6)
    # Run 1 is not the stored example (run 0): its estimate differs.
    example = np.load(out / "example_run.npz")
    assert not np.allclose(example["mean_pose"][:, :2], estimate[:, :2], atol=1e-3)


def test_default_study_folder_differs_when_set_changes_the_config(tmp_path, monkeypatch):
    """results/<name> for the config as defined; --set of anything but num_runs/chunk_size
    gives results/<name>-<digest> (a trial run never blocks the full study's folder)."""
    import argparse

    from jaxslam import studies

    monkeypatch.chdir(tmp_path)
    base = cli.demo_config()

    def out_for(*overrides):
        args = argparse.Namespace(out=None, config=None)
        return cli._out_dir(args, cli.demo_config(list(overrides)), reference=base)

    assert out_for() == pathlib.Path("results/demo")
    assert out_for("num_runs=1000", "chunk_size=100") == pathlib.Path("results/demo")
    small = out_for("filter.num_particles=8")
    assert small.parent == pathlib.Path("results") and small.name.startswith("demo-")
    assert len(small.name) == len("demo-") + 8
    assert out_for("filter.num_particles=8") == small  # stable
    assert out_for("filter.num_particles=9") != small
    config = studies.load_study_config(None, [])
    assert cli._out_dir(argparse.Namespace(out="elsewhere", config=None), config) == \
        pathlib.Path("elsewhere")
