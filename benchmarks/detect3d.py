"""Benchmark of 3D trunk detection (``jaxslam.detect3d.fit_trunks_3d``) per lidar scan.

The cloud is synthesised analytically: a 16-ring x 1800-beam lidar (rings every 2 degrees from
-15 to +15, 0.2 degrees in azimuth, like a Velodyne VLP-16) 1 m above a sloped ground plane,
rays cast exactly against the ground and ``--trunks`` leaning cylinders (radius 0.1-0.3 m, lean
0-15 degrees, 3-16 m away), 20 m range, Gaussian point noise ``--noise``. N = 28,800 points per
scan (rays without a return are padded, ``valid = False``).

Prints compile time and steady-state run time apart (AOT ``lower().compile()``, then the median
of ``--repeats`` calls after ``block_until_ready``), for one scan and for a vmapped batch of
``--batch`` scans, with the detection errors against the true trunks as a sanity check; and the
same for the 2D alternative on the same clouds (a 0.8-1.8 m height slice flattened per azimuth,
``jaxslam.detect.clip_points_by_height``, then Kasa circle fits, ``detect_trunks``).

Usage:
  python benchmarks/detect3d.py                      # float32, batch 8
  python benchmarks/detect3d.py --batch 32 --dtype float64 --noise 0
"""
from __future__ import annotations

import argparse
import math
import pathlib
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

# Time this checkout's code, also when an editable install points at another checkout.
sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

SENSOR_HEIGHT = 1.0
MAX_RANGE = 20.0


def directions(num_rings=16, num_beams=1800):
    """(num_rings num_beams, 3) unit ray directions, ring-major."""
    elevation = np.radians(np.linspace(-15.0, 15.0, num_rings))
    azimuth = -np.pi + 2.0 * np.pi * np.arange(num_beams) / num_beams
    e, a = np.meshgrid(elevation, azimuth, indexing="ij")
    return np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], -1).reshape(-1, 3)


def random_trunks(rng, num):
    """(num, 5) rows (x, y, radius, lean, lean azimuth) [m, m, m, rad, rad], 2 m apart."""
    rows = []
    while len(rows) < num:
        r, b = rng.uniform(3.0, 16.0), rng.uniform(-np.pi, np.pi)
        x, y = r * math.cos(b), r * math.sin(b)
        if all(math.hypot(x - q[0], y - q[1]) > 2.0 for q in rows):
            rows.append((x, y, rng.uniform(0.1, 0.3), math.radians(rng.uniform(0, 15)),
                         rng.uniform(-np.pi, np.pi)))
    return np.array(rows)


def ground_height(x, y, slope=(0.05, -0.03)):
    return -SENSOR_HEIGHT + slope[0] * x + slope[1] * y


def ray_cast(d, trunks):
    """Nearest hit per ray against the ground plane and finite leaning cylinders (8 m long)."""
    sx, sy = 0.05, -0.03
    denom = sx * d[:, 0] + sy * d[:, 1] - d[:, 2]
    with np.errstate(divide="ignore"):
        t = np.where(denom > 0, SENSOR_HEIGHT / denom, np.inf)
    for x, y, radius, lean, azimuth in trunks:
        u = np.array([math.sin(lean) * math.cos(azimuth), math.sin(lean) * math.sin(azimuth),
                      math.cos(lean)])
        base = np.array([x, y, ground_height(x, y)])
        dp = d - np.outer(d @ u, u)
        bp = base - (base @ u) * u
        qa, qb, qc = np.sum(dp * dp, 1), -2.0 * dp @ bp, bp @ bp - radius ** 2
        disc = qb * qb - 4.0 * qa * qc
        with np.errstate(invalid="ignore"):
            hit = (-qb - np.sqrt(np.maximum(disc, 0.0))) / (2.0 * qa)
        s = (hit[:, None] * d - base) @ u
        t = np.minimum(t, np.where((disc >= 0) & (hit > 0) & (s >= 0) & (s <= 8.0), hit,
                                   np.inf))
    valid = t < MAX_RANGE
    return np.where(valid, t, 0.0)[:, None] * d, valid


def breast_points(trunks, breast_height=1.3):
    out = []
    for x, y, _, lean, azimuth in trunks:
        shift = breast_height * math.tan(lean)
        out.append((x + shift * math.cos(azimuth), y + shift * math.sin(azimuth)))
    return np.array(out)


def timed(compiled, args, repeats):
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        out = jax.block_until_ready(compiled(*args))
        times.append(time.perf_counter() - start)
    return float(np.median(times)), out


def main(argv=None):
    from jaxslam.detect3d import fit_trunks_3d

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trunks", type=int, default=8)
    parser.add_argument("--batch", type=int, default=8)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--noise", type=float, default=0.01, help="point noise std [m]")
    parser.add_argument("--dtype", choices=("float32", "float64"), default="float32")
    args = parser.parse_args(argv)
    if args.dtype == "float64":
        jax.config.update("jax_enable_x64", True)
    dtype = jnp.dtype(args.dtype)

    rng = np.random.default_rng(0)
    d = directions()
    clouds, truths = [], []
    for _ in range(args.batch):
        trunks = random_trunks(rng, args.trunks)
        pts, valid = ray_cast(d, trunks)
        pts = pts + args.noise * rng.normal(size=pts.shape)
        clouds.append((pts, valid))
        truths.append(trunks)
    points = jnp.asarray(np.stack([c[0] for c in clouds]), dtype)
    valid = jnp.asarray(np.stack([c[1] for c in clouds]))
    keys = jax.random.split(jax.random.PRNGKey(0), args.batch)
    n = points.shape[1]
    print(f"3D trunk detection: {n} points per scan (16 x 1800 rays, "
          f"{int(valid[0].sum())} returns in scan 0), {args.trunks} trunks, "
          f"noise {args.noise} m, {args.dtype}, backend {jax.default_backend()} "
          f"({jax.devices()[0].device_kind}), default settings (C=32 clusters, P=512 points, "
          f"H=64 hypotheses)")

    single = jax.jit(lambda p, v, k: fit_trunks_3d(p, v, key=k))
    batched = jax.jit(jax.vmap(lambda p, v, k: fit_trunks_3d(p, v, key=k)))
    rows = []
    for name, fn, call_args, scans in (("single scan", single, (points[0], valid[0], keys[0]), 1),
                                       (f"batch of {args.batch}", batched,
                                        (points, valid, keys), args.batch)):
        start = time.perf_counter()
        compiled = fn.lower(*call_args).compile()
        compile_s = time.perf_counter() - start
        run_s, out = timed(compiled, call_args, args.repeats)
        rows.append((name, compile_s, run_s, run_s / scans, out))

    # The 2D alternative on the same clouds: a 0.8-1.8 m slice above the ground under the
    # sensor flattened per azimuth (clip_points_by_height), then Kasa circle fits.
    from jaxslam.detect import clip_points_by_height, detect_trunks

    elevations = np.radians(np.linspace(-15.0, 15.0, 16))
    angles = jnp.asarray(-np.pi + 2.0 * np.pi * np.arange(1800) / 1800, dtype)
    ranges = jnp.where(valid, jnp.linalg.norm(points, axis=-1), MAX_RANGE).reshape(-1, 16, 1800)

    def slice_kasa(r):
        flat = clip_points_by_height(r, elevations, SENSOR_HEIGHT, MAX_RANGE, 0.8, 1.8)
        return detect_trunks(flat, angles, "kasa", max_range=MAX_RANGE)

    for name, fn, call_args, scans in (
            ("slice+kasa 1", jax.jit(slice_kasa), (ranges[0],), 1),
            (f"slice+kasa {args.batch}", jax.jit(jax.vmap(slice_kasa)), (ranges,), args.batch)):
        start = time.perf_counter()
        compiled = fn.lower(*call_args).compile()
        compile_s = time.perf_counter() - start
        run_s, out = timed(compiled, call_args, args.repeats)
        rows.append((name, compile_s, run_s, run_s / scans, out))

    print(f"\n{'case':<14} {'compile [s]':>12} {'run [ms]':>10} {'per scan [ms]':>14} "
          f"{'scans/s':>9}")
    for name, compile_s, run_s, per_scan, _ in rows:
        print(f"{name:<14} {compile_s:12.2f} {run_s * 1e3:10.1f} {per_scan * 1e3:14.1f} "
              f"{1.0 / per_scan:9.1f}")

    out = rows[1][4]
    found, errors, radius_errors = 0, [], []
    for b, trunks in enumerate(truths):
        ok = np.asarray(out.observations.valid[b])
        pos = np.asarray(out.position[b, :, :2])
        for (x, y), (_, _, radius, _, _) in zip(breast_points(trunks), trunks):
            dist = np.where(ok, np.hypot(pos[:, 0] - x, pos[:, 1] - y), np.inf)
            k = int(np.argmin(dist))
            if dist[k] < 0.2:
                found += 1
                errors.append(dist[k])
                radius_errors.append(float(out.radius[b, k]) - radius)
    total = args.trunks * args.batch
    false = int(np.asarray(out.observations.valid).sum()) - found
    if errors:
        print(f"\ndetections: {found}/{total} trunks found, {false} other detections; "
              f"breast-height position error RMS {np.sqrt(np.mean(np.square(errors))) * 100:.2f}"
              f" cm (max {np.max(errors) * 100:.2f}), radius error RMS "
              f"{np.sqrt(np.mean(np.square(radius_errors))) * 100:.2f} cm")
    else:
        print(f"\ndetections: none of {total} trunks found")


if __name__ == "__main__":
    main()
