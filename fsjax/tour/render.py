"""Tour sections for measurement by rendering (issue 5, results 1 and 6).

* ``channels``: the rasteriser's depth of the Stanford Bunny, and fsjax's own Sobel
  magnitude (:func:`fsjax.ops.sobel_amp`) of it: the silhouette must be >= 20x stronger
  than the inside of the object (medians over a silhouette band and the 2-px-eroded interior).
  Null: the same ratio on the shaded image, where the inside has texture and shading edges.
* ``bunny``: the Stanford Bunny on a ground plane, Hapke photometry, ray-cast shadows from a
  sun of 0.53 deg angular diameter, zero ambient light. Its depth/normal channels are
  checked against the mesh: every back-projected depth lies on the plane of the triangle
  the rasteriser says it hit (to rounding), and the normal channel equals the mesh's face
  normal. Null: the distance to the nearest mesh *vertex* (a point-sampled surface).

Pure ``measure_*`` functions return dicts of numbers; ``tests/tour/test_tour_render.py``
asserts them; the section functions wrap them into :class:`fsjax.tour.Section`.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from pathlib import Path

import jax.numpy as jnp
import numpy as np

import fsjax
from fsjax.render import backproject, look_at, pixel_grid_uv, rasterize, sun_visibility
from fsjax.render.shading import hapke

from ._core import Section, _panel

__all__ = ["bunny_scene", "measure_bunny", "measure_channels", "SECTIONS"]

SUN = np.asarray([0.55, 0.75, -0.35])  # direction towards the sun (world, y up)
HAPKE = dict(w=0.6, b0=1.0, h=0.06, xi=-0.2, theta_bar_deg=20.0)  # illustrative regolith-like values


def bunny_scene(size: int, ground: bool = True):
    """The bunny (metres, y up), optionally on a 0.4 m ground square, and a camera looking at it."""
    b = fsjax.data.bunny()
    V = np.asarray(b.vertices, dtype=np.float64)
    F = np.asarray(b.faces)
    lo, hi = V.min(0), V.max(0)
    centre = 0.5 * (lo + hi)
    if ground:
        y = lo[1]
        s = 0.2
        G = np.asarray([[centre[0] - s, y, centre[2] - s], [centre[0] + s, y, centre[2] - s],
                        [centre[0] + s, y, centre[2] + s], [centre[0] - s, y, centre[2] + s]])
        n0 = V.shape[0]
        F = np.concatenate([F, n0 + np.asarray([[0, 2, 1], [0, 3, 2]])])  # normal +y (winding seen from above)
        V = np.concatenate([V, G])
    mesh = fsjax.Mesh(jnp.asarray(V), jnp.asarray(F, dtype=jnp.int32))
    K = fsjax.render.intrinsics_from_fov(size, size, fov_x_deg=40.0)
    R, t = look_at(jnp.asarray(centre + np.asarray([0.12, 0.09, 0.28])), jnp.asarray(centre),
                   up=jnp.asarray([0.0, 1.0, 0.0]))
    cam = fsjax.Camera(K, width=size, height=size, R=R, t=t)
    return mesh, cam, int(b.faces.shape[0])


def _raster(mesh, cam):
    return rasterize(mesh, cam, tile=8, capacity=768, cull_backfaces=True)


@functools.lru_cache(maxsize=4)
def measure_bunny(size: int = 128, samples: int = 16) -> dict:
    """Render the bunny scene; check depth/normal channels against the mesh; shade with Hapke and sun shadows."""
    mesh, cam, nb = bunny_scene(size, ground=True)
    r = _raster(mesh, cam)
    cov = np.asarray(r.alpha > 0)
    # depth channel: back-project and measure the distance to the hit triangle's plane
    X = backproject(cam, pixel_grid_uv(cam), r.depth)
    T = mesh.vertices[mesh.faces[jnp.maximum(r.face_id, 0)]]
    n = jnp.cross(T[..., 1, :] - T[..., 0, :], T[..., 2, :] - T[..., 0, :])
    nu = n / jnp.linalg.norm(n, axis=-1, keepdims=True)
    dist = np.abs(np.asarray(jnp.sum((X - T[..., 0, :]) * nu, -1)))[cov]
    # and inside the triangle: barycentrics of the back-projected point (in the face plane)
    e1, e2 = T[..., 1, :] - T[..., 0, :], T[..., 2, :] - T[..., 0, :]
    q = X - T[..., 0, :]
    d11, d12, d22 = jnp.sum(e1 * e1, -1), jnp.sum(e1 * e2, -1), jnp.sum(e2 * e2, -1)
    q1, q2 = jnp.sum(q * e1, -1), jnp.sum(q * e2, -1)
    den = d11 * d22 - d12 * d12
    bu = (d22 * q1 - d12 * q2) / den
    bv = (d11 * q2 - d12 * q1) / den
    bmin = np.asarray(jnp.minimum(jnp.minimum(bu, bv), 1 - bu - bv))[cov]
    rel_b = float(-min(bmin.min(), 0.0))
    # normal channel vs the mesh's face normal (sign: the side facing the camera)
    ang = np.degrees(np.arctan2(np.asarray(jnp.linalg.norm(jnp.cross(r.face_normal, nu), axis=-1)),
                                np.asarray(jnp.sum(r.face_normal * nu, -1))))[cov]
    # null: a point-sampled surface (nearest mesh vertex)
    from scipy.spatial import cKDTree

    Xc = np.asarray(X)[cov]
    dv, _ = cKDTree(np.asarray(mesh.vertices)).query(Xc)
    # shading: Hapke, sun of 0.53 deg, zero ambient
    L = jnp.asarray(SUN / np.linalg.norm(SUN))
    view = fsjax.render.camera_center(cam) - X
    nrm = jnp.where(r.front[..., None], r.normal, -r.normal)
    rad = hapke(jnp.where(jnp.asarray(cov)[..., None], nrm, L), L, jnp.where(jnp.asarray(cov)[..., None], view, L),
                **HAPKE)
    pts = X.reshape(-1, 3)
    vis, inc, ovf = sun_visibility(mesh, pts, L, angular_diameter_deg=0.53, samples=samples,
                                   ignore_face=r.face_id.reshape(-1), grid=256, capacity=256)
    vis = np.asarray(vis).reshape(size, size)
    vis = np.where(cov, vis, 0.0)
    img = np.where(cov, np.asarray(rad) * vis, 0.0)
    facing = cov & (np.asarray(jnp.sum(nrm * L, -1)) > 0)
    shadowed = facing & (vis == 0.0)
    penumbra = facing & (vis > 0) & (vis < 1)
    unshadowed = np.where(cov, np.asarray(rad), 0.0)
    return {
        "size": size, "faces": int(mesh.faces.shape[0]), "bunny_faces": nb, "coverage": float(cov.mean()),
        "overflow": int(r.overflow), "shadow_overflow": int(ovf), "shadow_incomplete": int(np.sum(inc)),
        "bad_faces": int(r.bad_faces),
        "max_plane_distance_m": float(dist.max()), "max_bary_outside": rel_b,
        "max_normal_angle_deg": float(ang.max()),
        "null_median_vertex_distance_m": float(np.median(dv)), "null_max_vertex_distance_m": float(dv.max()),
        "depth_m": (float(np.asarray(r.depth)[cov].min()), float(np.asarray(r.depth)[cov].max())),
        "shadowed_fraction": float(shadowed.sum() / max(facing.sum(), 1)),
        "penumbra_pixels": int(penumbra.sum()),
        "max_radiance_in_umbra": float(img[shadowed].max()) if shadowed.any() else 0.0,
        "max_radiance_lit": float(img.max()),
        "shadow_changed_pixels": int(np.sum(np.abs(img - unshadowed) > 1e-12)),
        "image": img, "depth": np.asarray(r.depth), "normal": np.asarray(r.normal), "visibility": vis,
    }


@functools.lru_cache(maxsize=4)
def measure_channels(size: int = 128) -> dict:
    """Sobel magnitude of the rendered depth: silhouette band vs eroded interior (medians)."""
    from scipy import ndimage as ndi

    mesh, cam, _ = bunny_scene(size, ground=False)
    r = _raster(mesh, cam)
    a = np.asarray(r.alpha > 0)
    z = np.asarray(r.depth)
    zmin, zmax = z[a].min(), z[a].max()
    # depth as an Image in [0, 1]: nearness, background 0 (the "no return" value)
    near = np.where(a, 0.2 + 0.8 * (zmax - z) / (zmax - zmin), 0.0)
    s = np.asarray(fsjax.ops.sobel_amp(fsjax.Image(jnp.asarray(near))).data)
    band = ndi.binary_dilation(a, iterations=1) & ~ndi.binary_erosion(a, iterations=1)
    inner = ndi.binary_erosion(a, iterations=2)
    sil, ins = float(np.median(s[band])), float(np.median(s[inner]))
    # null: the same measure on a shaded image (Lambert, head light) where the inside has shading edges
    L = fsjax.render.camera_center(cam) - jnp.asarray([0.0, 0.0, 0.0])
    shade = np.where(a, np.asarray(fsjax.render.lambert(r.normal, jnp.broadcast_to(L, r.normal.shape))), 0.0)
    shade = shade / shade.max()
    s2 = np.asarray(fsjax.ops.sobel_amp(fsjax.Image(jnp.asarray(shade))).data)
    return {"ratio": sil / ins, "silhouette_median": sil, "interior_median": ins,
            "null_ratio": float(np.median(s2[band]) / np.median(s2[inner])),
            "band_pixels": int(band.sum()), "interior_pixels": int(inner.sum()),
            "depth_image": near, "sobel": s}


def channels(out: Path, quick: bool) -> Section:
    res = measure_channels(96 if quick else 256)
    fig = _panel(out / "render_channels.png", [res["depth_image"], res["sobel"]],
                 ["bunny depth (nearness)", "sobel_amp of depth"])
    return Section(
        title="Rendered channels: depth edges found by the library's own Sobel",
        truth="the rasteriser's depth of the Stanford Bunny; silhouette = 1-px band around the coverage mask",
        rows=[("sobel_amp on depth: median silhouette / median interior", f"{res['ratio']:.1f}x"),
              ("null: the same on a Lambert-shaded image", f"{res['null_ratio']:.1f}x")],
        fsjax_figure=f"silhouette {res['ratio']:.1f}x stronger than interior",
        null_figure=f"shaded image {res['null_ratio']:.1f}x",
        beats_null=res["ratio"] >= 20.0 and res["ratio"] > res["null_ratio"],
        figure=fig,
        notes="target: >= 20x.",
    )


def bunny(out: Path, quick: bool) -> Section:
    # sized for a tour (256 px with 32 shadow samples took 105 s of CPU, a third of the tour)
    res = measure_bunny(96 if quick else 160, 8 if quick else 16)
    nrm = 0.5 + 0.5 * res["normal"][..., 2]
    fig = _panel(out / "render_bunny.png", [res["image"] ** (1 / 2.2), res["depth"], nrm, res["visibility"]],
                 ["Hapke + sun shadows", "depth", "normal z", "sun visibility"])
    return Section(
        title="A real shape: the Stanford Bunny, Hapke photometry, 0.53 deg sun, zero ambient",
        truth=f"the mesh itself ({res['bunny_faces']} faces + ground): back-projected depth must lie on the hit "
              "triangle's plane, inside the triangle; normals equal the face normals",
        rows=[("depth -> back-projected points, max distance to hit plane", f"{res['max_plane_distance_m']:.1e} m"),
              ("normal channel vs mesh face normal, max angle", f"{res['max_normal_angle_deg']:.1e} deg"),
              ("null: distance to the nearest mesh vertex (point-sampled surface), median",
               f"{res['null_median_vertex_distance_m']:.1e} m"),
              ("lit-facing pixels in cast shadow / penumbra pixels",
               f"{100 * res['shadowed_fraction']:.1f} % / {res['penumbra_pixels']}"),
              ("radiance in the umbra (zero ambient)", f"{res['max_radiance_in_umbra']:.1f}"),
              ("tile / shadow-grid overflow", f"{res['overflow']} / {res['shadow_overflow']}")],
        fsjax_figure=f"on the surface to {res['max_plane_distance_m']:.0e} m",
        null_figure=f"nearest vertex {res['null_median_vertex_distance_m']:.0e} m",
        beats_null=res["max_plane_distance_m"] < 1e-3 * res["null_median_vertex_distance_m"]
        and res["overflow"] == 0,
        figure=fig,
        notes="depth on the surface to rounding (float64); no ambient term, so the umbra is exactly 0.",
    )


SECTIONS: list[Callable[[Path, bool], Section]] = [channels, bunny]

