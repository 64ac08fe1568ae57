"""``label3d`` now against ``label3d`` at an older commit, in one process, beside SciPy.

Same workload as ``benchmarks/bench_volume.py``'s ``label`` task: thresholded smoothed noise
(``gaussian_filter(random, 2) > 0.52``) on N^3 voxels, 26-connectivity, capacity 16,384;
single volume and a batch of 4 (``jit(vmap)`` against a Python loop of
``scipy.ndimage.label``). Both fsjax versions are checked equal to SciPy's labels before they
are timed; the number of union-find rounds and the compile CPU time (``time.process_time`` of
``jit(f).lower(x).compile()``) are printed beside the medians of round-robin repeats.

Run ``python benchmarks/profile_label3d.py --old COMMIT [--sizes 64,128]``.
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


def _module_at(commit: str):
    """``fsjax/ops/volume/_label3d.py`` as it was at ``commit`` (``_harness.module_at``)."""
    return module_at(commit, "fsjax/ops/volume/_label3d.py", "fsjax.ops.volume._label3d_old")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--old", required=True, help="commit to compare with")
    ap.add_argument("--sizes", default="64,128")
    ap.add_argument("--repeats", type=int, default=7)
    a = ap.parse_args()

    import jax
    import jax.numpy as jnp
    import scipy.ndimage as ndi

    from fsjax.ops.volume import _label3d as L

    old = _module_at(a.old)
    cube = np.ones((3, 3, 3))
    for n in (int(s) for s in a.sizes.split(",")):
        rng = np.random.default_rng(0)
        ms = np.stack([ndi.gaussian_filter(rng.random((n, n, n)), 2.0) > 0.52 for _ in range(4)])
        ref = [ndi.label(m, cube)[0] for m in ms]
        x1, xb = jnp.asarray(ms[0]), jnp.asarray(ms)
        rounds = int(jax.jit(lambda d: L._block_union_find(d, 26)[-1])(x1))
        comp, info = {}, []
        for name, mod in ((a.old, old), ("now", L)):
            def g(d, mod=mod):
                return mod.label3d_array(d, 26, 16384)

            t0 = time.process_time()
            jax.jit(lambda d, mod=mod: mod.label3d_array.__wrapped__(d, 26, 16384)).lower(x1).compile()
            ct = time.process_time() - t0
            f1, fb = jax.jit(g), jax.jit(jax.vmap(g))
            same = (np.array_equal(np.asarray(f1(x1)[0]), ref[0])
                    and all(np.array_equal(o, r) for o, r in zip(np.asarray(fb(xb)[0]), ref)))
            info.append(f"{name}: labels equal to scipy {same}, compile {ct:.2f} s CPU")
            comp[name] = lambda f1=f1, x1=x1: jax.block_until_ready(f1(x1))
            comp[name + " B=4"] = lambda fb=fb, xb=xb: jax.block_until_ready(fb(xb))
        comp["scipy"] = lambda ms=ms: ndi.label(ms[0], cube)
        comp["scipy B=4"] = lambda ms=ms: [ndi.label(m, cube) for m in ms]
        tim = time_round_robin(comp, repeats=a.repeats if n < 256 else 3, warmup=1)
        print(f"label3d {n}^3 (26-connectivity, {int(ref[0].max())} components, {rounds} rounds); "
              f"load {tuple(round(v, 1) for v in load_average())}; " + "; ".join(info))
        print_ab_rows(tim, a.old)


if __name__ == "__main__":
    main()
