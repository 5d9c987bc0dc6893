"""Robot logs: the documented jaxslam ``.npz`` format, ROS bags, and the Victoria Park and MRCLAM
loaders. (``rosbag`` imports the optional ``rosbags`` package only when a bag is read.)"""
from jaxslam.datasets.log_format import (
    FORMAT_VERSION,
    VICTORIA_PARK_VEHICLE,
    AckermannVehicle,
    LogFormatError,
    RobotLog,
    integrate_controls,
    load_log,
    odometry_between,
    odometry_path,
    save_log,
    validate_log,
)
from jaxslam.datasets.mrclam import (
    MrclamFileError,
    MrclamRun,
    MrclamSteps,
    load_mrclam,
    mrclam_log,
    mrclam_steps,
    read_mrclam,
)
from jaxslam.datasets.rosbag import (
    RosbagError,
    is_rosbag_path,
    load_rosbag,
    rosbag_topics,
)
from jaxslam.datasets.victoria_park import (
    GpsError,
    VictoriaPark,
    dead_reckoning_controls,
    dead_reckoning_path,
    default_victoria_park_dir,
    filter_gps,
    gps_error,
    load_victoria_park,
    rigid_align_2d,
    rigid_transform_2d,
    victoria_park_log,
)
