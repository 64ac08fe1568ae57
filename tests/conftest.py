"""Test configuration.

* float64 everywhere (metrology is validated in float64).
* Measured figures: whatever a passing test prints (conformance errors,
  accuracy against ground truth, the null it beats) is collected and shown in
  one "measured figures" section at the end of the run, so the numbers the
  tests assert are visible in CI output without ``-s``.
"""

import gc

import jax
import pytest

jax.config.update("jax_enable_x64", True)


# Every executable XLA:CPU compiles holds a few memory mappings (about 3 each) until it
# is released. A test worker that compiles ~20,000 programs (the registry-wide contract
# suite does) reaches the kernel's ``vm.max_map_count`` (65,530 by default); mmap then
# fails inside the JIT linker and the worker dies ("Failed to materialize symbols",
# SIGSEGV/SIGABRT in backend_compile). So when a worker passes half of the limit, the
# compilation caches are dropped between tests (programs are recompiled on demand).
def _map_limit() -> int:
    try:
        with open("/proc/sys/vm/max_map_count") as f:
            return int(f.read())
    except (OSError, ValueError):
        return 65530


_MAP_LIMIT = _map_limit()


def _n_maps() -> int:
    try:
        with open("/proc/self/maps", "rb") as f:
            return sum(1 for _ in f)
    except OSError:
        return 0


@pytest.fixture(autouse=True)
def _release_compiled_programs():
    yield
    if _n_maps() > _MAP_LIMIT // 2:
        jax.clear_caches()
        gc.collect()

_FIGURES: list[tuple[str, str]] = []


def pytest_runtest_logreport(report):
    if report.when == "call" and report.passed and report.capstdout.strip():
        _FIGURES.append((report.nodeid, report.capstdout.strip()))


def pytest_terminal_summary(terminalreporter, exitstatus, config):
    if not _FIGURES:
        return
    terminalreporter.section("measured figures (printed by passing tests)")
    for nodeid, text in _FIGURES:
        terminalreporter.write_line(nodeid)
        for line in text.splitlines():
            if line.strip():
                terminalreporter.write_line("    " + line.rstrip())
