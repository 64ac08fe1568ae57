"""3-D filters (gaussian3d, box3d, median3d, sobel3d, log3d): conformance with
scipy.ndimage in float64 on an anisotropic random volume, float32, traced knobs,
jit/vmap, bad input. One volume shape throughout (compilations are reused)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.ndimage as ndi

import fsjax
from fsjax import Volume
from fsjax.ops import box3d, gaussian3d, log3d, median3d, sobel3d
from fsjax.ops.volume._filters3d import footprint_mask

SP = (2.0, 1.0, 0.5)
SHAPE = (12, 16, 20)


@pytest.fixture(scope="module")
def x():
    rng = np.random.default_rng(7)
    # random texture plus a smooth blob: both high and low frequencies
    z, y, xx = np.mgrid[0:SHAPE[0], 0:SHAPE[1], 0:SHAPE[2]].astype(float)
    blob = np.exp(-(((z - 5) * 2) ** 2 + (y - 8) ** 2 + ((xx - 9) * 0.5) ** 2) / 20)
    return 0.3 * rng.random(SHAPE) + 0.7 * blob


def _maxdiff(a, b):
    return float(np.max(np.abs(np.asarray(a, np.float64) - np.asarray(b, np.float64))))


def _ref(name, x, mode, sigma=1.5):
    s = tuple(sigma / d for d in SP)
    if name == "gaussian3d":
        return ndi.gaussian_filter(x, s, mode=mode)
    if name == "log3d":
        return sum(ndi.gaussian_filter(x, s, order=[2 * (a == b) for b in range(3)], mode=mode) / SP[a] ** 2
                   for a in range(3))
    if name == "box3d":
        return ndi.uniform_filter(x, 4, mode=mode)
    if name == "sobel3d":
        return np.sqrt(sum((ndi.sobel(x, axis=a, mode=mode) / (32 * SP[a])) ** 2 for a in range(3)))
    raise KeyError(name)


def _ours(name, v, mode, sigma=1.5):
    if name == "box3d":
        return box3d(v, size=4, mode=mode)
    if name == "sobel3d":
        return sobel3d(v, mode=mode)
    return getattr(fsjax.ops, name)(v, sigma=sigma, mode=mode)


@pytest.mark.parametrize("mode", ["reflect", "constant"])
@pytest.mark.parametrize("name", ["gaussian3d", "log3d", "box3d", "sobel3d"])
def test_linear_filters_match_scipy(x, name, mode):
    got = _ours(name, Volume(jnp.asarray(x), spacing=SP), mode)
    assert got.spacing == SP
    ref = _ref(name, x, mode)
    scale = max(1.0, float(np.abs(ref).max()))
    d = _maxdiff(got.data, ref)
    print(f"\n{name} {mode}: max |fsjax - scipy| = {d:.2e} (scale {scale:.2g})")
    assert d < 1e-12 * scale


@pytest.mark.parametrize("mode", ["mirror", "nearest", "wrap"])
def test_gaussian_other_modes(x, mode):
    got = gaussian3d(Volume(jnp.asarray(x), spacing=SP), sigma=1.5, mode=mode)
    assert _maxdiff(got.data, _ref("gaussian3d", x, mode)) < 1e-12


def test_gaussian_unit_spacing_is_scipy_isotropic(x):
    got = gaussian3d(Volume(jnp.asarray(x)), sigma=1.2)
    assert _maxdiff(got.data, ndi.gaussian_filter(x, 1.2)) < 1e-12
    lap = log3d(Volume(jnp.asarray(x)), sigma=1.2)
    assert _maxdiff(lap.data, ndi.gaussian_laplace(x, 1.2)) < 1e-12


@pytest.mark.parametrize("footprint", ["cube", "ball"])
def test_median_matches_scipy(x, footprint):
    v = Volume(jnp.asarray(x), spacing=SP)
    for mode in ("reflect", "nearest"):
        got = median3d(v, radius=1, footprint=footprint, mode=mode)
        ref = ndi.median_filter(x, footprint=footprint_mask(1, footprint), mode=mode)
        assert _maxdiff(got.data, ref) == 0.0


def test_median_radius2_ball_matches_scipy(x):
    got = median3d(Volume(jnp.asarray(x)), radius=2, footprint="ball")
    ref = ndi.median_filter(x, footprint=footprint_mask(2, "ball"), mode="reflect")
    assert footprint_mask(2, "ball").sum() == 33
    assert _maxdiff(got.data, ref) == 0.0


def test_float32(x):
    x32 = jnp.asarray(x, jnp.float32)
    v = Volume(x32, spacing=SP)
    for name in ("gaussian3d", "log3d", "box3d", "sobel3d"):
        got = _ours(name, v, "reflect")
        assert got.data.dtype == jnp.float32, name
        ref = _ref(name, x, "reflect")
        assert _maxdiff(got.data, ref) < 2e-6 * max(1.0, float(np.abs(ref).max())), name
    med = median3d(v)
    assert med.data.dtype == jnp.float32
    assert _maxdiff(med.data, ndi.median_filter(np.asarray(x32), size=3)) == 0.0


def test_traced_sigma_equals_concrete_and_fails_closed(x):
    v = Volume(jnp.asarray(x), spacing=SP)
    sig = jnp.asarray([0.7, 1.5, 3.0])
    out = jax.jit(jax.vmap(lambda s: gaussian3d(v, sigma=s, max_sigma=4.0).data))(sig)
    for i, s in enumerate([0.7, 1.5, 3.0]):
        assert _maxdiff(out[i], ndi.gaussian_filter(x, tuple(s / d for d in SP))) < 1e-12
    bad = jax.jit(lambda s: gaussian3d(v, sigma=s, max_sigma=1.0).data)(3.0)
    assert bool(jnp.all(jnp.isnan(bad)))
    sizes = jnp.asarray([1.0, 3.0, 4.0])
    ob = jax.jit(jax.vmap(lambda s: box3d(v, size=s, max_size=5).data))(sizes)
    for i, s in enumerate([1, 3, 4]):
        assert _maxdiff(ob[i], ndi.uniform_filter(x, s)) < 1e-12


def test_vmap_over_batch_equals_single(x):
    xs = jnp.stack([jnp.asarray(x), jnp.asarray(x[::-1].copy())])
    f = jax.jit(jax.vmap(lambda d: median3d(Volume(d, spacing=SP)).data))
    got = f(xs)
    assert _maxdiff(got[1], ndi.median_filter(x[::-1], size=3)) == 0.0
    g = jax.jit(jax.vmap(lambda d: sobel3d(Volume(d, spacing=SP)).data))(xs)
    assert _maxdiff(g[1], _ref("sobel3d", x[::-1].copy(), "reflect")) < 1e-12


def test_bad_input_names_op_and_argument(x):
    v = Volume(jnp.asarray(x))
    with pytest.raises(ValueError, match="gaussian3d: argument 'sigma'"):
        gaussian3d(v, sigma=-1.0)
    with pytest.raises(ValueError, match="gaussian3d: argument 'mode'"):
        gaussian3d(v, mode="bogus")
    with pytest.raises(ValueError, match="gaussian3d: argument 'sigma'.*bound"):
        gaussian3d(v, sigma=1000.0)
    with pytest.raises(ValueError, match="median3d: argument 'radius'"):
        median3d(v, radius=3)
    with pytest.raises(ValueError, match="median3d: argument 'footprint'"):
        median3d(v, footprint="sphere")
    with pytest.raises(ValueError, match="box3d: argument 'size'"):
        box3d(v, size=0)
    with pytest.raises(ValueError, match="log3d: argument 'sigma'"):
        log3d(v, sigma=0.0)
    with pytest.raises(TypeError, match="sobel3d"):
        sobel3d(fsjax.Image(jnp.zeros((4, 4))))
