"""How the odometry's heading error grows over n steps, against the white model the filter uses.

A diagnostic: nothing here is a setting. Eq. (1) of Geiser et al., "Practical Implementation
of FastSLAM for Forestry Robot" (ICAROB 2023), is white: each move's error is drawn afresh, so
the heading error summed over n moves has n times one move's variance, and a particle cloud
spreads by sqrt(n) sigma over a pause of n steps without landmarks. If the odometry drifts
(errors of one sign for a while), the true error grows faster, and the filter meets a
re-sighted landmark further from its prediction than its cloud covers.

Two measures, both robust to the odometry's spikes (variances from the median absolute
deviation, 1.4826 MAD squared, since a few steps with heading errors of tenths of a radian
dominate a mean square and partly cancel in the next step):

1. **Growth against ground truth** (MRCLAM's Vicon, which only scores here): the heading
   error of each move e_t = (rot1 + rot2)_measured - wrap(theta_t - theta_{t-1})_true, and

       g(n) = V(n) / (n V(1)),  V(n) the robust variance of e summed over consecutive,
                                 non-overlapping windows of n moves.

   White errors give g(n) = 1 at every n; a drift gives g(n) > 1, growing with n.
2. **The calibrated model against the log's own smoothed drift** (no ground truth): the
   calibrated filter's best history smoothed with its association fixed
   (``calibration_bootstrap.log_solution``) gives the heading residuals
   e_t = (rot1 + rot2)_measured - wrap(theta*_t - theta*_{t-1}) and their V_log(n). Replicate
   logs drawn from the calibrated model itself around that solution
   (``calibration_bootstrap.replicate_log``, its fitted bursts included) and smoothed with
   the same association give V_rep(n), averaged over the replicates; then

       kappa(n) = V_log(n) / V_rep(n).

   A smoothed path between two sightings spreads the correction over the moves in between,
   which correlates its residuals even when the odometry's errors are white; the replicates
   are smoothed the same way, so kappa(n) = 1 where the log drifts over n steps as the
   calibrated white model would, and kappa(n) > 1 where it drifts more.

With ``--heading-scales``, each MRCLAM robot's calibrated Params are also run with their
heading terms (rot1 and rot2 coefficients, ``association_heading_std``) times each scale,
over filter keys 100, 101, ... (Vicon scores: dead reckoning ATE / filter ATE).

    python experiments/motion_drift.py --mrclam-robots 1 2 3 4 5 [--seed 0] [--replicates 3]
        [--heading-scales 1 1.4 2 3] [--filter-keys 6]
    python experiments/motion_drift.py --victoria-park-params FILE [--observation-scale 8]

``FILE`` is the ``calibrated_params.toml`` that ``experiments/victoria_park.py`` writes;
``--observation-scale`` divides the observation noise by the likelihood search's factor
(printed by that script), so that the replicates are drawn at EM's own sensor noise.
"""
from __future__ import annotations

import argparse
import pathlib
import sys

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

from jaxslam import metrics, pipeline, smoothing  # noqa: E402
from jaxslam.calibration_bootstrap import log_solution, replicate_log  # noqa: E402
from jaxslam.datasets.odometry import odometry_path  # noqa: E402
from jaxslam.filter import run_filter  # noqa: E402
from jaxslam.types import FilterConfig  # noqa: E402

WINDOWS = (1, 2, 5, 10, 20, 50, 100, 200)
MIN_WINDOWS = 30  # fewer n-step windows than this in the log: the column is not printed
MAD_TO_STD = 1.4826  # std of a normal over its median absolute deviation
MRCLAM = pathlib.Path(__file__).resolve().parents[2] / "shared" / "data" / "mrclam1"


def wrap(angle):
    """Angles wrapped to [-pi, pi)."""
    return (np.asarray(angle, np.float64) + np.pi) % (2.0 * np.pi) - np.pi


def robust_variance(values) -> float:
    """(1.4826 MAD)^2 of ``values`` (N,): a normal's variance, little moved by spikes; nan
    when N = 0."""
    values = np.asarray(values, np.float64)
    if values.size == 0:
        return float("nan")
    return float((MAD_TO_STD * np.median(np.abs(values - np.median(values)))) ** 2)


def windowed_variance(errors, windows=WINDOWS) -> np.ndarray:
    """(W,) V(n): ``robust_variance`` of ``errors`` (T,) summed over consecutive,
    non-overlapping windows of n steps (the last T mod n steps left out), for each n in
    ``windows``; nan where T < n. ValueError for a window below 1."""
    errors = np.asarray(errors, np.float64)
    out = []
    for n in windows:
        if int(n) < 1:
            raise ValueError(f"window {n}: a window holds at least 1 step")
        count = errors.size // int(n)
        out.append(robust_variance(errors[:count * int(n)].reshape(count, int(n)).sum(axis=1)))
    return np.asarray(out)


def growth(errors, windows=WINDOWS) -> np.ndarray:
    """(W,) g(n) = V(n) / (n V(1)) of ``errors`` (T,) (module docstring, item 1)."""
    variance = windowed_variance(errors, windows)
    single = windowed_variance(errors, (1,))[0]
    return variance / (np.asarray(windows, np.float64) * single)


def heading_errors(controls, start, poses) -> np.ndarray:
    """(T,) measured heading change of each move (rot1 + rot2 of ``controls`` (T, 3)) minus
    the heading change of ``poses`` (T, 3), the pose after each move, from ``start`` (3,);
    wrapped to [-pi, pi)."""
    controls = np.asarray(controls, np.float64)
    poses = np.concatenate([np.asarray(start, np.float64)[None],
                            np.asarray(poses, np.float64)])
    if controls.shape != (len(poses) - 1, 3):
        raise ValueError(f"controls {controls.shape} for {len(poses) - 1} poses: expected "
                         "one (rot1, trans, rot2) move a pose")
    return wrap(controls[:, 0] + controls[:, 2] - np.diff(poses[:, 2]))


def drift_against_model(config: FilterConfig, params, controls, observations, start,
                        replicates: int, windows=WINDOWS, seed: int = 0):
    """(V_log (W,), V_rep (W, R)) of the module docstring's item 2: the log's smoothed
    heading residuals and those of ``replicates`` logs drawn from ``params``."""
    start = np.asarray(start, np.float64)
    solution = log_solution(config, jax.random.PRNGKey(seed), params, controls, observations,
                            start)
    log_variance = windowed_variance(heading_errors(controls, start, solution.path), windows)
    replicate_variance = []
    for index in range(replicates):
        moves, drawn = replicate_log(jax.random.PRNGKey(1000 + index), solution, params,
                                     observations, bursts=True)
        smoothed = smoothing.smooth_path(start, solution.path, moves,
                                         np.asarray(drawn.z, np.float64),
                                         solution.landmark_of_obs, params,
                                         calibrate_rounds=smoothing.VARIANCE_ROUNDS)
        replicate_variance.append(windowed_variance(
            heading_errors(moves, start, smoothed.path), windows))
    return log_variance, np.stack(replicate_variance, axis=-1)


def _columns(values, windows, steps: int, digits: int = 2) -> str:
    return " ".join(f"{n}:{value:.{digits}f}" for n, value in zip(windows, values)
                    if steps // n >= MIN_WINDOWS)


def _coefficients(values) -> str:
    return "(" + ", ".join(f"{float(v):.5f}" for v in np.asarray(values)) + ")"


def with_heading_scale(params, scale: float):
    """``params`` with rot1_noise, rot2_noise and association_heading_std times ``scale``."""
    return params._replace(rot1_noise=params.rot1_noise * scale,
                           rot2_noise=params.rot2_noise * scale,
                           association_heading_std=params.association_heading_std * scale)


def mrclam_robot(data, robot: int, seed: int, replicates: int, scales, filter_keys: int):
    """Calibrate MRCLAM robot ``robot`` (``pipeline.filter_log``, key ``seed``) and print
    both measures and, for each of ``scales``, the heading-scaled filter's ATE ratios."""
    from jaxslam.datasets.mrclam import read_mrclam
    from jaxslam.datasets.mrclam_convert import DEFAULT_MAX_OBS, mrclam_log, mrclam_steps

    raw = read_mrclam(data, robot)
    log = mrclam_log(raw, mrclam_steps(raw, DEFAULT_MAX_OBS))
    config = FilterConfig(num_particles=100, max_landmarks=64, max_obs=DEFAULT_MAX_OBS)
    run = pipeline.filter_log(log, config, key=jax.random.PRNGKey(seed), calibrate=True)
    config, controls, obs, start = pipeline.log_inputs(log, config)
    truth = np.asarray(log.truth_pose, np.float64)
    steps = len(truth)
    truth_errors = heading_errors(controls, start, truth)
    log_variance, replicate_variance = drift_against_model(config, run.params, controls, obs,
                                                           start, replicates, seed=seed)
    kappa = log_variance / replicate_variance.mean(axis=-1)
    print(f"robot {robot}: T={steps}, calibrated heading terms rot1 "
          f"{_coefficients(run.params.rot1_noise)}, rot2 "
          f"{_coefficients(run.params.rot2_noise)}, bursts "
          f"{float(run.params.motion_outlier_probability):.2f} x "
          f"{float(run.params.motion_outlier_scale):.2f}", flush=True)
    print(f"  Vicon: one move's robust heading std {np.sqrt(windowed_variance(truth_errors, (1,))[0]):.4f}"
          f" rad; growth g(n) {_columns(growth(truth_errors), WINDOWS, steps)}")
    print(f"  log alone: smoothed residuals' robust std {np.sqrt(log_variance[0]):.4f} rad "
          f"(replicates {np.sqrt(replicate_variance[0].mean()):.4f}); kappa(n) "
          f"{_columns(kappa, WINDOWS, steps)}", flush=True)
    if not scales:
        return
    dead_reckoning = np.asarray(odometry_path(log.controls, log.initial_pose))[-steps:]
    dr_ate = metrics.ate_rmse(dead_reckoning, truth)
    for scale in scales:
        ratios, kept = [], []
        for key in range(100, 100 + filter_keys):
            _, trace = run_filter(config, jax.random.PRNGKey(key),
                                  with_heading_scale(run.params, scale), controls, obs,
                                  jnp.asarray(start, jnp.float32))
            ratios.append(dr_ate / metrics.ate_rmse(np.asarray(trace.mean_pose, np.float64),
                                                    truth))
            kept.append(int(np.asarray(trace.num_landmarks)[-1]))
        print(f"  heading x{scale:g}: dead reckoning / filter ATE median "
              f"{np.median(ratios):.2f}x ({' '.join(f'{r:.2f}' for r in ratios)}); "
              f"landmarks {min(kept)}-{max(kept)}", flush=True)


def victoria_park(params_file: str, observation_scale: float, replicates: int, seed: int):
    """Item 2 on Victoria Park with the Params of ``params_file`` (the calibrated set's
    log: its detector, its constant laser steering bias)."""
    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
    import victoria_park_pipeline as vps
    from jaxslam.datasets import victoria_park as vpm

    data = vpm.load_victoria_park()
    settings = vps.load_settings(vps.CALIBRATED)
    config = vps.settings_config(settings)
    log, _, _ = vps.calibration_log(data, settings, config)
    params = pipeline.load_params(params_file, config)
    params = params._replace(range_noise=params.range_noise / observation_scale,
                             bearing_noise=params.bearing_noise / observation_scale)
    config, controls, obs, start = pipeline.log_inputs(log, config)
    log_variance, replicate_variance = drift_against_model(config, params, controls, obs,
                                                           start, replicates, seed=seed)
    steps = int(np.asarray(controls).shape[0])
    print(f"Victoria Park: T={steps}, observation noise / {observation_scale:g}; smoothed "
          f"residuals' robust std {np.sqrt(log_variance[0]):.5f} rad (replicates "
          f"{np.sqrt(replicate_variance[0].mean()):.5f}); kappa(n) "
          f"{_columns(log_variance / replicate_variance.mean(axis=-1), WINDOWS, steps)}")


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--mrclam-robots", type=int, nargs="*", default=[])
    parser.add_argument("--mrclam-data", default=str(MRCLAM))
    parser.add_argument("--victoria-park-params", default=None, metavar="FILE")
    parser.add_argument("--observation-scale", type=float, default=1.0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--replicates", type=int, default=3)
    parser.add_argument("--heading-scales", type=float, nargs="*", default=[])
    parser.add_argument("--filter-keys", type=int, default=6)
    args = parser.parse_args(argv)
    if not args.mrclam_robots and args.victoria_park_params is None:
        parser.error("name --mrclam-robots and/or --victoria-park-params")
    if args.replicates < 1:
        parser.error(f"--replicates {args.replicates}: at least 1")
    if args.observation_scale <= 0.0:
        parser.error(f"--observation-scale {args.observation_scale}: a positive factor")
    for robot in args.mrclam_robots:
        mrclam_robot(args.mrclam_data, robot, args.seed, args.replicates, args.heading_scales,
                     args.filter_keys)
    if args.victoria_park_params is not None:
        victoria_park(args.victoria_park_params, args.observation_scale, args.replicates,
                      args.seed)


if __name__ == "__main__":
    main()
