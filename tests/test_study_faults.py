"""Fault injection: a study crashed at many points and damaged between restarts ends with the
results of an uninterrupted run, bit for bit, every (run, condition) exactly once.

In-process (default tier): every file a study writes goes through ``study_store.atomic_write``
(temporary file, then rename), so the states a crash can leave are exactly "stopped before
write k" and "stopped during write k, its temporary file half written". The test crashes the
study at a random write (seeded: the same sequence every time) in each invocation, damages the
folder between some restarts (a flipped bit in a chunk, a deleted or truncated traces file, a
garbled manifest), and resumes until one invocation finishes. The same compiled program serves
every invocation (programs are cached per process), so the test costs one compile.

The slow tier kills real study processes with SIGKILL at random moments (``test_studies``
holds the single-kill SIGINT/SIGKILL tests; here 10 kills of one study).
"""
import json
import pathlib
import random
import signal
import subprocess
import time
import warnings

import numpy as np
import pytest

from jaxslam import study_store, studies
from test_studies import (REPO, assert_runs_once, assert_same_results, child_command,
                          child_env, run_child, tiny_config)

NUM_RUNS = 5


class _Crash(BaseException):
    """Stands for the process dying (BaseException: no ``except Exception`` catches it)."""


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """The uninterrupted study (chunk size 5: one chunk)."""
    out = tmp_path_factory.mktemp("faults") / "reference"
    config = tiny_config(f"num_runs={NUM_RUNS}", "chunk_size=5")
    studies.run_study(config, out, progress=False)
    return out


def _crashing_writes(monkeypatch, crash_at: int, half_written: bool):
    """Make the ``crash_at``-th atomic write of this invocation die (after writing half of
    its temporary file when ``half_written``, else before writing anything)."""
    real = study_store.atomic_write
    calls = {"count": 0}

    def atomic_write(path, write):
        calls["count"] += 1
        if calls["count"] == crash_at:
            if half_written:
                tmp = pathlib.Path(path).with_name(f".tmp-{pathlib.Path(path).name}")
                pathlib.Path(path).parent.mkdir(parents=True, exist_ok=True)
                write(tmp)
                tmp.write_bytes(tmp.read_bytes()[: tmp.stat().st_size // 2])
            raise _Crash(f"crash at write {crash_at} ({pathlib.Path(path).name})")
        real(path, write)

    monkeypatch.setattr(study_store, "atomic_write", atomic_write)


def _damage(out: pathlib.Path, rng: random.Random) -> str:
    """Damage one finished file at random; returns what was done."""
    chunks = sorted((out / "runs").glob("chunk-*.parquet"))
    traces = sorted((out / "traces").glob("traces-*.npz"))
    choice = rng.choice(["flip", "delete_traces", "truncate_traces", "manifest"])
    if choice == "flip" and chunks:
        path = rng.choice(chunks)
        data = bytearray(path.read_bytes())
        data[rng.randrange(len(data))] ^= 1 << rng.randrange(8)
        path.write_bytes(bytes(data))
    elif choice == "delete_traces" and traces:
        rng.choice(traces).unlink()
    elif choice == "truncate_traces" and traces:
        path = rng.choice(traces)
        path.write_bytes(path.read_bytes()[: rng.randrange(1, path.stat().st_size)])
    elif choice == "manifest" and (out / "manifest.json").exists():
        (out / "manifest.json").write_text('{"files": {"runs/x": 1')
    else:
        return "nothing"
    return choice


def test_crashes_and_damage_end_in_the_uninterrupted_results(reference, tmp_path, monkeypatch):
    config = tiny_config(f"num_runs={NUM_RUNS}", "chunk_size=1")
    out = tmp_path / "out"
    rng = random.Random(20261202)
    crashes, damages = 0, []
    for invocation in range(200):  # ends when one invocation finishes
        with monkeypatch.context() as patch:
            # A finishing invocation needs about 6 writes for its last chunk (provenance,
            # traces, chunk, manifest, summary...): crashes land anywhere in 1..10.
            _crashing_writes(patch, crash_at=rng.randint(1, 10), half_written=rng.random() < 0.5)
            try:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")  # damaged files are reported: expected
                    studies.run_study(config, out, progress=False)
                if crashes >= 10:
                    break
                damages.append(_damage(out, rng))  # finished too soon: damage, go on
                continue
            except _Crash:
                crashes += 1
        if invocation % 3 == 2 and invocation < 24:  # then let it finish
            damages.append(_damage(out, rng))
    else:
        pytest.fail("the study never finished in 200 invocations")
    assert crashes >= 10, crashes
    assert {"flip", "delete_traces", "truncate_traces", "manifest"} & set(damages), damages
    assert_runs_once(out, config)
    assert_same_results(out, reference)
    # The finished folder verifies: a clean resume finds nothing to move aside or redo.
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        again = studies.run_study(config, out, progress=False)
    assert again.filter_seconds == 0.0
    manifest = json.loads((out / "manifest.json").read_text())["files"]
    for name, digest in manifest.items():
        assert study_store.sha256(out / name) == digest, name


def test_crash_between_chunk_and_manifest_recomputes_that_chunk(reference, tmp_path,
                                                                monkeypatch):
    """A chunk written but not yet recorded (the narrowest crash window) does not count as
    done: it is moved aside and computed again, and the results are unchanged."""
    config = tiny_config(f"num_runs={NUM_RUNS}", "chunk_size=5")
    out = tmp_path / "out"

    def crash(out_dir, paths):
        raise _Crash("before the manifest")

    with monkeypatch.context() as patch:
        patch.setattr(study_store, "record_files", crash)
        with pytest.raises(_Crash):
            studies.run_study(config, out, progress=False)
    assert (out / "runs/chunk-000000-000005.parquet").exists()
    with pytest.warns(UserWarning, match="not in the manifest"):
        studies.run_study(config, out, progress=False)
    assert_same_results(out, reference)


@pytest.mark.slow
def test_ten_sigkills_end_in_the_uninterrupted_results(reference, tmp_path, tmp_path_factory):
    """10 real SIGKILLs at random moments of a study process (seeded), then a clean finish."""
    config = tiny_config(f"num_runs={NUM_RUNS}", "chunk_size=1")
    out, cache = tmp_path / "out", tmp_path_factory.mktemp("jax-cache-kills")
    run_child(tmp_path, tiny_config("num_runs=1", "chunk_size=1"), tmp_path / "warm", cache)
    rng = np.random.default_rng(7)
    kills = 0
    while kills < 10:
        child = subprocess.Popen(child_command(tmp_path, config, out, cache, chunk_delay=0.5),
                                 cwd=REPO, env=child_env(), stdout=subprocess.PIPE,
                                 stderr=subprocess.PIPE, text=True)
        time.sleep(float(rng.uniform(2.0, 12.0)))
        if child.poll() is None:
            child.send_signal(signal.SIGKILL)
            kills += 1
        child.communicate(timeout=60)
        if (out / "summary.md").exists() and child.returncode == 0:
            (out / "summary.md").unlink()  # finished too early: start over to keep killing
            for path in (out / "runs").glob("*"):
                path.unlink()
    run_child(tmp_path, config, out, cache)
    assert_runs_once(out, config)
    assert_same_results(out, reference)
