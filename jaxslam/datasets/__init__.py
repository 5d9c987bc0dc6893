"""Robot logs: the documented jaxslam ``.npz`` format, control integration, ROS bags, and the
Victoria Park and MRCLAM loaders. (``rosbag_reader`` imports the optional ``rosbags`` package
only when a bag is read.)"""
from jaxslam.datasets.log_format import (
    FORMAT_VERSION,
    LogFormatError,
    RobotLog,
    load_log,
    save_log,
    validate_log,
)
from jaxslam.datasets.mrclam import (
    MrclamFileError,
    MrclamRun,
    load_mrclam,
    read_mrclam,
)
from jaxslam.datasets.mrclam_convert import MrclamSteps, mrclam_log, mrclam_steps
from jaxslam.datasets.odometry import (
    VICTORIA_PARK_VEHICLE,
    AckermannVehicle,
    integrate_controls,
    odometry_between,
    odometry_path,
)
from jaxslam.datasets.rosbag import load_rosbag
from jaxslam.datasets.rosbag_reader import RosbagError, is_rosbag_path, rosbag_topics
from jaxslam.datasets.victoria_park import (
    GpsError,
    VictoriaPark,
    dead_reckoning_controls,
    dead_reckoning_path,
    default_victoria_park_dir,
    filter_gps,
    gps_error,
    load_victoria_park,
    rigid_transform_2d,
    victoria_park_log,
)
