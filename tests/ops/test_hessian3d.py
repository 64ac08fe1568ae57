"""Hessian 3-D filters: the Hessian against scipy.ndimage, vesselness and blobness selectivity
beside the Laplacian-of-Gaussian null."""

import jax.numpy as jnp
import numpy as np
import pytest

import fsjax
from fsjax.ops.volume._filters3d import _sigma_voxels
from fsjax.ops.volume._hessian3d import hessian3d_core


def test_hessian_equals_scipy_gaussian_derivatives():
    ndi = pytest.importorskip("scipy.ndimage")
    sp = (2.0, 1.0, 0.5)
    x = np.random.default_rng(0).random((10, 12, 14))
    sig, radii = _sigma_voxels("t", 1.5, sp, 4.0, 8.0)
    h = hessian3d_core(jnp.asarray(x), sig, radii, 4.0, "reflect", sp)
    err = 0.0
    for a in range(3):
        for b in range(a, 3):
            order = [0, 0, 0]
            order[a] += 1
            order[b] += 1
            ref = ndi.gaussian_filter(x, np.asarray(sig), order=order, mode="reflect", truncate=4.0) / (sp[a] * sp[b])
            err = max(err, float(np.abs(np.asarray(h[(a, b)]) - ref).max()))
    print(f"Hessian (6 entries, spacing {sp}) vs scipy.ndimage.gaussian_filter(order=...): max |diff| {err:.1e}")
    assert err < 1e-12


def _scene(sign=1.0):
    z, y, x = np.mgrid[:24, :24, :32].astype(float)
    tube = np.exp(-((z - 7) ** 2 + (y - 7) ** 2) / 8.0)
    ball = np.exp(-((z - 16) ** 2 + (y - 16) ** 2 + (x - 16) ** 2) / 8.0)
    return fsjax.Volume(jnp.asarray(0.5 + sign * 0.4 * (tube + ball)))


def test_vesselness_and_blobness_select_their_shapes_where_log_does_not():
    vol = _scene()
    v = np.asarray(fsjax.ops.vesselness3d(vol, sigma=2.0).data)
    b = np.asarray(fsjax.ops.blobness3d(vol, sigma=2.0).data)
    lg = np.abs(np.asarray(fsjax.ops.log3d(vol, sigma=2.0).data))
    tube_c, ball_c = (7, 7, 16), (16, 16, 16)
    print(f"tube axis / ball centre: vesselness {v[tube_c]:.3f} / {v[ball_c]:.3f}, blobness {b[tube_c]:.2e} / "
          f"{b[ball_c]:.3f}, |LoG| (null) {lg[tube_c]:.4f} / {lg[ball_c]:.4f}")
    assert v[tube_c] > 5 * v[ball_c] and b[ball_c] > 100 * b[tube_c]
    # the null responds to both shapes within a factor 2: it cannot tell a tube from a ball
    assert 0.5 < lg[tube_c] / lg[ball_c] < 2.0
    assert v.min() >= 0 and v.max() <= 1 and b.min() >= 0 and b.max() <= 1
    # dark structures: only with bright=False
    dark = _scene(-1.0)
    assert float(fsjax.ops.vesselness3d(dark, sigma=2.0).data[tube_c]) == 0.0
    assert float(fsjax.ops.vesselness3d(dark, sigma=2.0, bright=False).data[tube_c]) == pytest.approx(v[tube_c], rel=1e-4)


def test_flat_volume_and_errors():
    flat = fsjax.Volume(jnp.full((6, 7, 8), 0.3))
    assert float(jnp.max(fsjax.ops.vesselness3d(flat).data)) == 0.0
    assert not bool(jnp.any(jnp.isnan(fsjax.ops.blobness3d(flat).data)))
    with pytest.raises(ValueError, match="vesselness3d: argument 'alpha'"):
        fsjax.ops.vesselness3d(flat, alpha=0.0)
    with pytest.raises(TypeError, match="blobness3d: argument 'bright'"):
        fsjax.ops.blobness3d(flat, bright="yes")
    with pytest.raises(ValueError, match="vesselness3d: argument 'sigma'"):
        fsjax.ops.vesselness3d(flat, sigma=-1.0)
