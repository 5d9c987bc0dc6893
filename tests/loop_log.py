"""One simulated loop through a random forest, as a calibration sees a log (shared test helper)."""
import jax

from jaxslam.types import default_params
from sims.forest import random_forest
from sims.paths import loop_path
from sims.scenario import build_scenario


def loop_log(seed: int, num_steps: int, num_trees: int, radius: float, params, max_obs=10):
    """(controls (T, 3), ``Observations`` (T, K, ...), true poses (T + 1, 3)) of one run:
    ``num_steps`` 0.5 m steps along a circle of radius ``radius`` [m] around (30, 30) (a
    whole loop only when T x 0.5 m reaches its circumference), through
    ``num_trees`` trees drawn in the 60 m square clear of the path, with the noise of
    ``params``; the forest's and the run's keys split from PRNGKey(``seed``)."""
    key_forest, key_run = jax.random.split(jax.random.PRNGKey(seed))
    path = loop_path(num_steps, (30.0, 30.0), (radius, radius), 0.5)
    forest = random_forest(key_forest, num_trees, (60.0, 60.0), keep_clear=path[:, :2])
    scenario = build_scenario(key_run, forest, path, 1, params=params, max_obs=max_obs)
    return (scenario.controls[0], jax.tree.map(lambda a: a[0], scenario.observations),
            scenario.poses[0])


def loop_noise():
    """The noise the calibration tests' loops are drawn with: Eq. (1) rotations 0.1 rad/rad,
    translation 4 % of the move, each with a 1 mm or 1 mrad constant; range 1 cm/m + 3 cm,
    bearing 1 mrad/m + 4 mrad; a 12 m sensor."""
    return default_params(rot1_noise=(0.0, 0.1, 0.001), trans_noise=(0.04, 0.0, 0.001),
                          rot2_noise=(0.0, 0.1, 0.001), range_noise=(0.01, 0.03),
                          bearing_noise=(0.001, 0.004), range_std_floor=1e-4,
                          bearing_std_floor=1e-5, max_range=12.0)
