"""One simulated loop through a random forest, as a calibration sees a log (shared test helper)."""
import jax

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
