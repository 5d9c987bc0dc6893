"""Victoria Park: R runs of one setting in one vmapped call, GPS RMSE per run (for comparisons).

Each run r uses key fold_in(PRNGKey(0), r), so two settings see the same keys. Settings are
``name=value`` pairs read with ``ast.literal_eval``:

    .venv/bin/python experiments/victoria_park_runs.py --runs 8 --scans 3500
    .venv/bin/python experiments/victoria_park_runs.py --runs 8 --steering-bias 0.0052 \\
        --detector max_missing_beams=0 --params "bearing_noise=(0.0, 0.02)" \\
        --config proposal='observation' match_pose_uncertainty=True
    .venv/bin/python experiments/victoria_park_runs.py --runs 16 --smooth \
        --params radius_noise=0.0 association_gate=13.8

Prints one line: RMSE [m] of each run, their median, the final tree counts and the run time.
The comparisons quoted in docs/results.md (victoria_park, tuning history) were made this way.
``--settings`` picks the set of experiments/configs/victoria_park.toml whose fixed values
start the run (default "legacy"; the "calibrated" set's calibrated fields need
``experiments/victoria_park.py``, which calibrates them from the log first).
"""
from __future__ import annotations

import argparse
import ast
import pathlib
import sys

import jax
import jax.numpy as jnp
import numpy as np

import victoria_park_pipeline as vps  # experiments/ (this script's folder)
# Run this checkout's jaxslam, also when an editable install points at another checkout
# (an experiment started from a git worktree of an older commit).
sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

from jaxslam.datasets import victoria_park as vpm


def settings(pairs: list[str], what: str) -> dict:
    """``["a=1", "b=(0.0, 0.02)"]`` -> {"a": 1, "b": (0.0, 0.02)}, naming a malformed pair."""
    out = {}
    for pair in pairs:
        name, sep, value = pair.partition("=")
        if not sep:
            raise SystemExit(f"--{what} {pair!r}: expected name=value")
        try:
            out[name.strip()] = ast.literal_eval(value.strip())
        except (ValueError, SyntaxError):
            raise SystemExit(f"--{what} {pair!r}: the value must be a Python literal "
                             "(a number, a string in quotes, a tuple)") from None
    return out


def steering_bias(text: str):
    if text in ("laser", "constant"):
        return text
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected 'laser', 'constant' or a "
                                         "number [rad]") from None


def parse_args():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=8)
    parser.add_argument("--settings", choices=(vps.LEGACY, vps.CALIBRATED), default=vps.LEGACY,
                        help="settings set of experiments/configs/victoria_park.toml (its "
                             "filter, fixed params and smoother)")
    parser.add_argument("--params-file", default=None,
                        help="Params TOML (e.g. calibrated_params.toml written by "
                             "experiments/victoria_park.py); --params override it")
    parser.add_argument("--particles", type=int, default=100)
    parser.add_argument("--scans", type=int, default=None, help="prefix length (default all)")
    parser.add_argument("--steering-bias", type=steering_bias, default="laser",
                        help="'laser' (default: the steering_bias_profile of the scans), "
                             "'constant' (their steering_bias_from_scans) or a constant "
                             f"[rad], e.g. {vps.STEERING_BIAS}")
    parser.add_argument("--config", nargs="*", default=[], help="FilterConfig fields")
    parser.add_argument("--params", nargs="*", default=[], help="Params fields")
    parser.add_argument("--detector", nargs="*", default=[], help="detect_trunks settings")
    parser.add_argument("--smooth", action="store_true",
                        help="also smooth each run's best history (20 runs vmapped at a time) "
                             "and print its RMSE")
    return parser.parse_args()


def main():
    args = parse_args()
    data = vpm.load_victoria_park()
    log = vpm.victoria_park_log(data)
    obs = vps.detect_scans(log.scan_ranges, log.scan_angles,
                           **settings(args.detector, "detector"))
    chosen = vps.load_settings(args.settings)
    config = vps.settings_config(chosen, num_particles=args.particles,
                                 **settings(args.config, "config"))
    if args.params_file:
        from jaxslam.pipeline import load_params

        params = load_params(args.params_file, config)._replace(
            **{name: jnp.asarray(value, jnp.float32)
               for name, value in settings(args.params, "params").items()})
    else:
        params = vps.settings_params(chosen, config, **settings(args.params, "params"))
    batch = vps.run_victoria_park_batch(jax.random.key(0), data, args.runs, config,
                                        params=params, observations=obs,
                                        num_scans=args.scans,
                                        steering_bias=args.steering_bias,
                                        smooth=args.smooth, smoother=chosen.smoother)
    if args.smooth:
        smoothed = batch.smoothed_rmse
        print(f"smoothed rmse [m] {np.round(smoothed, 2).tolist()} median "
              f"{np.median(smoothed):.2f} mean {smoothed.mean():.2f} max {smoothed.max():.2f} "
              f"<= 2 m: {int(np.sum(smoothed <= 2.0))} | smoothing {batch.smooth_s:.0f} s")
    print(f"rmse [m] {np.round(batch.rmse, 1).tolist()} median {np.median(batch.rmse):.2f} | "
          f"trees {batch.num_trees.tolist()} | compile {batch.compile_s:.1f} s, "
          f"run {batch.run_s:.0f} s | settings={args.settings} "
          f"params_file={args.params_file} P={args.particles} scans={args.scans or 'all'} "
          f"bias={args.steering_bias} config={args.config} params={args.params} "
          f"detector={args.detector}", flush=True)


if __name__ == "__main__":
    main()
