"""Throughput of a whole Monte Carlo study on one accelerator, in chunks that fit its memory.

The study machinery itself runs (``jaxslam.studies``: the config's simulator, then every run
through one compiled filter-and-metrics program of fixed width), without writing result
files. Each chunk of runs is one compiled call (``run_width`` = the chunk), so the chunk size
sets the device memory. Two cases:

  analytic  filter only: R runs (default 100,000) x P=100, M=64, K=16, T=200 with analytic
            range-bearing observations (no lidar), the seed paper's FastSLAM proposal and
            stable matching (as ``benchmarks/filter_step.py``'s batched case). ``--world``:
            "per_run" (default: each run draws its own forest and path inside the compiled
            simulator, about 1 ms a run on the CPU) or "shared" (every run the same world,
            for paired comparisons).
  lidar     the same filter on MJX lidar scans and trunk detection (``--lidar-runs``, 0 to
            skip), in the same kind of world. A shared world's scans are cast once and each
            run adds its own beam noise and detects; a per-run world's trunks are written into
            one MJX template model per run (``sims.forest.world_with_trunks``) and every run
            casts its own culled scans. Detection needs far more memory per run than the
            filter, so its chunk is ``--lidar-chunk``.

The chunk: ``--chunk``, or, where the device reports its memory (GPUs), the largest multiple of
the probe width whose filter program (its arguments, outputs and temporaries, measured by XLA
on a probe chunk) fills half the memory; elsewhere a fallback of 1024 runs.

Timing, after ``block_until_ready`` (the runner waits for every output): the first chunk runs
twice, once to compile (``first_chunk_s``) and once in the timed pass, so
``compile_s = first_chunk_s - time of that chunk in the timed pass`` (simulator and filter
compiles with their tracing); ``filter_compile_s`` is XLA's compile of the filter program
alone. ``run_s`` is the timed pass over all R runs (simulator and filter), split into
``simulator_s`` and ``filter_s``; runs/s and particle-steps/s (R P T / s) are given for the
whole pass and for the filter alone.

Usage:
  python benchmarks/gpu_study.py --out results/gpu_study.json            # on the accelerator
  python benchmarks/gpu_study.py --runs 8 --particles 8 --steps 10 --landmarks 16 \\
      --max-obs 8 --chunk 4 --lidar-runs 0 --out /tmp/gpu_study.json    # small, on a CPU
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import pathlib
import sys
import time

import jax

# Time this checkout's code, also when an editable install points at another checkout.
sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

PROBE_WIDTH = 32  # runs in the chunk whose compiled program is measured
MEMORY_FRACTION = 0.5  # of the device's memory a chunk's filter program may take
FALLBACK_CHUNK = 1024  # runs per chunk where the device does not report its memory
DEFAULT_LIDAR_CHUNK = 1000  # lidar detection holds megabytes per run and step


def study_config(args, num_runs: int, chunk: int, lidar: bool):
    """The ``StudyConfig`` of a case: ``num_runs`` runs in compiled calls of ``chunk`` runs."""
    from jaxslam import studies

    scenario = [f'scenario.world="{args.world}"'] + (
        ['scenario.observation_source="lidar"'] if lidar else [])
    return studies.load_study_config(None, [
        f"num_runs={num_runs}", f"chunk_size={chunk}", f"run_width={chunk}",
        f"seed={args.seed}", f"filter.num_particles={args.particles}",
        f"filter.max_landmarks={args.landmarks}", f"filter.max_obs={args.max_obs}",
        f'filter.association="{args.association}"', f'filter.proposal="{args.proposal}"',
        f"scenario.num_steps={args.steps}", *scenario])


def device_memory_bytes() -> int | None:
    """The first local device's memory limit [bytes], or None where it is not reported."""
    stats = jax.local_devices()[0].memory_stats() or {}
    limit = stats.get("bytes_limit")
    return int(limit) if limit else None


def filter_bytes_per_run(config) -> float:
    """Device bytes per run of the compiled filter program (arguments, outputs, temporaries),
    measured by XLA on a chunk of ``PROBE_WIDTH`` runs."""
    from jaxslam.studies import _ChunkRunner

    probe = dataclasses.replace(config, num_runs=PROBE_WIDTH, chunk_size=PROBE_WIDTH,
                                run_width=PROBE_WIDTH)
    runner = _ChunkRunner(probe)
    runner(0, PROBE_WIDTH)
    memory = next(iter(runner.compiled.values())).memory_analysis()
    total = (memory.argument_size_in_bytes + memory.output_size_in_bytes
             + memory.temp_size_in_bytes)
    return total / PROBE_WIDTH


def choose_chunk(args) -> tuple[int, str, float | None]:
    """(chunk, how it was chosen, measured bytes per run or None)."""
    if args.chunk:
        return min(args.chunk, args.runs), "--chunk", None
    limit = device_memory_bytes()
    if limit is None:
        return min(FALLBACK_CHUNK, args.runs), "fallback (device memory not reported)", None
    per_run = filter_bytes_per_run(study_config(args, PROBE_WIDTH, PROBE_WIDTH, lidar=False))
    fits = int(MEMORY_FRACTION * limit / per_run) // PROBE_WIDTH * PROBE_WIDTH
    return max(PROBE_WIDTH, min(fits, args.runs)), "device memory", per_run


def timed_study(config, num_runs: int, chunk: int) -> dict:
    """Compile on the first chunk, then time all ``num_runs`` runs chunk by chunk."""
    from jaxslam.studies import _ChunkRunner

    runner = _ChunkRunner(config)
    tick = time.perf_counter()
    runner(0, min(chunk, num_runs))
    first_chunk_s = time.perf_counter() - tick
    filter_compile_s = runner.compile_seconds
    simulator_before, filter_before = runner.simulator_seconds, runner.filter_seconds
    chunk_seconds = []
    for start in range(0, num_runs, chunk):
        tick = time.perf_counter()
        runner(start, min(start + chunk, num_runs))
        chunk_seconds.append(time.perf_counter() - tick)
    run_s = sum(chunk_seconds)
    filter_s = runner.filter_seconds - filter_before
    particle_steps = num_runs * config.filter.num_particles * config.scenario.num_steps
    return dict(
        runs=num_runs, chunk=chunk, chunks=len(chunk_seconds),
        particles=config.filter.num_particles, landmarks=config.filter.max_landmarks,
        max_obs=config.filter.max_obs, steps=config.scenario.num_steps,
        world=config.scenario.world, observation_source=config.scenario.observation_source,
        first_chunk_s=first_chunk_s, compile_s=max(first_chunk_s - chunk_seconds[0], 0.0),
        filter_compile_s=filter_compile_s, run_s=run_s,
        simulator_s=runner.simulator_seconds - simulator_before, filter_s=filter_s,
        runs_per_s=num_runs / run_s, particle_steps_per_s=particle_steps / run_s,
        filter_runs_per_s=num_runs / filter_s,
        filter_particle_steps_per_s=particle_steps / filter_s)


def report_line(name: str, case: dict) -> str:
    return (f"{name}: R={case['runs']} P={case['particles']} M={case['landmarks']} "
            f"K={case['max_obs']} T={case['steps']} world={case['world']} chunk={case['chunk']}"
            f" | compile {case['compile_s']:.1f} s (filter XLA {case['filter_compile_s']:.1f} s)"
            f" | run {case['run_s']:.2f} s (simulator {case['simulator_s']:.2f} s, filter "
            f"{case['filter_s']:.2f} s) | {case['runs_per_s']:,.0f} runs/s, "
            f"{case['particle_steps_per_s'] / 1e6:,.2f} M particle-steps/s (filter alone "
            f"{case['filter_particle_steps_per_s'] / 1e6:,.2f} M)")


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs", type=int, default=100_000)
    parser.add_argument("--particles", type=int, default=100)
    parser.add_argument("--landmarks", type=int, default=64, help="M, landmark slots")
    parser.add_argument("--max-obs", type=int, default=16, help="K, observations per step")
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--chunk", type=int, default=0,
                        help="runs per compiled call (default: from the device's memory)")
    parser.add_argument("--world", choices=("shared", "per_run"), default="per_run")
    parser.add_argument("--association", default="stable")
    parser.add_argument("--proposal", default="motion")
    parser.add_argument("--lidar-runs", type=int, default=10_000, help="0: skip the lidar case")
    parser.add_argument("--lidar-chunk", type=int, default=0,
                        help=f"runs per call of the lidar case (default min(chunk, "
                             f"{DEFAULT_LIDAR_CHUNK}))")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", required=True, help="JSON file of the results")
    args = parser.parse_args(argv)
    for name in ("runs", "particles", "landmarks", "max_obs", "steps"):
        if getattr(args, name) < 1:
            parser.error(f"--{name.replace('_', '-')} must be at least 1")
    if args.chunk < 0 or args.lidar_runs < 0 or args.lidar_chunk < 0:
        parser.error("--chunk, --lidar-runs and --lidar-chunk must not be negative")
    return args


def main(argv=None) -> dict:
    args = parse_args(argv)
    device = jax.local_devices()[0]
    print(f"jax {jax.__version__} backend={jax.default_backend()} device={device.device_kind}")
    chunk, chunk_source, bytes_per_run = choose_chunk(args)
    print(f"chunk {chunk} runs ({chunk_source}"
          + (f", {bytes_per_run / 2**20:.2f} MiB a run)" if bytes_per_run else ")"))
    results = dict(backend=jax.default_backend(), device=device.device_kind,
                   jax_version=jax.__version__, device_memory_bytes=device_memory_bytes(),
                   chunk_source=chunk_source, filter_bytes_per_run=bytes_per_run, cases={})
    cases = [("analytic", args.runs, chunk, False)]
    if args.lidar_runs:
        lidar_chunk = args.lidar_chunk or min(chunk, DEFAULT_LIDAR_CHUNK)
        cases.append(("lidar", args.lidar_runs, min(lidar_chunk, args.lidar_runs), True))
    out = pathlib.Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    for name, num_runs, case_chunk, lidar in cases:
        config = study_config(args, num_runs, case_chunk, lidar)
        results["cases"][name] = case = timed_study(config, num_runs, case_chunk)
        print(report_line(name, case), flush=True)
        out.write_text(json.dumps(results, indent=1) + "\n")  # a finished case is kept
    return results


if __name__ == "__main__":
    main()
