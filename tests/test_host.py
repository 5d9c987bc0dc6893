"""``jaxslam.host``: the library's JAX models called on host arrays in float64."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam.geometry import wrap_angle
from jaxslam.host import _jitted, float64_on_host, in_float64
from jaxslam.types import default_params


def _scaled(x, params):
    return x * params.min_translation


def _count_and_scale(x, count, *, factor):
    return x * factor, count + 1


@pytest.mark.parametrize("global_x64", [False, True])
def test_float64_whatever_the_global_flag(global_x64):
    # 1 + 1e-12 is 1 in float32: the product keeps it only when computed in float64. The
    # float32 Params field enters with its exact value (float32(0.01) widened, not 0.01).
    value = np.array([1.0 + 1e-12, 2.0])
    with jax.enable_x64(global_x64):
        out = in_float64(_scaled, value, default_params())
    assert out.dtype == np.float64
    np.testing.assert_array_equal(out, value * np.float64(np.float32(0.01)))


def test_integer_leaves_keep_their_dtype_and_outputs_are_writable():
    scaled, count = in_float64(_count_and_scale, np.arange(3.0), np.arange(3), factor=2.0)
    assert count.dtype.kind == "i" and scaled.dtype == np.float64
    np.testing.assert_array_equal(count, [1, 2, 3])
    scaled[0] = -1.0  # NumPy semantics: a writable copy, not JAX's read-only buffer
    assert scaled[0] == -1.0


def test_matches_numpy_reference_across_pi():
    angles = np.array([np.pi - 1e-13, -np.pi + 1e-13, 3 * np.pi + 0.25, -7.0, 0.0])
    want = (angles + np.pi) % (2 * np.pi) - np.pi
    got = in_float64(wrap_angle, angles)
    np.testing.assert_allclose(np.cos(got), np.cos(want), atol=1e-14)  # +-pi are one angle
    np.testing.assert_allclose(np.sin(got), np.sin(want), atol=1e-12)


def test_decorator_and_compile_reuse():
    wrapped = float64_on_host(_scaled)
    assert wrapped.__name__ == "_scaled"
    compiled = _jitted(_scaled, ())
    wrapped(np.ones(4), default_params())
    size = compiled._cache_size()
    wrapped(np.full(4, 2.0), default_params())  # same shapes: no new compile
    assert compiled._cache_size() == size
    assert isinstance(wrapped(np.ones(2), default_params()), np.ndarray)


def test_a_jax_library_function_on_a_host_array():
    out = in_float64(jnp.cumsum, np.ones(5))
    np.testing.assert_array_equal(out, np.arange(1.0, 6.0))


def test_a_plain_tuple_is_one_array():
    # (dx, dy, dtheta) given as a tuple is one (3,) pose, as NumPy would read it.
    got = in_float64(jnp.sum, (1.0, 2.0, 3.5))
    assert got.dtype == np.float64 and got == 6.5
