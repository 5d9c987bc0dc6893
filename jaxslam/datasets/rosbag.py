"""ROS bags -> ``RobotLog``: lidar scans or point clouds plus wheel odometry, one step per scan.

Reads ROS 1 ``.bag`` files and ROS 2 bag folders (``metadata.yaml`` with ``.db3`` or ``.mcap``
storage) with the pure-Python ``rosbags`` package (the optional extra ``jaxslam[ros]``). What
becomes what (``docs/rosbag.md``):

  sensor_msgs/LaserScan      ranges (B,) on bearings angle_min + i angle_increment; NaN, values
                             outside [range_min, range_max] and non-positive ones are no return
                             (+inf); trunks by ``jaxslam.detect.detect_trunks`` on every scan.
  sensor_msgs/PointCloud2    points (N, 3) (float32/float64 x, y, z fields, any point_step and
                             row_step, either byte order, NaN points skipped); trunks by
                             ``cloud_detection``: "cylinder" (default) fits cylinders to the
                             whole cloud (``jaxslam.detect3d.fit_trunks_3d``: ground, height
                             band, clusters, RANSAC cylinders, position at breast height);
                             "slice" flattens a height band into a 2D scan of ``cloud_beams``
                             azimuth bins (nearest return per bin, the planar counterpart of
                             ``jaxslam.detect.clip_points_by_height``) detected like a
                             LaserScan; or a ``cloud_detector`` callable. The flattened scan
                             is stored as ``scan_ranges`` either way.
  nav_msgs/Odometry          planar poses (x, y, yaw from the quaternion) linearly interpolated
  (or PoseStamped, Pose-     onto the scan stamps; the moves between consecutive scan poses are
  WithCovarianceStamped,     the log's odometry controls (rot1, trans, rot2). With
  tf2_msgs/TFMessage)        ``odom_source="twist"``, the Odometry twist (v, omega) is integrated
                             instead (``log_format.integrate_controls``, velocity model).
  a truth pose topic         ``truth_pose`` at the scan stamps (same message types).

Shapes: T scans kept (the filter steps), B beams, K = ``max_obs`` padded detections, N points.
Times are seconds on the bag's clock (header stamps by default); poses are (x, y, theta) in
metres and radians; the tracked pose is the sensor's (``sensor_pose`` places it on the base).

Nothing heavy is imported at module level: ``rosbags`` and JAX are imported when a bag is read.
"""
from __future__ import annotations

from pathlib import Path
from typing import Callable, NamedTuple

import numpy as np

from jaxslam.datasets.log_format import (
    LogFormatError,
    RobotLog,
    integrate_controls,
    interpolate_poses,
    odometry_between,
    odometry_path,
    validate_log,
    wrap_angle_np,
)

SCAN_TYPE = "sensor_msgs/msg/LaserScan"
CLOUD_TYPE = "sensor_msgs/msg/PointCloud2"
ODOMETRY_TYPE = "nav_msgs/msg/Odometry"
POSE_STAMPED_TYPE = "geometry_msgs/msg/PoseStamped"
POSE_COVARIANCE_TYPE = "geometry_msgs/msg/PoseWithCovarianceStamped"
TF_TYPE = "tf2_msgs/msg/TFMessage"
POSE_TYPES = (ODOMETRY_TYPE, POSE_STAMPED_TYPE, POSE_COVARIANCE_TYPE, TF_TYPE)
ROS2_STORAGE_SUFFIXES = (".db3", ".mcap")
INSTALL_HINT = 'pip install "jaxslam[ros]"'
_EXPECTED_PATH = ("expected a ROS 1 .bag file or a ROS 2 bag folder holding metadata.yaml "
                  "and its .db3 or .mcap files")
# PointField datatypes (sensor_msgs/PointField): the float ones x, y and z may use.
_POINT_FIELD_FLOATS = {7: "f4", 8: "f8"}
_POINT_FIELD_NAMES = {1: "INT8", 2: "UINT8", 3: "INT16", 4: "UINT16", 5: "INT32", 6: "UINT32",
                      7: "FLOAT32", 8: "FLOAT64"}
_DETECT_CHUNK = 128  # scans per batched detection call (padded): one compile per beam count
_CLOUD_CHUNK = 8  # clouds per batched cylinder-detection call (padded with empty clouds)
_MIN_CLOUD_SLOTS = 1024  # clouds are padded to a power of two points, at least this many
CLOUD_DETECTIONS = ("cylinder", "slice")


class RosbagError(LogFormatError):
    """A ROS bag that cannot become a ``RobotLog``; the message names the bag, what is wrong
    and what is expected (a ``LogFormatError``, so a ``ValueError``: the CLI prints one line)."""


# ----------------------------------------------------------------------------------------------
# Paths and the reader


def is_rosbag_path(path) -> bool:
    """True when ``path`` should be read as a ROS bag, not a jaxslam ``.npz`` log: a ``.bag``,
    ``.db3`` or ``.mcap`` name (existing or not), or a folder holding ``metadata.yaml``."""
    path = Path(path)
    return (path.suffix.lower() in (".bag",) + ROS2_STORAGE_SUFFIXES
            or (path.is_dir() and (path / "metadata.yaml").is_file()))


def resolve_bag_path(path) -> Path:
    """The path to open: a ``.bag`` file, or a ROS 2 bag folder (for a ``.db3``/``.mcap`` file,
    its folder when that holds ``metadata.yaml``).

    Raises:
      RosbagError: the path is missing, a folder without ``metadata.yaml``, a storage file
        without ``metadata.yaml`` beside it, or any other kind of file.
    """
    path = Path(path)
    if not path.exists():
        raise RosbagError(f"{path}: no such file or folder; {_EXPECTED_PATH}")
    if path.is_dir():
        if (path / "metadata.yaml").is_file():
            return path
        inside = sorted(p.name for p in path.iterdir() if p.suffix.lower() == ".bag")
        hint = (f"; it holds ROS 1 bag file(s) {inside[:5]}: pass one of them" if inside else
                "; a ROS 2 bag folder lacking it can be repaired with `ros2 bag reindex`")
        raise RosbagError(f"{path}: a folder without metadata.yaml, so not a ROS 2 bag"
                          f"{hint}; {_EXPECTED_PATH}")
    suffix = path.suffix.lower()
    if suffix == ".bag":
        return path
    if suffix in ROS2_STORAGE_SUFFIXES:
        if (path.parent / "metadata.yaml").is_file():
            return path.parent
        raise RosbagError(f"{path}: a ROS 2 {suffix} storage file without metadata.yaml beside "
                          "it (`ros2 bag reindex FOLDER` recreates it); " + _EXPECTED_PATH)
    raise RosbagError(f"{path}: neither a ROS 1 .bag file nor a ROS 2 bag folder with "
                      f"metadata.yaml (a jaxslam .npz log loads with load_log); {_EXPECTED_PATH}")


def _import_rosbags():
    """``(AnyReader, get_typestore, Stores)``; RosbagError naming the extra when rosbags is
    not installed."""
    try:
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore
    except ImportError as error:
        raise RosbagError(f"reading ROS bags needs the rosbags package, which is not installed "
                          f"({error}); install it with: {INSTALL_HINT}") from error
    return AnyReader, get_typestore, Stores


class _Bag:
    """An open ``rosbags.highlevel.AnyReader`` with the bag's topic table."""

    def __init__(self, path: Path):
        any_reader, get_typestore, stores = _import_rosbags()
        self.path = path
        self.ros2 = path.is_dir()
        # Bags without embedded definitions (early ROS 2 distros) fall back to a standard store.
        store = get_typestore(stores.ROS2_HUMBLE if self.ros2 else stores.ROS1_NOETIC)
        try:
            self.reader = any_reader([path], default_typestore=store)
            self.reader.open()
        except Exception as error:  # noqa: BLE001 - whatever the reader meets: not a bag
            kind = "ROS 2 bag folder" if self.ros2 else "ROS 1 bag"
            raise RosbagError(f"{path}: cannot read as a {kind} ({type(error).__name__}: "
                              f"{error}); {_EXPECTED_PATH}") from error
        self.topics = {name: (info.msgtype, int(info.msgcount))
                       for name, info in self.reader.topics.items()}

    def close(self) -> None:
        self.reader.close()

    def describe(self) -> str:
        """``'/scan' (sensor_msgs/msg/LaserScan, 50 messages), ...`` of every topic."""
        if not self.topics:
            return "the bag has no topics"
        return "the bag's topics: " + ", ".join(
            f"{name!r} ({msgtype}, {count} messages)"
            for name, (msgtype, count) in sorted(self.topics.items()))

    def fail(self, message: str):
        raise RosbagError(f"{self.path}: {message}")

    def messages(self, topic: str):
        """(index in the topic, bag time [ns], message) of every message of ``topic``.

        A record that cannot be read (a truncated or corrupt bag) or decoded is a RosbagError
        naming the topic and the message index.
        """
        connections = [c for c in self.reader.connections if c.topic == topic]
        stream = self.reader.messages(connections=connections)
        index = 0
        while True:
            try:
                connection, bag_ns, raw = next(stream)
            except StopIteration:
                return
            except Exception as error:  # noqa: BLE001 - any reader failure: a damaged bag
                self.fail(f"topic {topic!r}: cannot read message {index} "
                          f"({type(error).__name__}: {error}); the bag is truncated or corrupt "
                          "(`rosbag reindex` or `ros2 bag reindex` may repair it)")
            try:
                message = self.reader.deserialize(raw, connection.msgtype)
            except Exception as error:  # noqa: BLE001 - a record that is not its type
                self.fail(f"topic {topic!r}: message {index} cannot be decoded as "
                          f"{connection.msgtype} ({type(error).__name__}: {error})")
            yield index, bag_ns, message
            index += 1


def _pick_topic(bag: _Bag, given: str | None, types: tuple[str, ...], role: str,
                option: str, default: bool = True) -> str | None:
    """The topic for ``role``: ``given`` after checking it exists and has one of ``types``;
    else, when ``default``, the only topic of ``types[0]`` (None when there is none)."""
    if given is not None:
        if given not in bag.topics:
            bag.fail(f"no topic {given!r} ({option}); {bag.describe()}")
        msgtype = bag.topics[given][0]
        if msgtype not in types:
            bag.fail(f"topic {given!r} ({option}) has type {msgtype}, which is not supported "
                     f"for {role}; expected {' or '.join(types)}")
        if bag.topics[given][1] == 0:
            bag.fail(f"topic {given!r} ({option}) has no messages; {bag.describe()}")
        return given
    if not default:
        return None
    found = sorted(name for name, (msgtype, count) in bag.topics.items()
                   if msgtype == types[0] and count)
    if len(found) > 1:
        bag.fail(f"{len(found)} {types[0]} topics {found}: choose {role} topic with "
                 f"{option}")
    return found[0] if found else None


# ----------------------------------------------------------------------------------------------
# Stamps


def _stamp_ns(stamp) -> int:
    """A builtin_interfaces/Time (sec, nanosec) as integer nanoseconds."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def format_stamp(ns: int) -> str:
    """Integer nanoseconds as exact seconds text, e.g. ``1700000000.250000000``."""
    sign, ns = ("-", -ns) if ns < 0 else ("", ns)
    return f"{sign}{ns // 1_000_000_000}.{ns % 1_000_000_000:09d}"


def _message_stamp(bag: _Bag, topic: str, index: int, bag_ns: int, header,
                   time_source: str) -> int:
    """The message's time [ns]: its header stamp, or the bag's record time."""
    if time_source == "bag":
        return int(bag_ns)
    stamp = _stamp_ns(header.stamp)
    if stamp == 0:
        bag.fail(f"topic {topic!r}: message {index} has a zero header stamp (the publisher "
                 "did not set it); pass time_source='bag' (CLI: --time-source bag) to use the "
                 "times the recorder received the messages")
    return stamp


def check_stamps(source: str, topic: str, stamps_ns, indices, max_gap: float | None) -> None:
    """Raise RosbagError unless ``stamps_ns`` (M,) increase strictly with gaps <= ``max_gap``.

    Args:
      source: the bag, for the message.  topic: its name.
      stamps_ns: (M,) integer nanoseconds in recording order.
      indices: (M,) the messages' indices in the topic (named in the message).
      max_gap: largest allowed step [s]; None: no limit.
    """
    stamps = np.asarray(stamps_ns, np.int64)
    if stamps.size < 2:
        return
    steps = np.diff(stamps)
    bad = np.flatnonzero(steps <= 0)
    if bad.size:
        i = int(bad[0])
        raise RosbagError(
            f"{source}: topic {topic!r}: message {int(indices[i + 1])} has stamp "
            f"{format_stamp(int(stamps[i + 1]))} s, not after message {int(indices[i])}'s "
            f"{format_stamp(int(stamps[i]))} s; expected strictly increasing stamps (a clock "
            "that jumped back, or messages recorded out of order)")
    if max_gap is not None:
        jumps = np.flatnonzero(steps > max_gap * 1e9)
        if jumps.size:
            i = int(jumps[0])
            raise RosbagError(
                f"{source}: topic {topic!r}: the stamp jumps forward by {steps[i] / 1e9:.3f} s "
                f"from message {int(indices[i])} ({format_stamp(int(stamps[i]))} s) to message "
                f"{int(indices[i + 1])} ({format_stamp(int(stamps[i + 1]))} s); expected gaps "
                f"of at most max_gap={max_gap:g} s (a clock jump, or a pause in the "
                "recording; raise max_gap, or None, to accept it)")


# ----------------------------------------------------------------------------------------------
# Poses


def quaternion_yaw(x, y, z, w):
    """Yaw [rad] (rotation about +z) of quaternions (x, y, z, w), each (...,):
    atan2(2 (w z + x y), 1 - 2 (y^2 + z^2)). Roll and pitch are dropped (planar robot)."""
    return np.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def compose_poses(poses, offset):
    """poses (..., 3) (+) offset (..., 3), broadcast: the pose of a frame placed at ``offset``
    in the frame of ``poses`` (e.g. the lidar on the base, ``sensor_pose``)."""
    poses, offset = np.asarray(poses, np.float64), np.asarray(offset, np.float64)
    cos_t, sin_t = np.cos(poses[..., 2]), np.sin(poses[..., 2])
    return np.stack([poses[..., 0] + cos_t * offset[..., 0] - sin_t * offset[..., 1],
                     poses[..., 1] + sin_t * offset[..., 0] + cos_t * offset[..., 1],
                     wrap_angle_np(poses[..., 2] + offset[..., 2])], axis=-1)


def _pose_of(message, msgtype: str):
    """(header, (x, y, yaw)) of an Odometry, PoseStamped or PoseWithCovarianceStamped."""
    pose = message.pose if msgtype == POSE_STAMPED_TYPE else message.pose.pose
    p, q = pose.position, pose.orientation
    return message.header, (p.x, p.y, float(quaternion_yaw(q.x, q.y, q.z, q.w)))


class PoseTrack(NamedTuple):
    """Planar poses of one topic.

    time_ns: (M,) int64 stamps [ns]; pose: (M, 3) (x, y, yaw); velocity: (M, 2) forward speed
    [m/s] and yaw rate [rad/s] (Odometry twist; zeros for other types); index: (M,) message
    indices in the topic.
    """

    time_ns: np.ndarray
    pose: np.ndarray
    velocity: np.ndarray
    index: np.ndarray


def _strip(frame: str) -> str:
    return frame.lstrip("/")


def read_pose_track(bag: _Bag, topic: str, time_source: str, tf_frames=None) -> PoseTrack:
    """The planar poses of ``topic`` (Odometry, PoseStamped, PoseWithCovarianceStamped, or a
    TFMessage topic's transforms from ``tf_frames[0]`` to ``tf_frames[1]``)."""
    msgtype = bag.topics[topic][0]
    stamps, poses, velocity, indices = [], [], [], []
    seen = set()
    for index, bag_ns, message in bag.messages(topic):
        if msgtype == TF_TYPE:
            for transform in message.transforms:
                pair = (_strip(transform.header.frame_id), _strip(transform.child_frame_id))
                seen.add(pair)
                if pair != tuple(_strip(f) for f in tf_frames):
                    continue
                t, q = transform.transform.translation, transform.transform.rotation
                stamps.append(_message_stamp(bag, topic, index, bag_ns, transform.header,
                                             time_source))
                poses.append((t.x, t.y, float(quaternion_yaw(q.x, q.y, q.z, q.w))))
                velocity.append((0.0, 0.0))
                indices.append(index)
            continue
        header, pose = _pose_of(message, msgtype)
        stamps.append(_message_stamp(bag, topic, index, bag_ns, header, time_source))
        poses.append(pose)
        twist = message.twist.twist if msgtype == ODOMETRY_TYPE else None
        velocity.append((0.0, 0.0) if twist is None else (twist.linear.x, twist.angular.z))
        indices.append(index)
    if msgtype == TF_TYPE and not stamps:
        bag.fail(f"topic {topic!r}: no transform from {tf_frames[0]!r} to {tf_frames[1]!r}; "
                 f"its transforms (parent, child): {sorted(seen)[:12]}; pass tf_frames="
                 "(parent, child) naming one of them")
    return PoseTrack(np.asarray(stamps, np.int64), np.asarray(poses, np.float64).reshape(-1, 3),
                     np.asarray(velocity, np.float64).reshape(-1, 2),
                     np.asarray(indices, np.int64))


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
    off_centre = np.abs(wrap_angle_np(azimuth - cloud_scan_angles(num_beams)[bins]))
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


def _pad_detections(detections: list, max_obs: int | None):
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


def _detector_keywords(detector: dict | None, cloud: bool, cloud_detection: str) -> dict:
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


def _read_scans(bag: _Bag, topic: str, time_source: str) -> SensorTrack:
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
        stamps.append(_message_stamp(bag, topic, index, bag_ns, message.header, time_source))
        indices.append(index)
        rows.append(ranges)
    return SensorTrack(np.asarray(stamps, np.int64), np.asarray(indices, np.int64),
                       np.stack(rows), first_angles, None)


def _read_clouds(bag: _Bag, topic: str, time_source: str, num_beams: int, z_band,
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
        stamps.append(_message_stamp(bag, topic, index, bag_ns, message.header, time_source))
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


# ----------------------------------------------------------------------------------------------
# The loader


def _scan_window(bag: _Bag, scan_ns, spans: dict, progress) -> np.ndarray:
    """Mask (S,) of scans inside every (start, end) [ns] of ``spans`` {what: span}."""
    keep = np.ones(scan_ns.shape, bool)
    for start, end in spans.values():
        keep &= (scan_ns >= start) & (scan_ns <= end)
    if not keep.any():
        covered = "; ".join(f"{what} {format_stamp(int(a))}..{format_stamp(int(b))} s"
                            for what, (a, b) in spans.items())
        bag.fail(f"no scan lies within the other topics' time spans: scans "
                 f"{format_stamp(int(scan_ns[0]))}..{format_stamp(int(scan_ns[-1]))} s; "
                 f"{covered}; expected overlapping stamps on one clock (mixing header "
                 "stamps and bag times? try time_source='bag')")
    if progress is not None and not keep.all():
        progress(f"dropped {int((~keep).sum())} of {keep.size} scans outside the time span of "
                 + " and ".join(spans))
    return keep


def _sensor_poses(bag: _Bag, odom: PoseTrack, odom_topic: str, scan_s, odom_source: str,
                  sensor_pose) -> np.ndarray:
    """(T, 3) sensor poses at the scan times [s] in the odometry frame."""
    odom_s = odom.time_ns / 1e9
    if odom_source == "pose":
        base = interpolate_poses(scan_s, odom_s, odom.pose)
    elif odom_source == "twist":
        if bag.topics[odom_topic][0] != ODOMETRY_TYPE:
            bag.fail(f"odom_source='twist' needs a {ODOMETRY_TYPE} topic; {odom_topic!r} is "
                     f"{bag.topics[odom_topic][0]}")
        # Moves between scans from the held (v, omega) samples; row 0 (into the first scan)
        # is replaced by the interpolated odometry pose there, the anchor of the path.
        moves = integrate_controls(odom_s, odom.velocity, scan_s, "velocity",
                                   min_translation=0.0)
        moves[0] = 0.0
        start = interpolate_poses(scan_s[:1], odom_s, odom.pose)[0]
        base = compose_poses(start, odometry_path(moves))
    else:
        raise ValueError(f"odom_source={odom_source!r}; expected 'pose' or 'twist'")
    return compose_poses(base, np.asarray(sensor_pose, np.float64))


def _controls(poses, min_translation: float) -> np.ndarray:
    """(T, 3) odometry moves: row 0 zero (the log starts at poses[0]), row t poses[t-1]->t."""
    moves = np.zeros((len(poses), 3))
    if len(poses) > 1:
        moves[1:] = odometry_between(poses[:-1], poses[1:], min_translation)
    return moves


def _observations(track: SensorTrack, keep, max_obs: int, detector: dict | None):
    """(z, valid, radius) of the kept scans: the cloud_detector's, else detect_trunks'."""
    if track.detections is not None:
        return _pad_detections([d for d, k in zip(track.detections, keep) if k], max_obs)
    return detect_trunks_batched(track.ranges[keep], track.angles, max_obs,
                                 **_detector_keywords(detector, False, "slice"))


def _check_options(time_source, odom_source, sensor_pose, cloud_beams, cloud_z_band, max_obs,
                   cloud_detection="cylinder"):
    if cloud_detection not in CLOUD_DETECTIONS:
        raise ValueError(f"cloud_detection={cloud_detection!r}; expected 'cylinder' (3D "
                         "cylinder fits, jaxslam.detect3d) or 'slice' (a flattened height band "
                         "and 2D circle fits)")
    if time_source not in ("header", "bag"):
        raise ValueError(f"time_source={time_source!r}; expected 'header' (message stamps) or "
                         "'bag' (the times the recorder received the messages)")
    if odom_source not in ("pose", "twist"):
        raise ValueError(f"odom_source={odom_source!r}; expected 'pose' or 'twist'")
    if np.asarray(sensor_pose).shape != (3,):
        raise ValueError(f"sensor_pose={sensor_pose!r}; expected (x [m], y [m], yaw [rad]) "
                         "of the sensor on the robot base")
    if int(cloud_beams) < 8:
        raise ValueError(f"cloud_beams={cloud_beams!r}; expected an integer >= 8")
    if len(cloud_z_band) != 2 or not cloud_z_band[0] < cloud_z_band[1]:
        raise ValueError(f"cloud_z_band={cloud_z_band!r}; expected (z_min, z_max) [m] with "
                         "z_min < z_max")
    if int(max_obs) < 1:
        raise ValueError(f"max_obs={max_obs!r}; expected an integer >= 1")


def load_rosbag(path, scan_topic: str | None = None, cloud_topic: str | None = None,
                odom_topic: str | None = None, truth_topic: str | None = None, *,
                max_obs: int = 16, detector: dict | None = None,
                cloud_detector: Callable | None = None, cloud_detection: str = "cylinder",
                cloud_beams: int = 720,
                cloud_z_band: tuple[float, float] = (-0.5, 0.5),
                sensor_pose=(0.0, 0.0, 0.0), odom_source: str = "pose",
                tf_frames: tuple[str, str] = ("odom", "base_link"),
                truth_tf_frames: tuple[str, str] = ("map", "base_link"),
                time_source: str = "header", max_gap: float | None = 10.0,
                min_translation: float = 0.01, keep_scans: bool = True,
                progress: Callable[[str], None] | None = None) -> RobotLog:
    """A ROS 1 or ROS 2 bag as a validated ``RobotLog`` with one filter step per scan.

    Args:
      path: a ROS 1 ``.bag`` file, a ROS 2 bag folder (``metadata.yaml``), or a ``.db3`` /
        ``.mcap`` file inside one.
      scan_topic / cloud_topic: the lidar topic, LaserScan or PointCloud2 (give at most one).
        Default: the only LaserScan topic, else the only PointCloud2 topic.
      odom_topic: Odometry (default: the only one), PoseStamped, PoseWithCovarianceStamped or
        TFMessage (transforms ``tf_frames`` = (parent, child)).
      truth_topic: optional ground truth of the same types (TF: ``truth_tf_frames``); none by
        default. The log then starts at the true pose, so estimate and truth share a frame.
      max_obs: K, detected trunks kept per scan (the nearest).
      detector: keywords overriding the defaults of the detector in use:
        ``jaxslam.detect.detect_trunks`` (method, max_range, min_points, ...) for LaserScans
        and ``cloud_detection="slice"``, ``jaxslam.detect3d.fit_trunks_3d`` (max_range,
        band_min, max_lean, ...) for ``cloud_detection="cylinder"``.
      cloud_detector: callable(points (N, 3) float64 [m], cloud frame) -> an object with
        ``z`` (K, 2) (range, bearing), ``valid`` (K,) and optionally ``radius`` (K,), such as
        an ``Observations``: replaces ``cloud_detection`` for PointCloud2 topics. K may vary;
        rows are padded to ``max_obs``.
      cloud_detection: how PointCloud2 trunks are found: "cylinder" (default: 3D cylinder
        fits per cloud, ``jaxslam.detect3d``; right for leaning trunks and sloped ground, it
        needs a cloud frame with z up and the ground in view) or "slice" (``flatten_cloud``
        of ``cloud_z_band``, then ``detect_trunks``: cheaper, and for sparse clouds of a few
        layers, where a trunk gets too few points for a cylinder).
      cloud_beams / cloud_z_band: azimuth bins and (z_min, z_max) [m] band (cloud frame) of
        ``flatten_cloud``.
      sensor_pose: (x [m], y [m], yaw [rad]) of the lidar on the robot base (the odometry's
        child frame); the log tracks the lidar's pose.
      odom_source: "pose" (interpolate the odometry poses) or "twist" (integrate the Odometry
        twist's forward speed and yaw rate).
      time_source: "header" (message stamps) or "bag" (the recorder's receive times).
      max_gap: largest step [s] between consecutive stamps of a topic before it counts as a
        clock jump (None: no limit).
      min_translation: [m] moves shorter than this are written as pure turns
        (``log_format.odometry_between``).
      keep_scans: store the ranges as ``scan_ranges`` / ``scan_angles`` too.
      progress: optional callable(str) told which topics are used.
    Returns:
      ``RobotLog`` (motion_model "odometry"): time (T,) scan stamps [s] within the odometry's
      (and truth's) time span, controls (T, 3) with row 0 zero, obs_z (T, K, 2), obs_valid,
      obs_radius, initial_pose (the odometry, or true, sensor pose at time[0]), truth_pose.
    Raises:
      RosbagError (a ``LogFormatError``): rosbags not installed, a path that is not a bag, a
        missing or ambiguous topic, an unsupported message type, no odometry, a zero, out of
        order or jumping stamp, scans outside the odometry's time span, a bad PointCloud2.
      ValueError: an option out of range.
    """
    _check_options(time_source, odom_source, sensor_pose, cloud_beams, cloud_z_band, max_obs,
                   cloud_detection)
    bag = _Bag(resolve_bag_path(path))
    try:
        return _load(bag, scan_topic, cloud_topic, odom_topic, truth_topic, max_obs=max_obs,
                     detector=detector, cloud_detector=cloud_detector,
                     cloud_detection=cloud_detection, cloud_beams=cloud_beams,
                     cloud_z_band=cloud_z_band, sensor_pose=sensor_pose,
                     odom_source=odom_source, tf_frames=tf_frames,
                     truth_tf_frames=truth_tf_frames, time_source=time_source,
                     max_gap=max_gap, min_translation=min_translation, keep_scans=keep_scans,
                     progress=progress)
    finally:
        bag.close()


def _sensor_topic(bag: _Bag, scan_topic, cloud_topic) -> tuple[str, str]:
    """(topic, "scan" or "cloud") of the lidar."""
    if scan_topic is not None and cloud_topic is not None:
        bag.fail(f"both a scan topic ({scan_topic!r}) and a cloud topic ({cloud_topic!r}) "
                 "were given; expected one lidar topic")
    if cloud_topic is not None:
        return _pick_topic(bag, cloud_topic, (CLOUD_TYPE,), "the point cloud",
                           "cloud_topic / --cloud-topic"), "cloud"
    scan = _pick_topic(bag, scan_topic, (SCAN_TYPE,), "the laser scan",
                       "scan_topic / --scan-topic")
    if scan is not None:
        return scan, "scan"
    cloud = _pick_topic(bag, None, (CLOUD_TYPE,), "the point cloud",
                        "cloud_topic / --cloud-topic")
    if cloud is None:
        bag.fail(f"no lidar topic: expected a {SCAN_TYPE} or {CLOUD_TYPE} topic with "
                 f"messages; {bag.describe()}")
    return cloud, "cloud"


def _odometry_topic(bag: _Bag, odom_topic) -> str:
    topic = _pick_topic(bag, odom_topic, POSE_TYPES, "odometry", "odom_topic / --odom-topic")
    if topic is None:
        bag.fail(f"no odometry: expected a {ODOMETRY_TYPE} topic with messages, or pass "
                 f"odom_topic (--odom-topic) naming a PoseStamped, PoseWithCovarianceStamped "
                 f"or TFMessage topic; {bag.describe()}")
    return topic


def _load(bag: _Bag, scan_topic, cloud_topic, odom_topic, truth_topic, *, max_obs, detector,
          cloud_detector, cloud_detection, cloud_beams, cloud_z_band, sensor_pose, odom_source,
          tf_frames, truth_tf_frames, time_source, max_gap, min_translation, keep_scans,
          progress) -> RobotLog:
    """``load_rosbag`` on an open bag."""
    source = str(bag.path)
    sensor, kind = _sensor_topic(bag, scan_topic, cloud_topic)
    odometry = _odometry_topic(bag, odom_topic)
    truth = (None if truth_topic is None else
             _pick_topic(bag, truth_topic, POSE_TYPES, "ground truth",
                         "truth_topic / --truth-topic"))
    if progress is not None:
        used = [(f"{kind}s", sensor), ("odometry", odometry)] + (
            [("truth", truth)] if truth else [])
        progress("reading " + ", ".join(f"{what} {name!r} ({bag.topics[name][0]}, "
                                        f"{bag.topics[name][1]} messages)"
                                        for what, name in used))
    settings = _detector_keywords(detector, kind == "cloud", cloud_detection)
    track = (_read_scans(bag, sensor, time_source) if kind == "scan" else
             _read_clouds(bag, sensor, time_source, int(cloud_beams), cloud_z_band,
                          cloud_detector, cloud_detection, int(max_obs), settings))
    check_stamps(source, sensor, track.time_ns, track.index, max_gap)
    odom = read_pose_track(bag, odometry, time_source, tf_frames)
    check_stamps(source, odometry, odom.time_ns, odom.index, max_gap)
    if len(odom.time_ns) < 2:
        bag.fail(f"topic {odometry!r} has {len(odom.time_ns)} odometry pose(s); expected at "
                 "least 2 to interpolate between")
    spans = {f"odometry {odometry!r}": (odom.time_ns[0], odom.time_ns[-1])}
    truth_track = None
    if truth is not None:
        truth_track = read_pose_track(bag, truth, time_source, truth_tf_frames)
        check_stamps(source, truth, truth_track.time_ns, truth_track.index, max_gap)
        if len(truth_track.time_ns) < 2:
            bag.fail(f"topic {truth!r} has {len(truth_track.time_ns)} pose(s); expected at "
                     "least 2 to interpolate between")
        spans[f"truth {truth!r}"] = (truth_track.time_ns[0], truth_track.time_ns[-1])
    keep = _scan_window(bag, track.time_ns, spans, progress)
    scan_ns = track.time_ns[keep]
    scan_s = scan_ns / 1e9
    poses = _sensor_poses(bag, odom, odometry, scan_s, odom_source, sensor_pose)
    offset = np.asarray(sensor_pose, np.float64)
    truth_pose = (None if truth_track is None else compose_poses(
        interpolate_poses(scan_s, truth_track.time_ns / 1e9, truth_track.pose), offset))
    z, valid, radius = _observations(track, keep, int(max_obs), detector)
    log = RobotLog(
        time=scan_s, motion_model="odometry", controls=_controls(poses, min_translation),
        obs_z=z, obs_valid=valid, obs_radius=radius,
        scan_ranges=track.ranges[keep] if keep_scans else None,
        scan_angles=track.angles if keep_scans else None, truth_pose=truth_pose,
        initial_pose=poses[0] if truth_pose is None else truth_pose[0])
    return validate_log(log, source=source)


def rosbag_topics(path) -> dict[str, tuple[str, int]]:
    """{topic: (message type, message count)} of a bag (``resolve_bag_path`` rules)."""
    bag = _Bag(resolve_bag_path(path))
    try:
        return dict(bag.topics)
    finally:
        bag.close()


