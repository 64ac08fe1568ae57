"""Harris-3D keypoints of a point cloud (Sipiran and Bustos 2011).

Per point ``p`` and its ``k`` nearest neighbours: the neighbours' principal axes (PCA about
their centroid; the normal is the least-variance axis) give a local frame; in it, centred on
``p`` and scaled by the neighbours' RMS distance from ``p``, a quadric
``z = a x^2 / 2 + b x y + c y^2 / 2 + d x + e y + f`` is fitted by least squares. The
Harris matrix of the image case, ``E = integral of g(x, y) grad f grad f^T`` with a unit
Gaussian ``g``, is then closed form (the paper's Section 3.2):
``E = [[d^2 + 2 a^2 + 2 b^2, d e + 2 a b + 2 b c], [., e^2 + 2 b^2 + 2 c^2]]``, and the
response ``h = det E - kappa tr(E)^2``. Keypoints: points whose response is the largest
among their ``nms_k`` nearest neighbours and above ``min_response``, not on the cloud's border, the strongest ``max_keypoints`` of them
(the paper keeps a fraction of the vertices or clusters them; a fixed capacity here).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from ..._checks import check_range, check_static_int
from ..._linalg import eigh_small, solve_small
from ...registry import register
from ...types import Points
from ._search import knn

__all__ = ["harris3d"]

_REF_SB = ("I. Sipiran, B. Bustos, Harris 3D: a robust extension of the Harris operator for interest "
           "point detection on 3D meshes, The Visual Computer 27(11), 2011, 963-976")
_REF_HS = "C. Harris, M. Stephens, A combined corner and edge detector, Alvey Vision Conference, 1988"


@functools.partial(jax.jit, static_argnames=("k", "nms_k", "max_keypoints"))
def _harris_core(xyz, valid, kappa, max_offset, min_response, k, nms_k, max_keypoints):
    dt = xyz.dtype
    idx, d2 = knn(xyz, xyz, k, ref_valid=valid)  # includes the point itself
    ok_n = idx >= 0
    Q = xyz[jnp.maximum(idx, 0)]  # (N, k, 3)
    wn = ok_n.astype(dt)
    cnt = jnp.maximum(jnp.sum(wn, -1), 1.0)
    c = jnp.sum(Q * wn[..., None], 1) / cnt[:, None]
    D = (Q - c[:, None, :]) * wn[..., None]
    C = jnp.einsum("nki,nkj->nij", D, D) / cnt[:, None, None]
    _, V = eigh_small(C)  # ascending: V[..., 0] = normal
    E = jnp.stack([V[..., 1], V[..., 2], V[..., 0]], -1)
    L = jnp.einsum("nki,nij->nkj", Q - xyz[:, None, :], E)
    s = jnp.sqrt(jnp.sum(jnp.sum(L * L, -1) * wn, -1) / cnt)
    L = L / jnp.where(s > 0, s, 1.0)[:, None, None]
    x, y, z = L[..., 0], L[..., 1], L[..., 2]
    A = jnp.stack([x * x / 2, x * y, y * y / 2, x, y, jnp.ones_like(x)], -1) * wn[..., None]
    M = jnp.einsum("nki,nkj->nij", A, A) + 1e-9 * jnp.eye(6, dtype=dt)
    rhs = jnp.einsum("nki,nk->ni", A, z * wn)
    p = solve_small(M, rhs)
    a, b, cc, d, e = p[:, 0], p[:, 1], p[:, 2], p[:, 3], p[:, 4]
    e11 = d * d + 2 * a * a + 2 * b * b
    e22 = e * e + 2 * b * b + 2 * cc * cc
    e12 = d * e + 2 * a * b + 2 * b * cc
    h = e11 * e22 - e12 * e12 - kappa * (e11 + e22) ** 2
    good = valid & (jnp.sum(wn, -1) >= 6) & jnp.isfinite(h) & (s > 0)
    # a point on the cloud's border sees its neighbours on one side: its quadric is extrapolated
    inner = jnp.linalg.norm(c - xyz, axis=-1) <= max_offset * s
    h = jnp.where(good, h, -jnp.inf)
    nb = idx[:, 1:nms_k + 1]
    hn = jnp.where(nb >= 0, h[jnp.maximum(nb, 0)], -jnp.inf)
    is_max = good & inner & (h > min_response) & jnp.all(h[:, None] >= hn, -1)
    score = jnp.where(is_max, h, -jnp.inf)
    top, order = jax.lax.top_k(score, max_keypoints)
    kv = jnp.isfinite(top)
    truncated = jnp.sum(is_max) > max_keypoints
    return xyz[order], kv, truncated, jnp.where(good, h, jnp.nan)


@register(family="points", takes=Points, gives=Points, differentiable=False, refs=[_REF_SB, _REF_HS])
def harris3d(points: Points, /, *, k: int = 32, nms_k: int = 16, max_keypoints: int = 32,
             kappa: float = 0.04, max_offset: float = 0.35,
             min_response: float = 0.01) -> Points:
    """Harris-3D interest points of a cloud (Sipiran and Bustos 2011), fixed capacity.

    Per point, the quadric of its ``k`` nearest neighbours in their principal frame (centred on
    the point, lengths in the neighbours' RMS distance, so the response is scale free) gives
    the Harris matrix in closed form and the response ``det E - kappa tr(E)^2`` (see the module
    docstring). Keypoints are the responses above ``min_response`` and the largest among the point's
    ``nms_k`` nearest neighbours, strongest first.

    Args:
      points: the cloud ``(N, 3)``; invalid slots are neither neighbours nor keypoints.
      k: neighbours of the quadric fit (static int in [8, 64]).
      nms_k: neighbours a keypoint must dominate (static int in [1, k - 1]).
      max_keypoints: capacity of the result (static int in [1, N]).
      kappa: Harris's constant (in [0, 0.25)).
      max_offset: a point whose neighbours' centroid lies farther than this many RMS
        neighbour distances from it is on the cloud's border (a crop, a scan's edge) and not a
        keypoint: its one-sided quadric is an extrapolation.
      min_response: a keypoint's response must exceed this (scale free: on 5,000 bunny samples
        the median response is 0.003, the 32 strongest maxima above 2; a sampled sphere stays
        below 0.006, a plane at 0 up to rounding).

    Returns:
      ``Points`` of capacity ``max_keypoints``: the keypoints by descending response, ``valid``
      for the filled slots (the rest repeat a point and are invalid), ``truncated`` when more
      local maxima passed than the capacity holds. A cloud without any (a plane, a sphere,
      too few points) gives no valid slot.

    Example:
      Keypoints of 5,000 bunny samples (unit size) and of the same samples turned by 60
      degrees: the turned keypoints of the first fall within 1 % of the size of a keypoint of
      the second (a plane gives none):

      >>> import numpy as np, jax.numpy as jnp, fsjax
      >>> from fsjax.synth import match3d_object, rotation_zyx
      >>> R, p = rotation_zyx((60, 0, 0)), match3d_object("bunny", 1.0, 5000, 0)
      >>> a = fsjax.ops.harris3d(fsjax.Points(jnp.asarray(p)))
      >>> b = fsjax.ops.harris3d(fsjax.Points(jnp.asarray(p @ R.T)))
      >>> pa, pb = np.asarray(a.xyz)[np.asarray(a.valid)] @ R.T, np.asarray(b.xyz)[np.asarray(b.valid)]
      >>> rep = np.mean(np.linalg.norm(pa[:, None] - pb[None], axis=-1).min(1) < 0.01)
      >>> bool(rep > 0.9), int(a.valid.sum())
      (True, 32)
      >>> g = np.stack(np.meshgrid(np.arange(20.0), np.arange(20.0)), -1).reshape(-1, 2)
      >>> plane = fsjax.Points(jnp.asarray(np.c_[g, 0.3 * g[:, 0] + 0.1 * g[:, 1]]))
      >>> int(fsjax.ops.harris3d(plane).valid.sum())
      0
    """
    op = "harris3d"
    if not isinstance(points, Points) or points.xyz.ndim != 2:
        raise ValueError(f"{op}: argument 'points' must be one Points cloud (N, 3) (batch with jax.vmap)")
    n = points.xyz.shape[0]
    k = check_static_int(op, "k", k, lo=8, hi=64)
    nms_k = check_static_int(op, "nms_k", nms_k, lo=1, hi=k - 1)
    max_keypoints = check_static_int(op, "max_keypoints", max_keypoints, lo=1, hi=n)
    check_range(op, "kappa", kappa, 0.0, 0.25, hi_open=True)
    check_range(op, "max_offset", max_offset, 0.0, None, lo_open=True)
    check_range(op, "min_response", min_response, 0.0, None)
    dt = jnp.result_type(points.xyz.dtype, jnp.float32)
    ok = points.valid & jnp.all(jnp.isfinite(points.xyz), -1)
    xyz = jnp.where(ok[:, None], points.xyz.astype(dt), 0.0)
    kp, kv, trunc, _ = _harris_core(xyz, ok, jnp.asarray(kappa, dt), jnp.asarray(max_offset, dt),
                                     jnp.asarray(min_response, dt), k=k, nms_k=nms_k, max_keypoints=max_keypoints)
    return Points(kp, valid=kv, truncated=trunc)
