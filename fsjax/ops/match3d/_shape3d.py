"""Shape-based 3-D matching: Steger's similarity on gradient directions, every translation at once.

The 2-D method (:func:`fsjax.ops.shape_locate`; Steger 2001, 2002) scores a pose by how well the
template's edge directions agree with the image's gradient directions at the posed model points.
Here it is taken to 3-D for translations (no rotation search; rotate first, e.g. with
:func:`fsjax.ops.fourier_mellin_z3d`, or search turns about z with :func:`fsjax.ops.shape_rotation_z3d`):

* **Model.** The template is smoothed by a Gaussian of ``sigma`` (the spacing's unit, boundary
  ``"nearest"``) and differentiated by central differences (physical units per axis); its
  model points are the voxels whose gradient magnitude exceeds ``model_contrast`` times the
  template's largest, each with its unit gradient direction ``d_m``.
* **Scene.** The same gradient; each voxel's direction is ``d_s = g / max(|g|, c)`` with
  ``c = min_contrast`` times the scene's largest gradient magnitude (Steger's contrast
  threshold, relative so that a gain of the scene changes nothing): strong edges count as unit
  vectors, weak gradients (noise, flat areas) count proportionally less.
* **Score.** ``s(o) = (1/n) sum_m <d_m, d_s(o + u_m)>`` over the ``n`` model points at offsets
  ``u_m``: a linear correlation, so all placements ``o`` come from 3 FFT correlations (one per
  gradient component, summed in the frequency domain, one inverse FFT).

Which of Steger's measures, and why: the default ``polarity="global"`` reports ``|s(o)|``, the
measure that ignores a *global* contrast reversal (every gradient flipped: a dark object on a
bright background, or ``-scene``) and any gain, with the 3 correlations the signed sum needs.
``polarity="local"`` ignores the sign of each point on its own; ``|<d_m, d_s>|`` is not linear
in ``d_s``, so this variant scores the mean of the *squared* cosine
``(1/n) sum <d_m, d_s>^2 = (1/n) sum_ab (d_m,a d_m,b) (d_s,a d_s,b)`` (6 correlations of the
products' distinct components): polarity-free per point, but it penalises a tilt more
(``cos^2``) and is always >= 0, so noise adds a floor. ``polarity="signed"`` keeps the sign
(``s`` itself): it tells a bright object from a dark one. The best placement is refined by a
Newton step on the 3x3x3 neighbourhood of the score map (:func:`ncc3d`'s peak).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from ..._checks import check_choice, check_range, is_concrete
from ...registry import LinKnob, register
from ...types import Match3D, Volume
from ._shared3d import (
    _INVALID,
    _NOT_FOUND,
    check_pair,
    make_match,
    neighbourhood3,
    newton_peak3,
    xyz_of,
)

__all__ = ["shape_locate3d"]

_REF_STEGER = ("C. Steger, Occlusion, clutter, and illumination invariant object recognition, "
               "Int. Archives of Photogrammetry and Remote Sensing XXXIV(3A), 2002, 345-350")
_REF_STEGER1 = ("C. Steger, Similarity measures for occlusion, clutter, and illumination invariant object "
                "recognition, DAGM 2001, LNCS 2191, 148-154")
_REF_NW = "J. Nocedal, S. J. Wright, Numerical Optimization, 2nd ed., Springer 2006, ch. 3 (Newton's method)"

_POLARITY = ("global", "local", "signed")
_MIN_MODEL_POINTS = 8


def _band(n: int, sigma_vox: float):
    """Static ``(n, n)`` matrices: Gaussian smoothing ``S`` (taps to ``int(3 sigma + 0.5)``, boundary
    ``"nearest"``) and the central difference of it, ``D S`` (one-sided at the ends)."""
    i = np.arange(n)
    if sigma_vox > 0:
        r = max(1, int(3 * sigma_vox + 0.5))
        k = np.arange(-r, r + 1)
        wts = np.exp(-0.5 * (k / sigma_vox) ** 2)
        wts = wts / wts.sum()
        S = np.zeros((n, n))
        for a in range(n):
            np.add.at(S[a], np.clip(a + k, 0, n - 1), wts)
    else:
        S = np.eye(n)
    D = np.zeros((n, n))
    if n > 1:
        D[i, np.clip(i + 1, 0, n - 1)] += 1.0
        D[i, np.clip(i - 1, 0, n - 1)] -= 1.0
        D = D / np.where((i == 0) | (i == n - 1), 1.0, 2.0)[:, None]
    return S, D @ S


def _along(x, m, axis: int):
    return jnp.moveaxis(jnp.tensordot(jnp.asarray(m, x.dtype), x, axes=([1], [axis])), 0, axis)


def gradient3(x, sigma: float, spacing):
    """``(3, D, H, W)`` gradient ``(d/dz, d/dy, d/dx)`` in data units per spacing unit of ``x``
    smoothed by a Gaussian of ``sigma`` (spacing unit; 0 = none; boundary ``"nearest"``): central
    differences inside, one-sided at the borders. Separable products with static band matrices
    (a handful of ops to compile, whatever the support; cost ``O(n)`` per voxel and axis)."""
    (Sz, DSz), (Sy, DSy), (Sx, DSx) = (_band(n, sigma / sp) for n, sp in zip(x.shape, spacing))
    a = _along(x, Sz, 0)
    b = _along(x, Sx, 2)
    gz = _along(_along(b, Sy, 1), DSz, 0) / spacing[0]
    gy = _along(_along(a, Sx, 2), DSy, 1) / spacing[1]
    gx = _along(_along(a, Sy, 1), DSx, 2) / spacing[2]
    return jnp.stack([gz, gy, gx])


def model_of(t, sigma: float, spacing, model_contrast):
    """Model points of a template: mask ``M`` (voxels above ``model_contrast`` of the largest
    gradient magnitude), their unit directions ``(3, d, h, w)`` (0 off the mask), their count."""
    g = gradient3(t, sigma, spacing)
    mag = jnp.sqrt(jnp.sum(g * g, 0))
    M = (mag > model_contrast * jnp.max(mag)) & (jnp.max(mag) > _floor(t, spacing))
    d = jnp.where(M, g / jnp.where(M, mag, 1.0), 0.0)
    return M, d, jnp.sum(M)


def scene_directions(x, sigma: float, spacing, min_contrast):
    """Scene gradient directions ``g / max(|g|, min_contrast * max|g|)`` ``(3, D, H, W)`` (0 where flat)."""
    g = gradient3(x, sigma, spacing)
    mag = jnp.sqrt(jnp.sum(g * g, 0))
    den = jnp.maximum(mag, min_contrast * jnp.max(mag))
    return jnp.where(den > 0, g / jnp.where(den > 0, den, 1.0), 0.0), jnp.max(mag) > _floor(x, spacing)


def _floor(x, spacing):
    """Gradient magnitude below which a volume counts as flat: rounding of its values (``1e3 eps``
    of the largest, per the smallest spacing): a constant volume's smoothed differences are not 0."""
    return 1e3 * jnp.finfo(x.dtype).eps * jnp.max(jnp.abs(x)) / min(spacing)


def check_gradient_match(op: str, scene, template, min_score, sigma, model_contrast, min_contrast, *,
                         sigma_positive: bool = False):
    """The argument checks shared by the gradient-field matchers (``shape_locate3d``,
    ``shape_index_locate3d``); returns ``(template shape, dtype)``."""
    _, T, dt = check_pair(op, scene, template)
    check_range(op, "min_score", min_score, -1.0, 1.0)
    if not is_concrete(sigma):
        raise TypeError(f"{op}: argument 'sigma' must be a static float")
    check_range(op, "sigma", sigma, 0.0, 8.0, lo_open=sigma_positive)
    check_range(op, "model_contrast", model_contrast, 0.0, 1.0, lo_open=True, hi_open=True)
    check_range(op, "min_contrast", min_contrast, 0.0, 1.0, hi_open=True)
    if min(T) < 3:
        raise ValueError(f"{op}: argument 'template' of shape {T} is too small (need >= 3 voxels per axis)")
    return T, dt


@functools.partial(jax.jit, static_argnames=("sigma", "spacing", "polarity"))
def _shape3d_core(x, t, model_contrast, min_contrast, *, sigma: float, spacing, polarity: str):
    D, H, W = x.shape
    d, h, w = t.shape
    M, dm, n = model_of(t, sigma, spacing, model_contrast)
    ds, lit = scene_directions(x, sigma, spacing, min_contrast)

    def F(a):
        return jnp.fft.rfftn(a, s=(D, H, W))

    if polarity == "local":
        pairs = [(a, b) for a in range(3) for b in range(a, 3)]
        acc = sum((1.0 if a == b else 2.0) * F(ds[a] * ds[b]) * jnp.conj(F(dm[a] * dm[b])) for a, b in pairs)
    else:
        acc = sum(F(ds[a]) * jnp.conj(F(dm[a])) for a in range(3))
    S = jnp.fft.irfftn(acc, s=(D, H, W))[: D - d + 1, : H - h + 1, : W - w + 1] / jnp.maximum(n, 1)
    if polarity == "global":
        S = jnp.abs(S)
    idx = jnp.asarray(jnp.unravel_index(jnp.argmax(S), S.shape))
    v, ok = neighbourhood3(S, idx)
    off = idx.astype(x.dtype) + newton_peak3(v, ok)
    return off, S[idx[0], idx[1], idx[2]], (n >= _MIN_MODEL_POINTS) & lit


@register(family="match3d", takes=(Volume, Volume), gives=Match3D, differentiable=False,
          knobs={"min_score": LinKnob(0.2, 0.9)}, refs=[_REF_STEGER, _REF_STEGER1, _REF_NW])
def shape_locate3d(scene: Volume, template: Volume, /, *, min_score: float = 0.75, polarity: str = "global",
                   sigma: float = 1.0, model_contrast: float = 0.3, min_contrast: float = 0.1) -> Match3D:
    """Locate a template in a scene by shape-based matching on 3-D gradient directions (translation).

    Steger's similarity (2001, 2002) in 3-D: the template's model points (gradient magnitude above
    ``model_contrast`` of its largest, after a Gaussian of ``sigma``) with unit gradient
    directions ``d_m``; at a placement ``o`` the score is the mean over model points of
    ``<d_m, d_s(o + u_m)>`` with the scene's direction ``d_s = g / max(|g|, min_contrast max|g|)``,
    for every placement at once by 3 FFT correlations (one per gradient component), refined by
    :func:`ncc3d`'s Newton peak. Edges, not intensities: the score does not change under a gain
    or offset of the scene, and (``polarity="global"``, the default) not under a contrast
    reversal either; an occluded part of the object lowers it by about the hidden fraction of the
    model points. Translation only (turns about z: :func:`shape_rotation_z3d`).

    Args:
      scene: the scene ``(D, H, W)``.
      template: the template ``(d, h, w)``, no larger than the scene, same spacing.
      min_score: ``valid`` needs a best score of at least this (knob ``a``, linear on [0.2, 0.9];
        default 0.75: on the grid's scenes the bunny scores 0.97-0.996 at its place and the same
        scenes without it at most 0.61 (clutter shells align in part); with half of the bunny's
        surface missing it scores 0.62-0.67, is still placed within 1.1 voxel, but is refused at
        this default; ``docs/matching_grid.md``, tests/ops/test_match3d_shape.py).
      polarity: ``"global"`` (default; ``|mean cos|``: invariant to a global contrast reversal),
        ``"local"`` (mean ``cos^2``: each point's polarity free; 6 correlations) or ``"signed"``
        (mean ``cos``: a reversed object scores negative).
      sigma: Gaussian smoothing before the gradients, in the spacing's unit (static; 0 = none).
      model_contrast: model points are template voxels above this fraction of the template's
        largest gradient magnitude (in (0, 1)).
      min_contrast: scene gradients weaker than this fraction of the scene's largest count as
        ``|g| / (min_contrast max|g|)`` of a unit vector (in [0, 1)).

    Returns:
      ``Match3D``: ``t`` = physical ``(x, y, z)`` position of the template's voxel ``[0, 0, 0]``
      (as :func:`ncc3d`), ``R = I``, ``scale = 1``; ``score`` = the similarity at the integer peak
      (in ``[0, 1]`` for ``"global"`` and ``"local"``, ``[-1, 1]`` for ``"signed"``). ``valid``
      False with ``invalid_input`` (fewer than 8 model points, or a scene without any gradient)
      or ``not_found`` (best score below ``min_score``).

    Example:
      A ball of radius 4 centred on voxel (12, 9, 10) ((k, i, j)) of a scene with a weaker, smaller
      ball elsewhere; the template is a ball of radius 4 centred on voxel (7, 7, 7) of a 15^3 box, so
      its voxel [0, 0, 0] belongs on (5, 2, 3), i.e. ``t = (3, 2, 5)`` as (x, y, z). Found within
      0.005 voxel (the other ball's smoothed tail tilts the peak by 0.002), score 1; the scene
      inverted (``1 - scene``) gives the same place and score (in float32):

      >>> import jax.numpy as jnp, fsjax
      >>> k, i, j = jnp.mgrid[0:24, 0:22, 0:22]
      >>> ball = lambda c, r: jnp.clip(r + 0.5 - jnp.sqrt((k - c[0]) ** 2 + (i - c[1]) ** 2 + (j - c[2]) ** 2), 0, 1)
      >>> scene = (ball((12, 9, 10), 4.0) + 0.5 * ball((5, 16, 16), 2.5)).astype(jnp.float32)
      >>> tpl = ball((7, 7, 7), 4.0)[:15, :15, :15].astype(jnp.float32)
      >>> m = fsjax.ops.shape_locate3d(fsjax.Volume(scene), fsjax.Volume(tpl))
      >>> [round(float(v), 2) + 0.0 for v in m.t], round(float(m.score), 4), bool(m.valid), m.t.dtype.name
      ([3.0, 2.0, 5.0], 1.0, True, 'float32')
      >>> mi = fsjax.ops.shape_locate3d(fsjax.Volume(1.0 - scene), fsjax.Volume(tpl))
      >>> [round(float(v), 2) + 0.0 for v in mi.t], round(float(mi.score), 4)
      ([3.0, 2.0, 5.0], 1.0)
    """
    op = "shape_locate3d"
    T, dt = check_gradient_match(op, scene, template, min_score, sigma, model_contrast, min_contrast)
    pol = check_choice(op, "polarity", polarity, _POLARITY)
    off, s, ok = _shape3d_core(scene.data.astype(dt), template.data.astype(dt), jnp.asarray(model_contrast, dt),
                               jnp.asarray(min_contrast, dt), sigma=float(sigma),
                               spacing=tuple(float(v) for v in scene.spacing), polarity=pol)
    valid = ok & (s >= jnp.asarray(min_score, dt))
    reason = jnp.where(ok, _NOT_FOUND, _INVALID)
    return make_match(jnp.eye(3, dtype=dt), xyz_of(off, scene.spacing).astype(dt), s, valid, reason)
