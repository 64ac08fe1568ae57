"""mesh -> SDF / occupancy on a bundled closed mesh (issue 16): the sign of ``mesh_to_volume``'s
signed distance against its occupancy by winding number, and the voxel-count volume against the
exact enclosed volume (``mesh_volume``, the divergence theorem).

Workload: the bundled Spot (closed, oriented, 5,856 faces) sampled on 16^3 and 24^3 grids of
spacing 2 / N covering its bounding box. Not a test: the exact distance to every triangle costs
N^3 x faces point-triangle distances (15-60 s on the shared 2-core machine).

Run ``python benchmarks/bench_mesh_sdf.py``.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))


def main() -> None:
    import jax.numpy as jnp

    import fsjax

    m = fsjax.data.spot()
    topo = fsjax.ops.mesh_topology(m)
    exact = float(fsjax.ops.mesh_volume(m))
    print(f"spot: {int(topo.faces)} faces, closed {bool(topo.closed)}, oriented {bool(topo.oriented)}, "
          f"enclosed volume {exact:.5f}")
    for n in (16, 24):
        h = 2.0 / n
        kw = dict(shape=(n, n, n), spacing=(h, h, h), origin=(-1.0, -0.9, -0.8))
        t = time.perf_counter()
        sdf = np.asarray(fsjax.ops.mesh_to_volume(m, **kw).data)
        t_sdf = time.perf_counter() - t
        occ = np.asarray(fsjax.ops.mesh_to_volume(m, kind="occupancy", **kw).data) > 0.5
        border = max(sdf[0].max(), sdf[-1].max(), sdf[:, 0].max(), sdf[:, -1].max(),
                     sdf[:, :, 0].max(), sdf[:, :, -1].max())
        frac = np.asarray(fsjax.ops.sdf_to_occupancy(fsjax.Volume(jnp.asarray(-sdf), spacing=(h, h, h))).data)
        print(f"{n}^3 (h = {h:.4f}): sdf {t_sdf:.1f} s (first call); occupancy by winding == sdf > 0 on every "
              f"voxel: {bool(np.array_equal(occ, sdf > 0))}; grid border outside: {bool(border < 0)}; volume "
              f"error: voxel count {(sdf > 0).sum() * h**3 / exact - 1:+.2%}, sdf_to_occupancy "
              f"{frac.sum() * h**3 / exact - 1:+.2%}")


if __name__ == "__main__":
    main()
