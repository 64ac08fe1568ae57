"""Registration across structures: a CAD mesh against a partial scan, a volume against points, ...

:func:`register_cross` brings both structures onto points (:func:`fsjax.ops.to_points`: mesh ->
area-weighted surface samples, depth map -> back-projected pixels, volume -> voxel centres above a
level, Gaussians -> means), thins both to one voxel grid (:func:`fsjax.ops.voxel_downsample`, so two
structures of different sampling density describe alike), and registers them by local descriptors
+ RANSAC (:func:`global_registration`) or, from a known start, by ICP; the fine ICP runs on the
dense point sets. Conventions are those of :mod:`fsjax.fit.rigid` (``target ~ R source + t``).
"""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp

from .._checks import check_choice, check_positive, check_range, check_static_int, is_concrete
from ..ops import to_points, voxel_downsample
from ..types import Depth, Gaussians, Mesh, Points, Volume
from .global_reg import DESCRIPTORS, GlobalResult, global_registration
from .icp import ICPResult, icp

__all__ = ["register_cross", "CROSS_METHODS", "CROSS_KINDS"]

CROSS_METHODS = (*DESCRIPTORS, "icp")
# the structure names of the matching grid (docs/matching_grid.md's rows) and the sort each one is
CROSS_KINDS = {"points": Points, "mesh": Mesh, "depth": Depth, "voxel": Volume, "gaussians": Gaussians}
_KINDS = tuple(CROSS_KINDS.values())
_BUCKET = 4096


def _check_kind(fn: str, name: str, x: Any, kind: str | None) -> None:
    """An explicit kind must name the argument's sort (the sort decides; the string is a check)."""
    if kind is None:
        return
    k = check_choice(fn, f"{name}_kind", kind, tuple(CROSS_KINDS))
    if not isinstance(x, CROSS_KINDS[k]):
        raise TypeError(f"{fn}: argument '{name}_kind' is {k!r} ({CROSS_KINDS[k].__name__}) but argument '{name}' is "
                        f"{type(x).__name__}")


def _as_points(fn: str, name: str, x: Any, n: int, level: float, seed: int) -> Points:
    if not isinstance(x, _KINDS):
        raise TypeError(f"{fn}: argument '{name}' must be Points, Mesh, Depth, Volume or Gaussians; got "
                        f"{type(x).__name__}")
    p = to_points(x, n=n, level=level, seed=seed)
    if p.xyz.ndim != 2:
        raise ValueError(f"{fn}: argument '{name}' must be one structure (batch with jax.vmap)")
    ok = p.valid & jnp.all(jnp.isfinite(p.xyz), -1)
    xyz = jnp.where(ok[:, None], p.xyz, 0.0)
    # padded to a bucket of _BUCKET slots: two scans of different sizes share one compiled program
    pad = -xyz.shape[0] % _BUCKET
    xyz, ok = jnp.pad(xyz, ((0, pad), (0, 0))), jnp.pad(ok, (0, pad))
    return Points(xyz, valid=ok)  # normals dropped: both sides get PCA normals


def register_cross(
    source: Any,
    target: Any,
    *,
    voxel: float,
    method: str = "fpfh",
    source_kind: str | None = None,
    target_kind: str | None = None,
    key: jax.Array | None = None,
    radius: float | None = None,
    distance: float | None = None,
    overlap: float = 1.0,
    n: int = 20000,
    level: float = 0.5,
    n_hypotheses: int = 16384,
    max_points: int = 4096,
    init_R: Any = None,
    init_t: Any = None,
    refine: str | None = "point_to_plane",
    **icp_kwargs: Any,
) -> GlobalResult | ICPResult:
    """Register two 3-D structures of any kind (``target ~ R source + t``).

    Args:
        source, target: each a ``Points``, ``Mesh``, ``Depth``, ``Volume`` or ``Gaussians`` (one
            instance; the kind is the sort).
        voxel: edge of the common grid both point sets are thinned to before the descriptors
            (cloud units; about 1/50 of the object's size).
        method: ``"fpfh"``, ``"spin"`` or ``"shot"`` (descriptors + RANSAC, no start needed), or
            ``"icp"`` (from ``init_R``/``init_t``, default identity).
        source_kind, target_kind: optional names of the structures (``"points"``, ``"mesh"``,
            ``"depth"``, ``"voxel"``, ``"gaussians"``: the grid's rows, :data:`CROSS_KINDS`), the
            issue's ``register_cross(src, src_kind, dst, dst_kind, method)`` as keywords. The sort
            decides how a structure is read, so a kind only checks it: a kind that does not name
            the argument's sort raises ``TypeError`` naming both (a mesh passed where the caller
            meant a scan is refused rather than registered), an unknown kind ``ValueError``.
        key: PRNG key of RANSAC (default ``jax.random.key(0)``).
        radius: descriptor support radius (default ``5 voxel``).
        distance: RANSAC inlier distance and half the ICP gate (default ``1.5 voxel``).
        overlap: the fraction of the *source* that the target shows (trimmed ICP; a model
            against a one-sided scan: about 0.5).
        n: surface samples drawn from a mesh (static int).
        level: volume threshold (volumes only).
        n_hypotheses: RANSAC hypotheses (static int).
        max_points: capacity of each thinned set (static int); more occupied voxels raise
            ``ValueError`` (``voxel`` too fine), or under ``jit`` fail the result (reason ``too_few``
            is not used: ``converged=False`` with the coarse stage's reason).
        init_R, init_t: the start of ``method="icp"``.
        refine: ICP method of the refinement on the dense point sets (``None``: the RANSAC pose).
        **icp_kwargs: further :func:`fsjax.fit.icp` arguments.

    Returns:
        :class:`GlobalResult` (descriptor methods: ``coarse`` the RANSAC stage, ``refined`` the ICP on
        the dense sets) or :class:`ICPResult` (``method="icp"``). Failures say so in ``converged`` /
        ``reason`` (NaN pose), as those records do.

    Example:
        A CAD part (Hoppe's fandisk mesh) against a one-sided noisy scan of it turned by 50 degrees:

        >>> import numpy as np, jax.numpy as jnp
        >>> from fsjax.fit import register_cross, rotation_error_deg
        >>> from fsjax.synth import cad_scan_pair
        >>> pair = cad_scan_pair("fandisk", angle_deg=50.0, seed=0)
        >>> res = register_cross(pair["mesh"], fsjax.Points(jnp.asarray(pair["scan"])), voxel=0.02 * pair["diag"],
        ...                      overlap=0.5)
        >>> bool(res.converged), float(rotation_error_deg(res.refined.R, jnp.asarray(pair["R"]))) < 0.15
        (True, True)
    """
    fn = "register_cross"
    _check_kind(fn, "source", source, source_kind)
    _check_kind(fn, "target", target, target_kind)
    check_choice(fn, "method", method, CROSS_METHODS)
    check_positive(fn, "voxel", voxel)
    check_range(fn, "overlap", overlap, 0.0, 1.0, lo_open=True)
    n = check_static_int(fn, "n", n, lo=16)
    src = _as_points(fn, "source", source, n, level, 0)
    tgt = _as_points(fn, "target", target, n, level, 1)
    radius = 5.0 * voxel if radius is None else radius
    distance = 1.5 * voxel if distance is None else distance
    check_positive(fn, "radius", radius)
    check_positive(fn, "distance", distance)
    icp_kwargs.setdefault("max_correspondence_distance", 2.0 * distance)
    if method == "icp":
        return icp(src, tgt, method=refine or "point_to_plane", init_R=init_R, init_t=init_t, overlap=overlap,
                   **icp_kwargs)
    max_points = check_static_int(fn, "max_points", max_points, lo=16)
    ds = voxel_downsample(src, voxel=voxel, capacity=min(max_points, src.xyz.shape[0]))
    dt = voxel_downsample(tgt, voxel=voxel, capacity=min(max_points, tgt.xyz.shape[0]))
    for name, d in (("source", ds), ("target", dt)):
        if is_concrete(d.truncated) and bool(d.truncated):
            raise ValueError(f"{fn}: argument 'voxel' ({voxel}) is too fine for the {name}: more than max_points = "
                             f"{max_points} occupied voxels; use a larger voxel or raise max_points")
    thin_ok = ~(ds.truncated | dt.truncated)
    res = global_registration(jax.random.key(0) if key is None else key, ds, dt, radius=radius, distance=distance,
                              n_hypotheses=n_hypotheses, descriptor=method, refine=None, overlap=overlap)
    if refine is None:
        return res
    fine = icp(src, tgt, method=refine, init_R=res.coarse.R, init_t=res.coarse.t, overlap=overlap, **icp_kwargs)
    ok = res.coarse.converged & thin_ok
    fine = eqx.tree_at(lambda r: (r.converged, r.reason), fine,
                       (fine.converged & ok, jnp.where(ok, fine.reason, res.coarse.reason).astype(jnp.int32)))
    return GlobalResult(coarse=res.coarse, refined=fine, coarse_matches_R=res.coarse_matches_R,
                        n_descriptors=res.n_descriptors, n_truncated=res.n_truncated)
