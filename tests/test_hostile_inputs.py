"""Hostile inputs (the reliability issue's list): each case gets the clear error or the
documented behaviour, asserted exactly.

Cases, by the issue's numbers:

1. Chunk-size independence is not rerun here: ``tests/test_study_determinism.py`` and
   ``tests/test_studies.py::test_results_do_not_depend_on_chunk_size`` cover it.
2. Non-finite controls (refused by ``run_filter`` on concrete arrays, masked and counted under
   ``jit`` of ``scan_filter``) and impossible ``Params`` (``default_params`` and
   ``validation.check_params`` name the field and the allowed range).
3. Wrong units (degrees, millimetres): warned in words by the units guard, by
   ``pipeline.filter_log`` and by ``jaxslam run --data``, which also prints the masked count.
4. Bad config values: ``ValueError`` naming the key and what is expected, and nothing written
   in the output folder; a sweep over a vector parameter loads.
5. A damaged study folder (built here without computing: the manifest checks SHA-256 only):
   a warning naming the file, the file moved to ``damaged/``, its runs pending again; a
   second holder of the lock gets a ``StudyError`` naming the first.
6. Corrupt, truncated, empty and ``.npy`` log files: ``LogFormatError`` naming the file and
   what is expected; no ``allow_pickle=True`` anywhere in the package.
7. Mixed float dtypes with x64 on (``tests/conftest.py``): cast to the controls' dtype at the
   entry of ``run_filter``, and the run finishes; ``scan_filter`` and ``Filter.step`` cast
   params, controls and observations to the state's dtype. (Two processes on one folder:
   case 5.)

Also: ``jaxslam run --data`` on a missing file, a directory or a log with wrong shapes or
dtypes exits with ``cli.EXIT_USAGE`` (2) and one error line naming the file and the field
(then the JAXSLAM_DEBUG hint), no traceback, nothing written.

Every filter run is tiny (P=4, M=8, K=4, T=5) and the runs share four compiled programs:
``scan_filter`` under jit in float32 and float64, ``run_filter`` with lineage in float32
(used by the mixed-dtype run, ``pipeline.filter_log`` and ``jaxslam run --data`` alike) and
in float64.
"""
from __future__ import annotations

import functools
import json
import os
import pathlib
import re
import subprocess
import sys
import warnings

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam import cli, pipeline, studies, study_store, validation
from jaxslam.datasets.log_format import LogFormatError, RobotLog, load_log, save_log
from jaxslam.filter import make_filter, run_filter, scan_filter
from jaxslam.types import FilterConfig, default_params, make_observations

F32, F64 = jnp.float32, jnp.float64
T, K = 5, 4
CONFIG = FilterConfig(num_particles=4, max_landmarks=8, max_obs=K)
KEY = jax.random.PRNGKey(0)
STEP = 0.4  # [m] forward move per step
TREES = np.array([[2.0, 3.0], [3.0, -3.0], [4.0, 2.5], [5.0, -2.0]])  # [m], all to the side
EXPECTED_FILE = "expected a .npz archive written by numpy.savez"
TINY_STUDY = ["num_runs=2", "chunk_size=1", "filter.num_particles=4", "filter.max_landmarks=8",
              "filter.max_obs=4", "scenario.num_steps=5", "scenario.num_trees=6",
              "scenario.size=20.0"]


def drive():
    """Noise-free (z (T, K, 2) [m, rad], controls (T, 3) odometry) of a drive along +x past
    ``TREES`` (every tree within 20 m, none ahead: every bearing is beyond 3 degrees)."""
    x = STEP * np.arange(1, T + 1)
    offset = TREES[None] - np.stack([x, np.zeros(T)], -1)[:, None]
    z = np.stack([np.hypot(offset[..., 0], offset[..., 1]),
                  np.arctan2(offset[..., 1], offset[..., 0])], -1)
    return z, np.tile([0.0, STEP, 0.0], (T, 1))


def inputs(control_dtype=F32, obs_dtype=F32):
    z, controls = drive()
    return (jnp.asarray(controls, control_dtype),
            make_observations(jnp.asarray(z, obs_dtype)))


def robot_log(bearing_scale=1.0, range_scale=1.0) -> RobotLog:
    """The drive as a log; the scales turn it into degrees or millimetres."""
    z, controls = drive()
    z = z * [range_scale, bearing_scale]
    return RobotLog(time=np.arange(T, dtype=float), motion_model="odometry",
                    controls=controls, obs_z=z, obs_valid=np.ones((T, K), bool))


def floats_finite(tree) -> bool:
    return all(bool(jnp.all(jnp.isfinite(leaf))) for leaf in jax.tree.leaves(tree)
               if jnp.issubdtype(leaf.dtype, jnp.floating))


@pytest.fixture
def cli_env(tmp_path, monkeypatch):
    """The CLI with its compilation cache in ``tmp_path`` (reset afterwards), no debug mode."""
    monkeypatch.setenv("JAXSLAM_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.delenv("JAXSLAM_DEBUG", raising=False)
    yield
    jax.config.update("jax_compilation_cache_dir", None)


def usage_error(capsys, argv) -> str:
    """Run ``jaxslam ARGV``; assert exit 2 and a one-line error without traceback; return it."""
    status = cli.main(argv)
    captured = capsys.readouterr()
    assert status == cli.EXIT_USAGE == 2, captured
    lines = captured.err.splitlines()
    assert lines[0].startswith(f"jaxslam {argv[0]}: error: "), lines
    assert lines[1:] == ["(set JAXSLAM_DEBUG=1 for the traceback)"], lines
    assert "Traceback" not in captured.err + captured.out
    return lines[0]


# --------------------------------------------------------------------------------------------
# 2. Non-finite controls and impossible Params


@pytest.mark.parametrize("bad, shown", [(np.nan, "nan"), (np.inf, "inf"), (-np.inf, "-inf")])
def test_run_filter_names_the_non_finite_control_row(bad, shown):
    controls, obs = inputs()
    controls = controls.at[2, 0].set(bad)
    # The row in its own dtype: float32 0.4 reads 0.4, not 0.4000000059604645.
    message = (f"controls row 2 is [{shown}, 0.4, 0.0] (1 of 5 rows hold NaN or inf); "
               "expected finite controls in every row")
    with pytest.raises(ValueError, match=re.escape(message)):
        run_filter(CONFIG, KEY, default_params(), controls, obs)


@functools.lru_cache(maxsize=None)
def jitted_scan():
    return jax.jit(functools.partial(scan_filter, CONFIG))


def test_jitted_scan_filter_masks_and_counts_non_finite_controls():
    controls, obs = inputs()
    state = make_filter(CONFIG).init(jnp.zeros(3, F32), dtype=F32)
    dirty = controls.at[1, 1].set(jnp.nan).at[3, 0].set(jnp.inf)
    final, trace = jitted_scan()(KEY, state, default_params(), dirty, obs)
    np.testing.assert_array_equal(trace.invalid_control, [False, True, False, True, False])
    assert int(trace.invalid_control.sum()) == 2
    assert floats_finite(final.particles) and floats_finite(trace.mean_pose)
    # The same compiled program on clean controls masks nothing.
    _, clean = jitted_scan()(KEY, state, default_params(), controls, obs)
    assert int(clean.invalid_control.sum()) == 0


# (override, the bad value as check_params shows it, the allowed range)
BAD_PARAMS = [
    (dict(rot1_noise=(-0.1, 0.06, 0.0)), "rot1_noise=-0.1 (component 0)", "a finite value >= 0"),
    (dict(trans_noise=(0.02, np.nan, 0.0)), "trans_noise=nan (component 1)",
     "a finite value >= 0"),
    (dict(range_noise=(np.nan, 0.0)), "range_noise=nan (component 0)", "a finite value >= 0"),
    (dict(association_gate=np.nan), "association_gate=nan", "a finite value > 0"),
    (dict(max_range=np.nan), "max_range=nan", "a finite value > 0"),
    (dict(max_range=-5.0), "max_range=-5.0", "a finite value > 0"),
    (dict(ess_threshold=np.nan), "ess_threshold=nan", "a value in [0, 1]"),
    (dict(mixture_ratio=np.nan), "mixture_ratio=nan", "a value in [0, 1]"),
    (dict(mixture_ratio=1.5), "mixture_ratio=1.5", "a value in [0, 1]"),
    (dict(detection_probability=1.5), "detection_probability=1.5", "a value in (0, 1]"),
    (dict(radius_noise=-0.1), "radius_noise=-0.1", "a finite value >= 0"),
]


@pytest.mark.parametrize("override, bad, allowed", BAD_PARAMS,
                         ids=[bad.split(" ")[0] for _, bad, _ in BAD_PARAMS])
def test_impossible_params_name_the_field_and_the_range(override, bad, allowed):
    with pytest.raises(ValueError, match=re.escape(
            f"default_params.{bad} is invalid; expected {allowed}")):
        default_params(**override)
    (name, value), = override.items()
    params = default_params()._replace(**{name: jnp.asarray(value, F32)})
    with pytest.raises(ValueError, match=re.escape(f"Params.{bad} is invalid; expected {allowed}")):
        validation.check_params(params)


# --------------------------------------------------------------------------------------------
# 3. Wrong units: warned in words; the masked count printed


DEGREES = "bearings look like degrees: 20 of 20 (100%) have |bearing| > pi"
ALL_MALFORMED = ("all 20 observations marked valid are malformed (0 NaN or inf, 0 with a "
                 "range <= 0, 20 with a bearing outside [-pi, pi]) and will be masked")
EXPECTED_UNITS = "expected ranges in metres and bearings in radians in [-pi, pi]"
REFUSING = " -- refusing to run on these observations"


def test_units_guard_names_degrees_and_millimetres():
    log = robot_log(bearing_scale=180.0 / np.pi)
    degrees, malformed = validation.observation_units_warnings(log.obs_z, log.obs_valid)
    assert degrees.startswith(DEGREES) and EXPECTED_UNITS in degrees, degrees
    assert "(multiply degrees by pi/180)" in degrees
    assert malformed.startswith(ALL_MALFORMED), malformed
    with pytest.raises(ValueError) as refused:  # certain: refused, with the same words
        validation.check_observation_units(log.obs_z, log.obs_valid)
    assert str(refused.value) == f"{degrees}; {malformed}{REFUSING}"

    log = robot_log(range_scale=1000.0)
    (warning,) = validation.observation_units_warnings(log.obs_z, log.obs_valid)
    median = np.median(drive()[0][..., 0]) * 1000.0  # 3552 m: within 1-100 m in mm and cm
    assert warning.startswith(f"ranges look wrong: the median valid range is {median:.4g} m"), \
        warning
    assert (f"these look like millimetres (median {median / 1000:.3g} m) or centimetres "
            f"(median {median / 100:.3g} m); {EXPECTED_UNITS}") in warning
    with pytest.raises(ValueError) as refused:  # median above 1000 m: refused
        validation.check_observation_units(log.obs_z, log.obs_valid)
    assert str(refused.value) == warning + REFUSING


def test_filter_log_warns_about_degrees_and_counts_the_masked_rows():
    run = pipeline.filter_log(robot_log(bearing_scale=180.0 / np.pi), CONFIG, default_params(),
                              KEY, calibrate=False)
    assert run.warnings[0].startswith(DEGREES), run.warnings
    assert run.warnings[1].startswith(ALL_MALFORMED), run.warnings
    # Every bearing is beyond pi in degrees: all T * K = 20 rows are masked and counted.
    assert run.metrics["invalid_observations"] == T * K
    assert run.warnings[2].startswith(f"{T * K} observations were masked as invalid"), \
        run.warnings


def test_filter_log_warns_about_millimetres():
    run = pipeline.filter_log(robot_log(range_scale=1000.0), CONFIG, default_params(), KEY,
                              calibrate=False)
    assert run.warnings[0].startswith("ranges look wrong"), run.warnings
    assert "millimetres" in run.warnings[0]
    assert run.metrics["invalid_observations"] == 0  # far, not malformed: ignored, not masked


def test_jaxslam_run_prints_the_units_warning_and_the_masked_count(tmp_path, cli_env, capsys):
    save_log(tmp_path / "degrees.npz", robot_log(bearing_scale=180.0 / np.pi))
    status = cli.main(["run", "--data", str(tmp_path / "degrees.npz"), "--no-calibrate",
                       "--out", str(tmp_path / "out"), "--set", "filter.num_particles=4",
                       "--set", "filter.max_landmarks=8"])
    out = capsys.readouterr().out
    assert status == 0
    assert f"WARNING: {DEGREES}" in out
    assert f"WARNING: {T * K} observations were masked as invalid" in out
    assert re.search(rf"^invalid_observations\s+{T * K}$", out, re.MULTILINE), out
    saved = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert saved["metrics"]["invalid_observations"] == T * K
    assert saved["warnings"][0].startswith(DEGREES)


# --------------------------------------------------------------------------------------------
# 4. Config values: refused by key, nothing written


BAD_CONFIG = [
    ('scenario.num_steps="20"', "study config scenario.num_steps='20' is invalid; expected a "
     "positive integer (>= 1) (a string: write numbers without quotes)"),
    ('params.max_range="far"', "study config params.max_range='far' is invalid; expected a "
     "number (or, for a vector field, a list of numbers)"),
    ("seed=1.5", "study config seed=1.5 is invalid; expected an integer >= 0"),
    ("seed=2.0", "study config seed=2.0 is invalid; expected an integer >= 0"),
    ("scenario.num_steps=0", "study config scenario.num_steps=0 is invalid; expected a positive "
     "integer (>= 1)"),
    ("scenario.num_steps=-3", "study config scenario.num_steps=-3 is invalid; expected a "
     "positive integer (>= 1)"),
    ("scenario.num_trees=0", "study config scenario.num_trees=0 is invalid; expected a positive "
     "integer (>= 1)"),
    ("params.rot1_noise=0.1", "study config params.rot1_noise=0.1 is refused: "
     "default_params.rot1_noise has shape () (value 0.1); expected shape (3,), coefficients "
     "(trans, rot, const)"),
    ("num_runs.x=5", "override 'num_runs.x=5': 'num_runs' is not a section of a study config; "
     "write key=value for a study setting or section.key=value with a section in ['filter', "
     "'scenario', 'params', 'sweep']"),
]


@pytest.mark.parametrize("override, message", BAD_CONFIG, ids=[o for o, _ in BAD_CONFIG])
def test_bad_config_value_is_refused_by_key_before_any_write(override, message, tmp_path,
                                                             cli_env, capsys):
    with pytest.raises(ValueError, match=re.escape(message)):
        studies.load_study_config(None, TINY_STUDY + [override])
    config_file = tmp_path / "study.toml"
    config_file.write_text("num_runs = 2\n")
    out = tmp_path / "out"
    line = usage_error(capsys, ["study", str(config_file), "--out", str(out), "--quiet",
                                "--set", override])
    assert line == f"jaxslam study: error: {message}"
    assert not out.exists()


def test_bad_value_in_the_config_file_is_refused_before_any_write(tmp_path, cli_env, capsys):
    config_file = tmp_path / "study.toml"
    config_file.write_text('num_runs = 2\n[scenario]\nnum_steps = "20"\n')
    out = tmp_path / "out"
    line = usage_error(capsys, ["study", str(config_file), "--out", str(out), "--quiet"])
    assert "scenario.num_steps='20' is invalid; expected a positive integer" in line
    assert not out.exists()


def test_sweep_over_a_vector_parameter_loads_into_two_conditions():
    config = studies.load_study_config(
        None, TINY_STUDY + ["sweep.rot1_noise=[[0.0,0.06,0.0002],[0.0,0.12,0.0004]]"])
    assert config.conditions == [{"rot1_noise": [0.0, 0.06, 0.0002]},
                                 {"rot1_noise": [0.0, 0.12, 0.0004]}]
    stacked = studies.condition_params(config).rot1_noise
    chex.assert_shape(stacked, (2, 3))
    # Exact: the float32 values of the config's numbers (tolerance 0).
    np.testing.assert_array_equal(
        stacked, np.asarray([[0.0, 0.06, 0.0002], [0.0, 0.12, 0.0004]], np.asarray(stacked).dtype))


# --------------------------------------------------------------------------------------------
# 5. A damaged study folder; a second lock holder


def study_folder(tmp_path):
    """A study folder of two finished one-run chunks, written without computing: the files
    hold placeholder arrays (verification compares SHA-256 with the manifest only)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    config = studies.load_study_config(None, TINY_STUDY)
    out = tmp_path / "study"
    assert studies.open_study(config, out) == [(0, 1), (1, 2)]
    written = []
    for start in (0, 1):
        chunk = study_store.chunk_path(out, start, start + 1)
        chunk.parent.mkdir(parents=True, exist_ok=True)
        pq.write_table(pa.table({"run_id": [start], "condition": [0],
                                 "final_pose_error": [0.1 * (start + 1)]}), chunk)
        traces = study_store.traces_path(out, start, start + 1)
        traces.parent.mkdir(parents=True, exist_ok=True)
        np.savez(traces, run_id=[start], condition=[0], pose_error=np.zeros((1, 5)))
        written += [chunk, traces]
    np.savez(out / "example_run.npz", mean_pose=np.zeros((5, 3)))
    study_store.record_files(out, written + [out / "example_run.npz"])
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # an intact folder: no warning, nothing pending
        assert studies.open_study(config, out) == []
    return config, out


def _flip_one_bit(path):
    content = bytearray(path.read_bytes())
    content[len(content) // 2] ^= 0x04
    path.write_bytes(bytes(content))


DAMAGE = {
    "chunk-one-flipped-bit": ("runs/chunk-000001-000002.parquet", _flip_one_bit,
                              "runs/chunk-000001-000002.parquet changed since it was written "
                              "(checksum mismatch)"),
    "traces-truncated": ("traces/traces-000001-000002.npz",
                         lambda p: p.write_bytes(p.read_bytes()[:100]),
                         "traces/traces-000001-000002.npz changed since it was written "
                         "(checksum mismatch)"),
    "traces-deleted": ("traces/traces-000001-000002.npz", pathlib.Path.unlink,
                       "traces/traces-000001-000002.npz is missing"),
}


@pytest.mark.parametrize("damage", list(DAMAGE))
def test_damaged_chunk_is_named_moved_aside_and_pending_again(damage, tmp_path):
    config, out = study_folder(tmp_path)
    name, spoil, reason = DAMAGE[damage]
    spoil(out / name)
    with pytest.warns(UserWarning) as record:
        pending = studies.open_study(config, out)
    assert pending == [(1, 2)]
    message = "\n".join(str(w.message) for w in record)
    assert "moved to damaged/ and computing again" in message
    assert f"runs/chunk-000001-000002.parquet and its traces ({reason})" in message, message
    moved = sorted(p.name.split(".", 1)[0] for p in (out / "damaged").iterdir())
    expected = ["chunk-000001-000002"] + ([] if damage == "traces-deleted"
                                          else ["traces-000001-000002"])
    assert moved == expected
    assert not (out / "runs/chunk-000001-000002.parquet").exists()
    assert (out / "runs/chunk-000000-000001.parquet").exists()  # the intact chunk stays


def test_a_second_process_on_the_study_folder_is_refused(tmp_path):
    config, out = study_folder(tmp_path)
    holder = subprocess.Popen(
        [sys.executable, "-c", "import fcntl, sys, time; f = open(sys.argv[1], 'a+'); "
         "fcntl.flock(f, fcntl.LOCK_EX); f.seek(0); f.truncate(); f.write('pid 4242 on rig'); "
         "f.flush(); print('locked', flush=True); time.sleep(60)", str(out / study_store.LOCK)],
        stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "locked"
        with pytest.raises(studies.StudyError, match=re.escape(
                f"{out} is in use by another study process (pid 4242 on rig)")):
            with study_store.study_lock(out):
                pass
    finally:
        holder.kill()
        holder.wait()
        holder.stdout.close()
    # In one process too: a second holder is refused and named; the lock is free afterwards.
    with study_store.study_lock(out):
        with pytest.raises(studies.StudyError, match=re.escape(f"(pid {os.getpid()} on ")):
            with study_store.study_lock(out):
                pass
    with study_store.study_lock(out):
        assert studies.open_study(config, out) == []


# --------------------------------------------------------------------------------------------
# 6. Unreadable log files


def _good_log_bytes(tmp_path) -> bytes:
    save_log(tmp_path / "good.npz", robot_log())
    return (tmp_path / "good.npz").read_bytes()


def _flip_middle_bit(content: bytes) -> bytes:
    content = bytearray(content)
    content[len(content) // 2] ^= 0x10
    return bytes(content)


def _write(name, content):
    def write(tmp_path):
        path = tmp_path / name
        path.write_bytes(content(tmp_path) if callable(content) else content)
        return path
    return write


def _pickled(tmp_path):
    path = tmp_path / "pickled.npz"
    arrays = {k: v for k, v in robot_log()._asdict().items() if v is not None}
    arrays["meta_ok"] = np.zeros(1)
    np.savez(path, **{**arrays, "truth_landmarks": np.array([{"tree": 1}], dtype=object)})
    return path


BAD_FILES = {
    "corrupt": (_write("corrupt.npz", b"hello, this is not an archive" * 4),
                "cannot read as a .npz archive: it is not a zip file (starts with b'hello,'"),
    "truncated": (_write("truncated.npz", lambda d: _good_log_bytes(d)[:300]),
                  "cannot read as a .npz archive, it is truncated or corrupt"),
    "flipped-bit": (_write("flipped.npz", lambda d: _flip_middle_bit(_good_log_bytes(d))),
                    "cannot read as a .npz archive"),
    "empty": (_write("empty.npz", b""), "the file is empty (0 bytes)"),
    "npy": (lambda d: (np.save(d / "single.npy", np.zeros((5, 3))), d / "single.npy")[1],
            "it is a single .npy array (numpy.save), not an archive of named arrays"),
    "pickled-array": (_pickled, "key 'truth_landmarks' is an object array that needs pickle, "
                                "which load_log never enables"),
    "missing": (lambda d: d / "missing.npz", "no such file"),
    "directory": (lambda d: d, "is a directory, not a file"),
}


@pytest.mark.parametrize("case", list(BAD_FILES))
def test_unreadable_log_file_names_the_file_and_what_is_expected(case, tmp_path):
    make, words = BAD_FILES[case]
    path = make(tmp_path)
    with pytest.raises(LogFormatError) as error:
        load_log(path)
    message = str(error.value)
    assert message.startswith(f"{path}: "), message
    assert words in message and EXPECTED_FILE in message, message


def test_no_allow_pickle_true_in_the_package():
    package = pathlib.Path(validation.__file__).resolve().parents[1]  # jaxslam/
    sources = sorted(package.rglob("*.py"))
    assert len(sources) > 20  # the package itself, not an empty folder
    pattern = re.compile(r"allow_pickle\s*=\s*True")
    offenders = [str(p.relative_to(package)) for p in sources if pattern.search(p.read_text())]
    assert offenders == []


# --------------------------------------------------------------------------------------------
# `jaxslam run --data` on what is not a usable log


def _log_with(field, value):
    def write(tmp_path):
        arrays = {k: v for k, v in robot_log()._asdict().items() if v is not None}
        arrays[field] = value
        np.savez(tmp_path / f"bad_{field}.npz", **arrays)
        return tmp_path / f"bad_{field}.npz"
    return write


BAD_DATA = {
    "missing": (lambda d: d / "missing.npz", "no such file"),
    "directory": (lambda d: d, "is a directory, not a file"),
    "controls-shape": (_log_with("controls", np.zeros((T, 2))),
                       "'controls' has shape (5, 2); expected (5, 3)"),
    "obs_z-steps": (_log_with("obs_z", np.ones((T + 1, K, 2))),
                    "'obs_z' has shape (6, 4, 2); expected (5, *, 2)"),
    "obs_valid-shape": (_log_with("obs_valid", np.ones((T, K + 1), bool)),
                        "'obs_valid' has shape (5, 5); expected (5, 4)"),
    # These three raised a bare TypeError / ValueError (a traceback) or were cast silently
    # before log_format checked them.
    "format_version-vector": (_log_with("format_version", np.asarray([1, 1])),
                              "'format_version' is [1, 1] (shape (2,), dtype int64); expected "
                              "the integer scalar 1"),
    "format_version-text": (_log_with("format_version", np.asarray("v1")),
                            "'format_version' is 'v1' (shape (), dtype <U2); expected the "
                            "integer scalar 1"),
    "controls-complex": (_log_with("controls", np.zeros((T, 3)) + 1j),
                         "'controls' is not numeric (dtype complex128); expected a float array"),
    "empty-file": (_write("empty.npz", b""), "the file is empty (0 bytes)"),
}


@pytest.mark.parametrize("case", list(BAD_DATA))
def test_jaxslam_run_data_refuses_a_bad_log_in_one_line(case, tmp_path, cli_env, capsys):
    make, words = BAD_DATA[case]
    path = make(tmp_path)
    out = tmp_path / "out"
    line = usage_error(capsys, ["run", "--data", str(path), "--no-calibrate", "--out", str(out)])
    assert line.startswith(f"jaxslam run: error: {path}: {words}"), line
    assert not out.exists()


# --------------------------------------------------------------------------------------------
# 7. Mixed float dtypes (x64 on): cast to the controls' dtype at the entry


@pytest.mark.parametrize("control_dtype, other_dtype", [(F32, F64), (F64, F32)],
                         ids=["f32-controls-f64-rest", "f64-controls-f32-rest"])
def test_mixed_float_dtypes_run_in_the_controls_dtype(control_dtype, other_dtype):
    assert jax.config.jax_enable_x64  # tests/conftest.py
    controls, obs = inputs(control_dtype, other_dtype)
    params = default_params(dtype=other_dtype)
    final, trace = run_filter(CONFIG, KEY, params, controls, obs,
                              initial_pose=jnp.zeros(3, other_dtype), record_lineage=True)
    chex.assert_type([trace.mean_pose, trace.best_pose, final.particles.pose], control_dtype)
    assert floats_finite(final) and floats_finite(trace.mean_pose)
    assert int(trace.invalid_control.sum()) == 0 and int(trace.num_invalid_obs.sum()) == 0
    # Noise-free drive: the estimate ends at the truth within 0.1 m, about 5 std of the
    # 0.018 m that the Table 1 odometry noise accumulates over five 0.4 m moves.
    np.testing.assert_allclose(np.asarray(trace.mean_pose[-1, :2], np.float64),
                               [STEP * T, 0.0], rtol=0, atol=0.1)


@pytest.mark.parametrize("state_dtype, other_dtype", [
    pytest.param(F32, F64, id="f32-state-f64-rest"),
    pytest.param(F64, F32, id="f64-state-f32-rest"),
])
def test_jitted_scan_filter_with_mixed_dtypes_runs_in_the_state_dtype(state_dtype, other_dtype):
    controls, obs = inputs(state_dtype, other_dtype)
    state = make_filter(CONFIG).init(jnp.zeros(3, state_dtype), dtype=state_dtype)
    final, trace = jitted_scan()(KEY, state, default_params(dtype=other_dtype), controls, obs)
    chex.assert_type([trace.mean_pose, final.particles.pose], state_dtype)
    assert floats_finite(final) and floats_finite(trace.mean_pose)
