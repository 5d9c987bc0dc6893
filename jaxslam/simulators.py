"""Simulators of Monte Carlo studies, as plugins named by the study config.

A study config names its simulator by a string (``simulator``, default ``"sims"``, the
MuJoCo-MJX forest simulator shipped beside jaxslam). The study machinery never imports a
simulator itself: ``load_simulator(name)`` imports the module of that name
(``importlib.import_module``), which registers itself with ``register_simulator`` when
imported, and returns the registered ``Simulator``. The simulator owns its [scenario] section:
it parses and checks the plain mapping the TOML gives, and simulates the runs of a study as a
``RunBatch``, the one type the study reads.

Only the standard library is imported here (the simulator's own modules import it too).
"""
from __future__ import annotations

import dataclasses
import importlib
from typing import Any, Callable, NamedTuple

DEFAULT_SIMULATOR = "sims"
SIM_INSTALL_COMMAND = 'pip install "jaxslam[sim]"'


class SimulatorUnavailable(ImportError):
    """A study's simulator, or a part of it that the study needs (e.g. MuJoCo for lidar
    scans), is not installed; the message says what is missing and how to install it."""


class RunBatch(NamedTuple):
    """What a simulator returns for a chunk of R runs: the filter's inputs and the truth.

    controls: (R, T, 3) odometry readings; observations: ``Observations`` with leaves
    (R, T, K, ...); tree_seen: (R, N) trees observed in each run (the map metrics score only
    these). The world is shared by every run, truth_pose (T+1, 3), tree_centres (N, 2),
    tree_radii (N,), or each run's own, leaves (R, T+1, 3), (R, N, 2), (R, N).
    """

    controls: Any
    observations: Any
    truth_pose: Any
    tree_centres: Any
    tree_radii: Any
    tree_seen: Any


class Simulator(NamedTuple):
    """A registered study simulator.

    settings: (mapping of the [scenario] section, or a settings object it built before) ->
      its frozen, hashable settings object (the study's ``config.scenario``); raises
      ValueError naming ``scenario.KEY`` for a key or value it refuses. The settings carry
      ``max_range`` [m], the sensor's range, which is the default of ``params.max_range``.
    simulate: (StudyConfig, run_ids (R,) int) -> RunBatch; run i draws from
      ``fold_in(PRNGKey(config.seed), i)`` alone, so a run never depends on its neighbours.
    to_dict: settings -> plain TOML-ready dict (the [scenario] section written back).
    """

    settings: Callable[[Any], Any]
    simulate: Callable[[Any, Any], RunBatch]
    to_dict: Callable[[Any], dict] = dataclasses.asdict


_REGISTRY: dict[str, Simulator] = {}


def register_simulator(name: str, simulate: Callable, settings: Callable,
                       to_dict: Callable = dataclasses.asdict) -> Simulator:
    """Register the study simulator ``name`` (see ``Simulator`` for the three functions).

    The module ``name`` calls this when imported, so that a study config naming it loads it;
    registering a name again replaces the earlier simulator. Returns the ``Simulator``.
    """
    if not isinstance(name, str) or not name:
        raise ValueError(f"register_simulator name={name!r}; expected a module name")
    simulator = Simulator(settings=settings, simulate=simulate, to_dict=to_dict)
    _REGISTRY[name] = simulator
    return simulator


def _install_hint(name: str) -> str:
    if name == DEFAULT_SIMULATOR:
        return f"install the simulator with: {SIM_INSTALL_COMMAND}"
    return (f"install the package that provides module {name!r}, or name an installed "
            f"simulator (default {DEFAULT_SIMULATOR!r})")


def load_simulator(name: str = DEFAULT_SIMULATOR) -> Simulator:
    """The simulator registered as ``name``, importing module ``name`` first when it has not
    registered yet (a plugin load by name).

    Raises:
      SimulatorUnavailable (an ImportError) when no module ``name`` is installed, naming how
        to install it; ValueError when the module does not register a simulator ``name``.
    """
    if name not in _REGISTRY:
        try:
            importlib.import_module(name)
        except ModuleNotFoundError as error:
            missing = error.name or ""
            if not (name == missing or name.startswith(missing + ".")):
                raise  # the module is there; one of its own imports is missing
            raise SimulatorUnavailable(f"the study simulator {name!r} is not installed (no "
                                       f"module {name!r}); {_install_hint(name)}",
                                       name=name) from error
        if name not in _REGISTRY:
            raise ValueError(f"module {name!r} registers no study simulator; it must call "
                             f"jaxslam.simulators.register_simulator({name!r}, simulate, "
                             "settings) when imported")
    return _REGISTRY[name]
