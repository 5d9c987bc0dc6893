"""Value rules of study config keys, shared by the study config and the simulator plugins that
validate their own [scenario] section (``jaxslam.simulators``), so every refused value reads
the same: "study config SECTION.KEY=VALUE is invalid; expected ...".

A rule is a ``Rule`` (kind, lower bound, bound included) with kind "int", "float" or "str".
Only the standard library is imported here.
"""
from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

MAX_SEED = 2**32  # fold_in(PRNGKey(seed), run) keys: an unsigned 32-bit seed


class Rule(NamedTuple):
    """kind: "int", "float" or "str"; low: the lower bound (None: none); inclusive: whether
    ``low`` itself is allowed."""

    kind: str
    low: float | None = None
    inclusive: bool | None = None


def describe(rule) -> str:
    """What a rule accepts, in words: "a positive integer (>= 1)", "a number > 0", ..."""
    kind, low, inclusive = rule
    if kind == "str":
        return "a string"
    what = "an integer" if kind == "int" else "a number"
    if low is None:
        return what
    if kind == "int" and low == 1 and inclusive:
        return "a positive integer (>= 1)"
    return f"{what} {'>=' if inclusive else '>'} {low:g}"


def value_error(section: str, key: str, value, rule) -> ValueError:
    """The error for ``section.key = value`` breaking ``rule`` (section "" for a study key)."""
    where = f"{section}.{key}" if section else key
    hint = ""
    if isinstance(value, str) and rule[0] != "str":
        hint = " (a string: write numbers without quotes)"
    return ValueError(f"study config {where}={value!r} is invalid; expected "
                      f"{describe(rule)}{hint}")


def check_value(section: str, key: str, value, rule) -> None:
    """Raise ``value_error`` unless ``value`` has the rule's kind and bound (finite floats;
    booleans are not numbers). The study seed must also fit in 32 bits."""
    kind, low, inclusive = rule
    if kind == "str":
        if not isinstance(value, str):
            raise value_error(section, key, value, rule)
        return
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise value_error(section, key, value, rule)
    if kind == "int" and not isinstance(value, int):
        raise value_error(section, key, value, rule)
    if kind == "float" and not math.isfinite(value):
        raise value_error(section, key, value, rule)
    if low is not None and (value < low or (value == low and not inclusive)):
        raise value_error(section, key, value, rule)
    if section == "" and key == "seed" and value >= MAX_SEED:
        raise ValueError(f"study config seed={value!r} is invalid; expected an integer in "
                         f"[0, {MAX_SEED})")


def check_fields(section: str, config, rules: dict) -> None:
    """``check_value`` of every ruled field of the dataclass ``config``."""
    for key, rule in rules.items():
        check_value(section, key, getattr(config, key), rule)


def normalise(section: str, given: dict, rules: dict) -> dict:
    """Check every given value against its rule; integers given for floats become floats."""
    out = {}
    for key, value in given.items():
        rule = rules[key]
        check_value(section, key, value, rule)
        out[key] = float(value) if rule[0] == "float" else value
    return out


def check_keys(section: str, given: dict, cls) -> None:
    """Refuse a key of ``given`` that is not a field of the dataclass ``cls``, listing the
    allowed keys."""
    allowed = [f.name for f in dataclasses.fields(cls)]
    for key in given:
        if key not in allowed:
            where = f"{section}.{key}" if section else key
            raise ValueError(f"unknown study config key {where!r}; allowed keys"
                             f"{' in [' + section + ']' if section else ''}: {allowed}")


def check_choices(section: str, given: dict, choices: dict) -> None:
    """Refuse a value of ``given`` outside its key's allowed choices (key -> tuple)."""
    for key, allowed in choices.items():
        if key in given and given[key] not in allowed:
            raise ValueError(f"{section}.{key}={given[key]!r} is not supported; expected one "
                             f"of {list(allowed)}")
