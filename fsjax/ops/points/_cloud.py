"""Local geometry of point clouds (``Points -> Points``).

Conventions:

* A cloud is one :class:`fsjax.Points`: ``xyz`` ``(N, 3)`` in the caller's
  length unit, a ``valid`` mask ``(N,)`` and optional per-point ``normals`` /
  ``colors``. Points with ``valid`` False, or with a non-finite coordinate, are
  ignored everywhere (never a neighbour, never counted). Ops that drop points
  (outlier removal) only clear ``valid``; ops that make a new cloud (voxel
  downsampling, farthest-point sampling) return a fixed static capacity with
  ``valid`` marking used slots and ``truncated`` set when more were needed.
  Unused and invalid slots hold NaN coordinates/normals.
* Neighbours are exact Euclidean k-nearest neighbours (the query point itself
  is its own first neighbour at distance 0 when it is valid). ``k`` and
  capacities fix array shapes: they are static ints, never knobs.
* Normals are unit vectors, the eigenvector of the smallest eigenvalue of the
  neighbourhood covariance (PCA; Hoppe et al. 1992), oriented so that
  ``dot(n, viewpoint - p) >= 0`` (they face the sensor). A neighbourhood with
  fewer than 3 valid points or a collinear one has no normal: NaN.
* Lengths (voxel edge, radius) are in the unit of ``xyz``. Batching is
  ``jax.vmap``.

The neighbour search is :func:`fsjax.ops.knn` (exact, sorted-cell grid;
equal to ``scipy.spatial.cKDTree``), so ``k`` is at most 32. ``estimate_normals``
on the grid runs its self-query and PCA in the grid's sorted order (the points
of one cell are consecutive rows: coherent gathers) and puts the normals back
in the input order; the same neighbours and arithmetic per point as ``knn``.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from ..._checks import check_positive, check_range, check_static_int
from ...registry import LinKnob, LogKnob, register
from ...types import Points
from ._search import (
    _BRUTE_LIMIT,
    _grid,
    _knn_cell_size,
    _query_grid_knn,
    _redo,
    _self_knn_sorted,
    _unsort,
)
from ._search import knn as _search_knn
from ._selfpca import self_cov_sorted

__all__ = [
    "estimate_normals",
    "voxel_downsample",
    "statistical_outlier_removal",
    "radius_outlier_removal",
    "farthest_point_sample",
]


# neighbour search: the exact grid kNN of the points_search family
# ---------------------------------------------------------------------------

knn = _search_knn


def _valid_mask(pts: Points):
    return pts.valid & jnp.all(jnp.isfinite(pts.xyz), axis=-1)


def _replace(pts: Points, *, valid=None, xyz=None, normals=None) -> Points:
    """A copy of ``pts`` with some fields replaced (keeps colors and truncated)."""
    return Points(pts.xyz if xyz is None else xyz,
                  valid=pts.valid if valid is None else valid,
                  normals=pts.normals if normals is None else normals,
                  colors=pts.colors, truncated=pts.truncated)


def _safe_unit(v, axis=-1):
    n2 = jnp.sum(v * v, axis=axis, keepdims=True)
    ok = n2 > 0
    return jnp.where(ok, v / jnp.sqrt(jnp.where(ok, n2, 1.0)), jnp.nan)


def smallest_eigvec3(cov):
    """Unit eigenvector of the smallest eigenvalue of symmetric 3 x 3 matrices ``(N, 3, 3)``; see
    :func:`eig3_smallest` (which also gives the eigenvalues)."""
    return eig3_smallest(cov)[1]


def eig3_smallest(cov):
    """Unit eigenvector of the smallest eigenvalue of symmetric 3 x 3 matrices ``(N, 3, 3)``, closed form.

    Eigenvalues by the trigonometric formula (O. K. Smith, "Eigenvalues of a symmetric 3 x 3
    matrix", CACM 4(4), 1961) on the matrix scaled by its largest entry; the eigenvector is the
    longest of the three cross products of the rows of ``A - lambda_min I`` (they span its null
    space when ``lambda_min`` is simple). Its error is about ``eps * lambda_max / (lambda_mid -
    lambda_min)`` (the conditioning of the eigenvector itself). About 10x faster than
    ``jnp.linalg.eigh`` on CPU (20,000 matrices: 5 ms vs 54 ms, float32). A zero matrix or a
    non-finite one gives NaN; a double smallest eigenvalue gives one vector of its plane.

    Returns ``(evals (N, 3) ascending, v (N, 3))``, the eigenvalues by the same formula
    (``lambda_mid = trace - lambda_min - lambda_max``): near a double eigenvalue the ``arccos``
    loses half the digits (on a line, ``diag(1.25, 0, 0)`` in float64, the two zero eigenvalues
    come out as -/+ 7e-9); callers that test ``lambda_mid`` use the minors instead (see
    :func:`_normals_of_cov`).
    """
    dtype = cov.dtype
    s = jnp.max(jnp.abs(cov), axis=(-2, -1))
    ok = (s > 0) & jnp.isfinite(s)
    a = cov / jnp.where(ok, s, 1.0)[..., None, None]
    q = (a[..., 0, 0] + a[..., 1, 1] + a[..., 2, 2]) / 3
    eye = jnp.eye(3, dtype=dtype)
    b = a - q[..., None, None] * eye
    p = jnp.sqrt(jnp.sum(b * b, axis=(-2, -1)) / 6)
    c = b / jnp.where(p > 0, p, 1.0)[..., None, None]
    det = (c[..., 0, 0] * (c[..., 1, 1] * c[..., 2, 2] - c[..., 1, 2] * c[..., 2, 1])
           - c[..., 0, 1] * (c[..., 1, 0] * c[..., 2, 2] - c[..., 1, 2] * c[..., 2, 0])
           + c[..., 0, 2] * (c[..., 1, 0] * c[..., 2, 1] - c[..., 1, 1] * c[..., 2, 0]))
    phi = jnp.arccos(jnp.clip(det / 2, -1.0, 1.0)) / 3
    lam = q + 2 * p * jnp.cos(phi + 2 * np.pi / 3)
    lam_max = q + 2 * p * jnp.cos(phi)
    evals = jnp.stack([lam, 3 * q - lam - lam_max, lam_max], -1) * jnp.where(ok, s, jnp.nan)[..., None]
    m = a - lam[..., None, None] * eye
    r0, r1, r2 = m[..., 0, :], m[..., 1, :], m[..., 2, :]
    cands = jnp.stack([jnp.cross(r0, r1), jnp.cross(r0, r2), jnp.cross(r1, r2)], -2)
    n2 = jnp.sum(cands * cands, -1)
    best = jnp.argmax(n2, -1)
    v = jnp.take_along_axis(cands, best[..., None, None], -2)[..., 0, :]
    vn = jnp.sqrt(jnp.max(n2, -1))
    # p == 0: a multiple of the identity (every vector is an eigenvector): take x
    v = jnp.where((p > 0)[..., None], v / jnp.where(vn > 0, vn, 1.0)[..., None], eye[0])
    return evals, jnp.where((ok & ((vn > 0) | (p == 0)))[..., None], v, jnp.nan)


def pca_frames(xyz, valid, idx):
    """Per-point PCA of the neighbourhood given by ``idx`` ``(N, k)`` (``-1`` = missing).

    Returns ``(evals (N, 3) ascending, evecs (N, 3, 3) columns, mean (N, 3), count (N,))``.
    """
    m = (idx >= 0) & valid[jnp.maximum(idx, 0)]
    nb = xyz[jnp.maximum(idx, 0)]
    w = m.astype(xyz.dtype)[..., None]
    cnt = jnp.sum(m, axis=1)
    cs = jnp.maximum(cnt, 1).astype(xyz.dtype)[:, None]
    mu = jnp.sum(jnp.where(m[..., None], nb, 0.0), axis=1) / cs
    d = jnp.where(m[..., None], nb - mu[:, None, :], 0.0) * w
    cov = jnp.einsum("nki,nkj->nij", d, d) / cs[..., None]
    evals, evecs = jnp.linalg.eigh(cov)
    return evals, evecs, mu, cnt


def _check_viewpoint(op: str, viewpoint):
    v = np.asarray(viewpoint, dtype=float)
    if v.shape != (3,) or not np.all(np.isfinite(v)):
        raise ValueError(f"{op}: argument 'viewpoint' must be 3 finite numbers (x, y, z), got {viewpoint!r}")
    return v


# ---------------------------------------------------------------------------
# normals
# ---------------------------------------------------------------------------


@register(family="points", takes=Points, gives=Points, differentiable=False,
          refs=["H. Hoppe, T. DeRose, T. Duchamp, J. McDonald, W. Stuetzle, Surface reconstruction "
                "from unorganized points, SIGGRAPH 1992"])
def estimate_normals(pts: Points, /, *, k: int = 16, viewpoint: tuple[float, float, float] = (0.0, 0.0, 0.0)
                     ) -> Points:
    """PCA normals from the ``k`` nearest neighbours, oriented toward a viewpoint.

    The normal of point ``p`` is the eigenvector of the smallest eigenvalue of
    the covariance of its ``k`` nearest valid neighbours (``p`` included); its
    sign is chosen so that ``dot(n, viewpoint - p) >= 0``.

    Args:
      pts: the cloud, ``xyz`` ``(N, 3)``.
      k: neighbours per point (static int, 3..32; default 16).
      viewpoint: sensor position ``(x, y, z)`` in the unit of ``xyz``
        (default the origin, the usual sensor frame).

    Returns:
      ``pts`` with ``normals`` ``(N, 3)`` set (unit length; NaN for invalid
      points and for neighbourhoods with fewer than 3 valid points or collinear
      ones).

    Note:
      Matches Open3D's ``estimate_normals(KDTreeSearchParamKNN(k))`` followed by
      ``orient_normals_towards_camera_location`` up to the eigen-solver's
      rounding (both are the PCA normal; tested against a NumPy PCA to 1e-9 and
      against analytic sphere normals).

    Example:
      Points on the plane ``z = 0.5`` seen from the origin get normal ``(0, 0, -1)``:

      >>> import numpy as np, jax.numpy as jnp, fsjax
      >>> g = np.stack(np.meshgrid(np.arange(6.0), np.arange(6.0)), -1).reshape(-1, 2)
      >>> xyz = np.c_[g, np.full(36, 0.5)]
      >>> out = fsjax.ops.estimate_normals(fsjax.Points(jnp.asarray(xyz)), k=8)
      >>> (np.round(np.asarray(out.normals[7]), 6) + 0.0).tolist()
      [0.0, 0.0, -1.0]
    """
    op = "estimate_normals"
    k = check_static_int(op, "k", k, lo=3, hi=32)
    vp = _check_viewpoint(op, viewpoint)
    return _replace(pts, normals=_estimate_normals_core(pts, k, jnp.asarray(vp, pts.xyz.dtype)))


# One compiled program per cloud shape and k (op by op: ~40 small programs per shape).
@functools.partial(jax.jit, static_argnames=("k",))
def _estimate_normals_core(pts: Points, k: int, vp):
    valid = _valid_mask(pts)
    xyz = jnp.where(valid[:, None], pts.xyz, 0.0)
    n = xyz.shape[0]
    if not _SORTED_NORMALS or n * n <= _BRUTE_LIMIT:  # knn's brute-force range
        idx, _ = knn(xyz, xyz, k, ref_valid=valid)
        return normals_from_neighbours(xyz, valid, idx, vp)
    # the grid's self-query and the PCA in the grid's sorted order (coherent gathers), then unsorted:
    # the same neighbours and the same arithmetic per row as knn + normals_from_neighbours
    g = _grid(xyz, valid, _knn_cell_size(xyz, valid, k))
    vs = valid[g.order]
    if not _THRESHOLD_NORMALS:
        pos, _ = _self_knn_sorted(g, k)
        return _unsort(g.order, normals_from_neighbours(g.spts, vs, pos, vp))
    # the k nearest of most rows by a threshold, their covariance by masked sums (no lists, no top_k);
    # the rows it does not answer (a tie at the threshold, an overflowing or uncertified block) from
    # exact neighbour lists, as knn gives them
    cov, ok = self_cov_sorted(g, k)

    def listed(sel):
        idx, _ = _query_grid_knn(g, g.spts[sel], k)
        return _cov_rows(xyz, valid, idx)

    cov, cnt = _redo(vs & ~ok, 128, listed, (cov, jnp.full(n, k, jnp.int32)))
    return _unsort(g.order, _normals_of_cov(cov, cnt, g.spts, vs, vp))


_SORTED_NORMALS = True  # estimate_normals in the grid's sorted order (a probe knob)
_THRESHOLD_NORMALS = True  # the sorted path's k nearest by self_cov_sorted's threshold (a probe knob)
_CLOSED_FORM_EIG = True  # normals by eig3_smallest, not jnp.linalg.eigh (a probe knob)


NORMALS_BLOCK = 4096  # query rows per step of normals_from_neighbours' lax.map


def normals_from_neighbours(xyz, valid, idx, viewpoint=None, *, block: int | None = NORMALS_BLOCK):
    """The PCA normals of :func:`estimate_normals` from given neighbour lists ``idx`` ``(N, k)``
    (``-1`` = missing; the point itself included), e.g. the first ``k`` columns of a larger kNN
    answer a caller already has (one neighbour search instead of two). Oriented toward
    ``viewpoint`` (default the origin); NaN where :func:`estimate_normals` gives NaN.

    The rows are done ``block`` at a time under ``lax.map`` (static; ``None``: all at once): the
    gathered neighbours, their centred copies and the ``3 x 3`` covariances and eigen-solves then
    take ``O(block k)`` memory instead of ``O(N k)`` (200,000 points, k = 30, float64: 421 MiB of
    XLA temporaries all at once). Each row's arithmetic is the same either way."""
    vp = jnp.zeros(3, xyz.dtype) if viewpoint is None else viewpoint
    n_rows, k = idx.shape
    if block is None or n_rows <= block:
        return _normals_rows(xyz, valid, idx, xyz, valid, vp)
    nb = -(-n_rows // block)
    pad = nb * block - n_rows
    idx_b = jnp.pad(idx, ((0, pad), (0, 0)), constant_values=-1).reshape(nb, block, k)
    q_b = jnp.pad(xyz, ((0, pad), (0, 0))).reshape(nb, block, 3)
    v_b = jnp.pad(valid, (0, pad)).reshape(nb, block)
    out = jax.lax.map(lambda a: _normals_rows(xyz, valid, a[0], a[1], a[2], vp), (idx_b, q_b, v_b))
    return out.reshape(nb * block, 3)[:n_rows]


def _normals_rows(xyz, valid, idx, q_xyz, q_valid, vp):
    """Normals of the query rows ``q_xyz`` (their neighbour lists ``idx`` into ``xyz``)."""
    cov, cnt = _cov_rows(xyz, valid, idx)
    return _normals_of_cov(cov, cnt, q_xyz, q_valid, vp)


def _cov_rows(xyz, valid, idx):
    """Covariance ``(B, 3, 3)`` and count ``(B,)`` of the valid points listed in each row of ``idx``."""
    m = (idx >= 0) & valid[jnp.maximum(idx, 0)]
    nb = xyz[jnp.maximum(idx, 0)]
    cnt = jnp.sum(m, axis=1)
    cs = jnp.maximum(cnt, 1).astype(xyz.dtype)[:, None]
    mu = jnp.sum(jnp.where(m[..., None], nb, 0.0), axis=1) / cs
    d = jnp.where(m[..., None], nb - mu[:, None, :], 0.0)
    cov = jnp.einsum("nki,nkj->nij", d, d) / cs[..., None]
    return cov, cnt.astype(jnp.int32)


def _normals_of_cov(cov, cnt, q_xyz, q_valid, vp):
    """The normals of the query rows from their neighbourhoods' covariances ``cov`` and counts ``cnt``."""
    if _CLOSED_FORM_EIG:
        evals, n = eig3_smallest(cov)
        # the line test's middle eigenvalue from the sum of the principal 2 x 2 minors c2 (c2 / lambda_max
        # lies in [lambda_mid, 3 lambda_mid]): the closed form's own lambda_mid is ~sqrt(eps) off on a line
        c = cov
        c2 = ((c[:, 0, 0] * c[:, 1, 1] - c[:, 0, 1] * c[:, 1, 0]) + (c[:, 0, 0] * c[:, 2, 2] - c[:, 0, 2] * c[:, 2, 0])
              + (c[:, 1, 1] * c[:, 2, 2] - c[:, 1, 2] * c[:, 2, 1]))
        lmax = evals[:, 2]
        evals = evals.at[:, 1].set(c2 / jnp.where(lmax > 0, lmax, 1.0))
    else:
        evals, evecs = jnp.linalg.eigh(cov)
        n = evecs[..., 0]
    scale = jnp.maximum(evals[:, 2], 0.0)
    # a neighbourhood on a line has no normal; its middle eigenvalue is 0 up to the solver's
    # error (~eps scale) and the coordinates' rounding (~(eps |x|)^2): the old floor 1e-12 scale
    # sat below float32's, and 54 of 64 float32 points on a line got a normal (issue 20 sweep)
    eps = jnp.finfo(q_xyz.dtype).eps
    floor = jnp.maximum(max(1e-12, 32 * float(eps)) * scale,
                        (32 * eps * jnp.max(jnp.abs(q_xyz), axis=-1)) ** 2)
    ok = q_valid & (cnt >= 3) & (evals[:, 1] > floor) & (scale > 0)
    s = jnp.sum(n * (vp - q_xyz), axis=-1)
    n = jnp.where((s < 0)[:, None], -n, n)
    return jnp.where(ok[:, None], n + 0.0, jnp.nan)


# ---------------------------------------------------------------------------
# voxel downsampling
# ---------------------------------------------------------------------------


@register(family="points", takes=Points, gives=Points, knobs={"voxel": LogKnob(0.02, 0.5)},
          differentiable=False,
          refs=["Q.-Y. Zhou, J. Park, V. Koltun, Open3D: a modern library for 3D data processing, "
                "arXiv:1801.09847, 2018 (voxel_down_sample)"])
def voxel_downsample(pts: Points, /, *, voxel: float = 0.1, capacity: int | None = None) -> Points:
    """Voxel-grid downsampling: one point per occupied voxel, at the centroid of its points.

    Voxels are cubes of edge ``voxel`` on a grid whose origin is the lower
    corner of the valid points' bounding box minus half a voxel (Open3D's
    grid); voxel ``(i, j, l) = floor((p - origin) / voxel)``. Output slots are
    the occupied voxels in lexicographic ``(i, j, l)`` order. Normals are
    averaged and renormalised, colours averaged.

    Args:
      pts: the cloud, ``xyz`` ``(N, 3)``.
      voxel: voxel edge length in the unit of ``xyz`` (knob ``a``, log
        0.02..0.5; default 0.1).
      capacity: output capacity (static int; default ``N``). More occupied
        voxels than ``capacity`` sets ``truncated`` and keeps the first ones.

    Returns:
      A cloud of capacity ``capacity`` with the voxel centroids.

    Note:
      Same voxel assignment and centroids as Open3D's ``voxel_down_sample``
      (tested against a NumPy ``np.unique`` reference to 1e-12); the order of
      the output points differs (Open3D's is hash order).

    Example:
      Eight points in two voxels of edge 1 give two centroids:

      >>> import numpy as np, jax.numpy as jnp, fsjax
      >>> xyz = np.array([[0, 0, 0], [0.2, 0, 0], [0, 0.2, 0], [0.2, 0.2, 0.1],
      ...                 [3, 0, 0], [3.2, 0, 0], [3, 0.1, 0], [3.2, 0.1, 0.1]])
      >>> out = fsjax.ops.voxel_downsample(fsjax.Points(jnp.asarray(xyz)), voxel=1.0, capacity=4)
      >>> int(out.valid.sum()), np.round(np.asarray(out.xyz[1]), 6).tolist()
      (2, [3.1, 0.05, 0.025])
    """
    op = "voxel_downsample"
    check_positive(op, "voxel", voxel)
    n = pts.xyz.shape[0]
    cap = n if capacity is None else check_static_int(op, "capacity", capacity, lo=1)
    return _voxel_downsample_core(pts, voxel, cap)


# One compiled program per cloud shape and capacity (op by op: ~25 small programs per shape).
@functools.partial(jax.jit, static_argnames=("cap",))
def _voxel_downsample_core(pts: Points, voxel, cap: int) -> Points:
    xyz = pts.xyz
    dt = xyz.dtype
    valid = _valid_mask(pts)
    x0 = jnp.where(valid[:, None], xyz, 0.0)
    lo = jnp.min(jnp.where(valid[:, None], xyz, jnp.inf), axis=0)
    lo = jnp.where(jnp.isfinite(lo), lo, 0.0)
    v = jnp.asarray(voxel, dt)
    g = jnp.floor((x0 - (lo - 0.5 * v)) / v)
    g = jnp.where(valid[:, None], g, 0.0)
    order = jnp.lexsort((g[:, 2], g[:, 1], g[:, 0], ~valid))
    gs, vs = g[order], valid[order]
    new = jnp.concatenate([jnp.ones((1,), bool), jnp.any(gs[1:] != gs[:-1], axis=-1)]) & vs
    count = jnp.sum(new)
    seg = jnp.cumsum(new) - 1
    seg = jnp.where(vs & (seg < cap), seg, cap)
    w = vs.astype(dt)

    def mean(field):
        s = jax.ops.segment_sum(field[order] * w[:, None], seg, num_segments=cap + 1)[:cap]
        c = jax.ops.segment_sum(w, seg, num_segments=cap + 1)[:cap]
        return jnp.where((c > 0)[:, None], s / jnp.where(c > 0, c, 1.0)[:, None], jnp.nan)

    out_valid = jnp.arange(cap) < count
    cen = mean(x0)
    normals = None
    if pts.normals is not None:
        normals = _safe_unit(mean(jnp.where(valid[:, None], pts.normals, 0.0)))
    colors = None
    if pts.colors is not None:
        colors = mean(jnp.where(valid[:, None], pts.colors, 0.0))
    return Points(cen, valid=out_valid, normals=normals, colors=colors, truncated=(count > cap) | pts.truncated)


# ---------------------------------------------------------------------------
# outlier removal
# ---------------------------------------------------------------------------


@register(family="points", takes=Points, gives=Points, knobs={"std_ratio": LinKnob(0.5, 4.0)},
          differentiable=False,
          refs=["R. B. Rusu, Z. C. Marton, N. Blodow, M. Dolha, M. Beetz, Towards 3D point cloud based "
                "object maps for household environments, Robotics and Autonomous Systems 56(11), 2008"])
def statistical_outlier_removal(pts: Points, /, *, k: int = 16, std_ratio: float = 2.0) -> Points:
    """Statistical outlier removal: drop points whose mean neighbour distance is unusually large.

    For each valid point, ``d_i`` is the mean Euclidean distance to its ``k``
    nearest other valid points; with ``mu`` and ``sigma`` the mean and sample
    standard deviation of ``d_i`` over valid points, a point stays valid iff
    ``d_i <= mu + std_ratio * sigma``.

    Args:
      pts: the cloud.
      k: neighbours per point, the point itself excluded (static int, 1..31; default 16).
      std_ratio: threshold in standard deviations (knob ``a``, 0.5..4; default 2).

    Returns:
      ``pts`` with ``valid`` cleared on the outliers (coordinates unchanged).

    Note:
      PCL's ``StatisticalOutlierRemoval`` rule. Open3D's
      ``remove_statistical_outlier(nb_neighbors=k)`` counts the point itself
      among its ``k`` neighbours; use ``k - 1`` here for the same neighbourhood.
      A point with fewer than ``k`` valid neighbours uses those it has; one
      with none is removed.

    Example:
      A 5 x 5 grid with spacing 1 plus one far point: only the far point goes:

      >>> import numpy as np, jax.numpy as jnp, fsjax
      >>> g = np.stack(np.meshgrid(np.arange(5.0), np.arange(5.0)), -1).reshape(-1, 2)
      >>> xyz = np.r_[np.c_[g, np.zeros(25)], [[2.0, 2.0, 30.0]]]
      >>> out = fsjax.ops.statistical_outlier_removal(fsjax.Points(jnp.asarray(xyz)), k=4)
      >>> int(out.valid.sum()), bool(out.valid[25])
      (25, False)
    """
    op = "statistical_outlier_removal"
    k = check_static_int(op, "k", k, lo=1, hi=31)
    check_range(op, "std_ratio", std_ratio, 0.0, None)
    return _replace(pts, valid=pts.valid & _sor_keep(pts, k, std_ratio))


# One compiled program per cloud shape and k (op by op: ~25 small programs per shape).
@functools.partial(jax.jit, static_argnames=("k",))
def _sor_keep(pts: Points, k: int, std_ratio):
    valid = _valid_mask(pts)
    xyz = jnp.where(valid[:, None], pts.xyz, 0.0)
    dt = xyz.dtype
    _, d2 = knn(xyz, xyz, k + 1, ref_valid=valid)
    d2 = d2[:, 1:]  # drop the point itself (distance 0)
    fin = jnp.isfinite(d2)
    nf = jnp.sum(fin, axis=1)
    d = jnp.sqrt(jnp.where(fin, d2, 0.0))
    md = jnp.sum(d, axis=1) / jnp.maximum(nf, 1).astype(dt)
    use = valid & (nf > 0)
    nu = jnp.sum(use).astype(dt)
    mu = jnp.sum(jnp.where(use, md, 0.0)) / jnp.maximum(nu, 1.0)
    var = jnp.sum(jnp.where(use, (md - mu) ** 2, 0.0)) / jnp.maximum(nu - 1.0, 1.0)
    thr = mu + jnp.asarray(std_ratio, dt) * jnp.sqrt(var)
    return use & (md <= thr)


@register(family="points", takes=Points, gives=Points, knobs={"radius": LogKnob(0.02, 1.0)},
          differentiable=False,
          refs=["R. B. Rusu, S. Cousins, 3D is here: Point Cloud Library (PCL), ICRA 2011 "
                "(RadiusOutlierRemoval)"])
def radius_outlier_removal(pts: Points, /, *, radius: float = 0.1, min_neighbors: int = 4) -> Points:
    """Radius outlier removal: keep points with at least ``min_neighbors`` others within ``radius``.

    A valid point stays valid iff its ``min_neighbors``-th nearest other valid
    point lies at distance ``<= radius`` (exactly the count rule, computed with
    a ``min_neighbors + 1`` nearest-neighbour query, so no radius capacity can
    overflow).

    Args:
      pts: the cloud.
      radius: search radius in the unit of ``xyz`` (knob ``a``, log 0.02..1; default 0.1).
      min_neighbors: required neighbours, the point itself excluded (static
        int, 1..31; default 4).

    Returns:
      ``pts`` with ``valid`` cleared on the outliers.

    Note:
      PCL's ``RadiusOutlierRemoval`` rule (the point itself not counted).
      Open3D's ``remove_radius_outlier(nb_points)`` counts the point itself:
      its ``nb_points`` equals ``min_neighbors + 1`` here. Tested against a
      ``scipy.spatial.cKDTree.query_ball_point`` count, exactly.

    Example:
      A pair of points 0.05 apart survives ``min_neighbors=1``; a lone point does not:

      >>> import jax.numpy as jnp, fsjax
      >>> xyz = jnp.array([[0.0, 0, 0], [0.05, 0, 0], [1.0, 0, 0]])
      >>> out = fsjax.ops.radius_outlier_removal(fsjax.Points(xyz), radius=0.1, min_neighbors=1)
      >>> [bool(v) for v in out.valid]
      [True, True, False]
    """
    op = "radius_outlier_removal"
    check_positive(op, "radius", radius)
    m = check_static_int(op, "min_neighbors", min_neighbors, lo=1, hi=31)
    valid = _valid_mask(pts)
    xyz = jnp.where(valid[:, None], pts.xyz, 0.0)
    _, d2 = knn(xyz, xyz, m + 1, ref_valid=valid)
    r = jnp.asarray(radius, xyz.dtype)
    keep = valid & (d2[:, m] <= r * r)
    return _replace(pts, valid=pts.valid & keep)


# ---------------------------------------------------------------------------
# farthest-point sampling
# ---------------------------------------------------------------------------


@functools.partial(jax.jit, static_argnums=2)
def _fps_indices(xyz, valid, ns: int):
    # module-level jit: the fori_loop's closure run eagerly would compile on every call
    x0 = jnp.where(valid[:, None], xyz, 0.0)
    start = jnp.argmax(valid).astype(jnp.int32)
    d = jnp.where(valid, jnp.inf, -jnp.inf)

    def body(i, carry):
        sel, d, last = carry
        sel = sel.at[i].set(last)
        d = jnp.minimum(d, jnp.where(valid, jnp.sum((x0 - x0[last]) ** 2, axis=-1), -jnp.inf))
        return sel, d, jnp.argmax(d).astype(jnp.int32)

    sel, _, _ = lax.fori_loop(0, ns, body, (jnp.zeros((ns,), jnp.int32), d, start))
    return sel


@register(family="points", takes=Points, gives=Points, differentiable=False,
          refs=["Y. Eldar, M. Lindenbaum, M. Porat, Y. Y. Zeevi, The farthest point strategy for "
                "progressive image sampling, IEEE TIP 6(9), 1997"])
def farthest_point_sample(pts: Points, /, *, n: int = 64) -> Points:
    """Farthest-point sampling: ``n`` points, each the farthest from those already chosen.

    Starts at the first valid point (lowest index: deterministic); then
    repeatedly takes the valid point maximising the distance to the chosen set
    (ties: lowest index). The result covers the cloud with covering radius
    within a factor 2 of the optimum (Gonzalez 1985).

    Args:
      pts: the cloud.
      n: number of samples, the output capacity (static int >= 1; default 64).
        With fewer valid points than ``n``, the extra slots are invalid.

    Returns:
      A cloud of capacity ``n`` (normals and colours carried over).

    Note:
      Same sequence as the classic O(nN) FPS used by PointNet++ (and
      ``open3d.geometry.PointCloud.farthest_point_down_sample`` with start
      index 0), tested against a NumPy implementation exactly.

    Example:
      On five points of a line the samples are the ends, then the middle:

      >>> import jax.numpy as jnp, fsjax
      >>> xyz = jnp.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0], [4, 0, 0]])
      >>> out = fsjax.ops.farthest_point_sample(fsjax.Points(xyz), n=3)
      >>> [float(x) for x in out.xyz[:, 0]]
      [0.0, 4.0, 2.0]
    """
    op = "farthest_point_sample"
    ns = check_static_int(op, "n", n, lo=1)
    xyz = pts.xyz
    valid = _valid_mask(pts)
    sel = _fps_indices(xyz, valid, ns)
    out_valid = jnp.arange(ns) < jnp.sum(valid)

    def take(f):
        return None if f is None else jnp.where(out_valid[:, None], f[sel], jnp.nan)

    return Points(take(xyz), valid=out_valid, normals=take(pts.normals), colors=take(pts.colors),
                  truncated=pts.truncated)
