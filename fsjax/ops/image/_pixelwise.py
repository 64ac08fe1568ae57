"""Point (pixel-wise) and image-arithmetic grey-value ops (``Image -> Image``).

Conventions:

* Every op here maps each pixel through a function of its own value (and, for
  :func:`normalize` and :func:`equalize_hist`, of image-wide statistics); there
  is no neighbourhood and therefore no boundary mode.
* ``Image`` values are nominally in ``[0, 1]``. Ops whose output can leave that
  range (:func:`gain_offset`, :func:`add_images`, :func:`sub_images`, and the
  odd extensions below for negative inputs) **do not clip**: clipping is an
  explicit op (:func:`clip`). Each docstring states its output range.
* Power and logarithmic curves (:func:`gamma`, :func:`log_transform`,
  :func:`exp_transform`) are defined on signed input by odd extension,
  ``f(-x) = -f(x)``, so signed images (differences, derivatives) keep their sign
  and every curve stays invertible by its partner.
* Degenerate inputs never produce NaN: a constant image normalises to zeros,
  ``0 ** gamma`` is 0 with a finite (zero) gradient. Divisions use a double
  ``jnp.where`` with a safe denominator, never ``x / (d + eps)``.
* Two-input ops take ``(Image, Image)`` of the same shape; their scale/offset
  follow HALCON's ``add_image`` / ``sub_image`` (``(g1 +/- g2) * mult + add``),
  with ``add`` expressed on the ``[0, 1]`` scale (HALCON's byte default of 128
  becomes 0.5).
* Dtype-generic: float32 stays float32, float64 stays float64.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ..._checks import check_positive, check_range, check_static_int, note_traced
from ...registry import LinKnob, LogKnob, register
from ...types import Image, is_concrete

__all__ = [
    "invert",
    "gain_offset",
    "gamma",
    "clip",
    "normalize",
    "log_transform",
    "exp_transform",
    "abs_diff",
    "add_images",
    "sub_images",
    "equalize_hist",
]


def _check_same_shape(op: str, a: Image, b: Image) -> None:
    if a.data.shape != b.data.shape:
        raise ValueError(
            f"{op}: inputs must have the same shape, got {tuple(a.data.shape)} and {tuple(b.data.shape)}"
        )


# ---------------------------------------------------------------------------
# One-input curves
# ---------------------------------------------------------------------------


@register(family="point", takes=Image, gives=Image, differentiable=True,
          refs=["R. C. Gonzalez, R. E. Woods, Digital Image Processing, 4th ed., Pearson, 2018, sec. 3.2"])
def invert(img: Image, /) -> Image:
    """Negative of an image: ``out = 1 - x``.

    Maps ``[0, 1]`` onto itself, reversing the order of grey values (HALCON
    ``invert_image`` on the ``[0, 1]`` scale).

    Args:
      img: input image ``(H, W)``.

    Returns:
      ``Image`` ``1 - x`` (inputs outside ``[0, 1]`` map outside it; no clipping).

    Matches ``skimage.util.invert`` on float images in ``[0, 1]`` exactly.

    Example:
      >>> import jax.numpy as jnp, fsjax
      >>> out = fsjax.ops.invert(fsjax.Image(jnp.array([[0.0, 0.25], [0.5, 1.0]])))
      >>> [float(v) for v in out.data.ravel()]
      [1.0, 0.75, 0.5, 0.0]
    """
    return Image(1.0 - img.data)


@register(family="point", takes=Image, gives=Image,
          knobs={"gain": LinKnob(0.25, 4.0), "offset": LinKnob(-0.5, 0.5)}, differentiable=True,
          refs=["R. C. Gonzalez, R. E. Woods, Digital Image Processing, 4th ed., Pearson, 2018, sec. 3.2",
                "MVTec HALCON reference: scale_image"])
def gain_offset(img: Image, /, *, gain: float = 1.0, offset: float = 0.0) -> Image:
    """Linear grey-value map ``out = x * gain + offset`` (contrast and brightness).

    Args:
      img: input image ``(H, W)``.
      gain: multiplicative contrast factor, > 0 (knob ``a``, linear on [0.25, 4]).
        ``1`` leaves contrast unchanged.
      offset: additive brightness shift in grey-value units of the ``[0, 1]`` scale
        (knob ``b``, linear on [-0.5, 0.5]); ``0`` means no shift.

    Returns:
      ``Image``; values may leave ``[0, 1]`` (not clipped: follow with :func:`clip`).

    Same map as HALCON ``scale_image(Mult=gain, Add=offset*255)`` on byte images,
    without HALCON's saturation.

    Example:
      >>> import jax.numpy as jnp, fsjax
      >>> out = fsjax.ops.gain_offset(fsjax.Image(jnp.full((2, 2), 0.25)), gain=2.0, offset=0.125)
      >>> float(out.data[0, 0])
      0.625
    """
    check_positive("gain_offset", "gain", gain)
    check_range("gain_offset", "offset", offset)
    x = img.data
    return Image((x * gain + offset).astype(x.dtype))


@register(family="point", takes=Image, gives=Image, knobs={"gamma": LogKnob(0.2, 5.0)},
          differentiable=True,
          refs=["C. Poynton, Digital Video and HD: Algorithms and Interfaces, 2nd ed., 2012 (gamma)"])
def gamma(img: Image, /, *, gamma: float = 1.0) -> Image:
    """Power-law (gamma) curve ``out = x ** gamma``, odd-extended to negative values.

    ``out = sign(x) |x| ** gamma`` (computed as ``x |x| ** (gamma - 1)``); it fixes
    0 and 1, darkens mid-tones for ``gamma > 1`` and brightens them for
    ``gamma < 1``. ``gamma(gamma(x, g), 1/g) = x``. At ``x = 0`` the value is 0 and
    the gradient w.r.t. ``x`` is the true slope (0 for ``gamma > 1``, 1 for
    ``gamma = 1``) except for ``gamma < 1``, where the infinite slope is reported
    as 0; there is no NaN anywhere.

    Args:
      img: input image ``(H, W)``.
      gamma: exponent, > 0 (knob ``a``, log-mapped to [0.2, 5]); ``1`` is the identity.

    Returns:
      ``Image``; ``[0, 1]`` maps onto ``[0, 1]``.

    Matches ``skimage.exposure.adjust_gamma(x, gamma)`` (gain 1) on float images in
    ``[0, 1]`` to 1e-12 in float64.

    Example:
      >>> import jax.numpy as jnp, fsjax
      >>> out = fsjax.ops.gamma(fsjax.Image(jnp.array([[0.0, 0.25, 1.0]])), gamma=0.5)
      >>> [float(v) for v in out.data.ravel()]
      [0.0, 0.5, 1.0]
    """
    check_positive("gamma", "gamma", gamma)
    x = img.data
    # out = x * |x|**(gamma - 1): odd, and the factor's value at 0 is the slope there
    ax = jnp.abs(x)
    pos = ax > 0
    safe = jnp.where(pos, ax, jnp.ones_like(ax))
    at_zero = jnp.where(gamma == 1, jnp.ones_like(ax), jnp.zeros_like(ax))
    t = jnp.where(pos, jnp.exp((gamma - 1) * jnp.log(safe)), at_zero)
    return Image((x * t).astype(x.dtype))


@register(family="point", takes=Image, gives=Image,
          knobs={"lo": LinKnob(0.0, 0.5), "hi": LinKnob(0.5, 1.0)}, differentiable=True,
          refs=["numpy.clip"])
def clip(img: Image, /, *, lo: float = 0.0, hi: float = 1.0) -> Image:
    """Clip grey values to ``[lo, hi]``: ``out = min(max(x, lo), hi)``.

    Piecewise linear: the gradient is 1 w.r.t. ``x`` inside the interval, 1 w.r.t.
    ``lo`` (``hi``) where clipped there, 0 elsewhere (undefined only on the
    measure-zero set ``x == lo`` or ``x == hi``).

    Args:
      img: input image ``(H, W)``.
      lo: lower bound (knob ``a``, linear on [0, 0.5]); default 0.
      hi: upper bound (knob ``b``, linear on [0.5, 1]); default 1. A concrete
        ``lo > hi`` raises; a traced one gives ``hi`` everywhere (NumPy's rule).

    Returns:
      ``Image`` with values in ``[lo, hi]``.

    Matches ``numpy.clip(x, lo, hi)`` exactly.

    Example:
      >>> import jax.numpy as jnp, fsjax
      >>> out = fsjax.ops.clip(fsjax.Image(jnp.array([[-0.5, 0.3, 0.9]])), lo=0.25, hi=0.75)
      >>> [float(v) for v in out.data.ravel()]
      [0.25, 0.3, 0.75]
    """
    check_range("clip", "lo", lo)
    check_range("clip", "hi", hi)
    if is_concrete(lo) and is_concrete(hi) and bool(np.any(np.asarray(lo) > np.asarray(hi))):
        raise ValueError(f"clip: argument 'lo' ({lo}) must be <= 'hi' ({hi})")
    # traced lo > hi: the output is poisoned (registry), as the eager call refuses it
    crossed = jnp.any(jnp.asarray(lo) > jnp.asarray(hi))
    note_traced(lo, crossed)
    note_traced(hi, crossed)
    x = img.data
    return Image(jnp.minimum(jnp.maximum(x, lo), hi).astype(x.dtype))


@register(family="point", takes=Image, gives=Image, differentiable=True,
          refs=["R. C. Gonzalez, R. E. Woods, Digital Image Processing, 4th ed., Pearson, 2018, sec. 2.6",
                "skimage.exposure.rescale_intensity"])
def normalize(img: Image, /) -> Image:
    """Min-max stretch to ``[0, 1]``: ``out = (x - min x) / (max x - min x)``.

    The image minimum maps to 0 and the maximum to 1. A constant image (zero
    range) returns all zeros, never NaN, with zero gradient. The gradient flows
    through the extreme pixels as well (ties share it equally).

    Args:
      img: input image ``(H, W)``; statistics are over the whole image.

    Returns:
      ``Image`` in ``[0, 1]`` (exactly 0 at the minimum and 1 at the maximum).

    Matches ``skimage.exposure.rescale_intensity(x, out_range=(0, 1))`` to 1e-15
    in float64 for non-constant images (for a constant image scikit-image returns
    the input values unchanged; fsjax returns zeros).

    Example:
      >>> import jax.numpy as jnp, fsjax
      >>> out = fsjax.ops.normalize(fsjax.Image(jnp.array([[0.2, 0.3], [0.4, 0.6]])))
      >>> [round(float(v), 12) for v in out.data.ravel()]
      [0.0, 0.25, 0.5, 1.0]
      >>> float(fsjax.ops.normalize(fsjax.Image(jnp.full((2, 2), 0.7))).data.max())
      0.0
    """
    x = img.data
    lo = jnp.min(x)
    rng = jnp.max(x) - lo
    ok = rng > 0
    safe = jnp.where(ok, rng, jnp.ones_like(rng))
    return Image(jnp.where(ok, (x - lo) / safe, jnp.zeros_like(x)))


@register(family="point", takes=Image, gives=Image, knobs={"c": LogKnob(0.1, 100.0)},
          differentiable=True,
          refs=["R. C. Gonzalez, R. E. Woods, Digital Image Processing, 4th ed., Pearson, 2018, sec. 3.2"])
def log_transform(img: Image, /, *, c: float = 10.0) -> Image:
    """Logarithmic curve ``out = log(1 + c x) / log(1 + c)``, odd-extended to ``x < 0``.

    Compresses bright values and expands dark ones; fixes 0 and 1. ``c -> 0``
    tends to the identity; larger ``c`` bends more. For negative input
    ``out = -f(-x)`` (continuous slope ``c / log(1 + c)`` at 0).
    :func:`exp_transform` with the same ``c`` is its exact inverse.

    Args:
      img: input image ``(H, W)``.
      c: curvature, > 0 (knob ``a``, log-mapped to [0.1, 100]); default 10.

    Returns:
      ``Image``; ``[0, 1]`` maps onto ``[0, 1]``.

    Reference: ``numpy.log1p(c x) / numpy.log1p(c)``, matched to 1e-15 in float64.

    Example:
      With ``c = e - 1`` the denominator is 1, so ``out = log(1 + (e - 1) x)``:

      >>> import math, jax.numpy as jnp, fsjax
      >>> out = fsjax.ops.log_transform(fsjax.Image(jnp.array([[0.0, 1.0]])), c=math.e - 1)
      >>> [round(float(v), 12) for v in out.data.ravel()]
      [0.0, 1.0]
      >>> x = 0.5
      >>> v = fsjax.ops.log_transform(fsjax.Image(jnp.full((1, 1), x)), c=math.e - 1).data[0, 0]
      >>> abs(float(v) - math.log(1 + (math.e - 1) * x)) < 1e-12
      True
    """
    check_positive("log_transform", "c", c)
    x = img.data
    pos = x >= 0
    xp = jnp.where(pos, x, jnp.zeros_like(x))  # split so the slope at 0 is c / log(1 + c)
    xn = jnp.where(pos, jnp.zeros_like(x), x)
    out = (jnp.log1p(c * xp) - jnp.log1p(-c * xn)) / jnp.log1p(c)
    return Image(out.astype(x.dtype))


@register(family="point", takes=Image, gives=Image, knobs={"c": LogKnob(0.1, 100.0)},
          differentiable=True,
          refs=["R. C. Gonzalez, R. E. Woods, Digital Image Processing, 4th ed., Pearson, 2018, sec. 3.2"])
def exp_transform(img: Image, /, *, c: float = 10.0) -> Image:
    """Exponential curve, the inverse of :func:`log_transform`: ``out = ((1 + c) ** x - 1) / c``.

    Written as ``expm1(x log(1 + c)) / c`` and odd-extended to ``x < 0``. Expands
    bright values and compresses dark ones; fixes 0 and 1.

    Args:
      img: input image ``(H, W)``.
      c: curvature, > 0 (knob ``a``, log-mapped to [0.1, 100]); default 10.

    Returns:
      ``Image``; ``[0, 1]`` maps onto ``[0, 1]``. Far outside ``[0, 1]`` the curve overflows:
      ``+inf`` (``-inf`` on the odd extension) where ``|x| log(1 + c)`` exceeds the log of the
      dtype's largest value (88.7 in float32, 709.8 in float64), as ``numpy.expm1`` does;
      never NaN.

    Reference: ``numpy.expm1(x * numpy.log1p(c)) / c``, matched to 1e-15 in float64;
    ``exp_transform(log_transform(x, c), c) == x`` to 1e-15.

    Example:
      With ``c = 3``: ``out = (4 ** x - 1) / 3``, so ``x = 0.5`` gives ``1 / 3``:

      >>> import jax.numpy as jnp, fsjax
      >>> out = fsjax.ops.exp_transform(fsjax.Image(jnp.full((1, 1), 0.5)), c=3.0)
      >>> abs(float(out.data[0, 0]) - 1 / 3) < 1e-12
      True
    """
    check_positive("exp_transform", "c", c)
    x = img.data
    pos = x >= 0
    xp = jnp.where(pos, x, jnp.zeros_like(x))  # split so the slope at 0 is log(1 + c) / c
    xn = jnp.where(pos, jnp.zeros_like(x), x)
    k = jnp.log1p(c)
    out = (jnp.expm1(xp * k) - jnp.expm1(-xn * k)) / c
    return Image(out.astype(x.dtype))


# ---------------------------------------------------------------------------
# Two-input arithmetic
# ---------------------------------------------------------------------------


@register(family="point", takes=(Image, Image), gives=Image, differentiable=False,
          refs=["MVTec HALCON reference: abs_diff_image"])
def abs_diff(img1: Image, img2: Image, /) -> Image:
    """Absolute difference of two images: ``out = |x - y|``.

    Not declared differentiable: ``|.|`` has a kink where the images agree (its
    gradient there is reported as 0).

    Args:
      img1: first image ``(H, W)``.
      img2: second image, same shape.

    Returns:
      ``Image`` in ``[0, 1]`` for inputs in ``[0, 1]``.

    Same as HALCON ``abs_diff_image(Mult=1)`` and ``numpy.abs(x - y)`` (exact).

    Example:
      >>> import jax.numpy as jnp, fsjax
      >>> a = fsjax.Image(jnp.array([[0.25, 0.75]]))
      >>> b = fsjax.Image(jnp.array([[0.5, 0.5]]))
      >>> [float(v) for v in fsjax.ops.abs_diff(a, b).data.ravel()]
      [0.25, 0.25]
    """
    _check_same_shape("abs_diff", img1, img2)
    return Image(jnp.abs(img1.data - img2.data))


@register(family="point", takes=(Image, Image), gives=Image,
          knobs={"offset": LinKnob(-0.5, 0.5), "scale": LinKnob(0.25, 2.0)}, differentiable=True,
          refs=["MVTec HALCON reference: add_image"])
def add_images(img1: Image, img2: Image, /, *, offset: float = 0.0, scale: float = 0.5) -> Image:
    """Scaled sum of two images: ``out = (x + y) * scale + offset`` (HALCON ``add_image``).

    The defaults (``scale = 0.5``, ``offset = 0``) give the mean of the two images,
    as HALCON's ``Mult = 0.5, Add = 0`` does.

    Args:
      img1: first image ``(H, W)``.
      img2: second image, same shape.
      offset: added after scaling, on the ``[0, 1]`` grey scale (knob ``a``, linear
        on [-0.5, 0.5]); HALCON's ``Add`` divided by 255.
      scale: multiplies the sum, > 0 (knob ``b``, linear on [0.25, 2]); HALCON's ``Mult``.

    Returns:
      ``Image``; values may leave ``[0, 1]`` (no saturation, unlike HALCON byte images).

    Reference: the formula of HALCON ``add_image``; exact against NumPy.

    Example:
      >>> import jax.numpy as jnp, fsjax
      >>> a = fsjax.Image(jnp.full((2, 2), 0.25))
      >>> b = fsjax.Image(jnp.full((2, 2), 0.75))
      >>> float(fsjax.ops.add_images(a, b).data[0, 0])
      0.5
      >>> float(fsjax.ops.add_images(a, b, scale=1.0, offset=-0.5).data[0, 0])
      0.5
    """
    _check_same_shape("add_images", img1, img2)
    check_range("add_images", "offset", offset)
    check_positive("add_images", "scale", scale)
    dt = jnp.result_type(img1.data, img2.data)  # both inputs' precision, as JAX promotes
    return Image(((img1.data + img2.data) * scale + offset).astype(dt))


@register(family="point", takes=(Image, Image), gives=Image,
          knobs={"offset": LinKnob(0.0, 1.0), "scale": LinKnob(0.25, 2.0)}, differentiable=True,
          refs=["MVTec HALCON reference: sub_image"])
def sub_images(img1: Image, img2: Image, /, *, offset: float = 0.5, scale: float = 1.0) -> Image:
    """Scaled difference of two images: ``out = (x - y) * scale + offset`` (HALCON ``sub_image``).

    The defaults (``scale = 1``, ``offset = 0.5``) are HALCON's ``Mult = 1,
    Add = 128`` on the ``[0, 1]`` scale: equal images give mid-grey 0.5, and the
    signed difference stays visible. Use ``offset=0`` for the plain difference.

    Args:
      img1: minuend image ``(H, W)``.
      img2: subtrahend image, same shape.
      offset: added after scaling (knob ``a``, linear on [0, 1]); default 0.5.
      scale: multiplies the difference, > 0 (knob ``b``, linear on [0.25, 2]).

    Returns:
      ``Image``; signed difference shifted by ``offset``; values may leave ``[0, 1]``.

    Reference: the formula of HALCON ``sub_image``; exact against NumPy.

    Example:
      >>> import jax.numpy as jnp, fsjax
      >>> a = fsjax.Image(jnp.full((2, 2), 0.75))
      >>> b = fsjax.Image(jnp.full((2, 2), 0.25))
      >>> float(fsjax.ops.sub_images(a, b).data[0, 0])
      1.0
      >>> float(fsjax.ops.sub_images(b, a, offset=0.0, scale=2.0).data[0, 0])
      -1.0
    """
    _check_same_shape("sub_images", img1, img2)
    check_range("sub_images", "offset", offset)
    check_positive("sub_images", "scale", scale)
    dt = jnp.result_type(img1.data, img2.data)  # both inputs' precision, as JAX promotes
    return Image(((img1.data - img2.data) * scale + offset).astype(dt))


# ---------------------------------------------------------------------------
# Histogram equalisation
# ---------------------------------------------------------------------------


def _histogram_equal_bins(x, nbins: int):
    """Counts of ``x`` in ``nbins`` equal bins over ``[min x, max x]`` and the bin centres.

    Follows ``numpy.histogram(x, bins=nbins, range=(x.min(), x.max()))`` exactly:
    the last bin is closed, and a zero-width range is widened to
    ``[v - 0.5, v + 0.5]``.
    """
    flat = x.reshape(-1)
    lo0, hi0 = jnp.min(flat), jnp.max(flat)
    const = hi0 <= lo0
    lo = jnp.where(const, lo0 - 0.5, lo0)
    hi = jnp.where(const, hi0 + 0.5, hi0)
    # edges as numpy.linspace computes them: start + k * step, last edge = stop
    k = jnp.arange(nbins + 1, dtype=flat.dtype)
    edges = (k * ((hi - lo) / nbins) + lo).at[-1].set(hi)
    idx = jnp.floor((flat - lo) / (hi - lo) * nbins).astype(jnp.int32)
    idx = jnp.clip(idx, 0, nbins - 1)
    # numpy's corrections for rounding at the edges
    idx = jnp.where(flat < edges[idx], idx - 1, idx)
    idx = jnp.where((flat >= edges[jnp.clip(idx + 1, 0, nbins)]) & (idx != nbins - 1), idx + 1, idx)
    idx = jnp.clip(idx, 0, nbins - 1)
    counts = jax.ops.segment_sum(jnp.ones_like(flat), idx, num_segments=nbins)
    centers = 0.5 * (edges[:-1] + edges[1:])
    return counts, centers


@register(family="point", takes=Image, gives=Image, differentiable=False,
          refs=["R. C. Gonzalez, R. E. Woods, Digital Image Processing, 4th ed., Pearson, 2018, sec. 3.3",
                "skimage.exposure.equalize_hist"])
def equalize_hist(img: Image, /, *, nbins: int = 256) -> Image:
    """Histogram equalisation: map each grey value through the image's cumulative histogram.

    The histogram has ``nbins`` equal-width bins spanning ``[min x, max x]`` (last
    bin closed, NumPy's convention); ``cdf_k`` is the fraction of pixels in bins
    ``0..k``; each pixel becomes the CDF linearly interpolated at its value
    between bin centres (clamped to ``cdf_0`` below the first centre and to 1
    above the last). Not differentiable (a histogram is piecewise constant).

    Args:
      img: input image ``(H, W)``.
      nbins: number of histogram bins, a static int in [2, 65536] (it fixes an
        array shape, so it is not a knob); default 256 as in scikit-image.

    Returns:
      ``Image`` in ``(0, 1]``: the maximum maps to 1, the output histogram is
      approximately flat. A constant image maps to the CDF at its own value,
      which is 0.5 for even ``nbins`` (NumPy widens a zero-width range by
      ``+/- 0.5``, as scikit-image does).

    Matches ``skimage.exposure.equalize_hist(x, nbins)`` on float images to 1e-12
    in float64 (same bins, same interpolation).

    Example:
      Four distinct values with two bins: values ``0, 0.25`` fall in bin 0 and
      ``0.75, 1`` in bin 1; centres ``0.25, 0.75`` carry CDF ``0.5, 1``, so the
      interpolated outputs are ``0.5, 0.5, 1, 1``:

      >>> import jax.numpy as jnp, fsjax
      >>> img = fsjax.Image(jnp.array([[0.0, 0.25], [0.75, 1.0]]))
      >>> [float(v) for v in fsjax.ops.equalize_hist(img, nbins=2).data.ravel()]
      [0.5, 0.5, 1.0, 1.0]
    """
    nbins = check_static_int("equalize_hist", "nbins", nbins, lo=2, hi=65536)
    x = img.data
    counts, centers = _histogram_equal_bins(x, nbins)
    cdf = jnp.cumsum(counts)
    cdf = cdf / cdf[-1]
    out = jnp.interp(x.reshape(-1), centers, cdf).reshape(x.shape)
    return Image(out.astype(x.dtype))
