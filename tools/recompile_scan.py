"""Which public functions compile again when called a second time with inputs of the same shapes?

Runs every API module's docstring examples (the modules ``tools/gen_docs.py`` documents, as
``tests/test_api_examples.py`` does) twice in one process and counts XLA compilations
(JAX's backend-compile events) during the second run. A second run compiles nothing when every
program is cached; a count above zero points at a function that builds a new program per call
(a ``jit`` of a closure over the call's arrays, an eager ``lax`` loop over a closure, a static
argument that changes per call). Usage::

    python tools/recompile_scan.py [--only fsjax.fit.icp,...] [--out FILE.md]
    python tools/recompile_scan.py --ops [--only gaussian,...]   # registered ops' worked examples, eager

Writes a Markdown table (module, compiles in run 1 / run 2, seconds of each run).
"""

from __future__ import annotations

import argparse
import doctest
import importlib.util
import sys
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import fsjax  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
_EVENTS = {"n": 0, "names": []}


def _on_duration(name, secs, **kw):
    if name == "/jax/core/compile/backend_compile_duration":
        _EVENTS["n"] += 1
        _EVENTS["names"].append(str(kw.get("fun_name", "?")))


def _modules():
    spec = importlib.util.spec_from_file_location("fsjax_tools_gen_docs_api", REPO / "tools" / "gen_docs.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod
    spec.loader.exec_module(mod)
    return mod.api_modules()


def _run(mod):
    finder = doctest.DocTestFinder()
    runner = doctest.DocTestRunner(optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    globs = {"fsjax": fsjax, "jnp": jnp, "np": np, "jax": jax}
    for t in finder.find(mod, globs=dict(globs)):
        if t.examples:
            runner.run(t, out=lambda s: None)
    return runner.summarize(verbose=False).failed


def _run_op(spec):
    parser = doctest.DocTestParser()
    globs = {"fsjax": fsjax, "jnp": jnp, "np": np, "jax": jax}
    test = parser.get_doctest(spec.doc, globs, spec.name, spec.module, 0)
    runner = doctest.DocTestRunner(optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    runner.run(test, out=lambda s: None)
    return runner.failures


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", default="", help="comma-separated module names")
    ap.add_argument("--out", default="", help="write the Markdown table here")
    ap.add_argument("--ops", action="store_true", help="registered ops' worked examples (eager calls)")
    a = ap.parse_args(argv)
    jax.monitoring.register_event_duration_secs_listener(_on_duration)
    only = {s for s in a.only.split(",") if s}
    rows = []
    items = ([(s.name, _run_op, s) for s in fsjax.list_ops()] if a.ops
             else [(m.__name__, _run, m) for m in _modules()])
    for name, run, obj in items:
        if only and name not in only:
            continue
        res = []
        for _ in range(2):
            n0 = _EVENTS["n"]
            del _EVENTS["names"][:]
            t0 = time.perf_counter()
            failed = run(obj)
            res.append((_EVENTS["n"] - n0, time.perf_counter() - t0, failed, list(_EVENTS["names"])))
        names = sorted(set(res[1][3]))
        rows.append((name, res[0][0], res[1][0], res[0][1], res[1][1], res[0][2] + res[1][2], names))
        print(f"{name:40s} compiles {res[0][0]:4d} -> {res[1][0]:4d}   {res[0][1]:7.1f} s -> "
              f"{res[1][1]:6.1f} s  {', '.join(names[:6])}", flush=True)
    lines = [f"| {'op' if a.ops else 'module'} | compiles, 1st run | compiles, 2nd run | 1st run s | 2nd run s | programs compiled again |",
             "|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r[0]} | {r[1]} | {r[2]} | {r[3]:.1f} | {r[4]:.1f} | {', '.join(r[6][:8])} |")
    if a.out:
        Path(a.out).write_text("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
