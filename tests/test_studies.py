"""Study runner: results independent of chunk size and device count, resume, faults, sweeps.

Every study here is tiny (P=8, M=24, K=8, T=20, 4 runs) but each new shape still costs one
simulator and one filter compile (~20-40 s on the shared 2-core CPU), so the default tier
computes two studies once per module (chunk sizes 3 and 2, both a 2-value sweep) and every
resume test works on copies of their folders. Killed studies, the 2-device run and the
sweep-vs-fixed-params check run in the slow tier.

"Identical" below means bit-identical: every column (timing lives in the chunk metadata, not
in a column) and every per-step error trace compared with ``assert_array_equal``.
"""
import json
import os
import pathlib
import shutil
import signal
import subprocess
import sys
import time
import tomllib
import warnings

import jax
import numpy as np
import pyarrow.parquet as pq
import pytest

from jaxslam import studies, study_store
from jaxslam.types import Params

PYTHON = sys.executable
REPO = pathlib.Path(__file__).resolve().parent.parent
TINY = ["num_runs=4", "filter.num_particles=8", "filter.max_landmarks=24", "filter.max_obs=8",
        "scenario.num_steps=20", "scenario.num_trees=15", "scenario.size=30.0",
        "sweep.detection_probability=[0.8, 0.9]",
        # The study machinery does not depend on the proposal: the seed paper's FastSLAM
        # compiles fastest, and detection_probability (landmark existence) changes its maps
        # within 20 steps (the default observation proposal deletes no landmark here).
        "filter.proposal='motion'", "filter.anchor_empty_map=false",
        "params.motion_outlier_probability=0.0"]


def tiny_config(*overrides) -> studies.StudyConfig:
    return studies.load_study_config(None, TINY + list(overrides))


# --------------------------------------------------------------------------------------------
# Helpers


def read_traces(out_dir) -> dict:
    """Per-step position errors of every (condition, run_id), from all traces-*.npz files."""
    traces = {}
    for path in sorted(pathlib.Path(out_dir).glob("traces/traces-*.npz")):
        with np.load(path) as data:
            for condition, run_id, errors in zip(data["condition"], data["run_id"],
                                                 data["pose_error"]):
                key = (int(condition), int(run_id))
                assert key not in traces, f"{key} appears twice in the traces"
                traces[key] = errors
    return traces


def assert_same_results(out_a, out_b, close=None):
    """Bit-identical rows and traces in two study folders.

    ``close`` maps a column to the relative tolerance it gets instead (see its callers).
    """
    close = close or {}
    table_a, table_b = studies.load_results(out_a), studies.load_results(out_b)
    assert table_a.column_names == table_b.column_names
    differing = []
    for name in table_a.column_names:
        a, b = table_a.column(name).to_numpy(), table_b.column(name).to_numpy()
        if name in close:
            np.testing.assert_allclose(a, b, rtol=close[name], atol=0, err_msg=name)
        elif not np.array_equal(a, b):
            differing.append(f"{name}: {a} != {b}")
    assert not differing, "\n".join(differing)
    traces_a, traces_b = read_traces(out_a), read_traces(out_b)
    assert sorted(traces_a) == sorted(traces_b)
    for key, errors in traces_a.items():
        np.testing.assert_array_equal(errors, traces_b[key], err_msg=str(key))


def assert_runs_once(out_dir, config):
    """Every (condition, run id) exactly once in the table and in the chunk files."""
    table = studies.load_results(out_dir)
    pairs = list(zip(table.column("condition").to_pylist(), table.column("run_id").to_pylist()))
    expected = [(c, r) for c in range(len(config.conditions)) for r in range(config.num_runs)]
    assert pairs == expected  # load_results sorts; equality also rules out duplicates
    assert sorted(read_traces(out_dir)) == expected


def file_stamps(out_dir, pattern="*") -> dict:
    """(inode, mtime) of files: an atomic rewrite changes the inode even within one tick."""
    return {p.name: (p.stat().st_ino, p.stat().st_mtime_ns)
            for p in pathlib.Path(out_dir).rglob(pattern) if p.is_file()}


def age_files(out_dir):
    """Backdate every file so that any rewrite shows in its mtime."""
    for path in pathlib.Path(out_dir).rglob("*"):
        os.utime(path, ns=(1_000_000_000, 1_000_000_000))


def copy_study(source, target) -> pathlib.Path:
    shutil.copytree(source, target)
    age_files(target)
    return pathlib.Path(target)


def run_quietly(config, out_dir):
    """run_study with every warning turned into an error (a clean resume warns about nothing)."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        return studies.run_study(config, out_dir, progress=False)


# --------------------------------------------------------------------------------------------
# The two reference studies (computed once per module)


@pytest.fixture(scope="module")
def study_3(tmp_path_factory):
    """Chunk size 3: chunks [0, 3) and [3, 4) (the second padded)."""
    config = tiny_config("chunk_size=3")
    out = tmp_path_factory.mktemp("study") / "chunk3"
    result = studies.run_study(config, out, progress=False)
    return config, out, result


@pytest.fixture(scope="module")
def study_2(tmp_path_factory):
    """Chunk size 2: chunks [0, 2) and [2, 4)."""
    config = tiny_config("chunk_size=2")
    out = tmp_path_factory.mktemp("study") / "chunk2"
    result = studies.run_study(config, out, progress=False)
    return config, out, result


# --------------------------------------------------------------------------------------------
# Config: parsing, round trip, errors naming the key and the allowed values


def test_overrides_and_round_trip():
    config = tiny_config("chunk_size=3", "params.association_gate=16.0", "seed=7")
    assert (config.num_runs, config.chunk_size, config.seed) == (4, 3, 7)
    assert config.filter.num_particles == 8 and config.scenario.size == 30.0
    assert config.params == (("motion_outlier_probability", 0.0), ("association_gate", 16.0))
    assert config.conditions == [{"detection_probability": 0.8},
                                 {"detection_probability": 0.9}]
    assert studies.study_config_from_dict(studies.study_config_to_dict(config)) == config
    # The swept value wins over a fixed one; the fixed one applies to every condition.
    params = studies.condition_params(config)
    np.testing.assert_allclose(params.detection_probability, [0.8, 0.9], rtol=1e-7)
    np.testing.assert_allclose(params.association_gate, [16.0, 16.0])


@pytest.mark.parametrize("overrides, named", [
    (["filter.num_particle=8"], ["filter.num_particle", "num_particles"]),
    (["scenario.trees=8"], ["scenario.trees", "num_trees"]),
    (["numruns=8"], ["numruns", "num_runs"]),
    (["params.not_a_param=1.0"], ["not_a_param", "detection_probability"]),
    (["sweep.not_a_param=[1.0, 2.0]"], ["not_a_param", "detection_probability"]),
    (["sweep.max_range=5.0"], ["sweep.max_range", "non-empty list"]),
    (["sweep.max_range=[]"], ["sweep.max_range", "non-empty list"]),
    (["scenario.forest='jungle'"], ["jungle", "plantation"]),
    (["scenario.path='spiral'"], ["spiral", "lawnmower"]),
    (["filter.association='best'"], ["best", "hungarian"]),
    (["num_runs=0"], ["num_runs", "positive integer"]),
    (["chunk_size=2.5"], ["chunk_size", "positive integer"]),
    (["num_runs"], ["num_runs", "section.key=value"]),
])
def test_bad_config_names_key_and_allowed_values(overrides, named):
    with pytest.raises(ValueError) as error:
        studies.load_study_config(None, overrides)
    for word in named:
        assert word in str(error.value), (word, str(error.value))


def test_config_file_and_missing_file(tmp_path):
    path = tmp_path / "study.toml"
    path.write_text('name = "file"\nnum_runs = 3\n[filter]\nnum_particles = 5\n'
                    '[sweep]\nmax_range = [10.0, 15.0]\n')
    config = studies.load_study_config(path, ["filter.num_particles=6"])
    assert (config.name, config.num_runs, config.filter.num_particles) == ("file", 3, 6)
    assert config.conditions == [{"max_range": 10.0}, {"max_range": 15.0}]
    with pytest.raises(FileNotFoundError, match="nope.toml"):
        studies.load_study_config(tmp_path / "nope.toml")
    path.write_text("[filter]\nnum_particles = 5\nnum_particle = 6\n")
    with pytest.raises(ValueError, match="filter.num_particle'"):
        studies.load_study_config(path)


# --------------------------------------------------------------------------------------------
# Chunk size, sweeps


def test_results_do_not_depend_on_chunk_size(study_3, study_2):
    config_3, out_3, result_3 = study_3
    config_2, out_2, result_2 = study_2
    assert sorted(p.name for p in out_3.glob("runs/chunk-*")) == [
        "chunk-000000-000003.parquet", "chunk-000003-000004.parquet"]
    assert sorted(p.name for p in out_2.glob("runs/chunk-*")) == [
        "chunk-000000-000002.parquet", "chunk-000002-000004.parquet"]
    for config, out in ((config_3, out_3), (config_2, out_2)):
        assert_runs_once(out, config)
    assert_same_results(out_3, out_2)
    # The returned table is the one on disk.
    assert result_3.table.equals(studies.load_results(out_3))
    assert result_3.filter_seconds > 0 and result_3.compile_seconds > 0


def test_sweep_gives_conditions_over_the_same_runs(study_3):
    config, out, result = study_3
    table = result.table.to_pydict()
    assert "detection_probability" in table
    for condition, value in enumerate((0.8, 0.9)):
        rows = [i for i, c in enumerate(table["condition"]) if c == condition]
        assert [table["run_id"][i] for i in rows] == [0, 1, 2, 3]
        assert {table["detection_probability"][i] for i in rows} == {value}
        assert {table["study_seed"][i] for i in rows} == {0}
        # run_key: the two words of fold_in(PRNGKey(0), run_id), one per run, equal across
        # conditions (common random numbers).
        keys = [jax.random.key_data(jax.random.fold_in(jax.random.PRNGKey(0), r))
                for r in range(4)]
        assert [table["run_key"][i] for i in rows] == [
            (int(k[0]) << 32) | int(k[1]) for k in keys]
    # The swept parameter reaches the filter: the two conditions score differently (same
    # forests, paths and noise, so a difference can only come from the parameter).
    landmarks = np.asarray(table["num_landmarks"]).reshape(2, 4)
    gospa = np.asarray(table["gospa"]).reshape(2, 4)
    assert not (np.array_equal(landmarks[0], landmarks[1]) and np.array_equal(gospa[0], gospa[1]))
    for name in studies.SUMMARY_METRICS:
        assert np.all(np.isfinite(np.asarray(table[name], float))), name
    summary = (out / "summary.md").read_text()
    assert "detection_probability=0.8" in summary and "detection_probability=0.9" in summary


# --------------------------------------------------------------------------------------------
# Resume


def test_rerun_computes_nothing_and_gives_the_same_table(study_3, tmp_path):
    config, source, result = study_3
    out = copy_study(source, tmp_path / "out")
    before = file_stamps(out, "chunk-*") | file_stamps(out, "traces-*")
    again = run_quietly(config, out)
    assert file_stamps(out, "chunk-*") | file_stamps(out, "traces-*") == before
    assert again.compile_seconds == again.filter_seconds == again.simulator_seconds == 0.0
    assert again.table.equals(result.table)


@pytest.mark.parametrize("key, then", [("jax_disable_most_optimizations", "flipped"),
                                       ("jax_version", "0.0.1")])
def test_resume_under_other_jax_numerics_warns(study_3, tmp_path, key, then):
    """provenance.toml records the jax version and the settings that change the numbers; a
    session that resumes finished chunks under another warns, naming it and both values (the
    chunks computed then may differ in their last bits), and records the new value. The
    finished results are kept. (An unchanged resume warns about nothing: run_quietly above.)"""
    import tomli_w

    config, source, result = study_3
    out = copy_study(source, tmp_path / "out")
    path = out / "provenance.toml"
    record = tomllib.loads(path.read_text())
    now = record[key]
    assert record["jax_enable_x64"] is True  # conftest's setting, recorded
    record[key] = (not now) if then == "flipped" else then
    path.write_text(tomli_w.dumps(record))
    with pytest.warns(UserWarning, match=f"{key}: {record[key]!r} then, {now!r} now"):
        again = studies.run_study(config, out, progress=False)
    assert again.table.equals(result.table) and again.filter_seconds == 0.0
    assert tomllib.loads(path.read_text())[key] == now


def test_missing_chunk_is_recomputed_alone(study_3, tmp_path):
    config, source, _ = study_3
    out = copy_study(source, tmp_path / "out")
    (out / "runs/chunk-000003-000004.parquet").unlink()
    (out / "traces/traces-000003-000004.npz").unlink()
    kept = file_stamps(out, "*000000-000003*")
    again = run_quietly(config, out)
    assert again.filter_seconds > 0
    assert file_stamps(out, "*000000-000003*") == kept
    assert_runs_once(out, config)
    assert_same_results(out, source)


def test_different_study_in_the_folder_is_refused(study_3, tmp_path):
    config, source, _ = study_3
    out = copy_study(source, tmp_path / "out")
    before = {p: p.read_bytes() for p in out.rglob("*") if p.is_file() and p.name != "study.lock"}
    for other in (tiny_config("chunk_size=3", "seed=1"), tiny_config("run_width=2"),
                  tiny_config("chunk_size=3", "filter.num_particles=9")):
        with pytest.raises(studies.StudyError, match="different study config"):
            studies.run_study(other, out, progress=False)
    assert {p: p.read_bytes() for p in out.rglob("*")
            if p.is_file() and p.name != "study.lock"} == before


def _assert_moved_aside_and_recomputed(config, out, reference, damaged_name, words):
    """Resume warns naming the file, moves it to damaged/ (kept, not deleted), recomputes."""
    with pytest.warns(UserWarning) as caught:
        studies.run_study(config, out, progress=False)
    message = " ".join(str(w.message) for w in caught)
    for word in (damaged_name, *words):
        assert word in message, (word, message)
    assert any(p.name.startswith(damaged_name) for p in (out / "damaged").iterdir())
    assert_runs_once(out, config)
    assert_same_results(out, reference)


@pytest.mark.parametrize("damage", ["garbage", "other_runs", "one_flipped_bit", "truncated"])
def test_damaged_chunk_is_moved_aside_and_recomputed(study_3, tmp_path, damage):
    config, source, _ = study_3
    out = copy_study(source, tmp_path / "out")
    chunk = out / "runs/chunk-000003-000004.parquet"
    content = bytearray(chunk.read_bytes())
    if damage == "garbage":
        chunk.write_bytes(b"\x00not parquet\xff" * 10)
    elif damage == "other_runs":  # a readable chunk of other runs
        shutil.copyfile(out / "runs/chunk-000000-000003.parquet", chunk)
    elif damage == "one_flipped_bit":
        content[len(content) // 2] ^= 0x04
        chunk.write_bytes(bytes(content))
    else:
        chunk.write_bytes(bytes(content[: len(content) // 2]))
    _assert_moved_aside_and_recomputed(config, out, source, chunk.name, ["checksum mismatch"])


@pytest.mark.parametrize("damage", ["deleted", "truncated"])
def test_damaged_traces_file_is_moved_aside_and_recomputed(study_3, tmp_path, damage):
    config, source, _ = study_3
    out = copy_study(source, tmp_path / "out")
    traces = out / "traces/traces-000000-000003.npz"
    if damage == "deleted":
        traces.unlink()
        words = ["traces-000000-000003.npz is missing"]
        damaged_name = "chunk-000000-000003.parquet"
    else:
        traces.write_bytes(traces.read_bytes()[:100])
        words = ["checksum mismatch"]
        damaged_name = traces.name
    _assert_moved_aside_and_recomputed(config, out, source, damaged_name, words)


def test_unreadable_manifest_recomputes_everything_to_the_same_results(study_3, tmp_path):
    config, source, _ = study_3
    out = copy_study(source, tmp_path / "out")
    (out / "manifest.json").write_text("{not json")
    _assert_moved_aside_and_recomputed(config, out, source, "chunk-000000-000003.parquet",
                                       ["manifest.json is unreadable", "not in the manifest"])
    assert len(list((out / "damaged").glob("chunk-*"))) == 2


def test_second_process_on_the_folder_is_refused(study_3, tmp_path):
    """While one process holds the study's lock, another gets a StudyError naming it; the
    lock is free again once its holder finishes."""
    config, source, result = study_3
    out = copy_study(source, tmp_path / "out")
    holder = subprocess.Popen(
        [PYTHON, "-c", "import fcntl, sys, time; f = open(sys.argv[1], 'a+'); "
         "fcntl.flock(f, fcntl.LOCK_EX); f.write('pid test-holder'); f.flush(); "
         "print('locked', flush=True); time.sleep(60)", str(out / "study.lock")],
        stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "locked"
        with pytest.raises(studies.StudyError, match="in use by another study process"):
            studies.run_study(config, out, progress=False)
    finally:
        holder.kill()
        holder.wait()
    assert run_quietly(config, out).table.equals(result.table)


def test_num_runs_grows_on_resume_and_equals_the_larger_study(study_3, tmp_path):
    config, source, _ = study_3
    out = copy_study(source, tmp_path / "grown")
    kept = file_stamps(out, "*000000-000003*") | file_stamps(out, "*000003-000004*")
    grown_config = tiny_config("chunk_size=3", "num_runs=6")
    grown = run_quietly(grown_config, out)
    assert file_stamps(out, "*000000-000003*") | file_stamps(out, "*000003-000004*") == kept
    assert sorted(p.name for p in out.glob("runs/chunk-*")) == [
        "chunk-000000-000003.parquet", "chunk-000003-000004.parquet",
        "chunk-000004-000006.parquet"]
    with open(out / "study.toml", "rb") as handle:
        assert tomllib.load(handle)["num_runs"] == 6
    assert_runs_once(out, grown_config)
    whole = studies.run_study(tiny_config("chunk_size=6", "num_runs=6"), tmp_path / "whole",
                              progress=False)
    assert_same_results(out, tmp_path / "whole")
    assert grown.table.num_rows == whole.table.num_rows == 12
    with pytest.raises(studies.StudyError, match="can grow on resume, not shrink"):
        studies.run_study(tiny_config("chunk_size=3", "num_runs=2"), out, progress=False)


def test_foreign_file_is_reported_and_left_alone(study_3, tmp_path):
    config, source, result = study_3
    out = copy_study(source, tmp_path / "out")
    (out / "notes.txt").write_text("mine")
    (out / "chunk-extra.csv").write_text("also mine")
    assert studies.foreign_files(out) == ["chunk-extra.csv", "notes.txt"]
    with pytest.warns(UserWarning, match="notes.txt"):
        again = studies.run_study(config, out, progress=False)
    assert (out / "notes.txt").read_text() == "mine"
    assert (out / "chunk-extra.csv").read_text() == "also mine"
    assert again.table.equals(result.table)


def test_leftover_temporary_file_is_cleaned(study_3, tmp_path):
    config, source, result = study_3
    out = copy_study(source, tmp_path / "out")
    (out / "runs/.tmp-chunk-000003-000004.parquet").write_bytes(b"half a chunk")
    before = file_stamps(out, "chunk-*")
    again = run_quietly(config, out)
    assert not list(out.rglob(".tmp-*"))
    assert file_stamps(out, "chunk-*") == before
    assert again.table.equals(result.table)


def test_output_folder_contents(study_3):
    config, out, _ = study_3
    names = sorted(p.relative_to(out).as_posix() for p in out.rglob("*") if p.is_file())
    assert names == ["example_run.npz", "manifest.json", "provenance.toml",
                     "runs/chunk-000000-000003.parquet", "runs/chunk-000003-000004.parquet",
                     "study.lock", "study.toml", "summary.json", "summary.md",
                     "traces/traces-000000-000003.npz",
                     "traces/traces-000003-000004.npz"]
    assert studies.foreign_files(out) == []
    schema = pq.read_schema(out / "runs/chunk-000000-000003.parquet")
    for name in ("run_id", "condition", "study_seed", "run_key", "detection_probability",
                 *studies.SUMMARY_METRICS):
        assert name in schema.names, name
    units = json.loads(schema.metadata[b"jaxslam.units"])
    assert units["final_pose_error"] == "m" and units["rpe_rotation"] == "rad"
    assert schema.field("ate_rmse").metadata == {b"unit": b"m"}
    assert set(units) == set(schema.names)
    embedded = tomllib.loads(schema.metadata[b"jaxslam.study"].decode())
    assert studies.study_config_from_dict(embedded) == config
    assert float(schema.metadata[b"jaxslam.update_rate_hz"]) > 0
    with np.load(out / "traces/traces-000000-000003.npz") as traces:
        assert traces["pose_error"].shape == (2 * 3, config.scenario.num_steps)
    manifest = json.loads((out / "manifest.json").read_text())["files"]
    assert sorted(manifest) == [n for n in names if n.startswith(("runs/", "traces/"))
                                or n == "example_run.npz"]


def test_tools_read_the_runs_folder_whole(study_3):
    """pandas and pyarrow.dataset read the study's rows straight from ``runs/``."""
    pd = pytest.importorskip("pandas")
    import pyarrow.dataset as ds

    config, out, result = study_3
    frame = pd.read_parquet(out / "runs").sort_values(["condition", "run_id"])
    assert len(frame) == 2 * config.num_runs
    np.testing.assert_array_equal(frame["final_pose_error"].to_numpy(),
                                  result.table.column("final_pose_error").to_numpy())
    assert ds.dataset(out / "runs").count_rows() == 2 * config.num_runs


def test_no_measured_column_shares_a_config_key(study_3):
    config, _, result = study_3
    keys = {k.rsplit(".", 1)[-1] for k in study_store._flatten(
        studies.study_config_to_dict(config))}
    keys |= set(Params._fields)
    swept = {name for name, _ in config.sweep}
    clashes = (set(result.table.column_names) - swept) & keys
    assert not clashes, clashes


def test_summary_has_units_and_a_confidence_interval_of_the_mean(study_3):
    from scipy import stats

    config, out, result = study_3
    rows = studies.summary_rows(config, result.table)
    row = next(r for r in rows if r["metric"] == "final_pose_error" and r["condition"] == 0)
    values = result.table.filter(pc_equal(result.table, 0)).column("final_pose_error")
    values = values.to_numpy().astype(np.float64)
    half = stats.t.ppf(0.975, 3) * np.std(values, ddof=1) / 2.0  # n = 4 runs
    np.testing.assert_allclose([row["ci_low"], row["ci_high"]],
                               [values.mean() - half, values.mean() + half], rtol=1e-12)
    np.testing.assert_allclose([row["p2_5"], row["p97_5"]],
                               np.percentile(values, [2.5, 97.5]), rtol=1e-12)
    assert row["unit"] == "m"
    text = (out / "summary.md").read_text()
    assert "| unit |" in text and "mean 95% CI" in text and "| final_pose_error | m |" in text
    stored = json.loads((out / "summary.json").read_text())
    assert stored["study"] == config.name and stored["rows"] == json.loads(json.dumps(rows))


WINDOW_COLUMNS = ["num_window_cut_steps", "peak_window_cut"]


def test_without_a_window_no_run_is_flagged(study_3):
    """No association window: the guard's columns exist, are 0 in every row, and the
    summary carries no window warning."""
    _, out, result = study_3
    for name in WINDOW_COLUMNS:
        np.testing.assert_array_equal(result.table.column(name).to_numpy(), 0)
    assert "association window" not in (out / "summary.md").read_text()


def test_chunk_written_before_a_column_existed_reads_as_null(study_3, tmp_path):
    """A store whose first chunk lacks the window columns (as an earlier version wrote it)
    still resumes and grows: its rows hold null there, a warning names the chunk and the
    columns, every other value is unchanged, and new chunks carry the columns."""
    import pyarrow.parquet as pq

    config, source, result = study_3
    out = copy_study(source, tmp_path / "older")
    chunk = out / "runs" / "chunk-000000-000003.parquet"
    pq.write_table(pq.read_table(chunk).drop_columns(WINDOW_COLUMNS), chunk)
    study_store.record_files(out, [chunk])  # as the earlier version recorded it
    grown_config = tiny_config("chunk_size=3", "num_runs=5")
    with pytest.warns(UserWarning, match=r"1 of 3 chunks \(chunk-000000-000003.parquet\) "
                                         "were written without num_window_cut_steps, "
                                         "peak_window_cut"):
        grown = studies.run_study(grown_config, out, progress=False)
    table = grown.table
    old = np.isin(table.column("run_id").to_numpy(), [0, 1, 2])
    for name in WINDOW_COLUMNS:
        column = table.column(name)
        assert column.null_count == old.sum() == 2 * 3
        np.testing.assert_array_equal(np.isnan(column.to_numpy(zero_copy_only=False)), old)
        np.testing.assert_array_equal(column.to_numpy(zero_copy_only=False)[~old], 0)
    first_rows = table.filter(pc_less(table, "run_id", 4))
    for name in result.table.column_names:
        if name not in WINDOW_COLUMNS:
            np.testing.assert_array_equal(first_rows.column(name).to_numpy(),
                                          result.table.column(name).to_numpy(), err_msg=name)
    assert "| final_pose_error | m |" in (out / "summary.md").read_text()


def test_chunks_that_disagree_on_a_column_type_are_refused_by_name(study_3, tmp_path):
    import pyarrow as pa
    import pyarrow.parquet as pq

    _, source, _ = study_3
    out = copy_study(source, tmp_path / "retyped")
    chunk = out / "runs" / "chunk-000003-000004.parquet"
    table = pq.read_table(chunk)
    index = table.column_names.index("num_landmarks")
    as_text = pa.array([str(v) for v in table.column(index).to_pylist()])
    pq.write_table(table.set_column(index, "num_landmarks", as_text), chunk)
    with pytest.raises(studies.StudyError, match="store a column with different types"):
        studies.load_results(out)


def _with_column(table, name, values):
    """``table`` with column ``name`` replaced by ``values`` (a list; None is null)."""
    import pyarrow as pa

    index = table.column_names.index(name)
    return table.set_column(index, name, pa.array(values, table.schema.field(name).type))


def test_summary_names_the_conditions_whose_runs_the_window_cut(study_3):
    """``warning_lines`` on the study's table with the column set by hand: only the
    condition with a flagged run is named, with its count of runs and the most steps."""
    config, _, result = study_3
    windowed = studies.load_study_config(None, TINY + ["filter.association_window=4"])
    cut = np.zeros(result.table.num_rows, int)
    condition = result.table.column("condition").to_numpy()
    cut[np.flatnonzero(condition == 1)[:2]] = [3, 7]
    table = _with_column(result.table, "num_window_cut_steps", cut.tolist())
    flagged = [line for line in studies.warning_lines(windowed, table) if line.startswith("- ")]
    assert flagged == [
        "- detection_probability=0.9: in 2 of 4 runs the association window "
        "(filter.association_window = 4) left out landmarks that could have taken part (up to "
        "7 steps in one run, `num_window_cut_steps`); raise it until no run is flagged, or set "
        "0 for the full association."]
    assert studies.warning_lines(config, result.table) == []
    # Runs of chunks written before the column existed (null) are neither flagged nor
    # counted as checked; they are named as unchecked.
    with_nulls = _with_column(table, "num_window_cut_steps",
                              [None if i < 3 else int(v) for i, v in enumerate(cut)])
    lines = [line for line in studies.warning_lines(windowed, with_nulls)
             if line.startswith("- ")]
    assert lines == [
        "- detection_probability=0.8: 3 runs were written before `num_window_cut_steps` "
        "existed (null there): not checked.",
        flagged[0]]


def test_summary_warns_of_full_maps_and_weight_resets(study_3, tmp_path):
    """Dropped births (a full map) and weight resets, set by hand in one run each, are named
    in summary.md and summary.json with what to do; the unchanged study warns of nothing."""
    config, source, result = study_3
    assert "Warnings:" not in (source / "summary.md").read_text()
    births = np.zeros(result.table.num_rows, int)
    births[0] = 12
    resets = np.zeros(result.table.num_rows, int)
    resets[-1] = 2
    table = _with_column(result.table, "num_dropped_births", births.tolist())
    table = _with_column(table, "num_weight_resets", resets.tolist())
    out = copy_study(source, tmp_path / "warned")
    text = studies.summarize_study(out, table)
    assert ("- detection_probability=0.8: in 1 of 4 runs the map's 24 slots were full and new "
            "landmarks were dropped (up to 12 births in one run, `num_dropped_births`); raise "
            "filter.max_landmarks") in text
    assert ("- detection_probability=0.9: in 1 of 4 runs every particle's weight was zero at "
            "some step") in text
    stored = json.loads((out / "summary.json").read_text())["warnings"]
    assert len(stored) == 2 and stored[0].startswith("detection_probability=0.8: in 1 of 4")


def pc_less(table, name, bound):
    import pyarrow.compute as pc

    return pc.less(table.column(name), bound)


def pc_equal(table, condition):
    import pyarrow.compute as pc

    return pc.equal(table.column("condition"), condition)


# --------------------------------------------------------------------------------------------
# Subprocess studies: faults and sharding (slow tier)

_CHILD = """
import json, sys, time
import jax
args = json.loads(sys.argv[1])
for name, value in args["jax"].items():  # the test process's settings (conftest's)
    jax.config.update(name, value)
jax.config.update("jax_numpy_rank_promotion", "raise")
jax.config.update("jax_compilation_cache_dir", args["cache"])
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
from jaxslam import studies

if args["chunk_delay"]:  # slow each chunk down (after computing it) so a kill lands mid-study
    compute = studies._ChunkRunner.__call__
    def slow(self, start, stop):
        output = compute(self, start, stop)
        time.sleep(args["chunk_delay"])
        return output
    studies._ChunkRunner.__call__ = slow
print("devices", jax.device_count(), flush=True)
studies.run_study(studies.study_config_from_dict(args["config"]), args["out"], progress=False)
print("finished", flush=True)
"""


@pytest.fixture(scope="module")
def compile_cache(tmp_path_factory):
    """A persistent compilation cache shared by the subprocesses of this module."""
    return tmp_path_factory.mktemp("jax-cache")


def child_command(tmp_path, config, out, cache, chunk_delay=0.0):
    script = tmp_path / "child.py"
    script.write_text(_CHILD)
    args = dict(config=studies.study_config_to_dict(config), out=str(out), cache=str(cache),
                chunk_delay=chunk_delay,
                # conftest's x64 and turned-down optimisation: the child compiles the same
                jax=study_store.numeric_jax_settings())
    return [PYTHON, str(script), json.dumps(args)]


def child_env(**extra):
    """The test process's environment with its own XLA_FLAGS (conftest's) before ``extra``'s."""
    env = dict(os.environ, PYTHONPATH=str(REPO), XLA_FLAGS=os.environ["JAXSLAM_TEST_XLA_FLAGS"])
    if "XLA_FLAGS" in extra:
        extra["XLA_FLAGS"] = f"{env['XLA_FLAGS']} {extra['XLA_FLAGS']}".strip()
    return dict(env, **extra)


def run_child(tmp_path, config, out, cache, **env):
    result = subprocess.run(child_command(tmp_path, config, out, cache), capture_output=True,
                            text=True, timeout=400, cwd=REPO, env=child_env(**env))
    assert result.returncode == 0, result.stderr[-3000:]
    return result.stdout


@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGKILL], ids=["SIGINT", "SIGKILL"])
def test_killed_study_resumes_to_the_same_results(study_2, compile_cache, tmp_path, sig):
    config, reference, _ = study_2
    out = tmp_path / "out"
    first_chunk = out / "runs/chunk-000000-000002.parquet"
    child = subprocess.Popen(child_command(tmp_path, config, out, compile_cache, chunk_delay=3.0),
                             cwd=REPO, env=child_env(), stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 300
        while not first_chunk.exists():
            assert child.poll() is None, child.communicate()[1][-3000:]
            assert time.monotonic() < deadline, "the study wrote no chunk in 300 s"
            time.sleep(0.05)
        child.send_signal(sig)
        _, stderr = child.communicate(timeout=60)
    finally:
        if child.poll() is None:
            child.kill()
            child.wait()
    assert child.returncode != 0
    if sig == signal.SIGINT:
        assert "KeyboardInterrupt" in stderr
    # Killed mid-study: the first chunk only, complete, and nothing half-written under a
    # chunk name (a .tmp-* file may remain; the restart removes it).
    assert sorted(p.name for p in out.glob("runs/chunk-*")) == [first_chunk.name]
    assert pq.read_table(first_chunk).column("run_id").to_pylist() == [0, 1, 0, 1]
    age_files(out)
    kept = file_stamps(out, "*000000-000002*")
    run_child(tmp_path, config, out, compile_cache)
    assert file_stamps(out, "*000000-000002*") == kept  # the finished chunk was not redone
    assert not list(out.rglob(".tmp-*"))
    assert_runs_once(out, config)
    assert_same_results(out, reference)


# Measured (x64 on and off): with 2 devices every trace and every metric is bit-identical to
# one device except rpe_translation, which differs by 1 float32 ulp in one run of the first
# chunk (the sharded program fuses that reduction differently; the metric alone, jitted and
# sharded outside the study, is bit-identical). 2 ulp are allowed for that column only.
DEVICE_COUNT_ULP_COLUMNS = {"rpe_translation": 2.5e-7}


@pytest.mark.slow
def test_two_devices_give_the_same_results(study_3, compile_cache, tmp_path):
    config, reference, _ = study_3
    out = tmp_path / "out"
    stdout = run_child(tmp_path, config, out, compile_cache,
                       XLA_FLAGS="--xla_force_host_platform_device_count=2")
    assert "devices 2" in stdout
    assert_runs_once(out, config)
    assert_same_results(out, reference, close=DEVICE_COUNT_ULP_COLUMNS)
    with open(out / "provenance.toml", "rb") as handle:
        assert len(tomllib.load(handle)["devices"]) == 2


@pytest.mark.slow
def test_sweep_condition_equals_fixed_params_study(study_3, tmp_path):
    config, reference, _ = study_3
    fixed = studies.load_study_config(
        None, [o for o in TINY if not o.startswith("sweep.")]
        + ["chunk_size=3", "params.detection_probability=0.9"])
    result = studies.run_study(fixed, tmp_path / "fixed", progress=False)
    swept = studies.load_results(reference).to_pydict()
    rows = [i for i, c in enumerate(swept["condition"]) if c == 1]
    single = result.table.to_pydict()
    assert single["run_id"] == [0, 1, 2, 3] and set(single["condition"]) == {0}
    for name in single:
        if name == "condition":
            continue
        expected = [swept[name][i] for i in rows]
        if name == "pose_nees":
            # ~1e6 here: 8 particles collapse, so the 3x3 solve is ill-conditioned and the
            # batched solve (G=1 vs G=2) moved one run's value by 0.3% (measured).
            np.testing.assert_allclose(single[name], expected, rtol=1e-2, err_msg=name)
        else:
            np.testing.assert_array_equal(single[name], expected, err_msg=name)
    traces, swept_traces = read_traces(tmp_path / "fixed"), read_traces(reference)
    for run_id in range(4):
        np.testing.assert_array_equal(traces[0, run_id], swept_traces[1, run_id])


# --------------------------------------------------------------------------------------------
# Sweeps over a vector parameter


def test_sweep_over_a_vector_parameter_from_toml_and_set(study_3, tmp_path):
    """A 3-vector field swept from a TOML file equals the same sweep from --set, and runs end
    to end: one column per component, ``name[j]``, constant within a condition."""
    values = [[0.0, 0.06, 0.0002], [0.0, 0.12, 0.0004]]
    base = [o for o in TINY if not o.startswith("sweep.")] + ["chunk_size=3"]
    from_set = studies.load_study_config(None, base + [f"sweep.rot1_noise={values}"])
    path = tmp_path / "vector.toml"
    path.write_text(f"[sweep]\nrot1_noise = {values}\n")
    from_file = studies.load_study_config(path, base)
    assert from_file == from_set
    assert from_set.conditions == [{"rot1_noise": v} for v in values]
    np.testing.assert_allclose(studies.condition_params(from_set).rot1_noise, values, rtol=1e-6)
    result = studies.run_study(from_set, tmp_path / "out", progress=False)
    table = result.table.to_pydict()
    for j in range(3):
        expected = np.repeat([v[j] for v in values], from_set.num_runs)
        np.testing.assert_allclose(table[f"rot1_noise[{j}]"], expected, rtol=0)
    assert "rot1_noise" not in table
    # The setting reaches the filter: doubled heading noise changes the runs' scores.
    errors = np.asarray(table["final_pose_error"]).reshape(2, -1)
    assert not np.array_equal(errors[0], errors[1])
    assert "rot1_noise=[0.0, 0.12, 0.0004]" in (tmp_path / "out" / "summary.md").read_text()
    with pytest.raises(ValueError, match="rot1_noise"):
        studies.load_study_config(None, base + ["sweep.rot1_noise=[[0.0, 0.06], [0.1, 0.2]]"])


# --------------------------------------------------------------------------------------------
# Per-run worlds


def test_per_run_worlds_differ_by_run_and_do_not_depend_on_the_batch(tmp_path):
    """world='per_run': run i's forest and path come from its own key (run_world), whatever
    runs are simulated with it; the study's results do not depend on the chunk size, and the
    example run carries run 0's own world."""
    from sims.batch import run_world, scenario_batch

    config = tiny_config("scenario.world='per_run'", "scenario.path='random'", "chunk_size=3")
    batch = scenario_batch(config, np.arange(3))
    centres = np.asarray(batch.tree_centres)
    assert centres.shape == (3, config.scenario.num_trees, 2)
    assert np.asarray(batch.truth_pose).shape == (3, config.scenario.num_steps + 1, 3)
    assert not np.allclose(centres[0], centres[1]) and not np.allclose(centres[1], centres[2])
    forest, path = run_world(config.scenario, config.seed, 1)
    np.testing.assert_array_equal(centres[1], np.asarray(forest.centres, np.float32))
    np.testing.assert_array_equal(np.asarray(batch.truth_pose)[1], np.asarray(path, np.float32))
    alone = scenario_batch(config, np.array([1]))
    for whole, part in zip(jax.tree.leaves(batch), jax.tree.leaves(alone)):
        np.testing.assert_array_equal(np.asarray(whole)[1], np.asarray(part)[0])
    result_3 = studies.run_study(config, tmp_path / "chunk3", progress=False)
    result_2 = studies.run_study(tiny_config("scenario.world='per_run'", "scenario.path='random'",
                                             "chunk_size=2"), tmp_path / "chunk2", progress=False)
    assert_same_results(tmp_path / "chunk3", tmp_path / "chunk2")
    assert result_3.table.num_rows == result_2.table.num_rows == 8
    with np.load(tmp_path / "chunk3" / "example_run.npz") as example:
        np.testing.assert_array_equal(example["tree_centres"], centres[0])


def test_per_run_worlds_accept_lidar_and_refuse_unknown_worlds():
    """Per-run lidar worlds are simulated (tests/sims/test_per_run_lidar.py)."""
    config = tiny_config("scenario.world='per_run'", "scenario.observation_source='lidar'")
    assert config.scenario.world == "per_run"
    with pytest.raises(ValueError, match="'shared', 'per_run'"):
        tiny_config("scenario.world='mine'")


def test_compiled_program_key_follows_the_numeric_jax_settings():
    """A program compiled under one optimisation setting is not reused under the other (the
    study's numbers, and provenance.toml, follow the setting in force)."""
    from jaxslam.studies import runner

    config, args = tiny_config(), (np.zeros((2, 3), np.float32),)
    key = runner._program_key(config, "cpu", args)
    name = "jax_disable_most_optimizations"
    before = jax.config.read(name)
    try:
        jax.config.update(name, not before)
        other = runner._program_key(config, "cpu", args)
    finally:
        jax.config.update(name, before)
    assert other != key and runner._program_key(config, "cpu", args) == key


def test_a_window_below_the_view_is_flagged_in_the_study(tmp_path):
    """A window of 2 against about 15 trees, several in view at once: the guard flags runs,
    its per-run columns are consistent (peak > 0 exactly where steps > 0), and the summary
    names the window."""
    config = tiny_config("filter.association_window=2", "num_runs=2", "chunk_size=2")
    result = studies.run_study(config, tmp_path / "windowed", progress=False)
    steps = result.table.column("num_window_cut_steps").to_numpy()
    peak = result.table.column("peak_window_cut").to_numpy()
    assert steps.max() > 0 and np.all(steps <= config.scenario.num_steps)
    np.testing.assert_array_equal(peak > 0, steps > 0)
    text = (tmp_path / "windowed" / "summary.md").read_text()
    assert "association window (filter.association_window = 2)" in text
