"""Compile and run time of the grid neighbour search and its users (issues 12 / 13: compile time).

Each workload is ``jax.jit(f).trace(...).lower().compile()`` with process CPU seconds around the
compile (the machine is shared: CPU seconds, not wall), then the median of 3 runs of the compiled
program (wall, and process CPU: the steadier figure on a shared machine). The load average is printed per line,
and the number of kernels of the compiled program, all and distinct (see :func:`kernels`: load-free; the
distinct count is the better guide to the compile time).

    python benchmarks/compile_knn.py [--only knn10_20k,icp_p2plane_20k,...] [--x64] [--fast | --ab]

``--fast``: the program compiled with ``fsjax._linalg.FAST_COMPILE`` (XLA:CPU's older loop emitters at
optimisation level 2: what a top-level call of a fit compiled with ``jit_fast_compile`` gets).
``--ab``: both programs (XLA's default options and ``FAST_COMPILE``) compiled in one process, the
order alternated over ``--rounds`` rounds; their runs interleaved (median of ``--runs`` each); the
largest difference of every output leaf printed (run time of the older emitters is not always
better: 3x slower on some stencil kernels, ``docs/compile_cache.md``).

Workloads: ``index_build_20k`` (``build_index(coarse=True)`` alone, ICP's target index),
``knn{1,10,32}_{2k,20k}`` (``fsjax.ops.knn``, method auto: 2k x 2k is the blocked
brute force, 20k the grid), ``index_knn10_20k`` (``build_index(coarse=True)`` + exact
``query_knn`` k = 10, the index ICP builds), ``index_knn1_approx_20k`` (the same with k = 1 and a
traced ``approx`` flag and gate, ICP's correspondence call), ``radius_20k`` (``radius_search``,
capacity 32), ``normals_20k`` (``estimate_normals`` k = 16), ``icp_p2plane_20k`` / ``icp_gicp_20k`` (``icp``,
10 deg, two bunny samples). FPFH + RANSAC (``global_registration``, not jittable whole) is measured by
``python benchmarks/bench_compile.py --sections targets --only fpfh_ransac``.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import jax

if "--x64" in sys.argv:
    jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from fsjax.data import surface_points  # noqa: E402


def _rot(deg):
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def workloads(dt):
    from fsjax import Points
    from fsjax.fit import icp
    from fsjax.ops import build_index, estimate_normals, knn, query_knn, radius_search

    clouds = {}

    def cloud(n, seed=0):
        if (n, seed) not in clouds:
            clouds[(n, seed)] = jnp.asarray(surface_points("bunny", n, seed), dt)
        return clouds[(n, seed)]

    w = {}
    for n, tag in ((2000, "2k"), (20000, "20k")):
        for k in (1, 10, 32):
            w[f"knn{k}_{tag}"] = (lambda r, q, k=k: knn(r, q, k), lambda n=n: (cloud(n, 0), cloud(n, 1)))
    w["index_build_20k"] = (lambda r: build_index(r, k=10, coarse=True), lambda: (cloud(20000, 0),))
    w["index_knn10_20k"] = (lambda r, q: query_knn(build_index(r, k=10, coarse=True), q, 10),
                            lambda: (cloud(20000, 0), cloud(20000, 1)))
    w["index_knn1_approx_20k"] = (
        lambda r, q, a, g: query_knn(build_index(r, k=10, coarse=True), q, 1, approx=a, max_dist=g),
        lambda: (cloud(20000, 0), cloud(20000, 1) @ jnp.asarray(_rot(10.0), dt).T, jnp.bool_(True),
                 jnp.asarray(np.inf, dt)))
    w["radius_20k"] = (lambda r, q: radius_search(r, q, 0.004, 32), lambda: (cloud(20000, 0), cloud(20000, 1)))
    w["normals_20k"] = (lambda x: estimate_normals(Points(x), k=16).normals, lambda: (cloud(20000, 0),))
    w["icp_p2plane_20k"] = (lambda s, t: icp(s, t, method="point_to_plane"),
                            lambda: (cloud(20000, 1) @ jnp.asarray(_rot(10.0), dt).T, cloud(20000, 0)))
    w["icp_gicp_20k"] = (lambda s, t: icp(s, t, method="gicp"),
                         lambda: (cloud(20000, 1) @ jnp.asarray(_rot(10.0), dt).T, cloud(20000, 0)))

    return w


def kernels(compiled, distinct: bool = False) -> int:
    """Kernels of a compiled program: instructions outside fused computations, less the free ones
    (parameters, constants, tuples, bitcasts, control flow). XLA:CPU compiles each one (a fusion, a
    sort, a scatter, ...) into its own function, so the count follows the compile time and, unlike
    CPU seconds on a shared machine, does not depend on the load.

    ``distinct=True`` counts each kernel once however often it occurs (a fusion by its fused
    computation's text, names and metadata removed). Exact copies seem to compile about once: GICP's
    second index build (identical shapes) was 105 of its 760 kernels but 1 of its 368 distinct ones,
    and removing it left the compile CPU time unchanged within the noise (``docs/benchmarks_icp.md``),
    so the distinct count is the better guide to what a change saves."""
    import re

    free = {"parameter", "constant", "get-tuple-element", "tuple", "bitcast", "while", "conditional", "call"}
    comps = {}
    for comp in re.split(r"\n(?=(?:ENTRY )?%?[\w.\-]+ \(.*\) -> .* \{)", compiled.as_text()):
        head = comp.split("\n", 1)[0]
        comps[(head.split(" ")[1] if head.startswith("ENTRY") else head.split(" ")[0]).lstrip("%")] = comp

    def text(s):  # an instruction or computation without its names and metadata
        return re.sub(r"%[\w.\-]+", "%", re.sub(r", metadata=\{[^}]*\}", "", s))

    keys = []
    for name, comp in comps.items():
        if "fused" in name or "wrapped" in name:
            continue
        for line in comp.split("\n")[1:]:
            m = re.search(r"= \S+ ([\w\-]+)\(", line)
            if m and m.group(1) not in free:
                called = re.search(r"calls=%?([\w.\-]+)", line)
                body = comps.get(called.group(1), "") if called and m.group(1) == "fusion" else ""
                keys.append(text(line.split("=", 1)[1].split(", calls=")[0]) + text(body.split("\n", 1)[-1]))
    return len(set(keys)) if distinct else len(keys)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--only", default=None)
    ap.add_argument("--x64", action="store_true")
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--fast", action="store_true")
    ap.add_argument("--ab", action="store_true")
    ap.add_argument("--rounds", type=int, default=2)
    a = ap.parse_args()
    dt = jnp.float64 if a.x64 else jnp.float32
    w = workloads(dt)
    names = a.only.split(",") if a.only else list(w)
    print(f"dtype={jnp.dtype(dt).name} jax={jax.__version__}", flush=True)
    if a.ab:
        return ab(w, names, a.runs, a.rounds)
    from fsjax._linalg import FAST_COMPILE

    for name in names:
        f, mk = w[name]
        args = mk()
        l0 = os.getloadavg()[0]
        c0 = time.process_time()
        lo = jax.jit(f, compiler_options=FAST_COMPILE if a.fast else None).trace(*args).lower()
        c1 = time.process_time()
        comp = lo.compile()
        c2 = time.process_time()
        jax.block_until_ready(comp(*args))
        ts, cs = [], []
        for _ in range(a.runs):
            t0, u0 = time.perf_counter(), time.process_time()
            jax.block_until_ready(comp(*args))
            ts.append(time.perf_counter() - t0)
            cs.append(time.process_time() - u0)
        print(f"{name:24s} trace+lower {c1 - c0:6.2f}s cpu  compile {c2 - c1:6.2f}s cpu  "
              f"kernels {kernels(comp):5d} ({kernels(comp, distinct=True):4d} distinct)  "
              f"run {np.median(ts) * 1e3:9.1f} ms wall {np.median(cs) * 1e3:9.1f} ms cpu  "
              f"load {l0:.1f}->{os.getloadavg()[0]:.1f}", flush=True)


def ab(w, names, runs, rounds):
    """XLA's default options against ``FAST_COMPILE``, one process: compile CPU (order alternated per
    round), interleaved run times, largest output difference."""
    from fsjax._linalg import FAST_COMPILE

    opts = {"default": None, "fast": FAST_COMPILE}
    for name in names:
        f, mk = w[name]
        args = mk()
        l0 = os.getloadavg()[0]
        comp, cpu = {}, {lab: [] for lab in opts}
        for r in range(rounds):
            for lab in (list(opts) if r % 2 == 0 else list(opts)[::-1]):
                jax.clear_caches()  # else a round after the first finds the program compiled
                lo = jax.jit(f, compiler_options=opts[lab]).trace(*args).lower()
                c0 = time.process_time()
                comp[lab] = lo.compile()
                cpu[lab].append(time.process_time() - c0)
        outs = {lab: jax.block_until_ready(comp[lab](*args)) for lab in opts}
        ts = {lab: [] for lab in opts}
        for _ in range(runs):
            for lab in opts:
                t0, u0 = time.perf_counter(), time.process_time()
                jax.block_until_ready(comp[lab](*args))
                ts[lab].append((time.perf_counter() - t0, time.process_time() - u0))
        la, lb = (jax.tree_util.tree_leaves(outs[lab]) for lab in opts)
        diff = max((float(np.max(np.abs(np.where(np.isnan(p) & np.isnan(q), 0.0, np.asarray(p, float) - np.asarray(q, float))))
                    if np.asarray(p).size else 0.0) for p, q in zip(la, lb)), default=0.0)
        line = "  ".join(f"{lab}: compile {' / '.join(f'{c:.2f}' for c in cpu[lab])} s cpu, run "
                         f"{np.median([t[0] for t in ts[lab]]) * 1e3:.1f} ms wall {np.median([t[1] for t in ts[lab]]) * 1e3:.1f} ms cpu"
                         for lab in opts)
        print(f"{name:24s} {line}  max|diff| {diff:.3g}  load {l0:.1f}->{os.getloadavg()[0]:.1f}", flush=True)
        for lab in opts:
            o = outs[lab]
            if hasattr(o, "iterations"):  # a fit record
                print(f"  {lab}: iterations {int(o.iterations)} converged {bool(o.converged)} reason {int(o.reason)} "
                      f"rms_len {float(o.rms_len):.9g} R[0] {np.asarray(o.R)[0]}", flush=True)


if __name__ == "__main__":
    main()
