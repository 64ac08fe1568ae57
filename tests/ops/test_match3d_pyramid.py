"""ncc3d_pyramid: coarse-to-fine 3-D NCC (fsjax/ops/match3d/_pyramid3d.py). The grid column: the same
placement as the exhaustive ncc3d on the grid scenes, failing closed without the object; where it breaks:
a template too small for the levels (ValueError), and a decoy that equals the template at the coarse level
(top_k=1 follows it and fails closed; top_k=4 finds the object). Speed beside ncc3d (64^3, 128^3):
benchmarks/bench_ncc_pyramid.py (timing is not a test condition)."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

import fsjax

ops = fsjax.ops


def _decoy_scene():
    """A smooth template with texture; in the scene: the template at an odd offset (its coarse version
    is sampled at another phase) and a decoy, the template plus a checkerboard along x (which the
    [1, 3, 3, 1] reduce cancels exactly) at an even offset, so the decoy equals the template at the
    coarse level and outscores the object there."""
    rng = np.random.default_rng(0)
    k, i, j = np.mgrid[0:24, 0:24, 0:24]
    tpl = np.exp(-((k - 11.5) ** 2 / 16 + (i - 11.0) ** 2 / 10 + (j - 12.0) ** 2 / 22)) \
        + 0.3 * np.asarray(ops.gaussian3d(fsjax.Volume(rng.standard_normal((24, 24, 24))), sigma=1.0).data)
    scene = 0.01 * rng.standard_normal((48, 48, 48))
    scene[1:25, 3:27, 23:47] += tpl  # the object: offset (k, i, j) = (1, 3, 23), odd
    checker = np.where(j % 2 == 0, 1.0, -1.0) * 1.2 * tpl.std()
    scene[24:48, 22:46, 0:24] += tpl + checker  # the decoy: offset (24, 22, 0), even
    return fsjax.Volume(scene), fsjax.Volume(tpl)


def test_pyramid_top_k_carries_the_object_past_a_coarse_decoy():
    scene, tpl = _decoy_scene()
    m1 = ops.ncc3d_pyramid(scene, tpl, levels=1, top_k=1)
    m4 = ops.ncc3d_pyramid(scene, tpl, levels=1, top_k=4)
    print(f"\ndecoy: top_k=1 score {float(m1.score):.3f} valid {bool(m1.valid)}; top_k=4 t {np.round(m4.t, 3)} "
          f"score {float(m4.score):.3f}")
    # top_k=1 followed the decoy (its fine score is below min_score): fails closed, no wrong position
    assert not bool(m1.valid) and "not found" in m1.message and float(m1.score) < 0.7
    from fsjax.ops.match3d._pyramid3d import _pyramid_core

    off, _, _, _ = _pyramid_core(scene.data, tpl.data, levels=1, top_k=1, window=2)
    np.testing.assert_allclose(np.asarray(off), [24.0, 22.0, 0.0], atol=0.2)  # (k, i, j): the decoy's place
    # top_k=4 carried the object down: found at its offset (x, y, z) = (23, 3, 1)
    assert bool(m4.valid) and float(m4.score) > 0.99
    np.testing.assert_allclose(np.asarray(m4.t), [23.0, 3.0, 1.0], atol=0.05)
    # the exhaustive search (the pyramid with no level) agrees
    np.testing.assert_allclose(np.asarray(ops.ncc3d(scene, tpl).t), np.asarray(m4.t), atol=1e-6)


def test_pyramid_refuses_levels_the_template_cannot_hold_and_flat_templates():
    scene, tpl = _decoy_scene()
    with pytest.raises(ValueError, match=r"ncc3d_pyramid: argument 'levels' must leave .* at most 2 levels, got 3"):
        ops.ncc3d_pyramid(scene, tpl, levels=3)  # 24 -> 12 -> 6 -> 3 voxels
    with pytest.raises(ValueError, match="ncc3d_pyramid: argument 'top_k'"):
        ops.ncc3d_pyramid(scene, tpl, top_k=0)
    m = ops.ncc3d_pyramid(scene, fsjax.Volume(np.full((24, 24, 24), 0.3)))
    assert not bool(m.valid) and "invalid input" in m.message
    # levels=None picks the most levels that keep the coarsest template >= 8 voxels: 24 -> 12 (one level)
    from fsjax.ops.match3d._pyramid3d import _auto_levels

    assert _auto_levels((16, 16, 16)) == 1 and _auto_levels((48, 48, 48)) == 2 and _auto_levels((6, 12, 16)) == 0


# the depth row's cell: tests/ops/test_match3d_depth.py; mesh and Gaussians: their scenes' transforms compile
# for 10-13 s on their own (shared with tests/ops/test_match3d.py in a full run)
PYR_ROWS = ("voxel", "points", pytest.param("mesh", marks=pytest.mark.slow),
            pytest.param("gaussians", marks=pytest.mark.slow))


@pytest.mark.parametrize("structure", PYR_ROWS)
def test_pyramid_grid_cell(structure):
    """The ncc3d_pyramid column of the matching grid: within the cell's tolerance, better than the null
    (the scene's centre of mass), the same placement as the ncc3d cell, valid=False without the object."""
    from fsjax.synth import MATCH3D_PYR_CELL_TOL, run_grid_cell

    r = run_grid_cell(structure, "ncc3d_pyramid")
    q = run_grid_cell(structure, "ncc3d")
    tol = MATCH3D_PYR_CELL_TOL[(structure, "ncc3d_pyramid")]
    print(f"\npyramid cell {structure}: error {r['error']:.4f} (tol {tol}; ncc3d {q['error']:.4f}), null {r['null']:.3f}")
    assert r["valid"] and r["error"] <= tol and r["error"] < r["null"]
    np.testing.assert_allclose(np.asarray(r["match"].t), np.asarray(q["match"].t), atol=1e-6)
    r0 = run_grid_cell(structure, "ncc3d_pyramid", with_object=False)
    assert not r0["valid"] and "not found" in r0["reason"]


@pytest.mark.slow  # a float32 compile of the pyramid and of ncc3d
def test_pyramid_grid_cell_float32():
    from fsjax.synth import MATCH3D_PYR_CELL_TOL, run_grid_cell

    r = run_grid_cell("voxel", "ncc3d_pyramid", dtype=jnp.float32)
    assert r["match"].t.dtype == jnp.float32 and r["valid"]
    assert r["error"] <= MATCH3D_PYR_CELL_TOL[("voxel", "ncc3d_pyramid")]
