"""``distance_transform3d`` now against an older commit, in one process, beside SciPy.

Same workload as ``benchmarks/bench_volume.py``'s ``edt`` task (a mask of random balls, spacing
(2, 1, 1)): single volume and a batch of 4 (``jit(vmap)`` against a Python loop of
``scipy.ndimage.distance_transform_edt``). Both versions are checked equal to each other
(single and batched) and their largest difference to SciPy printed; compile CPU time
(``time.process_time`` of ``jit(f).lower(x).compile()``) beside the medians of round-robin repeats.

Run ``python benchmarks/profile_edt3d.py --old COMMIT [--sizes 64,128]``.
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

from _harness import load_average, module_at, print_ab_rows, time_round_robin  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--old", required=True, help="commit to compare with")
    ap.add_argument("--sizes", default="64,128")
    ap.add_argument("--repeats", type=int, default=5)
    a = ap.parse_args()

    import jax
    import jax.numpy as jnp
    import scipy.ndimage as ndi
    from bench_volume import _inputs

    from fsjax.ops.volume import _distance3d as new

    old = module_at(a.old, "fsjax/ops/volume/_distance3d.py", "fsjax.ops.volume._distance3d_old")
    sp = (2.0, 1.0, 1.0)
    for n in (int(s) for s in a.sizes.split(",")):
        _, balls, _ = _inputs(n, 4)
        x1, xb = jnp.asarray(balls[0]), jnp.asarray(balls)
        ref = ndi.distance_transform_edt(balls[0] > 0.5, sampling=sp)
        comp, info, outs = {}, [], {}
        for name, mod in ((a.old, old), ("now", new)):
            def g(d, mod=mod):
                return mod._edt3d_core(d, 0.5, spacing=sp)

            f1, fb = jax.jit(g), jax.jit(jax.vmap(g))
            jax.clear_caches()
            t0 = time.process_time()
            fb.lower(xb).compile()
            ct = time.process_time() - t0
            outs[name] = (np.asarray(f1(x1)), np.asarray(fb(xb)))
            info.append(f"{name}: max diff to scipy {np.max(np.abs(outs[name][0] - ref)):.1e}, "
                        f"batched compile {ct:.2f} s CPU")
            comp[name] = lambda f1=f1, x1=x1: jax.block_until_ready(f1(x1))
            comp[name + " B=4"] = lambda fb=fb, xb=xb: jax.block_until_ready(fb(xb))
        same = all(np.array_equal(p, q) for p, q in zip(outs[a.old], outs["now"]))
        comp["scipy"] = lambda balls=balls: ndi.distance_transform_edt(balls[0] > 0.5, sampling=sp)
        comp["scipy B=4"] = lambda balls=balls: [ndi.distance_transform_edt(m > 0.5, sampling=sp) for m in balls]
        tim = time_round_robin(comp, repeats=a.repeats if n < 256 else 3, warmup=1)
        print(f"edt3d {n}^3 (balls, spacing {sp}); load {tuple(round(v, 1) for v in load_average())}; "
              f"old and new identical: {same}; " + "; ".join(info))
        print_ab_rows(tim, a.old)


if __name__ == "__main__":
    main()
