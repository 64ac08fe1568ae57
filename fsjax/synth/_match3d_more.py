"""More columns of the 3-D matching grid (beside :data:`fsjax.synth.MATCH3D_METHODS`, same scenes
and conventions as :func:`fsjax.synth.run_grid_cell`): Fourier-Mellin about z, the rotation
refinement started from it, and chamfer matching (translation; with a turn about z).

* ``fourier_mellin_z3d``: the bunny turned by a random angle in ``[-180, 180)`` degrees about z
  and moved (+-5 voxels) among six clutter shells with 1 % noise; the template is the bunny
  unturned in a volume of the scene's size (the method compares whole volumes).
* ``fourier_mellin_z3d+lm_rotation_z3d``: the same scene; the Fourier-Mellin pose, moved onto
  the 24^3 template box, starts :func:`fsjax.ops.lm_rotation_z3d`.
* ``chamfer_rotation_z3d``: the Fourier-Mellin scenes, the unturned bunny's 24^3 box as template,
  occupancy as ``chamfer3d``'s; the null is the unturned ``chamfer3d`` (and the identity rotation).
* ``chamfer3d``: the scene of the ``ncc3d`` cell (the bunny moved among clutter, 24^3 template);
  occupancy at 0.3 of the template's peak, in scene and template (the mesh row's scene at the
  template's mass per unit area, :func:`fsjax.synth._match3d.mesh_scene_at_template_density`).
"""

from __future__ import annotations

from typing import Any

import jax.numpy as jnp
import numpy as np

from ..types import Match3D
from ._match3d import (
    _on_grid,
    _rot_err_deg,
    com_null,
    match3d_scene,
    mesh_scene_at_template_density,
    timed_call,
)

__all__ = ["MATCH3D_MORE_METHODS", "MATCH3D_MORE_NOT_YET", "MATCH3D_MORE_CELL_TOL", "run_more_cell"]

MATCH3D_MORE_METHODS = ("fourier_mellin_z3d", "fourier_mellin_z3d+lm_rotation_z3d", "chamfer3d", "chamfer_rotation_z3d")

MATCH3D_MORE_NOT_YET = {
    **{("depth", m): "the depth row: fsjax/synth/_match3d_depth.py (run_depth_cell, tests/ops/test_match3d_depth.py)"
       for m in MATCH3D_MORE_METHODS},
}

# mesh cells whose scene is brought to the template's mass per unit area (fsjax.synth._match3d.MESH_AREA_DENSITY;
# chamfer3d: its occupancy level is a fraction of the template's peak, so the bunny's density must be the
# template's; the refined Fourier-Mellin cell: lm_rotation_z3d compares intensities without a gain)
MESH_MORE_AREA_DENSITY = ("fourier_mellin_z3d+lm_rotation_z3d", "chamfer3d", "chamfer_rotation_z3d")

# the refined Fourier-Mellin cell's lm_rotation_z3d support (the residuals over the template's voxels above this
# fraction of its range) per row; elsewhere the whole box. On the mesh row the scene is at the template's mass per
# area everywhere, clutter included, so the icospheres that reach into the bunny's 24^3 box weigh as much as the
# bunny: over the whole box the least-squares angle is 2.7 degrees off on seed 2 (the LM found it: 0.61 -> 2.69),
# over the support 0.2 degree
FM_LM_SUPPORT = {"mesh": 0.02, "gaussians": 0.02}

# degrees; about twice the largest error measured over seeds 0-2 (the test runs seed 0)
MATCH3D_MORE_CELL_TOL = {
    ("voxel", "fourier_mellin_z3d"): 2.5, ("points", "fourier_mellin_z3d"): 3.0, ("mesh", "fourier_mellin_z3d"): 3.0,
    ("voxel", "fourier_mellin_z3d+lm_rotation_z3d"): 1.2, ("points", "fourier_mellin_z3d+lm_rotation_z3d"): 1.5,
    # voxels (chamfer3d)
    ("voxel", "chamfer3d"): 0.2, ("points", "chamfer3d"): 0.4,
    # gaussians: about 1.7x the largest error over seeds 0-2 (1.98 degrees; 0.24 voxel)
    ("gaussians", "fourier_mellin_z3d"): 3.5, ("gaussians", "chamfer3d"): 0.4,
    # mesh (the scene at the template's mass per area): about twice the largest over seeds 0-2 (0.103 voxel)
    ("mesh", "chamfer3d"): 0.2,
    # the refined cells with lm_rotation_z3d's support (FM_LM_SUPPORT), about twice the largest over seeds 0-2:
    # mesh 0.046 / 0.039 / 0.087 degree from FM starts of 0.98 / 0.47 / 0.61; Gaussians 0.286 / 0.029 / 0.150
    # from 0.59 / 1.98 / 1.51 (over the whole box: 0.028 / 0.309 / 0.860)
    ("mesh", "fourier_mellin_z3d+lm_rotation_z3d"): 0.2, ("gaussians", "fourier_mellin_z3d+lm_rotation_z3d"): 0.6,
    # chamfer_rotation_z3d (degrees; the centre within 0.5 voxel): about twice the largest over seeds 0-2
    # (voxel 0.26 / 0.52 / 0.12, points 0.85 / 0.27 / 0.12, mesh 0.27 / 0.69 / 0.12, Gaussians 0.65 / 0.40 / 0.42;
    # centres 0.03-0.09 voxel; least mean distance 0.08-0.11, the scenes without the bunny 0.46-2.5)
    ("voxel", "chamfer_rotation_z3d"): 1.0, ("points", "chamfer_rotation_z3d"): 1.7,
    ("mesh", "chamfer_rotation_z3d"): 1.4, ("gaussians", "chamfer_rotation_z3d"): 1.3,
}


def run_more_cell(structure: str, method: str, *, seed: int = 0, with_object: bool = True, dtype: Any = None,
                timing: bool = False, clean: bool = False) -> dict:
    """One Fourier-Mellin cell; the same dict as :func:`fsjax.synth.run_grid_cell` (``error`` the
    rotation error in degrees, ``centre_error`` in voxels, ``null`` the identity rotation's error,
    and ``start_error``: the Fourier-Mellin start's rotation error for the refined column)."""
    from .. import ops

    if (structure, method) in MATCH3D_MORE_NOT_YET or method not in MATCH3D_MORE_METHODS:
        raise ValueError(f"run_more_cell: cell ({structure}, {method}) is not a built cell of this module")
    if method == "chamfer_rotation_z3d":
        return _chamfer_rot_cell(structure, seed=seed, with_object=with_object, dtype=dtype, timing=timing, clean=clean)
    if method == "chamfer3d":
        return _chamfer_cell(structure, seed=seed, with_object=with_object, dtype=dtype, timing=timing, clean=clean)
    rng = np.random.default_rng(200 + seed)
    size, ts = 48, 24
    kw = dict(shift=rng.uniform(-5, 5, 3), seed=seed, with_object=with_object, dtype=dtype, structure=structure,
              angles_deg=(rng.uniform(-180, 180), 0.0, 0.0), noise=0.01 if structure == "voxel" and not clean else 0.0,
              clutter=0 if clean else 6)
    scene, full, truth = match3d_scene(template_size=None, **kw)
    _, box, _ = match3d_scene(template_size=ts, **kw)
    if structure == "mesh" and method in MESH_MORE_AREA_DENSITY:
        scene = mesh_scene_at_template_density(scene, full, size)
        full, box = _on_grid(full, size, 1.0), _on_grid(box, ts, 1.0)
    elif structure != "voxel":
        scene, full, box = _on_grid(scene, size, 1.0), _on_grid(full, size, 1.0), _on_grid(box, ts, 1.0)
    c_full, c_box = np.full(3, (size - 1) / 2.0), np.full(3, (ts - 1) / 2.0)
    refine = method.endswith("+lm_rotation_z3d")

    def call():
        m = ops.fourier_mellin_z3d(scene, full)
        if not refine:
            return m, m
        # the same pose for the box template: its centre c_box is the full template's centre
        dt = m.t.dtype
        init = Match3D(m.R, m.apply(jnp.asarray(c_full, dt)) - m.scale * (m.R @ jnp.asarray(c_box, dt)),
                       m.score, m.valid, m.reason)
        return m, ops.lm_rotation_z3d(scene, box, init=init, support=FM_LM_SUPPORT.get(structure, 0.0))

    (m0, m), t_first, t_run = timed_call(call, timing)
    c_t = c_box if refine else c_full
    out = {"valid": bool(m.valid), "score": float(m.score), "reason": str(m.message), "match": m,
           "time_first_s": t_first, "time_s": t_run}
    out["error"] = _rot_err_deg(np.asarray(m.R), truth["R"]) if out["valid"] else float("nan")
    out["null"] = _rot_err_deg(np.eye(3), truth["R"])
    out["centre_error"] = float(np.linalg.norm(np.asarray(m.apply(jnp.asarray(c_t, m.t.dtype))) - truth["centre"]))
    if refine:
        out["start_error"] = _rot_err_deg(np.asarray(m0.R), truth["R"]) if bool(m0.valid) else float("nan")
    return out


def _chamfer_scene(structure, *, seed, with_object, dtype, clean, **kw):
    """Scene, template (24^3 box), truth and the occupancy level (0.3 of the template's peak) of the chamfer
    columns; ``kw`` goes to :func:`match3d_scene` (the shift, and the turn of the rotation column)."""
    size, ts = 48, 24
    scene, tpl, truth = match3d_scene(seed=seed, with_object=with_object, dtype=dtype, template_size=ts,
                                      structure=structure, noise=0.01 if structure == "voxel" and not clean else 0.0,
                                      clutter=0 if clean else 6, **kw)
    if structure == "mesh":
        scene, tpl = mesh_scene_at_template_density(scene, tpl, size), _on_grid(tpl, ts, 1.0)
    elif structure != "voxel":
        scene, tpl = _on_grid(scene, size, 1.0), _on_grid(tpl, ts, 1.0)
    return scene, tpl, truth, 0.3 * float(jnp.max(tpl.data))


def _chamfer_cell(structure, *, seed, with_object, dtype, timing, clean):
    """The chamfer column: as the ``ncc3d`` cell of :func:`run_grid_cell` (same seeds, scenes, null)."""
    from .. import ops

    rng = np.random.default_rng(100 + seed)
    ts = 24
    scene, tpl, truth, level = _chamfer_scene(structure, seed=seed, with_object=with_object, dtype=dtype, clean=clean,
                                              shift=rng.uniform(-5, 5, 3))

    def call():
        return ops.chamfer3d(scene, tpl, level=level)

    m, t_first, t_run = timed_call(call, timing)
    out = {"valid": bool(m.valid), "score": float(m.score), "reason": str(m.message), "match": m,
           "time_first_s": t_first, "time_s": t_run}
    c_t = np.full(3, (ts - 1) / 2.0)
    out["error"] = float(np.linalg.norm(np.asarray(m.apply(jnp.asarray(c_t, m.t.dtype))) - truth["centre"]))
    out["null"] = com_null(scene.data, truth["centre"])
    return out


def _chamfer_rot_cell(structure, *, seed, with_object, dtype, timing, clean):
    """The chamfer-with-rotation column: the Fourier-Mellin column's scenes (the bunny turned by a random
    angle about z and moved, same seeds), the unturned bunny's 24^3 box as the template, occupancy at 0.3 of
    the template's peak as ``chamfer3d``'s column. The null: the unturned ``chamfer3d`` on the same scene
    (``null`` its rotation error, the identity's; ``null_centre`` its centre error, NaN where it refuses)."""
    from .. import ops

    rng = np.random.default_rng(200 + seed)
    ts = 24
    shift = rng.uniform(-5, 5, 3)  # drawn before the angle, as before
    scene, tpl, truth, level = _chamfer_scene(structure, seed=seed, with_object=with_object, dtype=dtype, clean=clean,
                                              shift=shift, angles_deg=(rng.uniform(-180, 180), 0.0, 0.0))

    def call():
        return ops.chamfer_rotation_z3d(scene, tpl, level=level)

    m, t_first, t_run = timed_call(call, timing)
    c_t = np.full(3, (ts - 1) / 2.0)
    out = {"valid": bool(m.valid), "score": float(m.score), "reason": str(m.message), "match": m,
           "time_first_s": t_first, "time_s": t_run}
    out["error"] = _rot_err_deg(np.asarray(m.R), truth["R"]) if out["valid"] else float("nan")
    out["null"] = _rot_err_deg(np.eye(3), truth["R"])
    out["centre_error"] = float(np.linalg.norm(np.asarray(m.apply(jnp.asarray(c_t, m.t.dtype))) - truth["centre"]))
    m0 = ops.chamfer3d(scene, tpl, level=level)
    out["null_centre"] = (float(np.linalg.norm(np.asarray(m0.apply(jnp.asarray(c_t, m0.t.dtype))) - truth["centre"]))
                          if bool(m0.valid) else float("nan"))
    return out


def lm_rotation_floor(seed: int = 0, sigma: float = 1.0, start_offset_deg: float = 0.0) -> dict:
    """Where :func:`fsjax.ops.lm_rotation_z3d` ends on the clean voxel scene of the refined Fourier-Mellin
    column (no clutter, no noise; seeds ``200 + seed`` as :func:`run_more_cell`) when started from the TRUE
    pose turned by ``start_offset_deg`` about z, with scene and template blurred by ``sigma`` (the grid's 1.0):
    ``{"error_deg", "centre_error"}``. The same end from the truth and from a start off it says the error is
    the cost's minimum (the data's), not the start's or the solver's."""
    from .. import ops
    from ._match3d import rotation_zyx

    rng = np.random.default_rng(200 + seed)
    kw = dict(shift=rng.uniform(-5, 5, 3), seed=seed, structure="voxel", angles_deg=(rng.uniform(-180, 180), 0.0, 0.0),
              noise=0.0, clutter=0, sigma=sigma)
    scene, box, truth = match3d_scene(template_size=24, **kw)
    dt = scene.data.dtype
    R0 = rotation_zyx((start_offset_deg, 0.0, 0.0)) @ truth["R"]
    one = jnp.ones((), dt)
    init = Match3D(jnp.asarray(R0, dt), jnp.asarray(truth["t"], dt), one, jnp.asarray(True), jnp.asarray(0, jnp.int32))
    m = ops.lm_rotation_z3d(scene, box, init=init)
    c = jnp.full(3, 11.5, dt)
    return {"error_deg": _rot_err_deg(np.asarray(m.R), truth["R"]),
            "centre_error": float(np.linalg.norm(np.asarray(m.apply(c)) - truth["centre"]))}


def translation_floor(seed: int = 0, sigma: float = 1.0) -> dict:
    """The ``ncc3d`` column's clean voxel scene (no clutter, no noise; seeds ``100 + seed`` as
    :func:`fsjax.synth.run_grid_cell`), scene and template blurred by ``sigma`` (the grid's 1.0): the centre
    error of ``ncc3d``'s Newton peak (``newton``) and of :func:`fsjax.ops.lk_translation3d` started from the
    TRUE position (``lk_from_truth``: the least-squares minimum of the data, the floor any sub-voxel step
    on these volumes meets)."""
    from .. import ops

    rng = np.random.default_rng(100 + seed)
    scene, tpl, truth = match3d_scene(shift=rng.uniform(-5, 5, 3), seed=seed, template_size=24, structure="voxel",
                                      noise=0.0, clutter=0, sigma=sigma)
    dt = scene.data.dtype
    c = np.full(3, 11.5)
    m = ops.ncc3d(scene, tpl)
    init = Match3D(jnp.eye(3, dtype=dt), jnp.asarray(truth["t"], dt), jnp.ones((), dt), jnp.asarray(True),
                   jnp.asarray(0, jnp.int32))
    lk = ops.lk_translation3d(scene, tpl, init=init)
    return {"newton": float(np.linalg.norm(np.asarray(m.t) + c - truth["centre"])),
            "lk_from_truth": float(np.linalg.norm(np.asarray(lk.t) + c - truth["centre"]))}
