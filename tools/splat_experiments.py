"""Gaussian-splatting experiments: step timing, held-out quality, budget sweep, depth distortion.

Usage::

    python tools/splat_experiments.py --stages timing,main,sweep,distortion   # run, save JSON
    python tools/splat_experiments.py --write-docs                            # docs/splatting.md + figures

Each stage writes its numbers into ``docs/figures/splatting_results.json`` (merged), so stages
can run in separate processes; ``--write-docs`` only reads that file. Data: Spot rendered by
fsjax's mesh rasteriser (:func:`fsjax.fit.mesh_views`), cached in ``/tmp``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
RESULTS = ROOT / "docs" / "figures" / "splatting_results.json"


def _load():
    return json.loads(RESULTS.read_text()) if RESULTS.exists() else {}


def _save(key, value):
    # merge under a lock-free re-read (stages may run in parallel processes)
    d = _load()
    d[key] = value
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    tmp = RESULTS.with_suffix(f".{os.getpid()}.tmp")
    tmp.write_text(json.dumps(d, indent=1, sort_keys=True))
    tmp.replace(RESULTS)


def _data(size, views, mesh="spot"):
    import fsjax
    from fsjax.fit import mesh_views

    return mesh_views(getattr(fsjax.data, mesh)(), n_views=views, width=size, height=size, holdout_every=6,
                      capacity=4096)


def stage_timing(args):
    import jax

    from fsjax.fit import train_splats

    data = _data(args.size, 12)
    out = {}
    for n in [int(x) for x in args.timing_sizes.split(",")]:
        r = train_splats(jax.random.key(0), data, n_init=n, max_splats=n, iterations=6, densify_from=10**9,
                         progress=False, capacity=args.capacity or None)
        out[str(n)] = {"step_s": r.step_seconds, "compile_s": r.compile_seconds,
                       "overflow": int(np.max(r.overflow)), "load": os.getloadavg()[0],
                       "pairs": int(np.max(r.pairs)), "buffer": int(r.max_pairs)}
        print("timing", n, out[str(n)], flush=True)
        _save(f"timing_{args.size}_{_capkey(args.capacity)}", out)


def _capkey(cap):
    """Result key part: ``capN`` for the legacy fixed per-tile capacity, ``grown`` for the
    sort-based renderer whose pair buffer follows the measured demand (``--capacity 0``)."""
    return f"cap{cap}" if cap else "grown"


def _run(data, key, budget, iters, cap, dist_weight=0.0, dist_norm=False):
    import jax

    from fsjax.fit import evaluate_splats, train_splats

    t0 = time.time()
    r = train_splats(jax.random.key(key), data, n_init=max(budget // 2, 1), max_splats=budget, iterations=iters,
                     densify_every=100, densify_from=100, densify_until=int(iters * 0.6), capacity=cap or None,
                     dist_weight=dist_weight, dist_normalise=dist_norm, progress=True)
    wall = time.time() - t0
    ev = evaluate_splats(r.gaussians, data)  # eager renders: pair buffer sized from the demand, exact
    ev_train = evaluate_splats(r.gaussians, data, data.train[:6])
    return {"budget": budget, "iterations": iters, "final_splats": int(np.asarray(r.gaussians.valid).sum()),
            "heldout": ev, "train_psnr": ev_train["psnr"], "step_s": r.step_seconds, "wall_s": wall,
            "train_overflow_max": int(np.max(r.overflow)), "loss_first": float(r.loss[:20].mean()),
            "loss_last": float(r.loss[-20:].mean()), "dist_weight": dist_weight, "dist_norm": dist_norm}, r


def stage_main(args):
    data = _data(args.size, args.views)
    res, r = _run(data, 0, args.main_budget, args.main_iters, args.capacity)
    res.update(capacity=args.capacity, load=os.getloadavg()[0],
               command=f"python tools/splat_experiments.py --stages main --main-budget {args.main_budget} "
                       f"--main-iters {args.main_iters} --capacity {args.capacity} --size {args.size} "
                       f"--views {args.views}")
    print("main", res, flush=True)
    _save(f"main_{args.size}", res)
    from fsjax.io import write_splat

    write_splat(f"/tmp/splat_main_{args.size}.splat", r.gaussians)
    _save_images(data, r.gaussians, args.size)


def _save_images(data, g, size):
    import jax
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from fsjax.render import render_splats

    vi = int(data.test[0])
    cam = jax.tree_util.tree_map(lambda a: a[vi], data.cameras)
    cam = jax.tree_util.tree_map(lambda a: a.astype(g.means.dtype) if a.dtype.kind == "f" else a, cam)
    out = render_splats(g, cam, capacity=1024)
    fig, ax = plt.subplots(1, 3, figsize=(9, 3.2))
    ax[0].imshow(np.asarray(data.images[vi]))
    ax[0].set_title("held-out view (mesh raster)")
    ax[1].imshow(np.clip(np.asarray(out.color), 0, 1))
    ax[1].set_title("splats")
    ax[2].imshow(np.asarray(out.alpha), cmap="gray", vmin=0, vmax=1)
    ax[2].set_title("accumulated alpha")
    for a in ax:
        a.axis("off")
    fig.tight_layout()
    fig.savefig(ROOT / "docs" / "figures" / f"splatting_heldout_{size}.png", dpi=90)
    plt.close(fig)


def stage_sweep(args):
    data = _data(args.sweep_size, args.views)
    out = []
    for b in [int(x) for x in args.budgets.split(",")]:
        res, _ = _run(data, 0, b, args.sweep_iters, args.capacity)
        res.update(capacity=args.capacity, load=os.getloadavg()[0])
        print("sweep", b, res["heldout"]["psnr"], res["heldout"]["ssim"], flush=True)
        out.append(res)
        _save(f"sweep_{args.sweep_size}_{_capkey(args.capacity)}", out)


def stage_distortion(args):
    data = _data(args.sweep_size, args.views)
    out = []
    for w, norm in ((0.0, False), (args.dist_weight, False), (args.dist_weight, True)):
        res, _ = _run(data, 0, args.dist_budget, args.sweep_iters, args.capacity, dist_weight=w, dist_norm=norm)
        print("distortion", w, norm, res["heldout"], flush=True)
        out.append(res)
        _save(f"distortion_{args.sweep_size}", out)


def _bench_section():
    """Section from ``benchmarks/results/splat.json`` (``python benchmarks/bench_splat.py``)."""
    path = ROOT / "benchmarks" / "results" / "splat.json"
    if not path.exists():
        return []
    d = json.loads(path.read_text())
    goal = {10000: 0.3, 50000: 1.0}
    out = ["## Speed of the sort-based renderer", "",
           "Measured by `python benchmarks/bench_splat.py` (one process; float32; Spot at 128 x 128, splats",
           "initialised on the surface; training step = `train_splats` with densification off, forward +",
           "backward + Adam, median of the steps that did not compile; render = jitted forward, and forward +",
           "gradient of a scalar loss with respect to the means, pair buffer sized by `count_splat_pairs`;",
           "the step at `train_splats`' tile size, 8 px since issue 18's second round, the render columns at",
           "`render_splats`' default 16 px, so the pairs column is the step's).",
           f"Machine **shared** with other sessions: load average {d['load_before'][0]:.1f} before and "
           f"{d['load_after'][0]:.1f} after (2 cores)"
           + (", so absolute times are inflated several-fold;" if d['load_before'][0] > 6 else ";"),
           "the fixed-capacity before-figures below were measured under load 8-13. Compile: wall seconds and, in",
           "brackets, the process CPU seconds of the same calls (XLA compiles on one thread, so the CPU time is",
           "close to what an idle machine takes); the goal (<= 10 s) is judged on the CPU figure. Step CPU: the",
           "median process CPU time of a step (all threads), roughly an upper bound of an idle machine's step",
           "time; the step goals are judged on the wall time as measured.", "",
           "| splats | px | step (s) | step CPU (s) | goal | step compile: wall (CPU) s | compile goal | pairs (buffer) | overflow |"
           " render (s) | render + grad (s) | render / render + grad compile: wall (CPU) s |"
           " dense reference render (s) | load |",
           "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in d["rows"]:
        g = goal.get(r["splats"]) if r["size"] == 128 else None
        st = f"{r['step_s']:.3f}" if "step_s" in r else "-"
        gl = "-" if g is None else (f"<= {g} s: {'reached' if r['step_s'] <= g and r['overflow'] == 0 else 'not reached'}"
                                    f" ({r['step_s'] / g:.2f}x)")
        nan = float("nan")
        comp = (f"{r['step_compile_s']:.1f} ({r.get('step_compile_cpu_s', nan):.1f})" if "step_compile_s" in r
                else "-")
        cgoal = ("-" if "step_compile_s" not in r else
                 ("reached" if r.get("step_compile_cpu_s", 99) <= 10 else "not reached"))
        rcomp = f"{r['render_compile_s']:.1f} ({r.get('render_compile_cpu_s', nan):.1f})"
        if "grad_compile_s" in r:
            rcomp += f" / {r['grad_compile_s']:.1f} ({r.get('grad_compile_cpu_s', nan):.1f})"
        dense = (f"{r['dense reference forward_s']:.3f} (max diff {r['dense_vs_tiled_maxdiff']:.0e})"
                 if "dense reference forward_s" in r else "-")
        out.append(f"| {r['splats']:,} | {r['size']} | {st} | {format(r['step_cpu_s'], '.3f') if 'step_cpu_s' in r else '-'} | "
                   f"{gl} | {comp} | {cgoal} | {r['pairs']:,} "
                   f"({r['buffer']:,}) | {r.get('overflow', 0)} | {r['forward_s']:.3f} | "
                   f"{format(r['forward+grad_s'], '.3f') if 'forward+grad_s' in r else '-'} | {rcomp} | "
                   f"{dense} | {r['load_before']:.0f}-{r['load_after']:.0f} |")
    ba = ROOT / "benchmarks" / "results" / "splat_before_after.json"
    if ba.exists():
        e = json.loads(ba.read_text())
        out += ["", f"Before / after in one process (`python benchmarks/bench_splat.py --before {e['rev']} --counts "
                "10000,50000`): render + gradient with respect to the means, 128 x 128, the fixed-capacity",
                f"renderer loaded from git revision {e['rev']} beside the current one, interleaved repeats:", "",
                "| splats | pairs | max per tile | renderer | time (s) | overflow | max colour diff vs new | "
                "new is faster by |", "|---|---|---|---|---|---|---|---|"]
        for r in e["rows"]:
            out.append(f"| {r['splats']:,} | {r['pairs']:,} | {r['max_tile_count']:,} | sort-based (new) | "
                       f"{r['new_s']:.3f} | 0 | - | - |")
            for k in r:
                if k.startswith("before cap ") and k.endswith("_s") and "compile" not in k:
                    c = k[len("before cap "):-2]
                    out.append(f"| | | | fixed capacity {c} | {r[k]:.3f} | {r[f'before cap {c} overflow']:,} | "
                               f"{r[f'before cap {c} maxdiff']:.1e} | {r[k] / r['new_s']:.1f}x |")
        out += ["", "At 50,000 splats the old renderer would need capacity 5,933 per tile to be exact (not run: its",
                "cost grows with tiles x capacity x 256 pixels, ~12x the capacity-512 time)."]
    tl = ROOT / "benchmarks" / "results" / "splat_tiles.json"
    if tl.exists():
        e = json.loads(tl.read_text())
        out += ["", "Tile size, in one process (`python benchmarks/bench_splat.py --tiles 16,8 --counts 10000,50000 "
                "--steps 10`; load average", f"{e['load_before'][0]:.1f} before, {e['load_after'][0]:.1f} after): "
                "`train_splats(tile_size=T)` run twice per tile size, alternating (both step medians",
                "given), and render + gradient of all parameters (`distortion=False`) in interleaved repeats. "
                "Tiling is exact: the", "gradients differ by rounding only (relative max |diff| column) and the "
                "final training loss is the same. `train_splats` now defaults to 8 px tiles.", "",
                "| splats | tile px | pairs | step (s), two runs | step CPU (s) | step compile CPU (s) | "
                "render + grad (s) | grad rel. diff vs 16 px | overflow | final loss |",
                "|---|---|---|---|---|---|---|---|---|---|"]
        for r in e["rows"]:
            for t in r["tiles"]:
                k = f"tile {t}"
                out.append(f"| {r['splats']:,} | {t} | {r[k + ' pairs']:,} | "
                           + ", ".join(f"{x:.3f}" for x in r[k + " step_s"]) + " | "
                           + ", ".join(f"{x:.3f}" for x in r[k + " step_cpu_s"]) + " | "
                           + ", ".join(f"{x:.1f}" for x in r[k + " compile_cpu_s"]) + " | "
                           f"{r[k + ' render+grad_s']:.3f} | "
                           f"{format(r[k + ' grad rel maxdiff'], '.0e') if k + ' grad rel maxdiff' in r else '-'} | "
                           f"{r[k + ' overflow']} | {r[k + ' final_loss']:.6f} |")
    out += ["", "Before (the fixed-capacity renderer, same script shape, measured under load 8-13 with",
            "`train_splats(capacity=...)`): 10,000 splats at capacity 512: step 2.26 s, compile 31.9 s, 7,877 pairs",
            "dropped; render 0.38 s, render + grad 2.38 s; at capacity 2,048: step 10.2 s, compile 70.3 s, render",
            "1.88 s, render + grad 5.25 s. Idle-machine figures of that renderer are in the capacity tables below",
            "(0.45 s at capacity 512 with overflow, 1.71 s at 2,048, 10.2 s at 8,192 for 50k without overflow).",
            ""]
    prof = ROOT / "benchmarks" / "results" / "render_profile.md"  # written by hand from benchmarks/profile_render.py
    if prof.exists():
        out += [prof.read_text().rstrip(), ""]
    return out


    return out


def write_docs():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    d = _load()
    figs = ROOT / "docs" / "figures"
    lines = ["# Gaussian splatting in plain JAX/XLA", "",
             "Generated by `python tools/splat_experiments.py --write-docs` from",
             "`docs/figures/splatting_results.json` (written by the experiment stages of the same script).",
             "Machine: the project's 2-core CPU. The step-time tables, the 128 px training run and the",
             "capacity-4,096 budget sweep were measured with no other work on the machine (load average",
             "given); the capacity-512 budget sweep and the depth-distortion runs were measured earlier",
             "while the machine was **shared** (load average 15-20 from other sessions), so their times are",
             "upper bounds, several times the idle figure.",
             "", "## What is here", "",
             "* `fsjax.render.render_splats`: EWA projection with a stated 0.3 px^2 dilation, near-plane culling",
             "  by the splat's 3-sigma depth extent, exact-support tiles binned by one global sort of (tile,",
             "  depth) pairs into a buffer sized from the measured demand (overflow counted when a jitted",
             "  caller fixes it too small), front-to-back compositing of each tile's range in chunks with early",
             "  termination (T < 1e-4) that skips the remaining chunks, colour, alpha, expected and median depth,",
             "  2DGS depth distortion (prefix sums; `distortion=False` skips them when no loss uses the term).",
             "  `render_splats_dense` is the every-splat-on-every-pixel reference: images and gradients agree",
             "  to ~1e-13 in float64 when no tile overflows (tests/render/test_splat.py).",
             "* `fsjax.fit.train_splats`: L1 + 0.2 (1 - SSIM), `optimistix.OptaxMinimiser` (Adam per parameter",
             "  group) stepped through optimistix's `init`/`step`, split/clone by screen-space gradient and",
             "  opacity pruning under a fixed maximum count, tqdm bar, deterministic under a key.",
             "* On real photographs: `fsjax splat SFM_DIR` (`fsjax.sfm.splat`) trains `train_splats(init=...)` from the",
             "  coloured sparse points and cameras of an `fsjax sfm` result; held-out figures on fountain-P11 in",
             "  [sfm.md](sfm.md#splats-on-the-photographs-fsjax-splat).",
             "* `fsjax.fit.select_frames_by_rotation`, `fsjax.io` (3DGS PLY and 32-byte `.splat`: `write_ply_gaussians`, `write_splat`).",
             "", "Data: Spot (Crane et al.) rendered by fsjax's own mesh rasteriser with vertex colours from the",
             "normals times a band pattern, cameras on a spiral, every 6th view held out. Initialisation:",
             "surface samples of the mesh with noise (standing in for an SfM cloud).", ""]
    lines += _bench_section()

    def _cap(key):
        parts = key.split("_")
        if len(parts) > 2 and parts[2] == "grown":
            return (parts[1], 10**9)
        return (parts[1], int(parts[2][3:]) if len(parts) > 2 else 512)

    def _capname(parts):
        if len(parts) > 2 and parts[2] == "grown":
            return "sort-based binning, pair buffer grown to the demand"
        return f"tile capacity {parts[2][3:] if len(parts) > 2 else '512'}"

    for k in sorted((k for k in d if k.startswith("timing_")), key=_cap):
        if isinstance(d[k], dict):
            parts = k.split("_")
            lines += [f"## Step time ({parts[1]} px, {_capname(parts)}, one view per step, forward + backward "
                      "+ Adam)", "",
                      "| splats | step (s) | compile (s) | max tile overflow | pairs (buffer) | load average (1 min) |",
                      "|---|---|---|---|---|---|"]
            for n, v in sorted(d[k].items(), key=lambda kv: int(kv[0])):
                load = f"{v['load']:.1f}" if "load" in v else "15-20 (shared machine)"
                pb = f"{v['pairs']:,} ({v['buffer']:,})" if "pairs" in v else "-"
                lines.append(f"| {int(n):,} | {v['step_s']:.2f} | {v['compile_s']:.1f} | {v['overflow']} | {pb} "
                             f"| {load} |")
            lines.append("")
            if d.get("timing_note") and len(parts) == 2:
                lines += [d["timing_note"], ""]
    for k in sorted(d):
        if k.startswith("main_"):
            m = d[k]
            h = m["heldout"]
            lines += [f"## Training run ({k.split('_')[1]} px)", "",
                      f"{m['iterations']} steps, budget {m['budget']:,} (final {m['final_splats']:,} splats), "
                      f"median step {m['step_s']:.2f} s, wall {m['wall_s'] / 60:.1f} min"
                      + (f", tile capacity {m['capacity']}" if "capacity" in m else "")
                      + (f", max training overflow {m['train_overflow_max']} splat-tile pairs"
                         if "train_overflow_max" in m else "")
                      + (f", load average {m['load']:.1f}" if "load" in m else "") + "."
                      + (f" {m['note']}" if "note" in m else "")
                      + (f" Command: `{m['command']}`." if "command" in m else ""), "",
                      "| metric | held-out | train views |", "|---|---|---|",
                      f"| PSNR (dB) | {h['psnr']:.2f} | {m['train_psnr']:.2f} |",
                      f"| SSIM | {h['ssim']:.3f} | |",
                      f"| coverage holes (object pixels with alpha < 0.5): all / top / middle / bottom | "
                      f"{h['holes']['all']:.3f} / {h['holes']['top']:.3f} / {h['holes']['middle']:.3f} / "
                      f"{h['holes']['bottom']:.3f} | |",
                      f"| tile overflow (eval, capacity 1024) | {h['overflow']} | |", ""]
            goal = "reached" if h["psnr"] >= 30 else "**not reached**"
            lines += [f"The issue's goal of >= 30 dB held-out PSNR at 128x128 is {goal} in this run "
                      f"({h['psnr']:.2f} dB); see the limits section.", ""]
            if (figs / f"splatting_heldout_{k.split('_')[1]}.png").exists():
                lines += [f"![held-out view](figures/splatting_heldout_{k.split('_')[1]}.png)", ""]
    for k in sorted(d):
        if k.startswith("sweep_"):
            rows = d[k]
            parts = k.split("_")
            px = parts[1]
            cap = parts[2][3:] if len(parts) > 2 and parts[2] != "grown" else ("grown" if len(parts) > 2 else "512")
            capname = _capname(parts)
            b = [r["budget"] for r in rows]
            p = [r["heldout"]["psnr"] for r in rows]
            s = [r["heldout"]["ssim"] for r in rows]
            clean = [(bb, pp) for bb, pp, r in zip(b, p, rows) if r["heldout"]["overflow"] == 0]
            fig, ax = plt.subplots(figsize=(5.5, 3.4))
            ax.semilogx(b, p, "o-", label="held-out PSNR (dB)")
            bad = [(bb, pp) for bb, pp, r in zip(b, p, rows) if r["heldout"]["overflow"] > 0]
            if bad:
                ax.semilogx([x for x, _ in bad], [y for _, y in bad], "rx", ms=10, label="tile overflow at eval")
            if clean:
                ax.axhline(max(pp for _, pp in clean) - 0.5, color="gray", ls=":", label="best - 0.5 dB")
            ax.set_xlabel("splat budget (max count)")
            ax.set_ylabel("PSNR (dB)")
            ax2 = ax.twinx()
            ax2.semilogx(b, s, "s--", color="C1", label="SSIM")
            ax2.set_ylabel("SSIM")
            ax.legend(loc="lower right", fontsize=8)
            ax.set_title(f"Spot {px} px, {'grown buffer' if cap == 'grown' else 'capacity ' + cap}, "
                         f"{rows[0]['iterations']} steps per budget", fontsize=9)
            fig.tight_layout()
            fname = f"splatting_budget_{px}_{'grown' if cap == 'grown' else 'cap' + cap}.png"
            fig.savefig(figs / fname, dpi=90)
            plt.close(fig)
            loads = [r["load"] for r in rows if "load" in r]
            lines += [f"## Budget sweep ({px} px, {capname}, {rows[0]['iterations']} steps each)", "",
                      ("Measured with no other work on the machine (load average "
                       f"{min(loads):.1f}-{max(loads):.1f})." if loads and max(loads) < 4 else
                       "Measured while the machine was shared (load average "
                       + (f"{min(loads):.0f}-{max(loads):.0f}" if loads else "15-20")
                       + "): step times follow the load."),
                      "",
                      "| budget | final splats | held-out PSNR | SSIM | holes (all) | max overflow, training | "
                      "overflow, evaluation | step (s) |",
                      "|---|---|---|---|---|---|---|---|"]
            for r in rows:
                lines.append(f"| {r['budget']:,} | {r['final_splats']:,} | {r['heldout']['psnr']:.2f} | "
                             f"{r['heldout']['ssim']:.3f} | {r['heldout']['holes']['all']:.3f} | "
                             f"{r['train_overflow_max']} | {r['heldout']['overflow']} | {r['step_s']:.2f} |")
            lines += ["", "Overflow = splat-tile pairs dropped because a tile's capacity (or, sort-based, the pair "
                      "buffer) was full: a row with "
                      "overflow at evaluation was scored on an incomplete render and is **not a valid measurement** "
                      "of its budget; overflow during training means some steps saw incomplete renders. With a "
                      "fixed step count, larger budgets are also less trained per splat."]
            if len(clean) >= 3:
                best = max(pp for _, pp in clean)
                need = min(bb for bb, pp in clean if pp >= best - 0.5)
                if need == max(bb for bb, _ in clean):
                    lines += ["", f"Scene's need: **at least {need:,} splats**, not bounded by this sweep — PSNR "
                              f"is within 0.5 dB of its best only at the largest budget that was swept and "
                              f"rendered without overflow ({need:,}); the curve has not flattened, so larger "
                              "budgets (with a larger tile capacity) must be swept to bound it.", ""]
                else:
                    fin = {r["budget"]: r["final_splats"] for r in rows}
                    lines += ["", f"Scene's measured need: **{need:,} splats** (smallest budget within 0.5 dB of "
                              f"the best valid row, {best:.2f} dB; {fin[need]:,} splats after pruning), at this "
                              "resolution and step count. Above it the curve is flat within 0.25 dB although "
                              "densification in 250 steps does not fill the larger budgets (final counts column).",
                              ""]
            else:
                lines += ["", f"Scene's need: **not determined** (only {len(clean)} row(s) without overflow).", ""]
            lines += ["", f"![budget sweep](figures/{fname})", ""]
    for k in sorted(d):
        if k.startswith("distortion_"):
            rows = d[k]
            lines += [f"## Depth-distortion loss ({k.split('_')[1]} px)", "",
                      "2DGS term `sum_ij w_i w_j |z_i - z_j|` per ray (one pass, prefix sums; gradient FD-checked in",
                      "tests/render/test_splat.py). Thickness = mean over object pixels of distortion / A^2 (the",
                      "weight-normalised mean pairwise depth separation); median-depth error vs the mesh depth.", "",
                      "| loss | held-out PSNR | SSIM | thickness | median-depth error | holes | max overflow, training "
                      "| overflow, evaluation |", "|---|---|---|---|---|---|---|---|"]
            for r in rows:
                name = "none" if r["dist_weight"] == 0 else (f"{r['dist_weight']} x raw" if not r["dist_norm"]
                                                             else f"{r['dist_weight']} x per-ray normalised")
                h = r["heldout"]
                lines.append(f"| {name} | {h['psnr']:.2f} | {h['ssim']:.3f} | {h['thickness']:.4f} | "
                             f"{h['median_depth_error']:.4f} | {h['holes']['all']:.3f} | {r['train_overflow_max']} | "
                             f"{h['overflow']} |")
            lines += ["", "Reported as measured, whichever way it goes.", ""]
    lines += ["## Limits", "",
              "* The sections with a fixed tile capacity were measured with the renderer before sort-based",
              "  binning (every tile evaluated `capacity` splats per pixel, cost set by the capacity); the",
              "  sections marked 'sort-based binning' with the current one (cost follows the pairs, early",
              "  termination skips chunks). Each table says which.",
              "* Runs are short (hundreds to 1,500 steps, not the 30k of 3DGS) on a 2-core CPU; PSNR",
              "  figures are therefore below what the method reaches with full schedules.",
              "* Splatting ignores lens distortion (refused eagerly); colours here are degree-0 SH.", ""]
    (ROOT / "docs" / "splatting.md").write_text("\n".join(lines))
    print("wrote docs/splatting.md")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--stages", default="")
    ap.add_argument("--write-docs", action="store_true")
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--sweep-size", type=int, default=64)
    ap.add_argument("--views", type=int, default=48)
    ap.add_argument("--capacity", type=int, default=0,
                    help="legacy fixed per-tile capacity; 0 (default): pair buffer grown to the demand")
    ap.add_argument("--timing-sizes", default="1000,10000,50000")
    ap.add_argument("--main-budget", type=int, default=8000)
    ap.add_argument("--main-iters", type=int, default=800)
    ap.add_argument("--budgets", default="500,1000,2000,4000,8000")
    ap.add_argument("--sweep-iters", type=int, default=400)
    ap.add_argument("--dist-budget", type=int, default=2000)
    ap.add_argument("--dist-weight", type=float, default=0.1)
    a = ap.parse_args()
    import jax

    jax.config.update("jax_enable_x64", False)
    for s in [x for x in a.stages.split(",") if x]:
        {"timing": stage_timing, "main": stage_main, "sweep": stage_sweep, "distortion": stage_distortion}[s](a)
    if a.write_docs:
        write_docs()


if __name__ == "__main__":
    main()
