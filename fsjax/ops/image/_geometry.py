"""Geometric transforms (``Image -> Image``): mirror, translate, rotate, zoom, shear,
affine warp and resize, on one shared interpolating sampler.

Conventions:

* Arrays are ``(row, col)``; pixel centres sit on integer indices, so the image
  centre is ``((H - 1) / 2, (W - 1) / 2)``. ``dx``/``kx`` act along columns
  (x to the right), ``dy``/``ky`` along rows (y down).
* Every warp is written as an *inverse map*: output pixel ``(r, c)`` reads the
  input at a (sub-pixel) position ``(r_in, c_in)``; each op's docstring gives
  that map. Outputs have the input's shape except :func:`resize`.
* Interpolation (``method``): ``"nearest"`` (``floor(x + 0.5)``), ``"bilinear"``
  (default) or ``"bicubic"`` -- Keys' cubic convolution kernel with parameter
  ``cubic_a`` (``-0.5``: Keys 1981, third-order accurate; ``-0.75``: OpenCV's
  ``INTER_CUBIC``). The sampler gathers the 1, 2 or 4 taps per axis with
  clamped/folded integer indices and sums them with their weights; warps that
  are separable (translate, zoom, resize) interpolate one axis at a time.
* Boundary (``mode``), SciPy names as in ``scipy.ndimage.map_coordinates``:

  ==================  ========================================================
  ``"grid-constant"`` **default for warps**. The image is surrounded by
                      ``cval`` (default 0.0, black): taps outside the grid read
                      ``cval``, so pixels whose source lies more than one pixel
                      outside get exactly ``cval`` and the outermost ring blends
                      into it. Continuous in the geometry. (OpenCV's
                      ``BORDER_CONSTANT``, scikit-image's ``constant``.)
  ``"constant"``      SciPy's ``constant``: an output pixel whose source
                      position lies outside ``[0, H-1] x [0, W-1]`` gets
                      ``cval``; inside, taps beyond the edge repeat the edge
                      pixel (a round-off band of ``64 eps max(H, W)`` px counts
                      as inside). Jumps to ``cval`` at the border.
  ``"nearest"``       taps clamp to the edge (``a a | a b c d | d d``);
                      default for :func:`resize` (OpenCV's ``BORDER_REPLICATE``).
  ``"reflect"``       half-sample symmetric (``b a | a b c d | d c``).
  ``"mirror"``        whole-sample symmetric (``c b | a b c d | c b``).
  ``"wrap"``          periodic (``c d | a b c d | a b``), equal to SciPy's
                      ``"grid-wrap"`` (also accepted); SciPy's own ``"wrap"``
                      deviates near the edges for interpolation and is not copied.
  ==================  ========================================================

* Values: warps of an image in ``[0, 1]`` stay in ``[0, 1]`` for nearest and
  bilinear (convex weights) when ``cval`` is in ``[0, 1]``; bicubic can
  overshoot slightly near edges (negative lobes). Outputs are not clipped.
* Differentiability: every warp is linear in the image. In the geometry,
  bilinear sampling is continuous and piecewise linear (a kink whenever a
  source position crosses an integer; ``jax.grad`` returns the derivative of
  the piece it is on, exact almost everywhere), bicubic (Keys) sampling is
  continuously differentiable. A translation moves every pixel by the same
  amount, so its kinks sit only at integer shifts and :func:`translate`
  defaults to bilinear. Rotation, zoom and shear move each pixel differently,
  so in bilinear mode some pixel crosses an integer every ~1e-3 degree and
  finite differences disagree with the (correct, one-sided) gradient by
  percents; these ops default to ``"bicubic"``, whose gradient is continuous in
  the knob. ``method="nearest"`` is piecewise constant, and ``mode="constant"``
  jumps to ``cval`` where a source position leaves the image.
* Dtype-generic: coordinates are computed in the image's float dtype.
"""

from __future__ import annotations

import functools
import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from ..._checks import check_choice, check_positive, check_range, check_static_int
from ...registry import LinKnob, LogKnob, register
from ...types import Image, is_concrete
from .._common import correlate1d, eps, float_dtype
from ._filters import gaussian_weights

__all__ = ["mirror", "translate", "rotate", "zoom", "shear", "affine_warp", "resize"]

MODES = ("constant", "grid-constant", "nearest", "reflect", "mirror", "wrap", "grid-wrap")
METHODS = ("nearest", "bilinear", "bicubic")

_REF_KEYS = ("R. G. Keys, Cubic convolution interpolation for digital image processing, "
             "IEEE Trans. ASSP 29(6) (1981) 1153-1160")
_REF_WOLBERG = "G. Wolberg, Digital Image Warping, IEEE Computer Society Press, 1990"


# ---------------------------------------------------------------------------
# The shared sampler
# ---------------------------------------------------------------------------


def _check_sampling(op: str, method: str, mode: str, cval: Any, cubic_a: Any) -> None:
    check_choice(op, "method", method, METHODS)
    check_choice(op, "mode", mode, MODES)
    check_range(op, "cval", cval)
    check_range(op, "cubic_a", cubic_a, -3.0, 0.0)


def _fold(i, n: int, mode: str):
    """Map integer tap indices onto ``[0, n - 1]`` by the boundary ``mode``."""
    if mode in ("nearest", "constant", "grid-constant"):
        return jnp.clip(i, 0, n - 1)
    if mode in ("wrap", "grid-wrap"):
        return jnp.mod(i, n)
    if n == 1:
        return jnp.zeros_like(i)
    if mode == "reflect":
        j = jnp.mod(i, 2 * n)
        return jnp.where(j < n, j, 2 * n - 1 - j)
    j = jnp.mod(i, 2 * n - 2)  # mirror
    return jnp.where(j < n, j, 2 * n - 2 - j)


def _keys_inner(s, a):
    # Keys kernel for 0 <= s <= 1
    return ((a + 2.0) * s - (a + 3.0)) * s * s + 1.0


def _keys_outer(s, a):
    # Keys kernel for 1 <= s <= 2
    return ((a * s - 5.0 * a) * s + 8.0 * a) * s - 4.0 * a


def _taps(x, method: str, cubic_a):
    """Integer tap positions and weights for sample positions ``x`` (any shape)."""
    # The tap index is materialised once and the fraction is taken against it:
    # otherwise XLA may recompute x in several fusions with different rounding
    # (FMA contraction) and pair the index of one copy with the fraction of
    # another, a one-pixel error at integer positions. A fraction slightly
    # outside [0, 1) from such rounding is harmless (the weights are continuous).
    if method == "nearest":
        i = lax.optimization_barrier(jnp.floor(x + 0.5).astype(jnp.int32))
        return [(i, jnp.ones_like(x))]
    i0 = lax.optimization_barrier(jnp.floor(x).astype(jnp.int32))
    t = x - i0.astype(x.dtype)
    if method == "bilinear":
        return [(i0, 1.0 - t), (i0 + 1, t)]
    a = jnp.asarray(cubic_a, dtype=x.dtype)
    return [
        (i0 - 1, _keys_outer(1.0 + t, a)),
        (i0, _keys_inner(t, a)),
        (i0 + 1, _keys_inner(1.0 - t, a)),
        (i0 + 2, _keys_outer(2.0 - t, a)),
    ]


def _inside(x, n: int):
    tol = 64.0 * eps(x.dtype) * max(n, 1)
    return (x >= -tol) & (x <= (n - 1) + tol)


def sample2d(data, rows, cols, *, method: str = "bilinear", mode: str = "grid-constant", cval: Any = 0.0,
             cubic_a: Any = -0.5):
    """Interpolate ``data[..., H, W]`` at positions ``(rows, cols)`` (same shape, any).

    Returns an array of shape ``(*batch, *rows.shape)``. See the module docstring
    for ``method`` and ``mode``.
    """
    h, w = data.shape[-2:]
    dt = data.dtype
    cv = jnp.asarray(cval, dtype=dt)
    out = None
    for ir, wr in _taps(rows, method, cubic_a):
        for ic, wc in _taps(cols, method, cubic_a):
            v = data[..., _fold(ir, h, mode), _fold(ic, w, mode)]
            if mode == "grid-constant":
                ok = (ir >= 0) & (ir < h) & (ic >= 0) & (ic < w)
                v = jnp.where(ok, v, cv)
            term = (wr * wc) * v
            out = term if out is None else out + term
    if mode == "constant":
        out = jnp.where(_inside(rows, h) & _inside(cols, w), out, cv)
    return out


def sample1d(data, x, axis: int, *, method: str = "bilinear", mode: str = "grid-constant", cval: Any = 0.0,
             cubic_a: Any = -0.5):
    """Interpolate ``data`` along ``axis`` (-2 or -1) at the 1-D positions ``x``."""
    n = data.shape[axis]
    dt = data.dtype
    cv = jnp.asarray(cval, dtype=dt)
    shape = (-1, 1) if axis == -2 else (-1,)
    out = None
    for i, wt in _taps(x, method, cubic_a):
        v = jnp.take(data, _fold(i, n, mode), axis=axis)
        if mode == "grid-constant":
            v = jnp.where(((i >= 0) & (i < n)).reshape(shape), v, cv)
        term = wt.reshape(shape) * v
        out = term if out is None else out + term
    if mode == "constant":
        out = jnp.where(_inside(x, n).reshape(shape), out, cv)
    return out


def _grid(h: int, w: int, dt):
    r = jnp.arange(h, dtype=dt)[:, None] * jnp.ones((1, w), dt)
    c = jnp.ones((h, 1), dt) * jnp.arange(w, dtype=dt)[None, :]
    return r, c


# The op bodies below are compiled once per (shape, dtype, method, mode): eager
# calls then run one fused program instead of dispatching ~100 small ops.


@functools.partial(jax.jit, static_argnames=("method", "mode"))
def _warp_affine(data, m, cval, cubic_a, *, method, mode):
    """Inverse-map warp: input position ``m[:, :2] @ (r, c) + m[:, 2]`` for output ``(r, c)``."""
    h, w = data.shape[-2:]
    r, c = _grid(h, w, data.dtype)
    rows = m[0, 0] * r + m[0, 1] * c + m[0, 2]
    cols = m[1, 0] * r + m[1, 1] * c + m[1, 2]
    return sample2d(data, rows, cols, method=method, mode=mode, cval=cval, cubic_a=cubic_a)


@functools.partial(jax.jit, static_argnames=("method", "mode"))
def _separable(data, pos_r, pos_c, cval, cubic_a, *, method, mode):
    """Separable warp: rows read the input at ``pos_r``, columns at ``pos_c``."""
    kw = dict(method=method, mode=mode, cval=cval, cubic_a=cubic_a)
    return sample1d(sample1d(data, pos_r, -2, **kw), pos_c, -1, **kw)


def _about_centre(lin, h: int, w: int, dt):
    """2x3 inverse map ``p_in = centre + lin @ (p_out - centre)``."""
    ctr = jnp.asarray([(h - 1) / 2.0, (w - 1) / 2.0], dtype=dt)
    lin = jnp.asarray(lin, dtype=dt)
    return jnp.concatenate([lin, (ctr - lin @ ctr)[:, None]], axis=1)


def _traced_opts(cval, cubic_a, dt):
    return jnp.asarray(cval, dt), jnp.asarray(cubic_a, dt)


def _as_float(img: Image):
    dt = float_dtype(img.data)
    return img.data.astype(dt), dt


_SAMPLING_ARGS = """      method: ``"bilinear"``, ``"bicubic"`` (Keys, parameter ``cubic_a``) or ``"nearest"``;
        default ``"{default}"``.
      mode: boundary mode (module docstring); default ``"grid-constant"``: the
        image is surrounded by ``cval``, so pixels whose source lies outside get
        ``cval`` and the outermost ring blends into it (continuous in the knobs).
        ``"constant"`` is SciPy's variant that switches to ``cval`` abruptly.
      cval: fill value outside the image for ``"grid-constant"``/``"constant"`` (default 0.0).
      cubic_a: Keys kernel parameter for ``"bicubic"`` (default -0.5; OpenCV uses -0.75)."""


def _doc(fn):
    default = fn.__kwdefaults__["method"]
    fn.__doc__ = fn.__doc__.replace("      {sampling}", _SAMPLING_ARGS.replace("{default}", default))
    return fn


# ---------------------------------------------------------------------------
# Ops
# ---------------------------------------------------------------------------


@register(family="geometry", takes=Image, gives=Image, knobs={}, differentiable=True,
          refs=["numpy.flip"])
def mirror(img: Image, /, *, axis: int | None = 1) -> Image:
    """Mirror the image: reverse the columns (``axis=1``), the rows (``axis=0``) or both (``None``).

    ``out[r, c] = img[r, W - 1 - c]`` for ``axis=1`` (left-right),
    ``img[H - 1 - r, c]`` for ``axis=0`` (upside-down); ``None`` does both, which
    is a rotation by 180 degrees about the centre. Exact (no interpolation).

    Args:
      img: input image ``(H, W)``.
      axis: static ``0`` (rows), ``1`` (columns, default), ``-2``/``-1`` (same) or
        ``None`` (both).

    Returns:
      ``Image`` ``(H, W)``; equals ``numpy.flip(x, axis)`` exactly.

    Example:
      >>> import jax.numpy as jnp, fsjax
      >>> x = fsjax.Image(jnp.arange(12.0).reshape(3, 4) / 11)
      >>> out = fsjax.ops.mirror(x, axis=1).data
      >>> round(float(out[0, 0] * 11), 6), round(float(out[2, 3] * 11), 6)
      (3.0, 8.0)
    """
    if axis is not None and (isinstance(axis, bool) or axis not in (0, 1, -1, -2)):
        raise ValueError(f"mirror: argument 'axis' must be 0, 1, -2, -1 or None; got {axis!r}")
    ax = (-2, -1) if axis is None else (-2 if axis in (0, -2) else -1)
    return Image(jnp.flip(img.data, axis=ax))


@register(family="geometry", takes=Image, gives=Image,
          knobs={"dx": LinKnob(-8.0, 8.0, unit="px"), "dy": LinKnob(-8.0, 8.0, unit="px")},
          differentiable=True, refs=[_REF_WOLBERG, _REF_KEYS])
@_doc
def translate(img: Image, /, *, dx: float = 0.0, dy: float = 0.0, method: str = "bilinear",
              mode: str = "grid-constant", cval: float = 0.0, cubic_a: float = -0.5) -> Image:
    """Shift the image content by ``(dy, dx)`` pixels with sub-pixel interpolation.

    ``out[r, c] = img(r - dy, c - dx)``: positive ``dx`` moves content right,
    positive ``dy`` moves it down. Separable: interpolated along rows, then columns.

    Args:
      img: input image ``(H, W)``.
      dx: shift along columns in pixels (knob ``a``, [-8, 8]).
      dy: shift along rows in pixels (knob ``b``, [-8, 8]).
      {sampling}

    Returns:
      ``Image`` ``(H, W)``; uncovered pixels follow ``mode`` (``cval`` by default).

    Matches ``scipy.ndimage.shift(x, (dy, dx), order=1, mode=mode, cval=cval)`` to
    1e-12 (bilinear, every mode); an integer shift equals ``numpy.roll`` on the pixels that
    stay inside. Differentiable in ``dx``, ``dy`` (bilinear: piecewise linear,
    kinks at integer shifts).

    Example:
      A linear ramp ``0.1 c`` shifted right by 0.3 px reads ``0.1 (c - 0.3)``:

      >>> import jax.numpy as jnp, fsjax
      >>> ramp = fsjax.Image(0.1 * jnp.arange(8.0) * jnp.ones((4, 1)))
      >>> out = fsjax.ops.translate(ramp, dx=0.3).data
      >>> round(float(out[2, 5]), 12), round(float(out[2, 0]), 12)
      (0.47, 0.0)
    """
    _check_sampling("translate", method, mode, cval, cubic_a)
    check_range("translate", "dx", dx)
    check_range("translate", "dy", dy)
    x, dt = _as_float(img)
    h, w = x.shape[-2:]
    pos_r = jnp.arange(h, dtype=dt) - jnp.asarray(dy, dt)
    pos_c = jnp.arange(w, dtype=dt) - jnp.asarray(dx, dt)
    return Image(_separable(x, pos_r, pos_c, *_traced_opts(cval, cubic_a, dt), method=method, mode=mode))


@register(family="geometry", takes=Image, gives=Image, knobs={"angle_deg": LinKnob(-180.0, 180.0, unit="deg")},
          differentiable=True, refs=[_REF_WOLBERG, _REF_KEYS])
@_doc
def rotate(img: Image, /, *, angle_deg: float = 0.0, method: str = "bicubic", mode: str = "grid-constant",
           cval: float = 0.0, cubic_a: float = -0.5) -> Image:
    """Rotate the image content counter-clockwise (as displayed) by ``angle_deg`` about its centre.

    With centre ``(rc, cc) = ((H - 1) / 2, (W - 1) / 2)`` and ``t = angle_deg``,
    output pixel ``(r, c)`` reads the input at
    ``r_in = rc + cos t (r - rc) + sin t (c - cc)``,
    ``c_in = cc - sin t (r - rc) + cos t (c - cc)``. The output keeps the input
    shape (corners are cut, uncovered pixels follow ``mode``).

    Args:
      img: input image ``(H, W)``.
      angle_deg: angle in degrees, counter-clockwise with rows pointing down
        (knob ``a``, [-180, 180]); +90 equals ``numpy.rot90(x, 1)`` for a square image.
      {sampling}

    Returns:
      ``Image`` ``(H, W)``; pixels whose source lies outside get ``cval`` (0.0) by default.

    With ``method="bilinear"`` matches ``scipy.ndimage.rotate(x, angle_deg,
    reshape=False, order=1)`` (``mode="constant"``) and
    ``skimage.transform.rotate(x, angle_deg, order=1)`` (``mode="grid-constant"``)
    to 1e-12. Differentiable in ``angle_deg`` (C1 with the default bicubic).

    Example:
      A quarter turn of a square image is ``numpy.rot90`` (exact up to round-off):

      >>> import jax.numpy as jnp, numpy as np, fsjax
      >>> x = np.arange(25.0).reshape(5, 5) / 24
      >>> out = fsjax.ops.rotate(fsjax.Image(jnp.asarray(x)), angle_deg=90.0).data
      >>> float(np.max(np.abs(np.asarray(out) - np.rot90(x)))) < 1e-12
      True
    """
    _check_sampling("rotate", method, mode, cval, cubic_a)
    check_range("rotate", "angle_deg", angle_deg)
    x, dt = _as_float(img)
    h, w = x.shape[-2:]
    t = jnp.asarray(angle_deg, dt) * (math.pi / 180.0)
    cs, sn = jnp.cos(t), jnp.sin(t)
    lin = jnp.stack([jnp.stack([cs, sn]), jnp.stack([-sn, cs])])
    m = _about_centre(lin, h, w, dt)
    return Image(_warp_affine(x, m, *_traced_opts(cval, cubic_a, dt), method=method, mode=mode))


@register(family="geometry", takes=Image, gives=Image, knobs={"scale": LogKnob(0.5, 4.0)},
          differentiable=True, refs=[_REF_WOLBERG, _REF_KEYS])
@_doc
def zoom(img: Image, /, *, scale: float = 1.0, method: str = "bicubic", mode: str = "grid-constant",
         cval: float = 0.0, cubic_a: float = -0.5) -> Image:
    """Magnify the image by ``scale`` about its centre, keeping the output size.

    Output pixel ``(r, c)`` reads the input at ``centre + (p - centre) / scale``
    with centre ``((H - 1) / 2, (W - 1) / 2)``: ``scale > 1`` zooms in (crops),
    ``scale < 1`` zooms out (the border follows ``mode``; no anti-aliasing).

    Args:
      img: input image ``(H, W)``.
      scale: magnification, > 0 (knob ``a``, log-mapped to [0.5, 4]).
      {sampling}

    Returns:
      ``Image`` ``(H, W)``.

    With ``method="bilinear"`` matches ``scipy.ndimage.affine_transform`` with
    ``diag(1 / scale)`` about the centre, ``order=1``, to 1e-12. Bilinear and
    bicubic zoom-in of a linear ramp are exact. Differentiable in ``scale``.

    Example:
      A ramp ``0.1 c`` on 9 columns (centre 4) zoomed 2x reads ``0.1 (4 + (c - 4) / 2)``:

      >>> import jax.numpy as jnp, fsjax
      >>> ramp = fsjax.Image(0.1 * jnp.arange(9.0) * jnp.ones((3, 1)))
      >>> out = fsjax.ops.zoom(ramp, scale=2.0).data
      >>> round(float(out[1, 0]), 12), round(float(out[1, 7]), 12)
      (0.2, 0.55)
    """
    _check_sampling("zoom", method, mode, cval, cubic_a)
    check_positive("zoom", "scale", scale)
    x, dt = _as_float(img)
    h, w = x.shape[-2:]
    s = jnp.asarray(scale, dt)
    cr, cc = (h - 1) / 2.0, (w - 1) / 2.0
    pos_r = cr + (jnp.arange(h, dtype=dt) - cr) / s
    pos_c = cc + (jnp.arange(w, dtype=dt) - cc) / s
    return Image(_separable(x, pos_r, pos_c, *_traced_opts(cval, cubic_a, dt), method=method, mode=mode))


@register(family="geometry", takes=Image, gives=Image,
          knobs={"kx": LinKnob(-1.0, 1.0), "ky": LinKnob(-1.0, 1.0)},
          differentiable=True, refs=[_REF_WOLBERG])
@_doc
def shear(img: Image, /, *, kx: float = 0.0, ky: float = 0.0, method: str = "bicubic",
          mode: str = "grid-constant", cval: float = 0.0, cubic_a: float = -0.5) -> Image:
    """Shear the image about its centre: rows slide sideways by ``kx`` px per row, columns by ``ky``.

    Output pixel ``(r, c)`` reads the input at
    ``r_in = r - ky (c - cc)``, ``c_in = c - kx (r - rc)`` with centre
    ``(rc, cc) = ((H - 1) / 2, (W - 1) / 2)``. With ``ky = 0`` this is exactly the
    horizontal shear moving row ``r`` right by ``kx (r - rc)`` pixels (likewise
    ``kx = 0`` for the vertical shear); with both nonzero it is the stated inverse map.

    Args:
      img: input image ``(H, W)``.
      kx: horizontal shear, pixels of column shift per row (knob ``a``, [-1, 1]).
      ky: vertical shear, pixels of row shift per column (knob ``b``, [-1, 1]).
      {sampling}

    Returns:
      ``Image`` ``(H, W)``.

    Equals :func:`affine_warp` with the matrix above; differentiable in ``kx``, ``ky``.

    Example:
      With ``kx = 1`` on 5 rows (centre row 2), row 4 moves right by 2 px:

      >>> import jax.numpy as jnp, numpy as np, fsjax
      >>> x = np.tile(np.arange(8.0) / 7, (5, 1))
      >>> out = np.asarray(fsjax.ops.shear(fsjax.Image(jnp.asarray(x)), kx=1.0).data)
      >>> bool(np.allclose(out[4, 2:], x[4, :-2], atol=1e-12)), bool(np.all(out[4, :2] == 0))
      (True, True)
    """
    _check_sampling("shear", method, mode, cval, cubic_a)
    check_range("shear", "kx", kx)
    check_range("shear", "ky", ky)
    x, dt = _as_float(img)
    h, w = x.shape[-2:]
    one = jnp.ones((), dt)
    lin = jnp.stack([jnp.stack([one, -jnp.asarray(ky, dt)]), jnp.stack([-jnp.asarray(kx, dt), one])])
    m = _about_centre(lin, h, w, dt)
    return Image(_warp_affine(x, m, *_traced_opts(cval, cubic_a, dt), method=method, mode=mode))


def _affine_matrix(matrix, forward: bool, dt):
    m = jnp.eye(2, 3, dtype=dt) if matrix is None else jnp.asarray(matrix, dtype=dt)
    if m.shape == (3, 3):
        if is_concrete(matrix) and not np.allclose(np.asarray(matrix, float)[2], [0.0, 0.0, 1.0]):
            raise ValueError("affine_warp: argument 'matrix' of shape (3, 3) must have last row (0, 0, 1)")
        m = m[:2]
    if m.shape != (2, 3):
        raise ValueError(f"affine_warp: argument 'matrix' must have shape (2, 3) or (3, 3), got {m.shape}")
    if matrix is not None and is_concrete(matrix):
        mn = np.asarray(matrix, dtype=float)
        if not np.all(np.isfinite(mn)):
            raise ValueError("affine_warp: argument 'matrix' must be finite")
        if forward and abs(np.linalg.det(mn[:2, :2])) <= 1e-12 * max(1.0, np.max(np.abs(mn[:2, :2])) ** 2):
            raise ValueError("affine_warp: argument 'matrix' is singular; forward=True needs an invertible map")
    if forward:
        a, b = m[:, :2], m[:, 2]
        det = a[0, 0] * a[1, 1] - a[0, 1] * a[1, 0]  # traced singular -> inf/NaN output (fails closed)
        inv = jnp.stack([jnp.stack([a[1, 1], -a[0, 1]]), jnp.stack([-a[1, 0], a[0, 0]])]) / det
        m = jnp.concatenate([inv, (-inv @ b)[:, None]], axis=1)
    return m


@register(family="geometry", takes=Image, gives=Image, knobs={}, differentiable=True,
          refs=[_REF_WOLBERG, _REF_KEYS])
@_doc
def affine_warp(img: Image, /, *, matrix: Any = None, forward: bool = False, method: str = "bilinear",
                mode: str = "grid-constant", cval: float = 0.0, cubic_a: float = -0.5) -> Image:
    """Warp the image with a 2x3 affine matrix in ``(row, col)`` coordinates.

    By default (``forward=False``) the matrix maps **output to input**:
    output pixel ``(r, c)`` reads the input at
    ``(r_in, c_in) = matrix[:, :2] @ (r, c) + matrix[:, 2]`` -- SciPy's
    ``affine_transform`` convention (``matrix=M[:, :2], offset=M[:, 2]``). With
    ``forward=True`` the matrix maps **input to output** and is inverted first
    (note: OpenCV's ``warpAffine`` matrices act on ``(x, y) = (col, row)``; swap
    rows and columns of both blocks to use one here).

    Args:
      img: input image ``(H, W)``.
      matrix: ``(2, 3)`` array (or ``(3, 3)`` with last row ``(0, 0, 1)``), may be
        traced; ``None`` (default) is the identity. Not a knob.
      forward: ``False`` (default): output -> input map; ``True``: input -> output.
      {sampling}

    Returns:
      ``Image`` of the input's shape. A traced singular matrix with
      ``forward=True`` gives a non-finite output (fails closed); a concrete one raises.

    Matches ``scipy.ndimage.affine_transform(x, M[:, :2], offset=M[:, 2], order=1,
    mode=mode, cval=cval)`` to 1e-9 for every mode listed (``"wrap"`` against
    SciPy's ``"grid-wrap"``). Differentiable in the image and the matrix.

    Example:
      The matrix ``[[1, 0, -1], [0, 1, -2]]`` reads the input one row up and two
      columns left, i.e. moves content down 1 and right 2:

      >>> import jax.numpy as jnp, numpy as np, fsjax
      >>> x = np.arange(20.0).reshape(4, 5) / 19
      >>> m = [[1.0, 0.0, -1.0], [0.0, 1.0, -2.0]]
      >>> out = np.asarray(fsjax.ops.affine_warp(fsjax.Image(jnp.asarray(x)), matrix=m).data)
      >>> round(float(out[3, 4] * 19), 9), round(float(out[0, 0]), 9)
      (12.0, 0.0)
    """
    _check_sampling("affine_warp", method, mode, cval, cubic_a)
    if not isinstance(forward, bool):
        raise TypeError(f"affine_warp: argument 'forward' must be a bool, got {type(forward).__name__}")
    x, dt = _as_float(img)
    m = _affine_matrix(matrix, forward, dt)
    return Image(_warp_affine(x, m, *_traced_opts(cval, cubic_a, dt), method=method, mode=mode))


@register(family="geometry", takes=Image, gives=Image, knobs={}, differentiable=True,
          refs=[_REF_KEYS, _REF_WOLBERG])
def resize(img: Image, /, *, shape: tuple[int, int] | None = None, factor: float = 0.5,
           method: str = "bilinear", mode: str = "nearest", cubic_a: float = -0.5,
           antialias: bool = False) -> Image:
    """Resample the image to a new static shape (half-pixel convention).

    Along an axis of ``n_in`` input and ``n_out`` output pixels, output pixel
    ``i`` reads the input at ``(i + 0.5) n_in / n_out - 0.5``: pixel *areas* are
    aligned (corners of the first and last pixels coincide), not pixel centres.
    This is the convention of ``cv2.resize`` and ``skimage.transform.resize``
    (not ``align_corners``). Separable: rows first, then columns.

    Args:
      img: input image ``(H, W)``.
      shape: static output ``(H_out, W_out)``; if ``None`` (default) it is
        ``(max(1, round(H factor)), max(1, round(W factor)))``.
      factor: static scale used when ``shape`` is ``None`` (default 0.5: half size).
      method: ``"bilinear"`` (default), ``"bicubic"`` (Keys, ``cubic_a``) or ``"nearest"``.
      mode: boundary for taps beyond the edge; default ``"nearest"`` (edge
        replication, as OpenCV and ``skimage`` ``mode="edge"``); the constant
        modes fill with 0.
      cubic_a: Keys parameter (default -0.5; ``-0.75`` reproduces OpenCV ``INTER_CUBIC``).
      antialias: when down-sampling, first blur each shrunk axis with a Gaussian
        of ``sigma = (n_in / n_out - 1) / 2`` pixels (truncated at 4 sigma,
        boundary ``mode``), as ``skimage.transform.resize(anti_aliasing=True)``.
        Default ``False`` (plain interpolation, as ``cv2.resize``).

    Returns:
      ``Image`` ``(H_out, W_out)``.

    Matches ``cv2.resize(x, (W_out, H_out), interpolation=INTER_LINEAR)`` to 1e-14
    and, with ``cubic_a=-0.75``, ``INTER_CUBIC`` to 2e-6 (OpenCV computes its cubic
    weights in float32), float64 input, up- and down-sampling; matches
    ``skimage.transform.resize(x, shape, order=1, mode="edge", anti_aliasing=antialias)``
    to 1e-12; bicubic with ``cubic_a=-0.5`` matches Pillow's ``BICUBIC`` up-sampling
    away from the border to 1e-5 (float32 input; Pillow renormalises its window at
    the edges). Differentiable in the image.

    Example:
      Doubling ``[0, 1]`` samples at input positions ``-0.25, 0.25, 0.75, 1.25``
      (edges clamp):

      >>> import jax.numpy as jnp, fsjax
      >>> x = fsjax.Image(jnp.array([[0.0, 1.0]]))
      >>> out = fsjax.ops.resize(x, shape=(1, 4)).data
      >>> [round(float(v), 6) for v in out[0]]
      [0.0, 0.25, 0.75, 1.0]
    """
    check_choice("resize", "method", method, METHODS)
    check_choice("resize", "mode", mode, MODES)
    check_range("resize", "cubic_a", cubic_a, -3.0, 0.0)
    if not isinstance(antialias, bool):
        raise TypeError(f"resize: argument 'antialias' must be a bool, got {type(antialias).__name__}")
    x, dt = _as_float(img)
    h, w = x.shape[-2:]
    if shape is None:
        if not is_concrete(factor):
            raise TypeError("resize: argument 'factor' fixes the output shape and must be static")
        check_positive("resize", "factor", factor)
        shape = (max(1, int(round(h * float(factor)))), max(1, int(round(w * float(factor)))))
    if not isinstance(shape, (tuple, list)) or len(shape) != 2:
        raise ValueError(f"resize: argument 'shape' must be a pair (H_out, W_out), got {shape!r}")
    ho = check_static_int("resize", "shape", shape[0], lo=1)
    wo = check_static_int("resize", "shape", shape[1], lo=1)
    out = _resize_core(x, jnp.asarray(cubic_a, dt), shape=(ho, wo), method=method, mode=mode,
                       antialias=antialias)
    return Image(out)


@functools.partial(jax.jit, static_argnames=("shape", "method", "mode", "antialias"))
def _resize_core(x, cubic_a, *, shape, method, mode, antialias):
    h, w = x.shape[-2:]
    dt = x.dtype
    out = x
    for axis, n_in, n_out in ((-2, h, shape[0]), (-1, w, shape[1])):
        ratio = n_in / n_out
        if antialias and ratio > 1.0:
            sigma = (ratio - 1.0) / 2.0
            mode_f = "wrap" if mode == "grid-wrap" else ("constant" if "constant" in mode else mode)
            out = correlate1d(out, gaussian_weights(sigma).astype(dt), axis=axis, mode=mode_f)
        pos = (jnp.arange(n_out, dtype=dt) + 0.5) * ratio - 0.5
        out = sample1d(out, pos, axis, method=method, mode=mode, cubic_a=cubic_a)
    return out
