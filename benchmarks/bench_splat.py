"""Splat rasteriser benchmark: training-step time vs splat count, viewer-sized render, dense null.

Workload: Spot (Crane et al.) rendered by fsjax's mesh rasteriser into 12 views at 128 x 128
(:func:`fsjax.fit.mesh_views`); splats initialised on its surface (:func:`fsjax.fit.init_from_mesh`).

* Training step (the issue's goal): :func:`fsjax.fit.train_splats` with densification off, one
  view per step (forward + backward + Adam, float32), for 1k / 10k / 50k splats; median step
  time over the steps that did not compile, compile time apart (the first step, plus any step
  that grew the pair buffer), the pair demand and the buffer, the overflow (must be 0).
* Render only (forward, and forward + gradient of a scalar loss with respect to the means),
  jitted with the buffer sized by :func:`fsjax.render.count_splat_pairs`, for the same counts
  and for a viewer-sized frame (512 x 512, 100k splats).
* Null / reference: :func:`fsjax.render.render_splats_dense` (every splat on every pixel) at
  1k splats, where it fits in memory; max |diff| of the two images beside the time.

The fixed-capacity renderer this replaced is loaded from git (``--before``) for a same-process
ratio.

Run ``python benchmarks/bench_splat.py`` (``--quick``: 1k and 10k only, no 512 px frame;
``--json PATH`` to save the rows; ``--before REV --counts 10000,50000``: render + gradient of
the renderer at git revision ``REV`` beside the current one, in one process; ``--tiles 16,8``:
training step and render + gradient (distortion off) at each tile size, in one process; ``--chart``).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
ROOT = Path(__file__).resolve().parents[1]
from _harness import load_average, time_round_robin  # noqa: E402


def _cam(data, i, dt):
    import jax

    return jax.tree_util.tree_map(lambda a: a[i].astype(dt) if a.dtype.kind == "f" else a[i], data.cameras)


def run(counts, viewer: bool, repeats: int, steps: int):
    import jax
    import jax.numpy as jnp

    import fsjax
    from fsjax.fit import init_from_mesh, mesh_views, train_splats
    from fsjax.render import count_splat_pairs, render_splats, render_splats_dense
    from fsjax.render.splat import _bucket

    data = mesh_views(fsjax.data.spot(), n_views=12, width=128, height=128, holdout_every=6)
    rows = []
    for n in counts:
        row = {"splats": n, "size": 128, "load_before": os.getloadavg()[0]}
        r = train_splats(jax.random.key(0), data, n_init=n, max_splats=n, iterations=steps, densify_from=10**9,
                         progress=False)
        row.update(step_s=r.step_seconds, step_compile_s=r.compile_seconds, step_compile_cpu_s=r.compile_cpu_seconds,
                   step_cpu_s=r.step_cpu_seconds, pairs=int(np.max(r.pairs)),
                   buffer=int(r.max_pairs), overflow=int(np.max(r.overflow)))
        g = init_from_mesh(jax.random.key(0), data, n, n)
        cam = _cam(data, int(data.train[0]), jnp.float32)
        B = _bucket(count_splat_pairs(g, cam))
        fwd = jax.jit(lambda g: render_splats(g, cam, max_pairs=B, distortion=False).color)
        bwd = jax.jit(jax.grad(lambda m, g: jnp.sum(render_splats(
            fsjax.Gaussians(m, g.log_scales, g.quats, g.opacity_logits, g.colors, valid=g.valid), cam,
            max_pairs=B, distortion=False).color), argnums=0))
        t0, c0 = time.perf_counter(), time.process_time()
        jax.block_until_ready(fwd(g))
        row["render_compile_s"] = time.perf_counter() - t0
        row["render_compile_cpu_s"] = time.process_time() - c0
        t0, c0 = time.perf_counter(), time.process_time()
        jax.block_until_ready(bwd(g.means, g))
        row["grad_compile_s"] = time.perf_counter() - t0
        row["grad_compile_cpu_s"] = time.process_time() - c0
        comp = {"forward": lambda: jax.block_until_ready(fwd(g)),
                "forward+grad": lambda: jax.block_until_ready(bwd(g.means, g))}
        if n <= 1000:
            dense = jax.jit(lambda g: render_splats_dense(g, cam).color)
            ref = jax.block_until_ready(dense(g))
            row["dense_vs_tiled_maxdiff"] = float(jnp.max(jnp.abs(ref - fwd(g))))
            comp["dense reference forward"] = lambda: jax.block_until_ready(dense(g))
        for k, tm in time_round_robin(comp, repeats=repeats, warmup=0).items():
            row[f"{k}_s"] = tm.median
        row["load_after"] = os.getloadavg()[0]
        print(row, flush=True)
        rows.append(row)
    if viewer:
        n, size = 100_000, 512
        g = init_from_mesh(jax.random.key(1), data, n, n)
        K = fsjax.render.intrinsics_from_fov(size, size, fov_x_deg=40.0)
        c = _cam(data, int(data.train[0]), jnp.float32)
        cam = fsjax.Camera(K.astype(jnp.float32), width=size, height=size, R=c.R, t=c.t)
        row = {"splats": n, "size": size, "load_before": os.getloadavg()[0]}
        t0 = time.perf_counter()
        npairs = count_splat_pairs(g, cam)
        row["count_s"] = time.perf_counter() - t0
        B = _bucket(npairs)
        fwd = jax.jit(lambda g: render_splats(g, cam, max_pairs=B, distortion=False).color)
        t0, c0 = time.perf_counter(), time.process_time()
        jax.block_until_ready(fwd(g))
        row.update(pairs=npairs, buffer=B, render_compile_s=time.perf_counter() - t0,
                   render_compile_cpu_s=time.process_time() - c0)
        tm = time_round_robin({"forward": lambda: jax.block_until_ready(fwd(g))}, repeats=repeats, warmup=0)
        row["forward_s"] = tm["forward"].median
        row["load_after"] = os.getloadavg()[0]
        print(row, flush=True)
        rows.append(row)
    return rows


def _module_at(rev: str):
    """fsjax/render/splat.py as it was at git revision ``rev``, loaded as a private module (the
    fixed-capacity renderer, for a before/after ratio in one process)."""
    import subprocess
    import types

    src = subprocess.run(["git", "-C", str(ROOT), "show", f"{rev}:fsjax/render/splat.py"], check=True,
                         capture_output=True, text=True).stdout
    src = src.replace("from .._checks import", "from fsjax._checks import").replace(
        "from ..types import", "from fsjax.types import").replace(
        "from .camera import", "from fsjax.render.camera import")
    mod = types.ModuleType("splat_before")
    sys.modules["splat_before"] = mod  # dataclasses (equinox modules) look their module up
    exec(compile(src, f"splat.py@{rev}", "exec"), mod.__dict__)
    return mod


def before_after(rev: str, counts, repeats: int):
    """Render + gradient (w.r.t. the means) of the renderer at ``rev`` (fixed tile capacity) and of
    the current one, same splats, same camera, same process, interleaved repeats."""
    import jax
    import jax.numpy as jnp

    import fsjax
    from fsjax.fit import init_from_mesh, mesh_views
    from fsjax.render import count_splat_pairs, render_splats
    from fsjax.render.splat import _bucket

    old = _module_at(rev)
    data = mesh_views(fsjax.data.spot(), n_views=12, width=128, height=128, holdout_every=6)
    rows = []
    for n in counts:
        g = init_from_mesh(jax.random.key(0), data, n, n)
        cam = _cam(data, int(data.train[0]), jnp.float32)
        B = _bucket(count_splat_pairs(g, cam))
        new = render_splats(g, cam, max_pairs=B)
        exact_cap = int(-(-int(new.max_tile_count) // 64) * 64)
        caps = [512] + ([exact_cap] if exact_cap <= 2048 else [])

        def loss(render, **kw):
            return jax.jit(jax.grad(lambda m, g: jnp.sum(render(
                fsjax.Gaussians(m, g.log_scales, g.quats, g.opacity_logits, g.colors, valid=g.valid), cam,
                **kw).color)))

        comp = {"new": loss(render_splats, max_pairs=B)}
        for c in caps:
            comp[f"before cap {c}"] = loss(old.render_splats, capacity=c)
        fns = dict(comp)
        row = {"splats": n, "pairs": int(new.pairs), "max_tile_count": int(new.max_tile_count),
               "load_before": os.getloadavg()[0]}
        for c in caps:
            o = old.render_splats(g, cam, capacity=c)
            row[f"before cap {c} overflow"] = int(o.overflow)
            row[f"before cap {c} maxdiff"] = float(jnp.max(jnp.abs(o.color - new.color)))
        for k, f in fns.items():
            t0 = time.perf_counter()
            jax.block_until_ready(f(g.means, g))
            row[f"{k} compile+first_s"] = time.perf_counter() - t0
        tm = time_round_robin({k: (lambda f=f: jax.block_until_ready(f(g.means, g))) for k, f in fns.items()},
                              repeats=repeats, warmup=0)
        for k, t in tm.items():
            row[f"{k}_s"] = t.median
        row["load_after"] = os.getloadavg()[0]
        print(row, flush=True)
        rows.append(row)
    return rows


def step_tiles(tiles, counts, steps: int, repeats: int):
    """Training step and render + gradient (``distortion=False``, the training path) at several tile
    sizes, in one process: ``train_splats(tile_size=T)`` alternating over ``tiles`` (twice each), then
    the render + gradient calls in interleaved repeats, with the gradients' max |diff| to the first
    tile size (tiling is exact, so only rounding differs)."""
    import equinox as eqx
    import jax
    import jax.numpy as jnp

    import fsjax
    from fsjax.fit import init_from_mesh, mesh_views, train_splats
    from fsjax.render import count_splat_pairs, render_splats
    from fsjax.render.splat import _bucket

    data = mesh_views(fsjax.data.spot(), n_views=12, width=128, height=128, holdout_every=6)
    rows = []
    for n in counts:
        row = {"splats": n, "tiles": list(tiles), "load_before": os.getloadavg()[0]}
        for _rep in range(2):
            for t in tiles:
                res = train_splats(jax.random.key(0), data, n_init=n, max_splats=n, iterations=steps,
                                   densify_from=10**9, progress=False, tile_size=t)
                row.setdefault(f"tile {t} step_s", []).append(res.step_seconds)
                row.setdefault(f"tile {t} step_cpu_s", []).append(res.step_cpu_seconds)
                row.setdefault(f"tile {t} compile_cpu_s", []).append(res.compile_cpu_seconds)
                row[f"tile {t} overflow"] = int(np.max(res.overflow))
                row[f"tile {t} pairs"] = int(np.max(res.pairs))
                row[f"tile {t} final_loss"] = float(res.loss[-1])
        g = init_from_mesh(jax.random.key(0), data, n, n)
        cam = _cam(data, int(data.train[0]), jnp.float32)

        def grad_of(t, cam=cam, g=g):
            B = _bucket(count_splat_pairs(g, cam, tile_size=t))
            return eqx.filter_jit(eqx.filter_grad(
                lambda gs: jnp.sum(render_splats(gs, cam, tile_size=t, max_pairs=B, distortion=False).color)))

        fns = {t: grad_of(t) for t in tiles}
        grads = {t: jax.block_until_ready(f(g)) for t, f in fns.items()}
        ref = grads[tiles[0]]
        for t in tiles[1:]:
            row[f"tile {t} grad rel maxdiff"] = max(
                float(jnp.max(jnp.abs(getattr(grads[t], f) - getattr(ref, f)))) / float(jnp.max(jnp.abs(getattr(ref, f))))
                for f in ("means", "log_scales", "opacity_logits", "colors"))
        tm = time_round_robin({f"tile {t} render+grad": (lambda f=f, g=g: jax.block_until_ready(f(g)))
                               for t, f in fns.items()}, repeats=repeats, warmup=0)
        for k, t in tm.items():
            row[f"{k}_s"] = t.median
        row["load_after"] = os.getloadavg()[0]
        print(row, flush=True)
        rows.append(row)
    return rows

def chart():
    """docs/figures/bench_render_scaling.png: time vs splat count and vs face count (saved JSON)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sp = json.loads((ROOT / "benchmarks" / "results" / "splat.json").read_text())
    ra = json.loads((ROOT / "benchmarks" / "results" / "raster.json").read_text())
    fig, ax = plt.subplots(1, 2, figsize=(10, 3.8))
    rows = [r for r in sp["rows"] if r["size"] == 128]
    n = [r["splats"] for r in rows]
    ax[0].loglog(n, [r["step_s"] for r in rows], "o-", label="training step (fwd + bwd + Adam)")
    ax[0].loglog(n, [r["forward+grad_s"] for r in rows], "s-", label="render + gradient")
    ax[0].loglog(n, [r["forward_s"] for r in rows], "^-", label="render")
    ax[0].axhline(0.3, color="0.6", ls=":", lw=1)
    ax[0].axhline(1.0, color="0.6", ls=":", lw=1)
    ax[0].set(xlabel="splats", ylabel="seconds (median)", title="splats, 128 x 128 (goals dotted)")
    ax[0].legend(fontsize=8)
    f = [r["faces"] for r in ra["rows"]]
    ax[1].loglog(f, [r["time fsjax float32"] for r in ra["rows"]], "o-", label="fsjax float32")
    ax[1].loglog(f, [r["time fsjax float64"] for r in ra["rows"]], "s-", label="fsjax float64")
    ax[1].loglog(f, [r["time open3d"] for r in ra["rows"]], "^-", label="Open3D (Embree) cast_rays")
    ax[1].set(xlabel="faces", ylabel="seconds (median)", title="mesh depth, 512 x 512")
    ax[1].legend(fontsize=8)
    fig.suptitle(f"shared 2-core machine, load {sp['load_before'][0]:.0f}-{ra['load_before'][0]:.0f}", fontsize=9)
    fig.tight_layout()
    out = ROOT / "docs" / "figures" / "bench_render_scaling.png"
    fig.savefig(out, dpi=90)
    print(f"wrote {out}")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--counts", default="1000,10000,50000")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--steps", type=int, default=8)
    ap.add_argument("--json", default=str(ROOT / "benchmarks" / "results" / "splat.json"))
    ap.add_argument("--before", default=None, help="git revision of the renderer to compare against "
                    "(render + gradient only), e.g. 1fb1c3a")
    ap.add_argument("--tiles", default=None, help="tile sizes to compare the training step and render + "
                    "gradient at, in one process, e.g. 16,8")
    ap.add_argument("--chart", action="store_true", help="only draw the chart from the saved JSON files")
    a = ap.parse_args()
    if a.chart:
        chart()
        return
    if a.tiles:
        load0 = load_average()
        rows = step_tiles([int(x) for x in a.tiles.split(",")], [int(x) for x in a.counts.split(",")], a.steps,
                          a.repeats)
        out = {"load_before": load0, "load_after": load_average(), "rows": rows}
        Path(str(ROOT / "benchmarks" / "results" / "splat_tiles.json")).write_text(json.dumps(out, indent=1))
        return
    if a.before:
        rows = before_after(a.before, [int(x) for x in a.counts.split(",")], a.repeats)
        out = {"rev": a.before, "load_before": load_average(), "rows": rows}
        Path(str(ROOT / "benchmarks" / "results" / "splat_before_after.json")).write_text(json.dumps(out, indent=1))
        return
    load0 = load_average()
    if a.quick:
        rows = run([1000, 10000], False, 2, 4)
    else:
        rows = run([int(x) for x in a.counts.split(",")], True, a.repeats, a.steps)
    out = {"load_before": load0, "load_after": load_average(), "rows": rows}
    if a.json:
        Path(a.json).write_text(json.dumps(out, indent=1))
        print(f"wrote {a.json}")


if __name__ == "__main__":
    main()
