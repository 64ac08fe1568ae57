"""Marker-controlled watershed of a volume (``(Volume, LabelVolume) -> LabelVolume``).

Conventions:

* The same flooding as the 2-D :func:`fsjax.ops.watershed` (Meyer's flooding as a
  synchronous priority flood): every step pops all queued voxels at the lowest queued value;
  each unlabelled neighbour of a popped voxel takes the smallest label among its popped
  neighbours and joins the queue. A voxel lower than the current level is popped at the next
  step, so the queue is served in ``(value, age)`` order. Results can differ from a
  sequential priority queue (scikit-image) only among voxels of equal value (ties).
* Connectivity 6 (faces, default: scikit-image's ``connectivity=1``), 18 or 26 (static).
* Cost: one loop step per distinct value met on the flood front (per breadth-first layer on
  a plateau), each step ``O(D H W)``. ``levels`` (default 256) quantises the landscape to
  that many uniform levels between its minimum and maximum first, which bounds the number of
  steps on a float volume with ``D H W`` distinct values; ``levels=0`` floods the exact values
  (exact, and as slow as the number of distinct values).
* Every voxel connected to a marker through the volume is labelled (all of them when there
  is a marker); mask the result by a threshold for objects on a
  background. ``count`` and ``truncated`` are the markers'.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from jax import lax

from ..._checks import check_static_int
from ...registry import register
from ...types import LabelVolume, Volume
from ..measure2d._segment import _quantise
from ._label3d import _check_conn, neighbour_min3d

__all__ = ["watershed3d"]

_REFS = [
    "F. Meyer, Topographic distance and watershed lines, Signal Processing 38(1), 1994, 113-125",
    "S. Beucher, F. Meyer, The morphological approach to segmentation: the watershed "
    "transformation, in Mathematical Morphology in Image Processing, Marcel Dekker, 1993",
]
_BIG = jnp.iinfo(jnp.int32).max


@functools.partial(jax.jit, static_argnames=("connectivity", "levels"))
def _flood3d(img, markers, *, connectivity: int, levels: int):
    if levels:
        img = _quantise(img, levels)
    inf = jnp.asarray(jnp.inf, img.dtype)
    img = jnp.where(jnp.isnan(img), inf, img)
    lab0 = markers.astype(jnp.int32)
    queued0 = lab0 > 0

    def body(st):
        lab, queued, steps = st
        v = jnp.min(jnp.where(queued, img, inf))
        pop = queued & (img == v)
        best = neighbour_min3d(jnp.where(pop, lab, _BIG), connectivity, _BIG)
        new = (lab == 0) & (best < _BIG)
        return jnp.where(new, best, lab), (queued & ~pop) | new, steps + 1

    lab, _, steps = lax.while_loop(lambda st: jnp.any(st[1]), body, (lab0, queued0, jnp.int32(0)))
    return lab, steps


@register(family="watershed3d", takes=(Volume, LabelVolume), gives=LabelVolume, differentiable=False, refs=_REFS,
          infinite_ok=True)
def watershed3d(vol: Volume, markers: LabelVolume, /, *, connectivity: int = 6, levels: int = 256) -> LabelVolume:
    """Marker-controlled watershed of a volume: flood ``vol`` from the labelled markers.

    Basins meet on the crest surfaces of ``vol``. Typical landscapes: a gradient magnitude
    (``sobel3d``), or the negated distance map (``edt3d``) of touching objects.

    Args:
      vol: the landscape ``(D, H, W)`` (finite values; +-inf allowed, NaN refused).
      markers: ``LabelVolume`` of the same shape; every voxel with label ``k > 0`` seeds basin ``k``.
      connectivity: 6 (default), 18 or 26 (static).
      levels: quantisation levels of the landscape (static int, default 256; 0 = exact
        values; see the module notes for the cost).

    Returns:
      ``LabelVolume`` with the markers' ids, ``count``, ``truncated`` and spacing.

    Compared with ``skimage.segmentation.watershed`` in 3-D (tests): on the negated distance
    map of three touching balls, 99.6 % (6-) and 99.85 % (26-connectivity) of the voxels inside
    the balls agree (``levels=0`` and the default 256 alike); every disagreement is a voxel
    on the border of two basins (equal-value arrivals served in another order), and both
    agree with the nearest-centre truth to 99.2-99.3 % (the null, one label for the union: 33 %).

    Example:
      Two basins in a box, separated by a ridge at x = 4:

      >>> import jax.numpy as jnp, fsjax
      >>> x = jnp.arange(9.0)
      >>> v = fsjax.Volume(jnp.broadcast_to(1.0 - jnp.abs(x - 4) / 4, (3, 3, 9)))
      >>> m = fsjax.LabelVolume(jnp.zeros((3, 3, 9), jnp.int32).at[1, 1, 0].set(1).at[1, 1, 8].set(2), count=2)
      >>> fsjax.ops.watershed3d(v, m).data[2, 0].tolist()
      [1, 1, 1, 1, 1, 2, 2, 2, 2]
    """
    op = "watershed3d"
    conn = _check_conn(op, connectivity)
    lv = check_static_int(op, "levels", levels, lo=0, hi=1 << 20)
    if vol.data.shape != markers.data.shape:
        raise ValueError(f"{op}: arguments 'vol' and 'markers' must have the same shape, got "
                         f"{vol.data.shape} and {markers.data.shape}")
    lab, _ = _flood3d(vol.data, markers.data, connectivity=conn, levels=lv)
    return LabelVolume(lab, count=markers.count, truncated=markers.truncated, spacing=markers.spacing,
                       unit=markers.unit)
