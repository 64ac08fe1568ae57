"""Analytic signed distance volumes of simple solids, sampled at voxel centres.

``sdf_volume(kind, shape, spacing, centre=..., **size)`` returns a ``Volume`` whose voxel
``(k, j, i)`` holds the exact signed distance (negative inside, in ``unit``) from the point
``(k dz, j dy, i dx)`` to the solid. Formulas (exact Euclidean distances, see Quilez's
catalogue of distance functions and any computational-geometry text):

* ``sphere``: ``|p - c| - radius``;
* ``box``: with ``q = |p - c| - half`` per axis, ``|max(q, 0)| + min(max(q), 0)``;
* ``cylinder`` (axis along z, capped): with ``d = (sqrt(dy^2 + dx^2) - radius, |dz| - half_height)``,
  ``|max(d, 0)| + min(max(d), 0)``;
* ``torus`` (axis along z): ``sqrt((sqrt(dy^2 + dx^2) - major)^2 + dz^2) - minor``.

The parameters enter through ``jax.numpy``, so a fit can differentiate through them.
"""

from __future__ import annotations

import jax.numpy as jnp

from .._checks import check_choice, check_positive, check_static_int
from ..types import Volume

__all__ = ["SDF_KINDS", "sdf_volume"]

SDF_KINDS = ("sphere", "box", "cylinder", "torus")
_SIZES = {"sphere": ("radius",), "box": ("half",), "cylinder": ("radius", "half_height"),
          "torus": ("major", "minor")}


def _grid(shape, spacing, dtype):
    axes = [jnp.arange(n, dtype=dtype) * s for n, s in zip(shape, spacing)]
    return jnp.meshgrid(*axes, indexing="ij")


def sdf_volume(kind: str, shape: tuple[int, int, int], spacing=(1.0, 1.0, 1.0), *, centre=None,
               unit: str = "mm", dtype=None, **size) -> Volume:
    """Signed distance ``Volume`` of a sphere, box, capped cylinder or torus.

    Args:
      kind: one of ``SDF_KINDS``.
      shape: ``(D, H, W)`` voxels.
      spacing: ``(dz, dy, dx)`` in ``unit``.
      centre: ``(z, y, x)`` in ``unit`` (default: the volume's centre).
      unit: length unit of the distances.
      dtype: float dtype (default: JAX's default float).
      **size: ``radius`` (sphere); ``half`` = ``(hz, hy, hx)`` half extents (box);
        ``radius``, ``half_height`` (cylinder along z); ``major``, ``minor`` (torus about z).

    Returns:
      ``Volume`` of exact signed distances (negative inside).

    Example:
      A sphere of radius 3 mm in a 9^3 volume: the centre voxel is 3 mm inside, a corner
      ``4 sqrt(3) - 3`` mm outside:

      >>> import fsjax
      >>> v = fsjax.synth.sdf_volume("sphere", (9, 9, 9), radius=3.0)
      >>> float(v.data[4, 4, 4]), round(float(v.data[0, 0, 0]), 4)
      (-3.0, 3.9282)
    """
    check_choice("sdf_volume", "kind", kind, SDF_KINDS)
    shape = tuple(check_static_int("sdf_volume", "shape", n, lo=1) for n in shape)
    if len(shape) != 3:
        raise ValueError(f"sdf_volume: argument 'shape' must be (D, H, W), got {shape}")
    want = _SIZES[kind]
    if set(size) != set(want):
        raise TypeError(f"sdf_volume({kind!r}): expected size arguments {', '.join(want)}; got {', '.join(size) or 'none'}")
    for name in want:
        check_positive("sdf_volume", name, size[name])
    dtype = dtype or jnp.result_type(float)
    sp = tuple(float(s) for s in spacing)
    if centre is None:
        centre = tuple((n - 1) * s / 2 for n, s in zip(shape, sp))
    z, y, x = _grid(shape, sp, dtype)
    c = jnp.asarray(centre, dtype)
    dz, dy, dx = z - c[0], y - c[1], x - c[2]
    if kind == "sphere":
        d = jnp.sqrt(dz * dz + dy * dy + dx * dx) - size["radius"]
    elif kind == "box":
        h = jnp.broadcast_to(jnp.asarray(size["half"], dtype), (3,))
        q = jnp.stack([jnp.abs(dz) - h[0], jnp.abs(dy) - h[1], jnp.abs(dx) - h[2]])
        d = jnp.sqrt(jnp.sum(jnp.maximum(q, 0.0) ** 2, axis=0)) + jnp.minimum(jnp.max(q, axis=0), 0.0)
    elif kind == "cylinder":
        q = jnp.stack([jnp.sqrt(dy * dy + dx * dx) - size["radius"], jnp.abs(dz) - size["half_height"]])
        d = jnp.sqrt(jnp.sum(jnp.maximum(q, 0.0) ** 2, axis=0)) + jnp.minimum(jnp.max(q, axis=0), 0.0)
    else:
        ring = jnp.sqrt(dy * dy + dx * dx) - size["major"]
        d = jnp.sqrt(ring * ring + dz * dz) - size["minor"]
    return Volume(d, sp, unit)
