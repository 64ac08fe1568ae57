"""Pose from moments: the rigid pose of a volume relative to a template by principal axes.

Takes ``(scene, template)`` volumes of one spacing, returns a :class:`fsjax.Match3D` in the
family's convention (``scene = R p + t``, physical ``(x, y, z)``). The method sees the whole
volume: the scene must hold the object alone (segment first, or cut a box); clutter changes
the moments, and the op then reports the mismatch (``valid`` False) instead of a pose.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ..._checks import check_range
from ..._linalg import eigh_small
from ...registry import register
from ...types import Match3D, Volume
from ._shared3d import _DEGENERATE, _INVALID, _NOT_FOUND, check_pair, det3, make_match

__all__ = ["moments_pose3d"]

_REF_HU = "M.-K. Hu, Visual pattern recognition by moment invariants, IRE Trans. Information Theory 8(2), 1962"
_REF_GALVEZ = ("J. M. Galvez, M. Canton, Normalization and shape recognition of three-dimensional objects "
               "by 3D moments, Pattern Recognition 26(5), 1993, 667-681")


def _moments(vol, level, spacing):
    """Mass, centroid (x, y, z), principal axes (columns, descending variance, right-handed, each with
    positive skew except possibly the least skewed one), variances, and the normalised skews' sizes
    in descending order, of ``max(vol - level, 0)``."""
    dt = vol.dtype
    dz, dy, dx = spacing
    w = jnp.maximum(vol - level, 0.0)
    k, i, j = jnp.meshgrid(*(jnp.arange(n, dtype=dt) for n in vol.shape), indexing="ij")
    P = jnp.stack([j * dx, i * dy, k * dz], -1).reshape(-1, 3)
    wf = w.reshape(-1)
    M = jnp.sum(wf)
    Ms = jnp.where(M > 0, M, 1.0)
    c = wf @ P / Ms
    Q = P - c
    C = (Q * wf[:, None]).T @ Q / Ms
    lam, V = eigh_small(C)
    lam, V = lam[::-1], V[:, ::-1]
    u = Q @ V
    m3 = wf @ (u ** 3) / Ms
    lam_s = jnp.where(lam > 0, lam, 1.0)
    skew = m3 / lam_s ** 1.5
    # every axis signed by its skew; if that gives a mirror, the least skewed axis (the least
    # certain sign) is flipped instead, so the two best-determined signs decide
    sgn = jnp.where(skew >= 0, 1.0, -1.0).astype(dt)
    E = V * sgn
    weakest = jnp.argmin(jnp.abs(skew))
    mirror = det3(E) < 0
    E = E * jnp.where(mirror & (jnp.arange(3) == weakest), -1.0, 1.0).astype(dt)
    return M, c, E, lam, jnp.sort(jnp.abs(skew))[::-1]


@jax.jit
def _pose_core(S, T, level, min_gap, min_skew, spacing):
    Ms, cs, Es, ls, ks = _moments(S, level, spacing)
    Mt, ct, Et, lt, kt = _moments(T, level, spacing)
    R = Es @ Et.T
    t = cs - R @ ct
    lt_s = jnp.where(lt > 0, lt, 1.0)
    mismatch = jnp.maximum(jnp.max(jnp.abs(ls - lt) / lt_s), jnp.abs(Ms / jnp.where(Mt > 0, Mt, 1.0) - 1))
    score = 1.0 - mismatch

    def distinct(lam, kk):
        top = jnp.where(lam[0] > 0, lam[0], 1.0)
        return ((lam[0] - lam[1]) / top >= min_gap) & ((lam[1] - lam[2]) / top >= min_gap) & \
            (kk[0] >= min_skew) & (kk[1] >= min_skew) & (lam[2] > 0)

    massive = (Ms > 0) & (Mt > 0)
    return R, t, score, massive, distinct(ls, ks) & distinct(lt, kt)


@register(family="match3d", takes=(Volume, Volume), gives=Match3D, differentiable=False, refs=[_REF_HU, _REF_GALVEZ])
def moments_pose3d(scene: Volume, template: Volume, /, *, level: float = 0.0, min_score: float = 0.8,
                   min_gap: float = 0.05, min_skew: float = 0.03) -> Match3D:
    """Rigid pose of the scene's content relative to the template's by centroids and principal axes.

    With mass ``w = max(v - level, 0)`` per voxel: the centroids ``c`` and the covariance
    matrices' eigenvectors (principal axes, by descending variance) of both volumes. Each axis
    is signed so that the third central moment along it is positive (the object's skew picks
    the direction; Galvez and Canton 1993); when that makes a mirror frame, the axis with the
    least skew (the least certain sign) is flipped instead (a proper rotation: no mirror pose), and ``R = E_s E_t^T``, ``t = c_s - R c_t``. Closed
    form (no search), so the pose can be anything; the price: the scene must contain the
    object alone, and objects with near-equal principal variances or without skew are
    ambiguous -- reported, not guessed.

    Args:
      scene: the scene ``(D, H, W)``, holding the object alone.
      template: the template, any shape, same spacing.
      level: mass threshold in data units (voxels at or below it weigh 0; raise it above the
        noise).
      min_score: ``valid`` needs the moments to agree: ``score = 1 - max(relative difference
        of the three principal variances, relative difference of the masses)`` at least this.
      min_gap: the principal variances must differ by at least this fraction of the largest
        (else the axes are not defined: ``degenerate``).
      min_skew: the two largest normalised third moments ``|m3| / var^1.5`` along the axes must
        reach this (else the axes' directions are not defined: ``degenerate``; the bunny's are
        0.155 and 0.056).

    Returns:
      ``Match3D``: ``R``, ``t`` (``scale`` 1), ``score`` as above. ``valid`` False with
      ``invalid_input`` (no mass above ``level``), ``degenerate`` (ambiguous axes), or
      ``not_found`` (the moments disagree: clutter, another object, a different size).

    Example:
      An asymmetric blob cluster rotated by 90 degrees about z and moved: pose recovered to
      1e-6 (rotating the grid by 90 degrees is exact):

      >>> import jax.numpy as jnp, fsjax
      >>> k, i, j = jnp.mgrid[0:20, 0:20, 0:20]
      >>> def g(c, s):
      ...     return jnp.exp(-((j - c[0]) ** 2 + (i - c[1]) ** 2 + (k - c[2]) ** 2) / (2 * s * s))
      >>> tpl = g((6, 9, 9), 2.0) + 0.5 * g((12, 9, 9), 1.5) + 0.3 * g((9, 13, 10), 1.2)
      >>> scene = jnp.rot90(tpl, 1, axes=(2, 1))  # x -> y: a +90 degree turn about z
      >>> m = fsjax.ops.moments_pose3d(fsjax.Volume(scene), fsjax.Volume(tpl))
      >>> [[round(float(v), 6) + 0.0 for v in row] for row in m.R], bool(m.valid)
      ([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], True)
    """
    op = "moments_pose3d"
    _, _, dt = check_pair(op, scene, template, fits=False)
    for name, v, lo, hi in (("min_score", min_score, -1.0, 1.0), ("min_gap", min_gap, 0.0, 1.0),
                            ("min_skew", min_skew, 0.0, None)):
        check_range(op, name, v, lo, hi)
    R, t, score, massive, distinct = _pose_core(scene.data.astype(dt), template.data.astype(dt),
                                                jnp.asarray(level, dt), jnp.asarray(min_gap, dt),
                                                jnp.asarray(min_skew, dt), scene.spacing)
    valid = massive & distinct & (score >= jnp.asarray(min_score, dt))
    reason = jnp.where(~massive, _INVALID, jnp.where(~distinct, _DEGENERATE, _NOT_FOUND))
    return make_match(R, t, score, valid, reason)
