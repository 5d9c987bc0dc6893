"""Host-side checks of ``Params`` and controls at the public entry points.

The jitted filter cannot raise: a NaN gate or a negative noise coefficient there only turns
into NaN poses and maps many steps later. ``check_params`` and ``check_controls`` run on the
host, before any tracing (``run_filter`` and ``default_params`` call them), and raise a
``ValueError`` that names the field, the bad value and what is expected. Leaves that are JAX
tracers (inside ``jit`` / ``vmap``) have no value to check and are skipped silently.

``cast_floating`` casts every floating leaf of a pytree to one dtype: ``run_filter`` uses it so
float32 and float64 inputs mixed across params, controls and observations meet in the
controls' dtype instead of failing deep inside ``lax.scan``.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jaxslam.types import Params

# Trailing shape of every Params field (leading batch axes allowed for stacked sweeps).
_VECTOR_SHAPES = {
    "rot1_noise": (3,), "trans_noise": (3,), "rot2_noise": (3,),
    "range_noise": (2,), "bearing_noise": (2,),
}
FIELD_SHAPES = {name: _VECTOR_SHAPES.get(name, ()) for name in Params._fields}
_SHAPE_MEANING = {
    "rot1_noise": "coefficients (trans, rot, const)",
    "trans_noise": "coefficients (trans, rot, const)",
    "rot2_noise": "coefficients (trans, rot, const)",
    "range_noise": "coefficients (per metre, const)",
    "bearing_noise": "coefficients (per metre, const)",
}

# Per-field rules: (kind, expectation text). Kinds: "nonneg" (finite, >= 0), "positive"
# (finite, > 0), "finite", "unit" ([0, 1]), "open_low_unit" ((0, 1]), "unit_open_high"
# ([0, 1)), "nonneg_or_inf" (>= 0, +inf allowed).
_RULES = {
    "rot1_noise": "nonneg", "trans_noise": "nonneg", "rot2_noise": "nonneg",
    "motion_outlier_probability": "unit_open_high",
    "motion_outlier_scale": "positive",
    "min_translation": "positive",
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


def is_tracer(x) -> bool:
    """True for a JAX tracer (a value inside ``jit``/``vmap``/``grad`` with no concrete value)."""
    return isinstance(x, jax.core.Tracer)


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


__all__ = ["FIELD_SHAPES", "cast_floating", "check_controls", "check_params", "is_tracer"]


# --- Units guard (issue 18) ------------------------------------------------------------------
# Observations are (range [m], bearing [rad]). A log in other units loads fine and then every
# row is masked or ignored inside the filter, so the run "succeeds" with an empty map. These
# host-side checks look at the rows marked valid and say so in words, before the filter runs.
#
# Rules (all on the rows marked valid; none fire when there are no such rows):
#   malformed: a row is malformed when a value is NaN/inf, the range is <= 0, or the bearing is
#     outside [-pi, pi]. More than half malformed is a warning (with the counts per kind);
#     every row malformed is a refusal in ``check_observation_units``.
#   degrees: of the finite bearings, at least 10 % have |bearing| > pi and the 99th percentile
#     of |bearing| lies in (2 pi, 360] -- beyond any radian convention ([-pi, pi] or [0, 2 pi])
#     but within a degree circle. Certain (refusal) when, in addition, at least half of the
#     finite bearings have |bearing| > pi.
#   [0, 2 pi]: at least 10 % of the finite bearings exceed pi, none is negative and all are
#     <= 2 pi: radians measured from 0 to 2 pi instead of -pi to pi.
#   millimetres / centimetres: a forestry lidar sees trunks at about 5-80 m, so a median
#     positive finite range above 100 m is a warning; the message names which of millimetres
#     (median / 1000) or centimetres (median / 100) turn the median into a plausible 1-100 m.
#     A median above 1000 m is certain (refusal). With ``max_range`` given (finite, > 0), a
#     median above 10 * max_range is also a warning (most rows would be ignored as too far).
_EXPECTED_UNITS = "expected ranges in metres and bearings in radians in [-pi, pi]"
_DEGREE_SHARE = 0.10          # share of |bearing| > pi that starts the degree/[0, 2pi] rules
_CERTAIN_SHARE = 0.50         # share of |bearing| > pi that makes degrees certain
_MALFORMED_SHARE = 0.50       # share of malformed valid rows that is a warning
_FAR_MEDIAN = 100.0           # [m] median range above which the units look wrong
_CERTAIN_MEDIAN = 1000.0      # [m] median range above which the units are certainly wrong
_PLAUSIBLE_MEDIAN = (1.0, 100.0)  # [m] a plausible median range after conversion
_MAX_RANGE_FACTOR = 10.0      # median above this many max_range is a warning


def _units_facts(z, valid) -> dict:
    """Counts and statistics behind the units rules (see the comment above)."""
    z = np.asarray(z, np.float64)
    if z.ndim < 1 or z.shape[-1] != 2:
        raise ValueError(f"observations z must have shape (..., 2); got {z.shape}")
    valid = np.broadcast_to(np.asarray(valid, bool), z.shape[:-1])
    rows = z[valid].reshape(-1, 2)
    r, b = rows[:, 0], rows[:, 1]
    nonfinite = ~np.isfinite(rows).all(-1)
    with np.errstate(invalid="ignore"):
        bad_range = ~nonfinite & (r <= 0)
        bad_bearing = ~nonfinite & (np.abs(b) > np.pi)
    facts = dict(n=len(rows), nonfinite=int(nonfinite.sum()), bad_range=int(bad_range.sum()),
                 bad_bearing=int(bad_bearing.sum()),
                 malformed=int((nonfinite | bad_range | bad_bearing).sum()))
    fb = b[np.isfinite(b)]
    facts["n_bearing"] = len(fb)
    if len(fb):
        beyond = np.abs(fb) > np.pi
        facts.update(beyond=int(beyond.sum()), beyond_share=float(beyond.mean()),
                     b_p99=float(np.quantile(np.abs(fb), 0.99)), b_min=float(fb.min()),
                     b_max=float(fb.max()))
        facts["degrees"] = (facts["beyond_share"] >= _DEGREE_SHARE
                            and 2 * np.pi < facts["b_p99"] <= 360.0)
        facts["two_pi"] = (facts["beyond_share"] >= _DEGREE_SHARE and facts["b_min"] >= 0
                           and facts["b_max"] <= 2 * np.pi)
    else:
        facts.update(degrees=False, two_pi=False)
    fr = r[np.isfinite(r) & (r > 0)]
    facts["median_range"] = float(np.median(fr)) if len(fr) else None
    facts["max_seen_range"] = float(fr.max()) if len(fr) else None
    return facts


def _range_units_guess(median: float) -> str:
    low, high = _PLAUSIBLE_MEDIAN
    names = [f"{unit} (median {median / scale:.3g} m)"
             for unit, scale in (("millimetres", 1000.0), ("centimetres", 100.0))
             if low <= median / scale <= high]
    return " or ".join(names) if names else "a unit other than metres"


def observation_units_warnings(z, valid, max_range=None) -> list[str]:
    """Plain-word warnings that a log's observations are in the wrong units or malformed.

    Host-side NumPy check of the rows marked ``valid`` (rules in the comment above this
    function in ``jaxslam/validation.py``); each message names the numbers behind it and what
    is expected. Returns ``[]`` for a good log, and for a log with no valid row.

    Args:
      z: (..., K, 2) observations (range, bearing).
      valid: (..., K) bool mask of the rows that are observations.
      max_range: optional usable range [m] of the filter; a median range far beyond it warns.
    """
    f = _units_facts(z, valid)
    n = f["n"]
    if n == 0:
        return []
    warnings = []
    if f["degrees"]:
        warnings.append(
            f"bearings look like degrees: {f['beyond']} of {f['n_bearing']} "
            f"({100 * f['beyond_share']:.0f}%) have |bearing| > pi and the largest reach "
            f"{max(abs(f['b_min']), abs(f['b_max'])):.4g} (99th percentile "
            f"{f['b_p99']:.4g}), within 360; {_EXPECTED_UNITS} (multiply degrees by pi/180)")
    elif f["two_pi"]:
        warnings.append(
            f"bearings look like radians in [0, 2 pi]: {f['beyond']} of {f['n_bearing']} "
            f"({100 * f['beyond_share']:.0f}%) are above pi, none is negative and the largest "
            f"is {f['b_max']:.4g}; {_EXPECTED_UNITS} (subtract 2 pi from those above pi)")
    median = f["median_range"]
    if median is not None:
        far = median > _FAR_MEDIAN
        beyond_max = (max_range is not None and np.isfinite(float(max_range))
                      and float(max_range) > 0
                      and median > _MAX_RANGE_FACTOR * float(max_range))
        if far or beyond_max:
            reason = (f"a forestry lidar sees trunks at about 5-80 m; these look like "
                      f"{_range_units_guess(median)}" if far else
                      f"more than {_MAX_RANGE_FACTOR:.0f} times max_range "
                      f"{float(max_range):.4g} m, so most would be ignored as too far")
            warnings.append(
                f"ranges look wrong: the median valid range is {median:.4g} m (largest "
                f"{f['max_seen_range']:.4g} m), {reason}; {_EXPECTED_UNITS}")
    if f["malformed"] > _MALFORMED_SHARE * n:
        share = 100 * f["malformed"] / n
        head = (f"all {n} observations marked valid are malformed" if f["malformed"] == n else
                f"{f['malformed']} of {n} observations marked valid ({share:.0f}%) are "
                "malformed")
        warnings.append(
            f"{head} ({f['nonfinite']} NaN or inf, {f['bad_range']} with a range <= 0, "
            f"{f['bad_bearing']} with a bearing outside [-pi, pi]) and will be masked; "
            f"{_EXPECTED_UNITS}")
    return warnings


def check_observation_units(z, valid) -> None:
    """Raise ``ValueError`` when a log's observations are certainly unusable as given.

    Refuses when every row marked valid is malformed (NaN/inf, range <= 0 or bearing outside
    [-pi, pi]), when the bearings look like degrees with at least half beyond pi, or when the
    median valid range is above 1000 m. The message is the matching
    ``observation_units_warnings`` text. A log with no valid row passes (nothing to judge).
    """
    f = _units_facts(z, valid)
    if f["n"] == 0:
        return
    certain = (f["malformed"] == f["n"]
               or (f["degrees"] and f["beyond_share"] >= _CERTAIN_SHARE)
               or (f["median_range"] is not None and f["median_range"] > _CERTAIN_MEDIAN))
    if certain:
        raise ValueError("; ".join(observation_units_warnings(z, valid))
                         + " -- refusing to run on these observations")


__all__ += ["check_observation_units", "observation_units_warnings"]
