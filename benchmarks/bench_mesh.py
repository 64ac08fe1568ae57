"""Mesh benchmark: marching cubes against scikit-image, smoothing against Open3D.

Workloads (float32, JAX's default dtype; the peers get the same arrays):

* ``marching_cubes``: the iso-surface ``r = R`` of a sampled sphere field ``R - |x - c|`` on
  N^3 voxels (N = 64, 128; R = 0.39 N), fsjax ``ops.marching_cubes(level=0)`` against
  ``skimage.measure.marching_cubes(-field, 0)`` (Lewiner's method, its default). Accuracy
  beside speed: vertex and face counts, largest and mean radial error of the vertices, and
  the relative error of the mesh's area and enclosed volume against the analytic sphere.
  Batched: ``jit(vmap)`` over B = 4 spheres of different radii against a Python loop.
* ``taubin``: 10 lambda|mu iterations on a noisy icosphere (5 subdivisions, 20,480 faces),
  fsjax ``ops.taubin_smooth`` against Open3D's ``filter_smooth_taubin(number_of_iterations=10)``
  (Open3D counts a lambda|mu pair as one iteration, as fsjax does); accuracy: radial noise
  left and relative volume change (the noise-free sphere is the reference).

Timing from ``benchmarks/_harness.py``: medians of round-robin repeats after warm-up, compile
time apart, load average recorded.

Run ``python benchmarks/bench_mesh.py [--quick] [--write-docs]``; ``--write-docs`` writes
``docs/benchmarks_mesh.md``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(ROOT))

from _harness import jax_compile, load_average, machine_info, time_round_robin  # noqa: E402

BATCH = 4


def _sphere_field(n: int, radius: float) -> np.ndarray:
    z, y, x = np.mgrid[:n, :n, :n].astype(np.float32) - (n - 1) / 2.0
    return (radius - np.sqrt(x * x + y * y + z * z)).astype(np.float32)


def _mesh_stats(v: np.ndarray, f: np.ndarray, c: float, radius: float) -> dict:
    v = v.astype(np.float64)
    r = np.abs(np.linalg.norm(v - c, axis=1) - radius)
    a, b, d = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    area = 0.5 * np.linalg.norm(np.cross(b - a, d - a), axis=1).sum()
    vol = abs(np.einsum("ij,ij->i", a - c, np.cross(b - c, d - c)).sum() / 6.0)
    return dict(nv=len(v), nf=len(f), rmax=float(r.max()), rmean=float(r.mean()),
                area=float(area / (4 * np.pi * radius**2) - 1), vol=float(vol / (4 / 3 * np.pi * radius**3) - 1))


def bench_marching_cubes(quick: bool) -> list[dict]:
    import jax
    import jax.numpy as jnp
    from skimage import measure

    from fsjax import Volume
    from fsjax import ops as O

    rows = []
    for n in ((64,) if quick else (64, 128)):
        radius = 0.39 * n
        field = _sphere_field(n, radius)
        radii = [radius * (1 - 0.05 * k) for k in range(BATCH)]
        fields = np.stack([_sphere_field(n, r) for r in radii])

        def ours(d):
            m = O.marching_cubes(Volume(d), level=0.0)
            return m.vertices, m.faces, m.vertex_valid, m.face_valid, m.truncated

        f1, fb = jax.jit(ours), jax.jit(jax.vmap(ours))
        x1, xb = jnp.asarray(field), jnp.asarray(fields)
        c1, _ = jax_compile(ours, x1)
        cb, _ = jax_compile(jax.vmap(ours), xb)
        v, f, vv, fv, tr = (np.asarray(t) for t in f1(x1))
        assert not bool(tr)
        st = _mesh_stats(v[vv], f[fv], (n - 1) / 2.0, radius)
        vs, fs, _, _ = measure.marching_cubes(-field, 0.0)
        sk = _mesh_stats(vs, fs, (n - 1) / 2.0, radius)
        comp = {"fsjax": lambda f1=f1, x1=x1: jax.block_until_ready(f1(x1)),
                "skimage": lambda field=field: measure.marching_cubes(-field, 0.0),
                "fsjax_b": lambda fb=fb, xb=xb: jax.block_until_ready(fb(xb)),
                "skimage_b": lambda fields=fields: [measure.marching_cubes(-g, 0.0) for g in fields]}
        tim = time_round_robin(comp, repeats=3 if quick else 5, warmup=1)
        row = dict(task="marching_cubes", n=n, compile1=c1, compileb=cb, ours=st, peer=sk,
                   **{k: tim[k].median for k in comp}, load=load_average())
        rows.append(row)
        print(f"marching cubes {n}^3: fsjax {row['fsjax'] * 1e3:.1f} ms (compile {c1:.2f} s) "
              f"{st['nv']} v / {st['nf']} f, radial max {st['rmax']:.4f}, area {st['area']:+.5f}, volume "
              f"{st['vol']:+.5f}; skimage {row['skimage'] * 1e3:.1f} ms {sk['nv']} v / {sk['nf']} f, radial max "
              f"{sk['rmax']:.4f}, area {sk['area']:+.5f}, volume {sk['vol']:+.5f}; batch {BATCH}: fsjax "
              f"{row['fsjax_b'] * 1e3:.1f} ms (compile {cb:.2f} s), skimage {row['skimage_b'] * 1e3:.1f} ms; "
              f"load {row['load']}", flush=True)
    return rows


def bench_taubin(quick: bool) -> list[dict]:
    import jax
    import jax.numpy as jnp
    import open3d as o3d

    from fsjax import Mesh
    from fsjax import ops as O
    from fsjax.synth import icosphere

    v, f = icosphere(4 if quick else 5)
    rng = np.random.default_rng(0)
    noisy = (v * (1 + 0.02 * rng.standard_normal((len(v), 1)))).astype(np.float32)
    v0 = 4 / 3 * np.pi

    def ours(x, faces):
        return O.taubin_smooth(Mesh(x, faces), iterations=10).vertices

    f1 = jax.jit(ours)
    x1, faces = jnp.asarray(noisy), jnp.asarray(f)
    c1, _ = jax_compile(ours, x1, faces)
    om = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(noisy.astype(np.float64)),
                                   o3d.utility.Vector3iVector(f.astype(np.int32)))

    def peer():
        return om.filter_smooth_taubin(number_of_iterations=10)

    def stats(x):
        x = np.asarray(x, np.float64)
        r = np.linalg.norm(x, axis=1)
        a, b, d = x[f[:, 0]], x[f[:, 1]], x[f[:, 2]]
        vol = np.einsum("ij,ij->i", a, np.cross(b, d)).sum() / 6.0
        return dict(noise=float(r.std()), vol=float(vol / v0 - 1))

    st, sp, s0 = stats(f1(x1, faces)), stats(np.asarray(peer().vertices)), stats(noisy)
    comp = {"fsjax": lambda: jax.block_until_ready(f1(x1, faces)), "open3d": peer}
    tim = time_round_robin(comp, repeats=5, warmup=1)
    row = dict(task="taubin", n=len(f), compile1=c1, ours=st, peer=sp, input=s0,
               **{k: tim[k].median for k in comp}, load=load_average())
    print(f"taubin {len(f)} faces: fsjax {row['fsjax'] * 1e3:.1f} ms (compile {c1:.2f} s) noise "
          f"{st['noise']:.4f} volume {st['vol']:+.4f}; open3d {row['open3d'] * 1e3:.1f} ms noise "
          f"{sp['noise']:.4f} volume {sp['vol']:+.4f}; input noise {s0['noise']:.4f} volume {s0['vol']:+.4f}; "
          f"load {row['load']}", flush=True)
    return [row]


def _surface_distance(v, f, points):
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.asarray(v, np.float32)), o3d.core.Tensor(np.asarray(f, np.uint32)))
    return scene.compute_distance(o3d.core.Tensor(np.asarray(points, np.float32))).numpy()


def _area_samples(v, f, n, seed):
    rng = np.random.default_rng(seed)
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    w = np.linalg.norm(np.cross(b - a, c - a), axis=1)
    idx = rng.choice(len(f), n, p=w / w.sum())
    r1, r2 = rng.random((2, n))
    s = np.sqrt(r1)
    return (1 - s)[:, None] * a[idx] + (s * (1 - r2))[:, None] * b[idx] + (s * r2)[:, None] * c[idx]


def _hausdorff(v0, f0, v1, f1, n=200_000):
    """Symmetric Hausdorff and mean surface distance by exact point-to-triangle distances from
    ``n`` area-uniform samples of each mesh to the other (Open3D's raycasting scene)."""
    d01 = _surface_distance(v1, f1, _area_samples(v0, f0, n, 0))
    d10 = _surface_distance(v0, f0, _area_samples(v1, f1, n, 1))
    return float(max(d01.max(), d10.max())), float(0.5 * (d01.mean() + d10.mean()))


def bench_decimate(quick: bool) -> list[dict]:
    import time

    import jax
    import jax.numpy as jnp
    import open3d as o3d

    from fsjax import Mesh
    from fsjax import data as D
    from fsjax import ops as O

    v, f = D.mesh_arrays("fandisk")
    rows = []
    for ratio in ((0.1,) if quick else (0.25, 0.1)):
        target = int(np.ceil(ratio * len(f)))
        mesh = Mesh(jnp.asarray(v, jnp.float32), jnp.asarray(f))
        from fsjax.ops.mesh._decimate import _decimate_core as core
        jax.clear_caches()
        t0 = time.process_time()
        jax.jit(core.__wrapped__, static_argnames=("max_rounds",)).lower(
            mesh.vertices, mesh.faces, mesh.face_valid, mesh.vertex_valid, jnp.asarray(target, jnp.int32),
            jnp.asarray(1000.0, jnp.float32), max_rounds=2000).compile()
        compile_cpu = time.process_time() - t0
        jax.clear_caches()
        t0 = time.perf_counter()
        out = O.decimate(mesh, ratio=ratio)
        jax.block_until_ready(out.vertices)
        first = time.perf_counter() - t0
        fv = np.asarray(out.face_valid)
        ours = (np.asarray(out.vertices, np.float64), np.asarray(out.faces)[fv])
        om = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(v), o3d.utility.Vector3iVector(f.astype(np.int32)))
        peers = {"open3d": lambda om=om, target=target: om.simplify_quadric_decimation(target)}
        try:
            import fast_simplification

            peers["fast_simplification"] = lambda ratio=ratio: fast_simplification.simplify(
                v.astype(np.float32), f.astype(np.int32), target_reduction=1 - ratio)
        except ImportError:
            pass
        comp = {"fsjax": lambda mesh=mesh, ratio=ratio: jax.block_until_ready(O.decimate(mesh, ratio=ratio).vertices),
                **peers}
        tim = time_round_robin(comp, repeats=3, warmup=0)
        res = {"fsjax": ours}
        o3m = peers["open3d"]()
        res["open3d"] = (np.asarray(o3m.vertices), np.asarray(o3m.triangles))
        if "fast_simplification" in peers:
            res["fast_simplification"] = peers["fast_simplification"]()
        row = dict(task="decimate", n=len(f), ratio=ratio, first=first, compile_cpu=compile_cpu, load=load_average(),
                   **{k: tim[k].median for k in comp})
        for k, (vv, ff) in res.items():
            row[k + "_faces"] = len(ff)
            row[k + "_hd"], row[k + "_mean"] = _hausdorff(v, f, np.asarray(vv, np.float64), np.asarray(ff))
        print(f"decimate fandisk {len(f)} -> {ratio}: " + "; ".join(
            f"{k} {row[k + '_faces']} faces {row[k] * 1e3:.0f} ms Hausdorff {row[k + '_hd']:.5f} mean "
            f"{row[k + '_mean']:.6f}" for k in res) + f"; first call {first:.1f} s (compile {compile_cpu:.1f} s CPU); "
            f"load {row['load']}", flush=True)
        rows.append(row)
    return rows


def write_docs(rows: list[dict], cmd: str) -> None:
    mi = machine_info()
    out = ["# Mesh benchmarks: marching cubes, smoothing and decimation", "",
           "fsjax beside scikit-image (marching cubes), Open3D (Taubin smoothing, decimation) and",
           "fast-simplification (decimation, when installed), one process, same",
           f"inputs, float32. Reproduce with `{cmd}` (method in the script's docstring).", "",
           f"Machine: {mi.get('cpu', '')}, {mi.get('cores', '')} logical CPUs, {mi.get('memory', '')}; "
           f"load average recorded per row (2 cores).", "",
           "## Marching cubes (sphere field, R = 0.39 N)", "",
           "| N^3 | fsjax ms | skimage ms | ratio | batch 4: fsjax ms | skimage ms | ratio | compile s (single / batch) "
           "| vertices / faces (fsjax; skimage) | radial error max / mean, voxels (fsjax; skimage) "
           "| area error (fsjax; skimage) | volume error (fsjax; skimage) | load |",
           "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        if r["task"] != "marching_cubes":
            continue
        out.append(_mc_row(r))
    out += ["", "Ratio = fsjax time / peer time (below 1: fsjax faster). Goals (issue 16): area and enclosed",
            "volume within 0.5 % of the analytic sphere, radial error <= scikit-image's, time <= scikit-image's.", "",
            "## Taubin smoothing (noisy icosphere, 10 lambda|mu iterations)", "",
            "| faces | fsjax ms | Open3D ms | ratio | compile s | noise left (fsjax; Open3D; input) "
            "| volume change (fsjax; Open3D; input) | load |", "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        if r["task"] != "taubin":
            continue
        o, p, i = r["ours"], r["peer"], r["input"]
        out.append(f"| {r['n']} | {r['fsjax'] * 1e3:.1f} | {r['open3d'] * 1e3:.1f} | {r['fsjax'] / r['open3d']:.2f} | "
                   f"{r['compile1']:.1f} | {o['noise']:.4f}; {p['noise']:.4f}; {i['noise']:.4f} | "
                   f"{o['vol']:+.4f}; {p['vol']:+.4f}; {i['vol']:+.4f} | {r['load']} |")
    dec = [r for r in rows if r["task"] == "decimate"]
    if dec:
        diag = float(np.linalg.norm(np.ptp(__import__("fsjax").data.mesh_arrays("fandisk")[0], axis=0)))
        out += ["", f"## QEM decimation (fandisk, {dec[0]['n']} faces; bounding-box diagonal {diag:.2f})", "",
                "Hausdorff and mean distances are symmetric, by exact point-to-triangle distances from 200,000 "
                "area-uniform samples of each surface to the other.", "",
                "| ratio | method | faces | time ms | Hausdorff | mean distance | load |", "|---|---|---|---|---|---|---|"]
        for r in dec:
            out += _dec_rows(r)
    out += ["", "## Reading the figures", "",
            "* The machine is shared: the load average (1, 5, 15 min) is in each row. Under load 7-14",
            "  single-run times moved 3-4x between runs (128^3: 0.18 s and 0.85 s in two runs of this",
            "  script), so a ratio measured in one run is the figure, not the absolute times.",
            "* Compile times are wall seconds on that loaded machine; the marching-cubes program costs",
            "  about 1.5 s of CPU to compile at 128^3 (`time.process_time`; 1.7-2.2 s before vol16), after",
            "  an `optimization_barrier` stopped XLA from constant-folding the grid coordinates (that had",
            "  made compile time grow with the grid: 14 s at 64^3).",
            "* Marching cubes, where the time goes (128^3 sphere, `python benchmarks/profile_marching_cubes.py",
            "  --old 3a9c62c --trace`, load 13, medians of 9, each stage compiled as its own program and fed",
            "  the previous stage's outputs): 1 cell classification 9.6 ms, 2 vertex numbering (the",
            "  de-duplication: running popcounts of the crossed-edge words) 3.6 ms, 3 edge interpolation",
            "  (vertex slot -> edge -> position, over the 196,608 vertex slots) 18.9 ms, 4 face emission",
            "  (active-cube slots -> triangles -> vertex numbers) 18.1 ms; the whole op 42.8 ms, skimage",
            "  80.0 ms (0.54x), compile 1.55 s CPU.",
            "* The code before (commit 3a9c62c) built its flags over the grid: the crossed-edge flags of all",
            "  3 D H W edges (a concatenate of three shifted compares, fused by XLA into the bit-packing",
            "  reduction, where it ran at 88 ms to 480 ms per call from run to run), the corner pattern",
            "  of every cube as int32 and a cube mask, both operands of a `lax.cond` that was only needed",
            "  on overflow but were built on every call (and under `vmap` the cond became a select that ran",
            "  both branches). Now one pass over the voxels packs four bit planes (inside, has data, not on",
            "  the last x / y / z plane) 32 voxels to a word, and crossed edges and active cubes are word",
            "  operations on shifted bit streams; the cube pattern is gathered from the packed bits per",
            "  active cube; the edge-id table is precomputed per shape; the k-th set bit of a word is",
            "  counted by a 32-wide reduction (XLA materialises it once, where it copied the 5-step search",
            "  into every consumer); the overflow count comes from a second eager call instead of the cond.",
            "  Same outputs bit for bit (vertices, faces, masks, counts; spheres, random volumes with +-inf /",
            "  NaN, overflow, float32 and float64). In one process, 128^3: 88.6 -> 30.1 ms at load 13-15",
            "  (skimage 63.0 ms: 1.41x -> 0.48x) in one run, 518 -> 42.8 ms in another (the old fusion's",
            "  variance); batch of 4: 504 -> 285 ms (skimage 312); compile 1.66 -> 1.49-1.55 s CPU.",
            "* Accuracy: fsjax's vertices are skimage's (same edge intersections, same count); the",
            "  triangulations differ only in which diagonal splits a quad, which leaves area and volume",
            "  equal to five digits.",
            "* Taubin: both remove ~60 % of the radial noise at unchanged volume; fsjax's pass is a",
            "  segment-sum over the half-edges in one compiled loop.",
            "* Decimation: fsjax runs Garland-Heckbert's quadrics in parallel rounds of independent",
            "  collapses (Luby's random priority among the eligible edges, two edges apart: the cheapest",
            "  eighth or, while far from the target, twice the collapses still needed, up to four sqrt-2",
            "  cost buckets past the eighth's cut), in one `lax.while_loop` per stage of array capacity;",
            "  the peers run the sequential priority queue. Its",
            "  accuracy (the Hausdorff distance, set by the sharp creases and corners) is at or below",
            "  Open3D's at 10 %. Profile and changes (fandisk 10 %, float32, one core):",
            "  - one pass of Luby's rule per round selected ~1 edge per neighbourhood of cheap edges,",
            "    which cluster in flat regions: 10-15 collapses per round, ~490 rounds. Six passes (the",
            "    edges near a selected one drop out, the rest try again): ~50-75 rounds;",
            "  - each round sorted the half-edges four times (edges, cost order, priorities, link",
            "    condition; ~45 of 62 ms). Now the edge slots persist between rounds (a collapse",
            "    renames endpoints and merges the two edges to each apex), the cheapest eighth comes",
            "    from two histograms, priorities are the hash with the slot in its low bits, and the",
            "    link condition is counted by per-vertex scatter-min levels: no sort in a round;",
            "  - the quadric cost as a batched 4x4 `einsum` took 44 of 73 ms of a round; written",
            "    elementwise from the packed quadric it takes ~5 ms;",
            "  - together: 21.7 s -> 1.3 s (300x -> 16x Open3D in one run), Hausdorff 0.00513 ->",
            "    0.0033 (Open3D 0.0049). An earlier version that ranked candidates strictly by cost",
            "    found one local minimum per smooth region and, when the cheapest position folded,",
            "    fell back to an expensive one: Hausdorff 0.137; refusing such fall-backs fixed that.",
            "  - then (vol16): the eligible share widened as above (75 -> 52 rounds at 10 %, 49 -> 36 at",
            "    25 %); the arrays compacted between three stages of capacity (F, F/2, F/4 faces: the",
            "    valid faces and the edge slots they use move to the front, in order, so the result is",
            "    bit-identical to no compaction: 948 -> 481 ms alone); Luby's passes stop once no",
            "    candidate is left (identical). Together, in one process at load 6.6-7.7 (`python",
            "    benchmarks/profile_decimate.py --old 010bc42`): 10 %: 954 -> 322 ms (Open3D 85 ms: 11.2x",
            "    -> 3.8x), Hausdorff 0.00327 -> 0.00330 (Open3D 0.00487), mean 0.000232 -> 0.000237; 25 %:",
            "    958 -> 411 ms (Open3D 119 ms: 8.0x -> 3.4x), Hausdorff 0.00244 -> 0.00297 (Open3D",
            "    0.00230). Compile 4.2 -> 11.8 s CPU (one loop body per stage). The table above ran at load",
            "    12-14, where Open3D's time grew about 6x (491 ms) and fsjax's less: its 1.2x is the load's;",
            "  - left: in the middle phase about half the selected collapses are refused (every candidate",
            "    position folds a face) and the sets two edges apart stay small where the cheap edges",
            "    cluster (~50-230 of 1,000-3,000 eligible); each round recomputes every edge's cost (~2.7",
            "    of ~12 ms at full size, gathers); three Luby passes gave the same result as six on fandisk.", ""]
    (ROOT / "docs" / "benchmarks_mesh.md").write_text("\n".join(out) + "\n")


def _dec_rows(r: dict) -> list[str]:
    out = [f"| {r['ratio']} | {k} | {r[k + '_faces']} | {r[k] * 1e3:.0f} | {r[k + '_hd']:.5f} | "
           f"{r[k + '_mean']:.6f} | {r['load']} |" for k in ("fsjax", "open3d", "fast_simplification")
           if k + "_faces" in r]
    return out + [f"| {r['ratio']} | fsjax first call (compile + run; compile alone {r['compile_cpu']:.1f} s CPU) "
                  f"| | {r['first'] * 1e3:.0f} | | | |"]


def _mc_row(r: dict) -> str:
    o, p = r["ours"], r["peer"]
    return (f"| {r['n']} | {r['fsjax'] * 1e3:.1f} | {r['skimage'] * 1e3:.1f} | "
            f"{r['fsjax'] / r['skimage']:.2f} | {r['fsjax_b'] * 1e3:.1f} | {r['skimage_b'] * 1e3:.1f} | "
            f"{r['fsjax_b'] / r['skimage_b']:.2f} | {r['compile1']:.1f} / {r['compileb']:.1f} | "
            f"{o['nv']} / {o['nf']}; {p['nv']} / {p['nf']} | {o['rmax']:.4f} / {o['rmean']:.4f}; "
            f"{p['rmax']:.4f} / {p['rmean']:.4f} | {o['area']:+.5f}; {p['area']:+.5f} | "
            f"{o['vol']:+.5f}; {p['vol']:+.5f} | {r['load']} |")


def update_docs(rows: list[dict], cmd: str) -> None:
    """Replace, in the committed page, only the marching-cubes and decimation rows just measured
    (the other tables stay, from the run that wrote them) and say which rows came from this run."""
    import datetime

    page = ROOT / "docs" / "benchmarks_mesh.md"
    lines = page.read_text().splitlines()
    mc = [r for r in rows if r["task"] == "marching_cubes"]
    if mc:
        new = {f"| {r['n']} |": _mc_row(r) for r in mc}
        at = lines.index("## Marching cubes (sphere field, R = 0.39 N)")
        end = next(i for i in range(at + 1, len(lines)) if lines[i].startswith("## "))
        for i in range(at, end):
            for key, row in new.items():
                if lines[i].startswith(key):
                    lines[i] = row
        note = (f"Rows re-measured by `{cmd}` on {datetime.date.today().isoformat()}: marching cubes "
                f"{', '.join(str(r['n']) + '^3' for r in mc)}.")
        lines[at + 1:at + 1] = ["", note]
    dec = [r for r in rows if r["task"] == "decimate"]
    if dec:
        # the rows of each ratio measured are replaced as a block (the table's other ratios stay)
        at = next(i for i, x in enumerate(lines) if x.startswith("## QEM decimation"))
        end = next(i for i in range(at + 1, len(lines)) if lines[i].startswith("## "))
        for r in dec:
            idx = [i for i in range(at, end) if lines[i].startswith(f"| {r['ratio']} |")]
            if idx:
                lines[idx[0]:idx[-1] + 1] = _dec_rows(r)
                end = next(i for i in range(at + 1, len(lines)) if lines[i].startswith("## "))
        note = (f"Rows re-measured by `{cmd}` on {datetime.date.today().isoformat()}: decimation to "
                f"{', '.join(str(r['ratio']) for r in dec)}.")
        if at + 2 < len(lines) and lines[at + 2].startswith("Rows re-measured by"):
            lines[at + 2] = note     # the previous run's note is replaced, not stacked
        else:
            lines[at + 1:at + 1] = ["", note]
    page.write_text("\n".join(lines) + "\n")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--tasks", default="marching_cubes,taubin,decimate", help="comma-separated subset")
    ap.add_argument("--write-docs", action="store_true")
    ap.add_argument("--update-docs", action="store_true",
                    help="replace only the marching-cubes and decimation rows just measured in the committed page")
    args = ap.parse_args()
    tasks = args.tasks.split(",")
    rows = []
    for name, fn in (("marching_cubes", bench_marching_cubes), ("taubin", bench_taubin), ("decimate", bench_decimate)):
        if name in tasks:
            rows += fn(args.quick)
    flags = " --quick" if args.quick else ""
    if args.write_docs:
        write_docs(rows, "python benchmarks/bench_mesh.py" + flags)
    elif args.update_docs:
        update_docs(rows, f"python benchmarks/bench_mesh.py{flags} --tasks {args.tasks} --update-docs")


if __name__ == "__main__":
    main()
