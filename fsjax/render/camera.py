"""The one camera model of fsjax: pinhole with Brown-Conrady distortion, OpenCV convention.

Conventions (fixed by the design, used by rendering, calibration and splatting):

* Camera frame: x right, y down, z forward (OpenCV). A pose is ``world_from_camera``
  (``R``, ``t``): a camera-frame point ``p`` is the world point ``R @ p + t``; ``t`` is the
  camera centre in the world. The GL convention (x right, y up, z backward) is reached only
  through the named conversions :func:`gl_from_cv_pose` / :func:`cv_from_gl_pose`.
* Pixel coordinates ``uv``: ``u`` is the column (x), ``v`` the row (y); pixel centres sit on
  integer values, so the image spans ``[-0.5, W - 0.5] x [-0.5, H - 0.5]``. Arrays of
  pixels are indexed ``(row, col)``; only functions with ``uv`` in an argument or name take
  ``(x, y)`` order.
* Distortion: Brown-Conrady as in OpenCV, ``dist = (k1, k2, p1, p2, k3)`` acting on
  normalised coordinates ``(x, y) = (X/Z, Y/Z)``::

      r2 = x^2 + y^2,  a = 1 + k1 r2 + k2 r2^2 + k3 r2^3
      x_d = a x + 2 p1 x y + p2 (r2 + 2 x^2)
      y_d = a y + p1 (r2 + 2 y^2) + 2 p2 x y

  :func:`undistort_normalized` inverts it by Newton's method (2x2 Jacobian per point) to a
  residual below ``1e-10`` px in float64 (reported per point, never silently).
* Depth is the z coordinate in the camera frame (along the optical axis), not the range.

All functions take one unbatched :class:`fsjax.Camera`; use ``jax.vmap`` for batches. They
are differentiable with respect to the camera's arrays and the points.
"""

from __future__ import annotations

import functools
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._checks import check_range, check_static_int
from ..types import Camera, is_concrete

__all__ = [
    "intrinsics_from_fov",
    "look_at",
    "gl_from_cv_pose",
    "cv_from_gl_pose",
    "world_to_camera",
    "camera_to_world",
    "distort_normalized",
    "undistort_normalized",
    "project",
    "backproject",
    "pixel_grid_uv",
    "pixel_rays",
    "camera_center",
    "Undistorted",
]

_CV_GL_FLIP = np.diag([1.0, -1.0, -1.0])


def _check_unbatched(cam: Camera, fn: str) -> None:
    if not isinstance(cam, Camera):
        raise TypeError(f"{fn}(camera=...): expected a Camera, got {type(cam).__name__}")
    if cam.batch_shape:
        raise ValueError(f"{fn}(camera=...): expected one camera, got batch shape {cam.batch_shape}; use jax.vmap")


def intrinsics_from_fov(width: int, height: int, *, fov_x_deg: float | None = None,
                        fov_y_deg: float | None = None, dtype=None) -> jnp.ndarray:
    """Intrinsic matrix ``K`` for a pinhole camera of the given horizontal or vertical field of view.

    The field of view spans the full image extent ``W`` (or ``H``) pixels, from the left edge
    of the first pixel to the right edge of the last: ``fx = (W / 2) / tan(fov_x / 2)``. The
    principal point is the image centre ``((W - 1) / 2, (H - 1) / 2)`` (pixel centres on
    integers). Give one of ``fov_x_deg``/``fov_y_deg`` (square pixels) or both.

    Example:
        >>> K = fsjax.render.intrinsics_from_fov(640, 480, fov_x_deg=90.0)
        >>> [round(float(K[0, 0]), 6), float(K[0, 2]), float(K[1, 2])]
        [320.0, 319.5, 239.5]
    """
    check_static_int("intrinsics_from_fov", "width", width, lo=1)
    check_static_int("intrinsics_from_fov", "height", height, lo=1)
    if fov_x_deg is None and fov_y_deg is None:
        raise ValueError("intrinsics_from_fov(fov_x_deg=..., fov_y_deg=...): give at least one field of view")
    for name, v in (("fov_x_deg", fov_x_deg), ("fov_y_deg", fov_y_deg)):
        if v is not None:
            check_range("intrinsics_from_fov", name, v, 0.0, 180.0, lo_open=True, hi_open=True)
    fx = None if fov_x_deg is None else (width / 2.0) / math.tan(math.radians(fov_x_deg) / 2.0)
    fy = None if fov_y_deg is None else (height / 2.0) / math.tan(math.radians(fov_y_deg) / 2.0)
    fx = fy if fx is None else fx
    fy = fx if fy is None else fy
    K = jnp.array([[fx, 0.0, (width - 1) / 2.0], [0.0, fy, (height - 1) / 2.0], [0.0, 0.0, 1.0]])
    return K if dtype is None else K.astype(dtype)


def look_at(eye, target, up=(0.0, 1.0, 0.0)) -> tuple[jnp.ndarray, jnp.ndarray]:
    """``world_from_camera`` pose ``(R, t)`` of a camera at ``eye`` looking at ``target`` (OpenCV frame).

    The camera z axis points from ``eye`` to ``target``; its y axis (image down) is the
    component of ``-up`` orthogonal to z, so ``up`` (world) appears upward in the image; x is
    ``y x z`` (right-handed). ``R`` has the camera axes as columns; ``t = eye``.
    ``up`` parallel to the viewing direction, or ``eye == target``, is refused eagerly and
    gives NaN under ``jit``.

    Example:
        >>> R, t = fsjax.render.look_at([0.0, 0.0, -5.0], [0.0, 0.0, 0.0], up=[0.0, -1.0, 0.0])
        >>> np.allclose(R, np.eye(3)), [float(v) for v in t]
        (True, [0.0, 0.0, -5.0])
    """
    eye = jnp.asarray(eye, dtype=jnp.result_type(float))
    target = jnp.asarray(target, dtype=eye.dtype)
    up = jnp.asarray(up, dtype=eye.dtype)
    f = target - eye
    fn = jnp.linalg.norm(f)
    if is_concrete(fn) and not float(fn) > 0:
        raise ValueError("look_at(eye, target): eye and target coincide; the viewing direction is undefined")
    z = f / jnp.where(fn > 0, fn, 1.0)
    d = -up - jnp.dot(-up, z) * z
    dn = jnp.linalg.norm(d)
    un = jnp.linalg.norm(up)
    par = dn <= 1e-9 * jnp.maximum(un, 1.0)
    if is_concrete(par) and bool(par):
        raise ValueError("look_at(up=...): up is zero or parallel to the viewing direction")
    y = d / jnp.where(par, 1.0, dn)
    x = jnp.cross(y, z)
    R = jnp.stack([x, y, z], axis=1)
    bad = par | ~(fn > 0)
    return jnp.where(bad, jnp.nan, R), jnp.where(bad, jnp.nan, eye)


def gl_from_cv_pose(R, t) -> tuple[jnp.ndarray, jnp.ndarray]:
    """Convert a ``world_from_camera`` pose from the OpenCV frame to the GL frame (x right, y up, z back).

    ``R_gl = R_cv @ diag(1, -1, -1)``; the centre ``t`` is unchanged. Its inverse is
    :func:`cv_from_gl_pose` (the same flip).

    Example:
        >>> R, t = fsjax.render.look_at([0.0, 0.0, -5.0], [0.0, 0.0, 0.0], up=[0.0, -1.0, 0.0])
        >>> Rg, tg = fsjax.render.gl_from_cv_pose(R, t)
        >>> [float(v) for v in Rg[:, 2]]  # GL camera looks along its -z: +z points back to -world z
        [0.0, 0.0, -1.0]
    """
    R = jnp.asarray(R)
    return R @ jnp.asarray(_CV_GL_FLIP, R.dtype), jnp.asarray(t)


def cv_from_gl_pose(R, t) -> tuple[jnp.ndarray, jnp.ndarray]:
    """Convert a ``world_from_camera`` pose from the GL frame to the OpenCV frame (inverse of :func:`gl_from_cv_pose`).

    Example:
        >>> R = jnp.asarray(np.diag([1.0, -1.0, -1.0]))
        >>> Rc, _ = fsjax.render.cv_from_gl_pose(R, jnp.zeros(3))
        >>> np.allclose(Rc, np.eye(3))
        True
    """
    R = jnp.asarray(R)
    return R @ jnp.asarray(_CV_GL_FLIP, R.dtype), jnp.asarray(t)


def world_to_camera(cam: Camera, points) -> jnp.ndarray:
    """Camera-frame coordinates ``R^T (X - t)`` of world points ``(..., 3)``.

    Example:
        >>> cam = fsjax.Camera.from_intrinsics(100.0, 100.0, 15.5, 11.5, width=32, height=24,
        ...                                    t=jnp.asarray([0.0, 0.0, -4.0]))
        >>> [float(v) for v in fsjax.render.world_to_camera(cam, jnp.zeros(3))]
        [0.0, 0.0, 4.0]
    """
    _check_unbatched(cam, "world_to_camera")
    X = jnp.asarray(points)
    return (X - cam.t) @ cam.R


def camera_to_world(cam: Camera, points) -> jnp.ndarray:
    """World coordinates ``R p + t`` of camera-frame points ``(..., 3)``.

    Example:
        >>> cam = fsjax.Camera.from_intrinsics(100.0, 100.0, 15.5, 11.5, width=32, height=24,
        ...                                    t=jnp.asarray([0.0, 0.0, -4.0]))
        >>> [float(v) for v in fsjax.render.camera_to_world(cam, jnp.asarray([0.0, 0.0, 4.0]))]
        [0.0, 0.0, 0.0]
    """
    _check_unbatched(cam, "camera_to_world")
    p = jnp.asarray(points)
    return p @ cam.R.T + cam.t


def camera_center(cam: Camera) -> jnp.ndarray:
    """The camera centre in world coordinates (``t`` of the ``world_from_camera`` pose)."""
    _check_unbatched(cam, "camera_center")
    return cam.t


def distort_normalized(dist, xy) -> jnp.ndarray:
    """Apply Brown-Conrady distortion ``(k1, k2, p1, p2, k3)`` to normalised coordinates ``(..., 2)`` (x, y).

    Example:
        >>> d = jnp.asarray([0.1, 0.0, 0.0, 0.0, 0.0])
        >>> [round(float(v), 12) for v in fsjax.render.distort_normalized(d, jnp.asarray([0.5, 0.0]))]
        [0.5125, 0.0]
    """
    dist = jnp.asarray(dist)
    xy = jnp.asarray(xy)
    k1, k2, p1, p2, k3 = (dist[..., i] for i in range(5))
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    a = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = a * x + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = a * y + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return jnp.stack([xd, yd], axis=-1)


class Undistorted(eqx.Module):
    """Result of :func:`undistort_normalized`: ``xy`` (..., 2), ``residual`` (..., ) in normalised
    units (``|distort(xy) - xy_d|``), ``converged`` (...,) and the Newton ``iterations`` used."""

    xy: jax.Array
    residual: jax.Array
    converged: jax.Array
    iterations: jax.Array


@functools.partial(jax.jit, static_argnums=3)
def _undistort_core(dist, flat, tol, max_iter: int):
    # module-level jit: the Newton while_loop below is built from closures, which outside jit
    # would be traced and compiled again on every eager call (found by the chain fuzzer)

    def one(target):
        f = lambda p: distort_normalized(dist, p) - target  # noqa: E731

        def cond(s):
            p, r, i = s
            return (r > tol) & (i < max_iter)

        def body(s):
            p, _, i = s
            J = jax.jacfwd(f)(p)
            step = jnp.linalg.solve(J, f(p))
            p = p - step
            return p, jnp.linalg.norm(f(p)), i + 1

        p0 = jax.lax.stop_gradient(target)
        s = jax.lax.stop_gradient((p0, jnp.linalg.norm(f(p0)), jnp.asarray(0)))
        p, r, i = jax.lax.while_loop(cond, body, s)
        p = jax.lax.stop_gradient(p)
        # One Newton step outside the loop carries the implicit-function gradient:
        # d p / d theta = -J^-1 d(distort)/d theta at the solution (the loop itself is not
        # differentiated, so reverse mode works and costs one linear solve).
        p = p - jnp.linalg.solve(jax.lax.stop_gradient(jax.jacfwd(f)(p)), f(p))
        r = jax.lax.stop_gradient(r)
        # A root on a folded branch (negative radial factor or a Jacobian that flips
        # orientation) is not the undistorted point: fail closed there.
        J = jax.lax.stop_gradient(jax.jacfwd(f)(p))
        r2 = jnp.sum(p * p)
        radial = 1.0 + r2 * (dist[0] + r2 * (dist[1] + r2 * dist[4]))
        ok = jnp.isfinite(r) & (r <= tol) & (jnp.linalg.det(J) > 0) & (radial > 0)
        return jnp.where(ok, p, jnp.nan), r, ok, i

    return jax.vmap(one)(flat)


def undistort_normalized(dist, xy_distorted, *, max_iter: int = 30, tol=None) -> Undistorted:
    """Invert :func:`distort_normalized` by Newton's method, per point.

    Starts at the distorted point, iterates ``x <- x - J^-1 (d(x) - x_d)`` with the exact 2x2
    Jacobian until the residual is below ``tol`` (default: ``1e-13`` in float64, i.e. below
    1e-10 px for focal lengths up to 1000 px; ``1e-6`` in float32) or ``max_iter`` is reached.
    A point whose residual stays above ``tol``, or whose root lies on a folded branch of the
    distortion (negative radial factor or a Jacobian of negative determinant: outside the
    region where the model is invertible), has ``converged=False`` and NaN coordinates.
    Gradients flow through one extra Newton step at the solution (implicit function
    theorem), so reverse mode works.

    Example:
        >>> d = jnp.asarray([-0.28, 0.07, 0.001, -0.0005, 0.0])
        >>> xd = fsjax.render.distort_normalized(d, jnp.asarray([0.3, -0.2]))
        >>> u = fsjax.render.undistort_normalized(d, xd)
        >>> bool(u.converged), float(jnp.max(jnp.abs(u.xy - jnp.asarray([0.3, -0.2])))) < 1e-12
        (True, True)
    """
    xd = jnp.asarray(xy_distorted)
    dist = jnp.asarray(dist, dtype=xd.dtype)
    if tol is None:
        tol = 1e-13 if xd.dtype == jnp.float64 else 1e-6
    flat = xd.reshape(-1, 2)
    max_iter = check_static_int("undistort_normalized", "max_iter", max_iter, lo=0)
    p, r, ok, it = _undistort_core(dist, flat, jnp.asarray(tol, xd.dtype), max_iter)
    lead = xd.shape[:-1]
    return Undistorted(p.reshape(xd.shape), r.reshape(lead), ok.reshape(lead), it.reshape(lead))


def project(cam: Camera, points) -> tuple[jnp.ndarray, jnp.ndarray]:
    """Project world points ``(..., 3)`` to pixels: returns ``(uv (..., 2), depth (...))``.

    ``u`` is the column (x) and ``v`` the row (y), pixel centres on integers; ``depth`` is the
    camera-frame z. Points with ``depth <= 0`` (at or behind the camera) get NaN ``uv``: they
    have no image, and a plausible-looking mirrored pixel would be wrong.

    Example:
        >>> cam = fsjax.Camera.from_intrinsics(100.0, 100.0, 15.5, 11.5, width=32, height=24,
        ...                                    t=jnp.asarray([0.0, 0.0, -4.0]))
        >>> uv, z = fsjax.render.project(cam, jnp.asarray([0.4, -0.2, 0.0]))
        >>> [round(float(v), 9) for v in uv], float(z)
        ([25.5, 6.5], 4.0)
    """
    _check_unbatched(cam, "project")
    p = world_to_camera(cam, points)
    z = p[..., 2]
    front = z > 0
    zs = jnp.where(front, z, 1.0)
    xy = p[..., :2] / zs[..., None]
    xy = distort_normalized(cam.dist, xy)
    K = cam.K
    u = K[0, 0] * xy[..., 0] + K[0, 1] * xy[..., 1] + K[0, 2]
    v = K[1, 1] * xy[..., 1] + K[1, 2]
    uv = jnp.stack([u, v], axis=-1)
    return jnp.where(front[..., None], uv, jnp.nan), z


def _normalized_from_uv(cam: Camera, uv) -> jnp.ndarray:
    K = cam.K
    uv = jnp.asarray(uv)
    y = (uv[..., 1] - K[1, 2]) / K[1, 1]
    x = (uv[..., 0] - K[0, 2] - K[0, 1] * y) / K[0, 0]
    return jnp.stack([x, y], axis=-1)


def backproject(cam: Camera, uv, depth, *, undistort: bool = True) -> jnp.ndarray:
    """World points of pixels ``uv (..., 2)`` (u = column, v = row) at camera-frame ``depth (...)``.

    With ``undistort=True`` (default) the pixel is first undistorted by
    :func:`undistort_normalized` (NaN where that does not converge); with all-zero
    distortion the result is exact. Round trip ``backproject(project(X)) == X`` to 1e-12 in
    float64 (tested).

    Example:
        >>> cam = fsjax.Camera.from_intrinsics(100.0, 100.0, 15.5, 11.5, width=32, height=24,
        ...                                    t=jnp.asarray([0.0, 0.0, -4.0]))
        >>> X = fsjax.render.backproject(cam, jnp.asarray([25.5, 6.5]), 4.0)
        >>> [round(float(v), 12) for v in X]
        [0.4, -0.2, 0.0]
    """
    _check_unbatched(cam, "backproject")
    xy = _normalized_from_uv(cam, uv)
    if undistort:
        xy = undistort_normalized(cam.dist, xy).xy
    d = jnp.asarray(depth, dtype=xy.dtype)
    p = jnp.concatenate([xy * d[..., None], jnp.broadcast_to(d, xy.shape[:-1])[..., None]], axis=-1)
    return camera_to_world(cam, p)


def pixel_grid_uv(cam: Camera, dtype=None) -> jnp.ndarray:
    """``(H, W, 2)`` pixel-centre coordinates ``(u, v) = (col, row)`` of the camera's image."""
    _check_unbatched(cam, "pixel_grid_uv")
    dt = cam.K.dtype if dtype is None else dtype
    v, u = jnp.meshgrid(jnp.arange(cam.height, dtype=dt), jnp.arange(cam.width, dtype=dt), indexing="ij")
    return jnp.stack([u, v], axis=-1)


def pixel_rays(cam: Camera, *, undistort: bool = True) -> tuple[jnp.ndarray, jnp.ndarray]:
    """World-space rays through every pixel centre: ``(origins (H, W, 3), directions (H, W, 3))``.

    Directions are unit length; a ray's parameter ``s`` along ``direction`` relates to depth by
    ``depth = s * (direction . optical axis)``. Distortion is undone per pixel when
    ``undistort`` (NaN rays where the inverse does not converge).

    Example:
        >>> cam = fsjax.Camera.from_intrinsics(100.0, 100.0, 15.5, 11.5, width=32, height=24)
        >>> o, d = fsjax.render.pixel_rays(cam)
        >>> d.shape, round(float(jnp.linalg.norm(d[3, 5])), 12)
        ((24, 32, 3), 1.0)
    """
    _check_unbatched(cam, "pixel_rays")
    xy = _normalized_from_uv(cam, pixel_grid_uv(cam))
    if undistort:
        xy = undistort_normalized(cam.dist, xy).xy
    p = jnp.concatenate([xy, jnp.ones(xy.shape[:-1] + (1,), xy.dtype)], axis=-1)
    d = p / jnp.linalg.norm(p, axis=-1, keepdims=True)
    d = d @ cam.R.T
    o = jnp.broadcast_to(cam.t, d.shape)
    return o, d
