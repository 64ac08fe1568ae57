"""Grey morphology: conformance with SciPy / scikit-image on real photographs,
synthetic ground truths, traced-vs-concrete radius, nulls, bad input."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.ndimage as ndi
from skimage import data
from skimage import morphology as skm

import fsjax
from fsjax.ops import bottom_hat, closing, dilation, erosion, morph_gradient, opening, top_hat

CAMERA = data.camera()[::4, ::4].astype(np.float64) / 255.0  # 128 x 128
COINS = data.coins()[::2, ::2][:128, 32:160].astype(np.float64) / 255.0  # 128 x 128
IMAGES = {"camera": CAMERA, "coins": COINS}


def footprint(r: int, shape: str) -> np.ndarray:
    if shape == "disk":
        return skm.disk(r).astype(bool)
    return np.ones((2 * r + 1, 2 * r + 1), bool)


def run(op, x, **kw):
    return np.asarray(op(fsjax.Image(jnp.asarray(x)), **kw).data)


# ---------------------------------------------------------------------------
# Conformance
# ---------------------------------------------------------------------------


def test_disk_matches_skimage_disk():
    for r in range(0, 9):
        ours = np.array([[di * di + dj * dj <= r * r for dj in range(-r, r + 1)] for di in range(-r, r + 1)])
        assert np.array_equal(ours, skm.disk(r).astype(bool))
    # a single impulse dilated is the element itself
    for r, shape in [(3, "disk"), (4, "disk"), (2, "square")]:
        x = np.zeros((15, 15))
        x[7, 7] = 1.0
        got = run(dilation, x, radius=r, shape=shape)[7 - r:8 + r, 7 - r:8 + r] > 0.5
        assert np.array_equal(got, footprint(r, shape)), (r, shape)


@pytest.mark.parametrize("name", list(IMAGES))
@pytest.mark.parametrize("shape", ["disk", "square"])
def test_erosion_dilation_vs_scipy(name, shape):
    x = IMAGES[name]
    worst = 0.0
    for r in (1, 2, 4):
        fp = footprint(r, shape)
        d_e = np.max(np.abs(run(erosion, x, radius=r, shape=shape) - ndi.grey_erosion(x, footprint=fp, mode="reflect")))
        d_d = np.max(np.abs(run(dilation, x, radius=r, shape=shape) - ndi.grey_dilation(x, footprint=fp, mode="reflect")))
        print(f"{name} {shape} r={r}: erosion vs scipy.grey_erosion max|diff| = {d_e:.2e}, "
              f"dilation vs scipy.grey_dilation max|diff| = {d_d:.2e}")
        worst = max(worst, d_e, d_d)
    assert worst <= 1e-6


@pytest.mark.parametrize("mode", ["reflect", "mirror", "nearest", "wrap", "constant"])
def test_boundary_modes_vs_scipy(mode):
    x = COINS[:40, :48]
    fp = footprint(3, "disk")
    kw = dict(radius=3, mode=mode, cval=0.3)
    d_e = np.max(np.abs(run(erosion, x, **kw) - ndi.grey_erosion(x, footprint=fp, mode=mode, cval=0.3)))
    d_d = np.max(np.abs(run(dilation, x, **kw) - ndi.grey_dilation(x, footprint=fp, mode=mode, cval=0.3)))
    print(f"mode={mode}: erosion/dilation vs scipy max|diff| = {d_e:.2e} / {d_d:.2e}")
    assert d_e <= 1e-12 and d_d <= 1e-12


@pytest.mark.parametrize("name", list(IMAGES))
def test_open_close_hats_vs_skimage(name):
    # scikit-image (0.26) applies SciPy's grey erosion/dilation with its own `mode`
    # (default "reflect") at each of the two steps, as we do; SciPy's grey_opening
    # / grey_closing also use the same mode at both steps.
    x = IMAGES[name]
    fp = footprint(3, "disk")
    pairs = {
        "opening vs skimage.opening": (run(opening, x, radius=3), skm.opening(x, fp)),
        "closing vs skimage.closing": (run(closing, x, radius=3), skm.closing(x, fp)),
        "top_hat vs skimage.white_tophat": (run(top_hat, x, radius=3), skm.white_tophat(x, fp)),
        "bottom_hat vs skimage.black_tophat": (run(bottom_hat, x, radius=3), skm.black_tophat(x, fp)),
        "opening vs scipy.grey_opening": (run(opening, x, radius=3), ndi.grey_opening(x, footprint=fp)),
        "closing vs scipy.grey_closing": (run(closing, x, radius=3), ndi.grey_closing(x, footprint=fp)),
        "morph_gradient vs scipy.morphological_gradient": (
            run(morph_gradient, x, radius=3), ndi.morphological_gradient(x, footprint=fp)),
    }
    for label, (ours, ref) in pairs.items():
        d = float(np.max(np.abs(ours - ref)))
        print(f"{name}: {label} max|diff| = {d:.2e}")
        assert d <= 1e-12, label


def test_float32_equals_float64():
    x = CAMERA[:64, :64]
    for op in (erosion, dilation, top_hat):
        y32 = op(fsjax.Image(jnp.asarray(x, jnp.float32)), radius=2).data
        y64 = op(fsjax.Image(jnp.asarray(x.astype(np.float32).astype(np.float64))), radius=2).data
        assert y32.dtype == jnp.float32
        # min/max are exact; only the top-hat subtraction rounds
        assert np.max(np.abs(np.asarray(y32, np.float64) - np.asarray(y64))) <= 1e-7


# ---------------------------------------------------------------------------
# Traced radius (knob) == concrete radius
# ---------------------------------------------------------------------------


@pytest.mark.parametrize("shape", ["disk", "square"])
def test_traced_radius_equals_concrete(shape):
    x = jnp.asarray(COINS[:48, :48])
    radii = jnp.array([0.0, 1.5, 3.0, 8.0])
    for op in (erosion, opening, morph_gradient):
        batch = jax.jit(jax.vmap(lambda r, op=op: op(fsjax.Image(x), radius=r, shape=shape).data))(radii)
        for i, r in enumerate(np.asarray(radii)):
            ref = op(fsjax.Image(x), radius=float(r), shape=shape).data
            assert np.array_equal(np.asarray(batch[i]), np.asarray(ref)), (op.__name__, r)


def test_real_radius_elements():
    # r = 1 is the cross, r = 1.5 (or sqrt 2) the 3x3 square, r = 2.5 a 21-pixel disk
    x = np.zeros((11, 11))
    x[5, 5] = 1.0
    assert run(dilation, x, radius=1).sum() == 5
    assert run(dilation, x, radius=1.5).sum() == 9
    assert run(dilation, x, radius=2.5).sum() == 21
    assert run(dilation, x, radius=2.5, shape="square").sum() == 25


def test_traced_radius_beyond_support_fails_closed():
    x = jnp.asarray(CAMERA[:32, :32])
    f = jax.jit(lambda r: erosion(fsjax.Image(x), radius=r, max_radius=4).data)
    assert np.all(np.isfinite(np.asarray(f(4.0))))
    assert np.all(np.isnan(np.asarray(f(5.0))))
    assert np.all(np.isnan(np.asarray(f(-1.0))))
    # a concrete radius is not bounded by max_radius
    out = erosion(fsjax.Image(x), radius=6, max_radius=4).data
    assert np.array_equal(np.asarray(out), ndi.grey_erosion(np.asarray(x), footprint=skm.disk(6).astype(bool)))


# ---------------------------------------------------------------------------
# Ground truths and algebraic laws
# ---------------------------------------------------------------------------


def specks_scene():
    x = np.full((40, 40), 0.2)
    x[5:14, 5:14] = 0.8  # 9x9 square: larger than the element
    x[20:32, 22:35] = 0.6  # 12x13 rectangle
    specks = [(3, 30), (18, 8), (36, 4), (36, 36)]
    truth = x.copy()
    for i, j in specks:
        x[i, j] = 0.95  # 1-pixel specks
    x[25:27, 8:10] = 0.9  # 2x2 speck
    return x, truth


def test_opening_removes_small_specks_keeps_large_squares():
    x, truth = specks_scene()
    out = run(opening, x, radius=2, shape="square")  # 5x5 element
    d = np.max(np.abs(out - truth))
    print(f"5x5 opening vs speck-free truth: max|diff| = {d:.2e}")
    assert d == 0.0
    # a 3x3 element also removes the 2x2 speck; the 1-pixel element (r = 0, the
    # null) removes nothing
    assert np.max(np.abs(run(opening, x, radius=1, shape="square") - truth)) == 0.0
    assert np.max(np.abs(run(opening, x, radius=0) - truth)) > 0.5


def test_top_hat_recovers_dot_on_ramp():
    ramp = np.tile(np.linspace(0.1, 0.6, 31), (31, 1))
    slope = 0.5 / 30
    for h in (0.05, 0.3):
        x = ramp.copy()
        x[15, 15] += h
        th = run(top_hat, x, radius=3, shape="square")
        print(f"top_hat (square r=3) of a {h} dot on a ramp: {th[15, 15]:.6f}; "
              f"max elsewhere in the interior {np.max(np.abs(np.delete(th[5:26, 5:26].ravel(), 10 * 21 + 10))):.1e}")
        assert abs(th[15, 15] - h) < 1e-12
        inner = th[5:26, 5:26].copy()
        inner[10, 10] = 0.0
        assert np.max(np.abs(inner)) < 1e-12
        # A disk's extreme rows are single pixels, so on a slope the opening under the
        # dot rises by one slope step: the disk top-hat recovers h - slope (pinned).
        thd = run(top_hat, x, radius=3, shape="disk")
        assert abs(thd[15, 15] - (h - slope)) < 1e-12
        # bottom-hat: a pit of the same depth
        y = ramp.copy()
        y[15, 15] -= h
        assert abs(run(bottom_hat, y, radius=3, shape="square")[15, 15] - h) < 1e-12


def test_gradient_of_step_edge():
    x = np.full((12, 20), 0.3)
    x[:, 10:] = 0.8
    for r in (1, 2, 3):
        g = run(morph_gradient, x, radius=r, shape="square")
        band = np.zeros(20, bool)
        band[10 - r:10 + r] = True
        assert np.allclose(g[6, band], 0.5, atol=1e-12) and np.all(g[6, ~band] == 0.0)


@pytest.mark.parametrize("name", list(IMAGES))
def test_ordering_and_idempotence(name):
    x = IMAGES[name]
    e, d = run(erosion, x, radius=2), run(dilation, x, radius=2)
    o, c = run(opening, x, radius=2), run(closing, x, radius=2)
    assert np.all(e <= o) and np.all(o <= x) and np.all(x <= c) and np.all(c <= d)
    assert np.array_equal(run(opening, o, radius=2), o)
    assert np.array_equal(run(closing, c, radius=2), c)
    # duality: erosion(x) = -dilation(-x)  (1 - x keeps the value range)
    assert np.max(np.abs(run(erosion, x, radius=2) - (1 - run(dilation, 1 - x, radius=2)))) < 1e-12


# ---------------------------------------------------------------------------
# Nulls: salt / pepper noise
# ---------------------------------------------------------------------------


def blocks_scene():
    x = np.full((64, 64), 0.3)
    x[6:20, 6:26] = 0.7
    x[30:56, 10:22] = 0.55
    x[36:50, 34:58] = 0.8
    return x


def test_opening_beats_null_on_salt_noise():
    rng = np.random.default_rng(0)
    clean = blocks_scene()
    noisy = clean.copy()
    salt = rng.random(clean.shape) < 0.05
    noisy[salt] = 1.0
    mae_null = np.mean(np.abs(noisy - clean))
    mae_open = np.mean(np.abs(run(opening, noisy, radius=1, shape="square") - clean))
    mae_med = np.mean(np.abs(ndi.median_filter(noisy, 3, mode="reflect") - clean))
    print(f"salt 5%: MAE vs clean: noisy (null) {mae_null:.4f}, 3x3 opening {mae_open:.4f}, "
          f"3x3 median (for scale) {mae_med:.4f}")
    assert mae_open < 0.1 * mae_null


def test_closing_beats_null_on_pepper_noise():
    rng = np.random.default_rng(1)
    clean = blocks_scene()
    noisy = clean.copy()
    pepper = rng.random(clean.shape) < 0.05
    noisy[pepper] = 0.0
    mae_null = np.mean(np.abs(noisy - clean))
    mae_close = np.mean(np.abs(run(closing, noisy, radius=1, shape="square") - clean))
    mae_open = np.mean(np.abs(run(opening, noisy, radius=1, shape="square") - clean))
    print(f"pepper 5%: MAE vs clean: noisy (null) {mae_null:.4f}, 3x3 closing {mae_close:.4f}, "
          f"3x3 opening (wrong tool) {mae_open:.4f}")
    assert mae_close < 0.1 * mae_null
    assert mae_open > mae_null  # the dual operator makes pepper worse: the test can fail


# ---------------------------------------------------------------------------
# Bad input
# ---------------------------------------------------------------------------


@pytest.mark.parametrize("op", [erosion, dilation, opening, closing, top_hat, bottom_hat, morph_gradient])
def test_bad_parameters(op):
    img = fsjax.Image(jnp.asarray(CAMERA[:16, :16]))
    name = op.__name__
    with pytest.raises(ValueError, match=rf"{name}.*'radius'"):
        op(img, radius=-1)
    with pytest.raises(ValueError, match=rf"{name}.*'radius'"):
        op(img, radius=float("nan"))
    with pytest.raises(ValueError, match=rf"{name}.*'shape'"):
        op(img, shape="hexagon")
    with pytest.raises(ValueError, match=rf"{name}.*'mode'"):
        op(img, mode="periodic")
    with pytest.raises(TypeError, match=rf"{name}.*'max_radius'"):
        op(img, max_radius=2.5)
    with pytest.raises(TypeError, match=rf"{name}.*Image"):
        op(fsjax.Region(jnp.zeros((4, 4), bool)))
    with pytest.raises(ValueError, match=rf"{name}.*NaN"):
        op(fsjax.Image(jnp.full((4, 4), jnp.nan)))
