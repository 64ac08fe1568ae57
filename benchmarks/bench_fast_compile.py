"""Compile and run time of the compile-dominated fits with XLA:CPU's default emitters vs its
older loop emitters (compiler option ``xla_cpu_use_fusion_emitters=False``), one process,
interleaved.

    python benchmarks/bench_fast_compile.py [--only NAME,...]

The fits are jitted here from their undecorated functions (``__wrapped__``), once with and once
without the option, so the library's own decoration does not decide both columns. Compile is
process CPU seconds of ``lower(...).compile()``; run time the median of 9 interleaved calls;
"max |diff|" compares every floating output leaf of the two programs where both are finite; a NaN
given by one program only is counted, and integer leaves that differ are printed (fit_cylinder: its
four axis starts that reach the same cylinder tie in residual within rounding, so the two programs
may report different winning starts' step counts, 5 vs 52, parameters within 2e-7). Each fit
runs on data of its own model (an ellipse, a circle, a half cylinder, a spherical cap for
select_model).

The library sets the option on these fits when they are called at top level
(``fsjax._linalg.jit_fast_compile``: ``jax.jit(..., compiler_options=...)`` is refused on a jit
nested in another jit, so under a user's jit the enclosing program's options apply).
"""

import time

import jax
import jax.numpy as jnp
import numpy as np

from fsjax._linalg import FAST_COMPILE
from fsjax.fit import primitives3d as P
from fsjax.ops.measure2d import _fit2d as F


def _cases():
    rng = np.random.default_rng(0)
    t = np.linspace(0, 2 * np.pi, 64, endpoint=False)
    e = np.stack([20 + 5 * np.sin(t), 30 + 12 * np.cos(t)], -1) + 0.05 * rng.standard_normal((64, 2))
    e = jnp.asarray(e, jnp.float32)
    c = np.stack([20 + 9 * np.sin(t), 30 + 9 * np.cos(t)], -1) + 0.05 * rng.standard_normal((64, 2))
    c = jnp.asarray(c, jnp.float32)
    v = jnp.ones(64, bool)
    u = rng.normal(size=(600, 3))
    u = u / np.linalg.norm(u, axis=1, keepdims=True)
    pts = jnp.asarray(u[u[:, 2] > 0.3][:150] + 0.01 * rng.normal(size=(150, 3)), jnp.float32)
    # a cylinder of radius 0.5 about a tilted axis, half the way round, for fit_cylinder
    th, h = rng.uniform(0, np.pi, 150), rng.uniform(-1, 1, 150)
    cyl = np.stack([0.5 * np.cos(th), 0.5 * np.sin(th), h], -1) + 0.005 * rng.normal(size=(150, 3))
    a = 0.3
    cyl = cyl @ np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]]).T
    cyl = jnp.asarray(cyl, jnp.float32)
    kw = dict(robust=True, rounds=3, refine=True, max_steps=100)
    return [
        ("fit_ellipse core", lambda p, v: F._fit_ellipse_core.__wrapped__(p, v, 3.0, 0.15, 0.1, **kw), (e, v)),
        ("fit_circle core", lambda p, v: F._fit_circle_core.__wrapped__(p, v, 3.0, 0.15, 0.1, **kw), (c, v)),
        ("fit_cylinder", lambda x: P.fit_cylinder.__wrapped__(x), (cyl,)),
        ("select_model", lambda x: P.select_model.__wrapped__(x), (pts,)),
        _shape_case(),
        _relative_pose_case(),
    ]


def _relative_pose_case():
    """relative_pose's program on 500 noisy correspondences of two views (256 hypotheses)."""
    from fsjax.fit import twoview as T
    from fsjax.fit.calibrate import rodrigues

    rng = np.random.default_rng(1)
    X = rng.uniform([-2, -2, 6], [2, 2, 10], (500, 3))
    R = np.asarray(rodrigues(jnp.asarray([0.0, 0.1, 0.0])))
    K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])

    def pr(P):
        return (P[:, :2] / P[:, 2:]) * 500 + [320, 240] + 0.3 * rng.standard_normal((len(P), 2))

    uv1 = jnp.asarray(pr(X), jnp.float32)
    uv2 = jnp.asarray(pr(X @ R.T + [-1.0, 0.0, 0.0]), jnp.float32)
    K = jnp.asarray(K, jnp.float32)
    one = jnp.asarray(1.0, jnp.float32)
    fn = T._relative_pose.__wrapped__
    return ("relative_pose", lambda k, a, b, K: fn(k, a, b, K, K, None, None, one, 256, 1.5 * one),
            (jax.random.PRNGKey(0), uv1, uv2, K))


def _shape_case():
    """shape_locate's core on the alignment scene (240 x 320, template 56 x 72), the arguments
    shape_locate passes it captured from one call."""
    import fsjax
    from fsjax.ops.matching import _shape as S
    from fsjax.synth import alignment_scene
    from fsjax.synth._workpiece import workpiece_template

    img = fsjax.Image(jnp.asarray(alignment_scene()[0], jnp.float32))
    tpl = fsjax.Image(jnp.asarray(workpiece_template(), jnp.float32))
    core, seen = S._shape_core, {}

    def spy(*a, **k):
        seen["a"], seen["k"] = a, k
        return core(*a, **k)

    S._shape_core = spy
    try:
        fsjax.ops.shape_locate(img, tpl)
    finally:
        S._shape_core = core
    return ("shape_locate core", lambda *a: core.__wrapped__(*a, **seen["k"]), seen["a"])


def main():
    import sys

    only = sys.argv[sys.argv.index("--only") + 1].split(",") if "--only" in sys.argv else None
    for name, fn, x in _cases():
        if only is not None and not any(o in name for o in only):
            continue
        res = {}
        for lab, opt in (("default", None), ("fast", FAST_COMPILE)):
            c = time.process_time()
            f = jax.jit(fn, compiler_options=opt).lower(*x).compile()
            res[lab] = (f, time.process_time() - c)
        times = {"default": [], "fast": []}
        for _ in range(9):
            for lab in times:
                t0 = time.perf_counter()
                jax.block_until_ready(res[lab][0](*x))
                times[lab].append(time.perf_counter() - t0)
        la = jax.tree_util.tree_leaves(res["default"][0](*x))
        lb = jax.tree_util.tree_leaves(res["fast"][0](*x))
        d, nan_mismatch, ints = 0.0, 0, []
        for p, q in zip(la, lb):
            if not np.issubdtype(np.asarray(p).dtype, np.floating):
                if np.any(np.asarray(p) != np.asarray(q)):
                    ints.append(f"{np.asarray(p).tolist()} vs {np.asarray(q).tolist()}")
                continue
            p, q = np.asarray(p, float), np.asarray(q, float)
            nan_mismatch += int(np.sum(np.isnan(p) != np.isnan(q)))
            both = ~(np.isnan(p) | np.isnan(q))
            if both.any():
                d = max(d, float(np.max(np.abs(p[both] - q[both]))))
        print(f"{name:18s} compile CPU {res['default'][1]:.2f} -> {res['fast'][1]:.2f} s; "
              f"run {np.median(times['default']) * 1e3:.2f} -> {np.median(times['fast']) * 1e3:.2f} ms; "
              f"max |diff| {d:.2e}" + (f", {nan_mismatch} NaN in one only" if nan_mismatch else "")
              + (f"; integer leaves differ: {', '.join(ints)}" if ints else ""),
              flush=True)


if __name__ == "__main__":
    main()
