"""Frequency-domain analysis and filters (``Image -> Image``).

Conventions:

* **Periodic boundary.** Every op here works on the discrete Fourier transform
  of the whole image, so the image is treated as one period of a periodic
  signal: content leaving the right edge re-enters on the left. The filters
  take an optional static ``pad`` (pixels added on every side with a SciPy
  boundary ``mode``, default ``"reflect"``) to weaken the wrap-around; the
  padded result is cropped back to ``(H, W)``.
* **Frequencies** are in *cycles per pixel*: along an axis of length ``N`` the
  DFT bin ``k`` sits at ``numpy.fft.fftfreq(N)[k]`` (``|f| <= 0.5``, Nyquist).
  Filters are isotropic in the *radial* frequency
  ``f = sqrt(f_row**2 + f_col**2)`` (``f <= sqrt(0.5) ~ 0.707`` at the corners).
* **Transfer functions** (Gonzalez & Woods, *Digital Image Processing*, ch. 4),
  with cutoff ``fc`` in cycles/pixel:

  ============  ===================================  =========================
  profile       low-pass ``H_lp(f)``                 gain at ``f = fc``
  ============  ===================================  =========================
  ideal         ``1`` if ``f <= fc`` else ``0``      ``1`` (cutoff inclusive)
  butterworth   ``1 / (1 + (f / fc) ** (2 n))``      ``1 / 2``
  gaussian      ``exp(-f**2 / (2 fc**2))``           ``exp(-1/2) ~ 0.607``
  ============  ===================================  =========================

  The high-pass is exactly ``H_hp = 1 - H_lp`` (for Butterworth this equals
  the textbook ``1 / (1 + (fc / f) ** (2 n))``), so low-pass + high-pass with
  the same cutoff returns the input. The band-pass is the cascade
  ``H_bp = H_lp(f_hi) * H_hp(f_lo)`` with ``f_lo = centre * 2**(-octaves/2)``
  and ``f_hi = centre * 2**(+octaves/2)``, so any knob setting is a valid band.
  The Butterworth transfer is the *power* form used by
  ``skimage.filters.butterworth(squared_butterworth=True)``; the Gaussian
  low-pass with cutoff ``fc`` equals a spatial Gaussian blur with
  ``sigma = 1 / (2 pi fc)`` pixels applied periodically
  (``scipy.ndimage.fourier_gaussian``).
* **DC** (``f = 0``): every low-pass has ``H(0) = 1`` exactly (the mean grey
  value is preserved); every high-pass and band-pass has ``H(0) = 0`` exactly
  (the output has zero mean; a constant image gives 0 up to FFT round-off,
  measured <= 3e-16 in float64). High-pass and band-pass outputs are therefore
  **signed**: they are returned as ``Image`` holding values around 0 (roughly
  in ``[-1, 1]``), never clipped.
* **Spectra** (:func:`fft_magnitude`, :func:`fft_phase`) are centred with
  ``fftshift``: the DC term sits at pixel ``(H // 2, W // 2)`` and the bin at
  ``(H // 2 + ky, W // 2 + kx)`` has frequency ``(ky / H, kx / W)``. Magnitudes
  are normalised by the pixel count ``H * W``, so the DC value is the mean
  grey value and a cosine of amplitude ``A`` on a DFT bin gives two peaks of
  ``A / 2``; for an input in ``[0, 1]`` the normalised magnitude is in
  ``[0, 1]``.
* Differentiability: Butterworth and Gaussian filters are smooth in their
  cutoff (and order); ideal filters are piecewise constant in the cutoff and
  are registered as not differentiable. All filters are linear in the image.
* Computed with ``jnp.fft.rfft2``/``irfft2`` (the transfer functions are even
  in frequency, so the output is real). Dtype-generic: float32 input uses
  complex64 FFTs (round-off ~1e-7 of the input range), float64 uses complex128.
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from ..._checks import check_choice, check_positive, check_range, check_static_int
from ...registry import LinKnob, LogKnob, register
from ...types import Image
from .._common import check_mode, eps, float_dtype, pad2d

__all__ = [
    "fft_magnitude",
    "fft_phase",
    "ideal_lowpass",
    "ideal_highpass",
    "ideal_bandpass",
    "butterworth_lowpass",
    "butterworth_highpass",
    "butterworth_bandpass",
    "gaussian_lowpass",
    "gaussian_highpass",
    "gaussian_bandpass",
]

_REF_GW = "R. C. Gonzalez and R. E. Woods, Digital Image Processing, 4th ed., Pearson, 2018, ch. 4"
_REF_BUTTER = "S. Butterworth, On the theory of filter amplifiers, Wireless Engineer 7 (1930) 536-541"
_REF_FFT = ("J. W. Cooley and J. W. Tukey, An algorithm for the machine calculation of complex "
            "Fourier series, Math. Comp. 19 (1965) 297-301")


# ---------------------------------------------------------------------------
# Transfer functions (squared radial frequency f2 in cycles^2/pixel^2)
# ---------------------------------------------------------------------------


def _radial_f2_half(h: int, w: int, dtype) -> jnp.ndarray:
    """Squared radial frequency on the ``rfft2`` half-grid ``(h, w // 2 + 1)`` (static constant)."""
    fy = np.fft.fftfreq(h)
    fx = np.fft.rfftfreq(w)
    return jnp.asarray(fy[:, None] ** 2 + fx[None, :] ** 2, dtype=dtype)


def _lowpass_gain(f2, cutoff, profile: str, order):
    """Low-pass transfer ``H_lp`` at squared frequency ``f2`` (traced cutoff/order are fine)."""
    fc2 = cutoff * cutoff
    if profile == "ideal":
        return jnp.where(f2 <= fc2, 1.0, 0.0).astype(f2.dtype)
    if profile == "gaussian":
        return jnp.exp(-f2 / (2.0 * fc2))
    # butterworth: 1 / (1 + r**n), r = (f / fc)**2; r**n written AD-safely (r = 0 at DC).
    r = f2 / fc2
    pos = r > 0
    rn = jnp.where(pos, jnp.exp(order * jnp.log(jnp.where(pos, r, 1.0))), 0.0)
    return 1.0 / (1.0 + rn)


def _transfer(f2, kind: str, profile: str, cutoff, order, centre, octaves):
    if kind == "lowpass":
        return _lowpass_gain(f2, cutoff, profile, order)
    if kind == "highpass":
        return 1.0 - _lowpass_gain(f2, cutoff, profile, order)
    half = 0.5 * octaves * math.log(2.0)
    f_lo = centre * jnp.exp(-half)
    f_hi = centre * jnp.exp(half)
    return _lowpass_gain(f2, f_hi, profile, order) * (1.0 - _lowpass_gain(f2, f_lo, profile, order))


def _apply_filter(op: str, img: Image, kind: str, profile: str, *, cutoff=None, order=2.0,
                  centre=None, octaves=None, pad: int = 0, mode: str = "reflect") -> Image:
    if kind == "bandpass":
        check_positive(op, "centre", centre)
        check_positive(op, "octaves", octaves)
    else:
        check_positive(op, "cutoff", cutoff)
    if profile == "butterworth":
        check_positive(op, "order", order)
    pad = check_static_int(op, "pad", pad, lo=0)
    check_mode(op, mode)
    x = img.data
    dt = float_dtype(x)

    def as_dt(v):
        return jnp.zeros((), dt) if v is None else jnp.asarray(v, dtype=dt)

    out = _filter_core(x.astype(dt), as_dt(cutoff), as_dt(order), as_dt(centre), as_dt(octaves),
                       kind=kind, profile=profile, pad=pad, mode=mode)
    return Image(out)


@functools.partial(jax.jit, static_argnames=("kind", "profile", "pad", "mode"))
def _filter_core(x, cutoff, order, centre, octaves, *, kind, profile, pad, mode):
    # compiled once per (shape, dtype, kind, profile, pad, mode); parameters stay traced
    dt = x.dtype
    h, w = x.shape[-2:]
    if pad:
        x = pad2d(x, pad, pad, mode)
    hp, wp = x.shape[-2:]
    f2 = _radial_f2_half(hp, wp, dt)
    gain = _transfer(f2, kind, profile, cutoff, order, centre, octaves)
    out = jnp.fft.irfft2(jnp.fft.rfft2(x) * gain, s=(hp, wp)).astype(dt)
    if pad:
        out = out[..., pad:pad + h, pad:pad + w]
    return out


# ---------------------------------------------------------------------------
# Spectra
# ---------------------------------------------------------------------------


def _normalised_spectrum(op: str, img: Image):
    x = img.data
    dt = float_dtype(x)
    h, w = x.shape[-2:]
    spec = jnp.fft.fftshift(jnp.fft.fft2(x.astype(dt)), axes=(-2, -1)) / (h * w)
    re, im = jnp.real(spec).astype(dt), jnp.imag(spec).astype(dt)
    p = re * re + im * im
    pos = p > 0
    mag = jnp.where(pos, jnp.sqrt(jnp.where(pos, p, 1.0)), 0.0)
    return re, im, mag


@register(
    family="frequency",
    takes=Image,
    gives=Image,
    knobs={"gain": LogKnob(1.0, 1e6)},
    differentiable=True,
    refs=[_REF_FFT, _REF_GW],
)
def fft_magnitude(img: Image, /, *, scale: str = "log", gain: float = 1000.0) -> Image:
    """Centred Fourier magnitude spectrum, normalised by the pixel count, optionally log-compressed.

    With ``F = fft2(img)`` and ``m = |F| / (H W)`` (so ``m`` at DC is the mean grey
    value and ``m`` is in ``[0, 1]`` for an input in ``[0, 1]``), the output is
    ``fftshift(m)`` for ``scale="linear"`` or
    ``fftshift(log(1 + gain m) / log(1 + gain))`` for ``scale="log"``, which maps
    ``[0, 1]`` onto ``[0, 1]`` and shows weak coefficients (``m ~ 1 / gain``).

    Args:
      img: input image ``(H, W)``; treated as periodic.
      scale: ``"log"`` (default) or ``"linear"``.
      gain: log-compression gain, > 0; unused for ``scale="linear"`` (knob ``a``,
        log-mapped to [1, 1e6]).

    Returns:
      ``Image`` ``(H, W)`` in ``[0, 1]``, DC at pixel ``(H // 2, W // 2)``; pixel
      ``(H // 2 + ky, W // 2 + kx)`` is the frequency ``(ky / H, kx / W)`` cycles/pixel.

    Equals ``numpy.fft.fftshift(abs(numpy.fft.fft2(x))) / (H W)`` to 1e-15 in float64
    (linear scale). The gradient at an exactly zero coefficient is taken as 0.

    Example:
      A cosine of amplitude 0.25 with 4 cycles across 16 columns gives two peaks
      of 0.125 at 4 bins left and right of the centre, and the DC value is the mean:

      >>> import jax.numpy as jnp, fsjax
      >>> c = jnp.arange(16)
      >>> x = 0.5 + 0.25 * jnp.cos(2 * jnp.pi * 4 * c / 16) * jnp.ones((16, 1))
      >>> m = fsjax.ops.fft_magnitude(fsjax.Image(x), scale="linear").data
      >>> round(float(m[8, 8]), 9), round(float(m[8, 12]), 9), round(float(m[8, 4]), 9)
      (0.5, 0.125, 0.125)
      >>> round(float(m.sum()), 9)
      0.75
    """
    check_choice("fft_magnitude", "scale", scale, ("log", "linear"))
    check_positive("fft_magnitude", "gain", gain)
    _, _, mag = _normalised_spectrum("fft_magnitude", img)
    if scale == "linear":
        return Image(mag)
    g = jnp.asarray(gain, dtype=mag.dtype)
    return Image(jnp.log1p(g * mag) / jnp.log1p(g))


@register(
    family="frequency",
    takes=Image,
    gives=Image,
    knobs={},
    differentiable=False,
    refs=[_REF_FFT, _REF_GW],
)
def fft_phase(img: Image, /, *, floor: float | None = None) -> Image:
    """Centred Fourier phase spectrum in radians, signed, in ``(-pi, pi]``.

    ``out = fftshift(angle(fft2(img)))``, with the phase set to 0 where the
    normalised magnitude ``|F| / (H W)`` is at or below ``floor``: the phase of a
    coefficient at round-off level is noise, not information.

    Args:
      img: input image ``(H, W)``; treated as periodic.
      floor: magnitude floor in grey-value units (the scale of
        :func:`fft_magnitude` with ``scale="linear"``), >= 0. ``None`` (default)
        uses ``100 * eps(dtype) * max(m)``, i.e. the FFT's round-off level.

    Returns:
      ``Image`` ``(H, W)`` of **signed** phases in radians in ``(-pi, pi]`` (not in
      ``[0, 1]``), DC at pixel ``(H // 2, W // 2)``. Exactly real negative
      coefficients get ``+pi``.

    Equals ``numpy.angle(numpy.fft.fftshift(numpy.fft.fft2(x)))`` to 1e-12 in
    float64 wherever the magnitude is above the floor. Not differentiable (the
    phase jumps by ``2 pi`` across the negative real axis).

    Example:
      ``cos(2 pi 3 c / 16 + 0.7)`` has phase ``+0.7`` at the ``+3`` bin and
      ``-0.7`` at the ``-3`` bin; every other bin is zero, so its phase is 0:

      >>> import jax.numpy as jnp, fsjax
      >>> c = jnp.arange(16)
      >>> x = 0.5 + 0.25 * jnp.cos(2 * jnp.pi * 3 * c / 16 + 0.7) * jnp.ones((8, 1))
      >>> ph = fsjax.ops.fft_phase(fsjax.Image(x)).data
      >>> round(float(ph[4, 11]), 9), round(float(ph[4, 5]), 9), round(float(abs(ph[0, 0])), 9)
      (0.7, -0.7, 0.0)
    """
    if floor is not None:
        check_range("fft_phase", "floor", floor, 0.0)
    re, im, mag = _normalised_spectrum("fft_phase", img)
    if floor is None:
        thr = 100.0 * eps(mag.dtype) * jnp.max(mag, axis=(-2, -1), keepdims=True)
    else:
        thr = jnp.asarray(floor, dtype=mag.dtype)
    ph = jnp.arctan2(im, re)
    ph = jnp.where(ph <= -jnp.pi, jnp.pi, ph)  # atan2(-0.0, x < 0) = -pi: report +pi
    return Image(jnp.where(mag > thr, ph, 0.0).astype(mag.dtype))


# ---------------------------------------------------------------------------
# Filters
# ---------------------------------------------------------------------------

_CUTOFF = LogKnob(0.01, 0.5, unit="cycles/px")
_CENTRE = LogKnob(0.02, 0.4, unit="cycles/px")
_OCTAVES = LinKnob(0.5, 4.0, unit="octaves")
_ORDER = LinKnob(1.0, 8.0)

@register(family="frequency", takes=Image, gives=Image, knobs={"cutoff": _CUTOFF},
          differentiable=False, refs=[_REF_GW])
def ideal_lowpass(img: Image, /, *, cutoff: float = 0.1, pad: int = 0, mode: str = "reflect") -> Image:
    """Ideal (brick-wall) low-pass: keep the Fourier coefficients with radial frequency ``<= cutoff``.

    ``out = irfft2(H * rfft2(img))`` with ``H(f) = 1`` for ``f <= fc`` (inclusive) and
    0 above; ``H(0) = 1``, so the mean is preserved. Ringing (Gibbs) is expected
    near edges.

    Args:
      img: input image ``(H, W)``; periodic boundary unless ``pad`` > 0.
      cutoff: cutoff ``fc`` in cycles/pixel, > 0 (knob ``a``, log-mapped to
        [0.01, 0.5]); radial, compared with ``sqrt(f_row**2 + f_col**2)``.
      pad: static number of pixels added on every side (with ``mode``) before the
        FFT and cropped after; 0 (default) keeps the periodic boundary.
      mode: SciPy boundary mode used for the padding (default ``"reflect"``).

    Returns:
      ``Image`` ``(H, W)``, same dtype; values may leave ``[0, 1]`` slightly (ringing).

    ``ideal_lowpass(x, cutoff=c) + ideal_highpass(x, cutoff=c) == x`` to 1e-14.
    Not differentiable in ``cutoff`` (piecewise constant).

    Example:
      A cosine at 0.125 cycles/px passes a cutoff of 0.2 unchanged and is removed
      by a cutoff of 0.1 (only the mean 0.5 is left):

      >>> import jax.numpy as jnp, fsjax
      >>> c = jnp.arange(32)
      >>> x = fsjax.Image(0.5 + 0.3 * jnp.cos(2 * jnp.pi * 0.125 * c) * jnp.ones((16, 1)))
      >>> keep = fsjax.ops.ideal_lowpass(x, cutoff=0.2).data
      >>> gone = fsjax.ops.ideal_lowpass(x, cutoff=0.1).data
      >>> float(jnp.max(jnp.abs(keep - x.data))) < 1e-12, float(jnp.max(jnp.abs(gone - 0.5))) < 1e-12
      (True, True)
    """
    return _apply_filter("ideal_lowpass", img, "lowpass", "ideal", cutoff=cutoff, pad=pad, mode=mode)


@register(family="frequency", takes=Image, gives=Image, knobs={"cutoff": _CUTOFF},
          differentiable=False, refs=[_REF_GW])
def ideal_highpass(img: Image, /, *, cutoff: float = 0.1, pad: int = 0, mode: str = "reflect") -> Image:
    """Ideal (brick-wall) high-pass: keep the Fourier coefficients with radial frequency ``> cutoff``.

    ``H(f) = 0`` for ``f <= fc`` and 1 above, i.e. exactly ``1 - H`` of
    :func:`ideal_lowpass`; ``H(0) = 0`` so the output has zero mean.

    Args:
      img: input image ``(H, W)``; periodic boundary unless ``pad`` > 0.
      cutoff: cutoff ``fc`` in cycles/pixel, > 0 (knob ``a``, log-mapped to
        [0.01, 0.5]); frequencies equal to ``fc`` are removed.
      pad: static padding in pixels on every side (0 = periodic boundary).
      mode: SciPy boundary mode used for the padding (default ``"reflect"``).

    Returns:
      **Signed** ``Image`` ``(H, W)`` with zero mean (values around 0, not clipped).

    ``ideal_lowpass + ideal_highpass`` with the same cutoff returns the input to
    1e-14; not differentiable in ``cutoff``.

    Example:
      A constant image has no energy above DC, so its high-pass is 0:

      >>> import jax.numpy as jnp, fsjax
      >>> out = fsjax.ops.ideal_highpass(fsjax.Image(jnp.full((12, 20), 0.3)), cutoff=0.05)
      >>> float(jnp.max(jnp.abs(out.data))) < 1e-15
      True
    """
    return _apply_filter("ideal_highpass", img, "highpass", "ideal", cutoff=cutoff, pad=pad, mode=mode)


@register(family="frequency", takes=Image, gives=Image,
          knobs={"centre": _CENTRE, "octaves": _OCTAVES}, differentiable=False, refs=[_REF_GW])
def ideal_bandpass(img: Image, /, *, centre: float = 0.1, octaves: float = 1.0, pad: int = 0,
                   mode: str = "reflect") -> Image:
    """Ideal band-pass: keep the radial frequencies in ``(f_lo, f_hi]`` around ``centre``.

    ``f_lo = centre * 2**(-octaves / 2)``, ``f_hi = centre * 2**(octaves / 2)``;
    ``H = H_lp(f_hi) * (1 - H_lp(f_lo))`` with the ideal profile, ``H(0) = 0``.

    Args:
      img: input image ``(H, W)``; periodic boundary unless ``pad`` > 0.
      centre: geometric centre of the band in cycles/pixel, > 0 (knob ``a``,
        log-mapped to [0.02, 0.4]).
      octaves: band width in octaves (``log2(f_hi / f_lo)``), > 0 (knob ``b``,
        [0.5, 4]).
      pad: static padding in pixels on every side (0 = periodic boundary).
      mode: SciPy boundary mode used for the padding (default ``"reflect"``).

    Returns:
      **Signed** zero-mean ``Image`` ``(H, W)`` (not clipped).

    Not differentiable in ``centre``/``octaves`` (piecewise constant).

    Example:
      Of two cosines at 0.0625 and 0.25 cycles/px, a one-octave band around 0.25
      (0.177 to 0.354) keeps exactly the second:

      >>> import jax.numpy as jnp, fsjax
      >>> c = jnp.arange(32)
      >>> lo = 0.2 * jnp.cos(2 * jnp.pi * 0.0625 * c)
      >>> hi = 0.1 * jnp.cos(2 * jnp.pi * 0.25 * c)
      >>> x = fsjax.Image((0.5 + lo + hi) * jnp.ones((8, 1)))
      >>> out = fsjax.ops.ideal_bandpass(x, centre=0.25, octaves=1.0).data
      >>> float(jnp.max(jnp.abs(out - hi))) < 1e-12
      True
    """
    return _apply_filter("ideal_bandpass", img, "bandpass", "ideal", centre=centre, octaves=octaves,
                         pad=pad, mode=mode)


@register(family="frequency", takes=Image, gives=Image, knobs={"cutoff": _CUTOFF, "order": _ORDER},
          differentiable=True, refs=[_REF_BUTTER, _REF_GW])
def butterworth_lowpass(img: Image, /, *, cutoff: float = 0.1, order: float = 2.0, pad: int = 0,
                        mode: str = "reflect") -> Image:
    """Butterworth low-pass of order ``n``: ``H(f) = 1 / (1 + (f / fc) ** (2 n))``.

    Applied in the Fourier domain: ``out = irfft2(H * rfft2(img))``. Gain is 1 at
    DC (mean preserved), ``1/2`` at ``f = fc``; larger ``n`` gives a sharper edge
    (``n -> inf`` is the ideal filter).

    Args:
      img: input image ``(H, W)``; periodic boundary unless ``pad`` > 0.
      cutoff: half-gain frequency ``fc`` in cycles/pixel, > 0 (knob ``a``,
        log-mapped to [0.01, 0.5]); radial.
      order: ``n`` > 0, real-valued (knob ``b``, [1, 8]).
      pad: static padding in pixels on every side (0 = periodic boundary).
      mode: SciPy boundary mode used for the padding (default ``"reflect"``).

    Returns:
      ``Image`` ``(H, W)``, same dtype.

    Matches ``skimage.filters.butterworth(x, cutoff_frequency_ratio=fc,
    high_pass=False, order=n, squared_butterworth=True)`` to 1e-12 (with
    ``pad=p, mode="nearest"`` it matches ``npad=p``). Smooth in ``cutoff`` and ``order``.

    Example:
      A cosine at 0.125 cycles/px through ``fc = 0.125`` keeps half its amplitude
      (the gain at the cutoff is exactly 1/2 for every order):

      >>> import jax.numpy as jnp, fsjax
      >>> c = jnp.arange(32)
      >>> x = fsjax.Image(0.5 + 0.4 * jnp.cos(2 * jnp.pi * 0.125 * c) * jnp.ones((8, 1)))
      >>> out = fsjax.ops.butterworth_lowpass(x, cutoff=0.125, order=3.0).data
      >>> round(float(out[0, 0]), 9)
      0.7
    """
    return _apply_filter("butterworth_lowpass", img, "lowpass", "butterworth", cutoff=cutoff, order=order,
                         pad=pad, mode=mode)


@register(family="frequency", takes=Image, gives=Image, knobs={"cutoff": _CUTOFF, "order": _ORDER},
          differentiable=True, refs=[_REF_BUTTER, _REF_GW])
def butterworth_highpass(img: Image, /, *, cutoff: float = 0.1, order: float = 2.0, pad: int = 0,
                         mode: str = "reflect") -> Image:
    """Butterworth high-pass of order ``n``: ``H(f) = 1 - 1 / (1 + (f / fc) ** (2 n))``.

    Equal to the textbook ``1 / (1 + (fc / f) ** (2 n))`` for ``f > 0`` and exactly 0
    at DC, so the output has zero mean.

    Args:
      img: input image ``(H, W)``; periodic boundary unless ``pad`` > 0.
      cutoff: half-gain frequency ``fc`` in cycles/pixel, > 0 (knob ``a``,
        log-mapped to [0.01, 0.5]).
      order: ``n`` > 0 (knob ``b``, [1, 8]).
      pad: static padding in pixels on every side (0 = periodic boundary).
      mode: SciPy boundary mode used for the padding (default ``"reflect"``).

    Returns:
      **Signed**, zero-mean ``Image`` ``(H, W)`` (not clipped).

    Matches ``skimage.filters.butterworth(x, cutoff_frequency_ratio=fc,
    high_pass=True, order=n, squared_butterworth=True)`` to 1e-12. Smooth in
    ``cutoff`` and ``order``.

    Example:
      The gain at ``f = 2 fc`` with ``n = 2`` is ``16 / 17``:

      >>> import jax.numpy as jnp, fsjax
      >>> c = jnp.arange(32)
      >>> x = fsjax.Image(0.5 + 0.4 * jnp.cos(2 * jnp.pi * 0.25 * c) * jnp.ones((8, 1)))
      >>> out = fsjax.ops.butterworth_highpass(x, cutoff=0.125, order=2.0).data
      >>> abs(float(out[0, 0]) - 0.4 * 16 / 17) < 1e-12
      True
    """
    return _apply_filter("butterworth_highpass", img, "highpass", "butterworth", cutoff=cutoff,
                         order=order, pad=pad, mode=mode)


@register(family="frequency", takes=Image, gives=Image,
          knobs={"centre": _CENTRE, "octaves": _OCTAVES}, differentiable=True, refs=[_REF_BUTTER, _REF_GW])
def butterworth_bandpass(img: Image, /, *, centre: float = 0.1, octaves: float = 1.0, order: float = 2.0,
                         pad: int = 0, mode: str = "reflect") -> Image:
    """Butterworth band-pass: Butterworth low-pass at ``f_hi`` times high-pass at ``f_lo``.

    ``H = B_lp(f; f_hi) * (1 - B_lp(f; f_lo))`` with ``B_lp(f; c) = 1 / (1 + (f / c)**(2 n))``,
    ``f_lo = centre * 2**(-octaves / 2)``, ``f_hi = centre * 2**(octaves / 2)``;
    ``H(0) = 0``.

    Args:
      img: input image ``(H, W)``; periodic boundary unless ``pad`` > 0.
      centre: geometric band centre in cycles/pixel, > 0 (knob ``a``, log-mapped
        to [0.02, 0.4]).
      octaves: ``log2(f_hi / f_lo)``, > 0 (knob ``b``, [0.5, 4]).
      order: ``n`` > 0 of both Butterworth factors (not a knob).
      pad: static padding in pixels on every side (0 = periodic boundary).
      mode: SciPy boundary mode used for the padding (default ``"reflect"``).

    Returns:
      **Signed**, zero-mean ``Image`` ``(H, W)`` (not clipped).

    Equals ``butterworth_highpass(butterworth_lowpass(x, f_hi), f_lo)`` to 1e-14.
    Smooth in ``centre``, ``octaves`` and ``order``.

    Example:
      At the band centre ``f = 0.125`` with 2 octaves (``f_lo = 0.0625``,
      ``f_hi = 0.25``) and ``n = 1`` each factor is ``4 / 5``, the gain ``16 / 25``:

      >>> import jax.numpy as jnp, fsjax
      >>> c = jnp.arange(32)
      >>> x = fsjax.Image(0.5 + 0.4 * jnp.cos(2 * jnp.pi * 0.125 * c) * jnp.ones((8, 1)))
      >>> out = fsjax.ops.butterworth_bandpass(x, centre=0.125, octaves=2.0, order=1.0).data
      >>> abs(float(out[0, 0]) - 0.4 * 16 / 25) < 1e-12
      True
    """
    return _apply_filter("butterworth_bandpass", img, "bandpass", "butterworth", centre=centre,
                         octaves=octaves, order=order, pad=pad, mode=mode)


@register(family="frequency", takes=Image, gives=Image, knobs={"cutoff": _CUTOFF},
          differentiable=True, refs=[_REF_GW])
def gaussian_lowpass(img: Image, /, *, cutoff: float = 0.1, pad: int = 0, mode: str = "reflect") -> Image:
    """Gaussian low-pass in the Fourier domain: ``H(f) = exp(-f**2 / (2 fc**2))``.

    ``fc`` is the standard deviation of the transfer function (gain ``exp(-1/2)``
    at ``f = fc``); the filter equals a periodic spatial Gaussian blur with
    ``sigma = 1 / (2 pi fc)`` pixels. ``H(0) = 1``: the mean is preserved.

    Args:
      img: input image ``(H, W)``; periodic boundary unless ``pad`` > 0.
      cutoff: ``fc`` in cycles/pixel, > 0 (knob ``a``, log-mapped to [0.01, 0.5]).
      pad: static padding in pixels on every side (0 = periodic boundary).
      mode: SciPy boundary mode used for the padding (default ``"reflect"``).

    Returns:
      ``Image`` ``(H, W)``, same dtype; stays in ``[0, 1]`` for input in ``[0, 1]``
      up to round-off (the kernel is positive).

    Matches ``scipy.ndimage.fourier_gaussian`` with ``sigma = 1 / (2 pi fc)`` applied
    through ``numpy.fft.fft2`` to 1e-13. Smooth in ``cutoff``.

    Example:
      A cosine at ``f = 2 fc`` keeps ``exp(-2)`` of its amplitude:

      >>> import jax.numpy as jnp, fsjax
      >>> c = jnp.arange(32)
      >>> x = fsjax.Image(0.5 + 0.4 * jnp.cos(2 * jnp.pi * 0.25 * c) * jnp.ones((8, 1)))
      >>> out = fsjax.ops.gaussian_lowpass(x, cutoff=0.125).data
      >>> abs(float(out[0, 0]) - (0.5 + 0.4 * float(jnp.exp(-2.0)))) < 1e-12
      True
    """
    return _apply_filter("gaussian_lowpass", img, "lowpass", "gaussian", cutoff=cutoff, pad=pad, mode=mode)


@register(family="frequency", takes=Image, gives=Image, knobs={"cutoff": _CUTOFF},
          differentiable=True, refs=[_REF_GW])
def gaussian_highpass(img: Image, /, *, cutoff: float = 0.1, pad: int = 0, mode: str = "reflect") -> Image:
    """Gaussian high-pass in the Fourier domain: ``H(f) = 1 - exp(-f**2 / (2 fc**2))``.

    The complement of :func:`gaussian_lowpass` (``x - gaussian_lowpass(x)``), with
    ``H(0) = 0``: the output has zero mean.

    Args:
      img: input image ``(H, W)``; periodic boundary unless ``pad`` > 0.
      cutoff: ``fc`` in cycles/pixel, > 0 (knob ``a``, log-mapped to [0.01, 0.5]).
      pad: static padding in pixels on every side (0 = periodic boundary).
      mode: SciPy boundary mode used for the padding (default ``"reflect"``).

    Returns:
      **Signed**, zero-mean ``Image`` ``(H, W)`` (not clipped).

    Equals ``x - gaussian_lowpass(x)`` to 1e-14. Smooth in ``cutoff``.

    Example:
      At ``f = fc`` the gain is ``1 - exp(-1/2)``:

      >>> import jax.numpy as jnp, fsjax
      >>> c = jnp.arange(32)
      >>> x = fsjax.Image(0.5 + 0.4 * jnp.cos(2 * jnp.pi * 0.125 * c) * jnp.ones((8, 1)))
      >>> out = fsjax.ops.gaussian_highpass(x, cutoff=0.125).data
      >>> abs(float(out[0, 0]) - 0.4 * (1 - float(jnp.exp(-0.5)))) < 1e-12
      True
    """
    return _apply_filter("gaussian_highpass", img, "highpass", "gaussian", cutoff=cutoff, pad=pad, mode=mode)


@register(family="frequency", takes=Image, gives=Image,
          knobs={"centre": _CENTRE, "octaves": _OCTAVES}, differentiable=True, refs=[_REF_GW])
def gaussian_bandpass(img: Image, /, *, centre: float = 0.1, octaves: float = 1.0, pad: int = 0,
                      mode: str = "reflect") -> Image:
    """Gaussian band-pass: Gaussian low-pass at ``f_hi`` times Gaussian high-pass at ``f_lo``.

    ``H = exp(-f**2 / (2 f_hi**2)) * (1 - exp(-f**2 / (2 f_lo**2)))`` with
    ``f_lo = centre * 2**(-octaves / 2)``, ``f_hi = centre * 2**(octaves / 2)``;
    a smooth difference-of-Gaussians-like band with ``H(0) = 0``.

    Args:
      img: input image ``(H, W)``; periodic boundary unless ``pad`` > 0.
      centre: geometric band centre in cycles/pixel, > 0 (knob ``a``, log-mapped
        to [0.02, 0.4]).
      octaves: ``log2(f_hi / f_lo)``, > 0 (knob ``b``, [0.5, 4]).
      pad: static padding in pixels on every side (0 = periodic boundary).
      mode: SciPy boundary mode used for the padding (default ``"reflect"``).

    Returns:
      **Signed**, zero-mean ``Image`` ``(H, W)`` (not clipped).

    Smooth in ``centre`` and ``octaves``.

    Example:
      With ``centre = 0.125`` and 2 octaves, a cosine at ``f = 0.125`` has gain
      ``exp(-1/8) (1 - exp(-2))``:

      >>> import jax.numpy as jnp, fsjax
      >>> c = jnp.arange(32)
      >>> x = fsjax.Image(0.5 + 0.4 * jnp.cos(2 * jnp.pi * 0.125 * c) * jnp.ones((8, 1)))
      >>> out = fsjax.ops.gaussian_bandpass(x, centre=0.125, octaves=2.0).data
      >>> g = float(jnp.exp(-0.125) * (1 - jnp.exp(-2.0)))
      >>> abs(float(out[0, 0]) - 0.4 * g) < 1e-12
      True
    """
    return _apply_filter("gaussian_bandpass", img, "bandpass", "gaussian", centre=centre, octaves=octaves,
                         pad=pad, mode=mode)
