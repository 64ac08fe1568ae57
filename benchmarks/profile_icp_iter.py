"""One ICP iteration split into its parts, 20,000 vs 20,000 bunny points (issue 12, item 1).

Each part of a point-to-plane turn of ``fsjax.fit.icp`` is timed as its own compiled program on
the normalised clouds the loop sees (target centred and scaled to unit RMS radius), warm, medians
of ``--repeats`` interleaved runs (``_harness.time_round_robin``), beside the same neighbour
query by SciPy's cKDTree and Open3D's KDTreeFlann (Python loop) and ``open3d.core.nns`` (batched)
on the same points. Two poses: the benchmark's start (10 deg, 5 mm: the first, approximate
iterations) and the converged pose (the last, exact iterations; the "previous neighbours" of the
warm-started query are the exact neighbours 0.05 deg / 0.1 mm earlier). The whole call is timed
too and divided by its turns.

    python benchmarks/profile_icp_iter.py [--n 20000] [--repeats 7] [--x64]

``--ab``: the whole ``icp`` call before and after issue 12's per-iteration change (off: no warm
start, ``fsjax.fit.icp._WARM_START = False``, and 8 S slots in the fallback chain's one group,
``_search._S2_ONE = 8``, no skip of empty fallback passes, ``_search._REDO_SKIP = False``; on: all three
as shipped), both compiled ahead of time in this process (``jax.jit`` of the
call: XLA's default options), run interleaved; prints the compile CPU seconds, the medians, and
whether every output is bit-identical.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
from pathlib import Path

import jax

if "--x64" in sys.argv:
    jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _harness import time_round_robin  # noqa: E402

from fsjax._linalg import FAST_COMPILE  # noqa: E402
from fsjax.data import surface_points  # noqa: E402
from fsjax.fit import icp, rotation_from_axis_angle  # noqa: E402
from fsjax.ops.points import _search  # noqa: E402
from fsjax.ops.points._cloud import smallest_eigvec3  # noqa: E402

icp_mod = importlib.import_module("fsjax.fit.icp")


def scene(n, dt):
    x = surface_points("bunny", n, 0)
    y = surface_points("bunny", n, 1)
    r = np.asarray(rotation_from_axis_angle(jnp.array([0.3, 1.0, -0.4]), 10.0))
    t = np.array([0.005, -0.003, 0.002])
    src = (y - t) @ r  # target = R src + t
    c = x.mean(0)
    s = np.sqrt(((x - c) ** 2).sum(1).mean())
    norm = lambda a: jnp.asarray((a - c) / s, dt)  # noqa: E731
    # start: source as given; aligned: the source moved by the true pose (independent samples)
    small = np.asarray(rotation_from_axis_angle(jnp.array([1.0, -0.2, 0.5]), 0.05))
    return (jnp.asarray(src, dt), jnp.asarray(x, dt), norm(x), norm(src), norm(y),
            norm(y @ small.T + np.array([1e-4, 0, 0])))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=20000)
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--x64", action="store_true")
    ap.add_argument("--ab", action="store_true")
    ap.add_argument("--fast", action="store_true", help="--ab: compile with FAST_COMPILE (as an eager icp call)")
    ap.add_argument("--methods", default="point_to_plane,point_to_point,gicp")
    a = ap.parse_args()
    dt = jnp.float64 if a.x64 else jnp.float32
    if a.ab:
        return ab(a, dt)
    src_m, tgt_m, tgt, p_start, p_end, p_prev = scene(a.n, dt)
    n = a.n
    tv = jnp.ones(n, bool)
    kmax = 10  # the loop's selection width: the target's normal_k (one search program for both)
    print(f"# n={n} dtype={jnp.dtype(dt).name} load={os.getloadavg()}", flush=True)

    index = jax.jit(lambda t: _search.build_index(t, tv, k=10, coarse=True))(tgt)
    warm_ok = "warm" in _search._query_grid_knn.__code__.co_varnames

    @jax.jit
    def nn(x, approx):  # the correspondence call of the loop (kmax wide, k_used = 1, all rows)
        return _search._query_grid_knn(index, x, kmax, approx, jnp.asarray(jnp.inf, dt), jnp.int32(1),
                                       jnp.int32(n), one_group=True)

    if warm_ok:
        @jax.jit
        def nn_warm(x, jprev):
            return _search._query_grid_knn(index, x, kmax, jnp.bool_(False), jnp.asarray(jnp.inf, dt),
                                           jnp.int32(1), jnp.int32(n), one_group=True, warm=jprev)

    j_prev = nn(p_prev, False)[0][:, 0]
    j_end, d2_end = (v[:, 0] for v in nn(p_end, False))
    nrm = jax.jit(lambda t: smallest_eigvec3(icp_mod._cov_from_idx(t, _search._query_grid_knn(
        index, t, kmax)[0])[0]))(tgt)
    w = jnp.ones(n, dt)

    @jax.jit
    def pairs(j):  # the pair gathers of a turn (target point and normal of each correspondence)
        return tgt[j], nrm[j]

    q_end, n_end = pairs(j_end)

    @jax.jit
    def moment(x, q, nq):  # residual / Jacobian assembly: the 7 x 7 moment in one reduction
        return icp_mod._p2plane_moment(x, q, nq, w)

    m7 = moment(p_end, q_end, n_end)

    @jax.jit
    def solve(m):  # the 6 x 6 solve (eigenvalue test + Cholesky)
        return icp_mod._solve6(m)

    @jax.jit
    def gn2(x, q, nq):  # what a turn does after the pairs: 2 Gauss-Newton steps (2 moments + 2 solves)
        return icp_mod._p2plane_step(x, q, nq, w, 2)

    @jax.jit
    def conv(d2, ok, r):  # the convergence / stall / cycle tests: O(N) means and 3 x 3 algebra
        ms = jnp.sum(jnp.where(ok, d2, 0.0)) / jnp.maximum(jnp.sum(ok), 1)
        return ms, icp_mod.rotation_angle_deg(r), jnp.linalg.norm(r[0])

    okm = jnp.ones(n, bool)
    eye = jnp.eye(3, dtype=dt)

    import open3d as o3d
    from scipy.spatial import cKDTree
    tgt_np, pe_np, ps_np = (np.asarray(v, np.float64) for v in (tgt, p_end, p_start))
    tree = cKDTree(tgt_np)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(tgt_np))
    flann = o3d.geometry.KDTreeFlann(pcd)
    nns = o3d.core.nns.NearestNeighborSearch(o3d.core.Tensor(tgt_np.astype(np.float32)))
    nns.knn_index()
    pe32, ps32 = (o3d.core.Tensor(v.astype(np.float32)) for v in (pe_np, ps_np))

    def flann_loop(pts):
        for p in pts:
            flann.search_knn_vector_3d(p, 1)

    b = jax.block_until_ready
    comp = {
        "nn exact, start (10 deg)": lambda: b(nn(p_start, False)),
        "nn approximate, start (10 deg)": lambda: b(nn(p_start, True)),
        "nn exact, aligned": lambda: b(nn(p_end, False)),
        "pair gathers": lambda: b(pairs(j_end)),
        "moment 7x7 (assembly, one reduction)": lambda: b(moment(p_end, q_end, n_end)),
        "6x6 solve": lambda: b(solve(m7)),
        "2 GN steps (2 moments + 2 solves)": lambda: b(gn2(p_end, q_end, n_end)),
        "convergence tests": lambda: b(conv(d2_end, okm, eye)),
        "cKDTree k=1 1 thread, start": lambda: tree.query(ps_np, 1),
        "cKDTree k=1 1 thread, aligned": lambda: tree.query(pe_np, 1),
        "cKDTree k=1 workers=-1, aligned": lambda: tree.query(pe_np, 1, workers=-1),
        "Open3D KDTreeFlann loop k=1, aligned": lambda: flann_loop(pe_np),
        "Open3D core nns knn k=1, start": lambda: nns.knn_search(ps32, 1),
        "Open3D core nns knn k=1, aligned": lambda: nns.knn_search(pe32, 1),
    }
    if warm_ok:
        comp["nn warm-started, aligned"] = lambda: b(nn_warm(p_end, j_prev))
        iw, dw = nn_warm(p_end, j_prev)
        ie, de = nn(p_end, False)
        print(f"# warm vs exact: index mismatches {int(jnp.sum(iw[:, 0] != ie[:, 0]))}, "
              f"max |d2 diff| {float(jnp.max(jnp.abs(dw[:, 0] - de[:, 0])))}", flush=True)
    for name, f in (("icp point_to_plane (whole call)", "point_to_plane"), ("icp point_to_point (whole call)",
                                                                          "point_to_point")):
        comp[name] = (lambda m: lambda: b(icp(src_m, tgt_m, method=m, max_iterations=50)))(f)
    res = time_round_robin(comp, repeats=a.repeats, warmup=1)
    for name, tm in res.items():
        print(f"| {name} | {tm.median * 1e3:.2f} | {tm.iqr * 1e3:.2f} |", flush=True)
    for m in ("point_to_plane", "point_to_point"):
        r = icp(src_m, tgt_m, method=m, max_iterations=50)
        print(f"# {m}: iterations {int(r.iterations)}, converged {bool(r.converged)}", flush=True)
    print(f"# load at end {os.getloadavg()}", flush=True)


def ab(a, dt):
    import time

    src_m, tgt_m = scene(a.n, dt)[:2]
    print(f"# n={a.n} dtype={jnp.dtype(dt).name} fast={a.fast} load={os.getloadavg()}", flush=True)
    comp, outs, cpu = {}, {}, {}
    for m in a.methods.split(","):
        for warm in (False, True):
            icp_mod._WARM_START = warm
            _search._S2_ONE = 2 if warm else 8  # "on": the three changes of issue 12's iteration work
            _search._REDO_SKIP = warm
            # the knobs are read while tracing, and fsjax.fit.icp._icp_core is a jit of its own whose
            # traced program jax caches by argument shapes, not by module globals: without this every
            # variant after the first reused the first one's program (found 2026-12-05, branch icpcache)
            jax.clear_caches()
            t0 = time.process_time()
            opts = {"compiler_options": FAST_COMPILE} if a.fast else {}
            exe = jax.jit(lambda s, t, m=m: icp(s, t, method=m, max_iterations=50), **opts).lower(src_m, tgt_m).compile()
            cpu[(m, warm)] = time.process_time() - t0
            outs[(m, warm)] = jax.device_get(exe(src_m, tgt_m))
            comp[f"{m} warm={warm}"] = (lambda e: lambda: jax.block_until_ready(e(src_m, tgt_m)))(exe)
    icp_mod._WARM_START, _search._S2_ONE, _search._REDO_SKIP = True, 2, True
    res = time_round_robin(comp, repeats=a.repeats, warmup=1)
    for m in a.methods.split(","):
        o0, o1 = outs[(m, False)], outs[(m, True)]
        same = all(np.array_equal(np.asarray(x), np.asarray(y)) for x, y in
                   zip(jax.tree.leaves(o0), jax.tree.leaves(o1)))
        t0, t1 = res[f"{m} warm=False"].median, res[f"{m} warm=True"].median
        it = int(o1.iterations)
        print(f"| {m} | {t0 * 1e3:.1f} -> {t1 * 1e3:.1f} ms ({t1 / t0:.2f}x) | {it} it, "
              f"{t0 / (it + 2) * 1e3:.1f} -> {t1 / (it + 2) * 1e3:.1f} ms per turn | compile "
              f"{cpu[(m, False)]:.2f} -> {cpu[(m, True)]:.2f} s CPU | bit-identical {same} |", flush=True)
    print(f"# load at end {os.getloadavg()}", flush=True)


if __name__ == "__main__":
    main()
