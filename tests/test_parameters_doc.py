"""docs/parameters.md against the code, and the defaults of ``default_params``.

Every ``Params`` field has one row in the page's tables with the unit of
``columns.CONFIG_UNITS`` and the value ``default_params()`` gives; the derived default
``airlock_sigmas = sqrt(association_gate)`` follows the gate of the same call; and the default
``Params`` are pinned bit for bit to the documented values.
"""
from __future__ import annotations

import math
import pathlib
import re
import tomllib

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam.columns import CONFIG_UNITS
from jaxslam.types import DERIVED_DEFAULTS, PARAM_DEFAULTS, FilterConfig, Params, default_params
from jaxslam.validation import check_params

DOC = pathlib.Path(__file__).resolve().parents[1] / "docs" / "parameters.md"

# The fields jaxslam calibrate estimates (self_calibration.calibrate_params: the keys of its
# M-step ``update``, and association_heading_std, set from the fitted motion noise), which the
# page marks **calibrated**.
CALIBRATED = {
    "rot1_noise", "trans_noise", "rot2_noise", "motion_outlier_probability",
    "motion_outlier_scale", "range_noise", "bearing_noise", "range_std_floor",
    "bearing_std_floor", "max_range", "miss_range", "miss_bearing", "detection_probability",
    "false_alarm_probability", "association_gate", "airlock_sigmas", "association_heading_std",
    "radius_noise", "odometry_gain",
}

HEADER = ["Field", "Unit", "Default", "Read when", "Enters", "Estimate from"]


def _doc_rows() -> dict[str, dict[str, str]]:
    """{field: {column: cell}} of every parameter table row of docs/parameters.md."""
    rows: dict[str, dict[str, str]] = {}
    header = None
    for line in DOC.read_text().splitlines():
        if not line.startswith("|"):
            header = None
            continue
        cells = [cell.strip() for cell in line.strip().strip("|").split("|")]
        if header is None:
            header = cells
            continue
        if header != HEADER or set(line) <= set("|- "):
            continue
        assert len(cells) == len(HEADER), f"row with {len(cells)} cells: {line}"
        match = re.fullmatch(r"`(\w+)`", cells[0])
        assert match, f"a table row must start with a `field`: {line}"
        name = match.group(1)
        assert name not in rows, f"{name} has two rows in docs/parameters.md"
        rows[name] = dict(zip(HEADER, cells))
    return rows


def _default_value(cell: str):
    """The value in the first backticks of a Default cell, read as TOML."""
    match = re.match(r"`([^`]+)`", cell)
    assert match, f"the Default cell must start with a `value`: {cell!r}"
    return tomllib.loads(f"v = {match.group(1)}")["v"]


def _bits(value) -> np.ndarray:
    return np.asarray(value, np.float32).view(np.uint32)


def test_every_field_has_one_row_and_no_other_rows():
    assert set(_doc_rows()) == set(Params._fields)


@pytest.mark.parametrize("name", Params._fields)
def test_row_unit_matches_config_units(name):
    assert _doc_rows()[name]["Unit"] == CONFIG_UNITS[f"params.{name}"]


def test_rows_say_how_to_estimate_and_which_fields_are_calibrated():
    rows = _doc_rows()
    marked = {name for name, row in rows.items() if "**calibrated**" in row["Estimate from"]}
    assert marked == CALIBRATED
    for name, row in rows.items():
        assert row["Read when"] and row["Enters"] and row["Estimate from"], name
        assert "ground truth" not in row["Estimate from"].replace("not ground truth", ""), name


def test_page_says_how_to_set_a_field():
    text = DOC.read_text()
    for needle in ("default_params(config, max_range=15.0", "[params]",
                   "--set params.max_range=15", "jaxslam config show", "jaxslam calibrate",
                   "calibrate_params"):
        assert needle in text, needle


def test_default_table_covers_every_field_once():
    assert set(PARAM_DEFAULTS).isdisjoint(DERIVED_DEFAULTS)
    assert sorted([*PARAM_DEFAULTS, *DERIVED_DEFAULTS]) == sorted(Params._fields)


@pytest.mark.parametrize("name", Params._fields)
def test_defaults_are_the_documented_values_bit_for_bit(name):
    """docs/parameters.md is the pin: it states every default independently of the code, so a
    changed value in ``PARAM_DEFAULTS`` (or a changed derivation) fails here until the page,
    and with it every result computed with the defaults, is updated on purpose."""
    documented = _default_value(_doc_rows()[name]["Default"])
    leaf = np.asarray(getattr(default_params(), name))
    assert leaf.dtype == np.float32, name
    assert leaf.shape == np.shape(documented), name
    assert np.array_equal(leaf.view(np.uint32), _bits(documented)), (name, leaf, documented)
    if name in PARAM_DEFAULTS:
        assert np.array_equal(_bits(PARAM_DEFAULTS[name]), _bits(documented)), name


@pytest.mark.parametrize("config", [
    FilterConfig(), FilterConfig(motion_model="ackermann", max_obs=24),
    FilterConfig(proposal="mixture", mixture_mode="adaptive", boundary="hard"),
])
def test_config_does_not_change_defaults(config):
    for name, leaf in default_params(config)._asdict().items():
        assert np.array_equal(np.asarray(leaf).view(np.uint32),
                              np.asarray(getattr(default_params(), name)).view(np.uint32)), name


def test_config_must_be_a_filter_config():
    with pytest.raises(TypeError, match="FilterConfig or None"):
        default_params(15.0)


@pytest.mark.parametrize("gate, airlock", [(16.0, 4.0), (25.0, 5.0), (9.0, 3.0)])
def test_airlock_follows_the_gate_of_the_same_call(gate, airlock):
    params = default_params(association_gate=gate)
    assert float(params.airlock_sigmas) == airlock
    check_params(params, allow_batch=False)


def test_airlock_is_sqrt_of_the_stored_gate():
    params = default_params(association_gate=13.8)
    assert params.airlock_sigmas == jnp.sqrt(params.association_gate)
    assert math.isclose(float(params.airlock_sigmas), math.sqrt(13.8), rel_tol=1e-6)


@pytest.mark.parametrize("overrides", [
    dict(association_gate=16.0, airlock_sigmas=2.0),
    dict(airlock_sigmas=2.0),
    dict(association_gate=25.0, airlock_sigmas=0.0),
])
def test_explicit_airlock_wins(overrides):
    params = default_params(**overrides)
    assert float(params.airlock_sigmas) == overrides["airlock_sigmas"]
    assert float(params.association_gate) == overrides.get("association_gate", 25.0)
    check_params(params, allow_batch=False)


def test_airlock_follows_a_traced_gate():
    gates = jnp.asarray([16.0, 25.0, 4.0])
    airlocks = jax.vmap(lambda g: default_params(association_gate=g).airlock_sigmas)(gates)
    np.testing.assert_array_equal(np.asarray(airlocks), [4.0, 5.0, 2.0])


@pytest.mark.parametrize("gate", [-1.0, float("nan"), 0.0])
def test_an_invalid_gate_is_named_not_the_derived_airlock(gate):
    with pytest.raises(ValueError, match=r"default_params\.association_gate"):
        default_params(association_gate=gate)
