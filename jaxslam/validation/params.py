"""``check_params``: host-side rules for every ``Params`` field, before any tracing.

The jitted filter cannot raise: a NaN gate or a negative noise coefficient there only turns
into NaN poses and maps many steps later. ``check_params`` runs on the host (``run_filter`` and
``default_params`` call it) and raises a ``ValueError`` that names the field, the bad value and
what is expected. Leaves that are JAX tracers (inside ``jit`` / ``vmap``) have no value to
check and are skipped silently.
"""
from __future__ import annotations

import numpy as np

from jaxslam.types import Params
from jaxslam.validation.inputs import is_tracer

# Trailing shape of every Params field (leading batch axes allowed for stacked sweeps).
_VECTOR_SHAPES = {
    "rot1_noise": (3,), "trans_noise": (3,), "rot2_noise": (3,),
    "range_noise": (2,), "bearing_noise": (2,), "odometry_gain": (2,),
}
FIELD_SHAPES = {name: _VECTOR_SHAPES.get(name, ()) for name in Params._fields}
_SHAPE_MEANING = {
    "rot1_noise": "coefficients (trans, rot, const)",
    "trans_noise": "coefficients (trans, rot, const)",
    "rot2_noise": "coefficients (trans, rot, const)",
    "range_noise": "coefficients (per metre, const)",
    "bearing_noise": "coefficients (per metre, const)",
    "odometry_gain": "gains (translation, rotation)",
}

# Per-field rules: (kind, expectation text). Kinds: "nonneg" (finite, >= 0), "positive"
# (finite, > 0), "finite", "unit" ([0, 1]), "open_low_unit" ((0, 1]), "unit_open_high"
# ([0, 1)), "nonneg_or_inf" (>= 0, +inf allowed).
_RULES = {
    "rot1_noise": "nonneg", "trans_noise": "nonneg", "rot2_noise": "nonneg",
    "motion_outlier_probability": "unit_open_high",
    "motion_outlier_scale": "positive",
    "min_translation": "positive",
    "odometry_gain": "positive",
    "wheelbase": "positive",
    "encoder_offset": "finite", "laser_forward": "finite", "laser_left": "finite",
    "range_noise": "nonneg", "bearing_noise": "nonneg",
    "range_std_floor": "nonneg", "bearing_std_floor": "nonneg",
    "radius_noise": "nonneg",
    "max_range": "positive",
    "min_range": "nonneg",
    "miss_range": "nonneg_or_inf",
    "miss_bearing": "positive",
    "association_gate": "positive",
    "association_heading_std": "nonneg",
    "new_landmark_log_offset": "finite",
    "detection_probability": "open_low_unit",
    "false_alarm_probability": "unit_open_high",
    "existence_init": "finite",
    "existence_delete": "finite",
    "existence_max": "positive",
    "airlock_sigmas": "nonneg",
    "ess_threshold": "unit",
    "mixture_ratio": "unit",
    "mixture_min": "unit",
    "mixture_max": "unit",
    "likelihood_rate_fast": "unit",
    "likelihood_rate_slow": "unit",
}
_EXPECT = {
    "nonneg": "a finite value >= 0",
    "positive": "a finite value > 0",
    "finite": "a finite value",
    "unit": "a value in [0, 1]",
    "open_low_unit": "a value in (0, 1]",
    "unit_open_high": "a value in [0, 1)",
    "nonneg_or_inf": "a value >= 0 (+inf allowed)",
}
assert set(_RULES) == set(Params._fields)


def _ok(kind: str, x: np.ndarray) -> np.ndarray:
    """Boolean mask of the entries of ``x`` (float64) that satisfy rule ``kind``."""
    finite = np.isfinite(x)
    with np.errstate(invalid="ignore"):
        if kind == "nonneg":
            return finite & (x >= 0)
        if kind == "positive":
            return finite & (x > 0)
        if kind == "finite":
            return finite
        if kind == "unit":
            return finite & (x >= 0) & (x <= 1)
        if kind == "open_low_unit":
            return finite & (x > 0) & (x <= 1)
        if kind == "unit_open_high":
            return finite & (x >= 0) & (x < 1)
        if kind == "nonneg_or_inf":
            return ~np.isnan(x) & (x >= 0)
    raise AssertionError(kind)


def _show(x) -> str:
    """Short text of a number or small array in its own dtype (0.1, not 0.10000000149)."""
    x = np.asarray(x)
    return str(x[()]) if x.ndim == 0 else np.array2string(x, separator=", ", threshold=20)


def _first_bad(mask: np.ndarray):
    """Index tuple of the first False entry of ``mask``."""
    return tuple(int(i) for i in np.argwhere(~mask)[0])


def _describe(array: np.ndarray, index: tuple, batch_ndim: int, vector: bool) -> str:
    """The bad value, plus where it sits when the leaf is a vector or batched."""
    value = _show(array[index])
    if array.ndim == 0:
        return value
    parts = []
    if batch_ndim:
        parts.append(f"sweep condition {index[:batch_ndim]}")
    if vector:
        parts.append(f"component {index[-1]}")
    return f"{value} ({', '.join(parts)})"


def _as_numeric(where: str, name: str, value) -> np.ndarray:
    try:
        array = np.asarray(value)
    except Exception as error:  # noqa: BLE001 - anything unconvertible is refused by name
        raise ValueError(f"{where}.{name}={value!r} is not an array ({error}); expected a real "
                         "number") from error
    if array.dtype.kind not in "fiu":
        raise ValueError(f"{where}.{name}={value!r} has dtype {array.dtype}; expected a real "
                         "number (float or int)")
    return array


def check_params(params: Params, where: str = "Params", allow_batch: bool = True) -> None:
    """Raise ``ValueError`` for an impossible ``Params``; return None when every rule holds.

    Leaves that are JAX tracers are skipped silently (so this is a no-op inside ``jit``);
    rules that compare two fields are skipped when either is a tracer. The message names the
    field (``where.field``), the bad value (with its sweep condition and component when the
    leaf is batched or a vector) and what is expected.

    Rules (every value must be a real number: float or int dtype, never bool or complex):

    Shapes: ``rot1_noise``, ``trans_noise``, ``rot2_noise`` end in (3,); ``range_noise`` and
      ``bearing_noise`` end in (2,); every other field is a scalar. With ``allow_batch``
      (default) leading axes are allowed, for a stacked sweep ``Params`` (a vmap axis);
      ``default_params`` passes False, so a scalar given for a 3-vector, or a tuple for a
      scalar, is refused there.
    Motion noise: ``rot1_noise``, ``trans_noise``, ``rot2_noise`` finite and >= 0 (all zero
      is a noise-free motion model). ``min_translation`` finite and > 0 (it bounds the
      Jacobian 1 / trans of the motion density; 0 gives log(0) for a stationary robot).
      ``wheelbase`` finite and > 0 (it divides the Ackermann yaw rate); ``encoder_offset``,
      ``laser_forward``, ``laser_left`` finite (offsets of either sign).
    Observation noise: ``range_noise``, ``bearing_noise``, ``range_std_floor``,
      ``bearing_std_floor``, ``radius_noise`` finite and >= 0. Cross-field: the range and the
      bearing std at distance 0, max(c_const, floor), must be > 0 (the std is evaluated at
      every predicted range, however near), or the covariance is singular (log det = -inf).
    Sensor: ``max_range`` finite and > 0; ``min_range`` finite, >= 0 and < ``max_range``;
      ``miss_range`` >= 0, +inf allowed (the default: every matchable landmark may be missed),
      NaN refused.
    Association and map: ``association_gate`` finite and > 0 (+inf would credit every new
      landmark log-likelihood -inf); ``new_landmark_log_offset``, ``existence_init``,
      ``existence_delete`` finite; ``existence_max`` finite and > 0; ``airlock_sigmas``
      finite and >= 0 (0 makes the loose boundary act like the hard one).
      ``detection_probability`` in (0, 1] and ``false_alarm_probability`` in [0, 1) (the
      log-odds log(pd / pf) and log((1 - pd) / (1 - pf)) are then never 0 / 0 = NaN), and
      ``false_alarm_probability`` <= ``detection_probability`` (else a match lowers a
      landmark's existence; equal values switch existence evidence off).
      Cross-field: ``existence_delete`` < ``existence_init`` (else a landmark is deleted as
      soon as it is born) and -``existence_max`` < ``existence_delete`` (log-odds are clipped
      to [-existence_max, existence_max], so a lower threshold would never delete anything).
    Resampling: ``ess_threshold`` in [0, 1] (0 never resamples, 1 always).
    Mixture proposal: ``mixture_ratio``, ``mixture_min``, ``mixture_max``,
      ``likelihood_rate_fast``, ``likelihood_rate_slow`` in [0, 1] (they were silently
      clipped before); ``mixture_min`` <= ``mixture_max``.

    Args:
      params: a ``Params`` (leaves: JAX or NumPy arrays, Python numbers or tuples).
      where: prefix of the field names in messages, e.g. "Params" or "default_params".
      allow_batch: accept leading (sweep) axes in front of each field's shape.
    Raises:
      TypeError: ``params`` is not a ``Params``.
      ValueError: a rule fails.
    """
    if not isinstance(params, Params):
        raise TypeError(f"{where}: expected a jaxslam.types.Params; got {type(params).__name__}")
    values: dict[str, np.ndarray] = {}
    for name in Params._fields:
        leaf = getattr(params, name)
        if is_tracer(leaf):
            continue
        array = _as_numeric(where, name, leaf)
        expected = FIELD_SHAPES[name]
        trailing = array.shape[array.ndim - len(expected):] if array.ndim >= len(expected) else None
        shape_ok = trailing == expected and (allow_batch or array.ndim == len(expected))
        if not shape_ok:
            what = f"shape {expected}" + (f", {_SHAPE_MEANING[name]}" if name in _SHAPE_MEANING
                                          else " (a scalar)")
            batch = " with optional leading sweep axes" if allow_batch else ""
            raise ValueError(f"{where}.{name} has shape {array.shape} (value {_show(array)}); "
                             f"expected {what}{batch}")
        kind = _RULES[name]
        ok = _ok(kind, array.astype(np.float64))
        if not ok.all():
            index = _first_bad(ok)
            bad = _describe(array, index, array.ndim - len(expected), bool(expected))
            raise ValueError(f"{where}.{name}={bad} is invalid; expected {_EXPECT[kind]}")
        values[name] = array
    _check_cross_fields(values, where)


def _pair(values, first, second):
    """The two fields broadcast together, or None when either is traced or they don't fit."""
    if first not in values or second not in values:
        return None
    try:
        return np.broadcast_arrays(values[first], values[second])
    except ValueError:
        return None


def _fail_pair(where, first, a, second, b, ok, rule):
    index = _first_bad(ok)
    at = f" (sweep condition {index})" if ok.ndim else ""
    raise ValueError(f"{where}.{first}={_show(a[index])} and {where}.{second}="
                     f"{_show(b[index])}{at} are invalid; expected {rule}")


def _check_cross_fields(values: dict, where: str) -> None:
    for first, second, test, rule in (
            ("min_range", "max_range", np.less, "min_range < max_range"),
            ("mixture_min", "mixture_max", np.less_equal, "mixture_min <= mixture_max"),
            ("false_alarm_probability", "detection_probability", np.less_equal,
             "false_alarm_probability <= detection_probability (a match is evidence for a "
             "landmark)"),
            ("existence_delete", "existence_init", np.less,
             "existence_delete < existence_init (else a landmark is deleted at birth)")):
        pair = _pair(values, first, second)
        if pair is not None and not (ok := test(*pair)).all():
            _fail_pair(where, first, pair[0], second, pair[1], ok, rule)
    pair = _pair(values, "existence_delete", "existence_max")
    if pair is not None and not (ok := pair[0] > -pair[1]).all():
        _fail_pair(where, "existence_delete", pair[0], "existence_max", pair[1], ok,
                   "existence_delete > -existence_max (log-odds are clipped to "
                   "[-existence_max, existence_max]; a lower threshold never deletes)")
    for noise, floor in (("range_noise", "range_std_floor"),
                         ("bearing_noise", "bearing_std_floor")):
        if noise not in values or floor not in values:
            continue
        try:
            constant, floors = np.broadcast_arrays(values[noise][..., 1], values[floor])
        except ValueError:
            continue
        if not (ok := np.maximum(constant, floors) > 0).all():
            index = _first_bad(ok)
            at = f" (sweep condition {index})" if ok.ndim else ""
            raise ValueError(
                f"{where}.{noise} constant term {_show(constant[index])} and {where}.{floor}="
                f"{_show(floors[index])}{at} give a zero std at distance 0; expected the "
                f"constant term or {floor} > 0 (a zero std makes the covariance singular)")
