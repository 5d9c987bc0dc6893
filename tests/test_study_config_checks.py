"""Study configs are type-checked when read, and a failed start never locks a folder
(issue 18). Nothing here compiles a filter: the runs that would start are stopped before."""
import dataclasses
import pathlib

import pytest
import tomli_w

from jaxslam import studies

TINY = ["num_runs=4", "chunk_size=2", "filter.num_particles=8", "filter.max_landmarks=24",
        "filter.max_obs=8", "scenario.num_steps=20", "scenario.num_trees=15",
        "scenario.size=30.0"]


def tiny_config(*overrides) -> studies.StudyConfig:
    return studies.load_study_config(None, TINY + list(overrides))


@pytest.mark.parametrize("override, named", [
    ('scenario.num_steps="20"', ["scenario.num_steps", "'20'", "positive integer", "quotes"]),
    ('params.max_range="far"', ["params.max_range", "'far'", "number"]),
    ("seed=1.5", ["seed", "1.5", "integer"]),
    ("seed=-1", ["seed", "-1", ">= 0"]),
    ("scenario.num_steps=0", ["scenario.num_steps", "positive integer"]),
    ("scenario.num_steps=-5", ["scenario.num_steps", "positive integer"]),
    ("scenario.num_trees=0", ["scenario.num_trees", "positive integer"]),
    ("scenario.size=-30.0", ["scenario.size", "> 0"]),
    ("scenario.step_length='long'", ["scenario.step_length", "number"]),
    ("scenario.max_range=nan", ["scenario.max_range", "number"]),
    ("scenario.forest=3", ["scenario.forest", "plantation"]),
    ("num_runs.x=5", ["num_runs", "not a section", "filter"]),
    ("filter.num_particles.x=5", ["filter.num_particles", "not a section"]),
    ("filters.num_particles=5", ["filters", "not a section"]),
    ("run_width=0", ["run_width", "positive integer"]),
    ("chunk_size=true", ["chunk_size", "positive integer"]),
    ("name=3", ["name", "string"]),
    ("gospa_cutoff='wide'", ["gospa_cutoff", "number"]),
    ('filter.num_particles="8"', ["filter.num_particles", "integer"]),
    ("filter.match_pose_uncertainty=1", ["filter.match_pose_uncertainty", "true or false"]),
    ("params.rot1_noise=[0.0, 0.1]", ["params.rot1_noise", "shape"]),
    ("params.min_range=50.0", ["min_range", "max_range"]),
    ('sweep.max_range=[10.0, "far"]', ["sweep.max_range[1]", "'far'", "number"]),
    ("sweep.association_gate=[16.0, -1.0]", ["sweep.association_gate[1]"]),
])
def test_every_value_is_checked_when_read(override, named, tmp_path):
    with pytest.raises(ValueError) as error:
        studies.load_study_config(None, TINY + [override])
    for word in named:
        assert word in str(error.value), (word, str(error.value))


def test_config_file_values_are_checked_and_floats_normalised(tmp_path):
    path = tmp_path / "study.toml"
    path.write_text('num_runs = 3\n[scenario]\nnum_steps = "20"\n')
    with pytest.raises(ValueError, match="scenario.num_steps='20'"):
        studies.load_study_config(path)
    path.write_text('num_runs = 3\nnum_runs_x = 1\n')
    with pytest.raises(ValueError, match="num_runs_x"):
        studies.load_study_config(path)
    path.write_text('[num_runs]\nx = 5\n')
    with pytest.raises(ValueError, match="'num_runs' is not a section"):
        studies.load_study_config(path)
    path.write_text('filter = 5\n')
    with pytest.raises(ValueError, match=r"\[filter\] section"):
        studies.load_study_config(path)
    path.write_text('num_runs = 3\n[scenario]\nsize = 30\n')
    with pytest.raises(ValueError, match="num_runs.x"):
        studies.load_study_config(path, ["num_runs.x=5"])
    # An integer for a float setting is the same study as the float.
    assert studies.load_study_config(path) == studies.load_study_config(
        None, ["num_runs=3", "scenario.size=30.0"])


def test_configs_built_in_python_are_checked_too():
    config = tiny_config()
    for changes in (dict(seed=1.5), dict(num_runs=0), dict(params=(("max_range", "far"),)),
                    dict(sweep=(("min_range", (0.1, 80.0)),)), dict(run_width=2.0)):
        with pytest.raises(ValueError):
            dataclasses.replace(config, **changes)
    with pytest.raises(ValueError, match="scenario.num_steps"):
        dataclasses.replace(config.scenario, num_steps="20")


def test_a_refused_config_writes_nothing(tmp_path):
    out = tmp_path / "out"
    with pytest.raises(ValueError):
        studies.run_study(tiny_config('params.max_range="far"'), out, progress=False)
    assert not out.exists()


class _Stop(RuntimeError):
    pass


def _failing_start(config, out, monkeypatch):
    """run_study that stops in the first chunk's simulation (nothing is computed)."""

    def simulate(*args, **kwargs):
        raise _Stop("simulator failed")

    monkeypatch.setattr(studies.runner, "scenario_batch", simulate)  # where the runner looks
    with pytest.raises(_Stop):
        studies.run_study(config, out, progress=False)


def test_failed_start_refusal_names_the_keys_and_how_to_start_over(tmp_path, monkeypatch):
    out = tmp_path / "out"
    first = tiny_config()
    _failing_start(first, out, monkeypatch)
    assert (out / "study.toml").is_file() and not list(out.rglob("chunk-*"))
    other = tiny_config("seed=4", "filter.num_particles=9")
    with pytest.raises(studies.StudyError) as error:
        studies.open_study(other, out)
    message = str(error.value)
    for words in ("different study config", "seed: folder 0, this config 4",
                  "filter.num_particles: folder 8, this config 9", "no finished chunk",
                  f"delete {out / 'study.toml'}"):
        assert words in message, (words, message)
    assert "chunk_size:" not in message  # only the keys that differ
    # The same config resumes; deleting study.toml starts the other study over.
    assert studies.open_study(first, out) == [(0, 2), (2, 4)]
    (out / "study.toml").unlink()
    assert studies.open_study(other, out) == [(0, 2), (2, 4)]


def test_refusal_of_a_folder_with_results_says_to_resume_or_move(tmp_path, monkeypatch):
    out = tmp_path / "out"
    _failing_start(tiny_config(), out, monkeypatch)
    (out / "runs").mkdir()
    (out / "runs/chunk-000000-000002.parquet").write_bytes(b"stand-in")
    with pytest.raises(studies.StudyError) as error:
        studies.open_study(tiny_config("run_width=2"), out)
    message = str(error.value)
    assert "run_width: folder 1, this config 2" in message
    assert "1 finished chunk" in message and "another output folder" in message


def test_older_study_file_names_the_missing_key(tmp_path):
    """A folder of a jaxslam without run_width: its runs were computed at the chunk width."""
    out = tmp_path / "out"
    out.mkdir()
    config = tiny_config()
    old = studies.study_config_to_dict(config)
    del old["run_width"]
    (out / "study.toml").write_text(tomli_w.dumps(old))
    with pytest.raises(studies.StudyError, match=r"run_width: folder \(absent\), this config 1"):
        studies.open_study(config, out)


def test_same_study_written_differently_resumes(tmp_path):
    """study.toml with an integer where the config now writes a float is the same study."""
    out = tmp_path / "out"
    out.mkdir()
    config = tiny_config()
    data = studies.study_config_to_dict(config)
    data["scenario"]["size"] = 30
    text = tomli_w.dumps(data)
    (out / "study.toml").write_text(text)
    assert studies.open_study(config, pathlib.Path(out)) == [(0, 2), (2, 4)]
    assert (out / "study.toml").read_text() == text  # left as it was
