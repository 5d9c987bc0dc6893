"""The traced part of a study: filter one (run, condition) pair and score it.

Run i's filter draws from ``fold_in(fold_in(PRNGKey(seed), i), 1)`` (its simulator used 0);
``_group_fn`` is the jit(vmap) over a group of pairs that ``runner`` compiles once per study.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jaxslam import metrics
from jaxslam.filter import estimate, make_filter, scan_filter
from jaxslam.simulators import RunBatch, load_simulator
from jaxslam.study_config import StudyConfig
from jaxslam.types import Params, default_params


def scenario_batch(config: StudyConfig, run_ids) -> RunBatch:
    """Simulate the runs ``run_ids`` (R,) with the simulator ``config.simulator`` names.

    Raises ``SimulatorUnavailable`` (an ImportError naming the install command) when the
    simulator, or a part of it these runs need (MuJoCo for "sims" lidar scans), is missing.
    """
    return load_simulator(config.simulator).simulate(config, run_ids)


def condition_params(config: StudyConfig) -> Params:
    """Stacked ``Params`` of the G sweep conditions (leading axis G)."""
    base = {"max_range": config.scenario.max_range, **dict(config.params)}  # sensor range
    stacked = [default_params(config.filter, **{**base, **cond}) for cond in config.conditions]
    return jax.tree.map(lambda *leaves: jnp.stack(leaves), *stacked)


def _run_metrics(config: StudyConfig, key, params: Params, controls, observations,
                 world: RunBatch):
    """Filter one run and score it. Returns (metrics dict of (), error trace (T,), example).

    ``key`` is the run's key; the filter uses fold_in(key, 1) (the simulator used 0).
    """
    filter_config = config.filter
    state = make_filter(filter_config).init(world.truth_pose[0])
    final, trace = scan_filter(filter_config, jax.random.fold_in(key, 1), state, params,
                               controls, observations)
    truth = world.truth_pose[1:]
    est = estimate(final)
    position_error = jnp.hypot(trace.mean_pose[:, 0] - truth[:, 0],
                               trace.mean_pose[:, 1] - truth[:, 1])
    scores = metrics.summarize(
        trace.mean_pose, truth, est.landmark_mean, est.active, world.tree_centres,
        world.tree_seen, match_threshold=config.map_match_threshold,
        gospa_cutoff=config.gospa_cutoff, divergence_threshold=config.divergence_threshold,
        landmark_cov=est.landmark_cov, final_pose_cov=est.pose_cov + 1e-9 * jnp.eye(3))
    diameter_error, num_diameters = _diameter_error(est, world, config.map_match_threshold)
    values = dict(
        scores._asdict(),
        num_trees_seen=jnp.sum(world.tree_seen).astype(jnp.int32),
        diameter_error=diameter_error,
        num_diameters=num_diameters,
        min_ess=jnp.min(trace.ess),
        num_resampled=jnp.sum(trace.resampled).astype(jnp.int32),
        num_dropped_births=jnp.sum(trace.num_dropped_births).astype(jnp.int32),
        num_weight_resets=jnp.sum(trace.weights_reset).astype(jnp.int32),
        num_invalid_controls=jnp.sum(trace.invalid_control).astype(jnp.int32),
        peak_match_rounds=jnp.max(trace.match_rounds),
        num_window_cut_steps=jnp.sum(trace.window_cut > 0).astype(jnp.int32),
        peak_window_cut=jnp.max(trace.window_cut).astype(jnp.int32),
        mean_mixture_ratio=jnp.mean(trace.mixture_ratio),
    )
    example = dict(mean_pose=trace.mean_pose, landmark_mean=est.landmark_mean,
                   landmark_cov=est.landmark_cov, landmark_radius=est.landmark_radius,
                   active=est.active)
    return values, position_error, example


def _diameter_error(est, world: RunBatch, threshold):
    """Mean |2 r_landmark - 2 r_tree| [m] over landmarks matched to a tree that carry a
    measured radius (> 0), and their count. 0 when there are none (check the count)."""
    tree = metrics.match_landmarks(est.landmark_mean, est.active, world.tree_centres,
                                   world.tree_seen, threshold)
    measured = (tree >= 0) & (est.landmark_radius > 0)
    error = 2.0 * jnp.abs(est.landmark_radius - world.tree_radii[jnp.clip(tree, 0)])
    count = jnp.sum(measured)
    return (jnp.sum(jnp.where(measured, error, 0.0)) / jnp.maximum(count, 1),
            count.astype(jnp.int32))


def _group_fn(config: StudyConfig, per_run_world: bool):
    """jit(vmap over a group of (run, condition) pairs) of ``_run_metrics``.

    Arguments: keys, params (leaves with the pair axis first), controls, observations,
    tree_seen (pair axis first), then truth_pose, tree_centres, tree_radii (one world shared
    by every run, or with the pair axis first when ``per_run_world``).
    """

    def per_pair(key, params, controls, observations, seen, truth_pose, centres, radii):
        world = RunBatch(None, None, truth_pose, centres, radii, seen)
        return _run_metrics(config, key, params, controls, observations, world)

    world_axis = 0 if per_run_world else None
    return jax.jit(jax.vmap(per_pair, in_axes=(0, 0, 0, 0, 0) + (world_axis,) * 3))


def _per_run_world(scenario: RunBatch) -> bool:
    """Whether each run of the batch has its own world (truth_pose (R, T+1, 3))."""
    return np.ndim(scenario.truth_pose) == 3
