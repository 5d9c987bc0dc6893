"""Plots: non-empty PNGs from small synthetic arrays, clear errors for bad shapes, ellipse math."""
import numpy as np
import pytest

from jaxslam import plots


def _example(seed=0, steps=40, num_trees=12, num_slots=16):
    rng = np.random.default_rng(seed)
    angle = np.linspace(0.0, 2.0 * np.pi, steps + 1)
    truth = np.stack([8.0 * np.cos(angle), 5.0 * np.sin(angle), angle + np.pi / 2], 1)
    trees = rng.uniform(-12.0, 12.0, (num_trees, 2))
    landmark_mean = np.zeros((num_slots, 2))
    landmark_mean[:num_trees] = trees + rng.normal(0.0, 0.2, trees.shape)
    active = np.arange(num_slots) < num_trees - 2
    landmark_cov = np.tile(np.array([[0.04, 0.01], [0.01, 0.02]]), (num_slots, 1, 1))
    return dict(truth_pose=truth, mean_pose=truth[1:] + rng.normal(0.0, 0.1, (steps, 3)),
                landmark_mean=landmark_mean, landmark_cov=landmark_cov, active=active,
                tree_centres=trees, tree_radii=rng.uniform(0.1, 0.3, num_trees))


def _traces(num_runs=12, steps=30, seed=1):
    rng = np.random.default_rng(seed)
    condition = np.arange(num_runs) % 3
    error = np.abs(np.cumsum(rng.normal(0.0, 0.05, (num_runs, steps)), 1)) * (1 + condition[:, None])
    return dict(run_id=np.arange(num_runs), condition=condition, pose_error=error)


def _table(num_runs=12):
    condition = np.arange(num_runs) % 3
    return dict(run_id=np.arange(num_runs), condition=condition, seed=np.zeros(num_runs, int),
                num_particles=np.array([10.0, 50.0, 100.0])[condition],
                max_range=np.full(num_runs, 20.0),  # not swept: constant everywhere
                final_pose_error=np.linspace(0.1, 1.0, num_runs),
                num_landmarks=np.arange(num_runs) % 3 + 5)  # a metric, never a sweep column


def _assert_png_with_content(path):
    import matplotlib.image

    with open(path, "rb") as handle:
        assert handle.read(8) == b"\x89PNG\r\n\x1a\n"
    image = matplotlib.image.imread(path)
    assert image.shape[0] > 200 and image.shape[1] > 200
    # Something was drawn: far from a blank (all-white) canvas.
    assert np.mean(image[..., :3] < 0.9) > 0.01


def test_plot_map_from_arrays_and_file(tmp_path):
    example = _example()
    _assert_png_with_content(plots.plot_map(example, tmp_path / "a" / "map.png"))
    np.savez(tmp_path / "example_run.npz", **example, tree_seen=np.ones(12, bool))  # extra key ok
    _assert_png_with_content(plots.plot_map(tmp_path / "example_run.npz", tmp_path / "b.png"))


def test_plot_map_tree_seen_mask(tmp_path):
    example = _example()
    example["tree_seen"] = np.arange(12) < 6
    _assert_png_with_content(plots.plot_map(example, tmp_path / "map.png"))
    example["tree_seen"] = np.ones(5, bool)
    with pytest.raises(ValueError, match=r"tree_seen has shape \(5,\); expected \(12,\)"):
        plots.plot_map(example, tmp_path / "map2.png")


def test_plot_map_without_landmarks_or_trees(tmp_path):
    example = _example()
    example.update(active=np.zeros(16, bool), tree_centres=np.zeros((0, 2)),
                   tree_radii=np.zeros(0))
    _assert_png_with_content(plots.plot_map(example, tmp_path / "map.png"))


@pytest.mark.parametrize("name, value, expected", [
    ("landmark_cov", np.zeros((16, 3)), "landmark_cov has shape (16, 3); expected (16, 2, 2)"),
    ("active", np.ones(15, bool), "active has shape (15,); expected (16,)"),
    ("mean_pose", np.zeros((40, 2)), "mean_pose has shape (40, 2); expected (T, 3)"),
    ("tree_radii", np.ones(11), "tree_radii has shape (11,); expected (12,)"),
])
def test_plot_map_bad_shapes(tmp_path, name, value, expected):
    example = _example()
    example[name] = value
    with pytest.raises(ValueError, match=expected.replace("(", r"\(").replace(")", r"\)")):
        plots.plot_map(example, tmp_path / "map.png")
    assert not (tmp_path / "map.png").exists()


def test_plot_map_missing_key_and_file(tmp_path):
    example = _example()
    del example["tree_centres"]
    with pytest.raises(ValueError, match="missing array 'tree_centres'"):
        plots.plot_map(example, tmp_path / "map.png")
    with pytest.raises(FileNotFoundError, match="nothere.npz"):
        plots.plot_map(tmp_path / "nothere.npz", tmp_path / "map.png")


def test_covariance_ellipses_axes_and_angle():
    # diag(4, 1): std 2 along x, 1 along y -> 2-sigma full axes 8 and 4, major axis along x.
    rotation = np.array([[np.cos(0.5), -np.sin(0.5)], [np.sin(0.5), np.cos(0.5)]])
    cov = np.stack([np.diag([4.0, 1.0]), rotation @ np.diag([9.0, 0.25]) @ rotation.T])
    width, height, angle = plots.covariance_ellipses(cov)
    np.testing.assert_allclose(width, [8.0, 12.0], rtol=1e-12)
    np.testing.assert_allclose(height, [4.0, 2.0], rtol=1e-12)
    # the major axis direction is defined up to 180 degrees
    np.testing.assert_allclose(np.mod(angle, 180.0), [0.0, np.degrees(0.5)], atol=1e-9)


def test_plot_error_vs_time(tmp_path):
    labels = {0: "num_particles=10", 1: "num_particles=50", 2: "num_particles=100"}
    _assert_png_with_content(plots.plot_error_vs_time(_traces(), tmp_path / "err.png", labels))


def test_load_traces_from_folder_sorts_and_concatenates(tmp_path):
    traces = _traces(num_runs=12)
    second, first = slice(6, 12), slice(0, 6)
    np.savez(tmp_path / "traces-000006-000012.npz", **{k: v[second] for k, v in traces.items()})
    np.savez(tmp_path / "traces-000000-000006.npz", **{k: v[first][::-1]
                                                       for k, v in traces.items()})
    loaded = plots.load_traces(tmp_path)
    np.testing.assert_array_equal(loaded.run_id, np.arange(12))
    np.testing.assert_array_equal(loaded.pose_error, traces["pose_error"])
    with pytest.raises(FileNotFoundError, match="no such file"):
        plots.load_traces(tmp_path / "a")  # not a folder, not a file
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match="no traces"):
        plots.load_traces(tmp_path / "empty")


@pytest.mark.parametrize("name, value, expected", [
    ("pose_error", np.zeros(12), r"pose_error has shape \(12,\); expected \(R, T\)"),
    ("run_id", np.arange(11), r"run_id has shape \(11,\); expected \(12,\)"),
    ("condition", np.zeros((12, 1)), r"condition has shape \(12, 1\); expected \(12,\)"),
])
def test_plot_error_vs_time_bad_shapes(tmp_path, name, value, expected):
    traces = _traces()
    traces[name] = value
    with pytest.raises(ValueError, match=expected):
        plots.plot_error_vs_time(traces, tmp_path / "err.png")


def test_swept_columns_and_labels():
    table = _table()
    assert plots.swept_columns(table) == ["num_particles"]
    assert plots.condition_labels(table) == {0: "num_particles=10", 1: "num_particles=50",
                                             2: "num_particles=100"}
    assert plots.condition_labels(table, ["max_range"])[1] == "max_range=20"
    no_sweep = {k: v for k, v in table.items() if k != "num_particles"}
    assert plots.condition_labels(no_sweep)[0] == "condition 0"
    one = {k: v[:1] for k, v in no_sweep.items()}
    assert plots.condition_labels(one) == {0: "all runs"}


def test_plot_sweep_boxes_from_pyarrow_and_dict(tmp_path):
    import pyarrow as pa

    table = _table()
    _assert_png_with_content(plots.plot_sweep_boxes(pa.table(table), "final_pose_error",
                                                    tmp_path / "box.png"))
    _assert_png_with_content(plots.plot_sweep_boxes(table, "final_pose_error",
                                                    tmp_path / "box2.png"))
    with pytest.raises(ValueError, match="no 'gospa' column"):
        plots.plot_sweep_boxes(table, "gospa", tmp_path / "box3.png")
    with pytest.raises(TypeError, match="pyarrow.Table"):
        plots.plot_sweep_boxes(42, "final_pose_error", tmp_path / "box4.png")


def test_plot_study_writes_every_plot(tmp_path):
    import pyarrow as pa
    import pyarrow.parquet as pq

    np.savez(tmp_path / "example_run.npz", **_example())
    np.savez(tmp_path / "traces-000000-000012.npz", **_traces())
    pq.write_table(pa.table(_table()), tmp_path / "chunk-000000-000012.parquet")
    written = plots.plot_study(tmp_path, metrics=("final_pose_error", "not_a_metric"))
    names = sorted(p.rsplit("/", 1)[-1] for p in written)
    assert names == ["box_final_pose_error.png", "error_vs_time.png", "map.png"]
    for path in written:
        _assert_png_with_content(path)
