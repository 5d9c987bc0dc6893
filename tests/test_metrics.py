"""Metrics against plain NumPy float64 references, known answers, masks, jit, vmap and edges."""
import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.optimize import linear_sum_assignment

from jaxslam import metrics

RTOL = 1e-9


# ---------------------------------------------------------------------------------------------
# NumPy float64 references


def ref_wrap(angle):
    return (np.asarray(angle) + np.pi) % (2 * np.pi) - np.pi


def ref_se2(pose):
    c, s = np.cos(pose[2]), np.sin(pose[2])
    return np.array([[c, -s, pose[0]], [s, c, pose[1]], [0.0, 0.0, 1.0]])


def ref_kabsch_2d(est_xy, true_xy):
    """SVD Kabsch without scale: R, t minimising sum ||R e + t - q||^2."""
    est_c, true_c = est_xy.mean(0), true_xy.mean(0)
    h = (est_xy - est_c).T @ (true_xy - true_c)
    u, _, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(vt.T @ u.T))
    rotation = vt.T @ np.diag([1.0, d]) @ u.T
    return rotation, true_c - rotation @ est_c


def ref_ate(est, truth, valid, align):
    est_xy, true_xy = est[valid, :2], truth[valid, :2]
    if len(est_xy) == 0:
        return 0.0
    if align:
        rotation, shift = ref_kabsch_2d(est_xy, true_xy)
        est_xy = est_xy @ rotation.T + shift
    return float(np.sqrt(np.mean(np.sum((est_xy - true_xy) ** 2, axis=1))))


def ref_rpe(est, truth, delta, valid, all_pairs):
    n = len(est)
    if all_pairs:
        pairs = [(i, i + delta) for i in range(n) if i + delta < n]
    else:
        ids = list(range(0, n, delta))
        pairs = list(zip(ids[:-1], ids[1:]))
    trans, rot = [], []
    for i, j in pairs:
        if not (valid[i] and valid[j]):
            continue
        q_rel = np.linalg.inv(ref_se2(truth[i])) @ ref_se2(truth[j])
        p_rel = np.linalg.inv(ref_se2(est[i])) @ ref_se2(est[j])
        error = np.linalg.inv(q_rel) @ p_rel
        trans.append(np.hypot(error[0, 2], error[1, 2]))
        rot.append(abs(np.arctan2(error[1, 0], error[0, 0])))
    if not trans:
        return 0.0, 0.0
    return float(np.sqrt(np.mean(np.square(trans)))), float(np.sqrt(np.mean(np.square(rot))))


def ref_match(est_mean, est_active, true_centres, true_valid, threshold):
    match = -np.ones(len(est_mean), dtype=int)
    for m in range(len(est_mean)):
        if not est_active[m]:
            continue
        best, best_d = -1, np.inf
        for n in range(len(true_centres)):
            d = np.hypot(*(est_mean[m] - true_centres[n]))
            if true_valid[n] and d < best_d:
                best, best_d = n, d
        if best_d <= threshold:
            match[m] = best
    return match


def ref_map_metrics(est_mean, est_active, true_centres, true_valid, threshold):
    match = ref_match(est_mean, est_active, true_centres, true_valid, threshold)
    closest = {}
    for m, n in enumerate(match):
        if n >= 0:
            d = np.hypot(*(est_mean[m] - true_centres[n]))
            closest[n] = min(closest.get(n, np.inf), d)
    map_error = float(np.mean(list(closest.values()))) if closest else 0.0
    num_matched = int(np.sum(match >= 0))
    return dict(
        map_error=map_error,
        redundant=num_matched - len(closest),
        orphan=int(np.sum(est_active & (match < 0))),
        num_landmarks=int(np.sum(est_active)),
        num_trees_mapped=len(closest),
    )


def ref_gospa(est, est_valid, truth, truth_valid, c, p):
    """GOSPA alpha=2 from scipy's optimal assignment on the valid points only."""
    x, y = est[est_valid], truth[truth_valid]
    localisation, num_close = 0.0, 0
    if len(x) and len(y):
        distance = np.hypot(x[:, None, 0] - y[None, :, 0], x[:, None, 1] - y[None, :, 1])
        rows, cols = linear_sum_assignment(np.minimum(distance, c) ** p)
        close = distance[rows, cols] < c
        localisation = float(np.sum(distance[rows, cols][close] ** p))
        num_close = int(close.sum())
    missed = c**p / 2 * (len(y) - num_close)
    false = c**p / 2 * (len(x) - num_close)
    return (localisation + missed + false) ** (1 / p), localisation, missed, false


def ref_pose_nees(mean, cov, truth):
    error = mean - truth
    error[2] = ref_wrap(error[2])
    return float(error @ np.linalg.solve(cov, error))


def ref_moments(pose, log_weight):
    weight = np.exp(log_weight - log_weight.max())
    weight /= weight.sum()
    mean_xy = weight @ pose[:, :2]
    mean_theta = np.arctan2(weight @ np.sin(pose[:, 2]), weight @ np.cos(pose[:, 2]))
    deviation = np.column_stack([pose[:, :2] - mean_xy, ref_wrap(pose[:, 2] - mean_theta)])
    cov = np.einsum("p,pi,pj->ij", weight, deviation, deviation)
    return np.append(mean_xy, mean_theta), cov


# ---------------------------------------------------------------------------------------------
# Helpers


def random_trajectory(rng, num_poses):
    steps = np.column_stack(
        [rng.uniform(0.2, 1.0, num_poses), rng.normal(0, 0.1, num_poses),
         rng.normal(0, 0.3, num_poses)]
    )
    poses = [np.zeros(3)]
    for step in steps[1:]:
        poses.append((ref_se2(poses[-1]) @ np.array([step[0], step[1], 1.0]))[:2].tolist()
                     + [ref_wrap(poses[-1][2] + step[2])])
        poses[-1] = np.array(poses[-1])
    return np.array(poses)


def noisy(rng, poses, scale):
    out = poses + rng.normal(0, scale, poses.shape)
    out[:, 2] = ref_wrap(out[:, 2])
    return out


def rigid(poses, alignment):
    """Apply the SE(2) pose alignment to a trajectory (positions and headings)."""
    out = poses.copy()
    out[:, :2] = poses[:, :2] @ ref_se2(alignment)[:2, :2].T + alignment[:2]
    out[:, 2] = ref_wrap(poses[:, 2] + alignment[2])
    return out


gospa_jit = jax.jit(metrics.gospa, static_argnames="alpha")
both_jit = pytest.mark.parametrize("use_jit", [False, True], ids=["eager", "jit"])


def maybe_jit(fn, use_jit, **kwargs):
    return jax.jit(fn, **kwargs) if use_jit else fn


# ---------------------------------------------------------------------------------------------
# Poses and trajectories


@both_jit
def test_final_pose_and_heading_error(use_jit):
    est = jnp.array([1.0, 2.0, 3.1])
    truth = jnp.array([4.0, 6.0, -3.1])
    chex.assert_trees_all_close(
        maybe_jit(metrics.final_pose_error, use_jit)(est, truth), 5.0, rtol=RTOL
    )
    # 3.1 - (-3.1) = 6.2 wraps to 6.2 - 2 pi
    chex.assert_trees_all_close(
        maybe_jit(metrics.heading_error, use_jit)(est, truth), 2 * np.pi - 6.2, rtol=1e-9
    )


@both_jit
@pytest.mark.parametrize("align", [False, True])
def test_ate_matches_reference(use_jit, align):
    rng = np.random.default_rng(0)
    ate = maybe_jit(metrics.ate_rmse, use_jit, static_argnames="align")
    for _ in range(5):
        truth = random_trajectory(rng, 40)
        est = rigid(noisy(rng, truth, 0.3), rng.normal(0, [2.0, 2.0, 1.0]))
        valid = rng.random(40) > 0.3
        got = ate(jnp.asarray(est), jnp.asarray(truth), jnp.asarray(valid), align=align)
        np.testing.assert_allclose(got, ref_ate(est, truth, valid, align), rtol=1e-9)


def test_ate_alignment_known_answer():
    rng = np.random.default_rng(1)
    truth = random_trajectory(rng, 30)
    alignment = np.array([3.0, -5.0, 2.5])
    moved = rigid(truth, alignment)
    assert float(metrics.ate_rmse(jnp.asarray(moved), jnp.asarray(truth), align=True)) < 1e-9
    assert float(metrics.ate_rmse(jnp.asarray(moved), jnp.asarray(truth))) > 1.0
    # align_se2 recovers the inverse transform
    recovered = metrics.align_se2(jnp.asarray(moved), jnp.asarray(truth))
    inverse = np.linalg.inv(ref_se2(alignment))
    np.testing.assert_allclose(recovered[:2], inverse[:2, 2], atol=1e-9)
    np.testing.assert_allclose(ref_wrap(recovered[2] + alignment[2]), 0.0, atol=1e-9)


def test_ate_padding_ignored_and_empty():
    rng = np.random.default_rng(2)
    truth = random_trajectory(rng, 20)
    est = noisy(rng, truth, 0.2)
    valid = np.arange(20) < 12
    garbage = est.copy()
    garbage[12:] = 1e6
    for align in (False, True):
        a = metrics.ate_rmse(jnp.asarray(est[:12]), jnp.asarray(truth[:12]), align=align)
        b = metrics.ate_rmse(jnp.asarray(garbage), jnp.asarray(truth), jnp.asarray(valid), align)
        np.testing.assert_allclose(a, b, rtol=1e-9)
        none_valid = jnp.zeros(20, bool)
        assert float(metrics.ate_rmse(jnp.asarray(est), jnp.asarray(truth), none_valid, align)) == 0
        empty = jnp.zeros((0, 3))
        assert float(metrics.ate_rmse(empty, empty, align=align)) == 0.0


@both_jit
@pytest.mark.parametrize("delta,all_pairs", [(1, False), (3, False), (3, True), (7, True)])
def test_rpe_matches_reference(use_jit, delta, all_pairs):
    rng = np.random.default_rng(3)
    rpe = maybe_jit(metrics.rpe, use_jit, static_argnames=("delta", "all_pairs"))
    for _ in range(3):
        truth = random_trajectory(rng, 25)
        est = noisy(rng, truth, 0.1)
        valid = rng.random(25) > 0.2
        got = rpe(jnp.asarray(est), jnp.asarray(truth), delta=delta, valid=jnp.asarray(valid),
                  all_pairs=all_pairs)
        np.testing.assert_allclose(got, ref_rpe(est, truth, delta, valid, all_pairs), rtol=1e-9)


def test_rpe_known_answers_and_edges():
    rng = np.random.default_rng(4)
    truth = random_trajectory(rng, 15)
    moved = rigid(truth, np.array([1.0, 2.0, 0.7]))
    # RPE is invariant to a global rigid transform.
    np.testing.assert_allclose(metrics.rpe(jnp.asarray(moved), jnp.asarray(truth), 2), 0.0,
                               atol=1e-9)
    assert float(metrics.rpe(jnp.asarray(noisy(rng, truth, 0.1)), jnp.asarray(truth), 2)[0]) > 0
    # too short for one pair: zeros, not NaN
    short = jnp.asarray(truth[:3])
    assert metrics.rpe(short, short, 5) == (0.0, 0.0)
    with pytest.raises(ValueError, match="delta"):
        metrics.rpe(short, short, 0)


def test_divergence_flag():
    errors = jnp.array([0.5, 2.0, jnp.nan, 1.0])
    np.testing.assert_array_equal(metrics.divergence_flag(errors, 1.0), [False, True, True, False])


# ---------------------------------------------------------------------------------------------
# Consistency


@both_jit
def test_pose_nees_matches_reference(use_jit):
    rng = np.random.default_rng(5)
    nees = maybe_jit(metrics.pose_nees, use_jit)
    for _ in range(10):
        a = rng.normal(size=(3, 3))
        cov = a @ a.T + 0.1 * np.eye(3)
        mean = rng.normal(size=3) * [1, 1, 3]
        truth = rng.normal(size=3) * [1, 1, 3]
        np.testing.assert_allclose(nees(mean, cov, truth), ref_pose_nees(mean, cov, truth),
                                   rtol=1e-9)
    # heading difference wrapped: 3.1 vs -3.1 is 0.083 rad apart, not 6.2
    got = metrics.pose_nees(jnp.array([0.0, 0.0, 3.1]), jnp.eye(3), jnp.array([0.0, 0.0, -3.1]))
    np.testing.assert_allclose(got, (2 * np.pi - 6.2) ** 2, rtol=1e-9)


@both_jit
def test_particle_pose_moments(use_jit):
    rng = np.random.default_rng(6)
    moments = maybe_jit(metrics.particle_pose_moments, use_jit)
    for _ in range(5):
        pose = rng.normal(size=(50, 3)) * [1, 1, 0.3]
        pose[:, 2] = ref_wrap(pose[:, 2] + np.pi)  # headings straddle the +-pi cut
        log_weight = rng.normal(size=50) * 2
        log_weight[:5] = -np.inf
        mean, cov = moments(jnp.asarray(pose), jnp.asarray(log_weight))
        ref_mean, ref_cov = ref_moments(pose, log_weight)
        np.testing.assert_allclose(mean, ref_mean, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(cov, ref_cov, rtol=1e-9, atol=1e-12)
        assert abs(abs(float(mean[2])) - np.pi) < 0.5  # circular mean near pi, not near 0
    # all -inf log-weights: uniform, finite
    mean, cov = metrics.particle_pose_moments(jnp.asarray(pose), jnp.full(50, -jnp.inf))
    ref_mean, ref_cov = ref_moments(pose, np.zeros(50))
    np.testing.assert_allclose(mean, ref_mean, rtol=1e-9)
    np.testing.assert_allclose(cov, ref_cov, rtol=1e-9)


# ---------------------------------------------------------------------------------------------
# Maps


def random_map(rng, num_slots, num_trees):
    trees = rng.uniform(0, 30, (num_trees, 2))
    tree_valid = rng.random(num_trees) > 0.2
    owner = rng.integers(0, num_trees, num_slots)
    landmarks = trees[owner] + rng.normal(0, 0.5, (num_slots, 2))
    landmarks[rng.random(num_slots) < 0.2] = rng.uniform(0, 30, (1, 2))  # some strays
    active = rng.random(num_slots) > 0.25
    return landmarks, active, trees, tree_valid


@both_jit
def test_match_and_map_metrics_match_reference(use_jit):
    rng = np.random.default_rng(7)
    match = maybe_jit(metrics.match_landmarks, use_jit)
    map_metrics = maybe_jit(metrics.map_metrics, use_jit)
    for _ in range(10):
        landmarks, active, trees, tree_valid = random_map(rng, 24, 12)
        threshold = 1.0
        args = (jnp.asarray(landmarks), jnp.asarray(active), jnp.asarray(trees),
                jnp.asarray(tree_valid), threshold)
        np.testing.assert_array_equal(match(*args), ref_match(landmarks, active, trees,
                                                              tree_valid, threshold))
        got = map_metrics(*args)._asdict()
        want = ref_map_metrics(landmarks, active, trees, tree_valid, threshold)
        for name, value in want.items():
            np.testing.assert_allclose(got[name], value, rtol=1e-9, err_msg=name)


def test_map_metrics_known_answers():
    trees = jnp.array([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0]])
    landmarks = jnp.array([[0.1, 0.0], [0.0, 0.3], [10.0, 0.2], [50.0, 50.0], [3.0, 3.0]])
    active = jnp.array([True, True, True, True, False])
    result = metrics.map_metrics(landmarks, active, trees, jnp.ones(3, bool), 1.0)
    assert int(result.redundant) == 1  # the duplicate at (0, 0.3)
    assert int(result.orphan) == 1  # (50, 50) is far from everything; (3, 3) is inactive
    assert int(result.num_landmarks) == 4
    assert int(result.num_trees_mapped) == 2
    np.testing.assert_allclose(result.map_error, (0.1 + 0.2) / 2, rtol=1e-9)  # closest per tree


def test_map_metrics_alignment():
    rng = np.random.default_rng(8)
    landmarks, active, trees, tree_valid = random_map(rng, 16, 8)
    alignment = np.array([4.0, -2.0, 1.2])
    inverse = np.linalg.inv(ref_se2(alignment))
    moved = landmarks @ inverse[:2, :2].T + inverse[:2, 2]
    plain = metrics.map_metrics(jnp.asarray(landmarks), jnp.asarray(active), jnp.asarray(trees),
                                jnp.asarray(tree_valid), 1.0)
    moved_args = (jnp.asarray(moved), jnp.asarray(active), jnp.asarray(trees),
                  jnp.asarray(tree_valid), 1.0)
    # the moved map scores differently; aligned by the forward transform it scores as the plain
    assert int(metrics.map_metrics(*moved_args).num_trees_mapped) < int(plain.num_trees_mapped)
    aligned = metrics.map_metrics(*moved_args, jnp.asarray(alignment))
    chex.assert_trees_all_close(aligned, plain, rtol=1e-9)


def test_map_metrics_padding_ignored():
    rng = np.random.default_rng(9)
    landmarks, active, trees, tree_valid = random_map(rng, 20, 10)
    base = metrics.map_metrics(jnp.asarray(landmarks), jnp.asarray(active), jnp.asarray(trees),
                               jnp.asarray(tree_valid), 1.0)
    # extra inactive slots right on top of trees, extra invalid trees right on landmarks
    pad_landmarks = np.concatenate([landmarks, trees[:5]])
    pad_active = np.concatenate([active, np.zeros(5, bool)])
    pad_trees = np.concatenate([trees, landmarks[:5]])
    pad_valid = np.concatenate([tree_valid, np.zeros(5, bool)])
    padded = metrics.map_metrics(jnp.asarray(pad_landmarks), jnp.asarray(pad_active),
                                 jnp.asarray(pad_trees), jnp.asarray(pad_valid), 1.0)
    chex.assert_trees_all_close(padded, base, rtol=1e-12)


@pytest.mark.parametrize("num_slots,num_trees", [(0, 5), (5, 0), (0, 0), (5, 5)])
def test_map_metrics_empty(num_slots, num_trees):
    landmarks = jnp.ones((num_slots, 2))
    trees = jnp.ones((num_trees, 2)) * 2
    # (5, 5): nothing active and no valid tree
    result = metrics.map_metrics(landmarks, jnp.zeros(num_slots, bool), trees,
                                 jnp.zeros(num_trees, bool), 1.0)
    assert all(np.isfinite(np.asarray(v)) for v in result)
    assert float(result.map_error) == 0.0 and int(result.num_landmarks) == 0
    assert int(result.redundant) == 0 and int(result.orphan) == 0
    if num_slots:  # active landmarks but no (valid) tree: all orphans
        result = metrics.map_metrics(landmarks, jnp.ones(num_slots, bool), trees,
                                     jnp.zeros(num_trees, bool), 1.0)
        assert int(result.orphan) == num_slots and float(result.map_error) == 0.0
    nees = metrics.map_nees(landmarks, jnp.tile(jnp.eye(2), (num_slots, 1, 1)),
                            jnp.zeros(num_slots, bool), trees, jnp.zeros(num_trees, bool), 1.0)
    assert float(nees) == 0.0


def test_map_nees_matches_reference_and_packed_cov():
    rng = np.random.default_rng(10)
    landmarks, active, trees, tree_valid = random_map(rng, 20, 10)
    a = rng.normal(size=(20, 2, 2)) * 0.3
    cov = a @ np.transpose(a, (0, 2, 1)) + 0.05 * np.eye(2)
    match = ref_match(landmarks, active, trees, tree_valid, 1.0)
    best = {}
    for m, n in enumerate(match):
        if n >= 0:
            d = np.hypot(*(landmarks[m] - trees[n]))
            if d < best.get(n, (np.inf, -1))[0]:
                best[n] = (d, m)
    values = [(landmarks[m] - trees[n]) @ np.linalg.solve(cov[m], landmarks[m] - trees[n])
              for n, (_, m) in best.items()]
    args = (jnp.asarray(active), jnp.asarray(trees), jnp.asarray(tree_valid), 1.0)
    full = metrics.map_nees(jnp.asarray(landmarks), jnp.asarray(cov), *args)
    packed_cov = np.stack([cov[:, 0, 0], cov[:, 0, 1], cov[:, 1, 1]], -1)
    packed = metrics.map_nees(jnp.asarray(landmarks), jnp.asarray(packed_cov), *args)
    np.testing.assert_allclose(full, np.mean(values), rtol=1e-9)
    np.testing.assert_allclose(packed, np.mean(values), rtol=1e-9)
    with pytest.raises(ValueError, match=r"\(M, 2, 2\)"):
        metrics.map_nees(jnp.asarray(landmarks), jnp.ones((20, 4)), *args)


# ---------------------------------------------------------------------------------------------
# GOSPA


@both_jit
def test_gospa_matches_scipy_reference(use_jit):
    rng = np.random.default_rng(11)
    gospa = maybe_jit(metrics.gospa, use_jit)
    # eager Hungarian dispatches op by op (slow): fewer trials without jit
    for trial in range(20) if use_jit else (0, 11):
        num_est, num_true = (12, 9) if trial % 2 else (8, 12)  # both M > N and M < N
        est = rng.uniform(0, 10, (num_est, 2))
        truth = rng.uniform(0, 10, (num_true, 2))
        est_valid = rng.random(num_est) > 0.3
        truth_valid = rng.random(num_true) > 0.3
        c, p = (2.0, 2.0) if trial < 10 else (3.0, 1.0)
        got = gospa(jnp.asarray(est), jnp.asarray(est_valid), jnp.asarray(truth),
                    jnp.asarray(truth_valid), c, p)
        want = ref_gospa(est, est_valid, truth, truth_valid, c, p)
        np.testing.assert_allclose(got[:4], want, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(got.missed, c**p / 2 * int(got.num_missed), rtol=1e-12)


def test_gospa_known_answers():
    c, p = 3.0, 2.0
    points = jnp.array([[0.0, 0.0], [5.0, 1.0], [2.0, 7.0]])
    same = gospa_jit(points, jnp.ones(3, bool), points, jnp.ones(3, bool), c, p)
    assert float(same.distance) == 0.0
    for n in (1, 3):
        empty_vs_n = gospa_jit(jnp.zeros((0, 2)), jnp.zeros(0, bool), points[:n],
                                   jnp.ones(n, bool), c, p)
        np.testing.assert_allclose(empty_vs_n.distance, (n * c**p / 2) ** (1 / p), rtol=1e-12)
        assert int(empty_vs_n.num_missed) == n and int(empty_vs_n.num_false) == 0
        # the same with all estimated rows padded
        padded = gospa_jit(points, jnp.zeros(3, bool), points[:n], jnp.ones(n, bool), c, p)
        np.testing.assert_allclose(padded.distance, (n * c**p / 2) ** (1 / p), rtol=1e-12)
    # a pair farther than c is one missed plus one false, not a localisation error
    far = gospa_jit(jnp.array([[0.0, 0.0]]), jnp.ones(1, bool), jnp.array([[10.0, 0.0]]),
                        jnp.ones(1, bool), c, p)
    np.testing.assert_allclose(far.distance, c, rtol=1e-12)
    assert float(far.localisation) == 0.0 and int(far.num_missed) == 1
    both_empty = gospa_jit(jnp.zeros((0, 2)), jnp.zeros(0, bool), jnp.zeros((0, 2)),
                               jnp.zeros(0, bool), c, p)
    assert float(both_empty.distance) == 0.0
    with pytest.raises(ValueError, match="alpha"):
        gospa_jit(points, jnp.ones(3, bool), points, jnp.ones(3, bool), c, p, alpha=1.0)


def test_gospa_padding_ignored():
    rng = np.random.default_rng(12)
    est, truth = rng.uniform(0, 10, (6, 2)), rng.uniform(0, 10, (5, 2))
    base = gospa_jit(jnp.asarray(est), jnp.ones(6, bool), jnp.asarray(truth),
                         jnp.ones(5, bool), 2.0)
    # padding placed exactly on valid points of the other set must change nothing
    pad_est = np.concatenate([est, truth[:3]])
    pad_truth = np.concatenate([truth, est])
    padded = gospa_jit(jnp.asarray(pad_est), jnp.arange(9) < 6, jnp.asarray(pad_truth),
                           jnp.arange(11) < 5, 2.0)
    chex.assert_trees_all_close(padded, base, rtol=1e-12)


# ---------------------------------------------------------------------------------------------
# vmap and the per-run summary


def test_vmap_over_runs_matches_loop():
    rng = np.random.default_rng(13)
    runs = 3
    truth = np.stack([random_trajectory(rng, 30) for _ in range(runs)])
    est = np.stack([noisy(rng, t, 0.2) for t in truth])
    maps = [random_map(rng, 16, 10) for _ in range(runs)]
    landmarks, active, trees, tree_valid = (np.stack(x) for x in zip(*maps))
    kwargs = dict(match_threshold=1.0, gospa_cutoff=2.0, divergence_threshold=0.5)
    summarize = jax.jit(jax.vmap(lambda *a: metrics.summarize(*a, **kwargs)))
    batched = summarize(*(jnp.asarray(x) for x in (est, truth, landmarks, active, trees,
                                                    tree_valid)))
    assert batched.pose_nees is None and batched.map_nees is None
    summarize_one = jax.jit(lambda *a: metrics.summarize(*a, **kwargs))
    for r in range(runs):
        one = summarize_one(*(jnp.asarray(x[r]) for x in (est, truth, landmarks, active,
                                                          trees, tree_valid)))
        chex.assert_trees_all_close(jax.tree.map(lambda x: x[r], batched), one, rtol=1e-9)
        mm = ref_map_metrics(landmarks[r], active[r], trees[r], tree_valid[r], 1.0)
        np.testing.assert_allclose(one.map_error, mm["map_error"], rtol=1e-9)
        np.testing.assert_allclose(one.ate_rmse_aligned, ref_ate(est[r], truth[r],
                                                                 np.ones(30, bool), True),
                                   rtol=1e-9)
        np.testing.assert_allclose(one.gospa, ref_gospa(landmarks[r], active[r], trees[r],
                                                        tree_valid[r], 2.0, 2.0)[0], rtol=1e-9)
        np.testing.assert_allclose(one.rpe_translation,
                                   ref_rpe(est[r], truth[r], 1, np.ones(30, bool), False)[0],
                                   rtol=1e-9)
    # batch of zero runs
    empty = summarize(*(jnp.zeros((0,) + x.shape[1:], x.dtype) for x in
                        (est, truth, landmarks, active, trees, tree_valid)))
    assert empty.gospa.shape == (0,)


def test_summarize_with_covariances_and_alignment():
    rng = np.random.default_rng(14)
    truth = random_trajectory(rng, 20)
    landmarks, active, trees, tree_valid = random_map(rng, 12, 8)
    alignment = np.array([2.0, 3.0, 0.9])
    inverse = np.linalg.inv(ref_se2(alignment))
    est = rigid(truth, [inverse[0, 2], inverse[1, 2], -alignment[2]])  # rigidly moved copy
    moved_map = landmarks @ inverse[:2, :2].T + inverse[:2, 2]
    cov = np.tile(0.04 * np.eye(2), (12, 1, 1))
    kwargs = dict(match_threshold=1.0, gospa_cutoff=2.0, divergence_threshold=0.5,
                  landmark_cov=jnp.asarray(cov), final_pose_cov=0.1 * jnp.eye(3))
    summarize = jax.jit(metrics.summarize, static_argnames=("rpe_delta", "align_map"))
    plain = summarize(*(jnp.asarray(x) for x in (truth, truth, landmarks, active,
                                                         trees, tree_valid)), **kwargs)
    aligned = summarize(*(jnp.asarray(x) for x in (est, truth, moved_map, active,
                                                           trees, tree_valid)),
                                align_map=True, **kwargs)
    for name in ("map_error", "redundant", "orphan", "num_trees_mapped", "gospa", "map_nees"):
        np.testing.assert_allclose(getattr(aligned, name), getattr(plain, name), rtol=1e-7,
                                   atol=1e-9, err_msg=name)
    assert float(aligned.ate_rmse_aligned) < 1e-9 and float(aligned.ate_rmse) > 1.0
    assert bool(aligned.diverged) and not bool(plain.diverged)
    assert float(plain.pose_nees) == 0.0 and float(plain.final_pose_error) == 0.0


def test_float32_inputs_give_float32_finite_metrics():
    rng = np.random.default_rng(15)

    def f32(*shape):
        return jnp.asarray(rng.normal(size=shape), jnp.float32)

    result = jax.jit(lambda *a: metrics.summarize(
        *a, match_threshold=1.0, gospa_cutoff=2.0, divergence_threshold=1.0,
        landmark_cov=jnp.tile(jnp.eye(2, dtype=jnp.float32), (6, 1, 1)),
        final_pose_cov=jnp.eye(3, dtype=jnp.float32)))(
        f32(11, 3), f32(11, 3), f32(6, 2), jnp.ones(6, bool), f32(5, 2), jnp.ones(5, bool))
    for name, value in result._asdict().items():
        assert value.dtype in (jnp.float32, jnp.int32, jnp.bool_), (name, value.dtype)
        assert np.isfinite(np.asarray(value, float)), name
