"""Geometry family: mirror, translate, rotate, zoom, shear, affine_warp, resize.

References: numpy (flip, roll, rot90), scipy.ndimage (shift, rotate,
affine_transform), scikit-image (transform.rotate, transform.resize), OpenCV
(cv2.resize), Pillow (Image.resize); analytic ground truths on ramps and
smooth synthetic images.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.ndimage as ndi
import skimage.data
import skimage.transform

import fsjax
from fsjax import Image
from fsjax.ops import affine_warp, mirror, resize, rotate, shear, translate, zoom

cv2 = pytest.importorskip("cv2")

SCIPY_MODE = {"constant": "constant", "grid-constant": "grid-constant", "nearest": "nearest",
              "reflect": "reflect", "mirror": "mirror", "wrap": "grid-wrap"}


@pytest.fixture(scope="module")
def camera():
    return skimage.data.camera()[120:184, 200:260].astype(np.float64) / 255.0  # 64 x 60


@pytest.fixture(scope="module")
def coins():
    return skimage.data.coins()[60:117, 100:151].astype(np.float64) / 255.0  # 57 x 51 (odd)


def _smooth(h, w):
    """A smooth, analytically known image and its generating function."""

    def f(r, c):
        return 0.5 + 0.2 * np.sin(2 * np.pi * r / 23.0 + 0.3) * np.cos(2 * np.pi * c / 17.0) + 0.1 * np.cos(
            2 * np.pi * (r + c) / 31.0)

    r, c = np.mgrid[0:h, 0:w].astype(float)
    return f(r, c), f


def _rms(a):
    return float(np.sqrt(np.mean(np.square(a))))


# ---------------------------------------------------------------------------
# mirror
# ---------------------------------------------------------------------------


def test_mirror_equals_numpy_flip(coins):
    for axis in (0, 1, -1, -2, None):
        got = np.asarray(mirror(Image(coins), axis=axis).data)
        assert np.array_equal(got, np.flip(coins, axis=axis if axis is None else (axis % 2)))
    both = np.asarray(mirror(Image(coins), axis=None).data)
    rot = np.asarray(rotate(Image(coins), angle_deg=180.0, method="bilinear").data)
    d = np.max(np.abs(both - rot))
    print(f"mirror(axis=None) vs rotate(180): max |diff| = {d:.2e}")
    assert d < 1e-12


# ---------------------------------------------------------------------------
# translate
# ---------------------------------------------------------------------------


def test_translate_vs_scipy_shift(camera):
    worst = 0.0
    for mode, smode in SCIPY_MODE.items():
        for dy, dx in ((1.3, -2.7), (-0.25, 0.6), (-5.5, 3.0)):
            ref = ndi.shift(camera, (dy, dx), order=1, mode=smode, cval=0.2)
            got = np.asarray(translate(Image(camera), dx=dx, dy=dy, mode=mode, cval=0.2).data)
            worst = max(worst, np.max(np.abs(got - ref)))
    print(f"translate (bilinear, 6 modes) vs scipy.ndimage.shift(order=1): max |diff| = {worst:.2e}")
    assert worst < 1e-12


def test_translate_integer_equals_roll(camera):
    for method in ("nearest", "bilinear", "bicubic"):
        got = np.asarray(translate(Image(camera), dx=3.0, dy=-2.0, method=method).data)
        ref = np.roll(camera, (-2, 3), axis=(0, 1))
        d = np.max(np.abs(got[:-2, 3:] - ref[:-2, 3:]))  # pixels that did not wrap
        assert d < 1e-13, (method, d)
        assert np.all(got[-2:, :] == 0) and np.all(got[:, :3] == 0)  # uncovered -> cval
        wrapped = np.asarray(translate(Image(camera), dx=3.0, dy=-2.0, method=method, mode="wrap").data)
        assert np.max(np.abs(wrapped - ref)) < 1e-13  # periodic mode is exactly np.roll
    print(f"translate by (3, -2) vs numpy.roll (interior): max |diff| = {d:.2e}")


def test_translate_subpixel_beats_nearest():
    img, f = _smooth(48, 56)
    dy, dx = 0.37, -1.63
    r, c = np.mgrid[0:48, 0:56].astype(float)
    truth = f(r - dy, c - dx)
    inner = (slice(4, -4), slice(4, -4))
    errs = {}
    for method in ("nearest", "bilinear", "bicubic"):
        out = np.asarray(translate(Image(img), dx=dx, dy=dy, method=method).data)
        errs[method] = _rms((out - truth)[inner])
    print("translate sub-pixel RMS error vs analytic: " + ", ".join(f"{k} {v:.2e}" for k, v in errs.items()))
    assert errs["bicubic"] < errs["bilinear"] < errs["nearest"]
    assert errs["bicubic"] < 2e-3


# ---------------------------------------------------------------------------
# rotate
# ---------------------------------------------------------------------------


@pytest.mark.parametrize("n", [7, 8, 33])
def test_rotate_quarter_turns_equal_rot90(n):
    x = np.random.default_rng(n).random((n, n))
    worst = 0.0
    for method in ("nearest", "bilinear", "bicubic"):
        for angle, k in ((90.0, 1), (-90.0, -1), (180.0, 2), (270.0, 3)):
            got = np.asarray(rotate(Image(x), angle_deg=angle, method=method).data)
            worst = max(worst, np.max(np.abs(got - np.rot90(x, k))))
    print(f"rotate by multiples of 90 deg vs numpy.rot90 ({n}x{n}, 3 methods): max |diff| = {worst:.2e}")
    assert worst < 1e-12


def test_rotate_vs_scipy_and_skimage(camera, coins):
    w_sp = w_sk = 0.0
    for x in (camera, coins):
        for angle in (17.0, -63.5, 141.0):
            got_c = np.asarray(rotate(Image(x), angle_deg=angle, method="bilinear", mode="constant").data)
            ref_c = ndi.rotate(x, angle, reshape=False, order=1, mode="constant")
            w_sp = max(w_sp, np.max(np.abs(got_c - ref_c)))
            got_g = np.asarray(rotate(Image(x), angle_deg=angle, method="bilinear").data)
            ref_g = skimage.transform.rotate(x, angle, order=1, mode="constant", cval=0.0)
            w_sk = max(w_sk, np.max(np.abs(got_g - ref_g)))
    print(f"rotate(bilinear, constant) vs scipy.ndimage.rotate(order=1): max |diff| = {w_sp:.2e}")
    print(f"rotate(bilinear, grid-constant) vs skimage.transform.rotate(order=1): max |diff| = {w_sk:.2e}")
    assert w_sp < 1e-9 and w_sk < 1e-9


def test_rotate_round_trip_beats_nearest(camera):
    h, w = camera.shape
    r, c = np.mgrid[0:h, 0:w]
    disc = (r - (h - 1) / 2) ** 2 + (c - (w - 1) / 2) ** 2 <= (min(h, w) / 2 - 3) ** 2
    smooth = ndi.gaussian_filter(camera, 1.0)
    for name, x in (("camera", camera), ("camera blurred sigma=1", smooth)):
        errs = {}
        for method in ("nearest", "bilinear", "bicubic"):
            there = rotate(Image(x), angle_deg=33.0, method=method)
            back = np.asarray(rotate(there, angle_deg=-33.0, method=method).data)
            errs[method] = _rms((back - x)[disc])
        print(f"rotate +33/-33 round trip on {name}, RMS in the central disc: "
              + ", ".join(f"{k} {v:.2e}" for k, v in errs.items()))
        assert errs["bicubic"] < errs["bilinear"] < errs["nearest"]
    assert errs["bicubic"] < 5e-3  # smooth input: recovered to interpolation error


# ---------------------------------------------------------------------------
# zoom, shear, affine_warp
# ---------------------------------------------------------------------------


def test_zoom_of_ramp_is_exact():
    r, c = np.mgrid[0:21, 0:30].astype(float)
    ramp = 0.1 + 0.02 * r + 0.015 * c
    for method in ("bilinear", "bicubic"):
        for s in (2.0, 1.37):
            out = np.asarray(zoom(Image(ramp), scale=s, method=method).data)
            cr, cc = 10.0, 14.5
            truth = 0.1 + 0.02 * (cr + (r - cr) / s) + 0.015 * (cc + (c - cc) / s)
            d = np.max(np.abs(out - truth))
            print(f"zoom x{s} ({method}) of a linear ramp vs analytic: max |diff| = {d:.2e}")
            assert d < 1e-13


def test_zoom_vs_scipy_affine(camera):
    h, w = camera.shape
    ctr = np.array([(h - 1) / 2, (w - 1) / 2])
    worst = 0.0
    for s in (0.7, 1.6, 3.1):
        m = np.eye(2) / s
        ref = ndi.affine_transform(camera, m, offset=ctr - m @ ctr, order=1, mode="grid-constant")
        got = np.asarray(zoom(Image(camera), scale=s, method="bilinear").data)
        worst = max(worst, np.max(np.abs(got - ref)))
    print(f"zoom (bilinear) vs scipy.ndimage.affine_transform(diag(1/s)): max |diff| = {worst:.2e}")
    assert worst < 1e-12


def test_shear_integer_rows_equal_roll():
    x = np.random.default_rng(3).random((9, 40))  # centre row 4
    out = np.asarray(shear(Image(x), kx=1.0).data)
    for r in range(9):
        k = r - 4
        ref = np.roll(x[r], k)
        keep = slice(max(k, 0), 40 + min(k, 0))
        assert np.max(np.abs(out[r, keep] - ref[keep])) < 1e-13
    # and the vertical shear is its transpose
    out_v = np.asarray(shear(Image(x.T), ky=1.0).data)
    d = np.max(np.abs(out_v - out.T))
    print(f"shear kx=1 per-row numpy.roll check passed; vertical vs transposed horizontal: {d:.2e}")
    assert d < 1e-13


def test_affine_warp_vs_scipy(camera, coins):
    rng = np.random.default_rng(7)
    worst = {}
    for x in (camera, coins):
        for _ in range(3):
            lin = np.eye(2) + 0.3 * rng.standard_normal((2, 2))
            m = np.concatenate([lin, rng.uniform(-6, 6, (2, 1))], axis=1)
            for mode, smode in SCIPY_MODE.items():
                ref = ndi.affine_transform(x, m[:, :2], offset=m[:, 2], order=1, mode=smode, cval=0.4)
                got = np.asarray(affine_warp(Image(x), matrix=m, mode=mode, cval=0.4).data)
                worst[mode] = max(worst.get(mode, 0.0), float(np.max(np.abs(got - ref))))
            ref0 = ndi.affine_transform(x, m[:, :2], offset=m[:, 2], order=0, mode="nearest")
            got0 = np.asarray(affine_warp(Image(x), matrix=m, method="nearest", mode="nearest").data)
            worst["nearest-neighbour"] = max(worst.get("nearest-neighbour", 0.0), float(np.max(np.abs(got0 - ref0))))
    print("affine_warp vs scipy.ndimage.affine_transform(order=1), max |diff| per mode: "
          + ", ".join(f"{k} {v:.1e}" for k, v in worst.items()))
    assert max(worst.values()) < 1e-9


def test_affine_warp_forward_and_shear_consistency(camera):
    a = np.array([[1.1, 0.2, -3.0], [-0.15, 0.9, 2.0]])
    inv = np.linalg.inv(np.vstack([a, [0, 0, 1]]))
    fwd = np.asarray(affine_warp(Image(camera), matrix=a, forward=True).data)
    bwd = np.asarray(affine_warp(Image(camera), matrix=inv).data)
    d1 = np.max(np.abs(fwd - bwd))
    h, w = camera.shape
    rc, cc = (h - 1) / 2, (w - 1) / 2
    kx, ky = 0.3, -0.2
    m = np.array([[1.0, -ky, ky * cc], [-kx, 1.0, kx * rc]])
    d2 = np.max(np.abs(np.asarray(shear(Image(camera), kx=kx, ky=ky).data)
                       - np.asarray(affine_warp(Image(camera), matrix=m, method="bicubic").data)))
    ident = np.max(np.abs(np.asarray(affine_warp(Image(camera)).data) - camera))
    print(f"affine_warp forward=True vs inverse matrix: {d1:.2e}; shear vs affine_warp: {d2:.2e}; "
          f"identity: {ident:.1e}")
    assert d1 < 1e-12 and d2 < 1e-12 and ident == 0.0


# ---------------------------------------------------------------------------
# resize
# ---------------------------------------------------------------------------

SHAPES = [(40, 33), (128, 150), (17, 101), (64, 60)]


def test_resize_vs_opencv(camera):
    wl = wc = 0.0
    for shp in SHAPES:
        ref = cv2.resize(camera, (shp[1], shp[0]), interpolation=cv2.INTER_LINEAR)
        wl = max(wl, np.max(np.abs(np.asarray(resize(Image(camera), shape=shp).data) - ref)))
        ref = cv2.resize(camera, (shp[1], shp[0]), interpolation=cv2.INTER_CUBIC)
        got = np.asarray(resize(Image(camera), shape=shp, method="bicubic", cubic_a=-0.75).data)
        wc = max(wc, np.max(np.abs(got - ref)))
    print(f"resize bilinear vs cv2.resize INTER_LINEAR (up and down): max |diff| = {wl:.2e}")
    print(f"resize bicubic a=-0.75 vs cv2.resize INTER_CUBIC: max |diff| = {wc:.2e} (OpenCV float32 weights)")
    assert wl < 1e-14
    assert wc < 2e-6


def test_resize_vs_skimage(camera, coins):
    w0 = w1 = 0.0
    for x in (camera, coins):
        for shp in SHAPES:
            ref = skimage.transform.resize(x, shp, order=1, mode="edge", anti_aliasing=False)
            w0 = max(w0, np.max(np.abs(np.asarray(resize(Image(x), shape=shp).data) - ref)))
            ref = skimage.transform.resize(x, shp, order=1, mode="edge", anti_aliasing=True)
            w1 = max(w1, np.max(np.abs(np.asarray(resize(Image(x), shape=shp, antialias=True).data) - ref)))
    print(f"resize vs skimage.transform.resize(order=1, edge): max |diff| = {w0:.2e} "
          f"(anti_aliasing=True: {w1:.2e})")
    assert w0 < 1e-12 and w1 < 1e-12


def test_resize_bicubic_keys_vs_pillow(camera):
    pil = pytest.importorskip("PIL.Image")
    x32 = camera.astype(np.float32)
    worst = 0.0
    for shp in ((150, 131), (128, 120)):  # up-sampling: Pillow's bicubic is Keys a = -0.5
        ref = np.asarray(pil.fromarray(x32, mode="F").resize((shp[1], shp[0]), pil.Resampling.BICUBIC))
        got = np.asarray(resize(Image(x32.astype(np.float64)), shape=shp, method="bicubic").data)
        worst = max(worst, np.max(np.abs(got - ref)[3:-3, 3:-3]))
    print(f"resize bicubic a=-0.5 vs Pillow BICUBIC (up-sampling, 3-px border excluded): "
          f"max |diff| = {worst:.2e} (float32 input)")
    assert worst < 1e-5


def test_resize_antialias_beats_plain_decimation():
    # A fine grating far above the new Nyquist aliases to a false low-frequency pattern;
    # the anti-aliased resize should be close to the grating's mean (0.5).
    r, c = np.mgrid[0:96, 0:96].astype(float)
    grating = 0.5 + 0.4 * np.cos(2 * np.pi * 0.45 * c)
    plain = np.asarray(resize(Image(grating), shape=(32, 32)).data)
    aa = np.asarray(resize(Image(grating), shape=(32, 32), antialias=True).data)
    e_plain, e_aa = _rms(plain - 0.5), _rms(aa - 0.5)
    print(f"resize 96->32 of a 0.45 cyc/px grating, RMS alias: plain {e_plain:.3f}, antialias {e_aa:.2e}")
    assert e_aa < 0.1 * e_plain


def test_resize_ramp_and_default_factor():
    r, c = np.mgrid[0:20, 0:30].astype(float)
    ramp = 0.01 * r + 0.02 * c
    out = resize(Image(ramp), factor=1.5, method="bicubic")
    assert out.data.shape == (30, 45)
    ro, co = np.mgrid[0:30, 0:45].astype(float)
    truth = 0.01 * ((ro + 0.5) / 1.5 - 0.5) + 0.02 * ((co + 0.5) / 1.5 - 0.5)
    inner = (slice(2, -2), slice(2, -2))  # edge clamping bends the ramp at the border
    d = np.max(np.abs(np.asarray(out.data)[inner] - truth[inner]))
    print(f"resize x1.5 (bicubic) of a ramp vs analytic, interior: max |diff| = {d:.2e}")
    assert d < 1e-13
    assert resize(Image(ramp)).data.shape == (10, 15)


# ---------------------------------------------------------------------------
# gradients, batch, dtype, bad input
# ---------------------------------------------------------------------------


def test_gradients_in_knobs(camera):
    x = Image(camera[:32, :40])
    wts = jnp.asarray(np.random.default_rng(5).standard_normal((32, 40)))

    def loss(op, **kw):
        return jnp.sum(op(x, **kw).data * wts)

    cases = [  # (op, knob, value, FD step, other kwargs)
        (translate, "dx", -1.6, 1e-6, {"dy": 0.3}),
        (translate, "dy", 2.3, 1e-6, {"method": "bicubic"}),
        (rotate, "angle_deg", 23.0, 1e-3, {}),  # bicubic: C1 in the angle
        (rotate, "angle_deg", 23.0, 1e-8, {"method": "bilinear"}),  # piecewise linear: small step
        (zoom, "scale", 1.3, 1e-6, {"method": "bilinear"}),
        (zoom, "scale", 0.8, 1e-5, {}),
        (shear, "kx", 0.2, 1e-6, {"ky": -0.1}),
    ]
    for op, name, v, h, kw in cases:
        g = float(jax.grad(lambda p, op=op, name=name, kw=kw: loss(op, **{name: p}, **kw))(jnp.asarray(v)))
        fd = float((loss(op, **{name: v + h}, **kw) - loss(op, **{name: v - h}, **kw)) / (2 * h))
        print(f"{op.__name__}({kw.get('method', 'default')}) d/d{name}: grad {g:.6e}, FD {fd:.6e}")
        assert abs(g) > 1e-3
        assert abs(g - fd) <= 1e-5 * max(1.0, abs(fd))

    def loss_m(m):
        return jnp.sum(affine_warp(x, matrix=m).data * wts)

    # generic entries: with round ones, source positions land exactly on the kinks
    m0 = jnp.asarray([[0.9513, 0.1027, 1.3171], [-0.0531, 1.0213, -0.7093]])
    gm = np.asarray(jax.grad(loss_m)(m0))
    e = np.zeros((2, 3))
    e[0, 1] = 1e-7
    fd = float((loss_m(m0 + e) - loss_m(m0 - e)) / 2e-7)
    print(f"affine_warp d/dmatrix[0,1]: grad {gm[0, 1]:.6e}, FD {fd:.6e}")
    assert abs(gm[0, 1] - fd) <= 1e-5 * max(1.0, abs(fd)) and abs(fd) > 1e-3


def test_bilinear_rotate_gradient_has_kinks(camera):
    # Honest record of why rotate defaults to bicubic: with bilinear sampling the
    # loss is piecewise linear in the angle, so a coarse finite difference straddles kinks.
    rng = np.random.default_rng(11)
    x = Image(rng.random((32, 40)))  # rough texture: the slope changes at every kink
    wts = jnp.asarray(rng.standard_normal((32, 40)))

    def loss(a, method):
        return jnp.sum(rotate(x, angle_deg=a, method=method).data * wts)

    rel = {"bilinear": 0.0, "bicubic": 0.0}
    grad = jax.jit(jax.grad(loss), static_argnums=1)
    h = 3e-3
    for angle in 23.0 + 0.37 * np.arange(8):
        for method in rel:
            g = float(grad(jnp.asarray(angle), method))
            fd = float((loss(angle + h, method) - loss(angle - h, method)) / (2 * h))
            rel[method] = max(rel[method], abs(g - fd) / abs(fd))
    print(f"rotate d/dangle vs FD with step 3e-3 deg, worst relative gap over 8 angles: "
          f"bilinear {rel['bilinear']:.1e}, bicubic {rel['bicubic']:.1e}")
    assert rel["bicubic"] < 1e-4 < rel["bilinear"]


def test_vmap_batch_equals_per_image(camera, coins):
    xs = np.stack([camera[:40, :40], coins[:40, :40]])
    for op, kw in ((rotate, {"angle_deg": 20.0}), (translate, {"dx": 0.4, "dy": -1.2}),
                   (zoom, {"scale": 1.4}), (resize, {"shape": (30, 50)}), (mirror, {"axis": 0})):
        yb = np.asarray(jax.vmap(lambda d, op=op, kw=kw: op(Image(d), **kw).data)(jnp.asarray(xs)))
        for i in range(2):
            assert np.max(np.abs(yb[i] - np.asarray(op(Image(xs[i]), **kw).data))) < 1e-14


def test_float32(camera):
    x32 = Image(jnp.asarray(camera, dtype=jnp.float32))
    for op, kw in ((rotate, {"angle_deg": 31.0}), (translate, {"dx": 1.3}), (zoom, {"scale": 1.7}),
                   (resize, {"shape": (50, 70), "method": "bicubic"}), (shear, {"kx": 0.3})):
        y32 = op(x32, **kw).data
        y64 = op(Image(camera), **kw).data
        assert y32.dtype == jnp.float32
        d = float(jnp.max(jnp.abs(y32.astype(jnp.float64) - y64)))
        assert d < 1e-5, (op.__name__, d)


def test_bad_parameters():
    x = Image(jnp.full((8, 8), 0.5))
    with pytest.raises(ValueError, match="rotate.*'method'"):
        rotate(x, angle_deg=10.0, method="lanczos")
    with pytest.raises(ValueError, match="translate.*'mode'"):
        translate(x, dx=1.0, mode="edge")
    with pytest.raises(ValueError, match="rotate.*'angle_deg'"):
        rotate(x, angle_deg=float("nan"))
    with pytest.raises(ValueError, match="zoom.*'scale'"):
        zoom(x, scale=0.0)
    with pytest.raises(ValueError, match="shear.*'cubic_a'"):
        shear(x, kx=0.1, cubic_a=0.5)
    with pytest.raises(ValueError, match="mirror.*'axis'"):
        mirror(x, axis=2)
    with pytest.raises(ValueError, match="affine_warp.*'matrix'"):
        affine_warp(x, matrix=np.eye(2))
    with pytest.raises(ValueError, match="affine_warp.*'matrix'.*singular"):
        affine_warp(x, matrix=[[1.0, 2.0, 0.0], [2.0, 4.0, 0.0]], forward=True)
    with pytest.raises(ValueError, match="affine_warp.*'matrix'.*finite"):
        affine_warp(x, matrix=[[1.0, np.nan, 0.0], [0.0, 1.0, 0.0]])
    with pytest.raises(ValueError, match="resize.*'shape'"):
        resize(x, shape=(0, 4))
    with pytest.raises(TypeError, match="resize.*'shape'"):
        resize(x, shape=(4.5, 4))
    with pytest.raises(ValueError, match="resize.*'factor'"):
        resize(x, factor=-1.0)
    with pytest.raises(TypeError, match="rotate.*'img'"):
        rotate(np.zeros((8, 8)))
    with pytest.raises(ValueError, match="apply.*knob 'b'"):
        fsjax.apply(x, "rotate", a=0.5, b=0.5)


def test_traced_singular_forward_matrix_fails_closed():
    x = Image(jnp.full((6, 6), 0.5))
    sing = jnp.asarray([[1.0, 2.0, 0.0], [2.0, 4.0, 0.0]])
    out = jax.jit(lambda m: affine_warp(x, matrix=m, forward=True).data)(sing)
    assert not np.any(np.isfinite(np.asarray(out)))
