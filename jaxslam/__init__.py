"""jaxslam: JAX-accelerated, batched FastSLAM for forestry robots."""
from jaxslam.types import (
    FilterConfig,
    FilterState,
    Particles,
    Observations,
    Params,
    default_params,
    empty_observations,
    make_observations,
)

__version__ = "0.1.0"
