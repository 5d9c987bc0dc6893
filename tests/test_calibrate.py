"""Noise-model estimation: the optax non-negative least squares against ``scipy.optimize.nnls``,
per-group maximum likelihood against a NumPy float64 reference, the MAD outlier rules, recovery
of Geiser et al. 2023, Tables 1 and 2 from synthetic data drawn from Eq. (1), and bad input."""
import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.optimize import nnls

from jaxslam import calibrate, nonnegative
from jaxslam.types import default_params

# Geiser et al. 2023, Table 1: rows (rot1, trans, rot2), columns (translation, rotation, constant).
TABLE_1 = np.array([[0.0, 0.06, 0.0002], [0.02, 0.006, 0.00003], [0.0, 0.06, 0.0003]])
# Geiser et al. 2023, Table 2: rows (range, bearing), columns (distance, constant).
TABLE_2 = np.array([[0.005, 0.0], [0.0005, 0.0]])


def table1_std(measured):
    """Eq. (1) stds (S, 3) at the measured moves (S, 3), NumPy float64."""
    r1, t, r2 = np.abs(measured).T
    rots = (r1, r1 + r2, r2)
    return np.stack([TABLE_1[i, 0] * t + TABLE_1[i, 1] * rots[i] + TABLE_1[i, 2]
                     for i in range(3)], -1)


def synthetic_moves(seed, num_samples=20000):
    """Measured moves spread over |rot| <= 0.6 rad, trans <= 0.6 m; true = measured + noise."""
    rng = np.random.default_rng(seed)
    measured = np.stack([rng.uniform(-0.6, 0.6, num_samples), rng.uniform(0.0, 0.6, num_samples),
                         rng.uniform(-0.6, 0.6, num_samples)], -1)
    true = measured + table1_std(measured) * rng.standard_normal((num_samples, 3))
    return true, measured


def ref_nnls(design, target, weight):
    root = np.sqrt(weight)
    return nnls(design * root[:, None], target * root)[0]


# ---------------------------------------------------------------------------------------------
# Non-negative least squares


def random_problem(rng, num_groups=30, num_features=3, active=True):
    design = np.abs(rng.normal(size=(num_groups, num_features)))
    design[:, -1] = 1.0
    truth = np.abs(rng.normal(size=num_features))
    if active:
        truth[0] = -0.5  # the unconstrained optimum is negative: the constraint binds
    target = design @ truth + 0.05 * rng.normal(size=num_groups)
    weight = rng.integers(1, 50, num_groups).astype(float)
    return design, target, weight


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("active", [True, False])
def test_nonnegative_matches_scipy_nnls(seed, active):
    design, target, weight = random_problem(np.random.default_rng(seed), active=active)
    expected = ref_nnls(design, target, weight)
    got = nonnegative.fit_nonnegative(design, target, weight)
    np.testing.assert_allclose(got, expected, atol=1e-9, rtol=1e-7)
    # The optax projected gradient alone (no polish) also converges, to 1e-5.
    raw = nonnegative.fit_nonnegative(design, target, weight, num_steps=5000, polish=False)
    np.testing.assert_allclose(raw, expected, atol=1e-5)
    assert np.all(np.asarray(got) >= 0.0)


def test_nonnegative_jit_nojit_vmap():
    rng = np.random.default_rng(7)
    problems = [random_problem(rng) for _ in range(3)]
    design, target, weight = (np.stack(parts) for parts in zip(*problems))
    batched = jax.vmap(lambda d, t, w: nonnegative.fit_nonnegative(d, t, w))(design, target, weight)
    for i in range(3):
        np.testing.assert_allclose(batched[i], ref_nnls(design[i], target[i], weight[i]),
                                   atol=1e-9, rtol=1e-7)
    with jax.disable_jit():
        eager = nonnegative.fit_nonnegative(design[0], target[0], weight[0], num_steps=5)
    jitted = nonnegative.fit_nonnegative(design[0], target[0], weight[0], num_steps=5)
    np.testing.assert_allclose(eager, jitted, rtol=1e-10, atol=1e-12)


def test_zero_weight_drops_groups():
    design, target, weight = random_problem(np.random.default_rng(3))
    weight[:10] = 0.0
    target[:10] = 1e3  # garbage that must not matter
    np.testing.assert_allclose(nonnegative.fit_nonnegative(design, target, weight),
                               ref_nnls(design[10:], target[10:], weight[10:]),
                               atol=1e-9, rtol=1e-7)


# ---------------------------------------------------------------------------------------------
# Grouping and per-group maximum likelihood


def ref_group_stats(features, errors, group, num_groups, estimate_mean, threshold):
    stats = []
    for g in range(num_groups):
        e, f = errors[group == g], features[group == g]
        centre = np.median(e) if (estimate_mean and e.size) else 0.0
        dev = np.abs(e - centre)
        scale = 1.4826 * np.median(dev) if e.size else 0.0
        keep = dev <= threshold * scale
        e, f = e[keep], f[keep]
        mean = e.mean() if (estimate_mean and e.size) else 0.0
        std = np.sqrt(np.mean((e - mean) ** 2)) if e.size else 0.0
        stats.append((f.mean(0) if e.size else np.zeros(f.shape[1]), std, keep.sum(),
                      (~keep).sum()))
    return stats


@pytest.mark.parametrize("estimate_mean", [False, True])
def test_group_stats_matches_numpy(estimate_mean):
    rng = np.random.default_rng(5)
    num_samples, num_groups = 500, 7
    group = rng.integers(0, num_groups - 1, num_samples)  # the last group stays empty
    errors = 0.3 + (1.0 + group) * rng.standard_normal(num_samples)
    errors[::50] *= 30.0  # gross outliers
    features = np.stack([rng.uniform(size=num_samples), np.ones(num_samples)], -1)
    valid = np.ones(num_samples, bool)
    got = calibrate.group_stats(features, errors, group, valid, num_groups, estimate_mean, 4.0)
    expected = ref_group_stats(features, errors, group, num_groups, estimate_mean, 4.0)
    for g, (feat, std, count, removed) in enumerate(expected):
        np.testing.assert_allclose(got.features[g], feat, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(got.std[g], std, rtol=1e-10)
        assert int(got.count[g]) == count and int(got.removed[g]) == removed
    assert int(got.count[-1]) == 0 and float(got.std[-1]) == 0.0
    assert int(jnp.sum(got.removed)) >= 8  # the 10 planted outliers, most of them caught


def test_group_stats_masks_invalid_samples():
    rng = np.random.default_rng(6)
    errors = rng.standard_normal(200)
    group = rng.integers(0, 4, 200)
    features = np.ones((200, 1))
    valid = np.arange(200) < 150
    errors_bad = errors.copy()
    errors_bad[150:] = 1e6  # padded rows hold garbage
    masked = calibrate.group_stats(features, errors_bad, group, valid, 4, False, np.inf)
    clean = calibrate.group_stats(features[:150], errors[:150], group[:150],
                                  np.ones(150, bool), 4, False, np.inf)
    chex.assert_trees_all_close(masked, clean, rtol=1e-12)


def test_quantile_bins_balanced():
    values = np.random.default_rng(1).uniform(size=1000)
    group = np.asarray(calibrate.quantile_bins(jnp.asarray(values), 4))
    np.testing.assert_array_equal(np.bincount(group, minlength=4), [250, 250, 250, 250])
    assert np.all(np.diff(group[np.argsort(values)]) >= 0)


# ---------------------------------------------------------------------------------------------
# Recovery of Tables 1 and 2 from synthetic Eq. (1) data


def test_recovers_table1():
    """20000 moves; tolerance: rotation and translation slopes within 5% of their Table 1
    value (absolute 2e-3 where the table has 0), constants within 1e-3 absolute; the fitted
    std within 5% of the true one over the data range."""
    true, measured = synthetic_moves(0)
    fit = calibrate.fit_motion_noise(true, measured)
    coefficients = np.stack([np.asarray(f.coefficients) for f in fit])
    assert np.all(coefficients >= 0.0)
    np.testing.assert_allclose(coefficients[:, :2], TABLE_1[:, :2], rtol=0.05, atol=2e-3)
    np.testing.assert_allclose(coefficients[:, 2], TABLE_1[:, 2], atol=1e-3)
    grid = np.stack([np.full(4, 0.4), np.linspace(0.1, 0.6, 4), np.full(4, 0.3)], -1)
    params = calibrate.with_fitted_noise(default_params(dtype=jnp.float64), fit)
    from jaxslam.motion import odometry_std
    np.testing.assert_allclose(odometry_std(jnp.asarray(grid), params), table1_std(grid),
                               rtol=0.05)


def test_recovers_table2():
    """Ranges 1-20 m, 10000 detections; slopes within 5%, constants within 2e-3 m / 2e-4 rad."""
    rng = np.random.default_rng(2)
    distance = rng.uniform(1.0, 20.0, 10000)
    bearing = rng.uniform(-np.pi, np.pi, 10000)
    measured = np.stack([distance, bearing], -1)
    std = distance[:, None] * TABLE_2[:, 0] + TABLE_2[:, 1]
    true = measured + std * rng.standard_normal((10000, 2))
    fit = calibrate.fit_observation_noise(true, measured)
    np.testing.assert_allclose(fit.range.coefficients[0], TABLE_2[0, 0], rtol=0.05)
    np.testing.assert_allclose(fit.bearing.coefficients[0], TABLE_2[1, 0], rtol=0.05)
    assert abs(float(fit.range.coefficients[1])) < 2e-3
    assert abs(float(fit.bearing.coefficients[1])) < 2e-4
    params = calibrate.with_fitted_noise(default_params(), observation=fit)
    assert params.range_noise.dtype == jnp.float32 and params.range_noise.shape == (2,)
    np.testing.assert_allclose(params.bearing_noise, fit.bearing.coefficients, rtol=1e-6)
    assert params.rot1_noise.shape == (3,)  # motion rows untouched
    np.testing.assert_allclose(params.rot1_noise, default_params().rot1_noise)


def test_sample_outliers_removed():
    """2% of moves get a gross error (a wheel jump of 1 rad / 0.5 m): with the MAD rule the
    rotation slope stays within 5% of Table 1; without it (threshold inf) it is off by > 50%."""
    true, measured = synthetic_moves(1)
    rng = np.random.default_rng(11)
    hit = rng.uniform(size=true.shape[0]) < 0.02
    true = true + hit[:, None] * np.array([1.0, 0.5, 1.0])
    fit = calibrate.fit_motion_noise(true, measured)
    assert int(jnp.sum(fit.rot1.groups.removed)) >= int(hit.sum()) * 0.9
    np.testing.assert_allclose(fit.rot1.coefficients[1], TABLE_1[0, 1], rtol=0.05)
    raw = calibrate.fit_motion_noise(true, measured, sample_threshold=np.inf,
                                     group_threshold=np.inf)
    assert abs(float(raw.rot1.coefficients[1]) - TABLE_1[0, 1]) > 0.5 * TABLE_1[0, 1] or \
        float(raw.rot1.coefficients[2]) > 0.05


def test_group_outlier_removed():
    """One distance bin has 5x the noise of the model: the group rule drops it and only it."""
    rng = np.random.default_rng(4)
    distance = rng.uniform(1.0, 20.0, 12000)
    std = 0.005 * distance
    group = np.asarray(calibrate.quantile_bins(jnp.asarray(distance), 12))
    std = np.where(group == 5, 5.0 * std, std)
    errors = std * rng.standard_normal(12000)
    features = np.stack([distance, np.ones_like(distance)], -1)
    fit = calibrate.fit_noise(features, errors, group, 12)
    kept = np.asarray(fit.kept)
    assert not kept[5] and kept.sum() == 11
    np.testing.assert_allclose(fit.coefficients[0], 0.005, rtol=0.05)


def test_estimated_mean_separates_bias():
    """Errors N(0.05, 0.02^2): the known-zero-mean ML std is sqrt(0.05^2 + 0.02^2), the
    estimated-mean ML std is 0.02 (1% tolerance at 40000 samples)."""
    rng = np.random.default_rng(9)
    errors = 0.05 + 0.02 * rng.standard_normal(40000)
    features = np.ones((40000, 1))
    group = np.zeros(40000, np.int32)
    known = calibrate.fit_noise(features, errors, group, 1)
    estimated = calibrate.fit_noise(features, errors, group, 1, estimate_mean=True)
    np.testing.assert_allclose(known.coefficients[0], np.hypot(0.05, 0.02), rtol=0.01)
    np.testing.assert_allclose(estimated.coefficients[0], 0.02, rtol=0.01)
    np.testing.assert_allclose(estimated.groups.mean[0], 0.05, rtol=0.01)


def test_angle_errors_wrap():
    measured = np.array([[3.1, 0.2, -3.1]] * 40)
    true = measured + np.array([0.1, 0.0, -0.1])  # crosses +-pi
    errors, _ = calibrate.motion_samples(jnp.asarray(true), jnp.asarray(measured))
    np.testing.assert_allclose(errors[:, 0], 0.1, atol=1e-12)
    np.testing.assert_allclose(errors[:, 2], -0.1, atol=1e-12)


def test_motion_errors_take_the_decomposition_nearest_the_measured_move():
    """A true move 1.5 cm backwards (``odometry_from_poses`` writes it rot1 = pi, trans
    0.015, rot2 = -pi + 0.01) under a measured 2 cm forward creep: the errors are those of
    (0, -0.015, 0.01), not pi in rot1 and rot2; a move near its measurement is unchanged;
    eager and jit agree."""
    from jaxslam.motion import odometry_from_poses

    true = odometry_from_poses(jnp.zeros((2, 3)), jnp.array([[-0.015, 0.0, 0.01],
                                                             [0.5, 0.01, 0.02]]), 0.01)
    measured = jnp.array([[0.0, 0.02, 0.0], [0.01, 0.5, 0.0]])
    for samples in (calibrate.motion_samples, jax.jit(calibrate.motion_samples)):
        errors, features = samples(true, measured)
        np.testing.assert_allclose(errors[0], [0.0, -0.035, 0.01], atol=1e-12)
        np.testing.assert_allclose(errors[1], np.asarray(true[1] - measured[1]), atol=1e-12)
        np.testing.assert_allclose(features[1][0], [0.02, 0.0, 1.0], atol=1e-12)  # measured


# ---------------------------------------------------------------------------------------------
# Bad input


def test_bad_input_errors():
    true, measured = synthetic_moves(3, 200)
    with pytest.raises(ValueError, match=r"\(S, 3\)"):
        calibrate.fit_motion_noise(true[:, :2], measured[:, :2])
    with pytest.raises(ValueError, match=r"\(S, 3\)"):
        calibrate.fit_motion_noise(true, measured[:-1])
    bad = true.copy()
    bad[3, 1] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        calibrate.fit_motion_noise(bad, measured)
    with pytest.raises(ValueError, match="valid samples"):
        calibrate.fit_motion_noise(true[:20], measured[:20])
    with pytest.raises(ValueError, match="integer group"):
        calibrate.fit_noise(np.ones((50, 1)), np.zeros(50), np.zeros(50), 1)
    with pytest.raises(ValueError, match="num_groups"):
        calibrate.fit_noise(np.ones((50, 1)), np.zeros(50), np.zeros(50, np.int32), 0)
    with pytest.raises(ValueError, match="min_group_ratio"):
        calibrate.fit_noise(np.ones((50, 1)), np.zeros(50), np.zeros(50, np.int32), 1,
                            min_group_ratio=0.5)
    with pytest.raises(ValueError, match=r"\(S, 2\)"):
        calibrate.fit_observation_noise(np.ones((10, 3)), np.ones((10, 3)))
