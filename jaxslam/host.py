"""The library's JAX models evaluated on host (NumPy) arrays in float64.

Each model (angle wrap, SE(2) composition, the rot1-trans-rot2 decomposition, the noise std of
Eq. (1), range-bearing, Ackermann kinematics, SE(2) alignment) is written once, in JAX, in the
module that owns it. Host algorithms (log loaders, the smoother's residuals, the
self-calibration's M-step) call those same functions through ``in_float64``: jitted, on the
CPU, with 64-bit types switched on for the call only, whatever ``jax_enable_x64`` says
elsewhere. Their numbers then differ from a NumPy float64 transcription of the model by
rounding only, and a GPU default device never changes them.
"""
from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np


@functools.lru_cache(maxsize=None)
def _jitted(function, static_names: tuple[str, ...]):
    """One ``jax.jit`` wrapper per (function, static keyword names), so repeated host calls
    reuse its compilations (one per argument shape and dtype) instead of re-tracing."""
    return jax.jit(function, static_argnames=static_names)


def _as_float64(leaf):
    """A float leaf (NumPy array, Python float, float32 ``Params`` field) as float64 with its
    exact value; integer and bool leaves keep their dtype."""
    leaf = jnp.asarray(leaf)
    return leaf.astype(jnp.float64) if jnp.issubdtype(leaf.dtype, jnp.floating) else leaf


def _argument_as_float64(argument):
    """A NamedTuple (e.g. ``Params``) or dict argument leaf by leaf; anything else, a plain
    tuple or list of numbers included, as one array."""
    is_named_tuple = isinstance(argument, tuple) and hasattr(argument, "_fields")
    if is_named_tuple or isinstance(argument, dict):
        return jax.tree.map(_as_float64, argument)
    return _as_float64(argument)


def in_float64(function, *args, **options):
    """``function(*args, **options)`` jitted, in float64, on the CPU; the result as NumPy.

    Args:
      function: a module-level JAX function (a fresh lambda per call would be compiled per
        call).
      *args: array-likes (a plain tuple or list of numbers is one array), or NamedTuples
        and dicts of them (e.g. ``Params``); float leaves become float64.
      **options: static settings (hashable scalars such as ``min_translation``).
    Returns:
      The function's result with every leaf a writable NumPy array (float64 for float leaves),
      like the arrays a NumPy computation returns.
    """
    compiled = _jitted(function, tuple(sorted(options)))
    with jax.enable_x64(True), jax.default_device(jax.devices("cpu")[0]):
        result = compiled(*map(_argument_as_float64, args), **options)
        return jax.tree.map(np.array, result)  # a copy: JAX's buffers are read-only


def float64_on_host(function):
    """``function`` as a host function: each call runs ``in_float64(function, ...)``."""
    return functools.wraps(function)(functools.partial(in_float64, function))
