"""Point ops: conformance vs NumPy / scikit-image on photographs, analytic truths,
degenerate inputs, inverses, gradients at singular points, bad parameters."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from skimage import data, exposure, util

import fsjax
from fsjax import Image
from fsjax.ops import (
    abs_diff,
    add_images,
    clip,
    equalize_hist,
    exp_transform,
    gain_offset,
    gamma,
    invert,
    log_transform,
    normalize,
    sub_images,
)


@pytest.fixture(scope="module")
def camera():
    return data.camera()[::4, ::4].astype(np.float64) / 255.0  # 128 x 128, real photo


@pytest.fixture(scope="module")
def coins():
    return data.coins()[100:228, 100:228].astype(np.float64) / 255.0


def _d(a, b):
    return float(np.max(np.abs(np.asarray(a, dtype=float) - np.asarray(b, dtype=float))))


# ---------------------------------------------------------------------------
# Conformance on photographs
# ---------------------------------------------------------------------------


def test_invert_vs_skimage(camera):
    d = _d(invert(Image(camera)).data, util.invert(camera))
    print(f"invert vs skimage.util.invert: max |diff| = {d:.2e}")
    assert d <= 1e-15


def test_gain_offset_vs_numpy(camera):
    d = _d(gain_offset(Image(camera), gain=1.7, offset=-0.2).data, camera * 1.7 - 0.2)
    print(f"gain_offset vs numpy: max |diff| = {d:.2e}")
    assert d <= 1e-15


@pytest.mark.parametrize("g", [0.3, 1.0, 2.2, 4.5])
def test_gamma_vs_skimage(camera, g):
    d = _d(gamma(Image(camera), gamma=g).data, exposure.adjust_gamma(camera, g))
    print(f"gamma({g}) vs skimage.exposure.adjust_gamma: max |diff| = {d:.2e}")
    assert d <= 1e-12


def test_clip_vs_numpy(camera):
    d = _d(clip(Image(camera), lo=0.2, hi=0.7).data, np.clip(camera, 0.2, 0.7))
    print(f"clip vs numpy.clip: max |diff| = {d:.2e}")
    assert d == 0.0


def test_normalize_vs_skimage(coins):
    x = 0.3 + 0.4 * coins  # range strictly inside [0, 1]
    ref = exposure.rescale_intensity(x, out_range=(0.0, 1.0))
    out = np.asarray(normalize(Image(x)).data)
    d = _d(out, ref)
    print(f"normalize vs skimage.exposure.rescale_intensity: max |diff| = {d:.2e}")
    assert d <= 1e-15
    assert out.min() == 0.0 and out.max() == 1.0


@pytest.mark.parametrize("c", [0.1, 10.0, 100.0])
def test_log_exp_vs_numpy(camera, c):
    d1 = _d(log_transform(Image(camera), c=c).data, np.log1p(c * camera) / np.log1p(c))
    d2 = _d(exp_transform(Image(camera), c=c).data, np.expm1(camera * np.log1p(c)) / c)
    print(f"log_transform/exp_transform (c={c}) vs numpy: max |diff| = {d1:.2e} / {d2:.2e}")
    assert d1 <= 1e-15 and d2 <= 1e-15


def test_two_input_ops_vs_numpy(camera, coins):
    a, b = Image(camera), Image(coins)
    d1 = _d(abs_diff(a, b).data, np.abs(camera - coins))
    d2 = _d(add_images(a, b, scale=0.7, offset=0.1).data, (camera + coins) * 0.7 + 0.1)
    d3 = _d(sub_images(a, b, scale=1.5, offset=0.2).data, (camera - coins) * 1.5 + 0.2)
    print(f"abs_diff / add_images / sub_images vs numpy: max |diff| = {d1:.2e} / {d2:.2e} / {d3:.2e}")
    assert max(d1, d2, d3) <= 1e-15
    # HALCON defaults: add_image Mult=0.5 Add=0 (the mean), sub_image Mult=1 Add=128 (-> 0.5)
    assert _d(add_images(a, b).data, 0.5 * (camera + coins)) <= 1e-15
    assert _d(sub_images(a, a).data, np.full_like(camera, 0.5)) == 0.0


@pytest.mark.parametrize("nbins", [256, 64, 7])
def test_equalize_hist_vs_skimage(camera, coins, nbins):
    for name, x in (("camera", camera), ("coins", coins)):
        d = _d(equalize_hist(Image(x), nbins=nbins).data, exposure.equalize_hist(x, nbins=nbins))
        print(f"equalize_hist({name}, nbins={nbins}) vs skimage: max |diff| = {d:.2e}")
        assert d <= 1e-12


def test_equalize_hist_float32_vs_skimage(camera):
    x = camera.astype(np.float32)
    out = equalize_hist(Image(jnp.asarray(x)))
    assert out.data.dtype == jnp.float32
    d = _d(out.data, exposure.equalize_hist(x))
    print(f"equalize_hist float32 vs skimage: max |diff| = {d:.2e}")
    assert d <= 1e-6


def _ks_to_uniform(v):
    """Kolmogorov-Smirnov distance of the values' empirical CDF from uniform on [0, 1]."""
    s = np.sort(np.asarray(v).ravel())
    n = s.size
    k = np.arange(1, n + 1)
    return float(max(np.max(k / n - s), np.max(s - (k - 1) / n)))


def test_equalize_hist_beats_identity_and_stretch(coins):
    # null: the image as it is, and its min-max stretch; equalisation must be closer to uniform
    x = 0.2 + 0.5 * coins ** 2  # skewed, low-contrast histogram
    ks_id = _ks_to_uniform(x)
    ks_norm = _ks_to_uniform(normalize(Image(x)).data)
    ks_eq = _ks_to_uniform(equalize_hist(Image(x)).data)
    print(f"KS distance to uniform: identity {ks_id:.3f}, normalize {ks_norm:.3f}, equalize_hist {ks_eq:.3f}")
    assert ks_eq < 0.5 * ks_norm and ks_eq < 0.5 * ks_id


def test_equalize_hist_constant_image_is_half():
    out = equalize_hist(Image(jnp.full((6, 5), 0.3)))
    ref = exposure.equalize_hist(np.full((6, 5), 0.3))
    assert np.all(np.asarray(out.data) == 0.5) and np.allclose(ref, 0.5)


# ---------------------------------------------------------------------------
# Analytic truths, inverses, degenerate inputs
# ---------------------------------------------------------------------------


def test_gamma_inverse_and_odd_extension():
    x = jnp.linspace(-1.0, 1.0, 41).reshape(1, -1)
    y = gamma(gamma(Image(x), gamma=2.7), gamma=1 / 2.7).data
    assert _d(y, x) <= 1e-14
    g = gamma(Image(x), gamma=0.5).data
    assert _d(gamma(Image(-x), gamma=0.5).data, -g) == 0.0  # odd
    assert float(gamma(Image(jnp.zeros((1, 1))), gamma=0.5).data[0, 0]) == 0.0


def test_gamma_safe_at_zero_gradient():
    # true slope of x**0.5 at 0 is infinite; the op reports a finite 0, never NaN
    def f(v):
        return jnp.sum(gamma(Image(v), gamma=0.5).data)

    x = jnp.array([[0.0, 0.25]])
    gx = np.asarray(jax.grad(f)(x))
    assert np.all(np.isfinite(gx))
    assert gx[0, 0] == 0.0 and abs(gx[0, 1] - 0.5 / math.sqrt(0.25)) < 1e-12
    # gamma = 1 is the identity: slope 1 at 0 as everywhere
    g1 = np.asarray(jax.grad(lambda v: jnp.sum(gamma(Image(v), gamma=1.0).data))(x))
    assert np.array_equal(g1, [[1.0, 1.0]])
    # and w.r.t. gamma at x = 0
    gg = jax.grad(lambda p: jnp.sum(gamma(Image(x), gamma=p).data))(0.7)
    assert np.isfinite(float(gg))


def test_log_exp_are_inverse_on_signed_input():
    x = jnp.linspace(-1.0, 1.0, 81).reshape(3, 27)
    for c in (0.1, 3.0, 100.0):
        y = exp_transform(log_transform(Image(x), c=c), c=c).data
        z = log_transform(exp_transform(Image(x), c=c), c=c).data
        assert _d(y, x) <= 1e-14 and _d(z, x) <= 1e-14
    # small c tends to the identity
    assert _d(log_transform(Image(x), c=1e-8).data, x) <= 1e-8


def test_log_exp_slope_continuous_at_zero():
    c = 10.0
    x = jnp.array([[0.0, 1e-9, -1e-9]])
    g = jax.grad(lambda v: jnp.sum(log_transform(Image(v), c=c).data))(x)
    assert np.allclose(np.asarray(g), c / math.log1p(c), rtol=1e-7)
    g = jax.grad(lambda v: jnp.sum(exp_transform(Image(v), c=c).data))(x)
    assert np.allclose(np.asarray(g), math.log1p(c) / c, rtol=1e-7)


def test_normalize_constant_image_zeros_without_nan():
    x = jnp.full((4, 5), 0.42)
    out = normalize(Image(x)).data
    assert np.all(np.asarray(out) == 0.0)
    g = jax.grad(lambda v: jnp.sum(normalize(Image(v)).data ** 2))(x)
    assert np.all(np.isfinite(np.asarray(g)))


def test_clip_gradient_counts_clipped_pixels():
    x = jnp.array([[0.1, 0.3, 0.5, 0.9, 0.05]])
    g_lo = jax.grad(lambda lo: jnp.sum(clip(Image(x), lo=lo, hi=0.8).data))(0.2)
    g_hi = jax.grad(lambda hi: jnp.sum(clip(Image(x), lo=0.2, hi=hi).data))(0.8)
    g_x = jax.grad(lambda v: jnp.sum(clip(Image(v), lo=0.2, hi=0.8).data))(x)
    assert float(g_lo) == 2.0 and float(g_hi) == 1.0
    assert np.array_equal(np.asarray(g_x), [[0.0, 1.0, 1.0, 0.0, 0.0]])


def test_dtype_preserved_float32():
    x = Image(jnp.asarray(np.linspace(0, 1, 12).reshape(3, 4), dtype=jnp.float32))
    outs = [invert(x), gain_offset(x, gain=2.0), gamma(x, gamma=2.0), clip(x, lo=0.1), normalize(x),
            log_transform(x), exp_transform(x), abs_diff(x, x), add_images(x, x), sub_images(x, x)]
    assert all(o.data.dtype == jnp.float32 for o in outs)


def test_knobs_map_to_documented_ranges():
    x = Image(jnp.full((2, 2), 0.5))
    assert _d(fsjax.apply(x, "gain_offset", a=1.0, b=0.0).data, 0.5 * 4.0 - 0.5) <= 1e-15
    assert _d(fsjax.apply(x, "gamma", a=0.0).data, 0.5 ** 0.2) <= 1e-12
    assert _d(fsjax.apply((x, x), "sub_images", a=0.0, b=1.0).data, 0.0) == 0.0


# ---------------------------------------------------------------------------
# Bad input
# ---------------------------------------------------------------------------


@pytest.mark.parametrize(
    "call, op, arg",
    [
        (lambda x: gain_offset(x, gain=0.0), "gain_offset", "gain"),
        (lambda x: gain_offset(x, offset=float("nan")), "gain_offset", "offset"),
        (lambda x: gamma(x, gamma=-1.0), "gamma", "gamma"),
        (lambda x: clip(x, lo=0.8, hi=0.2), "clip", "lo"),
        (lambda x: log_transform(x, c=0.0), "log_transform", "c"),
        (lambda x: exp_transform(x, c=-2.0), "exp_transform", "c"),
        (lambda x: add_images(x, x, scale=0.0), "add_images", "scale"),
        (lambda x: sub_images(x, x, scale=-1.0), "sub_images", "scale"),
        (lambda x: equalize_hist(x, nbins=1), "equalize_hist", "nbins"),
    ],
)
def test_bad_parameters_raise_naming_op_and_arg(call, op, arg):
    x = Image(jnp.full((3, 3), 0.5))
    with pytest.raises(ValueError) as e:
        call(x)
    assert op in str(e.value) and f"'{arg}'" in str(e.value)


def test_equalize_hist_nbins_must_be_static_int():
    x = Image(jnp.full((3, 3), 0.5))
    with pytest.raises(TypeError, match="equalize_hist.*nbins"):
        equalize_hist(x, nbins=12.5)


def test_two_input_shape_mismatch_raises():
    a, b = Image(jnp.zeros((3, 3))), Image(jnp.zeros((3, 4)))
    for op in (abs_diff, add_images, sub_images):
        with pytest.raises(ValueError, match=f"{op.__name__}: inputs must have the same shape"):
            op(a, b)


def test_nan_input_and_wrong_sort_rejected():
    with pytest.raises(ValueError, match="normalize.*NaN"):
        normalize(Image(jnp.array([[0.1, jnp.nan]])))
    with pytest.raises(TypeError, match="invert.*must be Image"):
        invert(fsjax.Color(jnp.zeros((2, 2, 3))))


# The eleventh fuzz run (issue 19): `Region[scene f32] -> distance_transform -> sub_images#1` and
# `... -> distance_transform -> add_images#1` (the distance map of a Region is float64 with x64 on,
# the other operand a float32 pool image) returned float32: the ops cast to the first image's dtype
# and dropped the float64 operand's precision (CONTRACT "dtype not kept"). They promote both now.
@pytest.mark.parametrize("name,sign", [("add_images", 1.0), ("sub_images", -1.0)])
def test_two_image_ops_keep_the_promoted_dtype(name, sign):
    op = getattr(fsjax.ops, name)
    a32 = fsjax.Image(jnp.full((3, 4), 0.25, jnp.float32))
    b64 = fsjax.Image(jnp.full((3, 4), 0.1 + 1e-12, jnp.float64))   # 1e-12 is lost in float32
    for x, y in ((a32, b64), (b64, a32)):
        out = op(x, y, offset=0.0, scale=1.0)
        assert out.data.dtype == jnp.float64, (name, out.data.dtype)
        want = np.asarray(x.data, np.float64) + sign * np.asarray(y.data, np.float64)
        np.testing.assert_allclose(np.asarray(out.data), want, rtol=0, atol=1e-15)
    # the null: the old cast to the first image's dtype loses the float64 operand's 1e-12
    old = np.asarray(((a32.data + sign * b64.data) * 1.0).astype(a32.data.dtype), np.float64)
    assert np.abs(old - (0.25 + sign * (0.1 + 1e-12))).max() > 1e-12
