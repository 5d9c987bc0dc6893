"""Landmark life cycle: birth into the first free slots, full maps, existence evidence and
clipping, visibility, and the loose-boundary airlock of Geiser et al. 2023, Fig. 3 through the public
filter step (one particle, zero-noise motion, crafted states)."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam import ekf, landmarks
from jaxslam.filter import make_filter
from jaxslam.types import FilterConfig, default_params, make_observations

# Tiny motion noise: a stationary control leaves the single particle where it is.
QUIET = dict(rot1_noise=(0.0, 0.0, 1e-9), trans_noise=(0.0, 0.0, 1e-9),
             rot2_noise=(0.0, 0.0, 1e-9))


# ---------------------------------------------------------------------------------------------
# Birth slots


def ref_birth_slots(active, birth):
    """Plain Python: births take free slots in index order; extra births are dropped."""
    free = [m for m, a in enumerate(active) if not a]
    slots, dropped, used = [], 0, 0
    for b in birth:
        if b and used < len(free):
            slots.append(free[used])
            used += 1
        else:
            slots.append(len(active))
            dropped += int(bool(b))
    return np.array(slots), dropped


@pytest.mark.parametrize("active,birth", [
    ([True, False, True, False, False], [True, False, True, True]),
    ([False, False, False], [False, True, True]),
    ([True, True, True], [True, False, True]),           # full map
    ([True, False, True, True], [True, True, True]),     # one free slot, three births
    ([False, True], [False, False, False]),              # nothing born
])
def test_birth_slots_vs_reference(active, birth):
    slot, dropped = jax.jit(landmarks.birth_slots)(jnp.asarray(active), jnp.asarray(birth))
    ref_slot, ref_dropped = ref_birth_slots(active, birth)
    np.testing.assert_array_equal(np.asarray(slot), ref_slot)
    assert int(dropped) == ref_dropped
    assert slot.dtype == jnp.int32


def test_full_map_never_overwrites():
    active = jnp.ones(4, bool)
    values = jnp.arange(4.0)
    slot, dropped = landmarks.birth_slots(active, jnp.asarray([True, True]))
    out = landmarks.scatter_rows(values, slot, jnp.asarray([-1.0, -2.0]))
    np.testing.assert_array_equal(np.asarray(out), [0.0, 1.0, 2.0, 3.0])
    assert int(dropped) == 2


def test_birth_slots_vmap():
    active = jnp.asarray([[True, False, False], [False, True, True]])
    birth = jnp.asarray([[True, True], [True, True]])
    slot, dropped = jax.vmap(landmarks.birth_slots)(active, birth)
    np.testing.assert_array_equal(np.asarray(slot), [[1, 2], [0, 3]])
    np.testing.assert_array_equal(np.asarray(dropped), [0, 1])


# ---------------------------------------------------------------------------------------------
# Existence evidence


def test_update_existence_vs_reference():
    params = default_params(dtype=jnp.float64)
    hit, miss = np.log(0.9 / 0.05), np.log(0.1 / 0.95)
    existence = jnp.asarray([0.0, 1.0, 5.9, -5.9, 2.0])
    matched = jnp.asarray([True, False, True, False, False])
    missed = jnp.asarray([False, True, False, True, False])
    out = np.asarray(jax.jit(landmarks.update_existence)(existence, matched, missed, params))
    ref = np.clip(np.asarray(existence) + np.where(matched, hit, 0) + np.where(missed, miss, 0),
                  -6.0, 6.0)
    np.testing.assert_allclose(out, ref, rtol=1e-12)
    assert out[2] == 6.0 and out[3] == -6.0  # clipped at +-existence_max


def test_clipping_lets_a_long_seen_landmark_die():
    """After many hits the log-odds saturate at existence_max, so a few misses still delete."""
    params = default_params(dtype=jnp.float64)
    existence = jnp.zeros(1)
    for _ in range(100):
        existence = landmarks.update_existence(existence, jnp.asarray([True]),
                                               jnp.asarray([False]), params)
    assert float(existence[0]) == 6.0
    misses = 0
    while float(existence[0]) >= float(params.existence_delete):
        existence = landmarks.update_existence(existence, jnp.asarray([False]),
                                               jnp.asarray([True]), params)
        misses += 1
    assert misses == int(np.ceil((6.0 + 1.5) / -np.log(0.1 / 0.95)))  # 4


# ---------------------------------------------------------------------------------------------
# Visibility (unit level)


def visibility_case(landmark_range, obs_range, boundary):
    params = default_params(dtype=jnp.float64)
    pose = jnp.zeros(3)
    mean = jnp.asarray([[landmark_range, 0.0]])
    cov = jnp.asarray([[1e-4, 0.0, 1e-4]])
    predicted = ekf.predict_measurements(pose, mean, cov, params)
    z = jnp.asarray([[obs_range, 0.0]])
    d2 = ekf.mahalanobis_sq(z, predicted)
    return landmarks.visibility(z, jnp.asarray([True]), jnp.asarray([True]), predicted, d2,
                                params, boundary)


def test_visibility_hard_boundary():
    vis = visibility_case(20.05, 19.95, "hard")
    assert bool(vis.usable_obs[0]) and not bool(vis.matchable[0])
    vis = visibility_case(19.95, 20.05, "hard")
    assert not bool(vis.usable_obs[0]) and bool(vis.matchable[0])
    vis = visibility_case(20.0, 20.0, "hard")  # exactly at the range limit: inside
    assert bool(vis.usable_obs[0]) and bool(vis.matchable[0])


@pytest.mark.parametrize("landmark_range,obs_range", [(20.05, 19.95), (19.95, 20.05),
                                                      (20.0, 20.0)])
def test_visibility_loose_ring(landmark_range, obs_range):
    vis = visibility_case(landmark_range, obs_range, "loose")
    assert not bool(vis.usable_obs[0]) and bool(vis.set_aside_obs[0])
    assert not bool(vis.matchable[0]) and bool(vis.explained[0])


def test_visibility_loose_inside_is_normal():
    vis = visibility_case(10.0, 10.02, "loose")
    assert bool(vis.usable_obs[0]) and bool(vis.matchable[0])
    assert not bool(vis.set_aside_obs[0]) and not bool(vis.explained[0])


@pytest.mark.parametrize("boundary", ["hard", "loose"])
def test_miss_range_spares_far_landmarks_from_misses_only(boundary):
    """A landmark beyond ``miss_range`` stays matchable but is not expected (its misses do not
    count); ``test_miss_range_through_step`` checks the match, the hit and the kept evidence."""
    params = default_params(dtype=jnp.float64, max_range=45.0)
    pose = jnp.zeros(3)
    mean = jnp.asarray([[10.0, 0.0], [38.0, 5.0]])  # ranges 10 m and 38.3 m
    cov = jnp.asarray([[1e-4, 0.0, 1e-4]] * 2)
    predicted = ekf.predict_measurements(pose, mean, cov, params)
    # One observation elsewhere (no match for either landmark); the second row is padding, so
    # the detector is not saturated and its farthest report sets no horizon.
    z = jnp.asarray([[5.0, 1.0], [0.0, 0.0]])
    d2 = ekf.mahalanobis_sq(z, predicted)
    valid, active = jnp.asarray([True, False]), jnp.asarray([True, True])

    def expected(miss_range):
        vis = landmarks.visibility(z, valid, active, predicted, d2,
                                   params._replace(miss_range=miss_range), boundary)
        return vis.matchable, vis.expected

    matchable, default = expected(params.miss_range)  # +inf: both can be missed
    np.testing.assert_array_equal(matchable, [True, True])
    np.testing.assert_array_equal(default, [True, True])
    np.testing.assert_array_equal(expected(jnp.asarray(30.0))[1], [True, False])
    np.testing.assert_array_equal(expected(jnp.asarray(5.0))[1], [False, False])
    # The same under jit and vmap over a sweep of miss_range (a dynamic parameter).
    sweep = jnp.asarray([jnp.inf, 30.0, 5.0])
    _, swept = jax.jit(jax.vmap(expected))(sweep)
    np.testing.assert_array_equal(swept, [[True, True], [True, False], [False, False]])


def test_visibility_rejects_unknown_boundary():
    with pytest.raises(ValueError, match="boundary"):
        visibility_case(10.0, 10.0, "soft")


# ---------------------------------------------------------------------------------------------
# The airlock through the public filter step (Geiser et al. 2023, Fig. 3)


@pytest.fixture(scope="module")
def steps():
    """Jitted steps of two 1-particle filters, M = 4 slots, K = 2 observations."""
    out = {}
    for boundary in ("hard", "loose"):
        config = FilterConfig(num_particles=1, max_landmarks=4, max_obs=2, boundary=boundary,
                              association="stable")
        filt = make_filter(config)
        out[boundary] = (filt, jax.jit(filt.step))
    return out


def crafted_state(filt, landmark_xy, existence):
    """One particle at the origin facing +x with the given landmarks in slots 0.. (tight
    covariance 1 cm^2)."""
    state = filt.init(jnp.zeros(3, jnp.float32))
    p = state.particles
    n = len(landmark_xy)
    particles = p._replace(
        landmark_mean=p.landmark_mean.at[0, :n].set(jnp.asarray(landmark_xy, jnp.float32)),
        landmark_cov=p.landmark_cov.at[0, :n].set(jnp.asarray([1e-4, 0.0, 1e-4], jnp.float32)),
        active=p.active.at[0, :n].set(True),
        existence=p.existence.at[0, :n].set(jnp.asarray(existence, jnp.float32)),
        observation_count=p.observation_count.at[0, :n].set(5),
    )
    return state._replace(particles=particles)


def step_once(steps, boundary, state, z, valid):
    _, step = steps[boundary]
    obs = make_observations(jnp.asarray(z, jnp.float32), valid=jnp.asarray(valid))
    params = default_params(**QUIET)
    return step(jax.random.key(0), state, params, jnp.zeros(3, jnp.float32), obs)


@pytest.mark.parametrize("boundary", ["hard", "loose"])
def test_tree_beyond_range_landmark_inside(steps, boundary):
    """Tree at 20.05 m (unseen, beyond R_max = 20 m); its landmark estimated at 19.95 m.
    A tree at 10 m is seen and matched in both cases. The hard boundary counts a miss and
    deletes the landmark (existence 0.5 - 2.25 < -1.5); the loose one keeps it untouched."""
    filt, _ = steps[boundary]
    state = crafted_state(filt, [[10.0, 0.0], [19.95, 0.0]], [0.5, 0.5])
    new_state, info = step_once(steps, boundary, state, [[10.0, 0.0], [0.0, 0.0]],
                                [True, False])
    active = np.asarray(new_state.particles.active[0])
    assert int(info.match[0, 0]) == 0
    if boundary == "hard":
        np.testing.assert_array_equal(active, [True, False, False, False])
    else:
        np.testing.assert_array_equal(active, [True, True, False, False])
        np.testing.assert_allclose(float(new_state.particles.existence[0, 1]), 0.5)
        np.testing.assert_allclose(np.asarray(new_state.particles.landmark_mean[0, 1]),
                                   [19.95, 0.0], atol=1e-5)
    assert np.all(np.isfinite(np.asarray(new_state.log_weight)))


@pytest.mark.parametrize("boundary", ["hard", "loose"])
def test_tree_inside_landmark_beyond_range(steps, boundary):
    """Tree seen at 19.95 m; its landmark estimated at 20.05 m. The hard boundary cannot match
    them and creates a twin; the loose one sets the observation aside (no birth) and keeps the
    landmark's evidence."""
    filt, _ = steps[boundary]
    state = crafted_state(filt, [[10.0, 0.0], [20.05, 0.0]], [1.0, 1.0])
    new_state, info = step_once(steps, boundary, state, [[10.0, 0.0], [19.95, 0.0]],
                                [True, True])
    active = np.asarray(new_state.particles.active[0])
    np.testing.assert_array_equal(np.asarray(info.match[0]), [0, -1])
    if boundary == "hard":
        np.testing.assert_array_equal(active, [True, True, True, False])  # the twin in slot 2
        np.testing.assert_allclose(np.asarray(new_state.particles.landmark_mean[0, 2]),
                                   [19.95, 0.0], atol=1e-4)
        assert int(info.num_set_aside[0]) == 0
    else:
        np.testing.assert_array_equal(active, [True, True, False, False])
        assert int(info.num_set_aside[0]) == 1
        np.testing.assert_allclose(float(new_state.particles.existence[0, 1]), 1.0)
    assert int(info.num_landmarks[0]) == active.sum()


@pytest.mark.parametrize("boundary", ["hard", "loose"])
def test_miss_range_through_step(steps, boundary):
    """Landmarks at 10 m (seen) and 15 m, inside R_max = 20 m. Unseen, the 15 m one takes a
    miss and is deleted (0.5 - 2.25 < -1.5) by default, but keeps its evidence with
    miss_range = 12 m; seen, it still matches and gains a hit with miss_range = 12 m."""
    filt, step = steps[boundary]
    state = crafted_state(filt, [[10.0, 0.0], [15.0, 0.0]], [0.5, 0.5])

    def run(miss_range, z, valid):
        obs = make_observations(jnp.asarray(z, jnp.float32), valid=jnp.asarray(valid))
        params = default_params(**QUIET)._replace(miss_range=jnp.float32(miss_range))
        return step(jax.random.key(0), state, params, jnp.zeros(3, jnp.float32), obs)

    unseen = ([[10.0, 0.0], [0.0, 0.0]], [True, False])
    new_state, _ = run(np.inf, *unseen)
    np.testing.assert_array_equal(np.asarray(new_state.particles.active[0, :2]), [True, False])
    new_state, _ = run(12.0, *unseen)
    np.testing.assert_array_equal(np.asarray(new_state.particles.active[0, :2]), [True, True])
    np.testing.assert_allclose(float(new_state.particles.existence[0, 1]), 0.5)
    new_state, info = run(12.0, [[10.0, 0.0], [15.0, 0.0]], [True, True])
    np.testing.assert_array_equal(np.asarray(info.match[0]), [0, 1])
    assert float(new_state.particles.existence[0, 1]) > 0.5


def test_birth_goes_to_first_free_slot_through_step(steps):
    """Slots 0 and 2 hold landmarks; two new trees at 5 m fill slots 1 and 3, in order."""
    filt, _ = steps["loose"]
    state = crafted_state(filt, [[10.0, 0.0], [0.0, 0.0], [0.0, 12.0]], [1.0, 1.0, 1.0])
    particles = state.particles
    state = state._replace(particles=particles._replace(
        active=particles.active.at[0, 1].set(False)))
    new_state, info = step_once(steps, "loose", state, [[5.0, -1.0], [6.0, 1.0]], [True, True])
    np.testing.assert_array_equal(np.asarray(new_state.particles.active[0]), [True] * 4)
    mean = np.asarray(new_state.particles.landmark_mean[0])
    np.testing.assert_allclose(mean[1], [5 * np.cos(-1.0), 5 * np.sin(-1.0)], atol=1e-4)
    np.testing.assert_allclose(mean[3], [6 * np.cos(1.0), 6 * np.sin(1.0)], atol=1e-4)
    np.testing.assert_array_equal(np.asarray(new_state.particles.observation_count[0, [1, 3]]),
                                  [1, 1])
    assert int(info.num_dropped_births[0]) == 0


def test_landmarks_outside_the_field_of_view_are_not_missed():
    # A landmark behind the robot (bearing pi) is matchable but not expected with a +-0.6 rad
    # field of view; ahead (bearing 0) it is expected either way.
    from jaxslam.ekf import predict_measurements
    from jaxslam.landmarks import visibility

    params = default_params(miss_bearing=0.6)
    pose = jnp.zeros(3)
    mean = jnp.array([[5.0, 0.0], [-5.0, 0.0]])
    cov = jnp.tile(jnp.array([0.01, 0.0, 0.01]), (2, 1))
    predicted = predict_measurements(pose, mean, cov, params)
    z = jnp.zeros((1, 2))
    valid = jnp.zeros(1, bool)
    vis = visibility(z, valid, jnp.ones(2, bool), predicted, jnp.full((1, 2), jnp.inf),
                     params, "hard")
    np.testing.assert_array_equal(np.asarray(vis.expected), [True, False])
    wide = visibility(z, valid, jnp.ones(2, bool), predicted, jnp.full((1, 2), jnp.inf),
                      default_params(), "hard")
    np.testing.assert_array_equal(np.asarray(wide.expected), [True, True])
