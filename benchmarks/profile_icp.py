"""Per-stage profile of one ICP iteration on two 20,000-point bunny clouds (issue 12).

Times each stage of ``fsjax.fit.icp`` as its own compiled function (steady-state median of
``--repeats`` runs after a warm-up; compile apart), at the pose of the benchmark's first
iteration (10 deg, 5 mm). ``--x64`` runs in float64 (the default is JAX's float32).

    python benchmarks/profile_icp.py --n 20000 [--x64]
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time

import jax

if "--x64" in sys.argv:
    jax.config.update("jax_enable_x64", True)

import importlib  # noqa: E402

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from fsjax.data import surface_points  # noqa: E402

icp_mod = importlib.import_module("fsjax.fit.icp")
from fsjax.fit import rotation_from_axis_angle  # noqa: E402


def timed(fn, *args, repeats=3):
    t0 = time.perf_counter()
    jax.block_until_ready(fn(*args))
    first = time.perf_counter() - t0
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        ts.append(time.perf_counter() - t0)
    med = statistics.median(ts)
    return med, max(first - med, 0.0)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=20000)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--x64", action="store_true")
    a = ap.parse_args()
    dt = jnp.float64 if a.x64 else jnp.float32
    x = surface_points("bunny", a.n, 0)
    y = surface_points("bunny", a.n, 1)
    r = np.asarray(rotation_from_axis_angle(jnp.array([0.3, 1.0, -0.4]), 10.0))
    t = np.array([0.005, -0.003, 0.002])
    src = jnp.asarray((y - t) @ r, dt)
    tgt = jnp.asarray(x, dt)
    tv = jnp.ones(a.n, bool)
    print(f"# n={a.n} dtype={jnp.dtype(dt).name} load={os.getloadavg()[0]:.2f}")
    rows = []
    for name, fn, args in stages(src, tgt, tv):
        med, comp = timed(fn if name.startswith("for scale") else jax.jit(fn), *args, repeats=a.repeats)
        rows.append((name, med, comp))
        print(f"| {name} | {med * 1e3:.1f} | {comp:.1f} |", flush=True)
    print(f"# load at end {os.getloadavg()[0]:.2f}")


def stages(src, tgt, tv):
    """(name, function, args) of each stage of one point-to-plane / point-to-point iteration."""
    from fsjax.fit.icp import _estimate_normals as estimate_normals
    from fsjax.ops import knn, query_knn

    n = src.shape[0]
    w = jnp.ones(n, src.dtype)
    out = []
    if hasattr(icp_mod, "build_index"):  # after issue 12: one index of the target, built once
        build = jax.jit(lambda t: icp_mod.build_index(t, tv, k=10, coarse=True))
        index = build(tgt)
        out.append(("index build: 3-level sorted-cell grid (once per call)", build, (tgt,)))

        def nn(s, t):
            return query_knn(index, s, 1)

        def normals(t):
            return estimate_normals(t, tv, k=10, index=index)
        out += [("nn k=1 on the index, at 10 deg (first iteration)", nn, (src, tgt)),
                ("nn k=1 on the index, aligned (last iterations)", nn, (tgt, tgt))]
        if "approx" in query_knn.__code__.co_varnames:  # the approximate mode of the early iterations
            out.append(("nn k=1 on the index, approximate mode, at 10 deg (early iterations)",
                        lambda s: query_knn(index, s, 1, approx=True), (src,)))
        from scipy.spatial import cKDTree  # for scale: a tree built once, queried single-threaded
        tree = cKDTree(np.asarray(tgt))
        out += [("for scale: cKDTree query k=1, at 10 deg", lambda s: tree.query(np.asarray(s), 1), (src,)),
                ("for scale: cKDTree query k=1, aligned", lambda s: tree.query(np.asarray(s), 1), (tgt,))]
    else:  # before: brute force every call
        def nn(s, t):
            return knn(t, s, 1, ref_valid=tv)

        def normals(t):
            return estimate_normals(t, tv, k=10)
        out.append(("nn k=1 brute force (correspondences, per iteration)", nn, (src, tgt)))

    idx, d2 = jax.jit(nn)(src, tgt)
    j = idx[:, 0]
    nrm = jax.jit(normals)(tgt)
    out += [("normals k=10 (once per call)", normals, (tgt,)),
            ("sort for trimming (per iteration; now only when overlap < 1)", jnp.sort, (d2[:, 0],))]
    if hasattr(icp_mod, "_p2plane_res"):
        def gn(s, q, nq):
            c = jnp.mean(q, 0)
            args = (s - c, q - c, nq, w)
            ok = icp_mod._normal_eq_ok(icp_mod._p2plane_res, args, s.dtype)
            return icp_mod._gn_solve(icp_mod._p2plane_res, args, s.dtype, 2), ok
        out.append(("p2plane Gauss-Newton solve, optimistix + singularity test (per iteration)", gn,
                    (src, tgt[j], nrm[j])))
    if hasattr(icp_mod, "_p2plane_step"):
        def gn2(s, q, nq):
            return icp_mod._p2plane_step(s, q, nq, w, 2)
        out.append(("p2plane 2 GN steps, 7x7 moment in one reduction each (per iteration)", gn2,
                    (src, tgt[j], nrm[j])))

    def kabsch(s, q):
        return icp_mod._weighted_kabsch(s, q, w, False)[:2]
    out.append(("p2p weighted Kabsch (per iteration)", kabsch, (src, tgt[j])))
    return out


if __name__ == "__main__":
    main()
