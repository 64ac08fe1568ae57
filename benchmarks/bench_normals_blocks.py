"""Normals k = 30: all rows at once (the PCA step before the blocks, ``block=None``) against the
blocked ``estimate_normals``, and Open3D, in one process (issue 12 memory work).

Times (median of round-robin repeats), XLA temporaries of each compiled program, and the agreement
``|n . n|`` between the two fsjax programs and with Open3D. Float64, points on a bumpy surface.

    python benchmarks/bench_normals_blocks.py [--n 100000] [--repeats 7]
"""
from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_enable_x64", True)

from fsjax import Points  # noqa: E402
from fsjax.ops import estimate_normals  # noqa: E402
from fsjax.ops.points._cloud import _valid_mask, normals_from_neighbours  # noqa: E402
from fsjax.ops.points._search import knn  # noqa: E402

K = 30


def all_at_once(x):
    valid = _valid_mask(Points(x))
    idx, _ = knn(x, x, K, ref_valid=valid)
    return normals_from_neighbours(x, valid, idx, block=None)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=100000)
    ap.add_argument("--repeats", type=int, default=7)
    a = ap.parse_args()
    rng = np.random.default_rng(0)
    uv = rng.random((a.n, 2)) * 4
    xyz = np.c_[uv, 2 + 0.3 * np.sin(3 * uv[:, 0]) * np.cos(2 * uv[:, 1])]
    x = jnp.asarray(xyz)
    fns = {"all at once": jax.jit(all_at_once),
           "blocks (estimate_normals)": jax.jit(lambda x: estimate_normals(Points(x), k=K).normals)}
    for name, f in fns.items():
        m = f.lower(x).compile().memory_analysis()
        print(f"{name}: XLA temp {m.temp_size_in_bytes / 2**20:.1f} MiB")
    outs = {name: np.asarray(f(x)) for name, f in fns.items()}
    run = {name: (lambda f=f: f(x).block_until_ready()) for name, f in fns.items()}
    try:
        import open3d as o3d

        def o3d_normals():
            pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz))
            pc.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(K))
            return np.asarray(pc.normals)

        outs["Open3D"] = o3d_normals()
        run["Open3D"] = o3d_normals
    except ImportError:
        pass
    ts = {name: [] for name in run}
    for _ in range(a.repeats):
        for name, fn in run.items():
            t = time.perf_counter()
            fn()
            ts[name].append(time.perf_counter() - t)
    ref = outs["all at once"]
    for name in run:
        d = np.abs(np.sum(outs[name] * ref, 1))
        print(f"{name}: median {np.median(ts[name]):.3f} s; min |n . n_all_at_once| = {np.nanmin(d):.12f}")
    if "Open3D" in outs:
        d = np.abs(np.sum(outs["blocks (estimate_normals)"] * outs["Open3D"], 1))
        print(f"blocks vs Open3D: min |n . n| = {np.nanmin(d):.12f}")


if __name__ == "__main__":
    main()
