"""Colour ops: conformance vs scikit-image on a photograph, round trips (hypothesis),
defined hue at zero saturation, decorrelation-stretch properties, bad input."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from skimage import color as skcolor
from skimage import data

import fsjax
from fsjax import HSV, Color, Image, Lab
from fsjax.ops import (
    color_channel,
    decorrelation_stretch,
    grey_to_rgb,
    hsv_to_rgb,
    hue,
    lab_to_rgb,
    rgb_to_grey,
    rgb_to_hsv,
    rgb_to_lab,
)
from fsjax.ops.image._color import WHITE_D65, XYZ_FROM_RGB, linear_to_srgb, srgb_to_linear
from fsjax.synth import standard_input


@pytest.fixture(scope="module")
def srgb():
    """A real photograph, sRGB-encoded, 128 x 128 x 3 in [0, 1]."""
    return data.astronaut()[::4, ::4].astype(np.float64) / 255.0


@pytest.fixture(scope="module")
def linear(srgb):
    return np.asarray(srgb_to_linear(srgb))


def _d(a, b):
    return float(np.max(np.abs(np.asarray(a, dtype=float) - np.asarray(b, dtype=float))))


def _hue_d(a, b):
    d = np.abs(np.asarray(a) - np.asarray(b))
    return float(np.max(np.minimum(d, 1.0 - d)))


# jitted array-level wrappers: one compilation per shape for the property tests
_rgb2hsv = jax.jit(lambda x: rgb_to_hsv(Color(x)).data)
_hsv2rgb = jax.jit(lambda x: hsv_to_rgb(HSV(x)).data)
_rgb2lab = jax.jit(lambda x: rgb_to_lab(Color(x)).data)
_lab2rgb = jax.jit(lambda x: lab_to_rgb(Lab(x)).data)


# ---------------------------------------------------------------------------
# Grey
# ---------------------------------------------------------------------------


def test_rgb_to_grey_weights_and_vs_skimage(linear):
    out = np.asarray(rgb_to_grey(Color(linear)).data)
    own = linear @ np.array([0.2126, 0.7152, 0.0722])
    d_own = _d(out, own)
    d_sk = _d(out, skcolor.rgb2gray(linear))
    print(f"rgb_to_grey vs BT.709 weights: {d_own:.2e}; vs skimage.rgb2gray (0.2125/0.7154/0.0721): {d_sk:.2e}")
    assert d_own <= 1e-15
    assert d_sk <= 2e-4  # analytic bound for inputs in [0, 1]: 1e-4 + 2e-4 + 1e-4 with signs -> 2e-4


def test_grey_to_rgb_vs_skimage_and_back(linear):
    g = linear[..., 1]
    rgb = grey_to_rgb(Image(g)).data
    assert _d(rgb, skcolor.gray2rgb(g)) == 0.0
    assert _d(rgb_to_grey(Color(rgb)).data, g) <= 1e-15


# ---------------------------------------------------------------------------
# HSV
# ---------------------------------------------------------------------------


def test_rgb_to_hsv_vs_skimage(srgb):
    out = np.asarray(rgb_to_hsv(Color(srgb)).data)
    ref = skcolor.rgb2hsv(srgb)
    dh, dsv = _hue_d(out[..., 0], ref[..., 0]), _d(out[..., 1:], ref[..., 1:])
    print(f"rgb_to_hsv vs skimage.rgb2hsv: hue (circular) {dh:.2e}, s/v {dsv:.2e}")
    assert dh <= 1e-12 and dsv <= 1e-12
    assert out[..., 0].min() >= 0.0 and out[..., 0].max() < 1.0
    assert _d(hue(HSV(jnp.asarray(out))).data, out[..., 0]) == 0.0


def test_hsv_to_rgb_vs_skimage(srgb):
    hsv = skcolor.rgb2hsv(srgb)
    d = _d(hsv_to_rgb(HSV(hsv)).data, skcolor.hsv2rgb(hsv))
    print(f"hsv_to_rgb vs skimage.hsv2rgb: max |diff| = {d:.2e}")
    assert d <= 1e-12


def test_hue_defined_at_zero_saturation_without_nan_gradients():
    rgb = jnp.array([[[0.3, 0.3, 0.3], [0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [0.2, 0.5, 0.5]]])
    hsv = np.asarray(rgb_to_hsv(Color(rgb)).data)
    assert np.array_equal(hsv[0, :3, 0], [0.0, 0.0, 0.0]) and np.array_equal(hsv[0, :3, 1], [0.0, 0.0, 0.0])
    for ch in range(3):
        g = jax.grad(lambda x, c=ch: jnp.sum(rgb_to_hsv(Color(x)).data[..., c]))(rgb)
        assert np.all(np.isfinite(np.asarray(g))), f"NaN gradient in HSV channel {ch}"
    # tiny chroma near grey: still finite values and gradients
    near = rgb.at[0, 0, 0].add(1e-300)
    assert np.all(np.isfinite(np.asarray(jax.grad(lambda x: jnp.sum(rgb_to_hsv(Color(x)).data))(near))))


def test_hue_never_one():
    # red with a blue excess far below one ulp of 1: (g - b) / delta / 6 = -tiny would wrap to 1.0
    rgb = jnp.array([[[1.0, 0.0, 1e-17]]])
    h = float(rgb_to_hsv(Color(rgb)).data[0, 0, 0])
    assert 0.0 <= h < 1.0


@settings(max_examples=40, deadline=None)
@given(arrays(np.float64, (1, 32, 3), elements=st.floats(0.0, 1.0)))
def test_rgb_hsv_rgb_round_trip(x):
    assert _d(_hsv2rgb(_rgb2hsv(jnp.asarray(x))), x) <= 1e-9


@settings(max_examples=40, deadline=None)
@given(arrays(np.float64, (1, 32), elements=st.floats(0.0, 1.0, exclude_max=True)),
       arrays(np.float64, (1, 32), elements=st.floats(1e-3, 1.0)),
       arrays(np.float64, (1, 32), elements=st.floats(1e-3, 1.0)))
def test_hsv_rgb_hsv_round_trip(h, s, v):
    hsv = np.stack([h, s, v], axis=-1)
    back = np.asarray(_rgb2hsv(_hsv2rgb(jnp.asarray(hsv))))
    assert _hue_d(back[..., 0], h) <= 1e-9
    assert _d(back[..., 1:], hsv[..., 1:]) <= 1e-9


# ---------------------------------------------------------------------------
# Lab
# ---------------------------------------------------------------------------


def test_rgb_to_lab_vs_skimage(linear, srgb):
    out = np.asarray(rgb_to_lab(Color(linear)).data)
    ref = skcolor.rgb2lab(np.asarray(linear_to_srgb(linear)))  # skimage decodes sRGB itself
    d = np.max(np.abs(out - ref), axis=(0, 1))
    print(f"rgb_to_lab vs skimage.rgb2lab(sRGB-encoded): max |dL|, |da|, |db| = {d[0]:.2e}, {d[1]:.2e}, {d[2]:.2e}")
    assert np.all(d <= 0.02)


def test_lab_to_rgb_vs_skimage(linear):
    lab = skcolor.rgb2lab(np.asarray(linear_to_srgb(linear)))
    out = np.asarray(lab_to_rgb(Lab(lab)).data)
    ref = np.asarray(srgb_to_linear(skcolor.lab2rgb(lab)))
    d = _d(out, ref)
    print(f"lab_to_rgb vs srgb_to_linear(skimage.lab2rgb): max |diff| = {d:.2e}")
    assert d <= 2e-4


def test_lab_white_and_greys_are_neutral():
    g = jnp.linspace(0.0, 1.0, 11)
    lab = np.asarray(rgb_to_lab(Color(jnp.stack([g, g, g], -1)[None])).data)[0]
    assert np.max(np.abs(lab[:, 1:])) <= 1e-12
    assert abs(lab[-1, 0] - 100.0) <= 1e-12 and lab[0, 0] == 0.0
    # Y row of the derived matrix is BT.709 luminance to 4 decimals; white Y = 1
    assert np.allclose(XYZ_FROM_RGB[1], [0.2126, 0.7152, 0.0722], atol=5e-5) and WHITE_D65[1] == pytest.approx(1.0)
    # L* is continuous across the CIE breakpoint Y = (6/29)^3
    yb = (6 / 29) ** 3
    lo, hi = (np.asarray(rgb_to_lab(Color(jnp.full((1, 1, 3), yb * (1 + s * 1e-9)))).data)[0, 0, 0]
              for s in (-1, 1))
    assert abs(hi - lo) < 1e-6


@settings(max_examples=40, deadline=None)
@given(arrays(np.float64, (1, 32, 3), elements=st.floats(0.0, 1.0)))
def test_rgb_lab_rgb_round_trip(x):
    assert _d(_lab2rgb(_rgb2lab(jnp.asarray(x))), x) <= 1e-9


@settings(max_examples=40, deadline=None)
@given(arrays(np.float64, (1, 32), elements=st.floats(0.0, 100.0)),
       arrays(np.float64, (1, 32, 2), elements=st.floats(-128.0, 127.0)))
def test_lab_rgb_lab_round_trip(L, ab):
    lab = np.concatenate([L[..., None], ab], axis=-1)  # includes out-of-gamut colours (not clipped)
    assert _d(_rgb2lab(_lab2rgb(jnp.asarray(lab))), lab) <= 1e-9


def test_lab_gradient_finite_at_black():
    x = jnp.zeros((1, 2, 3)).at[0, 1].set(0.5)
    g = jax.grad(lambda v: jnp.sum(rgb_to_lab(Color(v)).data))(x)
    assert np.all(np.isfinite(np.asarray(g)))


# ---------------------------------------------------------------------------
# Decorrelation stretch
# ---------------------------------------------------------------------------


def _decorr_numpy(x, target=None, max_gain=None, soft=True):
    """The docstring's formula in NumPy (float64): the cap and the smooth factor w, optional."""
    f = x.reshape(-1, 3)
    mu = f.mean(0)
    c = np.cov(f.T, bias=True)
    lam, v = np.linalg.eigh(c)
    lam = np.maximum(lam, 0.0)
    g = 1 / np.sqrt(lam if max_gain is None else np.maximum(lam, lam.max() / max_gain**2))
    if soft:
        eps = np.finfo(np.float64).eps
        u = lam / (eps ** (2 / 3) * np.trace(c) + (64 * eps * np.abs(f).max()) ** 2)
        g = g * u**4 / np.sqrt(u**8 + 1)
    w = v @ np.diag(g) @ v.T
    s = np.sqrt(np.diag(c)) if target is None else np.full(3, target)
    return (mu + (f - mu) @ w * s).reshape(x.shape)


def _mean_abs_offdiag_corr(x):
    r = np.corrcoef(np.asarray(x).reshape(-1, 3).T)
    return float(np.mean(np.abs(r[np.triu_indices(3, 1)])))


def test_decorrelation_stretch_properties_on_photo(linear):
    out = np.asarray(decorrelation_stretch(Color(linear)).data)
    f_in, f_out = linear.reshape(-1, 3), out.reshape(-1, 3)
    c_out = np.cov(f_out.T, bias=True)
    d_cov = _d(c_out, np.diag(np.var(f_in, axis=0)))
    d_mean = _d(f_out.mean(0), f_in.mean(0))
    d_ref = _d(out, _decorr_numpy(linear))
    r_in, r_out = _mean_abs_offdiag_corr(linear), _mean_abs_offdiag_corr(out)
    print(f"decorrelation_stretch: |cov - diag(var_in)| = {d_cov:.2e}, mean shift {d_mean:.2e}, "
          f"vs numpy eigh {d_ref:.2e}; mean |corr| {r_in:.3f} (input, the null) -> {r_out:.2e}")
    assert d_cov <= 1e-10 and d_mean <= 1e-12 and d_ref <= 1e-12
    assert r_in > 0.5 and r_out < 1e-8


def test_decorrelation_stretch_target_sigma(linear):
    out = np.asarray(decorrelation_stretch(Color(linear), target_sigma=0.2).data).reshape(-1, 3)
    assert _d(np.cov(out.T, bias=True), 0.04 * np.eye(3)) <= 1e-10
    assert _d(out, _decorr_numpy(linear, 0.2).reshape(-1, 3)) <= 1e-12


def test_decorrelation_stretch_degenerate_inputs():
    rng = np.random.default_rng(3)
    g = rng.uniform(0.2, 0.8, (12, 12))
    const = np.full((12, 12, 3), 0.4)
    assert _d(decorrelation_stretch(Color(const)).data, const) <= 1e-15  # the mean's rounding
    # rank 1 (grey): finite, perfectly correlated with the input
    grey = np.stack([g, g, g], -1)
    out = np.asarray(decorrelation_stretch(Color(grey)).data)
    assert np.all(np.isfinite(out)) and np.corrcoef(out[..., 0].ravel(), g.ravel())[0, 1] > 1 - 1e-12
    # rank 2 (B an exact combination of R, G)
    rg = rng.uniform(0.2, 0.8, (12, 12, 2))
    r2 = np.concatenate([rg, (0.5 * rg[..., :1] + 0.3 * rg[..., 1:])], axis=-1)
    o1 = np.asarray(decorrelation_stretch(Color(r2)).data)
    # noise at the rounding level (1e-9: the null axis's eigenvalue ~1e-18, below r / 1e4) is not
    # stretched, whatever the cap: the smooth factor w takes it to zero
    n9 = r2 + 1e-9 * rng.standard_normal(r2.shape)
    d9 = _d(o1, decorrelation_stretch(Color(n9)).data)
    d9_uncapped = _d(o1, decorrelation_stretch(Color(n9), max_gain=1e12).data)
    # the null method: the cap alone (the op before the fix) stretches it by max_gain
    d9_cap_only = _d(o1, _decorr_numpy(n9, max_gain=100.0, soft=False))
    # noise well above r (1e-5: eigenvalue ~1e-10, r ~ 1e-12) is a real, weak axis: the cap bounds
    # its stretch; without the cap it is stretched to full variance (the null method)
    n5 = r2 + 1e-5 * rng.standard_normal(r2.shape)
    d5 = _d(o1, decorrelation_stretch(Color(n5)).data)
    d5_uncapped = _d(o1, decorrelation_stretch(Color(n5), max_gain=1e12).data)
    print(f"decorrelation_stretch, rank-2 image + 1e-9 noise: change {d9:.2e} (cap 100), {d9_uncapped:.2e} "
          f"(cap 1e12), {d9_cap_only:.2e} (cap 100 without w); + 1e-5 noise: {d5:.2e} (cap 100) vs "
          f"{d5_uncapped:.2e} (cap 1e12)")
    assert d9 < 1e-8 and d9_uncapped < 1e-8 and d9_cap_only > 10 * d9
    assert d5 < 1e-2 and d5_uncapped > 10 * d5
    assert _d(decorrelation_stretch(Color(n5)).data, _decorr_numpy(n5, max_gain=100.0)) < 1e-10   # the formula


# ---------------------------------------------------------------------------
# Channel selection, pools
# ---------------------------------------------------------------------------


def test_color_channel_exact_and_traced(linear):
    x = Color(linear)
    for c in range(3):
        assert _d(color_channel(x, channel=c).data, linear[..., c]) == 0.0
    outs = jax.jit(jax.vmap(lambda c: color_channel(x, channel=c).data))(jnp.array([2.0, 0.0, 1.0]))
    assert _d(outs, np.moveaxis(linear[..., [2, 0, 1]], -1, 0)) == 0.0


def test_pools_for_hsv_and_lab_are_conversions_of_the_color_pool():
    for v in (0, 1):
        rgb = standard_input(Color, v)
        hsv, lab = standard_input(HSV, v), standard_input(Lab, v)
        assert isinstance(hsv, HSV) and isinstance(lab, Lab)
        assert _d(hsv.data, rgb_to_hsv(rgb).data) == 0.0 and _d(lab.data, rgb_to_lab(rgb).data) == 0.0


# ---------------------------------------------------------------------------
# Bad input
# ---------------------------------------------------------------------------


@pytest.mark.parametrize("bad", [3, -1, 1.5, float("nan")])
def test_color_channel_bad_index(bad):
    with pytest.raises(ValueError, match="color_channel: argument 'channel'"):
        color_channel(Color(jnp.zeros((2, 2, 3))), channel=bad)


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_decorrelation_stretch_gradient_on_a_constant_image(dtype):
    """Found by the chain fuzzer (GRADNAN, minimised: a constant 15 x 17 float32 colour image ->
    decorrelation_stretch -> rgb_to_lab -> lab_to_rgb): the forward pass was finite (the mean),
    the gradient NaN (eigh of the zero covariance). The output is the channel mean, so the
    gradient of its sum is exactly 1 per pixel and channel."""
    x = jnp.full((15, 17, 3), 0.4903, dtype) * jnp.asarray([1.0, 0.8, 0.6], dtype)
    out = decorrelation_stretch(Color(x), target_sigma=0.2)
    assert np.allclose(np.asarray(out.data), np.asarray(x), atol=1e-6)
    for kw in ({}, {"target_sigma": 0.2}):
        g = jax.grad(lambda v, kw=kw: jnp.sum(decorrelation_stretch(Color(v), **kw).data))(x)
        assert bool(jnp.all(jnp.isfinite(g))), kw
        assert np.allclose(np.asarray(g), 1.0, atol=1e-5), kw
    chain = jax.grad(lambda v: jnp.sum(fsjax.ops.lab_to_rgb(fsjax.ops.rgb_to_lab(
        decorrelation_stretch(Color(v), target_sigma=0.2))).data))(x)
    assert bool(jnp.all(jnp.isfinite(chain))) and bool(jnp.any(chain != 0))


def test_decorrelation_stretch_bad_parameters():
    x = Color(jnp.zeros((2, 2, 3)))
    with pytest.raises(ValueError, match="decorrelation_stretch: argument 'target_sigma'"):
        decorrelation_stretch(x, target_sigma=0.0)
    with pytest.raises(ValueError, match="decorrelation_stretch: argument 'max_gain'"):
        decorrelation_stretch(x, max_gain=1.0)


def test_wrong_sort_and_nan_rejected():
    with pytest.raises(TypeError, match="rgb_to_hsv: argument 'img' must be Color, got HSV"):
        rgb_to_hsv(HSV(jnp.zeros((2, 2, 3))))
    with pytest.raises(TypeError, match="lab_to_rgb: argument 'img' must be Lab, got Color"):
        lab_to_rgb(Color(jnp.zeros((2, 2, 3))))
    with pytest.raises(ValueError, match="rgb_to_lab.*NaN"):
        rgb_to_lab(Color(jnp.full((2, 2, 3), jnp.nan)))
    assert fsjax.get_op("hue").takes == (HSV,)
