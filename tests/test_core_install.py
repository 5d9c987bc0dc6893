"""The core install (``pip install jaxslam``) without MuJoCo: importing the library imports no
MuJoCo, a robot log runs without it, analytic studies run without it, and whatever needs the
simulator's physics says in one line how to install it (``jaxslam[sim]``).

MuJoCo is installed in the test environment, so the subprocesses below block it:
``sys.modules["mujoco"] = None`` makes every ``import mujoco`` raise ModuleNotFoundError, as
on a core install.
"""
import json
import os
import pathlib
import subprocess
import sys

import pytest
import tomllib

import test_cli  # the small robot log of the other CLI tests

PYTHON = sys.executable
ROOT = pathlib.Path(__file__).resolve().parent.parent
BLOCK_MUJOCO = "import sys; sys.modules['mujoco'] = None; sys.modules['mujoco.mjx'] = None; "
TINY_STUDY = ["--set", "num_runs=2", "--set", "chunk_size=2", "--set", "run_width=2",
              "--set", "filter.num_particles=4", "--set", "filter.max_landmarks=12",
              "--set", "filter.max_obs=4", "--set", "scenario.num_steps=6",
              "--set", "scenario.num_trees=8", "--set", "scenario.size=20.0"]


def _python(code: str, tmp_path, timeout=300):
    """Run ``python -c code`` from the repository root with its own compilation cache."""
    env = {**os.environ, "JAXSLAM_CACHE_DIR": str(tmp_path / "cache")}
    return subprocess.run([PYTHON, "-c", code], capture_output=True, text=True, cwd=ROOT,
                          env=env, timeout=timeout)


def _cli_without_mujoco(args: list[str], tmp_path):
    """``jaxslam ARGS`` in a process where MuJoCo cannot be imported; it also checks on exit
    that nothing installed a MuJoCo module behind the block."""
    code = (BLOCK_MUJOCO + "from jaxslam import cli; status = cli.main(" + repr(args) + "); "
            "assert sys.modules['mujoco'] is None, 'mujoco was imported'; sys.exit(status)")
    return _python(code, tmp_path)


def test_core_imports_import_no_mujoco(tmp_path):
    result = _python("import jaxslam, jaxslam.studies, jaxslam.pipeline, jaxslam.cli, "
                     "jaxslam.datasets, sims, sims.batch, sims.scenario, sims.forest, sys; "
                     "assert 'mujoco' not in sys.modules, 'mujoco imported'", tmp_path)
    assert result.returncode == 0, result.stderr


def test_run_on_a_log_without_mujoco(tmp_path):
    from jaxslam.datasets.log_format import save_log

    save_log(tmp_path / "log.npz", test_cli._straight_log(steps=8))
    out = tmp_path / "out"
    result = _cli_without_mujoco(["run", "--data", str(tmp_path / "log.npz"), "--no-calibrate",
                                  "--out", str(out), "--set", "filter.num_particles=4",
                                  "--set", "filter.max_landmarks=8"], tmp_path)
    assert result.returncode == 0, result.stderr
    assert "final_pose_error" in json.loads((out / "metrics.json").read_text())["metrics"]
    assert (out / "map.png").is_file()


def test_config_show_and_help_without_mujoco(tmp_path):
    for args in (["config", "show"], ["--help"], ["run", "--help"]):
        result = _cli_without_mujoco(args, tmp_path)
        assert result.returncode == 0, (args, result.stderr)


def test_lidar_study_without_mujoco_says_how_to_install_it(tmp_path):
    result = _cli_without_mujoco(["demo", "--quiet", "--out", str(tmp_path / "demo"),
                                  "--set", 'scenario.observation_source="lidar"', *TINY_STUDY],
                                 tmp_path)
    assert result.returncode == 2, result.stderr
    assert "Traceback" not in result.stderr
    errors = [line for line in result.stderr.splitlines() if "error:" in line]
    assert len(errors) == 1, result.stderr
    assert errors[0].startswith("jaxslam demo: error: ")
    assert 'lidar' in errors[0] and 'pip install "jaxslam[sim]"' in errors[0]


def test_simulator_parts_without_mujoco_raise_the_install_hint(tmp_path):
    code = BLOCK_MUJOCO + """
import jax
from sims import forest, mujoco_loader, robot
trees = forest.random_forest(jax.random.PRNGKey(0), 5, (20.0, 20.0))  # layouts need no MuJoCo
for build in (lambda: forest.world_from_forest(trees), robot.make_robot):
    try:
        build()
    except mujoco_loader.SimulatorNotInstalled as error:
        assert isinstance(error, ImportError) and 'pip install "jaxslam[sim]"' in str(error), error
    else:
        raise AssertionError("built without MuJoCo")
print("ok")
"""
    result = _python(code, tmp_path)
    assert result.returncode == 0, result.stderr
    assert result.stdout == "ok\n"


@pytest.mark.slow  # 19 s; run --data without MuJoCo stays in the default tier
def test_analytic_study_runs_without_mujoco(tmp_path):
    out = tmp_path / "demo"
    result = _cli_without_mujoco(["demo", "--quiet", "--out", str(out), *TINY_STUDY], tmp_path)
    assert result.returncode == 0, result.stderr
    assert (out / "summary.md").is_file()


def test_dependencies_leave_mujoco_to_the_sim_extra():
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    assert not [d for d in project["dependencies"] if d.lower().startswith("mujoco")]
    extras = project["optional-dependencies"]
    assert set(extras["sim"]) == {"mujoco==3.17.0", "mujoco-mjx==3.17.0"}
    test = extras["test"]
    assert "jaxslam[sim]" in test or set(extras["sim"]) <= set(test), test


def test_top_level_api_resolves_and_is_lazy():
    """Every name of ``jaxslam.__all__`` resolves; the module-level exports a user needs for a
    single run (``scan_filter``, ``metrics``, the Params helpers) are among them; an unknown
    name is an AttributeError, not a silent None."""
    import jaxslam

    for name in ("scan_filter", "run_filter", "default_params", "starting_params", "metrics",
                 "calibrate_params", "filter_log"):
        assert name in jaxslam.__all__, name
    for name in jaxslam.__all__:
        assert getattr(jaxslam, name) is not None, name
    assert jaxslam.metrics.ate_rmse is not None
    with pytest.raises(AttributeError, match="no attribute 'nonexistent'"):
        jaxslam.nonexistent
