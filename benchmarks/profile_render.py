"""Where the time of the two renderers goes: a breakdown by stage, compile apart.

* Splat training step at 128 x 128 (Spot, 10k splats initialised on the surface, float32): the
  projection; the forward render; the render + gradient of an L1 loss (all Gaussian parameters);
  the same with the training loss's SSIM term; the SSIM value + gradient alone; the gradient by
  ``jax.linearize`` + transpose (the path ``optimistix.OptaxMinimiser`` takes).
* Mesh depth at 512 x 512 (the bumpy sphere of ``bench_raster.py``, float32, backface culling):
  the visibility setup (transform, clipped boxes); setup + candidate search; the whole
  ``rasterize`` returning the depth.

Each stage is jitted on its own: first-call time (tracing + compile + one run), the process CPU
time of that first call (compilation is single-threaded, so this is close to what an idle machine
would take), and the median of ``--repeats`` further calls. Stages are timed one after the other,
so on a shared machine compare within one run. Run ``python benchmarks/profile_render.py``
(``--splats N``, ``--tile T`` (splat tile px, default 16), ``--faces N``, ``--only splat|raster``).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))


def _stage(name, f, *args, repeats=5):
    import jax

    t0, c0 = time.perf_counter(), time.process_time()
    jax.block_until_ready(f(*args))
    first, cpu = time.perf_counter() - t0, time.process_time() - c0
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(f(*args))
        ts.append(time.perf_counter() - t0)
    print(f"| {name} | {first:.2f} | {cpu:.2f} | {1e3 * np.median(ts):.1f} |", flush=True)


def splat(n: int, repeats: int, tile: int = 16):
    import equinox as eqx
    import jax
    import jax.numpy as jnp

    import fsjax
    from fsjax.fit import init_from_mesh, mesh_views
    from fsjax.fit.splat_train import ssim_color
    from fsjax.render import count_splat_pairs, render_splats
    from fsjax.render.splat import _bucket, _project

    data = mesh_views(fsjax.data.spot(), n_views=12, width=128, height=128, holdout_every=6)
    g = init_from_mesh(jax.random.key(0), data, n, n)
    v = int(data.train[0])
    cam = jax.tree_util.tree_map(lambda a: a[v].astype(jnp.float32) if a.dtype.kind == "f" else a[v], data.cameras)
    img = data.images[v].astype(jnp.float32)
    B = _bucket(count_splat_pairs(g, cam, tile_size=tile))
    kw = {"max_pairs": B, "tile_size": tile}
    if "distortion" in render_splats.__code__.co_varnames:
        kw["distortion"] = False
    print(f"\nsplats {n}, 128 x 128, tile {tile} px, pairs {count_splat_pairs(g, cam, tile_size=tile)} (buffer {B}), "
          f"load {os.getloadavg()[0]:.1f}")
    print("| stage | first call s | first call CPU s | median ms |\n|---|---|---|---|")
    _stage("projection", jax.jit(lambda g: _project(g, cam, 0.01, 0.3, 1 / 255, 3.0, None).uv), g, repeats=repeats)
    _stage("render (forward)", eqx.filter_jit(lambda g: render_splats(g, cam, **kw).color), g, repeats=repeats)

    def l1(g):
        return jnp.mean(jnp.abs(render_splats(g, cam, **kw).color - img))

    def full(g):
        c = render_splats(g, cam, **kw).color
        return 0.8 * jnp.mean(jnp.abs(c - img)) + 0.2 * (1 - ssim_color(c, img))

    _stage("render + gradient, L1", eqx.filter_jit(eqx.filter_grad(l1)), g, repeats=repeats)
    _stage("render + gradient, L1 + SSIM", eqx.filter_jit(eqx.filter_grad(full)), g, repeats=repeats)
    _stage("SSIM value + gradient alone", jax.jit(jax.grad(lambda c: ssim_color(c, img))), img * 0.9,
           repeats=repeats)

    def lin(m):
        def f(m):
            return full(fsjax.Gaussians(m, g.log_scales, g.quats, g.opacity_logits, g.colors, valid=g.valid))
        y, lf = jax.linearize(f, m)
        return jax.linear_transpose(lf, m)(jnp.ones((), y.dtype))

    _stage("linearize + transpose (means), L1 + SSIM", jax.jit(lin), g.means, repeats=repeats)


def raster(nf: int, repeats: int):
    import jax
    import jax.numpy as jnp

    import fsjax
    from bench_raster import bumpy_sphere
    from fsjax.render import count_fragments, rasterize
    from fsjax.render import raster as RR
    from fsjax.render.splat import _bucket

    size = 512
    K = np.asarray(fsjax.render.intrinsics_from_fov(size, size, fov_x_deg=40.0))
    V, F = bumpy_sphere(nf)
    T = V[F]
    if np.mean(np.sum(np.cross(T[:, 1] - T[:, 0], T[:, 2] - T[:, 0]) * T.mean(1), 1)) < 0:
        F = F[:, ::-1].copy()
    dt = jnp.float32
    mesh = fsjax.Mesh(jnp.asarray(V, dt), jnp.asarray(F))
    cam = fsjax.Camera(jnp.asarray(K, dt), width=size, height=size, R=jnp.eye(3, dtype=dt),
                       t=jnp.asarray([0.0, 0.0, -4.0], dt))
    B = _bucket(count_fragments(mesh, cam, cull_backfaces=True))
    near = jnp.asarray(1e-6, dt)
    print(f"\nfaces {F.shape[0]}, 512 x 512, buffer {B}, load {os.getloadavg()[0]:.1f}")
    print("| stage | first call s | first call CPU s | median ms |\n|---|---|---|---|")

    def setup(m):
        return RR._visibility_setup(m, cam, near, True, dt)

    def search(m):
        Ks, boxes, Cj, Nn, det, _ = setup(m)
        return RR._search_fragments(boxes, size, size, B, Ks, Cj, Nn, det, near, dt)[0]

    _stage("visibility setup", jax.jit(lambda m: setup(m)[1][-1]), mesh, repeats=repeats)
    _stage("setup + candidate search", jax.jit(search), mesh, repeats=repeats)
    _stage("rasterize (depth)", jax.jit(lambda m: rasterize(m, cam, cull_backfaces=True, max_fragments=B).depth),
           mesh, repeats=repeats)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--splats", type=int, default=10000)
    ap.add_argument("--faces", type=int, default=50000)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--tile", type=int, default=16, help="splat tile size (train_splats uses 8)")
    ap.add_argument("--only", choices=("splat", "raster"), default=None)
    a = ap.parse_args()
    if a.only in (None, "splat"):
        splat(a.splats, a.repeats, a.tile)
    if a.only in (None, "raster"):
        raster(a.faces, a.repeats)


if __name__ == "__main__":
    main()
