"""Signed distance volumes: analytic primitives (fsjax.synth.sdf_volume), CSG (sdf_union /
sdf_intersection / sdf_difference, sharp and smooth), occupancy, and the SDF -> occupancy ->
mesh round trip, each against a closed-form volume or area. One grid throughout (32^3, 0.5 mm)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fsjax
from fsjax import Volume
from fsjax.ops import (
    marching_cubes,
    mesh_area,
    mesh_volume,
    sdf_difference,
    sdf_intersection,
    sdf_to_occupancy,
    sdf_union,
)
from fsjax.synth import sdf_volume

SHAPE = (32, 32, 32)
SP = (0.5, 0.5, 0.5)
VOX = 0.125
C = (7.75, 7.75, 7.75)


def _occ_volume(v: Volume) -> float:
    return float(jnp.sum(sdf_to_occupancy(v).data)) * VOX


def _binary_volume(v: Volume) -> float:
    return float(jnp.sum(v.data <= 0)) * VOX


def _lens(r: float, d: float) -> float:
    """Volume of the intersection of two balls of radius r whose centres are d apart."""
    return np.pi * (4 * r + d) * (2 * r - d) ** 2 / 12


def _brute_distance(p, surface):
    return float(np.min(np.linalg.norm(surface - p, axis=1)))


def test_primitives_are_exact_distances():
    """Box, cylinder and torus distances equal the brute-force distance to a dense sample of each
    surface (within the sample's spacing), inside (negative) and outside."""
    rng = np.random.default_rng(0)
    # dense surface samples (numpy, independent of the formulas)
    u = rng.uniform(-1, 1, (60000, 2))
    box_half = np.array([3.0, 2.0, 4.0])
    face = rng.integers(0, 6, 60000)
    box = np.zeros((60000, 3))
    for k in range(6):
        ax, sgn = k // 2, 1 - 2 * (k % 2)
        sel = face == k
        others = [a for a in range(3) if a != ax]
        box[sel, ax] = sgn * box_half[ax]
        box[sel, others[0]] = u[sel, 0] * box_half[others[0]]
        box[sel, others[1]] = u[sel, 1] * box_half[others[1]]
    t = rng.uniform(0, 2 * np.pi, 60000)
    hz = rng.uniform(-1, 1, 60000)
    side = np.stack([hz * 2.5, 3.0 * np.sin(t), 3.0 * np.cos(t)], 1)
    rr = 3.0 * np.sqrt(rng.uniform(0, 1, 60000))
    caps = np.stack([np.sign(hz) * 2.5, rr * np.sin(t), rr * np.cos(t)], 1)
    cyl = np.concatenate([side, caps])
    a, b = rng.uniform(0, 2 * np.pi, (2, 120000))
    tor = np.stack([1.2 * np.sin(b), (4.0 + 1.2 * np.cos(b)) * np.sin(a), (4.0 + 1.2 * np.cos(b)) * np.cos(a)], 1)
    cases = [("box", {"half": tuple(box_half)}, box), ("cylinder", {"radius": 3.0, "half_height": 2.5}, cyl),
             ("torus", {"major": 4.0, "minor": 1.2}, tor)]
    idx = rng.integers(0, 32, (25, 3))
    for kind, size, surf in cases:
        d = np.asarray(sdf_volume(kind, SHAPE, SP, **size).data)
        for k, j, i in idx:
            p = np.array([k, j, i]) * 0.5 - np.array(C)
            ref = _brute_distance(p, surf)
            inside = d[k, j, i] < 0
            assert abs(abs(d[k, j, i]) - ref) < 0.06, (kind, (k, j, i), d[k, j, i], ref)
            # the sign: inside the solid by its own definition
            if kind == "box":
                assert inside == bool(np.all(np.abs(p) < box_half))
            elif kind == "cylinder":
                assert inside == bool(np.hypot(p[1], p[2]) < 3.0 and abs(p[0]) < 2.5)
            else:
                assert inside == bool(np.hypot(np.hypot(p[1], p[2]) - 4.0, p[0]) < 1.2)


@pytest.mark.parametrize("kind,size,volume,area", [
    ("sphere", {"radius": 5.0}, 4 / 3 * np.pi * 125, 4 * np.pi * 25),
    ("torus", {"major": 4.5, "minor": 2.0}, 2 * np.pi ** 2 * 4.5 * 4.0, 4 * np.pi ** 2 * 4.5 * 2.0),
])
def test_sdf_occupancy_mesh_round_trip(kind, size, volume, area):
    """SDF -> occupancy -> marching cubes at 0.5: enclosed volume and area within 1 % of the
    closed form; the null (the binary mask d <= 0 meshed the same way) is several times worse."""
    sdf = sdf_volume(kind, SHAPE, SP, **size)
    occ = sdf_to_occupancy(sdf)
    m = marching_cubes(occ, level=0.5)
    null = marching_cubes(Volume((sdf.data <= 0).astype(sdf.data.dtype), SP), level=0.5)
    ev, ea = float(mesh_volume(m).value) / volume - 1, float(mesh_area(m).value) / area - 1
    nv, na = float(mesh_volume(null).value) / volume - 1, float(mesh_area(null).value) / area - 1
    print(f"{kind}: SDF->occupancy->mesh volume {ev:+.3%} area {ea:+.3%}; binary mask {nv:+.2%} / {na:+.2%}")
    assert abs(ev) < 0.01 and abs(ea) < 0.01
    assert abs(na) > 3 * abs(ea)
    assert not bool(m.truncated)


def test_occupancy_volume_beats_the_binary_mask():
    """Summed occupancy of balls of radius 6-12.6 voxels within 0.7 % of 4/3 pi r^3 (a curvature
    bias, falling with r); the binary mask d <= 0 errs 4x more on average."""
    occ, binary = [], []
    for r in (3.1, 4.0, 5.0, 6.3):
        s = sdf_volume("sphere", SHAPE, SP, radius=r)
        true = 4 / 3 * np.pi * r ** 3
        occ.append(abs(_occ_volume(s) / true - 1))
        binary.append(abs(_binary_volume(s) / true - 1))
    print("balls r = 6.2-12.6 voxels, volume error: occupancy " + ", ".join(f"{e:.2%}" for e in occ)
          + "; binary mask " + ", ".join(f"{e:.2%}" for e in binary))
    assert max(occ) < 0.007 and np.mean(binary) > 2 * np.mean(occ)


def test_csg_volumes_of_two_balls():
    """Union, intersection and difference of two balls (r 4 mm, centres 3 mm apart): occupancy
    volumes within 1.5 % of the lens formulas. Min/max CSG fields are bounds, not distances, near
    the crease where the surfaces meet, so the difference (a concave dimple with a sharp rim) reads
    ~1.1 % high (0.4 % and 0.5 % for union and intersection; the binary mask: 1.3, 2.1, 0.9 %)."""
    r, dist = 4.0, 3.0
    a = sdf_volume("sphere", SHAPE, SP, radius=r, centre=(7.75, 7.75, 7.75 - dist / 2))
    b = sdf_volume("sphere", SHAPE, SP, radius=r, centre=(7.75, 7.75, 7.75 + dist / 2))
    ball, lens = 4 / 3 * np.pi * r ** 3, _lens(r, dist)
    for name, out, true in [("union", sdf_union(a, b), 2 * ball - lens),
                            ("intersection", sdf_intersection(a, b), lens),
                            ("difference", sdf_difference(a, b), ball - lens)]:
        err = _occ_volume(out) / true - 1
        print(f"CSG {name}: occupancy volume {err:+.3%}")
        assert abs(err) < 0.015, (name, err)
    # the sharp union is the exact distance outside: the voxel (15, 15, 31) lies beyond b
    u = np.asarray(sdf_union(a, b).data)
    p = np.array([15, 15, 31]) * 0.5
    assert abs(u[15, 15, 31] - (np.linalg.norm(p - (7.75, 7.75, 7.75 + dist / 2)) - r)) < 1e-12


def test_smooth_blend_adds_material_and_is_c1():
    r = 4.0
    a = sdf_volume("sphere", SHAPE, SP, radius=r, centre=(7.75, 7.75, 6.25))
    b = sdf_volume("sphere", SHAPE, SP, radius=r, centre=(7.75, 7.75, 9.25))
    sharp, soft = _occ_volume(sdf_union(a, b)), _occ_volume(sdf_union(a, b, smooth=1.0))
    assert soft > sharp * 1.005  # the fillet in the crease adds material
    soft_i = _occ_volume(sdf_intersection(a, b, smooth=1.0))
    assert soft_i < _occ_volume(sdf_intersection(a, b)) * 0.995  # and removes it from the lens' rim
    # C1 across the band edge |a - b| = k: one-sided slopes agree
    k = 1.0
    f = lambda t: fsjax.ops.volume._sdf.smooth_min(jnp.asarray(t), jnp.asarray(0.0), k)  # noqa: E731
    for edge in (k, -k):
        g_in, g_out = jax.grad(f)(edge * (1 - 1e-9)), jax.grad(f)(edge * (1 + 1e-9))
        assert abs(float(g_in) - float(g_out)) < 1e-6
        assert abs(float(f(edge * (1 - 1e-9))) - float(f(edge * (1 + 1e-9)))) < 1e-8


def test_infinite_inputs_stay_exact_and_nan_free():
    s = sdf_volume("sphere", SHAPE, SP, radius=3.0)
    empty = Volume(jnp.full(SHAPE, jnp.inf), SP)
    full = Volume(jnp.full(SHAPE, -jnp.inf), SP)
    for k in (0.0, 1.0):
        assert np.array_equal(np.asarray(sdf_union(s, empty, smooth=k).data), np.asarray(s.data))
        assert np.all(np.asarray(sdf_union(s, full, smooth=k).data) == -np.inf)
        assert np.all(np.asarray(sdf_intersection(s, empty, smooth=k).data) == np.inf)
        assert np.array_equal(np.asarray(sdf_difference(s, full, smooth=k).data), np.full(SHAPE, np.inf))
        assert np.array_equal(np.asarray(sdf_difference(s, empty, smooth=k).data), np.asarray(s.data))
        mixed = Volume(jnp.where(jnp.arange(32)[None, None, :] < 16, jnp.inf, -jnp.inf) * jnp.ones(SHAPE), SP)
        both = np.asarray(sdf_union(empty, mixed, smooth=k).data)
        assert not np.any(np.isnan(both))
        g = jax.grad(lambda d: jnp.sum(jnp.where(jnp.isfinite(d), d, 0.0)))
        grad = g(sdf_union(s, Volume(jnp.where(s.data > 0, jnp.inf, s.data + 0.3), SP), smooth=k).data)
        assert np.all(np.isfinite(np.asarray(grad)))
    gu = jax.grad(lambda d: jnp.sum(sdf_union(Volume(d, SP), empty, smooth=1.0).data))(s.data)
    assert np.all(np.asarray(gu) == 1.0)  # d min(a, inf) / da = 1 everywhere, no NaN from inf


def test_volume_derivative_in_radius_is_the_area():
    """d(occupied volume)/d(radius) = surface area 4 pi r^2 (through sdf_volume and
    sdf_to_occupancy); checked against a finite difference and the closed form, and non-zero."""
    r0 = 4.3

    def vol(r):
        return jnp.sum(sdf_to_occupancy(sdf_volume("sphere", SHAPE, SP, radius=r)).data) * VOX

    g = float(jax.grad(vol)(r0))
    fd = (float(vol(r0 + 1e-4)) - float(vol(r0 - 1e-4))) / 2e-4
    assert g != 0.0 and abs(g - fd) < 1e-6 * abs(fd)
    assert abs(g / (4 * np.pi * r0 ** 2) - 1) < 0.03


def test_bad_input_fails_closed():
    s = sdf_volume("sphere", SHAPE, SP, radius=3.0)
    with pytest.raises(ValueError, match=r"sdf_union\(a, b\): the two volumes must share one grid"):
        sdf_union(s, sdf_volume("sphere", (32, 32, 31), SP, radius=3.0))
    with pytest.raises(ValueError, match="sdf_intersection.*grid"):
        sdf_intersection(s, sdf_volume("sphere", SHAPE, (0.5, 0.5, 0.6), radius=3.0))
    with pytest.raises(ValueError, match="sdf_difference.*'smooth'"):
        sdf_difference(s, s, smooth=-1.0)
    with pytest.raises(ValueError, match="sdf_union: argument 'b' .* 1 NaN value.*accepts \\+-inf but not NaN"):
        sdf_union(s, Volume(s.data.at[0, 0, 0].set(jnp.nan), SP))
    with pytest.raises(ValueError, match="sdf_volume.*'radius'"):
        sdf_volume("sphere", SHAPE, SP, radius=-1.0)
    with pytest.raises(TypeError, match="sdf_volume\\('torus'\\): expected size arguments major, minor"):
        sdf_volume("torus", SHAPE, SP, radius=1.0)
    with pytest.raises(ValueError, match="sdf_volume.*'kind'"):
        sdf_volume("cone", SHAPE, SP, radius=1.0)


def test_float32_and_vmap():
    s64 = sdf_volume("sphere", SHAPE, SP, radius=4.0)
    s32 = sdf_volume("sphere", SHAPE, SP, radius=4.0, dtype=jnp.float32)
    assert s32.data.dtype == jnp.float32
    a = jnp.stack([s32.data, s32.data + 0.5])
    out = jax.jit(jax.vmap(lambda d: sdf_union(Volume(d, SP), Volume(d[::-1], SP), smooth=0.5).data))(a)
    ref = sdf_union(s64, Volume(s64.data[::-1], SP), smooth=0.5).data
    assert float(jnp.max(jnp.abs(out[0] - ref))) < 1e-5
