"""Host-side checks of the controls given to the filter, and the cast of mixed float inputs.

``check_controls`` refuses controls that are not a finite (T, 3) float array, naming the first
bad row. ``cast_floating`` casts every floating leaf of a pytree to one dtype: ``run_filter``
uses it so float32 and float64 inputs mixed across params, controls and observations meet in
the controls' dtype instead of failing deep inside ``lax.scan``.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np


def is_tracer(x) -> bool:
    """True for a JAX tracer (a value inside ``jit``/``vmap``/``grad`` with no concrete value)."""
    return isinstance(x, jax.core.Tracer)


def check_controls(controls, num_steps: int | None = None, where: str = "controls") -> None:
    """Raise ``ValueError`` unless ``controls`` is a finite (T, 3) float array.

    A tracer is checked for shape and dtype only (its values are unknown). The message for a
    non-finite value names the first bad row, its values and how many rows are bad.

    Args:
      controls: (T, 3) controls of the motion model (array-like).
      num_steps: when given, T must equal it.
      where: the name used in messages.
    """
    if not is_tracer(controls):
        try:
            controls = np.asarray(controls)
        except Exception as error:  # noqa: BLE001
            raise ValueError(f"{where} is not an array ({error}); expected shape (T, 3)") from error
    shape, dtype = tuple(controls.shape), np.dtype(controls.dtype)
    if len(shape) != 2 or shape[1] != 3:
        raise ValueError(f"{where} must have shape (T, 3); got {shape}")
    if num_steps is not None and shape[0] != num_steps:
        raise ValueError(f"{where} must have shape (T, 3) with T = {num_steps}; got {shape}")
    if dtype.kind != "f":
        raise ValueError(f"{where} has dtype {dtype}; expected a float array (float32 or "
                         "float64): its dtype sets the filter's dtype")
    if is_tracer(controls):
        return
    bad_rows = ~np.isfinite(np.asarray(controls, np.float64)).all(axis=1)
    if bad_rows.any():
        row = int(np.argmax(bad_rows))
        values = ", ".join(str(v) for v in np.asarray(controls[row]))  # in its own dtype
        raise ValueError(f"{where} row {row} is [{values}] "
                         f"({int(bad_rows.sum())} of {shape[0]} rows hold NaN or inf); "
                         "expected finite controls in every row")


def cast_floating(tree, dtype):
    """``tree`` with every floating leaf cast to ``dtype`` (other leaves unchanged)."""
    dtype = jnp.dtype(dtype)

    def cast(leaf):
        leaf = jnp.asarray(leaf)
        return leaf.astype(dtype) if jnp.issubdtype(leaf.dtype, jnp.floating) else leaf

    return jax.tree.map(cast, tree)
