"""Mesh rasteriser benchmark: fsjax.render.rasterize against Open3D's RaycastingScene.

Workload: a bumpy sphere (latitude-longitude grid with radial ripples, pole axis along
world x so the poles sit on the silhouette) of about 50k and 200k triangles, seen by a
512 x 512 pinhole camera (fov 40 deg) at distance 4, filling about 40 % of the image.
Both produce a depth map (camera z) of the same mesh for the same pixel-centre rays:

* fsjax: ``jax.jit(rasterize)`` (backface culling), float32 and float64, with the candidate
  buffer ``max_fragments`` sized from :func:`fsjax.render.count_fragments` (as an eager call
  does; counting time reported apart); compile time apart; the overflow count is reported
  (0 = exact).
* Open3D 0.20 ``o3d.t.geometry.RaycastingScene`` (Embree BVH, float32): BVH build apart,
  then ``cast_rays`` of the 512 x 512 rays with directions ``R K^-1 (u, v, 1)`` so that
  ``t_hit`` is the depth.

Accuracy: max and median |depth difference| over pixels both cover, the fraction of
pixels with the same coverage, and with the same face id. Timing and compile time come
from ``benchmarks/_harness.py`` (medians of round-robin repeats after warm-up).

Run ``python benchmarks/bench_raster.py`` (``--quick`` for a smoke run at 256 x 256,
``--write-docs`` to write ``docs/benchmarks_render.md``).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _harness import jax_compile, load_average, machine_info, time_round_robin  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def bumpy_sphere(n_faces: int):
    nv = int(round(np.sqrt(n_faces / 4.0)))
    nu = 2 * nv  # faces = 2 * nu * (nv - 1) ~ n_faces
    th = np.linspace(0, np.pi, nv + 1)
    ph = np.linspace(0, 2 * np.pi, nu, endpoint=False)
    T, P = np.meshgrid(th, ph, indexing="ij")
    r = 1.0 + 0.03 * np.sin(7 * T) * np.cos(5 * P)
    x, y, z = r * np.cos(T), r * np.sin(T) * np.cos(P), r * np.sin(T) * np.sin(P)
    V = np.stack([x, y, z], -1).reshape(-1, 3)
    idx = np.arange((nv + 1) * nu).reshape(nv + 1, nu)
    a, b = idx[:-1], np.roll(idx[:-1], -1, axis=1)
    c, d = idx[1:], np.roll(idx[1:], -1, axis=1)
    F = np.concatenate([np.stack([a, c, b], -1).reshape(-1, 3), np.stack([b, c, d], -1).reshape(-1, 3)])
    # drop the degenerate triangles at the poles (two equal vertices)
    keep = (F[:, 0] != F[:, 1]) & (F[:, 1] != F[:, 2]) & (F[:, 0] != F[:, 2])
    keep &= ~((np.isin(F, idx[0]).sum(1) >= 2) | (np.isin(F, idx[-1]).sum(1) >= 2))
    return V, F[keep].astype(np.int32)


def _module_at(rev: str):
    """fsjax/render/raster.py as it was at git revision ``rev``, loaded as a private module (for a
    before/after ratio in one process)."""
    import subprocess
    import types

    src = subprocess.run(["git", "-C", str(ROOT), "show", f"{rev}:fsjax/render/raster.py"], check=True,
                         capture_output=True, text=True).stdout
    for rel, ab in (("from .._checks", "from fsjax._checks"), ("from ..types", "from fsjax.types"),
                    ("from .splat", "from fsjax.render.splat")):
        src = src.replace(rel, ab)
    mod = types.ModuleType("raster_before")
    sys.modules["raster_before"] = mod
    exec(compile(src, f"raster.py@{rev}", "exec"), mod.__dict__)
    return mod


def run(size: int, counts, repeats: int, before_rev: str | None = None):
    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    import open3d as o3d

    import fsjax
    from fsjax.render import rasterize

    K = np.asarray(fsjax.render.intrinsics_from_fov(size, size, fov_x_deg=40.0))
    R = np.eye(3)
    t = np.asarray([0.0, 0.0, -4.0])
    before = _module_at(before_rev) if before_rev else None
    rows = []
    for nf in counts:
        V, F = bumpy_sphere(nf)
        # outward winding check (flip if needed)
        T = V[F]
        nrm = np.cross(T[:, 1] - T[:, 0], T[:, 2] - T[:, 0])
        if np.mean(np.sum(nrm * T.mean(1), 1)) < 0:
            F = F[:, ::-1].copy()
        res = {"faces": int(F.shape[0]), "size": size}
        outs = {}
        competitors = {}
        for dt in (jnp.float32, jnp.float64):
            mesh = fsjax.Mesh(jnp.asarray(V, dt), jnp.asarray(F))
            cam = fsjax.Camera(jnp.asarray(K, dt), width=size, height=size, R=jnp.asarray(R, dt),
                               t=jnp.asarray(t, dt))
            t0 = time.perf_counter()
            demand = fsjax.render.count_fragments(mesh, cam, cull_backfaces=True)
            res["count s"] = time.perf_counter() - t0
            res["fragments"] = demand
            B = fsjax.render.raster._bucket(demand)
            res["buffer"] = B

            def f(m, c, B=B):
                r = rasterize(m, c, cull_backfaces=True, max_fragments=B)
                return r.depth, r.face_id, r.overflow

            c0 = time.process_time()
            ct, comp = jax_compile(f, mesh, cam)
            name = f"fsjax {jnp.dtype(dt).name}"
            res[f"compile {name}"] = ct
            res[f"compile cpu {name}"] = time.process_time() - c0
            outs[name] = comp(mesh, cam)
            competitors[name] = (lambda comp=comp, mesh=mesh, cam=cam: jax.block_until_ready(comp(mesh, cam)))
            if before is not None and dt == jnp.float32:

                def fb(m, c, B=B):
                    r = before.rasterize(m, c, cull_backfaces=True, max_fragments=B)
                    return r.depth, r.face_id, r.overflow

                c0 = time.process_time()
                ctb, compb = jax_compile(fb, mesh, cam)
                res["compile before float32"] = ctb
                res["compile cpu before float32"] = time.process_time() - c0
                zb = np.asarray(compb(mesh, cam)[0])
                res["before max |diff| float32"] = float(np.max(np.abs(zb - np.asarray(outs[name][0]))))
                competitors["before float32"] = (lambda comp=compb, mesh=mesh, cam=cam:
                                                 jax.block_until_ready(comp(mesh, cam)))
        # Open3D
        t0 = time.perf_counter()
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.core.Tensor(V.astype(np.float32)), o3d.core.Tensor(F.astype(np.uint32)))
        vv, uu = np.meshgrid(np.arange(size), np.arange(size), indexing="ij")
        d = np.stack([(uu - K[0, 2]) / K[0, 0], (vv - K[1, 2]) / K[1, 1], np.ones_like(uu, float)], -1) @ R.T
        rays = np.concatenate([np.broadcast_to(t, d.shape), d], -1).astype(np.float32)
        rays_t = o3d.core.Tensor(rays)
        scene.cast_rays(rays_t)  # builds the BVH
        res["build open3d"] = time.perf_counter() - t0
        competitors["open3d"] = lambda: scene.cast_rays(rays_t)["t_hit"].numpy()
        o3 = scene.cast_rays(rays_t)
        z_o3 = o3["t_hit"].numpy()
        id_o3 = o3["primitive_ids"].numpy().astype(np.int64)
        timings = time_round_robin(competitors, repeats=repeats, warmup=1)
        for k, tm in timings.items():
            res[f"time {k}"] = tm.median
            res[f"iqr {k}"] = tm.iqr
        cov_o3 = np.isfinite(z_o3)
        for name, (z, fid, ovf) in outs.items():
            z = np.asarray(z, float)
            fid = np.asarray(fid)
            cov = fid >= 0
            both = cov & cov_o3
            dz = np.abs(z - z_o3)[both]
            res[f"overflow {name}"] = int(ovf)
            res[f"max dz {name}"] = float(dz.max())
            res[f"median dz {name}"] = float(np.median(dz))
            res[f"same coverage {name}"] = float(np.mean(cov == cov_o3))
            res[f"same face {name}"] = float(np.mean(fid[both] == id_o3[both]))
        res["coverage"] = float(cov_o3.mean())
        rows.append(res)
        print({k: (round(v, 6) if isinstance(v, float) else v) for k, v in res.items()}, flush=True)
    return rows


def write_docs(rows, load0, load1):
    info = machine_info()
    lines = [
        "# Benchmark: mesh rasteriser (fsjax.render.rasterize vs Open3D RaycastingScene)",
        "",
        "Generated by `python benchmarks/bench_raster.py --write-docs`. Same mesh, same 512 x 512 pixel-centre",
        "rays; depth is the camera z. fsjax: jitted, candidate buffer sized from `count_fragments`,",
        "backface culling; Open3D 0.20: Embree BVH in float32 (build time apart).",
        f"Machine: {info.get('cpu', '?')}, load average {load0} before and {load1} after the run",
        "(a shared 2-core machine: absolute times are inflated; compare the columns of one row). Compile:",
        "wall seconds and, in brackets, the process CPU seconds (XLA compiles on one thread: close to what an",
        "idle machine takes); the compile goal is judged on the CPU figure.",
        "",
        "| faces | candidates (buffer) | fsjax f32 s | fsjax f64 s | compile f32 / f64: wall s (CPU s) |"
        " Open3D s (+ build s) | f32 / Open3D | goal <= 5x | compile goal <= 10 s (CPU) |"
        " before f32 s (compile CPU s) | before / now |"
        " overflow f32/f64 | depth max / median diff f32 | f64 | same coverage | same face f64 |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        ratio = r["time fsjax float32"] / r["time open3d"]
        lines.append(
            f"| {r['faces']} | {r['fragments']:,} ({r['buffer']:,}) | {r['time fsjax float32']:.3f} | "
            f"{r['time fsjax float64']:.3f} | "
            f"{r['compile fsjax float32']:.1f} ({r.get('compile cpu fsjax float32', float('nan')):.1f}) / "
            f"{r['compile fsjax float64']:.1f} ({r.get('compile cpu fsjax float64', float('nan')):.1f}) | "
            f"{r['time open3d']:.3f} (+{r['build open3d']:.2f}) | {ratio:.1f}x | "
            f"{'reached' if ratio <= 5 else 'not reached'} | "
            f"{'reached' if r.get('compile cpu fsjax float32', 99) <= 10 else 'not reached'} | "
            f"{r.get('time before float32', float('nan')):.3f} ({r.get('compile cpu before float32', float('nan')):.1f}) | "
            f"{r.get('time before float32', float('nan')) / r['time fsjax float32']:.2f}x | "
            f"{r['overflow fsjax float32']} / {r['overflow fsjax float64']} | "
            f"{r['max dz fsjax float32']:.1e} / {r['median dz fsjax float32']:.1e} | "
            f"{r['max dz fsjax float64']:.1e} / {r['median dz fsjax float64']:.1e} | "
            f"{100 * r['same coverage fsjax float64']:.3f} % | {100 * r['same face fsjax float64']:.3f} % |")
    iq = ", ".join(f"{r['faces']}: {r['iqr fsjax float32']:.3f} / {r['iqr open3d']:.3f}" for r in rows)
    lines += [
        "",
        f"Inter-quartile range of the repeats, fsjax f32 / Open3D (s): {iq}. On this shared machine the fsjax",
        "times spread much more than Open3D's: a ratio near 1x means 'comparable', not 'faster'.",
        "",
        "Before / now in one process: `python benchmarks/bench_raster.py --before 0fd092b --write-docs` loads",
        "`fsjax/render/raster.py` of revision 0fd092b (the candidate-buffer rasteriser as it was before the",
        "changes below) beside the current one and times both round-robin with Open3D (columns 'before').",
        "Older history: the tiled rasteriser with a dense per-tile search (capacity 1024) took 7.26 s (f32) at",
        "49,728 faces and 21.1 s at 199,808 faces against Open3D's 0.15 s and 0.25 s (48x and 83x), compile",
        "29.6 s and 13.1 s.",
        "",
        "Where the time went at 0fd092b (`python benchmarks/profile_render.py --only raster`, XLA:CPU, f32):",
        "the differentiable per-pixel part (gather the winning face, transform it, recompute depth,",
        "barycentrics, normals) as `(H, W, 3, 3)` stacks with a per-pixel 3x3 product took ~100 ms at",
        "512 x 512 -- as much as the visibility search -- and ~2 ms as coordinate arrays (same formulas);",
        "at 200k faces the per-face setup on `(F, 3, 3)` / `(F, 6, 3)` stacks took ~200 ms (XLA fused the",
        "face gathers into every consumer and recomputed them), ~40 ms as coordinate arrays with the gathers",
        "materialised once; the candidate test's batched `(B, 3) x (B, 3, 3)` product became three gathered",
        "dot products. Compile: three `lax.associative_scan` prefix sums (one each ~0.9 s of CPU to compile)",
        "became `cumsum`, 4.4 -> 2.4 s of CPU for the whole rasteriser in the profile.",
        "",
        "Method: every front-facing triangle emits one candidate per pixel centre in its clipped screen",
        "bounding box into one buffer (prefix sum, slot owners by scatter + running maximum), each candidate",
        "is ray-tested with the homogeneous edge functions, and two scatter-mins per pixel keep the nearest",
        "depth and the lowest face id at that depth. The work is the number of candidates (column 2, about 3x",
        "the covered pixels here), not tiles x capacity; it hardly grows with the face count, the per-face",
        "setup does (the 200k row). Why not a BVH ray cast: a traversal is a data-dependent loop per ray",
        "(a `while_loop` per pixel under `vmap` runs every lane to the deepest ray on XLA:CPU), while the",
        "candidate buffer is a few flat vector passes whose size is known before the call. Open3D (Embree, native",
        "SIMD BVH) still wins at 200k faces; fsjax's value is that it runs under jit/vmap, in float64, and",
        "gives interior gradients.",
        "",
        "Float32 depth errors (the isolated max of the f32 column): investigated at 199,808 faces. Where the float32",
        "and float64 renders choose the same face (all but ~2 in 10^4 covered pixels) the float32 depth is within",
        "1.2e-5 of float64 (3e-6 relative); the isolated large errors (1.1e-2, one pixel) are pixels whose centre",
        "lies within float32 rounding (~0.02-0.05 px) of the edge shared by two adjacent faces, where float32 picks",
        "the neighbour, seen at grazing incidence (|cos| = 0.024, 88.6 deg): the two faces' planes then differ",
        "by ~ offset x tan(incidence) at the pixel. Bound: |dz| <= (edge rounding in px) x (depth change per px",
        "across the silhouette); it is not a wrong-surface error (the neighbour face is hit, coverage identical).",
        "Use float64 where grazing-incidence depth matters (a fix would need edge functions in face-local",
        "coordinates, keeping watertightness; not done).",
        "",
        "## Time vs count, both renderers",
        "",
        "![time vs splat count and face count](figures/bench_render_scaling.png)",
        "",
        "Left: `python benchmarks/bench_splat.py` (splat training step, render, render + gradient at 128 x 128;",
        "the step-time goals 0.3 s at 10k and 1 s at 50k dotted; table in `docs/splatting.md`). Right: this",
        "page's table. Drawn by `python benchmarks/bench_splat.py --chart` from `benchmarks/results/*.json`.",
        "",
    ]
    out = ROOT / "docs" / "benchmarks_render.md"
    out.write_text("\n".join(lines))
    print(f"wrote {out}")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--write-docs", action="store_true")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--faces", default="12500,50000,200000")
    ap.add_argument("--from-json", action="store_true", help="write the docs from benchmarks/results/raster.json")
    ap.add_argument("--before", default=None, help="git revision of fsjax/render/raster.py to time beside the "
                    "current one (float32, same process), e.g. 0fd092b")
    a = ap.parse_args()
    if a.from_json:
        d = json.loads((ROOT / "benchmarks" / "results" / "raster.json").read_text())
        write_docs(d["rows"], d["load_before"], d["load_after"])
        return
    load0 = load_average()
    if a.quick:
        rows = run(256, [20000], 2)
    else:
        rows = run(512, [int(x) for x in a.faces.split(",")], a.repeats, a.before)
    load1 = load_average()
    if not a.quick:
        (ROOT / "benchmarks" / "results").mkdir(exist_ok=True)
        (ROOT / "benchmarks" / "results" / "raster.json").write_text(json.dumps(
            {"load_before": load0, "load_after": load1, "rows": rows}, indent=1))
    if a.write_docs:
        write_docs(rows, load0, load1)


if __name__ == "__main__":
    main()
