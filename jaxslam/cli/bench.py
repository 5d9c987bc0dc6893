"""``jaxslam bench``: the filter speed benchmark ``benchmarks/filter_step.py`` of the source
tree, loaded by its path (it is not part of the installed package)."""
from __future__ import annotations

import importlib.util
import pathlib

from jaxslam.cli import common
from jaxslam.cli.common import UsageError, simulator_errors


_REPO_ROOT = pathlib.Path(__file__).resolve().parents[2]

BENCHMARK_PATH = _REPO_ROOT / "benchmarks" / "filter_step.py"

BENCH_EPILOG = """\
Everything after "bench" goes to the script unchanged, except a first -h/--help (this help).
Put "--" first to pass -h/--help or anything else through explicitly.

examples:
  jaxslam bench                               the step case at (P, M, K) = (100, 64, 16)
                                              and (1000, 128, 16)
  jaxslam bench --batch-runs 1000 --chunk 250 also R = 1000 batched runs, 250 per chunk
  jaxslam bench --association greedy --proposal mixture
  jaxslam bench -- --help                     the script's own options

The script ships with the source tree, not the installed package: run from a checkout."""


def cmd_bench(args) -> int:
    """Run ``benchmarks/filter_step.py`` (imported by path: it is not part of the package)."""
    if not BENCHMARK_PATH.is_file():
        raise UsageError(f"the benchmark script {BENCHMARK_PATH} is not here (it ships with the "
                         "source tree, not the installed package); run from a source checkout")
    spec = importlib.util.spec_from_file_location("jaxslam_benchmark_filter_step", BENCHMARK_PATH)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    common.enable_compilation_cache()
    if hasattr(module, "main"):
        with simulator_errors():
            result = module.main(list(args.bench_args))
        return int(result) if isinstance(result, int) else 0
    raise UsageError(f"{BENCHMARK_PATH} defines no main(argv) function; run it directly with "
                     f"python {BENCHMARK_PATH}")
