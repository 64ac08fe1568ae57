"""The spherical-harmonic shape descriptor (fsjax.ops.sh_descriptor3d, points_sh_descriptor,
sh_similarity3d) and its cells of the 3-D matching grid (issue 17)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fsjax
from fsjax.synth import (
    MATCH3D_DESC_METHODS,
    MATCH3D_DESC_MIN,
    MATCH3D_DESC_NOT_YET,
    MATCH3D_DESC_STRUCTURES,
    match3d_object,
    rotation_zyx,
    run_descriptor_cell,
)

ops = fsjax.ops


def _cloud(name, n=3000, seed=0, R=None, dtype=jnp.float64):
    p = match3d_object(name, 20.0, n=n, seed=seed)
    return fsjax.Points(jnp.asarray(p if R is None else p @ R.T, dtype))


def test_real_harmonics_are_orthonormal():
    """The harmonics the descriptor uses: sum over a dense spherical quadrature of Y_lm Y_l'm' = I."""
    from fsjax.ops.match3d._shdesc import _coef_raw

    # Gauss-Legendre in z times uniform in phi: exact for degree <= 2 * 8
    zq, wz = np.polynomial.legendre.leggauss(12)
    phi = np.linspace(0, 2 * np.pi, 24, endpoint=False)
    Z, P = np.meshgrid(zq, phi, indexing="ij")
    W = (wz[:, None] * np.full_like(P, 2 * np.pi / 24)).ravel()
    s = np.sqrt(1 - Z**2)
    u = jnp.asarray(np.stack([s * np.cos(P), s * np.sin(P), Z], -1).reshape(-1, 3))
    Y = np.stack([np.asarray(_coef_raw(u, jnp.asarray(np.eye(len(W))[:, [i]]), 5))[0] for i in range(len(W))])
    G = (Y * W[:, None]).T @ Y
    np.testing.assert_allclose(G, np.eye(36), atol=1e-10)


def test_points_descriptor_is_rotation_translation_scale_invariant_and_separates_shapes():
    d = ops.points_sh_descriptor(_cloud("bunny"))
    assert d.data.shape == (20,) and abs(float(jnp.linalg.norm(d.data)) - 1) < 1e-12
    sims = []
    for ang in [(40, -25, 70), (170, 80, -120), (-90, 10, 5)]:
        c = _cloud("bunny", R=rotation_zyx(ang))
        moved = fsjax.Points(2.5 * c.xyz + jnp.asarray([3.0, -7.0, 11.0]))  # scaled and moved too
        sims.append(float(ops.sh_similarity3d(d, ops.points_sh_descriptor(moved))))
    assert min(sims) > 1 - 1e-9, sims
    others = [float(ops.sh_similarity3d(d, ops.points_sh_descriptor(_cloud(n, seed=1)))) for n in ("spot", "fandisk")]
    fresh = float(ops.sh_similarity3d(d, ops.points_sh_descriptor(_cloud("bunny", seed=1))))
    print(f"\nSH points: rotated {min(sims):.12f}, fresh draw {fresh:.4f}, spot/fandisk {others}")
    assert max(others) < 0.9 and fresh > 0.93 and fresh > max(others) + 0.05


def test_null_without_energies_is_not_invariant():
    """The energy step is what makes it invariant: the raw coefficients of a rotated copy differ."""
    from fsjax.synth._match3d_desc import _null_similarity

    a, b = _cloud("bunny"), _cloud("bunny", R=rotation_zyx((40, -25, 70)))
    assert _null_similarity(a, b, 0.0, 0.0) < 0.8
    assert _null_similarity(a, a, 0.0, 0.0) > 1 - 1e-12


def test_invalid_points_weigh_nothing_and_empty_gives_nan():
    c = _cloud("bunny", n=500)
    junk = jnp.concatenate([c.xyz, jnp.full((7, 3), 1e4)])
    masked = fsjax.Points(junk, valid=jnp.arange(507) < 500)
    np.testing.assert_allclose(ops.points_sh_descriptor(masked).data, ops.points_sh_descriptor(c).data, atol=1e-12)
    empty = ops.points_sh_descriptor(fsjax.Points(c.xyz, valid=jnp.zeros(500, bool)))
    assert float(jnp.abs(empty.data).max()) == 0.0
    assert np.isnan(float(ops.sh_similarity3d(empty, ops.points_sh_descriptor(c))))
    v0 = ops.sh_descriptor3d(fsjax.Volume(jnp.zeros((8, 8, 8))))
    assert np.isnan(float(ops.sh_similarity3d(v0, v0)))


def test_bad_arguments_name_the_op():
    c = _cloud("bunny", n=100)
    with pytest.raises(ValueError, match="points_sh_descriptor: argument 'n_shells'"):
        ops.points_sh_descriptor(c, n_shells=0)
    with pytest.raises(ValueError, match="sh_descriptor3d: argument 'max_degree'"):
        ops.sh_descriptor3d(fsjax.Volume(jnp.ones((4, 4, 4))), max_degree=17)
    with pytest.raises(ValueError, match="sh_similarity3d: arguments 'a' and 'b'"):
        ops.sh_similarity3d(ops.points_sh_descriptor(c), ops.points_sh_descriptor(c, n_shells=5))


def test_float32_jit_and_vmap():
    c32 = _cloud("bunny", n=2000, dtype=jnp.float32)
    d32 = ops.points_sh_descriptor(c32)
    assert d32.data.dtype == jnp.float32
    d64 = ops.points_sh_descriptor(_cloud("bunny", n=2000))
    np.testing.assert_allclose(d32.data, d64.data, atol=1e-5)
    f = jax.jit(lambda x: ops.points_sh_descriptor(fsjax.Points(x)).data)
    np.testing.assert_allclose(f(c32.xyz), d32.data, atol=1e-6)
    R = jnp.asarray(rotation_zyx((30, 60, 90)), jnp.float32)
    batch = jax.vmap(f)(jnp.stack([c32.xyz, c32.xyz @ R.T]))
    assert batch.shape == (2, 20) and float(ops.sh_similarity3d(fsjax.Signal(batch[0]), fsjax.Signal(batch[1]))) > 0.9999
    # a volume larger than one chunk (scan path) in float32
    v = ops.gaussian3d(ops.points_to_volume(fsjax.Points(c32.xyz + 23.5), shape=(48, 48, 48)), sigma=1.0)
    assert ops.sh_descriptor3d(v).data.dtype == jnp.float32


def test_volume_chunked_equals_direct():
    """The scan over chunks of voxels (> 8192 voxels) gives the direct sum."""
    from fsjax.ops.match3d._shdesc import _coef_raw, _sh_coefficients

    rng = np.random.default_rng(0)
    p = jnp.asarray(rng.normal(size=(20000, 3)))
    w = jnp.asarray(rng.uniform(size=20000))
    A, _ = _sh_coefficients(p, w, jnp.asarray(2.5), 3, 3)
    q = p - (w @ p) / jnp.sum(w)
    r = jnp.linalg.norm(q, axis=1)
    rms = jnp.sqrt(w @ r**2 / jnp.sum(w))
    xs = r / (2.5 * rms) * 3 - 0.5
    h = np.zeros((20000, 3))
    lo = np.floor(np.asarray(xs)).astype(int)
    f = np.asarray(xs) - lo
    for s in range(3):
        h[:, s] = (np.clip(lo, 0, 2) == s) * (1 - f) + (np.clip(lo + 1, 0, 2) == s) * f
    B = _coef_raw(q / r[:, None], jnp.asarray(h) * w[:, None], 3)
    np.testing.assert_allclose(A, B, atol=1e-9)


# --- the grid cells -------------------------------------------------------------------------------

CELLS = [(s, m) for s in MATCH3D_DESC_STRUCTURES for m in MATCH3D_DESC_METHODS if (s, m) not in MATCH3D_DESC_NOT_YET]


def test_descriptor_cells_are_all_accounted_for():
    assert len(CELLS) + len(MATCH3D_DESC_NOT_YET) == len(MATCH3D_DESC_STRUCTURES) * len(MATCH3D_DESC_METHODS)
    assert set(CELLS) == set(MATCH3D_DESC_MIN)


@pytest.mark.parametrize("structure,method", CELLS, ids=[f"{s}-{m}" for s, m in CELLS])
def test_descriptor_cell(structure, method):
    """The bunny against its rotated copy: similar above the cell's level, above the null (raw
    coefficients) and above the other shapes; a scene of clutter alone is not the bunny."""
    r = run_descriptor_cell(structure, method)
    same, floor = MATCH3D_DESC_MIN[(structure, method)]
    print(f"\ndescriptor cell ({structure}, {method}): similarity {r['similarity']:.4f} (floor {floor}), "
          f"null {r['null']:.3f}, other shapes {r['other']:.3f}")
    assert r["valid"] and r["similarity"] >= floor
    assert r["similarity"] > r["null"] and r["other"] < same
    r0 = run_descriptor_cell(structure, method, with_object=False)
    assert not r0["valid"]


def test_descriptor_cell_float32():
    r = run_descriptor_cell("voxel", dtype=jnp.float32)
    assert r["descriptor"].data.dtype == jnp.float32
    assert r["similarity"] >= MATCH3D_DESC_MIN[("voxel", "sh_descriptor3d")][1]


# --- Harris-3D ------------------------------------------------------------------------------------


def test_harris3d_repeatability_60deg_70pct_overlap():
    """Issue 17's reference: 85 % at 60 degrees and 70 % overlap. Same samples, two crops: mean
    over three seeds at least 0.85, every seed far above the null (random points)."""
    from fsjax.synth import harris3d_repeatability

    res = [harris3d_repeatability(seed=s) for s in range(3)]
    reps = [r["repeatability"] for r in res]
    print(f"\nHarris-3D repeatability (60 deg, 70 % overlap, eps 1 %): {reps}, null {[r['null'] for r in res]}")
    assert np.mean(reps) >= 0.85 and min(reps) >= 0.75
    assert all(r["repeatability"] > r["null"] + 0.5 for r in res) and all(r["valid"] for r in res)


def test_harris3d_fails_closed_and_float32():
    from fsjax.synth import harris3d_repeatability

    # the plane, the sphere and the bunny below: one shape and dtype (3,000 float32 points), one program
    g = np.stack(np.meshgrid(np.arange(60.0), np.arange(50.0)), -1).reshape(-1, 2) / 3.0
    plane = fsjax.Points(jnp.asarray(np.c_[g, 0.3 * g[:, 0] + 0.1 * g[:, 1]], jnp.float32))
    k = ops.harris3d(plane)
    assert int(k.valid.sum()) == 0 and k.xyz.shape == (32, 3)
    sp = np.random.default_rng(0).normal(size=(3000, 3))
    sphere = fsjax.Points(jnp.asarray(sp / np.linalg.norm(sp, axis=1, keepdims=True), jnp.float32))
    assert int(ops.harris3d(sphere).valid.sum()) == 0
    r = harris3d_repeatability(seed=0, dtype=jnp.float32)
    assert r["keypoints"].xyz.dtype == jnp.float32 and r["repeatability"] >= 0.85
    # invalid slots are never keypoints, and do not change the others
    c = _cloud("bunny", n=3000, dtype=jnp.float32)
    xyz = jnp.concatenate([c.xyz, jnp.zeros((5, 3), jnp.float32)])
    a = ops.harris3d(fsjax.Points(xyz, valid=jnp.arange(3005) < 3000))
    b = ops.harris3d(c)
    np.testing.assert_allclose(a.xyz[a.valid], b.xyz[b.valid])
    with pytest.raises(ValueError, match="harris3d: argument 'nms_k'"):
        ops.harris3d(c, k=16, nms_k=16)
    f = jax.jit(lambda x: ops.harris3d(fsjax.Points(x)).valid.sum())
    assert int(f(c.xyz)) == int(b.valid.sum())


@pytest.mark.slow  # two more voxel scenes (48^3 and 80^3) and their descriptors
def test_voxel_descriptor_cell_floor_is_the_objects_resolution():
    """The voxel cell's similarity 0.998 (below the issue's 0.999) is the voxelisation of a 16-voxel bunny:
    the same cell (1 % noise, seed 0) with the bunny 32 voxels across reaches 0.99912 (measured; seeds 1, 2:
    0.99916, 0.99951), at 16 voxels 0.99803."""
    from fsjax.synth._match3d_desc import sh_voxel_resolution

    lo, hi = sh_voxel_resolution(seed=0), sh_voxel_resolution(seed=0, extent=32.0)
    print(f"\nvoxel descriptor cell: bunny 16 voxels across {lo:.5f}, 32 across {hi:.5f}")
    assert lo < 0.999 <= hi


@pytest.mark.slow  # two more mesh scenes (48^3 and 80^3), their samples on the grid, and their descriptors
def test_mesh_descriptor_cell_floor_is_the_objects_resolution():
    """The mesh cell's similarity 0.998 (below the issue's 0.999) is, like the voxel cell's, the grid's
    resolution of a 16-voxel bunny, not the surface sampling: the same cell (seed 0, reproduced: 0.99841)
    with 80,000 samples instead of 20,000 stays at 0.99856, with the bunny 32 voxels across (the same
    samples per unit area) it reaches 0.99939 (measured; seeds 1, 2: 0.99961, 0.99955)."""
    from fsjax.synth._match3d_desc import sh_voxel_resolution

    cell = run_descriptor_cell("mesh")["similarity"]
    lo = sh_voxel_resolution(seed=0, structure="mesh")
    dense = sh_voxel_resolution(seed=0, structure="mesh", n=80000)
    hi = sh_voxel_resolution(seed=0, structure="mesh", extent=32.0)
    print(f"\nmesh descriptor cell: {cell:.5f}; 16 voxels across {lo:.5f} (80,000 samples {dense:.5f}), "
          f"32 across {hi:.5f}")
    assert lo == cell  # the same scene as the cell's
    assert lo < 0.999 and dense < 0.999 <= hi
    with pytest.raises(ValueError, match="sh_voxel_resolution: argument 'structure'"):
        sh_voxel_resolution(structure="points")
