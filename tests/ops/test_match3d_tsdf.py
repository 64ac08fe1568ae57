"""depth -> TSDF (fsjax.ops.depth_to_tsdf): the signed distance along the camera's rays against an
analytic sphere and a plane (ray casting gives the depth map and the truth), beside the null
(tsdf_fuse's nearest pixel and depth difference), failing closed where the rays meet nothing."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fsjax

ops = fsjax.ops
W, F, C = 97, 60.0, 48.0  # the camera: 97 px square, focal 60 px, at the origin looking along +z
SPH_C, SPH_R = np.array([0.7, -0.4, 10.0]), 3.0
TR, SP, SHAPE = 1.0, 0.25, (24, 40, 40)
ORIGIN = (SPH_C[0] - 5, SPH_C[1] - 5, 6.0)


def _rays_hit(dirs, kind):
    """Distance along unit rays ``dirs`` from the origin to the first hit (NaN: none)."""
    if kind == "sphere":
        b = dirs @ SPH_C
        disc = b * b - (SPH_C @ SPH_C - SPH_R ** 2)
        return np.where(disc >= 0, b - np.sqrt(np.maximum(disc, 0.0)), np.nan), disc
    nrm = np.array([0.3, -0.2, 1.0]) / np.linalg.norm([0.3, -0.2, 1.0])  # the plane n . x = 8.5, tilted
    den = dirs @ nrm
    return np.where(den > 0, 8.5 / np.where(den > 0, den, 1.0), np.nan), np.full(dirs.shape[:-1], 10.0)


def _scene(kind, dtype=np.float64):
    cam = fsjax.Camera.from_intrinsics(F, F, C, C, width=W, height=W)
    u, v = np.meshgrid(np.arange(W * 1.0), np.arange(W * 1.0))
    ray = np.stack([(u - C) / F, (v - C) / F, np.ones_like(u)], -1)
    ray = ray / np.linalg.norm(ray, axis=-1, keepdims=True)
    z = np.nan_to_num(_rays_hit(ray, kind)[0] * ray[..., 2], nan=0.0)
    cam = jax.tree.map(lambda a: a.astype(dtype) if hasattr(a, "dtype") and a.dtype.kind == "f" else a, cam)
    return fsjax.Depth(jnp.asarray(z, dtype), cam)


def _truth(kind):
    k, i, j = np.mgrid[0:SHAPE[0], 0:SHAPE[1], 0:SHAPE[2]]
    P = np.stack([ORIGIN[0] + j * SP, ORIGIN[1] + i * SP, ORIGIN[2] + k * SP], -1)
    d = np.linalg.norm(P, axis=-1)
    th, disc = _rays_hit(P / d[..., None], kind)
    # voxels within the truncation of the surface along their ray, away from the sphere's silhouette
    # (there a pixel next to the voxel's image has no return and the voxel is refused, below)
    u, v = C + F * P[..., 0] / P[..., 2], C + F * P[..., 1] / P[..., 2]
    m = np.isfinite(th) & (np.abs(d - th) < TR) & (disc > 1.5) & (np.minimum(u, v) > 1) & (np.maximum(u, v) < W - 2)
    return np.clip((d - th) / TR, -1, 1), m


@pytest.mark.parametrize("kind", ["sphere", "plane"])
def test_depth_to_tsdf_is_the_distance_along_the_rays(kind):
    """Within the truncation the value is the ray distance to the surface over the truncation: sphere
    max 0.015 (mean 0.003) of the truncation, 10x below the null (tsdf_fuse's nearest pixel and depth
    difference: max 0.16, mean 0.026); tilted plane max 0.0002 (null max 0.31, mean 0.049). The
    sphere's error is the bilinear interpolation of its depth across a pixel."""
    want, m = _truth(kind)
    d = _scene(kind)
    got = np.asarray(ops.depth_to_tsdf(d, shape=SHAPE, spacing=(SP,) * 3, origin=ORIGIN, truncation=TR).data)
    ds = fsjax.DepthStack(d.z[None], jax.tree.map(lambda a: a[None], d.camera))
    null = np.asarray(ops.tsdf_fuse(ds, shape=SHAPE, spacing=(SP,) * 3, origin=ORIGIN, truncation=TR).data)
    e, e0 = np.abs(got - want)[m], np.abs(null - want)[m]
    print(f"\n{kind}: {m.sum()} voxels, error max {e.max():.4f} mean {e.mean():.4f}; null max {e0.max():.4f} "
          f"mean {e0.mean():.4f}")
    assert m.sum() > 1000
    assert e.max() < 0.02 and e.mean() < 0.005
    assert e0.mean() > 5 * e.mean()
    # in front: negative; occluded (more than the truncation behind): +1; the zero crossing is the surface
    assert np.all(got[m & (want < -0.5)] < 0) and np.all(got[m & (want > 0.5)] > 0)


def test_depth_to_tsdf_float32():
    want, m = _truth("sphere")
    got = ops.depth_to_tsdf(_scene("sphere", np.float32), shape=SHAPE, spacing=(SP,) * 3, origin=ORIGIN,
                            truncation=TR)
    assert got.data.dtype == jnp.float32
    assert np.abs(np.asarray(got.data) - want)[m].max() < 0.02


def test_depth_to_tsdf_fails_closed_and_checks_arguments():
    """No return anywhere: every voxel in view is empty (-1; carve) or no data (-inf without carving and
    filling); at the sphere's silhouette a voxel whose image has a pixel without return is refused as
    empty, not interpolated towards 0; bad arguments name the op."""
    d = _scene("sphere")
    empty = fsjax.Depth(jnp.zeros_like(d.z), d.camera)
    v = ops.depth_to_tsdf(empty, shape=(4, 4, 4), origin=(0.0, 0.0, 5.0))
    assert float(jnp.max(v.data)) == -1.0
    v = ops.depth_to_tsdf(empty, shape=(4, 4, 4), origin=(0.0, 0.0, 5.0), carve=False, fill_holes=False)
    assert bool(jnp.all(jnp.isneginf(v.data)))
    nan = fsjax.Depth(jnp.full_like(d.z, jnp.nan), d.camera)
    assert float(jnp.max(ops.depth_to_tsdf(nan, shape=(4, 4, 4), origin=(0.0, 0.0, 5.0)).data)) == -1.0
    # behind the camera / out of the image: -1 (fill_holes) or -inf
    v = ops.depth_to_tsdf(d, shape=(2, 2, 2), origin=(100.0, 0.0, -5.0), fill_holes=False)
    assert bool(jnp.all(jnp.isneginf(v.data)))
    with pytest.raises(ValueError, match="depth_to_tsdf: argument 'truncation'"):
        ops.depth_to_tsdf(d, truncation=0.0)
    with pytest.raises(TypeError, match="depth_to_tsdf: argument 'depth' must be"):
        ops.depth_to_tsdf(fsjax.DepthStack(d.z[None], jax.tree.map(lambda a: a[None], d.camera)))
    with pytest.raises(ValueError, match="depth_to_tsdf: argument 'depth' .*jax.vmap"):
        ops.depth_to_tsdf(fsjax.Depth(d.z[None], d.camera))
