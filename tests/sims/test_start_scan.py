"""``sims.with_start_scan``: a scan at rest at the start pose, behind a zero move."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import sims
from jaxslam.filter import run_filter
from jaxslam.types import FilterConfig, Observations, default_params


def _observations(rng, lead, num_obs=4):
    """Random Observations with leaves (*lead, K, ...)."""
    return Observations(
        z=jnp.asarray(rng.uniform(0.5, 10.0, lead + (num_obs, 2)), jnp.float32),
        valid=jnp.asarray(rng.uniform(size=lead + (num_obs,)) < 0.7),
        radius=jnp.asarray(rng.uniform(0.1, 0.3, lead + (num_obs,)), jnp.float32),
        landmark_id=jnp.asarray(rng.integers(-1, 9, lead + (num_obs,)), jnp.int32))


def _reference(controls, observations, start):
    """NumPy: zero move first, then the given rows; the start scan first, then the given."""
    controls = np.asarray(controls, np.float64)
    axis = controls.ndim - 2
    zero = np.zeros(controls.shape[:axis] + (1, 3))
    leaves = [np.concatenate([np.expand_dims(np.asarray(s), axis), np.asarray(r)], axis=axis)
              for s, r in zip(start, observations)]
    return np.concatenate([zero, controls], axis=axis), Observations(*leaves)


@pytest.mark.parametrize("lead", [(), (3,)], ids=["one run", "batched runs"])
@pytest.mark.parametrize("jit", [False, True], ids=["eager", "jit"])
def test_matches_the_numpy_reference(lead, jit):
    rng = np.random.default_rng(0)
    num_steps = 5
    controls = jnp.asarray(rng.normal(size=lead + (num_steps, 3)), jnp.float32)
    observations = _observations(rng, lead + (num_steps,))
    start = _observations(rng, lead)
    function = jax.jit(sims.with_start_scan) if jit else sims.with_start_scan
    got_controls, got_obs = function(controls, observations, start)
    want_controls, want_obs = _reference(controls, observations, start)
    assert got_controls.shape == lead + (num_steps + 1, 3)
    assert got_controls.dtype == controls.dtype
    np.testing.assert_array_equal(np.asarray(got_controls), want_controls.astype(np.float32))
    for name in Observations._fields:
        got, want = np.asarray(getattr(got_obs, name)), getattr(want_obs, name)
        assert got.dtype == np.asarray(getattr(observations, name)).dtype, name
        np.testing.assert_array_equal(got, want, err_msg=name)


def test_under_vmap_equals_the_batched_call():
    rng = np.random.default_rng(1)
    controls = jnp.asarray(rng.normal(size=(3, 4, 3)), jnp.float32)
    observations, start = _observations(rng, (3, 4)), _observations(rng, (3,))
    mapped = jax.vmap(sims.with_start_scan)(controls, observations, start)
    batched = sims.with_start_scan(controls, observations, start)
    leaves = zip(jax.tree.leaves(mapped), jax.tree.leaves(batched))
    for got, want in leaves:
        np.testing.assert_array_equal(np.asarray(got), np.asarray(want))


def test_a_single_step_log_gets_two_rows():
    rng = np.random.default_rng(2)
    got_controls, got_obs = sims.with_start_scan(
        jnp.ones((1, 3)), _observations(rng, (1,)), _observations(rng, ()))
    assert got_controls.shape == (2, 3) and got_obs.z.shape == (2, 4, 2)
    np.testing.assert_array_equal(np.asarray(got_controls), [[0, 0, 0], [1, 1, 1]])


def test_bad_shapes_are_refused():
    rng = np.random.default_rng(3)
    observations = _observations(rng, (5,))
    with pytest.raises(ValueError, match=r"controls must have shape \(\.\.\., T, 3\)"):
        sims.with_start_scan(jnp.zeros((5, 2)), observations, _observations(rng, ()))
    with pytest.raises(ValueError, match=r"controls must have shape"):
        sims.with_start_scan(jnp.zeros((3,)), observations, _observations(rng, ()))
    with pytest.raises(ValueError, match="leading axes must be the controls'"):
        sims.with_start_scan(jnp.zeros((6, 3)), observations, _observations(rng, ()))
    with pytest.raises(ValueError, match="leading axes must be the controls'"):
        sims.with_start_scan(jnp.zeros((2, 5, 3)), observations, _observations(rng, ()))
    with pytest.raises(ValueError, match="start_observations.z has shape"):
        sims.with_start_scan(jnp.zeros((5, 3)), observations, _observations(rng, (5,)))
    with pytest.raises(ValueError, match="start_observations.z has shape"):
        sims.with_start_scan(jnp.zeros((5, 3)), observations, _observations(rng, (), 3))


def test_the_start_scan_anchors_the_map_at_the_start_pose():
    """The first move turns the robot by 0.4 rad where the odometry reads 0.3 rad (a slip
    burst: 5.5 of Table 1's stds for that turn), then it drives straight. Without a scan at
    the start, every landmark is placed from the pose after the first move and no later scan
    can reveal its 0.1 rad error; with the start scan the second scan shows it. Noise-free
    observations, P = 20. Bounds: without the start scan the final heading error is the
    first move's error (0.1 rad, to Table 1's 0.02 rad for the turn); with it, under a
    fifth of that."""
    turn, read_turn, num_steps = 0.4, 0.3, 12
    along = jnp.asarray([[6.0, 4.0], [9.0, -3.0], [12.0, 5.0], [15.0, -4.0], [18.0, 3.0],
                         [4.0, -5.0], [21.0, -2.0], [24.0, 4.0]], jnp.float32)
    rotation = jnp.asarray([[jnp.cos(turn), -jnp.sin(turn)], [jnp.sin(turn), jnp.cos(turn)]])
    trees = along @ rotation.T  # the trees beside the straight drive after the turn
    steps = jnp.arange(num_steps + 1, dtype=jnp.float32)
    truth = jnp.stack([steps * jnp.cos(turn), steps * jnp.sin(turn),
                       jnp.where(steps > 0, turn, 0.0)], axis=-1)
    odometry = jnp.tile(jnp.asarray([0.0, 1.0, 0.0], jnp.float32), (num_steps, 1))
    odometry = odometry.at[0, 0].set(read_turn)
    params = default_params()
    noise_free = params._replace(range_noise=(0.0, 0.0), bearing_noise=(0.0, 0.0))

    def scan(pose):
        return sims.analytic_observations(jax.random.PRNGKey(0), pose, trees,
                                          jnp.full((8,), 0.2, jnp.float32), noise_free, 8)

    observations = jax.vmap(scan)(truth[1:])
    config = FilterConfig(num_particles=20, max_landmarks=16, max_obs=8)
    key = jax.random.PRNGKey(4)

    def final_heading_error(controls, obs):
        _, trace = run_filter(config, key, params, controls, obs, truth[0])
        return abs(float(trace.mean_pose[-1, 2]) - turn)

    without = final_heading_error(odometry, observations)
    with_start = final_heading_error(*sims.with_start_scan(odometry, observations,
                                                           scan(truth[0])))
    print(f"final heading error: without the start scan {without:.4f} rad, "
          f"with it {with_start:.4f} rad")
    assert without > 0.07, without
    assert with_start < 0.02, with_start
