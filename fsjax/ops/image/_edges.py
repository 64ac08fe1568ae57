"""Derivatives, edge detectors and structure-tensor measures.

Conventions (stated once for the whole family):

* Arrays are ``(row, col)``; pixel centres sit on integer indices. Derivatives
  use image axes: ``x`` is the column index (increasing to the right), ``y`` is
  the row index (increasing downwards). ``gx = d/dcol``, ``gy = d/drow``; a grey
  value increasing to the right has ``gx > 0``.
* Boundary: SciPy mode names, default ``"reflect"`` (half-sample symmetric
  ``d c b a | a b c d``); ``"constant"`` pads with 0. See
  :mod:`fsjax.ops._common`.
* Scaling: every gradient operator is *normalised to physical slope*, so a
  linear ramp ``f = a * row + b * col`` gives ``gy = a``, ``gx = b`` (grey value
  per pixel) away from the border. The 3x3 operators are therefore the SciPy /
  OpenCV kernels divided by their ramp gain: Sobel ``/ 8``, Prewitt ``/ 6``,
  Scharr ``/ 32``. Second derivatives (Laplacian, LoG) are in grey value per
  pixel squared, with SciPy's scaling (no division).
* Gaussian derivative kernels are SciPy's: the sampled Gaussian truncated at
  ``int(truncate * sigma + 0.5)`` taps and normalised to sum 1, multiplied by
  the Hermite factor of the derivative order (``-k / s^2`` for order 1,
  ``(k^2 - s^2) / s^4`` for order 2). A *traced* sigma (knob) uses the static
  tap count of ``max_sigma`` with zero weight beyond the sigma-dependent
  radius, so it gives the same numbers as a concrete sigma.
* Value range: derivative, Laplacian, LoG, DoG, Harris and eigenvalue outputs
  are SIGNED responses (or magnitudes that may exceed 1) returned as ``Image``;
  the ``[0, 1]`` convention of ``Image`` does not hold for them and they are
  never clipped. ``sobel_dir`` is an angle in radians in ``(-pi, pi]`` and NaN
  where the gradient is zero up to rounding (direction undefined).
* Gradient magnitudes are ``sqrt(gx^2 + gy^2)`` with a safe square root: the
  value is exact and the gradient is 0 (a subgradient) where both are 0.
* Structure tensor: ``J = G_sigma * [[gy^2, gx gy], [gx gy, gx^2]]`` built from
  the normalised Sobel derivatives (as scikit-image, up to its ``8^2`` scale).
* Canny (in :mod:`fsjax.ops.image._edges_canny`) returns a ``Region``; pixels on the one-pixel image frame are never
  edges (their non-maximum-suppression neighbourhood is incomplete), as in
  scikit-image.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ..._checks import check_choice, check_positive, check_range
from ...registry import LinKnob, LogKnob, register
from ...types import Image, is_concrete
from .._common import (
    check_kernel_extent,
    check_mode,
    correlate1d,
    correlate1d_antisymmetric,
    support_exceeded,
)
from ._filters import _gaussian_radius, gaussian_weights

__all__ = [
    "sobel_amp",
    "sobel_dir",
    "prewitt_amp",
    "scharr_amp",
    "laplace",
    "log",
    "dog",
    "gauss_deriv",
    "harris",
    "shi_tomasi",
    "structure_coherence",
]

_SIGMA_KNOB = LogKnob(0.5, 8.0, unit="px")
_SMALL_SIGMA_KNOB = LogKnob(0.5, 4.0, unit="px")

# Smoothing taps of the 3x3 gradient operators, each normalised to sum 1; the
# derivative taps are the central difference [-1, 0, 1] / 2 (slope per pixel).
_SMOOTH = {
    "sobel": (0.25, 0.5, 0.25),
    "prewitt": (1.0 / 3.0, 1.0 / 3.0, 1.0 / 3.0),
    "scharr": (3.0 / 16.0, 10.0 / 16.0, 3.0 / 16.0),
}
_DIFF = (-0.5, 0.0, 0.5)


# --- private helpers -------------------------------------------------------


def _taps(values, x):
    return jnp.asarray(values, dtype=x.dtype)


def _grad3(x: Float[Array, "H W"], kind: str, mode: str):
    """Normalised 3x3 gradient ``(gy, gx)`` of operator ``kind`` (separable)."""
    s, d = _taps(_SMOOTH[kind], x), _taps(_DIFF, x)
    gx = correlate1d(correlate1d(x, s, axis=-2, mode=mode), d, axis=-1, mode=mode)
    gy = correlate1d(correlate1d(x, d, axis=-2, mode=mode), s, axis=-1, mode=mode)
    return gy, gx


def _safe_hypot(a, b):
    """``sqrt(a^2 + b^2)`` with a finite zero gradient where both are 0 (double where)."""
    m2 = a * a + b * b
    pos = m2 > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, m2, 1.0)), 0.0)


def _gauss_taps(sigma, order: int, truncate: float, max_sigma: float, dtype):
    """SciPy's Gaussian (derivative) correlation taps, static length, traced-sigma safe."""
    phi = gaussian_weights(sigma, truncate, max_sigma)
    r = phi.shape[0] // 2
    k = jnp.arange(-r, r + 1, dtype=phi.dtype)
    s2 = jnp.asarray(sigma, dtype=phi.dtype) ** 2
    if order == 0:
        w = phi
    elif order == 1:
        # d/dk of the Gaussian is -k/s^2 phi; as *correlation* taps (flipped) it is +k/s^2 phi
        w = k / s2 * phi
    else:
        w = (k * k - s2) / (s2 * s2) * phi
    return w.astype(dtype)


def _gauss_filter(x, sigma, orders, truncate, max_sigma, mode):
    """Separable Gaussian (derivative) filter; ``orders = (row_order, col_order)``."""
    wr = _gauss_taps(sigma, orders[0], truncate, max_sigma, x.dtype)
    wc = _gauss_taps(sigma, orders[1], truncate, max_sigma, x.dtype)
    # first-order taps are exactly antisymmetric (k phi_k with phi symmetric): summed as
    # mirrored differences, a constant image has exactly zero derivative in every program
    def along(v, w, order, axis):
        if order == 1:
            return correlate1d_antisymmetric(v, w, axis=axis, mode=mode)
        return correlate1d(v, w, axis=axis, mode=mode)

    out = along(along(x, wr, orders[0], -2), wc, orders[1], -1)
    return _poison_wide(out, sigma, truncate, wr.shape[0] // 2)


def _poison_wide(out, sigma, truncate, radius):
    """NaN where a traced sigma needs more than the static ``radius`` taps (fail closed)."""
    bad = support_exceeded(sigma, truncate, radius)
    return out if bad is None else jnp.where(bad, jnp.nan, out)


def _check_sigma(op, sigma, truncate, mode, shape=None):
    check_positive(op, "sigma", sigma)
    check_positive(op, "truncate", truncate)
    check_mode(op, mode)
    if shape is not None and is_concrete(sigma):
        check_kernel_extent(op, "sigma", int(truncate * float(np.max(np.asarray(sigma))) + 0.5), shape)


def _structure_tensor(x, sigma, truncate, max_sigma, mode):
    """``(Jrr, Jrc, Jcc)``: Gaussian-weighted products of normalised Sobel derivatives."""
    gy, gx = _grad3(x, "sobel", mode)
    w = _gauss_taps(sigma, 0, truncate, max_sigma, x.dtype)

    def smooth(v):
        return correlate1d(correlate1d(v, w, axis=-2, mode=mode), w, axis=-1, mode=mode)

    r = w.shape[0] // 2
    return tuple(_poison_wide(smooth(v), sigma, truncate, r) for v in (gy * gy, gx * gy, gx * gx))


# --- 3x3 gradient operators ------------------------------------------------


_RAMP_EXAMPLE = """
      A ramp ``f = 0.03 row + 0.04 col`` has slope ``hypot(0.03, 0.04) = 0.05``
      grey value per pixel everywhere away from the border:

      >>> import jax.numpy as jnp, fsjax
      >>> r, c = jnp.mgrid[0:16, 0:16]
      >>> img = fsjax.Image(0.03 * r + 0.04 * c)
      >>> out = fsjax.ops.{name}(img)
      >>> round(float(out.data[8, 8]), 9)
      0.05
"""


def _amp_doc(fn):
    fn.__doc__ = fn.__doc__.replace("{EXAMPLE}", _RAMP_EXAMPLE.format(name=fn.__name__).strip("\n"))
    return fn


@register(family="edges", takes=Image, gives=Image, differentiable=True,
          refs=["I. Sobel and G. Feldman, 'A 3x3 isotropic gradient operator for image processing', "
                "talk at the Stanford Artificial Intelligence Project, 1968",
                "R. O. Duda and P. E. Hart, Pattern Classification and Scene Analysis, Wiley, 1973"])
@_amp_doc
def sobel_amp(img: Image, /, *, mode: str = "reflect") -> Image:
    """Gradient magnitude of the 3x3 Sobel operator, in grey value per pixel.

    ``gx = ([1, 2, 1]^T / 4) (x) ([-1, 0, 1] / 2)`` correlated with the image (and
    its transpose for ``gy``); ``out = sqrt(gx^2 + gy^2)``. The kernel is SciPy's
    ``ndimage.sobel`` divided by 8, so a unit ramp gives slope 1.

    Args:
      img: input image ``(H, W)``.
      mode: boundary mode (SciPy names); default ``"reflect"``.

    Returns:
      ``Image`` of gradient magnitudes ``>= 0`` (grey value / pixel; may exceed 1,
      not clipped).

    Matches ``np.hypot(ndi.sobel(x, 0, mode=mode), ndi.sobel(x, 1, mode=mode)) / 8``
    to 1e-12 in float64. ``skimage.filters.sobel`` (same mode) equals
    ``sqrt(2) * sobel_amp``: its kernel is ``/ 4`` instead of ``/ 8`` and it
    divides the magnitude by ``sqrt(ndim)``.

    Example:
{EXAMPLE}
    """
    check_mode("sobel_amp", mode)
    gy, gx = _grad3(img.data, "sobel", mode)
    return Image(_safe_hypot(gx, gy))


@register(family="edges", takes=Image, gives=Image, differentiable=False,
          refs=["I. Sobel and G. Feldman, 'A 3x3 isotropic gradient operator for image processing', "
                "talk at the Stanford Artificial Intelligence Project, 1968"])
def sobel_dir(img: Image, /, *, mode: str = "reflect") -> Image:
    """Gradient direction of the 3x3 Sobel operator, radians in ``(-pi, pi]``.

    ``out = atan2(gy, gx)``: the angle from the +col axis towards the +row axis
    (clockwise on screen, since rows go down) of the direction in which grey
    values increase. A ramp increasing to the right gives 0, downwards
    ``pi / 2``, to the left ``pi``. Where the gradient is zero up to rounding
    (``|gx| + |gy| <= 8 eps sum_i |w_i x_i|`` over the 3x3 taps, e.g. a flat or
    exactly balanced neighbourhood) the direction is undefined and the output
    is NaN; mask it with :func:`sobel_amp`.

    Not differentiable: undefined on flat regions and discontinuous across the
    ``+-pi`` cut (``differentiable=False``; its gradient is nevertheless finite).

    Args:
      img: input image ``(H, W)``.
      mode: boundary mode (SciPy names); default ``"reflect"``.

    Returns:
      ``Image`` of angles in radians (signed; NaN where undefined).

    Matches ``np.arctan2(ndi.sobel(x, 0), ndi.sobel(x, 1))`` to 1e-12 where the
    gradient is above rounding level.

    Example:
      A ramp rising along the direction 0.5 rad (from +col towards +row):

      >>> import jax.numpy as jnp, numpy as np, fsjax
      >>> r, c = jnp.mgrid[0:16, 0:16]
      >>> img = fsjax.Image(0.02 * (np.cos(0.5) * c + np.sin(0.5) * r))
      >>> round(float(fsjax.ops.sobel_dir(img).data[8, 8]), 9)
      0.5
      >>> bool(jnp.isnan(fsjax.ops.sobel_dir(fsjax.Image(jnp.ones((5, 5)))).data[2, 2]))
      True
    """
    check_mode("sobel_dir", mode)
    x = img.data
    gy, gx = _grad3(x, "sobel", mode)
    # Rounding bound of gx, gy: sum_i |w_i| |x_i| over the 3x3 taps (the same for
    # both, by symmetry). Below 8 eps times it, the direction is rounding noise.
    a = jnp.abs(x)
    s, d = _taps(_SMOOTH["sobel"], x), _taps((0.5, 0.0, 0.5), x)
    bound = correlate1d(correlate1d(a, s, axis=-2, mode=mode), d, axis=-1, mode=mode)
    bound = bound + correlate1d(correlate1d(a, d, axis=-2, mode=mode), s, axis=-1, mode=mode)
    flat = jnp.abs(gx) + jnp.abs(gy) <= 8 * jnp.finfo(x.dtype).eps * bound
    # + 0.0 turns -0.0 into +0.0 so the range is (-pi, pi], not [-pi, pi]
    ang = jnp.arctan2(jnp.where(flat, 0.0, gy) + 0.0, jnp.where(flat, 1.0, gx))
    return Image(jnp.where(flat, jnp.nan, ang))


@register(family="edges", takes=Image, gives=Image, differentiable=True,
          refs=["J. M. S. Prewitt, 'Object enhancement and extraction', in Picture Processing and "
                "Psychopictorics, B. S. Lipkin and A. Rosenfeld (eds.), Academic Press, 1970"])
@_amp_doc
def prewitt_amp(img: Image, /, *, mode: str = "reflect") -> Image:
    """Gradient magnitude of the 3x3 Prewitt operator, in grey value per pixel.

    Like :func:`sobel_amp` with the box smoothing ``[1, 1, 1] / 3`` across the
    derivative direction: SciPy's ``ndimage.prewitt`` divided by 6.

    Args:
      img: input image ``(H, W)``.
      mode: boundary mode (SciPy names); default ``"reflect"``.

    Returns:
      ``Image`` of gradient magnitudes ``>= 0`` (grey value / pixel, not clipped).

    Matches ``np.hypot(ndi.prewitt(x, 0), ndi.prewitt(x, 1)) / 6`` to 1e-12;
    ``skimage.filters.prewitt`` equals ``sqrt(2) * prewitt_amp`` (kernel ``/ 3``,
    magnitude ``/ sqrt(2)``).

    Example:
{EXAMPLE}
    """
    check_mode("prewitt_amp", mode)
    gy, gx = _grad3(img.data, "prewitt", mode)
    return Image(_safe_hypot(gx, gy))


@register(family="edges", takes=Image, gives=Image, differentiable=True,
          refs=["H. Scharr, Optimale Operatoren in der digitalen Bildverarbeitung, PhD thesis, "
                "Universitaet Heidelberg, 2000",
                "B. Jaehne, H. Scharr and S. Koerkel, 'Principles of filter design', in Handbook of "
                "Computer Vision and Applications, vol. 2, Academic Press, 1999"])
@_amp_doc
def scharr_amp(img: Image, /, *, mode: str = "reflect") -> Image:
    """Gradient magnitude of the 3x3 Scharr operator, in grey value per pixel.

    Like :func:`sobel_amp` with the rotation-optimised smoothing ``[3, 10, 3] / 16``:
    OpenCV's ``cv2.Scharr`` kernel divided by 32. More isotropic than Sobel.

    Args:
      img: input image ``(H, W)``.
      mode: boundary mode (SciPy names); default ``"reflect"``.

    Returns:
      ``Image`` of gradient magnitudes ``>= 0`` (grey value / pixel, not clipped).

    Matches ``np.hypot(cv2.Scharr(x, CV_64F, 0, 1), cv2.Scharr(x, CV_64F, 1, 0)) / 32``
    with ``borderType=cv2.BORDER_REFLECT`` (= SciPy ``"reflect"``) to 1e-12, and
    ``skimage.filters.scharr`` equals ``sqrt(2) * scharr_amp`` (kernel ``/ 16``,
    magnitude ``/ sqrt(2)``).

    Example:
{EXAMPLE}
    """
    check_mode("scharr_amp", mode)
    gy, gx = _grad3(img.data, "scharr", mode)
    return Image(_safe_hypot(gx, gy))


# --- Second derivatives and scale-space derivatives ------------------------


@register(family="edges", takes=Image, gives=Image, differentiable=True,
          refs=["R. Jain, R. Kasturi and B. G. Schunck, Machine Vision, McGraw-Hill, 1995, ch. 5"])
def laplace(img: Image, /, *, mode: str = "reflect") -> Image:
    """Discrete 5-point Laplacian ``d2/drow2 + d2/dcol2`` (grey value / pixel^2).

    ``out[i, j] = x[i-1, j] + x[i+1, j] + x[i, j-1] + x[i, j+1] - 4 x[i, j]``; exact
    for quadratics. Signed; not clipped.

    Args:
      img: input image ``(H, W)``.
      mode: boundary mode (SciPy names); default ``"reflect"``.

    Returns:
      Signed ``Image`` (zero on linear ramps, ``4 a`` on ``a (row^2 + col^2)``).

    Matches ``scipy.ndimage.laplace(x, mode=mode)`` to 1e-12.

    Example:
      ``f = 0.01 (row^2 + col^2)`` has Laplacian ``0.04`` everywhere:

      >>> import jax.numpy as jnp, fsjax
      >>> r, c = jnp.mgrid[0:9, 0:9]
      >>> out = fsjax.ops.laplace(fsjax.Image(0.01 * (r**2 + c**2)))
      >>> round(float(out.data[4, 4]), 12)
      0.04
    """
    check_mode("laplace", mode)
    x = img.data
    d2 = _taps((1.0, -2.0, 1.0), x)
    return Image(correlate1d(x, d2, axis=-2, mode=mode) + correlate1d(x, d2, axis=-1, mode=mode))


@register(family="edges", takes=Image, gives=Image, knobs={"sigma": LogKnob(1.0, 8.0, unit="px")},
          differentiable=True,
          refs=["D. Marr and E. Hildreth, 'Theory of edge detection', Proc. R. Soc. Lond. B 207, "
                "187-217, 1980"])
def log(img: Image, /, *, sigma: float = 2.0, truncate: float = 4.0, mode: str = "reflect",
        max_sigma: float = 8.0) -> Image:
    """Laplacian of Gaussian ``(d2/drow2 + d2/dcol2)(G_sigma * img)`` (grey value / pixel^2).

    Sum of two separable second-derivative-of-Gaussian filters (SciPy's sampled
    kernels, see the module docstring). Negative on the bright side of an edge,
    zero-crossing at the edge; not scale-normalised (multiply by ``sigma^2`` for
    that). Signed; not clipped.

    The sampled, truncated kernel does not sum to exactly zero, so a constant
    grey value ``c`` gives ``L c`` instead of 0 (SciPy's behaviour, kept for
    conformance): ``L = -1.12`` at ``sigma = 0.5`` (sampling error; hence the
    knob starts at 1), ``-1.4e-4`` at 1, ``-1.7e-4`` at 2, ``-8e-5`` at 4,
    ``-2.6e-5`` at 8 (``truncate=4``); ``truncate=6`` makes it negligible for
    ``sigma >= 1``. :func:`dog` has no such leak.

    Args:
      img: input image ``(H, W)``.
      sigma: Gaussian standard deviation in pixels, > 0 (knob ``a``, log-mapped to
        [1, 8]).
      truncate: kernel half-width in units of sigma.
      mode: boundary mode (SciPy names); default ``"reflect"``.
      max_sigma: static bound on a traced sigma (fixes the tap count).

    Returns:
      Signed ``Image``.

    Matches ``scipy.ndimage.gaussian_laplace(x, sigma, mode=mode, truncate=truncate)``
    to 1e-12 in float64.

    Example:
      On ``f = 0.01 (row^2 + col^2)`` the Laplacian is 0.04; with the kernel
      truncated at ``6 sigma`` the sampled kernel reproduces it to ~1e-7:

      >>> import jax.numpy as jnp, fsjax
      >>> r, c = jnp.mgrid[0:41, 0:41]
      >>> img = fsjax.Image(0.01 * (r**2 + c**2))
      >>> abs(float(fsjax.ops.log(img, sigma=2.0, truncate=6.0).data[20, 20]) - 0.04) < 1e-6
      True

      With SciPy's default ``truncate=4`` the kernel's sum is not exactly 0, so a
      constant image of grey value 1 gives a small response (the DC leak):

      >>> round(float(fsjax.ops.log(fsjax.Image(jnp.ones((41, 41))), sigma=2.0).data[20, 20]), 6)
      -0.000173
    """
    _check_sigma("log", sigma, truncate, mode, img.data.shape)
    x = img.data
    out = (_gauss_filter(x, sigma, (2, 0), truncate, max_sigma, mode)
           + _gauss_filter(x, sigma, (0, 2), truncate, max_sigma, mode))
    return Image(out)


@register(family="edges", takes=Image, gives=Image,
          knobs={"sigma": LogKnob(0.5, 4.0, unit="px"), "ratio": LinKnob(1.1, 2.5)}, differentiable=True,
          refs=["D. Marr and E. Hildreth, 'Theory of edge detection', Proc. R. Soc. Lond. B 207, "
                "187-217, 1980",
                "D. G. Lowe, 'Distinctive image features from scale-invariant keypoints', IJCV 60(2), "
                "91-110, 2004"])
def dog(img: Image, /, *, sigma: float = 1.0, ratio: float = 1.6, truncate: float = 4.0,
        mode: str = "reflect", max_sigma: float = 10.0) -> Image:
    """Difference of Gaussians ``G_sigma * img - G_(ratio sigma) * img`` (band-pass).

    Positive on the bright side of an edge and on small bright blobs. For ``ratio``
    close to 1 it approximates ``-(ratio - 1) sigma^2`` times the Laplacian of
    Gaussian; Marr and Hildreth recommend ``ratio = 1.6``. Signed; not clipped.

    Args:
      img: input image ``(H, W)``.
      sigma: the smaller standard deviation in pixels, > 0 (knob ``a``, log-mapped
        to [0.5, 4]).
      ratio: the larger sigma divided by the smaller one, > 1 (knob ``b``, linear
        in [1.1, 2.5]).
      truncate: kernel half-width in units of sigma (SciPy's rule, each kernel).
      mode: boundary mode (SciPy names); default ``"reflect"``.
      max_sigma: static bound on a traced ``ratio * sigma`` (fixes the tap count).

    Returns:
      Signed ``Image`` (grey value); zero on linear ramps.

    Matches ``gaussian_filter(x, s) - gaussian_filter(x, ratio s)`` (SciPy) to 1e-12
    and ``skimage.filters.difference_of_gaussians(x, s, ratio s, mode=mode)``.

    Example:
      On ``f = a (row^2 + col^2)`` Gaussian smoothing adds ``2 a sigma^2``, so the
      DoG is ``2 a sigma^2 (1 - ratio^2)``: ``-0.006`` for ``a = 0.001``, ``sigma = 1``,
      ``ratio = 2`` (the sampled kernels agree to ~1e-6):

      >>> import jax.numpy as jnp, fsjax
      >>> r, c = jnp.mgrid[0:41, 0:41]
      >>> out = fsjax.ops.dog(fsjax.Image(0.001 * (r**2 + c**2)), sigma=1.0, ratio=2.0)
      >>> abs(float(out.data[20, 20]) - (-0.006)) < 1e-5
      True
    """
    _check_sigma("dog", sigma, truncate, mode, img.data.shape)
    check_range("dog", "ratio", ratio, 1.0, None, lo_open=True)
    x = img.data
    if is_concrete(sigma) and is_concrete(ratio):
        check_kernel_extent("dog", "ratio", int(truncate * float(sigma) * float(ratio) + 0.5), img.data.shape)
    s2 = jnp.asarray(sigma) * ratio
    out = (_gauss_filter(x, sigma, (0, 0), truncate, max_sigma, mode)
           - _gauss_filter(x, s2, (0, 0), truncate, max_sigma, mode))
    return Image(out)


_COMPONENTS = ("x", "y", "xx", "xy", "yy", "amp")
_ORDERS = {"x": (0, 1), "y": (1, 0), "xx": (0, 2), "xy": (1, 1), "yy": (2, 0)}


@register(family="edges", takes=Image, gives=Image, knobs={"sigma": _SIGMA_KNOB}, differentiable=True,
          refs=["J. J. Koenderink, 'The structure of images', Biol. Cybern. 50, 363-370, 1984",
                "T. Lindeberg, Scale-Space Theory in Computer Vision, Kluwer, 1994"])
def gauss_deriv(img: Image, /, *, sigma: float = 1.0, component: str = "x", truncate: float = 4.0,
                mode: str = "reflect", max_sigma: float = 8.0) -> Image:
    """Gaussian derivative of the image: one partial derivative, or the gradient magnitude.

    ``component`` selects ``d/dx`` (``"x"``, along columns), ``d/dy`` (``"y"``,
    along rows), ``"xx"``, ``"xy"``, ``"yy"``, or ``"amp" = sqrt(gx^2 + gy^2)``, each
    of ``G_sigma * img`` with SciPy's sampled derivative kernels. Signed (except
    ``"amp"``); not clipped.

    Args:
      img: input image ``(H, W)``.
      sigma: Gaussian standard deviation in pixels, > 0 (knob ``a``, log-mapped to
        [0.5, 8]).
      component: static choice, one of ``"x"``, ``"y"``, ``"xx"``, ``"xy"``,
        ``"yy"``, ``"amp"``; default ``"x"``.
      truncate: kernel half-width in units of sigma.
      mode: boundary mode (SciPy names); default ``"reflect"``.
      max_sigma: static bound on a traced sigma (fixes the tap count).

    Returns:
      ``Image`` in grey value / pixel (first order, ``"amp"``) or / pixel^2
      (second order).

    Matches ``scipy.ndimage.gaussian_filter(x, sigma, order=(o_row, o_col))``
    (``"x"`` is ``order=(0, 1)``) and, for ``"amp"``,
    ``scipy.ndimage.gaussian_gradient_magnitude`` to 1e-12 in float64.

    Example:
      ``f = 0.03 row + 0.04 col``: the x-derivative is 0.04 up to the sampled
      kernel's variance error (~7e-5 relative at ``sigma = 1``):

      >>> import jax.numpy as jnp, fsjax
      >>> r, c = jnp.mgrid[0:21, 0:21]
      >>> img = fsjax.Image(0.03 * r + 0.04 * c)
      >>> round(float(fsjax.ops.gauss_deriv(img, sigma=1.0).data[10, 10]), 5)
      0.04
      >>> round(float(fsjax.ops.gauss_deriv(img, sigma=1.0, component="amp").data[10, 10]), 5)
      0.05
    """
    _check_sigma("gauss_deriv", sigma, truncate, mode, img.data.shape)
    check_choice("gauss_deriv", "component", component, _COMPONENTS)
    x = img.data
    if component == "amp":
        gx = _gauss_filter(x, sigma, (0, 1), truncate, max_sigma, mode)
        gy = _gauss_filter(x, sigma, (1, 0), truncate, max_sigma, mode)
        return Image(_safe_hypot(gx, gy))
    return Image(_gauss_filter(x, sigma, _ORDERS[component], truncate, max_sigma, mode))


# --- Structure tensor ------------------------------------------------------


@register(family="edges", takes=Image, gives=Image,
          knobs={"sigma": _SMALL_SIGMA_KNOB, "k": LinKnob(0.02, 0.2)}, differentiable=True,
          refs=["C. Harris and M. Stephens, 'A combined corner and edge detector', Proc. 4th Alvey "
                "Vision Conference, 147-151, 1988"])
def harris(img: Image, /, *, sigma: float = 1.0, k: float = 0.05, truncate: float = 4.0,
           mode: str = "reflect", max_sigma: float = 4.0) -> Image:
    """Harris-Stephens corner response ``det(J) - k tr(J)^2`` of the structure tensor.

    ``J = G_sigma * [[gy^2, gx gy], [gx gy, gx^2]]`` with normalised Sobel
    derivatives (grey value / pixel). Large positive at corners, negative on
    straight edges, near zero on flat regions. Signed, in (grey value / pixel)^4.

    Args:
      img: input image ``(H, W)``.
      sigma: integration (window) scale in pixels, > 0 (knob ``a``, log-mapped to
        [0.5, 4]).
      k: sensitivity, >= 0 (knob ``b``, linear in [0.02, 0.2]); 0.04-0.06 is usual.
      truncate: Gaussian window half-width in units of sigma.
      mode: boundary mode for both derivative and window (SciPy names).
      max_sigma: static bound on a traced sigma (fixes the tap count).

    Returns:
      Signed ``Image`` of corner responses.

    Matches ``skimage.feature.corner_harris(x, method="k", k=k, sigma=sigma)``
    divided by ``8^4`` (scikit-image uses the unnormalised Sobel kernel) with
    ``mode="constant"`` (scikit-image's fixed boundary), to 1e-12 relative.

    Example:
      On the ramp ``f = 0.03 row + 0.04 col``, ``J = [[a^2, ab], [ab, b^2]]`` has
      ``det = 0`` and ``tr = 0.0025``, so the response is ``-k 0.0025^2``:

      >>> import jax.numpy as jnp, fsjax
      >>> r, c = jnp.mgrid[0:25, 0:25]
      >>> out = fsjax.ops.harris(fsjax.Image(0.03 * r + 0.04 * c), sigma=1.0, k=0.05)
      >>> abs(float(out.data[12, 12]) - (-0.05 * 0.0025**2)) < 1e-15
      True
    """
    _check_sigma("harris", sigma, truncate, mode, img.data.shape)
    check_range("harris", "k", k, 0.0, None)
    jrr, jrc, jcc = _structure_tensor(img.data, sigma, truncate, max_sigma, mode)
    tr = jrr + jcc
    return Image(jrr * jcc - jrc * jrc - k * tr * tr)


@register(family="edges", takes=Image, gives=Image, knobs={"sigma": _SMALL_SIGMA_KNOB}, differentiable=True,
          refs=["J. Shi and C. Tomasi, 'Good features to track', Proc. IEEE CVPR, 593-600, 1994"])
def shi_tomasi(img: Image, /, *, sigma: float = 1.0, truncate: float = 4.0, mode: str = "reflect",
               max_sigma: float = 4.0) -> Image:
    """Smaller eigenvalue of the structure tensor (Shi-Tomasi corner measure).

    ``lambda_min = (tr J - sqrt((Jrr - Jcc)^2 + 4 Jrc^2)) / 2`` with ``J`` as in
    :func:`harris`. Near zero on flat regions and straight edges, large at
    corners; in (grey value / pixel)^2. Rounding can make it slightly negative
    (about ``-1e-16 tr J``) where ``J`` is rank one; it is not clipped.

    Args:
      img: input image ``(H, W)``.
      sigma: integration scale in pixels, > 0 (knob ``a``, log-mapped to [0.5, 4]).
      truncate: Gaussian window half-width in units of sigma.
      mode: boundary mode (SciPy names); default ``"reflect"``.
      max_sigma: static bound on a traced sigma (fixes the tap count).

    Returns:
      ``Image`` of smaller eigenvalues.

    Matches ``skimage.feature.corner_shi_tomasi(x, sigma)`` divided by ``8^2`` with
    ``mode="constant"``, to 1e-12 relative.

    Example:
      A linear ramp has a rank-one tensor (no corner); the single-pixel corner of
      a bright quadrant has a clearly positive response:

      >>> import jax.numpy as jnp, fsjax
      >>> r, c = jnp.mgrid[0:25, 0:25]
      >>> ramp = fsjax.ops.shi_tomasi(fsjax.Image(0.03 * r + 0.04 * c)).data[12, 12]
      >>> abs(float(ramp)) < 1e-15
      True
      >>> quad = fsjax.Image(((r >= 12) & (c >= 12)).astype(float))
      >>> bool(fsjax.ops.shi_tomasi(quad).data[12, 12] > 0.01)
      True
    """
    _check_sigma("shi_tomasi", sigma, truncate, mode, img.data.shape)
    jrr, jrc, jcc = _structure_tensor(img.data, sigma, truncate, max_sigma, mode)
    d = jrr - jcc
    return Image(0.5 * (jrr + jcc - _safe_hypot(d, 2.0 * jrc)))


@register(family="edges", takes=Image, gives=Image, knobs={"sigma": _SMALL_SIGMA_KNOB}, differentiable=True,
          refs=["J. Biguen and G. H. Granlund, 'Optimal orientation detection of linear symmetry', "
                "Proc. 1st ICCV, 433-438, 1987",
                "B. Jaehne, Digital Image Processing, 6th ed., Springer, 2005, ch. 13"])
def structure_coherence(img: Image, /, *, sigma: float = 2.0, truncate: float = 4.0,
                        mode: str = "reflect", max_sigma: float = 4.0) -> Image:
    """Orientation coherence ``(l1 - l2) / (l1 + l2)`` of the structure tensor, in [0, 1].

    ``l1 >= l2`` are the eigenvalues of ``J`` (see :func:`harris`);
    ``l1 - l2 = sqrt((Jrr - Jcc)^2 + 4 Jrc^2)``. 1 for a single orientation (a ramp,
    straight stripes), 0 for isotropic structure. Where ``tr J = 0`` (a flat
    neighbourhood, no orientation at all) the output is 0 by definition.
    (Some texts use the square of this ratio.)

    Args:
      img: input image ``(H, W)``.
      sigma: integration scale in pixels, > 0 (knob ``a``, log-mapped to [0.5, 4]).
      truncate: Gaussian window half-width in units of sigma.
      mode: boundary mode (SciPy names); default ``"reflect"``.
      max_sigma: static bound on a traced sigma (fixes the tap count).

    Returns:
      ``Image`` in ``[0, 1]`` (up to rounding).

    Matches the ratio computed from ``skimage.feature.structure_tensor`` /
    ``structure_tensor_eigenvalues`` (``mode="constant"``) to 1e-9.

    Example:
      A ramp is perfectly oriented; ``row^2 + col^2`` is isotropic at its centre:

      >>> import jax.numpy as jnp, fsjax
      >>> r, c = jnp.mgrid[-12:13, -12:13]
      >>> ramp = fsjax.Image(0.5 + 0.01 * r + 0.02 * c)
      >>> round(float(fsjax.ops.structure_coherence(ramp).data[12, 12]), 9)
      1.0
      >>> bowl = fsjax.Image(0.001 * (r**2 + c**2))
      >>> abs(float(fsjax.ops.structure_coherence(bowl).data[12, 12])) < 1e-9
      True
    """
    _check_sigma("structure_coherence", sigma, truncate, mode, img.data.shape)
    jrr, jrc, jcc = _structure_tensor(img.data, sigma, truncate, max_sigma, mode)
    tr = jrr + jcc
    diff = _safe_hypot(jrr - jcc, 2.0 * jrc)
    pos = tr > 0
    out = jnp.where(pos, diff / jnp.where(pos, tr, 1.0), 0.0)
    # the where above would turn a poisoned (NaN) tensor into 0: poison the ratio itself
    return Image(_poison_wide(out, sigma, truncate, _gaussian_radius(sigma, truncate, max_sigma)))
