"""The grid index's build, its self-query and the PCA normals: stages, and old vs new in one process.

Issue 12, branch index40. Bunny samples (``fsjax.data.surface_points``, seed 0) normalised to unit RMS
radius, float32 unless ``--f64``. Every fsjax function is compiled alone (``jax.jit``; compile CPU
seconds apart, ``time.process_time``), then all run round-robin (``_harness.time_round_robin``,
medians). Sections (``--what``, comma separated):

* ``stages``: what ``build_index(k=10, coarse=True)`` spends on: the cell-size estimate, one grid level,
  the key sort (``argsort`` vs one sort of packed words), the cell-count histogram and its prefix sum.
* ``build``: ``build_index`` (coarse and fine only) of ``--old`` (a commit, default 2d75574: main before
  this branch, imported beside the current module by ``_harness.module_at``) vs the current one;
  every output leaf compared bit for bit.
* ``query``: ICP's self-query k (``_query_grid_knn(g, t, k, False, None, k, n, one_group=True)``), the
  same + PCA normals, the first far correspondence query (10 deg, approximate, k_used 1) and
  ``knn(x, x, k)``, old vs current module; answers compared bit for bit.
* ``normals``: ``estimate_normals`` (its compiled core) in the original order (knob
  ``_SORTED_NORMALS = False``, the old path) vs the grid's sorted order, answers compared bit for bit,
  beside Open3D's ``estimate_normals(KDTreeSearchParamKNN(k))`` (tree build included).
* ``icp``: ``fsjax.fit.icp`` (point-to-plane, point-to-point, GICP; 10 deg) with main's build (knobs
  ``_PACKED_SORT = False``, one ``jnp.cumsum``) vs the current one, results compared bit for bit.

    python benchmarks/profile_index_build.py --n 20000 --k 10 --what stages,build,query
    python benchmarks/profile_index_build.py --n 100000 --k 30 --what normals [--f64]
    python benchmarks/profile_index_build.py --n 20000 --what icp
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent))

import jax  # noqa: E402


def _compiled(f, *args):
    t0 = time.process_time()
    c = jax.jit(f).lower(*args).compile()
    return c, time.process_time() - t0


def _same(a, b):
    import numpy as np
    la, lb = jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)
    return len(la) == len(lb) and all(np.array_equal(np.asarray(p), np.asarray(q), equal_nan=True)
                                      for p, q in zip(la, lb))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=20000)
    ap.add_argument("--k", type=int, default=10)
    ap.add_argument("--what", default="stages,build,query")
    ap.add_argument("--old", default="2d75574")
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--f64", action="store_true")
    a = ap.parse_args()
    if a.f64:
        jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    import numpy as np
    from _harness import module_at, time_round_robin

    from fsjax import Points
    from fsjax.data import surface_points
    from fsjax.fit import rotation_from_axis_angle
    from fsjax.fit.icp import _cov_from_idx, icp
    from fsjax.ops.points import _cloud as C
    from fsjax.ops.points import _search as S
    from fsjax.ops.points._cloud import smallest_eigvec3

    n, k = a.n, a.k
    dt = jnp.float64 if a.f64 else jnp.float32
    x = surface_points("bunny", n, 0)
    y = surface_points("bunny", n, 1)
    r = np.asarray(rotation_from_axis_angle(jnp.array([0.3, 1.0, -0.4]), 10.0))
    src = (y - np.array([0.005, -0.003, 0.002])) @ r
    c = x.mean(0)
    s = np.sqrt(((x - c) ** 2).sum(1).mean())
    tgt = jnp.asarray((x - c) / s, dt)
    src = jnp.asarray((src - c) / s, dt)
    tv = jnp.ones(n, bool)
    what = set(a.what.split(","))
    fs, notes = {}, []
    old = module_at(a.old, "fsjax/ops/points/_search.py", "fsjax.ops.points._search_old") \
        if what & {"build", "query"} else None

    if "stages" in what:
        t = S._table_size(n)
        h = jax.jit(lambda p, v: S._knn_cell_size(p, v, k))(tgt, tv)
        g = S._grid(tgt, tv, h)
        key = g.key_of(tgt)
        cnt = jnp.zeros(t, jnp.int32).at[key].add(1, mode="drop")
        for nm, f, args in (
                ("stage: build_index coarse (4 levels)", lambda p, v: S.build_index(p, v, k=k, coarse=True), (tgt, tv)),
                ("stage: cell-size estimate", lambda p, v: S._knn_cell_size(p, v, k), (tgt, tv)),
                ("stage: one grid level (_grid)", S._grid, (tgt, tv, h)),
                ("stage: argsort of the keys", jnp.argsort, (key,)),
                ("stage: _sort_by_key (packed words)", lambda q: S._sort_by_key(q, t), (key,)),
                (f"stage: histogram of {t} cells", lambda q: jnp.zeros(t, jnp.int32).at[q].add(1, mode="drop"), (key,)),
                ("stage: jnp.cumsum of the counts", lambda q: jnp.cumsum(q, dtype=jnp.int32), (cnt,)),
                ("stage: _prefix_sum of the counts", S._prefix_sum, (cnt,))):
            fs[nm] = (_compiled(f, *args)[0], args)

    if "build" in what:
        for coarse in (True, False):
            outs = {}
            for tag, m in (("old", old), ("new", S)):
                cf, ct = _compiled(lambda p, v, m=m, co=coarse: m.build_index(p, v, k=k, coarse=co), tgt, tv)
                nm = f"build coarse={coarse} {tag}"
                fs[nm] = (cf, (tgt, tv))
                outs[tag] = cf(tgt, tv)
                notes.append(f"{nm}: compile {ct:.2f} s CPU")
            notes.append(f"build coarse={coarse}: old and new bit-identical {_same(outs['old'], outs['new'])}")

    if "query" in what:
        outs = {}
        for tag, m in (("old", old), ("new", S)):
            g = jax.jit(lambda p, v, m=m: m.build_index(p, v, k=k, coarse=True))(tgt, tv)

            def selfq(g, p, m=m):
                return m._query_grid_knn(g, p, k, jnp.bool_(False), None, k, n, one_group=True)

            def normals(g, p, selfq=selfq):
                idx, _ = selfq(g, p)
                return smallest_eigvec3(_cov_from_idx(p, idx)[0])

            def firstq(g, p, m=m):
                return m._query_grid_knn(g, p, k, jnp.bool_(True), jnp.inf, 1, n, one_group=True)

            for nm, f, args in (("self-query k", selfq, (g, tgt)), ("self-query k + PCA normals", normals, (g, tgt)),
                                ("first far query (approx, k_used 1)", firstq, (g, src)),
                                ("knn(x, x, k) incl. build", lambda p, m=m: m.knn(p, p, k), (tgt,))):
                cf, ct = _compiled(f, *args)
                fs[f"{nm} {tag}"] = (cf, args)
                outs[(nm, tag)] = cf(*args)
                notes.append(f"{nm} {tag}: compile {ct:.2f} s CPU")
        for nm in {q for q, _ in outs}:
            notes.append(f"{nm}: old and new bit-identical {_same(outs[(nm, 'old')], outs[(nm, 'new')])}")
        # what ICP's first turn could do (fsjax/fit/icp.py is not changed here): the same self-query
        # with the index's sorted points as the queries, the PCA there, the normals unsorted
        g = jax.jit(lambda p, v: S.build_index(p, v, k=k, coarse=True))(tgt, tv)

        def normals_sorted(g):
            idx, _ = S._query_grid_knn(g, g.spts, k, jnp.bool_(False), None, k, g.cstart[-1], one_group=True)
            inv = S._unsort(g.order, jnp.arange(n, dtype=jnp.int32))
            pos = jnp.where(idx >= 0, inv[jnp.maximum(idx, 0)], -1)
            return S._unsort(g.order, smallest_eigvec3(_cov_from_idx(g.spts, pos)[0]))

        cf, ct = _compiled(normals_sorted, g)
        fs["self-query k + PCA normals, sorted order"] = (cf, (g,))
        notes.append(f"self-query k + PCA normals, sorted order: compile {ct:.2f} s CPU; equal to the original "
                     f"order's: {_same(cf(g), outs[('self-query k + PCA normals', 'new')])}")

    if "normals" in what:
        pts = Points(tgt, valid=tv.at[::53].set(False))
        vp = jnp.zeros(3, dt)
        outs = {}
        for tag, knob in (("original order (old)", False), ("sorted order (new)", True)):
            C._SORTED_NORMALS = knob
            cf, ct = _compiled(lambda p, v: C._estimate_normals_core.__wrapped__(p, k, v), pts, vp)
            fs[f"estimate_normals k={k} {tag}"] = (cf, (pts, vp))
            outs[tag] = cf(pts, vp)
            notes.append(f"estimate_normals {tag}: compile {ct:.2f} s CPU")
        C._SORTED_NORMALS = True
        notes.append(f"estimate_normals: bit-identical {_same(*outs.values())}")

    if "icp" in what:
        for method in ("point_to_plane", "point_to_point", "gicp"):
            outs = {}
            for tag, kn in (("main build", dict(_PACKED_SORT=False, _PREFIX_W=1 << 30)),
                            ("new build", dict(_PACKED_SORT=True, _PREFIX_W=512))):
                for att, v in kn.items():
                    setattr(S, att, v)
                jax.clear_caches()  # the knobs are read while tracing
                cf, ct = _compiled(lambda p, q, me=method: icp(p, q, method=me), src, tgt)
                fs[f"icp {method} {tag}"] = (cf, (src, tgt))
                out = outs[tag] = cf(src, tgt)
                notes.append(f"icp {method} {tag}: compile {ct:.2f} s CPU, {int(out.iterations)} it, "
                             f"converged {bool(out.converged)}")
            notes.append(f"icp {method}: bit-identical {_same(*outs.values())}")
        S._PACKED_SORT, S._PREFIX_W = True, 512

    calls = {nm: (lambda f=f, args=args: jax.block_until_ready(f(*args))) for nm, (f, args) in fs.items()}
    if "normals" in what or "query" in what:
        import open3d as o3d
        pts64 = np.array(tgt, np.float64)

        def o3d_normals():
            pc = o3d.geometry.PointCloud()
            pc.points = o3d.utility.Vector3dVector(pts64)
            pc.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(k))

        calls[f"Open3D estimate_normals k={k} (incl. tree)"] = o3d_normals
    if "build" in what or "stages" in what:
        from scipy.spatial import cKDTree
        pts64 = np.array(tgt, np.float64)
        calls["cKDTree build"] = lambda: cKDTree(pts64)
    load0 = os.getloadavg()
    tm = time_round_robin(calls, repeats=a.repeats, warmup=1)
    for line in notes:
        print(line)
    print(f"n {n}, k {k}, {np.dtype(dt).name}; load {load0[0]:.1f} at start, {os.getloadavg()[0]:.1f} at end; "
          f"medians of {a.repeats}")
    for nm, v in tm.items():
        print(f"{nm:48s} {v.median * 1e3:9.2f} ms")


if __name__ == "__main__":
    main()
