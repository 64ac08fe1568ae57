"""Frequency family: spectra and Fourier-domain filters.

References: numpy.fft (spectra), skimage.filters.butterworth (Butterworth),
scipy.ndimage.fourier_gaussian (Gaussian); analytic gains on pure sinusoids.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.ndimage as ndi
import skimage.data
import skimage.filters

import fsjax
from fsjax import Image
from fsjax.ops import (
    butterworth_bandpass,
    butterworth_highpass,
    butterworth_lowpass,
    fft_magnitude,
    fft_phase,
    gaussian_bandpass,
    gaussian_highpass,
    gaussian_lowpass,
    ideal_bandpass,
    ideal_highpass,
    ideal_lowpass,
)

LOW = {"ideal": ideal_lowpass, "butterworth": butterworth_lowpass, "gaussian": gaussian_lowpass}
HIGH = {"ideal": ideal_highpass, "butterworth": butterworth_highpass, "gaussian": gaussian_highpass}
BAND = {"ideal": ideal_bandpass, "butterworth": butterworth_bandpass, "gaussian": gaussian_bandpass}


@pytest.fixture(scope="module")
def camera():
    # 128 x 96 crop (non-square, even x even) of the camera photograph, in [0, 1].
    return skimage.data.camera()[100:228, 200:296].astype(np.float64) / 255.0


@pytest.fixture(scope="module")
def coins_odd():
    # odd x odd crop: exercises the rfft half-grid without a Nyquist bin.
    return skimage.data.coins()[50:149, 100:177].astype(np.float64) / 255.0


def _gain(profile, f, fc, order=2.0):
    if profile == "ideal":
        return 1.0 if f <= fc else 0.0
    if profile == "butterworth":
        return 1.0 / (1.0 + (f / fc) ** (2 * order))
    return float(np.exp(-(f**2) / (2 * fc**2)))


def _sinusoid(h, w, ky, kx, amp=0.3, phase=0.4):
    r, c = np.mgrid[0:h, 0:w]
    return 0.5 + amp * np.cos(2 * np.pi * (ky * r / h + kx * c / w) + phase)


# ---------------------------------------------------------------------------
# spectra
# ---------------------------------------------------------------------------


def test_fft_magnitude_vs_numpy(camera, coins_odd):
    for x in (camera, coins_odd):
        h, w = x.shape
        ref = np.fft.fftshift(np.abs(np.fft.fft2(x))) / (h * w)
        lin = np.asarray(fft_magnitude(Image(x), scale="linear").data)
        d = np.max(np.abs(lin - ref))
        print(f"fft_magnitude(linear) vs numpy fft {x.shape}: max |diff| = {d:.2e}")
        assert d < 1e-15
        g = 500.0
        lg = np.asarray(fft_magnitude(Image(x), scale="log", gain=g).data)
        dl = np.max(np.abs(lg - np.log1p(g * ref) / np.log1p(g)))
        print(f"fft_magnitude(log, gain={g}) vs numpy: max |diff| = {dl:.2e}")
        assert dl < 1e-14
        assert lin[h // 2, w // 2] == pytest.approx(x.mean(), abs=1e-15)  # DC = mean
        assert lg.min() >= 0 and lg.max() <= 1


def test_fft_magnitude_peak_location():
    h, w, ky, kx = 24, 32, 3, -5
    x = _sinusoid(h, w, ky, kx, amp=0.2)
    m = np.asarray(fft_magnitude(Image(x), scale="linear").data)
    peaks = {(h // 2 + ky, w // 2 + kx), (h // 2 - ky, w // 2 - kx)}
    for p in peaks:
        assert m[p] == pytest.approx(0.1, abs=1e-14)
    rest = m.copy()
    for p in peaks | {(h // 2, w // 2)}:
        rest[p] = 0
    print(f"fft_magnitude sinusoid: peaks {m[list(peaks)[0]]:.15f}, max off-peak {rest.max():.2e}")
    assert rest.max() < 1e-15


def test_fft_phase_vs_numpy(camera):
    h, w = camera.shape
    spec = np.fft.fftshift(np.fft.fft2(camera))
    ref = np.angle(spec)
    got = np.asarray(fft_phase(Image(camera)).data)
    keep = np.abs(spec) / (h * w) > 1e-10
    d = np.max(np.abs(np.angle(np.exp(1j * (got[keep] - ref[keep])))))
    print(f"fft_phase vs numpy angle ({keep.sum()} of {keep.size} bins above 1e-10): max |diff| = {d:.2e} rad")
    assert d < 1e-12
    assert got.min() > -np.pi and got.max() <= np.pi


def test_fft_phase_floor_zeroes_noise():
    x = _sinusoid(16, 16, 0, 3, amp=0.25, phase=-1.1)
    ph = np.asarray(fft_phase(Image(x)).data)
    assert ph[8, 11] == pytest.approx(-1.1, abs=1e-12)
    assert ph[8, 5] == pytest.approx(1.1, abs=1e-12)
    other = ph.copy()
    other[8, 11] = other[8, 5] = 0
    assert np.all(other == 0)
    # with floor = 0, rounding-level bins get random phases (the null the floor fixes)
    raw = np.asarray(fft_phase(Image(x), floor=0.0).data)
    n_noise = int(np.sum(raw != 0)) - 2
    print(f"fft_phase: {n_noise} round-off bins have a nonzero phase without the floor, 0 with it")
    assert n_noise > 0


# ---------------------------------------------------------------------------
# analytic ground truth on sinusoids
# ---------------------------------------------------------------------------


@pytest.mark.parametrize("profile", ["ideal", "butterworth", "gaussian"])
def test_sinusoid_gain(profile):
    h, w, ky, kx = 32, 48, 4, 6  # f = sqrt((4/32)^2 + (6/48)^2) = 0.1768 cycles/px
    f = float(np.hypot(ky / h, kx / w))
    x = _sinusoid(h, w, ky, kx)
    ac = x - 0.5
    worst = 0.0
    for fc in (0.3, 0.25, 0.12, 0.08):
        kw = {"order": 3.0} if profile == "butterworth" else {}
        g = _gain(profile, f, fc, 3.0)
        lp = np.asarray(LOW[profile](Image(x), cutoff=fc, **kw).data)
        hp = np.asarray(HIGH[profile](Image(x), cutoff=fc, **kw).data)
        e_lp = np.max(np.abs(lp - (0.5 + g * ac)))
        e_hp = np.max(np.abs(hp - (1 - g) * ac))
        worst = max(worst, e_lp, e_hp)
        if fc < f and profile == "ideal":
            assert np.max(np.abs(lp - 0.5)) < 1e-13  # removed
    print(f"{profile}: sinusoid at f={f:.4f}, lp/hp gain vs analytic, max |diff| = {worst:.2e}")
    assert worst < 1e-13
    if profile != "ideal":
        # cutoff well above f: passes nearly intact; well below: nearly removed
        kw = {"order": 3.0} if profile == "butterworth" else {}
        lp_hi = np.asarray(LOW[profile](Image(x), cutoff=0.45, **kw).data)
        lp_lo = np.asarray(LOW[profile](Image(x), cutoff=0.04, **kw).data)
        assert np.max(np.abs(lp_hi - x)) < 0.1 * 0.3
        assert np.max(np.abs(lp_lo - 0.5)) < 1e-3 * 0.3


@pytest.mark.parametrize("profile", ["ideal", "butterworth", "gaussian"])
def test_bandpass_gain(profile):
    h, w = 32, 64
    centre, octv = 0.1, 2.0
    f_lo, f_hi = centre / 2, centre * 2
    worst = 0.0
    for k in (2, 6, 9, 20):
        x = _sinusoid(h, w, 0, k)
        f = k / w
        g = _gain(profile, f, f_hi) * (1 - _gain(profile, f, f_lo))
        out = np.asarray(BAND[profile](Image(x), centre=centre, octaves=octv).data)
        worst = max(worst, np.max(np.abs(out - g * (x - 0.5))))
    print(f"{profile}_bandpass sinusoid gains vs analytic: max |diff| = {worst:.2e}")
    assert worst < 1e-13


# ---------------------------------------------------------------------------
# identities
# ---------------------------------------------------------------------------


@pytest.mark.parametrize("profile", ["ideal", "butterworth", "gaussian"])
def test_highpass_of_constant_is_zero(profile):
    for shape in ((24, 32), (25, 31)):
        x = Image(jnp.full(shape, 0.37))
        hp = np.asarray(HIGH[profile](x, cutoff=0.05).data)
        bp = np.asarray(BAND[profile](x, centre=0.1).data)
        lp = np.asarray(LOW[profile](x, cutoff=0.05).data)
        m = max(np.max(np.abs(hp)), np.max(np.abs(bp)))
        print(f"{profile} {shape}: max |high-pass(constant)| = {m:.1e}, max |low-pass - c| = "
              f"{np.max(np.abs(lp - 0.37)):.1e}")
        assert m < 1e-15
        assert np.max(np.abs(lp - 0.37)) < 1e-15


@pytest.mark.parametrize("profile", ["ideal", "butterworth", "gaussian"])
def test_lowpass_plus_highpass_is_identity(profile, camera, coins_odd):
    worst = 0.0
    for x in (camera, coins_odd):
        for fc in (0.03, 0.11, 0.37):
            lp = LOW[profile](Image(x), cutoff=fc).data
            hp = HIGH[profile](Image(x), cutoff=fc).data
            d = float(jnp.max(jnp.abs(lp + hp - x)))
            worst = max(worst, d)
            assert d < 1e-14, (profile, x.shape, fc, d)
            assert abs(float(jnp.mean(hp))) < 1e-15  # DC removed
            assert abs(float(jnp.mean(lp)) - x.mean()) < 1e-15  # DC kept
    print(f"{profile}: lowpass + highpass vs input (2 crops x 3 cutoffs): max |diff| = {worst:.2e}")


def test_bandpass_is_cascade(camera):
    centre, octv = 0.08, 1.5
    f_lo, f_hi = centre * 2 ** (-octv / 2), centre * 2 ** (octv / 2)
    for profile in ("butterworth", "gaussian", "ideal"):
        kw = {"order": 2.5} if profile == "butterworth" else {}
        bp = BAND[profile](Image(camera), centre=centre, octaves=octv, **kw).data
        casc = HIGH[profile](LOW[profile](Image(camera), cutoff=f_hi, **kw), cutoff=f_lo, **kw).data
        d = float(jnp.max(jnp.abs(bp - casc)))
        print(f"{profile}_bandpass vs highpass(lowpass) cascade: max |diff| = {d:.2e}")
        assert d < 1e-14


# ---------------------------------------------------------------------------
# conformance with scikit-image and SciPy
# ---------------------------------------------------------------------------


def test_butterworth_vs_skimage(camera, coins_odd):
    worst = 0.0
    for x in (camera, coins_odd):
        for fc, n in ((0.05, 1.0), (0.15, 2.0), (0.3, 4.5)):
            for hp in (False, True):
                ref = skimage.filters.butterworth(x, cutoff_frequency_ratio=fc, high_pass=hp, order=n,
                                                  squared_butterworth=True)
                op = butterworth_highpass if hp else butterworth_lowpass
                got = np.asarray(op(Image(x), cutoff=fc, order=n).data)
                worst = max(worst, np.max(np.abs(got - ref)))
    print(f"butterworth vs skimage.filters.butterworth: max |diff| = {worst:.2e}")
    assert worst < 1e-12
    ref = skimage.filters.butterworth(camera, cutoff_frequency_ratio=0.1, high_pass=False, order=2.0,
                                      npad=16)
    got = np.asarray(butterworth_lowpass(Image(camera), cutoff=0.1, pad=16, mode="nearest").data)
    d = np.max(np.abs(got - ref))
    print(f"butterworth_lowpass(pad=16, nearest) vs skimage npad=16: max |diff| = {d:.2e}")
    assert d < 1e-12


def test_gaussian_lowpass_vs_scipy_fourier_gaussian(camera, coins_odd):
    worst = 0.0
    for x in (camera, coins_odd):
        for fc in (0.02, 0.08, 0.3):
            sigma = 1.0 / (2 * np.pi * fc)
            ref = np.fft.ifft2(ndi.fourier_gaussian(np.fft.fft2(x), sigma=sigma)).real
            got = np.asarray(gaussian_lowpass(Image(x), cutoff=fc).data)
            worst = max(worst, np.max(np.abs(got - ref)))
    print(f"gaussian_lowpass vs scipy.ndimage.fourier_gaussian: max |diff| = {worst:.2e}")
    assert worst < 1e-13


def test_gaussian_lowpass_vs_spatial_blur_and_padding(camera):
    # A spatial Gaussian (sigma = 1 / (2 pi fc)) with SciPy's reflect boundary is the
    # reference; the periodic FFT filter (pad=0) is the null, reflect padding must beat it.
    fc = 0.05
    sigma = 1.0 / (2 * np.pi * fc)
    ref = ndi.gaussian_filter(camera, sigma, mode="reflect", truncate=6.0)
    ref_wrap = ndi.gaussian_filter(camera, sigma, mode="wrap", truncate=6.0)
    periodic = np.asarray(gaussian_lowpass(Image(camera), cutoff=fc).data)
    padded = np.asarray(gaussian_lowpass(Image(camera), cutoff=fc, pad=32, mode="reflect").data)
    e_wrap = np.max(np.abs(periodic - ref_wrap))
    e_null = np.max(np.abs(periodic - ref))
    e_pad = np.max(np.abs(padded - ref))
    print(f"gaussian_lowpass fc={fc}: periodic vs gaussian_filter(wrap) {e_wrap:.2e}; vs reflect: "
          f"periodic (null) {e_null:.2e}, pad=32 {e_pad:.2e}")
    assert e_wrap < 1e-6
    assert e_pad < 1e-6 < e_null


def test_lowpass_denoises_better_than_nothing(camera):
    rng = np.random.default_rng(0)
    clean = ndi.gaussian_filter(camera, 1.0)
    noisy = clean + 0.08 * rng.standard_normal(clean.shape)

    def psnr(a):
        return 10 * np.log10(1.0 / np.mean((a - clean) ** 2))

    p0 = psnr(noisy)
    for name, out in (("gaussian_lowpass", gaussian_lowpass(Image(noisy), cutoff=0.12, pad=8)),
                      ("butterworth_lowpass", butterworth_lowpass(Image(noisy), cutoff=0.15, pad=8)),
                      ("ideal_lowpass", ideal_lowpass(Image(noisy), cutoff=0.15, pad=8))):
        p = psnr(np.asarray(out.data))
        print(f"{name}: PSNR {p:.2f} dB vs noisy input {p0:.2f} dB")
        assert p > p0 + 3.0


# ---------------------------------------------------------------------------
# gradients, dtype, bad input
# ---------------------------------------------------------------------------


def test_gradients_in_cutoff_and_order(camera):
    x = Image(camera[:32, :40])
    w = jnp.asarray(np.random.default_rng(1).standard_normal((32, 40)))

    def loss(op, **kw):
        return jnp.sum(op(x, **kw).data * w)

    cases = [
        (butterworth_lowpass, "cutoff", 0.13, {"order": 2.5}),
        (butterworth_lowpass, "order", 2.5, {"cutoff": 0.13}),
        (butterworth_highpass, "order", 1.5, {"cutoff": 0.2}),
        (gaussian_highpass, "cutoff", 0.07, {}),
        (gaussian_bandpass, "octaves", 1.3, {"centre": 0.1}),
        (butterworth_bandpass, "centre", 0.1, {"octaves": 1.3}),
    ]
    for op, name, v, kw in cases:
        g = float(jax.grad(lambda p, op=op, name=name, kw=kw: loss(op, **{name: p}, **kw))(jnp.asarray(v)))
        h = 1e-6 * v
        fd = float((loss(op, **{name: v + h}, **kw) - loss(op, **{name: v - h}, **kw)) / (2 * h))
        print(f"{op.__name__} d/d{name}: grad {g:.6e}, finite difference {fd:.6e}")
        assert abs(g) > 1e-6
        assert abs(g - fd) <= 1e-5 * max(1.0, abs(fd))


def test_float32(camera):
    x64 = camera[:40, :48]
    x32 = Image(jnp.asarray(x64, dtype=jnp.float32))
    for op in (gaussian_lowpass, butterworth_highpass, ideal_bandpass, fft_magnitude):
        y32 = op(x32).data
        y64 = op(Image(x64)).data
        assert y32.dtype == jnp.float32
        d = float(jnp.max(jnp.abs(y32.astype(jnp.float64) - y64)))
        assert d < 1e-5, (op.__name__, d)


def test_bad_parameters():
    x = Image(jnp.full((8, 8), 0.5))
    with pytest.raises(ValueError, match="butterworth_lowpass.*'cutoff'"):
        butterworth_lowpass(x, cutoff=0.0)
    with pytest.raises(ValueError, match="butterworth_highpass.*'order'"):
        butterworth_highpass(x, order=-1.0)
    with pytest.raises(ValueError, match="gaussian_bandpass.*'octaves'"):
        gaussian_bandpass(x, octaves=0.0)
    with pytest.raises(ValueError, match="ideal_bandpass.*'centre'"):
        ideal_bandpass(x, centre=float("nan"))
    with pytest.raises(ValueError, match="ideal_lowpass.*'pad'"):
        ideal_lowpass(x, pad=-1)
    with pytest.raises(TypeError, match="gaussian_lowpass.*'pad'"):
        gaussian_lowpass(x, pad=2.5)
    with pytest.raises(ValueError, match="gaussian_highpass.*'mode'"):
        gaussian_highpass(x, pad=2, mode="edge")
    with pytest.raises(ValueError, match="fft_magnitude.*'scale'"):
        fft_magnitude(x, scale="db")
    with pytest.raises(ValueError, match="fft_magnitude.*'gain'"):
        fft_magnitude(x, gain=0.0)
    with pytest.raises(ValueError, match="fft_phase.*'floor'"):
        fft_phase(x, floor=-1.0)
    with pytest.raises(TypeError, match="gaussian_lowpass.*'img'"):
        gaussian_lowpass(jnp.zeros((8, 8)))
    with pytest.raises(ValueError, match="apply.*knob 'a'"):
        fsjax.apply(x, "gaussian_lowpass", a=1.5)
