"""Grey-value morphology of a volume with flat cube and ball elements, and hole filling.

Conventions:

* Structuring elements are flat and sized in the volume's unit (spacing-aware): with
  ``spacing`` ``(dz, dy, dx)`` the ``"ball"`` of ``radius`` r holds the voxel offsets ``o``
  with ``(o_z dz)^2 + (o_y dy)^2 + (o_x dx)^2 <= r^2``, the ``"cube"`` the offsets with
  ``|o_a| spacing[a] <= r`` on every axis (a box of ``2 floor(r / spacing[a]) + 1`` voxels per
  axis). At unit spacing they are ``skimage.morphology.ball(r)`` and the ``(2r+1)^3`` cube.
  ``radius`` is static; the cube runs as three separable 1-D min/max passes, the ball as a
  min/max over its shifted copies.
* Boundary: SciPy's mode names (``"reflect"`` by default). ``"constant"`` pads with ``cval``.
* Binary morphology: on a 0/1 mask volume, ``erosion3d``/``dilation3d``/``opening3d``/
  ``closing3d`` with ``mode="constant"`` (``cval=0``) are ``scipy.ndimage.binary_erosion`` /
  ``binary_dilation`` / ``binary_opening`` / ``binary_closing`` with the same element
  (``border_value=0``), value for value (tested).
* ``fill_holes3d`` works on the foreground ``data > level`` and returns a 0/1 volume.
* Ops are written for one ``(D, H, W)`` volume; batching is ``jax.vmap``.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from ..._checks import check_choice, check_finite_number, check_positive
from ...registry import register
from ...types import Volume, is_concrete
from .._common import check_mode, pad_axis
from ._label3d import _check_conn, _components

__all__ = ["erosion3d", "dilation3d", "opening3d", "closing3d", "tophat3d", "fill_holes3d"]

_REFS = ["J. Serra, Image Analysis and Mathematical Morphology, Academic Press, 1982",
         "P. Soille, Morphological Image Analysis, 2nd ed., Springer, 2003"]
_SHAPES = ("ball", "cube")
_MAX_OFFSETS = 4096  # ball offsets (radius ~ 10 voxels); beyond it the call is refused


def element(radius: float, shape: str, spacing) -> np.ndarray:
    """The flat structuring element as a bool array ``(2 hz + 1, 2 hy + 1, 2 hx + 1)`` (static)."""
    h = [int(np.floor(radius / float(d) + 1e-9)) for d in spacing]
    g = np.meshgrid(*[np.arange(-k, k + 1) * float(d) for k, d in zip(h, spacing)], indexing="ij")
    if shape == "cube":
        return np.ones(tuple(2 * k + 1 for k in h), bool)
    return (g[0] ** 2 + g[1] ** 2 + g[2] ** 2) <= radius * radius * (1 + 1e-12)


def _reduce(x, elem_key, *, mode: str, cval: float, dilate: bool):
    elem = np.asarray(elem_key[1], bool).reshape(elem_key[0])
    red = jnp.maximum if dilate else jnp.minimum
    half = [s // 2 for s in elem.shape]
    if elem.all():  # a box: separable
        for a, h in enumerate(half):
            if h == 0:
                continue
            ax = x.ndim - 3 + a
            n = x.shape[ax]
            xp = pad_axis(x, h, h, ax, mode, cval)
            out = None
            for k in range(2 * h + 1):
                sl = [slice(None)] * x.ndim
                sl[ax] = slice(k, k + n)
                out = xp[tuple(sl)] if out is None else red(out, xp[tuple(sl)])
            x = out
        return x
    d, hh, w = x.shape[-3:]
    xp = x
    for a, h in enumerate(half):
        xp = pad_axis(xp, h, h, x.ndim - 3 + a, mode, cval)
    out = None
    for i, j, k in np.argwhere(elem):
        v = xp[..., i:i + d, j:j + hh, k:k + w]
        out = v if out is None else red(out, v)
    return out


@functools.partial(jax.jit, static_argnames=("elem_key", "mode", "cval", "kind"))
def _morph_core(x, *, elem_key, mode: str, cval: float, kind: str):
    def ero(v):
        return _reduce(v, elem_key, mode=mode, cval=cval, dilate=False)

    def dil(v):
        return _reduce(v, elem_key, mode=mode, cval=cval, dilate=True)

    if kind == "erosion":
        return ero(x)
    if kind == "dilation":
        return dil(x)
    if kind == "opening":
        return dil(ero(x))
    if kind == "closing":
        return ero(dil(x))
    return x - dil(ero(x))


def _morph(op: str, vol: Volume, radius, shape, mode, cval, kind: str) -> Volume:
    if not is_concrete(radius):
        raise TypeError(f"{op}: argument 'radius' fixes the element and must be a static number, "
                        f"got a traced value")
    check_positive(op, "radius", radius)
    check_choice(op, "shape", shape, _SHAPES)
    check_mode(op, mode)
    check_finite_number(op, "cval", cval)
    elem = element(float(radius), shape, vol.spacing)
    n_off = int(elem.sum()) if shape == "ball" else int(sum(elem.shape))
    if n_off > _MAX_OFFSETS or max(elem.shape) > 2 * max(vol.data.shape[-3:]) + 1:
        raise ValueError(f"{op}: argument 'radius' = {radius} gives an element of {elem.shape} voxels; the bound "
                         f"is {_MAX_OFFSETS} ball offsets and at most twice the volume's largest side")
    key = (elem.shape, tuple(bool(b) for b in elem.reshape(-1)))
    out = _morph_core(vol.data, elem_key=key, mode=mode, cval=float(cval), kind=kind)
    return Volume(out, vol.spacing, vol.unit)


_ARGS_DOC = """Args:
      vol: ``Volume`` ``(D, H, W)``.
      radius: element radius in the volume's unit (static, > 0).
      shape: ``"ball"`` (default) or ``"cube"`` (static); see the module notes.
      mode: boundary mode (SciPy names); default ``"reflect"``.
      cval: value outside the volume for ``mode="constant"``."""


def _doc(fn):
    fn.__doc__ = fn.__doc__.replace("{ARGS}", _ARGS_DOC)
    return fn


@register(family="morphology3d", takes=Volume, gives=Volume, differentiable=False, refs=_REFS)
@_doc
def erosion3d(vol: Volume, /, *, radius: float = 1.0, shape: str = "ball", mode: str = "reflect",
              cval: float = 0.0) -> Volume:
    """Grey erosion: the minimum over a flat ball or cube element.

    {ARGS}

    Returns:
      The eroded ``Volume``.

    Matches ``scipy.ndimage.grey_erosion(x, footprint=element, mode=mode, cval=cval)`` exactly;
    on a 0/1 mask with ``mode="constant"`` it is ``scipy.ndimage.binary_erosion``.

    Example:
      A 5 x 5 x 5 cube eroded by the unit ball keeps its 3 x 3 x 3 core:

      >>> import jax.numpy as jnp, fsjax
      >>> x = jnp.zeros((9, 9, 9)).at[2:7, 2:7, 2:7].set(1.0)
      >>> float(fsjax.ops.erosion3d(fsjax.Volume(x)).data.sum())
      27.0
    """
    return _morph("erosion3d", vol, radius, shape, mode, cval, "erosion")


@register(family="morphology3d", takes=Volume, gives=Volume, differentiable=False, refs=_REFS)
@_doc
def dilation3d(vol: Volume, /, *, radius: float = 1.0, shape: str = "ball", mode: str = "reflect",
               cval: float = 0.0) -> Volume:
    """Grey dilation: the maximum over a flat ball or cube element.

    {ARGS}

    Returns:
      The dilated ``Volume``.

    Matches ``scipy.ndimage.grey_dilation(x, footprint=element, mode=mode, cval=cval)`` exactly.

    Example:
      One voxel dilated by a ball of radius 2 mm at spacing (2, 1, 1) mm: the ball holds the
      13-voxel disc of radius 2 in the voxel's slice and one voxel above and below (2 mm away),
      15 voxels; the cube is 3 x 5 x 5 voxels:

      >>> import jax.numpy as jnp, fsjax
      >>> v = fsjax.Volume(jnp.zeros((7, 9, 9)).at[3, 4, 4].set(1.0), spacing=(2.0, 1.0, 1.0))
      >>> [float(fsjax.ops.dilation3d(v, radius=2.0, shape=s).data.sum()) for s in ("ball", "cube")]
      [15.0, 75.0]
    """
    return _morph("dilation3d", vol, radius, shape, mode, cval, "dilation")


@register(family="morphology3d", takes=Volume, gives=Volume, differentiable=False, refs=_REFS)
@_doc
def opening3d(vol: Volume, /, *, radius: float = 1.0, shape: str = "ball", mode: str = "reflect",
              cval: float = 0.0) -> Volume:
    """Grey opening: erosion then dilation by the same element (removes bright detail smaller than it).

    {ARGS}

    Returns:
      The opened ``Volume`` (``<= vol`` everywhere).

    Matches ``scipy.ndimage.grey_opening(x, footprint=element, mode=mode)`` exactly.

    Example:
      By the unit ball: a single bright voxel is removed; a bright 5 x 5 x 5 cube loses its
      12 edges (3 voxels each) and 8 corners, 125 - 36 - 8 = 81 voxels remain; by the
      3 x 3 x 3 cube it survives whole:

      >>> import jax.numpy as jnp, fsjax
      >>> x = jnp.zeros((11, 11, 11)).at[1, 1, 1].set(1.0).at[4:9, 4:9, 4:9].set(1.0)
      >>> out = fsjax.ops.opening3d(fsjax.Volume(x))
      >>> float(out.data[1, 1, 1]), float(out.data.sum()), float(out.data[4, 4, 4]), float(out.data[4, 6, 6])
      (0.0, 81.0, 0.0, 1.0)
      >>> float(fsjax.ops.opening3d(fsjax.Volume(x), shape="cube").data.sum())
      125.0
    """
    return _morph("opening3d", vol, radius, shape, mode, cval, "opening")


@register(family="morphology3d", takes=Volume, gives=Volume, differentiable=False, refs=_REFS)
@_doc
def closing3d(vol: Volume, /, *, radius: float = 1.0, shape: str = "ball", mode: str = "reflect",
              cval: float = 0.0) -> Volume:
    """Grey closing: dilation then erosion by the same element (fills dark detail smaller than it).

    {ARGS}

    Returns:
      The closed ``Volume`` (``>= vol`` everywhere).

    Matches ``scipy.ndimage.grey_closing(x, footprint=element, mode=mode)`` exactly.

    Example:
      A one-voxel dark hole inside a bright block is filled:

      >>> import jax.numpy as jnp, fsjax
      >>> x = jnp.ones((7, 7, 7)).at[3, 3, 3].set(0.0)
      >>> float(fsjax.ops.closing3d(fsjax.Volume(x)).data[3, 3, 3])
      1.0
    """
    return _morph("closing3d", vol, radius, shape, mode, cval, "closing")


@register(family="morphology3d", takes=Volume, gives=Volume, differentiable=False, refs=_REFS)
@_doc
def tophat3d(vol: Volume, /, *, radius: float = 1.0, shape: str = "ball", mode: str = "reflect",
             cval: float = 0.0) -> Volume:
    """White top-hat: ``vol - opening3d(vol)``, the bright detail smaller than the element.

    {ARGS}

    Returns:
      The top-hat ``Volume`` (``>= 0``).

    Matches ``scipy.ndimage.white_tophat(x, footprint=element, mode=mode)`` to rounding.

    Example:
      On a constant background of 0.2, a bright voxel of 0.9 comes out as 0.7:

      >>> import jax.numpy as jnp, fsjax
      >>> x = jnp.full((7, 7, 7), 0.2).at[3, 3, 3].set(0.9)
      >>> out = fsjax.ops.tophat3d(fsjax.Volume(x))
      >>> round(float(out.data[3, 3, 3]), 12), float(out.data[0, 0, 0])
      (0.7, 0.0)
    """
    return _morph("tophat3d", vol, radius, shape, mode, cval, "tophat")


@functools.partial(jax.jit, static_argnames=("connectivity",))
def _fill_core(x, level, *, connectivity: int):
    fg = x > level
    bg = ~fg
    root, _ = _components(bg, connectivity)
    d, h, w = fg.shape
    zz, yy, xx = jnp.meshgrid(jnp.arange(d), jnp.arange(h), jnp.arange(w), indexing="ij")
    edge = (zz == 0) | (zz == d - 1) | (yy == 0) | (yy == h - 1) | (xx == 0) | (xx == w - 1)
    outside = bg & edge
    reach = jax.ops.segment_max(outside.reshape(-1).astype(jnp.int32), root, num_segments=root.shape[0])
    keep_bg = bg.reshape(-1) & (reach.at[root].get(mode="promise_in_bounds") > 0)
    return jnp.where(keep_bg.reshape(fg.shape), 0.0, 1.0).astype(x.dtype)


@register(family="morphology3d", takes=Volume, gives=Volume, differentiable=False, refs=_REFS + [
    "Y. Shiloach, U. Vishkin, An O(log n) parallel connectivity algorithm, J. Algorithms 3(1), 1982"])
def fill_holes3d(vol: Volume, /, *, level: float = 0.5, connectivity: int = 6) -> Volume:
    """Fill the cavities of the foreground ``data > level``: background not connected to the border.

    A background voxel stays background when a path of background voxels (``connectivity``
    steps) joins it to the volume's border; every other voxel becomes foreground.

    Args:
      vol: ``Volume`` ``(D, H, W)``; foreground is ``vol.data > level``.
      level: foreground threshold (default 0.5: a 0/1 mask volume).
      connectivity: connectivity of the *background* (6, default, as SciPy's default
        structure; 18 or 26); static.

    Returns:
      A 0/1 ``Volume`` (same dtype, spacing and unit): the filled mask.

    Matches ``scipy.ndimage.binary_fill_holes(x > level, structure)`` exactly (structure the
    cross for 6, ``generate_binary_structure(3, 2)`` for 18, the full cube for 26).

    Example:
      A hollow 5 x 5 x 5 box (shell one voxel thick) is filled; an open box is not:

      >>> import jax.numpy as jnp, fsjax
      >>> box = jnp.zeros((7, 7, 7)).at[1:6, 1:6, 1:6].set(1.0).at[2:5, 2:5, 2:5].set(0.0)
      >>> float(fsjax.ops.fill_holes3d(fsjax.Volume(box)).data.sum()), float(box.sum())
      (125.0, 98.0)
      >>> opened = box.at[1, 3, 3].set(0.0)  # a hole in the lid
      >>> float(fsjax.ops.fill_holes3d(fsjax.Volume(opened)).data.sum())
      97.0
    """
    op = "fill_holes3d"
    check_finite_number(op, "level", level)
    conn = _check_conn(op, connectivity)
    return Volume(_fill_core(vol.data, level, connectivity=conn), vol.spacing, vol.unit)
