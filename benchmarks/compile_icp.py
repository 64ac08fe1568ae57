"""Trace / lower / compile time of ``fsjax.fit.icp`` per method (issue 12/13: compile time).

Each method is lowered and compiled once through ``_icp_core`` with the arguments ``icp`` passes
(AOT: ``.trace`` / ``.lower`` / ``.compile``), no execution. Wall and process-CPU seconds are
printed; on a loaded machine quote CPU seconds and the load average.

    python benchmarks/compile_icp.py --n 1200 [--methods point_to_plane,gicp,multistart] [--x64]

``trimmed`` is point-to-plane with ``overlap < 1``: ``overlap`` is a traced argument, so it is the
same program (its line shows the cache hit); ``multistart`` is ``jax.jit(icp_multistart)``.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import jax

if "--x64" in sys.argv:
    jax.config.update("jax_enable_x64", True)

import importlib  # noqa: E402

import jax.numpy as jnp  # noqa: E402

from fsjax.data import surface_points  # noqa: E402

icp_mod = importlib.import_module("fsjax.fit.icp")


def clock():
    return time.perf_counter(), time.process_time()


def query_split(x, v):
    from fsjax.ops.points._search import build_index, query_knn

    def idx(x, v):
        return build_index(x, v, k=10, coarse=True)

    for name, f in (("build_index", idx),
                    ("build + k=1 approx flag", lambda x, v: query_knn(idx(x, v), x, 1, approx=jnp.bool_(True))),
                    ("build + k=1 exact", lambda x, v: query_knn(idx(x, v), x, 1)),
                    ("build + k=10", lambda x, v: query_knn(idx(x, v), x, 10))):
        w0, _ = clock()
        lo = jax.jit(f).trace(x, v).lower()
        w1, c1 = clock()
        lo.compile()
        w2, c2 = clock()
        print(f"{name:24s} trace+lower {w1 - w0:5.2f}s  compile {w2 - w1:5.2f}s wall ({c2 - c1:5.2f}s cpu)  "
              f"stablehlo lines {lo.as_text().count(chr(10))}", flush=True)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=1200)
    ap.add_argument("--methods", default="point_to_point,point_to_plane,gicp,trimmed,multistart")
    ap.add_argument("--x64", action="store_true")
    ap.add_argument("--query-split", action="store_true",
                    help="also compile the grid index build and its k-NN queries alone (where the time goes)")
    a = ap.parse_args()
    dt = jnp.float64 if a.x64 else jnp.float32
    x = jnp.asarray(surface_points("bunny", a.n, 0), dt)
    y = jnp.asarray(surface_points("bunny", a.n, 1), dt)
    v = jnp.ones(a.n, bool)
    print(f"n={a.n} dtype={jnp.dtype(dt).name} load={os.getloadavg()[0]:.1f}")
    if a.query_split:
        query_split(x, v)
    for m in a.methods.split(","):
        if m == "multistart":  # vmap over the default 24 starts (point-to-plane), jitted whole
            f = jax.jit(icp_mod.icp_multistart, static_argnames=("method",))
            w0, c0 = clock()
            tr = f.trace(y, x, method="point_to_plane")
            w1, c1 = clock()
            lo = tr.lower()
            w2, c2 = clock()
            lo.compile()
            w3, c3 = clock()
            print(f"{m:16s} trace {w1 - w0:6.2f}s  lower {w2 - w1:6.2f}s  compile {w3 - w2:6.2f}s wall "
                  f"({c3 - c2:6.2f}s cpu)  total {w3 - w0:6.2f}s wall  stablehlo lines {lo.as_text().count(chr(10))}",
                  flush=True)
            continue
        method, overlap = (("point_to_plane", 0.8) if m == "trimmed" else (m, 1.0))
        args = (y, v, x, v, jnp.zeros((1, 3), dt), jnp.eye(3, dtype=dt), jnp.zeros(3, dt),
                jnp.asarray(jnp.inf, dt), jnp.asarray(overlap, dt), None, jnp.asarray(0.9 * overlap, dt),
                jnp.asarray(1e-7, dt), jnp.asarray(1e-7, dt))
        kw = dict(method=method, max_iterations=50, inner_steps=2, normal_k=10, cov_k=20, has_normals=False,
                  verbose=False)
        w0, c0 = clock()
        tr = icp_mod._icp_core.fast.trace(*args, **kw)  # the program an eager icp call compiles
        w1, c1 = clock()
        lo = tr.lower()
        w2, c2 = clock()
        lo.compile()
        w3, c3 = clock()
        n_ops = lo.as_text().count("\n")
        print(f"{m:16s} trace {w1 - w0:6.2f}s  lower {w2 - w1:6.2f}s  compile {w3 - w2:6.2f}s wall "
              f"({c3 - c2:6.2f}s cpu)  total {w3 - w0:6.2f}s wall  stablehlo lines {n_ops}", flush=True)


if __name__ == "__main__":
    main()
