"""MuJoCo imported on first use, so that the filter, robot logs and the analytic simulator run
without it (``pip install jaxslam``; the simulator's physics comes with ``jaxslam[sim]``).

``sims.forest``, ``sims.lidar`` and ``sims.robot`` bind ``mujoco`` and ``mjx`` to stand-ins
(``LazyModule``) that import the real module the first time one of its attributes is read:
when an MJX forest world, a lidar scan or the wheeled robot is built. Without MuJoCo that
read raises ``SimulatorNotInstalled``, whose message names what needs MuJoCo and the command
that installs it. The import drops the "Failed to import warp" lines MJX prints when the
optional NVIDIA Warp backend is absent (jaxslam never uses that backend).

Only the standard library and ``jaxslam.simulators`` (standard library only) are imported here.
"""
from __future__ import annotations

import contextlib
import importlib
import io
import sys

from jaxslam.simulators import SIM_INSTALL_COMMAND, SimulatorUnavailable

INSTALL_COMMAND = SIM_INSTALL_COMMAND
SIMULATOR_PARTS = "jaxslam's simulator (MJX forest worlds, lidar scans, the wheeled robot)"
# Lines that ``mujoco/mjx/warp/__init__.py`` prints (print(), not a warning) when the optional
# NVIDIA Warp backend is not installed.
WARP_NOISE = ("Failed to import warp:", "Failed to import mujoco_warp:")


class SimulatorNotInstalled(SimulatorUnavailable):
    """MuJoCo-MJX is needed but not installed; the message says what needs it and how to
    install it (a ``jaxslam.simulators.SimulatorUnavailable``, which the ``jaxslam`` command
    reports in one line)."""


def missing_message(needed_by: str) -> str:
    """The one-line error for ``needed_by`` (what needs MuJoCo) when MuJoCo is missing."""
    return (f"{needed_by} needs MuJoCo-MJX, which is not installed; install the simulator "
            f"with: {INSTALL_COMMAND}")


def import_quietly(name: str = "mujoco.mjx"):
    """Import module ``name`` without MJX's Warp lines (anything else printed passes on).
    Returns the module; raises ImportError as ``importlib.import_module`` does."""
    if sys.modules.get(name) is not None:
        return sys.modules[name]
    captured = io.StringIO()
    try:
        with contextlib.redirect_stdout(captured):
            return importlib.import_module(name)
    finally:
        for line in captured.getvalue().splitlines():
            if not line.startswith(WARP_NOISE):
                print(line)


def _is_mujoco(error: ImportError) -> bool:
    """Whether ``error`` is MuJoCo (or MJX) itself missing, not one of its dependencies."""
    name = error.name or ""
    return name == "mujoco" or name.startswith("mujoco.")


def require_mujoco(needed_by: str = SIMULATOR_PARTS):
    """Import ``mujoco`` and ``mujoco.mjx`` (quietly). Returns ``mujoco``.

    Raises ``SimulatorNotInstalled`` (an ImportError) naming ``needed_by`` and
    ``INSTALL_COMMAND`` when MuJoCo or MJX is not installed.
    """
    try:
        import_quietly("mujoco.mjx")
    except ImportError as error:
        if isinstance(error, SimulatorNotInstalled) or not _is_mujoco(error):
            raise
        raise SimulatorNotInstalled(missing_message(needed_by), name=error.name) from error
    return sys.modules["mujoco"]


class LazyModule:
    """Stand-in for module ``name`` (``mujoco`` or ``mujoco.mjx``): the first attribute read
    imports it through ``require_mujoco``; attributes read are then kept on the stand-in."""

    def __init__(self, name: str, needed_by: str = SIMULATOR_PARTS):
        self._name = name
        self._needed_by = needed_by

    def __getattr__(self, attribute: str):
        if attribute.startswith("__"):  # copy, pickle and introspection probes
            raise AttributeError(attribute)
        require_mujoco(self._needed_by)
        value = getattr(importlib.import_module(self._name), attribute)
        setattr(self, attribute, value)
        return value

    def __repr__(self) -> str:
        return f"<lazy module {self._name!r}>"


def lazy_functions(module: str, *names: str):
    """Stand-ins for the functions ``names`` of ``module``, which is imported at the first call
    (for a module that imports MuJoCo, from one that must not). Returns a tuple."""

    def stand_in(name: str):
        def call(*args, **kwargs):
            return getattr(importlib.import_module(module), name)(*args, **kwargs)

        call.__name__ = call.__qualname__ = name
        call.__doc__ = f"``{module}.{name}`` (its module is imported at the first call)."
        return call

    return tuple(stand_in(name) for name in names)


mujoco = LazyModule("mujoco")
mjx = LazyModule("mujoco.mjx")
