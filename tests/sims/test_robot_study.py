"""Studies driven by the MJX wheeled robot (``scenario.robot = "mjx_wheeled"``): a small study
through ``run_study``, bit-identical per-run results across chunk sizes, odometry that is the
robot's encoder dead reckoning (not the truth's moves, not Eq. (1) noise), and the settings
that are refused with the keys named.

One robot simulator compile (3 runs x 8 intervals of 0.5 s) and one filter compile serve the
default-tier tests; per-run worlds need a second robot compile and run in the slow tier.
"""
import jax
import numpy as np
import pytest

from jaxslam import studies
from jaxslam.motion import odometry_from_poses

ROBOT = ["num_runs=3", "filter.num_particles=8", "filter.max_landmarks=24", "filter.max_obs=8",
         "scenario.num_steps=8", "scenario.num_trees=15", "scenario.size=30.0",
         'scenario.robot="mjx_wheeled"',
         # The seed paper's FastSLAM compiles fastest; the robot, not the filter, is tested.
         "filter.proposal='motion'", "filter.anchor_empty_map=false",
         "params.motion_outlier_probability=0.0"]


def robot_config(*overrides) -> studies.StudyConfig:
    return studies.load_study_config(None, ROBOT + list(overrides))


@pytest.fixture(scope="module")
def chunked_studies(tmp_path_factory):
    """The same 3-run robot study with chunks of 3 runs and of 1 run."""
    root = tmp_path_factory.mktemp("robot_study")
    return {size: studies.run_study(robot_config(f"chunk_size={size}"), root / f"chunk{size}",
                                    progress=False)
            for size in (3, 1)}


@pytest.fixture(scope="module")
def batch():
    from sims.batch import scenario_batch

    return jax.tree.map(np.asarray, scenario_batch(robot_config(), np.arange(3)))


def test_robot_study_runs_and_is_identical_across_chunk_sizes(chunked_studies):
    tables = {size: result.table for size, result in chunked_studies.items()}
    assert tables[3].num_rows == 3 and len(list(
        (chunked_studies[1].out_dir / "runs").glob("chunk-*.parquet"))) == 3
    assert np.all(np.isfinite(tables[3].column("final_pose_error").to_numpy()))
    assert np.all(tables[3].column("num_trees_seen").to_numpy() > 0)
    assert tables[3].column_names == tables[1].column_names
    for name in tables[3].column_names:
        np.testing.assert_array_equal(tables[3].column(name).to_numpy(),
                                      tables[1].column(name).to_numpy(), err_msg=name)
    for run in range(3):
        traces = [np.load(result.out_dir / "traces" / name)
                  for result, name in ((chunked_studies[3], "traces-000000-000003.npz"),
                                       (chunked_studies[1], f"traces-{run:06d}-{run + 1:06d}.npz"))]
        np.testing.assert_array_equal(traces[0]["pose_error"][run], traces[1]["pose_error"][0])


def test_robot_odometry_is_encoder_dead_reckoning_not_eq1_noise(batch):
    """The controls are not the true path's moves: their errors are finite and above float32
    round-off (1e-3 m or rad; round-off on these poses is about 1e-5), and every run drives
    its own commands."""
    from sims.batch import simulation_params, study_world

    config = robot_config()
    min_translation = float(simulation_params(config.scenario).min_translation)
    truth = batch.truth_pose
    # 8 intervals after the start scan's zero move (row 0), which repeats the start pose.
    assert truth.shape == (3, 10, 3) and batch.controls.shape == (3, 9, 3)
    np.testing.assert_array_equal(batch.controls[:, 0], 0.0)
    np.testing.assert_array_equal(truth[:, 0], truth[:, 1])
    exact = np.asarray(odometry_from_poses(truth[:, :-1], truth[:, 1:], min_translation))
    error = batch.controls - exact
    error[..., [0, 2]] = np.angle(np.exp(1j * error[..., [0, 2]]))
    assert np.all(np.isfinite(error))
    assert np.max(np.abs(error)) > 1e-3
    # Each run starts at the scenario path's first pose (shared world) and then moves.
    start = np.asarray(study_world(config.scenario, config.seed)[1])[0]
    np.testing.assert_allclose(truth[:, 0], np.broadcast_to(start, (3, 3)), atol=1e-5)
    assert not np.array_equal(batch.controls[0], batch.controls[1])
    assert np.all(np.sum(np.abs(batch.controls[..., 1]), axis=1) > 0.1)
    # The observations are the analytic ones: each carries a tree id and a true range,
    # row t taken at truth[t + 1] (row 0, the start scan, at the start pose).
    valid = batch.observations.valid
    ids = batch.observations.landmark_id
    assert valid.any() and valid[:, 0].any() and np.all(ids[valid] >= 0)
    gap = batch.tree_centres[0][ids[0]] - truth[0, 1:, None, :2]
    true_range = np.hypot(gap[..., 0], gap[..., 1])
    # Table 2 range noise: 0.005 m/m at 20 m is 0.1 m; 0.6 m is six of those stds.
    assert np.max(np.abs(batch.observations.z[0, ..., 0] - true_range)[valid[0]]) < 0.6


def test_robot_steps_after_the_start_scan_keep_their_draws(batch):
    """Row t >= 1 is the scan at truth[t + 1] drawn with split(obs_key, T)[t - 1], as before
    the start scan existed; row 0 is the scan at the start pose with fold_in(obs_key, T).
    Recomputed here from the run keys of the module docstring (same float32 ops: exact)."""
    from sims.batch import simulation_params
    from sims.scenario import analytic_observations

    config = robot_config()
    params = simulation_params(config.scenario)
    num_steps, max_obs = config.scenario.num_steps, config.filter.max_obs
    for run in range(3):
        run_key = jax.random.fold_in(jax.random.PRNGKey(config.seed), run)
        obs_key = jax.random.split(jax.random.fold_in(run_key, 0))[1]
        centres, radii = batch.tree_centres[run], batch.tree_radii[run]
        truth = batch.truth_pose[run]
        step_keys = jax.random.split(obs_key, num_steps)
        keys_and_poses = [(jax.random.fold_in(obs_key, num_steps), truth[0])] + [
            (step_keys[t - 1], truth[t + 1]) for t in range(1, num_steps + 1)]
        for t, (key, pose) in enumerate(keys_and_poses):
            want = analytic_observations(key, pose, centres, radii, params, max_obs)
            for name in ("z", "valid", "landmark_id"):
                np.testing.assert_array_equal(
                    getattr(batch.observations, name)[run, t], np.asarray(getattr(want, name)),
                    err_msg=f"run {run} row {t} {name}")


def test_robot_runs_do_not_depend_on_the_runs_asked_together(batch):
    from sims.batch import scenario_batch

    part = jax.tree.map(np.asarray, scenario_batch(robot_config(), np.array([2, 1])))
    for got, want in zip(jax.tree.leaves(part), jax.tree.leaves(batch)):
        np.testing.assert_array_equal(got, want[[2, 1]])


def test_robot_setting_is_written_only_when_not_the_default():
    kinematic = studies.load_study_config(None, [])
    assert kinematic.scenario.first_scan == "after_first_move"
    assert not {"robot", "first_scan"} & set(studies.study_config_to_dict(kinematic)["scenario"])
    config = robot_config()
    assert config.scenario.first_scan == "at_start"  # the robot's own default
    written = studies.study_config_to_dict(config)
    assert written["scenario"]["robot"] == "mjx_wheeled"
    assert written["scenario"]["first_scan"] == "at_start"
    assert studies.study_config_from_dict(written) == config
    from jaxslam.cli import config_rows

    assert ("scenario.robot", '"mjx_wheeled"', "-", "") in config_rows(config)
    assert ("scenario.first_scan", '"at_start"', "-", "") in config_rows(config)
    # The robot study without the start scan writes its value and reads back the same.
    earlier = robot_config('scenario.first_scan="after_first_move"')
    written = studies.study_config_to_dict(earlier)
    assert written["scenario"]["first_scan"] == "after_first_move"
    assert studies.study_config_from_dict(written) == earlier


def test_a_robot_study_from_before_the_key_is_not_resumed_by_mistake(tmp_path):
    """A robot study folder written before first_scan existed (its study.toml lacks the
    key; its runs have no start scan) is refused under either value, naming the key; with
    first_scan = "after_first_move" added to its study.toml it resumes. Only the folder's
    config is written: no run."""
    import tomllib

    import tomli_w

    from jaxslam import study_store

    without = studies.study_config_to_dict(robot_config('scenario.first_scan="after_first_move"'))
    old = {**without, "scenario": {k: v for k, v in without["scenario"].items()
                                   if k != "first_scan"}}
    study_store.prepare_out_dir(old, tmp_path)
    for value in ("at_start", "after_first_move"):
        config = studies.study_config_to_dict(robot_config(f'scenario.first_scan="{value}"'))
        with pytest.raises(study_store.StudyError, match="scenario.first_scan"):
            study_store.prepare_out_dir(config, tmp_path)
    study_file = tmp_path / "study.toml"
    edited = tomllib.loads(study_file.read_text())
    edited["scenario"]["first_scan"] = "after_first_move"
    study_file.write_text(tomli_w.dumps(edited))
    study_store.prepare_out_dir(without, tmp_path)  # the same study now: accepted


def test_robot_runs_without_the_start_scan_are_the_rows_after_it(batch):
    """first_scan = "after_first_move": T steps, truth (T+1, 3); every row equals the
    start-scan batch's row after its first (the same keys and robot). The two batches come
    from separately compiled programs, whose float results may differ in the last bits (3e-17
    measured on near-zero odometry), so floats are compared to rtol 1e-6 (a few float32 ulp)
    with atol 1e-9 for values near zero, masks and ids exactly."""
    from sims.batch import scenario_batch

    config = robot_config('scenario.first_scan="after_first_move"')
    without = jax.tree.map(np.asarray, scenario_batch(config, np.arange(3)))
    assert without.controls.shape == (3, 8, 3) and without.truth_pose.shape == (3, 9, 3)
    np.testing.assert_allclose(without.controls, batch.controls[:, 1:], rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(without.truth_pose, batch.truth_pose[:, 1:], rtol=1e-6,
                               atol=1e-9)
    for got, want in zip(jax.tree.leaves(without.observations),
                         jax.tree.leaves(batch.observations)):
        if np.issubdtype(got.dtype, np.floating):
            np.testing.assert_allclose(got, want[:, 1:], rtol=1e-6, atol=1e-9)
        else:
            np.testing.assert_array_equal(got, want[:, 1:])
    # Trees seen: those of rows 1..T, so within the start-scan runs' (which add row 0's).
    assert np.all(batch.tree_seen[without.tree_seen])
    assert np.sum(batch.tree_seen) >= np.sum(without.tree_seen)


def test_the_kinematic_robot_has_no_start_scan_yet():
    with pytest.raises(ValueError, match="scenario.first_scan='at_start'.*mjx_wheeled"):
        studies.load_study_config(None, ['scenario.first_scan="at_start"'])


@pytest.mark.parametrize("overrides, keys", [
    (['scenario.observation_source="lidar"'], ("scenario.robot", "scenario.observation_source")),
    (["scenario.odometry_noise_scale=2.0"], ("scenario.odometry_noise_scale", "scenario.robot")),
    (['scenario.robot="tracked"'], ("scenario.robot", "mjx_wheeled")),
    (['scenario.first_scan="sometimes"'], ("scenario.first_scan", "at_start",
                                           "after_first_move")),
])
def test_bad_robot_settings_name_the_keys(overrides, keys):
    with pytest.raises(ValueError) as error:
        studies.load_study_config(None, ROBOT + overrides)
    for key in keys:
        assert key in str(error.value)


@pytest.mark.slow
def test_per_run_worlds_start_each_robot_on_its_own_path():
    from sims.batch import run_world, scenario_batch

    config = robot_config('scenario.world="per_run"', 'scenario.path="random"')
    batch = jax.tree.map(np.asarray, scenario_batch(config, np.arange(2)))
    for run in range(2):
        forest, path = run_world(config.scenario, config.seed, run)
        np.testing.assert_allclose(batch.truth_pose[run, 0], np.asarray(path)[0], atol=1e-5)
        np.testing.assert_array_equal(batch.tree_centres[run], np.asarray(forest.centres,
                                                                          np.float32))
    assert not np.array_equal(batch.tree_centres[0], batch.tree_centres[1])
