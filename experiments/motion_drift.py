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

   Gaussian white errors give g(n) = 1 at every n; a drift gives g(n) > 1, growing with n.
   Spikes raise g as well (V(1) sees the core, an n-step sum also the spikes in it), so g is
   printed beside the g of the same errors in a random order (white, the same values), and
   their ratio is the drift's part.
2. **The calibrated model against the log's own smoothed drift** (no ground truth): the
   calibrated filter's best history smoothed with its association fixed
   (``calibration_bootstrap.log_solution``) gives the heading residuals
   e_t = (rot1 + rot2)_measured - wrap(theta*_t - theta*_{t-1}) and their V_log(n). Replicate
   logs drawn from the calibrated model itself around that solution
   (``calibration_bootstrap.replicate_log``, bursts only where fitted) and smoothed with
   the same association (started from the solution, their own truth, where the log's
   smoothing starts from the filter's history) give V_rep(n), averaged over the replicates;
   then

       kappa(n) = V_log(n) / V_rep(n).

   A smoothed path between two sightings spreads the correction over the moves in between,
   which correlates its residuals even when the odometry's errors are white; the replicates
   are smoothed the same way, so kappa(n) = 1 where the log drifts over n steps as the
   calibrated white model would, and kappa(n) > 1 where it drifts more. The replicates keep
   the log's association and are drawn around its solution, so they carry none of the log's
   wrong matches (as in ``calibration_bootstrap``): kappa leans low. On three simulated logs
   drawn from the model itself, kappa(1) came out 0.62, 0.84 and 1.08
   (``tests/test_motion_drift_experiment.py``).

``--command-delay SECONDS`` applies MRCLAM's commanded velocities (the dataset's odometry)
that much later, as a robot that answers its commands with a lag would move; the whole
diagnostic (calibration included) then runs on those controls. A delay read off Vicon is a
diagnostic, not a setting.

With ``--heading-scales``, each MRCLAM robot's calibrated Params are also run with their
heading terms (rot1 and rot2 coefficients, ``association_heading_std``) times each scale,
over filter keys 100, 101, ... (Vicon scores: dead reckoning ATE / filter ATE).

    python experiments/motion_drift.py --mrclam-robots 1 2 3 4 5 [--seed 0] [--replicates 3]
        [--heading-scales 1 1.4 2 3] [--filter-keys 6]
    python experiments/motion_drift.py --mrclam-robots 1 2 3 4 5 --truth-only
        [--command-delay 0.2]
    python experiments/motion_drift.py --victoria-park-params FILE [--observation-scale 8]
        [--steering-bias constant|profile]

``FILE`` is the ``calibrated_params.toml`` that ``experiments/victoria_park.py`` writes;
``--observation-scale`` divides the model's observation noise by the likelihood search's
factor (printed by that script), so that the replicates are drawn, and both the log and the
replicates smoothed, at EM's own sensor noise; the filter that finds the log's association
keeps the file's Params. Columns with fewer than ``MIN_WINDOWS`` windows are left out; a
variance from 30-50 windows is uncertain by 33-43 % (one standard error).
"""
from __future__ import annotations

import argparse
import pathlib
import sys
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

from jaxslam import metrics, pipeline, smoothing  # noqa: E402
from jaxslam.calibrate import MAD_TO_STD  # noqa: E402
from jaxslam.calibration_bootstrap import log_solution, replicate_log  # noqa: E402
from jaxslam.datasets.odometry import odometry_path  # noqa: E402
from jaxslam.filter import run_filter  # noqa: E402
from jaxslam.host import in_float64  # noqa: E402
from jaxslam.motion import control_to_odometry  # noqa: E402
from jaxslam.self_calibration import group_scales  # noqa: E402
from jaxslam.smoothing.residuals import wrap  # noqa: E402
from jaxslam.types import FilterConfig  # noqa: E402

WINDOWS = (1, 2, 5, 10, 20, 50, 100, 200)
# Fewer n-step windows than this in the log: the column is not printed. A variance from the
# MAD of N window sums has a relative standard error of about 2.33 / sqrt(N) for a normal
# law (the MAD's asymptotic variance, 1.36 sigma^2 / N): 40 % at N = 34, 16 % at N = 200.
MIN_WINDOWS = 30
MRCLAM = pathlib.Path(__file__).resolve().parents[2] / "shared" / "data" / "mrclam1"


class Drift(NamedTuple):
    """The module docstring's item 2.

    log_variance: (W,) V_log(n), the log's smoothed heading residuals; replicate_variance:
    (W, R) V_rep(n) of each replicate. ``kappa`` is their ratio (W,).
    """

    log_variance: np.ndarray
    replicate_variance: np.ndarray

    @property
    def kappa(self) -> np.ndarray:
        return self.log_variance / self.replicate_variance.mean(axis=-1)


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


def shuffled_growth(errors, windows=WINDOWS, seed: int = 0) -> np.ndarray:
    """(W,) g(n) of ``errors`` (T,) in a random order (``numpy.random.default_rng(seed)``):
    the same values made white. With spikes g exceeds 1 even for white errors (V(1) sees
    the core, an n-step sum also the spikes it holds); g / shuffled g leaves the order's
    part, the drift."""
    return growth(np.random.default_rng(seed).permutation(np.asarray(errors, np.float64)),
                  windows)


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


def _smooth(start, path, moves, z, landmark_of_obs, params):
    return smoothing.smooth_path(start, path, moves, np.asarray(z, np.float64),
                                 landmark_of_obs, params,
                                 calibrate_rounds=smoothing.VARIANCE_ROUNDS)


def drift_against_model(config: FilterConfig, filter_params, model_params, controls,
                        observations, start, replicates: int, windows=WINDOWS,
                        seed: int = 0, bursts: bool = True) -> Drift:
    """``Drift`` of a log (controls (T, 3), ``Observations``, start (3,)).

    The log's solution: the filter run with ``filter_params`` (key ``seed``), its best
    history smoothed with its association fixed (``calibration_bootstrap.log_solution``),
    smoothed again with ``model_params`` when they differ. Each replicate r is drawn from
    ``model_params`` around that solution (key fold_in(PRNGKey(seed), 1000 + r); its bursts
    drawn only with ``bursts``, which should say whether the calibration fitted them,
    ``CalibrationInfo.bursts_fitted``) and smoothed with ``model_params`` from the
    solution's path, its own truth; the log's smoothing starts from the filter's history,
    so the replicates start nearer their optimum.
    """
    start = np.asarray(start, np.float64)
    solution = log_solution(config, jax.random.PRNGKey(seed), filter_params, controls,
                            observations, start)
    # The measured moves are the readings times the model's odometry gains (motion.py).
    measured = in_float64(control_to_odometry, controls, model_params,
                          motion_model="odometry")
    if model_params is not filter_params:
        smoothed = _smooth(start, solution.path, measured, observations.z,
                           solution.landmark_of_obs, model_params)
        solution = solution._replace(path=np.asarray(smoothed.path, np.float64),
                                     landmark=np.asarray(smoothed.landmark, np.float64))
    log_variance = windowed_variance(heading_errors(measured, start, solution.path), windows)
    replicate_variance = []
    for index in range(replicates):
        key = jax.random.fold_in(jax.random.PRNGKey(seed), 1000 + index)
        readings, drawn = replicate_log(key, solution, model_params, observations, bursts)
        moves = in_float64(control_to_odometry, readings, model_params,
                           motion_model="odometry")
        smoothed = _smooth(start, solution.path, moves, drawn.z, solution.landmark_of_obs,
                           model_params)
        replicate_variance.append(windowed_variance(
            heading_errors(moves, start, smoothed.path), windows))
    return Drift(log_variance, np.stack(replicate_variance, axis=-1))


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


def mrclam_robot_log(data, robot: int, command_delay: float = 0.0):
    """(``RobotLog`` of MRCLAM robot ``robot`` with its commands taking effect
    ``command_delay`` s late, on the steps of the log as stamped (``mrclam_log``'s
    ``command_delay``), FilterConfig: P = 100, 64 slots)."""
    from jaxslam.datasets.mrclam import load_mrclam
    from jaxslam.datasets.mrclam_convert import DEFAULT_MAX_OBS

    config = FilterConfig(num_particles=100, max_landmarks=64, max_obs=DEFAULT_MAX_OBS)
    return load_mrclam(data, robot, DEFAULT_MAX_OBS, command_delay=command_delay), config


def print_truth_growth(log, label: str) -> None:
    """Item 1 for a log with ``truth_pose`` (T, 3): g(n), its shuffled twin and their ratio."""
    truth = np.asarray(log.truth_pose, np.float64)
    errors = heading_errors(log.controls, log.initial_pose, truth)
    steps = len(truth)
    g, white = growth(errors), shuffled_growth(errors)
    print(f"{label}: one move's robust heading std "
          f"{np.sqrt(windowed_variance(errors, (1,))[0]):.4f} rad; g(n) "
          f"{_columns(g, WINDOWS, steps)}; shuffled {_columns(white, WINDOWS, steps)}; "
          f"ratio {_columns(g / white, WINDOWS, steps)}", flush=True)


def heading_scale_ratios(params, inputs, truth, dead_reckoning_ate: float, scale: float,
                         keys) -> tuple[list, list]:
    """(dead reckoning / filter ATE, final landmarks) of one run a key in ``keys`` with
    ``with_heading_scale(params, scale)``; inputs = ``pipeline.log_inputs``' tuple."""
    config, controls, obs, start = inputs
    ratios, kept = [], []
    for key in keys:
        _, trace = run_filter(config, jax.random.PRNGKey(key), with_heading_scale(params, scale),
                              controls, obs, jnp.asarray(start, jnp.float32))
        ate = metrics.ate_rmse(np.asarray(trace.mean_pose, np.float64), truth)
        ratios.append(dead_reckoning_ate / ate)
        kept.append(int(np.asarray(trace.num_landmarks)[-1]))
    return ratios, kept


def mrclam_robot(data, robot: int, seed: int, replicates: int, scales, filter_keys: int,
                 command_delay: float = 0.0):
    """Calibrate MRCLAM robot ``robot`` (``pipeline.filter_log``, key ``seed``; commands
    delayed by ``command_delay`` s) and print both measures and, for each of ``scales``, the
    heading-scaled filter's ATE ratios."""
    log, config = mrclam_robot_log(data, robot, command_delay)
    print_truth_growth(log, f"robot {robot}, Vicon")
    run = pipeline.filter_log(log, config, key=jax.random.PRNGKey(seed), calibrate=True)
    inputs = pipeline.log_inputs(log, config)
    config, controls, obs, start = inputs
    truth = np.asarray(log.truth_pose, np.float64)
    steps = len(truth)
    drift = drift_against_model(config, run.params, run.params, controls, obs, start,
                                replicates, seed=seed,
                                bursts=bool(run.calibration.bursts_fitted))
    print(f"  calibrated heading terms rot1 {_coefficients(run.params.rot1_noise)}, rot2 "
          f"{_coefficients(run.params.rot2_noise)}, bursts "
          f"{float(run.params.motion_outlier_probability):.2f} x "
          f"{float(run.params.motion_outlier_scale):.2f}; the likelihood's motion x"
          f"{group_scales(run.calibration)[0]:g} (in these Params)")
    print(f"  log alone: smoothed residuals' robust std {np.sqrt(drift.log_variance[0]):.4f}"
          f" rad (replicates {np.sqrt(drift.replicate_variance[0].mean()):.4f}); kappa(n) "
          f"{_columns(drift.kappa, WINDOWS, steps)}", flush=True)
    if not scales:
        return
    dead_reckoning = np.asarray(odometry_path(log.controls, log.initial_pose))[-steps:]
    dr_ate = metrics.ate_rmse(dead_reckoning, truth)
    for scale in scales:
        ratios, kept = heading_scale_ratios(run.params, inputs, truth, dr_ate, scale,
                                            range(100, 100 + filter_keys))
        print(f"  heading x{scale:g}: dead reckoning / filter ATE median "
              f"{np.median(ratios):.2f}x ({' '.join(f'{r:.2f}' for r in ratios)}); "
              f"landmarks {min(kept)}-{max(kept)}", flush=True)


def victoria_park(params_file: str, observation_scale: float, replicates: int, seed: int,
                  steering_bias: str = "constant"):
    """Item 2 on Victoria Park: the filter with the Params of ``params_file`` on the
    calibrated set's log (its detector; the controls corrected by the laser-only steering
    bias ``steering_bias``, "constant" as the set has it or the windowed "profile", whose
    window ``victoria_park_pipeline.BIAS_WINDOW`` the legacy set's GPS tuning chose), the
    model with their observation noise divided by ``observation_scale``."""
    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
    import victoria_park_pipeline as vps
    from jaxslam.datasets import victoria_park as vpm

    data = vpm.load_victoria_park()
    settings = vps.load_settings(vps.CALIBRATED)
    settings = settings._replace(run={**settings.run, "steering_bias": steering_bias})
    config = vps.settings_config(settings)
    log, _, _ = vps.calibration_log(data, settings, config)
    params = pipeline.load_params(params_file, config)
    model = params._replace(range_noise=params.range_noise / observation_scale,
                            bearing_noise=params.bearing_noise / observation_scale)
    config, controls, obs, start = pipeline.log_inputs(log, config)
    drift = drift_against_model(config, params, model, controls, obs, start, replicates,
                                seed=seed)
    steps = int(np.asarray(controls).shape[0])
    print(f"Victoria Park: T={steps}, {steering_bias} steering bias, model's observation "
          f"noise / {observation_scale:g}; "
          f"smoothed residuals' robust std {np.sqrt(drift.log_variance[0]):.5f} rad "
          f"(replicates {np.sqrt(drift.replicate_variance[0].mean()):.5f}); kappa(n) "
          f"{_columns(drift.kappa, WINDOWS, steps)}", flush=True)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--mrclam-robots", type=int, nargs="*", default=[])
    parser.add_argument("--mrclam-data", default=str(MRCLAM))
    parser.add_argument("--victoria-park-params", default=None, metavar="FILE")
    parser.add_argument("--observation-scale", type=float, default=1.0)
    parser.add_argument("--steering-bias", choices=("constant", "profile"), default="constant",
                        help="Victoria Park: the laser-only steering bias the controls take")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--replicates", type=int, default=3)
    parser.add_argument("--heading-scales", type=float, nargs="*", default=[])
    parser.add_argument("--filter-keys", type=int, default=6)
    parser.add_argument("--command-delay", type=float, default=0.0, metavar="SECONDS",
                        help="MRCLAM: apply each commanded velocity this much later "
                             "(a diagnostic: the robot's lag behind its commands)")
    parser.add_argument("--truth-only", action="store_true",
                        help="MRCLAM: only the growth against Vicon (item 1; seconds)")
    args = parser.parse_args(argv)
    if not args.mrclam_robots and args.victoria_park_params is None:
        parser.error("name --mrclam-robots and/or --victoria-park-params")
    if args.replicates < 1:
        parser.error(f"--replicates {args.replicates}: at least 1")
    if args.observation_scale <= 0.0:
        parser.error(f"--observation-scale {args.observation_scale}: a positive factor")
    if any(scale <= 0.0 for scale in args.heading_scales):
        parser.error(f"--heading-scales {args.heading_scales}: positive factors")
    if not np.isfinite(args.command_delay):
        parser.error(f"--command-delay {args.command_delay}: a finite number of seconds")
    if args.heading_scales and args.filter_keys < 1:
        parser.error(f"--filter-keys {args.filter_keys}: at least 1 with --heading-scales")
    for robot in args.mrclam_robots:
        if args.truth_only:
            print_truth_growth(mrclam_robot_log(args.mrclam_data, robot,
                                                args.command_delay)[0],
                               f"robot {robot}, commands {args.command_delay:+g} s, Vicon")
            continue
        mrclam_robot(args.mrclam_data, robot, args.seed, args.replicates, args.heading_scales,
                     args.filter_keys, args.command_delay)
    if args.victoria_park_params is not None:
        victoria_park(args.victoria_park_params, args.observation_scale, args.replicates,
                      args.seed, args.steering_bias)


if __name__ == "__main__":
    main()
