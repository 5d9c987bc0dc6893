"""Packages in one direction: jaxslam loads its study simulator by name (a plugin) and never
imports sims or MuJoCo itself; a simulator passed to run_study or registered by name is used."""
import ast
import dataclasses
import pathlib
import subprocess
import sys

import pytest

from jaxslam import simulators, studies

ROOT = pathlib.Path(__file__).resolve().parent.parent
TINY = ["num_runs=2", "chunk_size=2", "filter.num_particles=4", "filter.max_landmarks=12",
        "filter.max_obs=4", "scenario.num_steps=6", "scenario.num_trees=8", "scenario.size=20.0"]


def _imported_modules(path: pathlib.Path) -> set[str]:
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module:
            names.add(node.module)
    return names


def test_jaxslam_imports_nothing_from_sims():
    offenders = {str(path.relative_to(ROOT)): sorted(found)
                 for path in sorted((ROOT / "jaxslam").rglob("*.py"))
                 if (found := {m for m in _imported_modules(path)
                               if m == "sims" or m.startswith("sims.") or m.startswith("mujoco")})}
    assert not offenders, f"jaxslam imports the simulator: {offenders}"


def test_importing_the_study_machinery_imports_no_simulator():
    code = ("import jaxslam, jaxslam.studies, jaxslam.study_config, sys; "
            "assert 'mujoco' not in sys.modules, 'mujoco'; assert 'sims' not in sys.modules, "
            "'sims'")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                            cwd=ROOT, timeout=120)
    assert result.returncode == 0, result.stderr


def test_the_default_simulator_is_loaded_by_name():
    config = studies.load_study_config(None, ["scenario.size=30"])
    assert config.simulator == "sims" and "sims" in sys.modules
    from sims.config import ScenarioConfig

    assert isinstance(config.scenario, ScenarioConfig) and config.scenario.size == 30.0
    # the default is not written out: study.toml, digests and resume checks are unchanged
    assert "simulator" not in studies.study_config_to_dict(config)
    assert studies.load_study_config(None, ['simulator="sims"', "scenario.size=30"]) == config


def test_a_missing_simulator_is_a_config_error_naming_it():
    with pytest.raises(ValueError, match="simulator='no_such_simulator'.*not installed"):
        studies.load_study_config(None, ['simulator="no_such_simulator"'])
    with pytest.raises(simulators.SimulatorUnavailable, match="no module 'no_such_simulator'"):
        simulators.load_simulator("no_such_simulator")
    with pytest.raises(ValueError, match="registers no study simulator"):
        simulators.load_simulator("json")  # a module that is there but is no simulator


def test_the_mujoco_error_is_a_simulator_unavailable():
    from sims.mujoco_loader import INSTALL_COMMAND, SimulatorNotInstalled

    assert issubclass(SimulatorNotInstalled, simulators.SimulatorUnavailable)
    assert INSTALL_COMMAND == simulators.SIM_INSTALL_COMMAND == 'pip install "jaxslam[sim]"'


@dataclasses.dataclass(frozen=True)
class _Settings:
    max_range: float = 12.0


def test_a_registered_simulator_parses_its_own_scenario_section():
    seen = []

    def settings(section):
        seen.append(section)
        return section if isinstance(section, _Settings) else _Settings(**section)

    simulators.register_simulator("test_fake_simulator", simulate=None, settings=settings)
    config = studies.load_study_config(
        None, ['simulator="test_fake_simulator"', "scenario.max_range=9.0"])
    assert config.scenario == _Settings(9.0) and seen[0] == {"max_range": 9.0}
    data = studies.study_config_to_dict(config)
    assert data["simulator"] == "test_fake_simulator" and data["scenario"] == {"max_range": 9.0}
    assert studies.condition_params(config).max_range.tolist() == [9.0]  # the sensor range


@pytest.mark.slow  # 19 s: two studies; the registry tests above keep the lookup and errors
def test_run_study_takes_a_simulator_function(tmp_path):
    from sims.batch import scenario_batch

    config = studies.load_study_config(None, TINY)
    calls = []

    def simulate(config, run_ids):
        calls.append(list(run_ids))
        return scenario_batch(config, run_ids)

    given = studies.run_study(config, tmp_path / "given", progress=False, simulate=simulate)
    default = studies.run_study(config, tmp_path / "default", progress=False)
    assert calls == [[0, 1]]
    assert given.table.equals(default.table)
