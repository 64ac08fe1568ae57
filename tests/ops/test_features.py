"""Image features: conformance with NumPy / SciPy / scikit-image / OpenCV on real
photographs, analytic ground truths, nulls, undefined values and bad input."""

from __future__ import annotations

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.ndimage as ndi
import skimage
from skimage.measure import shannon_entropy
from skimage.metrics import mean_squared_error, peak_signal_noise_ratio, structural_similarity
from skimage.util import img_as_ubyte

import fsjax
from fsjax import Image
from fsjax.ops import (
    entropy,
    max_value,
    mean,
    michelson_contrast,
    min_value,
    mse,
    noise_sigma,
    percentile,
    psnr,
    rmse,
    sharpness,
    ssim,
    std,
)


def _camera():
    return skimage.data.camera()[::4, ::4].astype(np.float64) / 255.0  # 128 x 128


def _coins():
    return skimage.data.coins()[100:228, 150:278].astype(np.float64) / 255.0  # 128 x 128


def _noisy(x, sigma, seed=0):
    rng = np.random.default_rng(seed)
    return np.clip(x + sigma * rng.standard_normal(x.shape), 0.0, 1.0)


def _smooth(size=128):
    rr, cc = np.mgrid[0:size, 0:size].astype(float)
    return 0.5 + 0.2 * np.sin(2 * np.pi * rr / 64) * np.cos(2 * np.pi * cc / 48) + 0.1 * cc / (size - 1)


PHOTOS = {"camera": _camera, "coins": _coins}


# ---------------------------------------------------------------------------
# Grey statistics
# ---------------------------------------------------------------------------


@pytest.mark.parametrize("name", sorted(PHOTOS))
def test_grey_statistics_match_numpy(name):
    x = PHOTOS[name]()
    img = Image(jnp.asarray(x))
    pairs = [(mean, np.mean(x)), (std, np.std(x)), (min_value, np.min(x)), (max_value, np.max(x))]
    worst = 0.0
    for op, ref in pairs:
        f = op(img)
        assert f.unit == "grey"
        worst = max(worst, abs(float(f.value) - float(ref)))
    print(f"mean/std/min/max vs numpy on {name}: max |diff| = {worst:.2e}")
    assert worst <= 1e-12


def test_std_of_constant_is_zero_with_finite_gradient():
    img = Image(jnp.full((6, 7), 0.3))
    assert abs(float(std(img).value)) <= 1e-15  # the mean of 42 equal values rounds
    g = jax.grad(lambda d: std(Image(d)).value)(img.data)
    assert bool(jnp.all(jnp.isfinite(g)))


@pytest.mark.parametrize("name", sorted(PHOTOS))
def test_percentile_matches_numpy(name):
    x = _noisy(PHOTOS[name](), 0.01)  # break ties so interpolation matters
    img = Image(jnp.asarray(x))
    ps = [0.0, 0.5, 1.0, 12.5, 25.0, 33.3, 50.0, 66.7, 75.0, 99.0, 99.99, 100.0]
    got = np.array([float(percentile(img, p=p).value) for p in ps])
    ref = np.percentile(x, ps)
    d = float(np.max(np.abs(got - ref)))
    # the same values through a traced p (one vmap over the knob values); XLA folds
    # (p / 100) * (n - 1) into p * c, which may move the virtual index by one ulp
    f = jax.jit(jax.vmap(lambda p, d: percentile(Image(d), p=p).value, in_axes=(0, None)))
    dt = float(np.max(np.abs(np.asarray(f(jnp.asarray(ps), img.data)) - ref)))
    print(f"percentile vs np.percentile on {name}: max |diff| = {d:.2e} (concrete), {dt:.2e} (traced p)")
    assert d <= 1e-15 and dt <= 1e-12


def test_percentile_ends_are_min_and_max():
    x = _camera()
    img = Image(jnp.asarray(x))
    assert float(percentile(img, p=0.0).value) == float(x.min())
    assert float(percentile(img, p=100.0).value) == float(x.max())


# ---------------------------------------------------------------------------
# Entropy
# ---------------------------------------------------------------------------


def test_entropy_matches_skimage_on_uint8_photo():
    u8 = skimage.data.camera()[::4, ::4]
    got = float(entropy(Image.from_uint(u8)).value)
    ref = shannon_entropy(u8)
    print(f"entropy vs skimage.measure.shannon_entropy (camera uint8): {got:.6f} vs {ref:.6f} bit, "
          f"|diff| = {abs(got - ref):.2e}")
    assert abs(got - ref) <= 1e-12


@pytest.mark.parametrize("name", sorted(PHOTOS))
def test_entropy_matches_skimage_on_quantised_float(name):
    x = _noisy(PHOTOS[name](), 0.03, seed=3)  # float values, not on the 1/255 grid
    got = float(entropy(Image(jnp.asarray(x))).value)
    ref = shannon_entropy(img_as_ubyte(x))
    print(f"entropy vs shannon_entropy(img_as_ubyte(x)) on noisy {name}: |diff| = {abs(got - ref):.2e}")
    assert abs(got - ref) <= 1e-12


def test_entropy_bounds():
    assert float(entropy(Image(jnp.full((9, 9), 0.4))).value) == 0.0
    flat = Image(jnp.arange(256.0).reshape(16, 16) / 255.0)  # every level once
    assert abs(float(entropy(flat).value) - 8.0) <= 1e-12


# ---------------------------------------------------------------------------
# Sharpness
# ---------------------------------------------------------------------------


@pytest.mark.parametrize("name", sorted(PHOTOS))
def test_sharpness_matches_scipy_and_opencv(name):
    x = PHOTOS[name]()
    img = Image(jnp.asarray(x))
    got = float(sharpness(img).value)
    ref = float(ndi.laplace(x, mode="reflect").var())
    got_m = float(sharpness(img, mode="mirror").value)
    ref_cv = float(cv2.Laplacian(x, cv2.CV_64F, ksize=1, borderType=cv2.BORDER_REFLECT_101).var())
    r1, r2 = abs(got - ref) / ref, abs(got_m - ref_cv) / ref_cv
    print(f"sharpness vs scipy laplace().var() on {name}: rel diff = {r1:.2e}; "
          f"mode='mirror' vs cv2.Laplacian().var(): rel diff = {r2:.2e}")
    assert r1 <= 1e-12 and r2 <= 1e-12


def test_sharpness_ranks_focus_where_the_mean_cannot():
    """Blur stack: the focus measure picks the in-focus frame; the null (mean) is blind to blur."""
    x = _camera()
    sigmas = [0.0, 0.7, 1.4, 2.8]
    frames = [x if s == 0 else ndi.gaussian_filter(x, s, mode="reflect") for s in sigmas]
    sh = [float(sharpness(Image(jnp.asarray(f))).value) for f in frames]
    mn = [float(mean(Image(jnp.asarray(f))).value) for f in frames]
    print("sharpness over blur sigma " + ", ".join(f"{s}: {v:.3e}" for s, v in zip(sigmas, sh, strict=True)))
    print(f"null (mean) spread over the stack: {max(mn) - min(mn):.2e}")
    assert all(a > 1.5 * b for a, b in zip(sh[:-1], sh[1:], strict=True))  # strictly and clearly decreasing
    # the null cannot rank: its spread is tiny relative to its value
    assert (max(mn) - min(mn)) / np.mean(mn) < 1e-2


# ---------------------------------------------------------------------------
# Noise
# ---------------------------------------------------------------------------


def _skimage_estimate_sigma(x):
    """scikit-image's wavelet MAD estimate, printed for comparison (it needs PyWavelets,
    which the test extra does not install; the assertions do not depend on it)."""
    try:
        import pywt  # noqa: F401
    except ImportError:
        return None
    from skimage.restoration import estimate_sigma

    return float(estimate_sigma(x))


@pytest.mark.parametrize("sigma", [0.01, 0.02, 0.05])
def test_noise_sigma_recovers_known_sigma_on_smooth_image(sigma):
    clean = _smooth()
    rng = np.random.default_rng(7)
    x = clean + sigma * rng.standard_normal(clean.shape)  # unclipped: the noise is exactly Gaussian
    img = Image(jnp.asarray(x))
    est_i = float(noise_sigma(img).value)
    est_m = float(noise_sigma(img, method="mad").value)
    est_sk = _skimage_estimate_sigma(x)
    naive = float(np.std(x))  # null: the image's standard deviation
    sk = ("n/a (needs PyWavelets)" if est_sk is None
          else f"{est_sk:.5f} ({est_sk / sigma - 1:+.1%})")
    print(f"noise_sigma true {sigma}: immerkaer {est_i:.5f} ({est_i / sigma - 1:+.1%}), "
          f"mad {est_m:.5f} ({est_m / sigma - 1:+.1%}), skimage estimate_sigma {sk}, "
          f"null std(x) {naive:.5f} ({naive / sigma - 1:+.1%})")
    assert abs(est_i / sigma - 1) <= 0.10
    assert abs(est_m / sigma - 1) <= 0.10
    assert abs(est_i - sigma) < abs(naive - sigma) / 10


def test_noise_sigma_mad_is_less_biased_by_texture():
    """On a textured photo every estimator over-reads; the MAD residual over-reads less."""
    cam = _camera()
    for sigma in (0.01, 0.02, 0.05):
        rng = np.random.default_rng(11)
        img = Image(jnp.asarray(cam + sigma * rng.standard_normal(cam.shape)))
        ei = float(noise_sigma(img).value)
        em = float(noise_sigma(img, method="mad").value)
        print(f"noise_sigma on camera+N(0,{sigma}^2): immerkaer {ei / sigma:.2f}x, mad {em / sigma:.2f}x")
        assert abs(em - sigma) < abs(ei - sigma)


def test_noise_sigma_zero_on_bilinear_image():
    rr, cc = np.mgrid[0:20, 0:30].astype(float)
    img = Image(jnp.asarray(0.1 + 0.01 * rr + 0.02 * cc + 0.0005 * rr * cc))
    for method in ("immerkaer", "mad"):
        assert abs(float(noise_sigma(img, method=method).value)) <= 1e-13


# ---------------------------------------------------------------------------
# Two-image comparisons
# ---------------------------------------------------------------------------


@pytest.mark.parametrize("name", sorted(PHOTOS))
def test_mse_rmse_psnr_match_skimage(name):
    x = PHOTOS[name]()
    y = _noisy(x, 0.04)
    a, b = Image(jnp.asarray(x)), Image(jnp.asarray(y))
    d_mse = abs(float(mse(a, b).value) - mean_squared_error(x, y))
    d_rmse = abs(float(rmse(a, b).value) - np.sqrt(mean_squared_error(x, y)))
    p = float(psnr(a, b).value)
    p_ref = peak_signal_noise_ratio(x, y, data_range=1)
    print(f"{name}: mse |diff| = {d_mse:.2e}, rmse |diff| = {d_rmse:.2e}, "
          f"psnr {p:.4f} dB vs skimage {p_ref:.4f} dB, |diff| = {abs(p - p_ref):.2e} dB")
    assert d_mse <= 1e-15 and d_rmse <= 1e-15
    assert abs(p - p_ref) <= 1e-10
    # data_range scales the peak: 20 log10(2) dB more for a range of 2
    p2 = float(psnr(a, b, data_range=2.0).value)
    assert abs(p2 - p - 20 * np.log10(2.0)) <= 1e-10


def test_psnr_of_identical_images_is_inf_with_zero_gradient():
    x = jnp.asarray(_camera())
    a = Image(x)
    val = float(psnr(a, a).value)
    with np.errstate(divide="ignore"):
        ref = peak_signal_noise_ratio(np.asarray(x), np.asarray(x), data_range=1)
    print(f"psnr(x, x) = {val} (skimage: {ref})")
    assert val == np.inf and ref == np.inf
    assert float(jax.jit(psnr)(a, a).value) == np.inf
    g = jax.grad(lambda d: psnr(Image(d), a).value)(x)
    assert bool(jnp.all(g == 0))
    assert float(mse(a, a).value) == 0.0 and float(rmse(a, a).value) == 0.0
    gr = jax.grad(lambda d: rmse(Image(d), a).value)(x)
    assert bool(jnp.all(jnp.isfinite(gr)))


def test_psnr_beats_null_ranking():
    """More noise, lower PSNR (and the null, mean difference, cannot tell)."""
    x = _camera()
    a = Image(jnp.asarray(x))
    vals = [float(psnr(a, Image(jnp.asarray(_noisy(x, s, seed=5)))).value) for s in (0.01, 0.03, 0.1)]
    print(f"psnr at noise 0.01 / 0.03 / 0.1: {vals[0]:.2f} / {vals[1]:.2f} / {vals[2]:.2f} dB")
    assert vals[0] > vals[1] > vals[2]


def _sk_ssim(x, y):
    return structural_similarity(x, y, gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
                                 data_range=1)


@pytest.mark.parametrize("name", sorted(PHOTOS))
@pytest.mark.parametrize("distortion", ["noise", "blur", "shift"])
def test_ssim_matches_skimage(name, distortion):
    x = PHOTOS[name]()
    if distortion == "noise":
        y = _noisy(x, 0.05)
    elif distortion == "blur":
        y = ndi.gaussian_filter(x, 1.5)
    else:
        y = np.clip(x * 0.8 + 0.1, 0, 1)
    x, y = x[:, :117], y[:, :117]  # non-square, odd width
    got = float(ssim(Image(jnp.asarray(x)), Image(jnp.asarray(y))).value)
    ref = _sk_ssim(x, y)
    print(f"ssim vs skimage on {name} ({distortion}): {got:.8f} vs {ref:.8f}, |diff| = {abs(got - ref):.2e}")
    assert abs(got - ref) <= 1e-6


def test_ssim_other_sigma_matches_skimage():
    x = _coins()
    y = _noisy(x, 0.03)
    got = float(ssim(Image(jnp.asarray(x)), Image(jnp.asarray(y)), sigma=2.5).value)
    ref = structural_similarity(x, y, gaussian_weights=True, sigma=2.5, use_sample_covariance=False,
                                data_range=1)
    print(f"ssim sigma=2.5 vs skimage: |diff| = {abs(got - ref):.2e}")
    assert abs(got - ref) <= 1e-6


def test_ssim_float32_close_to_float64():
    x = _camera()
    y = _noisy(x, 0.05)
    g64 = float(ssim(Image(jnp.asarray(x)), Image(jnp.asarray(y))).value)
    out32 = ssim(Image(jnp.asarray(x, jnp.float32)), Image(jnp.asarray(y, jnp.float32)))
    assert out32.value.dtype == jnp.float32
    d = abs(float(out32.value) - g64)
    print(f"ssim float32 vs float64: |diff| = {d:.2e}")
    assert d <= 1e-4


def test_ssim_identity_and_ranking():
    x = _camera()
    a = Image(jnp.asarray(x))
    assert abs(float(ssim(a, a).value) - 1.0) <= 1e-12
    vals = [float(ssim(a, Image(jnp.asarray(_noisy(x, s, seed=2)))).value) for s in (0.01, 0.05, 0.2)]
    assert 1.0 > vals[0] > vals[1] > vals[2]


def test_ssim_gradient_matches_finite_difference():
    x = _coins()[:40, :40]
    y = _noisy(x, 0.05)[:40, :40]
    b = jnp.asarray(y)
    f = jax.jit(lambda d, e: ssim(Image(d), Image(e)).value)
    g = jax.jit(jax.grad(f))(jnp.asarray(x), b)
    rng = np.random.default_rng(0)
    v = jnp.asarray(rng.standard_normal(x.shape))
    h = 1e-5
    fd = (f(jnp.asarray(x) + h * v, b) - f(jnp.asarray(x) - h * v, b)) / (2 * h)
    dd = float(jnp.sum(g * v))
    print(f"ssim grad . v = {dd:.6e}, FD = {float(fd):.6e}")
    assert abs(dd) > 1e-6
    assert abs(dd - float(fd)) <= 1e-6 * max(1.0, abs(float(fd)))


# ---------------------------------------------------------------------------
# Contrast
# ---------------------------------------------------------------------------


def test_michelson_contrast_and_undefined_cases():
    x = _coins()
    got = float(michelson_contrast(Image(jnp.asarray(x))).value)
    ref = (x.max() - x.min()) / (x.max() + x.min())
    assert abs(got - ref) <= 1e-14
    assert np.isnan(float(michelson_contrast(Image(jnp.zeros((5, 5)))).value))
    signed = Image(jnp.asarray(x - 0.5))
    assert np.isnan(float(michelson_contrast(signed).value))
    assert float(michelson_contrast(Image(jnp.full((3, 3), 0.7))).value) == 0.0


# ---------------------------------------------------------------------------
# Units, jit, bad input
# ---------------------------------------------------------------------------


def test_units_are_declared():
    img = Image(jnp.asarray(_coins()))
    units = {
        "entropy": entropy(img).unit,
        "sharpness": sharpness(img).unit,
        "psnr": psnr(img, img).unit,
        "ssim": ssim(img, img).unit,
        "mse": mse(img, img).unit,
        "percentile": percentile(img).unit,
    }
    assert units == {"entropy": "bit", "sharpness": "grey^2/px^4", "psnr": "dB", "ssim": "1",
                     "mse": "grey^2", "percentile": "grey"}


def test_apply_with_knob_maps_percentile():
    x = _camera()
    img = Image(jnp.asarray(x))
    got = float(fsjax.apply(img, "percentile", a=0.9).value)
    assert abs(got - np.percentile(x, 90.0)) <= 1e-14


@pytest.mark.parametrize(
    "call, op, arg",
    [
        (lambda i: percentile(i, p=101.0), "percentile", "p"),
        (lambda i: percentile(i, p=-1.0), "percentile", "p"),
        (lambda i: sharpness(i, mode="bogus"), "sharpness", "mode"),
        (lambda i: noise_sigma(i, method="wavelet"), "noise_sigma", "method"),
        (lambda i: noise_sigma(Image(jnp.zeros((2, 9)))), "noise_sigma", "img"),
        (lambda i: psnr(i, Image(jnp.zeros((4, 4)))), "psnr", "test"),
        (lambda i: psnr(i, i, data_range=0.0), "psnr", "data_range"),
        (lambda i: mse(i, Image(jnp.zeros((4, 4)))), "mse", "test"),
        (lambda i: rmse(i, Image(jnp.zeros((4, 4)))), "rmse", "test"),
        (lambda i: ssim(i, Image(jnp.zeros((4, 4)))), "ssim", "test"),
        (lambda i: ssim(i, i, sigma=-1.0), "ssim", "sigma"),
        (lambda i: ssim(i, i, k1=-0.1), "ssim", "k1"),
        (lambda i: ssim(i, i, data_range=0.0), "ssim", "data_range"),
        (lambda i: ssim(Image(jnp.zeros((8, 30))), Image(jnp.zeros((8, 30)))), "ssim", "11 x 11"),
    ],
)
def test_bad_parameters_raise_naming_op_and_argument(call, op, arg):
    img = Image(jnp.asarray(_coins()[:20, :20]))
    with pytest.raises(ValueError) as ei:
        call(img)
    msg = str(ei.value)
    assert op in msg and arg in msg, msg


def test_ssim_traced_sigma_is_refused():
    img = Image(jnp.asarray(_coins()[:20, :20]))
    with pytest.raises(TypeError, match="ssim: argument 'sigma'"):
        jax.jit(lambda s: ssim(img, img, sigma=s).value)(1.5)


def test_wrong_sort_and_nan_are_refused():
    with pytest.raises(TypeError, match="mean: argument 'img' must be Image"):
        mean(jnp.zeros((4, 4)))
    bad = Image(np.full((12, 12), np.nan))
    with pytest.raises(ValueError, match="ssim"):
        ssim(bad, bad)
