"""A run's results are bit-identical whatever the chunk size, the number of runs, the sweep
it belongs to and the device count (issue 18).

Before, each chunk was one vmap of its own width, and XLA's floating point differed with the
width (the particle filter can grow one ulp into a different resampling): on the study below
(x64 on, as in these tests) chunk sizes 1, 3 and 8 each differed from 64 in ate_rmse_aligned in
19 of 26 rows, and with the demo filter (P=64) widths 1 and 3 against 8 changed final errors
and whole traces. Now every (run, condition) pair goes through one compiled program of
``run_width`` pairs.

"Identical" means bit-identical: every column but ``update_rate_hz`` (a wall-clock rate) and
every per-step error trace, compared with ``np.array_equal``. Each compiled filter costs
~15 s on the shared 2-core CPU, so the chunk sizes 1, 3 and 8 share one runner (the
open_study / write_chunk path the Ray backend uses) and chunk size 64 goes through
``run_study``.
"""
import json
import os
import pathlib
import subprocess
import sys

import jax
import numpy as np
import pytest

from jaxslam import studies, study_store

REPO = pathlib.Path(__file__).resolve().parent.parent
TIMING_COLUMNS = ("update_rate_hz",)
TINY = ["num_runs=13", "filter.num_particles=8", "filter.max_landmarks=24", "filter.max_obs=8",
        "scenario.num_steps=20", "scenario.num_trees=15", "scenario.size=30.0",
        "sweep.detection_probability=[0.8, 0.9]"]
CHUNK_SIZES = (1, 3, 8, 64)


def tiny_config(*overrides) -> studies.StudyConfig:
    return studies.load_study_config(None, TINY + list(overrides))


def with_chunk(config, chunk_size, **changes):
    return studies.study_config_from_dict(
        {**studies.study_config_to_dict(config), "chunk_size": chunk_size, **changes})


def run_with(runner, config, out) -> pathlib.Path:
    """The study ``config`` into ``out`` through an existing runner (as ray_backend does)."""
    out = pathlib.Path(out)
    for start, stop in studies.open_study(config, out):
        studies.write_chunk(out, config, start, stop, runner(start, stop))
    return out


def results(out_dir) -> tuple[dict, dict]:
    """Columns of every (condition, run_id) row (sorted) and the per-step error traces."""
    table = studies.load_results(out_dir).to_pydict()
    traces = {}
    for path in sorted(pathlib.Path(out_dir).glob("traces/traces-*.npz")):
        with np.load(path) as data:
            for condition, run_id, errors in zip(data["condition"], data["run_id"],
                                                 data["pose_error"]):
                key = (int(condition), int(run_id))
                assert key not in traces, f"{key} appears twice"
                traces[key] = errors
    return table, traces


def assert_bit_identical(a, b, rows_of_b=None):
    """Every column (timing aside) and trace of the folder ``a`` equals ``b``'s; with
    ``rows_of_b`` (a predicate on (condition, run_id)) only those rows of ``b``."""
    (table_a, traces_a), (table_b, traces_b) = results(a), results(b)
    keep = [i for i, key in enumerate(zip(table_b["condition"], table_b["run_id"]))
            if rows_of_b is None or rows_of_b(key)]
    assert sorted(table_a) == sorted(table_b)
    differing = []
    for name, values in table_a.items():
        if name in TIMING_COLUMNS:
            continue
        other = np.asarray(table_b[name])[keep]
        if not np.array_equal(np.asarray(values), other, equal_nan=True):
            differing.append(f"{name}: {values} != {other.tolist()}")
    assert not differing, "\n".join(differing)
    expected = {k: v for k, v in traces_b.items() if rows_of_b is None or rows_of_b(k)}
    assert sorted(traces_a) == sorted(expected)
    for key, errors in traces_a.items():
        assert np.array_equal(errors, expected[key], equal_nan=True), key


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """The 13-run, 2-condition study at chunk size 64 (one chunk), through run_study."""
    config = tiny_config("chunk_size=64")
    out = tmp_path_factory.mktemp("determinism") / "chunk64"
    studies.run_study(config, out, progress=False)
    return config, out


def test_results_are_bit_identical_whatever_the_chunk_size(reference, tmp_path):
    config, reference_out = reference
    assert config.run_width == 1  # the default
    runner = studies._ChunkRunner(config)
    programs_before = set(studies._COMPILED)
    folders = {}
    for chunk_size in CHUNK_SIZES[:-1]:
        chunked = with_chunk(config, chunk_size)
        folders[chunk_size] = run_with(runner, chunked, tmp_path / f"chunk{chunk_size}")
        assert len(list(folders[chunk_size].glob("runs/chunk-*.parquet"))) == -(-13 // chunk_size)
    for chunk_size, out in folders.items():
        assert_bit_identical(out, reference_out)
    # A study of fewer runs holds exactly the first runs of the longer one.
    five = with_chunk(config, 2, num_runs=5)
    assert_bit_identical(run_with(runner, five, tmp_path / "five"), reference_out,
                         rows_of_b=lambda key: key[1] < 5)
    # One compiled program for every chunk size (the runner holds one, and at most one was
    # added to the process's cache: the reference study may have compiled it already).
    assert len(runner.compiled) == 1
    assert len(set(studies._COMPILED) - programs_before) <= 1


@pytest.mark.slow  # 31 s: a second program width; the default tier checks chunk sizes above
def test_wider_groups_are_bit_identical_whatever_the_chunk_size(tmp_path):
    """run_width=3: a run sits at different positions of its group and next to different
    runs (or padding, or the other condition) from one chunk size to the next."""
    config = tiny_config("run_width=3", "chunk_size=1")
    runner = studies._ChunkRunner(config)
    folders = {size: run_with(runner, with_chunk(config, size), tmp_path / f"chunk{size}")
               for size in CHUNK_SIZES}
    for size in CHUNK_SIZES[1:]:
        assert_bit_identical(folders[size], folders[CHUNK_SIZES[0]])
    seven = with_chunk(config, 4, num_runs=7)
    assert_bit_identical(run_with(runner, seven, tmp_path / "seven"), folders[1],
                         rows_of_b=lambda key: key[1] < 7)


def test_simulated_inputs_do_not_depend_on_the_runs_asked_together():
    """The simulator, too, runs in groups of a fixed width. (Its vmap width matters: with x64
    on, simulating 13 runs at once and one at a time differed by 1 ulp in the odometry.)"""
    from sims.batch import scenario_batch

    config = tiny_config()
    for width in (1, 3):
        whole = scenario_batch(config, np.arange(13), width=width)
        expected = jax.tree.leaves((whole.controls, whole.observations, whole.tree_seen))
        for ids in (np.array([7, 2, 11]), np.array([12]), np.arange(5, 13)):
            part = scenario_batch(config, ids, width=width)
            leaves = jax.tree.leaves((part.controls, part.observations, part.tree_seen))
            for got, want in zip(leaves, expected):
                assert np.array_equal(np.asarray(got), np.asarray(want)[ids], equal_nan=True)


# --------------------------------------------------------------------------------------------
# Slow tier: a sweep condition against its fixed-parameter study, two devices


@pytest.mark.slow
def test_sweep_condition_is_bit_identical_to_the_fixed_params_study(reference, tmp_path):
    config, reference_out = reference
    fixed = studies.load_study_config(
        None, [o for o in TINY if not o.startswith("sweep.")]
        + ["chunk_size=5", "params.detection_probability=0.9"])
    out = tmp_path / "fixed"
    studies.run_study(fixed, out, progress=False)
    table, traces = results(out)
    swept, swept_traces = results(reference_out)
    rows = [i for i, c in enumerate(swept["condition"]) if c == 1]
    for name, values in table.items():
        if name in TIMING_COLUMNS + ("condition", "detection_probability"):
            continue
        expected = np.asarray(swept[name])[rows]
        assert np.array_equal(np.asarray(values), expected, equal_nan=True), name
    for (_, run_id), errors in traces.items():
        assert np.array_equal(errors, swept_traces[1, run_id])


_CHILD = """
import json, sys
import jax
args = json.loads(sys.argv[1])
for name, value in args["jax"].items():  # this test process's settings (conftest's)
    jax.config.update(name, value)
from jaxslam import studies
config = studies.study_config_from_dict(args["config"])
studies.run_study(config, args["out"], progress=False)
print("devices", len(jax.devices()))
"""


@pytest.mark.slow
@pytest.mark.parametrize("run_width", [1, 3])
def test_two_devices_are_bit_identical(reference, tmp_path, run_width):
    config, reference_out = reference
    config = with_chunk(config, 5, run_width=run_width)
    one = tmp_path / "one"
    if run_width == 1:
        one = reference_out
    else:
        studies.run_study(config, one, progress=False)
    script = tmp_path / "child.py"
    script.write_text(_CHILD)
    payload = json.dumps(dict(config=studies.study_config_to_dict(config),
                              out=str(tmp_path / "two"),
                              jax=study_store.numeric_jax_settings()))
    env = dict(os.environ, PYTHONPATH=str(REPO),
               XLA_FLAGS=f"{os.environ['JAXSLAM_TEST_XLA_FLAGS']} "
                         "--xla_force_host_platform_device_count=2")
    child = subprocess.run([sys.executable, str(script), payload], capture_output=True,
                           text=True, timeout=600, cwd=REPO, env=env)
    assert child.returncode == 0, child.stderr[-3000:]
    assert "devices 2" in child.stdout
    assert_bit_identical(tmp_path / "two", one)
