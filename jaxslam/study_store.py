"""A study's results folder: layout, integrity manifest, lock, resume rules.

Layout of ``out_dir``::

  study.toml        the resolved study config; a resumed study must match it (``num_runs``
                    may grow and ``chunk_size`` may change: results do not depend on them)
  provenance.toml   package version, git revision, jax version, backend, devices, the JAX
                    settings that change the numbers (``NUMERIC_JAX_SETTINGS``), start time;
                    resuming finished chunks under another jax version, backend or setting
                    warns (the new chunks may differ in their last bits)
  manifest.json     SHA-256 of every finished chunk, traces file and example_run.npz
  study.lock        held (``flock``) by the one process computing the study
  runs/chunk-AAAAAA-BBBBBB.parquet    one row per (run, condition) of runs [A, B); the
                    folder holds only these, so ``pandas.read_parquet(out_dir / "runs")`` and
                    ``pyarrow.dataset.dataset(out_dir / "runs")`` read the whole study (but
                    they keep only the first file's columns when chunks written by an
                    earlier version lack a newer column: ``studies.load_results`` keeps
                    every column, null where a chunk lacks it)
  traces/traces-AAAAAA-BBBBBB.npz     per-step position error (rows, T), run_id, condition
  damaged/          chunk files that failed verification, moved aside (never deleted)
  example_run.npz, summary.md, summary.json, *.png  written by the runner and the plots
  *.tum, run-I-condition-C/           written by ``jaxslam export``

Integrity: a chunk counts as done only when its Parquet file and its traces file are both
listed in the manifest with their current SHA-256. Anything else (a changed or truncated
file, one missing its partner, one written by a process killed before it recorded it, or every
file when the manifest itself is unreadable) is moved to ``damaged/`` with a warning naming
it, and its runs are computed again. Results depend only on the run ids and the study config,
so the recomputed files equal the lost ones.

Every write is atomic (temporary file + rename). The manifest is written by the process that
holds the lock (the local runner or the Ray driver), after the chunk's files are complete.
"""
from __future__ import annotations

import contextlib
import datetime
import fcntl
import hashlib
import json
import os
import pathlib
import re
import socket
import subprocess
import tomllib
import warnings

import jax
import numpy as np

RUNS_DIR = "runs"
TRACES_DIR = "traces"
DAMAGED_DIR = "damaged"
MANIFEST = "manifest.json"
LOCK = "study.lock"
KNOWN_FILES = {"study.toml", "provenance.toml", "summary.md", "summary.json",
               "example_run.npz", MANIFEST, LOCK, "metrics.json"}
KNOWN_DIRS = {RUNS_DIR, TRACES_DIR, DAMAGED_DIR}
# JAX settings a user (or this library's tests) may change that alter a program's numbers:
# precision, and XLA's optimisation (other rounding). Recorded in provenance.toml; a Ray actor,
# a fresh process that starts with JAX's defaults, takes the driver's. Others (the PRNG
# implementation, matmul precision, XLA_FLAGS) are not recorded or passed on: keep them at
# their defaults, or set them alike on every host and session.
NUMERIC_JAX_SETTINGS = ("jax_enable_x64", "jax_disable_most_optimizations")
# provenance.toml keys whose change between two sessions of one study changes its numbers.
NUMERIC_PROVENANCE = ("jax_version", "backend") + NUMERIC_JAX_SETTINGS
# May change between invocations of one study: the results do not depend on them.
RESUMABLE_KEYS = ("num_runs", "chunk_size")
_EXPORT_DIR = re.compile(r"^run-\d+-condition-\d+$")  # ``jaxslam export --run I --condition C``
_CHUNK_PATTERN = re.compile(r"^chunk-(\d{6})-(\d{6})\.parquet$")
_MISSING = object()


class StudyError(RuntimeError):
    """A study cannot run or resume safely (foreign study in the folder, folder in use...)."""


def chunk_path(out_dir, start: int, stop: int) -> pathlib.Path:
    return pathlib.Path(out_dir) / RUNS_DIR / f"chunk-{start:06d}-{stop:06d}.parquet"


def traces_path(out_dir, start: int, stop: int) -> pathlib.Path:
    return pathlib.Path(out_dir) / TRACES_DIR / f"traces-{start:06d}-{stop:06d}.npz"


def atomic_write(path: pathlib.Path, write) -> None:
    """``write(tmp)`` then rename onto ``path``: readers see the old file or the new one."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".tmp-{path.name}")
    write(tmp)
    os.replace(tmp, path)


def sha256(path: pathlib.Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


# --------------------------------------------------------------------------------------------
# Lock


@contextlib.contextmanager
def study_lock(out_dir):
    """Hold ``out_dir/study.lock`` (an exclusive ``flock``) for the ``with`` block.

    A second process on the same folder gets a StudyError naming the holder instead of
    computing the same chunks. The operating system releases the lock when its holder exits,
    however it exits (SIGKILL included), so a crash never leaves the folder locked.
    """
    out_dir = pathlib.Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    handle = open(out_dir / LOCK, "a+")
    try:
        fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        handle.seek(0)
        holder = handle.read().strip() or "unknown process"
        handle.close()
        raise StudyError(f"{out_dir} is in use by another study process ({holder}); wait for "
                         "it to finish (it resumes and computes every chunk once), or use "
                         "another output folder") from None
    try:
        handle.seek(0)
        handle.truncate()
        handle.write(f"pid {os.getpid()} on {socket.gethostname()}\n")
        handle.flush()
        yield
    finally:
        fcntl.flock(handle, fcntl.LOCK_UN)
        handle.close()


# --------------------------------------------------------------------------------------------
# Manifest


def read_manifest(out_dir) -> dict[str, str]:
    """{relative path: sha256}; {} (and a warning) when the manifest is missing or unreadable."""
    path = pathlib.Path(out_dir) / MANIFEST
    if not path.exists():
        return {}
    try:
        files = json.loads(path.read_text())["files"]
        if not all(isinstance(k, str) and isinstance(v, str) for k, v in files.items()):
            raise ValueError("entries are not path: checksum strings")
        return files
    except (ValueError, KeyError, TypeError, AttributeError, UnicodeDecodeError) as error:
        warnings.warn(f"{path} is unreadable ({error}): no finished chunk can be verified, so "
                      "every chunk is moved to damaged/ and computed again")
        return {}


def record_files(out_dir, paths) -> None:
    """Add the SHA-256 of ``paths`` (files under ``out_dir``) to the manifest."""
    out_dir = pathlib.Path(out_dir)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # an unreadable manifest was reported at open
        files = read_manifest(out_dir)
    for path in paths:
        files[pathlib.Path(path).relative_to(out_dir).as_posix()] = sha256(pathlib.Path(path))
    text = json.dumps({"files": dict(sorted(files.items()))}, indent=1) + "\n"
    atomic_write(out_dir / MANIFEST, lambda p: p.write_text(text))


def _verified(out_dir: pathlib.Path, path: pathlib.Path, manifest: dict) -> str | None:
    """None when ``path`` matches its manifest entry, else what is wrong with it."""
    name = path.relative_to(out_dir).as_posix()
    if not path.exists():
        return f"{name} is missing"
    if name not in manifest:
        return f"{name} is not in the manifest (written by a process stopped before it recorded it)"
    if sha256(path) != manifest[name]:
        return f"{name} changed since it was written (checksum mismatch)"
    return None


def _move_aside(out_dir: pathlib.Path, paths) -> None:
    damaged = out_dir / DAMAGED_DIR
    stamp = datetime.datetime.now(datetime.timezone.utc).strftime("%Y%m%dT%H%M%S%f")
    for path in paths:
        if path.exists():
            damaged.mkdir(exist_ok=True)
            os.replace(path, damaged / f"{path.name}.{stamp}")


def finished_chunks(out_dir, num_runs: int) -> list[tuple[int, int]]:
    """Run ranges [start, stop) whose chunk and traces files verify against the manifest.

    Every chunk file that does not verify is moved to ``damaged/`` (with its traces file),
    with a warning naming the file and the reason; so is a traces file without a chunk, and
    example_run.npz when it does not verify (the chunk holding run 0 is then redone too).
    """
    out_dir = pathlib.Path(out_dir)
    manifest = read_manifest(out_dir)
    done, problems = [], []
    for path in sorted((out_dir / RUNS_DIR).glob("chunk-*.parquet")):
        match = _CHUNK_PATTERN.match(path.name)
        if match is None:
            continue  # reported as a foreign file
        start, stop = int(match[1]), int(match[2])
        traces = traces_path(out_dir, start, stop)
        reasons = [r for r in (_verified(out_dir, path, manifest),
                               _verified(out_dir, traces, manifest)) if r]
        if start == 0 and not reasons:
            example = _verified(out_dir, out_dir / "example_run.npz", manifest)
            reasons += [f"{example} (it is written with runs {start}..{stop - 1})"] if example else []
        if not reasons and stop > num_runs:
            raise StudyError(f"{path} holds runs up to {stop - 1} but this config asks for "
                             f"num_runs={num_runs}: num_runs can grow on resume, not shrink; "
                             f"ask for at least {stop} runs or use another output folder")
        if reasons:
            problems.append(f"{path.relative_to(out_dir)} and its traces ({'; '.join(reasons)})")
            _move_aside(out_dir, [path, traces])
        else:
            done.append((start, stop))
    done_names = {traces_path(out_dir, a, b).name for a, b in done}
    for orphan in sorted((out_dir / TRACES_DIR).glob("traces-*.npz")):
        if orphan.name not in done_names:
            problems.append(f"{orphan.relative_to(out_dir)} has no verified chunk")
            _move_aside(out_dir, [orphan])
    if problems:
        warnings.warn(f"{out_dir}: moved to {DAMAGED_DIR}/ and computing again: "
                      + "; ".join(problems))
    return sorted(done)


def pending_chunks(done: list[tuple[int, int]], num_runs: int, chunk_size: int):
    """The run ranges of [0, num_runs) not in ``done``, cut at multiples of chunk_size."""
    covered = np.zeros(num_runs, bool)
    for start, stop in done:
        covered[start:stop] = True
    pending, start = [], 0
    while start < num_runs:
        if covered[start]:
            start += 1
            continue
        boundary = min((start // chunk_size + 1) * chunk_size, num_runs)
        stop = start + 1
        while stop < boundary and not covered[stop]:
            stop += 1
        pending.append((start, stop))
        start = stop
    return pending


# --------------------------------------------------------------------------------------------
# study.toml, provenance, foreign files


def _flatten(data: dict, prefix: str = "") -> dict:
    out = {}
    for key, value in data.items():
        if isinstance(value, dict):
            out.update(_flatten(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value
    return out


def config_differences(old: dict, new: dict, ignore=()) -> list[str]:
    """"key: folder X, this config Y" for every key whose value differs (``ignore`` aside)."""
    old, new = _flatten(old), _flatten(new)
    show = lambda v: "(absent)" if v is _MISSING else repr(v)  # noqa: E731
    return [f"{key}: folder {show(old.get(key, _MISSING))}, this config "
            f"{show(new.get(key, _MISSING))}"
            for key in sorted(set(old) | set(new))
            if key not in ignore and old.get(key, _MISSING) != new.get(key, _MISSING)]


def prepare_out_dir(resolved: dict, out_dir) -> None:
    """Create ``out_dir`` for a validated config dict, or check the study already there.

    A folder holding a different study is refused (the error names the differing keys and
    how to start over); nothing is written before that check.
    """
    import tomli_w

    out_dir = pathlib.Path(out_dir)
    study_file = out_dir / "study.toml"
    rewrite = True
    if study_file.exists():
        try:
            old = tomllib.loads(study_file.read_text())
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as error:
            raise StudyError(_refusal(out_dir, [f"(its study.toml is not readable TOML: "
                                                f"{error})"])) from None
        differences = config_differences(old, resolved, ignore=RESUMABLE_KEYS)
        if differences:
            raise StudyError(_refusal(out_dir, differences))
        rewrite = any(old.get(key) != resolved.get(key) for key in RESUMABLE_KEYS)
    out_dir.mkdir(parents=True, exist_ok=True)
    if rewrite:  # a new study, or one that grew: the file states the runs it holds
        text = tomli_w.dumps(resolved)
        atomic_write(study_file, lambda p: p.write_text(text))
    for folder in (out_dir, out_dir / RUNS_DIR, out_dir / TRACES_DIR):
        for stale in folder.glob(".tmp-*"):
            stale.unlink()  # a half-written file of an interrupted run (we hold the lock)
    record = provenance()
    _warn_if_numerics_changed(out_dir, record)
    atomic_write(out_dir / "provenance.toml", lambda p: p.write_text(tomli_w.dumps(record)))


def _refusal(out_dir: pathlib.Path, differences: list[str]) -> str:
    study_file = out_dir / "study.toml"
    chunks = sorted((out_dir / RUNS_DIR).glob("chunk-*.parquet"))
    if chunks:
        start_over = (f"it holds {len(chunks)} finished chunk(s) of that study: resume it with "
                      f"the config in {study_file}, or choose another output folder (to start "
                      f"over here, delete {out_dir} first)")
    else:
        start_over = (f"it holds no finished chunk yet: delete {study_file} to start this "
                      "study over here, or choose another output folder")
    return (f"{study_file} holds a different study config; resume only the same study "
            f"({' and '.join(RESUMABLE_KEYS)} may change). Keys that differ:\n  "
            + "\n  ".join(differences) + f"\n{start_over}")


def _git_revision() -> str:
    try:
        root = pathlib.Path(__file__).resolve().parent.parent
        return subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"], check=True,
                              capture_output=True, text=True, timeout=5).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def numeric_jax_settings() -> dict:
    """This process's values of ``NUMERIC_JAX_SETTINGS``: name -> bool."""
    return {name: bool(jax.config.read(name)) for name in NUMERIC_JAX_SETTINGS}


def provenance() -> dict:
    from jaxslam import __version__

    return dict(jaxslam_version=__version__, git_revision=_git_revision(),
                jax_version=jax.__version__, backend=jax.default_backend(),
                devices=[str(d) for d in jax.devices()], **numeric_jax_settings(),
                started=datetime.datetime.now(datetime.timezone.utc).isoformat())


def numeric_changes(old: dict, new: dict) -> list[str]:
    """"key: X then, Y now" for each ``NUMERIC_PROVENANCE`` key recorded in both that differs
    (a folder written before a key was recorded is not compared on it)."""
    return [f"{key}: {old[key]!r} then, {new[key]!r} now" for key in NUMERIC_PROVENANCE
            if key in old and key in new and old[key] != new[key]]


def _warn_if_numerics_changed(out_dir: pathlib.Path, new: dict) -> None:
    """Warn when finished chunks were computed under another jax version, backend or
    numeric setting than this session's (the chunks computed now may then differ in their
    last bits from an uninterrupted study's). Silent for a new folder or an unreadable
    provenance.toml (it is rewritten)."""
    if not any((out_dir / RUNS_DIR).glob("chunk-*.parquet")):
        return
    try:
        old = tomllib.loads((out_dir / "provenance.toml").read_text())
    except (OSError, tomllib.TOMLDecodeError, UnicodeDecodeError):
        return
    changes = numeric_changes(old, new)
    if changes:
        warnings.warn(f"{out_dir}: the study's last session ran under other JAX numerics "
                      f"({'; '.join(changes)}); the chunks computed now may differ in their "
                      f"last bits from an uninterrupted study's (README, What is guaranteed)",
                      UserWarning, stacklevel=3)


def foreign_files(out_dir) -> list[str]:
    """Files in the output folder that a study did not write (reported, never touched)."""
    out_dir = pathlib.Path(out_dir)
    out = [path.name for path in sorted(out_dir.iterdir())
           if not (path.name in KNOWN_FILES or path.name.endswith((".png", ".tum"))
                   or (path.is_dir() and (path.name in KNOWN_DIRS
                                          or _EXPORT_DIR.match(path.name))))]
    for folder, pattern in ((RUNS_DIR, _CHUNK_PATTERN),
                            (TRACES_DIR, re.compile(r"^traces-\d{6}-\d{6}\.npz$"))):
        if (out_dir / folder).is_dir():
            out += [f"{folder}/{p.name}" for p in sorted((out_dir / folder).iterdir())
                    if not (pattern.match(p.name) or p.name.startswith(".tmp-"))]
    return out


def default_out_dir(name: str, resolved: dict, reference: dict | None = None,
                    root="results") -> pathlib.Path:
    """``root/<name>`` for a config equal to ``reference`` (the one its file or the demo
    defines), else ``root/<name>-<8 hex digits of its digest>``: a trial run with ``--set``
    overrides never blocks the full study's folder. ``RESUMABLE_KEYS`` do not count, so
    ``--set num_runs=...`` grows the same study."""
    if reference is not None and not config_differences(reference, resolved,
                                                        ignore=RESUMABLE_KEYS):
        return pathlib.Path(root) / name
    identity = {k: v for k, v in _flatten(resolved).items() if k not in RESUMABLE_KEYS}
    digest = hashlib.sha256(json.dumps(identity, sort_keys=True, default=repr).encode())
    return pathlib.Path(root) / f"{name}-{digest.hexdigest()[:8]}"
