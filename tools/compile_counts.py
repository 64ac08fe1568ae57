"""Where a test run's time goes: per-test CPU time and XLA compiles (a pytest plugin).

Wall times on a shared machine move 2x with its load; the number of programs XLA compiles
and the seconds it spends compiling them do not move with it, so A/B comparisons of a
change to the suite or to an op's compile cost are made on them. The plugin listens to
JAX's ``/jax/core/compile/backend_compile_duration`` events and records, per test, the
number of backend compiles, their seconds, the process CPU time and the wall time; each
worker appends one JSON line per test to ``COMPILE_COUNTS_OUT`` (default
``compile_counts.jsonl``) and prints a one-line total.

Use (from the repository root)::

    PYTHONPATH=$PWD:$PWD/tools COMPILE_COUNTS_OUT=/tmp/cc.jsonl \\
        python -m pytest -q -p compile_counts -n 2 tests/test_contract.py
    python tools/compile_counts.py /tmp/cc.jsonl          # totals per test function, slowest tests

Measured with it (docs/compile_cache.md): the contract suite spends 70 % of its CPU in XLA
compilation.
"""

from __future__ import annotations

import collections
import json
import os
import sys
import time

import pytest

_S = {"n": 0, "s": 0.0}
_REC: list[dict] = []


def _on_duration(name, secs, **kw):
    if name == "/jax/core/compile/backend_compile_duration":
        _S["n"] += 1
        _S["s"] += float(secs)


def pytest_configure(config):
    import jax

    jax.monitoring.register_event_duration_secs_listener(_on_duration)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    n0, s0, c0, w0 = _S["n"], _S["s"], time.process_time(), time.perf_counter()
    yield
    _REC.append({"id": item.nodeid, "n": _S["n"] - n0, "backend_s": round(_S["s"] - s0, 3),
                 "cpu": round(time.process_time() - c0, 3), "wall": round(time.perf_counter() - w0, 3)})


def pytest_sessionfinish(session, exitstatus):
    if not _REC:
        return
    out = os.environ.get("COMPILE_COUNTS_OUT", "compile_counts.jsonl")
    worker = os.environ.get("PYTEST_XDIST_WORKER", "main")
    with open(out, "a") as f:
        for r in _REC:
            f.write(json.dumps({**r, "worker": worker}) + "\n")
    print(f"\ncompile counts ({worker}): {sum(r['n'] for r in _REC)} compiles, "
          f"{sum(r['backend_s'] for r in _REC):.1f} s compiling, {sum(r['cpu'] for r in _REC):.1f} s CPU")


def summarise(path: str, top: int = 25) -> str:
    """Totals per test function and the ``top`` costliest tests (CPU) of a JSON-lines file."""
    rows = [json.loads(line) for line in open(path) if line.strip()]
    by = collections.defaultdict(lambda: [0, 0, 0.0, 0.0])
    for r in rows:
        fn = r["id"].split("[")[0]
        b = by[fn]
        b[0] += 1
        b[1] += r["n"]
        b[2] += r["backend_s"]
        b[3] += r["cpu"]
    lines = ["| test function | tests | compiles | compile s | CPU s |", "|---|---|---|---|---|"]
    for fn, (k, n, s, c) in sorted(by.items(), key=lambda kv: -kv[1][3]):
        lines.append(f"| {fn} | {k} | {n} | {s:.1f} | {c:.1f} |")
    lines += ["", "| test | compiles | compile s | CPU s |", "|---|---|---|---|"]
    for r in sorted(rows, key=lambda r: -r["cpu"])[:top]:
        lines.append(f"| {r['id']} | {r['n']} | {r['backend_s']:.1f} | {r['cpu']:.1f} |")
    return "\n".join(lines)


if __name__ == "__main__":
    if len(sys.argv) != 2:
        sys.exit("usage: python tools/compile_counts.py COUNTS.jsonl")
    print(summarise(sys.argv[1]))
