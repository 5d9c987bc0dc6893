"""Study configuration: the simulated scenario and the study (runs, chunks, filter, sweeps),
read from TOML with "section.key=value" overrides; every error names the key and the allowed
values. Used by ``jaxslam.studies`` and the ``jaxslam`` command.
"""
from __future__ import annotations

import dataclasses
import itertools
import pathlib
import tomllib
from typing import Any, NamedTuple

import jax.numpy as jnp

from jaxslam.types import FilterConfig, Params


@dataclasses.dataclass(frozen=True)
class ScenarioConfig:
    """The simulated world of every run (see ``sims.scenario``).

    forest: "random" or "plantation"; num_trees; size: square side [m]; path: "loop",
    "lawnmower" or "random"; num_steps: T; step_length [m]; max_range [m] of the sensor;
    observation_source: "analytic" (range-bearing to trunk centres with Table 2 noise) or
    "lidar" (MJX scans + trunk detection); detection: centroid | kasa | geometric | ransac;
    odometry_noise_scale: multiplies the Table 1 noise of the simulated odometry.
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


@dataclasses.dataclass(frozen=True)
class StudyConfig:
    """Everything that defines a study. ``params`` are overrides of ``default_params``;
    ``sweep`` maps Params fields to lists of values (cartesian grid of conditions)."""

    name: str = "study"
    num_runs: int = 100
    chunk_size: int = 50
    seed: int = 0
    filter: FilterConfig = FilterConfig()
    scenario: ScenarioConfig = ScenarioConfig()
    params: tuple = ()
    sweep: tuple = ()
    divergence_threshold: float = 2.0
    map_match_threshold: float = 1.0
    gospa_cutoff: float = 2.0

    def __post_init__(self):
        for name in ("num_runs", "chunk_size"):
            value = getattr(self, name)
            if not isinstance(value, int) or value < 1:
                raise ValueError(f"study {name}={value!r}; expected a positive integer")
        params_fields = set(Params._fields)
        for section, items in (("params", self.params), ("sweep", self.sweep)):
            for key, _ in items:
                if key not in params_fields:
                    raise ValueError(f"{section}.{key} is not a filter parameter; expected one "
                                     f"of {sorted(params_fields)}")

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
    """Build and validate a ``StudyConfig``; errors name the key and the allowed values."""
    data = dict(data)
    filter_section = dict(data.pop("filter", {}))
    scenario_section = dict(data.pop("scenario", {}))
    params_section = dict(data.pop("params", {}))
    sweep_section = dict(data.pop("sweep", {}))
    _check_keys("", data, StudyConfig)
    _check_keys("filter", filter_section, FilterConfig)
    _check_keys("scenario", scenario_section, ScenarioConfig)
    _check_scenario(scenario_section)
    for key, values in sweep_section.items():
        if not isinstance(values, list) or not values:
            raise ValueError(f"sweep.{key} must be a non-empty list of values; got {values!r}")
    return StudyConfig(filter=FilterConfig(**filter_section),
                       scenario=ScenarioConfig(**scenario_section),
                       params=_as_tuple_items(params_section),
                       sweep=_as_tuple_items(sweep_section), **data)


_SCENARIO_CHOICES = {"forest": ("random", "plantation"), "path": ("loop", "lawnmower", "random"),
                     "observation_source": ("analytic", "lidar"),
                     "detection": ("centroid", "kasa", "geometric", "ransac")}


def _check_scenario(section: dict) -> None:
    for key, allowed in _SCENARIO_CHOICES.items():
        if key in section and section[key] not in allowed:
            raise ValueError(f"scenario.{key}={section[key]!r} is not supported; expected one of "
                             f"{list(allowed)}")


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
        target = data
        for section in sections:
            target = target.setdefault(section, {})
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
