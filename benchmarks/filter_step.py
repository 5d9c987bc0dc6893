"""Benchmark of the FastSLAM step and of batched runs (issues 2, 3 and 6).

Prints compile time and steady-state run time apart (after ``block_until_ready``), with the
settings. Cases:
  step   one ``step`` at (P, M, K) with every landmark slot active and K observations, all
         within range: association (stable matching by default), updates, births, deaths,
         resampling included. Reports (particle, observation, landmark) evaluations per second.
  batch  R runs x P x M x K x T on the default simulated forest (analytic observations), vmapped
         in chunks of runs; reports particle-steps per second. The simulator part is timed apart.

Usage:
  python benchmarks/filter_step.py                 # step at (100,64,16) and (1000,128,16)
  python benchmarks/filter_step.py --batch-runs 1000 --chunk 250
  python benchmarks/filter_step.py --association greedy --proposal mixture
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


def _full_map_state(config, key, params):
    """A state whose M slots all hold landmarks scattered within range of the origin."""
    from jaxslam.filter import make_filter

    state = make_filter(config).init(jnp.zeros(3))
    num, slots = config.num_particles, config.max_landmarks
    key_mean, key_pose = jax.random.split(key)
    angle = jax.random.uniform(key_mean, (slots,), minval=-np.pi, maxval=np.pi)
    radius = jnp.linspace(2.0, 0.9 * float(params.max_range), slots)
    mean = jnp.stack([radius * jnp.cos(angle), radius * jnp.sin(angle)], -1)
    particles = state.particles._replace(
        pose=0.02 * jax.random.normal(key_pose, (num, 3)),
        landmark_mean=jnp.broadcast_to(mean, (num, slots, 2)),
        landmark_cov=jnp.broadcast_to(jnp.array([0.01, 0.0, 0.01]), (num, slots, 3)),
        active=jnp.ones((num, slots), bool),
        existence=jnp.ones((num, slots)),
        observation_count=jnp.ones((num, slots), jnp.int32),
    )
    return state._replace(particles=particles), mean, angle, radius


def bench_step(num_particles, max_landmarks, max_obs, association="stable",
               proposal="motion", repeats=20):
    from jaxslam.filter import make_filter
    from jaxslam.types import FilterConfig, default_params, make_observations

    config = FilterConfig(num_particles=num_particles, max_landmarks=max_landmarks,
                          max_obs=max_obs, association=association, proposal=proposal)
    params = default_params(config)
    state, _, angle, radius = _full_map_state(config, jax.random.PRNGKey(0), params)
    seen = jnp.arange(max_obs) * (max_landmarks // max_obs)
    z = jnp.stack([radius[seen] + 0.02, angle[seen] + 0.001], -1)
    obs = make_observations(z, landmark_id=seen)
    control = jnp.array([0.0, 0.3, 0.01])
    step = jax.jit(make_filter(config).step)
    key = jax.random.PRNGKey(1)
    tick = time.perf_counter()
    compiled = step.lower(key, state, params, control, obs).compile()
    compile_s = time.perf_counter() - tick
    memory = compiled.memory_analysis()
    temp_mib = getattr(memory, "temp_size_in_bytes", 0) / 2**20 if memory is not None else 0.0
    out = jax.block_until_ready(compiled(key, state, params, control, obs))
    times = []
    for i in range(repeats):
        tick = time.perf_counter()
        out = jax.block_until_ready(compiled(jax.random.fold_in(key, i), state, params,
                                             control, obs))
        times.append(time.perf_counter() - tick)
    info = out[1]
    step_s = float(np.median(times))
    pairs = num_particles * max_obs * max_landmarks / step_s
    print(f"step  P={num_particles:5d} M={max_landmarks:4d} K={max_obs:3d} "
          f"assoc={association:9s} proposal={proposal:11s} compile {compile_s:6.2f} s  "
          f"step {1e3 * step_s:8.3f} ms (median of {repeats}, min {1e3 * min(times):.3f})  "
          f"{pairs / 1e6:7.1f} M pair-evals/s  rounds={int(info.match_rounds)}  "
          f"temp {temp_mib:.1f} MiB")
    return compile_s, step_s, temp_mib


def bench_batch(num_runs, chunk, num_particles, max_landmarks, max_obs, num_steps,
                association="stable", proposal="motion", association_window=0):
    """Time R runs in chunks; returns (compile s, filter s, simulator s, window cut): the
    window cut is the most landmarks any step of any run's association window left out
    although they could have taken part (``StepInfo.window_cut``; 0: the windowed runs are
    the full association's)."""
    from jaxslam.studies import StudyConfig, scenario_batch
    from jaxslam.filter import make_filter, scan_filter
    from jaxslam.types import FilterConfig, default_params
    from sims.config import ScenarioConfig

    config = FilterConfig(num_particles=num_particles, max_landmarks=max_landmarks,
                          max_obs=max_obs, association=association, proposal=proposal,
                          association_window=association_window)
    study = StudyConfig(num_runs=num_runs, chunk_size=chunk, filter=config,
                        scenario=ScenarioConfig(num_steps=num_steps))
    params = default_params(config)

    def one(key, controls, observations, start_pose):
        state = make_filter(config).init(start_pose)
        final, trace = scan_filter(config, key, state, params, controls, observations)
        return trace.mean_pose[-1], jnp.max(trace.window_cut)

    batched = None  # built at the first chunk: a shared world's start pose is one (3,)
    sim_s = filter_s = compile_s = 0.0
    compiled = None
    window_cut = 0
    for start in range(0, num_runs, chunk):
        ids = np.arange(start, start + chunk)
        tick = time.perf_counter()
        scenario = jax.block_until_ready(scenario_batch(study, ids))
        sim_s += time.perf_counter() - tick
        keys = jax.vmap(lambda i: jax.random.fold_in(jax.random.PRNGKey(7), i))(
            jnp.asarray(ids, jnp.uint32))
        starts = scenario.truth_pose[..., 0, :]  # (3,) shared world, (R, 3) per-run worlds
        args = (keys, scenario.controls, scenario.observations, starts)
        if batched is None:
            batched = jax.jit(jax.vmap(one, in_axes=(0, 0, 0, 0 if starts.ndim == 2 else None)))
        if compiled is None:
            tick = time.perf_counter()
            compiled = batched.lower(*args).compile()
            compile_s = time.perf_counter() - tick
        tick = time.perf_counter()
        _, cut = jax.block_until_ready(compiled(*args))
        filter_s += time.perf_counter() - tick
        window_cut = max(window_cut, int(np.max(cut)))
    runs = (num_runs // chunk) * chunk
    rate = runs * num_particles * num_steps / filter_s
    print(f"batch R={runs} P={num_particles} M={max_landmarks} K={max_obs} T={num_steps} "
          f"chunk={chunk} assoc={association} window={association_window or 'none'} "
          f"world={study.scenario.world}: compile {compile_s:.1f} s, filter {filter_s:.1f} s "
          f"({rate / 1e3:.0f} k particle-steps/s), simulator {sim_s:.1f} s, window cut "
          f"{window_cut}")
    return compile_s, filter_s, sim_s, window_cut


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--association", default="stable")
    parser.add_argument("--proposal", default="motion")
    parser.add_argument("--batch-runs", type=int, default=0,
                        help="also run the batched case with this many runs (e.g. 1000)")
    parser.add_argument("--chunk", type=int, default=250)
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--skip-step", action="store_true")
    parser.add_argument("--association-window", type=int, default=0,
                        help="batch case: match against each particle's N nearest landmarks "
                             "(FilterConfig.association_window; 0: all)")
    args = parser.parse_args(argv)
    print(f"jax {jax.__version__} backend={jax.default_backend()} devices={jax.devices()}")
    if not args.skip_step:
        for shape in ((100, 64, 16), (1000, 128, 16)):
            bench_step(*shape, association=args.association, proposal=args.proposal)
    if args.batch_runs:
        bench_batch(args.batch_runs, min(args.chunk, args.batch_runs), 100, 64, 16, args.steps,
                    association=args.association, proposal=args.proposal,
                    association_window=args.association_window)


if __name__ == "__main__":
    main()
