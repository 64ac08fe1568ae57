"""Volume crop, pad and resample: conformance with NumPy / SciPy, the physical frame, accuracy
against the nearest-voxel null, round trips, jit/vmap/grad, and refusals."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import ndimage as ndi

import fsjax


def _vol(dtype=jnp.float64, spacing=(1.0, 1.0, 1.0), shape=(9, 11, 13), seed=0):
    x = np.random.default_rng(seed).random(shape)
    return x, fsjax.Volume(jnp.asarray(x, dtype), spacing=spacing)


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
def test_resample_equals_scipy_map_coordinates(dtype):
    x, v = _vol(dtype, spacing=(2.0, 1.0, 0.5))
    for new in [(1.0, 0.7, 0.5), (3.0, 2.5, 1.1), (0.3, 1.0, 2.0)]:
        r = fsjax.ops.volume_resample(v, spacing=new)
        shp = tuple(int(np.floor((n - 1) * s / t + 1e-9)) + 1 for n, s, t in zip(x.shape, v.spacing, new))
        assert r.data.shape == shp and r.spacing == new
        grids = np.meshgrid(*[np.arange(m) * t / s for m, s, t in zip(shp, v.spacing, new)], indexing="ij")
        ref = ndi.map_coordinates(x, grids, order=1, mode="nearest")
        tol = 1e-12 if dtype == jnp.float64 else 2e-6
        np.testing.assert_allclose(np.asarray(r.data), ref, atol=tol, err_msg=str(new))


def test_resample_keeps_the_physical_frame_and_beats_nearest():
    # f(z, y, x) = sin(0.3 z) cos(0.2 y) + 0.1 x sampled on 1.5 x 1.0 x 0.8 mm voxels, resampled to
    # 1.1 x 0.9 x 1.3 mm: trilinear error against the analytic function at the new centres is
    # well below the nearest-voxel null's
    sp = (1.5, 1.0, 0.8)
    shp = (20, 24, 28)
    zz, yy, xx = np.meshgrid(*[np.arange(n) * s for n, s in zip(shp, sp)], indexing="ij")
    f = lambda z, y, x: np.sin(0.3 * z) * np.cos(0.2 * y) + 0.1 * x  # noqa: E731
    v = fsjax.Volume(jnp.asarray(f(zz, yy, xx)), spacing=sp)
    new = (1.1, 0.9, 1.3)
    errs = {}
    for order in (0, 1):
        r = fsjax.ops.volume_resample(v, spacing=new, order=order)
        z2, y2, x2 = np.meshgrid(*[np.arange(n) * s for n, s in zip(r.data.shape, new)], indexing="ij")
        errs[order] = float(np.max(np.abs(np.asarray(r.data) - f(z2, y2, x2))))
    print(f"resample max error: trilinear {errs[1]:.4f}, nearest (null) {errs[0]:.4f}")
    assert errs[1] < 0.05 and errs[1] < errs[0] / 4
    # the last new centre stays inside the old extent (no extrapolation) and one more would not
    for n, s, t, m in zip(shp, sp, new, r.data.shape):
        assert (m - 1) * t <= (n - 1) * s + 1e-9 and m * t > (n - 1) * s


def test_nearest_resampling_keeps_labels():
    lab = np.zeros((10, 10, 10))
    lab[2:5, 2:8, 3:9] = 3
    lab[6:9, 1:4, 1:4] = 7
    r = fsjax.ops.volume_resample(fsjax.Volume(jnp.asarray(lab)), spacing=(0.5, 0.5, 2.0), order=0)
    assert set(np.unique(np.asarray(r.data))) == {0.0, 3.0, 7.0}
    # the label-3 box spans 3 x 6 x 6 mm of voxel centres; at 0.5 x 0.5 x 2 mm it has
    # (3 / 0.5) x (6 / 0.5) x (6 / 2) voxels, give or take the half-voxel rounding at each face
    n3 = int(np.sum(np.asarray(r.data) == 3))
    assert 6 * 12 * 3 <= n3 <= 7 * 13 * 4


@pytest.mark.parametrize("mode, np_mode", [("constant", "constant"), ("nearest", "edge"), ("reflect", "symmetric"),
                                           ("mirror", "reflect"), ("wrap", "wrap")])
def test_pad_equals_numpy_and_crop_undoes_it(mode, np_mode):
    x, v = _vol(shape=(4, 5, 6))
    b, a = (2, 0, 3), (1, 4, 2)
    p = fsjax.ops.volume_pad(v, before=b, after=a, mode=mode)
    ref = np.pad(x, list(zip(b, a)), mode=np_mode)
    np.testing.assert_array_equal(np.asarray(p.data), ref)
    c = fsjax.ops.volume_crop(p, start=b, size=x.shape)
    np.testing.assert_array_equal(np.asarray(c.data), x)
    assert c.spacing == v.spacing


def test_crop_equals_slicing_jit_vmap_and_grad():
    x, v = _vol(spacing=(1.0, 2.0, 3.0))
    c = fsjax.ops.volume_crop(v, start=(1, 2, 3), size=(4, 5, 6))
    np.testing.assert_array_equal(np.asarray(c.data), x[1:5, 2:7, 3:9])
    assert c.spacing == (1.0, 2.0, 3.0)
    batch = fsjax.Volume(jnp.stack([v.data, 2 * v.data]), spacing=v.spacing)
    out = jax.jit(jax.vmap(lambda d: fsjax.ops.volume_resample(fsjax.Volume(d, spacing=v.spacing),
                                                                 spacing=1.5).data))(batch.data)
    one = fsjax.ops.volume_resample(v, spacing=1.5).data
    np.testing.assert_allclose(np.asarray(out[1]), 2 * np.asarray(one), atol=1e-12)

    def loss(d):
        r = fsjax.ops.volume_resample(fsjax.Volume(d, spacing=v.spacing), spacing=(0.7, 1.3, 2.2))
        return jnp.sum(r.data ** 2)

    g = jax.grad(loss)(v.data)
    d = np.random.default_rng(3).standard_normal(x.shape)
    eps = 1e-6
    fd = (loss(v.data + eps * d) - loss(v.data - eps * d)) / (2 * eps)
    assert abs(float(jnp.sum(g * d))) > 1e-2
    assert float(jnp.sum(g * d)) == pytest.approx(float(fd), rel=1e-6)


def test_refusals_name_the_op_and_argument():
    _, v = _vol(shape=(4, 5, 6))
    with pytest.raises(ValueError, match="volume_crop.*does not fit"):
        fsjax.ops.volume_crop(v, start=(1, 0, 0), size=(4, 1, 1))
    with pytest.raises(TypeError, match="volume_crop.*'size'"):
        fsjax.ops.volume_crop(v, size=(1.5, 1, 1))
    with pytest.raises(ValueError, match="volume_crop.*'start'"):
        fsjax.ops.volume_crop(v, start=(-1, 0, 0))
    with pytest.raises(ValueError, match="volume_pad.*'mode'"):
        fsjax.ops.volume_pad(v, mode="edge")
    with pytest.raises(ValueError, match="volume_pad.*4096"):
        fsjax.ops.volume_pad(v, before=5000)
    with pytest.raises(ValueError, match="volume_resample.*'spacing'"):
        fsjax.ops.volume_resample(v, spacing=(1.0, 0.0, 1.0))
    with pytest.raises(ValueError, match="volume_resample.*'spacing'"):
        fsjax.ops.volume_resample(v, spacing=float("nan"))
    with pytest.raises(ValueError, match="volume_resample.*'order'"):
        fsjax.ops.volume_resample(v, order=3)
    with pytest.raises(ValueError, match="volume_resample.*voxels"):
        fsjax.ops.volume_resample(v, spacing=1e-4)
