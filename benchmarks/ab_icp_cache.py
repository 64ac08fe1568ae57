"""The certified correspondence cache of ``fsjax.fit.icp``: the whole call with and without it, one process.

Each variant (``--variants``: ``off`` = ``_CACHE_K = 0``, the plain search every turn; ``K:step:sub`` =
``_CACHE_K = K``, ``step`` = 0 (the approximate-phase cache, ``_CACHE_STEP``, was removed after it measured worse), ``_SUBSET = sub``, 1 if not given) of each method is compiled ahead of
time in this process (``jax.jit(..., compiler_options=FAST_COMPILE)``: what an eager ``icp`` call
compiles; ``--default-options``: XLA's default, a user's ``jit``), then all run interleaved
(round robin), ``--repeats`` times. Prints per variant the compile CPU seconds, the median wall and
process-CPU time of a call, the iterations, and whether every output leaf is bit-identical to the
first variant's (else the largest differences of R, t, rms_len and the rotation error).

    python benchmarks/ab_icp_cache.py [--n 20000] [--x64] [--repeats 5] [--variants off,0:0:4,4:0:4]
        [--methods point_to_point,point_to_plane,gicp] [--batch 64 --batch-n 5000] [--compile-repeats 3]

``--batch B``: instead, ``jax.jit(jax.vmap(icp))`` over B point-to-plane problems of ``--batch-n``
points (``bench_icp.py``'s batched scene), default XLA options as that benchmark.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
import time
from pathlib import Path

import jax

if "--x64" in sys.argv:
    jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from profile_icp_iter import scene  # noqa: E402

from fsjax._linalg import FAST_COMPILE  # noqa: E402
from fsjax.fit import icp, rotation_error_deg, rotation_from_axis_angle  # noqa: E402

icp_mod = importlib.import_module("fsjax.fit.icp")


def set_variant(v):
    # the knobs are read while tracing; fsjax.fit.icp._icp_core is a jit of its own whose traced
    # program jax caches by argument shapes, not by module globals: clear it, or every variant
    # after the first reuses the first variant's program
    jax.clear_caches()
    if v == "off":
        icp_mod._CACHE_K, icp_mod._SUBSET = 0, 1
    else:
        k, step, sub = (v.split(":") + ["", ""])[:3]
        if float(step or 0.0) != 0.0:
            raise SystemExit("ab_icp_cache: the cache's approximate-phase step (_CACHE_STEP) was removed; use K:0:sub")
        icp_mod._CACHE_K, icp_mod._SUBSET = int(k), int(sub or 1)


def batched_scene(b, n, dt):
    from fsjax.data import surface_points

    tgt = surface_points("bunny", n, 0)
    rng = np.random.default_rng(7)  # bench_icp.bench_batched's scene
    srcs, rots = [], []
    for i in range(b):
        y = surface_points("bunny", n, 100 + i)
        ax = rng.normal(size=3)
        r = np.asarray(rotation_from_axis_angle(jnp.asarray(ax), 10.0))
        t = rng.normal(size=3) * 0.003
        srcs.append((y - t) @ r)
        rots.append(r)
    return jnp.asarray(np.stack(srcs), dt), jnp.asarray(np.stack([tgt] * b), dt), np.stack(rots)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=20000)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--x64", action="store_true")
    ap.add_argument("--variants", default="off,0:0:4,4:0:4")
    ap.add_argument("--methods", default="point_to_point,point_to_plane,gicp")
    ap.add_argument("--default-options", action="store_true")
    ap.add_argument("--batch", type=int, default=0)
    ap.add_argument("--batch-n", type=int, default=5000)
    ap.add_argument("--compile-repeats", type=int, default=0,
                    help="only compile: each variant this many times, interleaved; medians of CPU seconds")
    a = ap.parse_args()
    dt = jnp.float64 if a.x64 else jnp.float32
    variants = a.variants.split(",")
    print(f"# n={a.n} dtype={jnp.dtype(dt).name} batch={a.batch} load={os.getloadavg()}", flush=True)
    cases = {}
    if a.batch:
        src, tgt, rots = batched_scene(a.batch, a.batch_n, dt)
        true_r = rots
        for v in variants:
            set_variant(v)
            f = jax.jit(jax.vmap(lambda s, t: icp(s, t, method="point_to_plane", max_iterations=50),
                                 ))
            cases[(f"point_to_plane x{a.batch}", v)] = (f, (src, tgt))
    else:
        src, tgt = scene(a.n, dt)[:2]
        true_r = np.asarray(rotation_from_axis_angle(jnp.array([0.3, 1.0, -0.4]), 10.0))
        opts = {} if a.default_options else {"compiler_options": FAST_COMPILE}
        for m in a.methods.split(","):
            for v in variants:
                set_variant(v)
                f = jax.jit(lambda s, t, m=m: icp(s, t, method=m, max_iterations=50), **opts)
                cases[(m, v)] = (f, (src, tgt))
    if a.compile_repeats:
        cpu = {k: [] for k in cases}
        for _ in range(a.compile_repeats):
            for key, (f, args) in cases.items():
                set_variant(key[1])
                t0 = time.process_time()
                f.lower(*args).compile()
                cpu[key].append(time.process_time() - t0)
        print("| method | variant | compile [s CPU], median | runs |\n|---|---|---|---|")
        for key, v in cpu.items():
            print(f"| {key[0]} | {key[1]} | {np.median(v):.2f} | {' '.join(f'{x:.2f}' for x in v)} |", flush=True)
        print(f"# load at end {os.getloadavg()}", flush=True)
        return
    comp, exe, outs = {}, {}, {}
    for key, (f, args) in cases.items():
        set_variant(key[1])
        t0 = time.process_time()
        exe[key] = f.lower(*args).compile()
        comp[key] = time.process_time() - t0
        outs[key] = jax.device_get(exe[key](*args))
    set_variant("0:0:4")  # the shipped knobs (the cache off, the subset on)
    wall = {k: [] for k in cases}
    cpu = {k: [] for k in cases}
    keys = list(cases)
    for r in range(a.repeats + 1):
        order = keys[r % len(keys):] + keys[:r % len(keys)]
        for k in order:
            args = cases[k][1]
            t0, c0 = time.perf_counter(), time.process_time()
            jax.block_until_ready(exe[k](*args))
            if r:  # the first round: warm-up
                wall[k].append(time.perf_counter() - t0)
                cpu[k].append(time.process_time() - c0)
    print("| method | variant | wall [ms] | CPU [ms] | compile [s CPU] | iterations | rotation error [deg] | vs first variant |")
    print("|---|---|---|---|---|---|---|---|")
    for key in keys:
        m, v = key
        ref = outs[(m, variants[0])]
        o = outs[key]
        same = all(np.array_equal(np.asarray(x), np.asarray(y), equal_nan=True)
                   for x, y in zip(jax.tree.leaves(ref), jax.tree.leaves(o)))
        err = np.asarray(rotation_error_deg(jnp.asarray(o.R), jnp.asarray(true_r)))
        if same:
            diff = "bit-identical"
        else:
            dr = float(np.max(np.abs(np.asarray(o.R) - np.asarray(ref.R))))
            dtr = float(np.max(np.abs(np.asarray(o.t) - np.asarray(ref.t))))
            drms = float(np.max(np.abs(np.asarray(o.rms_len) / np.asarray(ref.rms_len) - 1)))
            dit = np.asarray(o.iterations) - np.asarray(ref.iterations)
            diff = f"R {dr:.2e}, t {dtr:.2e}, rms rel {drms:.2e}, iterations diff {dit.min()}..{dit.max()}"
        its = np.asarray(o.iterations)
        it_s = str(int(its)) if its.ndim == 0 else f"mean {its.mean():.1f} max {its.max()}"
        print(f"| {m} | {v} | {np.median(wall[key]) * 1e3:.1f} | {np.median(cpu[key]) * 1e3:.1f} | "
              f"{comp[key]:.2f} | {it_s} | {float(np.max(err)):.4f} | {diff} |", flush=True)
    print(f"# load at end {os.getloadavg()}", flush=True)


if __name__ == "__main__":
    main()
