"""ICP's pose after each iteration count, and whether a run settles (issue 12/13 convergence).

Runs ``fsjax.fit.icp`` on the float32 scene of ``tests/fit/test_icp.py::_f32_scene`` (bunny vertices vs an
independent sample, 10 deg + 5 mm, metres) with ``max_iterations = m`` for several ``m`` and prints, per m,
the reason, the rms, the rotation error, and the pose change against ``m - 1`` and ``m - 2`` (a 2-cycle
shows as a large change against m - 1 and ~0 against m - 2). Set ``XLA_FLAGS`` to compare compiler
settings, e.g. (the suite's settings plus the flag that stopped two ICP tests converging):

    XLA_FLAGS="--xla_cpu_use_fusion_emitters=false --xla_backend_optimization_level=0" \\
        python benchmarks/icp_trajectory.py --method point_to_plane
"""

from __future__ import annotations

import argparse
import os
import sys

import jax

jax.config.update("jax_enable_x64", True)  # as the test suite (the clouds stay float32 unless --x64)

import jax.numpy as jnp  # noqa: E402

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "tests", "fit"))
from test_icp import _f32_scene  # noqa: E402

from fsjax.fit import icp, rotation_error_deg  # noqa: E402


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--method", default="point_to_plane")
    ap.add_argument("--iterations", default="8,9,10,11,12,13,14,40,41,42,43")
    ap.add_argument("--scale", type=float, default=1.0, help="1 = metres, 1000 = millimetres")
    ap.add_argument("--x64", action="store_true")
    a = ap.parse_args()
    tgt, src, r, _ = _f32_scene(a.scale)
    dt = jnp.float64 if a.x64 else jnp.float32
    tgt, src = tgt.astype(dt), src.astype(dt)
    ms = [int(v) for v in a.iterations.split(",")]
    res = {m: icp(src, tgt, method=a.method, max_iterations=m) for m in ms}
    print(f"XLA_FLAGS={os.environ.get('XLA_FLAGS', '')!r} method={a.method} dtype={jnp.dtype(dt).name}")
    for m in ms:
        x = res[m]

        def vs(k, x=x, m=m):
            return f"{float(rotation_error_deg(x.R, res[m - k].R)):.4f}" if m - k in res else "-"

        err = float(rotation_error_deg(x.R, jnp.asarray(r, dt)))
        print(f"max_iterations {m:3d}: reason {int(x.reason)} after {int(x.iterations):2d}, rms {float(x.rms_len) / a.scale * 1e3:.4f} mm, "
              f"rotation error {err:.4f} deg, pose change vs m-1 {vs(1)} deg, vs m-2 {vs(2)} deg")


if __name__ == "__main__":
    main()
