"""Independent NumPy float64 reference of ``jaxslam.detect3d`` and the analytic test clouds.

Written from the math of the ``jaxslam.detect3d`` module docstring, not from its code: loops
over cells and clusters, a breadth-first flood fill for the clusters, the analytic Jacobian of
the cylinder residual, ``np.linalg.lstsq`` for the ground planes (from the raw points), and
NumPy's own random draws for the RANSAC hypotheses (so only the deterministic hypotheses agree
with the JAX code; after refinement both land on the same least-squares cylinder).

Analytic clouds (``ray_cast``): rays from the sensor at the origin hit a ground surface
z = g(x, y) = g0 + gx x + gy y + gxx x^2 + gyy y^2 (exactly, by a quadratic in the ray
parameter), leaning finite cylinders, and vertical rectangular walls.
"""
from __future__ import annotations

import collections
import math
from typing import NamedTuple

import numpy as np


# ----------------------------------------------------------------------------------------------
# Analytic scenes.


class Ground(NamedTuple):
    """z = g0 + gx x + gy y + gxx x^2 + gyy y^2 [m] in the sensor frame."""

    g0: float = -1.0
    gx: float = 0.0
    gy: float = 0.0
    gxx: float = 0.0
    gyy: float = 0.0

    def height(self, x, y):
        return self.g0 + self.gx * x + self.gy * y + self.gxx * x * x + self.gyy * y * y


class Trunk(NamedTuple):
    """A cylinder whose axis meets the ground at (x, y), leaning by ``lean`` toward ``azimuth``."""

    x: float
    y: float
    radius: float
    lean: float = 0.0
    azimuth: float = 0.0
    length: float = 8.0

    def axis(self):
        s = math.sin(self.lean)
        return np.array([s * math.cos(self.azimuth), s * math.sin(self.azimuth),
                         math.cos(self.lean)])

    def base(self, ground: Ground):
        return np.array([self.x, self.y, ground.height(self.x, self.y)])

    def breast_point(self, ground: Ground, breast_height=1.3):
        """The axis point 1.3 m (vertically) above the base."""
        u = self.axis()
        return self.base(ground) + u * (breast_height / u[2])


class Wall(NamedTuple):
    """A vertical rectangle centred at (x, y), facing ``normal_angle``, from the ground up."""

    x: float
    y: float
    normal_angle: float
    width: float
    top: float = 2.5


def ray_directions(elevations, azimuths):
    """(L B, 3) unit directions, layer-major (elevation e, azimuth a) [rad]."""
    e, a = np.meshgrid(np.asarray(elevations, float), np.asarray(azimuths, float), indexing="ij")
    return np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], -1).reshape(-1, 3)


def _ground_hit(d, g: Ground):
    a = g.gxx * d[:, 0] ** 2 + g.gyy * d[:, 1] ** 2
    b = g.gx * d[:, 0] + g.gy * d[:, 1] - d[:, 2]
    c = g.g0 * np.ones(len(d))
    t = np.full(len(d), np.inf)
    lin = np.abs(a) < 1e-15
    with np.errstate(divide="ignore", invalid="ignore"):
        t_lin = -c / b
        disc = b * b - 4 * a * c
        sq = np.sqrt(np.maximum(disc, 0))
        roots = np.stack([(-b - sq) / (2 * a), (-b + sq) / (2 * a)], -1)
    roots = np.where((roots > 0) & (disc[:, None] >= 0), roots, np.inf).min(-1)
    t = np.where(lin, np.where(t_lin > 0, t_lin, np.inf), roots)
    return t


def _trunk_hit(d, trunk: Trunk, g: Ground):
    u, b = trunk.axis(), trunk.base(g)
    dp = d - np.outer(d @ u, u)
    bp = b - (b @ u) * u
    qa = np.sum(dp * dp, -1)
    qb = -2 * dp @ bp
    qc = bp @ bp - trunk.radius ** 2
    disc = qb * qb - 4 * qa * qc
    with np.errstate(invalid="ignore", divide="ignore"):
        t = (-qb - np.sqrt(np.maximum(disc, 0))) / (2 * qa)
    s = (t[:, None] * d - b[None]) @ u
    ok = (disc >= 0) & (t > 0) & (s >= 0) & (s <= trunk.length)
    return np.where(ok, t, np.inf)


def _wall_hit(d, wall: Wall, g: Ground):
    n = np.array([math.cos(wall.normal_angle), math.sin(wall.normal_angle), 0.0])
    tangent = np.array([-n[1], n[0], 0.0])
    centre = np.array([wall.x, wall.y, 0.0])
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (centre @ n) / (d @ n)
    p = t[:, None] * d
    along = (p - centre[None]) @ tangent
    z = p[:, 2]
    ok = (t > 0) & (np.abs(along) <= wall.width / 2) & (z >= g.height(p[:, 0], p[:, 1])) & (
        z <= g.height(wall.x, wall.y) + wall.top)
    return np.where(ok, t, np.inf)


def ray_cast(directions, ground: Ground, trunks=(), walls=(), max_range=20.0):
    """Nearest hit of each ray: points (R, 3) (zeros where none) and hit (R,) bool."""
    t = _ground_hit(directions, ground)
    for trunk in trunks:
        t = np.minimum(t, _trunk_hit(directions, trunk, ground))
    for wall in walls:
        t = np.minimum(t, _wall_hit(directions, wall, ground))
    hit = t < max_range
    return np.where(hit[:, None], t[:, None] * directions, 0.0), hit


def blob(rng, centre, radii, num):
    """``num`` points uniform in an axis-aligned ellipsoid (a bush)."""
    v = rng.normal(size=(num, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    v *= rng.uniform(size=(num, 1)) ** (1 / 3)
    return np.asarray(centre, float) + v * np.asarray(radii, float)


# ----------------------------------------------------------------------------------------------
# Reference detector.


DEFAULTS = dict(max_obs=16, max_clusters=32, max_range=20.0, min_range=0.1, ground_cell=2.0,
                ground_quantile=0.1, ground_bandwidth=3.0, ground_tol=0.15,
                ground_iterations=4, band_min=0.5, band_max=3.0, breast_height=1.3,
                cluster_cell=0.15, min_points=10, cluster_points=512, num_hypotheses=64,
                ring_thickness=0.1, inlier_tol=0.03, lm_iterations=10, refine_rounds=2,
                min_radius=0.03, max_radius=0.5, max_lean=math.radians(20.0),
                min_inlier_ratio=0.6, max_width=1.5, min_flatness=0.02)


class RefTrunk(NamedTuple):
    position: np.ndarray  # (3,)
    base: np.ndarray  # (3,)
    axis: np.ndarray  # (3,)
    lean: float
    radius: float
    num_points: int
    num_inliers: int
    inlier_ratio: float
    accepted: bool
    reasons: dict


def _cell_of(x, cell, size):
    i = int(math.floor(x / cell + 0.5 * size))
    return i


def _cells(points, cell, size):
    """Per point: (i, j) cell or None outside."""
    out = []
    for x, y in points[:, :2]:
        i, j = _cell_of(x, cell, size), _cell_of(y, cell, size)
        out.append((i, j) if 0 <= i < size and 0 <= j < size else None)
    return out


def _centre(i, j, cell, size):
    return np.array([(i + 0.5 - 0.5 * size) * cell, (j + 0.5 - 0.5 * size) * cell])


def _weighted_plane(x, y, z, w, q):
    """z ~ alpha + beta (x - qx) + gamma (y - qy) by weighted least squares (lstsq)."""
    if np.sum(w) <= 0:
        return np.zeros(3)
    s = np.sqrt(w)
    a = np.stack([np.ones_like(x), x - q[0], y - q[1]], -1) * s[:, None]
    sol, *_ = np.linalg.lstsq(a, z * s, rcond=None)
    return sol


def ground_model(points, usable, p):
    """The ground of the module docstring, step 2, from the raw points.

    Returns (cells, ground_at, height_above): each point's ground cell (i, j) or None,
    ground_at(q) the ground height at q (2,) from the plane of q's (clipped) cell, and
    height_above(n) of point n."""
    cell, h = p["ground_cell"], p["ground_bandwidth"]
    size = int(math.ceil(2 * p["max_range"] / cell - 1e-9))
    cells = _cells(points, cell, size)
    members = collections.defaultdict(list)
    for n, c in enumerate(cells):
        if usable[n] and c is not None:
            members[c].append(n)
    seeds = {}
    for c, idx in members.items():
        order = sorted(idx, key=lambda n: points[n, 2])
        k = int(math.floor(p["ground_quantile"] * (len(order) - 1)))
        seeds[c] = points[order[k]]
    sp = np.array([seeds[c] for c in sorted(seeds)]) if seeds else np.zeros((0, 3))

    def kernel(src_xy, q):
        return np.exp(-0.5 * np.sum((src_xy - q[None]) ** 2, -1) / h ** 2)

    # Robust LOWESS of the seeds: n asymmetric Tukey reweightings.
    rho = np.ones(len(sp))
    n_it = p["ground_iterations"]
    for i in range(n_it):
        scale = 1.0 * (p["ground_tol"] / 1.0) ** (i / max(n_it - 1, 1))
        e = np.array([sp[k, 2] - _weighted_plane(sp[:, 0], sp[:, 1], sp[:, 2],
                                                 kernel(sp[:, :2], sp[k, :2]) * rho,
                                                 sp[k, :2])[0] for k in range(len(sp))])
        u = np.where(e >= 0, e / scale, e / (3 * scale))
        rho = np.where(np.abs(u) < 1, (1 - u * u) ** 2, 0.0)
    rough = {c: _weighted_plane(sp[:, 0], sp[:, 1], sp[:, 2],
                                kernel(sp[:, :2], _centre(*c, cell, size)) * rho,
                                _centre(*c, cell, size)) for c in members}

    def plane_at(planes, c, x, y):
        q = _centre(*c, cell, size)
        a, b, g = planes[c]
        return a + b * (x - q[0]) + g * (y - q[1])

    rough_h = {n: points[n, 2] - plane_at(rough, c, *points[n, :2])
               for c, idx in members.items() for n in idx}
    # Object footprint on the cluster grid, dilated by one cell.
    ocell = p["cluster_cell"]
    osize = int(math.ceil(2 * p["max_range"] / ocell - 1e-9))

    def ocell_of(n):
        return _cell_of(points[n, 0], ocell, osize), _cell_of(points[n, 1], ocell, osize)

    marked = set()
    for n, hh in rough_h.items():
        if p["ground_tol"] <= hh <= p["band_max"]:
            i, j = ocell_of(n)
            if 0 <= i < osize and 0 <= j < osize:
                marked.update((i + di, j + dj) for di in (-1, 0, 1) for dj in (-1, 0, 1))
    ground_pts, ground_src = [], []
    for n, hh in rough_h.items():
        if abs(hh) < p["ground_tol"] and ocell_of(n) not in marked:
            ground_pts.append(points[n])
            ground_src.append(_centre(*cells[n], cell, size))
    gp = np.array(ground_pts) if ground_pts else np.zeros((0, 3))
    gs = np.array(ground_src) if ground_src else np.zeros((0, 2))
    final = {}
    for i in range(size):
        for j in range(size):
            q = _centre(i, j, cell, size)
            final[(i, j)] = _weighted_plane(gp[:, 0], gp[:, 1], gp[:, 2], kernel(gs, q), q)

    def ground_at(q):
        c = tuple(min(max(_cell_of(v, cell, size), 0), size - 1) for v in q)
        return final[c], _centre(*c, cell, size)

    def height_above(n):
        return points[n, 2] - plane_at(final, cells[n], *points[n, :2])

    return cells, ground_at, height_above


def clusters(points, band, p):
    """Fitted clusters: list of point-index lists (input order), nearest first; and the count."""
    cell = p["cluster_cell"]
    size = int(math.ceil(2 * p["max_range"] / cell - 1e-9))
    occupied = collections.defaultdict(list)
    for n in np.flatnonzero(band):
        i, j = _cell_of(points[n, 0], cell, size), _cell_of(points[n, 1], cell, size)
        if 0 <= i < size and 0 <= j < size:
            occupied[(i, j)].append(n)
    seen, groups = set(), []
    for start in occupied:
        if start in seen:
            continue
        seen.add(start)
        queue, comp = collections.deque([start]), []
        while queue:
            i, j = queue.popleft()
            comp.extend(occupied[(i, j)])
            for di in (-1, 0, 1):
                for dj in (-1, 0, 1):
                    nb = (i + di, j + dj)
                    if nb in occupied and nb not in seen:
                        seen.add(nb)
                        queue.append(nb)
        groups.append(sorted(comp))
    groups = [g for g in groups if len(g) >= p["min_points"]]
    groups.sort(key=lambda g: float(np.hypot(*points[g, :2].mean(0))))
    return groups[:p["max_clusters"]], len(groups)


def residual_and_jacobian(theta, pts, z_ref):
    """e = d - r and its analytic Jacobian (P, 5) w.r.t. (x0, y0, a, b, r).

    With w = p - p0, v = (a, b, 1), s = w.v / |v|^2: d^2 = |w|^2 - s^2 |v|^2,
    dd/dx0 = -(w_x - s a)/d, dd/dy0 = -(w_y - s b)/d, dd/da = -s (w_x - s a)/d,
    dd/db = -s (w_y - s b)/d, de/dr = -1.
    """
    x0, y0, a, b, r = theta
    w = pts - np.array([x0, y0, z_ref])
    v = np.array([a, b, 1.0])
    vv = v @ v
    s = (w @ v) / vv
    d = np.sqrt(np.maximum(np.sum(w * w, -1) - s * s * vv, 1e-300))
    px, py = w[:, 0] - s * a, w[:, 1] - s * b
    jac = np.stack([-px / d, -py / d, -s * px / d, -s * py / d, -np.ones_like(d)], -1)
    return d - r, jac


def kasa(xy):
    """Algebraic circle x^2 + y^2 + D x + E y + F = 0 by least squares: centre, radius."""
    a = np.stack([xy[:, 0], xy[:, 1], np.ones(len(xy))], -1)
    (dd, ee, ff), *_ = np.linalg.lstsq(a, -(xy ** 2).sum(1), rcond=None)
    return np.array([-dd / 2, -ee / 2]), math.sqrt(max(dd * dd / 4 + ee * ee / 4 - ff, 0.0))


def circle3(p):
    """Centre of the circle through three points (3, 2), or None when collinear."""
    (x1, y1), (x2, y2), (x3, y3) = p
    m = np.array([[2 * (x2 - x1), 2 * (y2 - y1)], [2 * (x3 - x1), 2 * (y3 - y1)]])
    if abs(np.linalg.det(m)) < 1e-12:
        return None
    rhs = np.array([x2 ** 2 - x1 ** 2 + y2 ** 2 - y1 ** 2, x3 ** 2 - x1 ** 2 + y3 ** 2 - y1 ** 2])
    return np.linalg.solve(m, rhs)


def _line_theta(lo, up, z_ref):
    dz = up[2] - lo[2]
    if dz <= 0:
        return None
    a, b = (up[0] - lo[0]) / dz, (up[1] - lo[1]) / dz
    return np.array([lo[0] + a * (z_ref - lo[2]), lo[1] + b * (z_ref - lo[2]), a, b])


def _distances(th4, pts, z_ref):
    e, _ = residual_and_jacobian(np.append(th4, 0.0), pts, z_ref)
    return e


def fit_cluster(pts, h, p, rng):
    """RANSAC + LM cylinder (theta, z_ref, found) of one cluster's sample pts (P, 3)."""
    z_ref = pts[:, 2].mean()
    lo_h, hi_h = h.min(), h.max()
    third = (hi_h - lo_h) / 3
    lower, upper = h <= lo_h + third, h >= hi_h - third
    hyps = []
    c, r = kasa(pts[:, :2])
    hyps.append(np.array([c[0], c[1], 0.0, 0.0, r]))
    if lower.sum() >= 3 and upper.sum() >= 3:
        lo = np.append(kasa(pts[lower, :2])[0], pts[lower, 2].mean())
        up = np.append(kasa(pts[upper, :2])[0], pts[upper, 2].mean())
        th = _line_theta(lo, up, z_ref)
        if th is not None:
            hyps.append(np.append(th, _distances(th, pts, z_ref).mean()))
    for _ in range(p["num_hypotheses"] - 2):
        centres, six = [], []
        for sel in (lower, upper):
            cand = np.flatnonzero(sel)
            anchor = rng.choice(cand)
            near = [n for n in cand if n != anchor
                    and abs(pts[n, 2] - pts[anchor, 2]) <= p["ring_thickness"]]
            if len(near) < 2:
                break
            pick = [anchor, *rng.choice(near, 2, replace=False)]
            cc = circle3(pts[pick, :2])
            if cc is None:
                break
            centres.append(np.append(cc, pts[pick, 2].mean()))
            six.extend(pick)
        if len(centres) < 2:
            continue
        th = _line_theta(centres[0], centres[1], z_ref)
        if th is None:
            continue
        hyps.append(np.append(th, _distances(th, pts[six], z_ref).mean()))
    cap = math.tan(min(3 * p["max_lean"], math.radians(70)))
    best, best_votes = None, -1
    for th in hyps:
        if not (0 < th[4] <= 2 * p["max_radius"] and math.hypot(th[2], th[3]) <= cap):
            continue
        e, _ = residual_and_jacobian(th, pts, z_ref)
        votes = int(np.sum(np.abs(e) < p["inlier_tol"]))
        if votes > best_votes:
            best, best_votes = th, votes
    if best is None:
        return np.zeros(5), z_ref, False
    theta = best.copy()
    for _ in range(p["refine_rounds"]):
        e, _ = residual_and_jacobian(theta, pts, z_ref)
        inl = np.abs(e) < p["inlier_tol"]
        theta = lm(theta, pts[inl], z_ref, p["lm_iterations"])
    return theta, z_ref, best_votes >= 3


def lm(theta, pts, z_ref, iterations):
    """Levenberg-Marquardt with mu / 10 on success, x 10 on failure (module docstring 5b)."""
    mu = 1e-3

    def cost(th):
        e, _ = residual_and_jacobian(th, pts, z_ref)
        return float(e @ e)

    old = cost(theta)
    for _ in range(iterations):
        if len(pts) == 0:
            break
        e, jac = residual_and_jacobian(theta, pts, z_ref)
        a = jac.T @ jac
        g = jac.T @ e
        lhs = a + np.diag(mu * np.diag(a) + 1e-12 * np.trace(a) + 1e-150)
        new = theta + np.linalg.solve(lhs, -g)
        c = cost(new)
        if np.isfinite(c) and c <= old:
            theta, old, mu = new, c, max(mu * 0.1, 1e-12)
        else:
            mu = min(mu * 10, 1e12)
    return theta


def detect(points, valid=None, seed=0, **overrides):
    """Reference detection: (accepted trunks nearest first, all fitted clusters, num_clusters)."""
    p = dict(DEFAULTS, **overrides)
    rng = np.random.default_rng(seed)
    points = np.asarray(points, float)
    valid = np.ones(len(points), bool) if valid is None else np.asarray(valid, bool)
    finite = np.all(np.isfinite(points), 1)
    points = np.where(finite[:, None], points, 0.0)
    usable = valid & finite & (np.linalg.norm(points, axis=1) > p["min_range"])
    cells, ground_at, height_above = ground_model(points, usable, p)
    height = np.full(len(points), np.nan)
    for n in range(len(points)):
        if usable[n] and cells[n] is not None:
            height[n] = height_above(n)
    band = usable & (height >= p["band_min"]) & (height <= p["band_max"])
    groups, num_clusters = clusters(points, band, p)
    fits = []
    for g in groups:
        count = len(g)
        cap = p["cluster_points"]
        sample = g if count <= cap else [g[(j * count) // cap] for j in range(cap)]
        pts, h = points[sample], height[sample]
        theta, z_ref, found = fit_cluster(pts, h, p, rng)
        x0, y0, a, b, r = theta
        e, _ = residual_and_jacobian(theta, pts, z_ref)
        inl = np.abs(e) < p["inlier_tol"]
        # Base: three line-plane intersections with the plane of the cell under the crossing.
        z = z_ref
        for _ in range(3):
            (al, be, ga), c = ground_at(np.array([x0 + a * (z - z_ref), y0 + b * (z - z_ref)]))
            z = (al + be * (x0 - a * z_ref - c[0]) + ga * (y0 - b * z_ref - c[1])) / (
                1 - be * a - ga * b)
        base = np.array([x0 + a * (z - z_ref), y0 + b * (z - z_ref), z])
        zb = z + p["breast_height"]
        position = np.array([x0 + a * (zb - z_ref), y0 + b * (zb - z_ref), zb])
        # Cross-section along the axis onto z_ref.
        q = pts[:, :2] - np.outer(pts[:, 2] - z_ref, [a, b])
        qc = q - q.mean(0)
        evals, evecs = np.linalg.eigh(qc.T @ qc / len(q))
        proj = qc @ evecs[:, 1]
        width = proj.max() - proj.min()
        flatness = evals[0] / max(evals[1], 1e-300)
        lean = math.atan(math.hypot(a, b))
        facing = math.hypot(x0, y0) > math.hypot(*pts[:, :2].mean(0))
        horizontal = math.hypot(position[0], position[1])
        reasons = dict(
            enough_points=count >= p["min_points"] and inl.sum() >= p["min_points"],
            radius_ok=p["min_radius"] <= abs(r) <= p["max_radius"],
            upright=lean <= p["max_lean"],
            cylindrical=inl.sum() / len(pts) >= p["min_inlier_ratio"],
            not_wall=width <= p["max_width"] and flatness >= p["min_flatness"],
            fit_ok=bool(found and facing and p["min_range"] < horizontal < p["max_range"]))
        v = np.array([a, b, 1.0])
        fits.append(RefTrunk(position=position, base=base, axis=v / np.linalg.norm(v), lean=lean,
                             radius=abs(r), num_points=count, num_inliers=int(inl.sum()),
                             inlier_ratio=inl.sum() / len(pts), accepted=all(reasons.values()),
                             reasons=reasons))
    accepted = sorted([f for f in fits if f.accepted], key=lambda f: math.hypot(*f.position[:2]))
    return accepted[:p["max_obs"]], fits, num_clusters
