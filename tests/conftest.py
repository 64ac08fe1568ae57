"""Test configuration.

* float64 everywhere (metrology is validated in float64).
* Measured figures: whatever a passing test prints (conformance errors,
  accuracy against ground truth, the null it beats) is collected and shown in
  one "measured figures" section at the end of the run, so the numbers the
  tests assert are visible in CI output without ``-s``.
"""

import gc
import os
import time

# One BLAS/LAPACK thread per test process. numpy, scipy and jaxlib's CPU linear algebra call
# OpenBLAS, which by default starts a thread per core and spin-waits between calls; with two
# xdist workers on two cores (and more so on a shared machine) those threads fight each
# other. Measured on a loaded 2-core machine: one compiled 14-view calibrate_camera call
# took 2-3 s of CPU (12-21 s wall) with the default and 0.07 s (0.6-0.8 s wall) with one
# thread; results are identical. Set before numpy is imported (pytest and its plugins do not
# import it); a value given by the caller is kept.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

# XLA compiles thousands of small programs in this suite (eager op-by-op dispatch compiles
# one per primitive and shape) and compilation, not execution, dominates its run time.
# LLVM's optimisation level changes speed only, not results: XLA:CPU does not enable
# fast-math, so IEEE semantics hold at every level. Level 0 cut the suite's heaviest files by
# ~20 % (measured: splat training + rasteriser + ICP files 119 s -> 97 s on 2 cores).
# Set before jax initialises its backend; an XLA_FLAGS given by the caller is kept.
if "xla_backend_optimization_level" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " --xla_backend_optimization_level=0").strip()
# Not set here: XLA:CPU's older loop emitters (--xla_cpu_use_fusion_emitters=false), which compile
# 1.5-2x faster. Together with level 0 above they miscompile: measure_pos on a three-edge profile
# returns five edges (tools/repro_xla_emitters_level0.py; each flag alone gives three), and ICP
# stops converging (docs/benchmarks_icp.md). A clean-clone run with both (stop 34) failed 8 tests.

import jax  # noqa: E402
import pytest  # noqa: E402

jax.config.update("jax_enable_x64", True)
# Clean-clone runs hung inside XLA:CPU (main thread in BlockUntilReady on a vmapped
# model-selection fit, every XLA thread idle). The cause (gdb stacks; tools/repro_xla_hang.py):
# jaxlib 0.10's batched LAPACK kernels (eigh, LU, QR, ...) split their batch onto XLA:CPU's
# intra-op pool and block on it; when as many of them run at once as the pool has threads (2
# here), no thread is left to do the work. select_model, the 3-D primitive fits and
# photometric_stereo now use no LAPACK (fsjax/_linalg.py) and the 200-per-model test
# runs again. Synchronous CPU dispatch does not prevent the deadlock (measured); it is kept
# because every full run since has used it. A hang elsewhere is ended by pytest-timeout's
# thread method (pyproject: timeout_method = "thread") with every stack dumped, failing the
# test instead of stalling the run.
jax.config.update("jax_cpu_enable_async_dispatch", False)


# Every executable XLA:CPU compiles holds a few memory mappings (about 3 each) until it
# is released. A test worker that compiles ~20,000 programs (the registry-wide contract
# suite does) reaches the kernel's ``vm.max_map_count`` (65,530 by default); mmap then
# fails inside the JIT linker and the worker dies ("Failed to materialize symbols",
# SIGSEGV/SIGABRT in backend_compile). So when a worker passes half of the limit, the
# compilation caches are dropped between tests (programs are recompiled on demand).
@pytest.fixture(autouse=True)
def _release_compiled_programs():
    yield
    from fsjax._cache import near_map_limit

    if near_map_limit():
        jax.clear_caches()
        gc.collect()

_FIGURES: list[tuple[str, str]] = []


def pytest_runtest_logreport(report):
    if report.when == "call" and report.passed and report.capstdout.strip():
        _FIGURES.append((report.nodeid, report.capstdout.strip()))


def pytest_terminal_summary(terminalreporter, exitstatus, config):
    if getattr(config, "_fsjax_cache", "") and _SAVED["hits"] + _SAVED["misses"]:
        terminalreporter.write_line(
            f"compile cache ({'shared, per run' if getattr(config, '_fsjax_cache_own', False) else config._fsjax_cache}): "
            f"{_SAVED['hits']} programs loaded, {_SAVED['misses']} compiled and offered, "
            f"{round(_SAVED['saved_s'])} s of compilation saved (as recorded at compile time)")
    if not _FIGURES:
        return
    terminalreporter.section("measured figures (printed by passing tests)")
    for nodeid, text in _FIGURES:
        terminalreporter.write_line(nodeid)
        for line in text.splitlines():
            if line.strip():
                terminalreporter.write_line("    " + line.rstrip())


# ---------------------------------------------------------------------------
# Time budget. CI gives a run 90 minutes in all, on a machine that may be shared and much
# slower than a developer's (a run that took 23 min on an idle machine here did not finish
# in 90 min there). Tests marked ``slow`` run last; once the session has used its budget
# (FSJAX_TEST_BUDGET_S, default 3600 s from the start of the session), every test not yet
# started is skipped with a reason that says so -- visible in the ``-rs`` summary, never a
# silent pass -- so that a slow machine gives a partial run rather than none.
# FSJAX_TEST_BUDGET_S=0 disables the budget.
# ---------------------------------------------------------------------------
def _budget_s() -> float:
    try:
        return float(os.environ.get("FSJAX_TEST_BUDGET_S", "3600"))
    except ValueError:
        return 3600.0


# ---------------------------------------------------------------------------
# One persistent compilation cache shared by the xdist workers of a run. A program compiled
# by one worker (or by the same worker again after the map-count release above, or from a
# fresh ``jax.jit(lambda ...)`` that traces to the same program in another test) is loaded
# from disk instead of compiled. ``FSJAX_CACHE_DIR`` set by the caller is used as is (a
# developer's warm re-run; ``off`` disables it); otherwise each run gets its own new
# directory (a cold cache, as CI has), removed at the end of the run. The compile time the
# cache saved is printed in the summary.
# ---------------------------------------------------------------------------
_SAVED = {"hits": 0, "misses": 0, "saved_s": 0.0}


def _count_cache_event(name, **kw):
    if name == "/jax/compilation_cache/cache_hits":
        _SAVED["hits"] += 1
    elif name == "/jax/compilation_cache/cache_misses":
        _SAVED["misses"] += 1


def _count_cache_saving(name, secs, **kw):
    if name == "/jax/compilation_cache/compile_time_saved_sec":
        _SAVED["saved_s"] += float(secs)


def _enable_test_cache(path):
    import fsjax

    if path:
        fsjax.enable_compile_cache(path, min_compile_time_s=0.05)
        jax.monitoring.register_event_listener(_count_cache_event)
        jax.monitoring.register_event_duration_secs_listener(_count_cache_saving)


def pytest_configure(config):
    if not hasattr(config, "workerinput"):  # controller (or a run without xdist)
        config._fsjax_t0 = time.time()
        env = os.environ.get("FSJAX_CACHE_DIR")
        if env is not None:
            config._fsjax_cache = "" if env.strip().lower() in {"off", "0", "none", "false", "no", ""} else env
            config._fsjax_cache_own = False
        else:
            import tempfile

            config._fsjax_cache = tempfile.mkdtemp(prefix="fsjax-test-xla-")
            config._fsjax_cache_own = True
    else:
        config._fsjax_t0 = float(config.workerinput.get("fsjax_t0", time.time()))
        config._fsjax_cache = config.workerinput.get("fsjax_cache", "")
        config._fsjax_cache_own = False
    _enable_test_cache(config._fsjax_cache)


def pytest_unconfigure(config):
    if getattr(config, "_fsjax_cache_own", False):
        import shutil

        shutil.rmtree(config._fsjax_cache, ignore_errors=True)


@pytest.hookimpl(optionalhook=True)
def pytest_configure_node(node):  # xdist hook, called on the controller for each worker
    node.workerinput["fsjax_t0"] = node.config._fsjax_t0
    node.workerinput["fsjax_cache"] = node.config._fsjax_cache


@pytest.hookimpl(optionalhook=True)
def pytest_testnodedown(node, error):  # xdist: collect each worker's cache figures
    out = getattr(node, "workeroutput", {}) or {}
    for k in _SAVED:
        _SAVED[k] += out.get("fsjax_cache_" + k, 0)


def pytest_sessionfinish(session, exitstatus):
    wo = getattr(session.config, "workeroutput", None)
    if wo is not None:  # a worker: hand its figures to the controller
        for k, v in _SAVED.items():
            wo["fsjax_cache_" + k] = v


def pytest_collection_modifyitems(config, items):
    items.sort(key=lambda it: it.get_closest_marker("slow") is not None)  # stable: slow suites last


def pytest_runtest_setup(item):
    budget = _budget_s()
    if budget > 0:
        used = time.time() - item.config._fsjax_t0
        if used > budget:
            pytest.skip(f"time budget exhausted (FSJAX_TEST_BUDGET_S={budget:.0f} s): this test did not run")
