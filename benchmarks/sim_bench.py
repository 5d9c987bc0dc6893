"""Simulator benchmark: lidar scans per second, scenario build times, per-run worlds and the
cost of per-run lidar worlds.

Run: ``.venv/bin/python benchmarks/sim_bench.py [--quick | --only-per-run-lidar]``. Compile
and run times are printed apart; run times are measured after ``block_until_ready`` on a
second call.
"""
from __future__ import annotations

import argparse
import pathlib
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

# Time this checkout's code, also when an editable install points at another checkout.
sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

import sims  # noqa: E402


def timed(fn, *args):
    """(compile + first run seconds, steady run seconds, result)."""
    start = time.perf_counter()
    jax.block_until_ready(fn(*args))
    first = time.perf_counter() - start
    start = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    return first, time.perf_counter() - start, out


def bench_scans(num_poses: int):
    forest = sims.random_forest(jax.random.PRNGKey(0), 400, (120.0, 120.0))
    world = sims.world_from_forest(forest)
    poses = jnp.concatenate([jax.random.uniform(jax.random.PRNGKey(1), (num_poses, 2),
                                                minval=20.0, maxval=100.0),
                             jnp.zeros((num_poses, 1))], -1)
    print(f"scans: 720 beams, 400 trunks in 120 m x 120 m (+ ground plane), 20 m range, "
          f"{num_poses} poses per vmapped call")
    for cull in (True, False):
        fn = jax.jit(jax.vmap(lambda p: sims.scan_2d_full(world, p, 720, 20.0, cull=cull)))
        first, run, scan = timed(fn, poses)
        print(f"  cull={cull!s:5}: compile+first {first:6.2f} s, run {run:6.3f} s, "
              f"{num_poses / run:8.1f} scans/s, culling complete: {bool(scan.complete.all())}")


def bench_scenarios(num_runs: int, num_steps: int, lidar_runs: int, lidar_steps: int):
    key = jax.random.PRNGKey(2)
    path = sims.loop_path(num_steps, (30.0, 30.0), (15.9, 15.9), 0.5)
    dense = sims.loop_path(720, (30.0, 30.0), (15.9, 15.9), 0.14)
    forest = sims.random_forest(jax.random.PRNGKey(3), 80, (60.0, 60.0), keep_clear=dense[:, :2])
    build = lambda k, runs, p, **kw: sims.build_scenario(k, forest, p, runs, **kw)
    first, run, _ = timed(lambda k: build(k, num_runs, path), key)
    print(f"analytic scenario, {num_runs} runs x {num_steps} steps, 80 trees, K=16: "
          f"compile+first {first:.2f} s, run {run:.2f} s")
    world = sims.world_from_forest(forest)
    short = path[:lidar_steps + 1]
    first, run, _ = timed(lambda k: build(k, lidar_runs, short, source="lidar", world=world),
                          key)
    scans = lidar_runs * lidar_steps
    print(f"lidar scenario (1440 beams, culled, kasa), {lidar_runs} runs x "
          f"{lidar_steps} steps: compile+first {first:.2f} s, run {run:.2f} s "
          f"({scans / run:.0f} scan+detect/s); extrapolated linearly to 1000 x 200: "
          f"{run * 1000 * 200 / scans:.0f} s")


def bench_per_run_worlds(num_runs: int, eager_runs: int):
    """Per-run worlds (80 trees in 60 m x 60 m, T=200, K=16): a forest and path drawn on the
    host per run (``_draw_world``, as the shared world still is) against the worlds drawn in
    one compiled, vmapped program (``run_world_arrays``) and the whole per-run simulator
    (world + odometry + observations, ``scenario_batch``), in groups of 100 runs."""
    from jaxslam import studies
    from sims import batch

    for path in ("loop", "random"):
        config = studies.load_study_config(None, [
            "scenario.world='per_run'", f"scenario.path='{path}'", "scenario.num_trees=80",
            "scenario.size=60.0", "scenario.num_steps=200", "filter.max_obs=16",
            "run_width=100"])
        settings, seed = config.scenario, config.seed
        jax.block_until_ready(batch._draw_world(settings, batch._run_world_key(seed, eager_runs)))
        start = time.perf_counter()  # after a first draw: its compiles are not counted
        for run in range(eager_runs):
            jax.block_until_ready(batch._draw_world(settings, batch._run_world_key(seed, run)))
        eager = (time.perf_counter() - start) / eager_runs
        ids = np.arange(num_runs)
        draw = lambda: batch.run_world_arrays(settings, seed, ids, width=100)  # noqa: E731
        first, run, _ = timed(draw)
        simulate = lambda: batch.scenario_batch(config, ids)  # noqa: E731
        sim_first, sim_run, _ = timed(simulate)
        print(f"per-run worlds, {path} path: host draw {1e3 * eager:7.1f} ms/run | in-program "
              f"draw {num_runs} runs: compile+first {first:.2f} s, run {run:.3f} s "
              f"({1e3 * run / num_runs:.2f} ms/run) | whole simulator: compile+first "
              f"{sim_first:.2f} s, run {sim_run:.3f} s ({1e3 * sim_run / num_runs:.2f} ms/run)")


def bench_per_run_lidar(num_runs: int, num_steps: int):
    """Simulator cost per run (``scenario_batch``: world, odometry, observations; all
    ``num_runs`` runs in one call of width ``num_runs``) for per-run lidar worlds (each run's
    trunks written into one template MJX world, T culled 1440-beam scans a run, then beam
    noise and Kasa detection) against shared-world lidar (T scans cast once for the study,
    each run adds noise and detects) and per-run analytic observations. 80 trees in 60 m x
    60 m, loop path, K=16. "first" = trace + compile + first call (for the shared world also
    its MJX model and its T scans, cast once per study); "run" = a second call."""
    from jaxslam import studies
    from sims import batch

    cases = {"per-run lidar": ("per_run", "lidar"), "shared lidar": ("shared", "lidar"),
             "per-run analytic": ("per_run", "analytic")}
    for name, (world, source) in cases.items():
        config = studies.load_study_config(None, [
            f"scenario.world='{world}'", f"scenario.observation_source='{source}'",
            "scenario.num_trees=80", "scenario.size=60.0", f"scenario.num_steps={num_steps}",
            "filter.max_obs=16", f"num_runs={num_runs}", f"run_width={num_runs}"])
        batch.study_world.cache_clear()  # the shared world's model and scans count as "first"
        batch._simulator.cache_clear()
        ids = np.arange(num_runs)
        first, run, _ = timed(lambda: batch.scenario_batch(config, ids))  # noqa: B023
        print(f"{name:17}: {num_runs} runs x {num_steps} steps: first (compile) {first:6.2f} s, "
              f"run {run:6.3f} s = {1e3 * run / num_runs:8.2f} ms/run "
              f"({num_runs * num_steps / run:8.0f} run-steps/s)")


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--quick", action="store_true", help="smaller sizes")
    parser.add_argument("--only-per-run-lidar", action="store_true",
                        help="only the per-run lidar cost (20 runs x 100 steps)")
    args = parser.parse_args()
    if args.only_per_run_lidar:
        bench_per_run_lidar(20, 100)
        return
    print(f"jax {jax.__version__}, devices {jax.devices()}")
    bench_scans(64 if args.quick else 256)
    if args.quick:
        bench_scenarios(100, 200, 1, 20)
        bench_per_run_worlds(200, 3)
        bench_per_run_lidar(20, 100)
    else:
        bench_scenarios(1000, 200, 4, 50)
        bench_per_run_worlds(1000, 10)
        bench_per_run_lidar(20, 100)


if __name__ == "__main__":
    main()
