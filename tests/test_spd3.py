"""Closed-form 3x3 SPD algebra (jaxslam.spd3) against NumPy float64 (LAPACK).

Tolerances: float32 inputs, so the closed forms are compared with a relative tolerance of
c * cond(A) * eps32 (the forward error bound of a backward-stable factorisation, Higham,
Accuracy and Stability of Numerical Algorithms, ch. 10), c = 50 for the few operations each
entry passes through; the float64 runs must agree to 1e-9 relative.
"""
import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam import spd3

EPS32 = float(np.finfo(np.float32).eps)


def _spd(rng, cond):
    """A random SPD 3x3 matrix with condition number ``cond`` (float64)."""
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    eigenvalues = np.geomspace(1.0, 1.0 / cond, 3) * rng.uniform(0.1, 10.0)
    return (q * eigenvalues) @ q.T


def _cases():
    rng = np.random.default_rng(0)
    mats = [_spd(rng, cond) for cond in (1.0, 10.0, 1e3, 1e5) for _ in range(4)]
    # A badly conditioned pose covariance: a pure turn (no lateral variance) plus a jitter of
    # 1e-5 of its heading variance (the proposal's rule before 2026-12-04; the current one,
    # proposal.pose_jitter, adds 100 eps of the position block); and a diagonal one.
    mats.append(np.diag([0.0, 0.0, 0.04]) + 1e-5 * 0.04 * np.eye(3) + 1e-14 * np.eye(3))
    mats.append(np.diag([2.0, 3.0, 5.0]))
    return np.stack(mats)


def _reference(a):
    chol = np.linalg.cholesky(a)
    return chol, np.linalg.inv(a), np.linalg.slogdet(a)[1]


@pytest.mark.parametrize("jit", [False, True])
@pytest.mark.parametrize("dtype,factor", [(np.float32, 50.0), (np.float64, None)])
def test_against_lapack(jit, dtype, factor):
    mats = _cases()
    if dtype == np.float64 and not jax.config.jax_enable_x64:
        pytest.skip("float64 needs jax_enable_x64")
    inv_fn = jax.jit(spd3.spd_inverse3) if jit else spd3.spd_inverse3
    chol_fn = jax.jit(spd3.cholesky3) if jit else spd3.cholesky3
    for a in mats:
        cond = np.linalg.cond(a)
        rtol = factor * cond * EPS32 if factor else 1e-9
        chol_ref, inv_ref, logdet_ref = _reference(a)
        chol = np.asarray(chol_fn(jnp.asarray(a, dtype)), np.float64)
        inv, logdet = (np.asarray(x, np.float64) for x in inv_fn(jnp.asarray(a, dtype)))
        scale = np.abs(chol_ref).max()
        np.testing.assert_allclose(chol, chol_ref, rtol=0, atol=rtol * scale)
        np.testing.assert_allclose(inv, inv_ref, rtol=0, atol=rtol * np.abs(inv_ref).max())
        np.testing.assert_allclose(logdet, logdet_ref, rtol=0, atol=rtol * 3)
        np.testing.assert_array_equal(inv, inv.T)  # symmetric by construction


def test_solve_lower_and_inverse_against_numpy():
    rng = np.random.default_rng(1)
    for a in _cases():
        chol = np.linalg.cholesky(a)
        b = rng.normal(size=3)
        x = np.asarray(spd3.solve_lower3(jnp.asarray(chol, jnp.float32),
                                         jnp.asarray(b, jnp.float32)), np.float64)
        x_ref = np.linalg.solve(chol, b)
        cond = np.linalg.cond(chol)
        np.testing.assert_allclose(x, x_ref, rtol=0,
                                   atol=50 * cond * EPS32 * np.abs(x_ref).max())
        inv_chol = np.asarray(spd3.lower_inverse3(jnp.asarray(chol, jnp.float32)), np.float64)
        np.testing.assert_allclose(inv_chol, np.linalg.inv(chol), rtol=0,
                                   atol=50 * cond * EPS32 * np.abs(np.linalg.inv(chol)).max())
        assert np.all(np.triu(inv_chol, 1) == 0.0)


def test_vmap_matches_loop_and_batch_axes():
    mats = jnp.asarray(_cases(), jnp.float32)
    inv, logdet = jax.vmap(spd3.spd_inverse3)(mats)
    inv_b, logdet_b = spd3.spd_inverse3(mats)  # leading batch axis without vmap
    # The log-determinant sums three logs; XLA may associate that sum differently for a batch
    # than for one matrix, so it is compared to 4 ulp of its magnitude; the inverse is exact.
    for i in range(mats.shape[0]):
        inv_i, logdet_i = spd3.spd_inverse3(mats[i])
        np.testing.assert_array_equal(inv[i], inv_i)
        np.testing.assert_allclose(logdet[i], logdet_i, rtol=4 * EPS32, atol=4 * EPS32)
    np.testing.assert_array_equal(inv, inv_b)
    np.testing.assert_allclose(logdet, logdet_b, rtol=4 * EPS32, atol=4 * EPS32)
    chex.assert_shape(inv, (mats.shape[0], 3, 3))
    chex.assert_shape(logdet, (mats.shape[0],))


def test_identity_and_upper_triangle_ignored():
    eye = jnp.eye(3)
    inv, logdet = spd3.spd_inverse3(eye)
    np.testing.assert_array_equal(inv, eye)
    assert float(logdet) == 0.0
    a = jnp.asarray(_cases()[5], jnp.float32)
    garbage_upper = a + jnp.triu(jnp.full((3, 3), 7.0), 1)
    np.testing.assert_array_equal(spd3.cholesky3(garbage_upper), spd3.cholesky3(a))


def test_not_positive_definite_gives_nan():
    """As jnp.linalg.cholesky: an indefinite matrix yields NaN, never a silent number."""
    indefinite = jnp.diag(jnp.array([1.0, -1.0, 1.0]))
    assert np.isnan(np.asarray(spd3.cholesky3(indefinite))).any()
    assert np.isnan(float(spd3.spd_inverse3(indefinite)[1]))
