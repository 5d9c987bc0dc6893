"""Study configuration: the simulated scenario and the study (runs, chunks, filter, sweeps),
read from TOML with "section.key=value" overrides; every error names the key and the allowed
values. Used by ``jaxslam.studies`` and the ``jaxslam`` command.
"""
from __future__ import annotations

import dataclasses
import itertools
import math
import pathlib
import tomllib
from typing import Any, NamedTuple

import jax.numpy as jnp

from jaxslam.types import FilterConfig, Params, default_params

_SECTIONS = ("filter", "scenario", "params", "sweep")


# --------------------------------------------------------------------------------------------
# Value rules: (kind, lower bound, bound included); kinds "int", "float", "str"

_STUDY_RULES = {
    "name": ("str", None, None),
    "num_runs": ("int", 1, True),
    "chunk_size": ("int", 1, True),
    "run_width": ("int", 1, True),
    "seed": ("int", 0, True),
    "divergence_threshold": ("float", 0.0, False),
    "map_match_threshold": ("float", 0.0, False),
    "gospa_cutoff": ("float", 0.0, False),
}
_SCENARIO_RULES = {
    "forest": ("str", None, None),
    "num_trees": ("int", 1, True),
    "size": ("float", 0.0, False),
    "path": ("str", None, None),
    "num_steps": ("int", 1, True),
    "step_length": ("float", 0.0, False),
    "max_range": ("float", 0.0, False),
    "observation_source": ("str", None, None),
    "detection": ("str", None, None),
    "odometry_noise_scale": ("float", 0.0, True),
    "world": ("str", None, None),
}
_MAX_SEED = 2**32  # fold_in(PRNGKey(seed), run) keys: an unsigned 32-bit seed


def _describe(rule) -> str:
    kind, low, inclusive = rule
    if kind == "str":
        return "a string"
    what = "an integer" if kind == "int" else "a number"
    if low is None:
        return what
    if kind == "int" and low == 1 and inclusive:
        return "a positive integer (>= 1)"
    return f"{what} {'>=' if inclusive else '>'} {low:g}"


def _value_error(section: str, key: str, value, rule) -> ValueError:
    where = f"{section}.{key}" if section else key
    hint = ""
    if isinstance(value, str) and rule[0] != "str":
        hint = " (a string: write numbers without quotes)"
    return ValueError(f"study config {where}={value!r} is invalid; expected "
                      f"{_describe(rule)}{hint}")


def _check_value(section: str, key: str, value, rule) -> None:
    kind, low, inclusive = rule
    if kind == "str":
        if not isinstance(value, str):
            raise _value_error(section, key, value, rule)
        return
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise _value_error(section, key, value, rule)
    if kind == "int" and not isinstance(value, int):
        raise _value_error(section, key, value, rule)
    if kind == "float" and not math.isfinite(value):
        raise _value_error(section, key, value, rule)
    if low is not None and (value < low or (value == low and not inclusive)):
        raise _value_error(section, key, value, rule)
    if section == "" and key == "seed" and value >= _MAX_SEED:
        raise ValueError(f"study config seed={value!r} is invalid; expected an integer in "
                         f"[0, {_MAX_SEED})")


def _check_fields(section: str, config, rules: dict) -> None:
    for key, rule in rules.items():
        _check_value(section, key, getattr(config, key), rule)


def _normalise(section: str, given: dict, rules: dict) -> dict:
    """Check every given value against its rule; integers given for floats become floats."""
    out = {}
    for key, value in given.items():
        rule = rules[key]
        _check_value(section, key, value, rule)
        out[key] = float(value) if rule[0] == "float" else value
    return out


def _check_filter_types(section: dict) -> None:
    """Types of [filter] values, by the type of each field's default (``FilterConfig``
    checks the ranges and choices)."""
    defaults = {f.name: f.default for f in dataclasses.fields(FilterConfig)}
    for key, value in section.items():
        default = defaults[key]
        if isinstance(default, bool):
            ok, what = isinstance(value, bool), "true or false"
        elif isinstance(default, int):
            ok, what = isinstance(value, int) and not isinstance(value, bool), "an integer"
        elif isinstance(default, str):
            ok, what = isinstance(value, str), "a string"
        else:
            continue
        if not ok:
            raise ValueError(f"study config filter.{key}={value!r} is invalid; expected {what}")


def _check_param_value(where: str, key: str, value, base: dict) -> None:
    """A Params value must be a number or a flat list of numbers; then ``default_params``
    checks its shape and range."""
    items = list(value) if isinstance(value, (list, tuple)) else [value]
    for item in items:
        if isinstance(item, bool) or not isinstance(item, (int, float)):
            raise ValueError(f"study config {where}={value!r} is invalid; expected a number "
                             "(or, for a vector field, a list of numbers)")
    try:
        default_params(None, **{**base, key: value})
    except (ValueError, TypeError) as error:
        raise ValueError(f"study config {where}={value!r} is refused: {error}") from None


_SCENARIO_CHOICES = {"forest": ("random", "plantation"), "path": ("loop", "lawnmower", "random"),
                     "observation_source": ("analytic", "lidar"),
                     "detection": ("centroid", "kasa", "geometric", "ransac"),
                     "world": ("shared", "per_run")}


def _check_scenario(section: dict) -> None:
    for key, allowed in _SCENARIO_CHOICES.items():
        if key in section and section[key] not in allowed:
            raise ValueError(f"scenario.{key}={section[key]!r} is not supported; expected one of "
                             f"{list(allowed)}")


@dataclasses.dataclass(frozen=True)
class ScenarioConfig:
    """The simulated world of every run (see ``sims.scenario``).

    forest: "random" or "plantation"; num_trees; size: square side [m]; path: "loop",
    "lawnmower" or "random"; num_steps: T; step_length [m]; max_range [m] of the sensor;
    observation_source: "analytic" (range-bearing to trunk centres with Table 2 noise) or
    "lidar" (MJX scans + trunk detection); detection: centroid | kasa | geometric | ransac;
    odometry_noise_scale: multiplies the Table 1 noise of the simulated odometry.
    world: "shared" (every run follows one path through one forest, drawn from the seed:
    runs differ in noise only, for paired comparisons) or "per_run" (run i draws its own
    forest and path from its run key: the spread over worlds is part of every metric;
    analytic observations only).
    """

    forest: str = "random"
    num_trees: int = 80
    size: float = 60.0
    path: str = "loop"
    num_steps: int = 200
    step_length: float = 0.5
    max_range: float = 20.0
    observation_source: str = "analytic"
    detection: str = "kasa"
    odometry_noise_scale: float = 1.0
    world: str = "shared"

    def __post_init__(self):
        _check_fields("scenario", self, _SCENARIO_RULES)
        _check_scenario(dataclasses.asdict(self))
        if self.world == "per_run" and self.observation_source != "analytic":
            raise ValueError("scenario.world='per_run' needs scenario.observation_source="
                             "'analytic' (lidar scans are cast in one MJX model of a shared "
                             "forest); use world='shared' for lidar studies")


@dataclasses.dataclass(frozen=True)
class StudyConfig:
    """Everything that defines a study. ``params`` are overrides of ``default_params``;
    ``sweep`` maps Params fields to lists of values (cartesian grid of conditions).

    chunk_size: runs per result file (the unit of resume). run_width: (run, condition) pairs
    per compiled filter call and per device, fixed for the whole study: every chunk is cut
    into groups of run_width pairs (the last padded), so a run's numbers never depend on the
    chunk size, the number of runs or of sweep conditions, or the device count. 1 (the
    default) is the fastest on a CPU; on a GPU choose e.g. 64-256 for throughput.
    """

    name: str = "study"
    num_runs: int = 100
    chunk_size: int = 50
    run_width: int = 1
    seed: int = 0
    filter: FilterConfig = FilterConfig()
    scenario: ScenarioConfig = ScenarioConfig()
    params: tuple = ()
    sweep: tuple = ()
    divergence_threshold: float = 2.0
    map_match_threshold: float = 1.0
    gospa_cutoff: float = 2.0

    def __post_init__(self):
        _check_fields("", self, _STUDY_RULES)
        for name, cls in (("filter", FilterConfig), ("scenario", ScenarioConfig)):
            if not isinstance(getattr(self, name), cls):
                raise ValueError(f"study {name}={getattr(self, name)!r}; expected a "
                                 f"{cls.__name__}")
        params_fields = set(Params._fields)
        for section, items in (("params", self.params), ("sweep", self.sweep)):
            for key, _ in items:
                if key not in params_fields:
                    raise ValueError(f"{section}.{key} is not a filter parameter; expected one "
                                     f"of {sorted(params_fields)}")
        self._check_param_values()

    def _check_param_values(self) -> None:
        """Every fixed and swept parameter value as ``default_params`` would see it (the
        types, shapes and ranges of ``validation.check_params``), so a bad value is refused
        when the config is read, before any folder is written."""
        base = {"max_range": self.scenario.max_range}
        for key, value in self.params:
            _check_param_value(f"params.{key}", key, value, base)
            base[key] = value
        for key, values in self.sweep:
            for index, value in enumerate(values):
                _check_param_value(f"sweep.{key}[{index}]", key, value, base)
        for condition in self.conditions:  # rules between fields (e.g. min < max range)
            try:
                default_params(self.filter, **{**base, **condition})
            except (ValueError, TypeError) as error:
                where = ", ".join(f"{k}={v!r}" for k, v in condition.items())
                raise ValueError(f"the filter parameters{' of condition ' + where if where else ''}"
                                 f" are refused: {error}") from None

    @property
    def conditions(self) -> list[dict[str, Any]]:
        """The sweep grid as a list of {param: value} (one empty dict without a sweep)."""
        if not self.sweep:
            return [{}]
        names = [name for name, _ in self.sweep]
        values = [list(vals) for _, vals in self.sweep]
        return [dict(zip(names, combo)) for combo in itertools.product(*values)]


# --------------------------------------------------------------------------------------------
# Config files


def _as_tuple_items(mapping: dict) -> tuple:
    return tuple((k, tuple(v) if isinstance(v, list) else v) for k, v in mapping.items())


def study_config_to_dict(config: StudyConfig) -> dict:
    """Plain dict (TOML-ready) of a study config."""
    out = {f.name: getattr(config, f.name) for f in dataclasses.fields(config)
           if f.name not in ("filter", "scenario", "params", "sweep")}
    out["filter"] = dataclasses.asdict(config.filter)
    out["scenario"] = dataclasses.asdict(config.scenario)
    out["params"] = {k: list(v) if isinstance(v, tuple) else v for k, v in config.params}
    out["sweep"] = {k: list(v) for k, v in config.sweep}
    return out


def _check_keys(section: str, given: dict, cls) -> None:
    allowed = [f.name for f in dataclasses.fields(cls)]
    for key in given:
        if key not in allowed:
            where = f"{section}.{key}" if section else key
            raise ValueError(f"unknown study config key {where!r}; allowed keys"
                             f"{' in [' + section + ']' if section else ''}: {allowed}")


def study_config_from_dict(data: dict) -> StudyConfig:
    """Build and validate a ``StudyConfig``; errors name the key and the allowed values.

    Every value is type-checked here (a string where a number belongs, a float seed, a
    count below 1...), before anything is written; a float field given as an integer is
    stored as a float, so ``size = 30`` and ``size = 30.0`` are the same study.
    """
    data = dict(data)
    sections = {}
    for name in _SECTIONS:
        section = data.pop(name, {})
        if not isinstance(section, dict):
            raise ValueError(f"{name} must be a [{name}] section of key = value lines; got "
                             f"{name} = {section!r}")
        sections[name] = dict(section)
    _check_keys("", data, StudyConfig)
    for key, value in data.items():
        if isinstance(value, dict):
            raise ValueError(f"{key!r} is not a section of a study config (sections: "
                             f"{list(_SECTIONS)}); {key} is a single value: {key} = ...")
    _check_keys("filter", sections["filter"], FilterConfig)
    _check_keys("scenario", sections["scenario"], ScenarioConfig)
    _check_scenario(sections["scenario"])
    _check_filter_types(sections["filter"])
    for key, values in sections["sweep"].items():
        if not isinstance(values, list) or not values:
            raise ValueError(f"sweep.{key} must be a non-empty list of values; got {values!r}")
    for name, value in sections["params"].items():
        if isinstance(value, dict):
            raise ValueError(f"params.{name} must be a number or a list of numbers; got a "
                             f"section {value!r}")
    data = _normalise("", data, _STUDY_RULES)
    return StudyConfig(filter=FilterConfig(**sections["filter"]),
                       scenario=ScenarioConfig(**_normalise("scenario", sections["scenario"],
                                                            _SCENARIO_RULES)),
                       params=_as_tuple_items(sections["params"]),
                       sweep=_as_tuple_items(sections["sweep"]), **data)


def _parse_value(text: str):
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text


def load_study_config(path=None, overrides=()) -> StudyConfig:
    """Read a study TOML (or start from the defaults) and apply "section.key=value" overrides.

    Example overrides: ``num_runs=20``, ``filter.num_particles=50``, ``params.max_range=15``,
    ``sweep.mixture_ratio=[0.0, 0.3]``.
    """
    data: dict = {}
    if path is not None:
        path = pathlib.Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"study config {str(path)!r} does not exist")
        with open(path, "rb") as handle:
            data = tomllib.load(handle)
    for item in overrides:
        if "=" not in item:
            raise ValueError(f"override {item!r} must look like section.key=value")
        dotted, text = item.split("=", 1)
        *sections, key = dotted.strip().split(".")
        if len(sections) > 1 or (sections and sections[0] not in _SECTIONS):
            raise ValueError(
                f"override {item!r}: {'.'.join(sections)!r} is not a section of a study "
                f"config; write key=value for a study setting or section.key=value with a "
                f"section in {list(_SECTIONS)}")
        target = data
        for section in sections:
            target = target.setdefault(section, {})
            if not isinstance(target, dict):
                raise ValueError(f"override {item!r}: {section} is not a section in the "
                                 "config file")
        target[key] = _parse_value(text.strip())
    return study_config_from_dict(data)


def demo_study_config() -> StudyConfig:
    """The README's main job: 64 runs on the default simulated forest, stable matching,
    the loose boundary, P=64 particles; a few minutes on a 2-core CPU."""
    return StudyConfig(name="demo", num_runs=64, chunk_size=32, seed=0,
                       filter=FilterConfig(num_particles=64, max_landmarks=96, max_obs=16),
                       scenario=ScenarioConfig(num_steps=150))


class RunBatch(NamedTuple):
    """Scenarios of a chunk of runs. Run-dependent leaves have a leading axis R; the forest is
    shared by every run of a study (runs differ in odometry and observation noise).

    controls: (R, T, 3); observations: leaves (R, T, K, ...); truth_pose: (T+1, 3);
    tree_centres: (N, 2); tree_radii: (N,); tree_seen: (R, N) trees observed in each run.
    """

    controls: jnp.ndarray
    observations: Any
    truth_pose: jnp.ndarray
    tree_centres: jnp.ndarray
    tree_radii: jnp.ndarray
    tree_seen: jnp.ndarray
