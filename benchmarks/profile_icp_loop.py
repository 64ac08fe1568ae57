"""Where an ICP call's time goes inside its ``while_loop`` (issue 12), 20,000 bunny points, float32.

Three measurements, each printed as a Markdown row (``docs/benchmarks_icp.md``, "The ICP loop
body"):

``--timeline`` (default on): one ``fsjax.fit.icp`` call with ``verbose=True`` whose per-iteration
host callback is replaced by a time stamp, so the call splits into its turns: the setup (centre,
scale, index build), the target's own k-NN turn (normals / covariances / spacing) and the first
correspondence turn together, then one segment per later turn, then the evaluation turn and the
return. Medians of ``--repeats`` calls. (The callbacks order the turns on the host; they cost
~0.1 ms each.)

``--marginal``: the marginal cost of one aligned turn, three ways, compiled ahead of time in this
process and timed interleaved (``_harness.time_round_robin``): (a) ``icp`` point-to-point with
``max_iterations`` 15 and 35 (both stop at the cap; the difference / 20 is one aligned turn of the
real loop); (b) the same k = 1 warm-started query as the loop calls it, alone in a ``fori_loop`` of
10 and 30 turns carrying only the previous pairs (the query as a loop body, nothing else); (c) the
query compiled alone, once. Both XLA option sets: ``FAST_COMPILE`` (what an eager ``icp`` call
compiles with) and the default (what ``icp`` inside a user's ``jit`` / ``vmap`` gets).

``--hlo``: the compiled program's outer ``while`` body (``jax.jit(f).lower(...).compile().as_text()``):
its instructions, fusions and ``copy`` instructions with the bytes they move per turn, and the
instructions of every computation it reaches (the query's nested loops).

    python benchmarks/profile_icp_loop.py [--n 20000] [--repeats 5] [--method point_to_plane]
        [--timeline] [--marginal] [--hlo] [--default-options]
"""

from __future__ import annotations

import argparse
import collections
import importlib
import os
import re
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _harness import time_round_robin  # noqa: E402
from profile_icp_iter import scene  # noqa: E402

from fsjax._linalg import FAST_COMPILE  # noqa: E402
from fsjax.fit import icp  # noqa: E402
from fsjax.ops.points import _search  # noqa: E402

icp_mod = importlib.import_module("fsjax.fit.icp")
_BYTES = {"f32": 4, "s32": 4, "pred": 1, "f64": 8, "s64": 8, "u32": 4, "u8": 1, "s8": 1}


def timeline(a, src, tgt):
    stamps = []

    def stamp(it, n_ok, rms, step, exact):
        stamps.append((time.perf_counter(), int(it), bool(exact)))

    saved = icp_mod._progress_line
    icp_mod._progress_line = stamp
    try:
        def call():
            return jax.block_until_ready(icp(src, tgt, method=a.method, max_iterations=50, verbose=True))

        call()
        runs = []
        for _ in range(a.repeats):
            stamps.clear()
            t0 = time.perf_counter()
            res = call()
            t1 = time.perf_counter()
            runs.append(np.diff([t0] + [s[0] for s in stamps] + [t1]) * 1e3)
            info = [(s[1], s[2]) for s in stamps]
    finally:
        icp_mod._progress_line = saved
    med = np.median(np.asarray(runs), 0)
    print(f"# timeline {a.method}: {int(res.iterations)} iterations; load {os.getloadavg()}", flush=True)
    print("| segment of the call | median [ms] |\n|---|---|")
    for i, m in enumerate(med):
        if i == 0:
            lab = "setup + index build + the target's own k-NN turn + the first correspondence turn"
        elif i == len(med) - 1:
            lab = "evaluation turn (exact pairs at the returned pose) + return"
        else:
            lab = f"turn of iteration {info[i][0] + 1} ({'exact' if info[i][1] else 'approximate'} pairs)"
        print(f"| {lab} | {m:.1f} |")
    print(f"| whole call | {np.median(np.sum(runs, 1)):.1f} |", flush=True)


def marginal(a, src, tgt_m, tgt, p_end, p_prev, opts, label):
    dt, n = tgt.dtype, tgt.shape[0]
    tv = jnp.ones(n, bool)

    def build(t):
        return _search.build_index(t, tv, k=10, coarse=True)

    def query(g, x, jp):  # the loop's correspondence call (point-to-point: width 2, k_used 1, warm)
        return _search._query_grid_knn(g, x, 2, jnp.bool_(False), jnp.asarray(jnp.inf, dt), jnp.int32(1),
                                       jnp.int32(n), one_group=True, warm=jp)

    def alone(t, x, jp):
        return query(build(t), x, jp)

    def looped(turns):
        def f(t, x, jp):
            g = build(t)

            def body(i, st):
                j, acc = st
                idx, d2 = query(g, x + 1e-6 * i.astype(dt), j)  # moves a little: nothing loop-invariant
                return idx[:, 0], acc + d2[0, 0]

            return jax.lax.fori_loop(0, turns, body, (jp, jnp.asarray(0.0, dt)))
        return f

    def whole(cap):
        return lambda s, t: icp(s, t, method="point_to_point", max_iterations=cap)

    j_prev = jax.jit(alone)(tgt, p_prev, jnp.full(n, -1, jnp.int32))[0][:, 0]
    progs = {"build + query": (alone, (tgt, p_end, j_prev)), "loop 10": (looped(10), (tgt, p_end, j_prev)),
             "loop 30": (looped(30), (tgt, p_end, j_prev)), "icp 15": (whole(15), (src, tgt_m)),
             "icp 35": (whole(35), (src, tgt_m)), "build": (build, (tgt,))}
    exes = {}
    for k, (f, args) in progs.items():
        t0 = time.process_time()
        exes[k] = (jax.jit(f, **opts).lower(*args).compile(), args)
        print(f"# {label}: compile {k}: {time.process_time() - t0:.2f} s CPU", flush=True)
    res = time_round_robin({k: (lambda e, x: lambda: jax.block_until_ready(e(*x)))(*v) for k, v in exes.items()},
                           repeats=a.repeats, warmup=1)
    m = {k: v.median * 1e3 for k, v in res.items()}
    print(f"| {label} | {(m['icp 35'] - m['icp 15']) / 20:.1f} | {(m['loop 30'] - m['loop 10']) / 20:.1f} | "
          f"{m['build + query'] - m['build']:.1f} | load {os.getloadavg()[0]:.1f} |", flush=True)


def hlo(a, src, tgt, opts):
    txt = jax.jit(lambda s, t: icp(s, t, method=a.method, max_iterations=50), **opts).lower(src, tgt).compile().as_text()
    comps, cur = {}, None
    for line in txt.splitlines():
        head = re.match(r"^(?:ENTRY )?%?([\w.\-]+) .*\{$", line)
        if head:
            cur = head.group(1)
            comps[cur] = []
        elif cur and line.startswith("  "):
            comps[cur].append(line)
    calls = collections.defaultdict(list)
    for k, lines in comps.items():
        for ln in lines:
            for attr in ("body", "condition", "to_apply", "calls", "branch_computations"):
                for mm in re.finditer(attr + r"=\{?([%\w.\-, ]+)\}?", ln):
                    calls[k] += [x.strip().lstrip("%") for x in mm.group(1).split(",")]

    def opcount(lines):
        c = collections.Counter()
        for ln in lines:
            mm = re.search(r"= (?:\([^=]*\)|[^ ]+) ([\w\-]+)\(", ln)
            if mm:
                c[mm.group(1)] += 1
        return c

    def copy_bytes(lines):
        tot = 0
        for ln in lines:
            mm = re.search(r"= (\w+)\[([\d,]*)\][^ ]* copy\(", ln)
            if mm:
                tot += _BYTES.get(mm.group(1), 4) * int(np.prod([int(x) for x in mm.group(2).split(",") if x] or [1]))
        return tot

    entry = next(k for k in comps if f"ENTRY %{k}" in txt or f"ENTRY {k}" in txt)
    bodies = [re.search(r"body=%?([\w.\-]+)", ln).group(1) for ln in comps[entry] if " while(" in ln]
    outer = max(bodies, key=lambda b: len(comps[b]))  # the ICP loop (the other: the index build's scan)
    seen, stack = set(), [outer]
    while stack:
        x = stack.pop()
        if x in seen or x not in comps:
            continue
        seen.add(x)
        stack += calls[x]
    own = opcount(comps[outer])
    reach = collections.Counter()
    for c in seen:
        if "fused" not in c and not c.startswith("wrapped"):
            reach += opcount(comps[c])
    print(f"# hlo {a.method} ({'default' if not opts else 'FAST_COMPILE'}): outer while body {outer}")
    print(f"| body's own instructions | {sum(own.values())} (fusions {own['fusion']}, copies {own['copy']}, "
          f"{copy_bytes(comps[outer]) / 1e3:.0f} kB copied per turn; while {own['while']}, conditional "
          f"{own['conditional']}) |")
    print(f"| reached computations (nested loops, branches; fusions' insides not counted) | {len(seen)}: "
          f"{sum(reach.values())} instructions, fusions {reach['fusion']}, copies {reach['copy']}, while "
          f"{reach['while']}, conditional {reach['conditional']} |", flush=True)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=20000)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--method", default="point_to_plane")
    ap.add_argument("--timeline", action="store_true")
    ap.add_argument("--marginal", action="store_true")
    ap.add_argument("--hlo", action="store_true")
    ap.add_argument("--default-options", action="store_true", help="--hlo with XLA's default options")
    a = ap.parse_args()
    if not (a.timeline or a.marginal or a.hlo):
        a.timeline = a.marginal = a.hlo = True
    src, tgt_m, tgt, _, p_end, p_prev = scene(a.n, jnp.float32)
    print(f"# n={a.n} float32 load={os.getloadavg()}", flush=True)
    if a.timeline:
        timeline(a, src, tgt_m)
    if a.marginal:
        print("| XLA options | one aligned turn of icp point-to-point [ms] | the query alone in a fori_loop [ms per turn] "
              "| the query compiled alone [ms] | load |\n|---|---|---|---|---|")
        marginal(a, src, tgt_m, tgt, p_end, p_prev, {"compiler_options": FAST_COMPILE}, "FAST_COMPILE (eager icp)")
        marginal(a, src, tgt_m, tgt, p_end, p_prev, {}, "default (icp in a user's jit)")
    if a.hlo:
        hlo(a, src, tgt_m, {} if a.default_options else {"compiler_options": FAST_COMPILE})
    print(f"# load at end {os.getloadavg()}", flush=True)


if __name__ == "__main__":
    main()
