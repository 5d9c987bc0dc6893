"""Ray backend: a clear error without the extra; on a local Ray instance (slow tier) the same
results as the local backend, bit for bit, and resume across the two backends."""
import importlib.util
import os
import pathlib
import shutil
import sys

import numpy as np
import pytest
import tomli_w

from jaxslam import ray_backend, studies
from test_studies import read_traces  # shared helper, as test_proposal uses test_filter

HAVE_RAY = importlib.util.find_spec("ray") is not None
needs_ray = pytest.mark.skipif(not HAVE_RAY, reason="ray is not installed (optional extra: "
                               "pip install 'jaxslam[ray]')")
REPO = pathlib.Path(__file__).resolve().parent.parent
TIMING_COLUMNS = ("update_rate_hz",)
# The tiny study of test_studies.py with chunk size 2 (2 chunks, 2 sweep conditions).
TINY = ["num_runs=4", "chunk_size=2", "filter.num_particles=8", "filter.max_landmarks=24",
        "filter.max_obs=8", "scenario.num_steps=20", "scenario.num_trees=15",
        "scenario.size=30.0", "sweep.detection_probability=[0.8, 0.9]"]


def test_missing_ray_names_the_extra(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # makes `import ray` raise ImportError
    with pytest.raises(ImportError, match=r"pip install 'jaxslam\[ray\]'"):
        ray_backend.import_ray()
    config = studies.load_study_config(None, TINY)
    with pytest.raises(ImportError, match="optional 'ray' extra"):
        ray_backend.run_study_ray(config, tmp_path / "out")
    assert not (tmp_path / "out").exists()  # nothing touched before the error


@pytest.mark.parametrize("num_workers", [0, -1, 1.5])
def test_bad_worker_count(tmp_path, num_workers):
    config = studies.load_study_config(None, TINY)
    with pytest.raises(ValueError, match="num_workers.*positive integer"):
        ray_backend.run_study_ray(config, tmp_path / "out", num_workers=num_workers)
    assert not (tmp_path / "out").exists()


def assert_same_results(out_a, out_b):
    """Bit-identical rows (the wall-clock rate aside) and per-step error traces."""
    table_a, table_b = studies.load_results(out_a), studies.load_results(out_b)
    assert table_a.column_names == table_b.column_names
    for name in table_a.column_names:
        if name not in TIMING_COLUMNS:
            np.testing.assert_array_equal(table_a.column(name).to_numpy(),
                                          table_b.column(name).to_numpy(), err_msg=name)
    traces_a, traces_b = read_traces(out_a), read_traces(out_b)
    assert sorted(traces_a) == sorted(traces_b) == [(c, r) for c in (0, 1) for r in range(4)]
    for key, errors in traces_a.items():
        np.testing.assert_array_equal(errors, traces_b[key], err_msg=str(key))


def stamps(out_dir, pattern):
    """name -> (inode, mtime) of the files under ``out_dir`` (runs/, traces/) matching."""
    return {p.name: (p.stat().st_ino, p.stat().st_mtime_ns)
            for p in pathlib.Path(out_dir).rglob(pattern)}


@pytest.fixture(scope="module")
def local_ray():
    """A 2-CPU local Ray instance whose workers import this checkout."""
    ray = pytest.importorskip("ray", reason="ray is not installed (optional extra: "
                              "pip install 'jaxslam[ray]')")
    path = os.pathsep.join([str(REPO)] + [p for p in [os.environ.get("PYTHONPATH")] if p])
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False,
             runtime_env={"env_vars": {"PYTHONPATH": path}})
    yield ray
    ray.shutdown()


@needs_ray
@pytest.mark.slow
def test_ray_matches_local_and_resumes_across_backends(local_ray, tmp_path):
    config = studies.load_study_config(None, TINY)
    studies.run_study(config, tmp_path / "local", progress=False)

    result = ray_backend.run_study_ray(config, tmp_path / "ray", num_workers=2, progress=False)
    assert sorted(p.name for p in (tmp_path / "ray").iterdir()) == sorted(
        p.name for p in (tmp_path / "local").iterdir())
    assert_same_results(tmp_path / "ray", tmp_path / "local")
    assert result.filter_seconds > 0 and result.compile_seconds > 0
    assert local_ray.is_initialized()  # a Ray the caller started is left running

    # Ray finishes a study the local backend started (and the other way round), redoing
    # nothing already on disk.
    mixed = tmp_path / "mixed"
    shutil.copytree(tmp_path / "local", mixed)
    (mixed / "runs/chunk-000002-000004.parquet").unlink()
    (mixed / "traces/traces-000002-000004.npz").unlink()
    kept = stamps(mixed, "*000000-000002*")
    assert len(kept) == 2  # the chunk and its traces
    ray_backend.run_study_ray(config, mixed, num_workers=2, progress=False)
    assert stamps(mixed, "*000000-000002*") == kept
    assert_same_results(mixed, tmp_path / "local")
    before = stamps(tmp_path / "ray", "chunk-*")
    assert len(before) == 2
    again = studies.run_study(config, tmp_path / "ray", progress=False)
    assert again.filter_seconds == 0.0 and stamps(tmp_path / "ray", "chunk-*") == before

    # A complete folder: no actor is started, nothing is written.
    again = ray_backend.run_study_ray(config, mixed, num_workers=2, progress=False)
    assert again.compile_seconds == again.filter_seconds == 0.0
    assert again.table.equals(studies.load_results(mixed))


@needs_ray
@pytest.mark.slow
def test_ray_refuses_a_different_study_and_moves_a_damaged_chunk_aside(local_ray, tmp_path):
    """As the local backend: another study's folder is refused; a damaged chunk is reported
    by name, kept in damaged/ and recomputed, to the local backend's results."""
    config = studies.load_study_config(None, TINY)
    out = tmp_path / "out"
    out.mkdir()
    other = studies.load_study_config(None, TINY + ["seed=3"])
    (out / "study.toml").write_text(tomli_w.dumps(studies.study_config_to_dict(other)))
    with pytest.raises(studies.StudyError, match="different study config"):
        ray_backend.run_study_ray(config, out, progress=False)
    (out / "study.toml").unlink()
    garbage = b"not a parquet file"
    (out / "runs").mkdir()
    (out / "runs/chunk-000002-000004.parquet").write_bytes(garbage)
    with pytest.warns(UserWarning, match="chunk-000002-000004.parquet"):
        ray_backend.run_study_ray(config, out, progress=False)
    moved = [p for p in (out / "damaged").iterdir()
             if p.name.startswith("chunk-000002-000004.parquet")]
    assert len(moved) == 1 and moved[0].read_bytes() == garbage  # kept, not deleted
    studies.run_study(config, tmp_path / "local", progress=False)
    assert_same_results(out, tmp_path / "local")
