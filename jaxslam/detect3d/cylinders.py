"""One cylinder per cluster by RANSAC and Levenberg-Marquardt (module docstring of
``jaxslam.detect3d``, step 5).

A cylinder theta = (x0, y0, a, b, r): its axis crosses (x0, y0) at the height z_ref, has the
slopes (a, b) and the radius r. Hypotheses (Fischler and Bolles, "Random Sample Consensus",
CACM 1981) come from Kasa circles (Kasa, "A Circle Fitting Procedure and its Error Analysis",
IEEE TIM 1976) and three-point circles on lidar rings; the best is refined on its inliers.
C clusters, P points per cluster, H hypotheses.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxslam.detect3d.solve import spd_solve


def cylinder_residual(theta, p, z_ref):
    """Signed distance e = |(p - p0) x u| - r of points to cylinders (step 5).

    Args:
      theta: (..., 5) (x0, y0, a, b, r). p: (..., 3). z_ref: (...). Shapes broadcast (same rank).
    Returns:
      (...) residuals [m].
    """
    wx, wy, wz = p[..., 0] - theta[..., 0], p[..., 1] - theta[..., 1], p[..., 2] - z_ref
    a, b = theta[..., 2], theta[..., 3]
    cx, cy, cz = wy - b * wz, a * wz - wx, wx * b - wy * a  # w x (a, b, 1)
    d2 = (cx * cx + cy * cy + cz * cz) / (1.0 + a * a + b * b)
    return jnp.sqrt(jnp.maximum(d2, jnp.finfo(p.dtype).tiny)) - theta[..., 4]


def _kasa_xy(xy, w):
    """Weighted Kasa circle of xy (..., P, 2): centre (..., 2), radius (...), ok (...)."""
    n = jnp.sum(w, -1)
    safe = jnp.maximum(n, 1e-12)
    mean = jnp.sum(w[..., None] * xy, -2) / safe[..., None]
    d = xy - mean[..., None, :]
    u, v = d[..., 0], d[..., 1]
    z = u * u + v * v
    sums = jnp.sum(w[..., None] * jnp.stack([u * u, u * v, v * v, z * u, z * v, z], -1), -2)
    suu, suv, svv, szu, szv, sz = (sums[..., i] for i in range(6))
    det = suu * svv - suv * suv
    ok = (det > 1e-12 * jnp.maximum(suu * svv, 1e-30)) & (n >= 3)
    safe_det = jnp.where(ok, det, 1.0)
    cu = 0.5 * (svv * szu - suv * szv) / safe_det
    cv = 0.5 * (suu * szv - suv * szu) / safe_det
    radius = jnp.sqrt(jnp.maximum(cu * cu + cv * cv + sz / safe, 0.0))
    return mean + jnp.stack([cu, cv], -1), radius, ok


def _circle_through(p):
    """Circle through the three points p (..., 3, 2): centre (..., 2), ok (...)."""
    ax, ay = p[..., 1, 0] - p[..., 0, 0], p[..., 1, 1] - p[..., 0, 1]
    bx, by = p[..., 2, 0] - p[..., 0, 0], p[..., 2, 1] - p[..., 0, 1]
    det = 2.0 * (ax * by - ay * bx)
    ok = jnp.abs(det) > 1e-12
    safe = jnp.where(ok, det, 1.0)
    a2, b2 = ax * ax + ay * ay, bx * bx + by * by
    return p[..., 0, :] + jnp.stack([(by * a2 - ay * b2) / safe, (ax * b2 - bx * a2) / safe],
                                    -1), ok


def _axis_theta(lower, upper, z_ref):
    """(x0, y0, a, b) of the line through points lower, upper (..., 3) at height z_ref (...)."""
    d = upper - lower
    ok = d[..., 2] > 0.0
    dz = jnp.where(ok, d[..., 2], 1.0)
    a, b = d[..., 0] / dz, d[..., 1] / dz
    t = z_ref - lower[..., 2]
    return jnp.stack([lower[..., 0] + a * t, lower[..., 1] + b * t, a, b], -1), ok


def _slices(h, mask):
    """Lower and upper thirds (C, P) bool of each cluster's height range."""
    big = jnp.finfo(h.dtype).max
    lo = jnp.min(jnp.where(mask, h, big), -1, keepdims=True)
    hi = jnp.max(jnp.where(mask, h, -big), -1, keepdims=True)
    third = (hi - lo) / 3.0
    return mask & (h <= lo + third), mask & (h >= hi - third), (hi - lo)[:, 0]


def _pick_ranks(allowed, ranks):
    """Index (...) of the point of rank ``ranks`` (...) among the ``allowed`` (..., P) points."""
    order = jnp.cumsum(allowed.astype(jnp.int32), -1) - 1
    return jnp.argmax(allowed & (order == ranks[..., None]), -1)


def _ring_samples(draws, z, candidate, ring):
    """Indices (C, M, 3) of three distinct points: an anchor uniform among ``candidate`` (C, P)
    and two more uniform among the candidates within ``ring`` of its height z (C, P), from the
    uniform ``draws`` (3, C, M) (rank = floor(u n)); ok (C, M) when there were enough."""
    p = z.shape[1]
    n_anchor = jnp.sum(candidate, -1)[:, None]
    rank = jnp.minimum(jnp.floor(draws[0] * n_anchor), n_anchor - 1).astype(jnp.int32)
    anchor = _pick_ranks(jnp.broadcast_to(candidate[:, None, :], draws.shape[1:] + (p,)), rank)
    z_anchor = jnp.take_along_axis(z, anchor, axis=1)
    near = (candidate[:, None, :] & (jnp.abs(z[:, None, :] - z_anchor[..., None]) <= ring)
            & (jnp.arange(p)[None, None, :] != anchor[..., None]))
    n_near = jnp.sum(near, -1)
    first = jnp.minimum(jnp.floor(draws[1] * n_near), n_near - 1).astype(jnp.int32)
    second = jnp.minimum(jnp.floor(draws[2] * (n_near - 1)), n_near - 2).astype(jnp.int32)
    second = second + (second >= first)  # a uniform second rank among the n - 1 others
    pair = jnp.stack([_pick_ranks(near, first), _pick_ranks(near, second)], -1)
    ok = (n_anchor >= 1) & (n_near >= 2)
    return jnp.concatenate([anchor[..., None], pair], -1), ok


def _mean_distance(theta4, pts, w, z_ref):
    """Mean distance (...) of points pts (..., P, 3) with weights w (..., P) to axes theta4
    (..., 4) at heights z_ref (...)."""
    theta = jnp.concatenate([theta4, jnp.zeros_like(theta4[..., :1])], -1)
    d = cylinder_residual(theta[..., None, :], pts, z_ref[..., None])
    return jnp.sum(w * d, -1) / jnp.maximum(jnp.sum(w, -1), 1e-12)


def cylinder_hypotheses(key, pts, h, mask, z_ref, *, num_hypotheses: int, ring_thickness):
    """RANSAC hypotheses (step 5a): theta (C, H, 5) and ok (C, H).

    Args:
      key: PRNG key. pts: (C, P, 3). h: (C, P) height above the ground. mask: (C, P) bool.
      z_ref: (C,) reference heights. num_hypotheses: H >= 2. ring_thickness: () [m].
    """
    c, p, _ = pts.shape
    dtype = pts.dtype
    w = mask.astype(dtype)
    lower, upper, _ = _slices(h, mask)
    # 0: vertical axis through the Kasa circle of all points; 1: the axis through the Kasa
    # centres of the lower and upper thirds (one stacked Kasa fit of the three point sets).
    sets = jnp.stack([mask, lower, upper]).astype(dtype)  # (3, C, P)
    centre, radius, ok_k = _kasa_xy(jnp.broadcast_to(pts[None, ..., :2], (3, c, p, 2)), sets)
    z_mean = jnp.sum(sets * pts[None, ..., 2], -1) / jnp.maximum(jnp.sum(sets, -1), 1e-12)
    theta0 = jnp.concatenate([centre[0], jnp.zeros((c, 2), dtype), radius[0][:, None]], -1)
    ok0 = ok_k[0]
    slice_c = jnp.concatenate([centre[1:], z_mean[1:, :, None]], -1)  # (2, C, 3)
    axis1, ok_axis = _axis_theta(slice_c[0], slice_c[1], z_ref)
    theta1 = jnp.concatenate([axis1, _mean_distance(axis1, pts, w, z_ref)[:, None]], -1)
    ok1 = ok_k[1] & ok_k[2] & ok_axis

    # 2..H-1: three points on a ring in each third (the two thirds vmapped, one draw).
    num = num_hypotheses - 2
    draws = jax.random.uniform(key, (2, 3, c, num), dtype)
    rows = jnp.arange(c)[:, None, None]

    def ring_circle(draw, sel):
        idx, ok = _ring_samples(draw, pts[..., 2], sel, ring_thickness)
        sample = pts[rows, idx]  # (C, M, 3, 3)
        centre, ok_c = _circle_through(sample[..., :2])
        z = jnp.mean(sample[..., 2], -1)
        return jnp.concatenate([centre, z[..., None]], -1), sample, ok & ok_c

    ring, sample, ok_ring = jax.vmap(ring_circle)(draws, jnp.stack([lower, upper]))
    z_rep = jnp.broadcast_to(z_ref[:, None], (c, num))
    axis_r, ok_ar = _axis_theta(ring[0], ring[1], z_rep)
    six = jnp.concatenate([sample[0], sample[1]], -2)
    theta_r = jnp.concatenate(
        [axis_r, _mean_distance(axis_r, six, jnp.ones(six.shape[:-1], dtype), z_rep)[..., None]],
        -1)
    theta = jnp.concatenate([theta0[:, None], theta1[:, None], theta_r], 1)
    ok = jnp.concatenate([ok0[:, None], ok1[:, None], ok_ring[0] & ok_ring[1] & ok_ar], 1)
    return theta, ok & jnp.all(jnp.isfinite(theta), -1)


def _inliers(theta, pts, mask, z_ref, tol):
    """Inlier mask (C, P) of the cylinders theta (C, 5)."""
    e = cylinder_residual(theta[:, None, :], pts, z_ref[:, None])
    return mask & (jnp.abs(e) < tol)


def levenberg_marquardt(theta, pts, weight, z_ref, iterations: int):
    """``iterations`` LM steps on sum_i w_i e_i(theta)^2 per cluster (step 5b).

    Normal equations (J^T W J + mu diag(J^T W J) + eps I) delta = -J^T W e with J (C, P, 5) the
    Jacobian of ``cylinder_residual`` (per-point ``jax.grad``); mu starts at 1e-3.

    Args:
      theta: (C, 5). pts: (C, P, 3). weight: (C, P). z_ref: (C,).
    Returns:
      theta (C, 5).
    """
    grad = jax.vmap(jax.vmap(jax.value_and_grad(cylinder_residual), in_axes=(None, 0, None)),
                    in_axes=(0, 0, 0))
    eye = jnp.eye(5, dtype=theta.dtype)

    def cost(th):
        e = cylinder_residual(th[:, None, :], pts, z_ref[:, None])
        return jnp.sum(weight * e * e, -1)

    def step(carry, _):
        th, mu, old = carry
        e, jac = grad(th, pts, z_ref)
        wj = weight[..., None] * jac
        a = jnp.einsum("cpi,cpj->cij", wj, jac)
        g = jnp.einsum("cpi,cp->ci", wj, e)
        diag = jnp.diagonal(a, axis1=-2, axis2=-1)
        eps = 1e-12 * jnp.sum(diag, -1) + jnp.finfo(th.dtype).tiny ** 0.5
        lhs = a + (mu[:, None] * diag + eps[:, None])[..., None] * eye[None]
        delta = spd_solve(lhs, -g)
        new = th + delta
        new_cost = cost(new)
        good = jnp.isfinite(new_cost) & (new_cost <= old) & jnp.all(jnp.isfinite(new), -1)
        th = jnp.where(good[:, None], new, th)
        return (th, jnp.where(good, mu * 0.1, mu * 10.0).clip(1e-12, 1e12),
                jnp.where(good, new_cost, old)), None

    mu = jnp.full(theta.shape[:1], 1e-3, theta.dtype)
    (theta, _, _), _ = jax.lax.scan(step, (theta, mu, cost(theta)), None, length=iterations)
    return theta


def fit_cylinders(key, pts, h, mask, *, num_hypotheses: int, ring_thickness, inlier_tol,
                  max_radius, max_lean, lm_iterations: int, refine_rounds: int):
    """RANSAC and refinement of one cylinder per cluster (step 5).

    Args:
      key: PRNG key. pts: (C, P, 3). h: (C, P). mask: (C, P) bool.
    Returns:
      theta (C, 5) (x0, y0, a, b, r), z_ref (C,), found (C,) bool (a hypothesis with 3+ inliers).
    """
    w = mask.astype(pts.dtype)
    z_ref = jnp.sum(w * pts[..., 2], -1) / jnp.maximum(jnp.sum(w, -1), 1.0)
    theta, ok = cylinder_hypotheses(key, pts, h, mask, z_ref, num_hypotheses=num_hypotheses,
                                    ring_thickness=ring_thickness)
    lean_cap = jnp.minimum(3.0 * max_lean, jnp.deg2rad(70.0))
    ok = (ok & (theta[..., 4] > 0.0) & (theta[..., 4] <= 2.0 * max_radius)
          & (jnp.hypot(theta[..., 2], theta[..., 3]) <= jnp.tan(lean_cap)))
    e = cylinder_residual(theta[:, :, None, :], pts[:, None], z_ref[:, None, None])
    votes = jnp.sum(mask[:, None, :] & (jnp.abs(e) < inlier_tol), -1)
    votes = jnp.where(ok, votes, -1)
    best = jnp.argmax(votes, -1)
    found = jnp.max(votes, -1) >= 3
    theta = jnp.take_along_axis(theta, best[:, None, None], axis=1)[:, 0]

    def refine(theta, _):
        inl = _inliers(theta, pts, mask, z_ref, inlier_tol)
        return levenberg_marquardt(theta, pts, inl.astype(pts.dtype), z_ref, lm_iterations), None

    theta, _ = jax.lax.scan(refine, theta, None, length=refine_rounds)
    return theta, z_ref, found
