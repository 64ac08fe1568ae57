"""Scaling of the 3-D point workloads with the cloud size (issue 12): fsjax against cKDTree and Open3D.

For each size N (points sampled area-weighted on the Stanford Bunny, ``fsjax.data.surface_points``),
in one process, round robin, medians of ``--repeats`` timed calls after one warm-up, compile apart:

* ``knn``: every point's k = 16 nearest points of the same cloud (float64). fsjax ``ops.knn`` (grid
  build inside the call); ``cKDTree`` build + ``query`` with one thread and with ``workers=-1``;
  Open3D's tensor ``core.nns.NearestNeighborSearch`` (build + ``knn_search``).
* ``normals``: PCA normals from the k = 30 nearest points (float64). fsjax ``ops.estimate_normals``;
  Open3D ``PointCloud.estimate_normals(KDTreeSearchParamKNN(30))`` (KD-tree build inside).
  Agreement: the median and 1st percentile of ``|n_fsjax . n_open3d|`` (normals' signs differ).
* ``icp``: point-to-plane ICP between two independent samples (seeds 0 and 1), the source moved by
  10 deg and ~6 mm (as ``benchmarks/bench_icp.py``), float32 for fsjax (JAX's default) with target
  normals estimated inside the call (k = 10); Open3D ``registration_icp`` point-to-plane with
  ``estimate_normals(KDTreeSearchParamKNN(10))`` inside the timed call, 50 iterations at most.
  Rotation error in degrees against the true rotation.

fsjax compile: process CPU seconds around ``jax.jit(f).trace(...).lower().compile()`` (the
machine is shared: CPU seconds are steadier than wall), and the wall time, one program per size.

``--mem N`` (default 200000): peak memory at N, one fresh subprocess per (workload, method):
the peak resident set ``VmHWM`` of ``/proc/self/status`` (the whole process: interpreter, libraries,
inputs, compilation; not ``ru_maxrss``, which a child inherits from its parent) after the imports and
after making the inputs and compiling; then, after a warm-up call, the high-water mark is reset
(``/proc/self/clear_refs``) and one call made: ``VmHWM`` after it (resident set plus that call's peak) and its growth
(``_harness.rss_peak_bytes``: a lower bound where an allocator reuses memory it holds), plus the
XLA buffers of the compiled fsjax program (temporaries + outputs).

    python benchmarks/bench_points_scaling.py [--sizes 1000,2000,...] [--repeats 3] [--mem 200000]
        [--write-docs]

Writes ``benchmarks/results/points_scaling.json``, ``docs/figures/benchmarks_points_scaling.png``
and (``--write-docs``) the scaling section of ``docs/benchmarks_points.md``.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from scipy.spatial import cKDTree  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _harness import _status_kb, json_subprocess, rss_peak_bytes, time_round_robin, xla_memory_bytes  # noqa: E402

from fsjax import Points  # noqa: E402
from fsjax.data import surface_points  # noqa: E402
from fsjax.fit import icp, rotation_error_deg, rotation_from_axis_angle  # noqa: E402
from fsjax.ops import estimate_normals, knn  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results" / "points_scaling.json"
FIGURE = ROOT / "docs" / "figures" / "benchmarks_points_scaling.png"
SIZES = (1000, 2000, 5000, 10000, 20000, 50000, 100000, 200000)
K_KNN, K_NORMALS, K_ICP_NORMALS = 16, 30, 10
WORKLOADS = ("knn", "normals", "icp")
METHODS = {"knn": ("fsjax", "cKDTree", "cKDTree-mt", "Open3D"), "normals": ("fsjax", "Open3D"),
           "icp": ("fsjax", "Open3D")}


def icp_inputs(n: int):
    x = surface_points("bunny", n, 0)
    y = surface_points("bunny", n, 1)
    r = np.asarray(rotation_from_axis_angle(jnp.array([0.3, 1.0, -0.4]), 10.0))
    t = np.array([0.005, -0.003, 0.002])
    return (y - t) @ r, x, r  # target = R source + t


def compile_cpu(f, *args):
    """(CPU seconds, wall seconds, compiled) of ``jax.jit(f)`` for ``args``."""
    c0, w0 = time.process_time(), time.perf_counter()
    comp = jax.jit(f).trace(*args).lower().compile()
    return time.process_time() - c0, time.perf_counter() - w0, comp


def make(workload: str, method: str, n: int):
    """(zero-argument callable running one call, compile record or None, checker(out) -> dict)."""
    import open3d as o3d

    if workload in ("knn", "normals"):
        p = surface_points("bunny", n, 0).astype(np.float64)
        pj = jnp.asarray(p)
        if workload == "knn":
            if method == "fsjax":
                cpu, wall, comp = compile_cpu(lambda a: knn(a, a, K_KNN), pj)
                return (lambda: jax.block_until_ready(comp(pj))), (cpu, wall, comp), None
            if method.startswith("cKDTree"):
                w = 1 if method == "cKDTree" else -1
                return (lambda: cKDTree(p).query(p, K_KNN, workers=w)), None, None
            t = o3d.core.Tensor(p)

            def run():
                nns = o3d.core.nns.NearestNeighborSearch(t)
                nns.knn_index()
                return nns.knn_search(t, K_KNN)

            return run, None, None
        if method == "fsjax":
            cpu, wall, comp = compile_cpu(lambda a: estimate_normals(Points(a), k=K_NORMALS).normals, pj)
            return (lambda: jax.block_until_ready(comp(pj))), (cpu, wall, comp), None

        def run():
            pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p))
            pc.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(K_NORMALS))
            return np.asarray(pc.normals)

        return run, None, None
    src, tgt, r = icp_inputs(n)
    if method == "fsjax":
        sj, tj = jnp.asarray(src, jnp.float32), jnp.asarray(tgt, jnp.float32)
        cpu, wall, comp = compile_cpu(lambda s, t: icp(s, t, method="point_to_plane", max_iterations=50,
                                                       normal_k=K_ICP_NORMALS), sj, tj)

        def check(res):
            return {"error_deg": float(rotation_error_deg(res.R, jnp.asarray(r, jnp.float32))),
                    "iterations": int(res.iterations), "converged": bool(res.converged)}

        return (lambda: jax.block_until_ready(comp(sj, tj))), (cpu, wall, comp), check
    reg = o3d.pipelines.registration
    crit = reg.ICPConvergenceCriteria(max_iteration=50)
    ps = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(src))

    def run():
        q = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(tgt))
        q.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(K_ICP_NORMALS))
        return reg.registration_icp(ps, q, 1.0, np.eye(4), reg.TransformationEstimationPointToPlane(), crit)

    def check(out):
        return {"error_deg": float(rotation_error_deg(jnp.asarray(out.transformation[:3, :3]), jnp.asarray(r)))}

    return run, None, check


def normals_agreement(a, b) -> dict:
    d = np.abs(np.sum(np.asarray(a) * np.asarray(b), -1))
    d = d[np.isfinite(d)]
    return {"dot_median": float(np.median(d)), "dot_p01": float(np.percentile(d, 1))}


def run_size(n: int, repeats: int, log) -> list[dict]:
    rows = []
    for wl in WORKLOADS:
        calls, recs, checks = {}, {}, {}
        for m in METHODS[wl]:
            fn, rec, chk = make(wl, m, n)
            calls[m], recs[m], checks[m] = fn, rec, chk
        l0 = os.getloadavg()[0]
        tim = time_round_robin(calls, repeats=repeats, warmup=1)
        l1 = os.getloadavg()[0]
        outs = {m: calls[m]() for m in calls}
        for m in calls:
            row = {"workload": wl, "method": m, "n": n, "median_s": tim[m].median, "q1_s": tim[m].q1,
                   "q3_s": tim[m].q3, "load": [l0, l1]}
            if recs[m] is not None:
                row["compile_cpu_s"], row["compile_wall_s"] = recs[m][0], recs[m][1]
            if checks[m] is not None:
                row.update(checks[m](outs[m]))
            rows.append(row)
        if wl == "normals":
            agree = normals_agreement(outs["fsjax"], outs["Open3D"])
            for row in rows[-2:]:
                row.update(agree)
        for row in rows[-len(calls):]:
            log(row)
    return rows


# ---------------------------------------------------------------------------
# peak memory (one subprocess per workload and method)
# ---------------------------------------------------------------------------


def _maxrss_bytes() -> int:
    """High-water mark of this process's resident set: ``VmHWM`` of ``/proc/self/status``, which is
    new at ``exec`` and reset by ``clear_refs``; ``ru_maxrss`` where there is no ``/proc``. (``ru_maxrss``
    survives fork + exec and ``clear_refs``: the subprocesses of a full run all reported their parent's
    peak, 1,625 MiB at 200,000 points, whatever they used.)"""
    try:
        return _status_kb("VmHWM") * 1024
    except (OSError, KeyError):
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def mem_case(wl: str, m: str, n: int) -> dict:
    # reset the high-water mark first (it then restarts from the resident set after the imports)
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
    except OSError:
        pass
    out = {"workload": wl, "method": m, "n": n, "maxrss_start": _maxrss_bytes()}
    fn, rec, _ = make(wl, m, n)
    out["maxrss_after_inputs_and_compile"] = _maxrss_bytes()
    if rec is not None:
        mem = xla_memory_bytes(rec[2])
        if mem:
            out["xla_bytes"] = mem["temp"] + mem["output"]
    fn()  # warm-up: first-call allocations
    out["rss_growth_one_call"] = rss_peak_bytes(fn)
    out["maxrss_end"] = _maxrss_bytes()
    return out


def mem_subprocess(wl: str, m: str, n: int) -> dict:
    return json_subprocess(__file__, ["--mem-case", f"{wl},{m},{n}"], 3600, {"workload": wl, "method": m, "n": n})


# ---------------------------------------------------------------------------
# report
# ---------------------------------------------------------------------------


def slopes(rows) -> dict:
    """Least-squares slope of log(time) against log(N), sizes >= 10,000 (the small sizes are overhead)."""
    out = {}
    for wl in WORKLOADS:
        for m in METHODS[wl]:
            pts = [(r["n"], r["median_s"]) for r in rows if r["workload"] == wl and r["method"] == m
                   and r["n"] >= 10000]
            if len(pts) >= 2:
                x, y = np.log([p[0] for p in pts]), np.log([p[1] for p in pts])
                out[f"{wl}/{m}"] = float(np.polyfit(x, y, 1)[0])
    return out


def chart(rows, sl) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    titles = {"knn": f"kNN, k = {K_KNN} (float64)", "normals": f"normals, k = {K_NORMALS} (float64)",
              "icp": "ICP point-to-plane (fsjax float32)"}
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.6))
    for ax, wl in zip(axes, WORKLOADS, strict=True):
        for m in METHODS[wl]:
            rr = sorted((r for r in rows if r["workload"] == wl and r["method"] == m), key=lambda r: r["n"])
            if not rr:
                continue
            lab = f"{m} (slope {sl[f'{wl}/{m}']:.2f})" if f"{wl}/{m}" in sl else m
            ax.loglog([r["n"] for r in rr], [r["median_s"] for r in rr], "o-", label=lab)
            if m == "fsjax" and "compile_cpu_s" in rr[0]:
                ax.loglog([r["n"] for r in rr], [r["compile_cpu_s"] for r in rr], "x--", color="gray",
                          label="fsjax compile (CPU s, once per size)")
        ax.set_title(titles[wl])
        ax.set_xlabel("points N")
        ax.set_ylabel("seconds per call (median)")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    FIGURE.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(FIGURE, dpi=90)


def fmt_t(s):
    return "-" if s is None else (f"{s * 1e3:.1f} ms" if s < 1 else f"{s:.2f} s")


def fmt_b(b):
    return "-" if b is None else f"{b / 2**20:.0f} MiB"


def markdown(res) -> str:
    rows, sl, mem, info = res["rows"], res["slopes"], res.get("mem", []), res["info"]
    lines = ["<!-- BEGIN scaling (benchmarks/bench_points_scaling.py --write-docs) -->", "",
             "## Scaling with the cloud size, and peak memory (issue 12)", "",
             f"Produced by `python benchmarks/bench_points_scaling.py {info['args']} --write-docs` "
             f"(one process for fsjax and its peers, round robin, medians of {info['repeats']} after a "
             f"warm-up; fsjax compile apart, in process CPU seconds). {info['machine']}; load average "
             f"{info['load'][0]:.1f} at start, {info['load'][1]:.1f} at end (shared machine: the ratios "
             "measured in one process are the figures). Workloads and peers: see the script's docstring "
             "(kNN k = 16 and normals k = 30 in float64, each cloud against itself; ICP point-to-plane "
             "in float32, 10 deg, normals k = 10 estimated inside the call by both).", "",
             "![scaling](figures/benchmarks_points_scaling.png)", "",
             "| workload | N | fsjax | fsjax compile (CPU) | cKDTree | cKDTree `workers=-1` | Open3D | "
             "fsjax / best peer | notes |",
             "|---|---|---|---|---|---|---|---|---|"]
    by = {(r["workload"], r["method"], r["n"]): r for r in rows}
    for wl in WORKLOADS:
        for n in sorted({r["n"] for r in rows}):
            f = by.get((wl, "fsjax", n))
            if f is None:
                continue
            peers = {m: by.get((wl, m, n)) for m in METHODS[wl] if m != "fsjax"}
            best = min(p["median_s"] for p in peers.values() if p)
            note = ""
            if wl == "normals":
                note = f"\\|n . n_o3d\\| median {f['dot_median']:.6f}, 1st pct {f['dot_p01']:.4f}"
            if wl == "icp":
                o = peers["Open3D"]
                note = (f"error {f['error_deg']:.4f} deg ({f['iterations']} it, converged {f['converged']}) "
                        f"vs Open3D {o['error_deg']:.4f} deg")
            cell = {m: (fmt_t(peers[m]["median_s"]) if peers.get(m) else "") for m in
                    ("cKDTree", "cKDTree-mt", "Open3D")}
            lines.append(f"| {wl} | {n:,} | {fmt_t(f['median_s'])} | {f.get('compile_cpu_s', 0):.1f} s | "
                         f"{cell['cKDTree']} | {cell['cKDTree-mt']} | {cell['Open3D']} | "
                         f"{f['median_s'] / best:.2f} | {note} |")
    lines += ["", "Fitted slopes of log(time) against log(N) over N >= 10,000 (1 = linear): " +
              ", ".join(f"{k} {v:.2f}" for k, v in sl.items()) + "."]
    if mem:
        n_mem = mem[0]["n"]
        lines += ["", f"Peak memory at {n_mem:,} points, one fresh subprocess per row "
                  "(peak resident set `VmHWM`, the whole process -- interpreter, JAX/Open3D/SciPy/fsjax imports, inputs, "
                  "compilation and calls: after the imports, and after making the inputs and compiling; then "
                  "one warm-up call; then the high-water mark is reset (`/proc/self/clear_refs`) "
                  "and one more call made: *peak of one call* = `VmHWM` after it "
                  "(what is resident plus that call's peak), *growth* = its growth over the resident set "
                  "before it (a lower bound where an allocator reuses memory it holds); *XLA buffers* = "
                  "temporaries + outputs of the compiled fsjax program):", "",
                  "| workload | method | peak RSS after imports | after inputs + compile | peak of one call | "
                  "growth of one call | XLA buffers |", "|---|---|---|---|---|---|---|"]
        for m in mem:
            if "error" in m:
                lines.append(f"| {m['workload']} | {m['method']} | failed: {m['error'][:80]} | | | | |")
                continue
            lines.append(f"| {m['workload']} | {m['method']} | {fmt_b(m['maxrss_start'])} | "
                         f"{fmt_b(m['maxrss_after_inputs_and_compile'])} | "
                         f"{fmt_b(m['maxrss_end'])} | {fmt_b(m['rss_growth_one_call'])} | "
                         f"{fmt_b(m.get('xla_bytes'))} |")
    lines += ["", "<!-- END scaling -->"]
    return "\n".join(lines) + "\n"


def write_docs(section: str) -> None:
    page = ROOT / "docs" / "benchmarks_points.md"
    txt = page.read_text()
    b, e = "<!-- BEGIN scaling", "<!-- END scaling -->"
    if b in txt:
        i, j = txt.index(b), txt.index(e) + len(e)
        txt = txt[:i] + section.rstrip("\n") + txt[j:]
    else:
        txt = txt.rstrip("\n") + "\n\n" + section
    page.write_text(txt)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--sizes", default=",".join(map(str, SIZES)))
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--mem", type=int, default=200000, help="size of the memory subprocesses (0: none)")
    ap.add_argument("--write-docs", action="store_true")
    ap.add_argument("--from-json", action="store_true", help="redo the chart and docs from the saved results")
    ap.add_argument("--mem-lines", default=None, help="with --from-json: a file of --mem-case output lines")
    ap.add_argument("--mem-case", default=None, help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.mem_case:
        wl, m, n = a.mem_case.split(",")
        print(json.dumps(mem_case(wl, m, int(n))))
        return
    if a.from_json:  # also a partial run (the rows are saved after every size)
        res = json.loads(RESULTS.read_text())
        if a.mem_lines:  # memory rows measured apart (``--mem-case`` runs, one JSON line each)
            res["mem"] = [json.loads(x) for x in Path(a.mem_lines).read_text().splitlines() if x.startswith("{")]
        res.setdefault("slopes", slopes(res["rows"]))
        loads = [x for r in res["rows"] for x in r["load"]]
        res.setdefault("info", {"args": "(partial run) " + " ".join(sys.argv[1:]), "repeats": a.repeats,
                                "load": [loads[0], loads[-1]], "machine": "see the rows"})
    else:
        import platform

        args = " ".join(x for x in sys.argv[1:] if x != "--write-docs")
        load0 = os.getloadavg()[0]
        rows = []
        for n in [int(s) for s in a.sizes.split(",")]:
            rows += run_size(n, a.repeats if n <= 100000 else max(1, a.repeats - 1),
                             lambda r: print(json.dumps(r), flush=True))
            RESULTS.write_text(json.dumps({"rows": rows}, indent=1))
        mem = []
        if a.mem:
            for wl in WORKLOADS:
                for m in METHODS[wl]:
                    mem.append(mem_subprocess(wl, m, a.mem))
                    print(json.dumps(mem[-1]), flush=True)
        ncpu = os.cpu_count()
        res = {"rows": rows, "mem": mem, "slopes": slopes(rows),
               "info": {"args": args, "repeats": a.repeats, "load": [load0, os.getloadavg()[0]],
                        "machine": f"{platform.processor() or platform.machine()}, {ncpu} cores, "
                                   f"jax {jax.__version__}"}}
        RESULTS.write_text(json.dumps(res, indent=1))
    chart(res["rows"], res["slopes"])
    sec = markdown(res)
    print(sec)
    if a.write_docs:
        write_docs(sec)


if __name__ == "__main__":
    main()
