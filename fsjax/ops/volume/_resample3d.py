"""Crop, pad and resample a volume (``Volume -> Volume``).

Conventions:

* Voxel centres sit on integer indices; voxel ``(k, i, j)`` is at ``(k dz, i dy, j dx)`` in
  the volume's own frame, the first voxel's centre at the origin (as in ``marching_cubes``).
  ``Volume`` carries no origin: after ``volume_crop(start=(k0, i0, j0))`` the new first voxel
  is the old voxel ``start``, i.e. at ``(k0 dz, i0 dy, j0 dx)`` in the old frame; after
  ``volume_pad`` with ``before = (p, q, r)`` the old first voxel is the new voxel ``(p, q, r)``.
  The caller who needs world coordinates adds that offset.
* ``volume_resample`` keeps the physical frame: the new first voxel centre is the old one,
  the new spacing is the one asked for, and along each axis the new grid has
  ``floor((n - 1) s / s') + 1`` voxels, the most whose centres stay within the old centres'
  extent (no extrapolation). ``order=1`` is trilinear interpolation and equals
  ``scipy.ndimage.map_coordinates(x, coords, order=1)`` at those coordinates; ``order=0``
  takes the nearest voxel (for masks and labels; ties at exactly half a voxel round up).
  Downsampling by ``order=1`` without smoothing aliases: smooth first
  (``gaussian3d(sigma ~ s' / 2)``) where that matters.
* Pads use SciPy's boundary mode names (``"constant"`` with ``cval``, ``"nearest"``,
  ``"reflect"``, ``"mirror"``, ``"wrap"``), as the 3-D filters do.
* All shapes are static (``start``, ``size``, ``pad`` and the new spacing are Python numbers),
  so each op is one program under ``jit`` and ``vmap``; values are differentiable.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from ...registry import register
from ...types import Volume
from .._common import check_mode, pad_axis

__all__ = ["volume_crop", "volume_pad", "volume_resample"]

_MAX_VOXELS = 1_000_000_000
_REF_INTERP = ("P. Thevenaz, T. Blu, M. Unser, Interpolation revisited, IEEE Trans. Med. Imaging 19(7), "
               "2000 (nearest and linear interpolation on a sampled grid)")


def _triple(op: str, name: str, v, lo: int):
    """A static int or a triple of static ints, each ``>= lo``."""
    t = (v, v, v) if isinstance(v, (int, np.integer)) and not isinstance(v, bool) else v
    ok = isinstance(t, (tuple, list)) and len(t) == 3 and all(
        isinstance(a, (int, np.integer)) and not isinstance(a, bool) for a in t)
    if not ok:
        raise TypeError(f"{op}: argument {name!r} must be an int or three ints (z, y, x); got {v!r}")
    if any(int(a) < lo for a in t):
        raise ValueError(f"{op}: argument {name!r} must be >= {lo} on every axis; got {tuple(int(a) for a in t)}")
    return tuple(int(a) for a in t)


@register(family="resample3d", takes=Volume, gives=Volume, differentiable=True)
def volume_crop(vol: Volume, /, *, start=(0, 0, 0), size=(1, 1, 1)) -> Volume:
    """The box of ``size`` voxels whose first voxel is ``start``.

    Args:
      vol: ``Volume`` ``(D, H, W)``.
      start: first voxel ``(k0, i0, j0)``, or one int for all axes (static, ``>= 0``).
      size: ``(d, h, w)`` voxels, or one int (static, ``>= 1``); the box must lie inside the
        volume (a box that does not is refused, never silently clipped).

    Returns:
      ``Volume`` ``(d, h, w)``, same spacing and unit (origin shift: see the module notes).

    Example:
      >>> import jax.numpy as jnp, fsjax
      >>> v = fsjax.Volume(jnp.arange(60.0).reshape(3, 4, 5), spacing=(2.0, 1.0, 1.0))
      >>> c = fsjax.ops.volume_crop(v, start=(1, 2, 3), size=(2, 2, 2))
      >>> c.data.shape, float(c.data[0, 0, 0]), float(c.data[1, 1, 1]), c.spacing
      ((2, 2, 2), 33.0, 59.0, (2.0, 1.0, 1.0))
    """
    op = "volume_crop"
    s0 = _triple(op, "start", start, 0)
    sz = _triple(op, "size", size, 1)
    shp = vol.data.shape[-3:]
    if any(a + b > n for a, b, n in zip(s0, sz, shp)):
        raise ValueError(f"{op}: the box start={s0}, size={sz} does not fit in the volume of shape {shp}")
    sl = tuple(slice(a, a + b) for a, b in zip(s0, sz))
    return Volume(vol.data[(Ellipsis, *sl)], spacing=vol.spacing, unit=vol.unit)


@register(family="resample3d", takes=Volume, gives=Volume, differentiable=True)
def volume_pad(vol: Volume, /, *, before=(1, 1, 1), after=(1, 1, 1), mode: str = "constant",
               cval: float = 0.0) -> Volume:
    """Pad a volume by ``before``/``after`` voxels per axis with a SciPy boundary mode.

    Args:
      vol: ``Volume`` ``(D, H, W)``.
      before: voxels added before the first voxel on each axis ``(z, y, x)``, or one int
        (static, ``>= 0``; at most 4096 per side).
      after: voxels added after the last voxel, likewise.
      mode: ``"constant"`` (default, value ``cval``), ``"nearest"``, ``"reflect"``,
        ``"mirror"`` or ``"wrap"`` (SciPy's names; static).
      cval: the value of ``"constant"`` padding (default 0).

    Returns:
      ``Volume`` ``(D + b_z + a_z, ...)``, same spacing and unit.

    Example:
      Equal to ``numpy.pad`` with the matching mode (SciPy's ``reflect`` is NumPy's
      ``symmetric``):

      >>> import numpy as np, jax.numpy as jnp, fsjax
      >>> x = np.arange(24.0).reshape(2, 3, 4)
      >>> p = fsjax.ops.volume_pad(fsjax.Volume(jnp.asarray(x)), before=(1, 0, 2), after=0, mode="reflect")
      >>> p.data.shape, bool(np.array_equal(p.data, np.pad(x, ((1, 0), (0, 0), (2, 0)), mode="symmetric")))
      ((3, 3, 6), True)
      >>> float(fsjax.ops.volume_pad(fsjax.Volume(jnp.asarray(x)), cval=-1.0).data[0, 0, 0])
      -1.0
    """
    op = "volume_pad"
    b = _triple(op, "before", before, 0)
    a = _triple(op, "after", after, 0)
    if max(b + a) > 4096:
        raise ValueError(f"{op}: a pad of {max(b + a)} voxels is above the bound of 4096 per side")
    check_mode(op, mode)
    x = vol.data
    for ax in range(3):
        x = pad_axis(x, b[ax], a[ax], x.ndim - 3 + ax, mode, cval)
    return Volume(x, spacing=vol.spacing, unit=vol.unit)


def _axis_weights(n: int, m: int, ratio: float, order: int, dtype):
    """Source index pairs and weights of the new samples ``i * ratio`` along one axis."""
    pos = np.arange(m, dtype=np.float64) * ratio
    if order == 0:
        i0 = np.minimum(np.floor(pos + 0.5), n - 1).astype(np.int32)
        return i0, i0, np.zeros(m)
    i0 = np.minimum(np.floor(pos), n - 1).astype(np.int32)
    i1 = np.minimum(i0 + 1, n - 1)
    return i0, i1, pos - i0


@functools.partial(jax.jit, static_argnames=("shape", "ratios", "order"))
def _resample_core(x, *, shape, ratios, order):
    for ax in range(3):
        n = x.shape[x.ndim - 3 + ax]
        i0, i1, w = _axis_weights(n, shape[ax], ratios[ax], order, x.dtype)
        a = x.ndim - 3 + ax
        lo = jnp.take(x, jnp.asarray(i0), axis=a)
        if order == 0:
            x = lo
            continue
        hi = jnp.take(x, jnp.asarray(i1), axis=a)
        bshape = [1] * x.ndim
        bshape[a] = -1
        wt = jnp.asarray(w, x.dtype).reshape(bshape)
        x = lo + wt * (hi - lo)
    return x


@register(family="resample3d", takes=Volume, gives=Volume, differentiable=True, refs=[_REF_INTERP])
def volume_resample(vol: Volume, /, *, spacing=(1.0, 1.0, 1.0), order: int = 1) -> Volume:
    """Resample a volume to a new voxel spacing in the same physical frame.

    Args:
      vol: ``Volume`` ``(D, H, W)`` with spacing ``(dz, dy, dx)``.
      spacing: the new ``(dz', dy', dx')`` in the volume's unit, or one number (static,
        positive). The new grid is at most 1e9 voxels.
      order: 1 (trilinear, default) or 0 (nearest voxel, for masks and labels); static.

    Returns:
      ``Volume`` on the new grid (shape rule in the module notes), spacing ``spacing``.

    Example:
      A linear ramp is reproduced exactly by trilinear resampling; 0.5 mm voxels to 1.5 mm
      along z keep ``floor(9 * 0.5 / 1.5) + 1 = 4`` slices:

      >>> import numpy as np, jax.numpy as jnp, fsjax
      >>> z = np.arange(10.0)[:, None, None] * 0.5 * np.ones((1, 4, 4))
      >>> r = fsjax.ops.volume_resample(fsjax.Volume(jnp.asarray(z), spacing=(0.5, 1.0, 1.0)), spacing=(1.5, 1.0, 1.0))
      >>> r.data.shape, [float(v) for v in r.data[:, 0, 0]], r.spacing
      ((4, 4, 4), [0.0, 1.5, 3.0, 4.5], (1.5, 1.0, 1.0))
    """
    op = "volume_resample"
    sp = spacing if isinstance(spacing, (tuple, list)) else (spacing, spacing, spacing)
    try:
        sp = tuple(float(s) for s in sp)
    except (TypeError, ValueError):
        raise TypeError(f"{op}: argument 'spacing' must be a positive number or three (dz, dy, dx); got {spacing!r}") from None
    if len(sp) != 3 or not all(np.isfinite(s) and s > 0 for s in sp):
        raise ValueError(f"{op}: argument 'spacing' must be three positive finite numbers (dz, dy, dx); got {spacing!r}")
    if isinstance(order, bool) or not isinstance(order, (int, np.integer)) or order not in (0, 1):
        raise ValueError(f"{op}: argument 'order' must be 0 (nearest) or 1 (trilinear); got {order!r}")
    shp = vol.data.shape[-3:]
    # a tiny relative slack keeps an exact multiple (e.g. 9 * 0.5 / 1.5 = 3) from flooring to 2.999...
    new = tuple(int(np.floor((n - 1) * s / t * (1 + 1e-12))) + 1 for n, s, t in zip(shp, vol.spacing, sp))
    if int(np.prod(new, dtype=np.float64)) > _MAX_VOXELS:
        raise ValueError(f"{op}: the new grid {new} has more than {_MAX_VOXELS:,} voxels; "
                         "choose a coarser 'spacing' or crop first")
    ratios = tuple(t / s for s, t in zip(vol.spacing, sp))
    return Volume(_resample_core(vol.data, shape=new, ratios=ratios, order=int(order)), spacing=sp, unit=vol.unit)
