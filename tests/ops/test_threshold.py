"""Thresholds: conformance with scikit-image / SciPy on camera and coins, nulls, failure modes.

Run with ``pytest -s`` to see the measured figures.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.ndimage as ndi

import fsjax
from fsjax.ops.image import _threshold as T

skimage = pytest.importorskip("skimage")
from skimage import data, img_as_float  # noqa: E402
from skimage import filters as skf  # noqa: E402

ops = fsjax.ops


@functools.cache
def _photo(name: str) -> np.ndarray:
    return img_as_float(getattr(data, name)()).astype(np.float64)


def _crop(name: str) -> np.ndarray:
    im = _photo(name)
    return im[100:228, 200:328] if name == "camera" else im[60:188, 100:228]


PHOTOS = ["camera", "coins"]


def _jit(op, **kw):
    return jax.jit(lambda x: op(x, **kw))


# ---------------------------------------------------------------------------
# Histogram convention
# ---------------------------------------------------------------------------


@pytest.mark.parametrize("name", PHOTOS)
def test_histogram_matches_numpy(name):
    im = _photo(name)
    h, c, ok = jax.jit(T._histogram, static_argnums=1)(jnp.asarray(im), 256)
    hn, e = np.histogram(im, 256, range=(im.min(), im.max()))
    dc = np.max(np.abs(np.asarray(c) - (e[:-1] + e[1:]) / 2))
    print(f"\nhistogram {name}: counts equal = {np.array_equal(np.asarray(h), hn)}, "
          f"max |centre diff| = {dc:.1e}")
    assert bool(ok)
    assert np.array_equal(np.asarray(h), hn)
    assert dc <= 1e-15


# ---------------------------------------------------------------------------
# Global levels vs scikit-image
# ---------------------------------------------------------------------------

LEVELS = [
    ("otsu_level", "otsu", skf.threshold_otsu),
    ("triangle_level", "triangle", skf.threshold_triangle),
    ("yen_level", "yen", skf.threshold_yen),
    ("li_level", "li", skf.threshold_li),
    ("isodata_level", "isodata", skf.threshold_isodata),
]


@pytest.mark.parametrize("name", PHOTOS)
@pytest.mark.parametrize("level_op,region_op,ref", LEVELS, ids=[t[0] for t in LEVELS])
def test_global_level_vs_skimage(level_op, region_op, ref, name):
    im = _photo(name)
    img = fsjax.Image(jnp.asarray(im))
    both = jax.jit(lambda x: (getattr(ops, level_op)(x).value, getattr(ops, region_op)(x).data))
    got, reg = both(img)
    got, reg = float(got), np.asarray(reg)
    want = float(ref(im))
    n_diff = int(np.sum(reg != (im > want)))
    print(f"\n{level_op} vs skimage.filters.{ref.__name__} on {name}: {got:.12f} vs {want:.12f}, "
          f"|diff| = {abs(got - want):.1e} (tol 1e-12); region pixels differing: {n_diff}")
    assert abs(got - want) <= 1e-12
    assert n_diff == 0


def test_otsu_level_float32():
    im = _photo("camera").astype(np.float32)
    got = _jit(ops.otsu_level)(fsjax.Image(jnp.asarray(im))).value
    want = skf.threshold_otsu(im)
    print(f"\notsu_level float32 camera: {float(got)!r} vs skimage {float(want)!r}")
    assert got.dtype == jnp.float32
    assert abs(float(got) - float(want)) <= 1e-6


@pytest.mark.parametrize("name,classes", [("camera", 3), ("coins", 3), ("camera", 4)])
def test_multi_otsu_vs_skimage(name, classes):
    im = _photo(name)
    img = fsjax.Image(jnp.asarray(im))
    got = np.asarray(jax.jit(lambda x: ops.multi_otsu_levels(x, classes=classes))(img))
    want = skf.threshold_multiotsu(im, classes=classes)
    d = float(np.max(np.abs(got - want)))
    lab = jax.jit(lambda x: ops.multi_otsu(x, classes=classes))(img)
    labels = np.asarray(lab.data)
    # our convention: label = 1 + #{t : x > t}; scikit-image's np.digitize uses x >= t
    agree = float(np.mean(labels == 1 + np.digitize(im, want)))
    print(f"\nmulti_otsu_levels(classes={classes}) vs skimage.filters.threshold_multiotsu on {name}: "
          f"{np.round(got, 6)} vs {np.round(want, 6)}, max |diff| = {d:.1e} (tol 1e-12); "
          f"labels agree with 1 + np.digitize on {100 * agree:.3f} % of pixels")
    assert d <= 1e-12
    assert np.array_equal(labels, 1 + np.digitize(im, got, right=True))
    assert int(lab.count) == classes and set(np.unique(labels)) == set(range(1, classes + 1))


def test_multi_otsu_two_classes_is_otsu():
    img = fsjax.Image(jnp.asarray(_photo("coins")))
    lab = jax.jit(lambda x: ops.multi_otsu(x, classes=2))(img)
    reg = _jit(ops.otsu)(img)
    assert np.array_equal(np.asarray(lab.data) == 2, np.asarray(reg.data))


def test_li_is_a_fixed_point_and_respects_tolerance():
    im = _photo("camera")
    img = fsjax.Image(jnp.asarray(im))
    t = float(_jit(ops.li_level)(img).value)
    u = im - im.min()
    fg = u > t - im.min()
    mf, mb = u[fg].mean(), u[~fg].mean()
    t_next = im.min() + (mb - mf) / (np.log(mb) - np.log(mf))
    tol = np.min(np.diff(np.unique(im))) / 2
    print(f"\nli_level camera: t = {t:.12f}, one more Li step moves it by {abs(t_next - t):.1e} "
          f"(stopping tolerance {tol:.1e})")
    assert abs(t_next - t) <= tol
    # an explicit coarse tolerance stops earlier, still near the optimum and like skimage
    t_coarse = float(_jit(ops.li_level, tolerance=0.05)(img).value)
    want = skf.threshold_li(im, tolerance=0.05)
    print(f"li_level(tolerance=0.05): {t_coarse:.12f} vs skimage {want:.12f}")
    assert abs(t_coarse - want) <= 1e-12


def test_li_fails_closed_without_convergence():
    img = fsjax.Image(jnp.asarray(_photo("camera")))
    capped, full, reg = jax.jit(lambda x: (ops.li_level(x, max_iter=1).value, ops.li_level(x).value,
                                           ops.li(x, max_iter=1).data))(img)
    capped, full = float(capped), float(full)
    print(f"\nli_level camera: max_iter=1 -> {capped}, max_iter=256 -> {full:.6f}")
    assert np.isnan(capped) and np.isfinite(full)
    assert not bool(reg.any())


# ---------------------------------------------------------------------------
# Local thresholds vs scikit-image / SciPy
# ---------------------------------------------------------------------------


def _agreement(name, ours, x, thr, tol=1e-9):
    """Fraction of agreeing pixels; every disagreement must sit within ``tol`` of ``thr``."""
    ref = x > thr
    bad = ours != ref
    margin = float(np.max(np.abs(x - thr)[bad])) if bad.any() else 0.0
    frac = float(np.mean(~bad))
    print(f"\n{name}: pixel agreement {100 * frac:.4f} % ({int(bad.sum())} differ, "
          f"all within {margin:.1e} of the reference threshold; tol {tol:.0e})")
    assert margin <= tol
    assert frac >= 0.9999
    return frac


@pytest.mark.parametrize("name", PHOTOS)
@pytest.mark.parametrize("radius,k", [(3, 0.2), (7, 0.5)])
def test_sauvola_vs_skimage(name, radius, k):
    x = _crop(name)
    r = 0.5 * (x.max() - x.min())
    ours = np.asarray(_jit(ops.sauvola, radius=radius, k=k, r=r, mode="mirror")(fsjax.Image(jnp.asarray(x))).data)
    thr = skf.threshold_sauvola(x, window_size=2 * radius + 1, k=k, r=r)
    _agreement(f"sauvola r={radius} k={k} vs skimage on {name} crop", ours, x, thr)


@pytest.mark.parametrize("name", PHOTOS)
@pytest.mark.parametrize("radius,k", [(3, 0.2), (7, -0.3)])
def test_niblack_vs_skimage(name, radius, k):
    x = _crop(name)
    ours = np.asarray(_jit(ops.niblack, radius=radius, k=k, mode="mirror")(fsjax.Image(jnp.asarray(x))).data)
    thr = skf.threshold_niblack(x, window_size=2 * radius + 1, k=k)
    _agreement(f"niblack r={radius} k={k} vs skimage on {name} crop", ours, x, thr)


@pytest.mark.parametrize("mode", ["reflect", "nearest", "wrap"])
def test_local_mean_vs_skimage(mode):
    x = _crop("camera")
    ours = np.asarray(_jit(ops.local_mean, radius=5, offset=0.02, mode=mode)(fsjax.Image(jnp.asarray(x))).data)
    thr = skf.threshold_local(x, 11, "mean", offset=0.02, mode=mode)
    _agreement(f"local_mean r=5 mode={mode} vs skimage.threshold_local", ours, x, thr)


@pytest.mark.parametrize("smoothing", ["mean", "gaussian"])
@pytest.mark.parametrize("light_dark", ["light", "dark", "equal", "not_equal"])
def test_dyn_threshold_vs_scipy(smoothing, light_dark):
    x = _crop("coins")
    r, off = 4, 0.03
    if smoothing == "mean":
        s = ndi.uniform_filter(x, 2 * r + 1, mode="reflect")
    else:  # sigma = r / 3 truncated at 3 sigma = r taps
        s = ndi.gaussian_filter(x, r / 3, mode="reflect", truncate=3.0)
    ref = {"light": x >= s + off, "dark": x <= s - off,
           "equal": (x >= s - off) & (x <= s + off)}.get(light_dark)
    if ref is None:
        ref = ~((x >= s - off) & (x <= s + off))
    ours = np.asarray(_jit(ops.dyn_threshold, offset=off, radius=r, smoothing=smoothing,
                           light_dark=light_dark)(fsjax.Image(jnp.asarray(x))).data)
    bad = ours != ref
    margin = float(np.max(np.abs(np.abs(x - s) - off)[bad])) if bad.any() else 0.0
    print(f"\ndyn_threshold {smoothing}/{light_dark} vs scipy: {int(bad.sum())} pixels differ "
          f"(all within {margin:.1e} of the decision boundary; tol 1e-9)")
    assert margin <= 1e-9 and bad.mean() <= 1e-4


def test_local_traced_radius_equals_concrete():
    """vmap over radius (static max support + masks) equals each concrete call exactly."""
    img = fsjax.Image(jnp.asarray(_crop("camera")[:64, :64]))
    radii = [1, 4, 12]
    for op, kw in ((ops.sauvola, {"k": 0.3}), (ops.dyn_threshold, {"smoothing": "gaussian"})):
        batched = jax.jit(jax.vmap(lambda r, op=op, kw=kw: op(img, radius=r, **kw).data))(
            jnp.asarray(radii, float))
        singles = jax.jit(lambda x, op=op, kw=kw: [op(x, radius=r, **kw).data for r in radii])(img)
        for i, r in enumerate(radii):
            assert np.array_equal(np.asarray(batched[i]), np.asarray(singles[i])), (op.__name__, r)


# ---------------------------------------------------------------------------
# Hysteresis and fixed band
# ---------------------------------------------------------------------------


def _hysteresis_ref(x, low, high, structure):
    lab, n = ndi.label(x > low, structure=structure)
    keep = np.zeros(n + 1, bool)
    keep[np.unique(lab[(x > high) & (lab > 0)])] = True
    keep[0] = False
    return keep[lab]


@pytest.mark.parametrize("low,high", [(0.3, 0.6), (0.5, 0.7), (0.2, 0.25)])
def test_hysteresis_vs_skimage(low, high):
    x = _crop("camera")
    img = fsjax.Image(jnp.asarray(x))
    four = np.asarray(_jit(ops.hysteresis, low=low, high=high, connectivity=4)(img).data)
    eight = np.asarray(_jit(ops.hysteresis, low=low, high=high)(img).data)
    sk = skf.apply_hysteresis_threshold(x, low, high)
    ref8 = _hysteresis_ref(x, low, high, np.ones((3, 3)))
    print(f"\nhysteresis ({low}, {high}) camera crop: 4-conn vs skimage differ in "
          f"{int((four != sk).sum())} px; 8-conn vs scipy-labelled reference differ in "
          f"{int((eight != ref8).sum())} px ({int(eight.sum())} vs {int(four.sum())} px selected)")
    assert np.array_equal(four, sk)
    assert np.array_equal(eight, ref8)


def test_hysteresis_high_below_low_is_plain_threshold():
    x = _crop("coins")
    out = np.asarray(_jit(ops.hysteresis, low=0.5, high=0.2)(fsjax.Image(jnp.asarray(x))).data)
    assert np.array_equal(out, x > 0.5)


def test_threshold_band_matches_numpy():
    x = _crop("coins")
    img = fsjax.Image(jnp.asarray(x))
    band = np.asarray(_jit(ops.threshold, lo=0.3, hi=0.6)(img).data)
    single = np.asarray(_jit(ops.threshold, lo=0.45)(img).data)
    assert np.array_equal(band, (x >= 0.3) & (x <= 0.6))
    assert np.array_equal(single, x >= 0.45)
    assert not bool(_jit(ops.threshold, lo=0.6, hi=0.3)(img).data.any())


# ---------------------------------------------------------------------------
# Nulls: local vs global under an illumination ramp; Otsu vs a fixed level
# ---------------------------------------------------------------------------


def _ink_page(seed=0, size=128):
    """Dark blobs ("ink", truth) on a light page under shading from 1.0 to 0.4 across columns."""
    rng = np.random.default_rng(seed)
    rr, cc = np.mgrid[0:size, 0:size].astype(float)
    ink = np.zeros((size, size), bool)
    for cy, cx in rng.uniform(8, size - 8, size=(30, 2)):
        ink |= (rr - cy) ** 2 + (cc - cx) ** 2 <= 4.0**2
    shade = 1.0 - 0.6 * cc / (size - 1)
    img = np.where(ink, 0.35, 0.7) * shade + 0.02 * rng.standard_normal((size, size))
    return np.clip(img, 0.0, 1.0), ink


def test_local_methods_beat_global_under_illumination_ramp():
    x, ink = _ink_page()
    img = fsjax.Image(jnp.asarray(x))
    page = ~ink  # every Region op marks the bright side

    def err(region):
        return float(np.mean(np.asarray(region.data) != page))

    rates = {name: err(_jit(getattr(ops, name))(img)) for name in ("otsu", "li", "yen", "triangle", "isodata")}
    rates["multi_otsu(3) > 1"] = float(np.mean((np.asarray(jax.jit(ops.multi_otsu)(img).data) > 1) != page))
    rates["sauvola"] = err(_jit(ops.sauvola, radius=10, k=0.2)(img))
    rates["niblack"] = err(_jit(ops.niblack, radius=10, k=0.2)(img))
    rates["local_mean"] = err(_jit(ops.local_mean, radius=10, offset=0.05)(img))
    dyn_ink = _jit(ops.dyn_threshold, offset=0.05, radius=10, light_dark="dark")(img)
    rates["dyn_threshold(dark) as ink"] = float(np.mean(np.asarray(dyn_ink.data) != ink))
    print(f"\npixel error rate, ink on a shaded page (ink = {100 * ink.mean():.1f} % of pixels):")
    for k, v in rates.items():
        print(f"  {k:28s} {100 * v:6.2f} %")
    for local in ("sauvola", "local_mean", "dyn_threshold(dark) as ink"):
        assert rates[local] < rates["otsu"]
        assert rates[local] < 0.02
    assert rates["otsu"] > 0.1  # the ramp really defeats the global method


def test_otsu_beats_fixed_level_on_shifted_histogram():
    rng = np.random.default_rng(3)
    truth = np.zeros((96, 96), bool)
    truth[20:60, 30:80] = True
    x = np.clip(np.where(truth, 0.3, 0.1) + 0.02 * rng.standard_normal(truth.shape), 0, 1)
    img = fsjax.Image(jnp.asarray(x))
    e_otsu = float(np.mean(np.asarray(_jit(ops.otsu)(img).data) != truth))
    e_fixed = float(np.mean(np.asarray(_jit(ops.threshold, lo=0.5)(img).data) != truth))
    print(f"\nshifted histogram (0.1 / 0.3): error otsu {100 * e_otsu:.2f} %, fixed 0.5 {100 * e_fixed:.2f} %")
    assert e_otsu < e_fixed
    assert e_otsu < 0.01


# ---------------------------------------------------------------------------
# Failing closed
# ---------------------------------------------------------------------------


def test_constant_image_fails_closed():
    img = fsjax.Image(jnp.full((16, 16), 0.4))
    lines = []
    allops = jax.jit(lambda x: [(getattr(ops, lo)(x).value, getattr(ops, ro)(x).data) for lo, ro, _ in LEVELS]
                     + [ops.multi_otsu(x), ops.multi_otsu_levels(x)])
    *pairs, lab, lv = allops(img)
    for (level_op, _, _), (lvl, reg) in zip(LEVELS, pairs, strict=True):
        lines.append(f"{level_op}={float(lvl)}")
        assert np.isnan(float(lvl))
        assert not bool(reg.any())
    lv = np.asarray(lv)
    print("\nconstant image: " + ", ".join(lines) + f", multi_otsu levels {lv}, count {int(lab.count)}"
          f" (skimage threshold_otsu returns the value itself: {skf.threshold_otsu(np.full((16, 16), 0.4))})")
    assert np.all(np.isnan(lv))
    assert int(lab.count) == 0 and not bool(lab.data.any())


def test_multi_otsu_too_few_grey_values_fails_closed():
    img = fsjax.Image(jnp.where(jnp.arange(64).reshape(8, 8) < 20, 0.2, 0.7))
    lab = jax.jit(lambda x: ops.multi_otsu(x, classes=3))(img)
    assert int(lab.count) == 0 and not bool(lab.data.any())
    with pytest.raises(ValueError):  # scikit-image refuses the same input
        skf.threshold_multiotsu(np.asarray(img.data), classes=3)
    two = jax.jit(lambda x: ops.multi_otsu(x, classes=2))(img)
    assert int(two.count) == 2


# ---------------------------------------------------------------------------
# Bad parameters
# ---------------------------------------------------------------------------

IMG = fsjax.Image(jnp.linspace(0.0, 1.0, 64).reshape(8, 8))


@pytest.mark.parametrize("call,op,arg,exc", [
    (lambda: ops.otsu(IMG, nbins=1), "otsu", "nbins", ValueError),
    (lambda: ops.otsu_level(IMG, nbins=2.5), "otsu_level", "nbins", TypeError),
    (lambda: ops.yen(IMG, nbins=1), "yen", "nbins", ValueError),
    (lambda: ops.multi_otsu(IMG, classes=5), "multi_otsu", "classes", ValueError),
    (lambda: jax.jit(lambda c: ops.multi_otsu(IMG, classes=c))(3), "multi_otsu", "classes", TypeError),
    (lambda: ops.multi_otsu(IMG, nbins=4096), "multi_otsu", "nbins", ValueError),
    (lambda: ops.li_level(IMG, tolerance=-1.0), "li_level", "tolerance", ValueError),
    (lambda: ops.li(IMG, max_iter=0), "li", "max_iter", ValueError),
    (lambda: ops.threshold(IMG, lo=float("nan")), "threshold", "lo", ValueError),
    (lambda: ops.local_mean(IMG, radius=2.5), "local_mean", "radius", ValueError),
    (lambda: ops.local_mean(IMG, radius=0), "local_mean", "radius", ValueError),
    (lambda: ops.local_mean(IMG, mode="bogus"), "local_mean", "mode", ValueError),
    (lambda: ops.sauvola(IMG, r=0.0), "sauvola", "r", ValueError),
    (lambda: ops.sauvola(IMG, k=-0.1), "sauvola", "k", ValueError),
    (lambda: ops.niblack(IMG, k=float("inf")), "niblack", "k", ValueError),
    (lambda: ops.dyn_threshold(IMG, light_dark="up"), "dyn_threshold", "light_dark", ValueError),
    (lambda: ops.dyn_threshold(IMG, smoothing="median"), "dyn_threshold", "smoothing", ValueError),
    (lambda: ops.dyn_threshold(IMG, offset=-0.1), "dyn_threshold", "offset", ValueError),
    (lambda: ops.hysteresis(IMG, connectivity=6), "hysteresis", "connectivity", ValueError),
    (lambda: ops.hysteresis(IMG, low=float("nan")), "hysteresis", "low", ValueError),
])
def test_bad_parameters_raise(call, op, arg, exc):
    with pytest.raises(exc) as e:
        call()
    msg = str(e.value)
    assert op in msg and repr(arg) in msg, msg


def test_wrong_sort_raises():
    with pytest.raises(TypeError, match="otsu"):
        ops.otsu(fsjax.Region(jnp.zeros((4, 4), bool)))


def test_traced_radius_above_support_fails_closed():
    """Issue 20 item 3 sweep: local thresholds clipped a traced radius into [1, max_radius] and
    returned the Region of the clamped window (radius 30 gave radius 25's answer). Now a traced
    radius outside its support (or not an integer) raises at run time (a Region cannot carry
    NaN), the concrete radius is bounded by the image, and the support by the image's side."""
    img = fsjax.Image(jnp.asarray(np.random.default_rng(0).random((40, 48)), jnp.float32))
    f = jax.jit(lambda r: fsjax.ops.local_mean(img, radius=r).data)
    assert bool(jnp.array_equal(f(jnp.float32(3.0)), fsjax.ops.local_mean(img, radius=3).data))  # the null
    with pytest.raises(Exception, match="out of range"):
        jax.block_until_ready(f(jnp.float32(30.0)))
    with pytest.raises(Exception, match="out of range"):
        jax.block_until_ready(f(jnp.float32(2.5)))
    with pytest.raises(ValueError, match="local_mean.*'radius'.*bound"):
        fsjax.ops.local_mean(img, radius=10 ** 6)


def test_traced_nan_band_limit_fails_closed():
    """Issue 20 sweep, second pass (tools/sweep_traced_params.py): ``threshold`` refuses a NaN
    ``lo``/``hi`` eagerly, but a traced NaN gave an empty Region (every comparison false); a
    Region cannot carry NaN, so the call now raises at run time. In range it equals eager."""
    img = fsjax.Image(jnp.arange(16.0).reshape(4, 4) / 15)
    f = jax.jit(lambda lo: fsjax.ops.threshold(img, lo=lo, hi=10 / 15).data)
    assert int(f(5 / 15).sum()) == 6
    with pytest.raises(Exception, match="out of range"):
        jax.block_until_ready(f(jnp.nan))
