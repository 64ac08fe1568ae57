"""``decimate`` now against ``decimate`` at an older commit, in one process, beside Open3D.

Workload as ``benchmarks/bench_mesh.py``'s ``decimate`` task: fandisk (12,946 faces) to 25 %
and 10 % of its faces, float32 (and float64 with ``--f64``). For each version: the number of
parallel rounds, the compile CPU time (``time.process_time`` of ``jit(core).lower(...).compile()``),
the symmetric Hausdorff and mean surface distance to the input (``bench_mesh._hausdorff``,
``--samples`` points a side) and whether the two versions' results are identical (valid
faces and the used vertices' positions); then medians of round-robin repeats beside Open3D's
``simplify_quadric_decimation``.

Run ``python benchmarks/profile_decimate.py --old COMMIT [--ratios 0.25,0.1] [--f64]``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(ROOT))

from _harness import load_average, module_at, time_round_robin  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--old", required=True, help="commit to compare with")
    ap.add_argument("--ratios", default="0.25,0.1")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--samples", type=int, default=200_000)
    ap.add_argument("--f64", action="store_true")
    ap.add_argument("--stage-divs", default=None,
                    help="override the current version's later stage capacities (faces / d), e.g. '2,4' or ''")
    a = ap.parse_args()

    import jax

    if a.f64:
        jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    import open3d as o3d
    from bench_mesh import _hausdorff

    from fsjax import data as D
    from fsjax.ops.mesh import _decimate as new

    if a.stage_divs is not None:
        new._STAGE_DIVS = tuple(int(d) for d in a.stage_divs.split(",") if d)
    old = module_at(a.old, "fsjax/ops/mesh/_decimate.py", "fsjax.ops.mesh._decimate_old")
    dt = jnp.float64 if a.f64 else jnp.float32
    v, f = D.mesh_arrays("fandisk")
    args0 = (jnp.asarray(v, dt), jnp.asarray(f), jnp.ones(len(f), bool), jnp.ones(len(v), bool))
    bw = jnp.asarray(1000.0, dt)
    om = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(v), o3d.utility.Vector3iVector(f.astype(np.int32)))
    for ratio in (float(r) for r in a.ratios.split(",")):
        target = jnp.asarray(int(np.ceil(ratio * len(f))), jnp.int32)
        comp, res, info = {}, {}, []
        for name, mod in ((a.old, old), ("now", new)):
            jax.clear_caches()
            t0 = time.process_time()
            jax.jit(mod._decimate_core.__wrapped__, static_argnames=("max_rounds",)).lower(
                *args0, target, bw, max_rounds=2000).compile()
            ct = time.process_time() - t0

            def run(mod=mod, target=target):
                return jax.block_until_ready(mod._decimate_core(*args0, target, bw, max_rounds=2000))

            p, fc, fv, vv, rounds = (np.asarray(x) for x in run())
            tri = fc[fv]
            hd, mean = _hausdorff(v, f, p.astype(np.float64), tri, n=a.samples)
            res[name] = (p, tri)
            info.append(f"{name}: {len(tri)} faces, {int(rounds)} rounds, compile {ct:.2f} s CPU, "
                        f"Hausdorff {hd:.5f}, mean {mean:.6f}")
            comp[name] = run
        comp["open3d"] = lambda t=int(target): om.simplify_quadric_decimation(t)
        o3m = comp["open3d"]()
        hd, mean = _hausdorff(v, f, np.asarray(o3m.vertices), np.asarray(o3m.triangles), n=a.samples)
        info.append(f"open3d: Hausdorff {hd:.5f}, mean {mean:.6f}")
        (p0, t0_), (p1, t1_) = res[a.old], res["now"]
        same_faces = np.array_equal(np.sort(np.sort(t0_, 1), 0), np.sort(np.sort(t1_, 1), 0))
        used = np.unique(t1_)
        same = same_faces and np.array_equal(p0[used], p1[used])
        tim = time_round_robin(comp, repeats=a.repeats, warmup=1)
        print(f"decimate fandisk {len(f)} -> {ratio} ({'float64' if a.f64 else 'float32'}); load "
              f"{tuple(round(x, 1) for x in load_average())}; results identical: {same}")
        for line in info:
            print("  " + line)
        for k in comp:
            t, s = tim[k].median, tim["open3d"].median
            print(f"  {k:10s} {t * 1e3:8.1f} ms   ratio to open3d {t / s:.2f}")


if __name__ == "__main__":
    main()
