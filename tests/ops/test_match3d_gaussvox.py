"""Gaussians -> voxels (fsjax.ops.gaussians_to_volume): the footprint splat's mass, centroid and
second moments against the Gaussian's own, beside the nulls (no prefilter; the mean splatted as a
point), the footprint cap failing closed, float32; the grid cells of the gaussians row run in
tests/ops/test_match3d.py and tests/ops/test_match3d_fm.py."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fsjax
from fsjax.synth import rotation_zyx

ops = fsjax.ops


def _quat(R):
    """(w, x, y, z) of a rotation matrix (Shepperd's branch for a trace > -1, enough here)."""
    w = np.sqrt(1.0 + np.trace(R)) / 2.0
    return np.array([w, (R[2, 1] - R[1, 2]) / (4 * w), (R[0, 2] - R[2, 0]) / (4 * w), (R[1, 0] - R[0, 1]) / (4 * w)])


def _gauss(means, scales, quats, logit=2.0, dtype=np.float64, valid=None):
    means = np.atleast_2d(means)
    n = len(means)
    return fsjax.Gaussians(jnp.asarray(means, dtype), jnp.asarray(np.log(np.broadcast_to(scales, (n, 3))), dtype),
                           jnp.asarray(np.broadcast_to(quats, (n, 4)), dtype), jnp.full(n, logit, dtype),
                           jnp.ones((n, 1, 3), dtype), valid=None if valid is None else jnp.asarray(valid))


def _moments(v, spacing=(1.0, 1.0, 1.0)):
    """Mass, centroid (x, y, z) and second central moment (3x3) of a volume on the op's grid."""
    v = np.asarray(v, np.float64)
    k, i, j = np.mgrid[0:v.shape[0], 0:v.shape[1], 0:v.shape[2]]
    X = np.stack([j * spacing[2], i * spacing[1], k * spacing[0]], -1).reshape(-1, 3)
    w = v.ravel()
    m = (w[:, None] * X).sum(0) / w.sum()
    d = X - m
    return w.sum(), m, (w[:, None, None] * d[:, :, None] * d[:, None, :]).sum(0) / w.sum()


@pytest.mark.parametrize("dtype,tol_mass", [(np.float64, 1e-12), (np.float32, 2e-6)])
def test_thin_gaussian_mass_and_centroid_beat_the_unfiltered_splat(dtype, tol_mass):
    """A Gaussian thinner than a voxel (sigma 0.3, 0.3, 0.15) at 16 sub-voxel positions: the
    splat holds its weight (sigmoid(2) = 0.881) and its centroid is the mean within 4e-3 voxel
    (the EWA prefilter of 0.6 voxel; measured 2.3e-3). The null, the same splat without the
    prefilter, snaps the centroid towards the nearest voxel (measured 0.43 voxel)."""
    rng = np.random.default_rng(0)
    mus = 6.0 + rng.uniform(0, 1, (16, 3))
    qs = np.stack([_quat(rotation_zyx(a)) for a in rng.uniform(-180, 180, (16, 3))])
    batch = jax.tree_util.tree_map(lambda *a: jnp.stack(a), *[_gauss(m, (0.3, 0.3, 0.15), q, dtype=dtype)
                                                             for m, q in zip(mus, qs)])

    def run(pf):
        f = jax.jit(jax.vmap(lambda g: ops.gaussians_to_volume(g, shape=(14, 14, 14), prefilter=pf).data))
        vs = np.asarray(f(batch))
        assert vs.dtype == dtype
        mass = np.array([_moments(v)[0] for v in vs])
        err = np.array([np.abs(_moments(v)[1] - m).max() for v, m in zip(vs, mus)])
        return mass, err

    mass, err = run(0.6)
    w = 1.0 / (1.0 + np.exp(-2.0))
    print(f"\nthin Gaussian ({np.dtype(dtype).name}): centroid error max {err.max():.2e} voxel; mass error "
          f"{np.abs(mass - w).max():.1e}")
    np.testing.assert_allclose(mass, w, atol=tol_mass)
    assert err.max() < 4e-3
    if dtype == np.float64:  # the null (one dtype: the same program)
        mass0, err0 = run(0.0)
        print(f"no prefilter: centroid error max {err0.max():.3f} voxel")
        np.testing.assert_allclose(mass0, w, atol=tol_mass)  # the discrete normalisation holds the mass either way
        assert err0.max() > 0.05 and err.max() < err0.max() / 10


def test_anisotropic_second_moments_equal_the_covariance():
    """A turned Gaussian, scales (2, 1.2, 0.8): without prefilter, cut at 5 sigma, its splat's
    second central moment is Sigma to 1e-4 voxel^2 (measured 4.5e-5: aliasing and the cut) and its
    centroid is the mean (1.6e-6). With the defaults on a grid of spacing (dz, dy, dx) = (2, 1,
    0.5), it is Sigma + diag((0.6 dx)^2, (0.6 dy)^2, (0.6 dz)^2) to 0.3 % of Sigma's largest entry
    (measured 0.17 %; without the prefilter 0.87 %: the z axis samples it every 2 units).
    The null, the mean splatted as a point, has the moments of a trilinear stencil (< 0.25 per
    axis), nothing like Sigma."""
    R = rotation_zyx((30.0, -20.0, 50.0))
    s = np.array([2.0, 1.2, 0.8])
    S = R @ np.diag(s ** 2) @ R.T
    mu = np.array([10.3, 9.7, 12.2])
    g = _gauss(mu, s, _quat(R))
    w = 1.0 / (1.0 + np.exp(-2.0))
    m, c, M = _moments(ops.gaussians_to_volume(g, shape=(24, 24, 24), prefilter=0.0, radius_sigma=5.0,
                                               max_radius=11).data)
    assert abs(m - w) < 1e-12 and np.abs(c - mu).max() < 1e-5 and np.abs(M - S).max() < 1e-4
    sp = (2.0, 1.0, 0.5)
    F = np.diag((0.6 * np.array(sp[::-1])) ** 2)
    m, c, M = _moments(ops.gaussians_to_volume(g, shape=(12, 24, 48), spacing=sp, max_radius=17).data, sp)
    rel = np.abs(M - S - F).max() / np.abs(S).max()
    print(f"\nsecond moments on spacing {sp}: {rel:.2e} of |Sigma|; centroid {np.abs(c - mu).max():.1e}")
    assert abs(m - w) < 1e-12 and np.abs(c - mu).max() < 1e-3 and rel < 3e-3
    _, cp, Mp = _moments(ops.points_to_volume(fsjax.Points(jnp.asarray(mu[None])), shape=(24, 24, 24)).data)
    assert np.abs(cp - mu).max() < 1e-12 and np.abs(Mp - S).max() > 1.0


def test_footprint_cap_fails_closed_and_does_not_change_the_answer():
    """A footprint wider than the static window: eagerly a ValueError naming the radius needed,
    under jit a NaN volume (per member under vmap); inside the cap, the cap changes nothing."""
    g_small = _gauss([[7.2, 7.6, 6.9]], (0.7, 0.5, 0.9), _quat(rotation_zyx((10.0, 20.0, 30.0))))
    g_big = _gauss([[7.2, 7.6, 6.9]], (1.5, 0.5, 0.9), _quat(rotation_zyx((10.0, 20.0, 30.0))))
    with pytest.raises(ValueError, match=r"gaussians_to_volume: argument 'max_radius' \(4 voxels\).*max_radius >= 6"):
        ops.gaussians_to_volume(g_big, shape=(16, 16, 16))
    both = jax.tree_util.tree_map(lambda a, b: jnp.stack([a, b]), g_small, g_big)
    vb = jax.jit(jax.vmap(lambda g: ops.gaussians_to_volume(g, shape=(16, 16, 16)).data))(both)
    assert bool(jnp.all(jnp.isfinite(vb[0]))) and bool(jnp.all(jnp.isnan(vb[1])))
    wide = ops.gaussians_to_volume(g_small, shape=(16, 16, 16), max_radius=6).data
    np.testing.assert_allclose(np.asarray(vb[0]), np.asarray(wide), rtol=0, atol=1e-15)
    assert np.isfinite(np.asarray(ops.gaussians_to_volume(g_big, shape=(16, 16, 16), max_radius=6).data)).all()


def test_grid_border_invalid_slots_and_the_transforms():
    """The grid holds the part of a footprint inside it: a crop of a larger grid (origin moved)
    equals the splat onto the crop; invalid slots add nothing; to_voxel and to_points take
    Gaussians."""
    rng = np.random.default_rng(2)
    qs = np.stack([_quat(rotation_zyx(a)) for a in rng.uniform(-180, 180, (6, 3))])
    g = _gauss(rng.uniform(1.0, 10.0, (6, 3)), rng.uniform(0.3, 0.8, (6, 3)), qs,
               valid=[True, True, True, True, True, False])
    big = np.asarray(ops.gaussians_to_volume(g, shape=(12, 12, 12)).data)
    crop = ops.gaussians_to_volume(g, shape=(6, 7, 8), origin=(3.0, 2.0, 4.0))
    np.testing.assert_allclose(np.asarray(crop.data), big[4:10, 2:9, 3:11], rtol=0, atol=1e-15)
    assert float(crop.data.sum()) < big.sum() - 0.1
    moved = fsjax.Gaussians(g.means.at[5].set(6.0), g.log_scales.at[5].set(0.0), g.quats, g.opacity_logits.at[5].set(5.0),
                            g.colors, g.valid)  # the invalid slot, moved into the grid and made heavy
    assert bool(jnp.all(ops.gaussians_to_volume(moved, shape=(12, 12, 12)).data == big))
    v = ops.to_voxel(g, (1.0, 1.0, 1.0), shape=(12, 12, 12))
    assert v.spacing == (1.0, 1.0, 1.0) and bool(jnp.all(v.data == big))
    p = ops.to_points(g)
    assert p.valid.tolist() == [True] * 5 + [False] and bool(jnp.all(p.xyz == g.means))


def test_bad_arguments_name_the_op():
    g = _gauss([[1.0, 2.0, 3.0]], (0.5, 0.5, 0.5), (1.0, 0.0, 0.0, 0.0))
    for kw, arg in (({"radius_sigma": 0.0}, "radius_sigma"), ({"prefilter": -0.1}, "prefilter"),
                    ({"max_radius": -1}, "max_radius"), ({"spacing": (1.0, 0.0, 1.0)}, "spacing")):
        with pytest.raises(ValueError, match=f"gaussians_to_volume: argument '{arg}'"):
            ops.gaussians_to_volume(g, **kw)
    with pytest.raises(TypeError, match="gaussians_to_volume: argument 'g' must be Gaussians"):
        ops.gaussians_to_volume(fsjax.Points(jnp.zeros((2, 3))))
