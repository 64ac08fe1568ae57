"""Projections of a volume along one of its axes (``Volume -> Image``).

Conventions:

* ``axis`` is 0 (z), 1 (y) or 2 (x) of the ``(D, H, W)`` volume (static); the image keeps
  the other two axes in their order: ``axis=0`` gives ``(H, W)``, ``1`` gives ``(D, W)``,
  ``2`` gives ``(D, H)``.
* ``kind``: ``"max"`` (maximum intensity projection, MIP), ``"min"``, ``"mean"`` or
  ``"sum"`` (the sum of the voxel values times the voxel length along ``axis``: a line
  integral in value times unit, the parallel-beam ray sum of a density volume).
* The ``Image``'s ``[0, 1]`` convention holds for ``max``, ``min`` and ``mean`` of a volume
  in ``[0, 1]``; ``sum`` is a line integral and exceeds it. The voxel spacing of the two
  kept axes is not carried (``Image`` has none). Perspective projections through a camera
  are :func:`fsjax.ops.volume_mip` and :func:`fsjax.ops.volume_drr`.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from ..._checks import check_choice
from ...registry import register
from ...types import Image, Volume

__all__ = ["project3d"]

_KINDS = ("max", "min", "mean", "sum")


@functools.partial(jax.jit, static_argnames=("axis", "kind", "step"))
def _project_core(x, *, axis: int, kind: str, step: float):
    ax = x.ndim - 3 + axis
    if kind == "max":
        return jnp.max(x, axis=ax)
    if kind == "min":
        return jnp.min(x, axis=ax)
    if kind == "mean":
        return jnp.mean(x, axis=ax)
    return jnp.sum(x, axis=ax) * step


@register(family="project3d", takes=Volume, gives=Image, differentiable=True,
          refs=["J. W. Wallis et al., Three-dimensional display in nuclear medicine, "
                "IEEE Trans. Med. Imaging 8(4), 1989 (maximum intensity projection)"])
def project3d(vol: Volume, /, *, axis: int = 0, kind: str = "max") -> Image:
    """Maximum / minimum / mean / sum projection of a volume along one axis.

    Args:
      vol: ``Volume`` ``(D, H, W)``.
      axis: 0 (z, default), 1 (y) or 2 (x); static.
      kind: ``"max"`` (MIP, default), ``"min"``, ``"mean"`` or ``"sum"`` (values times the
        voxel length ``spacing[axis]``: a line integral); static.

    Returns:
      ``Image`` of the two other axes (see the module notes for their order).

    Equals ``np.max`` / ``np.min`` / ``np.mean`` / ``np.sum * spacing[axis]`` along the axis
    exactly (to rounding of the sum).

    Example:
      Two bright voxels on one z line: the MIP sees the brighter; the sum along z at
      spacing 2 mm integrates both:

      >>> import jax.numpy as jnp, fsjax
      >>> v = fsjax.Volume(jnp.zeros((4, 3, 5)).at[1, 2, 3].set(0.5).at[3, 2, 3].set(0.25), spacing=(2.0, 1.0, 1.0))
      >>> mip = fsjax.ops.project3d(v)
      >>> mip.data.shape, float(mip.data[2, 3]), float(fsjax.ops.project3d(v, kind="sum").data[2, 3])
      ((3, 5), 0.5, 1.5)
      >>> fsjax.ops.project3d(v, axis=2, kind="mean").data.shape
      (4, 3)
    """
    op = "project3d"
    if isinstance(axis, bool) or axis not in (0, 1, 2):
        raise ValueError(f"{op}: argument 'axis' must be 0 (z), 1 (y) or 2 (x); got {axis!r}")
    check_choice(op, "kind", kind, _KINDS)
    return Image(_project_core(vol.data, axis=int(axis), kind=kind, step=float(vol.spacing[int(axis)])))
