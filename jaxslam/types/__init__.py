"""Types shared by the whole library: static config, dynamic params, filter state, observations.

One module per type: ``config`` (``FilterConfig`` and its choices), ``params`` (``Params`` and
``default_params``), ``state`` (``Particles``, ``FilterState``), ``observations``
(``Observations`` and their constructors). Every name is importable from ``jaxslam.types``.

Dimension glossary (used in every docstring of the package):

    P   particles                     (``FilterConfig.num_particles``)
    M   landmark slots per particle   (``FilterConfig.max_landmarks``)
    K   padded observations per step  (``FilterConfig.max_obs``)
    B   lidar beams per scan
    T   time steps
    R   independent Monte Carlo runs
    N   true trees in a simulated forest
    C   motion control vector length (3 for every built-in motion model)
    L   landmark identities of one smoothed history (``smoothing``)
    V   visits of those landmarks, and E links between visits (``smoothing.split_visits``)

Conventions: poses are ``(x, y, theta)`` in metres and radians, theta wrapped to [-pi, pi);
observations are ``(range, bearing)`` in the robot frame; landmark covariances are stored as
their three distinct components ``(sxx, sxy, syy)`` in a trailing axis of size 3 so that the hot
code can do closed-form 2x2 arithmetic; ``estimate`` expands them.
"""
from jaxslam.types.config import (ASSOCIATIONS, BOUNDARIES, MIXTURE_MODES, MOTION_MODELS,
                                  PROPOSALS, RESAMPLINGS, FilterConfig)
from jaxslam.types.observations import Observations, empty_observations, make_observations
from jaxslam.types.params import DERIVED_DEFAULTS, PARAM_DEFAULTS, Params, default_params
from jaxslam.types.state import FilterState, Particles

__all__ = [
    "ASSOCIATIONS", "BOUNDARIES", "DERIVED_DEFAULTS", "MIXTURE_MODES", "MOTION_MODELS",
    "PARAM_DEFAULTS", "PROPOSALS", "RESAMPLINGS", "FilterConfig", "FilterState",
    "Observations", "Params", "Particles", "default_params", "empty_observations",
    "make_observations",
]
