"""Why fsjax is slower than OpenCV on some filters: small controlled experiments.

Not part of the library: each experiment times fsjax's op beside a variant
written here, on the benchmark's workload (``bench_filters.make_batch``), with
the same round-robin harness. The findings are summarised in
``benchmarks/notes_filters.md`` (and so in ``docs/benchmarks.md``).

1. Batching strategy: ``jit(vmap(op))`` over 64 images against
   ``jit(lax.map(op, batch_size=k))`` and a Python loop of ``jit(op)``.
   On a CPU ``vmap`` turns every shift-and-add into a pass over the whole
   64 x 256 x 256 batch (16 MiB per intermediate), which falls out of cache.
2. Median: ``jnp.sort`` over a stacked 25-sample window axis against a
   pruned min/max selection network (Batcher's odd-even merge sort for 32
   inputs, comparators that cannot reach rank 12 removed). Both are exact.
3. Sobel magnitude: fsjax's four padded 1-D passes against one padded copy
   and eight shifted slices.

Run ``python benchmarks/profile_filters.py [--batch 64] [--repeats 7]``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent))

from _harness import jax_compile, time_round_robin  # noqa: E402
from bench_filters import _fsjax_call, make_batch, reference  # noqa: E402

# The exact selection network now lives in fsjax (median fast path); reuse it.
from fsjax.ops.image._filters import _batcher_pairs as batcher_pairs  # noqa: E402
from fsjax.ops.image._filters import _selection_network as selection_network  # noqa: E402


def main(argv=None) -> int:
    import jax
    import jax.numpy as jnp

    p = argparse.ArgumentParser()
    p.add_argument("--batch", type=int, default=64)
    p.add_argument("--repeats", type=int, default=7)
    args = p.parse_args(argv)
    batch = make_batch(args.batch)
    xb = jax.device_put(batch)
    xs = [jax.device_put(batch[i]) for i in range(len(batch))]
    n = len(batch)

    def variants(f):
        vf = jax.jit(jax.vmap(f))
        m4 = jax.jit(lambda x: jax.lax.map(f, x, batch_size=4))
        m1 = jax.jit(lambda x: jax.lax.map(f, x))
        j1 = jax.jit(f)
        return {
            "jit(vmap)": lambda: jax.block_until_ready(vf(xb)),
            "jit(lax.map bs=4)": lambda: jax.block_until_ready(m4(xb)),
            "jit(lax.map bs=1)": lambda: jax.block_until_ready(m1(xb)),
            "loop of jit(op), blocking": lambda: [jax.block_until_ready(j1(x)) for x in xs],
        }

    def report(title, comps):
        t = time_round_robin(comps, repeats=args.repeats, warmup=1)
        print(f"\n{title}")
        for k, v in t.items():
            print(f"  {k:45s} {v.median:8.4f} s / batch  {1e3 * v.median / n:8.3f} ms / image  "
                  f"IQR [{v.q1:.4f}, {v.q3:.4f}]")
        sys.stdout.flush()

    # 1. batching strategy, per op
    for op in ("gaussian", "sobel", "dilation"):
        report(f"[1] batching strategy: {op}", variants(_fsjax_call(op)))

    # 2. median: sort versus selection network
    net = selection_network(25, 12)
    print(f"\n[2] median selection network: {len(net)} comparators "
          f"(full Batcher network restricted to 25 inputs: {len([q for q in batcher_pairs(32) if q[1] < 25])})")

    def median_network(x):
        h, w = x.shape
        xp = jnp.pad(x, 2, mode="symmetric")  # SciPy 'reflect'
        v = [xp[i:i + h, j:j + w] for i in range(5) for j in range(5)]
        for a, b in net:
            v[a], v[b] = jnp.minimum(v[a], v[b]), jnp.maximum(v[a], v[b])
        return v[12]

    fm = _fsjax_call("median")
    ref = reference("median", batch)
    for name, f in [("fsjax median (sort)", fm), ("selection network", median_network)]:
        c, _ = jax_compile(jax.vmap(f), xb)
        out = np.asarray(jax.jit(jax.vmap(f))(xb), np.float64)
        print(f"  {name:22s} compile {c:.2f} s, max|diff| vs SciPy {np.abs(out - ref).max():.1e}")
    j_sort = jax.jit(fm)
    j_net = jax.jit(median_network)
    m_net = jax.jit(lambda x: jax.lax.map(median_network, x, batch_size=4))
    report("[2] median 5x5", {
        "fsjax median, loop of jit(op)": lambda: [jax.block_until_ready(j_sort(x)) for x in xs],
        "selection network, loop of jit": lambda: [jax.block_until_ready(j_net(x)) for x in xs],
        "selection network, jit(lax.map bs=4)": lambda: jax.block_until_ready(m_net(xb)),
    })

    # 3. sobel: four padded passes versus one pad and shifted slices
    fs = _fsjax_call("sobel")

    def sobel_onepad(x):
        h, w = x.shape
        xp = jnp.pad(x, 1, mode="symmetric")

        def s(i, j):
            return xp[i:i + h, j:j + w]

        gx = (s(0, 2) - s(0, 0)) + 2 * (s(1, 2) - s(1, 0)) + (s(2, 2) - s(2, 0))
        gy = (s(2, 0) - s(0, 0)) + 2 * (s(2, 1) - s(0, 1)) + (s(2, 2) - s(0, 2))
        return jnp.sqrt(gx * gx + gy * gy) * 0.125

    d = float(np.abs(np.asarray(jax.vmap(sobel_onepad)(xb)) - np.asarray(jax.vmap(fs)(xb))).max())
    print(f"\n[3] sobel one-pad variant vs fsjax sobel_amp: max|diff| {d:.1e}")
    j_fs, j_op = jax.jit(fs), jax.jit(sobel_onepad)
    m_op = jax.jit(lambda x: jax.lax.map(sobel_onepad, x, batch_size=4))
    report("[3] sobel magnitude", {
        "fsjax sobel_amp, loop of jit(op)": lambda: [jax.block_until_ready(j_fs(x)) for x in xs],
        "one pad + 8 slices, loop of jit": lambda: [jax.block_until_ready(j_op(x)) for x in xs],
        "one pad + 8 slices, jit(lax.map bs=4)": lambda: jax.block_until_ready(m_op(xb)),
    })
    return 0


if __name__ == "__main__":
    sys.exit(main())
