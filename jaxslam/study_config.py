"""Study configuration: the study (runs, chunks, filter, sweeps) and the simulated scenario,
read from TOML with "section.key=value" overrides; every error names the key and the allowed
values. Used by ``jaxslam.studies`` and the ``jaxslam`` command.

The [scenario] section belongs to the study's simulator (``simulator``, default "sims"): it
reaches the simulator plugin as a plain mapping, and the plugin checks it and builds its own
settings (``jaxslam.simulators``); nothing here knows a scenario key.
"""
from __future__ import annotations

import dataclasses
import itertools
import pathlib
import tomllib
from typing import Any

from jaxslam.config_rules import Rule, check_fields, check_keys, check_value, normalise
from jaxslam.simulators import DEFAULT_SIMULATOR, SimulatorUnavailable, load_simulator
from jaxslam.types import FilterConfig, Params, default_params

_SECTIONS = ("filter", "scenario", "params", "sweep")

_STUDY_RULES = {
    "name": Rule("str"),
    "simulator": Rule("str"),
    "num_runs": Rule("int", 1, True),
    "chunk_size": Rule("int", 1, True),
    "run_width": Rule("int", 1, True),
    "seed": Rule("int", 0, True),
    "divergence_threshold": Rule("float", 0.0, False),
    "map_match_threshold": Rule("float", 0.0, False),
    "gospa_cutoff": Rule("float", 0.0, False),
}


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


def _scenario_settings(simulator: str, scenario):
    """The simulator's settings of a [scenario] mapping (None: all its defaults), or a
    settings object checked again by its simulator; a simulator that is not installed is a
    config error (ValueError naming ``simulator``)."""
    try:
        plugin = load_simulator(simulator)
    except SimulatorUnavailable as error:
        raise ValueError(f"study config simulator={simulator!r}: {error}") from None
    return plugin.settings({} if scenario is None else scenario)


@dataclasses.dataclass(frozen=True)
class StudyConfig:
    """Everything that defines a study. ``params`` are overrides of ``default_params``;
    ``sweep`` maps Params fields to lists of values (cartesian grid of conditions).

    simulator: the module name of the study's simulator plugin (``jaxslam.simulators``).
    scenario: its settings; given as a mapping of [scenario] keys (or None: its defaults),
    the simulator builds and checks them, so ``config.scenario`` is always its settings
    object (for "sims", a ``sims.config.ScenarioConfig``).

    chunk_size: runs per result file (the unit of resume). run_width: (run, condition) pairs
    per compiled filter call and per device, fixed for the whole study: every chunk is cut
    into groups of run_width pairs (the last padded), so a run's numbers never depend on the
    chunk size, the number of runs or of sweep conditions, or the device count. 1 (the
    default) is the fastest on a CPU; on a GPU choose e.g. 64-256 for throughput.
    """

    name: str = "study"
    simulator: str = DEFAULT_SIMULATOR
    num_runs: int = 100
    chunk_size: int = 50
    run_width: int = 1
    seed: int = 0
    filter: FilterConfig = FilterConfig()
    scenario: Any = None
    params: tuple = ()
    sweep: tuple = ()
    divergence_threshold: float = 2.0
    map_match_threshold: float = 1.0
    gospa_cutoff: float = 2.0

    def __post_init__(self):
        check_fields("", self, _STUDY_RULES)
        if not isinstance(self.filter, FilterConfig):
            raise ValueError(f"study filter={self.filter!r}; expected a FilterConfig")
        object.__setattr__(self, "scenario", _scenario_settings(self.simulator, self.scenario))
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
    """Plain dict (TOML-ready) of a study config. ``simulator`` is left out when it is the
    default one, so the study.toml, folder digest and resume check of a study on the
    built-in simulator do not change with the plugin mechanism."""
    out = {f.name: getattr(config, f.name) for f in dataclasses.fields(config)
           if f.name not in ("filter", "scenario", "params", "sweep")}
    if out["simulator"] == DEFAULT_SIMULATOR:
        del out["simulator"]
    out["filter"] = dataclasses.asdict(config.filter)
    out["scenario"] = load_simulator(config.simulator).to_dict(config.scenario)
    out["params"] = {k: list(v) if isinstance(v, tuple) else v for k, v in config.params}
    out["sweep"] = {k: list(v) for k, v in config.sweep}
    return out


def study_config_from_dict(data: dict) -> StudyConfig:
    """Build and validate a ``StudyConfig``; errors name the key and the allowed values.

    Every value is type-checked here (a string where a number belongs, a float seed, a
    count below 1...), before anything is written; a float field given as an integer is
    stored as a float, so ``size = 30`` and ``size = 30.0`` are the same study. The
    [scenario] section goes to the simulator named by ``simulator`` as a plain mapping.
    """
    data = dict(data)
    sections = {}
    for name in _SECTIONS:
        section = data.pop(name, {})
        if not isinstance(section, dict):
            raise ValueError(f"{name} must be a [{name}] section of key = value lines; got "
                             f"{name} = {section!r}")
        sections[name] = dict(section)
    check_keys("", data, StudyConfig)
    for key, value in data.items():
        if isinstance(value, dict):
            raise ValueError(f"{key!r} is not a section of a study config (sections: "
                             f"{list(_SECTIONS)}); {key} is a single value: {key} = ...")
    check_keys("filter", sections["filter"], FilterConfig)
    simulator = data.get("simulator", DEFAULT_SIMULATOR)
    check_value("", "simulator", simulator, _STUDY_RULES["simulator"])
    scenario = _scenario_settings(simulator, sections["scenario"])  # the simulator's checks
    _check_filter_types(sections["filter"])
    for key, values in sections["sweep"].items():
        if not isinstance(values, list) or not values:
            raise ValueError(f"sweep.{key} must be a non-empty list of values; got {values!r}")
    for name, value in sections["params"].items():
        if isinstance(value, dict):
            raise ValueError(f"params.{name} must be a number or a list of numbers; got a "
                             f"section {value!r}")
    data = normalise("", data, _STUDY_RULES)
    return StudyConfig(filter=FilterConfig(**sections["filter"]), scenario=scenario,
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
                       scenario={"num_steps": 150})
