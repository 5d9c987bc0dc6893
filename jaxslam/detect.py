"""Trunk detection from a 2D scan: segmentation, per-segment circle fits, padded observations.

Pipeline (Geiser et al. 2023, section 2, Park and Park, sections 2.2-2.3), fixed shapes throughout:
  1. Beam b is a point p_b = r_b (cos a_b, sin a_b) when min_range < r_b < max_range.
  2. Segments are runs of points. With p the previous beam that has a point, a break precedes
     the point of beam b when more than ``max_missing_beams`` beams between p and b have no
     point, |r_b - r_p| > range_jump or |a_b - a_p| > max_angle_gap. With the default 0, any
     missing beam breaks; a positive value bridges short dropouts where the ranges on both
     sides agree within ``bridge_range_jump`` (default range_jump), so a wall or a ground
     strike whose returns are interrupted every few beams stays one wide (rejected) segment
     instead of many trunk-sized pieces (Victoria Park), while a trunk beside a dropout and
     a neighbour at another range stays apart. Beams without a point join the
     current segment with weight 0. Labels are cumsum(breaks) - 1, so per-segment sums are
     ``segment_sum`` with num_segments = B. A full-circle scan is rolled to start at a break
     so a trunk across the -pi seam stays one segment.
  3. Segments are rejected when too short (fewer than ``min_points`` points), too narrow
     (chord < ``min_width``), too wide (chord > ``max_width``: walls, logs, bushes), occluded
     (a neighbouring beam is nearer than the segment edge by more than ``range_jump``, so part
     of the trunk is hidden), or when the fit is not a plausible trunk (radius outside
     [min_radius, max_radius], centre not behind the arc, RMS residual > ``max_residual``).
  4. Centre and radius per segment by ``method``:
       centroid   mean of the points (Geiser et al. 2023, section 2.1; biased toward the sensor), radius = chord/2;
       kasa       algebraic fit min sum (x^2 + y^2 + D x + E y + F)^2 (Kasa 1976, Park and Park);
       geometric  Gauss-Newton on sum (|p - c| - r)^2 started from Kasa;
       ransac     best of ``num_hypotheses`` 3-point circles by inlier count (Geiser et al. 2023, section 2.2, in
                  2D), then a Kasa fit on its inliers.
  5. The ``max_obs`` nearest accepted trunks become ``Observations``: range and bearing of the
     trunk centre in the sensor frame and the radius; unused rows are invalid.
"""
from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from jaxslam.types import Observations

METHODS = ("centroid", "kasa", "geometric", "ransac")


def _segment_sum(values, labels, num_segments):
    return jax.ops.segment_sum(values, labels, num_segments=num_segments)


def segment_labels(ranges, angles, point_valid, range_jump, max_angle_gap,
                   max_missing_beams=0, bridge_range_jump=None):
    """Break flags (B,) and segment labels (B,) in [0, B) of a scan (roll already applied).

    A point breaks from the previous point p (module docstring, step 2); beams without a
    point never break (they join the current segment), except beam 0, which always starts one.
    """
    index = jnp.arange(ranges.shape[0])
    last_point = jax.lax.cummax(jnp.where(point_valid, index, -1))
    previous = jnp.concatenate([jnp.full(1, -1, last_point.dtype), last_point[:-1]])
    has_previous = previous >= 0
    safe = jnp.maximum(previous, 0)
    num_missing = index - previous - 1
    bridge = range_jump if bridge_range_jump is None else bridge_range_jump
    jump = jnp.abs(ranges - ranges[safe]) > jnp.where(num_missing > 0, bridge, range_jump)
    gap = jnp.abs(angles - angles[safe]) > max_angle_gap
    missing = num_missing > max_missing_beams
    breaks = point_valid & (~has_previous | jump | gap | missing)
    breaks = breaks.at[0].set(True)
    return breaks, jnp.cumsum(breaks) - 1


def _seam_shift(ranges, angles, point_valid, range_jump, max_angle_gap, max_missing_beams=0,
                bridge_range_jump=None):
    """Roll offset that starts a full-circle scan at a break (0 when the seam is a break)."""
    two_pi = 2.0 * jnp.pi
    seam_gap = jnp.abs(angles[0] + two_pi - angles[-1])
    seam_joined = ((seam_gap <= max_angle_gap) & point_valid[0] & point_valid[-1]
                   & (jnp.abs(ranges[0] - ranges[-1]) <= range_jump))
    breaks, _ = segment_labels(ranges, angles, point_valid, range_jump, max_angle_gap,
                               max_missing_beams, bridge_range_jump)
    inner = breaks.at[0].set(False)
    first_break = jnp.where(jnp.any(inner), jnp.argmax(inner), 0)
    return jnp.where(seam_joined, first_break, 0)


def _solve_kasa(suu, suv, svv, szu, szv):
    """Centred Kasa normal equations [[Suu, Suv], [Suv, Svv]] (D, E) = -(Szu, Szv).

    Returns the centre offset (cu, cv) = (-D/2, -E/2) and a bool ``ok`` (non-singular)."""
    det = suu * svv - suv * suv
    ok = det > 1e-12 * jnp.maximum(suu * svv, 1e-30)
    safe = jnp.where(ok, det, 1.0)
    d = -(svv * szu - suv * szv) / safe
    e = -(suu * szv - suv * szu) / safe
    return -0.5 * d, -0.5 * e, ok


def _kasa(x, y, weight, labels, num_segments):
    """Weighted Kasa fit per segment on coordinates centred at each segment's mean.

    Returns centre x, y (S,), radius (S,), ok (S,)."""
    count = _segment_sum(weight, labels, num_segments)
    safe_count = jnp.maximum(count, 1e-12)
    mean_x = _segment_sum(weight * x, labels, num_segments) / safe_count
    mean_y = _segment_sum(weight * y, labels, num_segments) / safe_count
    u, v = x - mean_x[labels], y - mean_y[labels]
    z = u * u + v * v

    def total(values):
        return _segment_sum(weight * values, labels, num_segments)

    cu, cv, ok = _solve_kasa(total(u * u), total(u * v), total(v * v), total(z * u),
                             total(z * v))
    # F = -mean(z); r^2 = (D^2 + E^2)/4 - F = cu^2 + cv^2 + mean(z).
    radius_sq = cu * cu + cv * cv + total(z) / safe_count
    return mean_x + cu, mean_y + cv, jnp.sqrt(jnp.maximum(radius_sq, 0.0)), ok & (count >= 3)


def _geometric(x, y, weight, labels, num_segments, iterations):
    """Gauss-Newton on sum_i (|p_i - c| - r)^2 per segment, from the Kasa solution.

    Residual e_i = d_i - r, d_i = |p_i - c|; Jacobian row (-(x_i-cx)/d_i, -(y_i-cy)/d_i, -1).
    """
    cx, cy, radius, ok = _kasa(x, y, weight, labels, num_segments)

    def total(values):
        return _segment_sum(weight * values, labels, num_segments)

    def step(carry, _):
        cx, cy, radius = carry
        dx, dy = x - cx[labels], y - cy[labels]
        dist = jnp.maximum(jnp.hypot(dx, dy), 1e-9)
        res = dist - radius[labels]
        jx, jy, jr = -dx / dist, -dy / dist, -jnp.ones_like(dist)
        a = jnp.stack([jnp.stack([total(jx * jx), total(jx * jy), total(jx * jr)], -1),
                       jnp.stack([total(jx * jy), total(jy * jy), total(jy * jr)], -1),
                       jnp.stack([total(jx * jr), total(jy * jr), total(jr * jr)], -1)], -2)
        g = jnp.stack([total(jx * res), total(jy * res), total(jr * res)], -1)
        a = a + 1e-9 * jnp.eye(3, dtype=a.dtype)[None]  # Levenberg damping keeps empty slots finite
        delta = jnp.linalg.solve(a, -g[..., None])[..., 0]
        delta = jnp.where(jnp.all(jnp.isfinite(delta), -1, keepdims=True), delta, 0.0)
        return (cx + delta[:, 0], cy + delta[:, 1], radius + delta[:, 2]), None

    (cx, cy, radius), _ = jax.lax.scan(step, (cx, cy, radius), None, length=iterations)
    return cx, cy, jnp.abs(radius), ok


def _circle_through(p1, p2, p3):
    """Circle through three points, each (..., 2): centre (..., 2), radius (...), ok (...)."""
    ax, ay = p2[..., 0] - p1[..., 0], p2[..., 1] - p1[..., 1]
    bx, by = p3[..., 0] - p1[..., 0], p3[..., 1] - p1[..., 1]
    det = 2.0 * (ax * by - ay * bx)
    ok = jnp.abs(det) > 1e-9
    safe = jnp.where(ok, det, 1.0)
    a2, b2 = ax * ax + ay * ay, bx * bx + by * by
    ux = (by * a2 - ay * b2) / safe
    uy = (ax * b2 - bx * a2) / safe
    centre = jnp.stack([p1[..., 0] + ux, p1[..., 1] + uy], -1)
    return centre, jnp.hypot(ux, uy), ok


def _ransac(key, x, y, weight, labels, first, count, num_segments, num_hypotheses,
            inlier_tol, min_radius, max_radius):
    """RANSAC circles: H random 3-point hypotheses per segment, keep the most inliers
    (|d_i - r| < inlier_tol, radius within bounds), refit by Kasa on the inliers."""
    draws = jax.random.uniform(key, (num_segments, num_hypotheses, 3))
    span = jnp.maximum(count, 1.0)[:, None, None]
    # Stratified picks (first, middle, last third) keep the three points apart.
    offset = jnp.floor((draws + jnp.arange(3)[None, None]) / 3.0 * span).astype(jnp.int32)
    index = jnp.clip(first[:, None, None] + offset, 0, x.shape[0] - 1)
    points = jnp.stack([x[index], y[index]], -1)  # (S, H, 3, 2)
    centre, radius, ok = _circle_through(points[..., 0, :], points[..., 1, :],
                                         points[..., 2, :])
    ok = ok & (radius >= min_radius) & (radius <= max_radius)
    dist = jnp.hypot(x[:, None] - centre[labels, :, 0], y[:, None] - centre[labels, :, 1])
    inlier = (jnp.abs(dist - radius[labels]) < inlier_tol) & (weight[:, None] > 0)
    votes = _segment_sum(inlier.astype(x.dtype), labels, num_segments)  # (S, H)
    votes = jnp.where(ok, votes, -1.0)
    best = jnp.argmax(votes, axis=1)
    best_inlier = jnp.take_along_axis(inlier, best[labels][:, None], axis=1)[:, 0]
    cx, cy, r, fit_ok = _kasa(x, y, weight * best_inlier, labels, num_segments)
    return cx, cy, r, fit_ok & (jnp.max(votes, axis=1) >= 3)


def detect_trunks(ranges, angles, method: str = "kasa", *, max_obs: int = 16,
                  max_range: float = 20.0, min_range: float = 0.1, key=None,
                  range_jump: float = 0.3, max_angle_gap: float = 0.05,
                  max_missing_beams: int = 0, bridge_range_jump: float | None = None,
                  min_points: int = 4,
                  min_width: float = 0.04, max_width: float = 1.0, min_radius: float = 0.03,
                  max_radius: float = 0.5, max_residual: float = 0.03,
                  geometric_iterations: int = 8, num_hypotheses: int = 32,
                  inlier_tol: float = 0.02) -> Observations:
    """Trunks in one 2D scan as padded observations.

    Args:
      ranges: (B,) [m]; a reading >= max_range (or <= min_range) is no return.
      angles: (B,) increasing beam bearings in the sensor frame [rad].
      method: one of ``METHODS``; ``ransac`` needs ``key``.
      max_obs: K, the number of output rows (nearest trunks first).
      Other arguments: thresholds of the module docstring, in metres.
    Returns:
      ``Observations`` with z (K, 2) = (range, bearing) of each trunk centre, radius (K,),
      valid (K,), landmark_id (K,) = -1.
    """
    if method not in METHODS:
        raise ValueError(f"detect_trunks method={method!r}; expected one of {list(METHODS)}")
    if method == "ransac" and key is None:
        raise ValueError("detect_trunks method='ransac' needs a PRNG key: pass key=...")
    if isinstance(max_missing_beams, (int, float)) and max_missing_beams < 0:
        raise ValueError(f"detect_trunks max_missing_beams={max_missing_beams}; expected an "
                         "integer >= 0 (0: any beam without a return breaks a segment)")
    ranges, angles = jnp.asarray(ranges), jnp.asarray(angles, jnp.asarray(ranges).dtype)
    if ranges.ndim != 1 or ranges.shape != angles.shape:
        raise ValueError(f"detect_trunks expects ranges (B,) and angles (B,); got "
                         f"{ranges.shape} and {angles.shape}")
    thresholds = dict(max_range=max_range, min_range=min_range, range_jump=range_jump,
                      max_angle_gap=max_angle_gap, max_missing_beams=max_missing_beams,
                      bridge_range_jump=(range_jump if bridge_range_jump is None
                                         else bridge_range_jump),
                      min_points=min_points, min_width=min_width,
                      max_width=max_width, min_radius=min_radius, max_radius=max_radius,
                      max_residual=max_residual, inlier_tol=inlier_tol)
    return _detect(ranges, angles, key, method, max_obs, geometric_iterations, num_hypotheses,
                   **thresholds)


@functools.partial(jax.jit, static_argnames=("method", "max_obs", "geometric_iterations",
                                             "num_hypotheses"))
def _detect(ranges, angles, key, method, max_obs, geometric_iterations, num_hypotheses, *,
            max_range, min_range, range_jump, max_angle_gap, max_missing_beams,
            bridge_range_jump, min_points,
            min_width, max_width,
            min_radius, max_radius, max_residual, inlier_tol) -> Observations:
    """Jitted body of ``detect_trunks`` (thresholds are traced: no recompile per value)."""
    num_beams = ranges.shape[0]
    point_valid = (ranges > min_range) & (ranges < max_range)
    shift = _seam_shift(ranges, angles, point_valid, range_jump, max_angle_gap,
                        max_missing_beams, bridge_range_jump)
    ranges, angles, point_valid = (jnp.roll(v, -shift) for v in (ranges, angles, point_valid))
    angles = jnp.where(jnp.arange(num_beams) >= num_beams - shift, angles + 2.0 * jnp.pi,
                       angles)
    breaks, labels = segment_labels(ranges, angles, point_valid, range_jump, max_angle_gap,
                                    max_missing_beams, bridge_range_jump)
    weight = point_valid.astype(ranges.dtype)
    x, y = ranges * jnp.cos(angles), ranges * jnp.sin(angles)

    index = jnp.arange(num_beams)
    count = _segment_sum(weight, labels, num_beams)
    first = jax.ops.segment_min(jnp.where(point_valid, index, num_beams), labels, num_beams)
    last = jax.ops.segment_max(jnp.where(point_valid, index, -1), labels, num_beams)
    first_c, last_c = jnp.clip(first, 0, num_beams - 1), jnp.clip(last, 0, num_beams - 1)
    chord = jnp.hypot(x[last_c] - x[first_c], y[last_c] - y[first_c])
    # Occluded: the beam just outside an edge returned nearer than that edge.
    before = jnp.where(first_c > 0, ranges[first_c - 1], jnp.inf)
    after = jnp.where(last_c < num_beams - 1, ranges[jnp.minimum(last_c + 1, num_beams - 1)],
                      jnp.inf)
    before = jnp.where(before > min_range, before, jnp.inf)
    after = jnp.where(after > min_range, after, jnp.inf)
    occluded = (before < ranges[first_c] - range_jump) | (after < ranges[last_c] - range_jump)

    safe_count = jnp.maximum(count, 1.0)
    mean_x = _segment_sum(weight * x, labels, num_beams) / safe_count
    mean_y = _segment_sum(weight * y, labels, num_beams) / safe_count
    if method == "centroid":
        cx, cy, radius, fit_ok = mean_x, mean_y, 0.5 * chord, jnp.ones(num_beams, bool)
    elif method == "kasa":
        cx, cy, radius, fit_ok = _kasa(x, y, weight, labels, num_beams)
    elif method == "geometric":
        cx, cy, radius, fit_ok = _geometric(x, y, weight, labels, num_beams,
                                            geometric_iterations)
    else:
        cx, cy, radius, fit_ok = _ransac(key, x, y, weight, labels, first_c, count, num_beams,
                                         num_hypotheses, inlier_tol, min_radius, max_radius)
    residual = jnp.hypot(x - cx[labels], y - cy[labels]) - radius[labels]
    rms = jnp.sqrt(_segment_sum(weight * residual ** 2, labels, num_beams) / safe_count)
    centre_range = jnp.hypot(cx, cy)
    behind = centre_range > jnp.hypot(mean_x, mean_y)  # the arc faces the sensor
    shape_ok = (radius >= min_radius) & (radius <= max_radius)
    if method != "centroid":
        shape_ok = shape_ok & behind & (rms <= max_residual)
    accepted = ((count >= min_points) & (chord >= min_width) & (chord <= max_width)
                & ~occluded & fit_ok & shape_ok & jnp.isfinite(centre_range))
    return _pack(accepted, centre_range, jnp.arctan2(cy, cx), radius, max_obs)


def _pack(accepted, centre_range, bearing, radius, max_obs: int) -> Observations:
    """The ``max_obs`` nearest accepted segments as padded ``Observations``."""
    num = accepted.shape[0]
    k = min(max_obs, num)
    neg, pick = jax.lax.top_k(-jnp.where(accepted, centre_range, jnp.inf), k)
    valid = jnp.isfinite(neg)
    z = jnp.stack([jnp.where(valid, centre_range[pick], 0.0),
                   jnp.where(valid, bearing[pick], 0.0)], -1)
    rad = jnp.where(valid, radius[pick], 0.0)
    pad = max_obs - k
    return Observations(
        z=jnp.pad(z, ((0, pad), (0, 0))), valid=jnp.pad(valid, (0, pad)),
        radius=jnp.pad(rad, (0, pad)), landmark_id=jnp.full(max_obs, -1, jnp.int32))


def clip_points_by_height(ranges_3d, elevations, sensor_height, max_range, z_min=0.2,
                          z_max=2.0):
    """3D path: keep returns with height in [z_min, z_max] (drops ground and canopy), project
    to the horizontal plane and keep the nearest per azimuth, giving (B,) 2D ranges for
    ``detect_trunks``.

    Args:
      ranges_3d: (L, B) ranges along beams of elevation ``elevations`` (L,) [rad].
    """
    elevations = jnp.asarray(elevations, ranges_3d.dtype)[:, None]
    height = sensor_height + ranges_3d * jnp.sin(elevations)
    horizontal = ranges_3d * jnp.cos(elevations)
    keep = (ranges_3d < max_range) & (height >= z_min) & (height <= z_max)
    return jnp.min(jnp.where(keep, horizontal, max_range), axis=0)


# 3D point clouds: ground, height band, clusters and RANSAC cylinder fits (jaxslam.detect3d).
from jaxslam.detect3d import detect_trunks_3d, fit_trunks_3d  # noqa: E402,F401
