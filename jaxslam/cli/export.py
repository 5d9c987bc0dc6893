"""``jaxslam export``: a run's true, estimated and smoothed trajectories as TUM text (for evo),
from a folder's example run or from run I / condition C of a study, simulated again."""
from __future__ import annotations

import pathlib

from jaxslam.cli import common
from jaxslam.cli.common import UsageError, simulator_errors


TUM_HEADER = "# timestamp x y z qx qy qz qw"


def yaw_to_quaternion(yaw):
    """(qx, qy, qz, qw) of a rotation by ``yaw`` about +z. yaw: (T,) -> four (T,) arrays."""
    import numpy as np

    half = 0.5 * np.asarray(yaw, np.float64)
    zero = np.zeros_like(half)
    return zero, zero, np.sin(half), np.cos(half)


def tum_lines(timestamps, poses) -> list[str]:
    """TUM trajectory lines ``timestamp x y z qx qy qz qw`` of planar poses (T, 3)."""
    import numpy as np

    poses = np.asarray(poses, np.float64)
    if poses.ndim != 2 or poses.shape[1] != 3:
        raise UsageError(f"poses have shape {poses.shape}; expected (T, 3) rows (x, y, theta)")
    qx, qy, qz, qw = yaw_to_quaternion(poses[:, 2])
    rows = np.stack([np.asarray(timestamps, np.float64), poses[:, 0], poses[:, 1],
                     np.zeros(len(poses)), qx, qy, qz, qw], axis=1)
    return [" ".join(f"{value:.9f}" for value in row) for row in rows]


def _step_times(truth, estimate, dt: float):
    """Timestamps on a step time base: truth row k is the pose after k steps when the truth
    has one more row than the estimate (a study: row 0 is the start), else after k + 1
    steps; estimate row t is the pose after step t + 1. Returns (truth times, estimate times).
    """
    import numpy as np

    first = 0 if len(truth) == len(estimate) + 1 else 1
    return ((first + np.arange(len(truth), dtype=np.float64)) * dt,
            (1 + np.arange(len(estimate), dtype=np.float64)) * dt)


def _example_tracks(source: pathlib.Path, dt) -> list[tuple[str, object, object]]:
    """(name, timestamps, poses) of an example_run.npz: truth (when it has rows), estimate,
    smoothed (when it holds smoothed_pose). A log run's own ``time`` is the time base, else
    ``dt`` seconds per step (default 1)."""
    import numpy as np

    from jaxslam import plots

    try:
        run = plots.load_example_run(source)
    except ValueError as error:
        raise UsageError(f"{source}: {error}") from error
    with np.load(source, allow_pickle=False) as arrays:
        extra = {name: arrays[name] for name in ("time", "smoothed_pose") if name in arrays}
    if "time" in extra:
        if dt is not None:
            raise UsageError(f"--dt {dt}: {source} holds its log's own timestamps (time), which "
                             "the export uses; leave --dt out")
        times = np.asarray(extra["time"], np.float64)
        if times.shape != (len(run.mean_pose),):
            raise UsageError(f"{source}: time has shape {times.shape}; expected "
                             f"({len(run.mean_pose)},), one timestamp per mean_pose row")
        if len(run.truth_pose) not in (0, len(times)):
            raise UsageError(f"{source}: truth_pose has {len(run.truth_pose)} rows; expected "
                             f"{len(times)}, one per timestamp (or none)")
        truth_times, estimate_times = times, times
    else:
        truth_times, estimate_times = _step_times(run.truth_pose, run.mean_pose,
                                                  1.0 if dt is None else dt)
    tracks = [("estimate", estimate_times, run.mean_pose)]
    if len(run.truth_pose):
        tracks.insert(0, ("truth", truth_times, run.truth_pose))
    if "smoothed_pose" in extra:
        smoothed = np.asarray(extra["smoothed_pose"], np.float64)
        if smoothed.shape != run.mean_pose.shape:
            raise UsageError(f"{source}: smoothed_pose has shape {smoothed.shape}; expected "
                             f"{run.mean_pose.shape} like mean_pose")
        tracks.append(("smoothed", estimate_times, smoothed))
    return tracks


def read_study_folder_config(folder: pathlib.Path):
    """The ``StudyConfig`` of a study folder (its study.toml); UsageError when there is none
    or it cannot be read."""
    import tomllib

    from jaxslam import studies

    path = folder / "study.toml"
    if not path.is_file():
        raise UsageError(f"{path} does not exist; --run and --condition need a study folder "
                         "(written by jaxslam demo, study or sweep)")
    try:
        with open(path, "rb") as handle:
            return studies.study_config_from_dict(tomllib.load(handle))
    except (tomllib.TOMLDecodeError, ValueError, TypeError) as error:
        raise UsageError(f"{path}: cannot read the study config ({error})") from error


def _check_run_and_condition(config, folder, run: int, condition: int) -> None:
    """UsageError naming the valid range when run or condition is outside the study."""
    if not 0 <= run < config.num_runs:
        raise UsageError(f"--run {run} is out of range: the study in {folder} has runs 0 to "
                         f"{config.num_runs - 1} (num_runs = {config.num_runs})")
    conditions = config.conditions
    if not 0 <= condition < len(conditions):
        listed = "; ".join(f"{i}: " + (", ".join(f"{k}={v}" for k, v in c.items()) or "default")
                           for i, c in enumerate(conditions))
        raise UsageError(f"--condition {condition} is out of range: the study in {folder} has "
                         f"conditions 0 to {len(conditions) - 1} ({listed})")


def _study_run_tracks(folder: pathlib.Path, run: int, condition: int, dt):
    """(name, timestamps, poses) of run ``run`` under condition ``condition`` of a study,
    simulated and filtered again (``studies.recompute_runs``: the same numbers as the stored
    ones). The time base is ``dt`` seconds per step (default 1): the simulated scenario has
    no clock of its own."""
    import numpy as np

    config = read_study_folder_config(folder)
    _check_run_and_condition(config, folder, run, condition)
    from jaxslam import studies

    common.enable_compilation_cache()
    print(f"recomputing run {run} of {folder} (all {len(config.conditions)} condition(s))",
          flush=True)
    with simulator_errors():
        output = studies.recompute_runs(config, run, run + 1)
    truth = np.asarray(output.scenario.truth_pose, np.float64)
    truth = truth[0] if truth.ndim == 3 else truth  # a per-run world: this run's own path
    estimate = np.asarray(output.example["mean_pose"], np.float64)[condition, 0]
    truth_times, estimate_times = _step_times(truth, estimate, 1.0 if dt is None else dt)
    return [("truth", truth_times, truth), ("estimate", estimate_times, estimate)]


def _write_tum(out: pathlib.Path, tracks) -> list[pathlib.Path]:
    """Write ``<name>.tum`` per (name, timestamps, poses); print each."""
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for name, times, poses in tracks:
        path = out / f"{name}.tum"
        path.write_text("\n".join([TUM_HEADER] + tum_lines(times, poses)) + "\n")
        written.append(path)
        print(f"wrote {path} ({len(poses)} poses)")
    return written


def cmd_export(args) -> int:
    """Write a run's true and estimated trajectories (and the smoothed one when the run has
    it) as TUM text for evo: the example run of a folder, or run I / condition C of a study."""
    import numpy as np

    results = pathlib.Path(args.results_dir)
    if args.run is not None or args.condition is not None:
        if not results.is_dir():
            raise UsageError(f"{results} is not a folder; --run and --condition need a study "
                             "folder holding study.toml")
        run, condition = args.run or 0, args.condition or 0
        tracks = _study_run_tracks(results, run, condition, args.dt)
        default_out = results / f"run-{run}-condition-{condition}"
    else:
        source = results / "example_run.npz" if results.is_dir() else results
        if not source.is_file():
            raise UsageError(f"{source} does not exist; expected a study folder holding "
                             "example_run.npz (run a study or `jaxslam run` first)")
        tracks = _example_tracks(source, args.dt)
        default_out = source.parent
    written = _write_tum(pathlib.Path(args.out) if args.out else default_out, tracks)
    poses = {name: pose for name, _, pose in tracks}
    if "truth" in poses:
        final = float(np.hypot(*(poses["estimate"][-1, :2] - poses["truth"][-1, :2])))
        print(f"final position error {final:.6g} m")
        print(f"compare with evo:  evo_ape tum {written[0]} {written[1]} --align")
    else:
        print("(the run has no truth poses: only the estimate is written)")
    return 0
