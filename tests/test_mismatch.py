"""experiments/mismatch.py: its table row against a hand-worked example, and its filter loop
against the library's ``scan_filter`` on tiny logs (2 runs, 12 steps, 4 particles)."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from experiments.mismatch import (CHI2_3DOF_95, HEADER, filter_settings, main, regime_key,
                                  run_logs, summary_row)
from experiments.proposal_study import make_logs, wilson
from experiments.self_calibration import true_params
from jaxslam.filter import make_filter, scan_filter
from jaxslam.types import FilterConfig


def test_summary_row_hand_example():
    """Four runs, final errors 0.2, 1.5, NaN and 0.9: a NaN estimate counts as diverged (2 of
    4), and the median of errors holding a NaN is shown as nan, not hidden. NEES (4 runs x 2
    steps): run medians 1, 2.95, 10.0075, inf -> median (2.95 + 10.0075) / 2 = 6.47875,
    shown to 3 digits; steps inside 7.815: 1, 1, 3, 2.9 and 7.0, 5 of 8 = 62.5 % (inf is
    outside)."""
    error = np.array([0.2, 1.5, np.nan, 0.9])
    nees = np.array([[1.0, 1.0], [3.0, 2.9], [CHI2_3DOF_95 + 0.1, 12.1], [np.inf, 7.0]])
    row = summary_row(0.3, 4.0, 1.0, "after", error, nees, 1234.0, forests=2)
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[:5] == ["0.3", "4", "1", "after", "4"]
    assert cells[5].startswith("50.0 % [")
    # Forests (0.2, 1.5) and (NaN, 0.9): one diverged run each, rates 0.5 and 0.5, no
    # spread, so the forest interval is Wilson's for 2 of 4 (at the 95 % normal quantile).
    low, high = wilson(2, 4, 1.959963984540054)
    assert cells[6] == f"[{100 * low:.1f}, {100 * high:.1f}]" == "[15.0, 85.0]"
    assert cells[7] == "nan"
    assert cells[8] == "6.48"
    assert cells[9] == "62.5 %"
    assert row.count("|") == HEADER.splitlines()[0].count("|")


def test_grid_keys_are_distinct_and_never_shared_with_the_simulation():
    """The default grid (and the sensor rows) gives one key per point, and the filter runs'
    keys (``split(key_filters, R)``) are none of the simulation's keys (``fold_in(key_logs,
    f)`` per forest and the two halves of each forest's split): the defect fixed in the
    script, where the filter key was a forest's key."""
    points = ([(w, o, 1.0) for w in (0.0, 0.3) for o in (1.0, 2.0, 4.0, 6.0)]
              + [(w, 1.0, s) for w in (0.0, 0.3) for s in (2.0, 4.0)])
    keys = [regime_key(900, *point) for point in points]
    assert len({tuple(np.asarray(k).tolist()) for k in keys}) == len(points)
    for key in keys:
        key_logs, key_filters = jax.random.split(key)
        simulation = set()
        for forest in range(10):
            folded = jax.random.fold_in(key_logs, forest)
            simulation.add(tuple(np.asarray(folded).tolist()))
            simulation.update(tuple(np.asarray(k).tolist()) for k in jax.random.split(folded))
        filters = {tuple(np.asarray(k).tolist()) for k in jax.random.split(key_filters, 100)}
        assert not simulation & filters


def test_filter_settings_and_overrides():
    """before: the seed paper's filter, no bursts; after: the shipped defaults; overrides after
    a colon reach FilterConfig or Params; an unknown filter name stops with its name."""
    config, params = filter_settings("before", 4)
    assert config.proposal == "motion" and not config.anchor_empty_map
    assert float(params.motion_outlier_probability) == 0.0
    config, params = filter_settings("after", 4)
    assert config.proposal == FilterConfig().proposal
    assert float(params.motion_outlier_probability) == pytest.approx(0.05)
    assert float(params.max_range) == 12.0
    config, params = filter_settings('after:motion_outlier_probability=0.2,proposal="mixture"', 4)
    assert config.proposal == "mixture"
    assert float(params.motion_outlier_probability) == pytest.approx(0.2)
    with pytest.raises(SystemExit, match="unknown filter 'later'"):
        filter_settings("later", 4)


def test_filter_loop_matches_scan_filter():
    """run_logs steps the filter itself (to read the particle moments each step); its final
    position error must be the library's: ``scan_filter`` with the same per-run keys, final
    weighted mean against the truth. Both run the same float32 step, one vmapped in a jit and
    one not, so only XLA's code generation may round differently: 5.6e-6 m at coordinates of
    ~49 m with full optimisation, 3.4e-5 m (about 9 float32 ulps there) at the test tier's
    lower backend optimisation (tests/conftest.py); atol 1e-4 m. (Should rounding ever flip
    a resampling draw the runs would part by centimetres and this would fail: re-check the
    keys before loosening it.)"""
    key = jax.random.PRNGKey(3)
    controls, obs, truth, _ = make_logs(key, true_params(2.0, 1.0), 0.3, 2, 1)
    controls, truth = controls[:, :12], truth[:, :13]
    obs = jax.tree.map(lambda a: a[:, :12], obs)
    for name in ("before", "after"):
        config, params = filter_settings(name, 4)
        error, nees, _, _ = run_logs(config, params, key, controls, obs, truth, chunk=2)
        assert error.shape == (2,) and nees.shape == (2, 12)
        assert np.all(np.isfinite(nees) & (nees >= 0))  # the covariance floor keeps C invertible
        keys = jax.random.split(key, 2)
        for run in range(2):
            state = make_filter(config).init(jnp.asarray(truth[run, 0]),
                                             dtype=jnp.asarray(controls).dtype)
            _, trace = scan_filter(config, keys[run], state, params, controls[run],
                                   jax.tree.map(lambda a, r=run: a[r], obs))
            want = np.hypot(*(np.asarray(trace.mean_pose[-1, :2]) - truth[run, -1, :2]))
            np.testing.assert_allclose(error[run], want, atol=1e-4)


def _nees_reference(pose, log_weight, true_pose, floor):
    """float64 NumPy: weighted mean (circular heading) and covariance of the (P, 3) particles,
    plus the floor, and e^T C^-1 e against the true pose (heading wrapped)."""
    pose, log_weight = np.asarray(pose, np.float64), np.asarray(log_weight, np.float64)
    w = np.exp(log_weight - log_weight.max())
    w /= w.sum()
    mean = np.array([w @ pose[:, 0], w @ pose[:, 1],
                     np.arctan2(w @ np.sin(pose[:, 2]), w @ np.cos(pose[:, 2]))])
    wrap = lambda a: (a + np.pi) % (2 * np.pi) - np.pi
    d = np.column_stack([pose[:, :2] - mean[:2], wrap(pose[:, 2] - mean[2])])
    cov = (w[:, None] * d).T @ d + np.diag(floor)
    e = np.array([mean[0] - true_pose[0], mean[1] - true_pose[1], wrap(mean[2] - true_pose[2])])
    return e @ np.linalg.solve(cov, e)


def test_nees_against_a_numpy_reference():
    """The per-step NEES of run_logs against the float64 NumPy moments of the particles after
    each step, the filter stepped one jitted call at a time with the same keys (3 steps, 4
    particles, 2 runs). Tolerance: the experiment forms the moments in float32 from poses of
    ~30 m, so each deviation from the mean carries ~2e-6 m of rounding against particle
    spreads of ~1e-3 m: a few 1e-3 relative in the quadratic form (measured 1.4e-3); rtol
    1e-2. A moment of the wrong step or taken before the step's update is off by far more
    (the robot moves 0.5 m a step against spreads of millimetres)."""
    from experiments.mismatch import COV_FLOOR

    key_logs, key = jax.random.split(jax.random.PRNGKey(5))
    controls, obs, truth, _ = make_logs(key_logs, true_params(2.0, 1.0), 0.3, 2, 1)
    controls, truth = controls[:, :3], truth[:, :4]
    obs = jax.tree.map(lambda a: a[:, :3], obs)
    config, params = filter_settings("after", 4)
    _, nees, _, _ = run_logs(config, params, key, controls, obs, truth, chunk=2)
    filt = make_filter(config)
    step = jax.jit(filt.step)
    keys = jax.random.split(key, 2)
    for run in range(2):
        state = filt.init(jnp.asarray(truth[run, 0]), dtype=jnp.asarray(controls).dtype)
        for t in range(3):
            state, _ = step(jax.random.fold_in(keys[run], t), state, params, controls[run, t],
                            jax.tree.map(lambda a, r=run, t=t: a[r, t], obs))
            want = _nees_reference(state.particles.pose, state.log_weight, truth[run, t + 1],
                                   COV_FLOOR)
            assert np.isfinite(want)  # assert_allclose would take NaN == NaN
            np.testing.assert_allclose(nees[run, t], want, rtol=1e-2)


def test_main_tiny(tmp_path):
    """End to end: one regime, both filters, a table written with its command."""
    out = tmp_path / "table.md"
    rows = main(["--runs", "2", "--forests", "2", "--chunk", "2", "--particles", "4",
                 "--steps", "10", "--wobble", "0.3", "--odometry", "2", "--out", str(out),
                 "--errors", str(tmp_path / "errors.npz")])
    saved = np.load(tmp_path / "errors.npz")
    assert sorted(saved.files) == ["0.3/2/1/after", "0.3/2/1/before"]
    assert all(saved[k].shape == (2,) for k in saved.files)
    assert [r.split("|")[4].strip() for r in rows] == ["before", "after"]
    text = out.read_text()
    assert text.startswith("`python experiments/mismatch.py --runs 2")
    assert text.count("\n| 0.3 | 2 | 1 |") == 2
