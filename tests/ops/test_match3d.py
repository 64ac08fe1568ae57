"""3-D matching (fsjax.ops.match3d): the Match3D record, the transforms, the FFT-family methods,
the refinements, and the start of the matching grid (every (structure, method) cell built so far
on a bundled mesh placed with a known pose among clutter, beside its null, and failing closed
on the same scene without the object)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fsjax
from fsjax.synth import (
    MATCH3D_CELL_TOL,
    MATCH3D_METHODS,
    MATCH3D_NOT_YET,
    MATCH3D_STRUCTURES,
    run_grid_cell,
)
from fsjax.synth._match3d import MATCH3D_SCALE_TOL
from fsjax.types import reason_code

ops = fsjax.ops


def _fourier_shift(x, d_zyx):
    k = [np.fft.fftfreq(n) for n in x.shape]
    ph = np.exp(-2j * np.pi * (k[0][:, None, None] * d_zyx[0] + k[1][None, :, None] * d_zyx[1]
                               + k[2][None, None, :] * d_zyx[2]))
    return np.real(np.fft.ifftn(np.fft.fftn(x) * ph))


@pytest.fixture(scope="module")
def smooth_random():
    rng = np.random.default_rng(0)
    x = rng.standard_normal((20, 22, 24))
    # band-limit a little so that trilinear sampling (LK) is accurate too
    return np.asarray(ops.gaussian3d(fsjax.Volume(x), sigma=1.5).data)


# --- the record ---------------------------------------------------------------------------------


def test_match3d_record_fill_apply_and_batch():
    m = fsjax.Match3D(jnp.eye(3), jnp.asarray([1.0, 2.0, 3.0]), 0.9, True, 0, scale=2.0)
    assert m.batch_shape == () and m.message == "ok"
    np.testing.assert_allclose(m.apply(jnp.asarray([[1.0, 0.0, 0.0]])), [[3.0, 2.0, 3.0]])
    b = jax.vmap(lambda s: fsjax.Match3D(jnp.eye(3), jnp.zeros(3) + s, s, s > 0, 0))(jnp.arange(3.0))
    assert b.batch_shape == (3,) and b.valid.tolist() == [False, True, True]
    with pytest.raises(ValueError, match="batch shape"):
        fsjax.Match3D(jnp.eye(3), jnp.zeros((2, 3)), 0.0, True, 0)
    with pytest.raises(ValueError, match=r"Match3D\(R=...\)"):
        fsjax.Match3D(jnp.eye(2), jnp.zeros(3), 0.0, True, 0)


# --- transforms ---------------------------------------------------------------------------------


def test_points_to_volume_conserves_mass_and_centroid():
    """Trilinear splatting interpolates linearly: mass = number of points inside, centroid exact
    (the null, nearest-voxel binning, is off by up to half a voxel)."""
    rng = np.random.default_rng(1)
    p = rng.uniform(2.0, 9.0, (500, 3))
    v = ops.points_to_volume(fsjax.Points(jnp.asarray(p)), shape=(12, 12, 12), spacing=(1.0, 1.0, 1.0))
    d = np.asarray(v.data)
    assert abs(d.sum() - 500) < 1e-9
    k, i, j = np.mgrid[0:12, 0:12, 0:12]
    com = np.array([(d * a).sum() for a in (j, i, k)]) / d.sum()
    np.testing.assert_allclose(com, p.mean(0), atol=1e-10)
    nearest = np.zeros((12, 12, 12))
    r = np.rint(p).astype(int)
    np.add.at(nearest, (r[:, 2], r[:, 1], r[:, 0]), 1.0)
    com_null = np.array([(nearest * a).sum() for a in (j, i, k)]) / 500
    assert np.abs(com_null - p.mean(0)).max() > 1e-3
    # a point outside the grid adds nothing; invalid slots add nothing; spacing and origin
    q = fsjax.Points(jnp.asarray([[50.0, 0, 0], [1.0, 1.0, 1.0], [2.0, 2.0, 2.0]]), valid=jnp.asarray([True, True, False]))
    v = ops.points_to_volume(q, shape=(4, 4, 4), spacing=(0.5, 0.5, 0.5), origin=(0.0, 0.0, 0.0))
    assert float(v.data.sum()) == 1.0 and float(v.data[2, 2, 2]) == 1.0 and v.spacing == (0.5, 0.5, 0.5)
    with pytest.raises(ValueError, match="points_to_volume: argument 'spacing'"):
        ops.points_to_volume(q, shape=(4, 4, 4), spacing=(0.0, 1.0, 1.0))


def test_to_points_and_to_voxel_accept_every_structure():
    mesh = fsjax.Mesh(jnp.asarray([[0.0, 0, 0], [4, 0, 0], [0, 4, 0]]), jnp.asarray([[0, 1, 2]]))
    p = ops.to_points(mesh, n=300)
    assert p.xyz.shape == (300, 3) and float(jnp.abs(p.xyz[:, 2]).max()) == 0.0
    cam = fsjax.Camera.from_intrinsics(10.0, 10.0, 1.5, 1.5, width=4, height=4)
    dp = ops.to_points(fsjax.Depth(jnp.full((4, 4), 2.0).at[0, 0].set(0.0), cam))
    assert int(dp.valid.sum()) == 15
    vol = ops.to_voxel(mesh, (1.0, 1.0, 1.0), shape=(2, 6, 6), n=1000)
    assert abs(float(vol.data.sum()) - 1000) < 1e-6  # every sample lands inside the grid
    assert ops.to_voxel(vol, (1.0, 1.0, 1.0)) is vol
    assert float(ops.to_voxel(dp, (1.0, 1.0, 1.0), shape=(4, 4, 4), origin=(-1.0, -1.0, 0.0)).data.sum()) > 0
    g = fsjax.Gaussians(jnp.zeros((2, 3)), jnp.zeros((2, 3)), jnp.asarray([[1.0, 0, 0, 0]] * 2), jnp.zeros(2),
                        jnp.ones((2, 3)))
    assert ops.to_points(g).xyz.shape == (2, 3)
    # Gaussians: the footprint splat (tests/ops/test_match3d_gaussvox.py)
    gv = ops.to_voxel(g, (1.0, 1.0, 1.0), shape=(2, 2, 2))
    assert bool(jnp.all(gv.data == ops.gaussians_to_volume(g, shape=(2, 2, 2)).data)) and float(gv.data.sum()) > 0
    with pytest.raises(ValueError, match="to_voxel: argument 'x' is a Volume of spacing"):
        ops.to_voxel(vol, (2.0, 1.0, 1.0))
    with pytest.raises(ValueError, match="argument 'shape' is required"):
        ops.to_voxel(mesh, (1.0, 1.0, 1.0))
    with pytest.raises(TypeError, match="to_points: argument 'x' must be"):
        ops.to_points(jnp.zeros((3, 3)))


def test_volume_to_sdf_of_a_ball_against_the_true_distance():
    """voxel -> SDF: a voxelised ball of radius 5.5 against the true signed distance |p - c| - 5.5:
    within 0.48 voxel everywhere (measured 0.477; the mask's surface is not the sphere's); the null,
    the unsigned distance_transform3d (0 outside, the depth inside, negated), is 11.8 off. The mask
    comes back through sdf_to_occupancy; anisotropic spacing in physical units; float32 kept."""
    k, i, j = np.mgrid[0:21, 0:21, 0:21]
    r = np.sqrt((k - 10.0) ** 2 + (i - 10.0) ** 2 + (j - 10.0) ** 2)
    ball = (r <= 5.5).astype(float)
    d = np.asarray(ops.volume_to_sdf(fsjax.Volume(ball)).data)
    err = np.abs(d - (r - 5.5)).max()
    null = np.abs(-np.asarray(ops.distance_transform3d(fsjax.Volume(ball)).data) - (r - 5.5)).max()
    print(f"\nvolume_to_sdf: ball max error {err:.3f} voxel (null: unsigned distance {null:.2f})")
    assert err < 0.48 and null > 10 * err
    assert (np.asarray(ops.sdf_to_occupancy(fsjax.Volume(d)).data) == ball).all()
    d2 = ops.volume_to_sdf(fsjax.Volume(ball.astype(np.float32), spacing=(2.0, 1.0, 1.0))).data
    assert d2.dtype == jnp.float32 and float(d2[19, 10, 10]) == 2.0 * 4 - 0.5  # 4 voxels of dz = 2 past the last
    assert float(ops.volume_to_sdf(fsjax.Volume(np.zeros((3, 3, 3)))).data.min()) == np.inf
    assert float(ops.volume_to_sdf(fsjax.Volume(np.ones((3, 3, 3)))).data.max()) == -np.inf
    with pytest.raises(ValueError, match="volume_to_sdf: argument 'vol' has batch shape"):
        ops.volume_to_sdf(fsjax.Volume(np.zeros((2, 3, 3, 3))))


# --- peaks --------------------------------------------------------------------------------------


def test_newton_peak_is_exact_on_a_quadratic_and_beats_per_axis_parabolas():
    """The full-Hessian Newton step lands on the maximum of any quadratic; separate parabolas
    (the null) miss it when the axes are coupled."""
    from fsjax.ops.match3d._shared3d import newton_peak3

    H = np.array([[-2.0, 0.8, 0.3], [0.8, -1.5, -0.6], [0.3, -0.6, -1.2]])
    x_star = np.array([0.31, -0.22, 0.17])
    o = np.arange(-1, 2.0)
    d = np.stack(np.meshgrid(o, o, o, indexing="ij"), -1) - x_star
    v = 0.5 * np.einsum("...i,ij,...j->...", d, H, d) + 3.0
    got = np.asarray(newton_peak3(jnp.asarray(v), jnp.ones(3, bool)))
    np.testing.assert_allclose(got, x_star, atol=1e-12)
    par = np.array([0.5 * (v[0, 1, 1] - v[2, 1, 1]) / (v[0, 1, 1] - 2 * v[1, 1, 1] + v[2, 1, 1]),
                    0.5 * (v[1, 0, 1] - v[1, 2, 1]) / (v[1, 0, 1] - 2 * v[1, 1, 1] + v[1, 2, 1]),
                    0.5 * (v[1, 1, 0] - v[1, 1, 2]) / (v[1, 1, 0] - 2 * v[1, 1, 1] + v[1, 1, 2])])
    assert np.abs(par - x_star).max() > 0.1


# --- methods on exact data: the numbers, float32, failing closed -------------------------------


@pytest.mark.parametrize("dtype,tol", [(np.float64, 1e-6), (np.float32, 2e-3)])
def test_phase_correlation3d_sub_voxel_exact(smooth_random, dtype, tol):
    d = (0.37, -1.62, 2.25)  # (z, y, x) voxels
    moved = _fourier_shift(smooth_random, d).astype(dtype)
    m = ops.phase_correlation3d(fsjax.Volume(moved, spacing=(2.0, 1.0, 0.5)),
                                fsjax.Volume(smooth_random.astype(dtype), spacing=(2.0, 1.0, 0.5)))
    assert m.t.dtype == dtype and bool(m.valid)
    np.testing.assert_allclose(np.asarray(m.t), [2.25 * 0.5, -1.62 * 1.0, 0.37 * 2.0], atol=tol)
    # the null, the integer peak (newton_steps=0), is off by up to half a voxel
    m0 = ops.phase_correlation3d(fsjax.Volume(moved), fsjax.Volume(smooth_random.astype(dtype)), newton_steps=0)
    assert np.abs(np.asarray(m0.t) - [2.25, -1.62, 0.37]).max() > 0.3


def test_phase_correlation3d_and_ncc3d_fail_closed(smooth_random):
    flat = fsjax.Volume(np.full((20, 22, 24), 0.3))
    vol = fsjax.Volume(smooth_random)
    m = ops.phase_correlation3d(vol, flat)
    assert not bool(m.valid) and int(m.reason) == reason_code("invalid_input") and bool(jnp.all(jnp.isnan(m.t)))
    m = ops.ncc3d(vol, fsjax.Volume(np.full((5, 5, 5), 0.3)))
    assert not bool(m.valid) and int(m.reason) == reason_code("invalid_input")
    with pytest.raises(ValueError, match="phase_correlation3d: argument 'template' has shape"):
        ops.phase_correlation3d(vol, fsjax.Volume(smooth_random[:10]))
    with pytest.raises(ValueError, match="ncc3d: argument 'template' of shape .* is larger"):
        ops.ncc3d(fsjax.Volume(smooth_random[:10]), vol)
    with pytest.raises(ValueError, match="ncc3d: argument 'template' has spacing"):
        ops.ncc3d(vol, fsjax.Volume(smooth_random[:5, :5, :5], spacing=(2.0, 1.0, 1.0)))


@pytest.mark.parametrize("dtype,tol", [(np.float64, 0.02), (np.float32, 0.02)])  # measured 0.011 (trilinear bias)
def test_lk_translation3d_on_a_band_limited_shift(smooth_random, dtype, tol):
    d = np.array([0.37, -0.62, 0.25])
    moved = _fourier_shift(smooth_random, d).astype(dtype)
    scene, tpl = fsjax.Volume(moved), fsjax.Volume(smooth_random[4:16, 4:18, 4:20].astype(dtype))
    init = ops.ncc3d(scene, tpl)
    m = ops.lk_translation3d(scene, tpl, init=init)
    truth = np.array([4 + d[2], 4 + d[1], 4 + d[0]])
    err, err0 = np.abs(np.asarray(m.t) - truth).max(), np.abs(np.asarray(init.t) - truth).max()
    print(f"\nLK on a band-limited shift ({np.dtype(dtype).name}): {err:.4f} voxel (NCC Newton start {err0:.4f})")
    assert bool(m.valid) and m.t.dtype == dtype and err < tol and err < err0
    # a template without gradient along z (a plate constant in z) cannot fix z: degenerate
    plate = np.broadcast_to(smooth_random[10:11, 4:18, 4:20], (12, 14, 16)).astype(dtype)
    sc = np.broadcast_to(smooth_random[10:11], (20, 22, 24)).astype(dtype)
    m = ops.lk_translation3d(fsjax.Volume(sc), fsjax.Volume(plate), init=fsjax.Match3D(
        jnp.eye(3, dtype=dtype), jnp.asarray([4.0, 4.0, 4.0], dtype), 1.0, True, 0))
    assert not bool(m.valid) and int(m.reason) == reason_code("degenerate")


def test_moments_pose3d_fails_closed_on_clutter_and_on_symmetric_objects():
    from fsjax.synth import match3d_scene

    sc, tp, _ = match3d_scene(angles_deg=(30.0, 20.0, 10.0), clutter=6, noise=0.01, template_size=32)
    m = ops.moments_pose3d(sc, tp, level=0.2 * float(tp.data.max()))
    assert not bool(m.valid) and int(m.reason) == reason_code("not_found")
    k, i, j = np.mgrid[0:16, 0:16, 0:16]
    ball = fsjax.Volume(np.exp(-((k - 7.5) ** 2 + (i - 7.5) ** 2 + (j - 7.5) ** 2) / 8.0))
    m = ops.moments_pose3d(ball, ball)
    assert not bool(m.valid) and int(m.reason) == reason_code("degenerate")


# --- the grid -----------------------------------------------------------------------------------

CELLS = [(s, m) for s in MATCH3D_STRUCTURES for m in MATCH3D_METHODS if (s, m) not in MATCH3D_NOT_YET]


def test_grid_cells_are_all_accounted_for():
    assert len(CELLS) + len(MATCH3D_NOT_YET) == len(MATCH3D_STRUCTURES) * len(MATCH3D_METHODS)
    assert set(CELLS) == set(MATCH3D_CELL_TOL)


# cells that cost 7-13 s each here beyond what the other cells compile (a 60,000-sample mesh sampler and
# 48^3 mesh templates; new points / Gaussian splat sizes; LM runs of 0.5-0.9 s, twice): marked slow (still run
# in CI, last)
SLOW = {("mesh", "phase_correlation3d"), ("points", "lm_rotation_z3d"), ("mesh", "lm_rotation_z3d"),
        ("points", "lm_translation_scale3d"), ("mesh", "lm_translation_scale3d"), ("gaussians", "lm_translation_scale3d")}


@pytest.mark.parametrize("structure,method", [pytest.param(s, m, marks=pytest.mark.slow) if (s, m) in SLOW else (s, m)
                                              for s, m in CELLS], ids=[f"{s}-{m}" for s, m in CELLS])
def test_grid_cell(structure, method):
    """The template found at its known pose within the cell's tolerance, better than the null,
    and the same scene without the object gives valid=False."""
    r = run_grid_cell(structure, method)
    tol = MATCH3D_CELL_TOL[(structure, method)]
    unit = "deg" if method in ("moments_pose3d", "lm_rotation_z3d") else "voxel"
    print(f"\ngrid cell ({structure}, {method}): error {r['error']:.4f} {unit} (tol {tol}), null {r['null']:.3f}, "
          f"score {r['score']:.3f}" + (f", scale error {r['scale_error']:.4f}" if "scale_error" in r else ""))
    assert r["valid"], r["reason"]
    assert r["error"] <= tol and r["error"] < r["null"]
    if "scale_error" in r:
        assert r["scale_error"] < MATCH3D_SCALE_TOL[structure]
    r0 = run_grid_cell(structure, method, with_object=False)
    assert not r0["valid"] and ("not found" in r0["reason"] or "invalid input" in r0["reason"])


def test_grid_cell_float32():
    r = run_grid_cell("voxel", "ncc3d+lk_translation3d", dtype=jnp.float32)
    assert r["match"].t.dtype == jnp.float32 and r["valid"]
    assert r["error"] <= MATCH3D_CELL_TOL[("voxel", "ncc3d+lk_translation3d")]


def test_fuse_to_voxel_mixed_structures():
    """A mesh, a point cloud and a Gaussian of one scene fused: each carries its weight's share of the
    mass, the fused centroid is the weighted mean of the items' centroids (ground truth here: each
    item's own centroid on the grid), and bad items fail with the op and the item's position."""
    sq = fsjax.Mesh(jnp.asarray([[0.0, 0, 2], [6, 0, 2], [6, 6, 2], [0, 6, 2]]), jnp.asarray([[0, 1, 2], [0, 2, 3]]))
    pts = fsjax.Points(jnp.asarray(np.random.default_rng(0).uniform(1, 5, (200, 3)) * [1, 1, 0] + [0, 0, 3]))
    g = fsjax.Gaussians(jnp.asarray([[3.0, 3.0, 4.0]]), jnp.log(jnp.full((1, 3), 0.7)), jnp.asarray([[1.0, 0, 0, 0]]),
                        jnp.asarray([5.0]), jnp.ones((1, 3)))
    sp, shp = (1.0, 1.0, 1.0), (7, 8, 8)
    fused = ops.fuse_to_voxel([sq, pts, g], sp, shape=shp, weights=[1.0, 2.0, 1.0], n=3000)
    assert abs(float(fused.data.sum()) - 4.0) < 1e-9

    def zc(v):  # centroid along z (index 0) of a grid
        z = np.arange(shp[0])[:, None, None]
        return float((np.asarray(v) * z).sum() / np.asarray(v).sum())

    parts = [ops.to_voxel(x, sp, shape=shp, n=3000, seed=i).data for i, x in enumerate((sq, pts, g))]
    want = (zc(parts[0]) + 2 * zc(parts[1]) + zc(parts[2])) / 4
    assert abs(zc(fused.data) - want) < 1e-9 and abs(zc(parts[0]) - 2) < 1e-9 and abs(zc(parts[1]) - 3) < 1e-9
    # null: summing without normalising lets the 3,000-sample mesh outweigh the rest
    raw = ops.fuse_to_voxel([sq, pts, g], sp, shape=shp, normalise=False, n=3000)
    assert zc(raw.data) < 2.2 < zc(fused.data)
    # an item entirely off the grid has no mass: NaN, not silently dropped
    off = fsjax.Points(jnp.asarray([[100.0, 0, 0]]))
    assert bool(jnp.all(jnp.isnan(ops.fuse_to_voxel([pts, off], sp, shape=shp).data)))
    with pytest.raises(TypeError, match=r"fuse_to_voxel: argument 'items' \[1\]"):
        ops.fuse_to_voxel([pts, jnp.zeros((3, 3))], sp, shape=shp)
    with pytest.raises(ValueError, match="fuse_to_voxel: argument 'weights'"):
        ops.fuse_to_voxel([pts], sp, shape=shp, weights=[-1.0])
    with pytest.raises(ValueError, match="fuse_to_voxel: argument 'items'"):
        ops.fuse_to_voxel(pts, sp, shape=shp)


@pytest.mark.slow  # ncc3d and lk_translation3d on three clean 48^3 scenes
def test_clean_scene_sub_voxel_floor_is_the_datas():
    """Why ncc3d's Newton peak on the clean bunny scene (0.0122 / 0.0255 / 0.0068 voxel, seeds 0-2) does not
    reach the reference's 0.011 on every seed: the least-squares minimum of the data itself (Lucas-Kanade
    started from the TRUE position) lies 0.0118 / 0.0174 / 0.0191 voxel off (the bunny splatted at another
    sub-voxel phase than the template's, then blurred), so no sub-voxel step on these volumes is exact there;
    Newton is within 0.01 voxel of that floor on every seed."""
    from fsjax.synth._match3d_more import translation_floor

    r = [translation_floor(seed=k) for k in range(3)]
    print("\n" + "; ".join(f"seed {k}: newton {x['newton']:.4f}, LK from the truth {x['lk_from_truth']:.4f}"
                           for k, x in enumerate(r)))
    assert sum(x["lk_from_truth"] > 0.011 for x in r) >= 2
    assert all(x["newton"] < x["lk_from_truth"] + 0.01 for x in r)
