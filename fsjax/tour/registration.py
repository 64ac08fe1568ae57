"""Tour sections for 3-D registration (issue 4: bunny self-registration, basin of convergence, global registration).

Each scene has a pure ``measure_*`` function returning a dict of numbers (asserted by
``tests/tour/test_tour_registration.py`` and ``tests/fit/``); the section functions wrap them into
:class:`fsjax.tour.Section` with a figure.

Scenes (all on area-weighted samples of the bundled Stanford Bunny, metres):

* self-registration: the cloud rotated by 30 deg about a fixed oblique axis, translated by
  (20, -10, 15) mm and perturbed by Gaussian noise (0.1 mm per axis, 0.07 % of the bunny's size);
  null: no ICP (the rotation error of the identity, 30 deg).
* basin: the same cloud rotated about its centroid by 0..180 deg about random axes; ICP from the
  identity; success = rotation error below 1 deg. Multi-start = point-to-plane from the 24
  rotations of the cube group. ``hidden`` counts failures that reported ``converged=True``.
* global: two crops of independent samples (each keeps 76.9 % of the bunny along its x extent,
  so the shared part is 70 % of each cloud), 60 deg apart plus a translation; FPFH + RANSAC with
  no initial guess, then trimmed point-to-plane ICP.
"""

from __future__ import annotations

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from fsjax._linalg import FAST_COMPILE
from fsjax.data import surface_points
from fsjax.fit import icp, icp_multistart, rotation_error_deg, rotation_from_axis_angle

from ._core import Section

__all__ = ["measure_self_registration", "measure_basin", "measure_global", "SECTIONS"]

_AXIS = np.array([0.3, 1.0, -0.4])
_SHIFT = np.array([0.02, -0.01, 0.015])


def measure_self_registration(n_points: int = 1000, noise: float = 1e-4, angle_deg: float = 30.0,
                              seed: int = 0) -> dict:
    """Unknown rotation + translation + noise; ICP p2p / p2plane / GICP from the identity."""
    x = surface_points("bunny", n_points, seed)
    rng = np.random.default_rng(seed + 100)
    r = np.asarray(rotation_from_axis_angle(jnp.asarray(_AXIS), angle_deg))
    src = (x - _SHIFT) @ r + noise * rng.normal(size=x.shape)  # target = R src + t
    out = {"n_points": n_points, "noise": noise, "angle_deg": angle_deg,
           "null_error_deg": float(rotation_error_deg(jnp.eye(3), jnp.asarray(r)))}
    for m in ("point_to_point", "point_to_plane", "gicp"):
        res = icp(jnp.asarray(src), jnp.asarray(x), method=m, max_iterations=100)
        out[m] = {"error_deg": float(rotation_error_deg(res.R, jnp.asarray(r))),
                  "t_error": float(np.linalg.norm(np.asarray(res.t) - _SHIFT)),
                  "iterations": int(res.iterations), "converged": bool(res.converged), "rmse": float(res.rms_len),
                  "reason": int(res.reason)}
    return out


def measure_basin(method: str, angles_deg=(0, 30, 60, 90, 120, 150, 180), n_axes: int = 6, n_points: int = 600,
                  noise: float = 2e-4, success_deg: float = 1.0, seed: int = 0, max_iterations: int = 60) -> dict:
    """Success rate of ICP from the identity against the initial rotation angle (one ``vmap`` per method).

    ``method`` is an :func:`fsjax.fit.icp` method or ``"multistart"`` (point-to-plane, 24 cube-group starts).
    """
    from scipy.spatial.transform import Rotation

    x = surface_points("bunny", n_points, seed)
    c = x.mean(0)
    axes = Rotation.random(n_axes, random_state=seed + 2).apply([1.0, 0.0, 0.0])
    angles = np.asarray(angles_deg, float)
    rots = np.stack([Rotation.from_rotvec(a * np.radians(g)).as_matrix() for g in angles for a in axes])
    rng = np.random.default_rng(seed + 1)
    srcs = np.einsum("bji,nj->bni", rots, x - c) + c + noise * rng.normal(size=(len(rots), n_points, 3))
    tgt = jnp.asarray(x)
    if method == "multistart":
        def run(s):
            return icp_multistart(s, tgt, method="point_to_plane", max_iterations=max_iterations).best
    else:
        def run(s):
            return icp(s, tgt, method=method, max_iterations=max_iterations)
    # one program over all starts: at top level, XLA:CPU's older emitters at level 2 (fsjax._linalg.FAST_COMPILE;
    # safe at that level, faster to compile; pinned so a process-wide level 0 does not slow the run)
    res = jax.jit(jax.vmap(run), compiler_options=FAST_COMPILE)(jnp.asarray(srcs))
    err = np.asarray(rotation_error_deg(res.R, jnp.asarray(rots))).reshape(len(angles), n_axes)
    conv = np.asarray(res.converged).reshape(len(angles), n_axes)
    ok = err < success_deg
    return {"method": method, "angles_deg": angles, "error_deg": err, "converged": conv,
            "success_rate": ok.mean(1), "reported_rate": conv.mean(1),
            "hidden": int(np.sum(~ok & conv)), "false_alarm": int(np.sum(ok & ~conv)),
            "iterations": np.asarray(res.iterations).reshape(len(angles), n_axes),
            "inlier_fraction": np.asarray(res.inlier_fraction).reshape(len(angles), n_axes)}


def measure_global(*args, **kwargs) -> dict:
    """Issue 4 item 2: 60 deg, 70 % overlap; FPFH + RANSAC, then trimmed ICP (see ``fit.global_reg``)."""
    from fsjax.fit.global_reg import _measure_global

    return _measure_global(*args, **kwargs)


def _scatter(path: Path, clouds: list[tuple[np.ndarray, str]], title: str) -> str:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(4.2, 4.0), dpi=90)
    for pts, col in clouds:
        ax.scatter(pts[:, 0], pts[:, 1], s=1, c=col)
    ax.set_aspect("equal")
    ax.set_title(title, fontsize=8)
    ax.set_xticks([])
    ax.set_yticks([])
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path.name


def self_registration(out: Path, quick: bool) -> Section:
    n = 1000
    r = measure_self_registration(n, 1e-4)
    x = surface_points("bunny", n, 0)
    rot = np.asarray(rotation_from_axis_angle(jnp.asarray(_AXIS), 30.0))
    fig = _scatter(out / "registration_self.png", [(x, "0.6"), ((x - _SHIFT) @ rot, "k")],
                   "bunny (grey) and the moved copy (black), x-y")
    rows = [(m, f"{r[m]['error_deg']:.4f} deg, {r[m]['iterations']} iterations")
            for m in ("point_to_point", "point_to_plane", "gicp")]
    rows.append(("null: no ICP", f"{r['null_error_deg']:.1f} deg"))
    worst = max(r[m]["error_deg"] for m in ("point_to_point", "point_to_plane", "gicp"))
    return Section(
        title="Bunny self-registration (ICP)",
        truth=f"{n} bunny points rotated 30 deg, moved (20, -10, 15) mm, noise 0.1 mm",
        rows=rows, fsjax_figure=f"worst ICP rotation error {worst:.4f} deg",
        null_figure=f"{r['null_error_deg']:.1f} deg", beats_null=worst <= 0.03, figure=fig)


def basin(out: Path, quick: bool) -> Section:
    # sized for a tour: the full form was 7 angles x 6 axes x 600 points (237 s of CPU, most of
    # the tour's time); the exhaustive sweep is benchmarks/bench_icp.py's basin chart
    angles = (30, 90, 150) if quick else (0, 60, 120, 180)
    res = {m: measure_basin(m, angles_deg=angles, n_axes=2 if quick else 3, n_points=300 if quick else 400)
           for m in ("point_to_point", "point_to_plane", "gicp", "multistart")}
    rows = [(m, ", ".join(f"{a:g}: {s:.2f}" for a, s in zip(angles, b["success_rate"], strict=True))
             + f"; hidden failures {b['hidden']}") for m, b in res.items()]
    ms = res["multistart"]["success_rate"].min()
    single = max(res[m]["success_rate"][-1] for m in ("point_to_point", "point_to_plane", "gicp"))
    return Section(
        title="ICP basin of convergence (success rate vs initial rotation)",
        truth="bunny rotated about its centroid by the given angle about random axes; success = error < 1 deg",
        rows=rows, fsjax_figure=f"multi-start success at every angle >= {ms:.2f}",
        null_figure=f"single-start success at {angles[-1]} deg: {single:.2f}",
        beats_null=bool(ms == 1.0 and single < 1.0
                        and all(b["hidden"] == 0 for b in res.values())))


def global_registration(out: Path, quick: bool) -> Section:
    r = measure_global(n_points=1800, refine_points=4000, n_hypotheses=8192) if quick else measure_global()
    rot, t = r["R"], r["t"]
    fig = _scatter(out / "registration_global.png",
                   [(r["tgt"], "0.6"), (np.asarray(r["src"]) @ rot.T + t, "k")],
                   "target crop (grey), source crop at the true pose (black)")
    return Section(
        title="Global registration: FPFH + RANSAC, then ICP (no initial guess)",
        truth=f"two bunny crops sharing 70 % of each, 60 deg apart plus a translation ({r['n_source']} points)",
        rows=[("FPFH + RANSAC (matches only)", f"{r['matches_only_error_deg']:.3f} deg"),
              ("+ point-pair refit", f"{r['coarse_error_deg']:.3f} deg"),
              (f"+ trimmed point-to-plane ICP ({r['n_refine']} points)", f"{r['refined_error_deg']:.4f} deg"),
              ("null: identity", f"{r['null_error_deg']:.0f} deg")],
        fsjax_figure=f"{r['refined_error_deg']:.4f} deg after ICP", null_figure=f"{r['null_error_deg']:.0f} deg",
        beats_null=r["refined_error_deg"] < 1.0, figure=fig)


SECTIONS = [self_registration, basin, global_registration]
