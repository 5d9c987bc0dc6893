"""Plots: what the figures say (titles, legends, tick labels, units, scaled ellipses, inset),
PNGs from small synthetic arrays, clear errors for bad shapes, ellipse math, a real tiny study
(plotted, and every column of its table defined in docs/metrics.md)."""
import pathlib
import re

import numpy as np
import pytest

from jaxslam import plots

REPO = pathlib.Path(__file__).resolve().parent.parent
STUDY_INFO = plots.StudyInfo(name="forest", sweep=("detection_probability",),
                             conditions=("detection_probability=0.8",
                                         "detection_probability=0.9"),
                             num_runs=8, observation_source="analytic", max_range=20.0,
                             max_obs=16)


def _example(seed=0, steps=40, num_trees=12, num_slots=16):
    rng = np.random.default_rng(seed)
    angle = np.linspace(0.0, 2.0 * np.pi, steps + 1)
    truth = np.stack([8.0 * np.cos(angle), 5.0 * np.sin(angle), angle + np.pi / 2], 1)
    trees = rng.uniform(-12.0, 12.0, (num_trees, 2))
    landmark_mean = np.zeros((num_slots, 2))
    landmark_mean[:num_trees] = trees + rng.normal(0.0, 0.2, trees.shape)
    active = np.arange(num_slots) < num_trees - 2
    # std ~ 1-2 cm, as in the simulated forest: invisible at true scale on a 24 m map
    landmark_cov = np.tile(np.array([[4e-4, 1e-4], [1e-4, 2e-4]]), (num_slots, 1, 1))
    landmark_cov[3] *= 9.0  # the least certain landmark (3x the std)
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
                # metrics that are constant within each condition: never sweep columns
                num_landmarks=np.arange(num_runs) % 3 + 5,
                mean_mixture_ratio=np.array([0.0, 0.3, 0.6])[condition],
                peak_match_rounds=np.array([3, 4, 5])[condition],
                num_trees_seen=np.array([7, 8, 9])[condition])


def _assert_png_with_content(path):
    import matplotlib.image

    with open(path, "rb") as handle:
        assert handle.read(8) == b"\x89PNG\r\n\x1a\n"
    image = matplotlib.image.imread(path)
    assert image.shape[0] > 200 and image.shape[1] > 200
    # Something was drawn: far from a blank (all-white) canvas.
    assert np.mean(image[..., :3] < 0.9) > 0.01


def _legend_texts(ax):
    return [text.get_text() for text in ax.get_legend().get_texts()]


def _ellipses(ax):
    found = [c for c in ax.collections if c.get_gid() == "landmark_ellipses"]
    assert len(found) == 1
    return found[0]


def _inset(ax):
    insets = [child for child in ax.child_axes if child.get_gid() == "true_scale_inset"]
    return insets[0] if insets else None


def _assert_units_on_axes(fig):
    for ax in fig.axes:
        for label in (ax.get_xlabel(), ax.get_ylabel()):
            assert re.search(r"\[[^\]]+\]", label), f"no unit in axis label {label!r}"


# ------------------------------------------------------------------------------------------
# Map


def test_plot_map_from_arrays_and_file(tmp_path):
    example = _example()
    _assert_png_with_content(plots.plot_map(example, tmp_path / "a" / "map.png"))
    np.savez(tmp_path / "example_run.npz", **example, tree_seen=np.ones(12, bool))
    _assert_png_with_content(plots.plot_map(tmp_path / "example_run.npz", tmp_path / "b.png"))


def test_map_title_names_study_run_and_condition():
    fig = plots.map_figure(_example(), info=STUDY_INFO)
    title = fig.axes[0].get_title()
    assert "Study 'forest'" in title
    assert "run 0 (of 8), condition 0 (detection_probability=0.8)" in title
    no_sweep = STUDY_INFO._replace(sweep=(), conditions=("no sweep",))
    title = plots.map_figure(_example(), info=no_sweep).axes[0].get_title()
    assert "condition 0 (no sweep)" in title
    assert plots.map_figure(_example(), "my title").axes[0].get_title() == "my title"


def test_plot_map_takes_the_title_from_the_study_folder(tmp_path, monkeypatch):
    np.savez(tmp_path / "example_run.npz", **_example())
    monkeypatch.setattr(plots.labels, "study_info", lambda folder: STUDY_INFO
                        if pathlib.Path(folder) == tmp_path else None)
    figures = []
    monkeypatch.setattr(plots.figure, "save_figure",
                        lambda fig, path: figures.append(fig) or path)
    plots.plot_map(tmp_path / "example_run.npz", tmp_path / "map.png")
    assert "Study 'forest'" in figures[0].axes[0].get_title()


def test_ellipse_scale_is_a_round_factor_never_below_one():
    assert plots.ellipse_scale([0.1, 0.1, 0.1], 60.0) == 5.0  # wants 9 -> 5
    assert plots.ellipse_scale([0.01], 60.0) == 50.0  # wants 90 -> 50
    assert plots.ellipse_scale([0.009], 60.0) == 100.0  # wants 100 -> 100
    assert plots.ellipse_scale([1.0, 2.0], 60.0) == 1.0  # already visible: never shrunk
    assert plots.ellipse_scale([], 60.0) == 1.0
    assert plots.ellipse_scale([0.1], 0.0) == 1.0


def test_map_ellipses_are_enlarged_by_the_stated_factor_with_a_true_scale_inset():
    example = _example()
    active = example["active"]
    width, height, _ = plots.covariance_ellipses(example["landmark_cov"][active])
    fig = plots.map_figure(example)
    ax = fig.axes[0]
    scale = plots.ellipse_scale(width, plots._map_extent(plots.load_example_run(example)))
    assert scale > 1  # 8 cm ellipses on a ~25 m map
    np.testing.assert_allclose(_ellipses(ax).get_widths(), scale * width, rtol=1e-12)
    np.testing.assert_allclose(_ellipses(ax).get_heights(), scale * height, rtol=1e-12)
    assert f"landmark 2σ ellipse ×{scale:g} (enlarged to be visible)" in _legend_texts(ax)
    inset = _inset(ax)
    assert inset is not None and "true scale" in inset.get_title()
    np.testing.assert_allclose(_ellipses(inset).get_widths(), width, rtol=1e-12)
    # centred on the least certain landmark (slot 3), whose 2-sigma ellipse fits inside
    x_low, x_high = inset.get_xlim()
    assert x_low < example["landmark_mean"][3, 0] < x_high
    assert x_high - x_low > width.max()
    _assert_units_on_axes(fig)


def test_map_without_magnification_has_no_inset_and_says_true_scale():
    fig = plots.map_figure(_example(), scale=1.0)
    ax = fig.axes[0]
    assert "landmark 2σ ellipse (true scale)" in _legend_texts(ax)
    assert _inset(ax) is None
    assert _inset(plots.map_figure(_example(), inset=False).axes[0]) is None


@pytest.mark.parametrize("info, seen, unseen", [
    (STUDY_INFO, "true trunks measured at some step: 6\n(in range and among the 16 nearest)",
     "true trunks never measured: 6 (not scored)"),
    (STUDY_INFO._replace(observation_source="lidar", max_range=15.0),
     "true trunks within 15 m of the path at some step: 6",
     "true trunks never within 15 m: 6 (not scored)"),
    (None, "true trunks seen at some step: 6", "true trunks never seen: 6 (not scored)"),
])
def test_map_legend_says_what_tree_seen_means(info, seen, unseen):
    example = _example()
    example["tree_seen"] = np.arange(12) < 6
    texts = _legend_texts(plots.map_figure(example, info=info).axes[0])
    assert seen in texts and unseen in texts
    assert not any("observed" in text for text in texts)


def test_map_without_tree_seen_draws_every_trunk_alike():
    texts = _legend_texts(plots.map_figure(_example(), info=STUDY_INFO).axes[0])
    assert "true trunks: 12" in texts
    assert not any("never" in text for text in texts)
    assert "estimated landmarks: 10" in texts


def test_map_draws_the_smoothed_path_when_given():
    example = _example()
    ax = plots.map_figure(example).axes[0]
    assert "smoothed path" not in _legend_texts(ax)
    smoothed = example["mean_pose"] * 0.5
    ax = plots.map_figure({**example, "smoothed_pose": smoothed}).axes[0]
    assert "smoothed path" in _legend_texts(ax)
    line, = [line for line in ax.lines if line.get_label() == "smoothed path"]
    np.testing.assert_allclose(np.stack(line.get_data(), 1), smoothed[:, :2])
    with pytest.raises(ValueError, match=r"smoothed_pose has shape \(39, 3\); expected \(40, 3\)"):
        plots.map_figure({**example, "smoothed_pose": smoothed[1:]})


def test_plot_map_tree_seen_mask_shape(tmp_path):
    example = _example()
    example["tree_seen"] = np.ones(5, bool)
    with pytest.raises(ValueError, match=r"tree_seen has shape \(5,\); expected \(12,\)"):
        plots.plot_map(example, tmp_path / "map2.png")


def test_plot_map_without_landmarks_trees_or_truth(tmp_path):
    example = _example()
    example.update(active=np.zeros(16, bool), tree_centres=np.zeros((0, 2)),
                   tree_radii=np.zeros(0))
    fig = plots.map_figure(example)
    assert _inset(fig.axes[0]) is None
    _assert_png_with_content(plots.plot_map(example, tmp_path / "map.png"))
    example["truth_pose"] = np.zeros((0, 3))  # a robot log without ground truth
    texts = _legend_texts(plots.map_figure(example).axes[0])
    assert "true path" not in texts and "start" in texts


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


# ------------------------------------------------------------------------------------------
# Error against time


def test_error_vs_time_figure_legend_and_units(tmp_path):
    labels = {0: "num_particles=10", 1: "num_particles=50", 2: "num_particles=100"}
    fig = plots.error_vs_time_figure(_traces(), labels, title="Study 'forest': error")
    ax = fig.axes[0]
    assert ax.get_title() == "Study 'forest': error"
    assert _legend_texts(ax) == [f"{label}  (median, 5-95 % band, 4 runs)"
                                 for label in labels.values()]
    assert len(ax.lines) == 3
    _assert_units_on_axes(fig)
    _assert_png_with_content(plots.plot_error_vs_time(_traces(), tmp_path / "err.png", labels))


def test_load_traces_from_study_folder_sorts_and_concatenates(tmp_path):
    traces = _traces(num_runs=12)
    second, first = slice(6, 12), slice(0, 6)
    (tmp_path / "traces").mkdir()
    np.savez(tmp_path / "traces" / "traces-000006-000012.npz",
             **{k: v[second] for k, v in traces.items()})
    np.savez(tmp_path / "traces" / "traces-000000-000006.npz",
             **{k: v[first][::-1] for k, v in traces.items()})
    loaded = plots.load_traces(tmp_path)
    np.testing.assert_array_equal(loaded.run_id, np.arange(12))
    np.testing.assert_array_equal(loaded.pose_error, traces["pose_error"])
    np.testing.assert_array_equal(plots.load_traces(tmp_path / "traces").run_id, np.arange(12))
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


# ------------------------------------------------------------------------------------------
# Sweep boxes


def test_swept_columns_never_guess_a_metric():
    table = _table()
    assert plots.swept_columns(table) == ["num_particles"]
    assert plots.condition_labels(table) == {0: "num_particles=10", 1: "num_particles=50",
                                             2: "num_particles=100"}
    assert plots.condition_labels(table, ["max_range"])[1] == "max_range=20"
    no_sweep = {k: v for k, v in table.items() if k != "num_particles"}
    assert plots.condition_labels(no_sweep)[0] == "condition 0"
    one = {k: v[:1] for k, v in no_sweep.items()}
    assert plots.condition_labels(one) == {0: "all runs"}


def _tick_texts(ax):
    return [label.get_text() for label in ax.get_xticklabels()]


def test_sweep_boxes_label_only_the_swept_settings():
    table = _table()
    fig = plots.sweep_boxes_figure(table, "final_pose_error", sweep=["num_particles"])
    ax = fig.axes[0]
    assert _tick_texts(ax) == ["num_particles=10\n(n=4)", "num_particles=50\n(n=4)",
                               "num_particles=100\n(n=4)"]
    assert ax.get_ylabel() == "final_pose_error [m]"
    assert ax.get_xlabel().startswith("sweep condition: num_particles")
    # guessed from the table alone: still only the swept setting, never mean_mixture_ratio
    guessed = _tick_texts(plots.sweep_boxes_figure(table, "final_pose_error").axes[0])
    assert guessed == _tick_texts(ax)
    with pytest.raises(ValueError, match="no column for the swept setting 'gate'"):
        plots.sweep_boxes_figure(table, "final_pose_error", sweep=["gate"])


def test_sweep_boxes_vector_setting_and_units_from_pyarrow():
    import pyarrow as pa

    table = _table()
    table["range_noise[0]"] = np.array([0.01, 0.02, 0.03])[table["condition"]]
    table["range_noise[1]"] = np.zeros(12)
    fields = [pa.field(name, pa.array(values).type,
                       metadata={"unit": "m"} if name == "final_pose_error" else None)
              for name, values in table.items()]
    arrow = pa.table(table, schema=pa.schema(fields))
    ax = plots.sweep_boxes_figure(arrow, "final_pose_error", sweep=["range_noise"],
                                  title="t").axes[0]
    assert _tick_texts(ax)[1] == "range_noise[0]=0.02\nrange_noise[1]=0\n(n=4)"
    assert ax.get_ylabel() == "final_pose_error [m]"


def test_plot_sweep_boxes_from_pyarrow_and_dict(tmp_path):
    import pyarrow as pa

    table = _table()
    _assert_png_with_content(plots.plot_sweep_boxes(pa.table(table), "final_pose_error",
                                                    tmp_path / "box.png"))
    with pytest.raises(ValueError, match="no 'gospa' column"):
        plots.plot_sweep_boxes(table, "gospa", tmp_path / "box3.png")
    with pytest.raises(TypeError, match="pyarrow.Table"):
        plots.plot_sweep_boxes(42, "final_pose_error", tmp_path / "box4.png")


def test_plot_study_writes_every_plot_without_study_toml(tmp_path):
    import pyarrow as pa
    import pyarrow.parquet as pq

    np.savez(tmp_path / "example_run.npz", **_example())
    (tmp_path / "traces").mkdir()
    (tmp_path / "runs").mkdir()
    np.savez(tmp_path / "traces" / "traces-000000-000012.npz", **_traces())
    pq.write_table(pa.table(_table()), tmp_path / "runs" / "chunk-000000-000012.parquet")
    written = plots.plot_study(tmp_path, metrics=("final_pose_error", "not_a_metric"))
    names = sorted(p.rsplit("/", 1)[-1] for p in written)
    assert names == ["box_final_pose_error.png", "error_vs_time.png", "map.png"]
    for path in written:
        _assert_png_with_content(path)


# ------------------------------------------------------------------------------------------
# A real tiny study: plots and the metrics page

TINY = ['name="plotstudy"', "num_runs=1", "chunk_size=1", "filter.num_particles=4",
        "filter.max_landmarks=8", "filter.max_obs=4", "scenario.num_steps=5",
        "scenario.num_trees=6", "scenario.size=20.0", "sweep.detection_probability=[0.8, 0.9]"]


@pytest.fixture(scope="module")
def tiny_study(tmp_path_factory):
    """One run x two conditions of a 5-step study (~15 s: one simulator, one filter compile)."""
    from jaxslam import studies

    config = studies.load_study_config(None, TINY)
    out = tmp_path_factory.mktemp("plotstudy")
    studies.run_study(config, out, progress=False)
    return config, out, studies.load_results(out)


def test_plot_study_titles_and_labels_of_a_real_study(tiny_study, monkeypatch):
    _, out, _ = tiny_study
    figures = {}
    monkeypatch.setattr(plots.figure, "save_figure",
                        lambda fig, path: figures.setdefault(pathlib.Path(path).name, fig) and path)
    plots.plot_study(out)
    assert sorted(figures) == ["box_ate_rmse.png", "box_final_pose_error.png",
                               "box_gospa.png", "box_map_error.png", "error_vs_time.png",
                               "map.png"]
    map_ax = figures["map.png"].axes[0]
    assert map_ax.get_title().startswith(
        "Study 'plotstudy': example map, run 0 (of 1), condition 0 (detection_probability=0.8)")
    assert any(text.startswith("true trunks measured at some step") for text in
               _legend_texts(map_ax))
    error_ax = figures["error_vs_time.png"].axes[0]
    assert error_ax.get_title() == "Study 'plotstudy': position error over time"
    assert [t.split("  (")[0] for t in _legend_texts(error_ax)] == [
        "detection_probability=0.8", "detection_probability=0.9"]
    box_ax = figures["box_gospa.png"].axes[0]
    assert box_ax.get_title().startswith("Study 'plotstudy': gospa across sweep conditions")
    assert _tick_texts(box_ax) == ["detection_probability=0.8\n(n=1)",
                                   "detection_probability=0.9\n(n=1)"]
    assert box_ax.get_ylabel() == "gospa [m]"
    for fig in figures.values():
        _assert_units_on_axes(fig)


def test_every_study_column_is_known_to_plots(tiny_study):
    """With one run per condition every column is constant within a condition, so the
    guessed sweep is right only if every metric column is known as a non-parameter."""
    config, _, table = tiny_study
    sweep = [name for name, _ in config.sweep]
    assert plots.swept_columns(plots.table_columns(table)) == sweep
    unknown = set(table.column_names) - set(sweep) - plots.NON_SETTING_COLUMNS
    assert not unknown, f"columns plots.py does not know: {sorted(unknown)}"


def _documented_names(text: str) -> set[str]:
    """Names in backticks in the Markdown headings and in the first cell of table rows."""
    names = set()
    for line in text.splitlines():
        if line.startswith("#"):
            names.update(re.findall(r"`([^`]+)`", line))
        elif line.startswith("|"):
            cells = line.split("|")
            if len(cells) > 2:
                names.update(re.findall(r"`([^`]+)`", cells[1]))
    return names


def test_metrics_page_defines_every_column(tiny_study):
    config, _, table = tiny_study
    text = (REPO / "docs" / "metrics.md").read_text()
    documented = _documented_names(text)
    sweep = {name for name, _ in config.sweep}
    missing = sorted(set(table.column_names) - sweep - documented)
    assert not missing, f"docs/metrics.md does not define: {missing}"
    assert any(line.startswith("#") and "swept setting" in line.lower()
               for line in text.splitlines())
    metadata = {key.decode() for key in (table.schema.metadata or {})}
    missing_metadata = sorted(key for key in metadata if f"`{key}`" not in text)
    assert not missing_metadata, f"docs/metrics.md does not explain: {missing_metadata}"
