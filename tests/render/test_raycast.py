"""Tests of ray-mesh intersection, parallel shadow rays and sun penumbrae (fsjax.render.raycast)."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import programs_built

import fsjax
from fsjax.render import intersect, occluded_parallel, rasterize, sun_directions, sun_visibility
from fsjax.synth._pool import icosphere


def _blob(sub=2):
    V, F = icosphere(sub)
    V = V * np.asarray([1.0, 0.7, 1.2]) + 0.15 * np.sin(3 * V[:, [1, 2, 0]])
    return fsjax.Mesh(jnp.asarray(V), jnp.asarray(F))


def test_intersect_agrees_with_rasteriser():
    m = _blob()
    K = fsjax.render.intrinsics_from_fov(24, 20, fov_x_deg=50.0)
    R, t = fsjax.render.look_at(jnp.asarray([1.0, -1.2, -3.0]), jnp.zeros(3))
    cam = fsjax.Camera(K, width=24, height=20, R=R, t=t)
    r = rasterize(m, cam, tile=8, capacity=512)
    o, d = fsjax.render.pixel_rays(cam)
    h = intersect(m, o.reshape(-1, 3), d.reshape(-1, 3), chunk=100)
    z = (h.s * (d.reshape(-1, 3) @ cam.R[:, 2])).reshape(20, 24)
    same = np.asarray(h.face_id.reshape(20, 24) == r.face_id)
    err = float(jnp.max(jnp.abs(jnp.where(h.hit.reshape(20, 24), z, 0.0) - r.depth)))
    print(f"Moller-Trumbore vs rasteriser: {same.mean() * 100:.1f} % same face, max depth diff {err:.1e}")
    assert same.all() and err < 1e-12


def test_occluded_parallel_matches_bruteforce_and_flags_overflow():
    m = _blob()
    rng = np.random.default_rng(0)
    P = jnp.asarray(rng.normal(size=(400, 3)) * 1.4)
    d = jnp.asarray([0.3, -0.5, 0.8])
    ref = intersect(m, P, jnp.broadcast_to(d, P.shape), s_min=1e-9).hit
    o = occluded_parallel(m, P, d, grid=32, capacity=64, s_min=1e-9)
    print(f"parallel shadow rays vs brute force: {int(jnp.sum(o.occluded != ref))} of 400 differ, "
          f"overflow {int(o.overflow)}, {int(ref.sum())} occluded")
    assert int(o.overflow) == 0 and bool(jnp.all(o.occluded == ref))
    # second eager calls of the same shapes build no program (eager lax.scan / lax.map over
    # closures compiled again on every call)
    (ref2, o2), n = programs_built(lambda: (intersect(m, P, jnp.broadcast_to(d, P.shape), s_min=1e-9).hit,
                                            occluded_parallel(m, P, d, grid=32, capacity=64, s_min=1e-9)))
    assert n == 0 and bool(jnp.all(ref2 == ref)) and bool(jnp.all(o2.occluded == o.occluded))
    small = occluded_parallel(m, P, d, grid=4, capacity=8, s_min=1e-9)
    wrong = small.occluded != ref
    print(f"capacity 8 on a 4x4 grid: overflow {int(small.overflow)}, {int(wrong.sum())} wrong answers, "
          f"all flagged: {bool(jnp.all(small.incomplete[wrong]))}")
    assert int(small.overflow) > 0 and int(wrong.sum()) > 0
    assert bool(jnp.all(small.incomplete[wrong]))
    # sun_visibility is the mean of the per-direction answers
    dirs = sun_directions(d, angular_diameter_deg=8.0, samples=5)
    per = jnp.mean(jnp.stack([occluded_parallel(m, P, di, grid=32, capacity=64, s_min=1e-9).occluded
                              for di in dirs]).astype(float), axis=0)
    vis, _, ovf = sun_visibility(m, P, d, angular_diameter_deg=8.0, samples=5, grid=32, capacity=64, s_min=1e-9)
    assert int(ovf) == 0 and bool(jnp.all(1.0 - per == vis))


def test_default_capacity_grows_when_eager_and_is_flagged_under_jit():
    """Issue 20 (capacities outside the registry): 300 small triangles stacked over one spot sit
    in one grid cell, beyond the default 128 per cell. An eager call with the defaults re-sizes
    its buffers and answers every ray exactly; under jit, or with a capacity the caller passes,
    the overflow is flagged, never silent. (Before: the eager default dropped 172 triangles.)"""
    rng = np.random.default_rng(4)
    n = 300
    base = np.array([[0.0, 0, 0], [0.05, 0, 0], [0, 0.05, 0]])
    off = np.concatenate([rng.uniform(-0.02, 0.02, (n, 2)), rng.uniform(1.0, 2.0, (n, 1))], 1)
    V = (base[None] + off[:, None]).reshape(-1, 3)
    m = fsjax.Mesh(jnp.asarray(V), jnp.arange(3 * n, dtype=jnp.int32).reshape(n, 3))
    P = jnp.asarray(np.concatenate([rng.uniform(-0.05, 0.08, (200, 2)), np.zeros((200, 1))], 1))
    d = jnp.asarray([0.0, 0.0, 1.0])
    ref = intersect(m, P, jnp.broadcast_to(d, P.shape), s_min=1e-9).hit
    eager = occluded_parallel(m, P, d, s_min=1e-9)
    assert int(eager.overflow) == 0 and not bool(jnp.any(eager.incomplete))
    assert bool(jnp.all(eager.occluded == ref)) and 0 < int(ref.sum()) < 200
    kept = occluded_parallel(m, P, d, s_min=1e-9, capacity=128)
    assert int(kept.overflow) > 0 and bool(jnp.any(kept.incomplete))
    traced = jax.jit(lambda pts: occluded_parallel(m, pts, d, s_min=1e-9))(P)
    assert int(traced.overflow) > 0
    wrong = traced.occluded != ref
    assert bool(jnp.all(traced.incomplete[wrong]))
    vis, inc, ovf = sun_visibility(m, P, d, samples=3, s_min=1e-9)
    assert int(ovf) == 0 and not bool(jnp.any(inc))
    dirs = sun_directions(d, samples=3)
    per = jnp.mean(jnp.stack([intersect(m, P, jnp.broadcast_to(di, P.shape), s_min=1e-9).hit for di in dirs])
                   .astype(float), axis=0)
    assert bool(jnp.all(vis == 1.0 - per))


def test_sun_penumbra_width():
    """A half-plane occluder at height h: the penumbra spans h * tan(0.53 deg) on the ground."""
    h = 1.0
    big = 50.0
    v = jnp.asarray([[-big, -big, h], [0.0, -big, h], [0.0, big, h], [-big, big, h]])
    m = fsjax.Mesh(v, jnp.asarray([[0, 1, 2], [0, 2, 3]]))
    half = h * math.tan(math.radians(0.53 / 2))
    x = jnp.linspace(-3 * half, 3 * half, 61)
    pts = jnp.stack([x, jnp.zeros_like(x), jnp.zeros_like(x)], -1)
    vis, inc, ovf = sun_visibility(m, pts, jnp.asarray([0.0, 0.0, 1.0]), angular_diameter_deg=0.53, samples=64)
    vis = np.asarray(vis)
    xs = np.asarray(x)
    # Fraction of a uniform disc of radius `half` beyond a chord at signed distance x
    a = np.clip(xs / half, -1, 1)
    exact = 0.5 + (a * np.sqrt(1 - a * a) + np.arcsin(a)) / np.pi
    err = float(np.max(np.abs(vis - exact)))
    print(f"sun 0.53 deg penumbra: max |visible - disc fraction| = {err:.3f} with 64 samples")
    assert err < 0.06
    assert np.all(vis[xs < -1.01 * half] == 0.0) and np.all(vis[xs > 1.01 * half] == 1.0)
    assert int(ovf) == 0 and not bool(np.any(inc))
    d = sun_directions(jnp.asarray([0.0, 0.0, 1.0]), samples=64)
    ang = np.degrees(np.arccos(np.clip(np.asarray(d[:, 2]), -1, 1)))
    assert ang.max() <= 0.265 and abs(float(jnp.mean(d[:, 0]))) < 0.01 * math.radians(0.265)


def test_bad_input():
    m = _blob(1)
    with pytest.raises(ValueError, match="occluded_parallel.*direction.*zero-length"):
        occluded_parallel(m, jnp.zeros((2, 3)), jnp.zeros(3))
    with pytest.raises(ValueError, match="sun_directions.*direction"):
        sun_visibility(m, jnp.zeros((2, 3)), jnp.zeros(3))
    with pytest.raises(ValueError, match="capacity"):
        occluded_parallel(m, jnp.zeros((2, 3)), jnp.ones(3), capacity=0)
    with pytest.raises(ValueError, match="intersect.*empty"):
        intersect(fsjax.Mesh(jnp.zeros((0, 3)), jnp.zeros((0, 3), jnp.int32)), jnp.zeros((1, 3)), jnp.ones((1, 3)))
    # a NaN triangle is skipped, not a hit everywhere
    V = jnp.asarray([[0.0, 0, 2], [1, 0, 2], [0, 1, 2], [jnp.nan, 0, 0]])
    h = intersect(fsjax.Mesh(V, jnp.asarray([[3, 1, 2], [0, 1, 2]])), jnp.asarray([[0.2, 0.2, 0.0]]),
                  jnp.asarray([[0.0, 0.0, 1.0]]))
    assert int(h.face_id[0]) == 1 and float(h.s[0]) == 2.0
