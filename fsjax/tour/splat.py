"""Tour section for Gaussian splatting (issue 8): near-plane culling over a ground plane.

A camera flies 0.12 units above a plane of flat splats, its near plane at 0.3, deeper than
its altitude, so near-plane culling decides what the bottom of the frame shows. fsjax culls a
splat only when its whole 3-sigma depth extent is behind the near plane and draws a straddling
splat from its ridge point on the plane; the null is the common centre-only rule.
``measure_near_plane`` returns the numbers; the section wraps them.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

import fsjax
from fsjax.render import intrinsics_from_fov, look_at, render_splats, rgb_to_sh0

from ._core import Section, _panel

__all__ = ["ground_plane", "low_camera", "measure_near_plane", "SECTIONS"]


def ground_plane(spacing: float = 0.1, half: float = 1.5, far: float = 4.0) -> fsjax.Gaussians:
    """Flat checkerboard splats on the plane y = 0 (world up is -y), z from -0.5 to ``far``."""
    xs = np.arange(-half, half + 1e-9, spacing)
    zs = np.arange(-0.5, far, spacing)
    X, Z = np.meshgrid(xs, zs)
    n = X.size
    means = np.stack([X.ravel(), np.zeros(n), Z.ravel()], 1)
    chk = ((np.floor(X.ravel() / 0.3) + np.floor(Z.ravel() / 0.3)) % 2)[:, None]
    rgb = chk * np.array([[0.85, 0.7, 0.45]]) + (1 - chk) * np.array([[0.35, 0.6, 0.4]])
    return fsjax.Gaussians(means, np.log(np.tile([[spacing * 0.8, 0.004, spacing * 0.8]], (n, 1))),
                           np.tile([[1.0, 0.0, 0.0, 0.0]], (n, 1)), np.full(n, 3.0), rgb_to_sh0(rgb)[:, None, :])


def low_camera(altitude: float = 0.12, width: int = 256, height: int = 192) -> fsjax.Camera:
    R, t = look_at([0.0, -altitude, 0.0], [0.0, 0.0, 1.5], up=[0.0, -1.0, 0.0])
    return fsjax.Camera(intrinsics_from_fov(width, height, fov_x_deg=70.0), width=width, height=height, R=R, t=t)


def measure_near_plane(quick: bool = True, near: float = 0.3) -> dict:
    w, h = (128, 96) if quick else (256, 192)
    g, cam = ground_plane(), low_camera(width=w, height=h)
    ext = render_splats(g, cam, near=near, capacity=1024)
    cen = render_splats(g, cam, near=near, near_extent_sigma=0.0, capacity=1024)  # centre-only rule
    bottom = slice(2 * h // 3, h)
    return {"holes": float(np.mean(np.asarray(ext.alpha)[bottom] < 0.5)),
            "null_holes": float(np.mean(np.asarray(cen.alpha)[bottom] < 0.5)),
            "overflow": int(ext.overflow), "alpha": np.asarray(ext.alpha), "null_alpha": np.asarray(cen.alpha),
            "color": np.asarray(ext.color).mean(-1)}


def near_plane(out: Path, quick: bool) -> Section:
    r = measure_near_plane(quick)
    fig = _panel(out / "splat_near_plane.png", [r["color"], r["alpha"], r["null_alpha"]],
                 ["splats (grey)", "alpha, extent culling", "alpha, centre-only culling"])
    return Section(
        title="Splats under a low camera: near-plane culling by extent",
        truth="a continuous ground plane: no holes anywhere the ground is in view",
        rows=[("render_splats, extent culling", f"bottom-third hole fraction {r['holes']:.3f}"),
              ("null: centre-only culling", f"bottom-third hole fraction {r['null_holes']:.3f}")],
        fsjax_figure=f"holes {r['holes']:.3f}",
        null_figure=f"holes {r['null_holes']:.3f}",
        beats_null=r["holes"] < 0.05 and r["holes"] < r["null_holes"],
        figure=fig,
        notes="the drone pipeline's viewer shipped the centre-only rule; the browser test checks the WebGL viewer.",
    )


SECTIONS: list[Callable[[Path, bool], Section]] = [near_plane]
