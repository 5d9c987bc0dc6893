"""Resampling schemes: unbiasedness over many keys, count bounds of systematic and residual,
ESS, the all -inf reset, the one-tree-map gather, jit and vmap. References in NumPy float64."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam import resampling
from jaxslam.types import Particles

SCHEMES = ("systematic", "stratified", "multinomial", "residual")
NUM_KEYS = 4000


def ref_normalize(log_weight):
    w = np.exp(log_weight - np.max(log_weight))
    return w / w.sum()


@pytest.fixture(scope="module")
def log_weight():
    rng = np.random.default_rng(0)
    # P = 16 unequal weights, some large (P w > 1), some tiny, one exactly zero.
    raw = rng.gamma(0.7, size=16)
    raw[3] = 0.0
    raw[5] = 4.0
    with np.errstate(divide="ignore"):
        lw = np.log(raw / raw.sum())
    return jnp.asarray(lw, jnp.float64)


def counts_over_keys(kind, log_weight, num_keys=NUM_KEYS, seed=0):
    keys = jax.random.split(jax.random.key(seed), num_keys)
    fn = jax.jit(jax.vmap(lambda k: resampling.resample_indices(k, log_weight, kind)))
    indices = np.asarray(fn(keys))
    num = log_weight.shape[0]
    assert indices.shape == (num_keys, num) and indices.dtype == np.int32
    assert indices.min() >= 0 and indices.max() < num
    return np.stack([np.bincount(row, minlength=num) for row in indices])


@pytest.mark.parametrize("kind", SCHEMES)
def test_unbiased(kind, log_weight):
    """Mean copy count of particle i over 4000 keys is P w_i within 4 standard errors, with the
    per-draw variance bounded by max(P w (1 - w), 1/4) (multinomial; the others are lower or
    within {floor, floor + 1})."""
    num = log_weight.shape[0]
    w = ref_normalize(np.asarray(log_weight))
    counts = counts_over_keys(kind, log_weight)
    expected = num * w
    tolerance = 4 * np.sqrt(np.maximum(num * w * (1 - w), 0.25) / NUM_KEYS)
    error = np.abs(counts.mean(0) - expected)
    assert np.all(error < tolerance), (kind, error, tolerance)
    assert np.all(counts.sum(1) == num)
    assert np.all(counts[:, 3] == 0), "a zero-weight particle was copied"


def test_systematic_count_bounds(log_weight):
    expected = log_weight.shape[0] * ref_normalize(np.asarray(log_weight))
    counts = counts_over_keys("systematic", log_weight, num_keys=1000, seed=1)
    assert np.all(counts >= np.floor(expected)) and np.all(counts <= np.floor(expected) + 1)


def test_residual_count_bounds(log_weight):
    expected = log_weight.shape[0] * ref_normalize(np.asarray(log_weight))
    counts = counts_over_keys("residual", log_weight, num_keys=1000, seed=2)
    assert np.all(counts >= np.floor(expected))


def test_residual_exact_integer_weights():
    """P w all integers: residual is deterministic and exact (no remainder left to draw)."""
    w = np.array([0.5, 0.25, 0.25, 0.0])
    with np.errstate(divide="ignore"):
        lw = jnp.asarray(np.log(w))
    for seed in range(5):
        idx = np.asarray(resampling.residual(jax.random.key(seed), lw))
        np.testing.assert_array_equal(np.bincount(idx, minlength=4), [2, 1, 1, 0])


@pytest.mark.parametrize("kind", SCHEMES)
def test_single_surviving_particle(kind):
    lw = jnp.full((8,), -jnp.inf).at[5].set(0.0)
    idx = np.asarray(jax.jit(resampling.resample_indices, static_argnums=2)(
        jax.random.key(0), lw, kind))
    np.testing.assert_array_equal(idx, 5)


@pytest.mark.parametrize("kind", SCHEMES)
def test_jit_equals_eager_and_float32(kind, log_weight):
    key = jax.random.key(4)
    eager = resampling.resample_indices(key, log_weight, kind)
    jitted = jax.jit(resampling.resample_indices, static_argnums=2)(key, log_weight, kind)
    np.testing.assert_array_equal(np.asarray(eager), np.asarray(jitted))
    idx32 = resampling.resample_indices(key, log_weight.astype(jnp.float32), kind)
    assert idx32.dtype == jnp.int32 and int(idx32.min()) >= 0 and int(idx32.max()) < 16


def test_unknown_scheme_raises(log_weight):
    with pytest.raises(ValueError, match="resampling"):
        resampling.resample_indices(jax.random.key(0), log_weight, "bootstrap")


# ---------------------------------------------------------------------------------------------
# Normalisation, ESS, reset


def test_normalize_and_ess_vs_reference():
    rng = np.random.default_rng(3)
    raw = jnp.asarray(rng.normal(0, 3, 50) - 1000.0)  # far from 0: needs log-space care
    lw, reset = resampling.normalize_log_weights(raw)
    w = ref_normalize(np.asarray(raw))
    np.testing.assert_allclose(np.exp(np.asarray(lw)), w, rtol=1e-9)
    assert not bool(reset)
    np.testing.assert_allclose(float(resampling.effective_sample_size(lw)), 1 / np.sum(w**2),
                               rtol=1e-9)
    uniform = jnp.full((10,), -jnp.log(10.0))
    np.testing.assert_allclose(float(resampling.effective_sample_size(uniform)), 10.0, rtol=1e-9)
    one_hot = jnp.full((10,), -jnp.inf).at[2].set(0.0)
    np.testing.assert_allclose(float(resampling.effective_sample_size(one_hot)), 1.0, rtol=1e-9)


@pytest.mark.parametrize("bad", [-np.inf, np.nan])
@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_all_zero_weights_reset_to_uniform(bad, dtype):
    lw = jnp.full((6,), bad, dtype)
    out, reset = jax.jit(resampling.normalize_log_weights)(lw)
    assert bool(reset)
    np.testing.assert_allclose(np.asarray(out), -np.log(6.0), rtol=1e-6)
    assert np.all(np.isfinite(np.asarray(out)))
    np.testing.assert_allclose(float(resampling.effective_sample_size(out)), 6.0, rtol=1e-5)


def test_some_nan_weights_are_dropped_not_propagated():
    lw = jnp.asarray([0.0, np.nan, -np.inf, np.log(3.0)])
    out, reset = resampling.normalize_log_weights(lw)
    assert not bool(reset)
    np.testing.assert_allclose(np.exp(np.asarray(out)), [0.25, 0.0, 0.0, 0.75], atol=1e-12)


def test_normalize_vmap():
    lw = jnp.asarray([[0.0, 1.0, 2.0], [-np.inf, -np.inf, -np.inf]])
    out, reset = jax.vmap(resampling.normalize_log_weights)(lw)
    np.testing.assert_array_equal(np.asarray(reset), [False, True])
    np.testing.assert_allclose(np.exp(np.asarray(out[0])), ref_normalize(np.array([0., 1., 2.])),
                               rtol=1e-9)


# ---------------------------------------------------------------------------------------------
# Gather


def test_gather_applies_to_every_leaf():
    num, slots = 5, 3
    rng = np.random.default_rng(4)
    particles = Particles(
        pose=jnp.asarray(rng.normal(size=(num, 3))),
        landmark_mean=jnp.asarray(rng.normal(size=(num, slots, 2))),
        landmark_cov=jnp.asarray(rng.normal(size=(num, slots, 3))),
        landmark_radius=jnp.asarray(rng.normal(size=(num, slots))),
        landmark_id=jnp.asarray(rng.integers(-1, 9, (num, slots)), jnp.int32),
        active=jnp.asarray(rng.random((num, slots)) < 0.5),
        existence=jnp.asarray(rng.normal(size=(num, slots))),
        observation_count=jnp.asarray(rng.integers(0, 9, (num, slots)), jnp.int32),
        radius_count=jnp.asarray(rng.integers(0, 9, (num, slots)), jnp.int32),
    )
    indices = jnp.asarray([4, 4, 0, 2, 1], jnp.int32)
    out = jax.jit(resampling.gather)(particles, indices)
    for name, leaf, got in zip(Particles._fields, particles, out):
        np.testing.assert_array_equal(np.asarray(got), np.asarray(leaf)[np.asarray(indices)],
                                      err_msg=name)
        assert got.dtype == leaf.dtype, name
