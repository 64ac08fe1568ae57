"""Camera ops: conversions between depth maps and point sets (family ``camera``).

Conventions: the camera model of :mod:`fsjax.render.camera` (OpenCV frame, x right,
y down, z forward; ``world_from_camera`` poses; pixel centres on integer indices;
Brown-Conrady distortion undone iteratively). Depth is the camera-frame z, not the range.
"""

from __future__ import annotations

import jax.numpy as jnp

from ...registry import register
from ...render.camera import backproject, pixel_grid_uv
from ...types import Depth, Points

__all__ = ["depth_to_points"]


@register(family="camera", takes=Depth, gives=Points, differentiable=True,
          refs=["R. Hartley, A. Zisserman, Multiple View Geometry in Computer Vision, 2nd ed., "
                "Cambridge University Press, 2004, sec. 6.1"])
def depth_to_points(depth: Depth, /) -> Points:
    """Back-project every pixel of a depth map to a world point.

    Pixel ``(row, col)`` with depth ``z > 0`` becomes ``R (z K^-1 [col, row, 1]) + t`` (after
    undistortion when the camera has distortion), in the camera's world frame. The output has
    one slot per pixel, in row-major order, so ``Points.xyz`` reshapes to ``(H, W, 3)``;
    pixels with no return (``z <= 0`` or NaN) are invalid slots holding zeros.

    Args:
      depth: ``Depth`` map ``(H, W)`` with its camera (one camera; use ``vmap`` for batches).

    Returns:
      ``Points`` with ``H * W`` slots; ``valid`` marks pixels with a finite positive depth.

    Matches the closed form exactly for undistorted cameras (round trip through
    :func:`fsjax.render.project` to 1e-12 in float64).

    Example:
        >>> cam = fsjax.Camera.from_intrinsics(100.0, 100.0, 15.5, 11.5, width=32, height=24,
        ...                                    t=jnp.asarray([0.0, 0.0, -4.0]))
        >>> pts = fsjax.ops.depth_to_points(fsjax.Depth(jnp.full((24, 32), 4.0), cam))
        >>> # pixel (row 6, col 25): x = (25 - 15.5) * 4 / 100, y = (6 - 11.5) * 4 / 100, z = 4 - 4
        >>> [round(float(v), 12) for v in pts.xyz[6 * 32 + 25]]
        [0.38, -0.22, 0.0]
    """
    cam = depth.camera
    z = depth.z
    ok = jnp.isfinite(z) & (z > 0)
    zs = jnp.where(ok, z, 1.0)
    X = backproject(cam, pixel_grid_uv(cam, dtype=z.dtype), zs)
    X = jnp.where(ok[..., None], X, 0.0)
    n = z.shape[0] * z.shape[1]
    return Points(X.reshape(n, 3), valid=ok.reshape(n))
