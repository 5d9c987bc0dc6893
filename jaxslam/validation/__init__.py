"""Host-side checks at the public entry points, before any tracing.

The jitted filter cannot raise, so what a user gives it is checked on the host and refused (or
warned about) in words that name the field, the bad value and what is expected:

  ``params``  ``check_params``: every ``Params`` field's shape and range, and the rules that
              tie two fields together (``run_filter`` and ``default_params`` call it).
  ``inputs``  ``check_controls`` (a finite (T, 3) float array), ``cast_floating`` (mixed float
              inputs meet in one dtype) and ``is_tracer``.
  ``units``   ``observation_units_warnings`` / ``check_observation_units``: observations in
              degrees, millimetres or otherwise malformed.
"""
from jaxslam.validation.inputs import cast_floating, check_controls, is_tracer
from jaxslam.validation.params import FIELD_SHAPES, check_params
from jaxslam.validation.units import check_observation_units, observation_units_warnings

__all__ = ["FIELD_SHAPES", "cast_floating", "check_controls", "check_observation_units",
           "check_params", "is_tracer", "observation_units_warnings"]
