"""Test configuration: float64 available, silent broadcasting turned into errors, and the
persistent compilation cache kept out of the test process, XLA's backend optimisation turned
down (compiling is most of the default tier's time; ``JAXSLAM_TEST_OPTIMIZED=1`` keeps it).

Subprocess tests (the ``jaxslam`` command) share a cache of this session's own, removed when
the session ends (unless ``JAXSLAM_CACHE_DIR`` is set: then that folder is used and kept).
In this process a test that calls ``cli.main`` turns the persistent cache on
(``cli.enable_compilation_cache``); it is turned off again after that test, because writing
some of the later tests' executables to it aborted the process
(jax 0.10.2 on the CPU, ``compilation_cache.put_executable_and_time``, seen twice in full
runs).
"""
import atexit
import importlib.util
import os
import pathlib
import shutil
import subprocess
import sys
import tempfile

import jax
import pytest

if "JAXSLAM_CACHE_DIR" not in os.environ:  # pytest-xdist workers inherit the controller's
    os.environ["JAXSLAM_CACHE_DIR"] = tempfile.mkdtemp(prefix="jaxslam-test-cache-")
    atexit.register(shutil.rmtree, os.environ["JAXSLAM_CACHE_DIR"], ignore_errors=True)

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")
# Most of the default tier's time is XLA compiling small programs that then run for
# milliseconds, so XLA's backend (LLVM) optimisation is turned down. There is no fast-math at
# either level, but rounding can differ between the levels (instruction selection, fused
# multiply-adds): a 12-step float32 final error moved by 3.4e-5 m (5.6e-6 m between two
# optimised programs), and one chaotic run ended 0.48 m off instead of 3.10 m.
# JAXSLAM_TEST_OPTIMIZED=1 tests the fully optimised programs; the benchmarks and the
# ``jaxslam`` subprocesses that tests start always run at that level. The flag is not part
# of the key of JAX's in-memory compilation caches, so it is set once, here, before anything
# compiles.
OPTIMISATION_TURNED_DOWN = os.environ.get("JAXSLAM_TEST_OPTIMIZED", "") in ("", "0")
jax.config.update("jax_disable_most_optimizations", OPTIMISATION_TURNED_DOWN)
# XLA:CPU's older emitters compile the filter's programs about 35 % faster than its fusion
# emitters when optimisation is turned down (a filter-loop and a proposal-rounds test: 40 s
# -> 26-28 s in one process, jax 0.10.2), so the default tier (``-m "not slow"``, turned
# down) uses them (``pytest_configure``); with optimisation on they changed no program's
# speed (docs/results.md, throughput). The slow tier and ``JAXSLAM_TEST_OPTIMIZED=1`` keep
# XLA's defaults, as the slow tier's bit-identity checks were measured with them. The
# ``jaxslam`` and study subprocesses that tests start inherit the flag (the CLI's run
# optimised with the older emitters), and a test that sets its child's XLA_FLAGS starts from
# ``JAXSLAM_TEST_XLA_FLAGS`` (the child then compiles what this process compiles).
FASTER_COMPILING = "--xla_cpu_use_fusion_emitters=false"


def _starts_with(flags: str) -> bool:
    """Whether this jaxlib's CPU backend starts with ``flags`` added to XLA_FLAGS (XLA
    aborts the process on a flag it does not know; a probe that hangs counts as no)."""
    env = dict(os.environ, XLA_FLAGS=f"{os.environ.get('XLA_FLAGS', '')} {flags}".strip())
    try:
        probe = subprocess.run([sys.executable, "-c", "import jax; jax.devices('cpu')"],
                               env=env, capture_output=True, timeout=300)
    except subprocess.TimeoutExpired:
        return False
    return probe.returncode == 0


def pytest_configure(config):
    """Add ``FASTER_COMPILING`` to XLA_FLAGS for the default tier, before anything starts
    XLA's CPU backend. The first test process keeps the user's own XLA_FLAGS and the probe's
    answer in the environment, so pytest-xdist's workers (started after this) decide alike
    and probe nothing; a user's own setting of the emitters wins."""
    user = os.environ.setdefault("JAXSLAM_TEST_USER_XLA_FLAGS", os.environ.get("XLA_FLAGS", ""))
    wanted = (OPTIMISATION_TURNED_DOWN and config.option.markexpr == "not slow"
              and "xla_cpu_use_fusion_emitters" not in user)
    if wanted and "JAXSLAM_TEST_FLAG_PROBE" not in os.environ:
        os.environ["JAXSLAM_TEST_FLAG_PROBE"] = "1" if _starts_with(FASTER_COMPILING) else "0"
    used = wanted and os.environ["JAXSLAM_TEST_FLAG_PROBE"] == "1"
    os.environ["JAXSLAM_TEST_XLA_FLAGS"] = FASTER_COMPILING if used else ""
    os.environ["XLA_FLAGS"] = f"{user} {os.environ['JAXSLAM_TEST_XLA_FLAGS']}".strip()


def pytest_report_header(config):
    return f"XLA_FLAGS added by the tests: {os.environ['JAXSLAM_TEST_XLA_FLAGS'] or 'none'}"


@pytest.fixture(scope="session")
def load_benchmark():
    """``load(name)`` imports ``benchmarks/<name>.py`` by its path (the folder is scripts, not
    a package) and returns the module."""
    folder = pathlib.Path(__file__).resolve().parent.parent / "benchmarks"

    def load(name: str):
        spec = importlib.util.spec_from_file_location(f"benchmark_{name}", folder / f"{name}.py")
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        return module

    return load


@pytest.fixture(autouse=True)
def _persistent_cache_off_after_each_test():
    yield
    if jax.config.jax_compilation_cache_dir is not None:
        from jax._src import compilation_cache

        jax.config.update("jax_compilation_cache_dir", None)
        compilation_cache.reset_cache()


def _num_memory_mappings() -> int:
    try:
        with open("/proc/self/maps") as maps:
            return sum(1 for _ in maps)
    except OSError:  # not Linux: no limit to watch
        return 0


# Free compiled programs once the process holds this many memory mappings (the kernel's
# default limit, vm.max_map_count, is 65,530).
MAPPINGS_BEFORE_CLEARING = 30_000


@pytest.fixture(autouse=True, scope="module")
def _free_compiled_programs_when_mappings_run_high():
    """Drop every compiled program after a test module when the process holds many memory
    mappings. Each XLA:CPU executable keeps a few (measured about 3.7 per small program); a
    whole default-tier run compiled enough to approach the kernel's limit of 65,530, and
    then crashed inside the XLA compiler. Clearing only when needed keeps the programs that
    later modules reuse."""
    yield
    if _num_memory_mappings() < MAPPINGS_BEFORE_CLEARING:
        return
    import gc
    import sys

    jax.clear_caches()
    studies = sys.modules.get("jaxslam.studies")
    if studies is not None:
        studies._COMPILED.clear()
    gc.collect()
