"""The depth row of the 3-D matching grid (fsjax/synth/_match3d_depth.py): the scene (bunny + clutter)
seen by one camera as a Depth map, brought onto the grid by depth -> points -> to_voxel; each built
column within its tolerance (about 1.5-2x the largest error over seeds 0-2), beside its null, failing
closed on the same scene without the bunny; the column that a single view cannot support is pinned."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

import fsjax
from fsjax.synth import (
    MATCH3D_DEPTH_CELL_TOL,
    MATCH3D_DEPTH_METHODS,
    MATCH3D_DEPTH_NOT_APPLICABLE,
    MATCH3D_DEPTH_SCALE_TOL,
    match3d_depth_scene,
    run_depth_cell,
)
from fsjax.synth._match3d_depth import depth_to_grid

COLS = [m for m in MATCH3D_DEPTH_METHODS if m not in MATCH3D_DEPTH_NOT_APPLICABLE]
# the LM and Fourier-Mellin columns compile 7-11 s each on their own (shared with tests/ops/test_match3d.py
# and test_match3d_fm.py in a full run): marked slow
SLOW = ("lm_translation_scale3d", "lm_rotation_z3d", "fourier_mellin_z3d", "fourier_mellin_z3d+lm_rotation_z3d")
ROT = ("lm_rotation_z3d", "fourier_mellin_z3d", "fourier_mellin_z3d+lm_rotation_z3d", "chamfer_rotation_z3d")
# chamfer_rotation_z3d: its 48^3 / 24^3 program (shared with tests/ops/test_match3d_fm.py's slow cells);
# generalised_hough_rotation_z3d likewise (tests/ops/test_match3d_shape.py's slow cells)
SLOW = SLOW + ("chamfer_rotation_z3d", "generalised_hough_rotation_z3d")
ROT = ROT + ("generalised_hough_rotation_z3d",)


def test_depth_row_columns_are_all_accounted_for():
    assert set(COLS) | set(MATCH3D_DEPTH_NOT_APPLICABLE) == set(MATCH3D_DEPTH_METHODS)
    assert set(COLS) == set(MATCH3D_DEPTH_CELL_TOL)
    with pytest.raises(ValueError, match="run_depth_cell: argument 'method'.*not applicable"):
        run_depth_cell("moments_pose3d")


def test_depth_scene_is_a_partial_view():
    """The scene is one camera's depth map: one point per pixel with a return, all on the side of the
    bunny facing the camera (-z); the template is a view of the bunny alone; no pixel is left NaN."""
    sc, tp, truth = match3d_depth_scene(shift=(1.0, -2.0, 0.5), seed=0)
    assert isinstance(sc, fsjax.Depth) and isinstance(tp, fsjax.Depth)
    assert not bool(jnp.any(jnp.isnan(sc.z))) and not bool(jnp.any(jnp.isnan(tp.z)))
    pts = fsjax.ops.depth_to_points(tp)
    xyz = np.asarray(pts.xyz)[np.asarray(pts.valid)]
    c_t = np.full(3, 11.5)
    # the full surface reaches about 8 voxels either side of the centre along z; the view only the near side
    # (a few points of the far side show past the silhouette)
    assert xyz.shape[0] > 1000 and np.mean(xyz[:, 2] < c_t[2]) > 0.8
    np.testing.assert_allclose(truth["centre"], [24.5, 21.5, 24.0])
    with pytest.raises(ValueError, match="match3d_depth_scene: argument 'clutter'"):
        match3d_depth_scene(clutter=7)


@pytest.mark.parametrize("method", [pytest.param(m, marks=pytest.mark.slow) if m in SLOW else m for m in COLS])
def test_depth_cell(method):
    r = run_depth_cell(method)
    tol = MATCH3D_DEPTH_CELL_TOL[method]
    print(f"\ndepth cell {method}: error {r['error']:.4f} (tol {tol}), null {r['null']:.3f}, score {r['score']:.3f}"
          + "".join(f", {k} {r[k]:.4f}" for k in ("centre_error", "scale_error", "start_error") if k in r))
    assert r["valid"], r["reason"]
    assert r["error"] <= tol and r["error"] < r["null"]
    if method in ROT:
        assert r["centre_error"] < 0.2
    if "scale_error" in r:
        assert r["scale_error"] < MATCH3D_DEPTH_SCALE_TOL
    if "start_error" in r:  # the refinement beats its Fourier-Mellin start
        assert r["error"] < r["start_error"]
    if "null_centre" in r:  # the unturned chamfer3d refuses the turned bunny or places it worse
        assert not r["null_centre"] <= r["centre_error"]
    r0 = run_depth_cell(method, with_object=False)
    assert not r0["valid"] and ("not found" in r0["reason"] or "invalid input" in r0["reason"])


@pytest.mark.slow  # float32 compiles of ncc3d and lk_translation3d (shared with test_match3d.py in a full run)
def test_depth_cell_float32():
    r = run_depth_cell("ncc3d+lk_translation3d", dtype=jnp.float32)
    assert r["match"].t.dtype == jnp.float32 and r["valid"]
    assert r["error"] <= MATCH3D_DEPTH_CELL_TOL["ncc3d+lk_translation3d"]


def test_moments_pose3d_fails_closed_on_one_view():
    """Moments need the whole object: on one view of the bunny turned arbitrarily (no clutter) the
    visible part is another part of the surface than the template view's, and moments_pose3d refuses."""
    rng = np.random.default_rng(100)
    sc, tp, _ = match3d_depth_scene(shift=rng.uniform(-5, 5, 3), angles_deg=rng.uniform(-180, 180, 3), clutter=0,
                                    template_size=32)
    S, T = depth_to_grid(sc, 48), depth_to_grid(tp, 32)
    m = fsjax.ops.moments_pose3d(S, T, level=0.2 * float(jnp.max(T.data)))
    assert not bool(m.valid) and "not found" in m.message


@pytest.mark.slow  # two more scenes rendered
def test_occluding_clutter_breaks_the_rows_margin():
    """Where the row breaks: with the shells that overlap the bunny's silhouette kept (``overlap=True``:
    in front they hide part of it, behind it they show through the template box), seed 0's bunny scores
    0.79 and the same scene WITHOUT the bunny 0.77 (measured; seeds 2 and 3 alike: 0.84 / 0.74, 0.72 / 0.78).
    No min_score separates them: ncc3d's fixed threshold alone (``max_chance=1``) reports the empty scene
    as found. Its mirror test refuses it (z 1.14: the shells fit the template's mirror images as well;
    seeds 2, 3: z 0.44, 0.00) and still accepts the half-hidden bunny (z 2.61, 0.25 voxel off; seed 3
    z 2.54, seed 2 refused at z 1.58). The row leaves such clutter out (occlusion is not covered by this
    grid; the default scenes keep a 0.30+ margin)."""
    rng = np.random.default_rng(100)
    kw = dict(shift=rng.uniform(-5, 5, 3), seed=0, overlap=True)
    sc, tp, truth = match3d_depth_scene(**kw)
    sc0, _, _ = match3d_depth_scene(with_object=False, **kw)
    T = depth_to_grid(tp, 24)
    m1 = fsjax.ops.ncc3d(depth_to_grid(sc, 48), T)
    s1 = float(m1.score)
    m0 = fsjax.ops.ncc3d(depth_to_grid(sc0, 48), T)
    m0_fixed = fsjax.ops.ncc3d(depth_to_grid(sc0, 48), T, max_chance=1.0)
    print(f"\noverlapping clutter: bunny {s1:.3f} (valid {bool(m1.valid)}), without the bunny {float(m0.score):.3f} "
          f"(valid {bool(m0.valid)}; the fixed threshold alone {bool(m0_fixed.valid)})")
    assert abs(s1 - float(m0.score)) < 0.05  # the score margin is gone ...
    assert bool(m0_fixed.valid)  # ... so the threshold alone passes the empty scene
    assert not bool(m0.valid) and "not found" in m0.message  # the mirror test refuses it
    assert bool(m1.valid) and np.linalg.norm(np.asarray(m1.t) + 11.5 - truth["centre"]) < 0.5
    # the default scene of the same seed keeps the margin (test_depth_cell)
    r0 = run_depth_cell("ncc3d", with_object=False)
    assert not r0["valid"] and r0["score"] < s1 - 0.1
