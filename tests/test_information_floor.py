"""The information-floor experiment: true associations, dead reckoning, the MAP's bound checks.

Three 30-step logs of the simulator the proposal study uses (``build_scenario``, analytic
source) in its first regime's noise (6x Table 1 odometry, the 5 mm / 0.5 mrad lidar, 12 m
range): a wobbly arc (0.3 m radial wobble, 6 m wavelength, on a 20 m circle) through 40
trees, path and forest drawn in NumPy to keep the test fast.
"""
import chex
import jax
import numpy as np
import pytest

from experiments.information_floor import (dead_reckoning, floor_of_log, gaussian_cost,
                                           true_associations)
from experiments.mixture_regime import regime_params
from jaxslam.smoothing import initial_landmarks, smooth_path
from sims.forest import Forest, empty_clutter
from sims.scenario import build_scenario

STEPS, RUNS = 30, 3


def wobbly_arc(steps: int, radius: float = 20.0, wobble: float = 0.3, step: float = 0.5):
    """(steps + 1, 3) poses ~``step`` m apart on a circle about (30, 30) with a radial
    wobble, heading along the path."""
    arc = step * np.arange(steps + 2)
    r = radius + wobble * np.sin(2 * np.pi * arc / 6.0)
    xy = 30.0 + r[:, None] * np.stack([np.cos(arc / radius), np.sin(arc / radius)], -1)
    heading = np.arctan2(*(xy[1:] - xy[:-1]).T[::-1])
    return np.concatenate([xy[:-1], heading[:, None]], -1)


def numpy_forest(rng, path, trees: int = 40, spacing: float = 2.0, clearance: float = 1.5):
    """(trees, 2) uniform in [0, 60]^2, ``spacing`` apart and ``clearance`` off the path."""
    centres = []
    while len(centres) < trees:
        c = rng.uniform(0.0, 60.0, 2)
        if (np.min(np.linalg.norm(path[:, :2] - c, axis=1)) > clearance
                and all(np.linalg.norm(c - d) > spacing for d in centres)):
            centres.append(c)
    return np.asarray(centres)


@pytest.fixture(scope="module")
def logs():
    params = regime_params(6.0, "lidar")
    path = wobbly_arc(STEPS)
    centres = numpy_forest(np.random.default_rng(11), path)
    forest = Forest(np.asarray(centres, np.float32), np.full(len(centres), 0.15, np.float32),
                    empty_clutter())
    scenario = build_scenario(jax.random.PRNGKey(11), forest, path, RUNS, params=params,
                              max_obs=12)
    return scenario, centres, params


def numpy_nearest_tree(pose, z, centres):
    """Reference: index (N,) of the tree nearest each observation z (N, 2) placed from the
    true pose (3,) by plain NumPy inverse range-bearing."""
    angle = pose[2] + z[:, 1]
    point = pose[:2] + z[:, :1] * np.stack([np.cos(angle), np.sin(angle)], -1)
    return np.argmin(np.linalg.norm(point[:, None] - centres[None], axis=-1), axis=1)


def test_true_associations_hand_example():
    """Non-contiguous ids become 0..L-1 in ascending tree order; invalid rows (any id) -1."""
    ids = np.array([[7, 3, 5], [3, -1, 9]])
    valid = np.array([[True, True, False], [True, False, True]])
    landmark_of_obs, trees = true_associations(ids, valid)
    np.testing.assert_array_equal(trees, [3, 7, 9])
    np.testing.assert_array_equal(landmark_of_obs, [[1, 0, -1], [0, -1, 2]])
    empty, no_trees = true_associations(ids, np.zeros_like(valid))  # nothing seen
    np.testing.assert_array_equal(empty, -np.ones_like(ids))
    assert no_trees.size == 0


def test_true_associations_match_nearest_tree(logs):
    """Every valid observation maps to the tree nearest its inverse at the true pose (the
    lidar's 5 mm / 0.5 mrad put it within centimetres; trees are metres apart), every
    invalid one to -1."""
    scenario, centres, _ = logs
    for r in range(RUNS):
        valid = np.asarray(scenario.observations.valid[r])
        landmark_of_obs, trees = true_associations(scenario.observations.landmark_id[r], valid)
        assert valid.sum() > 0
        np.testing.assert_array_equal(landmark_of_obs[~valid], -1)
        t, k = np.nonzero(valid)
        z = np.asarray(scenario.observations.z[r], np.float64)[t, k]
        pose = np.asarray(scenario.poses[r], np.float64)[t + 1]  # z[t] is taken at pose t + 1
        nearest = np.array([numpy_nearest_tree(p, zi[None], centres)[0]
                            for p, zi in zip(pose, z)])
        np.testing.assert_array_equal(trees[landmark_of_obs[t, k]], nearest)


def test_dead_reckoning_of_true_moves_is_the_true_path(logs):
    """Noise-free moves from the true start retrace the true path (float32 truth: 1e-4 m,
    1e-4 rad over 30 steps)."""
    scenario, _, _ = logs
    path = dead_reckoning(scenario.poses[0, 0], scenario.moves[0])
    chex.assert_shape(path, (STEPS, 3))
    np.testing.assert_allclose(path, np.asarray(scenario.poses[0, 1:], np.float64), atol=1e-4)


def test_gaussian_cost_is_the_smoothers(logs):
    """``gaussian_cost`` at a start equals ``smooth_path``'s first cost (the same problem;
    relative 1e-12: the same float64 sums)."""
    scenario, _, params = logs
    obs = scenario.observations
    landmark_of_obs, _ = true_associations(obs.landmark_id[0], obs.valid[0])
    z = np.asarray(obs.z[0], np.float64)
    start = np.asarray(scenario.poses[0, 0], np.float64)
    path = dead_reckoning(start, scenario.controls[0])
    result = smooth_path(start, path, scenario.controls[0], z, landmark_of_obs, params,
                         iterations=1, huber=1e6)
    landmark = initial_landmarks(path, z, landmark_of_obs, int(landmark_of_obs.max()) + 1)
    cost, groups = gaussian_cost(start, path, landmark, scenario.controls[0], z,
                                 landmark_of_obs, params)
    np.testing.assert_allclose(cost, result.cost[0], rtol=1e-12)
    chex.assert_shape(groups, (4,))


def test_map_with_true_association_beats_dead_reckoning_and_truth(logs):
    """Started at the truth, the MAP ends no farther than dead reckoning and at a cost no
    higher than the truth's (true path and tree centres); the kept solution is the lower
    cost; the observation groups' mean squares at the truth are chi-square / n ~ 1 (the
    model is the simulator's: within 0.5 for ~100+ observations)."""
    scenario, centres, params = logs
    for r in range(RUNS):
        obs = scenario.observations
        floor = floor_of_log(scenario.poses[r, 0], scenario.controls[r], obs.z[r],
                             obs.landmark_id[r], obs.valid[r],
                             np.asarray(scenario.poses[r, 1:], np.float64), centres, params,
                             iterations=50)
        assert floor.from_truth <= floor.dead_reckoning
        assert floor.cost_truth <= floor.cost_at_truth
        assert min(floor.cost_truth, floor.cost_dead_reckoning) <= floor.cost_at_truth
        expected = (floor.from_truth if floor.cost_truth < floor.cost_dead_reckoning
                    else floor.from_dead_reckoning)
        assert floor.error == expected
        np.testing.assert_allclose(floor.chi2_at_truth[2:], 1.0, atol=0.5)


def test_rate_row_puts_the_forests_interval_beside_wilson():
    """4 forests x 10 logs, all 10 logs of forest 0 over 1 m and none of the others: the rate
    is 25 %, Wilson's interval (independent logs) is about [14, 40] %, and the forests'
    interval (t with 3 degrees of freedom over the rates 1, 0, 0, 0) is clipped to [0, 1]
    and wider. One forest: no forest interval, '-'."""
    from experiments.information_floor import RATE_HEADER, rate_row
    from experiments.proposal_study import clustered_interval, wilson

    exceed = np.repeat([True, False, False, False], 10)
    errors = np.where(exceed, 2.0, 0.5)
    cells = [c.strip() for c in rate_row("x", exceed, errors, 4).strip(" |").split("|")]
    assert len(cells) == len(RATE_HEADER.strip(" |").split("|")) == 5
    low, high = wilson(10, 40)
    c_low, c_high = clustered_interval(exceed, 4)
    assert cells[:3] == ["x", "40", f"10 (25.0 %) [{100 * low:.1f}, {100 * high:.1f}]"]
    assert cells[3] == f"[{100 * c_low:.1f}, {100 * c_high:.1f}]" == "[0.0, 100.0]"
    assert cells[4] == "0.500"
    assert rate_row("x", exceed, errors, 1).split("|")[4].strip() == "-"
