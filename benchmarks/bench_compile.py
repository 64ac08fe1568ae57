"""Compile time of the library: every registered op, a 6-stage pipeline, the public fit and
render functions on their docstring examples, and the named heavy fits (issue 13).

Writes ``docs/compile_times.md`` (and the raw figures to ``benchmarks/results/compile_times.json``).

Method:

* **Registered ops** on their standard input (``fsjax.synth.standard_input`` of each input
  sort, images 256 x 256): a fresh ``jax.jit(spec.fn)``, then ``.trace(*x)``, ``.lower()``,
  ``.compile()``, each timed apart (``time.perf_counter``); steady state = median of 5 calls
  of the compiled program (``block_until_ready``). Ops run in registry order in one process,
  so a jitted helper shared by several ops is traced by the first that uses it (XLA compiles
  every program whole, so the compile column is not shared).
* **6-stage pipeline**: ``fsjax.pipeline([...])`` on a 256 x 256 image, jitted with its knobs
  traced, timed the same way, with the compiler options its top-level call uses (``FAST_COMPILE``,
  since stop 38).
* **Fit / render functions** (modules ``fsjax.fit``, ``fsjax.render``): each public function
  whose docstring has an example runs it twice in a fresh namespace. The first run's
  trace / lower / compile seconds are summed from JAX's own monitoring events
  (``/jax/core/compile/jaxpr_trace_duration``, ``..._to_mlir_module_duration``,
  ``backend_compile_duration``; every program the example compiles, including eager
  op-by-op ones); "steady" is the wall time of the second run.
* **Named targets**: GICP (``icp(method="gicp")``), FPFH + RANSAC (``global_registration``,
  no ICP refinement), ``shape_locate`` on the alignment scene, a splat training step at the
  default capacity, measured by the same events.

Run on a loaded machine, every figure is longer than on an idle one; the load average is
recorded before and after each section. Compile times are single cold measurements (a
second compile of the same program would hit JAX's in-memory cache), so compare ratios
within one run.

Usage::

    python benchmarks/bench_compile.py                     # everything, float32 (JAX's default)
    python benchmarks/bench_compile.py --sections ops --ops shape_locate,gaussian
    python benchmarks/bench_compile.py --sections examples --merge   # add to the last results
"""

from __future__ import annotations

import argparse
import contextlib
import doctest
import inspect
import json
import os
import platform
import sys
import time
import traceback
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results" / "compile_times.json"
DOC = REPO / "docs" / "compile_times.md"

GOAL_OP = 0.5
GOAL_PIPELINE = 2.0
GOAL_FIT = 5.0
GOAL_SPLAT = 10.0
PIPELINE = ["gaussian", "median", "sobel_amp", "opening", "otsu", "count_obj"]

_EVENTS = {
    "/jax/core/compile/jaxpr_trace_duration": "trace",
    "/jax/core/compile/jaxpr_to_mlir_module_duration": "lower",
    "/jax/core/compile/backend_compile_duration": "compile",
}
_ACC = {"on": False, "trace": 0.0, "lower": 0.0, "compile": 0.0, "n": 0}


def _listener(event: str, duration: float, **_):
    if _ACC["on"] and event in _EVENTS:
        _ACC[_EVENTS[event]] += duration
        if _EVENTS[event] == "compile":
            _ACC["n"] += 1


jax.monitoring.register_event_duration_secs_listener(_listener)


@contextlib.contextmanager
def _events():
    """Sum JAX's trace / lower / compile durations over the block."""
    for k in ("trace", "lower", "compile"):
        _ACC[k] = 0.0
    _ACC["n"] = 0
    _ACC["on"] = True
    try:
        yield _ACC
    finally:
        _ACC["on"] = False


def _log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def _block(x):
    return jax.block_until_ready(jax.tree_util.tree_map(lambda a: a, x))


def _steady(f, n=5):
    ts = []
    for _ in range(n):
        t0 = time.perf_counter()
        _block(f())
        ts.append(time.perf_counter() - t0)
    return float(np.median(ts))


def _aot(fn, args, *, name, kind, static_kw=None, compiler_options=None):
    """trace / lower / compile of ``jax.jit(fn)`` apart (wall and process CPU seconds), then steady state.
    ``compiler_options``: those the library's own top-level call compiles with (the pipeline's)."""
    kw = static_kw or {}
    jf = jax.jit(lambda *a: fn(*a, **kw), compiler_options=compiler_options)
    c0, t0 = time.process_time(), time.perf_counter()
    traced = jf.trace(*args)
    t1 = time.perf_counter()
    lowered = traced.lower()
    c2, t2 = time.process_time(), time.perf_counter()
    compiled = lowered.compile()
    c3, t3 = time.process_time(), time.perf_counter()
    steady = _steady(lambda: compiled(*args))
    return {"name": name, "kind": kind, "trace": t1 - t0, "lower": t2 - t1, "compile": t3 - t2,
            "total": t3 - t0, "cpu": c3 - c0, "cpu_compile": c3 - c2, "steady": steady}


def bench_ops(names=None):
    import fsjax
    from fsjax.synth import standard_input

    out = []
    specs = [s for s in fsjax.list_ops() if names is None or s.name in names]
    for i, spec in enumerate(specs):
        try:
            x = tuple(standard_input(t, (0 + j) % 2, size=(256, 256)) for j, t in enumerate(spec.takes))
            r = _aot(spec.fn, x, name=spec.name, kind="op")
            r["family"] = spec.family
        except Exception as e:  # an op that cannot run on its pool input is reported, not hidden
            r = {"name": spec.name, "kind": "op", "family": spec.family, "error": f"{type(e).__name__}: {e}"[:200]}
        out.append(r)
        _log(f"[op {i + 1}/{len(specs)}] {spec.name}: "
             + (f"{r['total']:.2f} s, CPU {r['cpu']:.2f} s (trace {r['trace']:.2f}, lower {r['lower']:.2f}, "
                f"compile {r['compile']:.2f}),"
                f" steady {r['steady'] * 1e3:.1f} ms" if "error" not in r else r["error"]))
    return out


def bench_pipeline():
    import fsjax
    from fsjax.synth import standard_input

    p = fsjax.pipeline(PIPELINE)
    x = standard_input(fsjax.Image, 0, size=(256, 256))
    knobs = jnp.full((len(PIPELINE), 2), 0.5)
    from fsjax._linalg import FAST_COMPILE

    # what `p(x, knobs)` compiles at top level: its program with FAST_COMPILE (fsjax.pipeline)
    r = _aot(lambda img, k: p._run(img, k), (x, knobs), name="pipeline: " + " > ".join(PIPELINE),
             kind="pipeline", compiler_options=FAST_COMPILE)
    _log(f"[pipeline] {r['total']:.2f} s")
    return [r]


def _examples(modules):
    """(qualified name, doctest) of every public function of ``modules`` with a docstring example."""
    seen, out = set(), []
    for mod in modules:
        for n in sorted(getattr(mod, "__all__", dir(mod))):
            if n.startswith("_"):
                continue
            obj = getattr(mod, n, None)
            if obj is None or inspect.isclass(obj) or inspect.ismodule(obj) or not callable(obj):
                continue
            raw = inspect.unwrap(obj)
            key = id(raw)
            if key in seen:
                continue
            seen.add(key)
            doc = inspect.getdoc(obj) or ""
            if ">>>" not in doc:
                continue
            qual = f"{getattr(raw, '__module__', mod.__name__)}.{n}"
            t = doctest.DocTestParser().get_doctest(doc, {}, qual, None, 0)
            out.append((qual, t))
    return out


def _run_doctest(test, globs):
    runner = doctest.DocTestRunner(optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE, verbose=False)
    test.globs = dict(globs)
    with open(os.devnull, "w") as devnull, contextlib.redirect_stdout(devnull):
        res = runner.run(test, out=lambda s: None)
    return res.failed


def bench_examples(only=None):
    import fsjax
    import fsjax.fit
    import fsjax.render

    globs = {"fsjax": fsjax, "jnp": jnp, "np": np, "jax": jax}
    out = []
    items = [(q, t) for q, t in _examples([fsjax.fit, fsjax.render]) if only is None or q.split(".")[-1] in only]
    for i, (qual, t) in enumerate(items):
        try:
            with _events() as ev:
                c0, t0 = time.process_time(), time.perf_counter()
                failed = _run_doctest(t, globs)
                c1, first = time.process_time(), time.perf_counter() - t0
            t0 = time.perf_counter()
            _run_doctest(t, globs)
            second, c2 = time.perf_counter() - t0, time.process_time()
            r = {"name": qual.replace("fsjax.", ""), "kind": "example", "trace": ev["trace"], "lower": ev["lower"],
                 "compile": ev["compile"], "total": ev["trace"] + ev["lower"] + ev["compile"], "programs": ev["n"],
                 "cpu": max((c1 - c0) - (c2 - c1), 0.0), "first_call": first, "steady": second,
                 "example_failed": int(failed)}
        except Exception as e:
            r = {"name": qual.replace("fsjax.", ""), "kind": "example", "error": f"{type(e).__name__}: {e}"[:200]}
        out.append(r)
        _log(f"[example {i + 1}/{len(items)}] {r['name']}: "
             + (f"{r['total']:.2f} s (CPU {r['cpu']:.2f} s) in {r['programs']} programs, first call {r['first_call']:.2f} s, "
                f"second {r['steady']:.2f} s" if "error" not in r else r["error"]))
    return out


def _measured(name, kind, fn):
    with _events() as ev:
        c0, t0 = time.process_time(), time.perf_counter()
        _block(fn())
        c1, first = time.process_time(), time.perf_counter() - t0
    t0 = time.perf_counter()
    _block(fn())
    second, c2 = time.perf_counter() - t0, time.process_time()
    r = {"name": name, "kind": kind, "trace": ev["trace"], "lower": ev["lower"], "compile": ev["compile"],
         "total": ev["trace"] + ev["lower"] + ev["compile"], "programs": ev["n"],
         "cpu": max((c1 - c0) - (c2 - c1), 0.0), "first_call": first, "steady": second}
    _log(f"[target] {name}: {r['total']:.2f} s (CPU {r['cpu']:.2f} s) in {r['programs']} programs, first call {first:.2f} s, "
         f"second {second:.2f} s")
    return r


def bench_targets(only=None):
    import fsjax
    from fsjax.fit import global_registration, icp
    from fsjax.fit.global_reg import _crop_pair

    out = []

    def want(n):
        return only is None or n in only

    if want("shape_locate"):
        from fsjax.synth import alignment_scene
        from fsjax.synth._workpiece import workpiece_template

        img = fsjax.Image(jnp.asarray(alignment_scene()[0]))
        tpl = fsjax.Image(jnp.asarray(workpiece_template()))
        out.append(_measured(f"shape_locate (alignment scene {img.data.shape[0]}x{img.data.shape[1]}, "
                             f"template {tpl.data.shape[0]}x{tpl.data.shape[1]})", "target",
                             lambda: fsjax.ops.shape_locate(img, tpl)))
    xs, xt = _crop_pair(2600, 0.7, 0)
    c, s = np.cos(np.radians(20.0)), np.sin(np.radians(20.0))
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    src = jnp.asarray(xs @ R.T + np.array([0.01, -0.02, 0.005]))
    tgt = jnp.asarray(xt)
    if want("gicp"):
        out.append(_measured(f"GICP icp(method='gicp'), {src.shape[0]} -> {tgt.shape[0]} points", "target",
                             lambda: icp(src, tgt, method="gicp", overlap=0.7)))
    if want("fpfh_ransac"):
        out.append(_measured(f"FPFH + RANSAC global_registration(refine=None), {src.shape[0]} -> {tgt.shape[0]} "
                             "points", "target",
                             lambda: global_registration(jax.random.PRNGKey(0), src, tgt, radius=0.025,
                                                         distance=0.01, refine=None)))
    if want("splat_step"):
        out.append(_splat_step())
    return out


def _splat_step():
    import inspect as _inspect

    from fsjax import Mesh
    from fsjax.fit.splat_train import mesh_views, train_splats
    from fsjax.synth._pool import icosphere

    v, f = icosphere(3)
    mesh = Mesh(vertices=jnp.asarray(v, jnp.float32), faces=jnp.asarray(f, jnp.int32))
    data = mesh_views(mesh, n_views=6, width=64, height=64, holdout_every=6)
    cap = _inspect.signature(train_splats).parameters["max_splats"].default
    return _measured(f"splat training step (train_splats, 1 iteration, max_splats {cap} default, 64x64 views)",
                     "target", lambda: train_splats(jax.random.PRNGKey(0), data, iterations=1, progress=False))


# ---------------------------------------------------------------------------
# report
# ---------------------------------------------------------------------------


def _goal(r):
    if r["kind"] == "op":
        return GOAL_OP
    if r["kind"] == "pipeline":
        return GOAL_PIPELINE
    if r["name"].startswith("splat training step"):
        return GOAL_SPLAT
    return GOAL_FIT


def _heavy_second(r):
    """A second call costing over 20 % of the first: it recompiles or runs eager work each call, so the CPU
    difference is only a lower bound of the compile cost."""
    return "first_call" in r and r["steady"] > 0.2 * r["first_call"]


def _state(r):
    if r["cpu"] > _goal(r):
        return "**not reached**"
    return "undetermined (CPU is a lower bound)" if _heavy_second(r) else "reached"


_HEAD = ["| name | kind | CPU s | wall s | trace s | lower s | compile s | steady | first call | goal (CPU) |",
         "|---|---|---|---|---|---|---|---|---|---|"]


def _fmt_row(r):
    if "error" in r:
        return f"| {r['name']} | {r['kind']} | error: {r['error']} | | | | | | | |"
    first = f"{r['first_call']:.2f} s" if "first_call" in r else ""
    ok = _state(r)
    return (f"| {r['name']} | {r['kind']} | {r['cpu']:.2f} | {r['total']:.2f} | {r['trace']:.2f} | {r['lower']:.2f} | "
            f"{r['compile']:.2f} | {r['steady'] * 1e3:.1f} ms | {first} | {ok} (<= {_goal(r):g} s) |")


def write_doc(data):
    rows = [r for sec in ("ops", "pipeline", "examples", "targets") for r in data.get(sec, [])]
    good = [r for r in rows if "error" not in r and "cpu" in r]
    good.sort(key=lambda r: -r["cpu"])
    ops = [r for r in good if r["kind"] == "op"]
    ex = [r for r in good if r["kind"] in ("example", "target")]
    pipe = [r for r in good if r["kind"] == "pipeline"]
    L = ["# Compile times", "",
         "Trace + lower + XLA compile time of the library's programs, and their steady-state time,",
         "measured by `benchmarks/bench_compile.py` (method in its docstring). Reproduce with",
         "", "    python benchmarks/bench_compile.py", "",
         f"Machine: {data['machine']}. dtype: {data['dtype']}. jax {data['jax']}. XLA_FLAGS: "
         f"`{data['xla_flags'] or '(none)'}`.", "",
         "**Read the CPU column.** This run shared 2 cores with several other jobs (load averages",
         "below, 15-20 on 2 cores), so wall times are inflated several-fold by waiting for a core.",
         "*CPU s* is the process CPU time of trace + lower + compile (for ops: `time.process_time()`",
         "around the three steps; for docstring examples and named targets: CPU of the first run",
         "minus CPU of the second, i.e. the cost of the first call over a warm one). XLA:CPU compiles",
         "a program mostly on one thread, so on an idle machine the wall time of a first call is close",
         "to its CPU time; the goals are judged on it. *wall s* = trace + lower + compile wall time",
         "(for examples: summed from JAX's compile events), *steady* = a warm call.", "",
         "Load average (1, 5, 15 min) around each section:", ""]
    for sec, (a, b) in data["load"].items():
        L.append(f"* {sec}: before {tuple(round(x, 1) for x in a)}, after {tuple(round(x, 1) for x in b)}")
    L += ["", "## Goals", ""]

    def goal_line(label, items, goal):
        if not items:
            return f"* {label}: not measured in this run"
        bad = [r for r in items if r["cpu"] > goal]
        und = [r for r in items if _state(r).startswith("undetermined")]
        worst = max(items, key=lambda r: r["cpu"])
        state = ("**reached**" if not bad and not und else f"**not reached** ({len(bad)} of {len(items)} over)"
                 if bad else f"**undetermined** ({len(und)} of {len(items)} recompile on every call)")
        return f"* {label} <= {goal:g} s: {state}; worst {worst['name']} {worst['cpu']:.2f} s CPU"

    L.append(goal_line("every registered op", ops, GOAL_OP))
    L.append(goal_line("6-stage pipeline", pipe, GOAL_PIPELINE))
    L.append(goal_line("every fit/render function (docstring example) and named target",
                       [r for r in ex if _goal(r) == GOAL_FIT], GOAL_FIT))
    L.append(goal_line("splat training step", [r for r in ex if _goal(r) == GOAL_SPLAT], GOAL_SPLAT))
    errs = [r for r in rows if "error" in r]
    if errs:
        L += ["", f"{len(errs)} item(s) could not be measured (listed at the end)."]
    L += ["", "## Slowest 20 to compile (CPU)", ""] + _HEAD + [_fmt_row(r) for r in good[:20]]
    for title, items in (("Named targets and fit / render functions (docstring examples)", ex),
                         ("Pipeline", pipe), ("Registered ops (256 x 256 standard input)", ops)):
        L += ["", f"## {title}", ""] + _HEAD + [_fmt_row(r) for r in items]
    if ex:
        L += ["", "For docstring examples, *steady* is the wall time of a second run of the whole example",
              "(Python and eager dispatch included) and *wall s* sums every program the example compiled."]
    if data.get("notes"):
        L += ["", "## Notes", ""] + [f"* {n}" for n in data["notes"]]
    if errs:
        L += ["", "## Not measured", ""] + [f"* {r['name']} ({r['kind']}): {r['error']}" for r in errs]
    L += _kept_sections()
    DOC.write_text("\n".join(L) + "\n")


# Hand-written sections of the doc that this script does not measure (the test suite's profile,
# measured with pytest --durations): carried over verbatim when the doc is rewritten.
KEPT = ("## Where the suite's time goes",)


def _kept_sections() -> list[str]:
    if not DOC.exists():
        return []
    lines, out, keep = DOC.read_text().splitlines(), [], False
    for line in lines:
        if line.startswith("## "):
            keep = line.strip() in KEPT
            if keep:
                out.append("")
        if keep:
            out.append(line)
    while out and not out[-1].strip():
        out.pop()
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sections", default="ops,pipeline,examples,targets")
    ap.add_argument("--ops", default="", help="comma-separated op names (default all)")
    ap.add_argument("--only", default="", help="comma-separated function / target names for examples, targets")
    ap.add_argument("--x64", action="store_true", help="float64 (default: float32, JAX's default)")
    ap.add_argument("--merge", action="store_true", help="keep sections of the last results not re-measured")
    ap.add_argument("--no-doc", action="store_true")
    ap.add_argument("--results", default=str(RESULTS), help="JSON file of the raw figures")
    ap.add_argument("--doc-from", default="", help="comma-separated result files: merge them, write the doc, exit")
    args = ap.parse_args()
    if args.doc_from:
        data = {"load": {}}
        for f in args.doc_from.split(","):
            d = json.loads(Path(f).read_text())
            load = {**data["load"], **d.pop("load", {})}
            data.update(d)
            data["load"] = load
        write_doc(data)
        _log(f"wrote {DOC.relative_to(REPO)}")
        return
    results = Path(args.results)
    if args.x64:
        jax.config.update("jax_enable_x64", True)
    data = json.loads(results.read_text()) if args.merge and results.exists() else {"load": {}}
    data.update({"machine": f"{platform.machine()}, {os.cpu_count()} logical CPUs, {platform.python_version()}",
                 "dtype": "float64" if args.x64 else "float32", "jax": jax.__version__,
                 "xla_flags": os.environ.get("XLA_FLAGS", "")})
    only = set(args.only.split(",")) if args.only else None
    for sec in args.sections.split(","):
        before = os.getloadavg()
        try:
            if sec == "ops":
                data["ops"] = bench_ops(set(args.ops.split(",")) if args.ops else None)
            elif sec == "pipeline":
                data["pipeline"] = bench_pipeline()
            elif sec == "examples":
                data["examples"] = bench_examples(only)
            elif sec == "targets":
                data["targets"] = bench_targets(only)
            else:
                raise SystemExit(f"unknown section {sec!r}")
        except Exception:
            traceback.print_exc()
        data["load"][sec] = (before, os.getloadavg())
        results.parent.mkdir(parents=True, exist_ok=True)
        results.write_text(json.dumps(data, indent=1))
    if not args.no_doc:
        write_doc(data)
        _log(f"wrote {DOC.relative_to(REPO)}")


if __name__ == "__main__":
    main()
