"""Units of the study config keys and of the results table's columns, and which columns are
not settings.

Plain Python (no JAX import), shared by the study writer (``jaxslam.studies``, which stores the
units in each Parquet file's metadata), the plots and ``jaxslam config show``. Every column is
defined in docs/metrics.md.
"""

_COUNT, _NONE = "count", "-"
# Unit of every study config key ("section.key"; "-" for names, choices, flags, factors).
# Params units follow the Params docstring (jaxslam/types/params.py); vector fields name one
# unit per component. tests/test_cli_ux.py checks that every key of the config and of Params is
# here.
CONFIG_UNITS = {
    "name": _NONE, "num_runs": _COUNT, "chunk_size": _COUNT, "run_width": _COUNT,
    "seed": _NONE, "divergence_threshold": "m", "map_match_threshold": "m",
    "gospa_cutoff": "m",
    "filter.num_particles": _COUNT, "filter.max_landmarks": _COUNT, "filter.max_obs": _COUNT,
    "filter.motion_model": _NONE, "filter.association": _NONE, "filter.proposal": _NONE,
    "filter.mixture_mode": _NONE, "filter.resampling": _NONE, "filter.boundary": _NONE,
    "filter.max_match_rounds": _COUNT, "filter.association_window": _COUNT,
    "filter.match_pose_uncertainty": _NONE, "filter.anchor_empty_map": _NONE,
    "filter.associate_at_sample": _NONE, "filter.burst_proposal": _NONE,
    "filter.burst_turn_pieces": _COUNT, "filter.burst_turn_span": _NONE,
    "filter.proposal_iterations": _COUNT,
    "scenario.forest": _NONE, "scenario.num_trees": _COUNT, "scenario.size": "m",
    "scenario.path": _NONE, "scenario.num_steps": _COUNT, "scenario.step_length": "m",
    "scenario.max_range": "m", "scenario.observation_source": _NONE,
    "scenario.detection": _NONE, "scenario.odometry_noise_scale": _NONE, "scenario.world": _NONE,
    "scenario.robot": _NONE, "scenario.first_scan": _NONE,
    "params.rot1_noise": "rad/m, rad/rad, rad", "params.trans_noise": "m/m, m/rad, m",
    "params.rot2_noise": "rad/m, rad/rad, rad", "params.motion_outlier_probability": "probability",
    "params.motion_outlier_scale": _NONE, "params.min_translation": "m",
    "params.odometry_gain": "-, -",
    "params.wheelbase": "m", "params.encoder_offset": "m", "params.laser_forward": "m",
    "params.laser_left": "m", "params.range_noise": "m/m, m",
    "params.bearing_noise": "rad/m, rad", "params.range_std_floor": "m",
    "params.bearing_std_floor": "rad", "params.radius_noise": "m", "params.max_range": "m",
    "params.min_range": "m", "params.miss_range": "m", "params.miss_bearing": "rad",
    "params.association_gate": "squared Mahalanobis distance",
    "params.association_heading_std": "rad",
    "params.new_landmark_log_offset": "log-likelihood",
    "params.detection_probability": "probability",
    "params.false_alarm_probability": "probability", "params.existence_init": "log-odds",
    "params.existence_delete": "log-odds", "params.existence_max": "log-odds",
    "params.airlock_sigmas": "standard deviations", "params.ess_threshold": "fraction of P",
    "params.mixture_ratio": "probability", "params.mixture_min": "probability",
    "params.mixture_max": "probability", "params.likelihood_rate_fast": "1/step",
    "params.likelihood_rate_slow": "1/step",
}


def config_unit(key: str) -> str:
    """The unit of a config key ("filter.num_particles", "sweep.max_range", ...).

    A sweep key has the unit of the parameter it sweeps. Raises ``KeyError`` for a key the
    table lacks (a new config field needs its unit added to ``CONFIG_UNITS``).
    """
    if key.startswith("sweep."):
        key = "params." + key[len("sweep."):]
    return CONFIG_UNITS[key]



# Unit of every column of a chunk (also in each Parquet file's schema metadata).
COLUMN_UNITS = {
    "run_id": "-", "condition": "-", "study_seed": "-", "run_key": "-",
    "final_pose_error": "m", "final_heading_error": "rad", "ate_rmse": "m",
    "ate_rmse_aligned": "m", "rpe_translation": "m", "rpe_rotation": "rad", "map_error": "m",
    "redundant": "count", "orphan": "count", "num_landmarks": "count",
    "num_trees_mapped": "count", "gospa": "m", "gospa_localisation": "m^2", "gospa_missed": "m^2",
    "gospa_false": "m^2", "diverged": "0/1", "pose_nees": "-", "map_nees": "-",
    "num_trees_seen": "count", "diameter_error": "m", "num_diameters": "count",
    "min_ess": "particles", "num_resampled": "steps", "num_dropped_births": "count",
    "num_weight_resets": "steps", "num_invalid_controls": "steps",
    "peak_match_rounds": "rounds", "num_window_cut_steps": "steps", "peak_window_cut": "count",
    "mean_mixture_ratio": "fraction",
}
def column_unit(name: str) -> str:
    """The unit of a column: a metric's, or a swept parameter's (``name`` or, for one
    component of a vector field, ``name[j]``); "-" when unknown or unitless."""
    base, _, index = name.partition("[")
    if base in COLUMN_UNITS:
        return COLUMN_UNITS[base]
    unit = CONFIG_UNITS.get(f"params.{base}", _NONE)
    components = unit.split(", ")
    return components[int(index.rstrip("]"))] if index and len(components) > 1 else unit


# Identifiers and measured values: never swept settings (the plots label boxes by settings).
# The last names are columns of folders written by earlier versions.
NON_SETTING_COLUMNS = frozenset(COLUMN_UNITS) | {"seed", "chunk", "max_match_rounds",
                                                 "update_rate_hz", "wall_time_s"}
