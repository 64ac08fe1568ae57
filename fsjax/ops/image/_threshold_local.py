"""Local (adaptive) thresholds and hysteresis (``Image -> Region``).

Split from :mod:`fsjax.ops.image._threshold` (global histogram methods); the
conventions stated there apply: bright side ``x > T`` unless an op says
otherwise; square ``(2 radius + 1)^2`` windows with SciPy boundary mode names
(default ``"reflect"``); a traced ``radius`` knob uses the static
``max_radius`` support with exact-zero weights outside the window, so the
result is bit-identical to the concrete call (a traced radius above
``max_radius`` is clipped to it); local standard deviation is
``sqrt(max(E[x^2] - E[x]^2, 0))``; hysteresis propagates through 8-connected
(default) or 4-connected neighbours with a ``lax.while_loop`` to the fixed
point.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from ..._checks import check_choice, check_positive, check_range, check_static_int, note_traced
from ...registry import IntKnob, LinKnob, register
from ...types import Image, Region, is_concrete
from .._common import check_kernel_extent, check_mode, correlate1d

__all__ = [
    "local_mean",
    "sauvola",
    "niblack",
    "hysteresis",
    "dyn_threshold",
]

# ---------------------------------------------------------------------------
# Local (adaptive) thresholds
# ---------------------------------------------------------------------------


def _check_radius(op: str, radius, max_radius, shape) -> int:
    """Check ``radius``; return the static support for a traced one.

    A concrete radius must be an integer in ``[1, side]`` (side = the image's larger side:
    the cost bound). A traced radius's support is ``max_radius`` clipped to the side; a
    traced value outside ``[1, support]`` or not an integer is recorded for the registry,
    which fails the call closed (these ops give a ``Region``: it raises at run time) instead
    of computing a clamped window.
    """
    max_radius = check_static_int(op, "max_radius", max_radius, 1)
    side = max(int(v) for v in shape[-2:])
    if is_concrete(radius):
        r = np.asarray(radius, dtype=float)
        if r.ndim or not np.isfinite(r) or r < 1 or r != np.round(r):
            raise ValueError(f"{op}: argument 'radius' must be an integer >= 1, got {radius}")
        check_kernel_extent(op, "radius", int(r), shape)
        return max_radius
    R = min(max_radius, side)
    rv = jnp.asarray(radius)
    note_traced(radius, ~((rv >= 1) & (rv <= R) & (rv == jnp.round(rv))))
    return R


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
    max_radius = _check_radius("local_mean", radius, max_radius, img.data.shape)
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
    max_radius = _check_radius("sauvola", radius, max_radius, img.data.shape)
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
    max_radius = _check_radius("niblack", radius, max_radius, img.data.shape)
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
    max_radius = _check_radius("dyn_threshold", radius, max_radius, img.data.shape)
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
    return Region(_hysteresis_core(img.data, low, high, connectivity, steps))


@functools.partial(jax.jit, static_argnums=(3, 4))
def _hysteresis_core(x, low, high, connectivity: int, steps: int):
    # one compiled program per shape/dtype and static settings: a while_loop built from fresh
    # closures outside jit would be traced and compiled again on every eager call
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
    return out

