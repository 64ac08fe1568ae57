"""Transforms between the 3-D structures: points -> voxels (Gaussians -> voxels:
:mod:`fsjax.ops.match3d._gaussvox`), and the ``to_points`` / ``to_voxel``
entry points that accept any structure (the rows of the 3-D matching grid).

Conventions:

* **Grid**: ``shape = (D, H, W)`` voxels, voxel ``[k, i, j]`` centred at
  ``origin + (j dx, i dy, k dz)`` with ``spacing = (dz, dy, dx)`` and ``origin = (x0, y0, z0)``
  in the input's unit -- the placement of :func:`fsjax.ops.mesh_to_volume` and
  :func:`fsjax.ops.tsdf_fuse`, so a structure brought onto a grid here lands where those put it.
* **Splatting** (:func:`points_to_volume`): each valid point adds its weight to the 8 voxels
  around it with trilinear weights (the adjoint of trilinear interpolation), so the volume's
  sum equals the total weight of the points inside the grid; a point outside the grid adds
  nothing to the voxels it misses (the op reports nothing of it: size the grid to hold the
  structure). The result is points per voxel, not a density per unit volume.
* What each structure becomes is stated by :func:`to_points` and :func:`to_voxel`; these two
  are plain functions (they take any of several sorts), not registered ops. Existing ops do
  the work wherever one exists (``sample_surface``, ``depth_to_points``, ``mesh_to_volume``).
"""

from __future__ import annotations

import functools
from typing import Any

import jax
import jax.numpy as jnp

from ..._checks import check_choice, check_finite_number, check_static_int
from ...registry import register
from ...types import Depth, Gaussians, Mesh, Points, Volume
from .._common import check_grid, check_one
from ..measure3d._camera import depth_to_points
from ..mesh._voxelize import mesh_to_volume
from ..points._search import sample_surface
from ..volume._distance3d import edt3d_squared
from ._gaussvox import gaussians_to_volume

__all__ = ["points_to_volume", "volume_to_sdf", "to_points", "to_voxel", "fuse_to_voxel"]


@functools.partial(jax.jit, static_argnames=("spacing",))
def _sdf_core(x, level, *, spacing):
    dt = x.dtype
    on = x > level
    half = 0.5 * min(float(v) for v in spacing)
    d_out = jnp.sqrt(edt3d_squared(on, spacing, dt))  # to the nearest foreground voxel centre
    d_in = jnp.sqrt(edt3d_squared(~on, spacing, dt))  # to the nearest background voxel centre
    inf = jnp.asarray(jnp.inf, dt)
    sdf = jnp.where(on, half - d_in, d_out - half)
    sdf = jnp.where(jnp.any(on), sdf, inf)
    return jnp.where(jnp.all(on), -inf, sdf)


@register(family="match3d", takes=Volume, gives=Volume, differentiable=False, refs=[
    "P. F. Felzenszwalb, D. P. Huttenlocher, Distance transforms of sampled functions, Theory of Computing 8, "
    "2012, 415-428"])
def volume_to_sdf(vol: Volume, /, *, level: float = 0.5) -> Volume:
    """Signed Euclidean distance of a voxel grid's foreground surface (voxel -> SDF), negative inside.

    The foreground is ``vol.data > level``. A background voxel gets its exact Euclidean distance
    to the nearest foreground voxel centre less ``h / 2``, a foreground voxel minus its distance to
    the nearest background voxel centre less ``h / 2`` (``h`` the smallest spacing): the surface
    sits halfway between the two voxel layers, where :func:`sdf_to_occupancy` puts it, so
    ``sdf_to_occupancy(volume_to_sdf(m))`` is the mask ``m`` again. Two exact distance transforms
    (Felzenszwalb and Huttenlocher's lower envelope per axis, the spacing honoured). Voxel-exact:
    the surface of the mask, not of the object the mask came from (a ball's signed distance is
    off by up to about half a voxel near its surface).

    Args:
      vol: ``Volume`` ``(D, H, W)``; its spacing is honoured.
      level: foreground threshold (default 0.5: a 0/1 mask).

    Returns:
      ``Volume`` of signed distances in ``vol.unit``, same grid; ``+inf`` everywhere when there
      is no foreground voxel, ``-inf`` when there is no background voxel.

    Example:
      A ball of radius 5.5 voxels (its voxels within 5.5 of the centre): the centre is 5.157
      inside (its nearest background voxel, 4 voxels along two axes, is sqrt(32) = 5.657 away, less
      half a voxel), a voxel 9 voxels out along an axis is 3.5 out (the ball's last voxel is 5
      out), and the mask comes back from the signed distance:

      >>> import numpy as np, fsjax
      >>> k, i, j = np.mgrid[0:21, 0:21, 0:21]
      >>> ball = (((k - 10) ** 2 + (i - 10) ** 2 + (j - 10) ** 2) <= 5.5 ** 2).astype(float)
      >>> d = fsjax.ops.volume_to_sdf(fsjax.Volume(ball)).data
      >>> round(float(d[10, 10, 10]), 3), float(d[10, 10, 19])
      (-5.157, 3.5)
      >>> bool((np.asarray(fsjax.ops.sdf_to_occupancy(fsjax.Volume(d)).data) == ball).all())
      True
    """
    op = "volume_to_sdf"
    check_one(op, "vol", vol, Volume, "data", ndim=3)
    check_finite_number(op, "level", level)
    dt = jnp.result_type(vol.data.dtype, jnp.float32)
    return Volume(_sdf_core(vol.data.astype(dt), jnp.asarray(level, dt), spacing=tuple(float(v) for v in vol.spacing)),
                  vol.spacing, vol.unit)


@functools.partial(jax.jit, static_argnames=("shape", "spacing"))
def _splat_core(xyz, w, origin, *, shape, spacing):
    D, H, W = shape
    dz, dy, dx = spacing
    dt = xyz.dtype
    u = (xyz - origin) / jnp.asarray([dx, dy, dz], dt)  # (x, y, z) in voxels
    base = jnp.floor(u)
    f = u - base
    b = base.astype(jnp.int32)
    out = jnp.zeros(D * H * W, dt)
    for oz in (0, 1):
        for oy in (0, 1):
            for ox in (0, 1):
                j, i, k = b[:, 0] + ox, b[:, 1] + oy, b[:, 2] + oz
                wt = (jnp.where(ox, f[:, 0], 1 - f[:, 0]) * jnp.where(oy, f[:, 1], 1 - f[:, 1])
                      * jnp.where(oz, f[:, 2], 1 - f[:, 2]))
                inside = (j >= 0) & (j < W) & (i >= 0) & (i < H) & (k >= 0) & (k < D)
                idx = jnp.where(inside, (k * H + i) * W + j, 0)
                out = out.at[idx].add(jnp.where(inside, wt * w, 0.0))
    return out.reshape(D, H, W)


@register(family="match3d", takes=Points, gives=Volume, differentiable=True, refs=[
    "J. Westover, Footprint evaluation for volume rendering, SIGGRAPH 1990 (splatting)",
    "R. W. Hockney, J. W. Eastwood, Computer Simulation Using Particles, McGraw-Hill 1981 "
    "(cloud-in-cell assignment)"])
def points_to_volume(pts: Points, /, *, shape: tuple[int, int, int] = (16, 16, 16),
                     spacing: tuple[float, float, float] = (1.0, 1.0, 1.0),
                     origin: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> Volume:
    """Splat a point cloud onto a voxel grid with trilinear weights (cloud-in-cell).

    Each valid point ``p`` adds ``(1 - fx)(1 - fy)(1 - fz)``-style weights to the 8 voxels
    around it (``f`` its fractional voxel position): the adjoint of trilinear interpolation
    (Hockney and Eastwood's cloud-in-cell assignment). The volume sums to the number of valid
    points inside the grid, and its centre of mass is the points' centroid exactly (the
    weights interpolate linearly), so a sub-voxel move of the cloud moves the volume's
    moments by the same amount.

    Args:
      pts: ``Points`` ``(N, 3)`` (one cloud; batch with ``jax.vmap``); invalid slots add nothing.
      shape: ``(D, H, W)`` voxels (static ints >= 1; default ``(16, 16, 16)``).
      spacing: voxel size ``(dz, dy, dx)`` in the points' unit (static, positive).
      origin: ``(x0, y0, z0)``, the position of voxel ``[0, 0, 0]``'s centre (static).

    Returns:
      ``Volume`` ``(D, H, W)`` with ``spacing``: points per voxel (trilinear shares).
      Differentiable in the point positions (piecewise linear).

    Example:
      One point at the centre of 8 voxels gives 1/8 to each; a point on a voxel centre all to
      it; the total is the number of points and the centre of mass is their centroid:

      >>> import jax.numpy as jnp, fsjax
      >>> pts = fsjax.Points(jnp.asarray([[1.5, 1.5, 1.5], [2.0, 1.0, 3.0]]))
      >>> v = fsjax.ops.points_to_volume(pts, shape=(5, 4, 4))
      >>> float(v.data[1, 1, 1]), float(v.data[2, 2, 2]), float(v.data[3, 1, 2]), float(v.data.sum())
      (0.125, 0.125, 1.0, 2.0)
      >>> k, i, j = jnp.mgrid[0:5, 0:4, 0:4]
      >>> [float((v.data * a).sum() / v.data.sum()) for a in (j, i, k)]
      [1.75, 1.25, 2.25]
    """
    op = "points_to_volume"
    check_one(op, "pts", pts, Points, "xyz")
    shp, sp, org = check_grid(op, shape, spacing, origin)
    dt = pts.xyz.dtype
    w = pts.valid.astype(dt)
    xyz = jnp.where(pts.valid[:, None], pts.xyz, 0.0)
    return Volume(_splat_core(xyz, w, jnp.asarray(org, dt), shape=shp, spacing=sp), spacing=sp)


def to_points(x: Any, /, *, n: int = 4096, level: float = 0.5, seed: int = 0) -> Points:
    """Any 3-D structure as a point set (the "points" column of the matching grid).

    * ``Points``: itself.
    * ``Mesh``: ``n`` area-weighted surface samples with normals (:func:`sample_surface`).
    * ``Depth``: every pixel back-projected (:func:`depth_to_points`; no-return pixels invalid).
    * ``Volume``: the centres of the voxels whose value is above ``level`` (``(x, y, z)`` =
      ``(j dx, i dy, k dz)``), one slot per voxel, the others invalid.
    * ``Gaussians``: their means (valid where the splat is valid); extents and opacities are
      dropped.

    Args:
      x: a ``Points``, ``Mesh``, ``Depth``, ``Volume`` or ``Gaussians`` (one instance).
      n: samples drawn from a mesh (static int >= 1).
      level: the volume threshold (volumes only).
      seed: seed of the mesh sampling.

    Example:
      >>> import jax.numpy as jnp, fsjax
      >>> vol = fsjax.Volume(jnp.zeros((2, 3, 4)).at[1, 2, 3].set(1.0), spacing=(2.0, 1.0, 0.5))
      >>> p = fsjax.ops.to_points(vol)
      >>> p.xyz[p.valid].tolist()
      [[1.5, 2.0, 2.0]]
    """
    if isinstance(x, Points):
        return x
    if isinstance(x, Mesh):
        return sample_surface(x, n=n, seed=seed)
    if isinstance(x, Depth):
        return depth_to_points(x)
    if isinstance(x, Volume):
        d = x.data
        if d.ndim != 3:
            raise ValueError(f"to_points: argument 'x' must be one volume; got data of shape {d.shape}")
        dz, dy, dx = x.spacing
        k, i, j = jnp.meshgrid(*(jnp.arange(s, dtype=d.dtype) for s in d.shape), indexing="ij")
        xyz = jnp.stack([j * dx, i * dy, k * dz], -1).reshape(-1, 3)
        return Points(xyz, valid=(d > level).reshape(-1))
    if isinstance(x, Gaussians):
        return Points(x.means, valid=x.valid)
    raise TypeError(f"to_points: argument 'x' must be Points, Mesh, Depth, Volume or Gaussians; got "
                    f"{type(x).__name__}")


def to_voxel(x: Any, /, spacing: tuple[float, float, float], *, shape: tuple[int, int, int] | None = None,
             origin: tuple[float, float, float] = (0.0, 0.0, 0.0), mesh_kind: str = "surface",
             n: int = 8192, seed: int = 0) -> Volume:
    """Any 3-D structure on a voxel grid of ``spacing`` (the "voxel" column of the matching grid).

    * ``Volume``: itself, if its spacing is ``spacing`` (a resampling is not done here: a
      different spacing raises ``ValueError``).
    * ``Points``: trilinear splat (:func:`points_to_volume`).
    * ``Depth``: back-projected (:func:`depth_to_points`), then splatted.
    * ``Mesh``: ``mesh_kind="surface"`` (default): ``n`` area-weighted surface samples splatted,
      a surface density (cheap: ``O(n)``); ``"occupancy"`` or ``"sdf"``: the exact inside test /
      signed distance of :func:`mesh_to_volume` (``O(voxels x faces)``: small meshes only).
    * ``Gaussians``: footprint splat (:func:`gaussians_to_volume` with its defaults: each
      Gaussian's opacity as a mass spread by its density, prefiltered by 0.6 voxel).

    Args:
      x: the structure (one instance): ``Volume``, ``Points``, ``Mesh``, ``Depth`` or ``Gaussians``.
      spacing: ``(dz, dy, dx)`` in the structure's unit.
      shape: ``(D, H, W)``; required for everything but a ``Volume``.
      origin: ``(x0, y0, z0)``, the centre of voxel ``[0, 0, 0]``.
      mesh_kind: ``"surface"``, ``"occupancy"`` or ``"sdf"`` (meshes only).
      n: mesh surface samples (``mesh_kind="surface"``).
      seed: seed of the mesh sampling.

    Example:
      >>> import jax.numpy as jnp, fsjax
      >>> v = fsjax.ops.to_voxel(fsjax.Points(jnp.asarray([[1.0, 2.0, 0.0]])), (1.0, 1.0, 1.0), shape=(2, 3, 3))
      >>> float(v.data[0, 2, 1]), float(v.data.sum())
      (1.0, 1.0)
    """
    op = "to_voxel"
    sp = tuple(float(s) for s in spacing)
    if isinstance(x, Volume):
        if tuple(x.spacing) != sp:
            raise ValueError(f"{op}: argument 'x' is a Volume of spacing {x.spacing}, not {sp}; resampling is not "
                             f"done here")
        return x
    if shape is None:
        raise ValueError(f"{op}: argument 'shape' is required for a {type(x).__name__}")
    if isinstance(x, Mesh):
        check_choice(op, "mesh_kind", mesh_kind, ("surface", "occupancy", "sdf"))
        if mesh_kind != "surface":
            return mesh_to_volume(x, shape=shape, spacing=sp, origin=origin, kind=mesh_kind)
        x = sample_surface(x, n=check_static_int(op, "n", n, lo=1), seed=seed)
    elif isinstance(x, Depth):
        x = depth_to_points(x)
    elif isinstance(x, Gaussians):
        return gaussians_to_volume(x, shape=shape, spacing=sp, origin=origin)
    if not isinstance(x, Points):
        raise TypeError(f"{op}: argument 'x' must be Volume, Points, Mesh, Depth or Gaussians; got "
                        f"{type(x).__name__}")
    return points_to_volume(x, shape=shape, spacing=sp, origin=origin)


def fuse_to_voxel(items: Any, /, spacing: tuple[float, float, float], *, shape: tuple[int, int, int],
                  origin: tuple[float, float, float] = (0.0, 0.0, 0.0), weights: Any = None,
                  normalise: bool = True, n: int = 8192, seed: int = 0) -> Volume:
    """Several 3-D structures of any kinds fused on one voxel grid (the sum of their :func:`to_voxel`).

    Each item goes onto the grid by :func:`to_voxel` (points and depth maps: trilinear splat of
    their points; meshes: ``n`` surface samples; Gaussians: footprint splat; a ``Volume`` must
    already be on the grid: same ``spacing`` and ``shape``). With ``normalise`` (default) each
    item's grid is scaled to unit total mass first, so a 20,000-sample mesh and a 500-point scan
    count alike; ``weights`` then sets each item's share (default 1 each). The fused grid's total
    mass is ``sum(weights)`` when every item lies inside the grid.

    Args:
      items: a sequence of structures (``Points``, ``Mesh``, ``Depth``, ``Volume``, ``Gaussians``).
      spacing: ``(dz, dy, dx)``.
      shape: ``(D, H, W)``.
      origin: ``(x0, y0, z0)``, the centre of voxel ``[0, 0, 0]``.
      weights: one non-negative weight per item (default ones).
      normalise: scale each item to unit mass before weighting. An item with no mass on the grid
        (outside it, or empty) makes the result NaN rather than silently dropping it.
      n: mesh surface samples; seed: their seed.

    Example:
      A point cloud and a mesh of the same unit square, fused with weights 1 and 3: the total is 4
      and the points' mass (a quarter) sits on their one voxel:

      >>> import jax.numpy as jnp, fsjax
      >>> sq = fsjax.Mesh(jnp.asarray([[0.0, 0, 1], [4, 0, 1], [4, 4, 1], [0, 4, 1]]),
      ...                 jnp.asarray([[0, 1, 2], [0, 2, 3]]))
      >>> pt = fsjax.Points(jnp.asarray([[2.0, 2.0, 1.0]]))
      >>> v = fsjax.ops.fuse_to_voxel([pt, sq], (1.0, 1.0, 1.0), shape=(3, 5, 5), weights=[1.0, 3.0], n=4000)
      >>> round(float(v.data.sum()), 6), float(v.data[1, 2, 2]) > 0.25
      (4.0, True)
    """
    op = "fuse_to_voxel"
    if isinstance(items, (Points, Mesh, Depth, Volume, Gaussians)) or not hasattr(items, "__len__") or len(items) == 0:
        raise ValueError(f"{op}: argument 'items' must be a non-empty sequence of structures")
    w = [1.0] * len(items) if weights is None else [float(x) for x in weights]
    if len(w) != len(items) or not all(x >= 0 and x == x for x in w):
        raise ValueError(f"{op}: argument 'weights' must be {len(items)} non-negative numbers; got {weights!r}")
    shp = tuple(int(x) for x in shape)
    total = None
    for i, (x, wi) in enumerate(zip(items, w)):
        if isinstance(x, Volume) and tuple(x.data.shape) != shp:
            raise ValueError(f"{op}: argument 'items' [{i}] is a Volume of shape {tuple(x.data.shape)}, not {shp}")
        try:
            v = to_voxel(x, spacing, shape=shp, origin=origin, n=n, seed=seed + i).data
        except (TypeError, ValueError) as e:
            raise type(e)(f"{op}: argument 'items' [{i}]: {e}") from None
        if normalise:
            m = jnp.sum(v)
            v = v / jnp.where(m > 0, m, jnp.nan)
        total = wi * v if total is None else total + wi * v
    return Volume(total, spacing=tuple(float(x) for x in spacing))

