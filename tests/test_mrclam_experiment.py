"""experiments/mrclam.py's barcode diagnostic (``with_barcodes``) on a tiny exact log."""
import argparse

import numpy as np
import pytest

import experiments.mrclam as experiment
from jaxslam.types import FilterConfig
from test_pipeline import _log  # tests/ is on sys.path (no tests/__init__.py)


@pytest.mark.slow  # two calibrations, about 20 s on this 2-core CPU
@pytest.mark.parametrize("barcodes, run_association", [("both", "known"),
                                                       ("calibration", "stable")])
def test_with_barcodes_calibrates_and_filters_an_exact_log(barcodes, run_association,
                                                           monkeypatch):
    """test_pipeline's straight drive past five trees, exact odometry and observations, with
    observation k of every step tree k; the ids are given on padding rows too, and must
    reach the filter as -1 there."""
    log = _log(30)
    ids = np.tile(np.arange(5), (30, 1))
    seen = []

    def recording(function):
        def wrapped(config, *args, **kwargs):
            obs = next(a for a in args if hasattr(a, "landmark_id"))  # the Observations
            seen.append((function.__name__, config.association,
                         np.asarray(obs.landmark_id).copy(), config.num_particles,
                         int(np.asarray(args[0])[-1])))  # PRNGKey(k)'s last word is k
            return function(config, *args, **kwargs)
        wrapped.__name__ = function.__name__
        return wrapped

    monkeypatch.setattr(experiment, "calibrate_params", recording(experiment.calibrate_params))
    monkeypatch.setattr(experiment, "run_filter", recording(experiment.run_filter))
    config = FilterConfig(num_particles=8, max_landmarks=16)
    ate, landmarks, info, key_runs = experiment.with_barcodes(
        log, ids, config, barcodes, seed=0, filter_keys=(100, 101), filter_particles=4)
    # The calibration and key 0 at the config's 8 particles, then keys 100 and 101 at 4.
    assert [(name, association, particles, key)
            for name, association, _, particles, key in seen] == [
        ("calibrate_params", "known", 8, 0), ("run_filter", run_association, 8, 0),
        ("run_filter", run_association, 4, 100), ("run_filter", run_association, 4, 101)]
    masked = np.where(log.obs_valid, ids, -1)
    for _, _, landmark_id, _, _ in seen:
        np.testing.assert_array_equal(landmark_id, masked)
    assert len(key_runs) == 2 and all(key_ate < 0.1 and kept == 5 for key_ate, kept in key_runs)
    # Exact odometry and observations: whichever association runs, the path stays on the
    # truth (the observations' calibrated floor is centimetres) and the five trees seen are
    # mapped once each.
    assert ate < 0.1
    assert landmarks == 5
    assert info.iterations >= 1 and info.verdict


def test_keys_summary_gives_the_median_and_each_ratio():
    line = experiment.keys_summary([2.0, 4.0, 3.0], 14, 3, 1000)
    assert line == ("   filter keys 100-102 (P = 1000): dead reckoning / filter ATE median "
                    "3.00x (2.00 4.00 3.00); landmarks kept, median 14")


def test_barcodes_refuse_the_options_they_do_not_run(capsys):
    for extra in (["--no-calibrate"], ["--close-loops"]):
        with pytest.raises(SystemExit):
            experiment.main(["--barcodes", "both", "--robots", "1", *extra])
        assert "--barcodes calibrates and filters only" in capsys.readouterr().err


def test_command_delay_argument(capsys):
    """``--command-delay``: "auto" or a finite number of seconds; auto needs the blind
    calibration, so --no-calibrate and --barcodes ask for a number."""
    assert experiment.command_delay_argument("auto") == "auto"
    assert experiment.command_delay_argument("0.25") == 0.25
    assert experiment.command_delay_argument("-0.1") == -0.1
    for text in ("nan", "inf", "soon"):
        with pytest.raises(argparse.ArgumentTypeError, match="'auto' or a finite number"):
            experiment.command_delay_argument(text)
    with pytest.raises(SystemExit):
        experiment.main(["--robots", "1", "--command-delay", "soon"])
    assert "'auto' or a finite number of seconds" in capsys.readouterr().err
    for extra in (["--no-calibrate"], ["--barcodes", "both"]):
        with pytest.raises(SystemExit):
            experiment.main(["--robots", "1", *extra])
        assert "--command-delay auto fits the delay" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        experiment.main(["--robots", "1", "--filter-keys", "-1"])
    assert "--filter-keys -1" in capsys.readouterr().err


def test_filter_particles_needs_a_count_and_the_filter_keys(capsys):
    """``--filter-particles N`` sets the particles of the ``--filter-keys`` runs: refused
    below 1 and without ``--filter-keys``, before any data is read."""
    for extra, message in ((["--filter-particles", "0", "--filter-keys", "2"],
                            "--filter-particles 0: expected 1 or more"),
                           (["--filter-particles", "1000"], "give --filter-keys N too")):
        with pytest.raises(SystemExit):
            experiment.main(["--robots", "1", "--data", "/nonexistent", *extra])
        assert message in capsys.readouterr().err


def test_start_params_sets_only_the_existence_cap():
    """``--existence-max X``: the starting settings (``starting_params`` when calibrating,
    ``default_params`` otherwise) with ``existence_max`` X and every other field unchanged;
    no value: None, so the pipeline picks its own default."""
    from jaxslam.self_calibration import starting_params
    from jaxslam.types import default_params

    config = FilterConfig()
    assert experiment.start_params(config, None) is None
    for calibrate, base in ((True, starting_params(config)), (False, default_params(config))):
        got = experiment.start_params(config, 1000.0, calibrate)
        assert float(got.existence_max) == 1000.0
        for name in base._fields:
            if name != "existence_max":
                np.testing.assert_array_equal(np.asarray(getattr(got, name)),
                                              np.asarray(getattr(base, name)), err_msg=name)


def test_keys_summary_adds_the_smoothed_ratios_and_counts_failures():
    line = experiment.keys_summary([2.0, 4.0, 3.0], 14, 3, 100, (5.0, float("nan"), 3.0))
    assert line.endswith("; smoothed: median 4.00x (5.00 nan 3.00), 1 smoother failures")
    assert experiment.keys_summary([2.0], 14, 1, 100, (1.5,)).endswith(
        "; smoothed: median 1.50x (1.50)")


def test_fit_gain_is_refused_where_nothing_is_calibrated_blind(capsys):
    """``--fit-gain`` fits in the blind calibration: refused with ``--no-calibrate`` and with
    ``--barcodes``, before any data is read."""
    for extra, message in ((["--no-calibrate", "--command-delay", "0"],
                            "--fit-gain fits the gains in the calibration"),
                           (["--barcodes", "both", "--command-delay", "0"],
                            "--barcodes calibrates and filters only")):
        with pytest.raises(SystemExit):
            experiment.main(["--robots", "1", "--data", "/nonexistent", "--fit-gain", *extra])
        assert message in capsys.readouterr().err


def test_fit_gain_reaches_the_calibration(monkeypatch):
    """``--fit-gain`` hands ``calibrate_gain=True`` to the pipeline's calibration, and
    without it False (the library's default); the log itself is replaced by a stub."""
    seen = []

    class Stop(Exception):
        pass

    def filter_log(log, config, params, key, **options):
        seen.append(options["calibration_options"])
        raise Stop

    monkeypatch.setattr(experiment, "read_mrclam", lambda data, robot: None)
    monkeypatch.setattr(experiment, "mrclam_steps", lambda raw, max_obs: None)
    monkeypatch.setattr(experiment, "mrclam_log", lambda raw, steps, **kw: _log(5))
    monkeypatch.setattr(experiment.pipeline, "filter_log", filter_log)
    for extra in ([], ["--fit-gain"], ["--em-iterations", "2"], ["--em-significance", "0.05"]):
        with pytest.raises(Stop):
            experiment.main(["--robots", "1", *extra])
    assert seen == [{"calibrate_gain": False}, {"calibrate_gain": True},
                    {"calibrate_gain": False, "iterations": 2},
                    {"calibrate_gain": False, "significance": 0.05}]


def test_em_significance_is_refused_outside_0_1_or_without_a_calibration(capsys):
    for extra, message in ((["--em-significance", "1.0"], "expected a level in (0, 1), or 0"),
                           (["--em-significance", "-0.5"], "expected a level in (0, 1), or 0"),
                           (["--em-significance", "0.05", "--no-calibrate", "--command-delay",
                             "0"], "not without a calibration (--no-calibrate)")):
        with pytest.raises(SystemExit):
            experiment.main(["--robots", "1", "--data", "/nonexistent", *extra])
        assert message in capsys.readouterr().err


def test_em_iterations_is_refused_below_one_or_without_a_calibration(capsys):
    for extra in (["--em-iterations", "0"],
                  ["--em-iterations", "2", "--no-calibrate", "--command-delay", "0"]):
        with pytest.raises(SystemExit):
            experiment.main(["--robots", "1", "--data", "/nonexistent", *extra])
        assert "expected 1 or more, and a calibration" in capsys.readouterr().err


def test_proposal_and_mixture_ratio_reach_the_pipeline(monkeypatch):
    """``--proposal mixture --mixture-ratio 0.9``: the pipeline gets a config with the
    mixture proposal and starting settings with phi 0.9 (every other field the
    ``starting_params`` one); without the options the library's proposal and None (the
    pipeline's own starting settings)."""
    from jaxslam.self_calibration import starting_params

    seen = []

    class Stop(Exception):
        pass

    def filter_log(log, config, params, key, **options):
        seen.append((config.proposal, params))
        raise Stop

    monkeypatch.setattr(experiment, "read_mrclam", lambda data, robot: None)
    monkeypatch.setattr(experiment, "mrclam_steps", lambda raw, max_obs: None)
    monkeypatch.setattr(experiment, "mrclam_log", lambda raw, steps, **kw: _log(5))
    monkeypatch.setattr(experiment.pipeline, "filter_log", filter_log)
    for extra in ([], ["--proposal", "mixture", "--mixture-ratio", "0.9"]):
        with pytest.raises(Stop):
            experiment.main(["--robots", "1", *extra])
    assert seen[0] == ("observation", None)
    proposal, params = seen[1]
    assert proposal == "mixture"
    base = starting_params(FilterConfig(proposal="mixture"))
    assert float(params.mixture_ratio) == pytest.approx(0.9)
    for name in base._fields:
        if name != "mixture_ratio":
            np.testing.assert_array_equal(np.asarray(getattr(params, name)),
                                          np.asarray(getattr(base, name)), err_msg=name)


def test_mixture_ratio_is_refused_without_the_mixture_or_outside_0_1(capsys):
    for extra in (["--mixture-ratio", "0.9"],
                  ["--proposal", "mixture", "--mixture-ratio", "1.5"],
                  ["--proposal", "mixture", "--mixture-ratio", "-0.1"]):
        with pytest.raises(SystemExit):
            experiment.main(["--robots", "1", "--data", "/nonexistent", *extra])
        assert "expected a probability in [0, 1] with --proposal mixture" in (
            capsys.readouterr().err)


def test_pooled_summary_by_hand():
    """Six runs online (two at 3x or more) and smoothed with one smoother failure, which
    is left out of the smoothed figures and counted."""
    line = experiment.pooled_summary(2, [1.0, 3.0, 2.0, 4.0, 2.5, 1.5],
                                     [3.5, float("nan"), 2.0, 1.0, 3.0, 4.0], 2, 3)
    assert line == ("robot 2, 2 calibration seeds x 3 filter keys: online median 2.25x "
                    "(1.00-4.00), 2 of 6 at 3x or more; smoothed median 3.00x (1.00-4.00), "
                    "3 of 5 at 3x or more; 1 smoother failures")


def test_each_seed_calibrates_each_robot_and_the_keys_are_pooled(monkeypatch, capsys):
    """``--seed 0 1 --robots 1 2 --filter-keys 2``: one calibration per robot and seed,
    robots in the outer loop, and each robot's keys pooled over its seeds into one line
    (the per-seed runs stubbed: robot r, seed s gives ratios r + s and r + s + 1 online,
    twice that smoothed, with one smoother failure for robot 2, seed 1)."""
    calls = []

    def robot_seed(args, config, robot, seed):
        calls.append((robot, seed))
        online = [robot + seed, robot + seed + 1.0]
        smoothed = [2 * r for r in online]
        if (robot, seed) == (2, 1):
            smoothed[1] = float("nan")
        return (4.0, 2.0, 1.0, 10, 5), online, smoothed

    monkeypatch.setattr(experiment, "robot_seed", robot_seed)
    experiment.main(["--robots", "1", "2", "--seed", "0", "1", "--filter-keys", "2"])
    assert calls == [(1, 0), (1, 1), (2, 0), (2, 1)]
    out = capsys.readouterr().out.splitlines()
    # Robot 1: online 1, 2, 2, 3 (median 2), smoothed 2, 4, 4, 6; robot 2: online 2, 3, 3,
    # 4, smoothed 4, 6, 6 and a failure.
    assert out[-2] == experiment.pooled_summary(1, [1, 2, 2, 3], [2, 4, 4, 6], 2, 2)
    assert out[-1] == experiment.pooled_summary(2, [2, 3, 3, 4], [4, 6, 6, float("nan")],
                                                2, 2)
    assert out[-2].startswith("robot 1, 2 calibration seeds x 2 filter keys: online median "
                              "2.00x (1.00-3.00), 1 of 4 at 3x or more; smoothed median 4.00x")
    assert out[-1].endswith("3 of 3 at 3x or more; 1 smoother failures")


def test_each_seed_reaches_the_pipeline_with_its_key(monkeypatch):
    """``robot_seed`` calibrates with PRNGKey(seed), and passes ``--fit-gain`` on."""
    import types

    import jax

    seen = []

    class Stop(Exception):
        pass

    def filter_log(log, config, params, key, **options):
        seen.append((np.asarray(key).tolist(), options["calibration_options"]))
        raise Stop

    monkeypatch.setattr(experiment, "read_mrclam", lambda data, robot: None)
    monkeypatch.setattr(experiment, "mrclam_steps", lambda raw, max_obs: None)
    monkeypatch.setattr(experiment, "mrclam_log", lambda raw, steps, **kw: _log(5))
    monkeypatch.setattr(experiment.pipeline, "filter_log", filter_log)
    args = types.SimpleNamespace(data="unused", command_delay="auto", seed=[0, 7],
                                 barcodes="none", existence_max=None, no_calibrate=False,
                                 close_loops=False, fit_gain=True, filter_keys=0,
                                 particles=100, filter_particles=None, mixture_ratio=None)
    for seed in (0, 7):
        with pytest.raises(Stop):
            experiment.robot_seed(args, FilterConfig(), 1, seed)
    assert seen == [(np.asarray(jax.random.PRNGKey(seed)).tolist(), {"calibrate_gain": True})
                    for seed in (0, 7)]
