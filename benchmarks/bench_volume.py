"""Volume benchmark: fsjax 3-D Gaussian / median / EDT / label against SciPy and scikit-image.

Workloads, on N^3 volumes (N = 64, 128; ``--big`` adds 256), float32 (JAX's default dtype;
SciPy gets the same float32 arrays and returns float32 for the filters):

* ``gaussian``: ``gaussian3d(sigma=2)`` at unit spacing vs ``scipy.ndimage.gaussian_filter(x, 2)``;
* ``median``: ``median3d(radius=1)`` (3x3x3 cube) vs ``scipy.ndimage.median_filter(x, size=3)``;
* ``edt``: ``distance_transform3d`` of a mask of random balls at spacing (2, 1, 1) vs
  ``scipy.ndimage.distance_transform_edt(m, sampling=(2, 1, 1))``;
* ``label``: ``label3d(connectivity=26)`` of a thresholded smoothed noise vs
  ``scipy.ndimage.label(m, np.ones((3, 3, 3)))`` and ``skimage.measure.label(m, connectivity=3)``.

scikit-image's 3-D Gaussian, median and EDT call ``scipy.ndimage`` (``skimage.filters.gaussian``
and ``median`` wrap it; it has no EDT of its own), so only its labelling is timed separately.
Each task runs single (one volume) and batched (B = 4 volumes: ``jit(vmap(op))`` against a
Python loop of the peer). Accuracy beside speed: max |fsjax - scipy| (labels: equal arrays).
Timing from ``benchmarks/_harness.py``: medians of round-robin repeats after warm-up, compile
time apart, load average recorded.

Run ``python benchmarks/bench_volume.py [--quick] [--big] [--write-docs]``; ``--write-docs``
writes ``docs/benchmarks_volume.md``.
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

NOTES = [
    "## Reading the figures",
    "",
    "* The machine is shared (load average above, 2 cores); a ratio within about 10 % of 1 is a",
    "  tie, not a win or a loss. 256^3 rows come from `--big` (3 repeats instead of 5).",
    "* **median**: a pruned Batcher selection network over the 27 shifted copies of the volume",
    "  (elementwise min/max of whole volumes) against SciPy's per-voxel selection: the one task",
    "  where fsjax is far ahead.",
    "* **gaussian**: both are separable 1-D correlations (17 taps per axis at sigma 2); fsjax's",
    "  shift-and-add is on a par with SciPy's C loop, within the noise of a loaded machine.",
    "* **edt**: the same separable algorithm as SciPy (a scan per line, then the lower envelope of",
    "  parabolas per axis); the parabola passes are sequential `lax.scan`s whose stack pops are",
    "  `while_loop`s. The lines of a pass go through in chunks of 512, one chunk after the other,",
    "  and under `vmap` the members run one after the other (a `custom_vmap` rule: `lax.map`): a",
    "  chunk's stacks (n x 512) stay in the cache and its pops wait only for its own longest chain",
    "  of pops. Before, all lines of a volume (and of a batch) ran as lanes in lock-step. Each",
    "  step measured old against new in one process, identical results: members one after the",
    "  other (commit adae71c; `python benchmarks/profile_edt3d.py --old 2054329`, load 12), batch",
    "  of 4 at 128^3 4543 -> 1736 ms (SciPy 1842), 64^3 336 -> 207 ms (SciPy 154); then chunks",
    "  of 512 lines (`--old adae71c`, load 10): 128^3 594 -> 210 ms, batch 2250 -> 821 ms; 64^3",
    "  53 -> 15 ms, batch 224 -> 87 ms (SciPy's times in that run were inflated by a second",
    "  benchmark running beside it).",
    "* **label**: Shiloach-Vishkin union-find rounds on the graph of 2x2x2 blocks (any two voxels of",
    "  a 2x2x2 cube are 26-neighbours, so a block's foreground is one piece; 8x fewer nodes than",
    "  voxels), each round a gather, 26 masked neighbour taps (13 loop steps) and a scatter-min over the",
    "  blocks, with block indices as pointers; one scatter-min of first-voxel keys onto the roots",
    "  after convergence finds each component's first voxel, and those blocks are ranked by running",
    "  popcounts of packed marks (one per (z, y, x // 2) cell). Against SciPy's and scikit-image's",
    "  single sequential two-pass scans. History, each step measured old against new in one",
    "  process: one node per voxel (commit 0ae1fc4) -> 2x2x2 blocks (commit 4ffbe78), load 1.4:",
    "  128^3 101.3 -> 54.3 ms (SciPy 36.6). Ranking by a float32 cumulative sum over all voxels",
    "  (commit 3a9c62c) -> packed cell marks, load 12-13: 128^3 95.2 -> 81.7 ms (SciPy 55.6).",
    "  Voxel keys as pointers (each gather and scatter of a round divided a key into its block)",
    "  and adjacency bits re-reduced per term (commit 4a4ffe3) -> block-index pointers and bits",
    "  from shared ORs (commit 3ed2629), load 2.5-3.5 (`python benchmarks/profile_label3d.py --old",
    "  4a4ffe3 --sizes 64,128,256`): 64^3 6.6 -> 3.0 ms (SciPy 2.8), 128^3 30.8 -> 26.2 ms (SciPy",
    "  22.1), 256^3 242 -> 195 ms (SciPy 193); compile 1.23 -> 0.97 s CPU at 128^3. Then the bits",
    "  from one per-block word of position-set bits (commit e189844; `--old 3ed2629`), load",
    "  0.9-1.2: 128^3 16.0 -> 14.5 ms (SciPy 21.2), 256^3 208.5 -> 160.6 ms (SciPy 166.5), batch",
    "  of 4 at 256^3 915 -> 865 ms (SciPy 665). Then two neighbour taps per loop step (commit",
    "  cb3a63d; `--old e189844`), load 1.2-1.5: 128^3 17.4 -> 13.7 ms (SciPy 20.9), 256^3 144.4 ->",
    "  133.5 ms (SciPy 156.8), batch of 4 at 256^3 813 -> 678 ms (SciPy 986). The union-find",
    "  rounds are unchanged (4 / 5 / 6 at",
    "  64 / 128 / 256^3; runs along x as the starting pointers, and one or three pointer jumps per",
    "  round instead of two, were measured: no fewer rounds, or slower; 26 taps unrolled into one",
    "  fusion over the whole volume: slower). Then (vol16, second stop) the 26 taps run per z-slab",
    "  of 8 block layers, all of a slab's taps in one fused pass (the slab stays in the cache),",
    "  and a root block's position inside its block comes from arithmetic instead of two gathers",
    "  from an 8-entry table (`python benchmarks/profile_label3d.py --old 34a80f2 --sizes",
    "  64,128,256`, `nice -n 5`, load 8-10): 256^3 610 -> 419 ms (SciPy 797), batch of 4 2804 ->",
    "  2057 ms (SciPy 2910); 128^3 50.2 -> 47.4 ms (SciPy 49.3), batch 339 -> 314 ms (SciPy 213);",
    "  64^3 batch 29.7 -> 17.0 ms (SciPy 18.7); identical labels; compile 1.05 -> 1.15 s CPU. Before",
    "  it, at 256^3 a call was roughly: writing the 64 MB int32 output ~35 ms (SciPy",
    "  writes the same), adjacency bits ~11 ms, 6 rounds of 26 masked taps plus 3 gathers and a",
    "  scatter (these ~5 ms a round), at load 0.5. A batch is labelled as one volume (members stacked along",
    "  z with a background block layer between them). fsjax runs XLA's two threads and suffers more",
    "  from a loaded machine than SciPy's one thread: the ratio moves with the load (the profile",
    "  lines above are unniced; the table is `nice -n 5`).",
    "* Marching cubes is benchmarked beside scikit-image in [benchmarks_mesh.md](benchmarks_mesh.md),",
    "  with its stage breakdown (`python benchmarks/profile_marching_cubes.py`).",
]


def _inputs(n: int, b: int, seed: int = 0):
    """``b`` volumes of each kind: grey texture, ball mask, blob mask (float32)."""
    import scipy.ndimage as ndi

    rng = np.random.default_rng(seed)
    grey, balls, blobs = [], [], []
    zz, yy, xx = np.ogrid[0:n, 0:n, 0:n]
    for _ in range(b):
        grey.append(rng.random((n, n, n)).astype(np.float32))
        m = np.ones((n, n, n), bool)
        for c in rng.uniform(0, n, (max(4, n // 8), 3)):
            r = rng.uniform(n / 16, n / 6)
            m &= ((zz - c[0]) ** 2 + (yy - c[1]) ** 2 + (xx - c[2]) ** 2) > r * r
        balls.append(m.astype(np.float32))
        blobs.append((ndi.gaussian_filter(rng.random((n, n, n)), 2.0) > 0.52).astype(np.float32))
    return np.stack(grey), np.stack(balls), np.stack(blobs)


def run(quick: bool, big: bool, tasks: tuple[str, ...] = ("gaussian", "median", "edt", "label")) -> list[dict]:
    import jax
    import jax.numpy as jnp
    import scipy.ndimage as ndi
    from skimage import measure

    from fsjax import Volume
    from fsjax import ops as O

    sp = (2.0, 1.0, 1.0)
    ops = {
        "gaussian": (lambda d: O.gaussian3d(Volume(d), sigma=2.0).data,
                     lambda v: ndi.gaussian_filter(v, 2.0), "grey"),
        "median": (lambda d: O.median3d(Volume(d), radius=1).data,
                   lambda v: ndi.median_filter(v, size=3), "grey"),
        "edt": (lambda d: O.distance_transform3d(Volume(d, spacing=sp)).data,
                lambda v: ndi.distance_transform_edt(v > 0.5, sampling=sp), "balls"),
        # capacity above the component count of every input here (6,485 blobs at 256^3): the
        # default 1,024 would truncate (flagged) and the labels could not equal SciPy's
        "label": (lambda d: O.label3d(Volume(d), connectivity=26, capacity=16384).data,
                  lambda v: ndi.label(v > 0.5, np.ones((3, 3, 3)))[0], "blobs"),
    }
    sizes = (64,) if quick else ((64, 128, 256) if big else (64, 128))
    rows = []
    for n in sizes:
        grey, balls, blobs = _inputs(n, BATCH)
        data = {"grey": grey, "balls": balls, "blobs": blobs}
        for task, (ours, ref, kind) in ops.items():
            if task not in tasks:
                continue
            xs = data[kind]
            f1 = jax.jit(ours)
            fb = jax.jit(jax.vmap(ours))
            x1, xb = jnp.asarray(xs[0]), jnp.asarray(xs)
            c1, _ = jax_compile(f1, x1)
            cb, _ = jax_compile(fb, xb)
            out1 = np.asarray(f1(x1))
            r1 = ref(xs[0])
            if task == "label":
                acc = "equal" if np.array_equal(out1, r1) else "DIFFER"
                sk = measure.label(xs[0] > 0.5, connectivity=3)
                acc_sk = "equal" if np.array_equal(out1, sk) else "DIFFER"
            else:
                acc = f"{float(np.max(np.abs(out1.astype(np.float64) - r1))):.1e}"
                acc_sk = ""
            comp = {"fsjax": lambda f1=f1, x1=x1: jax.block_until_ready(f1(x1)),
                    "scipy": lambda ref=ref, xs=xs: ref(xs[0]),
                    "fsjax_b": lambda fb=fb, xb=xb: jax.block_until_ready(fb(xb)),
                    "scipy_b": lambda ref=ref, xs=xs: [ref(v) for v in xs]}
            if task == "label":
                comp["skimage"] = lambda xs=xs: measure.label(xs[0] > 0.5, connectivity=3)
                comp["skimage_b"] = lambda xs=xs: [measure.label(v > 0.5, connectivity=3) for v in xs]
            reps = 3 if (quick or n >= 256) else 5
            tim = time_round_robin(comp, repeats=reps, warmup=1)
            row = dict(task=task, n=n, compile1=c1, compileb=cb, acc=acc, acc_sk=acc_sk,
                       **{k: tim[k].median for k in comp})
            rows.append(row)
            sk_txt = (f", skimage {row['skimage'] * 1e3:.1f} ms / batch {row['skimage_b'] * 1e3:.1f} ms"
                      if task == "label" else "")
            print(f"{task} {n}^3: fsjax {row['fsjax'] * 1e3:.1f} ms (compile {c1:.2f} s), scipy "
                  f"{row['scipy'] * 1e3:.1f} ms; batch {BATCH}: fsjax {row['fsjax_b'] * 1e3:.1f} ms "
                  f"(compile {cb:.2f} s), scipy {row['scipy_b'] * 1e3:.1f} ms{sk_txt}; accuracy {acc} "
                  f"{acc_sk}; load {load_average()}", flush=True)
    return rows


def _mark(ours, peer):
    return "reached" if ours <= peer else "not reached"


def _main_row(r: dict) -> str:
    return (f"| {r['task']} | {r['n']}^3 | {r['fsjax'] * 1e3:.1f} | {r['scipy'] * 1e3:.1f} | "
            f"{r['fsjax'] / r['scipy']:.2f} | {_mark(r['fsjax'], r['scipy'])} | {r['fsjax_b'] * 1e3:.1f} | "
            f"{r['scipy_b'] * 1e3:.1f} | {r['fsjax_b'] / r['scipy_b']:.2f} | {_mark(r['fsjax_b'], r['scipy_b'])} | "
            f"{r['compile1']:.2f} / {r['compileb']:.2f} | {r['acc']} |")


def _sk_row(r: dict) -> str:
    return (f"| {r['n']}^3 | {r['fsjax'] * 1e3:.1f} | {r['skimage'] * 1e3:.1f} | "
            f"{r['fsjax'] / r['skimage']:.2f} | {r['fsjax_b'] * 1e3:.1f} | "
            f"{r['skimage_b'] * 1e3:.1f} | {r['fsjax_b'] / r['skimage_b']:.2f} | {r['acc_sk']} |")


def update_docs(rows: list[dict], cmd: str) -> None:
    """Replace, in the committed page, the rows of the tasks and sizes just measured (the other
    rows stay, from the run named at the top) and say which rows came from this run."""
    import datetime

    page = ROOT / "docs" / "benchmarks_volume.md"
    lines = page.read_text().splitlines()
    main = {f"| {r['task']} | {r['n']}^3 |": _main_row(r) for r in rows}
    sk = {f"| {r['n']}^3 |": _sk_row(r) for r in rows if r["task"] == "label"}
    in_sk = False
    for i, ln in enumerate(lines):
        if ln.startswith("scikit-image labelling"):
            in_sk = True
        table = sk if in_sk else main
        for key, new in table.items():
            if ln.startswith(key):
                lines[i] = new
    la = ", ".join(f"{v:.1f}" for v in load_average())
    done = ", ".join(sorted({f"{r['task']} {r['n']}^3" for r in rows}))
    note = (f"Rows re-measured by `{cmd}` on {datetime.date.today().isoformat()} (load average at the end: "
            f"{la}): {done}; the other rows are from the run above.")
    at = next(i for i, ln in enumerate(lines) if ln.startswith("| task |"))
    if at >= 2 and lines[at - 2].startswith("Rows re-measured by"):
        lines[at - 2] = note     # the previous partial run's note is replaced, not stacked
    else:
        lines[at:at] = [note, ""]
    notes = next((i for i, ln in enumerate(lines) if ln == NOTES[0]), len(lines))
    lines[notes:] = NOTES                              # the prose follows the code, not the old run
    page.write_text("\n".join(lines) + "\n")


def write_docs(rows: list[dict], cmd: str) -> None:
    mi = machine_info()
    la = ", ".join(f"{v:.1f}" for v in load_average())

    lines = [
        "# Benchmark: volume filters, distance transform and labelling (issue 16)",
        "",
        f"Generated by `{cmd}`. fsjax (jitted, float32 inputs, x64 off) against",
        "`scipy.ndimage` and scikit-image in one process on the same arrays (see the module docstring",
        "of `benchmarks/bench_volume.py` for the workloads). Single: one N^3 volume; batched: B = 4",
        "volumes, fsjax as `jit(vmap(op))`, the peers as a Python loop. Medians of round-robin repeats",
        "after one warm-up; compile time (trace + lower + XLA compile of a fresh `jit`) measured apart",
        "and not included in the times. scikit-image's 3-D Gaussian, median and EDT are",
        "`scipy.ndimage` underneath, so they are not timed twice; its labelling is timed.",
        "",
        "Goal (issue 16): single and batched at or below SciPy. The *goal* columns say reached /",
        "not reached by the median times of this run.",
        "",
        f"Machine: {mi.get('cpu', '?')}, {mi.get('cores', '?')} cores, shared with other agents while",
        f"this ran (load average at the end: {la}); ratios measured in one process are more",
        "trustworthy than absolute times.",
        "",
        "| task | N | fsjax (ms) | scipy (ms) | ratio fsjax/scipy | goal single | fsjax B=4 (ms) | scipy B=4 (ms) "
        "| ratio B=4 | goal batched | compile single / batched (s) | accuracy vs scipy |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    lines += [_main_row(r) for r in rows]
    lab = [r for r in rows if r["task"] == "label"]
    if lab:
        lines += ["", "scikit-image labelling (`skimage.measure.label(m, connectivity=3)`):", "",
                  "| N | fsjax (ms) | skimage (ms) | ratio | fsjax B=4 (ms) | skimage B=4 (ms) | ratio B=4 | "
                  "labels equal |", "|---|---|---|---|---|---|---|---|"]
        lines += [_sk_row(r) for r in lab]
    lines += ["", *NOTES]
    (ROOT / "docs" / "benchmarks_volume.md").write_text("\n".join(lines) + "\n")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--big", action="store_true", help="add 256^3")
    ap.add_argument("--tasks", default="gaussian,median,edt,label", help="comma-separated subset")
    ap.add_argument("--write-docs", action="store_true")
    ap.add_argument("--update-docs", action="store_true",
                    help="replace only the measured rows of the committed page (with --tasks)")
    a = ap.parse_args()
    rows = run(a.quick, a.big, tuple(a.tasks.split(",")))
    flags = " ".join(f for f, on in (("--quick", a.quick), ("--big", a.big)) if on)
    if a.write_docs:
        write_docs(rows, f"python benchmarks/bench_volume.py {flags} --write-docs".replace("  ", " "))
    elif a.update_docs:
        update_docs(rows, f"python benchmarks/bench_volume.py {flags} --tasks {a.tasks} --update-docs".replace("  ", " "))


if __name__ == "__main__":
    main()
