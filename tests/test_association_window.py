"""The association window's guard: ``landmarks.may_take_part`` (which landmarks could take
part in an association, bounded by range and bearing in O(M + K)) against a NumPy float64
reference and against the visibility rule it bounds; the count of such landmarks a window
leaves out (``StepInfo.window_cut``, ``Trace.window_cut``) in the filter; the run warning."""
import functools

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxslam
from jaxslam import ekf, landmarks, pipeline
from jaxslam.types import FilterConfig, default_params

CONFIG = FilterConfig(num_particles=1, max_landmarks=40, max_obs=8)


def _params(dtype=jnp.float64, **overrides):
    fields = dict(max_range=12.0, range_noise=(0.01, 0.02), range_std_floor=0.005)
    fields.update(overrides)
    params = default_params(CONFIG, **fields)
    return jax.tree.map(lambda leaf: jnp.asarray(leaf, dtype), params)


def ref_may_take_part(pose, mean, cov, active, params, boundary, z=None, valid=None,
                      pose_cov=None, bearings=True):
    """Plain NumPy float64: r <= R_max (hard); r <= R_max + a sqrt(S_rr) (loose), with
    S = H Sigma H^T + diag(s_r(r)^2, s_b(r)^2), H the range-bearing Jacobian of the landmark,
    s(r) = max(c_d r + c_0, floor); with observations also (r <= z_max + sqrt(g Z_rr) and
    cos b >= cos(beta_max) - sqrt(g Z_bb)) or (r <= min(horizon, miss_range) and
    cos b >= cos(miss_bearing)), b from atan2, Z = S + Hx Sigma_u Hx^T (Hx = [-H, (0, -1)^T],
    the pose's share), z_max the farthest and beta_max the widest valid observation (clipped
    to [0, pi]). ``bearings=False``: the range rules alone (the guard before it bounded
    bearings)."""
    pose, mean, cov = (np.asarray(v, np.float64) for v in (pose, mean, cov))
    dx, dy = mean[:, 0] - pose[0], mean[:, 1] - pose[1]
    distance = np.hypot(dx, dy)
    max_range = float(params.max_range)
    rows = np.stack([np.stack([dx, dy], -1) / distance[:, None],
                     np.stack([-dy, dx], -1) / distance[:, None] ** 2], 1)  # (M, 2, 2)
    sigma = np.array([[[c[0, 0], c[0, 1]], [c[0, 1], c[0, 2]]] for c in cov[:, None]])
    s = rows @ sigma @ np.swapaxes(rows, 1, 2)
    slope, const = (float(v) for v in np.asarray(params.range_noise))
    b_slope, b_const = (float(v) for v in np.asarray(params.bearing_noise))
    s[:, 0, 0] += np.maximum(slope * distance + const, float(params.range_std_floor)) ** 2
    s[:, 1, 1] += np.maximum(b_slope * distance + b_const,
                             float(params.bearing_std_floor)) ** 2
    if boundary == "hard":
        keep = np.asarray(active) & (distance <= max_range)
    else:
        keep = np.asarray(active) & (distance <= max_range + float(params.airlock_sigmas)
                                     * np.sqrt(s[:, 0, 0]))
    if z is None:
        return keep
    z, valid = np.asarray(z, np.float64), np.asarray(valid)
    big_z = s.copy()
    if pose_cov is not None:
        hx = np.concatenate([-rows, np.array([0.0, -1.0])[None, :, None].repeat(len(mean), 0)],
                            2)  # (M, 2, 3)
        big_z += hx @ np.asarray(pose_cov, np.float64) @ np.swapaxes(hx, 1, 2)
    bearing = np.abs(np.angle(np.exp(1j * (np.arctan2(dy, dx) - pose[2]))))  # via atan2
    gate, slack = float(params.association_gate), landmarks.SLACK
    farthest = z[valid, 0].max() if valid.any() else -np.inf
    widest = np.abs(z[valid, 1]).max() if valid.any() else -np.inf
    could_gate = ((distance <= farthest + (1 + slack) * np.sqrt(gate * big_z[:, 0, 0]))
                  & (np.cos(bearing) >= np.cos(np.clip(widest, 0.0, np.pi))
                     - (1 + slack) * np.sqrt(gate * big_z[:, 1, 1]) - slack))
    horizon = z[valid, 0].max() if valid.all() else np.inf
    could_miss = ((distance <= min(horizon, float(params.miss_range)))
                  & (np.cos(bearing) >= np.cos(min(float(params.miss_bearing), np.pi)) - slack))
    if not bearings:
        could_gate = distance <= farthest + (1 + slack) * np.sqrt(gate * big_z[:, 0, 0])
        could_miss = distance <= min(horizon, float(params.miss_range))
    return keep & (could_gate | could_miss)


def _random_map(rng, num=40, spread=15.0):
    mean = rng.uniform(-spread, spread, (num, 2))
    a = rng.uniform(0.0, 0.7, num) ** 2
    c = rng.uniform(0.0, 0.7, num) ** 2
    b = rng.uniform(-1.0, 1.0, num) * np.sqrt(a * c)  # positive semi-definite
    active = rng.random(num) < 0.8
    return mean, np.stack([a, b, c], -1), active


POSE = np.array([0.3, -0.2, 0.7])


@pytest.mark.parametrize("boundary", ["hard", "loose", "loose_match"])
@pytest.mark.parametrize("jit", [False, True])
def test_may_take_part_matches_the_numpy_reference(boundary, jit):
    rng = np.random.default_rng(0)
    params = _params()
    mean, cov, active = _random_map(rng)
    fn = lambda p, m, s, a: landmarks.may_take_part(p, m, s, a, params, boundary)
    fn = jax.jit(fn) if jit else fn
    got = np.asarray(fn(*(jnp.asarray(v) for v in (POSE, mean, cov, active))))
    want = ref_may_take_part(POSE, mean, cov, active, params, boundary)
    np.testing.assert_array_equal(got, want)
    assert 0 < want.sum() < active.sum()  # the case holds landmarks on both sides


def test_may_take_part_under_vmap_equals_each_map_alone():
    rng = np.random.default_rng(1)
    params = _params()
    maps = [_random_map(rng) for _ in range(3)]
    poses = rng.normal(0.0, 1.0, (3, 3))
    mean, cov, active = (np.stack([m[i] for m in maps]) for i in range(3))
    got = jax.vmap(lambda p, m, s, a: landmarks.may_take_part(p, m, s, a, params, "loose"))(
        *(jnp.asarray(v) for v in (poses, mean, cov, active)))
    for i in range(3):
        np.testing.assert_array_equal(
            np.asarray(got[i]), ref_may_take_part(poses[i], mean[i], cov[i], active[i],
                                                  params, "loose"))


def _against_reference(params, mean, cov, active, z, valid, pose_cov, jit):
    """``may_take_part`` (loose) at ``POSE`` with observations, asserted equal to the NumPy
    reference, which is returned."""
    fn = lambda p, m, s, a, zz, v: landmarks.may_take_part(
        p, m, s, a, params, "loose", zz, v, None if pose_cov is None else jnp.asarray(pose_cov))
    fn = jax.jit(fn) if jit else fn
    got = np.asarray(fn(*(jnp.asarray(v) for v in (POSE, mean, cov, active, z, valid))))
    want = ref_may_take_part(POSE, mean, cov, active, params, "loose", z, valid, pose_cov)
    np.testing.assert_array_equal(got, want)
    return want


@pytest.mark.parametrize("saturated", [False, True])
@pytest.mark.parametrize("with_pose_cov", [False, True])
@pytest.mark.parametrize("jit", [False, True])
def test_may_take_part_with_observations_matches_the_numpy_reference(saturated, with_pose_cov,
                                                                     jit):
    rng = np.random.default_rng(3)
    params = _params(miss_range=9.0)
    mean, cov, active = _random_map(rng)
    z = np.stack([rng.uniform(1.0, 12.0, 8), rng.uniform(-np.pi, np.pi, 8)], -1)
    valid = np.ones(8, bool) if saturated else rng.random(8) < 0.6
    pose_cov = np.diag([0.04, 0.09, 0.01]) + 0.01 if with_pose_cov else None
    want = _against_reference(params, mean, cov, active, z, valid, pose_cov, jit)
    region = ref_may_take_part(POSE, mean, cov, active, params, "loose")
    assert 0 < want.sum() < region.sum()  # the observations leave some of the region out


@pytest.mark.parametrize("with_pose_cov", [False, True])
@pytest.mark.parametrize("jit", [False, True])
def test_may_take_part_in_a_limited_view_matches_the_numpy_reference(with_pose_cov, jit):
    """A sensor with a half field of view of 0.9 rad (``miss_bearing``) reporting bearings
    within it: the implementation equals the reference, whose bearing rules leave out part
    of what the range rules alone keep."""
    rng = np.random.default_rng(6)
    params = _params(miss_range=9.0, miss_bearing=0.9)
    mean, cov, active = _random_map(rng)
    z = np.stack([rng.uniform(1.0, 12.0, 8), rng.uniform(-0.9, 0.9, 8)], -1)
    valid = rng.random(8) < 0.7
    pose_cov = np.diag([0.04, 0.09, 0.01]) + 0.01 if with_pose_cov else None
    want = _against_reference(params, mean, cov, active, z, valid, pose_cov, jit)
    all_round = ref_may_take_part(POSE, mean, cov, active, _params(miss_range=9.0), "loose", z,
                                  valid, pose_cov)
    assert 0 < want.sum() < all_round.sum()


def test_may_take_part_bearing_edges():
    """Zero covariances, a half view of 1 rad, one valid observation (of two rows) at bearing
    0.5 rad and 6 m: at 3 m a landmark is kept up to arccos(cos 0.5 - sqrt(g) s_b), 1.69
    rad (the observation's cosine bound), and, beyond, up to 1 rad (a miss); at 8.5 m, past
    the observation's reach and inside miss_range 9 m, only the miss keeps it (|b| <= 1
    rad); behind the robot nothing does."""
    params = _params(miss_range=9.0, miss_bearing=1.0, bearing_noise=(0.0, 0.2))
    # one row unused: the sensor is not saturated, so misses count out to miss_range
    z, valid = jnp.asarray([[6.0, 0.5], [0.0, 0.0]]), jnp.asarray([True, False])
    def kept(r, b, miss_bearing=1.0):
        point = jnp.asarray([[r * np.cos(b), r * np.sin(b)]])
        p = params._replace(miss_bearing=jnp.asarray(miss_bearing, jnp.float64))
        return bool(landmarks.may_take_part(jnp.zeros(3), point, jnp.zeros((1, 3)),
                                            jnp.ones(1, bool), p, "loose", z, valid)[0])
    assert float(params.association_gate) == 25.0
    # cos b >= cos(0.5) - sqrt(g) s_b (1 + SLACK) - SLACK: |b| up to about 1.69 rad
    reach = np.arccos(np.cos(0.5) - 5.0 * (1.0 + landmarks.SLACK) * 0.2 - landmarks.SLACK)
    assert kept(3.0, 0.0) and kept(3.0, -1.4) and kept(3.0, reach - 0.01)
    assert not kept(3.0, reach + 0.01) and not kept(3.0, np.pi)
    # with a view of 0.2 rad the miss no longer reaches 1 rad: only the observation does
    assert kept(3.0, reach - 0.01, miss_bearing=0.2)
    assert kept(8.5, 0.99) and not kept(8.5, 1.01) and not kept(8.5, -2.0)


def test_may_take_part_with_observations_edges():
    """No valid observation: only a possible miss keeps a landmark (r <= miss_range). A
    saturated sensor (every row valid, farthest 6 m): a landmark 1 cm beyond
    6 m + sqrt(g S_rr) is left out, one 1 cm inside is kept, though both are within R_max."""
    params = _params(miss_range=9.0)
    zero_cov, origin = jnp.zeros((4, 3)), jnp.zeros(3)
    ranges = jnp.asarray([3.0, 8.5, 9.5, 11.0])
    ahead = lambda r: jnp.stack([jnp.asarray(r, jnp.float64), jnp.zeros(len(r))], -1)
    z = jnp.asarray([[6.0, 0.5], [2.0, -0.5]])
    kept = landmarks.may_take_part(origin, ahead(ranges), zero_cov, jnp.ones(4, bool), params,
                                   "loose", z, jnp.asarray([False, False]))
    np.testing.assert_array_equal(kept, [True, True, False, False])
    def saturated(r):
        return bool(landmarks.may_take_part(origin, ahead([r]), zero_cov[:1],
                                            jnp.ones(1, bool), params, "loose", z,
                                            jnp.asarray([True, True]))[0])
    # the margin uses the landmark's own S_rr (zero covariance: sigma_r(r)^2) and the gate
    # 25: the last range kept solves r = 6 + 5 (0.01 r + 0.02)
    assert float(params.association_gate) == 25.0
    a = 5.0 * (1.0 + landmarks.SLACK)
    last = (6.0 + a * 0.02) / (1.0 - a * 0.01)
    assert saturated(last - 0.01) and not saturated(last + 0.01)


@functools.partial(jax.jit, static_argnums=0)
def _association_and_guard(config, params, particle, pose, obs, pose_cov):
    """One particle's association at ``pose`` (``step_propose.associate``) and the guard's
    answer (``landmarks.may_take_part``), in one compiled call (200 trials a case): the
    matched slot of each observation (K,), the landmarks counted as expected (M,), the ring
    landmarks that gate with a valid observation and so set it aside (M,) (``visibility``;
    the caller ignores them on the hard boundary) and the landmarks the guard keeps (M,)."""
    from jaxslam.step_propose import associate

    found = associate(config, params, particle, pose, obs, pose_cov)
    predicted = ekf.predict_measurements(pose, particle.landmark_mean, particle.landmark_cov,
                                         params)
    width = params.airlock_sigmas * jnp.sqrt(predicted.s_rr)
    ring = (particle.active & (predicted.range > params.max_range - width)
            & (predicted.range <= params.max_range + width))
    gated = jnp.any(obs.valid[:, None] & (ekf.mahalanobis_sq(obs.z, predicted)
                                          <= params.association_gate), axis=0)
    kept = landmarks.may_take_part(pose, particle.landmark_mean, particle.landmark_cov,
                                   particle.active, params, config.boundary, obs.z, obs.valid,
                                   pose_cov)
    return found.match, found.visibility.expected, ring & gated, kept


@pytest.mark.parametrize("boundary", ["hard", "loose", "loose_match"])
@pytest.mark.parametrize("with_pose_cov", [False, True])
@pytest.mark.parametrize("half_view", [np.pi, 0.8])
def test_every_landmark_the_association_uses_is_kept(boundary, with_pose_cov, half_view):
    """The guard's claim, checked on the full association (no window): over 200 random
    maps, poses and observation sets (fixed seed; some observations right at a landmark,
    some at random, some steps with all rows valid), every landmark that is matched, counted
    as a miss or, in the loose ring, sets an observation aside is in ``may_take_part``.
    With a half field of view of 0.8 rad the sensor reports and misses only bearings within
    it. Against the range rules alone (the NumPy reference without bearings) the guard keeps
    nothing more, and leaves out landmarks: 1,189-1,736 a case behind the 0.8 rad view,
    22-154 all round (asserted over 500 and over 10)."""
    rng = np.random.default_rng(4)
    config = FilterConfig(num_particles=1, max_landmarks=30, max_obs=6, boundary=boundary)
    params = _params(max_range=10.0, miss_range=8.0, miss_bearing=half_view)
    left_out = 0
    from mapped_state import mapped_state

    used_total = 0
    for trial in range(200):
        mean, cov, active = _random_map(rng, num=30, spread=12.0)
        state = mapped_state(config, mean, variance=0.01)
        particle = jax.tree.map(lambda a: a[0].astype(jnp.float64) if a.dtype.kind == "f"
                                else a[0], state.particles)
        particle = particle._replace(landmark_cov=jnp.asarray(cov, particle.landmark_cov.dtype),
                                     active=jnp.asarray(active))
        pose = jnp.asarray(rng.normal(0.0, 1.0, 3))
        targets = mean[rng.integers(0, 30, 6)] + rng.normal(0.0, 0.2, (6, 2))
        delta = targets - np.asarray(pose[:2])
        z = np.stack([np.hypot(*delta.T), np.arctan2(delta[:, 1], delta[:, 0]) - float(pose[2])],
                     -1)
        z[3:] = np.stack([rng.uniform(0.5, 11.0, 3), rng.uniform(-3.0, 3.0, 3)], -1)
        z[:, 1] = np.angle(np.exp(1j * z[:, 1]))
        valid = np.ones(6, bool) if trial % 3 == 0 else rng.random(6) < 0.7
        valid &= np.abs(z[:, 1]) <= half_view  # the sensor reports within its view only
        obs = jaxslam.Observations(jnp.asarray(z, particle.pose.dtype), jnp.asarray(valid),
                                   jnp.zeros(6, particle.pose.dtype), jnp.full(6, -1, jnp.int32))
        pose_cov = (jnp.asarray(np.diag([0.05, 0.05, 0.02]), particle.pose.dtype)
                    if with_pose_cov else None)
        match, expected, ring_gated, kept = (np.asarray(a) for a in _association_and_guard(
            config, params, particle, pose, obs, pose_cov))
        matched = np.zeros(30, bool)
        matched[match[match >= 0]] = True
        # A ring landmark that gates with an observation sets it aside (``visibility``);
        # ``explained`` matters only for expected landmarks, which are counted already.
        sets_aside = ring_gated if boundary != "hard" else False
        used = matched | expected | sets_aside
        assert not np.any(used & ~kept), trial
        used_total += used.sum()
        range_rules = ref_may_take_part(pose, particle.landmark_mean, particle.landmark_cov,
                                        particle.active, params, boundary, obs.z, obs.valid,
                                        pose_cov, bearings=False)
        assert not np.any(kept & ~range_rules), trial  # the bearings only ever leave out
        left_out += int(np.sum(range_rules & ~kept))
    assert used_total > 400  # the trials used landmarks often enough to mean something
    # the bearing bounds leave out landmarks the range rules kept: behind a limited view,
    # and, all round, those far off the widest observation's bearing
    assert left_out > (500 if half_view < np.pi else 10)


def test_may_take_part_edges():
    params = _params()
    zero_cov = jnp.zeros((3, 3))
    origin = jnp.zeros(3)
    ahead = lambda r: jnp.stack([jnp.asarray(r, jnp.float64), jnp.zeros(3)], -1)
    # hard: exactly at R_max takes part, inactive never does
    np.testing.assert_array_equal(
        landmarks.may_take_part(origin, ahead([12.0, 12.0, 1.0]), zero_cov,
                                jnp.asarray([True, False, True]), params, "hard"),
        [True, False, True])
    # loose with zero covariance: r <= 12 + a (0.01 r + 0.02), so the last r in is
    # (12 + 0.02 a) / (1 - 0.01 a); a landmark on the pose itself takes part
    a = float(params.airlock_sigmas)
    last = (12.0 + 0.02 * a) / (1.0 - 0.01 * a)
    distance = [0.999 * last, 1.001 * last, 0.0]
    np.testing.assert_array_equal(
        landmarks.may_take_part(origin, ahead(distance), zero_cov, jnp.ones(3, bool), params,
                                "loose"), [True, False, True])
    with pytest.raises(ValueError, match="boundary"):
        landmarks.may_take_part(origin, ahead(distance), zero_cov, jnp.ones(3, bool), params,
                                "soft")


@pytest.mark.parametrize("boundary", ["hard", "loose", "loose_match"])
def test_may_take_part_is_the_visibility_rules_own_region(boundary):
    """A landmark is in ``may_take_part`` exactly when it is matchable or in the loose ring
    by ``landmarks.visibility``'s own rule on the predicted measurement (its S_rr; ranges
    over R_min here, so matchable is r <= R_max - w_m, or r <= R_max when hard). 2,000
    random landmarks around R_max (fixed seed), covariances up to 0.5 m^2."""
    rng = np.random.default_rng(2)
    params = _params()
    mean, cov, _ = _random_map(rng, num=2000, spread=14.0)
    active = jnp.ones(2000, bool)
    mean, cov, pose = jnp.asarray(mean), jnp.asarray(cov), jnp.asarray(POSE)
    predicted = ekf.predict_measurements(pose, mean, cov, params)
    obs_z = jnp.asarray([[100.0, 0.0]])  # one observation no landmark could explain
    vis = landmarks.visibility(obs_z, jnp.asarray([True]), active, predicted,
                               jnp.full((1, 2000), jnp.inf), params, boundary)
    width = params.airlock_sigmas * jnp.sqrt(predicted.s_rr)
    ring = ((predicted.range > params.max_range - width)
            & (predicted.range <= params.max_range + width))
    used = np.asarray(vis.matchable | (ring if boundary != "hard" else False))
    in_min_range = np.asarray(predicted.range >= params.min_range)
    bound = np.asarray(landmarks.may_take_part(pose, mean, cov, active, params, boundary))
    assert used.sum() > 500  # enough landmarks in view to mean something
    np.testing.assert_array_equal(used, bound & in_min_range)


@pytest.mark.parametrize("kind", ["stable", "greedy", "hungarian"])
@pytest.mark.parametrize("boundary", ["hard", "loose", "loose_match"])
@pytest.mark.parametrize("with_pose_cov", [False, True])
def test_a_window_whose_cut_is_zero_associates_as_the_full_map(kind, boundary, with_pose_cov):
    """The claim the count stands for: 300 random maps of 40 landmarks, poses and 8
    observations (fixed seed; half of them at landmarks, every third trial saturated),
    associated with a window of 20 and with none. Where the window's cut is 0, the matches,
    the usable and set-aside observations and the landmarks penalised (expected and not
    explained) are identical; such trials must include landmarks outside the window."""
    rng = np.random.default_rng(5)
    trials, slots, rows, window = 300, 40, 8, 20
    params = _params(max_range=10.0, miss_range=8.0)
    mean = rng.uniform(-12.0, 12.0, (trials, slots, 2))
    a, c = rng.uniform(0.0, 0.4, (2, trials, slots)) ** 2
    cov = np.stack([a, rng.uniform(-1, 1, (trials, slots)) * np.sqrt(a * c), c], -1)
    active = rng.random((trials, slots)) < 0.8
    pose = rng.normal(0.0, 1.0, (trials, 3))
    pick = mean[np.arange(trials)[:, None], rng.integers(0, slots, (trials, rows))]
    targets = np.where(np.arange(rows)[None, :, None] < rows // 2,
                       pick + rng.normal(0.0, 0.15, pick.shape),
                       pose[:, None, :2] + rng.uniform(-11.0, 11.0, pick.shape))
    delta = targets - pose[:, None, :2]
    z = np.stack([np.hypot(delta[..., 0], delta[..., 1]),
                  np.angle(np.exp(1j * (np.arctan2(delta[..., 1], delta[..., 0])
                                        - pose[:, 2:3])))], -1)
    valid = (rng.random((trials, rows)) < 0.7) | (np.arange(trials) % 3 == 0)[:, None]
    pose_cov = np.diag([0.05, 0.05, 0.02]) if with_pose_cov else None
    from jaxslam.step_propose import associate
    from mapped_state import mapped_state

    def run(window):
        config = FilterConfig(num_particles=1, max_landmarks=slots, max_obs=rows,
                              boundary=boundary, association=kind,
                              association_window=window)
        base = jax.tree.map(lambda leaf: leaf[0].astype(jnp.float64)
                            if leaf.dtype.kind == "f" else leaf[0],
                            mapped_state(config, np.zeros((slots, 2))).particles)

        def one(mean, cov, active, pose, z, valid):
            particle = base._replace(landmark_mean=mean, landmark_cov=cov, active=active)
            obs = jaxslam.Observations(z, valid, jnp.zeros(rows), jnp.full(rows, -1, jnp.int32))
            found = associate(config, params, particle, pose, obs,
                              None if pose_cov is None else jnp.asarray(pose_cov))
            vis = found.visibility
            return (found.match, vis.usable_obs, vis.set_aside_obs,
                    vis.expected & ~vis.explained, vis.matching_obs, found.window_cut)

        return jax.jit(jax.vmap(one))(*(jnp.asarray(v) for v in (mean, cov, active, pose, z,
                                                                  valid)))

    full, windowed = run(0), run(window)
    cut = np.asarray(windowed[-1])
    assert np.all(np.asarray(full[-1]) == 0)
    exact = cut == 0
    outside = active.sum(axis=1) > window
    assert np.sum(exact & outside) >= 30, (np.sum(exact & outside))  # not a vacuous check
    assert np.sum(~exact) >= 10  # and the guard does fire on small windows' trials
    for name, f, w in zip(("match", "usable", "set aside", "penalised", "matching"), full,
                          windowed):
        np.testing.assert_array_equal(np.asarray(f)[exact], np.asarray(w)[exact],
                                      err_msg=name)


def _line_of_trees(num_trees, steps=4):
    """Trees on a line ahead of a robot that stands still; every tree observed exactly."""
    trees = np.stack([np.linspace(2.0, 9.0, num_trees), np.full(num_trees, 0.5)], -1)
    z = np.zeros((steps, 8, 2), np.float32)
    valid = np.zeros((steps, 8), bool)
    z[:, :num_trees] = np.stack([np.hypot(*trees.T), np.arctan2(trees[:, 1], trees[:, 0])], -1)
    valid[:, :num_trees] = True
    obs = jaxslam.make_observations(jnp.asarray(z), jnp.asarray(valid))
    return jnp.zeros((steps, 3), jnp.float32), obs


@pytest.mark.parametrize("proposal", ["motion", "observation"])
def test_window_cut_is_zero_when_the_window_holds_the_view(proposal):
    controls, obs = _line_of_trees(6)
    config = FilterConfig(num_particles=4, max_landmarks=16, max_obs=8, association_window=10,
                          proposal=proposal)
    params = default_params(config, max_range=15.0)
    _, trace = jaxslam.run_filter(config, jax.random.PRNGKey(0), params, controls, obs)
    np.testing.assert_array_equal(np.asarray(trace.window_cut), 0)
    np.testing.assert_array_equal(np.asarray(trace.num_landmarks), 6)


@pytest.mark.parametrize("proposal", ["motion", "observation"])
def test_window_cut_counts_the_landmarks_in_view_left_out(proposal):
    """Six trees in view, a window of four: at the second step (the map holds the six from
    the first) each particle's window leaves out exactly two landmarks in view."""
    controls, obs = _line_of_trees(6)
    config = FilterConfig(num_particles=4, max_landmarks=16, max_obs=8, association_window=4,
                          proposal=proposal)
    params = default_params(config, max_range=15.0)
    step = jax.jit(jaxslam.make_filter(config).step)
    state = jaxslam.make_filter(config).init(jnp.zeros(3, jnp.float32))
    row = lambda t: jax.tree.map(lambda leaf: leaf[t], obs)
    state, first = step(jax.random.PRNGKey(0), state, params, controls[0], row(0))
    assert int(first.window_cut) == 0  # an empty map
    state, second = step(jax.random.PRNGKey(1), state, params, controls[1], row(1))
    chex.assert_shape(second.window_cut, ())
    assert int(second.window_cut) == 2
    _, trace = jaxslam.run_filter(config, jax.random.PRNGKey(0), params, controls, obs)
    assert int(trace.window_cut[0]) == 0 and np.all(np.asarray(trace.window_cut[1:]) >= 2)
    warnings = pipeline.run_warnings(trace, obs.valid, 0.1, config.num_particles)
    assert any("association window left out landmarks" in w and "in 3 steps" in w
               for w in warnings), warnings


def test_no_window_reports_no_cut():
    controls, obs = _line_of_trees(6)
    config = FilterConfig(num_particles=4, max_landmarks=16, max_obs=8)
    _, trace = jaxslam.run_filter(config, jax.random.PRNGKey(0),
                                  default_params(config, max_range=15.0), controls, obs)
    np.testing.assert_array_equal(np.asarray(trace.window_cut), 0)
    assert not any("window" in w for w in pipeline.run_warnings(trace, obs.valid, 0.1, 4))
