"""Units guard: plain-word warnings and refusals for observations in the wrong units.

Observations are (range [m], bearing [rad]). A log in other units loads fine and then every
row is masked or ignored inside the filter, so the run "succeeds" with an empty map. These
host-side checks look at the rows marked valid and say so in words, before the filter runs.

Rules (all on the rows marked valid; none fire when there are no such rows):
  malformed: a row is malformed when a value is NaN/inf, the range is <= 0, or the bearing is
    outside [-pi, pi]. More than half malformed is a warning (with the counts per kind);
    every row malformed is a refusal in ``check_observation_units``.
  degrees: of the finite bearings, at least 10 % have |bearing| > pi and the 99th percentile
    of |bearing| lies in (2 pi, 360] -- beyond any radian convention ([-pi, pi] or [0, 2 pi])
    but within a degree circle. Certain (refusal) when, in addition, at least half of the
    finite bearings have |bearing| > pi.
  [0, 2 pi]: at least 10 % of the finite bearings exceed pi, none is negative and all are
    <= 2 pi: radians measured from 0 to 2 pi instead of -pi to pi.
  millimetres / centimetres: a forestry lidar sees trunks at about 5-80 m, so a median
    positive finite range above 100 m is a warning; the message names which of millimetres
    (median / 1000) or centimetres (median / 100) turn the median into a plausible 1-100 m.
    A median above 1000 m is certain (refusal). With ``max_range`` given (finite, > 0), a
    median above 10 * max_range is also a warning (most rows would be ignored as too far).
"""
from __future__ import annotations

import numpy as np

_EXPECTED_UNITS = "expected ranges in metres and bearings in radians in [-pi, pi]"
_DEGREE_SHARE = 0.10          # share of |bearing| > pi that starts the degree/[0, 2pi] rules
_CERTAIN_SHARE = 0.50         # share of |bearing| > pi that makes degrees certain
_MALFORMED_SHARE = 0.50       # share of malformed valid rows that is a warning
_FAR_MEDIAN = 100.0           # [m] median range above which the units look wrong
_CERTAIN_MEDIAN = 1000.0      # [m] median range above which the units are certainly wrong
_PLAUSIBLE_MEDIAN = (1.0, 100.0)  # [m] a plausible median range after conversion
_MAX_RANGE_FACTOR = 10.0      # median above this many max_range is a warning


def _units_facts(z, valid) -> dict:
    """Counts and statistics behind the units rules (module docstring)."""
    z = np.asarray(z, np.float64)
    if z.ndim < 1 or z.shape[-1] != 2:
        raise ValueError(f"observations z must have shape (..., 2); got {z.shape}")
    valid = np.broadcast_to(np.asarray(valid, bool), z.shape[:-1])
    rows = z[valid].reshape(-1, 2)
    r, b = rows[:, 0], rows[:, 1]
    nonfinite = ~np.isfinite(rows).all(-1)
    with np.errstate(invalid="ignore"):
        bad_range = ~nonfinite & (r <= 0)
        bad_bearing = ~nonfinite & (np.abs(b) > np.pi)
    facts = dict(n=len(rows), nonfinite=int(nonfinite.sum()), bad_range=int(bad_range.sum()),
                 bad_bearing=int(bad_bearing.sum()),
                 malformed=int((nonfinite | bad_range | bad_bearing).sum()))
    fb = b[np.isfinite(b)]
    facts["n_bearing"] = len(fb)
    if len(fb):
        beyond = np.abs(fb) > np.pi
        facts.update(beyond=int(beyond.sum()), beyond_share=float(beyond.mean()),
                     b_p99=float(np.quantile(np.abs(fb), 0.99)), b_min=float(fb.min()),
                     b_max=float(fb.max()))
        facts["degrees"] = (facts["beyond_share"] >= _DEGREE_SHARE
                            and 2 * np.pi < facts["b_p99"] <= 360.0)
        facts["two_pi"] = (facts["beyond_share"] >= _DEGREE_SHARE and facts["b_min"] >= 0
                           and facts["b_max"] <= 2 * np.pi)
    else:
        facts.update(degrees=False, two_pi=False)
    fr = r[np.isfinite(r) & (r > 0)]
    facts["median_range"] = float(np.median(fr)) if len(fr) else None
    facts["max_seen_range"] = float(fr.max()) if len(fr) else None
    return facts


def _range_units_guess(median: float) -> str:
    low, high = _PLAUSIBLE_MEDIAN
    names = [f"{unit} (median {median / scale:.3g} m)"
             for unit, scale in (("millimetres", 1000.0), ("centimetres", 100.0))
             if low <= median / scale <= high]
    return " or ".join(names) if names else "a unit other than metres"


def observation_units_warnings(z, valid, max_range=None) -> list[str]:
    """Plain-word warnings that a log's observations are in the wrong units or malformed.

    Host-side NumPy check of the rows marked ``valid`` (rules in the module docstring
    of ``jaxslam.validation.units``); each message names the numbers behind it and what
    is expected. Returns ``[]`` for a good log, and for a log with no valid row.

    Args:
      z: (..., K, 2) observations (range, bearing).
      valid: (..., K) bool mask of the rows that are observations.
      max_range: optional usable range [m] of the filter; a median range far beyond it warns.
    """
    f = _units_facts(z, valid)
    n = f["n"]
    if n == 0:
        return []
    warnings = []
    if f["degrees"]:
        warnings.append(
            f"bearings look like degrees: {f['beyond']} of {f['n_bearing']} "
            f"({100 * f['beyond_share']:.0f}%) have |bearing| > pi and the largest reach "
            f"{max(abs(f['b_min']), abs(f['b_max'])):.4g} (99th percentile "
            f"{f['b_p99']:.4g}), within 360; {_EXPECTED_UNITS} (multiply degrees by pi/180)")
    elif f["two_pi"]:
        warnings.append(
            f"bearings look like radians in [0, 2 pi]: {f['beyond']} of {f['n_bearing']} "
            f"({100 * f['beyond_share']:.0f}%) are above pi, none is negative and the largest "
            f"is {f['b_max']:.4g}; {_EXPECTED_UNITS} (subtract 2 pi from those above pi)")
    median = f["median_range"]
    if median is not None:
        far = median > _FAR_MEDIAN
        beyond_max = (max_range is not None and np.isfinite(float(max_range))
                      and float(max_range) > 0
                      and median > _MAX_RANGE_FACTOR * float(max_range))
        if far or beyond_max:
            reason = (f"a forestry lidar sees trunks at about 5-80 m; these look like "
                      f"{_range_units_guess(median)}" if far else
                      f"more than {_MAX_RANGE_FACTOR:.0f} times max_range "
                      f"{float(max_range):.4g} m, so most would be ignored as too far")
            warnings.append(
                f"ranges look wrong: the median valid range is {median:.4g} m (largest "
                f"{f['max_seen_range']:.4g} m), {reason}; {_EXPECTED_UNITS}")
    if f["malformed"] > _MALFORMED_SHARE * n:
        share = 100 * f["malformed"] / n
        head = (f"all {n} observations marked valid are malformed" if f["malformed"] == n else
                f"{f['malformed']} of {n} observations marked valid ({share:.0f}%) are "
                "malformed")
        warnings.append(
            f"{head} ({f['nonfinite']} NaN or inf, {f['bad_range']} with a range <= 0, "
            f"{f['bad_bearing']} with a bearing outside [-pi, pi]) and will be masked; "
            f"{_EXPECTED_UNITS}")
    return warnings


def check_observation_units(z, valid) -> None:
    """Raise ``ValueError`` when a log's observations are certainly unusable as given.

    Refuses when every row marked valid is malformed (NaN/inf, range <= 0 or bearing outside
    [-pi, pi]), when the bearings look like degrees with at least half beyond pi, or when the
    median valid range is above 1000 m. The message is the matching
    ``observation_units_warnings`` text. A log with no valid row passes (nothing to judge).
    """
    f = _units_facts(z, valid)
    if f["n"] == 0:
        return
    certain = (f["malformed"] == f["n"]
               or (f["degrees"] and f["beyond_share"] >= _CERTAIN_SHARE)
               or (f["median_range"] is not None and f["median_range"] > _CERTAIN_MEDIAN))
    if certain:
        raise ValueError("; ".join(observation_units_warnings(z, valid))
                         + " -- refusing to run on these observations")
