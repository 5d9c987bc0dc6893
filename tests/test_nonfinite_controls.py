"""Non-finite controls inside jit: a control row with a NaN or inf is missing odometry. The
step keeps every pose (no motion noise, no observation draw), still runs the observation
update, and flags the row in ``StepInfo.invalid_control`` / ``Trace.invalid_control``; for
every proposal and motion model, eagerly, under jit and under vmap. ``run_filter`` on concrete
controls refuses such rows instead (``validation.check_controls``).

Small scene: 4 particles, 4 slots, 3 observations, 8 steps of a straight drive past three
trees, standing still at steps 2 and 5 (the rows the dirty runs replace by NaN / inf, so a
kept pose is the true one there and every observation is matched). Three compiled configs
cover the three proposals and the three motion models.
"""
import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam.filter import make_filter, run_filter, sanitize_control, scan_filter
from jaxslam.types import FilterConfig, default_params, make_observations

F32 = jnp.float32
T = 8
STILL = (2, 5)  # steps where the robot stands still; the dirty rows
# The plain motion proposal; the other two configs switch on the flags they test.
SMALL = FilterConfig(num_particles=4, max_landmarks=4, max_obs=3, boundary="loose",
                     proposal="motion", match_pose_uncertainty=False, anchor_empty_map=False,
                     associate_at_sample=False, burst_proposal=False)
CONFIGS = {
    "motion-odometry": SMALL,
    # The two-piece burst proposal (bursts are on in PARAMS) with pose-uncertainty matching.
    "observation-ackermann": dataclasses.replace(
        SMALL, proposal="observation", motion_model="ackermann", burst_proposal=True,
        match_pose_uncertainty=True),
    # Adaptive phi, re-association at the sample, the empty-map anchor.
    "mixture-velocity": dataclasses.replace(
        SMALL, proposal="mixture", motion_model="velocity", mixture_mode="adaptive",
        associate_at_sample=True, anchor_empty_map=True),
}
# A forward move of 0.5 m and standing still in each motion model's control:
# (rot1, trans, rot2), (v, omega, dt), (v_encoder, steering, dt).
FORWARD = {"odometry": [0.0, 0.5, 0.0], "velocity": [0.5, 0.0, 1.0],
           "ackermann": [0.5, 0.0, 1.0]}
STAND = {"odometry": [0.0, 0.0, 0.0], "velocity": [0.0, 0.0, 1.0],
         "ackermann": [0.0, 0.0, 1.0]}
START = jnp.asarray([0.2, -0.1, 0.05], F32)
PARAMS = default_params(motion_outlier_probability=0.05)


def scene(motion_model="odometry"):
    """Controls (T, 3) and observations (T, 3) of three trees along the true drive (the
    robot frame is START's; noise-free observations)."""
    moving = np.array([t not in STILL for t in range(T)])
    controls = np.where(moving[:, None], FORWARD[motion_model], STAND[motion_model])
    trees = np.array([[4.0, 2.0], [6.0, -2.0], [9.0, 1.0]])
    x, y, theta = np.asarray(START, np.float64)
    z = []
    for t in range(T):
        travelled = 0.5 * np.sum(moving[:t + 1])
        d = trees - np.array([x + travelled * np.cos(theta), y + travelled * np.sin(theta)])
        bearing = np.arctan2(d[:, 1], d[:, 0]) - theta
        z.append(np.stack([np.hypot(d[:, 0], d[:, 1]), bearing], 1))
    return jnp.asarray(controls, F32), make_observations(jnp.asarray(np.stack(z), F32))


def dirty(controls):
    """Row 2 with a NaN, row 5 with +inf."""
    return controls.at[2, 1].set(jnp.nan).at[5, 0].set(jnp.inf)


def floats_finite(tree):
    return all(bool(jnp.all(jnp.isfinite(leaf))) for leaf in jax.tree.leaves(tree)
               if jnp.issubdtype(leaf.dtype, jnp.floating))


@functools.lru_cache(maxsize=None)
def jitted_run(name):
    """One compiled run per config, shared by the tests: ``run_filter`` under jit (the
    controls are tracers, so ``check_controls`` checks their shape only), lineage recorded."""
    def run(key, params, controls, obs):
        return run_filter(CONFIGS[name], key, params, controls, obs, initial_pose=START,
                          record_lineage=True)

    return jax.jit(run)


def assert_trees_equal(got, want):
    for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(want), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def assert_kept_poses(trace, steps):
    """At each step t: every particle's pose after it is, bit for bit, the pose of its
    ancestor before it (``Lineage``: poses after resampling, ancestors of the step)."""
    pose, ancestor = np.asarray(trace.lineage.pose), np.asarray(trace.lineage.ancestor)
    for t in steps:
        np.testing.assert_array_equal(pose[t], pose[t - 1][ancestor[t]], err_msg=f"step {t}")


# ---------------------------------------------------------------------------------------------
# The mask itself


def test_sanitize_control_masks_rows_and_keeps_gradients_finite():
    controls = jnp.asarray([[0.25, 0.5, 0.0], [jnp.nan, 0.5, 0.0], [0.0, -jnp.inf, 0.2]], F32)
    clean, invalid = sanitize_control(controls)
    np.testing.assert_array_equal(np.asarray(invalid), [False, True, True])
    np.testing.assert_array_equal(np.asarray(clean), [[0.25, 0.5, 0.0], [0, 0, 0], [0, 0, 0]])
    # Double where: the gradient through a masked row is 0, not NaN.
    grad = jax.grad(lambda c: jnp.sum(sanitize_control(c)[0] ** 2))(controls)
    np.testing.assert_array_equal(np.asarray(grad), [[0.5, 1.0, 0.0], [0, 0, 0], [0, 0, 0]])


# ---------------------------------------------------------------------------------------------
# (a) + (e) NaN and inf rows, every proposal and motion model: finite, counted, poses kept


@pytest.mark.parametrize("name", list(CONFIGS))
def test_nan_and_inf_rows_are_masked_and_counted(name):
    config = CONFIGS[name]
    controls, obs = scene(config.motion_model)
    key = jax.random.key(0)
    runs = {"jit": jitted_run(name)(key, PARAMS, dirty(controls), obs)}
    if name == "motion-odometry":  # scan_filter called eagerly, not under jit
        runs["eager"] = scan_filter(config, key, make_filter(config).init(START), PARAMS,
                                    dirty(controls), obs, record_lineage=True)
    for how, (final, trace) in runs.items():
        assert floats_finite(final), how  # poses, weights, maps
        assert floats_finite(trace), how
        assert trace.invalid_control.shape == (T,) and trace.invalid_control.dtype == bool
        assert int(trace.invalid_control.sum()) == 2, how
        np.testing.assert_array_equal(np.flatnonzero(np.asarray(trace.invalid_control)), STILL)
        assert_kept_poses(trace, STILL)
        # No observation draw at a masked step (phi 0); the observation update still ran:
        # every particle matched the three trees there and the map holds them.
        np.testing.assert_array_equal(np.asarray(trace.mixture_ratio)[list(STILL)], 0.0)
        np.testing.assert_array_equal(np.asarray(trace.lineage.match)[list(STILL)] >= 0, True)
        np.testing.assert_array_equal(np.asarray(trace.num_landmarks)[list(STILL)], 3)
        # A valid control does move the particles.
        pose, ancestor = np.asarray(trace.lineage.pose), np.asarray(trace.lineage.ancestor)
        assert not np.array_equal(pose[3], pose[2][ancestor[3]])
    if "eager" in runs:
        # Same computation, compiled differently: float32 poses within 1e-5 m (rad).
        np.testing.assert_allclose(np.asarray(runs["eager"][1].mean_pose),
                                   np.asarray(runs["jit"][1].mean_pose), atol=1e-5)
    # The clean run (a zero control at the same steps) has no masked row.
    _, trace = jitted_run(name)(key, PARAMS, controls, obs)
    assert int(trace.invalid_control.sum()) == 0


def test_run_filter_refuses_concrete_controls():
    controls, obs = scene()
    with pytest.raises(ValueError, match="row 2"):
        run_filter(SMALL, jax.random.key(0), PARAMS, dirty(controls), obs, initial_pose=START)


# ---------------------------------------------------------------------------------------------
# (b) the documented behaviour: a masked row is a zero control without standstill noise


def test_masked_row_equals_zero_control_without_standstill_noise():
    # With the constant terms c of Eq. (1) at 0 a zero control has zero std, so its motion draw
    # is the previous pose exactly, which is what the mask does: with the same key both runs
    # agree bit for bit, on every field but the flag. (With c > 0 a zero control would add
    # standstill noise c; the mask adds none, see the filter's module docstring.)
    params = default_params(rot1_noise=(0.0, 0.06, 0.0), trans_noise=(0.02, 0.006, 0.0),
                            rot2_noise=(0.0, 0.06, 0.0), motion_outlier_probability=0.05)
    zero, obs = scene()  # zero controls at steps 2 and 5
    run = jitted_run("motion-odometry")
    final_m, trace_m = run(jax.random.key(3), params, dirty(zero), obs)
    final_z, trace_z = run(jax.random.key(3), params, zero, obs)
    np.testing.assert_array_equal(np.asarray(trace_m.invalid_control), np.isin(np.arange(T),
                                                                               STILL))
    assert not bool(jnp.any(trace_z.invalid_control))
    assert_trees_equal(final_m, final_z)
    assert_trees_equal(trace_m._replace(invalid_control=None),
                       trace_z._replace(invalid_control=None))
    # The particles did spread (the run is not trivially noise-free).
    assert float(jnp.std(final_m.particles.pose[:, 0])) > 0.0


# ---------------------------------------------------------------------------------------------
# (c) vmap over a clean and a dirty run


def test_vmap_clean_run_matches_its_unbatched_trace():
    name = "mixture-velocity"
    controls, obs = scene(CONFIGS[name].motion_model)
    key = jax.random.key(5)
    run = jitted_run(name)
    batched = jax.jit(jax.vmap(run, in_axes=(None, None, 0, None)))
    finals, traces = batched(key, PARAMS, jnp.stack([controls, dirty(controls)]), obs)
    np.testing.assert_array_equal(np.asarray(traces.invalid_control.sum(axis=1)), [0, 2])
    assert floats_finite(finals) and floats_finite(traces)
    for index, run_controls in enumerate((controls, dirty(controls))):
        final, trace = run(key, PARAMS, run_controls, obs)
        # Batched and unbatched programs fuse differently: float32 within 1e-5 (poses in m
        # and rad, log weights and likelihoods of order 10); flags, counts, ancestors exactly.
        for got, want in zip(jax.tree.leaves(jax.tree.map(lambda leaf: leaf[index], traces)),
                             jax.tree.leaves(trace), strict=True):
            if jnp.issubdtype(want.dtype, jnp.floating):
                np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=1e-5,
                                           atol=1e-5)
            else:
                np.testing.assert_array_equal(np.asarray(got), np.asarray(want))
        np.testing.assert_allclose(np.asarray(finals.particles.pose[index]),
                                   np.asarray(final.particles.pose), atol=1e-5)


# ---------------------------------------------------------------------------------------------
# (d) every control missing


@pytest.mark.parametrize("name", list(CONFIGS))
def test_all_controls_missing_keeps_the_initial_pose(name):
    controls, obs = scene(CONFIGS[name].motion_model)
    nan = jnp.full_like(controls, jnp.nan)
    final, trace = jitted_run(name)(jax.random.key(1), PARAMS, nan, obs)
    assert floats_finite(final) and floats_finite(trace)
    assert int(trace.invalid_control.sum()) == T
    # Every particle stays exactly at the start; the weighted mean (a float32 sum of P
    # weights x the same value) within 1e-6.
    np.testing.assert_array_equal(np.asarray(final.particles.pose),
                                  np.broadcast_to(np.asarray(START), (4, 3)))
    np.testing.assert_array_equal(np.asarray(trace.best_pose),
                                  np.broadcast_to(np.asarray(START), (T, 3)))
    np.testing.assert_allclose(np.asarray(trace.mean_pose),
                               np.broadcast_to(np.asarray(START), (T, 3)), atol=1e-6)
    np.testing.assert_array_equal(np.asarray(trace.mixture_ratio), 0.0)
    # The map was still built from the observations.
    assert int(trace.num_landmarks[-1]) >= 1
