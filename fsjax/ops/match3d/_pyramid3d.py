"""Coarse-to-fine 3-D normalised cross-correlation: an image pyramid over :func:`fsjax.ops.ncc3d`.

The scene and the template are reduced ``levels`` times by 2 along every axis (a 4-tap binomial
``[1, 3, 3, 1] / 8`` low-pass, then every second voxel: coarse voxel ``k`` is centred on fine
``2k + 1/2``, as a 2x2x2 block mean would be, with edge voxels repeated; a trailing odd voxel is
dropped). Burt and Adelson's pyramid, with the binomial kernel they recommend for the reduce step.

* **Top level**: the exhaustive NCC map (the one of :func:`ncc3d`: FFT numerator, box-sum local
  energy), its local maxima (3x3x3) and the ``top_k`` highest of them as candidates.
* **Each finer level**: a candidate at coarse offset ``o`` (template voxel ``[0, 0, 0]`` on scene
  voxel ``o``) maps to ``2 o``; the NCC map (the same formula) of the template over the scene region
  that holds every placement within ``+-window`` voxels of it (shifted inward at the scene's border)
  gives ``(2 window + 1)^3`` scores, one FFT of a region the template's size plus ``2 window``, and
  the candidate moves to its best one. All ``top_k`` candidates are carried down (a clutter
  peak that outscores the object at the coarse level does not decide the answer).
* **Finest level**: the best candidate's 3x3x3 NCC neighbourhood and the full-Hessian Newton step of
  :func:`ncc3d` (:func:`fsjax.ops.match3d._shared3d.newton_peak3`) give the sub-voxel offset.

Cost: the top level's FFT on ``N / 8^levels`` voxels plus, per finer level, ``top_k`` FFTs of regions
the template's size plus ``2 window``, instead of an FFT of the whole scene. Where the pyramid can miss: an
object whose coarse NCC peak is not among the ``top_k`` coarse maxima, or whose coarse peak sits
more than ``window`` fine voxels (half as many coarse ones) from its true place after doubling.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from jax import lax

from ..._checks import check_range, check_static_int
from ...registry import register
from ...types import Match3D, Volume
from ..matching._correlation import _template_stats
from ._fft3d import _ncc3d_map, mirror_chance
from ._shared3d import (
    _INVALID,
    _NOT_FOUND,
    check_pair,
    make_match,
    neighbourhood3,
    newton_peak3,
    xyz_of,
)

__all__ = ["ncc3d_pyramid"]

_REF_BA = ("P. J. Burt, E. H. Adelson, The Laplacian pyramid as a compact image code, IEEE Trans. "
           "Communications 31(4), 1983, 532-540")
_REF_LEWIS = "J. P. Lewis, Fast normalized cross-correlation, Vision Interface 1995, 120-123"
_REF_NW = "J. Nocedal, S. J. Wright, Numerical Optimization, 2nd ed., Springer 2006, ch. 3 (Newton's method)"

# the coarsest template must keep at least this many voxels along every axis (levels="auto" picks the
# most levels, at most _AUTO_MAX, that keep _AUTO_MIN)
_MIN_TOP = 4
_AUTO_MIN, _AUTO_MAX = 8, 3


def _reduce(x):
    """One pyramid step: ``[1, 3, 3, 1] / 8`` along each axis, sampled at ``2k + 1/2``."""
    for ax in range(3):
        n = x.shape[ax] // 2
        pad = [(0, 0)] * 3
        pad[ax] = (1, 1)
        p = jnp.pad(x, pad, mode="edge")

        def sl(s, n=n, ax=ax, p=p):
            idx = [slice(None)] * 3
            idx[ax] = slice(s, s + 2 * n, 2)
            return p[tuple(idx)]

        x = (sl(0) + 3 * sl(1) + 3 * sl(2) + sl(3)) / 8
    return x


def _window_ncc(x, t, start, size):
    """The NCC map of template ``t`` over the region of ``x`` of shape ``size`` starting at integer
    ``start (3,)`` (clipped into the scene): every placement within it, as :func:`ncc3d`'s map; and the
    start actually used."""
    start = jnp.clip(start, 0, jnp.asarray(x.shape) - jnp.asarray(size))
    S, _ = _ncc3d_map(lax.dynamic_slice(x, start, size), t)
    return S, start


@functools.partial(jax.jit, static_argnames=("levels", "top_k", "window"))
def _pyramid_core(x, t, *, levels, top_k, window):
    xs, ts = [x], [t]
    for _ in range(levels):
        xs.append(_reduce(xs[-1]))
        ts.append(_reduce(ts[-1]))
    # top level: exhaustive NCC, top_k local maxima
    S, _ = _ncc3d_map(xs[-1], ts[-1])
    mx = lax.reduce_window(S, -jnp.inf, lax.max, (3, 3, 3), (1, 1, 1), "SAME")
    peaks = jnp.where(S >= mx, S, -jnp.inf).reshape(-1)
    sc, flat = lax.top_k(peaks, min(top_k, peaks.size))
    cand = jnp.stack(jnp.unravel_index(flat, S.shape), -1).astype(jnp.int32)  # (k, 3)
    for lv in range(levels - 1, -1, -1):
        # each candidate's region: the template plus +-window voxels around its doubled offset
        size = tuple(min(a + 2 * window, b) for a, b in zip(ts[lv].shape, xs[lv].shape))
        maps, starts = jax.vmap(lambda c, lv=lv, size=size: _window_ncc(xs[lv], ts[lv], 2 * c - window, size))(cand)
        fl = maps.reshape(maps.shape[0], -1)
        best = jnp.argmax(fl, axis=1)
        sc = jnp.max(fl, axis=1)
        cand = starts + jnp.stack(jnp.unravel_index(best, maps.shape[1:]), -1).astype(jnp.int32)
    # finest level: the best candidate, its 3x3x3 neighbourhood, the Newton step
    p = cand[jnp.argmax(sc)]
    size = tuple(min(a + 2, b) for a, b in zip(t.shape, x.shape))
    S, start = _window_ncc(x, t, p - 1, size)
    tflat = _template_stats(t)[2]  # the full-resolution template decides flatness
    v, _ = neighbourhood3(S, p - start)
    ok = (p >= 1) & (p <= jnp.asarray(x.shape) - jnp.asarray(t.shape) - 1)
    off = p.astype(x.dtype) + newton_peak3(v, ok)
    s = S[tuple(p - start)]
    return off, s, tflat, mirror_chance(x, t, p, s)[0]


def _auto_levels(T) -> int:
    n = 0
    while n < _AUTO_MAX and min(T) >> (n + 1) >= _AUTO_MIN:
        n += 1
    return n


@register(family="match3d", takes=(Volume, Volume), gives=Match3D, differentiable=False,
          refs=[_REF_BA, _REF_LEWIS, _REF_NW])
def ncc3d_pyramid(scene: Volume, template: Volume, /, *, levels: int | None = None, top_k: int = 4,
                  window: int = 2, min_score: float = 0.7, max_chance: float = 0.01) -> Match3D:
    """Locate a template volume in a scene by coarse-to-fine 3-D NCC (a pyramid over :func:`ncc3d`).

    Both volumes are reduced ``levels`` times by 2 (binomial low-pass; Burt and Adelson 1983); the
    exhaustive NCC (Lewis 1995) runs on the coarsest level, its ``top_k`` local maxima are carried
    down, each refined at every finer level by the NCC in a ``+-window`` voxel box around its
    doubled position, and the best is refined to sub-voxel by the full-Hessian Newton step of
    :func:`ncc3d`. The score is the same normalised correlation as :func:`ncc3d`'s (gain and offset
    invariant, in ``[-1, 1]``), evaluated directly at the chosen placement.

    Measured (``docs/benchmarks_ncc_pyramid.md``, ``docs/matching_grid.md``): the same placement as
    :func:`ncc3d` on every row of the matching grid and on 64^3 and 128^3 bunny scenes; at 128^3 it
    takes 15-25 % of :func:`ncc3d`'s time per call (its compile is 2-4x longer). With the coarsest
    template only 4 voxels across, ``top_k=1`` missed the bunny on 3 of 3 scenes (reported
    ``valid=False``), ``top_k=4`` found it on all. A candidate that wins at the coarse level but is
    another object is returned if its full-resolution score reaches ``min_score`` and it passes
    :func:`ncc3d`'s mirror test: the carried candidates and the test lower that risk, they do not
    remove it.

    Args:
      scene: the scene ``(D, H, W)``.
      template: the template ``(d, h, w)``, no larger than the scene in any axis, same spacing.
      levels: reductions by 2 (static int >= 0; 0 is :func:`ncc3d`'s exhaustive search with this
        op's peak). Default ``None``: the most levels (at most 3) that keep the coarsest template at
        least 8 voxels along every axis. An explicit ``levels`` that leaves the coarsest template
        smaller than 4 voxels along an axis raises ``ValueError``.
      top_k: coarse candidates carried down (static int in [1, 64]; default 4).
      window: the search half-width at each finer level, fine voxels (static int in [1, 4]; default 2,
        i.e. one coarse voxel either side of the doubled position).
      min_score: ``valid`` needs a final score of at least this (default 0.7, as :func:`ncc3d`).
      max_chance: ``valid`` needs the final placement to pass :func:`ncc3d`'s mirror test (the box
        correlates with the template better than with each of its mirror images) at this p-value
        (default 0.01, as :func:`ncc3d`; 1 turns the test off).

    Returns:
      ``Match3D`` in :func:`ncc3d`'s convention: ``t`` = the physical ``(x, y, z)`` position of the
      template's voxel ``[0, 0, 0]`` in the scene, ``R = I``, ``scale = 1``, ``score`` = the NCC at
      the integer placement. ``valid`` False (``invalid_input``) for a flat template, (``not_found``)
      below ``min_score`` or not specific (the mirror test above ``max_chance``).

    Example:
      A smooth blob cut out of a 32^3 scene, found through two pyramid levels at the place it was cut
      (within 0.005 voxel; the same answer as the exhaustive :func:`ncc3d`):

      >>> import jax.numpy as jnp, fsjax
      >>> k, i, j = jnp.mgrid[0:32, 0:32, 0:32]
      >>> scene = (jnp.exp(-((k - 14.0) ** 2 + (i - 17.0) ** 2 / 2 + (j - 12.0) ** 2 / 3) / 8.0)
      ...          + 0.02 * jnp.sin(j + 2 * i - k))
      >>> tpl = fsjax.Volume(scene[6:22, 9:25, 4:20])
      >>> m = fsjax.ops.ncc3d_pyramid(fsjax.Volume(scene), tpl, levels=2)
      >>> [round(float(v), 2) for v in m.t], round(float(m.score), 6), bool(m.valid)
      ([4.0, 9.0, 6.0], 1.0, True)
    """
    op = "ncc3d_pyramid"
    _, T, dt = check_pair(op, scene, template)
    if levels is None:
        lv = _auto_levels(T)
    else:
        lv = check_static_int(op, "levels", levels, lo=0, hi=6)
        if min(T) >> lv < _MIN_TOP:
            raise ValueError(f"{op}: argument 'levels' must leave the coarsest template at least {_MIN_TOP} voxels "
                             f"along every axis; a template of shape {T} allows at most "
                             f"{max(0, (min(T) // _MIN_TOP).bit_length() - 1)} levels, got {lv}")
    k = check_static_int(op, "top_k", top_k, lo=1, hi=64)
    w = check_static_int(op, "window", window, lo=1, hi=4)
    check_range(op, "min_score", min_score, -1.0, 1.0)
    check_range(op, "max_chance", max_chance, 0.0, 1.0)
    off, s, tflat, chance = _pyramid_core(scene.data.astype(dt), template.data.astype(dt), levels=lv, top_k=k, window=w)
    valid = jnp.logical_not(tflat) & (s >= jnp.asarray(min_score, dt)) & (chance <= jnp.asarray(max_chance, dt))
    reason = jnp.where(tflat, _INVALID, _NOT_FOUND)
    return make_match(jnp.eye(3, dtype=dt), xyz_of(off, scene.spacing).astype(dt), s, valid, reason)
