"""Rendering ops (family ``render``): mesh -> depth / silhouette, depth -> shaded image.

Conventions: the camera model of :mod:`fsjax.render.camera` (OpenCV frame, x right, y down,
z forward; ``world_from_camera`` poses; pixel centres on integer ``(row, col)``), pinhole
only for rasterisation (:func:`fsjax.render.rasterize`; distortion refused). Depth is the
camera-frame z; pixels with no surface get depth 0 (the :class:`fsjax.Depth` "no return").
Shading values are in [0, 1] (Lambert, albedo 1 scaled by ``pi``: a surface facing the light
is 1). Light directions are given in the **camera** frame by ``azimuth_deg`` (in the image
plane, from +col towards -row, i.e. counter-clockwise on screen) and ``elevation_deg``
(from the image plane towards the camera; 90 is a head light).
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp

from ..._checks import check_static_int
from ...registry import LinKnob, register
from ...render.camera import backproject, pixel_grid_uv
from ...render.raster import rasterize
from ...types import Camera, Depth, Image, Mesh, Region

__all__ = ["render_depth", "render_silhouette", "shade_depth"]

_RASTER_REFS = ["M. Olano, T. Greer, Triangle scan conversion using 2D homogeneous coordinates, "
                "Proc. ACM SIGGRAPH/Eurographics Workshop on Graphics Hardware, 1997"]


@register(family="render", takes=(Mesh, Camera), gives=Depth, differentiable=True, refs=_RASTER_REFS)
def render_depth(mesh: Mesh, camera: Camera, /, *, tile: int = 16, capacity: int = 256) -> Depth:
    """Depth map of a triangle mesh seen by a pinhole camera (z-buffer by rasterisation).

    At each pixel centre the nearest triangle hit along the ray ``K^-1 (col, row, 1)`` gives
    the camera-frame depth ``z = (n . P0) / (n . d)`` (homogeneous edge functions, see
    :func:`fsjax.render.rasterize`). Background pixels are 0.

    Args:
      mesh: triangle mesh (world units).
      camera: pinhole camera (zero distortion); the depth has its ``height x width``.
      tile, capacity: static ints sizing the rasteriser's candidate buffer under ``jit``
        (``4 x capacity x tiles`` of ``tile x tile`` pixels; see :func:`fsjax.render.rasterize`);
        an eager call sizes it from the measured demand and is always complete. Pixels that
        an overflow may have changed are NaN (never a silent hole).

    Returns:
      ``Depth`` with the camera. Differentiable in the vertex positions and the camera
      inside faces (hard silhouette: coverage changes are not differentiated).

    Matches closed forms: a plane at known depth exactly (to 1e-15), a tessellated sphere
    between its inscribed and circumscribed spheres, Moller-Trumbore ray casting to 1e-14
    (tests/render/test_raster.py).

    Example:
        >>> cam = fsjax.synth.standard_input(fsjax.Camera)  # at z = -4 looking along +z, f = 40 px
        >>> v = jnp.asarray([[-1.0, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]])
        >>> d = fsjax.ops.render_depth(fsjax.Mesh(v, jnp.asarray([[0, 1, 2], [0, 2, 3]])), cam)
        >>> float(d.z[11, 15]), float(d.z[0, 0])  # the square at depth 4; background 0
        (4.0, 0.0)
    """
    check_static_int("render_depth", "tile", tile, lo=1)
    check_static_int("render_depth", "capacity", capacity, lo=1)
    r = rasterize(mesh, camera, tile=tile, capacity=capacity)
    return Depth(jnp.where(r.incomplete, jnp.nan, r.depth), camera)


@register(family="render", takes=(Mesh, Camera), gives=Region, differentiable=False, refs=_RASTER_REFS)
def render_silhouette(mesh: Mesh, camera: Camera, /, *, tile: int = 16, capacity: int = 256) -> Region:
    """Silhouette (coverage mask) of a mesh: pixels whose centre ray hits a triangle.

    Args:
      mesh: triangle mesh; camera: pinhole camera (zero distortion).
      tile, capacity: static buffer sizing under ``jit`` (see :func:`render_depth`); an
        eager call sizes the buffer from the measured demand and is always complete. A
        ``Region`` has no flag and a bool no NaN, so a traced call whose candidates overflow
        the buffer raises at run time through ``equinox.error_if`` ("render_silhouette:
        capacity ... exceeded"; under ``vmap`` when any member overflows) instead of
        returning a mask with holes; raise ``capacity`` (or use :func:`render_depth`, whose
        overflowed pixels are NaN).

    Returns:
      ``Region`` ``(H, W)``.

    Example:
        >>> cam = fsjax.synth.standard_input(fsjax.Camera)
        >>> v = jnp.asarray([[-1.0, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]])
        >>> sq = fsjax.Mesh(v, jnp.asarray([[0, 1, 2], [0, 2, 3]]))
        >>> # a 2 x 2 square at distance 4 with f = 40 px spans 20 x 20 pixel centres
        >>> int(fsjax.ops.render_silhouette(sq, cam).data.sum())
        400
    """
    check_static_int("render_silhouette", "tile", tile, lo=1)
    check_static_int("render_silhouette", "capacity", capacity, lo=1)
    r = rasterize(mesh, camera, tile=tile, capacity=capacity)
    # fail closed: after an overflow the kept candidates may miss covered pixels (a plausible
    # mask with holes); a bool mask cannot be poisoned, so the traced call raises (eager calls
    # size the buffer from the data and are never incomplete)
    covered = eqx.error_if(r.alpha > 0, jnp.any(r.incomplete),
                           f"render_silhouette: capacity {capacity} exceeded under jit (the candidate buffer "
                           "overflowed; raise capacity)")
    return Region(covered)


@register(family="render", takes=Depth, gives=Image, differentiable=True,
          knobs={"azimuth_deg": LinKnob(0.0, 360.0), "elevation_deg": LinKnob(10.0, 90.0)},
          refs=["J. H. Lambert, Photometria, 1760", "B. K. P. Horn, Hill shading and the reflectance map, "
                "Proc. IEEE 69(1), 1981"])
def shade_depth(depth: Depth, /, *, azimuth_deg: float = 135.0, elevation_deg: float = 45.0) -> Image:
    """Lambert shading of a depth map under a directional light (a hill-shade of the surface).

    Each pixel is back-projected with the depth's camera; the surface normal is the cross
    product of the central differences of the 3-D points along columns and rows (one-sided
    at the border and next to no-return pixels), turned towards the camera; the output is
    ``max(n . l, 0)`` (Lambert with albedo ``pi``, so a surface facing the light is 1).
    No-return pixels (depth 0 or NaN) are 0.

    Args:
      depth: ``Depth`` map with its camera.
      azimuth_deg: light azimuth in the image plane, degrees counter-clockwise on screen
        from +col (knob ``a``, 0-360).
      elevation_deg: light elevation from the image plane towards the camera, degrees
        (knob ``b``, 10-90; 90 is a head light).

    Returns:
      ``Image`` in [0, 1].

    Example:
        >>> cam = fsjax.synth.standard_input(fsjax.Camera)
        >>> flat = fsjax.Depth(jnp.full((24, 32), 4.0), cam)  # a wall facing the camera
        >>> img = fsjax.ops.shade_depth(flat, azimuth_deg=0.0, elevation_deg=30.0)
        >>> round(float(img.data[12, 16]), 9)  # n = -z, l . n = sin(30 deg)
        0.5
    """
    cam = depth.camera
    z = depth.z
    dt = jnp.result_type(z.dtype, float)
    ok = jnp.isfinite(z) & (z > 0)
    zs = jnp.where(ok, z, 1.0).astype(dt)
    X = backproject(cam, pixel_grid_uv(cam, dtype=dt), zs, undistort=True)
    X = jnp.where(ok[..., None], X, 0.0)

    def diff(axis):
        n = X.shape[axis]
        idx = jnp.arange(n)
        fwd = jnp.minimum(idx + 1, n - 1)
        bwd = jnp.maximum(idx - 1, 0)
        shape = (n, 1) if axis == 0 else (1, n)
        okf = jnp.take(ok, fwd, axis=axis) & (fwd != idx).reshape(shape)
        okb = jnp.take(ok, bwd, axis=axis) & (bwd != idx).reshape(shape)
        Xf = jnp.where(okf[..., None], jnp.take(X, fwd, axis=axis), X)
        Xb = jnp.where(okb[..., None], jnp.take(X, bwd, axis=axis), X)
        return Xf - Xb

    dc = diff(1)
    dr = diff(0)
    n = jnp.cross(dc, dr)  # camera frame (x right, y down): dc x dr points away from the camera
    n2 = jnp.sum(n * n, -1, keepdims=True)
    good = ok & (n2[..., 0] > 0)
    n = jnp.where(good[..., None], n / jnp.sqrt(jnp.where(good[..., None], n2, 1.0)), 0.0)
    # orient towards the camera: n . (camera centre - X) > 0
    to_cam = cam.t - X
    s = jnp.where(jnp.sum(n * to_cam, -1, keepdims=True) < 0, -1.0, 1.0)
    n = n * s
    az = jnp.deg2rad(jnp.asarray(azimuth_deg, dt))
    el = jnp.deg2rad(jnp.asarray(elevation_deg, dt))
    l_cam = jnp.stack([jnp.cos(el) * jnp.cos(az), -jnp.cos(el) * jnp.sin(az), -jnp.sin(el)])
    l_w = cam.R.astype(dt) @ l_cam
    out = jnp.maximum(jnp.sum(n * l_w, -1), 0.0)
    return Image(jnp.where(good, jnp.minimum(out, 1.0), 0.0))
