"""Surface curvature of point clouds from local quadric fits (``Points -> PointValues``).

Conventions:

* Curvatures are in inverse length units of ``xyz`` (a sphere of radius
  ``R`` has principal curvatures ``1/R``).
* Sign: curvature is positive where the surface bends *away* from its outward
  normal (convex, like a sphere seen from outside). The outward side of each
  point is taken from the input ``normals`` when the cloud carries them, else
  it is the side facing away from the centroid of the valid points (right for
  closed, star-shaped objects; pass normals for anything else).
* Shape index (Koenderink & van Doorn 1992), ``[-1, 1]`` form, written with
  ``atan2`` so it is exact at umbilics: ``S = (2/pi) atan2(k1 + k2, k1 - k2)``
  with ``k1 >= k2``: sphere (convex) ``1``, cylinder ``0.5``, symmetric saddle
  ``0``, cylindrical trough ``-0.5``, concave sphere ``-1``. At a planar point
  (``k1 = k2 = 0``) the shape index is undefined; it is reported as ``0``
  there and ``curvedness`` (``0``) says so.
* Curvedness ``C = sqrt((k1^2 + k2^2) / 2)``.
* Per-point results are a :class:`PointValues` (values ``(N, C)`` with static
  column ``names`` and the cloud's ``valid`` mask); a point whose fit is
  impossible (fewer than 6 valid neighbours, degenerate neighbourhood) holds
  NaN.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from ..._checks import check_static_int
from ...registry import register
from ...types import Points, PointValues
from ._cloud import _valid_mask, knn, pca_frames

__all__ = ["curvature"]


CURVATURE_NAMES = ("k1", "k2", "mean", "gaussian", "shape_index", "curvedness")


def _safe_sqrt(x):
    pos = x > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, x, 1.0)), 0.0)


def quadric_curvatures(xyz, valid, idx, outward):
    """Principal curvatures at each point from a least-squares quadric in its PCA frame.

    ``idx`` ``(N, k)`` neighbours (``-1`` missing); ``outward`` ``(N, 3)`` a
    vector on the outward side. Returns ``(k1, k2, ok)``.
    """
    dt = xyz.dtype
    evals, evecs, _, cnt = pca_frames(xyz, valid, idx)
    e1, e2, n = evecs[..., 2], evecs[..., 1], evecs[..., 0]
    flip = jnp.sum(n * outward, axis=-1) < 0
    n = jnp.where(flip[:, None], -n, n)
    e2 = jnp.where(flip[:, None], -e2, e2)  # keep (e1, e2, n) right-handed
    m = (idx >= 0) & valid[jnp.maximum(idx, 0)]
    d = xyz[jnp.maximum(idx, 0)] - xyz[:, None, :]
    u = jnp.einsum("nki,ni->nk", d, e1)
    v = jnp.einsum("nki,ni->nk", d, e2)
    w = jnp.einsum("nki,ni->nk", d, n)
    mf = m.astype(dt)
    s2 = jnp.sum(mf * (u * u + v * v), axis=1) / jnp.maximum(jnp.sum(mf, axis=1), 1.0)
    ok = valid & (cnt >= 6) & (s2 > 0)
    s = jnp.sqrt(jnp.where(ok, s2, 1.0))
    U, V, W = u / s[:, None], v / s[:, None], w / s[:, None]
    A = jnp.stack([U * U, U * V, V * V, U, V, jnp.ones_like(U)], axis=-1) * mf[..., None]
    ata = jnp.einsum("nki,nkj->nij", A, A)
    atb = jnp.einsum("nki,nk->ni", A, W * mf)
    # a well-posed fit needs the 6 x 6 normal matrix to be far from singular
    ev = jnp.linalg.eigvalsh(ata)
    ok = ok & (ev[:, 0] > 1e-10 * jnp.maximum(ev[:, -1], 1e-300))
    eye = jnp.eye(6, dtype=dt)
    c = jnp.linalg.solve(jnp.where(ok[:, None, None], ata, eye), jnp.where(ok[:, None], atb, 0.0)[..., None])[..., 0]
    a, b, cc, du, dv = c[:, 0], c[:, 1], c[:, 2], c[:, 3], c[:, 4]
    # h(u, v) = s * (a (u/s)^2 + b (u/s)(v/s) + c (v/s)^2 + d u/s + e v/s + f)
    huu, huv, hvv, hu, hv = 2 * a / s, b / s, 2 * cc / s, du, dv
    E, F, G = 1 + hu * hu, hu * hv, 1 + hv * hv
    Wn = jnp.sqrt(1 + hu * hu + hv * hv)
    L, M, N = huu / Wn, huv / Wn, hvv / Wn
    det = E * G - F * F
    K = (L * N - M * M) / det
    H = -(E * N - 2 * F * M + G * L) / (2 * det)  # sign: convex toward the outside is positive
    r = _safe_sqrt(H * H - K)
    return H + r, H - r, ok


@register(family="points", takes=Points, gives=PointValues, differentiable=False,
          refs=["J. J. Koenderink, A. J. van Doorn, Surface shape and curvature scales, Image and Vision "
                "Computing 10(8), 1992",
                "F. Cazals, M. Pouget, Estimating differential quantities using polynomial fitting of "
                "osculating jets, Computer Aided Geometric Design 22(2), 2005"])
def curvature(pts: Points, /, *, k: int = 24) -> PointValues:
    """Principal, mean and Gaussian curvature, shape index and curvedness per point.

    In the PCA frame ``(e1, e2, n)`` of the ``k`` nearest neighbours, the
    height ``h(u, v)`` of the neighbours along ``n`` is fitted by the full
    quadric ``a u^2 + b uv + c v^2 + d u + e v + f`` (least squares); the
    fundamental forms of that graph at ``(0, 0)`` give the Gaussian curvature
    ``K``, the mean curvature ``H`` and ``k1,2 = H +- sqrt(H^2 - K)``. Then
    ``S = (2/pi) atan2(k1 + k2, k1 - k2)`` and ``C = sqrt((k1^2 + k2^2)/2)``.

    Args:
      pts: the cloud (its ``normals``, when present, only fix the outward side).
      k: neighbours per fit (static int, 6..32; default 24). More neighbours
        average noise but add the quartic bias of a quadric on a patch of
        radius ``rho``: about ``rho^2 / (4 R^2)`` relative on a sphere.

    Returns:
      :class:`PointValues` with columns ``k1, k2, mean, gaussian, shape_index,
      curvedness`` (curvatures in 1/length, ``k1 >= k2``). Its ``valid`` is the
      cloud's mask and a well-posed fit: a point with fewer than 6 valid
      neighbours, or whose patch is degenerate (collinear, a repeated point), is
      invalid and holds NaN, never a plausible curvature.

    Note:
      The osculating-jet estimator of degree 2 (Cazals & Pouget 2005) with
      the PCA plane as the reference frame. Tested on absolute scale: on a
      sphere of radius ``R`` the median curvedness is ``1/R`` within 2 %;
      shape index 1.0 (sphere), 0.5 (cylinder), 0.0 (saddle).

    Example:
      Points on a sphere of radius 2 have curvedness 1/2 and shape index 1:

      >>> import numpy as np, jax.numpy as jnp, fsjax
      >>> i = np.arange(2000) + 0.5
      >>> phi, th = np.arccos(1 - 2 * i / 2000), np.pi * (1 + 5 ** 0.5) * i
      >>> xyz = 2.0 * np.c_[np.cos(th) * np.sin(phi), np.sin(th) * np.sin(phi), np.cos(phi)]
      >>> cv = fsjax.ops.curvature(fsjax.Points(jnp.asarray(xyz)), k=16)
      >>> round(float(np.median(cv["curvedness"])), 2), round(float(np.median(cv["shape_index"])), 2)
      (0.5, 1.0)
    """
    op = "curvature"
    k = check_static_int(op, "k", k, lo=6, hi=32)
    vals, valid = _curvature_core(pts, k)
    # a row whose fit is ill-posed is not measured: invalid, and NaN as an invalid row holds
    return PointValues(vals, CURVATURE_NAMES, valid=valid)


# One compiled program per cloud shape and k: run op by op, the fit compiled ~90 small programs at
# each new cloud size.
@functools.partial(jax.jit, static_argnames=("k",))
def _curvature_core(pts, k):
    valid = _valid_mask(pts)
    xyz = jnp.where(valid[:, None], pts.xyz, 0.0)
    idx, _ = knn(xyz, xyz, k, ref_valid=valid)
    if pts.normals is not None:
        outward = jnp.where(jnp.isfinite(pts.normals), pts.normals, 0.0)
    else:
        nv = jnp.maximum(jnp.sum(valid), 1).astype(xyz.dtype)
        cen = jnp.sum(jnp.where(valid[:, None], xyz, 0.0), axis=0) / nv
        outward = xyz - cen
    k1, k2, ok = quadric_curvatures(xyz, valid, idx, outward)
    H = 0.5 * (k1 + k2)
    K = k1 * k2
    si = (2.0 / jnp.pi) * jnp.arctan2(k1 + k2, k1 - k2)
    cv = jnp.sqrt(0.5 * (k1 * k1 + k2 * k2))
    vals = jnp.stack([k1, k2, H, K, si, cv], axis=-1)
    return jnp.where(ok[:, None], vals, jnp.nan), valid & ok
