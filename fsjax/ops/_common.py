"""Op-only helpers shared by the op families: boundary modes and padding, separable
correlation, dtype-keyed epsilons and float dtypes, kernel-extent guards. Argument
checks are not here: op modules import them from :mod:`fsjax._checks` (one message
style for ops, fits and renderers).

Boundary modes use SciPy's names (``scipy.ndimage``), so conformance tests can
pass the same string to both libraries:

======================  ==================================  ================
fsjax / SciPy mode      extension of ``a b c d``            ``jnp.pad`` mode
======================  ==================================  ================
``"reflect"`` (default)  ``d c b a | a b c d | d c b a``     ``symmetric``
``"mirror"``             ``d c b | a b c d | c b a``         ``reflect``
``"nearest"``            ``a a a | a b c d | d d d``         ``edge``
``"wrap"``               ``b c d | a b c d | a b c``         ``wrap``
``"constant"``           ``k k k | a b c d | k k k``         ``constant``
======================  ==================================  ================

Correlation is written as shift-and-add over a static number of taps: on a
CPU, XLA's convolution is ~20x slower than this for small kernels (measured;
see ``docs/benchmarks.md``). Tap weights may be traced, so a kernel whose *values*
depend on a knob (sigma) compiles once for all knob values.
"""

from __future__ import annotations

import functools
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax.custom_derivatives import SymbolicZero

from .._checks import check_static_int, is_concrete

MODES = ("reflect", "mirror", "nearest", "wrap", "constant")
UNROLL_TAPS = 129  # correlate1d unrolls kernels up to this many taps, loops over longer ones
_JNP_MODE = {"reflect": "symmetric", "mirror": "reflect", "nearest": "edge", "wrap": "wrap", "constant": "constant"}


def check_mode(op: str, mode: str, arg: str = "mode") -> str:
    """Validate a boundary mode at trace time; raise listing the supported set."""
    if mode not in _JNP_MODE:
        raise ValueError(f"{op}: argument {arg!r} must be one of {', '.join(MODES)}; got {mode!r}")
    return mode


def pad_axis(x: Any, before: int, after: int, axis: int, mode: str = "reflect", cval: float = 0.0):
    """Pad one axis of ``x`` by ``before``/``after`` samples with a SciPy boundary mode."""
    if before == 0 and after == 0:
        return x
    widths = [(0, 0)] * x.ndim
    widths[axis] = (before, after)
    jmode = _JNP_MODE[mode]
    # For pads wider than the axis, jnp.pad repeats the pattern, which matches
    # SciPy's periodic extension for these modes.
    if jmode == "constant":
        return jnp.pad(x, widths, mode="constant", constant_values=cval)
    return jnp.pad(x, widths, mode=jmode)


def pad2d(x: Any, r0: int, r1: int, mode: str = "reflect", cval: float = 0.0):
    """Pad the last two axes of ``x`` by ``r0`` rows and ``r1`` columns on each side."""
    x = pad_axis(x, r0, r0, x.ndim - 2, mode, cval)
    return pad_axis(x, r1, r1, x.ndim - 1, mode, cval)


def correlate1d(x: Any, weights: Any, axis: int, mode: str = "reflect", cval: float = 0.0, origin: int = 0):
    """Correlate ``x`` along ``axis`` with ``weights`` (static length, values may be traced).

    ``out[i] = sum_k w[k] * x[i + k - r]`` with ``r = len(w) // 2`` (SciPy's
    ``correlate1d`` with ``origin=0``), boundary by ``mode``.

    Differentiable in ``x`` and ``weights``; derivatives go through a custom JVP
    (:func:`_shift_add`), so ``grad`` of a long traced kernel compiles in a fraction of
    a second instead of transposing every shifted slice.
    """
    axis = axis % x.ndim
    w = jnp.asarray(weights)
    n = int(w.shape[0])
    r = n // 2 + origin
    xp = pad_axis(x, r, n - 1 - r, axis, mode, cval)
    length = x.shape[axis]
    dt = jnp.result_type(x, w)
    if n > UNROLL_TAPS:
        # a long kernel: a loop over the taps keeps the program size (and compile time)
        # independent of the kernel length; the unrolled form took 49 s to build for 1601 taps
        def body(k, acc):
            return acc + w[k] * jax.lax.dynamic_slice_in_dim(xp, k, length, axis=axis)

        zero = jnp.zeros(x.shape, dt)
        return jax.lax.fori_loop(0, n, body, zero)
    return _shift_add(xp.astype(dt), w.astype(dt), axis, length)


def _shift_add_plain(xp, w, axis: int, length: int):
    """``sum_k w[k] * xp[k : k + length]`` along ``axis``, unrolled over the static taps."""
    out = None
    for k in range(int(w.shape[0])):
        sl = [slice(None)] * xp.ndim
        sl[axis] = slice(k, k + length)
        term = w[k] * xp[tuple(sl)]
        out = term if out is None else out + term
    return out


def _conv_along(xp, w, axis: int):
    """The same correlation as one XLA convolution (a valid 1-D correlation along ``axis``)."""
    xm = jnp.moveaxis(xp, axis, -1)
    lead = xm.shape[:-1]
    lhs = xm.reshape((-1, 1, xm.shape[-1]))
    out = jax.lax.conv_general_dilated(lhs, w.reshape(1, 1, -1).astype(lhs.dtype), (1,), "VALID",
                                       dimension_numbers=("NCH", "OIH", "NCH"),
                                       precision=jax.lax.Precision.HIGHEST)
    return jnp.moveaxis(out.reshape(lead + (out.shape[-1],)), -1, axis)


def _pairs_plain(xp, w, axis: int, length: int):
    """``sum_{k>=1} w[r+k] * (xp[r+k : r+k+length] - xp[r-k : r-k+length])`` along ``axis``:
    the correlation with an antisymmetric kernel (``w[r-k] = -w[r+k]``, ``w[r] = 0``) summed as
    differences of mirrored samples, so that a constant signal gives exactly 0 whatever the
    summation order (eager and compiled programs agree bit for bit there)."""
    r = int(w.shape[0]) // 2
    out = None
    for k in range(1, r + 1):
        hi = [slice(None)] * xp.ndim
        lo = [slice(None)] * xp.ndim
        hi[axis] = slice(r + k, r + k + length)
        lo[axis] = slice(r - k, r - k + length)
        term = w[r + k] * (xp[tuple(hi)] - xp[tuple(lo)])
        out = term if out is None else out + term
    return out


def _make_shift_add(plain=None):
    """The unrolled shift-and-add with a JVP written as XLA convolutions.

    The unrolled form is the fastest forward pass on a CPU, but reverse-mode autodiff
    transposes each of its ``n`` shifted slices into a padded full-size array: ``grad`` of
    one 81-tap separable Gaussian took 10.7 s to compile and 365 ms to run (256 x 256,
    float64). The JVP below is the same bilinear map as convolutions, whose transposes XLA
    has as convolutions (0.2-0.3 s to compile). Zero tangents stay symbolic, so a constant
    kernel costs nothing in the derivative pass.
    """
    plain = _shift_add_plain if plain is None else plain

    @functools.partial(jax.custom_jvp, nondiff_argnums=(2, 3))
    def shift_add(xp, w, axis, length):
        return plain(xp, w, axis, length)

    def _jvp(axis, length, primals, tangents):
        xp, w = primals
        dxp, dw = tangents
        y = plain(xp, w, axis, length)
        dy = jnp.zeros_like(y)
        if not isinstance(dxp, SymbolicZero):
            dy = dy + _conv_along(dxp, w, axis)
        if not isinstance(dw, SymbolicZero):
            dy = dy + _conv_along(xp, dw, axis)
        return y, dy

    shift_add.defjvp(_jvp, symbolic_zeros=True)

    return shift_add


_shift_add = _make_shift_add()
_shift_add_pairs = _make_shift_add(_pairs_plain)


def correlate1d_antisymmetric(x: Any, weights: Any, axis: int, mode: str = "reflect", cval: float = 0.0):
    """:func:`correlate1d` for an antisymmetric odd-length kernel (``w[r-k] = -w[r+k]``,
    ``w[r] = 0``, e.g. a first-derivative kernel), summed as differences of mirrored samples.

    Equal to :func:`correlate1d` up to round-off, and **exactly 0 on a constant signal**
    (eager and compiled alike): a plain weighted sum cancels its positive and negative taps
    only to round-off, in an order that differs between programs, so a derivative of a flat
    image was noise of a few ulps whose pattern changed under ``jit`` (found by the chain
    fuzzer: ``gauss_deriv -> equalize_hist`` on a constant image). The caller guarantees the
    antisymmetry; kernels longer than ``UNROLL_TAPS`` fall back to :func:`correlate1d`.
    """
    axis = axis % x.ndim
    w = jnp.asarray(weights)
    n = int(w.shape[0])
    if n > UNROLL_TAPS or n < 3:
        return correlate1d(x, w, axis, mode, cval)
    r = n // 2
    xp = pad_axis(x, r, r, axis, mode, cval)
    dt = jnp.result_type(x, w)
    return _shift_add_pairs(xp.astype(dt), w.astype(dt), axis, x.shape[axis])


def window_stack(x: Any, r0: int, r1: int, mode: str = "reflect", cval: float = 0.0, mask: Any = None):
    """Stack the ``(2 r0 + 1) x (2 r1 + 1)`` neighbourhood of every pixel on a new last axis.

    ``mask`` (static bool array of the window shape) keeps only selected offsets
    (e.g. a disk). Returns shape ``(*x.shape, n_offsets)``; offsets are ordered
    row-major.
    """
    h, w = x.shape[-2:]
    xp = pad2d(x, r0, r1, mode, cval)
    taps = []
    for i in range(2 * r0 + 1):
        for j in range(2 * r1 + 1):
            if mask is not None and not bool(np.asarray(mask)[i, j]):
                continue
            taps.append(xp[..., i:i + h, j:j + w])
    return jnp.stack(taps, axis=-1)


def eps(dtype: Any) -> float:
    """Machine epsilon of a float dtype (one helper for dtype-keyed tolerances)."""
    return float(jnp.finfo(dtype).eps)


def support_exceeded(sigma: Any, truncate: float, radius: int) -> Any:
    """Traced bool: a *traced* ``sigma`` whose kernel radius ``int(truncate * sigma + 0.5)``
    exceeds the static support ``radius`` (or is NaN); ``None`` for a concrete ``sigma``
    (whose support is then exact). Ops poison their output with it
    (:func:`fsjax.registry.poison`) rather than silently truncate the kernel."""
    if is_concrete(sigma):
        return None
    s = jnp.asarray(sigma)
    return ~(jnp.floor(truncate * s + 0.5) <= radius)


def check_kernel_extent(op: str, name: str, radius: int, shape: tuple[int, ...]) -> None:
    """Bound the cost that grows with one parameter: a kernel radius (px) set by ``name`` may be
    at most the image's larger side (beyond it the kernel only folds the image onto itself
    again, at O(radius) work per pixel)."""
    side = max(int(s) for s in shape[-2:])
    if radius > side:
        raise ValueError(f"{op}: argument {name!r} gives a kernel radius of {radius} px, larger than the image "
                         f"({'x'.join(map(str, shape[-2:]))}); the bound is radius <= {side} px "
                         f"(for wider smoothing use gaussian, which folds any width exactly)")


def float_dtype(x: Any):
    """Result float dtype for array ``x`` (keeps float32/float64)."""
    dt = jnp.result_type(x)
    return dt if jnp.issubdtype(dt, jnp.floating) else jnp.result_type(float)


def check_grid(op: str, shape: Any, spacing: Any, origin: Any) -> tuple[tuple[int, int, int], tuple[float, float, float],
                                                                     tuple[float, float, float]]:
    """Check a voxel grid's ``shape (D, H, W)``, ``spacing (dz, dy, dx)`` and ``origin (x0, y0, z0)``.

    Returns them as static ints / floats; raises naming ``op`` and the argument.
    """
    if not isinstance(shape, (tuple, list)) or len(shape) != 3:
        raise ValueError(f"{op}: argument 'shape' must be (D, H, W); got {shape!r}")
    shp = tuple(check_static_int(op, "shape", s, lo=1) for s in shape)
    out = []
    for name, val, positive in (("spacing", spacing, True), ("origin", origin, False)):
        try:
            vals = tuple(float(x) for x in val)
        except (TypeError, ValueError):
            raise TypeError(f"{op}: argument '{name}' must be three numbers; got {val!r}") from None
        if len(vals) != 3 or not all(x == x and abs(x) != float("inf") for x in vals) or \
                (positive and not all(x > 0 for x in vals)):
            raise ValueError(f"{op}: argument '{name}' must be three finite{' positive' if positive else ''} "
                             f"numbers; got {val!r}")
        out.append(vals)
    return shp, out[0], out[1]


def check_one(op: str, arg: str, value: Any, sort: type, field: str, ndim: int = 2) -> None:
    """Refuse anything but one instance of ``sort`` (its ``field`` has ``ndim`` axes): ops that are
    called directly take one mesh or cloud, and a batch goes through ``jax.vmap``."""
    if not isinstance(value, sort):
        article = "a " if sort.__name__[0] not in "AEIOU" else "an "
        raise TypeError(f"{op}: argument {arg!r} must be {article}{sort.__name__}; got {type(value).__name__}")
    arr = getattr(value, field)
    if arr.ndim != ndim:
        raise ValueError(f"{op}: argument {arg!r} must be one {sort.__name__} (batch with jax.vmap); got "
                         f"{field} of shape {arr.shape}")
