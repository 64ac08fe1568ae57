"""Tour sections for 2-D inspection metrology and alignment (issue 3, scenes 2, 3 and 5).

Each scene has a pure ``measure_*`` function that builds the exact scene
(``fsjax.synth``: ``shaft``, ``edge_sweep``, ``bar_code``, ``alignment_scene``), measures it with
fsjax and with the null on the same data, and returns a dict of numbers; the
section functions wrap those dicts into :class:`fsjax.tour.Section` with a PNG.
``tests/tour/test_tour_metrology.py`` asserts the numbers of the ``measure_*``
functions directly.

Nulls:

* metrology (shaft, edge sweep, bars): the *pixel of maximum gradient* --
  an edge at the integer sample where ``|central difference|`` of the same
  averaged profile is a local maximum (no sub-pixel interpolation);
* alignment: ``ncc_locate`` with the unrotated template (no rotation search).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from scipy import ndimage as ndi

import fsjax
from fsjax.synth import (
    alignment_scene,
    bar_code,
    edge_sweep,
    render_part,
    shaft,
    workpiece_template,
)

from ._core import Section, _panel

__all__ = ["measure_shaft", "measure_edge_sweep", "measure_alignment", "measure_bars", "SECTIONS"]


def _img(x) -> fsjax.Image:
    return fsjax.Image(jnp.asarray(x))


def _max_grad_pixels(profile: np.ndarray, min_slope: float) -> np.ndarray:
    """Null edge detector: integer positions of local maxima of ``|central difference|``."""
    g = np.abs(np.gradient(np.asarray(profile, dtype=float)))
    k = np.arange(1, g.size - 1)
    peak = (g[k] >= g[k - 1]) & (g[k] > g[k + 1]) & (g[k] >= min_slope)
    return k[peak].astype(float)


# ---------------------------------------------------------------------------
# scene 2: sub-pixel metrology
# ---------------------------------------------------------------------------


def measure_shaft() -> dict:
    """Diameters of the 3-step shaft by vertical ``measure_pairs`` calipers; null: max-gradient pixels."""
    x, t = shaft()
    f = jax.jit(jax.vmap(lambda c: fsjax.ops.measure_pairs(_img(x), row=t["axis_row"], col=c, angle_deg=-90.0,
                                                          length=50, width=5, sigma=2.5, transition="negative")))
    e = f(jnp.asarray(t["centre_cols"]))
    n_edges = np.asarray(e.valid.sum(axis=1))
    w = np.asarray(e.width[:, 0])
    err = w - t["diameters"]
    # null on the same data: the column profile (5-column mean) at each caliper, edges at the two strongest
    # max-gradient pixels; diameter = their distance
    null_w = []
    for c in t["centre_cols"]:
        c0 = int(round(c))
        prof = x[:, c0 - 2:c0 + 3].mean(axis=1)
        g = np.abs(np.gradient(prof))
        pk = _max_grad_pixels(prof, 0.0)
        top2 = np.sort(pk[np.argsort(g[pk.astype(int)])[-2:]])
        null_w.append(top2[1] - top2[0])
    null_err = np.asarray(null_w) - t["diameters"]
    return {
        "image": x, "truth": t, "edge_rows": np.asarray(e.row[:, :2]), "edge_cols": np.asarray(e.col[:, :2]),
        "edges_per_caliper": n_edges, "diameters": t["diameters"], "measured": w,
        "max_error": float(np.abs(err).max()), "null_measured": np.asarray(null_w),
        "null_max_error": float(np.abs(null_err).max()),
    }


def measure_edge_sweep(n: int = 21) -> dict:
    """An edge moved across one pixel in 0.05 px steps: ``measure_pos`` RMS vs the max-gradient pixel."""
    imgs, edges = edge_sweep(start=23.0, step=0.05, n=n, shape=(9, 48), blur=0.7)
    f = jax.jit(jax.vmap(lambda x: fsjax.ops.measure_pos(fsjax.Image(x), row=4, col=24.0, length=40, sigma=2.0)))
    e = f(jnp.asarray(imgs))
    found = np.asarray(e.col[:, 0])
    err = found - edges
    prof = imgs[:, 4, :]
    null = np.argmax(np.abs(np.gradient(prof, axis=1)), axis=1).astype(float)
    null_err = null - edges
    return {
        "images": imgs, "truth": edges, "measured": found, "null": null,
        "edges_per_image": np.asarray(e.valid.sum(axis=1)),
        "rms": float(np.sqrt(np.mean(err**2))), "max_error": float(np.abs(err).max()),
        "null_rms": float(np.sqrt(np.mean(null_err**2))), "null_max_error": float(np.abs(null_err).max()),
    }


def _mark(img: np.ndarray, r: float, c: float, val: float, arm: int = 3) -> None:
    h, w = img.shape
    ri, ci = int(round(r)), int(round(c))
    for d in range(-arm, arm + 1):
        if 0 <= ri < h and 0 <= ci + d < w:
            img[ri, ci + d] = val
        if 0 <= ri + d < h and 0 <= ci < w:
            img[ri + d, ci] = val


def metrology(out: Path, quick: bool) -> Section:
    s = measure_shaft()
    sw = measure_edge_sweep(21)  # 0.05 px steps across one full pixel (cheap: one vmapped call)
    # figure (nearest-neighbour enlarged): the shaft with the measured edge points marked, the middle image of
    # the sweep, and the sweep as a plot (grey: true edge, black: null, dark grey: fsjax,
    # drawn over the truth; x = sweep step)
    z = 3
    x = np.repeat(np.repeat(s["image"], z, axis=0), z, axis=1)
    for rr, cc in zip(s["edge_rows"].ravel(), s["edge_cols"].ravel(), strict=True):
        _mark(x, z * rr + 1, z * cc + 1, 1.0, arm=6)
    mid = np.repeat(np.repeat(sw["images"][len(sw["truth"]) // 2], 6, axis=0), 6, axis=1)
    mid = np.pad(mid, 1, constant_values=float(mid.min()))  # a dark frame: the bright side meets the white page
    h, step = 150, 8
    plot = np.ones((h, step * len(sw["truth"])))
    lo, hi = float(sw["truth"][0]) - 0.6, float(sw["truth"][-1]) + 0.6
    for i, (tv, mv, nv) in enumerate(zip(sw["truth"], sw["measured"], sw["null"], strict=True)):
        for v, g in ((tv, 0.6), (nv, 0.0), (mv, 0.3)):
            py = int(round((hi - v) / (hi - lo) * (h - 1)))
            plot[max(0, py - 1):py + 2, step * i:step * i + step - 2] = g
    fig = _panel(out / "metrology.png", [x, mid, plot],
                 ["shaft, measure_pairs edges (white)", "swept edge (middle step)",
                  "sweep: fsjax on truth, null black"])
    dia = ", ".join(f"{d:.2f}" for d in s["diameters"])
    got = ", ".join(f"{d:.4f}" for d in s["measured"])
    return Section(
        title="Sub-pixel metrology: shaft diameters and an edge swept across a pixel",
        truth=(f"back-lit 3-step shaft, diameters {dia} px (exact blur 0.6 + pixel integration); a vertical edge "
               f"moved from {sw['truth'][0]:.2f} to {sw['truth'][-1]:.2f} px in 0.05 px steps (blur 0.7)"),
        rows=[("measure_pairs diameters (sigma 2.5, width 5)", f"{got}: max |error| {s['max_error']:.4f} px"),
              ("null: distance of the two max-gradient pixels", f"max |error| {s['null_max_error']:.3f} px"),
              (f"measure_pos over {len(sw['truth'])} sweep positions (sigma 2)",
               f"RMS {sw['rms']:.4f} px, max {sw['max_error']:.4f} px"),
              ("null: pixel of maximum gradient", f"RMS {sw['null_rms']:.3f} px, max {sw['null_max_error']:.3f} px")],
        fsjax_figure=f"diameters max error {s['max_error']:.4f} px; sweep RMS {sw['rms']:.4f} px",
        null_figure=f"max-gradient pixel: diameters {s['null_max_error']:.3f} px, sweep RMS {sw['null_rms']:.3f} px",
        beats_null=(s["max_error"] < s["null_max_error"] and sw["rms"] < sw["null_rms"]),
        figure=fig,
        notes="targets: diameter error <= 0.02 px, sweep RMS <= 0.012 px (null about 0.28 px).",
    )


# ---------------------------------------------------------------------------
# scene 3: alignment
# ---------------------------------------------------------------------------


def _nearest(m, r, c):
    d = np.hypot(np.asarray(m.row) - r, np.asarray(m.col) - c)
    d = np.where(np.asarray(m.valid), d, np.inf)
    i = int(np.argmin(d))
    return i, float(d[i])


def measure_alignment() -> dict:
    """``shape_locate`` on the alignment scene vs ``ncc_locate`` without rotation search."""
    img, truth = alignment_scene()
    tpl = workpiece_template()
    m = fsjax.ops.shape_locate(_img(img), _img(tpl))
    pos_err, ang_err, found = [], [], []
    for r, c, a in truth["poses"]:
        i, d = _nearest(m, r, c)
        pos_err.append(d)
        ang_err.append(float(m.angle_deg[i]) - a if np.isfinite(d) else np.inf)
        found.append(d <= 1.0)
    decoy_dist = [_nearest(m, r, c)[1] for r, c, _, _ in truth["decoys"]]
    nm = fsjax.ops.ncc_locate(_img(img), _img(tpl), min_score=0.5, capacity=8)
    ncc_dist = [_nearest(nm, r, c)[1] for r, c, _ in truth["poses"]]
    v = np.asarray(m.valid)
    return {
        "image": img, "truth": truth,
        "found_poses": list(zip(np.asarray(m.row)[v], np.asarray(m.col)[v], np.asarray(m.angle_deg)[v],
                                np.asarray(m.score)[v], strict=True)),
        "n_valid": int(v.sum()), "truncated": bool(m.truncated),
        "n_found": int(sum(found)), "pos_errors": pos_err, "angle_errors": ang_err,
        "max_pos_error": float(max(pos_err)), "max_angle_error": float(max(abs(a) for a in ang_err)),
        "decoy_distances": decoy_dist, "decoys_matched": int(sum(d <= 20 for d in decoy_dist)),
        "null_found": int(sum(d <= 1.0 for d in ncc_dist)), "null_n_valid": int(np.asarray(nm.valid).sum()),
        "null_nearest": ncc_dist,
        "null_poses": list(zip(np.asarray(nm.row)[np.asarray(nm.valid)], np.asarray(nm.col)[np.asarray(nm.valid)], strict=True)),
    }


def _draw_pose(img: np.ndarray, r: float, c: float, a_deg: float, val: float, length: float = 22.0) -> None:
    """A cross at the found reference point and a line along the part's rotated +col axis."""
    _mark(img, r, c, val, arm=4)
    a = np.radians(a_deg)
    ur, uc = -np.sin(a), np.cos(a)  # rotated +col axis, counter-clockwise on screen
    for t in np.linspace(0, length, int(4 * length)):
        ri, ci = int(round(r + t * ur)), int(round(c + t * uc))
        if 0 <= ri < img.shape[0] and 0 <= ci < img.shape[1]:
            img[ri, ci] = val


def alignment(out: Path, quick: bool) -> Section:
    res = measure_alignment()
    img, truth = res["image"], res["truth"]
    shown = img.copy()
    for r, c, a, _ in res["found_poses"]:  # the model outline at each found pose, and its axis
        cov = render_part(img.shape, r, c, a, "workpiece", ss=4) > 0.5
        shown[cov & ~ndi.binary_erosion(cov)] = 0.0
        _draw_pose(shown, r, c, a, 0.0)
    null_img = img.copy()
    for r, c in res["null_poses"]:
        _mark(null_img, r, c, 0.0, arm=5)
    fig = _panel(out / "alignment.png", [img, shown, null_img],
                 ["scene: 3 workpieces + 2 decoys", "shape_locate: model at found poses", "null: ncc_locate (no rotation)"])
    rows = []
    for (r, c, a), d, da in zip(truth["poses"], res["pos_errors"], res["angle_errors"], strict=True):
        rows.append((f"workpiece at ({r:.2f}, {c:.2f}, {a:.1f} deg)",
                     f"position error {d:.3f} px, angle error {da:+.3f} deg"))
    for (r, c, _, kind), d in zip(truth["decoys"], res["decoy_distances"], strict=True):
        rows.append((f"decoy {kind} at ({r:.1f}, {c:.1f})", f"nearest match {d:.1f} px away"))
    rows.append(("null: ncc_locate, unrotated template, min_score 0.5",
                 f"{res['null_found']}/3 within 1 px ({res['null_n_valid']} matches in all)"))
    return Section(
        title="Alignment: rotated workpieces among decoys",
        truth=("3 workpieces at 13.7, -41.3, 97.2 deg (off the search grid) at sub-pixel positions, a rectangle and a "
               "mirrored part as decoys; textured background, illumination gradient, noise 0.01"),
        rows=rows,
        fsjax_figure=(f"shape_locate: {res['n_found']}/3 found, max position error {res['max_pos_error']:.3f} px, "
                      f"max angle error {res['max_angle_error']:.3f} deg, {res['decoys_matched']} decoys matched"),
        null_figure=f"ncc_locate without rotation: {res['null_found']}/3 found",
        beats_null=res["n_found"] > res["null_found"] and res["decoys_matched"] == 0,
        figure=fig,
        notes="targets: 3/3 found, position error <= 0.1 px, angle error <= 0.1 deg, no decoy matched.",
    )


# ---------------------------------------------------------------------------
# scene 5: bar edges
# ---------------------------------------------------------------------------


def measure_bars() -> dict:
    """45 bars read along one scan line with ``measure_pairs``; null: max-gradient pixels on the same profile."""
    x, t = bar_code(45)
    length = x.shape[1] - 1
    e = fsjax.ops.measure_pairs(_img(x), row=t["row"], length=length, width=5, sigma=0.5,
                                transition="negative", capacity=128)
    v = np.asarray(e.valid)
    pos = np.asarray(e.col)[v]
    n = pos.shape[0]
    err = np.abs(pos - t["edges"]) if n == t["edges"].size else np.full(t["edges"].size, np.inf)
    # null: the same 5-row profile, edges at the max-gradient pixels
    prof = np.asarray(fsjax.ops.measure_projection(_img(x), row=t["row"], length=length, width=5).data)
    nk = _max_grad_pixels(prof, 0.02)
    start = float(e.col[0] - e.pos[0])  # image column of profile position 0 (the caliper is horizontal)
    null_pos = start + nk
    null_err = np.abs(null_pos - t["edges"]) if null_pos.size == t["edges"].size else np.full(t["edges"].size, np.inf)
    return {
        "image": x, "truth": t, "measured": pos, "n_edges": int(n), "truncated": bool(e.truncated),
        "max_error": float(err.max()), "median_error": float(np.median(err)),
        "null_n_edges": int(null_pos.size), "null_max_error": float(null_err.max()),
        "null_median_error": float(np.median(null_err)),
    }


def bars(out: Path, quick: bool) -> Section:
    res = measure_bars()
    x, t = res["image"], res["truth"]
    big = np.repeat(x, 2, axis=0)
    marked = big.copy()
    for cpos in res["measured"]:
        marked[: big.shape[0] // 2, int(round(cpos))] = 0.5
    for cpos in t["edges"]:
        marked[big.shape[0] // 2:, int(round(cpos))] = 0.5
    fig = _panel(out / "bars.png", [big, marked], ["45 bars", "measured (top) / true (bottom) edges"])
    return Section(
        title="Bar edges along a scan line",
        truth="45 dark bars, widths and gaps uniform in 2-6 px at sub-pixel positions, blur 0.5; 90 edges",
        rows=[("measure_pairs (sigma 0.5, width 5)",
               f"{res['n_edges']} edges, max |error| {res['max_error']:.3f} px, median {res['median_error']:.3f} px"),
              ("null: max-gradient pixels of the same profile",
               f"{res['null_n_edges']} edges, max |error| {res['null_max_error']:.3f} px, "
               f"median {res['null_median_error']:.3f} px")],
        fsjax_figure=f"{res['n_edges']}/90 edges, max error {res['max_error']:.3f} px",
        null_figure=f"{res['null_n_edges']}/90 edges, max error {res['null_max_error']:.3f} px",
        beats_null=res["n_edges"] == 90 and res["max_error"] < res["null_max_error"],
        figure=fig,
        notes="target: every edge within +-0.5 px.",
    )


SECTIONS: list[Callable[[Path, bool], Section]] = [metrology, alignment, bars]
