"""Where a self-query's time goes, and normals by a threshold instead of top-k lists (issue 12).

Three measurements on the Stanford Bunny (``fsjax.data.surface_points``), one process, medians:

``--what select``: ``_self_knn_sorted(g, k)`` (the grid's exact self k-NN in its sorted order), then the
same with the selection ``_select_flag`` replaced by a row minimum broadcast to ``k`` columns (the
certificates still pass, so no fallback pass runs): the difference is the top-k selection's share.

``--what selfcov``: ``_self_knn_sorted`` against ``self_cov_sorted`` (the threshold and masked sums of
``fsjax/ops/points/_selfpca.py``) on the same grid, and the rows the threshold leaves to the lists.

``--what normals``: ``estimate_normals`` through the lists (``_THRESHOLD_NORMALS = False``) and through
the threshold, each compiled after ``jax.clear_caches()``, and Open3D's ``estimate_normals`` (KNN search
parameter, its tree built inside), timed interleaved; agreement of the two fsjax paths.

    python benchmarks/profile_selfcov.py [--n 100000] [--k 30] [--f64] [--what select,selfcov,normals]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
jax.config.update("jax_enable_x64", True)

import fsjax  # noqa: E402
from fsjax.data import surface_points  # noqa: E402
from fsjax.ops.points import _cloud as P  # noqa: E402
from fsjax.ops.points import _search as S  # noqa: E402
from fsjax.ops.points._selfpca import self_cov_sorted  # noqa: E402


def med_ms(f, *a, repeats=7):
    jax.block_until_ready(f(*a))
    ts = []
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(f(*a))
        ts.append(time.perf_counter() - t)
    return float(np.median(ts)) * 1e3


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=100000)
    ap.add_argument("--k", type=int, default=30)
    ap.add_argument("--f64", action="store_true")
    ap.add_argument("--what", default="select,selfcov,normals")
    ap.add_argument("--repeats", type=int, default=7)
    a = ap.parse_args()
    dt = np.float64 if a.f64 else np.float32
    n, k = a.n, a.k
    xn = surface_points("bunny", n, 0).astype(dt)
    x, v = jnp.asarray(xn), jnp.ones(n, bool)
    g = jax.jit(lambda x: S._grid(x, v, S._knn_cell_size(x, v, k)))(x)
    print(f"# n {n}, k {k}, {np.dtype(dt).name}, load {os.getloadavg()[0]:.1f}")
    what = a.what.split(",")
    if "select" in what:
        full = med_ms(jax.jit(lambda g: S._self_knn_sorted(g, k)), g, repeats=a.repeats)
        orig = S._select_flag

        def row_min(d, ids, kk):  # the certificates pass, the selection costs nothing
            if kk == 1:
                return orig(d, ids, kk)
            m = jnp.min(d, axis=1, keepdims=True)
            return jnp.broadcast_to(m, (d.shape[0], kk)), ids[:, :kk], None

        S._select_flag = row_min
        try:
            jax.clear_caches()
            rest = med_ms(jax.jit(lambda g: S._self_knn_sorted(g, k)), g, repeats=a.repeats)
        finally:
            S._select_flag = orig
            jax.clear_caches()
        print(f"self-query {full:.1f} ms; without the top-k selection {rest:.1f} ms; selection {full - rest:.1f} ms")
    if "selfcov" in what:
        lists = med_ms(jax.jit(lambda g: S._self_knn_sorted(g, k)), g, repeats=a.repeats)
        f = jax.jit(lambda g: self_cov_sorted(g, k))
        thr = med_ms(f, g, repeats=a.repeats)
        ok = np.asarray(f(g)[1])
        print(f"sorted top-k lists {lists:.1f} ms; self_cov_sorted {thr:.1f} ms; rows left to the lists "
              f"{int(n - ok.sum())} ({(n - ok.sum()) / n:.2%})")
    if "normals" in what:
        import open3d as o3d

        pts, vp = fsjax.Points(x), jnp.zeros(3, x.dtype)
        fs, outs = {}, {}
        for name, thr in (("lists", False), ("threshold", True)):
            P._THRESHOLD_NORMALS = thr
            jax.clear_caches()
            c0 = time.process_time()
            fs[name] = jax.jit(lambda p: P._estimate_normals_core.__wrapped__(p, k, vp)).lower(pts).compile()
            print(f"{name}: compile {time.process_time() - c0:.2f} s CPU")
            outs[name] = np.asarray(fs[name](pts))
        P._THRESHOLD_NORMALS = True
        pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.array(xn, np.float64)))
        ts = {name: [] for name in (*fs, "Open3D")}
        for _ in range(a.repeats):
            for name, f in fs.items():
                t = time.perf_counter()
                jax.block_until_ready(f(pts))
                ts[name].append(time.perf_counter() - t)
            t = time.perf_counter()
            pc.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(k))
            ts["Open3D"].append(time.perf_counter() - t)
        mo = np.median(ts["Open3D"])
        for name, tt in ts.items():
            print(f"estimate_normals {name}: {np.median(tt) * 1e3:.1f} ms ({np.median(tt) / mo:.2f}x Open3D)")
        a_, b_ = outs["lists"], outs["threshold"]
        ok = ~np.isnan(a_[:, 0])
        print(f"NaN rows equal: {np.array_equal(np.isnan(a_), np.isnan(b_))}; max 1-|cos| "
              f"{np.max(1 - np.abs(np.sum(a_[ok] * b_[ok], 1))):.1e}")
        print(f"# load at end {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
