"""experiments/self_calibration.py's recovery check against hand-worked examples."""
import types

import numpy as np
import jax.numpy as jnp

from experiments.self_calibration import (Recovery, _write_offline, _write_recovery, recovery,
                                         true_params)
from jaxslam.calibration_residuals import typical_stds
from jaxslam.noise_scale import scaled_noise
from jaxslam.types import default_params, make_observations

ODOMETRY = jnp.asarray([[0.05, 0.5, -0.02], [0.0, 0.5, 0.1], [-0.1, 0.4, 0.0]])
# Rows (0, 0), (0, 1), (1, 0) valid: ranges 3, 9, 3; (1, 1) valid but NaN (not counted).
OBS = make_observations(jnp.asarray([[[3.0, 0.1], [9.0, -0.4]], [[3.0, 0.2], [jnp.nan, 0.0]],
                                     [[5.0, 0.0], [6.0, 0.0]]]),
                        valid=jnp.asarray([[True, True], [True, True], [False, False]]))


def _true_typical(truth):
    return np.asarray(typical_stds(truth, np.asarray(ODOMETRY, np.float64),
                                   np.array([3.0, 9.0, 3.0])))


def test_recovery_hand_example():
    """EM's typical stds 1.0, 1.5, 0.9 and 1.02 times the truth's on the same log, with
    stated relative errors 1 %, 10 %, 5 % and 0.1 %: half-widths 0.0196, 0.196, 0.098 and
    0.00196, so only the heading (ratio 1) lies inside; a group the calibration did not fit
    (no relative_std) has an infinite half-width and counts as inside."""
    truth = true_params(2.0, 2.0)
    true = _true_typical(truth)
    factor = np.array([1.0, 1.5, 0.9, 1.02])
    info = types.SimpleNamespace(
        typical_std=np.stack([true * 3.0, true * factor]), noise_scales=None, values={},
        bursts_fitted=None,
        relative_std={"heading": 0.01, "translation": 0.1, "range": 0.05, "bearing": 0.001})
    found = recovery(truth, info, ODOMETRY, OBS)
    np.testing.assert_allclose(found.ratio, factor, rtol=1e-12)
    np.testing.assert_array_equal(found.total_ratio, found.ratio)  # no bursts fitted
    np.testing.assert_allclose(found.half_width, 1.96 * np.array([0.01, 0.1, 0.05, 0.001]),
                               rtol=1e-12)
    np.testing.assert_array_equal(found.inside, [True, False, False, False])
    assert not found.scaled.any()
    del info.relative_std["bearing"]
    found = recovery(truth, info, ODOMETRY, OBS)
    assert np.isinf(found.half_width[3]) and found.inside[3]


def test_recovery_divides_out_the_search_scales():
    """Returned settings = EM's estimate (here the truth) with the library's own
    ``scaled_noise`` motion x2, observation x4 on top: the ratio is EM's (1 everywhere,
    inside any interval), and the groups the search changed are flagged (all four here; the
    motion pair only when the observation scale is 1)."""
    truth = true_params(4.0, 2.0)
    returned = _true_typical(scaled_noise(truth, 2.0, 4.0))
    info = types.SimpleNamespace(
        typical_std=np.stack([_true_typical(truth), returned]),
        noise_scales=types.SimpleNamespace(motion_scale=2.0, observation_scale=4.0), values={},
        bursts_fitted=False,
        relative_std={"heading": 0.01, "translation": 0.01, "range": 0.01, "bearing": 0.01})
    found = recovery(truth, info, ODOMETRY, OBS)
    np.testing.assert_allclose(found.ratio, np.ones(4), rtol=1e-6)  # float32 Params
    assert found.inside.all() and found.scaled.all()
    info.noise_scales = types.SimpleNamespace(motion_scale=2.0, observation_scale=1.0)
    info.typical_std = np.stack([_true_typical(truth),
                                 _true_typical(scaled_noise(truth, 2.0, 1.0))])
    found = recovery(truth, info, ODOMETRY, OBS)
    np.testing.assert_array_equal(found.scaled, [True, True, False, False])


def test_write_recovery_rows_match_the_header(tmp_path, monkeypatch):
    """Two calls append two blocks of four rows to one table whose rows have the header's
    column count; the counts of runs inside and scaled are per group."""
    monkeypatch.chdir(tmp_path)
    args = types.SimpleNamespace(seed=500, odometry_scale=4.0, sensor_scale=2.0, wobble=0.3,
                                 odometry_gain=(1.0, 1.0), fit_gain=False)
    runs = [Recovery(np.array([1.0, 1.5, 0.99, 1.0]), np.full(4, 0.1),
                     np.array([True, False, True, True]), np.array([True, True, False, False]),
                     np.array([1.2, 1.8, 0.99, 1.0]), np.array([False, False, True, True])),
            Recovery(np.array([0.5, 1.0, 1.0, 1.2]), np.full(4, 0.1),
                     np.array([False, True, True, False]), np.zeros(4, bool),
                     np.array([0.6, 1.05, 1.0, 1.2]), np.array([False, True, True, False]))]
    _write_recovery(args, runs)
    _write_recovery(args, runs)
    lines = (tmp_path / "results" / "self_calibration" / "recovery.md").read_text().splitlines()
    table = [line for line in lines if line.startswith("|")]
    header, rows = table[0], table[2:]
    assert len(rows) == 8
    assert all(row.count("|") == header.count("|") for row in rows)
    heading = [c.strip() for c in rows[0].strip("|").split("|")]
    assert heading[:7] == ["500", "4", "2", "0.3", "1, 1; not fitted", "heading", "2"]
    assert heading[7] == "0.75 [0.50, 1.00]" and heading[9] == "1 of 2" and heading[10] == "1"
    assert heading[11] == "0.90 [0.60, 1.20]" and heading[12] == "0 of 2"
    bearing = [c.strip() for c in rows[3].strip("|").split("|")]
    assert bearing[9] == "1 of 2" and bearing[10] == "0"


def test_fitted_bursts_count_in_the_total_ratio():
    """Fitted bursts eps 0.1, kappa 3: the mixture's rms is sqrt(0.9 + 0.9) = 1.342 times the
    core, so a core ratio of 0.75 is a total of 1.006 (inside +-0.02); the defensive bursts
    kept when none were fitted count as none, whatever their values (``bursts_fitted``
    False), as does no motion fit (None); the sensor groups never change."""
    from experiments.self_calibration import burst_rms_factor

    bursts = {"motion_outlier_probability": 0.1, "motion_outlier_scale": 3.0}
    fitted = types.SimpleNamespace(values=bursts, bursts_fitted=True)
    np.testing.assert_allclose(burst_rms_factor(fitted), np.sqrt(1.8), rtol=1e-6)  # float32
    assert burst_rms_factor(types.SimpleNamespace(values=bursts, bursts_fitted=False)) == 1.0
    assert burst_rms_factor(types.SimpleNamespace(values={}, bursts_fitted=None)) == 1.0
    truth = true_params(2.0, 2.0)
    true = _true_typical(truth)
    info = types.SimpleNamespace(
        typical_std=np.stack([true, true * np.array([0.75, 0.75, 0.75, 1.0])]),
        noise_scales=None,
        values=bursts, bursts_fitted=True,
        relative_std={"heading": 0.01, "translation": 0.01, "range": 0.01, "bearing": 0.01})
    found = recovery(truth, info, ODOMETRY, OBS)
    np.testing.assert_allclose(found.total_ratio, [0.75 * np.sqrt(1.8)] * 2 + [0.75, 1.0],
                               rtol=1e-6)  # the burst factor from float32 Params
    np.testing.assert_array_equal(found.inside, [False, False, False, True])
    np.testing.assert_array_equal(found.total_inside, [True, True, False, True])


def test_offline_table_by_hand(tmp_path, monkeypatch):
    """Three runs: medians and the over-0.5 m counts of each column, worked by hand; the row
    has the header's column count."""
    monkeypatch.chdir(tmp_path)
    args = types.SimpleNamespace(odometry_scale=2.0, sensor_scale=5.0, wobble=0.3,
                                 particles=100, proposal="observation",
                                 odometry_gain=(0.93, 0.9), fit_gain=True)
    # dead reckoning, true online, calibrated online, maps, trees seen
    rows = np.array([[1.0, 3.0, 0.2, 30, 31, 31], [9.0, 0.2, 0.6, 28, 28, 28],
                     [2.0, 1.2, 0.9, 28, 29, 31]])
    offline = np.array([[0.1, 0.3], [0.13, np.inf], [0.46, 0.05]])
    _write_offline(args, rows, offline)
    table = [line for line in (tmp_path / "results" / "self_calibration" / "offline.md")
             .read_text().splitlines() if line.startswith("|")]
    assert table[2].count("|") == table[0].count("|")
    cells = [c.strip() for c in table[2].strip("|").split("|")]
    assert cells == ["2", "5", "0.3", "0.93, 0.9; fitted", "3", "2.00", "1.200 (2)",
                     "0.130 (0)", "0.600 (2)", "0.300 (1)"]


def test_offline_error_closes_what_the_online_estimate_misses():
    """Run 1 of the held-out seed-500 logs with a sensor 5x Table 2 (wobbly loop, 2x
    odometry), the filter given the true noise at P = 20: the online estimate ends metres
    off (1.89 m with the test tier's lower XLA optimisation, 2.35 m fully optimised: the run
    is chaotic, so rounding moves it), the smoothed history with the missed loop closed
    under a quarter of that (0.14 m at both levels), from the same run. Run 1 was chosen
    because the claim holds at both levels; run 0 ends 0.48 m or 3.10 m off online, by
    level. The bound is the claim the docs make of the offline estimate (far better than
    online on such logs), not a tolerance: a single log's offline error is not always small
    (run 2 of these logs ends 4.3 m off offline; 0-2 of 8 logs a row in the docs' table over
    0.5 m). The paper's ``loose`` boundary is pinned: it throws away the observations in
    its ring, which is what sends this run metres off online (with the default
    ``loose_match`` the online estimate no longer fails here: docs/results.md, "Matching
    across the airlock")."""
    import jax

    from experiments.self_calibration import make_log, score
    from jaxslam.types import FilterConfig

    params = true_params(2.0, 5.0)
    key_log, key_filter = jax.random.split(jax.random.fold_in(jax.random.PRNGKey(500), 1))
    controls, obs, truth, trees = make_log(key_log, params, 0.3)
    config = FilterConfig(num_particles=20, max_landmarks=96, max_obs=12, boundary="loose")
    online, landmarks, _, _, offline = score(config, key_filter, params, controls, obs, truth,
                                              trees, offline=True)
    assert online > 1.0 and 0.0 <= offline < 0.25 * online
    # Recording the lineage for the offline estimate leaves the run itself as it was.
    plain = score(config, key_filter, params, controls, obs, truth, trees)
    assert plain[:2] == (online, landmarks) and np.isnan(plain[4])


def test_bootstrap_recovery_and_its_table(tmp_path, monkeypatch):
    """The truth over EM's estimate against the interval's limits over it, by hand; two
    runs give one block of four rows with the header's column count."""
    from experiments.self_calibration import _write_bootstrap, bootstrap_recovery
    from jaxslam.calibration_bootstrap import BootstrapIntervals

    monkeypatch.chdir(tmp_path)
    controls = np.tile([0.1, 0.5, -0.1], (20, 1))
    obs = make_observations(jnp.asarray(np.tile([3.0, 0.2], (20, 2, 1)), jnp.float32))
    truth = default_params(rot1_noise=(0.0, 0.1, 0.001), trans_noise=(0.04, 0.0, 0.001),
                           rot2_noise=(0.0, 0.1, 0.001), range_noise=(0.01, 0.03),
                           bearing_noise=(0.001, 0.004))
    true = typical_stds(truth, controls, np.full(40, 3.0))
    estimate = true * np.array([0.8, 1.0, 1.0, 1.3])
    found = BootstrapIntervals(estimate, np.ones((3, 4)), np.ones((3, 4)), np.zeros(4),
                               np.zeros(4), estimate * np.array([1.1, 0.9, 0.95, 0.8]),
                               estimate * np.array([1.3, 1.1, 1.05, 0.9]), 0.95,
                               np.zeros(4, int))
    booted = bootstrap_recovery(truth, found, controls, obs)
    np.testing.assert_allclose(booted.truth, [1.25, 1.0, 1.0, 1 / 1.3], rtol=1e-6)
    np.testing.assert_array_equal(booted.inside, [True, True, True, False])
    np.testing.assert_allclose(booted.lower, [1.1, 0.9, 0.95, 0.8], rtol=1e-12)
    args = types.SimpleNamespace(seed=500, odometry_scale=2.0, sensor_scale=2.0, wobble=0.0,
                                 bootstrap=20, odometry_gain=(1.0, 1.0), fit_gain=False)
    _write_bootstrap(args, [booted, booted._replace(inside=np.zeros(4, bool))])
    lines = (tmp_path / "results" / "self_calibration" / "bootstrap.md").read_text().splitlines()
    table = [line for line in lines if line.startswith("|")]
    header, rows = table[0], table[2:]
    assert len(rows) == 4 and all(row.count("|") == header.count("|") for row in rows)
    heading = [c.strip() for c in rows[0].strip("|").split("|")]
    assert heading == ["500", "2", "2", "0", "1, 1; not fitted", "20", "heading", "2", "1.10",
                       "1.30", "1.25", "1 of 2"]


def test_a_table_of_other_columns_gets_the_header_again(tmp_path, monkeypatch):
    """Rows go under their own header: a file whose last table has another header (other
    columns, or the same columns under another intro) gets the header again before them;
    the same header does not. A last line without its newline, and an empty file, are
    handled."""
    from experiments.self_calibration import _append_rows

    monkeypatch.chdir(tmp_path)
    old = "Old.\n\n| a | b |\n|---|---|\n| 1 | 2 |\n"
    new = "New.\n\n| a | b | c |\n|---|---|---|\n"
    path = tmp_path / "results" / "self_calibration" / "t.md"
    path.parent.mkdir(parents=True)
    path.write_text(old)
    _append_rows("t.md", new, "| 1 | 2 | 3 |\n")
    _append_rows("t.md", new, "| 4 | 5 | 6 |\n")
    assert path.read_text() == old + "\n" + new + "| 1 | 2 | 3 |\n| 4 | 5 | 6 |\n"
    _append_rows("fresh.md", new, "| 7 | 8 | 9 |\n")
    assert (path.parent / "fresh.md").read_text() == new + "| 7 | 8 | 9 |\n"
    # The same columns under another intro (another P or proposal) get the header again.
    other = "Other P.\n\n| a | b | c |\n|---|---|---|\n"
    _append_rows("fresh.md", other, "| 1 | 1 | 1 |\n")
    assert (path.parent / "fresh.md").read_text() == (new + "| 7 | 8 | 9 |\n\n" + other
                                                      + "| 1 | 1 | 1 |\n")
    # A last row without its newline keeps its own line; an empty file gets the header.
    (path.parent / "cut.md").write_text(new + "| 1 | 2 | 3 |")
    _append_rows("cut.md", new, "| 4 | 5 | 6 |\n")
    assert (path.parent / "cut.md").read_text() == new + "| 1 | 2 | 3 |\n| 4 | 5 | 6 |\n"
    (path.parent / "empty.md").write_text("")
    _append_rows("empty.md", new, "| 4 | 5 | 6 |\n")
    assert (path.parent / "empty.md").read_text() == new + "| 4 | 5 | 6 |\n"


def test_logs_read_with_a_gain():
    """``read_with_gain``: the readings times the gains are the log's moves (rot1 and rot2
    by g_r, trans by g_t); gains (1, 1) return the moves themselves."""
    from experiments.self_calibration import read_with_gain

    moves = np.array([[0.1, 0.5, -0.2], [0.0, 0.4, 0.05]], np.float32)
    readings = np.asarray(read_with_gain(moves, (0.8, 0.5)), np.float64)
    np.testing.assert_allclose(readings * [0.5, 0.8, 0.5], moves, rtol=1e-6)
    assert read_with_gain(moves, (1.0, 1.0)) is moves


def test_em_significance_reaches_the_calibration(monkeypatch, capsys):
    """``--em-significance LEVEL`` is calibrate_params' significance (default 0: None, the
    plain sums, as in the library); a level outside [0, 1) is refused by name. The log's
    true-noise run is replaced by a stub."""
    import pytest

    import experiments.self_calibration as experiment

    seen = []

    class Stop(Exception):
        pass

    def calibrate_params(*args, **options):
        seen.append(options["significance"])
        raise Stop

    monkeypatch.setattr(experiment, "score", lambda *args: (0.0, 0, 0, None, 0.0))
    monkeypatch.setattr(experiment, "calibrate_params", calibrate_params)
    for extra in ([], ["--em-significance", "0.05"], ["--em-significance", "0"]):
        with pytest.raises(Stop):
            experiment.main(["--runs", "1", *extra])
    assert seen == [None, 0.05, None]
    with pytest.raises(SystemExit):
        experiment.main(["--runs", "1", "--em-significance", "1.5"])
    assert "--em-significance 1.5: expected a level in (0, 1), or 0" in capsys.readouterr().err
