"""``tsdf_fuse``'s core now against the same core at an older commit, in one process.

Workload of ``benchmarks/bench_tsdf.py`` (the bundled bunny rendered from 24 views of 256 x 256
by ``render_depth``, a 96^3 grid, truncation 3 voxels, float32). Prints the compile CPU time
(``time.process_time`` of ``lower(...).compile()``) of each version, the largest difference of
their float64 results, how many voxels each float32 result has off the old float64 result,
and the median float32 fusion time of round-robin repeats.

Run ``python benchmarks/profile_tsdf.py --old COMMIT [--repeats 5]``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent))

from _harness import load_average, module_at, time_round_robin  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--old", required=True, help="commit to compare with")
    ap.add_argument("--repeats", type=int, default=5)
    a = ap.parse_args()

    import jax

    jax.config.update("jax_enable_x64", True)     # float64 reference; timed runs are float32
    import bench_tsdf as B
    import jax.numpy as jnp

    import fsjax
    from fsjax.ops.volume import _tsdf as new

    old = module_at(a.old, "fsjax/ops/volume/_tsdf.py", "fsjax.ops.volume._tsdf_old")
    n_grid, n_views, px = 96, 24, 256
    v, f = fsjax.data.mesh_arrays("bunny")
    v, f = np.asarray(v, np.float64), np.asarray(f)
    lo, hi = v.min(0), v.max(0)
    center, ext = 0.5 * (lo + hi), float((hi - lo).max())
    mesh = fsjax.Mesh(jnp.asarray(v, jnp.float32), jnp.asarray(f))
    cams = B._cameras(center, 2.2 * ext, n_views, px, 1.4 * px)
    depths = np.stack([np.asarray(fsjax.ops.render_depth(mesh, c).z, np.float64) for c in cams])
    vox = (ext + 6 * ext / n_grid) / (n_grid - 1)
    origin = tuple(float(c - 0.5 * (n_grid - 1) * vox) for c in center)

    def args(dt):
        cam = jax.tree.map(lambda *x: jnp.stack(x).astype(dt), *cams)
        return (jnp.asarray(depths, dt), cam.K, cam.dist, cam.R, cam.t, jnp.asarray(origin, dt),
                jnp.asarray(3 * vox, dt))

    kw = dict(shape=(n_grid,) * 3, spacing=(vox,) * 3, width=cams[0].width, height=cams[0].height,
              carve=True, fill_holes=True)
    a32, a64 = args(jnp.float32), args(jnp.float64)
    ref = np.asarray(old._tsdf_core(*a64, **kw))
    new64 = np.asarray(new._tsdf_core(*a64, **kw))
    print(f"float64: old vs new max |diff| {float(np.max(np.abs(ref - new64))):.2e}")
    comp = {}
    for name, mod in ((a.old, old), ("now", new)):
        t0 = time.process_time()
        mod._tsdf_core.lower(*a32, **kw).compile()
        ct = time.process_time() - t0
        d = np.abs(np.asarray(mod._tsdf_core(*a32, **kw), np.float64) - ref)
        print(f"{name}: compile {ct:.2f} s CPU; float32 vs the float64 values: {int(np.sum(d > 1e-5))} of "
              f"{d.size} voxels off by > 1e-5 (max {d.max():.3f})")
        comp[name] = lambda mod=mod: jax.block_until_ready(mod._tsdf_core(*a32, **kw))
    tim = time_round_robin(comp, repeats=a.repeats, warmup=1)
    print(f"load {tuple(round(x, 1) for x in load_average())}")
    for k, t in tim.items():
        print(f"  {k:10s} {t.median * 1e3:8.1f} ms   {t.median * 1e3 / n_views:6.2f} ms per view")


if __name__ == "__main__":
    main()
