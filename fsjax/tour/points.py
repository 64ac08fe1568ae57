"""Tour sections for 3-D points (issue 4: LiDAR clustering, curvature, RANSAC breakdown, model selection).

Each scene has a pure ``measure_*`` function returning a dict of numbers
(asserted by ``tests/tour/test_tour_points.py``; ``tools/points_figures.py`` charts
them for ``docs/points.md``); the section functions wrap them into
:class:`fsjax.tour.Section` with a figure.

Scenes and nulls:

* LiDAR clustering: :func:`fsjax.synth.lidar_scene` (sphere, box, cylinder,
  cone on ground sloped 5 deg); ``remove_ground`` then ``euclidean_cluster``
  (radius 0.3); null: clustering without ground removal (the ground links
  everything into one cluster).
* Curvature: Fibonacci sphere of radius 0.5 (curvedness 1/R = 2), a cylinder
  (shape index 0.5) and a saddle (0); null: the PCA "surface variation"
  ``l0 / (l0 + l1 + l2)``, which has no absolute scale.
* RANSAC breakdown: a plane plus uniform outliers in ``[-1, 1]^3``, 0-90 %
  outliers, 64 hypotheses; success = normal error <= 1 deg; null: total least
  squares on all points.
* Model selection: noisy plane / sphere-cap / half-cylinder patches; BIC vs
  AIC (AIC is the null that over-fits nested models).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import fsjax
from fsjax._linalg import FAST_COMPILE
from fsjax.fit import ransac, select_model
from fsjax.ops import cluster_centroids
from fsjax.synth import lidar_scene

from ._core import Section

__all__ = ["measure_lidar", "measure_curvature", "measure_breakdown", "measure_model_selection",
           "plane_scene", "surface_patch", "SECTIONS"]


# ---------------------------------------------------------------------------
# LiDAR clustering
# ---------------------------------------------------------------------------


@jax.jit
def _lidar_pipeline(pts):
    ng = fsjax.ops.remove_ground(pts, threshold=0.1, max_slope_deg=15.0)
    lab = fsjax.ops.euclidean_cluster(ng, radius=0.3, min_size=20, max_neighbors=128, capacity=16)
    null = fsjax.ops.euclidean_cluster(pts, radius=0.3, min_size=20, max_neighbors=128, capacity=16)
    return ng, lab, cluster_centroids(ng, lab, 16), null


def measure_lidar(seed: int = 0) -> dict:
    """Ground removal + Euclidean clustering on the LiDAR scene; null: clustering without ground removal."""
    pts, info = lidar_scene(seed)
    ng, lab, (cen, _, ok), null = _lidar_pipeline(pts)
    truth = info["labels"]
    v = np.asarray(ng.valid)
    cen = np.asarray(cen)[np.asarray(ok)]
    err = (np.array([np.min(np.linalg.norm(cen - c, axis=1)) for c in info["centroids"]])
           if len(cen) else np.full(4, np.inf))
    return {"xyz": np.asarray(pts.xyz), "labels": np.asarray(lab.labels), "truth": truth,
            "count": int(lab.count), "truncated": bool(lab.truncated), "null_count": int(null.count),
            "ground_left": int(np.sum(v[truth == 0])), "objects_removed": int(np.sum(~v[truth > 0])),
            "n_objects": int(np.sum(truth > 0)), "centroid_errors": err}


# ---------------------------------------------------------------------------
# curvature
# ---------------------------------------------------------------------------


def _fib(n, r):
    i = np.arange(n) + 0.5
    phi, th = np.arccos(1 - 2 * i / n), np.pi * (1 + 5 ** 0.5) * i
    return r * np.c_[np.cos(th) * np.sin(phi), np.sin(th) * np.sin(phi), np.cos(phi)]


def measure_curvature(n: int = 1500, radius: float = 0.5, k: int = 16) -> dict:
    """Curvedness and shape index on a sphere, a cylinder and a saddle; null: PCA surface variation."""
    rng = np.random.default_rng(0)
    sph = _fib(n, radius)
    th, z = rng.uniform(0, 2 * np.pi, n), rng.uniform(-1, 1, n)
    cyl = np.c_[radius * np.cos(th), radius * np.sin(th), z]
    cyl_n = np.c_[np.cos(th), np.sin(th), 0 * z]
    g = rng.uniform(-1, 1, (n, 2))
    sad = np.c_[g, 0.5 * (g[:, 0] ** 2 - g[:, 1] ** 2)]
    up = np.tile([0.0, 0.0, 1.0], (n, 1))
    f = jax.jit(lambda p: fsjax.ops.curvature(p, k=k))
    cs = f(fsjax.Points(jnp.asarray(sph)))
    cc = f(fsjax.Points(jnp.asarray(cyl), normals=jnp.asarray(cyl_n)))
    cd = f(fsjax.Points(jnp.asarray(sad), normals=jnp.asarray(up)))
    mid = np.abs(z) < 0.7
    centre = np.sum(g ** 2, 1) < 0.05
    curv = np.asarray(cs["curvedness"])
    # null: PCA surface variation l0 / sum(l) of the same neighbourhoods, scaled on the sphere
    from fsjax.ops import knn
    from fsjax.ops.points._cloud import pca_frames

    def variation(xyz):
        x = jnp.asarray(xyz)
        idx, _ = knn(x, x, k)
        ev, _, _, _ = pca_frames(x, jnp.ones(len(xyz), bool), idx)
        return np.asarray(ev[:, 0] / jnp.sum(ev, axis=1))

    sv_small, sv_big = np.median(variation(sph)), np.median(variation(_fib(n, 4 * radius)))
    return {"radius": radius, "sphere_curvedness": float(np.median(curv)),
            "sphere_curvedness_max_rel_err": float(np.max(np.abs(curv * radius - 1))),
            "sphere_shape_index": float(np.median(np.asarray(cs["shape_index"]))),
            "cylinder_shape_index": float(np.median(np.asarray(cc["shape_index"])[mid])),
            "saddle_shape_index": float(np.median(np.asarray(cd["shape_index"])[centre])),
            "null_variation_R": float(sv_small), "null_variation_4R": float(sv_big),
            "sphere_xyz": sph, "sphere_si": np.asarray(cs["shape_index"]),
            "cyl_xyz": cyl, "cyl_si": np.asarray(cc["shape_index"]),
            "saddle_xyz": sad, "saddle_si": np.asarray(cd["shape_index"])}


# ---------------------------------------------------------------------------
# RANSAC breakdown
# ---------------------------------------------------------------------------


def plane_scene(seed: int, ratio: float, n: int = 500, noise: float = 0.002):
    """A plane through ``0.1 n`` (inliers on a 2 x 2 square) plus uniform outliers in ``[-1, 1]^3``."""
    rng = np.random.default_rng(seed)
    n_out = int(round(ratio * n))
    nrm = rng.normal(size=3)
    nrm /= np.linalg.norm(nrm)
    e1 = np.cross(nrm, [1.0, 0, 0]) if abs(nrm[0]) < 0.9 else np.cross(nrm, [0, 1.0, 0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(nrm, e1)
    g = rng.uniform(-1, 1, (n - n_out, 2))
    p = g[:, :1] * e1 + g[:, 1:] * e2 + (0.1 + noise * rng.normal(size=(n - n_out, 1))) * nrm
    return np.r_[p, rng.uniform(-1, 1, (n_out, 3))], nrm


def _angle(a, b):
    return np.degrees(np.arccos(np.clip(np.abs(np.sum(a * b, -1)), 0, 1)))


def measure_breakdown(ratios=(0.0, 0.3, 0.5, 0.6, 0.7, 0.8, 0.9), trials: int = 20, n_hypotheses: int = 64,
                      n: int = 500) -> dict:
    """Plane RANSAC over outlier ratios: success rate, acceptance rate, wrongly accepted fits, null error."""
    f = jax.jit(jax.vmap(lambda key, x: ransac(key, x, "plane", threshold=0.01, n_hypotheses=n_hypotheses)),
                compiler_options=FAST_COMPILE)
    key = jax.random.PRNGKey(0)
    rows = []
    for r in ratios:
        xs, ns = zip(*[plane_scene(100 * int(round(r * 10)) + i, r, n=n) for i in range(trials)])
        xs, ns = np.stack(xs), np.stack(ns)
        res = f(jax.random.split(key, trials), jnp.asarray(xs))
        err = _angle(np.asarray(res.raw_params[:, :3]), ns)
        conv = np.asarray(res.converged)
        c = xs - xs.mean(1, keepdims=True)
        null_n = np.linalg.eigh(np.einsum("tni,tnj->tij", c, c))[1][:, :, 0]
        rows.append({"ratio": float(r), "success": float(np.mean(err <= 1.0)), "accepted": float(np.mean(conv)),
                     "wrong_accepted": int(np.sum(conv & (err > 1.0))), "median_error": float(np.median(err)),
                     "null_median_error": float(np.median(_angle(null_n, ns))),
                     "predicted": float(1 - (1 - (1 - r) ** 3) ** n_hypotheses)})
    return {"rows": rows, "n_hypotheses": n_hypotheses, "trials": trials, "n": n}


# ---------------------------------------------------------------------------
# model selection
# ---------------------------------------------------------------------------

MODEL_KINDS = ("plane", "sphere", "cylinder")


def surface_patch(kind: str, seed: int, n: int = 150, noise: float = 0.01):
    """Noisy patch of a plane square / sphere cap (60 deg) / half cylinder (unit size), random pose."""
    rng = np.random.default_rng(seed)
    if kind == "plane":
        g = rng.uniform(-1, 1, (n, 2))
        p, nr = np.c_[g, np.zeros(n)], np.tile([0.0, 0.0, 1.0], (n, 1))
    elif kind == "sphere":
        u = rng.normal(size=(12 * n, 3))
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        p = nr = u[u[:, 2] > 0.5][:n]
    else:
        th, z = rng.uniform(-np.pi / 2, np.pi / 2, n), rng.uniform(-1, 1, n)
        p, nr = np.c_[np.cos(th), np.sin(th), z], np.c_[np.cos(th), np.sin(th), 0 * z]
    p = p + noise * rng.normal(size=(n, 1)) * nr
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    return p @ (q * np.sign(np.diag(r))).T + rng.uniform(-2, 2, 3)


def measure_model_selection(trials: int = 67, n: int = 150, noise: float = 0.01) -> dict:
    """BIC and AIC accuracy per true model, median RMS of every candidate, median criterion values."""
    # at top level: XLA:CPU's older emitters at level 2 (FAST_COMPILE), whatever the process-wide level
    f = jax.jit(jax.vmap(lambda x: select_model(x)), compiler_options=FAST_COMPILE)
    out = {}
    for i, kind in enumerate(MODEL_KINDS):
        x = jnp.asarray(np.stack([surface_patch(kind, 1000 * i + t, n, noise) for t in range(trials)]))
        r = f(x)
        rms, bic, aic = np.asarray(r.rms_len), np.asarray(r.bic), np.asarray(r.aic)

        def med(a):
            return [float(np.median(c[np.isfinite(c)])) if np.isfinite(c).any() else float("nan") for c in a.T]

        out[kind] = {"bic_correct": float(np.mean(np.asarray(r.choice) == i)),
                     "aic_correct": float(np.mean(np.argmin(aic, axis=1) == i)),
                     "rms": med(rms), "bic": med(bic), "aic": med(aic),
                     "picked": np.bincount(np.asarray(r.choice), minlength=4).tolist()}
    return {"by_kind": out, "names": ("plane", "sphere", "cylinder", "quadric"), "k": (3, 4, 5, 6),
            "trials": trials, "n": n, "noise": noise}


# ---------------------------------------------------------------------------
# sections
# ---------------------------------------------------------------------------


def _fig(path: Path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def lidar(out: Path, quick: bool) -> Section:
    res = measure_lidar(0)
    plt = _fig(out)
    fig, ax = plt.subplots(1, 2, figsize=(9, 4))
    x, lab = res["xyz"], res["labels"]
    ax[0].scatter(x[:, 0], x[:, 1], c=x[:, 2], s=1)
    ax[0].set_title("scene (colour = height)")
    ax[1].scatter(x[lab == 0, 0], x[lab == 0, 1], c="0.85", s=1)
    ax[1].scatter(x[lab > 0, 0], x[lab > 0, 1], c=lab[lab > 0], s=1, cmap="tab10")
    ax[1].set_title(f"{res['count']} clusters after ground removal")
    for a in ax:
        a.set_aspect("equal")
    fig.tight_layout()
    fig.savefig(out / "points_lidar.png", dpi=80)
    plt.close(fig)
    e = res["centroid_errors"]
    return Section(
        title="LiDAR scene: ground removal + Euclidean clustering",
        truth="sphere, box, cylinder, cone on ground sloped 5 deg; 4 objects",
        rows=[("remove_ground + euclidean_cluster (r 0.3)",
               f"{res['count']} clusters, centroid error max {e.max():.3f}, ground left {res['ground_left']}"),
              ("null: euclidean_cluster without ground removal", f"{res['null_count']} cluster(s) (fused)")],
        fsjax_figure=f"{res['count']} clusters, centroid error <= {e.max():.3f}",
        null_figure=f"{res['null_count']} cluster",
        beats_null=res["count"] == 4 and bool(np.all(e <= 0.13)) and res["null_count"] == 1,
        figure="points_lidar.png", notes="target: exactly 4 clusters, centroids within 0.13.")


def curvature(out: Path, quick: bool) -> Section:
    res = measure_curvature(n=1500)
    plt = _fig(out)
    fig, ax = plt.subplots(1, 3, figsize=(10, 3.4))
    for a, key, title in zip(ax, ("sphere", "cyl", "saddle"), ("sphere", "cylinder", "saddle")):
        xyz, si = res[f"{key}_xyz"], res[f"{key}_si"]
        sc = a.scatter(xyz[:, 0], xyz[:, 1] if key != "cyl" else xyz[:, 2], c=si, s=2, vmin=-1, vmax=1,
                       cmap="coolwarm")
        a.set_title(f"{title}: shape index {np.median(si):.3f}")
        a.set_aspect("equal")
    fig.colorbar(sc, ax=ax, shrink=0.8)
    fig.savefig(out / "points_curvature.png", dpi=80)
    plt.close(fig)
    r = res["radius"]
    return Section(
        title="Curvature from local quadric fits",
        truth=f"sphere R={r}: curvedness {1 / r:g}, shape index 1; cylinder 0.5; saddle 0",
        rows=[("curvature (quadric, k=16)",
               f"curvedness {res['sphere_curvedness']:.4f} (max rel. error "
               f"{res['sphere_curvedness_max_rel_err']:.3%}); SI sphere {res['sphere_shape_index']:.3f}, "
               f"cylinder {res['cylinder_shape_index']:.3f}, saddle {res['saddle_shape_index']:.3f}"),
              ("null: PCA surface variation", f"{res['null_variation_R']:.4f} at R, {res['null_variation_4R']:.4f} "
               "at 4R with the same sampling: no absolute scale")],
        fsjax_figure=f"curvedness {res['sphere_curvedness']:.4f} vs {1 / r:g}",
        null_figure="surface variation: scale-free",
        beats_null=res["sphere_curvedness_max_rel_err"] < 0.02 and abs(res["cylinder_shape_index"] - 0.5) < 0.02,
        figure="points_curvature.png", notes="target: curvedness within 2 % of 1/R.")


def breakdown_chart(res: dict, path: Path) -> None:
    plt = _fig(path)
    rows = res["rows"]
    r = [x["ratio"] * 100 for x in rows]
    fig, ax = plt.subplots(1, 2, figsize=(9, 3.6))
    ax[0].plot(r, [x["success"] for x in rows], "o-", label="success (error <= 1 deg)")
    ax[0].plot(r, [x["accepted"] for x in rows], "s--", label="reported converged")
    ax[0].plot(r, [x["predicted"] for x in rows], ":", label="1 - (1 - w^3)^H")
    ax[0].set_xlabel("outliers (%)")
    ax[0].set_ylabel("rate")
    ax[0].legend(fontsize=8)
    ax[1].semilogy(r, [max(x["median_error"], 1e-3) for x in rows], "o-", label="RANSAC (median)")
    ax[1].semilogy(r, [max(x["null_median_error"], 1e-3) for x in rows], "x-", label="null: TLS on all points")
    ax[1].set_xlabel("outliers (%)")
    ax[1].set_ylabel("normal error (deg)")
    ax[1].legend(fontsize=8)
    fig.suptitle(f"plane RANSAC, {res['n_hypotheses']} hypotheses, {res['trials']} trials per ratio")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def breakdown(out: Path, quick: bool) -> Section:
    res = measure_breakdown(trials=10 if quick else 20)
    breakdown_chart(res, out / "points_ransac_breakdown.png")
    by = {x["ratio"]: x for x in res["rows"]}
    return Section(
        title="RANSAC breakdown: plane normal vs outlier ratio",
        truth="plane + uniform outliers, 0-90 %; 64 hypotheses",
        rows=[(f"{x['ratio']:.0%} outliers", f"success {x['success']:.2f}, converged {x['accepted']:.2f}, "
               f"wrong accepted {x['wrong_accepted']}, median error {x['median_error']:.2f} deg "
               f"(null {x['null_median_error']:.1f})") for x in res["rows"]],
        fsjax_figure=f"success {by[0.6]['success']:.2f} at 60 %, {by[0.9]['success']:.2f} at 90 %",
        null_figure=f"TLS median error {by[0.3]['null_median_error']:.1f} deg at 30 %",
        beats_null=by[0.6]["success"] == 1.0 and all(x["wrong_accepted"] == 0 for x in res["rows"]),
        figure="points_ransac_breakdown.png",
        notes="fails past ~70 % outliers with 64 hypotheses, and says so (converged=False).")


def selection_chart(res: dict, path: Path) -> None:
    plt = _fig(path)
    names, k = res["names"], res["k"]
    fig, ax = plt.subplots(1, 2, figsize=(9, 3.6))
    for kind, mark in zip(MODEL_KINDS, "os^"):
        d = res["by_kind"][kind]
        ax[0].semilogy(k, d["rms"], mark + "-", label=f"{kind} data")
        b = np.asarray(d["bic"], float)
        ax[1].plot(k, b - np.nanmin(b), mark + "-", label=f"{kind} data")
    for a in ax:
        a.set_xticks(k)
        a.set_xticklabels([f"{m}\n(k={kk})" for m, kk in zip(names, k)], fontsize=8)
        a.legend(fontsize=8)
    ax[0].axhline(res["noise"], color="0.5", ls=":", lw=1)
    ax[0].set_ylabel("median residual RMS")
    ax[1].set_ylabel("median BIC - best")
    fig.suptitle(f"model selection, {res['trials']} trials x {res['n']} points, noise {res['noise']}")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def model_selection(out: Path, quick: bool) -> Section:
    res = measure_model_selection(trials=20 if quick else 67)
    selection_chart(res, out / "points_model_selection.png")
    b = res["by_kind"]
    return Section(
        title="Model selection among plane, sphere, cylinder, quadric",
        truth="noisy plane / sphere-cap / half-cylinder patches (150 points, noise 0.01)",
        rows=[(f"{kind} data", f"BIC correct {b[kind]['bic_correct']:.3f}, AIC {b[kind]['aic_correct']:.3f}")
              for kind in MODEL_KINDS],
        fsjax_figure=f"BIC correct >= {min(b[k]['bic_correct'] for k in MODEL_KINDS):.3f}",
        null_figure=f"AIC on planes {b['plane']['aic_correct']:.3f}",
        beats_null=all(b[k]["bic_correct"] >= 0.95 for k in MODEL_KINDS),
        figure="points_model_selection.png", notes="target: >= 95 % correct; a model is never more complex "
        "than the data supports.")


SECTIONS: list[Callable[[Path, bool], Section]] = [lidar, curvature, breakdown, model_selection]
