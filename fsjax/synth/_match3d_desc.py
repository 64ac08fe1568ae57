"""Descriptor and feature cells of the 3-D matching grid (issue 17): the spherical-harmonic shape
descriptor, measured on the bundled meshes in each structure beside a rotation-dependent null
and a scene without the object.

Kept apart from :mod:`fsjax.synth._match3d` (the pose/position cells): a descriptor answers
"is this the same shape, in any orientation", not "where is it", so its figures are
similarities, not pose errors.
"""

from __future__ import annotations

import time
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ..types import Points, Volume
from ._match3d import match3d_object, match3d_scene, rotation_zyx

__all__ = ["MATCH3D_DESC_METHODS", "MATCH3D_DESC_STRUCTURES", "MATCH3D_DESC_NOT_YET", "MATCH3D_DESC_MIN",
           "run_descriptor_cell", "harris3d_repeatability", "icp_floor"]

MATCH3D_DESC_METHODS = ("sh_descriptor3d",)
MATCH3D_DESC_STRUCTURES = ("voxel", "points", "mesh", "depth", "gaussians")
MATCH3D_DESC_NOT_YET = {
    ("depth", "sh_descriptor3d"): "not applicable as such: a depth map is a partial view, and the descriptor "
                                  "describes a whole shape (a partial view has another centre and shells)",
}
# per cell: the similarity that counts as "the same shape" (``valid``), and the similarity to
# the rotated copy the test asserts (about the measured minimum over seeds, minus a margin)
MATCH3D_DESC_MIN = {("voxel", "sh_descriptor3d"): (0.93, 0.995), ("points", "sh_descriptor3d"): (0.93, 0.96),
                    ("mesh", "sh_descriptor3d"): (0.93, 0.995), ("gaussians", "sh_descriptor3d"): (0.93, 0.965)}


def _null_similarity(a: Volume | Points, b: Volume | Points, level_a: float, level_b: float) -> float:
    """The null: the same shells and harmonics, but the raw coefficients ``a_slm`` (which turn
    with the shape) compared instead of their per-degree energies."""
    from ..ops.match3d._shdesc import _sh_coefficients, _volume_masses

    def coef(x, level):
        if isinstance(x, Volume):
            p, w, dt = _volume_masses(x, level)
        else:
            p, w, dt = x.xyz, x.valid.astype(x.xyz.dtype), x.xyz.dtype
        A, _ = _sh_coefficients(p, w, jnp.asarray(2.5, dt), 4, 4)
        A = np.asarray(A).ravel()
        return A / np.linalg.norm(A)

    return float(1.0 - np.linalg.norm(coef(a, level_a) - coef(b, level_b)))


def _scene(structure: str, name: str, R: np.ndarray, shift: np.ndarray, seed: int, with_object: bool, dtype: Any):
    """(scene, template) of one structure: the object alone turned by ``R`` (voxel: with 1 %
    noise; points: a fresh draw of 20,000 samples; mesh: the mesh itself; Gaussians: the grid's
    Gaussians scene and template splatted to voxels as the grid's cells do), or, with
    ``with_object=False``, six clutter shells and nothing else."""
    from ._match3d import _on_grid

    dt = jnp.result_type(float) if dtype is None else dtype
    if structure == "points":
        tpl = Points(jnp.asarray(match3d_object(name, 16.0, 20000, seed), dt))
        if with_object:
            q = match3d_object(name, 16.0, 20000, seed + 1000) @ R.T + 23.5 + shift
            return Points(jnp.asarray(q, dt)), tpl
        scene, _, _ = match3d_scene(name, structure="points", with_object=False, seed=seed, dtype=dtype)
        xyz = np.asarray(scene.xyz)
        return Points(jnp.asarray(xyz[np.all(xyz > -100, 1)], dt)), tpl  # drop the far dummy point
    angles = np.degrees(_zyx_angles(R))
    kw = dict(shift=shift, angles_deg=angles, seed=seed, dtype=dtype, template_size=24, structure=structure,
              noise=0.01 if structure == "voxel" else 0.0, clutter=0 if with_object else 6, with_object=with_object)
    scene, tpl, _ = match3d_scene(name, **kw)
    if structure in ("mesh", "gaussians"):
        scene, tpl = _on_grid(scene, 48, 1.0), _on_grid(tpl, 24, 1.0)
    return scene, tpl


def _zyx_angles(R: np.ndarray) -> np.ndarray:
    """Angles ``(a, b, c)`` (radians) with ``R = Rz(a) Ry(b) Rx(c)``."""
    b = np.arcsin(-np.clip(R[2, 0], -1, 1))
    return np.array([np.arctan2(R[1, 0], R[0, 0]), b, np.arctan2(R[2, 1], R[2, 2])])


def run_descriptor_cell(structure: str, method: str = "sh_descriptor3d", *, seed: int = 0, with_object: bool = True,
                        dtype: Any = None, timing: bool = False) -> dict:
    """Run one descriptor cell: the bunny's descriptor against its copy at a random rotation.

    Returns a dict: ``similarity`` (template vs the rotated copy in the scene), ``null`` (the
    same with the rotation-dependent raw coefficients), ``other`` (the largest similarity of
    the bunny's template to the spot and fandisk scenes, same setup), ``valid`` (``similarity``
    at least the cell's "same shape" level), ``time_first_s`` / ``time_s`` (descriptor of the
    scene: first call, and a second call with ``timing=True``). ``with_object=False``: the scene
    holds clutter shells only (``valid`` must be False).
    """
    from .. import ops

    if (structure, method) in MATCH3D_DESC_NOT_YET:
        raise ValueError(f"run_descriptor_cell: cell ({structure}, {method}) is "
                         f"{MATCH3D_DESC_NOT_YET[(structure, method)]}")
    if method != "sh_descriptor3d":
        raise ValueError(f"run_descriptor_cell: argument 'method' must be one of {MATCH3D_DESC_METHODS}; got {method!r}")
    rng = np.random.default_rng(200 + seed)
    R = rotation_zyx(rng.uniform(-180, 180, 3))
    shift = rng.uniform(-5, 5, 3)

    def desc(x):
        if isinstance(x, Points):
            return ops.points_sh_descriptor(x)
        return ops.sh_descriptor3d(x, level=0.05 * float(jnp.max(x.data)))

    def level(x):
        return 0.05 * float(jnp.max(x.data)) if isinstance(x, Volume) else 0.0

    scene, tpl = _scene(structure, "bunny", R, shift, seed, with_object, dtype)
    t0 = time.perf_counter()
    ds = jax.block_until_ready(desc(scene))
    t1 = time.perf_counter()
    if timing:
        jax.block_until_ready(desc(scene))
    t2 = time.perf_counter()
    dtpl = desc(tpl)
    sim = float(ops.sh_similarity3d(dtpl, ds))
    lo = MATCH3D_DESC_MIN[(structure, method)][0]
    out = {"similarity": sim, "valid": bool(sim >= lo), "descriptor": ds, "time_first_s": t1 - t0,
           "time_s": (t2 - t1) if timing else float("nan")}
    if with_object:
        out["null"] = _null_similarity(tpl, scene, level(tpl), level(scene))
        others = []
        for name in ("spot", "fandisk"):
            sc, _ = _scene(structure, name, R, shift, seed, True, dtype)
            others.append(float(ops.sh_similarity3d(dtpl, desc(sc))))
        out["other"] = max(others)
    return out


def harris3d_repeatability(*, seed: int = 0, n: int = 5000, angle_deg: float = 60.0, overlap: float = 0.7,
                           eps: float = 0.01, fresh: bool = False, dtype: Any = None, **kw) -> dict:
    """Repeatability of :func:`fsjax.ops.harris3d` on two crops of the bunny (unit size) sharing
    ``overlap`` of each, the second turned by ``angle_deg`` about the axis (0.2, 1, 0.5).

    The first crop keeps the low-x part of ``n`` samples, the second the high-x part of the same
    samples (``fresh=True``: of a fresh draw). Repeatability: the fraction of the first crop's
    keypoints inside the shared x-band that have a keypoint of the second (turned back) within
    ``eps``; the null does the same with as many random points of each crop. ``valid``: the
    detector found keypoints in both; ``kw`` goes to ``harris3d``.
    """
    from .. import ops
    from ..fit import rotation_from_axis_angle

    dt = jnp.result_type(float) if dtype is None else dtype
    keep = 1.0 / (2.0 - overlap)
    a = match3d_object("bunny", 1.0, n, seed)
    b = match3d_object("bunny", 1.0, n, seed + 1) if fresh else a
    xs = a[a[:, 0] <= np.quantile(a[:, 0], keep)]
    xt = b[b[:, 0] >= np.quantile(b[:, 0], 1.0 - keep)]
    R = np.asarray(rotation_from_axis_angle(jnp.array([0.2, 1.0, 0.5]), angle_deg))
    ka = ops.harris3d(Points(jnp.asarray(xs, dt)), **kw)
    kb = ops.harris3d(Points(jnp.asarray(xt @ R.T, dt)), **kw)
    pa = np.asarray(ka.xyz, float)[np.asarray(ka.valid)]
    pb = np.asarray(kb.xyz, float)[np.asarray(kb.valid)] @ R
    lo, hi = xt[:, 0].min(), xs[:, 0].max()

    def rep(p, q):
        p = p[(p[:, 0] >= lo) & (p[:, 0] <= hi)]
        q = q[(q[:, 0] >= lo) & (q[:, 0] <= hi)]
        if len(p) == 0 or len(q) == 0:
            return float("nan"), len(p)
        return float(np.mean(np.linalg.norm(p[:, None] - q[None], axis=-1).min(1) < eps)), len(p)

    r, n_in = rep(pa, pb)
    rng = np.random.default_rng(seed)
    null, _ = rep(xs[rng.choice(len(xs), len(pa))], xt[rng.choice(len(xt), len(pb))])
    return {"repeatability": r, "null": null, "n_keypoints": (len(pa), len(pb)), "n_shared": n_in,
            "valid": bool(len(pa) > 0 and len(pb) > 0), "keypoints": ka}


# the variants of icp_floor: (name, one draw for both crops, ICP method, trimmed fraction kept)
ICP_FLOOR_VARIANTS = (("independent draws, point-to-plane, trim 0.7 (measure_global's fine stage)", False,
                       "point_to_plane", 0.7),
                      ("one draw for both crops, point-to-plane, trim 0.7", True, "point_to_plane", 0.7),
                      ("independent draws, point-to-plane, trim 0.5", False, "point_to_plane", 0.5),
                      ("independent draws, GICP, trim 0.7", False, "gicp", 0.7))


def icp_floor(*, seed: int = 0, n: int = 10000, variants: Any = ICP_FLOOR_VARIANTS, start_deg: float = 0.0) -> dict:
    """Where "descriptor + RANSAC + ICP" ends on the global-registration crops, and why.

    The fine stage of ``fsjax.fit.global_reg._measure_global`` (issue 4's scene: two bunny crops
    sharing 70 % of each, 60 deg apart plus a translation; trimmed point-to-plane ICP, overlap 0.7,
    gate 20 mm, on crops of ``n`` samples drawn independently, seeds ``seed + 10`` and ``seed + 11``)
    run from the TRUE pose turned by ``start_deg`` (about (1, -0.3, 0.4)) instead of the descriptor's
    coarse pose, so the descriptor has no say; each variant changes one thing (``variants``: the
    name, one draw for both crops, the ICP method, the trimmed fraction). Returns ``{name: (rotation
    error deg, translation error in the crops' unit, iterations, converged)}``.
    """
    from ..data import surface_points
    from ..fit import icp
    from ..fit.rigid import rotation_error_deg, rotation_from_axis_angle

    keep = 1.0 / (2.0 - 0.7)
    R = np.asarray(rotation_from_axis_angle(jnp.array([0.2, 1.0, 0.5]), 60.0))
    shift = np.array([0.05, 0.02, -0.03])
    R0 = np.asarray(rotation_from_axis_angle(jnp.array([1.0, -0.3, 0.4]), start_deg)) @ R
    a, b = surface_points("bunny", n, seed + 10), surface_points("bunny", n, seed + 11)
    out = {}
    for name, one_draw, method, trim in variants:
        bb = a if one_draw else b
        xs = a[a[:, 0] <= np.quantile(a[:, 0], keep)]
        xt = bb[bb[:, 0] >= np.quantile(bb[:, 0], 1.0 - keep)]
        f = icp(jnp.asarray((xs - shift) @ R), jnp.asarray(xt), method=method, init_R=jnp.asarray(R0),
                init_t=jnp.asarray(shift), overlap=trim, max_correspondence_distance=0.02,
                min_inlier_fraction=0.35, max_iterations=100, rot_tol=1e-5, trans_tol=1e-5)
        out[name] = (float(rotation_error_deg(f.R, jnp.asarray(R))), float(np.linalg.norm(np.asarray(f.t) - shift)),
                     int(f.iterations), bool(f.converged))
    return out


def sh_voxel_resolution(seed: int = 0, extent: float = 16.0, noise: float = 0.01, structure: str = "voxel",
                        n: int | None = None) -> float:
    """The voxel (or mesh) descriptor cell's similarity (the bunny's template vs its copy at the cell's random
    rotation, no clutter) with the bunny ``extent`` voxels across (the grid's 16; scene ``2 extent + 16`` voxels,
    template box ``1.25 extent + 4``, samples ``20,000 (extent / 16)^2``: the grid's density per area) and
    ``noise`` (the grid's 0.01; voxel scenes only): how far the voxel cell's 0.998 is the voxelisation of a
    16-voxel object. ``structure="mesh"``: the mesh cell's route instead (the bunny's mesh turned, scene and
    template each brought onto the grid by ``n`` area-weighted samples, default the grid's density per area,
    and ``gaussian3d(sigma=1)``)."""
    from .. import ops
    from ._match3d import _on_grid

    if structure not in ("voxel", "mesh"):
        raise ValueError(f"sh_voxel_resolution: argument 'structure' must be 'voxel' or 'mesh'; got {structure!r}")
    rng = np.random.default_rng(200 + seed)
    R = rotation_zyx(rng.uniform(-180, 180, 3))
    shift = rng.uniform(-5, 5, 3)
    size, ts = int(2 * extent + 16), int(1.25 * extent + 4)
    n_grid = int(20000 * (extent / 16.0) ** 2)
    sc, tp, _ = match3d_scene("bunny", size=size, extent=extent, shift=shift, angles_deg=np.degrees(_zyx_angles(R)),
                              seed=seed, template_size=ts, structure=structure,
                              noise=noise if structure == "voxel" else 0.0, clutter=0, n=n_grid)
    if structure == "mesh":
        k = n_grid if n is None else int(n)
        sc, tp = _on_grid(sc, size, 1.0, n=k), _on_grid(tp, ts, 1.0, n=k)

    def desc(x):
        return ops.sh_descriptor3d(x, level=0.05 * float(jnp.max(x.data)))

    return float(ops.sh_similarity3d(desc(tp), desc(sc)))
