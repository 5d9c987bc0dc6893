"""Ray backend for studies on many hosts (optional extra: ``pip install 'jaxslam[ray]'``).

The driver checks the output folder exactly as the local runner does (``studies.open_study``:
same study config, damaged chunks reported, foreign files warned about) and hands the chunks
still missing to W long-lived actors, one per worker. Each actor builds one
``studies._ChunkRunner`` (so it compiles the simulator and the filter once and keeps them) and
writes its own chunk files with ``studies.write_chunk`` into the shared output folder (the
driver, which holds the folder's lock, records each in the manifest): the same
names and the same atomic writes as the local backend, so a study started on one backend
resumes on the other. Run i depends only on ``fold_in(PRNGKey(seed), i)``, never on which
actor ran it, and each actor takes the driver's ``study_store.NUMERIC_JAX_SETTINGS``, so on
hosts of the driver's CPU type the results equal the local backend's bit for bit.

On several hosts ``out_dir`` must be a folder every host sees under the same path (NFS, a
mounted bucket...); each actor also shards its chunk over its host's local devices.
"""
from __future__ import annotations

import pathlib
import time
from typing import NamedTuple

from jaxslam.study_store import NUMERIC_JAX_SETTINGS, numeric_jax_settings

RAY_MISSING = ("the Ray backend needs the optional 'ray' extra, which is not installed: "
               "pip install 'jaxslam[ray]'")


def import_ray():
    """Import ray, or raise ImportError naming the extra to install."""
    try:
        import ray
    except ImportError as error:
        raise ImportError(RAY_MISSING) from error
    return ray


class WorkerTimes(NamedTuple):
    """Seconds one actor spent this study: compiling, filtering and simulating."""

    compile_seconds: float
    filter_seconds: float
    simulator_seconds: float


class StudyWorker:
    """One actor's state: a chunk runner built (and compiled) once, reused for every chunk.

    ``jax_settings`` holds the driver's values of ``NUMERIC_JAX_SETTINGS`` (precision and
    XLA's optimisation, which changes rounding), so an actor compiles the same programs as
    the local backend would (a fresh worker process starts with JAX's defaults).
    Plain Python: ``run_study_ray`` wraps it with ``ray.remote``; in-process it sets those
    settings for the whole process.
    """

    def __init__(self, config, out_dir: str, jax_settings: dict):
        import jax

        for name in NUMERIC_JAX_SETTINGS:
            jax.config.update(name, bool(jax_settings[name]))
        from jaxslam import studies

        self.config = config
        self.out_dir = pathlib.Path(out_dir)
        self.runner = studies._ChunkRunner(config)

    def run_chunk(self, start: int, stop: int) -> tuple[int, int, list[str]]:
        """Simulate, filter and score runs [start, stop) and write their chunk files.
        Returns (start, stop, the paths written) for the driver to record in the manifest."""
        from jaxslam import studies

        paths = studies.write_chunk(self.out_dir, self.config, start, stop,
                                    self.runner(start, stop))
        return start, stop, [str(path) for path in paths]

    def times(self) -> WorkerTimes:
        runner = self.runner
        return WorkerTimes(runner.compile_seconds, runner.filter_seconds,
                           runner.simulator_seconds)


def _schedule(ray, workers, chunks, on_done) -> None:
    """Keep every actor busy with one chunk at a time until none is left.

    Dynamic (not round-robin) so a slow host takes fewer chunks; a failed chunk raises here
    (its files are not written, so a rerun computes it again).
    """
    queue = list(chunks)
    in_flight = {}
    for worker in workers:
        if queue:
            in_flight[worker.run_chunk.remote(*queue.pop(0))] = worker
    while in_flight:
        (ref,), _ = ray.wait(list(in_flight), num_returns=1)
        worker = in_flight.pop(ref)
        on_done(*ray.get(ref))
        if queue:
            in_flight[worker.run_chunk.remote(*queue.pop(0))] = worker


def run_study_ray(config, out_dir, num_workers: int = 2, address: str | None = None, *,
                  progress: bool = True, worker_options: dict | None = None):
    """Run (or resume) a study on Ray actors; same folder layout and results as ``run_study``.

    Args:
      config: the ``StudyConfig``.
      out_dir: the results folder, visible under this path from every Ray host.
      num_workers: W long-lived actors (at most one per pending chunk is started).
      address: a Ray cluster to join (``"auto"``, ``"ray://host:10001"``...). Ignored when Ray
        is already initialised; with neither, a local Ray instance is started and shut down.
      progress: show a progress bar over chunks.
      worker_options: ``ray.remote`` options of each actor; default ``{"num_cpus": 1}``
        (e.g. ``{"num_gpus": 1}`` for one accelerator per actor).

    Returns a ``studies.StudyResult``: compile_seconds is the slowest actor's compile (they
    compile in parallel); filter_seconds and simulator_seconds are summed over actors.
    """
    if not isinstance(num_workers, int) or num_workers < 1:
        raise ValueError(f"num_workers={num_workers!r}; expected a positive integer")
    ray = import_ray()
    from jaxslam import studies
    from jaxslam.study_store import study_lock

    out_dir = pathlib.Path(out_dir).resolve()
    with study_lock(out_dir):
        pending = studies.open_study(config, out_dir)
        times = _run_pending(ray, config, out_dir, pending, num_workers, address, progress,
                             worker_options)
        table = studies.load_results(out_dir)
        studies.summarize_study(out_dir, table)
    return studies.StudyResult(out_dir, table,
                               max((t.compile_seconds for t in times), default=0.0),
                               sum(t.filter_seconds for t in times),
                               sum(t.simulator_seconds for t in times))


def _run_pending(ray, config, out_dir, pending, num_workers, address, progress,
                 worker_options) -> list[WorkerTimes]:
    """Compute the pending chunks on actors; the driver records each in the manifest."""
    from tqdm.auto import tqdm

    from jaxslam.study_store import record_files

    started_ray = not ray.is_initialized()
    times = []
    try:
        if pending:
            if started_ray:
                ray.init(address=address)
            actor = ray.remote(**(worker_options or {"num_cpus": 1}))(StudyWorker)
            workers = [actor.remote(config, str(out_dir), numeric_jax_settings())
                       for _ in range(min(num_workers, len(pending)))]
            bar = tqdm(total=len(pending), desc=f"study {config.name} (ray)", unit="chunk",
                       disable=not progress)
            tick = time.perf_counter()

            def chunk_done(start, stop, paths):
                record_files(out_dir, paths)
                bar.update(1)
                bar.set_postfix(last=f"{start}-{stop}", s=f"{time.perf_counter() - tick:.1f}")

            _schedule(ray, workers, pending, chunk_done)
            bar.close()
            times = ray.get([worker.times.remote() for worker in workers])
            for worker in workers:
                ray.kill(worker)
    finally:
        if started_ray and ray.is_initialized():
            ray.shutdown()
    return times
