"""The gradient-direction columns of the 3-D matching grid (beside :data:`fsjax.synth.MATCH3D_METHODS`,
same scenes and conventions as :func:`fsjax.synth.run_grid_cell`): shape-based matching
(:func:`fsjax.ops.shape_locate3d`), the generalised Hough transform
(:func:`fsjax.ops.generalised_hough3d`) and curvature matching on the shape index
(:func:`fsjax.ops.shape_index_locate3d`, the second derivatives).

Both columns run on the scenes of the ``ncc3d`` cell (same seeds: the bunny moved by +-5 voxels
among six clutter shells, 1 % noise on voxel scenes, a 24^3 template), each row brought onto the
48^3 grid by the row's transform (:func:`fsjax.synth._match3d._on_grid`). The null is the scene's
centre of mass. The last 12 scenes are kept (the two columns of a row, and the tests, share them).
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ._match3d import _on_grid, com_null, match3d_scene, timed_call

__all__ = ["MATCH3D_SHAPE_METHODS", "MATCH3D_SHAPE_NOT_YET", "MATCH3D_SHAPE_CELL_TOL", "run_shape_cell"]

MATCH3D_SHAPE_METHODS = ("shape_locate3d", "generalised_hough3d", "shape_index_locate3d")

# the depth row's cells of these columns are built in fsjax/synth/_match3d_depth.py (run_depth_cell)
MATCH3D_SHAPE_NOT_YET = {
    ("depth", m): "the depth row: fsjax/synth/_match3d_depth.py (run_depth_cell, tests/ops/test_match3d_depth.py)"
    for m in MATCH3D_SHAPE_METHODS
}

# voxels; about 1.5-2x the largest error measured over seeds 0-2 (the test runs seed 0)
MATCH3D_SHAPE_CELL_TOL = {  # measured max over seeds 0-2 in the comments
    ("voxel", "shape_locate3d"): 0.08, ("voxel", "generalised_hough3d"): 0.15,  # 0.039, 0.088
    ("points", "shape_locate3d"): 0.2, ("points", "generalised_hough3d"): 0.25,  # 0.118, 0.167
    ("mesh", "shape_locate3d"): 0.1, ("mesh", "generalised_hough3d"): 0.12,  # 0.048, 0.069
    ("gaussians", "shape_locate3d"): 0.25, ("gaussians", "generalised_hough3d"): 0.15,  # 0.161, 0.093
    # curvature matching (fsjax.ops.shape_index_locate3d), the same scenes
    ("voxel", "shape_index_locate3d"): 0.15, ("points", "shape_index_locate3d"): 0.3,  # 0.073, 0.161
    ("mesh", "shape_index_locate3d"): 0.25, ("gaussians", "shape_index_locate3d"): 0.4,  # 0.147, 0.250
}

_SCENES: dict = {}


def _scene(structure: str, seed: int, with_object: bool, dtype: Any, clean: bool):
    key = (structure, seed, with_object, str(jnp.dtype(jnp.result_type(float) if dtype is None else dtype)), clean)
    if key not in _SCENES:
        if len(_SCENES) >= 12:
            _SCENES.pop(next(iter(_SCENES)))
        rng = np.random.default_rng(100 + seed)  # the ncc3d cell's seeds
        scene, tpl, truth = match3d_scene(shift=rng.uniform(-5, 5, 3), seed=seed, with_object=with_object,
                                          dtype=dtype, template_size=24, structure=structure,
                                          noise=0.01 if structure == "voxel" and not clean else 0.0,
                                          clutter=0 if clean else 6)
        if structure != "voxel":
            scene, tpl = _on_grid(scene, 48, 1.0), _on_grid(tpl, 24, 1.0)
        _SCENES[key] = (scene, tpl, truth)
    return _SCENES[key]


def run_shape_cell(structure: str, method: str, *, seed: int = 0, with_object: bool = True, dtype: Any = None,
                   timing: bool = False, clean: bool = False) -> dict:
    """One cell of the gradient-direction columns; the same dict as :func:`fsjax.synth.run_grid_cell`
    (``error`` and ``null`` in voxels; for ``generalised_hough3d`` its best instance)."""
    from .. import ops

    if (structure, method) in MATCH3D_SHAPE_NOT_YET or method not in MATCH3D_SHAPE_METHODS:
        raise ValueError(f"run_shape_cell: cell ({structure}, {method}) is not a built cell of this module")
    scene, tpl, truth = _scene(structure, seed, with_object, dtype, clean)
    ts = 24
    fn = getattr(ops, method)

    def call():
        return fn(scene, tpl)

    m, t_first, t_run = timed_call(call, timing)
    best = jax.tree_util.tree_map(lambda a: a[0], m) if m.batch_shape else m
    out = {"valid": bool(best.valid), "score": float(best.score), "reason": str(best.message), "match": m,
           "time_first_s": t_first, "time_s": t_run}
    c_t = np.full(3, (ts - 1) / 2.0)
    out["error"] = float(np.linalg.norm(np.asarray(best.apply(jnp.asarray(c_t, best.t.dtype))) - truth["centre"]))
    out["null"] = com_null(scene.data, truth["centre"])
    return out
