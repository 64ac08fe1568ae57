"""Image features: one measured number per image (``Image -> Feature``, ``(Image, Image) -> Feature``).

Conventions:

* Inputs are grey images ``(H, W)``; a feature is computed over *every* pixel
  (no mask). Ops are written for one image; batching is ``jax.vmap``.
* Statistics are population statistics (``ddof = 0``), as in ``numpy.var``.
* Units (the static ``Feature.unit``): ``"grey"`` for values on the image's own
  scale (nominally ``[0, 1]``), ``"grey^2"`` for squared values, ``"bit"`` for
  entropy, ``"dB"`` for PSNR, ``"1"`` for dimensionless ratios (SSIM, Michelson
  contrast), ``"grey^2/px^4"`` for the Laplacian variance.
* Boundaries: ``sharpness`` filters with a SciPy boundary mode (default
  ``"reflect"``); ``ssim`` filters with ``"reflect"`` and then averages only over
  pixels at least the window radius away from the border (scikit-image's crop);
  ``noise_sigma`` uses only interior pixels (no boundary extension).
* Two-image ops take ``(reference, test)`` of the same shape (raises otherwise).
  They assume ``data_range = 1`` (the ``[0, 1]`` grey scale) unless told.
* Undefined values: PSNR of identical images is ``+inf`` (zero error);
  Michelson contrast of an all-zero image (or of an image with negative values)
  is NaN. No op divides by ``x + eps``: a safe denominator and ``jnp.where``
  select the defined branch, so gradients stay finite.
* Quantisation (``entropy``): ``q = clip(rint(255 x), 0, 255)`` with
  round-half-to-even, i.e. ``skimage.util.img_as_ubyte`` for ``x`` in ``[0, 1]``
  (values outside ``[0, 1]`` are clipped, where scikit-image would raise).
"""

from __future__ import annotations

import math

import jax.numpy as jnp
from jaxtyping import Array, Float

from ..._checks import check_choice, check_positive, check_range
from ...registry import LinKnob, register
from ...types import Feature, Image, is_concrete
from .._common import check_mode, correlate1d
from ._filters import gaussian_weights

__all__ = [
    "mean",
    "std",
    "min_value",
    "max_value",
    "percentile",
    "entropy",
    "sharpness",
    "noise_sigma",
    "mse",
    "rmse",
    "psnr",
    "ssim",
    "michelson_contrast",
]

_GREY_REFS = ["NumPy reference: numpy.mean / numpy.std / numpy.min / numpy.max"]


def _safe_sqrt(v: Float[Array, "..."]) -> Float[Array, "..."]:
    """``sqrt(v)`` for ``v >= 0`` with a finite (zero) gradient at ``v = 0``."""
    pos = v > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, v, 1.0)), 0.0)


def _check_same_shape(op: str, a: Image, b: Image) -> None:
    if a.data.shape != b.data.shape:
        raise ValueError(
            f"{op}: argument 'test' has shape {tuple(b.data.shape)}, which does not match "
            f"argument 'reference' of shape {tuple(a.data.shape)}"
        )


# ---------------------------------------------------------------------------
# Grey-value statistics
# ---------------------------------------------------------------------------


@register(family="features", takes=Image, gives=Feature, differentiable=True, refs=_GREY_REFS)
def mean(img: Image, /) -> Feature:
    """Mean grey value of the image.

    ``mean = (1 / HW) sum_ij x_ij``. Differentiable: ``d mean / d x_ij = 1 / HW``.

    Args:
      img: input image ``(H, W)``.

    Returns:
      ``Feature`` with the mean grey value, unit ``"grey"``.

    Matches ``numpy.mean`` to rounding (1e-15 in float64).

    Example:
      A linear ramp from 0 to 1 has mean 1/2:

      >>> import jax.numpy as jnp, fsjax
      >>> img = fsjax.Image(jnp.tile(jnp.linspace(0.0, 1.0, 11), (4, 1)))
      >>> round(float(fsjax.ops.mean(img).value), 12)
      0.5
    """
    return Feature(jnp.mean(img.data), unit="grey")


@register(family="features", takes=Image, gives=Feature, differentiable=True, refs=_GREY_REFS)
def std(img: Image, /) -> Feature:
    """Population standard deviation of the grey values (RMS contrast).

    ``std = sqrt((1 / HW) sum_ij (x_ij - mean)^2)`` (``ddof = 0``). It is also the
    RMS contrast of the image. The square root has a zero (not infinite)
    gradient on a constant image.

    Args:
      img: input image ``(H, W)``.

    Returns:
      ``Feature`` with the standard deviation, unit ``"grey"``; 0 (to rounding) for a
      constant image.

    Matches ``numpy.std`` (``ddof=0``) to 1e-14 in float64.

    Example:
      A checkerboard of 0.2 and 0.6 has standard deviation 0.2:

      >>> import jax.numpy as jnp, fsjax
      >>> r, c = jnp.mgrid[0:8, 0:8]
      >>> img = fsjax.Image(jnp.where((r + c) % 2 == 0, 0.2, 0.6))
      >>> round(float(fsjax.ops.std(img).value), 12)
      0.2
    """
    return Feature(_safe_sqrt(jnp.var(img.data)), unit="grey")


@register(family="features", takes=Image, gives=Feature, refs=_GREY_REFS)
def min_value(img: Image, /) -> Feature:
    """Smallest grey value of the image.

    Args:
      img: input image ``(H, W)``.

    Returns:
      ``Feature`` with ``min_ij x_ij``, unit ``"grey"``. Not declared
      differentiable (the gradient jumps between pixels).

    Matches ``numpy.min`` exactly.

    Example:
      >>> import jax.numpy as jnp, fsjax
      >>> img = fsjax.Image(jnp.full((5, 6), 0.5).at[2, 3].set(0.125))
      >>> float(fsjax.ops.min_value(img).value)
      0.125
    """
    return Feature(jnp.min(img.data), unit="grey")


@register(family="features", takes=Image, gives=Feature, refs=_GREY_REFS)
def max_value(img: Image, /) -> Feature:
    """Largest grey value of the image.

    Args:
      img: input image ``(H, W)``.

    Returns:
      ``Feature`` with ``max_ij x_ij``, unit ``"grey"``. Not declared
      differentiable (the gradient jumps between pixels).

    Matches ``numpy.max`` exactly.

    Example:
      >>> import jax.numpy as jnp, fsjax
      >>> img = fsjax.Image(jnp.full((5, 6), 0.5).at[4, 0].set(0.875))
      >>> float(fsjax.ops.max_value(img).value)
      0.875
    """
    return Feature(jnp.max(img.data), unit="grey")


def _percentile_linear(x: Float[Array, "..."], p) -> Float[Array, ""]:
    """NumPy's ``method='linear'`` percentile of all elements of ``x`` (``p`` may be traced)."""
    a = jnp.sort(jnp.ravel(x))
    n = a.shape[0]
    q = jnp.asarray(p, dtype=a.dtype) / 100
    vi = q * (n - 1)  # virtual index, NumPy's (n - 1) q
    lo = jnp.floor(vi)
    gamma = vi - lo
    i0 = jnp.clip(lo.astype(jnp.int32), 0, n - 1)
    i1 = jnp.clip(i0 + 1, 0, n - 1)
    a0, a1 = a[i0], a[i1]
    d = a1 - a0
    # NumPy's _lerp: interpolate from the nearer end for accuracy.
    return jnp.where(gamma >= 0.5, a1 - d * (1 - gamma), a0 + d * gamma)


@register(
    family="features",
    takes=Image,
    gives=Feature,
    knobs={"p": LinKnob(0.0, 100.0, unit="%")},
    refs=["R. J. Hyndman, Y. Fan, Sample quantiles in statistical packages, "
          "The American Statistician 50(4), 1996 (definition 7)"],
)
def percentile(img: Image, /, *, p: float = 50.0) -> Feature:
    """Exact ``p``-th percentile of the grey values (linear interpolation).

    The ``HW`` values are sorted, ``a_0 <= ... <= a_{n-1}``; with the virtual index
    ``v = (p / 100)(n - 1)``, ``i = floor(v)`` and ``g = v - i`` the result is
    ``a_i + g (a_{i+1} - a_i)`` (Hyndman & Fan definition 7, NumPy's default
    ``'linear'`` method). ``p = 0`` is the minimum, ``p = 100`` the maximum,
    ``p = 50`` the median.

    Args:
      img: input image ``(H, W)``.
      p: percentile in ``[0, 100]`` (knob ``a``, linear over [0, 100] %); default
        50 (the median). May be traced: the sort is done once, the index is traced.

    Returns:
      ``Feature`` with the percentile, unit ``"grey"``. Not declared
      differentiable (it is a sorting op).

    Matches ``numpy.percentile(x, p)`` (``method='linear'``) exactly in float64 for
    a concrete ``p`` (the same index and interpolation formula, from the nearer
    sample). Under ``jit`` with a traced ``p``, XLA folds ``(p / 100)(n - 1)``
    into one multiplication, which can move the virtual index by one ulp: the
    result then differs by at most ``~2e-16 n |a_{i+1} - a_i|`` (tested at 1e-12).

    Example:
      The values 0, 0.1, ..., 1.1 (n = 12): the 25th percentile sits at virtual
      index 2.75, i.e. 0.2 + 0.75 * 0.1:

      >>> import jax.numpy as jnp, fsjax
      >>> img = fsjax.Image(jnp.arange(12.0).reshape(3, 4) / 10)
      >>> round(float(fsjax.ops.percentile(img, p=25.0).value), 12)
      0.275
      >>> round(float(fsjax.ops.percentile(img, p=100.0).value), 12)
      1.1
    """
    check_range("percentile", "p", p, 0.0, 100.0)
    return Feature(_percentile_linear(img.data, p), unit="grey")


@register(
    family="features",
    takes=Image,
    gives=Feature,
    refs=["C. E. Shannon, A mathematical theory of communication, Bell System Technical "
          "Journal 27, 1948"],
)
def entropy(img: Image, /) -> Feature:
    """Shannon entropy of the 256-bin grey-level histogram, in bits.

    The image is quantised to 8 bits, ``q = clip(rint(255 x), 0, 255)``
    (round-half-to-even, as ``skimage.util.img_as_ubyte``); with ``p_k`` the
    fraction of pixels at level ``k``, ``H = -sum_k p_k log2 p_k`` (empty bins
    contribute 0). Ranges from 0 (constant image) to 8 bits (flat histogram).

    Args:
      img: input image ``(H, W)``, values in ``[0, 1]``; values outside are
        clipped to the end bins (scikit-image would raise instead).

    Returns:
      ``Feature`` with the entropy, unit ``"bit"``. Not differentiable
      (quantisation).

    Matches ``skimage.measure.shannon_entropy(skimage.util.img_as_ubyte(x))`` to
    1e-12 in float64.

    Example:
      Four grey levels in equal shares carry exactly 2 bits:

      >>> import jax.numpy as jnp, fsjax
      >>> levels = jnp.array([0.0, 0.25, 0.5, 1.0])
      >>> img = fsjax.Image(jnp.tile(levels, (6, 2)))
      >>> round(float(fsjax.ops.entropy(img).value), 12)
      2.0
    """
    x = img.data
    q = jnp.clip(jnp.round(x * 255), 0, 255).astype(jnp.int32)
    counts = jnp.bincount(jnp.ravel(q), length=256).astype(x.dtype)
    pk = counts / q.size
    nz = pk > 0
    h = -jnp.sum(jnp.where(nz, pk * jnp.log2(jnp.where(nz, pk, 1.0)), 0.0))
    return Feature(h, unit="bit")


# ---------------------------------------------------------------------------
# Focus and noise
# ---------------------------------------------------------------------------


@register(
    family="features",
    takes=Image,
    gives=Feature,
    differentiable=True,
    refs=["J. L. Pech-Pacheco, G. Cristobal, J. Chamorro-Martinez, J. Fernandez-Valdivia, "
          "Diatom autofocusing in brightfield microscopy: a comparative study, ICPR 2000"],
)
def sharpness(img: Image, /, *, mode: str = "reflect") -> Feature:
    """Focus measure: variance of the Laplacian.

    ``L = x * [[0, 1, 0], [1, -4, 1], [0, 1, 0]]`` (the 5-point discrete
    Laplacian, one-pixel steps, boundary by ``mode``), and the feature is the
    population variance of ``L`` over all pixels. Blur removes high frequencies
    and lowers it; it grows with contrast squared.

    Args:
      img: input image ``(H, W)``.
      mode: boundary mode (SciPy names); default ``"reflect"``
        (``d c b a | a b c d``). ``"mirror"`` is OpenCV's default border.

    Returns:
      ``Feature`` with ``var(L)``, unit ``"grey^2/px^4"``.

    Matches ``scipy.ndimage.laplace(x, mode=mode).var()`` and, with
    ``mode="mirror"``, ``cv2.Laplacian(x, cv2.CV_64F, ksize=1).var()``, both to
    1e-12 relative in float64.

    Example:
      A single impulse of height 1 on a flat 8 x 8 field gives the Laplacian
      response 1, 1, 1, 1, -4 (sum 0), so the variance is
      ``(4 * 1 + 16) / 64 = 0.3125``:

      >>> import jax.numpy as jnp, fsjax
      >>> img = fsjax.Image(jnp.zeros((8, 8)).at[3, 4].set(1.0))
      >>> float(fsjax.ops.sharpness(img).value)
      0.3125
    """
    check_mode("sharpness", mode)
    x = img.data
    w = jnp.asarray([1.0, -2.0, 1.0], dtype=x.dtype)
    lap = correlate1d(x, w, axis=-2, mode=mode) + correlate1d(x, w, axis=-1, mode=mode)
    return Feature(jnp.var(lap), unit="grey^2/px^4")


_NOISE_METHODS = ("immerkaer", "mad")
_MAD_TO_SIGMA = 0.6744897501960817  # Phi^-1(3/4): median |N(0, 1)|


@register(
    family="features",
    takes=Image,
    gives=Feature,
    refs=["J. Immerkaer, Fast noise variance estimation, Computer Vision and Image "
          "Understanding 64(2), 300-302, 1996",
          "D. L. Donoho, I. M. Johnstone, Ideal spatial adaptation by wavelet shrinkage, "
          "Biometrika 81(3), 425-455, 1994 (median absolute deviation estimator)"],
)
def noise_sigma(img: Image, /, *, method: str = "immerkaer") -> Feature:
    """Standard deviation of additive white Gaussian noise, estimated from one image.

    The residual ``r = x * N`` with ``N = [1, -2, 1]^T [1, -2, 1]`` (Immerkaer's
    mask: the difference of two Laplacians, which cancels locally linear and
    bilinear image content) is taken over the ``(H - 2)(W - 2)`` interior pixels.
    For white noise of standard deviation ``s``, ``r`` has standard deviation
    ``6 s`` (``sum N^2 = 36``). Estimators:

    * ``"immerkaer"``: ``s = sqrt(pi / 2) mean|r| / 6`` (Immerkaer 1996);
    * ``"mad"``: ``s = median|r| / (0.67449 * 6)`` (Donoho's robust MAD rule
      applied to the same residual; less biased by edges and texture).

    Args:
      img: input image ``(H, W)`` with ``H, W >= 3``.
      method: ``"immerkaer"`` (default) or ``"mad"``.

    Returns:
      ``Feature`` with the estimated sigma, unit ``"grey"``. Image structure
      that the mask does not cancel (edges, texture) biases the estimate
      upwards. Not differentiable (absolute value, median).

    Compared in the tests with ``skimage.restoration.estimate_sigma`` (wavelet
    MAD), which uses a different residual, so only the accuracy on a known
    sigma is asserted (within 10 % for sigma in {0.01, 0.02, 0.05} on a smooth
    128 x 128 image).

    Example:
      On a plane ``a + b r + c c`` the residual vanishes, so the estimate is 0;
      on a +-d checkerboard ``|r| = 16 d`` everywhere:

      >>> import jax.numpy as jnp, fsjax
      >>> r, c = jnp.mgrid[0:16, 0:16]
      >>> plane = fsjax.Image(0.2 + 0.01 * r + 0.02 * c)
      >>> abs(float(fsjax.ops.noise_sigma(plane).value)) < 1e-12
      True
      >>> board = fsjax.Image(0.5 + 0.01 * jnp.where((r + c) % 2 == 0, 1.0, -1.0))
      >>> est = float(fsjax.ops.noise_sigma(board).value)
      >>> abs(est - (jnp.pi / 2) ** 0.5 * 0.16 / 6) < 1e-12
      True
    """
    check_choice("noise_sigma", "method", method, _NOISE_METHODS)
    x = img.data
    h, w = x.shape[-2:]
    if h < 3 or w < 3:
        raise ValueError(f"noise_sigma: argument 'img' must be at least 3 x 3, got {h} x {w}")
    d = x[:-2, :] - 2 * x[1:-1, :] + x[2:, :]
    r = d[:, :-2] - 2 * d[:, 1:-1] + d[:, 2:]
    ar = jnp.abs(r)
    if method == "immerkaer":
        s = math.sqrt(math.pi / 2) * jnp.mean(ar) / 6
    else:
        s = jnp.median(ar) / (_MAD_TO_SIGMA * 6)
    return Feature(s, unit="grey")


# ---------------------------------------------------------------------------
# Two-image comparisons
# ---------------------------------------------------------------------------


@register(family="features", takes=(Image, Image), gives=Feature, differentiable=True,
          refs=["skimage.metrics.mean_squared_error"])
def mse(reference: Image, test: Image, /) -> Feature:
    """Mean squared difference between two images.

    ``mse = (1 / HW) sum_ij (x_ij - y_ij)^2``.

    Args:
      reference: reference image ``(H, W)``.
      test: image to compare, same shape.

    Returns:
      ``Feature`` with the MSE, unit ``"grey^2"``; 0 for identical images.

    Matches ``skimage.metrics.mean_squared_error`` to 1e-15 in float64.

    Example:
      Two constant images 0.25 apart differ by 0.0625 in the mean square:

      >>> import jax.numpy as jnp, fsjax
      >>> a = fsjax.Image(jnp.full((4, 4), 0.5))
      >>> b = fsjax.Image(jnp.full((4, 4), 0.75))
      >>> float(fsjax.ops.mse(a, b).value)
      0.0625
    """
    _check_same_shape("mse", reference, test)
    return Feature(jnp.mean((reference.data - test.data) ** 2), unit="grey^2")


@register(family="features", takes=(Image, Image), gives=Feature, differentiable=True,
          refs=["skimage.metrics.mean_squared_error (square root)"])
def rmse(reference: Image, test: Image, /) -> Feature:
    """Root mean squared difference between two images.

    ``rmse = sqrt(mse)``. The square root has a zero (not infinite) gradient when
    the images are identical.

    Args:
      reference: reference image ``(H, W)``.
      test: image to compare, same shape.

    Returns:
      ``Feature`` with the RMSE, unit ``"grey"``; 0 for identical images.

    Matches ``sqrt(skimage.metrics.mean_squared_error)`` to 1e-15 in float64.

    Example:
      A difference of +-0.1 on every pixel has RMSE 0.1:

      >>> import jax.numpy as jnp, fsjax
      >>> r, c = jnp.mgrid[0:6, 0:6]
      >>> a = fsjax.Image(jnp.full((6, 6), 0.5))
      >>> b = fsjax.Image(0.5 + 0.1 * jnp.where((r + c) % 2 == 0, 1.0, -1.0))
      >>> round(float(fsjax.ops.rmse(a, b).value), 12)
      0.1
    """
    _check_same_shape("rmse", reference, test)
    return Feature(_safe_sqrt(jnp.mean((reference.data - test.data) ** 2)), unit="grey")


@register(family="features", takes=(Image, Image), gives=Feature, differentiable=True,
          refs=["skimage.metrics.peak_signal_noise_ratio"])
def psnr(reference: Image, test: Image, /, *, data_range: float = 1.0) -> Feature:
    """Peak signal-to-noise ratio in decibels.

    ``psnr = 10 log10(data_range^2 / mse)``. For identical images the error is 0
    and the result is defined as ``+inf`` (as scikit-image returns, without its
    divide-by-zero warning); its gradient there is 0, not NaN.

    Args:
      reference: reference image ``(H, W)``.
      test: image to compare, same shape.
      data_range: peak-to-peak range of the grey scale, > 0; default 1 (images in
        ``[0, 1]``).

    Returns:
      ``Feature`` with the PSNR, unit ``"dB"``; ``+inf`` for identical images.

    Matches ``skimage.metrics.peak_signal_noise_ratio(ref, test, data_range=1)``
    to 1e-12 dB in float64.

    Example:
      An error of 0.1 on every pixel gives ``mse = 0.01``, i.e. 20 dB:

      >>> import jax.numpy as jnp, fsjax
      >>> a = fsjax.Image(jnp.full((4, 4), 0.5))
      >>> b = fsjax.Image(jnp.full((4, 4), 0.6))
      >>> round(float(fsjax.ops.psnr(a, b).value), 9)
      20.0
      >>> float(fsjax.ops.psnr(a, a).value)
      inf
    """
    _check_same_shape("psnr", reference, test)
    check_positive("psnr", "data_range", data_range)
    err = jnp.mean((reference.data - test.data) ** 2)
    pos = err > 0
    safe = jnp.where(pos, err, 1.0)
    dr = jnp.asarray(data_range, dtype=err.dtype)
    val = jnp.where(pos, 10 * jnp.log10(dr * dr / safe), jnp.inf)
    return Feature(val, unit="dB")


_SSIM_TRUNCATE = 3.5  # 11 taps at sigma 1.5, as Wang et al. 2004 and scikit-image


@register(
    family="features",
    takes=(Image, Image),
    gives=Feature,
    differentiable=True,
    refs=["Z. Wang, A. C. Bovik, H. R. Sheikh, E. P. Simoncelli, Image quality assessment: "
          "from error visibility to structural similarity, IEEE Trans. Image Processing "
          "13(4), 600-612, 2004"],
)
def ssim(reference: Image, test: Image, /, *, sigma: float = 1.5, k1: float = 0.01, k2: float = 0.03,
         data_range: float = 1.0) -> Feature:
    """Mean structural similarity (SSIM) with a Gaussian window.

    Local weighted statistics use a Gaussian window ``G`` (``sigma`` px, truncated
    at ``int(3.5 sigma + 0.5)`` px, i.e. 11 taps for 1.5, boundary ``"reflect"``):
    ``mu_x = G * x``, ``s_x^2 = G * x^2 - mu_x^2``, ``s_xy = G * xy - mu_x mu_y``
    (population covariances). With ``C1 = (k1 L)^2`` and ``C2 = (k2 L)^2``
    (``L = data_range``), ``S = (2 mu_x mu_y + C1)(2 s_xy + C2) /
    ((mu_x^2 + mu_y^2 + C1)(s_x^2 + s_y^2 + C2))`` and the result is the mean
    of ``S`` over the pixels at least one window radius from the border (the
    border ring, where the window reaches into the reflected extension, is
    cropped, as scikit-image does).

    Args:
      reference: reference image ``(H, W)``; ``H, W >= 2 radius + 1`` (11 at the
        default sigma).
      test: image to compare, same shape.
      sigma: window standard deviation in pixels, > 0; static (it fixes the
        window and the crop). Default 1.5 (Wang et al.).
      k1: luminance stabiliser, >= 0; default 0.01.
      k2: contrast stabiliser, >= 0; default 0.03.
      data_range: peak-to-peak range of the grey scale, > 0; default 1.

    Returns:
      ``Feature`` with the mean SSIM, unit ``"1"``; 1 for identical images, in
      ``[-1, 1]``.

    Matches ``skimage.metrics.structural_similarity(x, y, gaussian_weights=True,
    sigma=1.5, use_sample_covariance=False, data_range=1)`` to 1e-12 in float64
    (tested at 1e-6 as required).

    Example:
      An image compared with itself scores 1; a constant offset ``d`` changes
      only the luminance term, which is then ``(2 m (m + d) + C1) / (m^2 +
      (m + d)^2 + C1)`` everywhere:

      >>> import jax.numpy as jnp, fsjax
      >>> r, c = jnp.mgrid[0:16, 0:16]
      >>> x = fsjax.Image(0.3 + 0.02 * ((r * 7 + c * 3) % 5))
      >>> round(float(fsjax.ops.ssim(x, x).value), 12)
      1.0
      >>> a, b = fsjax.Image(jnp.full((16, 16), 0.4)), fsjax.Image(jnp.full((16, 16), 0.6))
      >>> c1 = 0.01 ** 2
      >>> truth = (2 * 0.4 * 0.6 + c1) / (0.4 ** 2 + 0.6 ** 2 + c1)
      >>> abs(float(fsjax.ops.ssim(a, b).value) - truth) < 1e-12
      True
    """
    op = "ssim"
    _check_same_shape(op, reference, test)
    if not is_concrete(sigma):
        raise TypeError(f"{op}: argument 'sigma' fixes the window size and must be a concrete number")
    check_positive(op, "sigma", sigma)
    check_range(op, "k1", k1, 0.0)
    check_range(op, "k2", k2, 0.0)
    check_positive(op, "data_range", data_range)
    x, y = reference.data, test.data
    dt = jnp.result_type(x, y)
    w = gaussian_weights(float(sigma), _SSIM_TRUNCATE).astype(dt)
    radius = (w.shape[0] - 1) // 2
    h, wd = x.shape[-2:]
    win = 2 * radius + 1
    if h < win or wd < win:
        raise ValueError(
            f"{op}: images must be at least {win} x {win} for sigma={float(sigma):g} "
            f"(window of {win} taps), got {h} x {wd}"
        )
    stack = jnp.stack([x, y, x * x, y * y, x * y])
    f = correlate1d(stack, w, axis=-2, mode="reflect")
    f = correlate1d(f, w, axis=-1, mode="reflect")
    ux, uy, uxx, uyy, uxy = f[0], f[1], f[2], f[3], f[4]
    vx = uxx - ux * ux
    vy = uyy - uy * uy
    vxy = uxy - ux * uy
    L = jnp.asarray(data_range, dtype=dt)
    c1 = (k1 * L) ** 2
    c2 = (k2 * L) ** 2
    num = (2 * ux * uy + c1) * (2 * vxy + c2)
    den = (ux * ux + uy * uy + c1) * (vx + vy + c2)
    # den > 0 whenever c1, c2 > 0; with k1 = k2 = 0 a flat dark patch is undefined (NaN).
    ok = den > 0
    s = jnp.where(ok, num / jnp.where(ok, den, 1.0), jnp.nan)
    s = s[radius:h - radius, radius:wd - radius]
    return Feature(jnp.mean(s), unit="1")


# ---------------------------------------------------------------------------
# Contrast
# ---------------------------------------------------------------------------


@register(
    family="features",
    takes=Image,
    gives=Feature,
    refs=["A. A. Michelson, Studies in Optics, University of Chicago Press, 1927"],
)
def michelson_contrast(img: Image, /) -> Feature:
    """Michelson contrast ``(max - min) / (max + min)`` of the grey values.

    Defined for non-negative images with ``max + min > 0``; in ``[0, 1]``. For an
    all-zero image, or an image with negative values (a signed response), the
    ratio has no meaning and the result is NaN. (The RMS contrast is
    :func:`std`.)

    Args:
      img: input image ``(H, W)``, values >= 0.

    Returns:
      ``Feature`` with the contrast, unit ``"1"``, or NaN where undefined.
      Not differentiable (min/max).

    Example:
      A grating between 0.2 and 0.6 has contrast 0.4 / 0.8 = 0.5; a black
      image has none:

      >>> import jax.numpy as jnp, fsjax
      >>> r, c = jnp.mgrid[0:4, 0:8]
      >>> img = fsjax.Image(jnp.where(c % 2 == 0, 0.2, 0.6))
      >>> round(float(fsjax.ops.michelson_contrast(img).value), 12)
      0.5
      >>> float(fsjax.ops.michelson_contrast(fsjax.Image(jnp.zeros((4, 4)))).value)
      nan
    """
    lo = jnp.min(img.data)
    hi = jnp.max(img.data)
    tot = hi + lo
    ok = (lo >= 0) & (tot > 0)
    val = jnp.where(ok, (hi - lo) / jnp.where(ok, tot, 1.0), jnp.nan)
    return Feature(val, unit="1")
