"""``boundary="loose_match"``: the airlock of Geiser et al. 2023 (section 3.1) for births and
deaths only, its observations and ring landmarks still matched.

The reference is plain NumPy float64: the three boundaries' visibility rules written out per
observation and landmark from the predicted ranges, the range variances S_rr and the pair
distances, compared field by field with ``landmarks.visibility`` with and without jit, under
vmap and on the edges (no valid observation, a saturated sensor, an observation nearer than
``min_range``, a landmark on the ring's inner edge). Through the filter step: an observation
in the ring updates the landmark it belongs to instead of being thrown away, and still never
creates one.
"""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam import ekf, landmarks
from jaxslam.filter import make_filter
from jaxslam.types import BOUNDARIES, FilterConfig, default_params, make_observations
from mapped_state import mapped_state  # tests/ is on sys.path

QUIET = dict(rot1_noise=(0.0, 0.0, 1e-9), trans_noise=(0.0, 0.0, 1e-9),
             rot2_noise=(0.0, 0.0, 1e-9))
FIELDS = ("usable_obs", "set_aside_obs", "matchable", "explained", "expected", "matching_obs")


def reference_visibility(z, valid, active, pred_range, pred_bearing, s_rr, d2, params,
                         boundary):
    """The three boundaries in NumPy float64 (``landmarks`` module docstring).

    z: (K, 2); valid: (K,); active: (M,); pred_range, pred_bearing, s_rr: (M,) the predicted
    range, bearing and range variance of each landmark; d2: (K, M) squared distances.
    Returns a dict of the ``Visibility`` fields (loose boundaries: also
    ``set_aside_by_gate``, the observations set aside only because they gate with a ring
    landmark).
    """
    p = {name: float(np.asarray(getattr(params, name))) for name in (
        "min_range", "max_range", "miss_range", "miss_bearing", "airlock_sigmas",
        "association_gate", "range_std_floor")}
    slope, const = (float(v) for v in np.asarray(params.range_noise))
    in_min = pred_range >= p["min_range"]
    horizon = np.max(np.where(valid, z[:, 0], 0.0)) if np.all(valid) else np.inf
    may_miss = ((pred_range <= horizon) & (pred_range <= p["miss_range"])
                & (np.abs(pred_bearing) <= p["miss_bearing"]))
    obs = valid & (z[:, 0] >= p["min_range"])
    if boundary == "hard":
        usable = obs & (z[:, 0] <= p["max_range"])
        matchable = active & in_min & (pred_range <= p["max_range"])
        return dict(usable_obs=usable, set_aside_obs=np.zeros_like(usable),
                    matchable=matchable, explained=np.zeros_like(matchable),
                    expected=matchable & may_miss, matching_obs=usable)
    sigma_obs = np.maximum(slope * z[:, 0] + const, p["range_std_floor"])
    obs_ring = z[:, 0] > p["max_range"] - p["airlock_sigmas"] * sigma_obs
    width = p["airlock_sigmas"] * np.sqrt(s_rr)
    lm_ring = (active & (pred_range > p["max_range"] - width)
               & (pred_range <= p["max_range"] + width))
    gated = d2 <= p["association_gate"]
    set_aside = obs & (obs_ring | np.any(gated & lm_ring[None, :], axis=1))
    inside = active & in_min & (pred_range <= p["max_range"] - width)
    explained = np.any(gated & set_aside[:, None], axis=0)
    out = dict(usable_obs=obs & ~set_aside, set_aside_obs=set_aside, explained=explained,
               expected=inside & may_miss, set_aside_by_gate=set_aside & ~obs_ring)
    if boundary == "loose":
        return dict(out, matchable=inside, matching_obs=obs & ~set_aside)
    return dict(out, matchable=inside | (lm_ring & in_min), matching_obs=obs)


def random_case(seed, num_obs=6, num_slots=8, saturated=False):
    """A pose at the origin, landmarks at 0.5-15 m (some near R_max = 12 m), observations of
    some of them (noisy), of nothing, and one just inside its own ring edge of a ring
    landmark; range noise wide enough for a ring of about 1.5 m."""
    rng = np.random.default_rng(seed)
    params = default_params(dtype=jnp.float64, max_range=12.0, range_noise=(0.025, 0.01),
                            bearing_noise=(0.0025, 0.001), range_std_floor=1e-4,
                            bearing_std_floor=1e-5, min_range=1.0, miss_bearing=1.2)
    ranges = rng.uniform(0.5, 15.0, num_slots)
    ranges[:3] = rng.uniform(10.0, 13.5, 3)  # at the ring
    ranges[0] = rng.uniform(10.7, 11.0)  # in the ring (w_m is about 1.5 m there)
    bearings = rng.uniform(-np.pi, np.pi, num_slots)
    mean = np.stack([ranges * np.cos(bearings), ranges * np.sin(bearings)], -1)
    cov = np.tile([0.02, 0.003, 0.03], (num_slots, 1))
    active = rng.random(num_slots) < 0.8
    seen = rng.choice(num_slots, num_obs, replace=False)
    z = np.stack([ranges[seen] + rng.normal(0, 0.2, num_obs),
                  bearings[seen] + rng.normal(0, 0.02, num_obs)], -1)
    z[-1] = [rng.uniform(0.5, 12.5), rng.uniform(-np.pi, np.pi)]  # a tree not in the map
    # Landmark 0 seen 0.3-0.5 m short: the observation lies inside its own ring edge (about
    # 10.6 m) but gates with the ring landmark, so it is set aside by the gate alone.
    active[0] = True
    z[0] = [ranges[0] - rng.uniform(0.3, 0.5), bearings[0]]
    valid = np.ones(num_obs, bool) if saturated else rng.random(num_obs) < 0.8
    return params, np.zeros(3), mean, cov, active, z, valid


def jax_visibility(params, pose, mean, cov, active, z, valid, boundary):
    predicted = ekf.predict_measurements(pose, mean, cov, params)
    d2 = jnp.where(valid[:, None] & active[None, :], ekf.mahalanobis_sq(z, predicted), jnp.inf)
    vis = landmarks.visibility(z, valid, active, predicted, d2, params, boundary)
    return vis, predicted, d2


def reference_of(params, pose, mean, cov, active, z, valid, boundary):
    _, predicted, d2 = jax_visibility(params, jnp.asarray(pose), jnp.asarray(mean),
                                      jnp.asarray(cov), jnp.asarray(active), jnp.asarray(z),
                                      jnp.asarray(valid), boundary)
    # The predicted range and S_rr in float64 from the geometry: S_rr = h Sigma h^T + sigma^2.
    dx, dy = mean[:, 0] - pose[0], mean[:, 1] - pose[1]
    rng_ = np.hypot(dx, dy)
    h = np.stack([dx / rng_, dy / rng_], -1)
    sigma = np.maximum(0.025 * rng_ + 0.01, 1e-4)
    s_rr = (h[:, 0] ** 2 * cov[:, 0] + 2 * h[:, 0] * h[:, 1] * cov[:, 1]
            + h[:, 1] ** 2 * cov[:, 2] + sigma**2)
    np.testing.assert_allclose(np.asarray(predicted.s_rr), s_rr, rtol=1e-10)
    # The pair distances in float64 too: nu^T S^-1 nu with S = H Sigma H^T + diag(sigma_r^2,
    # sigma_b^2), H the range-bearing Jacobian, nu = (z_r - r, wrap(z_b - b)).
    bearing = np.arctan2(dy, dx)
    rows = np.stack([h, np.stack([-dy, dx], -1) / rng_[:, None] ** 2], 1)  # (M, 2, 2)
    sigma_xy = np.array([[[c[0], c[1]], [c[1], c[2]]] for c in cov])
    s_full = rows @ sigma_xy @ np.swapaxes(rows, 1, 2)
    s_full[:, 0, 0] += sigma**2
    s_full[:, 1, 1] += np.maximum(0.0025 * rng_ + 0.001, 1e-5) ** 2
    nu = np.stack([z[:, None, 0] - rng_[None, :],
                   np.angle(np.exp(1j * (z[:, None, 1] - bearing[None, :])))], -1)  # (K, M, 2)
    d2_ref = np.einsum("kmi,mij,kmj->km", nu, np.linalg.inv(s_full), nu)
    pairs = valid[:, None] & active[None, :]
    np.testing.assert_allclose(np.asarray(d2)[pairs], d2_ref[pairs], rtol=1e-8)
    return reference_visibility(z, valid, active, rng_, bearing, s_rr,
                                np.where(pairs, d2_ref, np.inf), params, boundary)


@pytest.mark.parametrize("boundary", BOUNDARIES)
@pytest.mark.parametrize("jit", [False, True])
@pytest.mark.parametrize("seed", range(6))
def test_visibility_against_the_reference(boundary, jit, seed):
    case = random_case(seed, saturated=seed % 3 == 0)
    fn = lambda *a: jax_visibility(*a, boundary)[0]
    vis = (jax.jit(fn) if jit else fn)(*(case[:1] + tuple(jnp.asarray(a) for a in case[1:])))
    ref = reference_of(*case, boundary)
    for name in FIELDS:
        np.testing.assert_array_equal(np.asarray(getattr(vis, name)), ref[name], err_msg=name)


def test_the_cases_reach_every_rule():
    """The random cases above hold ring observations, ring landmarks and set-aside
    observations that gate with a ring landmark, so the reference comparison tests the
    rules that differ between the boundaries, not only the common inside."""
    counts = np.zeros(4, int)
    for seed in range(6):
        case = random_case(seed, saturated=seed % 3 == 0)
        ref = reference_of(*case, "loose_match")
        counts += [ref["set_aside_obs"].sum(), ref["set_aside_by_gate"].sum(),
                   (ref["matchable"] & ~reference_of(*case, "loose")["matchable"]).sum(),
                   ref["explained"].sum()]
    assert np.all(counts > 0), counts


def test_visibility_under_vmap():
    """A batch of cases (vmapped over pose, map and observations) equals case by case."""
    cases = [random_case(seed, saturated=seed % 2 == 0) for seed in range(4)]
    params = cases[0][0]
    stacked = [jnp.asarray(np.stack([c[i] for c in cases])) for i in range(1, 7)]
    vis = jax.vmap(lambda *a: jax_visibility(params, *a, "loose_match")[0])(*stacked)
    for i, case in enumerate(cases):
        ref = reference_of(params, *case[1:], "loose_match")
        for name in FIELDS:
            np.testing.assert_array_equal(np.asarray(getattr(vis, name))[i], ref[name],
                                          err_msg=f"case {i} {name}")


@pytest.mark.parametrize("boundary", BOUNDARIES)
def test_visibility_edges(boundary):
    params, pose, mean, cov, active, z, _ = random_case(0)
    # No valid observation: nothing set aside or matched, nothing explained.
    none = np.zeros(len(z), bool)
    vis = jax_visibility(params, *(jnp.asarray(a) for a in (pose, mean, cov, active, z, none)),
                         boundary)[0]
    for name in ("usable_obs", "set_aside_obs", "matching_obs", "explained"):
        assert not np.any(np.asarray(getattr(vis, name))), name
    # An observation nearer than min_range takes no part at all.
    near = z.copy()
    near[0] = [0.5, 0.0]
    vis = jax_visibility(params, *(jnp.asarray(a) for a in (pose, mean, cov, active, near,
                                                            np.ones(len(z), bool))), boundary)[0]
    assert not bool(vis.matching_obs[0]) and not bool(vis.set_aside_obs[0])
    # Landmarks a hair inside and a hair outside the ring's inner edge r = R_max - w (w from
    # their own S_rr): inside, every boundary matches and expects the first; the second is in
    # the ring (matched only by hard and loose_match, expected by hard alone).
    one = default_params(dtype=jnp.float64, max_range=12.0, range_noise=(0.0, 0.1))
    width = 5.0 * np.sqrt(0.1**2 + 1e-4)
    mean_edge = jnp.asarray([[12.0 - width - 1e-9, 0.0], [0.0, 12.0 - width + 1e-9]])
    predicted = ekf.predict_measurements(jnp.zeros(3), mean_edge,
                                         jnp.asarray([[1e-4, 0.0, 1e-4]] * 2), one)
    edge = landmarks.visibility(jnp.asarray([[3.0, 1.0], [0.0, 0.0]]),
                                jnp.asarray([True, False]), jnp.asarray([True, True]),
                                predicted, jnp.full((2, 2), jnp.inf), one, boundary)
    ring_matched = boundary != "loose"
    np.testing.assert_array_equal(np.asarray(edge.matchable), [True, ring_matched])
    np.testing.assert_array_equal(np.asarray(edge.expected), [True, boundary == "hard"])


# ---------------------------------------------------------------------------------------------
# Through the filter step (one particle, zero-noise motion, crafted states)


@pytest.fixture(scope="module")
def steps():
    out = {}
    for boundary in ("loose", "loose_match"):
        config = FilterConfig(num_particles=1, max_landmarks=4, max_obs=2, boundary=boundary)
        out[boundary] = (config, jax.jit(make_filter(config).step))
    return out


def step(steps, boundary, state, z, valid):
    _, jitted = steps[boundary]
    obs = make_observations(jnp.asarray(z, jnp.float32), valid=jnp.asarray(valid))
    # R_max 20 m, range std 0.02 d + 0.05: a ring of 5 sigma, about 2.2 m at 20 m.
    params = default_params(max_range=20.0, range_noise=(0.02, 0.05), **QUIET)
    return jitted(jax.random.key(0), state, params, jnp.zeros(3, jnp.float32), obs)


def test_a_ring_observation_updates_its_landmark(steps):
    """Tree at 19.0 m (in the ring), its landmark at 19.3 m. ``loose`` throws the observation
    away: no match, the landmark's mean, count and evidence unchanged. ``loose_match``
    matches it: the landmark moves towards 19.0 m and gains a hit; no twin either way."""
    results = {}
    for boundary in ("loose", "loose_match"):
        config, _ = steps[boundary]
        state = mapped_state(config, [[10.0, 0.0], [19.3, 0.0]], variance=1e-2, existence=1.0)
        new, info = step(steps, boundary, state, [[10.0, 0.0], [19.0, 0.0]], [True, True])
        results[boundary] = new.particles, info
        np.testing.assert_array_equal(np.asarray(new.particles.active[0]),
                                      [True, True, False, False])
        assert int(info.num_set_aside[0]) == 1
    loose, info = results["loose"]
    np.testing.assert_array_equal(np.asarray(info.match[0]), [0, -1])
    np.testing.assert_allclose(np.asarray(loose.landmark_mean[0, 1]), [19.3, 0.0], atol=1e-6)
    np.testing.assert_allclose(float(loose.existence[0, 1]), 1.0)
    matched, info = results["loose_match"]
    np.testing.assert_array_equal(np.asarray(info.match[0]), [0, 1])
    # The EKF's range update along x: gain k = P / (P + sigma_r^2), P = 0.01 m^2, sigma_r =
    # 0.02 * 19.3 + 0.05 at the predicted range. Tolerance 2 mm: the observation proposal
    # may shift the (quiet) pose by a hair, and the state is float32.
    gain = 0.01 / (0.01 + (0.02 * 19.3 + 0.05) ** 2)
    np.testing.assert_allclose(float(matched.landmark_mean[0, 1, 0]), 19.3 - gain * 0.3,
                               atol=2e-3)
    assert int(matched.observation_count[0, 1]) == 6
    assert float(matched.existence[0, 1]) > 1.0


def test_a_ring_observation_of_a_new_tree_is_still_not_born(steps):
    """An observation in the ring that matches nothing creates no landmark with
    ``loose_match`` either (the airlock's guard against twins)."""
    config, _ = steps["loose_match"]
    state = mapped_state(config, [[10.0, 0.0]], variance=1e-2, existence=1.0)
    new, info = step(steps, "loose_match", state, [[10.0, 0.0], [19.0, 1.5]], [True, True])
    np.testing.assert_array_equal(np.asarray(info.match[0]), [0, -1])
    np.testing.assert_array_equal(np.asarray(new.particles.active[0]),
                                  [True, False, False, False])


def test_an_unseen_ring_landmark_keeps_its_evidence(steps):
    """A landmark in the ring that nothing observes is neither matched nor penalised."""
    config, _ = steps["loose_match"]
    state = mapped_state(config, [[10.0, 0.0], [19.3, 0.0]], variance=1e-2, existence=0.5)
    new, _ = step(steps, "loose_match", state, [[10.0, 0.0], [0.0, 0.0]], [True, False])
    np.testing.assert_array_equal(np.asarray(new.particles.active[0, :2]), [True, True])
    np.testing.assert_allclose(float(new.particles.existence[0, 1]), 0.5)


def test_a_set_aside_observation_updates_a_landmark_inside_the_ring(steps):
    """An observation at 18.0 m lies in its own ring (20 - 5 (0.02 * 18 + 0.05) = 17.95 m);
    its tree's landmark at 17.7 m lies inside the ring (inner edge 20 - 5 sqrt(0.01 +
    (0.02 * 17.7 + 0.05)^2) = 17.92 m). ``loose`` sets the observation aside and spares the
    landmark the miss (it explains it); ``loose_match`` also matches the two."""
    for boundary, want in (("loose", -1), ("loose_match", 1)):
        config, _ = steps[boundary]
        state = mapped_state(config, [[10.0, 0.0], [17.7, 0.0]], variance=1e-2, existence=1.0)
        new, info = step(steps, boundary, state, [[10.0, 0.0], [18.0, 0.0]], [True, True])
        np.testing.assert_array_equal(np.asarray(info.match[0]), [0, want])
        assert int(info.num_set_aside[0]) == 1
        np.testing.assert_array_equal(np.asarray(new.particles.active[0]),
                                      [True, True, False, False])
        existence = float(new.particles.existence[0, 1])
        if want >= 0:
            assert existence > 1.0  # a hit
        else:
            assert existence == 1.0  # explained by the set-aside observation: no miss
