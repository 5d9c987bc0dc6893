"""Lidar topics of a ROS bag -> scans and trunk observations.

LaserScans become range arrays; PointCloud2 messages become points (N, 3), flattened into a 2D
scan (``flatten_cloud``) and, with ``cloud_detection="cylinder"``, fitted with cylinders
(``jaxslam.detect3d.fit_trunks_3d``). Trunks are found in batches: one jitted ``vmap`` per chunk
of scans or clouds, padded so a bag compiles each detector a few times, not once per message.

Shapes: S messages, B beams (or azimuth bins), K = ``max_obs`` padded detections, N points.
JAX and the detectors are imported when a bag is read.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from jaxslam.host import in_float64
from jaxslam.datasets.rosbag_reader import OpenBag, message_stamp
from jaxslam.geometry import wrap_angle

# PointField datatypes (sensor_msgs/PointField): the float ones x, y and z may use.
_POINT_FIELD_FLOATS = {7: "f4", 8: "f8"}
_POINT_FIELD_NAMES = {1: "INT8", 2: "UINT8", 3: "INT16", 4: "UINT16", 5: "INT32", 6: "UINT32",
                      7: "FLOAT32", 8: "FLOAT64"}
_DETECT_CHUNK = 128  # scans per batched detection call (padded): one compile per beam count
_CLOUD_CHUNK = 8  # clouds per batched cylinder-detection call (padded with empty clouds)
_MIN_CLOUD_SLOTS = 1024  # clouds are padded to a power of two points, at least this many
CLOUD_DETECTIONS = ("cylinder", "slice")


# ----------------------------------------------------------------------------------------------
# Scans and point clouds


def laser_scan_arrays(message):
    """One LaserScan as (ranges (B,) [m] with +inf for no return, angles (B,) [rad]).

    Beams are ordered by increasing bearing (a negative angle_increment is reversed). NaN,
    +-inf, non-positive ranges and ranges outside [range_min, range_max] are no return.
    """
    ranges = np.asarray(message.ranges, np.float64).copy()
    count = ranges.shape[0]
    angles = float(message.angle_min) + float(message.angle_increment) * np.arange(count)
    low = max(float(message.range_min), 0.0)
    high = float(message.range_max) if float(message.range_max) > 0 else np.inf
    with np.errstate(invalid="ignore"):
        no_return = ~np.isfinite(ranges) | (ranges <= low) | (ranges > high)
    ranges[no_return] = np.inf
    if count > 1 and message.angle_increment < 0:
        ranges, angles = ranges[::-1].copy(), angles[::-1].copy()
    return ranges, angles


def cloud_points(message) -> np.ndarray:
    """The finite points (N, 3) [m] of a PointCloud2 in its own frame, float64.

    Reads the x, y and z fields (FLOAT32 or FLOAT64, each with count 1) at their offsets in
    records of ``point_step`` bytes, rows of ``row_step`` bytes (padding skipped), in the
    message's byte order (``is_bigendian``). Points with a NaN or inf coordinate are dropped.

    Raises:
      ValueError: a missing or non-float x/y/z field, or data shorter than the layout says.
    """
    fields = {field.name: field for field in message.fields}
    missing = [name for name in "xyz" if name not in fields]
    if missing:
        raise ValueError(f"PointCloud2 has no field(s) {missing} (fields: {sorted(fields)}); "
                         "expected float x, y and z fields")
    order = ">" if message.is_bigendian else "<"
    formats = []
    for name in "xyz":
        field = fields[name]
        if field.datatype not in _POINT_FIELD_FLOATS or int(getattr(field, "count", 1)) > 1:
            raise ValueError(
                f"PointCloud2 field {name!r} has datatype "
                f"{_POINT_FIELD_NAMES.get(field.datatype, field.datatype)} (count "
                f"{field.count}); expected FLOAT32 or FLOAT64 with count 1")
        formats.append(order + _POINT_FIELD_FLOATS[field.datatype])
    width, height = int(message.width), int(message.height)
    point_step, row_step = int(message.point_step), int(message.row_step)
    row_step = row_step if row_step >= width * point_step else width * point_step
    data = np.asarray(message.data, np.uint8).reshape(-1)
    if width * height == 0:
        return np.zeros((0, 3))
    needed = (height - 1) * row_step + width * point_step
    if data.size < needed:
        raise ValueError(f"PointCloud2 data holds {data.size} bytes; its layout (height "
                         f"{height}, width {width}, point_step {point_step}, row_step "
                         f"{row_step}) needs {needed}")
    record = np.dtype({"names": list("xyz"), "formats": formats,
                       "offsets": [int(fields[n].offset) for n in "xyz"],
                       "itemsize": point_step})
    rows = [np.frombuffer(data, record, count=width, offset=r * row_step) for r in range(height)]
    table = np.concatenate(rows)
    points = np.stack([table[n].astype(np.float64) for n in "xyz"], axis=-1)
    return points[np.all(np.isfinite(points), axis=-1)]


def cloud_scan_angles(num_beams: int) -> np.ndarray:
    """(B,) bearings [rad] of the azimuth bins of ``flatten_cloud``: bin centres
    -pi + (i + 1/2) 2 pi / B."""
    return -np.pi + (np.arange(num_beams) + 0.5) * (2.0 * np.pi / num_beams)


def flatten_cloud(points, num_beams: int = 720, z_min: float = -0.5, z_max: float = 0.5,
                  min_range: float = 0.0, front_tolerance: float = 0.05) -> np.ndarray:
    """A height band of a point cloud as a 2D scan: (N, 3) points -> (B,) ranges [m].

    Points with z_min <= z <= z_max (the cloud frame's z, up) and horizontal range >
    ``min_range`` are projected to the plane and binned by azimuth into ``num_beams`` bins
    (bearings ``cloud_scan_angles``). A bin's range is that of its front surface: among its
    points within ``front_tolerance`` [m] of its nearest one, the point closest in azimuth to
    the bin centre (the nearest point alone sits at a bin edge on a trunk's flank, which
    would widen every trunk by up to half a bin). +inf for an empty bin. The same reduction
    as ``jaxslam.detect.clip_points_by_height`` for clouds that are point lists, not range
    images.
    """
    points = np.asarray(points, np.float64).reshape(-1, 3)
    ranges = np.full(num_beams, np.inf)
    horizontal = np.hypot(points[:, 0], points[:, 1])
    keep = (points[:, 2] >= z_min) & (points[:, 2] <= z_max) & (horizontal > min_range)
    if not keep.any():
        return ranges
    horizontal = horizontal[keep]
    azimuth = np.arctan2(points[keep, 1], points[keep, 0])
    bins = np.floor((azimuth + np.pi) / (2.0 * np.pi) * num_beams).astype(np.int64) % num_beams
    nearest = np.full(num_beams, np.inf)
    np.minimum.at(nearest, bins, horizontal)
    front = horizontal <= nearest[bins] + front_tolerance
    bins, horizontal, azimuth = bins[front], horizontal[front], azimuth[front]
    off_centre = np.abs(in_float64(wrap_angle, azimuth - cloud_scan_angles(num_beams)[bins]))
    order = np.lexsort((off_centre, bins))
    first = np.unique(bins[order], return_index=True)[1]
    ranges[bins[order][first]] = horizontal[order][first]
    return ranges


# ----------------------------------------------------------------------------------------------
# Trunk detection


def detect_trunks_batched(ranges, angles, max_obs: int = 16, **settings):
    """``jaxslam.detect.detect_trunks`` on every scan: (T, B) ranges, (B,) angles -> NumPy
    (z (T, K, 2) [m, rad], valid (T, K) bool, radius (T, K) [m]).

    Scans go through one ``jax.vmap``-ed, jitted call per chunk of 16, 32, 64 or 128 scans
    (the last chunk padded with empty scans), in float32, so a bag of any length compiles at
    most four times per beam count and setting. ``settings`` are ``detect_trunks`` keywords
    (``method`` included; not ``ransac``, which needs a key per scan).
    """
    import jax.numpy as jnp

    ranges = np.asarray(ranges, np.float64)
    steps, beams = ranges.shape
    chunk = min(_DETECT_CHUNK, max(16, 1 << max(steps - 1, 0).bit_length()))
    padded = np.full((-(-steps // chunk) * chunk, beams), np.inf, np.float32)
    padded[:steps] = ranges
    detect = _batched_detector(int(max_obs), tuple(sorted(settings.items())))
    angles32 = jnp.asarray(np.asarray(angles, np.float32))
    parts = [detect(jnp.asarray(padded[i:i + chunk]), angles32)
             for i in range(0, padded.shape[0], chunk)]
    z = np.concatenate([np.asarray(p.z, np.float64) for p in parts])[:steps]
    valid = np.concatenate([np.asarray(p.valid, bool) for p in parts])[:steps]
    radius = np.concatenate([np.asarray(p.radius, np.float64) for p in parts])[:steps]
    return z, valid, radius


_DETECTORS: dict = {}


def _batched_detector(max_obs: int, settings: tuple):
    """A jitted ``vmap`` of ``detect_trunks`` over scans, cached per (max_obs, settings)."""
    key = (max_obs, settings)
    if key not in _DETECTORS:
        import jax

        from jaxslam.detect import detect_trunks

        options = dict(settings)
        method = options.pop("method", "kasa")
        _DETECTORS[key] = jax.jit(jax.vmap(
            lambda scan, angles: detect_trunks(scan, angles, method, max_obs=max_obs,
                                               **options), in_axes=(0, None)))
    return _DETECTORS[key]


def pad_detections(detections: list, max_obs: int | None):
    """Per-cloud detections (each with z (K_i, 2), valid (K_i,), optional radius (K_i,)) as
    padded NumPy (z (T, K, 2), valid (T, K), radius (T, K)); K = max_obs (extra rows,
    the farthest, are dropped)."""
    arrays = []
    for found in detections:
        z = np.asarray(found.z, np.float64).reshape(-1, 2)
        valid = np.asarray(found.valid, bool).reshape(-1)
        radius = getattr(found, "radius", None)
        radius = np.zeros(len(z)) if radius is None else np.asarray(radius, np.float64)
        if valid.shape != (len(z),) or radius.shape != (len(z),):
            raise ValueError(f"cloud_detector returned z {z.shape}, valid {valid.shape}, "
                             f"radius {radius.shape}; expected (K, 2), (K,), (K,)")
        arrays.append((z, valid, radius.reshape(-1)))
    width = max_obs or max([len(z) for z, _, _ in arrays] + [1])
    z_all = np.zeros((len(arrays), width, 2))
    valid_all = np.zeros((len(arrays), width), bool)
    radius_all = np.zeros((len(arrays), width))
    for t, (z, valid, radius) in enumerate(arrays):
        order = np.argsort(np.where(valid, z[:, 0], np.inf), kind="stable")[:width]
        count = len(order)
        z_all[t, :count], valid_all[t, :count] = z[order], valid[order]
        radius_all[t, :count] = np.where(valid[order], radius[order], 0.0)
    z_all[~valid_all] = 0.0
    return z_all, valid_all, radius_all


class CloudTrunks(NamedTuple):
    """Trunks of one cloud (NumPy): z (K, 2) horizontal range [m] and bearing [rad] of the
    breast-height point, valid (K,) bool, radius (K,) = DBH / 2 [m]."""

    z: np.ndarray
    valid: np.ndarray
    radius: np.ndarray


def cloud_slots(num_points: int) -> int:
    """Padded point count of a cloud: the next power of two >= max(num_points, 1024), so a
    bag compiles the cylinder detector once per size bucket, not per cloud."""
    return max(_MIN_CLOUD_SLOTS, 1 << max(int(num_points) - 1, 0).bit_length())


def detect_trunks_3d_batched(clouds, indices, max_obs: int = 16, **settings) -> list:
    """``jaxslam.detect3d.fit_trunks_3d`` on each cloud: list of (N_i, 3) points -> list of
    ``CloudTrunks``.

    Clouds go through one jitted ``vmap`` per chunk of ``_CLOUD_CHUNK`` (the last one padded
    with empty clouds), in float32, each padded to ``cloud_slots`` of the chunk's largest cloud
    (``valid = False``). Cloud i's RANSAC key is ``fold_in(PRNGKey(0), indices[i])`` (its
    message index), so a cloud's trunks do not depend on its chunk. ``settings`` are
    ``fit_trunks_3d`` keywords.
    """
    import jax
    import jax.numpy as jnp

    detect = _batched_detector_3d(int(max_obs), tuple(sorted(settings.items())))
    out = []
    for start in range(0, len(clouds), _CLOUD_CHUNK):
        part = [np.asarray(c, np.float64).reshape(-1, 3) for c in
                clouds[start:start + _CLOUD_CHUNK]]
        slots = cloud_slots(max(len(c) for c in part))
        points = np.zeros((_CLOUD_CHUNK, slots, 3), np.float32)
        valid = np.zeros((_CLOUD_CHUNK, slots), bool)
        for i, c in enumerate(part):
            points[i, :len(c)], valid[i, :len(c)] = c, True
        index = np.zeros(_CLOUD_CHUNK, np.int64)
        index[:len(part)] = indices[start:start + len(part)]
        keys = jax.vmap(lambda i: jax.random.fold_in(jax.random.PRNGKey(0), i))(
            jnp.asarray(index, jnp.uint32))
        found = detect(jnp.asarray(points), jnp.asarray(valid), keys)
        z, ok, radius = (np.asarray(found.z, np.float64), np.asarray(found.valid, bool),
                         np.asarray(found.radius, np.float64))
        out += [CloudTrunks(z[i], ok[i], radius[i]) for i in range(len(part))]
    return out


_DETECTORS_3D: dict = {}


def _batched_detector_3d(max_obs: int, settings: tuple):
    """A jitted ``vmap`` of ``fit_trunks_3d(...).observations`` over clouds, cached per
    (max_obs, settings)."""
    key = (max_obs, settings)
    if key not in _DETECTORS_3D:
        import jax

        from jaxslam.detect3d import fit_trunks_3d

        options = dict(settings)
        _DETECTORS_3D[key] = jax.jit(jax.vmap(
            lambda points, valid, k: fit_trunks_3d(points, valid, key=k, max_obs=max_obs,
                                                   **options).observations))
    return _DETECTORS_3D[key]


def detector_keywords(detector: dict | None, cloud: bool, cloud_detection: str) -> dict:
    """``detector`` checked against the keywords of the detector that will use it:
    ``fit_trunks_3d`` for clouds with ``cloud_detection="cylinder"``, else ``detect_trunks``."""
    import inspect

    if cloud and cloud_detection == "cylinder":
        from jaxslam.detect3d import fit_trunks_3d as function
        name, skip = "jaxslam.detect3d.fit_trunks_3d", {"points", "valid", "key", "max_obs"}
    else:
        from jaxslam.detect import detect_trunks as function
        name, skip = "jaxslam.detect.detect_trunks", {"ranges", "angles", "key", "max_obs"}
    allowed = set(inspect.signature(function).parameters) - skip
    unknown = sorted(set(detector or {}) - allowed)
    if unknown:
        raise ValueError(f"detector has unknown keyword(s) {unknown}; expected keywords of "
                         f"{name}: {sorted(allowed)} (max_obs is its own argument)")
    return dict(detector or {})


# ----------------------------------------------------------------------------------------------
# Reading the sensor topic


class SensorTrack(NamedTuple):
    """Scans of one topic: time_ns (S,) int64, index (S,), ranges (S, B) [m] (+inf: no
    return), angles (B,) [rad], detections: per-message results of a cloud_detector or None."""

    time_ns: np.ndarray
    index: np.ndarray
    ranges: np.ndarray
    angles: np.ndarray
    detections: list | None


def read_scans(bag: OpenBag, topic: str, time_source: str) -> SensorTrack:
    """Every LaserScan of ``topic``; one beam layout for the whole topic."""
    stamps, indices, rows = [], [], []
    layout = None
    for index, bag_ns, message in bag.messages(topic):
        ranges, angles = laser_scan_arrays(message)
        this = (len(ranges), float(message.angle_min), float(message.angle_increment))
        if layout is None:
            layout, first_angles = this, angles
        elif this[0] != layout[0] or not np.allclose(this[1:], layout[1:], atol=1e-6):
            bag.fail(f"topic {topic!r}: message {index} has {this[0]} beams (angle_min "
                     f"{this[1]:.6g}, angle_increment {this[2]:.6g} rad); message 0 has "
                     f"{layout[0]} (angle_min {layout[1]:.6g}, angle_increment "
                     f"{layout[2]:.6g}); expected one beam layout for the whole topic")
        stamps.append(message_stamp(bag, topic, index, bag_ns, message.header, time_source))
        indices.append(index)
        rows.append(ranges)
    return SensorTrack(np.asarray(stamps, np.int64), np.asarray(indices, np.int64),
                       np.stack(rows), first_angles, None)


def read_clouds(bag: OpenBag, topic: str, time_source: str, num_beams: int, z_band,
                 cloud_detector, cloud_detection: str = "slice", max_obs: int = 16,
                 settings: dict | None = None) -> SensorTrack:
    """Every PointCloud2 of ``topic`` flattened (``flatten_cloud``) and its detections: the
    ``cloud_detector``'s, else with ``cloud_detection="cylinder"`` ``fit_trunks_3d``'s
    (``settings``), else none (the flattened scans are detected later). Clouds are reduced
    as they are read, ``_CLOUD_CHUNK`` at a time (bags of clouds are large)."""
    stamps, indices, rows, detections, pending, pending_index = [], [], [], [], [], []
    cylinder = cloud_detector is None and cloud_detection == "cylinder"

    def flush():
        detections.extend(detect_trunks_3d_batched(pending, pending_index, max_obs,
                                                   **(settings or {})))
        pending.clear()
        pending_index.clear()

    for index, bag_ns, message in bag.messages(topic):
        try:
            points = cloud_points(message)
        except ValueError as error:
            bag.fail(f"topic {topic!r}: message {index}: {error}")
        stamps.append(message_stamp(bag, topic, index, bag_ns, message.header, time_source))
        indices.append(index)
        rows.append(flatten_cloud(points, num_beams, z_band[0], z_band[1]))
        if cloud_detector is not None:
            detections.append(cloud_detector(points))
        elif cylinder:
            pending.append(points)
            pending_index.append(index)
            if len(pending) == _CLOUD_CHUNK:
                flush()
    if pending:
        flush()
    has = cloud_detector is not None or cylinder
    return SensorTrack(np.asarray(stamps, np.int64), np.asarray(indices, np.int64),
                       np.stack(rows), cloud_scan_angles(num_beams),
                       detections if has else None)
