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
* Local windows (in :mod:`fsjax.ops.image._threshold_local`): square ``(2 radius + 1)^2`` boxes (``radius`` in pixels; the
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

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from ..._checks import check_positive, check_static_int, note_traced
from ...registry import LinKnob, register
from ...types import Feature, Image, Labels, Region, is_concrete

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
        if not is_concrete(v):  # a traced NaN gave an empty Region (issue 20 sweep); now it raises
            note_traced(v, jnp.isnan(v))
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


@functools.partial(jax.jit, static_argnames="max_iter")
def _li_level(x, tolerance, max_iter: int):
    # jitted at module level: the while_loop's closures would otherwise be compiled again on
    # every eager call (tolerance None or a number: two programs, not one per call)
    v = x.reshape(-1)
    dt = v.dtype
    mn, mx = jnp.min(v), jnp.max(v)
    u = v - mn
    if tolerance is None:
        s = jnp.sort(v)
        d = s[1:] - s[:-1]
        # a single pixel has no gap (an empty min): the tolerance is then inf, and the
        # constant-image rule below gives NaN (the chain fuzzer's ncc_map -> li, a 1 x 1 map)
        tol = jnp.min(jnp.where(d > 0, d, jnp.inf), initial=jnp.inf) / 2
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
