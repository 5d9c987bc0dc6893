"""Monte Carlo studies and sweeps: chunked, seeded, resumable, one compiled program per study.

A study is R runs of a simulated scenario under one ``FilterConfig``, optionally over a grid of
``Params`` values (a sweep: G conditions). The runs come from the simulator the config names
(``jaxslam.simulators``: a plugin loaded by its module name, "sims" by default) or from a
``simulate`` function passed to ``run_study``; this package imports no simulator. Run i uses
``fold_in(PRNGKey(seed), i)`` for both its scenario and its filter, so every condition sees
the same forests, paths and noise (common random numbers). Every (run, condition) pair goes
through one compiled program of fixed width ``run_width`` (per device), so on one machine
type a run's numbers are bit-identical whatever the chunk size, the number of runs or
conditions, or the device count (``_ChunkRunner``).

The results folder (layout, integrity manifest, lock, resume rules) is described in
``jaxslam.study_store``: chunks of runs in ``runs/`` (Parquet, one row per (run, condition),
units and the resolved config in the schema metadata), per-step traces in ``traces/``, a
SHA-256 manifest checked on resume, and an exclusive lock while a process computes.
``num_runs`` can grow on resume (the new runs only are computed).

Modules: ``scoring`` (the traced filter and metrics of one (run, condition) pair), ``runner``
(chunks of runs through one compiled program, and ``run_study``), ``chunks`` (a chunk's
columns and files, and reading them back) and ``summary`` (per-condition statistics,
``summary.md``).
"""
from jaxslam.columns import COLUMN_UNITS, column_unit
from jaxslam.simulators import (RunBatch, Simulator, SimulatorUnavailable, load_simulator,
                                register_simulator)
from jaxslam.studies.chunks import (load_results, open_study, run_keys, run_world_of,
                                    write_chunk)
from jaxslam.studies.runner import (_COMPILED, ChunkOutput, StudyResult,  # noqa: F401
                                    _ChunkRunner, recompute_runs, run_study)
from jaxslam.studies.scoring import condition_params, scenario_batch
from jaxslam.studies.summary import (SUMMARY_METRICS, filter_throughput, summarize_study,
                                     summary_rows, warning_lines)
from jaxslam.study_config import (StudyConfig, demo_study_config, load_study_config,
                                  study_config_from_dict, study_config_to_dict)
from jaxslam.study_store import StudyError, foreign_files

# ``_ChunkRunner`` and its program cache ``_COMPILED`` are used by ``jaxslam.ray_backend`` and
# the tests; the rest is the public interface of a study.
__all__ = [
    "COLUMN_UNITS", "SUMMARY_METRICS", "ChunkOutput", "RunBatch", "Simulator",
    "SimulatorUnavailable", "StudyConfig", "StudyError", "StudyResult", "column_unit",
    "condition_params", "demo_study_config", "filter_throughput", "foreign_files",
    "load_results", "load_simulator", "load_study_config", "open_study", "recompute_runs",
    "register_simulator", "run_keys", "run_study", "run_world_of", "scenario_batch",
    "study_config_from_dict", "study_config_to_dict", "summarize_study", "summary_rows",
    "warning_lines",
    "write_chunk",
]
