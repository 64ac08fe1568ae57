"""3-D matching benchmark: fsjax's FFT methods against a NumPy/SciPy FFT implementation of the same method.

Workloads (float32, JAX's default; SciPy gets the same float32 arrays), on the matching grid's
bunny scenes (``fsjax.synth.match3d_scene``: clutter, 1 % noise) of N^3 voxels, N = 64 and 128:

* ``phase_correlation3d``: scene and template both N^3; the peer does the same steps with
  ``scipy.fft`` (cross-power spectrum with the Nyquist bins dropped, inverse FFT, integer
  peak, 6 Newton steps on the band-limited interpolant by the same separable contractions);
* ``ncc3d``: a 24^3 (N = 64) or 32^3 (N = 128) template in the scene; the peer: ``scipy.fft.rfftn``
  correlation, box sums by cumulative sums, the same 3x3x3 Newton peak.
* batched: ``jit(vmap(ncc3d))`` over B = 8 templates (crops of the scene) against a Python loop
  of the peer, throughput in templates per second.

Accuracy beside speed: both implementations' error against the scene's true shift (voxels).
Timing from ``benchmarks/_harness.py``: medians of round-robin repeats after warm-up, compile
time apart (fresh ``jax.jit``), load average recorded.

Run ``python benchmarks/bench_match3d.py [--quick] [--write-docs]``; ``--write-docs`` writes
``docs/benchmarks_match3d.md``.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

# one BLAS thread (as tests/conftest.py): OpenBLAS's spinning threads beside XLA's pool made the
# peer's small complex mat-vecs take seconds instead of milliseconds on 2 cores
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(ROOT))

from _harness import jax_compile, load_average, machine_info, time_round_robin  # noqa: E402

BATCH = 8


# ---------------------------------------------------------------------------
# the peers: the same methods in NumPy / SciPy
# ---------------------------------------------------------------------------


def _newton3(v):
    o = np.array([-1.0, 0.0, 1.0])
    d = np.meshgrid(o, o, o, indexing="ij")
    g = np.array([np.sum(a * v) / 18 for a in d])
    H = np.empty((3, 3))
    for a in range(3):
        H[a, a] = np.sum((d[a] ** 2 - 2 / 3) * v) / 3
        for b in range(a + 1, 3):
            H[a, b] = H[b, a] = np.sum(d[a] * d[b] * v) / 12
    if np.all(np.linalg.eigvalsh(H) < 0):
        step = -np.linalg.solve(H, g)
        if np.all(np.abs(step) <= 1):
            return step
    c = v[1, 1, 1]
    out = []
    for m, p in ((v[0, 1, 1], v[2, 1, 1]), (v[1, 0, 1], v[1, 2, 1]), (v[1, 1, 0], v[1, 1, 2])):
        den = m - 2 * c + p
        out.append(np.clip(0.5 * (m - p) / den, -0.5, 0.5) if den < 0 else 0.0)
    return np.array(out)


def pc_scipy(scene, tpl, steps=6):
    from scipy import fft

    a, b = tpl - tpl.mean(), scene - scene.mean()
    X = np.conj(fft.fftn(a)) * fft.fftn(b)
    mag = np.abs(X)
    ks = [np.fft.fftfreq(n) * n for n in X.shape]
    band = (np.abs(ks[0]) < X.shape[0] / 2)[:, None, None] & (np.abs(ks[1]) < X.shape[1] / 2)[None, :, None] \
        & (np.abs(ks[2]) < X.shape[2] / 2)[None, None, :]
    nz = (mag > 1e3 * np.finfo(a.dtype).eps * mag.max()) & band
    R = np.where(nz, X / np.where(nz, mag, 1), 0)
    r = np.real(fft.ifftn(R))
    idx = np.array(np.unravel_index(np.argmax(r), r.shape))
    x = np.where(idx > np.array(r.shape) // 2, idx - np.array(r.shape), idx).astype(float)
    w = [2 * np.pi * k / n for k, n in zip(ks, r.shape)]
    for _ in range(steps):
        ez, ey, ex = (np.exp(1j * wa * xa) for wa, xa in zip(w, x))
        Rx = [R @ (w[2] ** p * ex) for p in range(3)]
        Ry = {(p, q): Rx[p] @ (w[1] ** q * ey) for p in range(3) for q in range(3 - p)}

        def S(r_, q, p, Ry=Ry, ez=ez):
            return np.sum(Ry[(p, q)] * w[0] ** r_ * ez)

        g = -np.imag([S(1, 0, 0), S(0, 1, 0), S(0, 0, 1)])
        H = -np.real([[S(2, 0, 0), S(1, 1, 0), S(1, 0, 1)], [S(1, 1, 0), S(0, 2, 0), S(0, 1, 1)],
                      [S(1, 0, 1), S(0, 1, 1), S(0, 0, 2)]])
        x = x + np.clip(-np.linalg.solve(H, g), -0.5, 0.5)
    return x[::-1]  # (x, y, z)


def _box(x, n):
    c = np.cumsum(x, axis=0)
    c = np.concatenate([c[n - 1:n], c[n:] - c[:-n]], axis=0)
    return c


def ncc_scipy(scene, tpl):
    from scipy import fft

    D, H, W = scene.shape
    d, h, w = tpl.shape
    xc = scene - scene.mean()
    t0 = tpl - tpl.mean()
    num = fft.irfftn(fft.rfftn(xc) * np.conj(fft.rfftn(t0, s=scene.shape)), s=scene.shape)[:D - d + 1, :H - h + 1,
                                                                                           :W - w + 1]

    def boxes(a):
        a = _box(a, d)
        a = np.moveaxis(_box(np.moveaxis(a, 1, 0), h), 0, 1)
        return np.moveaxis(_box(np.moveaxis(a, 2, 0), w), 0, 2)

    n = d * h * w
    s1, s2 = boxes(xc.astype(np.float64)), boxes(xc.astype(np.float64) ** 2)
    var = np.maximum(s2 - s1 * s1 / n, 1e-30)
    S = num / np.sqrt(var * np.sum(t0 * t0))
    idx = np.array(np.unravel_index(np.argmax(S), S.shape))
    if np.all((idx >= 1) & (idx <= np.array(S.shape) - 2)):
        v = S[idx[0] - 1:idx[0] + 2, idx[1] - 1:idx[1] + 2, idx[2] - 1:idx[2] + 2]
        idx = idx + _newton3(v)
    return idx[::-1]


# ---------------------------------------------------------------------------


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--write-docs", action="store_true")
    args = ap.parse_args()
    import jax
    import jax.numpy as jnp

    import fsjax
    from fsjax.synth import match3d_scene

    sizes = (64,) if args.quick else (64, 128)
    repeats = 3 if args.quick else 7
    load0 = load_average()
    rows = []
    for N in sizes:
        ts = 24 if N == 64 else 32
        shift = (2.3, -1.6, 0.7)
        # phase correlation: template as large as the scene
        sc, tp, tr = match3d_scene(size=N, template_size=None, shift=shift, dtype=jnp.float32)
        s_np, t_np = np.asarray(sc.data), np.asarray(tp.data)

        def pc_fs(s, t):
            return fsjax.ops.phase_correlation3d(fsjax.Volume(s), fsjax.Volume(t)).t

        comp_s, compiled = jax_compile(pc_fs, sc.data, tp.data)
        t_fs = np.asarray(compiled(sc.data, tp.data))
        t_sp = pc_scipy(s_np, t_np)
        tim = time_round_robin({"fsjax": lambda c=compiled, a=sc.data, b=tp.data: jax.block_until_ready(c(a, b)),
                                "scipy": lambda a=s_np, b=t_np: pc_scipy(a, b)}, repeats=repeats, warmup=1)
        rows.append(("phase_correlation3d", f"{N}^3 vs {N}^3", tim["fsjax"].median, tim["scipy"].median, comp_s,
                     np.linalg.norm(t_fs - tr["t"]), np.linalg.norm(t_sp - tr["t"])))
        print(rows[-1], flush=True)
        # NCC: a template in the scene
        sc, tp, tr = match3d_scene(size=N, template_size=ts, shift=shift, dtype=jnp.float32)
        s_np, t_np = np.asarray(sc.data), np.asarray(tp.data)

        def ncc_fs(s, t):
            return fsjax.ops.ncc3d(fsjax.Volume(s), fsjax.Volume(t)).t

        comp_s, compiled = jax_compile(ncc_fs, sc.data, tp.data)
        t_fs = np.asarray(compiled(sc.data, tp.data))
        t_sp = ncc_scipy(s_np, t_np)
        tim = time_round_robin({"fsjax": lambda c=compiled, a=sc.data, b=tp.data: jax.block_until_ready(c(a, b)),
                                "scipy": lambda a=s_np, b=t_np: ncc_scipy(a, b)}, repeats=repeats, warmup=1)
        rows.append(("ncc3d", f"{ts}^3 in {N}^3", tim["fsjax"].median, tim["scipy"].median, comp_s,
                     np.linalg.norm(t_fs - tr["t"]), np.linalg.norm(t_sp - tr["t"])))
        print(rows[-1], flush=True)
        # batched: B templates (crops of the scene around the object, shifted by 0..B-1 voxels)
        c0 = np.round(tr["t"]).astype(int)[::-1]
        crops = np.stack([s_np[c0[0] + b % 3:c0[0] + b % 3 + ts, c0[1] + b // 3:c0[1] + b // 3 + ts,
                               c0[2]:c0[2] + ts] for b in range(BATCH)])
        crops_j = jnp.asarray(crops)
        comp_b, cb = jax_compile(jax.vmap(ncc_fs, in_axes=(None, 0)), sc.data, crops_j)
        tim = time_round_robin({"fsjax": lambda c=cb, a=sc.data, b=crops_j: jax.block_until_ready(c(a, b)),
                                "scipy": lambda a=s_np, b=crops: [ncc_scipy(a, t) for t in b]},
                               repeats=repeats, warmup=1)
        rows.append(("ncc3d vmap", f"{BATCH} x {ts}^3 in {N}^3", tim["fsjax"].median, tim["scipy"].median, comp_b,
                     float("nan"), float("nan")))
        print(rows[-1], flush=True)
    load1 = load_average()
    info = machine_info()
    L = ["# Benchmark: 3-D matching (FFT methods)", "",
         "Generated by `python benchmarks/bench_match3d.py --write-docs`" + (" --quick" if args.quick else "") +
         ". fsjax against a NumPy/SciPy (`scipy.fft`) implementation of the same method, one process, the "
         "same float32 inputs (the matching grid's bunny scenes: clutter, 1 % noise, true shift "
         "(2.3, -1.6, 0.7) voxels). Steady-state medians of round-robin repeats after warm-up; compile "
         "(trace + lower + XLA) apart on a fresh `jax.jit`.", "",
         f"Machine: {info.get('cpu', '?')}, {info.get('cores')} cores; load {load0[0]:.1f} -> {load1[0]:.1f} "
         f"(other jobs shared the machine); {repeats} repeats.", "",
         "| method | workload | fsjax (s) | scipy (s) | scipy / fsjax | fsjax compile (s) | error fsjax (vox) | "
         "error scipy (vox) |", "|---|---|---|---|---|---|---|---|"]
    for name, wl, tf, ts_, comp, ef, es in rows:
        extra = f" ({BATCH / tf:.1f} vs {BATCH / ts_:.1f} templates/s)" if "vmap" in name else ""
        L.append(f"| `{name}` | {wl} | {tf:.4f} | {ts_:.4f} | {ts_ / tf:.2f}{extra} | {comp:.2f} | "
                 f"{ef:.4f} | {es:.4f} |")
    L += ["", "A ratio above 1 means fsjax is faster. The errors differ where float32 rounding moves the "
          "integer peak or the Newton step (the methods are the same).", ""]
    text = "\n".join(L)
    print(text)
    if args.write_docs:
        (ROOT / "docs" / "benchmarks_match3d.md").write_text(text)


if __name__ == "__main__":
    main()
