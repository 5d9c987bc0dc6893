"""Host-side validation (issue 18): every Params rule (through default_params and
check_params), stacked sweeps, tracers skipped, controls, run_filter's entry checks and dtype
casting, and load_log on files that are not readable .npz logs."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam.datasets import log_format as lf
from jaxslam.filter import run_filter
from jaxslam.types import FilterConfig, Params, default_params, make_observations
from jaxslam.validation import FIELD_SHAPES, cast_floating, check_controls, check_params

NAN, INF = float("nan"), float("inf")

# (field, bad value, other overrides): each must raise ValueError naming ``field``.
BAD = [
    # shapes: a scalar for a vector field, a wrong length
    ("rot1_noise", 0.1, {}),
    ("trans_noise", (0.1, 0.2), {}),
    ("rot2_noise", (0.0, 0.1, 0.2, 0.3), {}),
    ("range_noise", 0.01, {}),
    ("bearing_noise", (0.1, 0.2, 0.3), {}),
    # motion noise
    ("rot1_noise", (0.0, -0.06, 0.0), {}),
    ("trans_noise", (0.02, NAN, 0.0), {}),
    ("rot2_noise", (INF, 0.06, 0.0), {}),
    ("min_translation", 0.0, {}),
    ("min_translation", -0.01, {}),
    ("odometry_gain", 0.9, {}),
    ("odometry_gain", (0.9, 0.0), {}),
    ("odometry_gain", (NAN, 1.0), {}),
    ("min_translation", NAN, {}),
    ("wheelbase", 0.0, {}),
    ("wheelbase", NAN, {}),
    ("encoder_offset", NAN, {}),
    ("laser_forward", INF, {}),
    ("laser_left", -INF, {}),
    # observation noise
    ("range_noise", (-0.005, 0.0), {}),
    ("bearing_noise", (0.0005, NAN), {}),
    ("range_std_floor", -0.01, {}),
    ("bearing_std_floor", NAN, {}),
    ("radius_noise", -0.05, {}),
    ("radius_noise", INF, {}),
    ("range_noise", (0.01, 0.0), {"range_std_floor": 0.0}),  # zero std at distance 0
    ("bearing_noise", (0.001, 0.0), {"bearing_std_floor": 0.0}),
    # sensor
    ("max_range", NAN, {}),
    ("max_range", -1.0, {}),
    ("max_range", 0.0, {}),
    ("max_range", INF, {}),
    ("min_range", -0.1, {}),
    ("min_range", NAN, {}),
    ("min_range", 20.0, {}),  # not below max_range 20
    ("miss_range", NAN, {}),
    ("miss_range", -1.0, {}),
    ("miss_range", -INF, {}),
    ("miss_bearing", 0.0, {}),
    ("motion_outlier_probability", 1.0, {}),
    ("motion_outlier_probability", -0.1, {}),
    ("motion_outlier_probability", NAN, {}),
    ("motion_outlier_scale", 0.0, {}),
    ("motion_outlier_scale", NAN, {}),
    ("miss_bearing", NAN, {}),
    ("miss_bearing", INF, {}),
    # association and map management
    ("association_gate", NAN, {}),
    ("association_gate", 0.0, {}),
    ("association_gate", -9.0, {}),
    ("association_gate", INF, {}),
    ("association_heading_std", NAN, {}),
    ("association_heading_std", -0.1, {}),
    ("association_heading_std", INF, {}),
    ("new_landmark_log_offset", NAN, {}),
    ("detection_probability", 1.5, {}),
    ("detection_probability", 0.0, {"false_alarm_probability": 0.0}),
    ("detection_probability", NAN, {}),
    ("false_alarm_probability", 1.0, {"detection_probability": 1.0}),
    ("false_alarm_probability", -0.1, {}),
    ("false_alarm_probability", NAN, {}),
    ("false_alarm_probability", 0.95, {}),  # above detection_probability 0.9
    ("existence_init", NAN, {}),
    ("existence_init", -2.0, {}),  # not above existence_delete -1.5
    ("existence_delete", INF, {}),
    ("existence_delete", -6.0, {}),  # not above -existence_max: nothing would be deleted
    ("existence_max", 0.0, {}),
    ("existence_max", NAN, {}),
    ("airlock_sigmas", -1.0, {}),
    ("airlock_sigmas", NAN, {}),
    # resampling and mixture proposal
    ("ess_threshold", 1.5, {}),
    ("ess_threshold", -0.1, {}),
    ("ess_threshold", NAN, {}),
    ("mixture_ratio", 1.5, {}),
    ("mixture_ratio", -0.1, {}),
    ("mixture_ratio", NAN, {}),
    ("mixture_min", 1.2, {}),
    ("mixture_min", 0.95, {"mixture_max": 0.9}),  # above mixture_max
    ("mixture_max", NAN, {}),
    ("likelihood_rate_fast", 1.5, {}),
    ("likelihood_rate_slow", -0.1, {}),
]


def _id(case):
    field, value, extra = case
    return f"{field}={value}" + ("+" + ",".join(extra) if extra else "")


@pytest.mark.parametrize("case", BAD, ids=[_id(c) for c in BAD])
def test_default_params_refuses(case):
    field, value, extra = case
    with pytest.raises(ValueError, match=rf"default_params\.{field}\b") as error:
        default_params(**extra, **{field: value})
    assert "expected" in str(error.value)


@pytest.mark.parametrize("case", BAD, ids=[_id(c) for c in BAD])
def test_check_params_refuses(case):
    """The same rules on a Params built by hand (as ``_replace`` would), float64 too."""
    field, value, extra = case
    params = default_params(dtype=jnp.float64)
    params = params._replace(**{name: jnp.asarray(v, jnp.float64)
                                for name, v in {**extra, field: value}.items()})
    with pytest.raises(ValueError, match=rf"Params\.{field}\b"):
        check_params(params)


def test_every_field_has_a_bad_case():
    assert {field for field, _, _ in BAD} == set(Params._fields)


def test_messages_name_value_and_expectation():
    with pytest.raises(ValueError, match=r"rot1_noise has shape \(\).*expected shape \(3,\)"):
        default_params(rot1_noise=0.1)
    with pytest.raises(ValueError, match=r"mixture_ratio=1\.5 is invalid; expected a value in "
                                         r"\[0, 1\]"):
        default_params(mixture_ratio=1.5)
    with pytest.raises(ValueError, match=r"trans_noise=-0\.2 \(component 1\)"):
        default_params(trans_noise=(0.02, -0.2, 0.0))
    with pytest.raises(ValueError, match=r"min_range=30\.0 and default_params\.max_range=20\.0"):
        default_params(min_range=30.0)


def test_scalar_field_given_a_tuple_is_refused_by_default_params():
    with pytest.raises(ValueError, match=r"default_params\.max_range has shape \(2,\)"):
        default_params(max_range=(10.0, 20.0))


@pytest.mark.parametrize("value", [jnp.asarray(True), jnp.asarray(1.0 + 2.0j), "20"])
def test_non_real_leaf_is_refused(value):
    with pytest.raises(ValueError, match=r"Params\.max_range.*expected a real number"):
        check_params(default_params()._replace(max_range=value))


def test_not_params_is_a_type_error():
    with pytest.raises(TypeError, match="Params"):
        check_params(dict(max_range=1.0))


# ------------------------------------------------------------------------------- valid values

EDGES = [
    dict(),
    dict(ess_threshold=0.0), dict(ess_threshold=1.0), dict(ess_threshold=1),
    dict(mixture_ratio=0.0), dict(mixture_ratio=1.0),
    dict(mixture_min=0.0, mixture_max=1.0), dict(mixture_min=0.5, mixture_max=0.5),
    dict(detection_probability=1.0), dict(false_alarm_probability=0.0),
    dict(detection_probability=0.5, false_alarm_probability=0.5),
    dict(miss_range=INF), dict(miss_range=0.0), dict(miss_range=12.0),
    dict(airlock_sigmas=0.0), dict(radius_noise=0.0), dict(radius_noise=0.05),
    dict(min_range=0.0), dict(likelihood_rate_fast=1.0, likelihood_rate_slow=0.0),
    dict(rot1_noise=(0.0, 0.0, 0.0), trans_noise=(0.0, 0.0, 0.0), rot2_noise=(0.0, 0.0, 0.0)),
    dict(range_noise=(0.0, 0.1), range_std_floor=0.0),
    dict(encoder_offset=-0.76, laser_left=-0.5, new_landmark_log_offset=-3.0),
    dict(association_gate=100.0, existence_init=-1.0),
]


@pytest.mark.parametrize("overrides", EDGES, ids=[str(e) for e in EDGES])
@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_valid_edges_pass(overrides, dtype):
    params = default_params(dtype=dtype, **overrides)
    check_params(params)
    check_params(params, allow_batch=False)


def test_library_parameter_sets_pass():
    from experiments.victoria_park_pipeline import CALIBRATED, LEGACY, victoria_park_params

    check_params(victoria_park_params(settings=LEGACY))
    check_params(victoria_park_params(settings=CALIBRATED))
    check_params(default_params()._replace(max_range=20.0, miss_range=np.float32(5.0)))


def _stack(*params):
    return jax.tree.map(lambda *leaves: jnp.stack(leaves), *params)


def test_stacked_sweep_params_pass_and_name_the_condition():
    stacked = _stack(default_params(), default_params(mixture_ratio=1.0),
                     default_params(trans_noise=(0.2, 0.006, 0.00003)))
    assert stacked.rot1_noise.shape == (3, 3) and stacked.max_range.shape == (3,)
    check_params(stacked)
    # Two sweep axes (a grid of conditions) too.
    check_params(_stack(stacked, stacked))
    with pytest.raises(ValueError, match=r"mixture_ratio=1\.5 \(sweep condition \(1,\)\)"):
        check_params(stacked._replace(mixture_ratio=stacked.mixture_ratio.at[1].set(1.5)))
    with pytest.raises(ValueError, match=r"range_noise=-1\.0 \(sweep condition \(2,\), "
                                         r"component 0\)"):
        check_params(stacked._replace(range_noise=stacked.range_noise.at[2, 0].set(-1.0)))
    with pytest.raises(ValueError, match=r"min_range.*sweep condition \(0,\)"):
        check_params(stacked._replace(min_range=jnp.asarray([25.0, 0.1, 0.1])))
    # A stacked vector field with the wrong trailing shape.
    with pytest.raises(ValueError, match=r"Params\.rot1_noise has shape \(3, 2\)"):
        check_params(stacked._replace(rot1_noise=stacked.rot1_noise[:, :2]))
    # default_params builds one condition: no batch axes there.
    with pytest.raises(ValueError, match="has shape"):
        check_params(stacked, allow_batch=False)


def test_vmapped_sweep_runs_and_tracers_are_skipped():
    stacked = _stack(default_params(), default_params(association_gate=16.0))

    def gate(params):
        check_params(params)  # tracers under vmap: skipped
        return params.association_gate * 2.0

    np.testing.assert_allclose(np.asarray(jax.vmap(gate)(stacked)), [50.0, 32.0])


def test_check_params_is_silent_inside_jit():
    bad = default_params()._replace(association_gate=jnp.float32(NAN),
                                    mixture_ratio=jnp.float32(1.5),
                                    rot1_noise=jnp.float32(0.1))

    @jax.jit
    def traced(params):
        check_params(params)
        check_params(params, allow_batch=False)
        return params.association_gate

    assert np.isnan(float(traced(bad)))
    # default_params with a traced override: the override is skipped, the rest checked.
    gates = jax.vmap(lambda g: default_params(association_gate=g).association_gate)(
        jnp.asarray([9.0, 25.0]))
    np.testing.assert_allclose(np.asarray(gates), [9.0, 25.0])


def test_partly_traced_params_still_check_concrete_fields():
    concrete = default_params()  # built outside jit (inside, jnp ops give tracers)

    def f(gate):
        params = concrete._replace(association_gate=gate, max_range=np.float32(-1.0))
        check_params(params)
        return gate

    with pytest.raises(ValueError, match=r"Params\.max_range=-1\.0"):
        jax.jit(f)(jnp.float32(25.0))


def test_field_shapes_match_defaults():
    params = default_params()
    assert {name: getattr(params, name).shape for name in Params._fields} == FIELD_SHAPES


# ---------------------------------------------------------------------------------- controls


def test_check_controls():
    good = np.zeros((4, 3), np.float32)
    check_controls(good)
    check_controls(good, num_steps=4)
    with pytest.raises(ValueError, match=r"\(T, 3\)"):
        check_controls(good[:, :2])
    with pytest.raises(ValueError, match=r"\(T, 3\)"):
        check_controls(good[0])
    with pytest.raises(ValueError, match=r"T = 5"):
        check_controls(good, num_steps=5)
    with pytest.raises(ValueError, match="dtype int"):
        check_controls(np.zeros((4, 3), np.int32))
    bad = good.copy()
    bad[2, 1], bad[3, 0] = np.nan, np.inf
    with pytest.raises(ValueError, match=r"controls row 2 is \[0\.0, nan, 0\.0\] \(2 of 4 rows"):
        check_controls(bad)
    # Inside jit only the shape and dtype can be checked.
    jax.jit(lambda c: check_controls(c) or c)(jnp.asarray(bad))
    with pytest.raises(ValueError, match=r"\(T, 3\)"):
        jax.jit(lambda c: check_controls(c) or c)(jnp.asarray(bad[:, :2]))


CONFIG = FilterConfig(num_particles=4, max_landmarks=4, max_obs=2)
T = 4


def _inputs(control_dtype=jnp.float32, obs_dtype=jnp.float32):
    controls = jnp.tile(jnp.asarray([0.0, 0.1, 0.0], control_dtype), (T, 1))
    z = jnp.tile(jnp.asarray([[5.0, 0.3], [7.0, -0.4]], obs_dtype), (T, 1, 1))
    return controls, make_observations(z)


@pytest.mark.parametrize("bad", [NAN, INF, -INF])
def test_run_filter_refuses_a_non_finite_control_row(bad):
    controls, obs = _inputs()
    controls = controls.at[2, 1].set(bad)
    with pytest.raises(ValueError, match=r"controls row 2 is"):
        run_filter(CONFIG, jax.random.key(0), default_params(), controls, obs)


def test_run_filter_refuses_bad_params():
    controls, obs = _inputs()
    params = default_params()._replace(association_gate=jnp.float32(NAN))
    with pytest.raises(ValueError, match=r"Params\.association_gate=nan"):
        run_filter(CONFIG, jax.random.key(0), params, controls, obs)
    params = default_params()._replace(rot1_noise=jnp.float32(0.1))
    with pytest.raises(ValueError, match=r"Params\.rot1_noise has shape \(\)"):
        run_filter(CONFIG, jax.random.key(0), params, controls, obs)


@pytest.mark.parametrize("params_dtype,control_dtype,obs_dtype", [
    (jnp.float64, jnp.float32, jnp.float32),
    (jnp.float32, jnp.float32, jnp.float64),
    (jnp.float32, jnp.float64, jnp.float32),
])
def test_run_filter_casts_mixed_dtypes_to_the_controls_dtype(params_dtype, control_dtype,
                                                             obs_dtype):
    controls, obs = _inputs(control_dtype, obs_dtype)
    state, trace = run_filter(CONFIG, jax.random.key(0), default_params(dtype=params_dtype),
                              controls, obs)
    assert state.particles.pose.dtype == control_dtype
    assert trace.mean_pose.dtype == control_dtype
    assert bool(jnp.all(jnp.isfinite(trace.mean_pose)))


def test_cast_floating_keeps_other_leaves():
    _, obs = _inputs(obs_dtype=jnp.float64)
    cast = cast_floating(obs, jnp.float32)
    assert cast.z.dtype == jnp.float32 and cast.radius.dtype == jnp.float32
    assert cast.valid.dtype == jnp.bool_ and cast.landmark_id.dtype == jnp.int32


# --------------------------------------------------------------------------------- log files


def _valid_log():
    return lf.RobotLog(time=np.array([1.5, 2.5, 3.5]), motion_model="odometry",
                       controls=np.full((3, 3), 0.25), obs_z=np.ones((3, 2, 2)),
                       obs_valid=np.ones((3, 2), bool))


def _saved(tmp_path, compress=False):
    path = tmp_path / "good.npz"
    lf.save_log(path, _valid_log(), compress=compress)
    return path, path.read_bytes()


def _assert_log_format_error(path, match):
    with pytest.raises(lf.LogFormatError, match=match) as error:
        lf.load_log(path)
    message = str(error.value)
    assert message.startswith(f"{path}: "), message
    assert "expected a .npz archive" in message and "save_log" in message, message
    assert isinstance(error.value, ValueError)
    return message


def test_saved_log_loads(tmp_path):
    path, _ = _saved(tmp_path)
    np.testing.assert_array_equal(lf.load_log(path).time, [1.5, 2.5, 3.5])


def test_empty_file(tmp_path):
    path = tmp_path / "empty.npz"
    path.write_bytes(b"")
    _assert_log_format_error(path, "empty")


@pytest.mark.parametrize("compress", [False, True])
@pytest.mark.parametrize("fraction", [0.1, 0.5, 0.9])
def test_truncated_file(tmp_path, compress, fraction):
    _, data = _saved(tmp_path, compress)
    path = tmp_path / "truncated.npz"
    path.write_bytes(data[:int(len(data) * fraction)])
    _assert_log_format_error(path, "cannot read as a .npz archive")


def test_corrupt_member(tmp_path):
    """A flipped byte inside an array's data: the zip CRC check fails on read."""
    _, data = _saved(tmp_path)
    offset = data.find(np.array([1.5, 2.5, 3.5]).tobytes())
    assert offset > 0
    corrupt = bytearray(data)
    corrupt[offset + 3] ^= 0xFF
    path = tmp_path / "corrupt.npz"
    path.write_bytes(bytes(corrupt))
    _assert_log_format_error(path, r"key 'time' is a corrupt or truncated member")


def _member_data_start(data: bytes, name: bytes) -> int:
    """Offset of the (compressed) data of zip member ``name`` after its local header."""
    import struct

    header = data.find(b"PK\x03\x04")  # first local header
    while header >= 0:
        name_length, extra_length = struct.unpack("<HH", data[header + 26:header + 30])
        if data[header + 30:header + 30 + name_length] == name:
            return header + 30 + name_length + extra_length
        header = data.find(b"PK\x03\x04", header + 4)
    raise AssertionError(name)


@pytest.mark.parametrize("member", [b"time.npy", b"controls.npy"])
def test_corrupt_compressed_member(tmp_path, member):
    _, data = _saved(tmp_path, compress=True)
    start = _member_data_start(data, member)
    corrupt = bytearray(data)
    corrupt[start + 4:start + 20] = bytes(16)
    path = tmp_path / "corrupt.npz"
    path.write_bytes(bytes(corrupt))
    _assert_log_format_error(path, f"key '{member.decode()[:-4]}' is a corrupt or truncated")


def test_npy_file(tmp_path):
    path = tmp_path / "time.npy"
    np.save(path, np.arange(3.0))
    _assert_log_format_error(path, r"single \.npy array")


def test_text_and_pickle_files(tmp_path):
    import pickle

    text = tmp_path / "run.csv"
    text.write_text("time,x,y\n")
    _assert_log_format_error(text, "not a zip file")
    pickled = tmp_path / "run.pkl"
    pickled.write_bytes(pickle.dumps({"time": [1.0]}))
    _assert_log_format_error(pickled, "not a zip file")


def test_missing_file_and_directory(tmp_path):
    _assert_log_format_error(tmp_path / "missing.npz", "no such file")
    _assert_log_format_error(tmp_path, "directory")


def test_object_array_needs_pickle_and_is_refused(tmp_path):
    arrays = {name: value for name, value in _valid_log()._asdict().items()
              if value is not None}
    arrays["motion_model"] = np.asarray("odometry")
    arrays["time"] = np.array([1.5, 2.5, 3.5], dtype=object)
    path = tmp_path / "pickled.npz"
    np.savez(path, **arrays)  # numpy pickles object arrays when saving
    _assert_log_format_error(path, r"key 'time' is an object array that needs pickle")


def test_object_metadata_is_never_read(tmp_path):
    arrays = {name: value for name, value in _valid_log()._asdict().items()
              if value is not None}
    arrays["motion_model"] = np.asarray("odometry")
    path = tmp_path / "meta.npz"
    np.savez(path, meta_notes=np.array([{"robot": 3}], dtype=object), **arrays)
    assert lf.load_log(path).num_steps == 3


def test_zip_that_is_not_an_npz(tmp_path):
    import zipfile

    path = tmp_path / "other.zip"
    with zipfile.ZipFile(path, "w") as archive:
        archive.writestr("time", b"not an array")
    _assert_log_format_error(path, r"member 'time' of the zip is not a \.npy array")
