"""Test configuration.

* float64 everywhere (metrology is validated in float64).
* Measured figures: whatever a passing test prints (conformance errors,
  accuracy against ground truth, the null it beats) is collected and shown in
  one "measured figures" section at the end of the run, so the numbers the
  tests assert are visible in CI output without ``-s``.
"""

import jax

jax.config.update("jax_enable_x64", True)

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
