"""Colour conversions and colour ops (``Color``, ``HSV``, ``Lab`` <-> ``Image``).

Conventions:

* ``Color`` is **linear** RGB in ``[0, 1]`` with sRGB / ITU-R BT.709 primaries
  and D65 white. Files are usually sRGB-*encoded*; decode them with
  ``fsjax.io.read_image(..., linearize=True)`` or :func:`srgb_to_linear`.
* ``HSV``: hue in **turns** ``[0, 1)`` (0 red, 1/3 green, 2/3 blue), saturation
  and value in ``[0, 1]`` (Smith 1978, the hexcone model). Where saturation is
  0 (grey, black) the hue is *defined* as 0, with finite (zero) gradients.
* ``Lab``: CIE 1976 L*a*b*, D65 white, L* in ``[0, 100]``. The RGB -> XYZ matrix
  is derived in float64 from the BT.709 primaries and the D65 chromaticity
  ``(0.3127, 0.3290)`` (IEC 61966-2-1), and the reference white is that matrix
  applied to RGB ``(1, 1, 1)``, so every neutral grey has ``a* = b* = 0``
  exactly. The CIE piecewise function uses the exact constants
  ``delta = 6/29`` (continuous value and slope), not the rounded ``0.008856 /
  7.787``.
* Conversions do not clip: a Lab or HSV value outside the RGB gamut gives RGB
  outside ``[0, 1]``, which is the visible sign of an out-of-gamut colour.
* Divisions use a double ``jnp.where`` with a safe denominator (no ``+ eps``).
* Channel axis is last; ops are written for one image, batching is ``vmap``.
* Dtype-generic (float32 / float64).

This module also registers the standard-input pool builders of the ``HSV`` and
``Lab`` sorts (the pool's ``Color`` image converted by the ops below).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ..._checks import check_positive, check_range, note_traced
from ...registry import IntKnob, LinKnob, LogKnob, register
from ...types import HSV, Color, Image, Lab, is_concrete

__all__ = [
    "rgb_to_grey",
    "grey_to_rgb",
    "rgb_to_hsv",
    "hsv_to_rgb",
    "hue",
    "rgb_to_lab",
    "lab_to_rgb",
    "decorrelation_stretch",
    "color_channel",
]

# ---------------------------------------------------------------------------
# Constants
# ---------------------------------------------------------------------------

#: ITU-R BT.709 luma weights (rounded, as printed in the recommendation).
LUMA_709 = (0.2126, 0.7152, 0.0722)


def _rgb_to_xyz_matrix() -> np.ndarray:
    """RGB -> XYZ for BT.709 / sRGB primaries and D65 white, derived in float64."""
    prim = np.array([[0.64, 0.33], [0.30, 0.60], [0.15, 0.06]])  # R, G, B chromaticities (x, y)
    wx, wy = 0.3127, 0.3290  # D65
    P = np.stack([prim[:, 0] / prim[:, 1], np.ones(3), (1 - prim[:, 0] - prim[:, 1]) / prim[:, 1]])
    white = np.array([wx / wy, 1.0, (1 - wx - wy) / wy])
    s = np.linalg.solve(P, white)
    return P * s[None, :]


XYZ_FROM_RGB = _rgb_to_xyz_matrix()
RGB_FROM_XYZ = np.linalg.inv(XYZ_FROM_RGB)
#: Reference white (Xn, Yn, Zn) = XYZ_FROM_RGB @ (1, 1, 1); Yn = 1.
WHITE_D65 = XYZ_FROM_RGB.sum(axis=1)

_DELTA = 6.0 / 29.0


def _mix(x, m):
    """``out[..., r] = sum_c m[r, c] x[..., c]`` with static float64 ``m`` (dtype of ``x`` kept)."""
    cols = [x[..., 0], x[..., 1], x[..., 2]]
    rows = [float(m[r, 0]) * cols[0] + float(m[r, 1]) * cols[1] + float(m[r, 2]) * cols[2] for r in range(3)]
    return jnp.stack(rows, axis=-1)


# ---------------------------------------------------------------------------
# sRGB transfer functions (plain array functions, used by fsjax.io)
# ---------------------------------------------------------------------------


def srgb_to_linear(v):
    """sRGB EOTF (IEC 61966-2-1): encoded ``v`` in ``[0, 1]`` -> linear light.

    ``v / 12.92`` for ``v <= 0.04045``, else ``((v + 0.055) / 1.055) ** 2.4``;
    the linear segment is extended to negative values.
    """
    v = jnp.asarray(v)
    hi = v > 0.04045
    safe = jnp.where(hi, v, jnp.ones_like(v))
    return jnp.where(hi, ((safe + 0.055) / 1.055) ** 2.4, v / 12.92)


def linear_to_srgb(x):
    """Inverse sRGB EOTF: linear ``x`` -> sRGB-encoded value (``12.92 x`` near 0)."""
    x = jnp.asarray(x)
    hi = x > 0.0031308
    safe = jnp.where(hi, x, jnp.ones_like(x))
    return jnp.where(hi, 1.055 * safe ** (1.0 / 2.4) - 0.055, 12.92 * x)


# ---------------------------------------------------------------------------
# Array-level conversions (also used by the pool builders)
# ---------------------------------------------------------------------------


def _rgb_to_hsv(rgb):
    r, g, b = rgb[..., 0], rgb[..., 1], rgb[..., 2]
    v = jnp.max(rgb, axis=-1)
    delta = v - jnp.min(rgb, axis=-1)
    chroma = delta > 0
    d_safe = jnp.where(chroma, delta, jnp.ones_like(delta))
    v_safe = jnp.where(v > 0, v, jnp.ones_like(v))
    s = jnp.where(chroma & (v > 0), delta / v_safe, jnp.zeros_like(v))
    # sector of the hexcone, in sixths of a turn; blue wins ties over green over red
    # (the formulas agree at ties, so the choice only matters for the gradient)
    h6 = jnp.where(b == v, 4.0 + (r - g) / d_safe,
                   jnp.where(g == v, 2.0 + (b - r) / d_safe, (g - b) / d_safe))
    h = h6 / 6.0
    h = jnp.where(h < 0, h + 1.0, h)
    h = jnp.where(h >= 1.0, h - 1.0, h)  # -tiny + 1 rounds to 1
    h = jnp.where(chroma, h, jnp.zeros_like(h))
    return jnp.stack([h, s, v], axis=-1)


def _hsv_to_rgb(hsv):
    h, s, v = hsv[..., 0], hsv[..., 1], hsv[..., 2]
    h6 = 6.0 * (h - jnp.floor(h))
    out = []
    for n in (5.0, 3.0, 1.0):  # R, G, B
        k = jnp.mod(n + h6, 6.0)
        w = jnp.clip(jnp.minimum(k, 4.0 - k), 0.0, 1.0)
        out.append(v - v * s * w)
    return jnp.stack(out, axis=-1)


def _lab_f(t):
    big = t > _DELTA**3
    safe = jnp.where(big, t, jnp.ones_like(t))
    return jnp.where(big, jnp.cbrt(safe), t / (3.0 * _DELTA**2) + 4.0 / 29.0)


def _lab_finv(f):
    return jnp.where(f > _DELTA, f**3, 3.0 * _DELTA**2 * (f - 4.0 / 29.0))


def _rgb_to_lab(rgb):
    xyz = _mix(rgb, XYZ_FROM_RGB)
    fx = _lab_f(xyz[..., 0] / float(WHITE_D65[0]))
    fy = _lab_f(xyz[..., 1] / float(WHITE_D65[1]))
    fz = _lab_f(xyz[..., 2] / float(WHITE_D65[2]))
    return jnp.stack([116.0 * fy - 16.0, 500.0 * (fx - fy), 200.0 * (fy - fz)], axis=-1)


def _lab_to_rgb(lab):
    fy = (lab[..., 0] + 16.0) / 116.0
    fx = fy + lab[..., 1] / 500.0
    fz = fy - lab[..., 2] / 200.0
    xyz = jnp.stack([_lab_finv(fx) * float(WHITE_D65[0]), _lab_finv(fy) * float(WHITE_D65[1]),
                     _lab_finv(fz) * float(WHITE_D65[2])], axis=-1)
    return _mix(xyz, RGB_FROM_XYZ)


# ---------------------------------------------------------------------------
# Grey <-> colour
# ---------------------------------------------------------------------------


@register(family="color", takes=Color, gives=Image, differentiable=True,
          refs=["ITU-R Recommendation BT.709-6 (2015), item 3.2"])
def rgb_to_grey(img: Color, /) -> Image:
    """Relative luminance of linear RGB: ``Y = 0.2126 R + 0.7152 G + 0.0722 B`` (BT.709).

    On linear RGB this is the CIE luminance ``Y`` of the sRGB primaries (to 4
    decimals); on sRGB-encoded values it would be "luma", a different quantity.

    Args:
      img: linear RGB ``(H, W, 3)``.

    Returns:
      ``Image`` ``(H, W)`` in ``[0, 1]`` (the weights sum to 1).

    Note: ``skimage.color.rgb2gray`` uses the older weights ``0.2125, 0.7154,
    0.0721``; the two differ by at most ``2e-4`` for inputs in ``[0, 1]``
    (tested at that bound; measured ~1e-4 on photographs).

    Example:
      Pure green gives its weight; white gives 1:

      >>> import jax.numpy as jnp, fsjax
      >>> rgb = jnp.array([[[0.0, 1.0, 0.0], [1.0, 1.0, 1.0]]])
      >>> [round(float(v), 12) for v in fsjax.ops.rgb_to_grey(fsjax.Color(rgb)).data.ravel()]
      [0.7152, 1.0]
    """
    x = img.data
    wr, wg, wb = LUMA_709
    return Image(wr * x[..., 0] + wg * x[..., 1] + wb * x[..., 2])


@register(family="color", takes=Image, gives=Color, differentiable=True,
          refs=["ITU-R Recommendation BT.709-6 (2015)"])
def grey_to_rgb(img: Image, /) -> Color:
    """Neutral colour image from grey: ``R = G = B = x``.

    The result is achromatic (HSV saturation 0, Lab ``a* = b* = 0``) and
    :func:`rgb_to_grey` returns ``x`` again (the BT.709 weights sum to 1).

    Args:
      img: grey image ``(H, W)``.

    Returns:
      ``Color`` ``(H, W, 3)``.

    Matches ``skimage.color.gray2rgb`` exactly.

    Example:
      >>> import jax.numpy as jnp, fsjax
      >>> out = fsjax.ops.grey_to_rgb(fsjax.Image(jnp.full((2, 2), 0.25)))
      >>> out.data.shape, [float(v) for v in out.data[0, 0]]
      ((2, 2, 3), [0.25, 0.25, 0.25])
    """
    x = img.data
    return Color(jnp.stack([x, x, x], axis=-1))


# ---------------------------------------------------------------------------
# HSV
# ---------------------------------------------------------------------------


@register(family="color", takes=Color, gives=HSV, differentiable=False,
          refs=["A. R. Smith, Color gamut transform pairs, SIGGRAPH 1978, doi:10.1145/800248.807361"])
def rgb_to_hsv(img: Color, /) -> HSV:
    """RGB to hue/saturation/value (hexcone model); hue in turns ``[0, 1)``.

    ``V = max(R, G, B)``, ``S = (V - min) / V``, and the hue is the position on
    the hexagon, ``(G - B) / (6 delta)`` (mod 1) when red is largest, ``(2 + (B - R)
    / delta) / 6`` for green and ``(4 + (R - G) / delta) / 6`` for blue, with
    ``delta = V - min``. Grey pixels (``delta = 0``) get hue 0 and saturation 0,
    black gets ``S = 0``; no NaN in values or gradients.

    Not declared differentiable: hue jumps from ~1 to 0 across red and is
    non-smooth where the largest channel changes. Saturation and value
    gradients are finite everywhere.

    Args:
      img: linear (or encoded, the formula does not care) RGB ``(H, W, 3)``.

    Returns:
      ``HSV`` ``(H, W, 3)``: hue ``[0, 1)``, saturation and value ``[0, 1]`` for
      inputs in ``[0, 1]``.

    Matches ``skimage.color.rgb2hsv`` to 1e-12 in float64 (skimage can return
    hue exactly 1.0 by rounding; fsjax wraps it to 0, compared circularly).

    Example:
      >>> import jax.numpy as jnp, fsjax
      >>> rgb = jnp.array([[[0.0, 0.5, 0.0], [0.4, 0.4, 0.4], [1.0, 0.0, 0.5]]])
      >>> hsv = fsjax.ops.rgb_to_hsv(fsjax.Color(rgb)).data
      >>> [[round(float(v), 12) for v in px] for px in hsv[0]]
      [[0.333333333333, 1.0, 0.5], [0.0, 0.0, 0.4], [0.916666666667, 1.0, 1.0]]
    """
    return HSV(_rgb_to_hsv(img.data))


@register(family="color", takes=HSV, gives=Color, differentiable=True,
          refs=["A. R. Smith, Color gamut transform pairs, SIGGRAPH 1978, doi:10.1145/800248.807361"])
def hsv_to_rgb(img: HSV, /) -> Color:
    """HSV (hue in turns) back to RGB, the inverse of :func:`rgb_to_hsv`.

    Channel ``n`` (``n = 5, 3, 1`` for R, G, B) is ``V - V S clip(min(k, 4 - k),
    0, 1)`` with ``k = (n + 6 H) mod 6``: continuous and piecewise linear in hue,
    so it is differentiable almost everywhere. Hue outside ``[0, 1)`` wraps.

    Args:
      img: ``HSV`` ``(H, W, 3)``.

    Returns:
      ``Color`` ``(H, W, 3)``; in ``[0, 1]`` when ``S, V`` are in ``[0, 1]``.

    Matches ``skimage.color.hsv2rgb`` to 1e-12 in float64;
    ``hsv_to_rgb(rgb_to_hsv(x)) == x`` to 1e-15.

    Example:
      One third of a turn is pure green; half saturation halves the gap to white:

      >>> import jax.numpy as jnp, fsjax
      >>> hsv = jnp.array([[[1 / 3, 1.0, 1.0], [0.0, 0.5, 0.8]]])
      >>> rgb = fsjax.ops.hsv_to_rgb(fsjax.HSV(hsv)).data
      >>> [[round(float(v), 12) for v in px] for px in rgb[0]]
      [[0.0, 1.0, 0.0], [0.8, 0.4, 0.4]]
    """
    return Color(_hsv_to_rgb(img.data))


@register(family="color", takes=HSV, gives=Image, differentiable=True,
          refs=["A. R. Smith, Color gamut transform pairs, SIGGRAPH 1978, doi:10.1145/800248.807361"])
def hue(img: HSV, /) -> Image:
    """The hue channel of an HSV image, in turns ``[0, 1)``.

    Hue is circular: 0 and 1 are the same red, so differences should be taken
    modulo 1. Grey pixels carry hue 0 (see :func:`rgb_to_hsv`).

    Args:
      img: ``HSV`` ``(H, W, 3)``.

    Returns:
      ``Image`` ``(H, W)``.

    Reference: ``skimage.color.rgb2hsv(x)[..., 0]`` (exact selection).

    Example:
      >>> import jax.numpy as jnp, fsjax
      >>> hsv = fsjax.ops.rgb_to_hsv(fsjax.Color(jnp.array([[[0.0, 0.0, 1.0]]])))
      >>> round(float(fsjax.ops.hue(hsv).data[0, 0]), 12)
      0.666666666667
    """
    return Image(img.data[..., 0])


# ---------------------------------------------------------------------------
# CIE L*a*b*
# ---------------------------------------------------------------------------


@register(family="color", takes=Color, gives=Lab, differentiable=True,
          refs=["CIE 15:2004 Colorimetry, 3rd ed., sec. 8.2.1",
                "IEC 61966-2-1:1999 (sRGB primaries and D65 white)"])
def rgb_to_lab(img: Color, /) -> Lab:
    """Linear RGB to CIE L*a*b* (D65): ``XYZ = M rgb``, then the CIE 1976 formulas.

    ``L* = 116 f(Y/Yn) - 16``, ``a* = 500 (f(X/Xn) - f(Y/Yn))``, ``b* = 200
    (f(Y/Yn) - f(Z/Zn))`` with ``f(t) = t^(1/3)`` above ``(6/29)^3`` and the
    linear segment ``t / (3 (6/29)^2) + 4/29`` below (continuous slope, so the
    op is C1 and safe at 0). ``M`` and the white are described in the module
    docstring. The input is *linear* RGB.

    Args:
      img: linear RGB ``(H, W, 3)``.

    Returns:
      ``Lab`` ``(H, W, 3)``: L* in ``[0, 100]`` for inputs in ``[0, 1]``, a*, b*
      roughly in ``[-110, 110]``.

    Conformance: ``skimage.color.rgb2lab`` expects sRGB-*encoded* input, so the
    reference is ``rgb2lab(linear_to_srgb(x))``. scikit-image uses a 6-digit
    matrix, white ``(0.95047, 1, 1.08883)`` and the rounded constants ``0.008856
    / 7.787``; the results agree to 0.02 in each of L*, a*, b* (far below one
    just-noticeable difference, about 1 unit of Delta E).

    Example:
      White is L* = 100 and any grey is neutral (a* = b* = 0 exactly); 18 %
      grey has L* = 116 * 0.18 ** (1/3) - 16:

      >>> import jax.numpy as jnp, fsjax
      >>> rgb = jnp.array([[[1.0, 1.0, 1.0], [0.18, 0.18, 0.18]]])
      >>> lab = fsjax.ops.rgb_to_lab(fsjax.Color(rgb)).data
      >>> [round(float(v), 9) + 0.0 for v in lab[0, 0]]
      [100.0, 0.0, 0.0]
      >>> abs(float(lab[0, 1, 0]) - (116 * 0.18 ** (1 / 3) - 16)) < 1e-9
      True
    """
    return Lab(_rgb_to_lab(img.data))


@register(family="color", takes=Lab, gives=Color, differentiable=True,
          refs=["CIE 15:2004 Colorimetry, 3rd ed., sec. 8.2.1",
                "IEC 61966-2-1:1999 (sRGB primaries and D65 white)"])
def lab_to_rgb(img: Lab, /) -> Color:
    """CIE L*a*b* (D65) back to linear RGB, the exact inverse of :func:`rgb_to_lab`.

    ``f^-1(u) = u^3`` above ``6/29``, else ``3 (6/29)^2 (u - 4/29)``; then
    ``rgb = M^-1 XYZ``. Out-of-gamut colours give RGB outside ``[0, 1]`` (not
    clipped; scikit-image's ``lab2rgb`` clips and warns).

    Args:
      img: ``Lab`` ``(H, W, 3)``.

    Returns:
      ``Color`` ``(H, W, 3)``, linear RGB.

    ``lab_to_rgb(rgb_to_lab(x)) == x`` to 1e-12 in float64 (tested with
    hypothesis); agrees with ``srgb_to_linear(skimage.color.lab2rgb(lab))`` to
    2e-4 in linear RGB for in-gamut colours.

    Example:
      >>> import jax.numpy as jnp, fsjax
      >>> rgb = fsjax.ops.lab_to_rgb(fsjax.Lab(jnp.array([[[100.0, 0.0, 0.0], [50.0, 0.0, 0.0]]]))).data
      >>> [round(float(v), 9) for v in rgb[0, 0]]
      [1.0, 1.0, 1.0]
      >>> abs(float(rgb[0, 1, 1]) - (66 / 116) ** 3) < 1e-12
      True
    """
    return Color(_lab_to_rgb(img.data))


# ---------------------------------------------------------------------------
# Decorrelation stretch, channel selection
# ---------------------------------------------------------------------------


def _stretch_gains(lam, aux):
    """Per-axis gains of :func:`decorrelation_stretch` from the covariance's eigenvalues ``lam``
    and ``aux = (tol, flat, max_gain, trace C)`` (see its docstring for the formula)."""
    tol, flat, max_gain, tr = aux[0], aux[1] > 0.5, aux[2], aux[3]
    eps = jnp.finfo(lam.dtype).eps
    lam = jnp.maximum(lam, 0.0)
    floor = jnp.maximum(lam, jnp.max(lam) / max_gain**2)
    # A null axis (rank-deficient covariance) holds only rounding: eigh's absolute error on its
    # eigenvalue, ~eps * lam_max, and the data's own rounding, below tol / 4096. The max_gain
    # floor alone stretched it by max_gain at every call (float32: three stretches of a rank-2
    # image drifted 4.5e-3 from float64 and eager from jit, the chain fuzzer's MISMATCH); a hard
    # cut-off made the op discontinuous there. Each axis's gain is multiplied by the smooth
    # factor w = u^4 / sqrt(u^8 + 1), u = lam / r (1 - u^-8 / 2 for u >> 1, u^4 -> 0 for
    # u << 1), r = eps^(2/3) tr(C) + tol: eps^(-1/3) (float32 203, float64 1.6e5) times eigh's
    # rounding, so a rounding eigenvalue gets w < 1e-9. The fourth power keeps a finite-difference
    # step of 1e-7 of the data (u ~ 1e-3 on a null axis in float64) well inside w ~ 0 (with u^2
    # and r = 64 eps tr(C), the contract's FD gradient failed); u is capped at 1e3 (w = 1 to
    # 5e-25) so u^8 stays finite in float32.
    r = jnp.where(flat, 1.0, eps ** (2.0 / 3.0) * tr + tol)   # > 0 (all-zero image: tol = 0)
    u4 = jnp.minimum(lam / r, 1e3) ** 4
    w = u4 / jnp.sqrt(u4**2 + 1.0)
    ok = (floor > 0) & ~flat
    return jnp.where(ok, w / jnp.sqrt(jnp.where(ok, floor, jnp.ones_like(floor))), jnp.zeros_like(floor))


@jax.custom_jvp
def _whitening(c, aux):
    """``V diag(g(lam)) V^T`` for the symmetric 3 x 3 ``c = V diag(lam) V^T``, ``g`` =
    :func:`_stretch_gains`, with a derivative that stays finite where eigenvalues coincide."""
    lam, vec = jnp.linalg.eigh(c)
    return (vec * _stretch_gains(lam, aux)[None, :]) @ vec.T


@_whitening.defjvp
def _whitening_jvp(primals, tangents):
    # A spectral matrix function M = V diag(g(lam)) V^T has the derivative (Daleckii-Krein; for g
    # depending on every eigenvalue, Lewis 1996 / Sendov 2007) V [diag(J dlam) + D o S] V^T with
    # S = V^T dC V, dlam = diag(S), J = dg/dlam and D_ij = (g_i - g_j) / (lam_i - lam_j), whose
    # limit at lam_i = lam_j is J_ii - J_ij. eigh's own derivative has 1 / (lam_i - lam_j) in the
    # eigenvectors' part: 0 * inf = NaN at a repeated eigenvalue (two null colour axes of a grey
    # image: the chain fuzzer's GRADNAN), although M does not depend on the basis chosen there.
    c, aux = primals
    dc, daux = tangents
    lam, vec = jnp.linalg.eigh(c)
    g, dg_aux = jax.jvp(lambda a: _stretch_gains(lam, a), (aux,), (daux,))
    jac = jax.jacfwd(_stretch_gains)(lam, aux)
    sm = vec.T @ dc @ vec
    sm = 0.5 * (sm + sm.T)
    dg = jac @ jnp.diagonal(sm) + dg_aux
    dl = lam[:, None] - lam[None, :]
    eps = jnp.finfo(lam.dtype).eps
    close = jnp.abs(dl) <= jnp.sqrt(eps) * jnp.maximum(jnp.max(jnp.abs(lam)), jnp.finfo(lam.dtype).tiny)
    jd = jnp.diagonal(jac)
    lim = 0.5 * ((jd[:, None] - jac) + (jd[None, :] - jac.T))
    dd = jnp.where(close, lim, (g[:, None] - g[None, :]) / jnp.where(close, 1.0, dl))
    inner = jnp.where(jnp.eye(3, dtype=bool), jnp.diag(dg), dd * sm)
    return (vec * g[None, :]) @ vec.T, vec @ inner @ vec.T


@register(family="color", takes=Color, gives=Color,
          knobs={"target_sigma": LinKnob(0.05, 0.3), "max_gain": LogKnob(3.0, 300.0)},
          differentiable=True,
          refs=["A. R. Gillespie, A. B. Kahle, R. E. Walker, Color enhancement of highly correlated "
                "images. I. Decorrelation and HSI contrast stretches, Remote Sensing of Environment "
                "20(3), 209-235, 1986"])
def decorrelation_stretch(img: Color, /, *, target_sigma: float | None = None,
                          max_gain: float = 100.0) -> Color:
    """Decorrelation stretch: whiten the RGB channel covariance, then rescale each channel.

    With channel mean ``mu`` and (population) covariance ``C = V diag(lam) V^T``
    over all pixels, ``out = mu + diag(s) V diag(g) V^T (x - mu)`` with
    ``g_i = lam_i^-1/2``: the data are rotated onto their principal axes, every
    axis is stretched to unit variance, and rotated back, so the output channels
    are *uncorrelated*, each with standard deviation ``s`` and the original mean.
    Hue differences hidden in highly correlated channels become visible
    (Gillespie et al. 1986; the same transform as MATLAB's ``decorrstretch``).

    A weak principal axis is mostly noise, and a null one (rank-deficient
    covariance, e.g. channels that are exact linear combinations of each other)
    would get an infinite gain. The gain of every axis is therefore capped at
    ``max_gain`` times the gain of the strongest axis, and multiplied by a smooth
    factor that goes to 0 on an axis at the dtype's rounding level:
    ``g_i = w(lam_i) max(lam_i, lam_max / max_gain^2)^-1/2`` with
    ``w = u^4 / sqrt(u^8 + 1)``, ``u = lam_i / r``,
    ``r = eps^(2/3) tr(C) + (64 eps max|x|)^2`` (``eps`` the dtype's resolution:
    ``r`` is 2.4e-5 of the total variance in float32, 3.7e-11 in float64; the
    second term, the data's rounding, matters only on near-constant images).
    Axes above the cap's floor are whitened exactly up to ``w``
    (``1 - w <= (r / lam)^8 / 2``): in float64 to 1e-20 for every axis above 1e-8
    of the total variance; **in float32 an axis with ``lam >= 1e-4 tr(C)`` is
    whitened to a relative 6e-6**, one at ``lam = r`` gets ``w = 0.71``, and one below
    ``r / 10`` gets ``w < 1e-4``: a null axis, whose eigenvalue is rounding (eigh's
    error ~``eps lam_max``, ``u < 5e-3``), carries nothing. So a null axis's rounding
    noise is not stretched and repeated stretches do not amplify it: six stretches
    in a row of the pool's rank-2 float32 colour scene stay within 6e-7 of float64,
    eager and ``jit`` within 1e-6 (with the cap alone, ``max_gain`` per call: 4.5e-3
    after three, the chain fuzzer's MISMATCH). ``w`` is smooth, so the op stays
    continuous and differentiable at rank-deficient input (a hard cut-off at the
    rounding level was not). A constant image (variance below
    ``(64 eps max|x|)^2``, the mean's rounding) is returned as its mean, with or
    without ``target_sigma``.
    Gradients are finite everywhere, also where two eigenvalues coincide (a grey
    image: two null colour axes; found by the chain fuzzer as a NaN gradient): the
    whitening matrix is a spectral function of the covariance, differentiated by
    divided differences of the gains with their limit at a repeated eigenvalue
    (Daleckii-Krein) instead of through the eigenvectors, whose derivative is
    singular there.

    Args:
      img: linear RGB ``(H, W, 3)``.
      target_sigma: output standard deviation of every channel (knob ``a``, linear
        on [0.05, 0.3]). ``None`` (default) keeps each channel's own input
        standard deviation, as MATLAB ``decorrstretch`` does.
      max_gain: cap on the stretch of the weakest axis relative to the strongest,
        > 1 (knob ``b``, log-mapped to [3, 300]); default 100, i.e. axes with less
        than 1e-4 of the largest variance are not fully whitened.

    Returns:
      ``Color`` ``(H, W, 3)``; not clipped (stretched values can leave ``[0, 1]``).

    No reference implementation in scikit-image/OpenCV; tested against the
    defining property (output covariance ``diag(s^2)`` to 1e-10, mean preserved)
    and against an explicit NumPy eigen-decomposition to 1e-12.

    Example:
      Two noisy but strongly correlated channels come out uncorrelated, each
      keeping its own spread:

      >>> import numpy as np, jax.numpy as jnp, fsjax
      >>> rng = np.random.default_rng(0)
      >>> base = rng.uniform(0.3, 0.7, (16, 16))
      >>> rgb = np.stack([base, base + 0.02 * rng.standard_normal((16, 16)),
      ...                 0.5 + 0.1 * rng.standard_normal((16, 16))], axis=-1)
      >>> out = fsjax.ops.decorrelation_stretch(fsjax.Color(jnp.asarray(rgb))).data.reshape(-1, 3)
      >>> bool(abs(np.corrcoef(rgb.reshape(-1, 3).T)[0, 1]) > 0.9)
      True
      >>> c = np.cov(np.asarray(out).T, bias=True)
      >>> bool(abs(c[0, 1]) < 1e-12 and abs(np.sqrt(c[1, 1]) - rgb[..., 1].std()) < 1e-12)
      True
    """
    if target_sigma is not None:
        check_positive("decorrelation_stretch", "target_sigma", target_sigma)
    check_range("decorrelation_stretch", "max_gain", max_gain, 1.0, None, lo_open=True)
    x = img.data
    flat = x.reshape(-1, 3)
    mu = jnp.mean(flat, axis=0)
    d = flat - mu
    cov = d.T @ d / flat.shape[0]
    # A constant image: its deviations from the mean are the mean's rounding error (the same at
    # every pixel), which whitening would stretch into a spurious offset of order target_sigma;
    # and its covariance has equal eigenvalues, where eigh's eigenvector derivative is
    # 0 * inf = NaN even for a zero tangent. Below a variance of (64 eps max|x|)^2 the image is
    # taken as constant: the output is its mean, the decomposition is of a fixed matrix with
    # distinct eigenvalues, and the gradient stays finite.
    eps = jnp.finfo(x.dtype).eps
    tol = (64 * eps * jnp.max(jnp.abs(flat))) ** 2
    flat_cov = jnp.trace(cov) <= 3 * tol
    c = jnp.where(flat_cov, jnp.diag(jnp.arange(1.0, 4.0, dtype=cov.dtype)), cov)
    aux = jnp.stack([tol, flat_cov.astype(cov.dtype), jnp.asarray(max_gain, cov.dtype), jnp.trace(cov)])
    whiten = _whitening(c, aux)
    if target_sigma is None:
        var = jnp.diagonal(cov)
        pos = var > 0
        s = jnp.where(pos, jnp.sqrt(jnp.where(pos, var, jnp.ones_like(var))), jnp.zeros_like(var))
    else:
        s = jnp.full((3,), target_sigma, dtype=x.dtype)
    out = mu + (d @ whiten) * s[None, :]
    return Color(out.reshape(x.shape).astype(x.dtype))


@register(family="color", takes=Color, gives=Image, knobs={"channel": IntKnob(0, 2)},
          differentiable=False, refs=["numpy indexing x[..., channel]"])
def color_channel(img: Color, /, *, channel: int = 0) -> Image:
    """One RGB channel as a grey image: ``out = x[..., channel]`` (0 = R, 1 = G, 2 = B).

    The channel may be a traced value (knob ``a`` is an ``IntKnob`` on {0, 1, 2}),
    so a search can pick the channel; the selection is an exact ``where`` chain. A
    traced channel other than 0, 1 or 2 gives an all-NaN image (an eager one raises).
    Not differentiable in the knob (piecewise constant); linear in the input.

    Args:
      img: RGB ``(H, W, 3)``.
      channel: channel index 0, 1 or 2 (knob ``a``, ``IntKnob(0, 2)``); default 0 (red).

    Returns:
      ``Image`` ``(H, W)``.

    Reference: NumPy indexing ``x[..., channel]`` (exact).

    Example:
      >>> import jax.numpy as jnp, fsjax
      >>> rgb = fsjax.Color(jnp.array([[[0.1, 0.2, 0.3]]]))
      >>> [float(fsjax.ops.color_channel(rgb, channel=c).data[0, 0]) for c in (0, 1, 2)]
      [0.1, 0.2, 0.3]
    """
    if is_concrete(channel):
        c = np.asarray(channel)
        if c.ndim != 0 or not np.isfinite(float(c)) or float(c) != int(float(c)) or not 0 <= int(float(c)) <= 2:
            raise ValueError(f"color_channel: argument 'channel' must be 0, 1 or 2, got {channel!r}")
    x = img.data
    ch = jnp.asarray(channel)
    # a traced channel outside {0, 1, 2} would select blue: the output is poisoned instead
    note_traced(channel, ~((ch == 0) | (ch == 1) | (ch == 2)))
    return Image(jnp.where(ch == 0, x[..., 0], jnp.where(ch == 1, x[..., 1], x[..., 2])))
