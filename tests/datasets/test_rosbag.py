"""ROS bags -> RobotLog: bags written here with rosbags' own writers from a simulated scene.

The scene: six trunks (circles), a robot driving an arc at 0.8 m/s turning 0.08 rad/s; a
360-beam LaserScan at 5 Hz whose ranges are exact ray-circle intersections (NumPy, below);
wheel odometry at 50 Hz (poses in an odom frame that starts at the robot, twist v, omega);
ground truth as PoseStamped in the world frame. Tolerances: controls and truth 1e-4 (linear
interpolation of 50 Hz poses along an arc errs by ~1e-5 m), detected trunk centres 2 cm in
range and 0.01 rad in bearing from LaserScans (the Kasa fit of exact arc points is exact up to
float32), 8 cm and 0.02 rad from point clouds (flattened into 0.5-degree azimuth bins, which
err at a trunk's flanks by up to half a bin).
"""
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rosbags")  # the `test` extra installs it; `pip install "jaxslam[ros]"`

from rosbags.highlevel import AnyReader  # noqa: E402
from rosbags.rosbag1 import Writer as Writer1  # noqa: E402
from rosbags.rosbag2 import StoragePlugin, Writer as Writer2  # noqa: E402
from rosbags.typesys import Stores, get_typestore  # noqa: E402

from jaxslam import cli  # noqa: E402
from jaxslam.datasets import LogFormatError, RobotLog, load_log, odometry_between  # noqa: E402
from jaxslam.datasets import rosbag_clouds, rosbag_reader  # noqa: E402
from jaxslam.host import in_float64  # noqa: E402
from jaxslam.datasets.rosbag import load_rosbag  # noqa: E402
from jaxslam.datasets.rosbag_reader import RosbagError  # noqa: E402
from jaxslam.geometry import compose  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tests/: detect3d_reference
T0_NS = 1_700_000_000 * 10**9  # an epoch stamp, as a real robot's clock gives
TREES = np.array([[3.0, 2.5, 0.20], [6.0, -2.0, 0.25], [9.0, 3.5, 0.18], [4.5, 6.0, 0.30],
                  [11.0, -1.0, 0.22], [1.5, -3.0, 0.15]])  # x [m], y [m], radius [m]
BEAMS = 360
ANGLE_MIN, ANGLE_INCREMENT = -np.pi, 2 * np.pi / BEAMS
START = np.array([0.5, -0.2, 0.1])  # world pose at t = 0 (the odom frame's origin)
SPEED, YAW_RATE = 0.8, 0.08  # m/s, rad/s
SCAN_PERIOD_NS, ODOM_PERIOD_NS = 200_000_000, 20_000_000  # 5 Hz, 50 Hz


# ---------------------------------------------------------------------------- the simulation


def world_pose(t):
    """(..., 3) true base pose at t [s] after T0: an arc from START."""
    t = np.asarray(t, np.float64)
    radius = SPEED / YAW_RATE
    local = np.stack([radius * np.sin(YAW_RATE * t), radius * (1 - np.cos(YAW_RATE * t)),
                      YAW_RATE * t], -1)
    return in_float64(compose, START, local)


def relative(origin, poses):
    """poses (..., 3) in the frame of origin (3,)."""
    c, s = np.cos(origin[2]), np.sin(origin[2])
    dx, dy = poses[..., 0] - origin[0], poses[..., 1] - origin[1]
    return np.stack([c * dx + s * dy, -s * dx + c * dy,
                     np.angle(np.exp(1j * (poses[..., 2] - origin[2])))], -1)


def ray_ranges(pose, angles, trees=TREES):
    """Exact ranges (B,) from sensor pose (3,) along bearings (B,) to the nearest circle
    (+inf: none), and the index (B,) of the circle each beam hits (-1: none).

    Ray p + s d, circle |q - c| = r: s = b - sqrt(b^2 - |c - p|^2 + r^2), b = d . (c - p).
    """
    heading = pose[2] + angles
    d = np.stack([np.cos(heading), np.sin(heading)], -1)  # (B, 2)
    offset = trees[:, :2] - pose[:2]  # (N, 2)
    b = d @ offset.T  # (B, N)
    disc = b ** 2 - np.sum(offset ** 2, -1) + trees[:, 2] ** 2
    s = np.where(disc >= 0, b - np.sqrt(np.maximum(disc, 0)), np.inf)
    s = np.where(s > 0, s, np.inf)
    hit = np.argmin(s, 1)
    ranges = s[np.arange(len(s)), hit]
    return ranges, np.where(np.isfinite(ranges), hit, -1)


def expected_trunks(pose, angles, min_hits=5, max_range=18.0):
    """(range, bearing, radius, tree) of the trunks the detector should find from ``pose``:
    hit by >= min_hits beams, centre nearer than max_range, not occluded (the beams beside
    the run are not nearer than its ends by more than detect_trunks' range_jump 0.3 m)."""
    ranges, hit = ray_ranges(pose, angles)
    found = []
    for tree in range(len(TREES)):
        beams = np.flatnonzero(hit == tree)
        if len(beams) < min_hits:
            continue
        first, last = beams[0], beams[-1]
        if last - first + 1 != len(beams):  # split across the seam or by an occluder
            continue
        edges = [ranges[(first - 1) % BEAMS], ranges[(last + 1) % BEAMS]]
        if min(edges) < min(ranges[first], ranges[last]) - 0.3:
            continue
        offset = TREES[tree, :2] - pose[:2]
        distance = np.hypot(*offset)
        bearing = np.angle(np.exp(1j * (np.arctan2(offset[1], offset[0]) - pose[2])))
        if distance < max_range:
            found.append((distance, bearing, TREES[tree, 2], tree))
    return found


# ---------------------------------------------------------------------------- messages and bags


class Messages:
    """Message constructors for one typestore (ROS 1 headers carry ``seq``)."""

    def __init__(self, ros1: bool):
        self.ros1 = ros1
        self.store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
        self.t = self.store.types

    def header(self, ns, frame="base_link"):
        stamp = self.t["builtin_interfaces/msg/Time"](sec=int(ns // 10**9),
                                                       nanosec=int(ns % 10**9))
        extra = {"seq": 0} if self.ros1 else {}
        return self.t["std_msgs/msg/Header"](stamp=stamp, frame_id=frame, **extra)

    def pose(self, x, y, yaw):
        g = "geometry_msgs/msg/"
        return self.t[g + "Pose"](position=self.t[g + "Point"](x=x, y=y, z=0.0),
                                  orientation=self.quaternion(yaw))

    def quaternion(self, yaw):
        return self.t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=np.sin(yaw / 2),
                                                      w=np.cos(yaw / 2))

    def vector(self, x=0.0, y=0.0, z=0.0):
        return self.t["geometry_msgs/msg/Vector3"](x=x, y=y, z=z)

    def scan(self, ns, ranges):
        return self.t["sensor_msgs/msg/LaserScan"](
            header=self.header(ns, "laser"), angle_min=ANGLE_MIN,
            angle_max=ANGLE_MIN + ANGLE_INCREMENT * (len(ranges) - 1),
            angle_increment=ANGLE_INCREMENT, time_increment=0.0, scan_time=0.2,
            range_min=0.05, range_max=30.0,
            ranges=np.where(np.isfinite(ranges), ranges, np.nan).astype(np.float32),
            intensities=np.zeros(0, np.float32))

    def odometry(self, ns, pose, speed=SPEED, yaw_rate=YAW_RATE):
        g = "geometry_msgs/msg/"
        twist = self.t[g + "Twist"](linear=self.vector(speed), angular=self.vector(z=yaw_rate))
        return self.t["nav_msgs/msg/Odometry"](
            header=self.header(ns, "odom"), child_frame_id="base_link",
            pose=self.t[g + "PoseWithCovariance"](pose=self.pose(*pose),
                                                  covariance=np.zeros(36)),
            twist=self.t[g + "TwistWithCovariance"](twist=twist, covariance=np.zeros(36)))

    def pose_stamped(self, ns, pose):
        return self.t["geometry_msgs/msg/PoseStamped"](header=self.header(ns, "map"),
                                                       pose=self.pose(*pose))

    def tf(self, ns, pairs):
        """A TFMessage of (parent, child, pose) transforms."""
        g = "geometry_msgs/msg/"
        return self.t["tf2_msgs/msg/TFMessage"](transforms=[
            self.t[g + "TransformStamped"](
                header=self.header(ns, parent), child_frame_id=child,
                transform=self.t[g + "Transform"](translation=self.vector(x, y),
                                                  rotation=self.quaternion(yaw)))
            for parent, child, (x, y, yaw) in pairs])

    def cloud(self, ns, points, big_endian=False, float64=False, extra_bytes=4, rows=1,
              row_padding=0):
        """A PointCloud2 of points (N, 3) with an intensity field and padding bytes."""
        size = 8 if float64 else 4
        dtype = np.dtype((">" if big_endian else "<") + ("f8" if float64 else "f4"))
        point_step = 4 * size + extra_bytes
        width = len(points) // rows
        record = np.zeros((rows, width * point_step + row_padding), np.uint8)
        for r in range(rows):
            for i, point in enumerate(points[r * width:(r + 1) * width]):
                values = np.array(list(point) + [7.0], dtype).tobytes()
                record[r, i * point_step:i * point_step + 4 * size] = np.frombuffer(values,
                                                                                 np.uint8)
        field = self.t["sensor_msgs/msg/PointField"]
        datatype = 8 if float64 else 7
        fields = [field(name=n, offset=i * size, datatype=datatype, count=1)
                  for i, n in enumerate(["x", "y", "z", "intensity"])]
        return self.t["sensor_msgs/msg/PointCloud2"](
            header=self.header(ns, "lidar"), height=rows, width=width, fields=fields,
            is_bigendian=big_endian, point_step=point_step,
            row_step=width * point_step + row_padding, data=record.reshape(-1),
            is_dense=False)


def write_bag(path, kind, topics):
    """Write ``topics`` {name: (msgtype, [(stamp_ns, message), ...])} as a bag: kind "ros1"
    (a .bag file), "ros2" (sqlite3 folder) or "mcap" (MCAP folder). Each message is recorded
    1 ms after its stamp unless the stamp list says otherwise."""
    store = get_typestore(Stores.ROS1_NOETIC if kind == "ros1" else Stores.ROS2_HUMBLE)
    if kind == "ros1":
        writer = Writer1(path)
    else:
        plugin = StoragePlugin.MCAP if kind == "mcap" else StoragePlugin.SQLITE3
        writer = Writer2(path, version=9, storage_plugin=plugin)
    serialize = store.serialize_ros1 if kind == "ros1" else store.serialize_cdr
    with writer:
        records = []
        for topic, (msgtype, messages) in topics.items():
            connection = writer.add_connection(topic, msgtype, typestore=store)
            for order, (ns, message) in enumerate(messages):
                records.append((ns, topic, order, connection, message, msgtype))
        records.sort(key=lambda r: (r[0], r[1], r[2]))
        for ns, _, _, connection, message, msgtype in records:
            writer.write(connection, int(ns) + 1_000_000, serialize(message, msgtype))
    return path


def scene_topics(kind, num_scans=8, truth=True, first_scan_offset_ns=-187_000_000,
                 odometry=True, tf=False):
    """Topics of the simulated run: /scan (num_scans, the first 0.187 s before odometry
    starts), /odom (50 Hz, covering the scans), optionally /truth (PoseStamped) and /tf."""
    msgs = Messages(kind == "ros1")
    angles = ANGLE_MIN + ANGLE_INCREMENT * np.arange(BEAMS)
    scan_ns = T0_NS + first_scan_offset_ns + SCAN_PERIOD_NS * np.arange(num_scans)
    odom_ns = T0_NS + ODOM_PERIOD_NS * np.arange(int(scan_ns[-1] - T0_NS) // ODOM_PERIOD_NS + 3)
    topics = {"/scan": ("sensor_msgs/msg/LaserScan", [
        (ns, msgs.scan(ns, ray_ranges(world_pose((ns - T0_NS) / 1e9), angles)[0]))
        for ns in scan_ns])}
    odom_pose = relative(START, world_pose((odom_ns - T0_NS) / 1e9))
    if odometry:
        topics["/odom"] = ("nav_msgs/msg/Odometry", [
            (ns, msgs.odometry(ns, pose)) for ns, pose in zip(odom_ns, odom_pose)])
    if truth:
        true = world_pose((odom_ns - T0_NS) / 1e9)
        topics["/truth"] = ("geometry_msgs/msg/PoseStamped", [
            (ns, msgs.pose_stamped(ns, pose)) for ns, pose in zip(odom_ns, true)])
    if tf:
        topics["/tf"] = ("tf2_msgs/msg/TFMessage", [
            (ns, msgs.tf(ns, [("map", "odom", START), ("odom", "base_link", pose)]))
            for ns, pose in zip(odom_ns, odom_pose)])
    return topics, scan_ns


def bag_path(tmp_path, kind, name="run"):
    return tmp_path / (f"{name}.bag" if kind == "ros1" else name)


def expected_controls(times_s, offset=np.zeros(3)):
    """(T, 3) true odometry moves of the sensor at ``offset`` on the base; row 0 zero."""
    poses = in_float64(compose, world_pose(times_s - T0_NS / 1e9), offset)
    moves = np.zeros((len(poses), 3))
    moves[1:] = odometry_between(poses[:-1], poses[1:])
    return moves, poses


def assert_detections_match(log: RobotLog, range_tol, bearing_tol, min_recall=0.95):
    """Every valid detection is a trunk (centre range and bearing within the tolerances of
    the nearest true trunk, radius within 2 range_tol), and at least ``min_recall`` of the
    detectable trunks (``expected_trunks``) are found."""
    angles = ANGLE_MIN + ANGLE_INCREMENT * np.arange(BEAMS)
    detectable = found = 0
    for t, stamp in enumerate(log.time):
        pose = world_pose(stamp - T0_NS / 1e9)
        offset = TREES[:, :2] - pose[:2]
        true_range = np.hypot(offset[:, 0], offset[:, 1])
        true_bearing = np.arctan2(offset[:, 1], offset[:, 0]) - pose[2]
        expected = {tree for *_, tree in expected_trunks(pose, angles)}
        detectable += len(expected)
        for z, radius in zip(log.obs_z[t][log.obs_valid[t]],
                             log.obs_radius[t][log.obs_valid[t]]):
            range_error = np.abs(z[0] - true_range)
            bearing_error = np.abs(np.angle(np.exp(1j * (z[1] - true_bearing))))
            tree = int(np.argmin(range_error + bearing_error))
            assert range_error[tree] < range_tol and bearing_error[tree] < bearing_tol, (
                t, z, range_error[tree], bearing_error[tree])
            assert abs(radius - TREES[tree, 2]) < 2 * range_tol, (t, radius, tree)
            found += tree in expected
    assert detectable > 3 * len(log.time)
    assert found >= min_recall * detectable, (found, detectable)


# ---------------------------------------------------------------------------- LaserScan bags


@pytest.mark.parametrize("kind", ["ros1", "ros2", "mcap"])
def test_laser_scan_bag_reads_back_to_the_simulated_log(tmp_path, kind):
    topics, scan_ns = scene_topics(kind)
    path = write_bag(bag_path(tmp_path, kind), kind, topics)
    told = []
    log = load_rosbag(path, truth_topic="/truth", progress=told.append)
    assert "'/scan' (sensor_msgs/msg/LaserScan, 8 messages)" in told[0]
    assert "dropped 1 of 8 scans outside the time span of odometry '/odom' and truth " \
           "'/truth'" in told  # scan 0 precedes /odom
    np.testing.assert_array_equal(log.time, scan_ns[1:] / 1e9)
    assert log.motion_model == "odometry" and log.num_steps == 7
    moves, poses = expected_controls(log.time)
    np.testing.assert_allclose(log.controls, moves, atol=1e-4)
    np.testing.assert_allclose(log.truth_pose, poses, atol=1e-4)
    np.testing.assert_allclose(log.initial_pose, poses[0], atol=1e-4)
    assert log.scan_ranges.shape == (7, BEAMS) and np.isinf(log.scan_ranges).any()
    assert_detections_match(log, range_tol=0.02, bearing_tol=0.01)
    if kind == "ros2":  # a storage file inside the folder names the same bag
        file = next(p for p in path.iterdir() if p.suffix == ".db3")
        np.testing.assert_array_equal(load_rosbag(file, truth_topic="/truth").obs_z, log.obs_z)


def test_without_truth_the_log_starts_at_the_odometry_pose(tmp_path):
    topics, _ = scene_topics("ros2", num_scans=5, truth=False)
    path = write_bag(tmp_path / "bag", "ros2", topics)
    log = load_rosbag(path)
    assert log.truth_pose is None
    start = relative(START, world_pose(log.time[0] - T0_NS / 1e9))
    np.testing.assert_allclose(log.initial_pose, start, atol=1e-4)
    np.testing.assert_allclose(log.controls, expected_controls(log.time)[0], atol=1e-4)
    near = load_rosbag(path, detector={"max_range": 6.0}, max_obs=4, keep_scans=False)
    assert near.obs_z.shape == (4, 4, 2) and near.scan_ranges is None
    assert 0 < near.obs_valid.sum() < log.obs_valid.sum()
    assert (near.obs_z[..., 0][near.obs_valid] < 6.0).all()
    with pytest.raises(ValueError, match=r"detector has unknown keyword\(s\) \['max_rang'\]"):
        load_rosbag(path, detector={"max_rang": 6.0})


def test_tf_odometry_twist_and_sensor_offset(tmp_path):
    topics, _ = scene_topics("ros2", num_scans=6, truth=False, tf=True)
    path = write_bag(tmp_path / "bag", "ros2", topics)
    want = expected_controls(load_rosbag(path).time)[0]
    from_tf = load_rosbag(path, odom_topic="/tf", tf_frames=("odom", "base_link"))
    np.testing.assert_allclose(from_tf.controls, want, atol=1e-4)
    truth_tf = load_rosbag(path, truth_topic="/tf", truth_tf_frames=("map", "odom"))
    np.testing.assert_allclose(truth_tf.truth_pose, np.tile(START, (len(want), 1)), atol=1e-9)
    # Constant (v, omega) held between 50 Hz samples: explicit Euler, errors ~ v omega dt^2.
    from_twist = load_rosbag(path, odom_source="twist")
    np.testing.assert_allclose(from_twist.controls, want, atol=2e-3)
    offset = np.array([0.4, 0.1, 0.05])
    shifted = load_rosbag(path, sensor_pose=offset)
    np.testing.assert_allclose(shifted.controls, expected_controls(shifted.time, offset)[0],
                               atol=1e-4)
    with pytest.raises(RosbagError, match=r"no transform from 'odom' to 'base'; its "
                                          r"transforms \(parent, child\): \[\('map', 'odom'\)"):
        load_rosbag(path, odom_topic="/tf", tf_frames=("odom", "base"))


# ---------------------------------------------------------------------------- PointCloud2


def trunk_cloud(pose, heights=np.linspace(-0.9, 0.9, 7), beams=1440):
    """Points (N, 3) in the sensor frame: every trunk surface hit by ``beams`` rays at each
    height, a ground ring at z = -1.2 m, canopy at z = 2.0 m and a few NaN points. The rays
    are a quarter spacing off the 0.5-degree bin edges of flatten_cloud, so float32 rounding
    never moves a point across an edge (which would leave a bin empty and split a trunk)."""
    angles = -np.pi + 2 * np.pi * (np.arange(beams) + 0.25) / beams
    ranges, _ = ray_ranges(pose, angles)
    hit = np.isfinite(ranges)
    ring = np.stack([ranges[hit] * np.cos(angles[hit]), ranges[hit] * np.sin(angles[hit])], -1)
    layers = [np.column_stack([ring, np.full(len(ring), h)]) for h in heights]
    around = np.stack([3 * np.cos(angles[::8]), 3 * np.sin(angles[::8])], -1)
    layers += [np.column_stack([around, np.full(len(around), z)]) for z in (-1.2, 2.0)]
    layers.append(np.full((3, 3), np.nan))
    return np.concatenate(layers)


@pytest.mark.parametrize("big_endian, float64, rows, row_padding",
                         [(False, False, 1, 0), (True, True, 2, 6)])
def test_cloud_points_round_trip(tmp_path, big_endian, float64, rows, row_padding):
    points = np.array([[1.0, 2.0, 3.0], [-4.5, 0.25, 0.5], [np.nan, 1.0, 2.0],
                       [7.0, -8.0, -0.75]])
    msgs = Messages(ros1=False)
    message = msgs.cloud(T0_NS, points, big_endian, float64, rows=rows,
                         row_padding=row_padding)
    path = write_bag(tmp_path / "bag", "ros2",
                     {"/points": ("sensor_msgs/msg/PointCloud2", [(T0_NS, message)])})
    with AnyReader([path]) as reader:
        (connection, _, raw), = reader.messages()
        read = reader.deserialize(raw, connection.msgtype)
    np.testing.assert_array_equal(rosbag_clouds.cloud_points(read), points[[0, 1, 3]])
    bad = msgs.cloud(T0_NS, points)
    bad.fields[2].datatype = 2  # z as UINT8
    with pytest.raises(ValueError, match="field 'z' has datatype UINT8"):
        rosbag_clouds.cloud_points(bad)


def cloud_topics(num_scans=5):
    msgs = Messages(ros1=False)
    topics, scan_ns = scene_topics("ros2", num_scans=num_scans, truth=False,
                                   first_scan_offset_ns=13_000_000)
    del topics["/scan"]
    topics["/points"] = ("sensor_msgs/msg/PointCloud2", [
        (ns, msgs.cloud(ns, trunk_cloud(world_pose((ns - T0_NS) / 1e9))))
        for ns in scan_ns])
    return topics


def test_point_cloud_bag_is_flattened_and_detected(tmp_path):
    path = write_bag(tmp_path / "bag", "ros2", cloud_topics())
    log = load_rosbag(path, cloud_detection="slice")  # the only lidar topic is the cloud
    assert log.scan_ranges.shape == (5, 720)
    np.testing.assert_allclose(log.controls, expected_controls(log.time)[0], atol=1e-4)
    # Binning errs at a trunk's flanks: a bin the trunk only partly covers takes its one hit
    # as if at the bin centre (0.19 degrees off here), which widens the arc; on a 0.18 m
    # trunk 9 m away (4-5 bins) the fitted centre moves up to ~6 cm outward.
    assert_detections_match(log, range_tol=0.08, bearing_tol=0.02, min_recall=0.8)
    # A band that holds only the ground ring: a circle of radius 3 m, no trunk.
    ground = load_rosbag(path, cloud_z_band=(-1.3, -1.1), cloud_detection="slice")
    assert not ground.obs_valid.any()


def test_cloud_detector_hook(tmp_path):
    path = write_bag(tmp_path / "bag", "ros2", cloud_topics(num_scans=3))
    calls = []

    class Found:  # what a 3D detector returns: z (K, 2), valid (K,), radius (K,)
        def __init__(self, n):
            self.z = np.array([[5.0, 0.1], [2.0, -0.3], [9.0, 1.0]])[:n]
            self.valid = np.array([True, True, False])[:n]
            self.radius = np.array([0.2, 0.1, 0.3])[:n]

    def detector(points):
        calls.append(points)
        return Found(3 if len(calls) == 1 else 2)

    log = load_rosbag(path, cloud_detector=detector, max_obs=4)
    assert len(calls) == 3 and all(p.shape[1] == 3 and np.isfinite(p).all() for p in calls)
    assert log.obs_z.shape == (3, 4, 2)
    np.testing.assert_array_equal(log.obs_z[0, :2], [[2.0, -0.3], [5.0, 0.1]])  # nearest first
    np.testing.assert_array_equal(log.obs_valid[0], [True, True, False, False])
    np.testing.assert_array_equal(log.obs_radius[0], [0.1, 0.2, 0.0, 0.0])


# Leaning trunks for the 3D path: x, y [m] (world), radius [m], lean [deg], lean azimuth [rad].
LEANING = np.array([[4.0, 2.5, 0.20, 12.0, 0.5], [7.0, -2.0, 0.25, 15.0, 2.5],
                    [9.0, 3.5, 0.18, 8.0, -1.0], [4.5, 6.0, 0.30, 14.0, 3.0],
                    [2.0, -4.0, 0.15, 10.0, 1.5]])
SENSOR_UP = 1.0  # lidar height above the flat ground [m]


def leaning_trunks_local(pose):
    """The LEANING trunks as ``detect3d_reference.Trunk`` in the sensor frame at ``pose``."""
    import detect3d_reference as ref

    local = relative(pose, np.column_stack([LEANING[:, :2], np.zeros(len(LEANING))]))
    return [ref.Trunk(x, y, r, np.radians(lean), azimuth - pose[2], length=8.0)
            for (x, y, _), (_, _, r, lean, azimuth) in zip(local, LEANING)]


def leaning_cloud(pose):
    """A 16-layer (-15..15 degrees) x 900-beam cloud of the leaning trunks and flat ground
    1 m below the sensor, exact ray casts (``detect3d_reference``); returns only."""
    import detect3d_reference as ref

    directions = ref.ray_directions(np.radians(np.linspace(-15, 15, 16)),
                                    -np.pi + 2 * np.pi * np.arange(900) / 900)
    with np.errstate(invalid="ignore"):  # inf * 0 on the rays that miss
        points, hit = ref.ray_cast(directions, ref.Ground(-SENSOR_UP),
                                   leaning_trunks_local(pose))
    return points[hit]


def breast_errors(log, max_range=12.0):
    """Per detection: horizontal distance [m] to the nearest true breast-height point (in the
    sensor frame) and the radius error [m], over the trunks within ``max_range``."""
    import detect3d_reference as ref

    errors, radius_errors = [], []
    for t, stamp in enumerate(log.time):
        trunks = leaning_trunks_local(world_pose(stamp - T0_NS / 1e9))
        truth = np.array([tr.breast_point(ref.Ground(-SENSOR_UP))[:2] for tr in trunks])
        for (rng, bearing), radius in zip(log.obs_z[t][log.obs_valid[t]],
                                          log.obs_radius[t][log.obs_valid[t]]):
            found = rng * np.array([np.cos(bearing), np.sin(bearing)])
            dist = np.hypot(*(truth - found).T)
            k = int(np.argmin(dist))
            errors.append(dist[k])
            radius_errors.append(radius - trunks[k].radius)
    return np.array(errors), np.array(radius_errors)


def test_cloud_bag_cylinder_detection_of_leaning_trunks(tmp_path, capsys):
    """The default cloud path fits cylinders: noise-free rays give breast-height positions
    within 1 cm and radii within 5 mm (the 3D detector's own tests bound it at 1 mm on such
    clouds; 1 cm leaves room for the float32 cloud in the bag). The slice path on the same
    bag puts a 15-degree trunk's centre where the band cuts it (0.3 m below breast height:
    ~8 cm off) and widens it (an ellipse of semi-axes r, r / cos(lean))."""
    msgs = Messages(ros1=False)
    topics, scan_ns = scene_topics("ros2", num_scans=3, truth=False,
                                   first_scan_offset_ns=13_000_000)
    del topics["/scan"]
    topics["/points"] = ("sensor_msgs/msg/PointCloud2", [
        (ns, msgs.cloud(ns, leaning_cloud(world_pose((ns - T0_NS) / 1e9)))) for ns in scan_ns])
    path = write_bag(tmp_path / "bag", "ros2", topics)
    log = load_rosbag(path, detector={"max_range": 12.0})  # default: cloud_detection="cylinder"
    assert log.scan_ranges.shape == (3, 720)  # the flattened scan is still stored
    errors, radius_errors = breast_errors(log)
    assert len(errors) >= 3 * 4  # at least 4 of the 5 trunks in every cloud
    assert errors.max() < 0.01 and np.abs(radius_errors).max() < 0.005, (errors, radius_errors)
    sliced = load_rosbag(path, cloud_detection="slice")
    slice_errors, slice_radius = breast_errors(sliced)
    assert np.median(slice_errors) > 3 * np.median(errors)
    assert slice_radius.mean() > radius_errors.mean()
    # The CLI flag reaches load_rosbag.
    assert cli.main(["convert", str(path), "--out", str(tmp_path / "log"),
                     "--cloud-detection", "slice"]) == 0
    np.testing.assert_array_equal(load_log(tmp_path / "log.npz").obs_z, sliced.obs_z)
    capsys.readouterr()
    with pytest.raises(ValueError, match="fit_trunks_3d"):
        load_rosbag(path, detector={"method": "kasa"})  # a detect_trunks keyword
    with pytest.raises(ValueError, match="cloud_detection='hough'"):
        load_rosbag(path, cloud_detection="hough")


def test_flatten_cloud_keeps_the_nearest_point_per_bin_in_the_band():
    points = np.array([[2.0, 0.0, 0.0], [3.0, 0.0, 0.1], [1.0, 0.0, 0.9], [0.0, -4.0, 0.0]])
    ranges = rosbag_clouds.flatten_cloud(points, num_beams=8, z_min=-0.5, z_max=0.5)
    angles = rosbag_clouds.cloud_scan_angles(8)
    assert ranges[np.argmin(np.abs(angles - np.pi / 8))] == 2.0  # bin [0, pi/4)
    assert ranges[np.argmin(np.abs(angles + 3 * np.pi / 8))] == 4.0  # bin [-pi/2, -pi/4)
    assert np.isinf(ranges).sum() == 6


# ---------------------------------------------------------------------------- errors


@pytest.fixture
def small_bag(tmp_path):
    topics, _ = scene_topics("ros1", num_scans=3, truth=False)
    return write_bag(tmp_path / "small.bag", "ros1", topics)


def test_missing_topic_lists_the_bags_topics(small_bag):
    with pytest.raises(RosbagError, match=r"no topic '/lidar' \(scan_topic / --scan-topic\); "
                                          r"the bag's topics: '/odom' \(nav_msgs/msg/Odometry, "
                                          r"\d+ messages\), '/scan' \(sensor_msgs/msg/LaserScan, "
                                          r"3 messages\)"):
        load_rosbag(small_bag, scan_topic="/lidar")
    with pytest.raises(LogFormatError, match="no topic '/gps'"):
        load_rosbag(small_bag, truth_topic="/gps")


def test_unsupported_message_types(small_bag):
    with pytest.raises(RosbagError, match=r"topic '/odom' \(scan_topic / --scan-topic\) has "
                                          r"type nav_msgs/msg/Odometry, which is not supported "
                                          r"for the laser scan; expected "
                                          r"sensor_msgs/msg/LaserScan"):
        load_rosbag(small_bag, scan_topic="/odom")
    with pytest.raises(RosbagError, match=r"topic '/scan' \(odom_topic / --odom-topic\) has "
                                          r"type sensor_msgs/msg/LaserScan.*expected "
                                          r"nav_msgs/msg/Odometry or "
                                          r"geometry_msgs/msg/PoseStamped"):
        load_rosbag(small_bag, odom_topic="/scan")
    with pytest.raises(RosbagError, match="expected sensor_msgs/msg/PointCloud2"):
        load_rosbag(small_bag, cloud_topic="/scan")


def test_no_odometry_no_lidar_and_ambiguous_topics(tmp_path):
    topics, _ = scene_topics("ros2", num_scans=3, truth=False, odometry=False)
    path = write_bag(tmp_path / "no_odom", "ros2", topics)
    with pytest.raises(RosbagError, match=r"no odometry: expected a nav_msgs/msg/Odometry topic "
                                          r"with messages, or pass odom_topic.*the bag's "
                                          r"topics: '/scan'"):
        load_rosbag(path)
    topics, _ = scene_topics("ros2", num_scans=3, truth=False)
    no_lidar = write_bag(tmp_path / "no_lidar", "ros2", {"/odom": topics["/odom"]})
    with pytest.raises(RosbagError, match="no lidar topic: expected a sensor_msgs/msg/"
                                          "LaserScan or sensor_msgs/msg/PointCloud2 topic"):
        load_rosbag(no_lidar)
    two = write_bag(tmp_path / "two", "ros2", {**topics, "/scan_rear": topics["/scan"]})
    with pytest.raises(RosbagError, match=r"2 sensor_msgs/msg/LaserScan topics \['/scan', "
                                          r"'/scan_rear'\]: choose the laser scan topic with "
                                          r"scan_topic / --scan-topic"):
        load_rosbag(two)
    with pytest.raises(RosbagError, match="both a scan topic"):
        load_rosbag(two, scan_topic="/scan", cloud_topic="/points")


def test_out_of_order_stamps_name_topic_index_and_stamps(tmp_path):
    topics, _ = scene_topics("ros2", num_scans=3, truth=False)
    msgtype, odometry = topics["/odom"]
    msgs = Messages(ros1=False)
    late = T0_NS + 5 * ODOM_PERIOD_NS + 5_000_000  # message 7 stamped between 5 and 6
    odometry[7] = (odometry[7][0], msgs.odometry(late, (0.0, 0.0, 0.0)))
    path = write_bag(tmp_path / "bag", "ros2", {**topics, "/odom": (msgtype, odometry)})
    with pytest.raises(RosbagError, match=r"topic '/odom': message 7 has stamp "
                                          r"1700000000\.105000000 s, not after message 6's "
                                          r"1700000000\.120000000 s; expected strictly "
                                          r"increasing stamps"):
        load_rosbag(path)


def test_clock_jump_names_the_gap(tmp_path):
    topics, _ = scene_topics("ros1", num_scans=4, truth=False)
    msgs = Messages(ros1=True)
    msgtype, scans = topics["/scan"]
    jumped = scans[3][0] + 100 * 10**9
    scans[3] = (scans[3][0], msgs.scan(jumped, np.full(BEAMS, np.inf)))
    path = write_bag(tmp_path / "bag.bag", "ros1", {**topics, "/scan": (msgtype, scans)})
    with pytest.raises(RosbagError, match=r"topic '/scan': the stamp jumps forward by "
                                          r"100\.200 s from message 2 \(1700000000\.213000000 s\)"
                                          r" to message 3 \(1700000100\.413000000 s\); expected "
                                          r"gaps of at most max_gap=10 s"):
        load_rosbag(path)
    # Accepting the jump leaves the last scan outside the odometry: dropped, not an error.
    assert load_rosbag(path, max_gap=None).num_steps == 2


def test_zero_header_stamps_suggest_bag_times(tmp_path):
    topics, _ = scene_topics("ros2", num_scans=3, truth=False)
    msgtype, scans = topics["/scan"]
    msgs = Messages(ros1=False)
    scans = [(ns, msgs.scan(0, np.full(BEAMS, np.inf))) for ns, _ in scans]
    path = write_bag(tmp_path / "bag", "ros2", {**topics, "/scan": (msgtype, scans)})
    with pytest.raises(RosbagError, match=r"topic '/scan': message 0 has a zero header stamp.*"
                                          r"time_source='bag'"):
        load_rosbag(path)


def test_paths_that_are_not_bags(tmp_path):
    with pytest.raises(RosbagError, match="no such file or folder; expected a ROS 1 .bag file "
                                          "or a ROS 2 bag folder holding metadata.yaml"):
        load_rosbag(tmp_path / "missing.bag")
    (tmp_path / "folder").mkdir()
    with pytest.raises(RosbagError, match="a folder without metadata.yaml, so not a ROS 2 bag"):
        load_rosbag(tmp_path / "folder")
    (tmp_path / "folder" / "a.bag").write_bytes(b"")
    with pytest.raises(RosbagError, match=r"it holds ROS 1 bag file\(s\) \['a.bag'\]"):
        load_rosbag(tmp_path / "folder")
    (tmp_path / "notes.txt").write_text("hello")
    with pytest.raises(RosbagError, match="neither a ROS 1 .bag file nor a ROS 2 bag folder"):
        load_rosbag(tmp_path / "notes.txt")
    (tmp_path / "lone.db3").write_bytes(b"")
    with pytest.raises(RosbagError, match="a ROS 2 .db3 storage file without metadata.yaml"):
        load_rosbag(tmp_path / "lone.db3")
    (tmp_path / "corrupt.bag").write_bytes(b"#ROSBAG V2.0\nnot really")
    with pytest.raises(RosbagError, match="cannot read as a ROS 1 bag"):
        load_rosbag(tmp_path / "corrupt.bag")
    assert rosbag_reader.is_rosbag_path(tmp_path / "x.bag")
    assert rosbag_reader.is_rosbag_path("x.mcap")
    assert not rosbag_reader.is_rosbag_path(tmp_path / "log.npz")
    assert not rosbag_reader.is_rosbag_path(tmp_path / "folder")  # no metadata.yaml: not a bag
    (tmp_path / "folder" / "metadata.yaml").write_text("{}")
    assert rosbag_reader.is_rosbag_path(tmp_path / "folder")
    with pytest.raises(RosbagError, match="cannot read as a ROS 2 bag folder"):
        load_rosbag(tmp_path / "folder")


def _hide_rosbags(monkeypatch):
    for name in [m for m in sys.modules if m == "rosbags" or m.startswith("rosbags.")]:
        monkeypatch.setitem(sys.modules, name, None)
    monkeypatch.setitem(sys.modules, "rosbags", None)


def test_missing_rosbags_names_the_extra(small_bag, monkeypatch, capsys):
    _hide_rosbags(monkeypatch)
    with pytest.raises(RosbagError, match=r'install it with: pip install "jaxslam\[ros\]"'):
        load_rosbag(small_bag)
    assert cli.main(["convert", str(small_bag), "--out", str(small_bag) + ".npz"]) == 2
    err = capsys.readouterr().err.splitlines()
    assert err[0].startswith("jaxslam convert: error: reading ROS bags needs the rosbags "
                             "package") and 'pip install "jaxslam[ros]"' in err[0]


# ---------------------------------------------------------------------------- CLI


@pytest.mark.slow  # 13 s: convert + a filter run; the reader tests keep the bag path
def test_cli_convert_then_run(tmp_path, monkeypatch, capsys):
    topics, _ = scene_topics("ros1", num_scans=10)
    bag = write_bag(tmp_path / "tiny.bag", "ros1", topics)
    monkeypatch.setenv("JAXSLAM_CACHE_DIR", str(tmp_path / "cache"))
    assert cli.main(["convert", str(bag), "--out", str(tmp_path / "log"),
                     "--truth-topic", "/truth"]) == 0
    out = capsys.readouterr().out
    assert "wrote " + str(tmp_path / "log.npz") in out and "9 steps" in out
    log = load_log(tmp_path / "log.npz")
    np.testing.assert_allclose(log.controls, expected_controls(log.time)[0], atol=1e-4)
    small = ["--no-calibrate", "--set", "filter.num_particles=8", "--set",
             "filter.max_landmarks=12"]
    try:
        assert cli.main(["run", "--data", str(tmp_path / "log.npz"), "--out",
                         str(tmp_path / "from_npz"), *small]) == 0
        from_npz = capsys.readouterr().out
        assert cli.main(["run", "--data", str(bag), "--truth-topic", "/truth",
                         "--scan-topic", "/scan", "--odom-topic", "/odom", "--out",
                         str(tmp_path / "from_bag"), *small]) == 0
        from_bag = capsys.readouterr().out
    finally:
        import jax

        jax.config.update("jax_compilation_cache_dir", None)  # as tests/test_cli.py does

    def metrics(text):
        return {k: v for k, v in (line.split() for line in text.splitlines()
                                  if len(line.split()) == 2)}

    values = metrics(from_npz)
    assert metrics(from_bag)["ate_rmse"] == values["ate_rmse"]
    assert float(values["ate_rmse"]) < 0.3 and int(values["num_landmarks"]) >= 2
    assert (tmp_path / "from_bag" / "map.png").is_file()


def test_cli_errors_are_one_line(tmp_path, small_bag, capsys):
    assert cli.main(["run", "--data", str(small_bag), "--scan-topic", "/lidar"]) == 2
    err = capsys.readouterr().err.splitlines()
    assert err[0].startswith("jaxslam run: error: ") and "no topic '/lidar'" in err[0]
    assert "the bag's topics: '/odom'" in err[0]
    assert cli.main(["run", "--data", str(tmp_path)]) == 2  # a folder, not a ROS 2 bag
    err = capsys.readouterr().err.splitlines()[0]
    assert "is a directory, not a file" in err and "nor a ROS 2 bag folder" in err
    np.savez(tmp_path / "log.npz", time=np.zeros(1))
    assert cli.main(["run", "--data", str(tmp_path / "log.npz"), "--odom-topic", "/x"]) == 2
    assert "--odom-topic applies to a ROS bag" in capsys.readouterr().err
    assert cli.main(["run", "--scan-topic", "/scan"]) == 2  # no --data at all
    assert "--scan-topic applies to a ROS bag: pass --data BAG too" in capsys.readouterr().err
    assert cli.main(["convert", str(tmp_path / "log.npz"), "--out", str(tmp_path / "o")]) == 2
    assert "neither a ROS 1 .bag file nor a ROS 2 bag folder" in capsys.readouterr().err
