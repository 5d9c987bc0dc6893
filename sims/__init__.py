"""MuJoCo-MJX forest simulation: forest worlds, lidar scans, robot paths and scenarios."""
from sims.forest import (
    Clutter,
    Forest,
    World,
    forest_mjcf,
    make_world,
    mj_model_of,
    plantation_forest,
    random_clutter,
    random_forest,
    sample_radii,
    world_from_forest,
)
from sims.lidar import (
    TABLE2_RANGE_NOISE,
    Scan,
    add_range_noise,
    beam_angles,
    clip_3d_to_2d,
    layer_elevations,
    scan_2d,
    scan_2d_full,
    scan_3d,
)
from sims.paths import (
    lawnmower_path,
    loop_path,
    noisy_odometry,
    path_clearance,
    random_smooth_path,
    resample_polyline,
    true_moves,
)
from sims.scenario import (
    Scenario,
    analytic_observations,
    build_scenario,
    default_scenario,
)
