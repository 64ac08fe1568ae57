"""The one point-cloud argument helper of the fits (ICP, global registration, RANSAC)."""

from __future__ import annotations

from typing import Any

import jax.numpy as jnp

from ..types import Points

__all__ = ["as_cloud"]


def as_cloud(fn: str, name: str, x: Any, valid: Any = None, normals: Any = None):
    """``(xyz, valid, normals)`` of a ``Points`` or an ``(N, 3)`` array argument ``name`` of ``fn``.

    ``xyz`` is floating (float32 at least); ``valid`` an ``(N,)`` bool mask (all True when not
    given); ``normals`` those of the ``Points`` unless given. A wrong shape or an empty cloud
    (0 points: a static shape, so refused while tracing) raises ``ValueError`` in the one style
    of :mod:`fsjax._checks`; all-invalid or non-finite points are data, reported by the fit's
    ``reason`` (``invalid_input``).
    """
    if isinstance(x, Points):
        if valid is not None:
            raise TypeError(f"{fn}: pass 'valid' only with a plain array; a Points carries its own mask")
        xyz, valid, normals = x.xyz, x.valid, x.normals if normals is None else normals
    else:
        xyz = jnp.asarray(x)
    if xyz.ndim != 2 or xyz.shape[-1] != 3:
        raise ValueError(f"{fn}: argument {name!r} must be Points or an (N, 3) array, got shape {tuple(xyz.shape)}")
    if xyz.shape[0] == 0:
        raise ValueError(f"{fn}: argument {name!r} must hold at least one point, got an empty cloud")
    xyz = xyz.astype(jnp.result_type(xyz.dtype, jnp.float32))
    valid = jnp.ones(xyz.shape[0], bool) if valid is None else jnp.asarray(valid, bool)
    return xyz, valid, normals
