"""Where marching cubes spends its time: the four stages of ``ops.marching_cubes`` on a sphere.

The compiled core (``fsjax/ops/volume/_isosurface.py``) is four stage functions: cell
classification (packed bits), vertex numbering (running popcounts of the crossed-edge words),
edge interpolation (vertex slot -> edge -> position) and face emission (active cube slots ->
triangles -> vertex numbers). Here each stage is compiled as its own program and fed the
previous stage's outputs, so its time is its own (the sum exceeds the whole a little: across
stage boundaries nothing is fused). Beside them, in the same round-robin: the whole op, the
whole op at an older commit (``--old``), and ``skimage.measure.marching_cubes``.

Workload: the sphere field ``R - |x - c|`` on N^3 voxels (default N = 128, R = 0.39 N),
float32, level 0, default capacities; the same input as ``benchmarks/bench_mesh.py``.
Compile time is CPU seconds (``time.process_time``) of ``jit(f).lower(x).compile()`` on a
fresh ``jit``, which moves less with the machine's load than wall time.

``--trace`` adds the ten costliest XLA fusions of one call of the whole op (and of ``--old``),
from ``jax.profiler``'s trace.

Run ``python benchmarks/profile_marching_cubes.py [--n 128] [--repeats 9] [--old COMMIT] [--trace]``.
"""

from __future__ import annotations

import argparse
import collections
import glob
import gzip
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(ROOT))

from _harness import load_average, module_at, time_round_robin  # noqa: E402


def _sphere_field(n: int, radius: float) -> np.ndarray:
    z, y, x = np.mgrid[:n, :n, :n].astype(np.float32) - (n - 1) / 2.0
    return (radius - np.sqrt(x * x + y * y + z * z)).astype(np.float32)


def _module_at(commit: str):
    """``fsjax/ops/volume/_isosurface.py`` as it was at ``commit`` (``_harness.module_at``)."""
    return module_at(commit, "fsjax/ops/volume/_isosurface.py", "fsjax.ops.volume._isosurface_old")


def _compile_cpu(fn, *args) -> float:
    import jax

    t0 = time.process_time()
    jax.jit(fn).lower(*args).compile()
    return time.process_time() - t0


def _top_fusions(fn, x, k: int = 10) -> list[tuple[str, float]]:
    import jax

    for _ in range(2):
        jax.block_until_ready(fn(x))
    d = tempfile.mkdtemp()
    reps = 5
    with jax.profiler.trace(d, create_perfetto_trace=True):
        for _ in range(reps):
            jax.block_until_ready(fn(x))
    fn_ = sorted(glob.glob(f"{d}/**/*.trace.json.gz", recursive=True))[-1]
    ev = json.load(gzip.open(fn_))
    ev = ev["traceEvents"] if isinstance(ev, dict) else ev
    acc = collections.Counter()
    for e in ev:
        if e.get("ph") == "X" and ("fusion" in e["name"] or e["name"].startswith(("wrapped_", "copy", "dot"))):
            acc[e["name"]] += e["dur"] / reps / 1e3
    return acc.most_common(k)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=128)
    ap.add_argument("--repeats", type=int, default=9)
    ap.add_argument("--old", default=None, help="also time the whole op at this commit")
    ap.add_argument("--trace", action="store_true", help="print the costliest XLA fusions")
    a = ap.parse_args()

    import jax
    import jax.numpy as jnp
    from skimage import measure

    from fsjax.ops.volume import _isosurface as M

    n = a.n
    field = _sphere_field(n, 0.39 * n)
    x = jnp.asarray(field)
    shape, sp = field.shape, (1.0, 1.0, 1.0)
    cap = M._default_capacity(shape)
    flat, level = x.reshape(-1), jnp.float32(0.0)

    s1 = jax.jit(lambda f: M._classify(f, level, shape))
    edges, active, inside, _ = s1(flat)
    s2 = jax.jit(M._number_vertices)
    vstart, vend = s2(edges)
    s3 = jax.jit(lambda f, e, a, b: M._interpolate(f, level, e, a, b, shape, sp, cap))
    s4 = jax.jit(lambda e, ac, ins, a: M._emit_faces(e, ac, ins, a, shape, cap, cap))

    def whole(mod):
        return jax.jit(lambda v: mod._mc_core(v, 0.0, max_faces=cap, max_vertices=cap, spacing=sp))

    comp = {
        "1 classify": lambda: jax.block_until_ready(s1(flat)),
        "2 number vertices": lambda: jax.block_until_ready(s2(edges)),
        "3 interpolate": lambda: jax.block_until_ready(s3(flat, edges, vstart, vend)),
        "4 emit faces": lambda: jax.block_until_ready(s4(edges, active, inside, vstart)),
    }
    w_new = whole(M)
    comp["whole"] = lambda: jax.block_until_ready(w_new(x))
    compile_s = {"whole": _compile_cpu(lambda v: M._mc_core.__wrapped__(v, 0.0, max_faces=cap,
                                                                         max_vertices=cap, spacing=sp), x)}
    old = None
    if a.old:
        old = _module_at(a.old)
        w_old = whole(old)
        comp[f"whole at {a.old}"] = lambda: jax.block_until_ready(w_old(x))
        compile_s[f"whole at {a.old}"] = _compile_cpu(
            lambda v: old._mc_core.__wrapped__(v, 0.0, max_faces=cap, max_vertices=cap, spacing=sp), x)
        same = all(np.array_equal(np.asarray(p), np.asarray(q), equal_nan=True)
                   for p, q in zip(w_new(x), w_old(x)))
        print(f"outputs equal to {a.old}'s (bit for bit): {same}")
    comp["skimage"] = lambda: measure.marching_cubes(-field, 0.0)
    tim = time_round_robin(comp, repeats=a.repeats, warmup=2)
    print(f"marching cubes, sphere {n}^3, capacity {cap}; medians of {a.repeats} round-robin repeats; "
          f"load {tuple(round(v, 1) for v in load_average())}")
    sk = tim["skimage"].median
    for k, t in tim.items():
        extra = f"  compile {compile_s[k]:.2f} s CPU" if k in compile_s else ""
        print(f"  {k:24s} {t.median * 1e3:8.1f} ms  ({t.median / sk:.2f}x skimage){extra}")
    if a.trace:
        todo = [("whole", w_new)] + ([(f"whole at {a.old}", w_old)] if old else [])
        for name, fn in todo:
            print(f"costliest fusions, {name} (ms per call):")
            for f, ms in _top_fusions(fn, x):
                print(f"  {ms:7.2f}  {f}")


if __name__ == "__main__":
    main()
