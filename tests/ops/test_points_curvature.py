"""Curvature from local quadric fits, on absolute scale (analytic spheres, cylinders, saddles)."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

import fsjax
from fsjax.types import PointValues


def fib_sphere(n, r=1.0):
    i = np.arange(n) + 0.5
    phi, th = np.arccos(1 - 2 * i / n), np.pi * (1 + 5 ** 0.5) * i
    u = np.c_[np.cos(th) * np.sin(phi), np.sin(th) * np.sin(phi), np.cos(phi)]
    return r * u, u


@pytest.mark.parametrize("radius", [0.25, 4.0])
def test_sphere_absolute_scale(radius):
    xyz, _ = fib_sphere(1500, radius)
    cv = fsjax.ops.curvature(fsjax.Points(jnp.asarray(xyz)), k=16)
    assert isinstance(cv, PointValues)
    c = np.asarray(cv["curvedness"]) * radius
    k1, k2 = np.asarray(cv["k1"]) * radius, np.asarray(cv["k2"]) * radius
    si = np.asarray(cv["shape_index"])
    print(f"sphere R={radius}: curvedness*R median {np.median(c):.4f} (max dev {np.max(np.abs(c - 1)):.4f}); "
          f"k1*R, k2*R medians {np.median(k1):.4f}, {np.median(k2):.4f}; shape index min {si.min():.4f}")
    assert np.max(np.abs(c - 1)) < 0.02
    assert np.max(np.abs(k1 - 1)) < 0.02 and np.max(np.abs(k2 - 1)) < 0.02
    assert np.all(si > 0.99)
    H, K = np.asarray(cv["mean"]) * radius, np.asarray(cv["gaussian"]) * radius ** 2
    assert np.max(np.abs(H - 1)) < 0.02 and np.max(np.abs(K - 1)) < 0.04


def test_concave_sphere_and_shape_index_exact_at_umbilic():
    xyz, u = fib_sphere(1500, 1.0)
    inward = fsjax.Points(jnp.asarray(xyz), normals=jnp.asarray(-u))
    si = np.asarray(fsjax.ops.curvature(inward, k=16)["shape_index"])
    assert np.all(si < -0.99)
    # the atan2 form is exact at an umbilic (k1 == k2): no 0/0
    k = jnp.array(0.7)
    assert float((2 / jnp.pi) * jnp.arctan2(k + k, k - k)) == 1.0


def test_cylinder_and_saddle_shape_index():
    rng = np.random.default_rng(0)
    th, z = rng.uniform(0, 2 * np.pi, 3000), rng.uniform(-2, 2, 3000)
    r = 0.5
    cyl = np.c_[r * np.cos(th), r * np.sin(th), z]
    nrm = np.c_[np.cos(th), np.sin(th), 0 * z]
    cv = fsjax.ops.curvature(fsjax.Points(jnp.asarray(cyl), normals=jnp.asarray(nrm)), k=16)
    m = np.abs(z) < 1.5
    si, k1, k2 = (np.asarray(cv[c])[m] for c in ("shape_index", "k1", "k2"))
    print(f"cylinder r=0.5: shape index median {np.median(si):.4f}, k1 median {np.median(k1):.4f} (truth 2), "
          f"k2 median {np.median(k2):.4f} (truth 0)")
    assert abs(np.median(si) - 0.5) < 0.01 and abs(np.median(k1) - 2.0) < 0.04 and abs(np.median(k2)) < 0.04
    g = rng.uniform(-1, 1, (3000, 2))
    sad = np.c_[g, 0.5 * (g[:, 0] ** 2 - g[:, 1] ** 2)]
    up = np.tile([0.0, 0.0, 1.0], (3000, 1))
    cs = fsjax.ops.curvature(fsjax.Points(jnp.asarray(sad), normals=jnp.asarray(up)), k=24)
    c = np.sum(g ** 2, 1) < 0.05
    si_s = np.asarray(cs["shape_index"])[c]
    print(f"saddle z=(x^2-y^2)/2 near the origin: shape index max |S| {np.max(np.abs(si_s)):.4f} (truth 0), "
          f"k1 {np.median(np.asarray(cs['k1'])[c]):.3f} (truth ~1)")
    assert np.max(np.abs(si_s)) < 0.02


def test_degenerate_and_invalid():
    xyz, _ = fib_sphere(300, 1.0)
    valid = np.ones(300, bool)
    valid[:10] = False
    cv = fsjax.ops.curvature(fsjax.Points(jnp.asarray(xyz), valid=jnp.asarray(valid)), k=12)
    v = np.asarray(cv.values)
    assert np.all(np.isnan(v[:10])) and np.all(np.isfinite(v[10:]))
    assert np.array_equal(np.asarray(cv.valid), valid)   # the cloud's mask where every fit is posed
    # collinear points: no surface, NaN rather than a plausible curvature
    line = np.c_[np.linspace(0, 1, 30), np.zeros(30), np.zeros(30)]
    cl = fsjax.ops.curvature(fsjax.Points(jnp.asarray(line)), k=8)
    assert bool(jnp.all(jnp.isnan(cl.values))) and not bool(jnp.any(cl.valid))   # flagged, not only NaN
    with pytest.raises(ValueError, match="curvature.*'k'"):
        fsjax.ops.curvature(fsjax.Points(jnp.asarray(xyz)), k=3)
    with pytest.raises(KeyError, match="no column"):
        cv["nope"]
