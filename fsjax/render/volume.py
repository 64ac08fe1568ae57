"""Volume projection from any camera: digitally reconstructed radiographs and MIP.

Conventions:

* A :class:`fsjax.Volume` ``(D, H, W)`` with ``spacing = (dz, dy, dx)`` sits centred on the
  world origin: voxel ``(iz, iy, ix)`` has its centre at world
  ``((ix - (W-1)/2) dx, (iy - (H-1)/2) dy, (iz - (D-1)/2) dz)``. The sampled field is the
  trilinear interpolant of the voxel values on the box spanned by the voxel centres, and
  zero outside it.
* Rays are the camera's pixel rays (:func:`fsjax.render.pixel_rays`, OpenCV frame, any
  pose). Each ray is clipped to the box (slab test) and sampled at ``n_samples`` points
  uniformly from entry to exit; the DRR is the trapezoid rule of the field along the ray
  (``sum mu ds``, in data units times the spacing unit), exact for fields linear along the
  ray, e.g. a constant or linear volume. MIP is the maximum of those samples. Rays that
  miss the box give 0.
* Differentiable w.r.t. the volume values (the DRR is linear in them) and, almost
  everywhere, the camera.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from .._checks import check_choice, check_static_int
from ..types import Camera, Image, Volume
from .camera import pixel_rays

__all__ = ["project_volume", "volume_box"]


def volume_box(volume: Volume) -> tuple[jnp.ndarray, jnp.ndarray]:
    """World ``(lo, hi)`` corners (x, y, z) of the box spanned by the voxel centres."""
    D, H, W = volume.data.shape[-3:]
    dz, dy, dx = volume.spacing
    half = jnp.asarray([(W - 1) * dx / 2.0, (H - 1) * dy / 2.0, (D - 1) * dz / 2.0], dtype=volume.data.dtype)
    return -half, half


def _trilinear(vol: jnp.ndarray, spacing, p: jnp.ndarray, on_box: bool = False) -> jnp.ndarray:
    """Trilinear samples of ``vol`` at world points ``p`` (0 outside the box of voxel centres).
    ``on_box``: the points lie on the box by construction (ray samples between entry and exit), so
    their voxel coordinates are clamped into it: a sample on a face must not fall outside by a
    rounding, which differed between eager and compiled programs (the end samples of a ray were
    dropped under ``jit``: MIP 11 %, DRR 1 % off at some pixels)."""
    D, H, W = vol.shape
    dz, dy, dx = spacing
    fx = p[..., 0] / dx + (W - 1) / 2.0
    fy = p[..., 1] / dy + (H - 1) / 2.0
    fz = p[..., 2] / dz + (D - 1) / 2.0
    if on_box:
        fx, fy, fz = jnp.clip(fx, 0, W - 1), jnp.clip(fy, 0, H - 1), jnp.clip(fz, 0, D - 1)
    inside = (fx >= 0) & (fx <= W - 1) & (fy >= 0) & (fy <= H - 1) & (fz >= 0) & (fz <= D - 1)
    x0 = jnp.clip(jnp.floor(fx), 0, max(W - 2, 0))
    y0 = jnp.clip(jnp.floor(fy), 0, max(H - 2, 0))
    z0 = jnp.clip(jnp.floor(fz), 0, max(D - 2, 0))
    tx, ty, tz = fx - x0, fy - y0, fz - z0
    xi, yi, zi = x0.astype(jnp.int32), y0.astype(jnp.int32), z0.astype(jnp.int32)
    out = 0.0
    for a, wz in ((0, 1.0 - tz), (1, tz)):
        for b, wy in ((0, 1.0 - ty), (1, ty)):
            for c, wx in ((0, 1.0 - tx), (1, tx)):
                v = vol[jnp.minimum(zi + a, D - 1), jnp.minimum(yi + b, H - 1), jnp.minimum(xi + c, W - 1)]
                out = out + v * wz * wy * wx
    return jnp.where(inside, out, 0.0)


def project_volume(volume: Volume, camera: Camera, *, mode: str = "drr", n_samples: int = 256) -> Image:
    """Digitally reconstructed radiograph (line integrals) or maximum-intensity projection.

    Args:
      volume: ``Volume`` ``(D, H, W)`` (one volume; ``vmap`` for batches), e.g. attenuation in
        1/mm with ``spacing`` in mm, so the DRR is dimensionless.
      camera: any pinhole camera (distortion is undone per ray).
      mode: ``"drr"`` (trapezoid line integral) or ``"mip"`` (maximum along the ray).
      n_samples: samples per ray between box entry and exit (static, >= 2).

    Returns:
      ``Image`` ``(camera.height, camera.width)``: line integrals in data x spacing units,
      or maxima in data units; 0 where the ray misses the volume.

    Example:
        >>> vol = fsjax.Volume(jnp.ones((5, 5, 5)), spacing=(0.5, 0.5, 0.5))  # box 2 x 2 x 2
        >>> R, t = fsjax.render.look_at([0.0, 0.0, -5.0], [0.0, 0.0, 0.0], up=[0.0, -1.0, 0.0])
        >>> cam = fsjax.Camera.from_intrinsics(20.0, 20.0, 4.0, 4.0, width=9, height=9, R=R, t=t)
        >>> drr = fsjax.render.project_volume(vol, cam)
        >>> round(float(drr.data[4, 4]), 9)  # the central ray crosses 2 units of a unit field
        2.0
    """
    fn = "project_volume"
    if not isinstance(volume, Volume):
        raise TypeError(f"{fn}(volume=...): expected a Volume, got {type(volume).__name__}")
    if volume.batch_shape:
        raise ValueError(f"{fn}(volume=...): expected one volume, got batch {volume.batch_shape}; use jax.vmap")
    check_choice(fn, "mode", mode, ("drr", "mip"))
    n_samples = check_static_int(fn, "n_samples", n_samples, lo=2)
    return _project_core(volume, camera, mode, int(n_samples))


@functools.partial(jax.jit, static_argnames=("mode", "n"))
def _project_core(volume: Volume, camera: Camera, mode: str, n: int) -> Image:
    """The body of :func:`project_volume` as one program (called eagerly it compiled ~80 small ones)."""
    vol = volume.data
    o, d = pixel_rays(camera)
    o = o.astype(vol.dtype)
    d = d.astype(vol.dtype)
    lo, hi = volume_box(volume)
    safe = jnp.where(jnp.abs(d) > 0, d, 1.0)
    t1 = jnp.where(jnp.abs(d) > 0, (lo - o) / safe, -jnp.inf)
    t2 = jnp.where(jnp.abs(d) > 0, (hi - o) / safe, jnp.inf)
    # axis-parallel rays: inside the slab means unbounded, outside means a miss
    par_in = jnp.where(jnp.abs(d) > 0, True, (o >= lo) & (o <= hi))
    tmin = jnp.max(jnp.minimum(t1, t2), axis=-1)
    tmax = jnp.min(jnp.maximum(t1, t2), axis=-1)
    tmin = jnp.maximum(tmin, 0.0)
    hit = (tmax > tmin) & jnp.all(par_in, axis=-1)
    tmin = jnp.where(hit, tmin, 0.0)
    tmax = jnp.where(hit, tmax, 0.0)
    u = jnp.linspace(0.0, 1.0, n, dtype=vol.dtype)
    ts = tmin[..., None] + (tmax - tmin)[..., None] * u  # (H, W, n)
    p = o[..., None, :] + ts[..., None] * d[..., None, :]
    # keep samples on the box (rounding at the faces must not drop the end samples)
    p = jnp.clip(p, lo, hi)
    vals = jax.vmap(lambda row: _trilinear(vol, volume.spacing, row, on_box=True))(p)
    if mode == "drr":
        w = jnp.ones(n, vol.dtype).at[0].set(0.5).at[-1].set(0.5)
        out = jnp.sum(vals * w, axis=-1) * (tmax - tmin) / (n - 1)
    else:
        out = jnp.max(vals, axis=-1)
    return Image(jnp.where(hit, out, 0.0))
