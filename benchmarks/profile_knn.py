"""Per-stage profile of the exact grid kNN (``fsjax.ops.knn``) beside cKDTree (issue 12).

Each stage of ``_grid_knn`` runs as its own compiled function on the same cloud (points
sampled on the Stanford Bunny, queried against themselves), steady-state median of
``--repeats`` calls after a warm-up, compile time apart; cKDTree (build + query, one
thread and ``workers=-1``) and the whole ``knn`` call are timed in the same process, so the
ratios are the figures (the machine is shared; its load average is printed).

Stages: ``cell size`` (the brute-force k-th-distance estimate), ``build`` (bin, sort, cell
starts), ``first pass`` (the per-query 27-cell gather + distance + selection, split into
``gather+d2`` and ``select``), ``fallback`` (the passes of the queries the first pass did not
certify; their count is printed).

    python benchmarks/profile_knn.py --n 10000,100000 --k 16,32 [--dtype float64,float32]
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from scipy.spatial import cKDTree  # noqa: E402

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from fsjax.data import bunny  # noqa: E402
from fsjax.ops import knn, sample_surface  # noqa: E402
from fsjax.ops.points import _search as S  # noqa: E402


def compiled(f, *args):
    t0 = time.perf_counter()
    c = jax.jit(f).lower(*args).compile()
    return c, time.perf_counter() - t0


def stages_v1(p, k):
    """The stages of the grid kNN of main before this session (fixed first pass + fallbacks)."""
    valid = jnp.ones(p.shape[0], bool)
    h = jax.jit(S._knn_cell_size, static_argnums=2)(p, valid, k)
    g = jax.jit(S._grid)(p, valid, h)
    C = S._fixed_slots(k)
    B = min(S._B1, p.shape[0])

    def gather(q):
        start, length, bound = g.runs(q, 1)
        cum = jnp.cumsum(length, axis=1)
        first = cum - length
        s = jnp.arange(C, dtype=jnp.int32)
        r = jnp.minimum(jnp.sum(s[None, :, None] >= cum[:, None, :], axis=-1, dtype=jnp.int32), cum.shape[1] - 1)
        ok = s[None, :] < cum[:, -1:]
        pos = jnp.where(ok, jnp.take_along_axis(start - first, r, 1) + s[None, :], 0)
        d2 = jnp.where(ok, S._sqdist(q[:, None, :], g.spts[pos]), jnp.inf)
        return d2, pos

    def f_gather(g, p):
        return S._batched(lambda q: gather(q), (p,), B)

    d2, pos = jax.jit(f_gather)(g, p)

    def f_select(d2, pos):
        return S._batched(lambda d, q: S._select(d, q, k), (d2, pos), B)

    return {"cell size": (lambda p, v: S._knn_cell_size(p, v, k), (p, valid)),
            "build": (S._grid, (p, valid, h)),
            "gather+d2": (f_gather, (g, p)),
            "select": (f_select, (d2, pos))}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", default="10000,100000")
    ap.add_argument("--k", default="16,32")
    ap.add_argument("--dtype", default="float64,float32")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--stages", action="store_true", help="also time the stages one by one (where they exist)")
    a = ap.parse_args()
    print(f"load average at start: {os.getloadavg()}", flush=True)
    rows = []
    for n in [int(x) for x in a.n.split(",")]:
        p64 = np.array(sample_surface(bunny(), n=n, seed=0).xyz, np.float64)
        for dt in a.dtype.split(","):
            p = jnp.asarray(p64, dt)
            pn = np.asarray(p)
            for k in [int(x) for x in a.k.split(",")]:
                whole, c_whole = compiled(lambda x, k=k: knn(x, x, k, method="grid"), p)
                fns = {"fsjax knn": lambda whole=whole, p=p: whole(p),
                       "cKDTree": lambda pn=pn, k=k: cKDTree(pn).query(pn, k, workers=1),
                       "cKDTree-mt": lambda pn=pn, k=k: cKDTree(pn).query(pn, k, workers=-1)}
                comp = {"fsjax knn": c_whole}
                if a.stages:
                    for name, (f, args) in stages_v1(p, k).items():
                        c, ct = compiled(f, *args)
                        fns[name] = (lambda c=c, args=args: c(*args))
                        comp[name] = ct
                for f in fns.values():  # warm-up
                    jax.block_until_ready(f())
                t = {name: [] for name in fns}
                for _ in range(a.repeats):  # round robin
                    for name, f in fns.items():
                        t0 = time.perf_counter()
                        jax.block_until_ready(f())
                        t[name].append(time.perf_counter() - t0)
                t = {name: statistics.median(v) for name, v in t.items()}
                idx, d2 = whole(p)
                dref, iref = cKDTree(p64.astype(dt)).query(p64.astype(dt), k)
                d2ref = np.asarray(dref, np.float64) ** 2
                exact_d = float(np.max(np.abs(np.sort(np.asarray(d2), 1) - np.sort(((p64[np.asarray(iref)] - p64[:, None]) ** 2).sum(-1), 1)))) if dt == "float64" \
                    else float(np.max(np.abs(np.asarray(d2, np.float64) - d2ref)))
                same_idx = float(np.mean(np.all(np.sort(np.asarray(idx), 1) == np.sort(iref, 1), 1)))
                extra = S.profile_counts(p, k) if hasattr(S, "profile_counts") else {}
                base = t["cKDTree"]
                line = (f"n={n} {dt} k={k}: " + ", ".join(
                    f"{name} {v * 1e3:.1f} ms ({v / base:.2f}x)" + (f" [compile {comp[name]:.1f} s]" if name in comp else "")
                    for name, v in t.items()) + f"; same index rows {same_idx:.4f}; d2 equal/err {exact_d}; {extra}")
                print(line, flush=True)
                rows.append(line)
    print(f"load average at end: {os.getloadavg()}")


if __name__ == "__main__":
    main()
