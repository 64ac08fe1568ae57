"""A/B of module-level knobs of ``fsjax.fit.icp`` against Open3D, one process (issue 12).

Each variant sets attributes of the module, clears JAX's caches (``_icp_core`` is jitted and cached by
shapes, not by module globals: without the clear, every variant would run the first one's program),
compiles by a first call, then runs fsjax and Open3D's same method interleaved, medians of 7. The
ratio of each variant is taken against the Open3D runs interleaved with it.

    python benchmarks/ab_icp_knob.py METHOD DTYPE "[('label', {'_ATTR': value}), ...]" [--n 20000]

e.g. ``python benchmarks/ab_icp_knob.py point_to_point float32 "[('cache', {'_CACHE_K': 4}), ('off',
{'_CACHE_K': 0})]"``. Two bunny samples 10 deg apart (``bench_icp.icp_inputs``), 50 iterations at most.
"""

from __future__ import annotations

import argparse
import ast
import importlib
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
jax.config.update("jax_enable_x64", True)

from bench_icp import icp_inputs  # noqa: E402

from fsjax.fit import icp, rotation_error_deg  # noqa: E402

icp_mod = importlib.import_module("fsjax.fit.icp")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("method", choices=("point_to_point", "point_to_plane", "gicp"))
    ap.add_argument("dtype", choices=("float32", "float64"))
    ap.add_argument("variants", help="a Python literal: [('label', {'_ATTR': value}), ...]")
    ap.add_argument("--n", type=int, default=20000)
    a = ap.parse_args()
    method, dname, n = a.method, a.dtype, a.n
    variants = ast.literal_eval(a.variants)
    import open3d as o3d

    src, tgt, r, _ = icp_inputs(n)
    reg = o3d.pipelines.registration
    ps = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(src))
    crit = reg.ICPConvergenceCriteria(max_iteration=50)

    def o3():
        q = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(tgt))
        if method == "point_to_plane":
            q.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(10))
            return reg.registration_icp(ps, q, 1.0, np.eye(4), reg.TransformationEstimationPointToPlane(), crit)
        if method == "gicp":
            return reg.registration_generalized_icp(ps, q, 1.0, np.eye(4),
                                                    reg.TransformationEstimationForGeneralizedICP(), crit)
        return reg.registration_icp(ps, q, 1.0, np.eye(4), reg.TransformationEstimationPointToPoint(), crit)

    dt = jnp.dtype(dname)
    js, jt = jnp.asarray(src, dt), jnp.asarray(tgt, dt)
    for label, knobs in variants:
        for k, v in knobs.items():
            if not hasattr(icp_mod, k):
                raise SystemExit(f"fsjax.fit.icp has no attribute {k!r}")
            setattr(icp_mod, k, v)
        jax.clear_caches()
        c0 = time.process_time()
        res = jax.block_until_ready(icp(js, jt, method=method, max_iterations=50))
        c = time.process_time() - c0
        tf, to = [], []
        for _ in range(7):
            t = time.perf_counter()
            jax.block_until_ready(icp(js, jt, method=method, max_iterations=50))
            tf.append(time.perf_counter() - t)
            t = time.perf_counter()
            o3()
            to.append(time.perf_counter() - t)
        mf, mo = np.median(tf) * 1e3, np.median(to) * 1e3
        err = float(rotation_error_deg(res.R, jnp.asarray(r, dt)))
        print(f"{method} {dname} {label}: fsjax {mf:.1f} ms vs Open3D {mo:.1f} ms = {mf / mo:.2f}x; "
              f"{int(res.iterations)} it, {err:.4f} deg; first call {c:.2f} s CPU", flush=True)


if __name__ == "__main__":
    main()
