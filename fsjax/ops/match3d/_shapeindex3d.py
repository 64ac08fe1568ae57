"""Curvature matching in 3-D: the template located by its field of shape indices (translation).

The shape index (Koenderink & van Doorn 1992) sorts a surface point by the kind of its bending,
whatever its size: with principal curvatures ``k1 >= k2``,
``S = (2/pi) atan2(k1 + k2, k1 - k2)`` in ``[-1, 1]``: a convex cap ``1``, a ridge (cylinder)
``0.5``, a symmetric saddle ``0``, a rut ``-0.5``, a cup ``-1`` (the ``atan2`` form of
:func:`fsjax.ops.curvature`, exact at umbilics). Here every voxel of a volume gets the shape
index of the iso-surface through it:

* **Curvatures of an iso-surface** (Thirion & Gourdon 1995): with the gradient ``g`` and Hessian
  ``H`` of the volume smoothed by a Gaussian of ``sigma``, ``P = I - n n^T`` (``n = g/|g|``), the
  matrix ``M = -P H P / |g|`` has eigenvalues ``0`` (along ``n``) and ``k1, k2``; so
  ``k1 + k2 = tr M`` and ``k1 - k2 = sqrt(2 tr(M^2) - (tr M)^2)``, no eigen-solver needed. Sign:
  a bright solid ball is convex (``S = 1`` on its boundary); a dark one is a cup (``S = -1``).
  On a thin bright shell (a surface splatted on a grid) the two flanks of the shell are
  iso-surfaces of opposite orientation, so the outer flank of a sphere reads ``1`` and the
  inner ``-1``: the field differs from the solid's, but alike in scene and template.
* **Code.** The shape index is coded into ``bins`` tent functions over ``[-1, 1]`` (``e_b(S)``,
  summing to 1), scaled to unit length (``e / |e|``), so the codes of two voxels have dot product
  1 exactly when their shape indices are equal, less as they part, 0 beyond one bin width. Model points are the template voxels whose gradient magnitude exceeds
  ``model_contrast`` of its largest; scene voxels are weighted like Steger's directions
  (:func:`shape_locate3d`): ``w = |g| / max(|g|, min_contrast max|g|)``, so strong surfaces count
  fully and noise little, whatever the gain.
* **Score** of a placement ``o``: ``(1/n) sum_m w(o + u_m) <e(S_m), e(S(o + u_m))>``, the
  mean over the ``n`` model points of how far the scene's shape index at the same place agrees
  with the template's (1: everywhere a strong surface of the same shape index). Linear in the
  scene's code, so every placement comes from ``bins`` FFT correlations; the best one is refined
  by :func:`ncc3d`'s Newton peak on the 3x3x3 score neighbourhood.

What it is for: the shape index does not change under a gain or an offset of the intensities nor
under a scale of the object (curvature ratios), and it tells a sphere (``1`` everywhere) or a
plane from a free-form object, which intensity correlation does only through the intensities.
It needs the iso-surfaces' second derivatives, so it is noisier than gradient directions
(tests/ops/test_match3d_curv.py, docs/matching_grid.md).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from ..._checks import check_static_int
from ...registry import LinKnob, register
from ...types import Match3D, Volume
from ._shape3d import _floor, check_gradient_match, gradient3
from ._shared3d import (
    _INVALID,
    _NOT_FOUND,
    make_match,
    neighbourhood3,
    newton_peak3,
    xyz_of,
)

__all__ = ["shape_index_locate3d"]

_REF_KVD = ("J. J. Koenderink, A. J. van Doorn, Surface shape and curvature scales, Image and Vision Computing "
            "10(8), 1992, 557-564")
_REF_TG = ("J.-P. Thirion, A. Gourdon, Computing the differential characteristics of isointensity surfaces, "
           "Computer Vision and Image Understanding 61(2), 1995, 190-202")
_REF_STEGER = ("C. Steger, Occlusion, clutter, and illumination invariant object recognition, "
               "Int. Archives of Photogrammetry and Remote Sensing XXXIV(3A), 2002, 345-350")

_MIN_MODEL_POINTS = 8


def shape_index_field(x, sigma: float, spacing):
    """``(S, mag)``: the shape index of the iso-surface through each voxel of ``x`` (in ``[-1, 1]``;
    0 where the surface is locally flat or the gradient vanishes) and the gradient magnitude, after a
    Gaussian of ``sigma`` (spacing unit). Gradient by :func:`gradient3`; Hessian by central
    differences of that gradient (symmetrised)."""
    g = gradient3(x, sigma, spacing)
    Hr = jnp.stack([gradient3(g[a], 0.0, spacing) for a in range(3)])  # Hr[a, b] = d_b g_a
    H = 0.5 * (Hr + jnp.swapaxes(Hr, 0, 1))
    mag = jnp.sqrt(jnp.sum(g * g, 0))
    ok = mag > _floor(x, spacing)
    n = jnp.where(ok, g / jnp.where(ok, mag, 1.0), 0.0)
    eye = jnp.eye(3, dtype=x.dtype)[:, :, None, None, None]
    P = eye - n[:, None] * n[None, :]
    M = -jnp.einsum("ab...,bc...,cd...->ad...", P, H, P) / jnp.where(ok, mag, 1.0)
    tr = jnp.einsum("aa...->...", M)
    tr2 = jnp.einsum("ab...,ba...->...", M, M)
    d2 = jnp.maximum(2.0 * tr2 - tr * tr, 0.0)
    diff = jnp.where(d2 > 0, jnp.sqrt(jnp.where(d2 > 0, d2, 1.0)), 0.0)
    flat = (jnp.abs(tr) + diff) <= 0
    S = jnp.where(ok & ~flat, (2.0 / jnp.pi) * jnp.arctan2(tr, jnp.where(flat, 1.0, diff)), 0.0)
    return S, mag


def shape_index_code(S, bins: int):
    """``(bins, ...)`` tent code of shape indices over ``[-1, 1]`` (centres ``-1 + 2b/(bins-1)``; sums to 1)."""
    c = jnp.linspace(-1.0, 1.0, bins, dtype=S.dtype)
    h = 2.0 / (bins - 1)
    return jnp.maximum(0.0, 1.0 - jnp.abs(S[None] - c.reshape((bins,) + (1,) * S.ndim)) / h)


def _unit_code(S, bins: int):
    """The tent code scaled to unit length per voxel: two voxels' codes have dot product 1 exactly when
    their shape indices are equal, less the further apart they are (0 beyond one bin width)."""
    e = shape_index_code(S, bins)
    return e / jnp.sqrt(jnp.sum(e * e, 0))


@functools.partial(jax.jit, static_argnames=("sigma", "spacing", "bins"))
def _si3d_core(x, t, model_contrast, min_contrast, *, sigma: float, spacing, bins: int):
    D, H, W = x.shape
    d, h, w = t.shape
    St, mt = shape_index_field(t, sigma, spacing)
    M = (mt > model_contrast * jnp.max(mt)) & (jnp.max(mt) > _floor(t, spacing))
    n = jnp.sum(M)
    et = jnp.where(M[None], _unit_code(St, bins), 0.0)
    Ss, ms = shape_index_field(x, sigma, spacing)
    den = jnp.maximum(ms, min_contrast * jnp.max(ms))
    ws = jnp.where(den > 0, ms / jnp.where(den > 0, den, 1.0), 0.0)
    es = ws[None] * _unit_code(Ss, bins)
    acc = sum(jnp.fft.rfftn(es[b], s=(D, H, W)) * jnp.conj(jnp.fft.rfftn(et[b], s=(D, H, W))) for b in range(bins))
    Smap = jnp.fft.irfftn(acc, s=(D, H, W))[: D - d + 1, : H - h + 1, : W - w + 1] / jnp.maximum(n, 1)
    idx = jnp.asarray(jnp.unravel_index(jnp.argmax(Smap), Smap.shape))
    v, ok = neighbourhood3(Smap, idx)
    off = idx.astype(x.dtype) + newton_peak3(v, ok)
    return off, Smap[idx[0], idx[1], idx[2]], (n >= _MIN_MODEL_POINTS) & (jnp.max(ms) > _floor(x, spacing))


@register(family="match3d", takes=(Volume, Volume), gives=Match3D, differentiable=False,
          knobs={"min_score": LinKnob(0.2, 0.9)}, refs=[_REF_KVD, _REF_TG, _REF_STEGER])
def shape_index_locate3d(scene: Volume, template: Volume, /, *, min_score: float = 0.6, sigma: float = 1.0,
                         bins: int = 6, model_contrast: float = 0.3, min_contrast: float = 0.1) -> Match3D:
    """Locate a template in a scene by its shape-index field (curvature matching; translation).

    Every voxel gets the Koenderink-van Doorn shape index of the iso-surface through it (principal
    curvatures from the gradient and Hessian after a Gaussian of ``sigma``, Thirion & Gourdon),
    coded into ``bins`` tent functions; the score of a placement is the mean over the template's
    model points (gradient magnitude above ``model_contrast`` of its largest) of the agreement of
    the codes, each scene voxel weighted by its gradient strength (``|g| / max(|g|, min_contrast
    max|g|)``); all placements by ``bins`` FFT correlations, the best refined by :func:`ncc3d`'s
    Newton peak. Invariant to a gain and an offset of the scene; not to a contrast reversal (it
    turns caps into cups). Translation only (turns about z: :func:`shape_index_rotation_z3d`).

    Args:
      scene: the scene ``(D, H, W)``.
      template: the template ``(d, h, w)``, no larger than the scene, same spacing, at least 3
        voxels per axis.
      min_score: ``valid`` needs a best score of at least this (knob ``a``, linear on [0.2, 0.9];
        default 0.6: on the grid's scenes the bunny scores 0.86-0.95 at its place and the same
        scenes without it at most 0.47, seeds 0-2 of the voxel, points, mesh and Gaussians rows;
        docs/matching_grid.md).
      sigma: Gaussian smoothing before the derivatives, spacing unit (static; in (0, 8]).
      bins: number of tent bins of the shape index over [-1, 1] (static int in [3, 16]).
      model_contrast: model points are template voxels above this fraction of the template's
        largest gradient magnitude (in (0, 1)).
      min_contrast: scene gradients weaker than this fraction of the scene's largest weigh
        ``|g| / (min_contrast max|g|)`` (in [0, 1)).

    Returns:
      ``Match3D``: ``t`` = physical ``(x, y, z)`` of the template's voxel ``[0, 0, 0]`` (as
      :func:`ncc3d`), ``R = I``, ``scale = 1``; ``score`` in ``[0, 1]`` at the integer peak.
      ``valid`` False with ``invalid_input`` (fewer than 8 model points, or a flat scene) or
      ``not_found`` (best score below ``min_score``).

    Example:
      A solid ball (shape index 1 all round) and a cube of the same size (flat faces, ridges
      along its edges) in one scene; the template is the ball centred on voxel (7, 7, 7) of a
      15^3 box, the scene's ball is centred on voxel (20, 9, 10) ((k, i, j)), so its voxel
      [0, 0, 0] belongs on (13, 2, 3), ``t = (3, 2, 13)`` as (x, y, z). Found there (score 1); a
      template of the cube finds the cube, centred on voxel (8, 18, 16), i.e. ``t = (9, 11, 1)``:

      >>> import jax.numpy as jnp, fsjax
      >>> k, i, j = jnp.mgrid[0:30, 0:28, 0:26]
      >>> def ball(c, r):
      ...     return jnp.clip(r + 0.5 - jnp.sqrt((k - c[0]) ** 2 + (i - c[1]) ** 2 + (j - c[2]) ** 2), 0, 1)
      >>> def cube(c, r):
      ...     return jnp.clip(r + 0.5 - jnp.maximum(jnp.maximum(abs(k - c[0]), abs(i - c[1])), abs(j - c[2])), 0, 1)
      >>> scene = fsjax.Volume(ball((20, 9, 10), 4.0) + cube((8, 18, 16), 3.5))
      >>> m = fsjax.ops.shape_index_locate3d(scene, fsjax.Volume(ball((7, 7, 7), 4.0)[:15, :15, :15]))
      >>> [round(float(v), 2) + 0.0 for v in m.t], round(float(m.score), 2), bool(m.valid)
      ([3.0, 2.0, 13.0], 1.0, True)
      >>> mc = fsjax.ops.shape_index_locate3d(scene, fsjax.Volume(cube((7, 7, 7), 3.5)[:15, :15, :15]))
      >>> [round(float(v), 2) + 0.0 for v in mc.t], bool(mc.valid)
      ([9.0, 11.0, 1.0], True)
    """
    op = "shape_index_locate3d"
    T, dt = check_gradient_match(op, scene, template, min_score, sigma, model_contrast, min_contrast,
                                 sigma_positive=True)
    nb = check_static_int(op, "bins", bins, lo=3, hi=16)
    off, s, ok = _si3d_core(scene.data.astype(dt), template.data.astype(dt), jnp.asarray(model_contrast, dt),
                            jnp.asarray(min_contrast, dt), sigma=float(sigma),
                            spacing=tuple(float(v) for v in scene.spacing), bins=nb)
    valid = ok & (s >= jnp.asarray(min_score, dt))
    reason = jnp.where(ok, _NOT_FOUND, _INVALID)
    return make_match(jnp.eye(3, dtype=dt), xyz_of(off, scene.spacing).astype(dt), s, valid, reason)
