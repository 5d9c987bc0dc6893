"""Reading ROS bags: paths, the opened bag and its topics, message stamps, planar pose topics.

Reads ROS 1 ``.bag`` files and ROS 2 bag folders (``metadata.yaml`` with ``.db3`` or ``.mcap``
storage) with the pure-Python ``rosbags`` package (the optional extra ``jaxslam[ros]``),
imported only when a bag is opened. ``jaxslam.datasets.rosbag.load_rosbag`` turns a bag into a
``RobotLog``; ``jaxslam.datasets.rosbag_clouds`` reads its lidar topic.

Times are integer nanoseconds on the bag's clock (header stamps, or the recorder's receive
times with ``time_source="bag"``); poses are (x, y, theta) in metres and radians.
"""
from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import numpy as np

from jaxslam.datasets.log_format import LogFormatError

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


class OpenBag:
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


def pick_topic(bag: OpenBag, given: str | None, types: tuple[str, ...], role: str,
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


def message_stamp(bag: OpenBag, topic: str, index: int, bag_ns: int, header,
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


def read_pose_track(bag: OpenBag, topic: str, time_source: str, tf_frames=None) -> PoseTrack:
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
                stamps.append(message_stamp(bag, topic, index, bag_ns, transform.header,
                                             time_source))
                poses.append((t.x, t.y, float(quaternion_yaw(q.x, q.y, q.z, q.w))))
                velocity.append((0.0, 0.0))
                indices.append(index)
            continue
        header, pose = _pose_of(message, msgtype)
        stamps.append(message_stamp(bag, topic, index, bag_ns, header, time_source))
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


def rosbag_topics(path) -> dict[str, tuple[str, int]]:
    """{topic: (message type, message count)} of a bag (``resolve_bag_path`` rules)."""
    bag = OpenBag(resolve_bag_path(path))
    try:
        return dict(bag.topics)
    finally:
        bag.close()
