"""Thresholds: global histogram methods, local (adaptive) methods, hysteresis
(``Image -> Region``, ``Image -> Feature`` for levels, ``Image -> Labels`` for
multi-level Otsu).

Conventions:

* Polarity: every ``Image -> Region`` op except :func:`threshold` and
  :func:`dyn_threshold` (which say otherwise) marks the *bright* side,
  ``x > T``, strictly greater, like scikit-image's ``image > threshold``. For
  dark objects take the complement.
* Histograms: ``nbins`` (static, default 256) equal bins spanning the image's
  own ``[min, max]``, with NumPy's edges (``np.linspace(min, max, nbins + 1)``;
  the last bin is closed) and scikit-image's bin centres ``(e[i] + e[i+1]) / 2``.
  A histogram level is always a bin centre. Levels are piecewise constant in
  the image, so these ops are declared not differentiable.
* Failing closed: an image whose histogram is too degenerate for the method
  (a constant image for every histogram method; fewer occupied bins than
  ``classes`` for multi-level Otsu; Li without convergence) gives a NaN level,
  an empty ``Region`` (``x > NaN`` is False everywhere) and, for
  :func:`multi_otsu`, an all-background ``Labels`` with ``count = 0``. It never
  returns an arbitrary partition. (scikit-image returns the constant value as
  the level of a constant image; we deliberately do not.)
* Local windows: square ``(2 radius + 1)^2`` boxes (``radius`` in pixels; the
  scikit-image ``window_size``/``block_size`` is ``2 radius + 1``); boundary by
  SciPy mode names, default ``"reflect"`` (scikit-image's Sauvola/Niblack pad
  with NumPy ``"reflect"``, which is SciPy's ``"mirror"``). A traced ``radius``
  (a knob) uses the static ``max_radius`` support with zero weights outside
  the window; the extra taps add exact zeros, so the result is bit-identical to
  the concrete-radius call. A traced radius above ``max_radius`` is clipped to it.
* Local standard deviation is ``sqrt(max(E[x^2] - E[x]^2, 0))`` over the window.
* Hysteresis propagates through 8-connected (default) or 4-connected
  neighbours with a ``lax.while_loop`` to the fixed point.
"""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np
from jax import lax

from ..registry import IntKnob, LinKnob, register
from ..types import Feature, Image, Labels, Region, is_concrete
from ._common import (
    check_choice,
    check_mode,
    check_positive,
    check_range,
    check_static_int,
    correlate1d,
)

__all__ = [
    "threshold",
    "otsu",
    "otsu_level",
    "multi_otsu",
    "multi_otsu_levels",
    "triangle",
    "triangle_level",
    "yen",
    "yen_level",
    "li",
    "li_level",
    "isodata",
    "isodata_level",
    "local_mean",
    "sauvola",
    "niblack",
    "hysteresis",
    "dyn_threshold",
]

_SEZGIN = ("M. Sezgin, B. Sankur, Survey over image thresholding techniques and quantitative "
           "performance evaluation, J. Electronic Imaging 13(1), 2004")


# ---------------------------------------------------------------------------
# Histogram helpers
# ---------------------------------------------------------------------------


def _check_nbins(op: str, nbins, hi: int = 65536) -> int:
    return check_static_int(op, "nbins", nbins, 2, hi)


def _histogram(x, nbins: int):
    """Counts over ``[min, max]`` in ``nbins`` equal bins, NumPy's bin edges.

    Returns ``(counts, centres, ok)``; ``ok`` is False for a constant image.
    """
    v = x.reshape(-1)
    dt = v.dtype
    lo, hi = jnp.min(v), jnp.max(v)
    span = hi - lo
    ok = span > 0
    safe = jnp.where(ok, span, jnp.ones((), dt))
    top = jnp.where(ok, hi, lo + safe)
    step = safe / nbins
    edges = jnp.arange(nbins + 1, dtype=dt) * step + lo
    edges = edges.at[-1].set(top)
    idx = jnp.floor((v - lo) / safe * nbins).astype(jnp.int32)
    idx = jnp.clip(idx, 0, nbins - 1)
    # the same +-1 correction NumPy applies, so a value on an edge lands in its bin
    idx = idx - (v < edges[idx]).astype(jnp.int32)
    idx = idx + ((v >= edges[idx + 1]) & (idx != nbins - 1)).astype(jnp.int32)
    idx = jnp.clip(idx, 0, nbins - 1)
    counts = jnp.zeros((nbins,), dt).at[idx].add(1.0)
    centres = (edges[:-1] + edges[1:]) / 2
    return counts, centres, ok


def _rcumsum(a):
    return jnp.cumsum(a[::-1])[::-1]


def _safe_div(num, den):
    ok = den != 0
    return jnp.where(ok, num / jnp.where(ok, den, 1.0), 0.0), ok


def _first_argmax(score, valid):
    """Index of the first maximum of ``score`` among ``valid`` entries."""
    s = jnp.where(valid, score, -jnp.inf)
    return jnp.argmax(s)


def _otsu_from_hist(h, c, ok):
    w1 = jnp.cumsum(h)
    w2 = _rcumsum(h)
    hc = h * c
    m1, _ = _safe_div(jnp.cumsum(hc), w1)
    m2, _ = _safe_div(_rcumsum(hc), w2)
    var12 = w1[:-1] * w2[1:] * (m1[:-1] - m2[1:]) ** 2
    t = _first_argmax(var12, jnp.ones_like(var12, dtype=bool))
    return jnp.where(ok, c[t], jnp.nan)


def _multi_otsu_from_hist(h, c, classes: int):
    """Exact maximiser of the between-class variance over ``classes - 1`` bin thresholds.

    Dynamic programming over the segment score ``S^2 / W`` (first moment squared
    over mass), which is the between-class variance up to a constant. Among exact
    ties (thresholds moved across empty bins) the lowest indices win.
    """
    n = h.shape[0]
    W = jnp.concatenate([jnp.zeros((1,), h.dtype), jnp.cumsum(h)])
    S = jnp.concatenate([jnp.zeros((1,), h.dtype), jnp.cumsum(h * c)])
    i = jnp.arange(n)[:, None]
    j = jnp.arange(n)[None, :]
    segW = W[1:][None, :] - W[:-1][:, None]  # bins i..j
    segS = S[1:][None, :] - S[:-1][:, None]
    score, _ = _safe_div(segS * segS, segW)
    F = jnp.where(i <= j, score, -jnp.inf)
    G = jnp.concatenate([F[1:], jnp.full((1, n), -jnp.inf, h.dtype)])  # G[t, j] = F[t+1, j]
    best = F[0]
    args = []
    for _ in range(classes - 1):
        M = best[:, None] + G
        args.append(jnp.argmax(M, axis=0))
        best = jnp.max(M, axis=0)
    ts = []
    t = jnp.asarray(n - 1)
    for a in reversed(args):
        t = a[t]
        ts.append(t)
    ts = jnp.stack(ts[::-1])
    ok = jnp.sum(h > 0) >= classes
    return jnp.where(ok, c[ts], jnp.nan)


def _triangle_from_hist(h, c, ok):
    n = h.shape[0]
    ar = jnp.arange(n)
    peak = jnp.argmax(h)
    ph = h[peak]
    nz = h > 0
    low = jnp.argmax(nz)
    high = n - 1 - jnp.argmax(nz[::-1])
    flip = (peak - low) < (high - peak)
    hh = jnp.where(flip, h[::-1], h)
    low_ = jnp.where(flip, n - high - 1, low)
    peak_ = jnp.where(flip, n - peak - 1, peak)
    width = (peak_ - low_).astype(h.dtype)
    norm = jnp.sqrt(ph * ph + width * width)
    norm = jnp.where(norm > 0, norm, 1.0)
    x = (ar - low_).astype(h.dtype)
    dist = (ph / norm) * x - (width / norm) * hh
    a = _first_argmax(dist, (ar >= low_) & (ar < peak_))
    a = jnp.where(flip, n - a - 1, a)
    return jnp.where(ok & (width > 0), c[a], jnp.nan)


def _yen_from_hist(h, c, ok):
    p = h / jnp.sum(h)
    P1 = jnp.cumsum(p)
    P1sq = jnp.cumsum(p * p)
    P2sq = _rcumsum(p * p)
    den = P1sq[:-1] * P2sq[1:]
    inv, good = _safe_div(jnp.ones_like(den), den)
    num = (P1[:-1] * (1.0 - P1[:-1])) ** 2
    arg = inv * num
    crit = jnp.where(good & (arg > 0), jnp.log(jnp.where(arg > 0, arg, 1.0)), -jnp.inf)
    t = jnp.argmax(crit)
    return jnp.where(ok, c[t], jnp.nan)


def _isodata_from_hist(h, c, ok):
    cl = jnp.cumsum(h)
    ch = cl[-1] - cl
    isum = jnp.cumsum(h * c)
    lo_mean, _ = _safe_div(isum[:-1], cl[:-1])
    hi_mean, good = _safe_div(isum[-1] - isum[:-1], ch[:-1])
    mid = (lo_mean + hi_mean) / 2
    width = c[1] - c[0]
    d = mid - c[:-1]
    hit = good & (d >= 0) & (d < width)
    t = jnp.argmax(hit)
    return jnp.where(ok & jnp.any(hit), c[t], jnp.nan)


def _level_feature(level) -> Feature:
    return Feature(level, unit="grey")


def _region_above(img: Image, level) -> Region:
    return Region(img.data > level.astype(img.data.dtype))


# ---------------------------------------------------------------------------
# Fixed threshold
# ---------------------------------------------------------------------------


@register(family="threshold", takes=Image, gives=Region,
          knobs={"lo": LinKnob(0.0, 1.0), "hi": LinKnob(0.0, 1.0)},
          refs=["HALCON operator reference: threshold"])
def threshold(img: Image, /, *, lo: float = 0.5, hi: float = math.inf) -> Region:
    """Fixed grey-value band: the pixels with ``lo <= x <= hi`` (both ends inclusive).

    For a single level leave ``hi`` at its default ``+inf`` (``x >= lo``). An empty
    band (``lo > hi``) gives an empty region.

    Args:
      img: input image ``(H, W)``.
      lo: lower bound, inclusive (knob ``a``, linear on [0, 1]).
      hi: upper bound, inclusive; ``inf`` = no upper bound (knob ``b``, linear on [0, 1]).

    Returns:
      ``Region`` ``(H, W)``, True where ``lo <= x <= hi``.

    Matches ``(x >= lo) & (x <= hi)`` in NumPy exactly (HALCON ``threshold``).

    Example:
      A 4 x 4 ramp ``0, 1/15, ..., 1`` has exactly the six values ``5/15..10/15``
      in the band ``[1/3, 2/3]``:

      >>> import jax.numpy as jnp, fsjax
      >>> img = fsjax.Image(jnp.arange(16.0).reshape(4, 4) / 15)
      >>> int(fsjax.ops.threshold(img, lo=5 / 15, hi=10 / 15).data.sum())
      6
    """
    for name, v in (("lo", lo), ("hi", hi)):
        if is_concrete(v) and np.any(np.isnan(np.asarray(v, dtype=float))):
            raise ValueError(f"threshold: argument {name!r} must not be NaN, got {v}")
    x = img.data
    return Region((x >= jnp.asarray(lo, x.dtype)) & (x <= jnp.asarray(hi, x.dtype)))


# ---------------------------------------------------------------------------
# Otsu
# ---------------------------------------------------------------------------


_OTSU = "N. Otsu, A threshold selection method from gray-level histograms, IEEE Trans. SMC 9(1), 1979"


@register(family="threshold", takes=Image, gives=Feature, refs=[_OTSU])
def otsu_level(img: Image, /, *, nbins: int = 256) -> Feature:
    """Otsu's level: the bin centre that maximises the between-class variance.

    With class masses ``w1(t)``, ``w2(t)`` and means ``m1(t)``, ``m2(t)`` of the
    bins ``<= t`` and ``> t``, the level is the centre of the first bin ``t``
    maximising ``w1 w2 (m1 - m2)^2``; foreground is ``x > level``.

    Args:
      img: input image ``(H, W)``.
      nbins: number of histogram bins over ``[min, max]`` (static int, default 256).

    Returns:
      ``Feature`` (unit ``"grey"``): the level; NaN for a constant image.

    Matches ``skimage.filters.threshold_otsu(x, nbins)`` exactly (same bin,
    checked on camera and coins); deliberately returns NaN instead of the value
    of a constant image.

    Example:
      Two grey values 0.2 and 0.8: every split between them is optimal and the
      lowest one wins, the centre of bin 0, ``0.2 + 0.6 / 512``:

      >>> import jax.numpy as jnp, fsjax
      >>> img = fsjax.Image(jnp.where(jnp.arange(64).reshape(8, 8) < 40, 0.2, 0.8))
      >>> round(float(fsjax.ops.otsu_level(img).value), 9)
      0.201171875
    """
    nbins = _check_nbins("otsu_level", nbins)
    h, c, ok = _histogram(img.data, nbins)
    return _level_feature(_otsu_from_hist(h, c, ok))


@register(family="threshold", takes=Image, gives=Region, refs=[_OTSU])
def otsu(img: Image, /, *, nbins: int = 256) -> Region:
    """Otsu's global threshold: the pixels above :func:`otsu_level`.

    Args:
      img: input image ``(H, W)``.
      nbins: number of histogram bins over ``[min, max]`` (static int, default 256).

    Returns:
      ``Region``: ``x > level``; empty for a constant image (level NaN).

    Matches ``x > skimage.filters.threshold_otsu(x)`` exactly on camera and coins.

    Example:
      A bright 3 x 3 square (0.8) on a dark background (0.2) is recovered exactly:

      >>> import jax.numpy as jnp, fsjax
      >>> truth = jnp.zeros((8, 8), bool).at[2:5, 3:6].set(True)
      >>> reg = fsjax.ops.otsu(fsjax.Image(jnp.where(truth, 0.8, 0.2)))
      >>> bool((reg.data == truth).all()), int(reg.data.sum())
      (True, 9)
    """
    nbins = _check_nbins("otsu", nbins)
    h, c, ok = _histogram(img.data, nbins)
    return _region_above(img, _otsu_from_hist(h, c, ok))


def multi_otsu_levels(img: Image, /, *, classes: int = 3, nbins: int = 256):
    """Multi-level Otsu thresholds, an array ``(classes - 1,)`` of increasing bin centres.

    A helper, not a registered op (there is no sort for a vector of levels).
    The levels maximise the between-class variance of ``classes`` contiguous
    histogram classes (Otsu 1979; Liao, Chen, Chung 2001), found exactly by
    dynamic programming over the ``nbins x nbins`` segment table; among exact ties
    the lowest bins win. NaN when fewer than ``classes`` bins are occupied.

    Matches ``skimage.filters.threshold_multiotsu(x, classes, nbins)`` exactly on
    camera and coins (classes 3).

    Example:
      >>> import jax.numpy as jnp, fsjax
      >>> img = fsjax.Image(jnp.repeat(jnp.array([0.1, 0.5, 0.9]), 4).reshape(3, 4))
      >>> [round(float(v), 7) for v in fsjax.ops.multi_otsu_levels(img, classes=3)]
      [0.1015625, 0.5015625]
    """
    classes = check_static_int("multi_otsu_levels", "classes", classes, 2, 4)
    nbins = check_static_int("multi_otsu_levels", "nbins", nbins, 2, 1024)
    h, c, _ = _histogram(img.data, nbins)
    return _multi_otsu_from_hist(h, c, classes)


@register(family="threshold", takes=Image, gives=Labels,
          refs=[_OTSU, "P.-S. Liao, T.-S. Chen, P.-C. Chung, A fast algorithm for multilevel "
                "thresholding, J. Inf. Sci. Eng. 17(5), 2001"])
def multi_otsu(img: Image, /, *, classes: int = 3, nbins: int = 256) -> Labels:
    """Multi-level Otsu: ``classes`` grey classes, labelled ``1..classes`` from dark to bright.

    ``label = 1 + #{k : x > t_k}`` with the levels ``t_1 < ... < t_{classes-1}``
    of :func:`multi_otsu_levels`. Labels start at 1 because 0 is the background
    of the ``Labels`` sort; every pixel gets a class, so ``count = classes``.
    ``classes = 2`` reproduces :func:`otsu` (label 2 = the Otsu region).

    Args:
      img: input image ``(H, W)``.
      classes: number of classes, static int in 2..4 (not a knob: it fixes the
        search and the label count).
      nbins: histogram bins over ``[min, max]`` (static int, 2..1024).

    Returns:
      ``Labels`` with values in ``1..classes`` and ``count = classes``; all 0 with
      ``count = 0`` when fewer than ``classes`` bins are occupied (fail closed).

    Levels match ``skimage.filters.threshold_multiotsu`` exactly on camera and
    coins; pixels equal to a level go to the lower class (``x > t``), whereas
    scikit-image's ``np.digitize`` puts them in the upper one.

    Example:
      Three grey populations come back as labels 1, 2, 3:

      >>> import jax.numpy as jnp, fsjax
      >>> truth = jnp.repeat(jnp.array([1, 2, 3]), 4).reshape(3, 4)
      >>> img = fsjax.Image(jnp.array([0.1, 0.5, 0.9])[truth - 1])
      >>> lab = fsjax.ops.multi_otsu(img, classes=3)
      >>> bool((lab.data == truth).all()), int(lab.count)
      (True, 3)
    """
    classes = check_static_int("multi_otsu", "classes", classes, 2, 4)
    nbins = check_static_int("multi_otsu", "nbins", nbins, 2, 1024)
    h, c, _ = _histogram(img.data, nbins)
    levels = _multi_otsu_from_hist(h, c, classes)
    ok = jnp.all(jnp.isfinite(levels))
    x = img.data
    lab = 1 + jnp.sum(x[..., None] > levels.astype(x.dtype), axis=-1).astype(jnp.int32)
    lab = jnp.where(ok, lab, 0)
    return Labels(lab, count=jnp.where(ok, classes, 0), truncated=False)


# ---------------------------------------------------------------------------
# Triangle, Yen, Li, ISODATA
# ---------------------------------------------------------------------------


_ZACK = ("G. W. Zack, W. E. Rogers, S. A. Latt, Automatic measurement of sister chromatid "
         "exchange frequency, J. Histochem. Cytochem. 25(7), 1977")
_YEN = ("J.-C. Yen, F.-J. Chang, S. Chang, A new criterion for automatic multilevel "
        "thresholding, IEEE Trans. Image Process. 4(3), 1995")
_LI = ["C. H. Li, C. K. Lee, Minimum cross entropy thresholding, Pattern Recognition 26(4), 1993",
       "C. H. Li, P. K. S. Tam, An iterative algorithm for minimum cross entropy thresholding, "
       "Pattern Recognition Letters 18(8), 1998"]
_RIDLER = ("T. W. Ridler, S. Calvard, Picture thresholding using an iterative selection method, "
           "IEEE Trans. SMC 8(8), 1978")


def _triangle_level(img, nbins):
    h, c, ok = _histogram(img.data, nbins)
    return _triangle_from_hist(h, c, ok)


@register(family="threshold", takes=Image, gives=Feature, refs=[_ZACK, _SEZGIN])
def triangle_level(img: Image, /, *, nbins: int = 256) -> Feature:
    """Triangle (Zack 1977) level: the bin farthest below the peak-to-tail chord.

    A chord joins the histogram peak to the zero at the outer end of its longer
    tail (the first/last occupied bin); the level is the centre of the bin
    between them whose histogram value lies farthest below that chord
    (first such bin on the tail side).

    Args:
      img: input image ``(H, W)``.
      nbins: histogram bins over ``[min, max]`` (static int, default 256).

    Returns:
      ``Feature`` (``"grey"``): the level; NaN for a constant image.

    Matches ``skimage.filters.threshold_triangle(x, nbins)`` exactly on camera and coins.

    Example:
      Three quarters at 0.2 (the peak) and one quarter at 0.8: the chord runs from
      the peak (bin 0) across the empty bins to the tail (bin 255); the empty bin
      farthest below it is bin 1, next to the peak, so the level is its centre
      ``0.2 + 1.5 * 0.6 / 256`` (scikit-image gives the same):

      >>> import jax.numpy as jnp, fsjax
      >>> img = fsjax.Image(jnp.where(jnp.arange(64).reshape(8, 8) < 48, 0.2, 0.8))
      >>> round(float(fsjax.ops.triangle_level(img).value), 9)
      0.203515625
    """
    nbins = _check_nbins("triangle_level", nbins)
    return _level_feature(_triangle_level(img, nbins))


@register(family="threshold", takes=Image, gives=Region, refs=[_ZACK, _SEZGIN])
def triangle(img: Image, /, *, nbins: int = 256) -> Region:
    """Triangle threshold: the pixels above :func:`triangle_level`.

    Args:
      img: input image ``(H, W)``.
      nbins: histogram bins over ``[min, max]`` (static int, default 256).

    Returns:
      ``Region`` ``x > level``; empty for a constant image.

    Matches ``x > skimage.filters.threshold_triangle(x)`` exactly on camera and coins.

    Example:
      A small bright population (a skewed histogram, the method's use case):

      >>> import jax.numpy as jnp, fsjax
      >>> truth = jnp.zeros((8, 8), bool).at[1:3, 1:4].set(True)
      >>> reg = fsjax.ops.triangle(fsjax.Image(jnp.where(truth, 0.9, 0.3)))
      >>> bool((reg.data == truth).all())
      True
    """
    nbins = _check_nbins("triangle", nbins)
    return _region_above(img, _triangle_level(img, nbins))


def _yen_level(img, nbins):
    h, c, ok = _histogram(img.data, nbins)
    return _yen_from_hist(h, c, ok)


@register(family="threshold", takes=Image, gives=Feature, refs=[_YEN, _SEZGIN])
def yen_level(img: Image, /, *, nbins: int = 256) -> Feature:
    """Yen's maximum-correlation level.

    With ``P(t)`` the cumulative probability and ``Q1(t) = sum_{i<=t} p_i^2``,
    ``Q2(t) = sum_{i>t} p_i^2``, the level is the centre of the first bin ``t``
    maximising ``log[(P (1 - P))^2 / (Q1 Q2)]``.

    Args:
      img: input image ``(H, W)``.
      nbins: histogram bins over ``[min, max]`` (static int, default 256).

    Returns:
      ``Feature`` (``"grey"``): the level; NaN for a constant image.

    Matches ``skimage.filters.threshold_yen(x, nbins)`` exactly on camera and coins.

    Example:
      Two grey values: every split between them ties and the lowest wins:

      >>> import jax.numpy as jnp, fsjax
      >>> img = fsjax.Image(jnp.where(jnp.arange(64).reshape(8, 8) < 40, 0.2, 0.8))
      >>> round(float(fsjax.ops.yen_level(img).value), 9)
      0.201171875
    """
    nbins = _check_nbins("yen_level", nbins)
    return _level_feature(_yen_level(img, nbins))


@register(family="threshold", takes=Image, gives=Region, refs=[_YEN, _SEZGIN])
def yen(img: Image, /, *, nbins: int = 256) -> Region:
    """Yen threshold: the pixels above :func:`yen_level`.

    Args:
      img: input image ``(H, W)``.
      nbins: histogram bins over ``[min, max]`` (static int, default 256).

    Returns:
      ``Region`` ``x > level``; empty for a constant image.

    Matches ``x > skimage.filters.threshold_yen(x)`` exactly on camera and coins.

    Example:
      >>> import jax.numpy as jnp, fsjax
      >>> truth = jnp.zeros((8, 8), bool).at[2:6, 2:6].set(True)
      >>> reg = fsjax.ops.yen(fsjax.Image(jnp.where(truth, 0.7, 0.4)))
      >>> bool((reg.data == truth).all())
      True
    """
    nbins = _check_nbins("yen", nbins)
    return _region_above(img, _yen_level(img, nbins))


def _li_level(x, tolerance, max_iter: int):
    v = x.reshape(-1)
    dt = v.dtype
    mn, mx = jnp.min(v), jnp.max(v)
    u = v - mn
    if tolerance is None:
        s = jnp.sort(v)
        d = s[1:] - s[:-1]
        tol = jnp.min(jnp.where(d > 0, d, jnp.inf)) / 2
    else:
        tol = jnp.asarray(tolerance, dt)
    t0 = jnp.mean(v) - mn

    def means(t):
        fg = u > t
        nf = jnp.sum(fg)
        nb = u.shape[0] - nf
        mf, okf = _safe_div(jnp.sum(jnp.where(fg, u, 0)), nf.astype(dt))
        mb, okb = _safe_div(jnp.sum(jnp.where(fg, 0, u)), nb.astype(dt))
        return mf, mb, okf & okb

    def cond(state):
        t_curr, t_next, it, stop, _ = state
        return (jnp.abs(t_next - t_curr) > tol) & (~stop) & (it < max_iter)

    def body(state):
        _, t_next, it, _, bad = state
        t_curr = t_next
        mf, mb, ok = means(t_curr)
        stop = mb == 0  # background at the minimum: Li's log(mean) is undefined; keep t
        lf = jnp.log(jnp.where(mf > 0, mf, 1.0))
        lb = jnp.log(jnp.where(mb > 0, mb, 1.0))
        t_new, okd = _safe_div(mb - mf, lb - lf)
        t_new = jnp.where(stop, t_curr, t_new)
        bad = bad | ~ok | (~okd & ~stop)
        return t_curr, t_new, it + 1, stop | bad, bad

    init = (-2 * tol, t0, jnp.asarray(0), jnp.asarray(False), jnp.asarray(False))
    t_curr, t_next, it, stop, bad = lax.while_loop(cond, body, init)
    converged = (jnp.abs(t_next - t_curr) <= tol) | stop
    good = (mx > mn) & converged & ~bad
    return jnp.where(good, t_next + mn, jnp.nan)


def _check_li(op, tolerance, max_iter):
    if tolerance is not None:
        check_positive(op, "tolerance", tolerance)
    return check_static_int(op, "max_iter", max_iter, 1)


@register(family="threshold", takes=Image, gives=Feature, refs=_LI)
def li_level(img: Image, /, *, tolerance: float | None = None, max_iter: int = 256) -> Feature:
    """Li's minimum cross-entropy level, by the Li-Tam fixed-point iteration on the pixels.

    On ``u = x - min(x)``, starting from the mean, iterate
    ``t <- (mb - mf) / (ln mb - ln mf)`` with ``mb``, ``mf`` the means of
    ``u <= t`` and ``u > t``, in a ``lax.while_loop`` until ``|dt| <= tolerance``
    (or the background mean is 0, where the iteration stops at the current
    ``t``). Works on the pixel values, not a histogram.

    Args:
      img: input image ``(H, W)``.
      tolerance: stopping tolerance in grey units; ``None`` = half the smallest
        gap between distinct grey values (scikit-image's default).
      max_iter: iteration cap (static int); not converging by then gives NaN.

    Returns:
      ``Feature`` (``"grey"``): ``min(x) + t``; NaN for a constant image or
      without convergence.

    Matches ``skimage.filters.threshold_li(x)`` to 1e-12 on camera and coins
    (same start, same stopping rule).

    Example:
      Values 0.1 (half), 0.3 and 0.9 (a quarter each): from the mean the split
      {0.1, 0.3} | {0.9} is already stable, so the level is the closed form
      ``0.1 + (mb - mf) / ln(mb / mf)`` with ``mb = 0.2 / 3``, ``mf = 0.8``:

      >>> import math, jax.numpy as jnp, fsjax
      >>> img = fsjax.Image(jnp.array([0.1, 0.1, 0.3, 0.9] * 4).reshape(4, 4))
      >>> mb, mf = 0.2 / 3, 0.8
      >>> truth = 0.1 + (mb - mf) / math.log(mb / mf)
      >>> abs(float(fsjax.ops.li_level(img).value) - truth) < 1e-12
      True
    """
    max_iter = _check_li("li_level", tolerance, max_iter)
    return _level_feature(_li_level(img.data, tolerance, max_iter))


@register(family="threshold", takes=Image, gives=Region, refs=_LI)
def li(img: Image, /, *, tolerance: float | None = None, max_iter: int = 256) -> Region:
    """Li's minimum cross-entropy threshold: the pixels above :func:`li_level`.

    Args:
      img: input image ``(H, W)``.
      tolerance: stopping tolerance (grey units); ``None`` = half the smallest grey gap.
      max_iter: iteration cap (static int); no convergence gives an empty region.

    Returns:
      ``Region`` ``x > level``; empty for a constant image.

    Matches ``x > skimage.filters.threshold_li(x)`` on camera and coins (identical masks).

    Example:
      >>> import jax.numpy as jnp, fsjax
      >>> truth = jnp.zeros((8, 8), bool).at[2:6, 1:4].set(True)
      >>> reg = fsjax.ops.li(fsjax.Image(jnp.where(truth, 0.75, 0.25)))
      >>> bool((reg.data == truth).all())
      True
    """
    max_iter = _check_li("li", tolerance, max_iter)
    return _region_above(img, _li_level(img.data, tolerance, max_iter))


def _isodata_level(img, nbins):
    h, c, ok = _histogram(img.data, nbins)
    return _isodata_from_hist(h, c, ok)


@register(family="threshold", takes=Image, gives=Feature, refs=[_RIDLER, _SEZGIN])
def isodata_level(img: Image, /, *, nbins: int = 256) -> Feature:
    """ISODATA (Ridler-Calvard, inter-means) level.

    The centre ``t`` of the first bin for which the midpoint of the two class
    means, ``(mean(x <= t) + mean(x > t)) / 2`` over the histogram, lies in
    ``[t, t + bin width)``.

    Args:
      img: input image ``(H, W)``.
      nbins: histogram bins over ``[min, max]`` (static int, default 256).

    Returns:
      ``Feature`` (``"grey"``): the level; NaN for a constant image.

    Matches ``skimage.filters.threshold_isodata(x, nbins)`` exactly on camera and coins.

    Example:
      Equal halves at 0.2 and 0.8: the class means are the two bin centres,
      whose midpoint 0.5 lies in bin 127, so the level is its centre
      ``0.2 + 127.5 * 0.6 / 256``:

      >>> import jax.numpy as jnp, fsjax
      >>> img = fsjax.Image(jnp.where(jnp.arange(64).reshape(8, 8) < 32, 0.2, 0.8))
      >>> round(float(fsjax.ops.isodata_level(img).value), 9)
      0.498828125
    """
    nbins = _check_nbins("isodata_level", nbins)
    return _level_feature(_isodata_level(img, nbins))


@register(family="threshold", takes=Image, gives=Region, refs=[_RIDLER, _SEZGIN])
def isodata(img: Image, /, *, nbins: int = 256) -> Region:
    """ISODATA threshold: the pixels above :func:`isodata_level`.

    Args:
      img: input image ``(H, W)``.
      nbins: histogram bins over ``[min, max]`` (static int, default 256).

    Returns:
      ``Region`` ``x > level``; empty for a constant image.

    Matches ``x > skimage.filters.threshold_isodata(x)`` exactly on camera and coins.

    Example:
      >>> import jax.numpy as jnp, fsjax
      >>> truth = jnp.zeros((8, 8), bool).at[0:4, :].set(True)
      >>> reg = fsjax.ops.isodata(fsjax.Image(jnp.where(truth, 0.8, 0.2)))
      >>> bool((reg.data == truth).all())
      True
    """
    nbins = _check_nbins("isodata", nbins)
    return _region_above(img, _isodata_level(img, nbins))


# ---------------------------------------------------------------------------
# Local (adaptive) thresholds
# ---------------------------------------------------------------------------


def _check_radius(op: str, radius, max_radius) -> int:
    max_radius = check_static_int(op, "max_radius", max_radius, 1)
    if is_concrete(radius):
        r = np.asarray(radius, dtype=float)
        if r.ndim or not np.isfinite(r) or r < 1 or r != np.round(r):
            raise ValueError(f"{op}: argument 'radius' must be an integer >= 1, got {radius}")
    return max_radius


def _box_taps(radius, max_radius: int, dtype):
    """Normalised 1-D box taps; static length ``2R+1`` (``R`` = concrete radius or max_radius)."""
    if is_concrete(radius):
        R = int(np.asarray(radius))
        r = R
    else:
        R = max_radius
        r = jnp.clip(radius, 1, max_radius)
    k = jnp.arange(-R, R + 1)
    w = jnp.where(jnp.abs(k) <= r, 1.0, 0.0) / (2 * r + 1)
    return w.astype(dtype)


def _box_mean(x, radius, max_radius: int, mode: str):
    w = _box_taps(radius, max_radius, x.dtype)
    return correlate1d(correlate1d(x, w, axis=-2, mode=mode), w, axis=-1, mode=mode)


def _mean_std(x, radius, max_radius: int, mode: str):
    m = _box_mean(x, radius, max_radius, mode)
    m2 = _box_mean(x * x, radius, max_radius, mode)
    var = m2 - m * m
    return m, jnp.sqrt(jnp.where(var > 0, var, 0.0))


_RADIUS_KNOB = IntKnob(1, 25, unit="px")


@register(family="threshold", takes=Image, gives=Region,
          knobs={"radius": _RADIUS_KNOB, "offset": LinKnob(-0.2, 0.2)},
          refs=["R. C. Gonzalez, R. E. Woods, Digital Image Processing, 2nd ed., "
                "Prentice Hall, 2002, sec. 10.3"])
def local_mean(img: Image, /, *, radius: int = 7, offset: float = 0.0, mode: str = "reflect",
               max_radius: int = 25) -> Region:
    """Adaptive mean threshold: ``x > mean_window(x) - offset``.

    The mean is over the ``(2 radius + 1)^2`` box around each pixel.

    Args:
      img: input image ``(H, W)``.
      radius: box half-width in pixels, integer >= 1 (knob ``a``, 1..25); the
        scikit-image ``block_size`` is ``2 radius + 1``.
      offset: subtracted from the local mean (grey units; knob ``b``, [-0.2, 0.2]);
        negative values demand pixels brighter than their surround.
      mode: boundary mode (SciPy names), default ``"reflect"``.
      max_radius: static support for a traced radius.

    Returns:
      ``Region`` ``x > mean - offset``.

    Matches ``x > skimage.filters.threshold_local(x, 2 radius + 1, "mean",
    offset, mode)`` on camera crops: local thresholds to 1e-12 and identical masks.

    Example:
      A 3 x 3 bright square (0.8) on 0.2 with ``offset = -0.05``: the flat
      background equals its mean, so only the square passes:

      >>> import jax.numpy as jnp, fsjax
      >>> truth = jnp.zeros((12, 12), bool).at[4:7, 5:8].set(True)
      >>> img = fsjax.Image(jnp.where(truth, 0.8, 0.2))
      >>> reg = fsjax.ops.local_mean(img, radius=3, offset=-0.05)
      >>> bool((reg.data == truth).all())
      True
    """
    max_radius = _check_radius("local_mean", radius, max_radius)
    check_range("local_mean", "offset", offset)
    check_mode("local_mean", mode)
    x = img.data
    m = _box_mean(x, radius, max_radius, mode)
    return Region(x > m - jnp.asarray(offset, x.dtype))


@register(family="threshold", takes=Image, gives=Region,
          knobs={"radius": _RADIUS_KNOB, "k": LinKnob(0.0, 0.6)},
          refs=["J. Sauvola, M. Pietikäinen, Adaptive document image binarization, "
                "Pattern Recognition 33(2), 2000"])
def sauvola(img: Image, /, *, radius: int = 7, k: float = 0.2, r: float = 0.5,
            mode: str = "reflect", max_radius: int = 25) -> Region:
    """Sauvola's local threshold: ``x > m (1 + k (s / r - 1))``.

    ``m``, ``s`` are the mean and standard deviation over the ``(2 radius + 1)^2``
    window. The paper's setting is dark ink on a light page: the ink is the
    *complement* of the returned region.

    Args:
      img: input image ``(H, W)``.
      radius: window half-width in pixels, integer >= 1 (knob ``a``, 1..25);
        scikit-image ``window_size = 2 radius + 1``.
      k: weight of the deviation term, >= 0 (knob ``b``, [0, 0.6]); paper 0.5, default 0.2.
      r: dynamic range of the standard deviation, > 0; 0.5 is the paper's
        ``R = 128`` of 8-bit grey on the [0, 1] scale.
      mode: boundary mode (SciPy names), default ``"reflect"``; use ``"mirror"``
        to reproduce scikit-image's padding.
      max_radius: static support for a traced radius.

    Returns:
      ``Region`` ``x > T``.

    Matches ``x > skimage.filters.threshold_sauvola(x, 2 radius + 1, k, r)`` with
    ``mode="mirror"`` on camera crops: thresholds to 1e-9 and pixel agreement
    >= 99.99 % (disagreement only where ``x`` is within rounding of ``T``).

    Example:
      Alternating 0.2 / 0.8 columns, 3 x 3 window: every window sees both values,
      so exactly the bright columns pass:

      >>> import jax.numpy as jnp, fsjax
      >>> truth = jnp.tile(jnp.arange(10) % 2 == 1, (6, 1))
      >>> reg = fsjax.ops.sauvola(fsjax.Image(jnp.where(truth, 0.8, 0.2)), radius=1)
      >>> bool((reg.data == truth).all())
      True
    """
    max_radius = _check_radius("sauvola", radius, max_radius)
    check_range("sauvola", "k", k, 0.0)
    check_positive("sauvola", "r", r)
    check_mode("sauvola", mode)
    x = img.data
    m, s = _mean_std(x, radius, max_radius, mode)
    kk = jnp.asarray(k, x.dtype)
    t = m * (1 + kk * (s / jnp.asarray(r, x.dtype) - 1))
    return Region(x > t)


@register(family="threshold", takes=Image, gives=Region,
          knobs={"radius": _RADIUS_KNOB, "k": LinKnob(-1.0, 1.0)},
          refs=["W. Niblack, An Introduction to Digital Image Processing, Prentice-Hall, 1986"])
def niblack(img: Image, /, *, radius: int = 7, k: float = 0.2, mode: str = "reflect",
            max_radius: int = 25) -> Region:
    """Niblack's local threshold: ``x > m - k s`` (scikit-image's sign convention).

    ``m``, ``s`` are the window mean and standard deviation. Niblack writes
    ``T = m + k s`` with ``k = -0.2``; our ``k = 0.2`` is the same threshold.

    Args:
      img: input image ``(H, W)``.
      radius: window half-width in pixels, integer >= 1 (knob ``a``, 1..25).
      k: weight of the standard deviation (knob ``b``, [-1, 1]); default 0.2.
      mode: boundary mode (SciPy names), default ``"reflect"``; ``"mirror"``
        reproduces scikit-image.
      max_radius: static support for a traced radius.

    Returns:
      ``Region`` ``x > m - k s``. On flat areas ``s = 0`` and the decision is
      ``x > m``, decided by rounding: Niblack is noisy on empty background.

    Matches ``x > skimage.filters.threshold_niblack(x, 2 radius + 1, k)`` with
    ``mode="mirror"`` on camera crops: thresholds to 1e-9, pixel agreement
    >= 99.99 %.

    Example:
      >>> import jax.numpy as jnp, fsjax
      >>> truth = jnp.tile(jnp.arange(10) % 2 == 1, (6, 1))
      >>> reg = fsjax.ops.niblack(fsjax.Image(jnp.where(truth, 0.8, 0.2)), radius=1)
      >>> bool((reg.data == truth).all())
      True
    """
    max_radius = _check_radius("niblack", radius, max_radius)
    check_range("niblack", "k", k)
    check_mode("niblack", mode)
    x = img.data
    m, s = _mean_std(x, radius, max_radius, mode)
    return Region(x > m - jnp.asarray(k, x.dtype) * s)


def _gauss_taps(radius, max_radius: int, dtype):
    """Gaussian taps with sigma = radius / 3, truncated at |k| <= radius; static length.

    The normaliser is a sequential sum over the taps, so the extra zero taps of a
    traced radius leave it bit-identical to the concrete one.
    """
    if is_concrete(radius):
        R = int(np.asarray(radius))
        r = R
    else:
        R = max_radius
        r = jnp.clip(radius, 1, max_radius)
    k = jnp.arange(-R, R + 1).astype(dtype)
    sigma = jnp.asarray(r, dtype) / 3
    e = jnp.where(jnp.abs(k) <= r, jnp.exp(-0.5 * (k / sigma) ** 2), 0.0).astype(dtype)
    total = e[0]
    for i in range(1, 2 * R + 1):
        total = total + e[i]
    return e / total


@register(family="threshold", takes=Image, gives=Region,
          knobs={"offset": LinKnob(0.0, 0.3), "radius": _RADIUS_KNOB},
          refs=["HALCON operator reference: dyn_threshold"])
def dyn_threshold(img: Image, /, *, offset: float = 0.05, radius: int = 7,
                  smoothing: str = "mean", light_dark: str = "light", mode: str = "reflect",
                  max_radius: int = 25) -> Region:
    """Dynamic threshold against a smoothed copy ``s`` of the image (HALCON ``dyn_threshold``).

    ``light``: ``x >= s + offset``; ``dark``: ``x <= s - offset``; ``equal``:
    ``s - offset <= x <= s + offset``; ``not_equal``: the complement of ``equal``.

    Args:
      img: input image ``(H, W)``.
      offset: grey-value margin (knob ``a``, [0, 0.3]).
      radius: smoothing half-width in pixels, integer >= 1 (knob ``b``, 1..25).
      smoothing: ``"mean"`` ((2 radius + 1)^2 box, HALCON's usual ``mean_image``)
        or ``"gaussian"`` (sigma = radius / 3, truncated at radius, same support).
      light_dark: ``"light"``, ``"dark"``, ``"equal"`` or ``"not_equal"`` (static).
      mode: boundary mode (SciPy names), default ``"reflect"``.
      max_radius: static support for a traced radius.

    Returns:
      ``Region`` selected by ``light_dark``.

    The mean smoothing equals ``scipy.ndimage.uniform_filter(x, 2 radius + 1,
    mode=mode)`` to 1e-12 (checked with :func:`local_mean`).

    Example:
      A bright 3 x 3 spot (+0.3) on a gentle ramp: the ramp follows its own mean,
      so only the spot exceeds the smoothed copy by 0.1:

      >>> import jax.numpy as jnp, fsjax
      >>> truth = jnp.zeros((12, 16), bool).at[4:7, 6:9].set(True)
      >>> ramp = 0.3 + 0.01 * jnp.arange(16.0)[None, :] + jnp.zeros((12, 1))
      >>> img = fsjax.Image(ramp + 0.3 * truth)
      >>> reg = fsjax.ops.dyn_threshold(img, offset=0.1, radius=3)
      >>> bool((reg.data == truth).all())
      True
    """
    max_radius = _check_radius("dyn_threshold", radius, max_radius)
    check_range("dyn_threshold", "offset", offset, 0.0)
    check_choice("dyn_threshold", "smoothing", smoothing, ("mean", "gaussian"))
    check_choice("dyn_threshold", "light_dark", light_dark, ("light", "dark", "equal", "not_equal"))
    check_mode("dyn_threshold", mode)
    x = img.data
    if smoothing == "mean":
        w = _box_taps(radius, max_radius, x.dtype)
    else:
        w = _gauss_taps(radius, max_radius, x.dtype)
    s = correlate1d(correlate1d(x, w, axis=-2, mode=mode), w, axis=-1, mode=mode)
    off = jnp.asarray(offset, x.dtype)
    if light_dark == "light":
        out = x >= s + off
    elif light_dark == "dark":
        out = x <= s - off
    else:
        out = (x >= s - off) & (x <= s + off)
        if light_dark == "not_equal":
            out = ~out
    return Region(out)


# ---------------------------------------------------------------------------
# Hysteresis
# ---------------------------------------------------------------------------


def _dilate(m, connectivity: int):
    p = jnp.pad(m, 1)
    h, w = m.shape[-2:]
    out = m
    for di in (-1, 0, 1):
        for dj in (-1, 0, 1):
            if (di, dj) == (0, 0) or (connectivity == 4 and di != 0 and dj != 0):
                continue
            out = out | p[1 + di:1 + di + h, 1 + dj:1 + dj + w]
    return out


@register(family="threshold", takes=Image, gives=Region,
          knobs={"low": LinKnob(0.0, 1.0), "high": LinKnob(0.0, 1.0)},
          refs=["J. Canny, A computational approach to edge detection, IEEE TPAMI 8(6), 1986"])
def hysteresis(img: Image, /, *, low: float = 0.3, high: float = 0.6,
               connectivity: int = 8, steps_per_check: int = 4) -> Region:
    """Hysteresis threshold: the connected parts of ``x > low`` that contain a pixel ``> high``.

    Seeds ``x > max(low, high)`` grow by repeated dilation within ``x > low``
    (``lax.while_loop`` until nothing changes).

    Args:
      img: input image ``(H, W)``.
      low: lower threshold (knob ``a``, [0, 1]).
      high: upper threshold (knob ``b``, [0, 1]); ``high < low`` acts as
        ``high = low`` (the result is then ``x > low``; the knobs range
        independently, so the search meets this case and gets a defined answer).
      connectivity: 8 (default, the usual choice for edge chains) or 4 (static).
      steps_per_check: dilation steps per loop iteration (static; speed only).

    Returns:
      ``Region``.

    With ``connectivity=4`` this equals ``skimage.filters.apply_hysteresis_threshold``
    (which labels with SciPy's default cross) exactly; with 8 it equals the same
    definition labelled with a 3 x 3 structure (identical masks on camera).

    Example:
      scikit-image's 1-D example, scaled to [0, 1]:

      >>> import jax.numpy as jnp, fsjax
      >>> row = jnp.array([[1, 2, 3, 2, 1, 2, 1, 3, 2]]) / 4.0
      >>> reg = fsjax.ops.hysteresis(fsjax.Image(row), low=1.5 / 4, high=2.5 / 4)
      >>> [int(v) for v in reg.data[0]]
      [0, 1, 1, 1, 0, 0, 0, 1, 1]
    """
    for name, v in (("low", low), ("high", high)):
        check_range("hysteresis", name, v)
    if connectivity not in (4, 8):
        raise ValueError(f"hysteresis: argument 'connectivity' must be 4 or 8, got {connectivity!r}")
    steps = check_static_int("hysteresis", "steps_per_check", steps_per_check, 1)
    x = img.data
    lo = jnp.asarray(low, x.dtype)
    allowed = x > lo
    seed = allowed & (x > jnp.maximum(lo, jnp.asarray(high, x.dtype)))

    def body(state):
        m, _ = state
        new = m
        for _ in range(steps):
            new = _dilate(new, connectivity) & allowed
        return new, jnp.any(new != m)

    out, _ = lax.while_loop(lambda s: s[1], body, (seed, jnp.asarray(True)))
    return Region(out)

