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
                             instead (``odometry.integrate_controls``, velocity model).
  a truth pose topic         ``truth_pose`` at the scan stamps (same message types).

Shapes: T scans kept (the filter steps), B beams, K = ``max_obs`` padded detections, N points.
Times are seconds on the bag's clock (header stamps by default); poses are (x, y, theta) in
metres and radians; the tracked pose is the sensor's (``sensor_pose`` places it on the base).

Reading the bag is ``jaxslam.datasets.rosbag_reader``'s (``rosbags`` is imported when a bag is
opened), its lidar topic ``jaxslam.datasets.rosbag_clouds``'s; this module builds the log.
"""
from __future__ import annotations

from typing import Callable

import numpy as np

from jaxslam.host import in_float64
from jaxslam.datasets.log_format import RobotLog, validate_log
from jaxslam.datasets.odometry import (
    integrate_controls,
    interpolate_poses,
    odometry_between,
    odometry_path,
)
from jaxslam.datasets.rosbag_clouds import (
    CLOUD_DETECTIONS,
    SensorTrack,
    detect_trunks_batched,
    detector_keywords,
    pad_detections,
    read_clouds,
    read_scans,
)
from jaxslam.datasets.rosbag_reader import (
    CLOUD_TYPE,
    ODOMETRY_TYPE,
    POSE_TYPES,
    SCAN_TYPE,
    OpenBag,
    PoseTrack,
    check_stamps,
    format_stamp,
    pick_topic,
    read_pose_track,
    resolve_bag_path,
)
from jaxslam.geometry import compose


def _scan_window(bag: OpenBag, scan_ns, spans: dict, progress) -> np.ndarray:
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


def _sensor_poses(bag: OpenBag, odom: PoseTrack, odom_topic: str, scan_s, odom_source: str,
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
        base = odometry_path(moves, start)
    else:
        raise ValueError(f"odom_source={odom_source!r}; expected 'pose' or 'twist'")
    return in_float64(compose, base, sensor_pose)


def _controls(poses, min_translation: float) -> np.ndarray:
    """(T, 3) odometry moves: row 0 zero (the log starts at poses[0]), row t poses[t-1]->t."""
    moves = np.zeros((len(poses), 3))
    if len(poses) > 1:
        moves[1:] = odometry_between(poses[:-1], poses[1:], min_translation)
    return moves


def _observations(track: SensorTrack, keep, max_obs: int, detector: dict | None):
    """(z, valid, radius) of the kept scans: the cloud_detector's, else detect_trunks'."""
    if track.detections is not None:
        return pad_detections([d for d, k in zip(track.detections, keep) if k], max_obs)
    return detect_trunks_batched(track.ranges[keep], track.angles, max_obs,
                                 **detector_keywords(detector, False, "slice"))


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
        (``odometry.odometry_between``).
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
    bag = OpenBag(resolve_bag_path(path))
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


def _sensor_topic(bag: OpenBag, scan_topic, cloud_topic) -> tuple[str, str]:
    """(topic, "scan" or "cloud") of the lidar."""
    if scan_topic is not None and cloud_topic is not None:
        bag.fail(f"both a scan topic ({scan_topic!r}) and a cloud topic ({cloud_topic!r}) "
                 "were given; expected one lidar topic")
    if cloud_topic is not None:
        return pick_topic(bag, cloud_topic, (CLOUD_TYPE,), "the point cloud",
                           "cloud_topic / --cloud-topic"), "cloud"
    scan = pick_topic(bag, scan_topic, (SCAN_TYPE,), "the laser scan",
                       "scan_topic / --scan-topic")
    if scan is not None:
        return scan, "scan"
    cloud = pick_topic(bag, None, (CLOUD_TYPE,), "the point cloud",
                        "cloud_topic / --cloud-topic")
    if cloud is None:
        bag.fail(f"no lidar topic: expected a {SCAN_TYPE} or {CLOUD_TYPE} topic with "
                 f"messages; {bag.describe()}")
    return cloud, "cloud"


def _odometry_topic(bag: OpenBag, odom_topic) -> str:
    topic = pick_topic(bag, odom_topic, POSE_TYPES, "odometry", "odom_topic / --odom-topic")
    if topic is None:
        bag.fail(f"no odometry: expected a {ODOMETRY_TYPE} topic with messages, or pass "
                 f"odom_topic (--odom-topic) naming a PoseStamped, PoseWithCovarianceStamped "
                 f"or TFMessage topic; {bag.describe()}")
    return topic


def _load(bag: OpenBag, scan_topic, cloud_topic, odom_topic, truth_topic, *, max_obs, detector,
          cloud_detector, cloud_detection, cloud_beams, cloud_z_band, sensor_pose, odom_source,
          tf_frames, truth_tf_frames, time_source, max_gap, min_translation, keep_scans,
          progress) -> RobotLog:
    """``load_rosbag`` on an open bag."""
    source = str(bag.path)
    sensor, kind = _sensor_topic(bag, scan_topic, cloud_topic)
    odometry = _odometry_topic(bag, odom_topic)
    truth = (None if truth_topic is None else
             pick_topic(bag, truth_topic, POSE_TYPES, "ground truth",
                         "truth_topic / --truth-topic"))
    if progress is not None:
        used = [(f"{kind}s", sensor), ("odometry", odometry)] + (
            [("truth", truth)] if truth else [])
        progress("reading " + ", ".join(f"{what} {name!r} ({bag.topics[name][0]}, "
                                        f"{bag.topics[name][1]} messages)"
                                        for what, name in used))
    settings = detector_keywords(detector, kind == "cloud", cloud_detection)
    track = (read_scans(bag, sensor, time_source) if kind == "scan" else
             read_clouds(bag, sensor, time_source, int(cloud_beams), cloud_z_band,
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
    truth_pose = None
    if truth_track is not None:
        truth_base = interpolate_poses(scan_s, truth_track.time_ns / 1e9, truth_track.pose)
        truth_pose = in_float64(compose, truth_base, sensor_pose)
    z, valid, radius = _observations(track, keep, int(max_obs), detector)
    log = RobotLog(
        time=scan_s, motion_model="odometry", controls=_controls(poses, min_translation),
        obs_z=z, obs_valid=valid, obs_radius=radius,
        scan_ranges=track.ranges[keep] if keep_scans else None,
        scan_angles=track.angles if keep_scans else None, truth_pose=truth_pose,
        initial_pose=poses[0] if truth_pose is None else truth_pose[0])
    return validate_log(log, source=source)
