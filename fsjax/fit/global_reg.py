"""Global registration without an initial guess: FPFH descriptors, correspondence RANSAC, ICP refine.

Conventions are those of :mod:`fsjax.fit.rigid` (``target = R source + t``; reason codes).

* **FPFH** (Rusu, Blodow & Beetz 2009, "Fast Point Feature Histograms (FPFH) for 3D
  registration", ICRA). For a point ``p`` and each neighbour ``q`` within ``radius`` the pair is
  described in a Darboux frame built on the normal of the pair member whose normal makes the
  smaller angle with the connecting line (``u = n_s``, ``v = u x d``, ``w = u x v``, ``d`` the unit
  connecting vector): ``alpha = v . n_t``, ``phi = u . d``, ``theta = atan2(w . n_t, u . n_t)``.
  SPFH(p) = three 11-bin histograms of ``alpha`` and ``phi`` on [-1, 1] and ``theta`` on
  [-pi, pi], each normalised to sum 1 (33 values). FPFH(p) = ``0.5 SPFH(p) + 0.5 sum_k w_k
  SPFH(q_k)`` with ``w_k`` proportional to ``1 / |p - q_k|`` and summing to 1. Deviation: the
  paper adds ``(1/k) sum SPFH(q_k) / omega_k`` with ``omega_k`` the distance, whose scale depends
  on the length unit; normalising the weights makes the descriptor unit-free (Open3D normalises
  its histograms to sum 100 instead).
* Normals are PCA normals of the ``normal_k`` nearest points (:func:`fsjax.ops.estimate_normals`)
  oriented away from the cloud centroid, a rotation-invariant rule (normals nearly tangent to
  the radial direction can flip between two crops; RANSAC tolerates those points).
* Neighbours within ``radius`` come from the ``capacity`` nearest ones; a point whose
  ``capacity``-th neighbour is still inside ``radius`` is flagged ``truncated``.
* **Matching**: nearest descriptor (Euclidean, 33-D) from source to target; ``mutual=True`` keeps
  only pairs that are also nearest target-to-source.
* **RANSAC** (``ransac_registration``): ``n_hypotheses`` triples of matches drawn under ``key``; a triple whose three edge
  lengths disagree between the clouds (ratio below ``edge_ratio``, Open3D's edge-length checker
  idea) is rejected before fitting; the rest are fitted by Kabsch and scored -- all in one
  ``vmap`` -- by the number of matches within ``distance`` after the transform (only the triples
  that pass the check are fitted and scored). The best is refitted on its inliers. Fewer than
  ``min_inliers`` inliers: reason 6, NaN pose.
  :func:`global_registration` then refits the pose on nearest-neighbour *point* pairs within
  ``distance / 2`` (``refit_rounds`` Gauss-Newton steps of the point-to-plane error on the
  target's normals, the ones the descriptor used; target points on the edge of the sampled
  surface take no part, see :func:`_boundary`) and refines it by ICP. Point-to-point (Kabsch)
  pairs of two independent samples were the old refit: its fixed point lies 0.2-0.8 deg from the
  truth on the 2,000-point bunny crops even when started at the truth, since a pair's offset along
  the surface is about the point spacing; point-to-plane leaves only the offset across it, but
  pulls harder on the pairs a source point beyond the target's edge forms with the edge, hence
  their exclusion (docs/registration.md).
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from .._checks import check_choice, check_positive, check_range, check_static_int
from .._linalg import eigh_small, jit_fast_compile
from ..ops import knn
from ..ops.points._cloud import normals_from_neighbours
from ..ops.points._search import build_index, query_knn
from ..types import Points
from ..types.results import FitResult, WrappedFit
from ._cloud import as_cloud
from .icp import ICPResult, _p2plane_step, icp
from .rigid import NO_HYPOTHESIS, OK, TOO_FEW, _weighted_kabsch, kabsch_umeyama

__all__ = ["fpfh", "spin_images", "shot", "match_descriptors", "CorrespondenceRansacResult", "ransac_registration", "GlobalResult",
           "global_registration"]

_BINS = 11


def _pair_features(p, n_p, q, n_q):
    """(alpha, phi, theta) of a point pair (vectorised over leading axes); NaN-free for coincident points."""
    d = q - p
    dist2 = jnp.sum(d * d, -1)
    ok = dist2 > 0
    dist = jnp.sqrt(jnp.where(ok, dist2, 1.0))
    d = d / dist[..., None]
    a1 = jnp.sum(n_p * d, -1)
    a2 = jnp.sum(n_q * d, -1)
    # source = the normal at the smaller angle to the line; near-ties (points sharing a normal, frequent with
    # k-NN normals) keep the query point as source, so rounding cannot flip the sign of phi
    swap = jnp.abs(a1) < jnp.abs(a2) - 1e3 * jnp.finfo(d.dtype).eps
    ns = jnp.where(swap[..., None], n_q, n_p)
    nt = jnp.where(swap[..., None], n_p, n_q)
    d = jnp.where(swap[..., None], -d, d)
    phi = jnp.sum(ns * d, -1)
    v = jnp.cross(ns, d)
    vn2 = jnp.sum(v * v, -1)
    vok = vn2 > 1e-24
    v = v / jnp.sqrt(jnp.where(vok, vn2, 1.0))[..., None]
    w = jnp.cross(ns, v)
    alpha = jnp.where(vok, jnp.sum(v * nt, -1), 0.0)
    theta = jnp.where(vok, jnp.arctan2(jnp.sum(w * nt, -1), jnp.sum(ns * nt, -1)), 0.0)
    return alpha, phi, theta, ok


def _hist(vals, lo, hi, mask):
    b = jnp.clip(jnp.floor((vals - lo) / (hi - lo) * _BINS), 0, _BINS - 1).astype(jnp.int32)
    h = jnp.sum(jax.nn.one_hot(b, _BINS, dtype=vals.dtype) * mask[..., None], -2)
    s = jnp.sum(h, -1, keepdims=True)
    return h / jnp.where(s > 0, s, 1.0)


def _finite_rows(xyz, valid):
    """``(xyz, valid)`` with invalid or non-finite rows marked invalid and moved onto the valid points'
    centroid: a NaN query (the empty slots of ``voxel_downsample``) made the grid search fall back
    to scanning every cell (FPFH of 4,096 slots, 665 empty: 766 -> 120 ms); their answers are unused."""
    valid = valid & jnp.all(jnp.isfinite(xyz), -1)
    c = jnp.sum(jnp.where(valid[:, None], xyz, 0.0), 0) / jnp.maximum(jnp.sum(valid), 1)
    return jnp.where(valid[:, None], xyz, c), valid


@jit_fast_compile(static_argnames=("capacity", "normal_k"))
def _fpfh_core(xyz, valid, normals, radius, *, capacity, normal_k):
    xyz, valid = _finite_rows(xyz, valid)
    # one neighbour search serves the normals and the histograms (two searches compiled twice the code).
    # "auto": brute force up to 2,048 points; the grid would run 36 -> 19 ms at 2,000 points but
    # compiles 3.8 s longer (CPU, 2026-12-05), so it is left to the larger clouds
    idx, d2 = knn(xyz, xyz, max(capacity, normal_k) + 1, ref_valid=valid)  # includes the point itself
    if normals is None:
        normals = _pca_normals(xyz, valid, idx, normal_k)
        c = jnp.sum(jnp.where(valid[:, None], xyz, 0.0), 0) / jnp.maximum(jnp.sum(valid), 1)
        normals = normals * jnp.where(jnp.sum(normals * (xyz - c), -1) < 0, -1.0, 1.0)[:, None]
    nok = valid & jnp.all(jnp.isfinite(normals), -1)
    normals = jnp.where(nok[:, None], normals, 0.0)
    idx, d2 = idx[:, 1:capacity + 1], d2[:, 1:capacity + 1]
    inr = (idx >= 0) & (d2 <= radius**2) & (d2 > 0)
    truncated = inr[:, -1]
    inr = inr & nok[jnp.maximum(idx, 0)]  # neighbours without a normal take no part
    j = jnp.maximum(idx, 0)
    al, ph, th, ok = _pair_features(xyz[:, None, :], normals[:, None, :], xyz[j], normals[j])
    m = (inr & ok).astype(xyz.dtype)
    spfh = jnp.concatenate([_hist(al, -1.0, 1.0, m), _hist(ph, -1.0, 1.0, m), _hist(th, -jnp.pi, jnp.pi, m)], -1)
    wk = m / jnp.sqrt(jnp.where(m > 0, d2, 1.0))
    ws = jnp.sum(wk, -1, keepdims=True)
    wk = wk / jnp.where(ws > 0, ws, 1.0)
    f = 0.5 * spfh + 0.5 * jnp.einsum("nk,nkf->nf", wk, spfh[j])
    good = nok & (jnp.sum(m, -1) >= 3)
    return jnp.where(good[:, None], f, 0.0), good, truncated, normals, _boundary(xyz, normals, idx, d2)


def _descriptor_args(fn, points, radius, capacity, normal_k, min_capacity):
    """The arguments every local descriptor shares, checked: ``(xyz, valid, normals or None, capacity, normal_k)``."""
    xyz, valid, normals = as_cloud(fn, "points", points)
    check_positive(fn, "radius", radius)
    capacity = check_static_int(fn, "capacity", capacity, lo=min_capacity)
    normal_k = check_static_int(fn, "normal_k", normal_k, lo=3, hi=32)
    return xyz, valid, None if normals is None else jnp.asarray(normals, xyz.dtype), capacity, int(normal_k)


def fpfh(
    points: Points | Float[Array, "N 3"],
    *,
    radius: float,
    capacity: int = 48,
    normal_k: int = 10,
) -> tuple[Float[Array, "N 33"], Bool[Array, " N"], Bool[Array, " N"]]:
    """Fast Point Feature Histograms (33 values per point); see the module docstring.

    Args:
        points: cloud (``Points``, whose ``normals`` are used when present, or ``(N, 3)``).
        radius: neighbourhood radius (cloud units), typically 4-5x the point spacing.
        capacity: maximum neighbours per point (static int).
        normal_k: neighbours for the PCA normals when the cloud has none (static int).

    Returns:
        ``(descriptors (N, 33), valid (N,), truncated (N,))``; ``valid`` is False for invalid points
        and points with fewer than 3 neighbours in ``radius`` (their descriptor is 0).

    Example:
        >>> import jax.numpy as jnp
        >>> from fsjax.fit import fpfh, rotation_from_axis_angle
        >>> from fsjax.data import surface_points
        >>> x = jnp.asarray(surface_points("bunny", 400, 0))
        >>> f1, ok1, _ = fpfh(x, radius=0.03)
        >>> f2, ok2, _ = fpfh(x @ rotation_from_axis_angle(jnp.array([1.0, 2, 3]), 70.0).T, radius=0.03)
        >>> bool(ok1.all()), float(jnp.abs(f1 - f2).max()) < 1e-9   # rotation invariant
        (True, True)
    """
    return _fpfh(points, radius=radius, capacity=capacity, normal_k=normal_k)[:3]


def _fpfh(points, *, radius, capacity=48, normal_k=10):
    """:func:`fpfh` and the normals it used (``(N, 3)``, 0 where missing)."""
    xyz, valid, nrm, capacity, normal_k = _descriptor_args("fpfh", points, radius, capacity, normal_k, 3)
    return _fpfh_core(xyz, valid, nrm, jnp.asarray(radius, xyz.dtype), capacity=capacity, normal_k=normal_k)


def _tent(x, centres, circular_period=None):
    """Linear-interpolation weights of ``x`` (any shape) on bins centred at ``centres`` (ascending, equal spacing).

    Outside the outer centres the whole weight goes to the outer bin; ``circular_period`` wraps the axis.
    Returns ``x.shape + (len(centres),)`` weights summing to 1.
    """
    c = jnp.asarray(centres, x.dtype)
    h = c[1] - c[0] if c.shape[0] > 1 else jnp.asarray(1.0, x.dtype)
    if circular_period is None:
        xc = jnp.clip(x, c[0], c[-1])
        d = jnp.abs(xc[..., None] - c)
    else:
        d = jnp.abs(jnp.remainder(x[..., None] - c + 0.5 * circular_period, circular_period) - 0.5 * circular_period)
    return jnp.maximum(0.0, 1.0 - d / h)


_BOUNDARY_SHIFT = 0.2


def _boundary(xyz, normals, idx, d2):
    """Points on the edge of the sampled surface (Turk & Levoy 1994 leave pairs with such points out
    of the fit): the mean offset of the listed neighbours (``idx`` (N, K), ``d2`` inf where missing),
    projected on the tangent plane, longer than ``_BOUNDARY_SHIFT`` times the farthest one's distance.

    For uniform samples on a disc the shift is 0 (sampling noise: about 0.09 at 48 neighbours); on
    a half-disc (a straight edge through the point) it is 4 / (3 pi) = 0.42; 0.2 lies between (0.25
    gave a larger max on the bunny crops and worse CAD-vs-scan pairs: docs/benchmarks_icp.md).
    """
    ok = jnp.isfinite(d2)
    off = jnp.where(ok[..., None], xyz[jnp.maximum(idx, 0)] - xyz[:, None, :], 0.0)
    m = jnp.sum(off, 1) / jnp.maximum(jnp.sum(ok, 1), 1)[:, None]
    m = m - jnp.sum(m * normals, -1, keepdims=True) * normals
    far = jnp.sqrt(jnp.max(jnp.where(ok, d2, 0.0), 1))
    return jnp.sum(m * m, -1) > (_BOUNDARY_SHIFT * far) ** 2


def _pca_normals(xyz, valid, idx, normal_k):
    """PCA normals (:func:`fsjax.ops.estimate_normals`, unoriented) of the first ``normal_k`` columns of
    a kNN answer that includes each point itself."""
    return normals_from_neighbours(jnp.where(valid[:, None], xyz, 0.0), valid, idx[:, :normal_k])


def _neighbourhoods(xyz, valid, radius, capacity, normal_k):
    """Neighbours within ``radius`` among the ``capacity`` nearest (the point itself excluded), and
    the ``normal_k`` nearest (itself included) for :func:`_pca_normals`: one search for both."""
    idx, d2 = knn(xyz, xyz, max(capacity, normal_k) + 1, ref_valid=valid)
    near = idx[:, :normal_k]
    idx, d2 = idx[:, 1:capacity + 1], d2[:, 1:capacity + 1]
    inr = (idx >= 0) & (d2 <= radius**2) & (d2 > 0) & valid[:, None]
    return jnp.maximum(idx, 0), d2, inr, inr[:, -1], near


def _majority_sign(v, D, m):
    """Flip each ``v`` (N, 3) so that most of its neighbours' offsets ``D`` (N, K, 3) lie on its positive side.

    The sign disambiguation of Bro, Acar & Kolda (2008) as used by SHOT's local frame; a tie keeps ``v``.
    """
    proj = jnp.where(m, jnp.einsum("nki,ni->nk", D, v), 0.0)
    s = jnp.sum(jnp.sign(proj), -1)
    s = jnp.where(s == 0, jnp.sum(proj, -1), s)  # a tie in the count: the side of the summed offsets
    return v * jnp.where(s < 0, -1.0, 1.0)[:, None]


def _oriented_normals(xyz, valid, normals, D, m, near):
    """PCA normals of the neighbours ``near`` (or the given normals), each turned to the side where
    most of its neighbours lie.

    A rule of the local geometry alone, so two scans of one surface orient a normal alike wherever
    their neighbourhoods agree (the centroid rule of :func:`fpfh` depends on the crop).
    """
    if normals is None:
        normals = _pca_normals(xyz, valid, near, near.shape[1])
    nok = valid & jnp.all(jnp.isfinite(normals), -1)
    normals = jnp.where(nok[:, None], normals, 0.0)
    return _majority_sign(normals, D, m), nok


@functools.partial(jax.jit, static_argnames=("capacity", "normal_k", "n_alpha", "n_beta"))
def _spin_core(xyz, valid, normals, radius, cos_support, *, capacity, normal_k, n_alpha, n_beta):
    xyz, valid = _finite_rows(xyz, valid)
    j, d2, inr, truncated, near = _neighbourhoods(xyz, valid, radius, capacity, normal_k)
    D = xyz[j] - xyz[:, None, :]
    n, nok = _oriented_normals(xyz, valid, normals, D, inr, near)
    # beta's sign follows the normal's: orient away from the cloud's centroid (as fpfh); the
    # local majority rule flips on flat patches and lost 2 of 3 crop pairs (docs/registration.md)
    c = jnp.sum(jnp.where(valid[:, None], xyz, 0.0), 0) / jnp.maximum(jnp.sum(valid), 1)
    n = n * jnp.where(jnp.sum(n * (xyz - c), -1) < 0, -1.0, 1.0)[:, None]
    m = inr & nok[:, None] & nok[j] & (jnp.einsum("nki,nki->nk", n[j], jnp.broadcast_to(n[:, None], D.shape))
                                      >= cos_support)
    beta = jnp.einsum("nki,ni->nk", D, n)
    alpha = jnp.sqrt(jnp.maximum(jnp.sum(D * D, -1) - beta * beta, 0.0))
    ha, hb = radius / n_alpha, 2.0 * radius / n_beta
    wa = _tent(alpha, (jnp.arange(n_alpha) + 0.5) * ha)
    wb = _tent(beta, -radius + (jnp.arange(n_beta) + 0.5) * hb)
    img = jnp.einsum("nk,nka,nkb->nab", m.astype(xyz.dtype), wa, wb).reshape(xyz.shape[0], -1)
    # normalised to zero mean and unit norm: Euclidean distance ranks as Johnson's correlation coefficient
    img = img - jnp.mean(img, -1, keepdims=True)
    nrm = jnp.linalg.norm(img, axis=-1, keepdims=True)
    good = nok & (jnp.sum(m, -1) >= 3) & (nrm[:, 0] > 0)
    return (jnp.where(good[:, None], img / jnp.where(nrm > 0, nrm, 1.0), 0.0), good, truncated, n,
            _boundary(xyz, n, j, d2))


def spin_images(
    points: Points | Float[Array, "N 3"],
    *,
    radius: float,
    n_alpha: int = 8,
    n_beta: int = 16,
    support_angle: float = 180.0,
    capacity: int = 48,
    normal_k: int = 10,
) -> tuple[Float[Array, "N F"], Bool[Array, " N"], Bool[Array, " N"]]:
    """Spin images (Johnson & Hebert 1999), one per point, ``n_alpha * n_beta`` values.

    For the oriented point ``(p, n)`` each neighbour ``x`` within ``radius`` has the cylindrical
    coordinates ``beta = n . (x - p)`` (height over the tangent plane) and ``alpha = sqrt(|x - p|^2 -
    beta^2)`` (distance from the normal line); the image is their 2-D histogram on ``alpha`` in
    ``[0, radius]`` and ``beta`` in ``[-radius, radius]``, each sample spread bilinearly over the
    four nearest bin centres. Neighbours whose normal turns more than ``support_angle`` from ``n``
    are left out (the paper's support angle against self-occlusion and clutter; off by default:
    on the crop pairs of the registration benchmark, without clutter, the full support matched
    best). The image is invariant to a rotation about ``n``; the normal points away from the
    cloud's centroid (as in :func:`fpfh`; it can flip between two crops where the normal is
    nearly tangent to the radial direction). Each image is returned with its mean
    removed and unit norm, so the Euclidean distance ranks matches as the paper's correlation
    coefficient does.

    Args:
        points: cloud (``Points``, whose ``normals`` are used when present, or ``(N, 3)``).
        radius: support radius (cloud units), typically 4-6x the point spacing.
        n_alpha, n_beta: bins along ``alpha`` and ``beta`` (static ints >= 2).
        support_angle: degrees, in (0, 180] (the paper suggests about 60 in clutter).
        capacity: maximum neighbours per point (static int).
        normal_k: neighbours for the PCA normals when the cloud has none (static int).

    Returns:
        ``(descriptors (N, n_alpha * n_beta), valid (N,), truncated (N,))``; ``valid`` is False for
        invalid points and points with fewer than 3 supporting neighbours (their descriptor is 0).

    Example:
        >>> import jax.numpy as jnp
        >>> from fsjax.fit import spin_images, rotation_from_axis_angle
        >>> from fsjax.data import surface_points
        >>> x = jnp.asarray(surface_points("bunny", 400, 0))
        >>> f1, ok1, _ = spin_images(x, radius=0.03)
        >>> f2, ok2, _ = spin_images(x @ rotation_from_axis_angle(jnp.array([1.0, 2, 3]), 70.0).T, radius=0.03)
        >>> bool(ok1.mean() > 0.95), float(jnp.abs(f1 - f2).max()) < 1e-9   # rotation invariant
        (True, True)
    """
    fn = "spin_images"
    xyz, valid, nrm, capacity, normal_k = _descriptor_args(fn, points, radius, capacity, normal_k, 3)
    n_alpha = check_static_int(fn, "n_alpha", n_alpha, lo=2, hi=64)
    n_beta = check_static_int(fn, "n_beta", n_beta, lo=2, hi=64)
    check_range(fn, "support_angle", support_angle, 0.0, 180.0, lo_open=True)
    cs = jnp.asarray(np.cos(np.deg2rad(float(support_angle))) - 1e-12, xyz.dtype)
    return _spin_core(xyz, valid, nrm, jnp.asarray(radius, xyz.dtype), cs, capacity=capacity,
                      normal_k=normal_k, n_alpha=n_alpha, n_beta=n_beta)[:3]


def _spin(points, *, radius, capacity=48):
    """:func:`spin_images` (default bins) and the normals it used (``(N, 3)``, 0 where missing)."""
    xyz, valid, nrm, capacity, normal_k = _descriptor_args("spin_images", points, radius, capacity, 10, 3)
    cs = jnp.asarray(-1.0 - 1e-12, xyz.dtype)
    return _spin_core(xyz, valid, nrm, jnp.asarray(radius, xyz.dtype), cs, capacity=capacity, normal_k=normal_k,
                      n_alpha=8, n_beta=16)


_SHOT_COS, _SHOT_AZ, _SHOT_EL, _SHOT_RAD = 11, 8, 2, 2


@functools.partial(jax.jit, static_argnames=("capacity", "normal_k"))
def _shot_core(xyz, valid, normals, radius, *, capacity, normal_k):
    dt = xyz.dtype
    xyz, valid = _finite_rows(xyz, valid)
    j, d2, inr, truncated, near = _neighbourhoods(xyz, valid, radius, capacity, normal_k)
    D = xyz[j] - xyz[:, None, :]
    dist = jnp.sqrt(jnp.where(inr, d2, 0.0))
    # local reference frame: covariance about the point itself, weighted by (radius - distance)
    w = jnp.where(inr, radius - dist, 0.0)
    C = jnp.einsum("nk,nki,nkj->nij", w, D, D) / jnp.maximum(jnp.sum(w, -1), 1e-30)[:, None, None]
    _, V = eigh_small(C)  # ascending: V[..., 2] = x (largest), V[..., 0] = z (normal)
    ex = _majority_sign(V[..., 2], D, inr)
    ez = _majority_sign(V[..., 0], D, inr)
    ey = jnp.cross(ez, ex)
    n, nok = _oriented_normals(xyz, valid, normals, D, inr, near)
    m = inr & nok[j]
    L = jnp.einsum("nki,nji->nkj", D, jnp.stack([ex, ey, ez], 1))  # neighbour offsets in the frame
    cosang = jnp.einsum("nki,ni->nk", n[j], ez)
    az = jnp.arctan2(L[..., 1], L[..., 0])
    el = jnp.arctan2(L[..., 2], jnp.sqrt(L[..., 0] ** 2 + L[..., 1] ** 2))
    w_cos = _tent(cosang, -1.0 + (jnp.arange(_SHOT_COS) + 0.5) * (2.0 / _SHOT_COS))
    w_az = _tent(az, -jnp.pi + (jnp.arange(_SHOT_AZ) + 0.5) * (2 * jnp.pi / _SHOT_AZ), circular_period=2 * jnp.pi)
    w_el = _tent(el, jnp.array([-0.25, 0.25], dt) * jnp.pi)
    w_rad = _tent(dist, jnp.array([0.25, 0.75], dt) * radius)
    h = jnp.einsum("nk,nka,nkb,nkc,nkd->nabcd", m.astype(dt), w_az, w_el, w_rad, w_cos).reshape(xyz.shape[0], -1)
    nrm = jnp.linalg.norm(h, axis=-1, keepdims=True)
    good = valid & nok & (jnp.sum(m, -1) >= 5) & (nrm[:, 0] > 0)
    return jnp.where(good[:, None], h / jnp.where(nrm > 0, nrm, 1.0), 0.0), good, truncated, n, _boundary(xyz, n, j, d2)


def shot(
    points: Points | Float[Array, "N 3"],
    *,
    radius: float,
    capacity: int = 48,
    normal_k: int = 10,
) -> tuple[Float[Array, "N 352"], Bool[Array, " N"], Bool[Array, " N"]]:
    """SHOT, Signatures of Histograms of OrienTations (Tombari, Salti & Di Stefano 2010), 352 values per point.

    A local reference frame per point: the eigenvectors of the covariance of the neighbours within
    ``radius`` about the point itself, each neighbour weighted by ``radius - distance``; the largest
    axis is ``x``, the smallest ``z``, each turned to the side where most neighbours lie (Bro et al.
    2008's disambiguation; a tie goes by the sign of the summed offsets), ``y = z x x``. In that frame the sphere of ``radius`` is split into 32
    volumes (8 azimuth x 2 elevation x 2 radial); each volume holds an 11-bin histogram of the cosine
    between a neighbour's normal and ``z``. Every neighbour is spread by quadrilinear interpolation
    (cosine, azimuth (circular), elevation, radius) as in the paper; the 352 values have unit norm.
    Normals are PCA normals of ``normal_k`` points, each turned to the side where most of its
    neighbours lie.

    Args:
        points: cloud (``Points``, whose ``normals`` are used when present, or ``(N, 3)``).
        radius: support radius (cloud units).
        capacity: maximum neighbours per point (static int).
        normal_k: neighbours for the PCA normals when the cloud has none (static int).

    Returns:
        ``(descriptors (N, 352), valid (N,), truncated (N,))``; ``valid`` is False for invalid
        points and points with fewer than 5 neighbours in ``radius`` (their descriptor is 0).

    Example:
        >>> import jax.numpy as jnp
        >>> from fsjax.fit import shot, rotation_from_axis_angle
        >>> from fsjax.data import surface_points
        >>> x = jnp.asarray(surface_points("bunny", 400, 0))
        >>> f1, ok1, _ = shot(x, radius=0.03)
        >>> f2, ok2, _ = shot(x @ rotation_from_axis_angle(jnp.array([1.0, 2, 3]), 70.0).T, radius=0.03)
        >>> bool(ok1.mean() > 0.95), float(jnp.abs(f1 - f2).max()) < 1e-6   # rotation invariant
        (True, True)
    """
    return _shot(points, radius=radius, capacity=capacity, normal_k=normal_k)[:3]


def _shot(points, *, radius, capacity=48, normal_k=10):
    """:func:`shot` and the normals it used (``(N, 3)``, 0 where missing)."""
    xyz, valid, nrm, capacity, normal_k = _descriptor_args("shot", points, radius, capacity, normal_k, 5)
    return _shot_core(xyz, valid, nrm, jnp.asarray(radius, xyz.dtype), capacity=capacity, normal_k=normal_k)


DESCRIPTORS = {"fpfh": fpfh, "spin": spin_images, "shot": shot}
_WITH_NORMALS = {"fpfh": _fpfh, "spin": _spin, "shot": _shot}  # the same, plus the normals they used


def match_descriptors(desc_src, desc_tgt, valid_src=None, valid_tgt=None, *, mutual: bool = True):
    """Nearest-descriptor matches source -> target: ``(idx (Ns,) int32, ok (Ns,) bool)``.

    ``mutual=True`` keeps a match only when the source point is also the target point's nearest.
    Exact nearest neighbours in Euclidean distance, without an ``(Ns, Nt)`` matrix (blocks of rows);
    under ``jax_enable_x64`` float64 distances closer than ``2^(b - 52)`` relative (``2^b`` >= the
    larger count; 2e-12 at 4,096) count as ties, the lower index wins.
    """
    ds, dt = jnp.asarray(desc_src), jnp.asarray(desc_tgt)
    vs = jnp.ones(ds.shape[0], bool) if valid_src is None else jnp.asarray(valid_src, bool)
    vt = jnp.ones(dt.shape[0], bool) if valid_tgt is None else jnp.asarray(valid_tgt, bool)
    return _match_core(ds, dt, vs, vt, bool(mutual))


@functools.partial(jax.jit, static_argnames=("mutual", "block"))
def _match_core(ds, dt, vs, vt, mutual: bool, block: int | None = None):
    """The body of :func:`match_descriptors` as one program.

    With 64-bit integers available (``jax_enable_x64``), one pass over the descriptor distances,
    ``block`` source rows at a time (default 128, fewer when over 2^20 distances) against every target, ``|a - b|^2 = |a|^2 - 2 a.b + |b|^2``
    (clamped at 0, as the brute-force :func:`fsjax.ops.knn` computes it): each distance, as float64,
    becomes an int64 key (its bits, monotone for non-negative floats) whose lowest ``b`` bits (``2^b``
    at least the larger cloud's size) are replaced by the column (row) index, so one integer
    minimum gives a row's nearest target and a running column minimum a target's nearest source,
    lowest index first. Float32 distances are exact in such keys; float64 ones are compared to
    ``2^(b - 52)`` relative (4,096 points: 2e-12), closer pairs count as ties. Two brute-force kNN
    searches took 37 ms for 2,000 x 2,000 descriptors and 297 ms for 4,096 x 4,096 (argmin is a
    slow variadic reduction on XLA:CPU). Without x64: the two searches.
    """
    if not jax.config.jax_enable_x64:
        i_st, _ = knn(dt, ds, 1, ref_valid=vt)
        i_st = i_st[:, 0]
        ok = vs & (i_st >= 0)
        if mutual:
            i_ts, _ = knn(ds, dt, 1, ref_valid=vs)
            ok = ok & (i_ts[jnp.maximum(i_st, 0), 0] == jnp.arange(ds.shape[0]))
        return jnp.maximum(i_st, 0).astype(jnp.int32), ok
    n, m = ds.shape[0], dt.shape[0]
    block = max(8, min(128, 2**20 // max(m, 1))) if block is None else block  # 128: 18 ms vs 24 for 512 at 2,000
    bits = max(1, int(np.ceil(np.log2(max(n, m, 2)))))
    low = jnp.int64((1 << bits) - 1)
    top = jnp.iinfo(jnp.int64).max
    nb = -(-n // block)
    dsp = jnp.pad(ds, ((0, nb * block - n), (0, 0))).reshape(nb, block, -1)
    vsp = jnp.pad(vs, (0, nb * block - n)).reshape(nb, block)
    tt = jnp.sum(dt * dt, -1)
    cols = jnp.arange(m, dtype=jnp.int64)

    def step(ck, blk):
        q, qv, b0 = blk
        d2 = jnp.maximum(jnp.sum(q * q, -1)[:, None] - 2.0 * q @ dt.T + tt[None, :], 0.0)
        key = jax.lax.bitcast_convert_type(d2.astype(jnp.float64), jnp.int64) & ~low
        key = jnp.where(vt[None, :], key, top)
        rk = jnp.min(key | cols[None, :], 1)
        key = jnp.where(qv[:, None], key, top)
        return jnp.minimum(ck, jnp.min(key | (b0 + jnp.arange(block, dtype=jnp.int64))[:, None], 0)), rk

    starts = jnp.arange(nb, dtype=jnp.int64) * block
    ck, rk = jax.lax.scan(step, jnp.full(m, top, jnp.int64), (dsp, vsp, starts))
    rk = rk.reshape(-1)[:n]
    i_st = jnp.where(rk == top, 0, rk & low).astype(jnp.int32)
    ok = vs & (rk != top)
    if mutual:
        i_ts = (ck & low).astype(jnp.int32)
        ok = ok & (ck[i_st] != top) & (i_ts[i_st] == jnp.arange(n))
    return i_st, ok


class CorrespondenceRansacResult(FitResult):
    """Result of :func:`ransac_registration` (``target ~ R source + t``).

    Attributes:
        R, t: best pose refitted on its inliers (NaN when ``reason != 0``).
        rms_len: RMS distance of the inlier pairs at the RANSAC pose (input length unit; NaN
            when not ``converged``). Like ``n_inliers`` it is not updated by the point refits of
            :func:`global_registration`, which move ``R``, ``t``.
        iterations: hypotheses drawn (``n_hypotheses``).
        n_matches: candidate correspondences.
        n_inliers: matches within ``distance`` at the returned pose.
        inlier_fraction: ``n_inliers / n_matches``.
        n_checked: hypotheses that passed the edge-length check.
        chance: bound on the probability that the best inlier count arises by chance among the
            hypotheses tried (see ``max_chance`` of :func:`ransac_registration`); 1 when there is none.
        converged: a hypothesis with at least ``min_inliers`` inliers, unlikely by chance, was found.
        reason: code of :data:`fsjax.types.RESULTS`: ``ok``, ``too_few`` (fewer than 3 matches)
            or ``no_hypothesis``.
    """

    R: Float[Array, "3 3"]
    t: Float[Array, " 3"]
    n_matches: Int[Array, ""]
    n_inliers: Int[Array, ""]
    inlier_fraction: Float[Array, ""]
    n_checked: Int[Array, ""]
    chance: Float[Array, ""]
    converged: Bool[Array, ""]
    reason: Int[Array, ""]
    rms_len: Float[Array, ""] = None
    iterations: Int[Array, ""] = None
    residual_name = "rms_len"


def _score_hypotheses(ps, pt, ok, tri, distance, n_used, block: int = 512):
    """Inlier count of the Kabsch pose of each of the first ``n_used`` triples over all matches
    (-1 for the rest and for degenerate triples), without an (H, N, 3) temporary.

    In coordinates centred on the matches' centroids, ``|R p + t - q|^2 = |p|^2 + |q|^2 + |t|^2 - 2 t.q
    + 2 (R^T t).p - 2 vec(R).vec(q p^T)``: a product of an (H, 16) hypothesis table and a (16, N)
    match table, evaluated ``block`` hypotheses at a time (the vmap over hypotheses used to hold
    H x N x 3 residuals: 1.6 GB and 12 s for 16,384 x 4,096 matches); blocks past ``n_used`` are
    not computed.
    """
    dtype = ps.dtype
    w = ok.astype(dtype)
    nw = jnp.maximum(jnp.sum(w), 1.0)
    psc = jnp.where(ok[:, None], ps - jnp.sum(ps * w[:, None], 0) / nw, 0.0)
    ptc = jnp.where(ok[:, None], pt - jnp.sum(pt * w[:, None], 0) / nw, 0.0)

    def fit(a3, b3):
        r, t, _, sv, _, _ = _weighted_kabsch(a3, b3, jnp.ones(3, dtype), False)
        return r, t, sv[1] > 1e-9 * sv[0]

    fp = jnp.concatenate([jnp.sum(psc * psc + ptc * ptc, -1, keepdims=True), ptc, psc,
                          (ptc[:, :, None] * psc[:, None, :]).reshape(-1, 9)], -1)
    h = tri.shape[0]
    nb = -(-h // block)
    tri = jnp.pad(tri, ((0, nb * block - h), (0, 0))).reshape(nb, block, 3)

    def count(b, score):
        R, t, nondeg = jax.vmap(fit)(psc[tri[b]], ptc[tri[b]])
        fh = jnp.concatenate([jnp.ones((block, 1), dtype), -2 * t, 2 * jnp.einsum("hkj,hk->hj", R, t),
                              -2 * R.reshape(block, 9)], -1)
        d2 = fh @ fp.T + jnp.sum(t * t, -1)[:, None]
        s = jnp.sum(ok[None, :] & (d2 <= distance**2), -1)
        s = jnp.where(nondeg & (b * block + jnp.arange(block) < n_used), s, -1)
        return jax.lax.dynamic_update_slice(score, s.astype(score.dtype), (b * block,))

    score = jax.lax.fori_loop(0, (n_used + block - 1) // block, count, jnp.full(nb * block, -1, jnp.int32))
    return score[:h]


_CHANCE_SHIFTS = 32  # pairings of the null: the target side of the usable matches rolled by 1..32


def _chance_of_inliers(r, t, ps_u, pt_u, n_match, n_in, n_checked, distance):
    """How likely the best pose's inlier count is by chance: a bound on the probability that any of
    the ``n_checked`` hypotheses would reach it if no match were right.

    The null: the usable matches (first ``n_match`` rows of ``ps_u``, ``pt_u``) re-paired by rolling
    the target side by 1..32 places, which keeps both clouds' shapes and destroys every true pair.
    The pose's inliers among those pairings give the rate ``p`` at which a wrong pair lands within
    ``distance`` (add-one smoothed); a wrong hypothesis's count beyond its own 3 defining pairs is
    then about Poisson(``n_match p``), and the best of ``n_checked`` of them is bounded by
    ``n_checked * P(X >= n_in - 3)`` (Bonferroni). A true pose scores far above it; a wrong pose
    that only won among many hypotheses does not (8-15 of ~500 matches on a bunny crop, where the
    old absolute gate of 6 inliers accepted it).
    """
    dtype = ps_u.dtype
    n = ps_u.shape[0]
    i = jnp.arange(n)
    nm = jnp.maximum(n_match, 1)
    first = i < n_match
    q = ps_u @ r.T + t

    def shift(s, acc):
        j = jnp.where(first, (i + s) % nm, i)
        use = first & (s % nm != 0)
        d2 = jnp.sum((q - pt_u[j]) ** 2, -1)
        return (acc[0] + jnp.sum(use & (d2 <= distance**2), dtype=jnp.int32), acc[1] + jnp.sum(use, dtype=jnp.int32))

    hits, tried = jax.lax.fori_loop(1, _CHANCE_SHIFTS + 1, shift, (jnp.int32(0), jnp.int32(0)))
    hits, tried = hits.astype(dtype), tried.astype(dtype)
    lam = n_match * (hits + 1.0) / (tried + 1.0)
    extra = (n_in - 3).astype(dtype)
    tail = jax.scipy.special.gammainc(jnp.maximum(extra, 1.0), lam)  # P(Poisson(lam) >= extra), extra >= 1
    return jnp.where(extra >= 1, jnp.minimum(1.0, n_checked * tail), 1.0)


@jit_fast_compile(static_argnames=("n_hypotheses", "min_inliers"))
def _ransac_core(key, ps, pt, ok, distance, edge_ratio, *, n_hypotheses, min_inliers, max_chance):
    dtype = ps.dtype
    n_match = jnp.sum(ok)
    # uniform draws among the usable matches: their indices first (a stable sort), then a uniform
    # integer below their count (categorical sampling drew H x 3 x N Gumbel variates: 9 s at 16,384 x 4,096)
    usable = jnp.argsort(~ok, stable=True)
    u = jax.random.uniform(key, (n_hypotheses, 3), dtype)
    tri = usable[jnp.minimum((u * jnp.maximum(n_match, 1)).astype(jnp.int32), jnp.maximum(n_match, 1) - 1)]
    distinct = (tri[:, 0] != tri[:, 1]) & (tri[:, 0] != tri[:, 2]) & (tri[:, 1] != tri[:, 2])
    a, b = ps[tri], pt[tri]  # (H, 3, 3)
    ea = jnp.linalg.norm(a - jnp.roll(a, 1, axis=1), axis=-1)
    eb = jnp.linalg.norm(b - jnp.roll(b, 1, axis=1), axis=-1)
    lo, hi = jnp.minimum(ea, eb), jnp.maximum(ea, eb)
    edge_ok = jnp.all(lo >= edge_ratio * hi, -1) & jnp.all(hi > 0, -1)
    checked = distinct & edge_ok & jnp.all(ok[tri], -1)
    n_checked = jnp.sum(checked)

    # only the hypotheses that passed the check are fitted and scored (214 of 16,384 on the bunny
    # crops: 68 -> 4 ms), in their drawn order, so the first best is the one a full scoring picks
    order = jnp.nonzero(checked, size=n_hypotheses, fill_value=0)[0]
    score_c = _score_hypotheses(ps, pt, ok, tri[order], distance, n_checked)
    best = jnp.where(jnp.max(score_c) >= 0, order[jnp.argmax(score_c)], 0)
    score_best = jnp.max(score_c)
    r, t, _, _, _, _ = _weighted_kabsch(a[best], b[best], jnp.ones(3, dtype), False)
    # refit on inliers (twice: the refit can gain inliers)
    for _ in range(2):
        res = ps @ r.T + t - pt
        inl = ok & (jnp.sum(res * res, -1) <= distance**2)
        fit = kabsch_umeyama(ps, pt, weights=inl.astype(dtype))
        r = jnp.where(fit.converged, fit.R, r)
        t = jnp.where(fit.converged, fit.t, t)
    res = ps @ r.T + t - pt
    d2 = jnp.sum(res * res, -1)
    inl = ok & (d2 <= distance**2)
    n_in = jnp.sum(inl)
    rms = jnp.sqrt(jnp.sum(jnp.where(inl, d2, 0.0)) / jnp.maximum(n_in, 1))
    chance = _chance_of_inliers(r, t, ps[usable], pt[usable], n_match, n_in, n_checked, distance)
    reason = jnp.where(n_match < 3, TOO_FEW, jnp.where((score_best < min_inliers) | (n_in < min_inliers)
                                                       | ~(chance <= max_chance), NO_HYPOTHESIS, OK))
    good = reason == OK
    nan = jnp.asarray(jnp.nan, dtype)
    return CorrespondenceRansacResult(R=jnp.where(good, r, nan), t=jnp.where(good, t, nan), n_matches=n_match.astype(jnp.int32),
                        n_inliers=n_in.astype(jnp.int32),
                        inlier_fraction=(n_in / jnp.maximum(n_match, 1)).astype(dtype),
                        n_checked=n_checked.astype(jnp.int32), chance=chance.astype(dtype), converged=good,
                        reason=reason.astype(jnp.int32), rms_len=jnp.where(good, rms, nan),
                        iterations=jnp.asarray(n_hypotheses, jnp.int32))


def ransac_registration(
    key: Array,
    src_xyz: Float[Array, "N 3"],
    tgt_xyz: Float[Array, "N 3"],
    match_ok: Bool[Array, " N"],
    *,
    distance: float,
    n_hypotheses: int = 8192,
    edge_ratio: float = 0.9,
    min_inliers: int = 6,
    max_chance: float = 0.01,
) -> CorrespondenceRansacResult:
    """Correspondence RANSAC: pairs ``src_xyz[i] <-> tgt_xyz[i]`` where ``match_ok[i]``; all hypotheses in one vmap.

    Args:
        key: PRNG key (deterministic result per key).
        src_xyz, tgt_xyz: ``(N, 3)`` matched coordinates (row ``i`` of each is one candidate pair).
        match_ok: ``(N,)`` usable pairs.
        distance: inlier threshold (cloud units).
        n_hypotheses: number of 3-pair hypotheses (static int).
        edge_ratio: edge-length consistency: every edge ratio of a triple must reach this, in (0, 1].
        min_inliers: fewer inliers at the best hypothesis -> reason 6 (static int).
        max_chance: the best pose is refused (reason 6, NaN pose) when its inlier count could arise by
            chance among the hypotheses tried with a probability above this: matches re-paired at
            random give the rate at which a wrong pair lands within ``distance``, and the bound is
            ``n_checked * P(Poisson >= n_inliers - 3)``. The absolute ``min_inliers`` alone accepted
            wrong poses with 8-15 of ~500 matches on surface crops.
    """
    fn = "ransac_registration"
    n_hypotheses = check_static_int(fn, "n_hypotheses", n_hypotheses, lo=1)
    ps, pt = jnp.asarray(src_xyz), jnp.asarray(tgt_xyz)
    if ps.ndim != 2 or ps.shape[-1] != 3 or pt.shape != ps.shape:
        raise ValueError(f"{fn}: arguments 'src_xyz', 'tgt_xyz' must be two (N, 3) arrays of equal shape, "
                         f"got {tuple(ps.shape)} and {tuple(pt.shape)}")
    dtype = jnp.result_type(ps.dtype, pt.dtype, jnp.float32)
    ok = jnp.asarray(match_ok, bool) & jnp.all(jnp.isfinite(ps) & jnp.isfinite(pt), -1)
    ps = jnp.where(ok[:, None], ps, 0.0).astype(dtype)
    pt = jnp.where(ok[:, None], pt, 0.0).astype(dtype)
    return _ransac_core(key, ps, pt, ok, jnp.asarray(distance, dtype), jnp.asarray(edge_ratio, dtype),
                        n_hypotheses=n_hypotheses, min_inliers=int(min_inliers),
                        max_chance=jnp.asarray(max_chance, dtype))


class GlobalResult(WrappedFit):
    """Result of :func:`global_registration`: the RANSAC pose and the ICP-refined one.

    The base fields (``converged``, ``reason``, ``iterations``, ``rms_len``) are those of
    ``refined`` (which carries the coarse stage's failure when RANSAC failed).
    """

    coarse: CorrespondenceRansacResult
    refined: ICPResult
    coarse_matches_R: Float[Array, "3 3"]
    n_descriptors: Int[Array, ""]
    n_truncated: Int[Array, ""]
    residual_name = "rms_len"
    inner = "refined"

    @property
    def rms_len(self):
        return self.refined.rms_len


def global_registration(
    key: Array,
    source: Points | Float[Array, "N 3"],
    target: Points | Float[Array, "M 3"],
    *,
    radius: float,
    distance: float,
    n_hypotheses: int = 8192,
    mutual: bool = True,
    capacity: int = 48,
    refine: str | None = "point_to_plane",
    overlap: float = 1.0,
    refit_rounds: int = 10,
    descriptor: str = "fpfh",
    **icp_kwargs,
) -> GlobalResult:
    """Local descriptors (FPFH by default), mutual matching, correspondence RANSAC, then ICP from the RANSAC pose.

    Args:
        key: PRNG key for RANSAC.
        source, target: clouds (``Points`` or ``(N, 3)``).
        radius: descriptor support radius (cloud units).
        distance: RANSAC inlier threshold and ICP correspondence gate (2x) (cloud units).
        n_hypotheses: RANSAC hypotheses (static).
        mutual: mutual-nearest descriptor matches only.
        capacity: descriptor neighbour capacity (static).
        refine: ICP method for the refinement (``None``: none; the refined record then repeats the
            coarse pose with ``iterations=0``).
        overlap: trimmed-ICP overlap for the refinement (partial scans: about the shared fraction).
        refit_rounds: after RANSAC on the descriptor matches, at most this many point-to-plane
            refits of the coarse pose on *point* pairs (each source point and its nearest target
            point, pairs closer than ``distance / 2``, the target's normals from the descriptor,
            target points on the edge of its sampled surface left out; stops when a step turns
            less than 1e-6 rad); the matches of independent samples are
            only spacing-accurate, point pairs are many more. ``coarse_matches_R`` keeps the pure
            RANSAC rotation. 0 disables.
        descriptor: ``"fpfh"`` (:func:`fpfh`, 33 values), ``"spin"`` (:func:`spin_images`, 128) or
            ``"shot"`` (:func:`shot`, 352).
        **icp_kwargs: further :func:`fsjax.fit.icp` arguments.

    Returns:
        :class:`GlobalResult`. A failed RANSAC (reason != 0) gives a failed refinement (NaN) too.
    """
    check_choice("global_registration", "descriptor", descriptor, tuple(DESCRIPTORS))
    describe = _WITH_NORMALS[descriptor]
    fs, vs, trs, _, _ = describe(source, radius=radius, capacity=capacity)
    ft, vt, trt, nt, edge = describe(target, radius=radius, capacity=capacity)
    xs, vsrc, _ = as_cloud("global_registration", "source", source)
    xt, vtgt, _ = as_cloud("global_registration", "target", target)
    vsrc = vsrc & jnp.all(jnp.isfinite(xs), -1)
    vtgt = vtgt & jnp.all(jnp.isfinite(xt), -1)
    xs, xt = jnp.where(vsrc[:, None], xs, 0.0), jnp.where(vtgt[:, None], xt, 0.0)
    idx, ok = match_descriptors(fs, ft, vs, vt, mutual=mutual)
    coarse = ransac_registration(key, xs, xt[idx], ok, distance=distance, n_hypotheses=n_hypotheses)
    r_matches = coarse.R
    if refit_rounds:
        coarse = _point_refit(coarse, xs, xt, nt.astype(xs.dtype), vsrc, vtgt & ~edge,
                              jnp.asarray(0.5 * distance, xs.dtype), int(refit_rounds))
    if refine is None:
        refined = ICPResult(R=coarse.R, t=coarse.t, rms_len=jnp.asarray(jnp.nan, xs.dtype),
                            iterations=jnp.int32(0), converged=coarse.converged,
                            inlier_fraction=coarse.inlier_fraction, n_correspondences=coarse.n_inliers,
                            reason=coarse.reason)
    else:
        icp_kwargs.setdefault("max_correspondence_distance", 2.0 * distance)
        refined = icp(source, target, method=refine, init_R=coarse.R, init_t=coarse.t, overlap=overlap,
                      **icp_kwargs)
        refined = eqx.tree_at(lambda r: r.reason, refined, jnp.where(coarse.converged, refined.reason,
                                                                     coarse.reason).astype(jnp.int32))
        refined = eqx.tree_at(lambda r: r.converged, refined, refined.converged & coarse.converged)
    return GlobalResult(coarse=coarse, refined=refined, coarse_matches_R=r_matches,
                        n_descriptors=jnp.sum(vs) + jnp.sum(vt),
                        n_truncated=jnp.sum(trs) + jnp.sum(trt))


@jit_fast_compile(static_argnames=("rounds", "metric"))
def _point_refit(coarse, xs, xt, nt, vs, vt, distance, rounds, metric="plane"):
    """Refit the coarse pose on nearest-point pairs closer than ``distance``, ``rounds`` times at most.

    ``metric="plane"``: one Gauss-Newton step of the point-to-plane error on the target normals
    ``nt`` per round (pairs whose target normal is missing (0) take no part), stopping once the
    step turns less than 1e-6 rad and moves less than 1e-6 ``distance`` (float32: 64 eps); ``"point"``: closed-form
    Kabsch on the pairs (the refit before 2026-12-05, kept to measure against).

    Both clouds are centred on the target's valid points and scaled to their unit RMS radius first
    (as :func:`fsjax.fit.icp` does): the Gauss-Newton solve's singularity test compares rotation and
    translation columns, and in metres in float32 it refused every step (seeds 0-4: the RANSAC pose
    came back, 0.1-1.5 deg).
    """
    dtype = xs.dtype
    w_t = vt.astype(dtype)
    c = jnp.sum(xt * w_t[:, None], 0) / jnp.maximum(jnp.sum(w_t), 1.0)
    sc = jnp.sqrt(jnp.sum(jnp.sum((xt - c) ** 2, -1) * w_t) / jnp.maximum(jnp.sum(w_t), 1.0))
    sc = jnp.where(sc > 0, sc, 1.0)
    xs, xt, distance = (xs - c) / sc, (xt - c) / sc, distance / sc
    r, t = coarse.R, (coarse.t + coarse.R @ c - c) / sc
    # the target's grid is built once and queried with the gate as ``max_dist`` (a query stops at the
    # first cell block past it), also below knn's brute-force size: at 2,000 points 1.6 ms a round
    # instead of 11 (the whole call 183 -> ~130 ms wall, Open3D 174, idle), for 1.7 s CPU more compile
    # (FPFH + RANSAC's first call 4.85 -> 6.19 s CPU, over issue 13's 5 s; the persistent compile
    # cache pays it once; brute force below that size is in git history, commit 1a4ef6b)
    index = build_index(xt, vt, k=4)
    n_ok = jnp.sum(nt * nt, -1) > 0
    tol = max(1e-6, 64 * float(jnp.finfo(dtype).eps))  # float32: the solve's rounding noise

    def pairs(r, t):
        p = xs @ r.T + t
        j, d2 = query_knn(index, p, 1, max_dist=distance)
        w = vs & (j[:, 0] >= 0) & (d2[:, 0] <= distance**2)
        return p, jnp.maximum(j[:, 0], 0), w

    if metric == "point":
        def step(_, rt):
            _, j, w = pairs(*rt)
            fit = kabsch_umeyama(xs, xt[j], weights=w.astype(xs.dtype))
            return jnp.where(fit.converged, fit.R, rt[0]), jnp.where(fit.converged, fit.t, rt[1])

        r, t = jax.lax.fori_loop(0, rounds, step, (r, t))  # a loop, not `rounds` unrolled copies to compile
        return eqx.tree_at(lambda res: (res.R, res.t), coarse, (r, sc * t + c - r @ c))

    def body(st):
        r, t, i, _ = st
        p, j, w = pairs(r, t)
        dr, dt, ok = _p2plane_step(p, xt[j], nt[j], (w & n_ok[j]).astype(dtype))
        sin_turn = 0.5 * jnp.linalg.norm(jnp.stack([dr[2, 1] - dr[1, 2], dr[0, 2] - dr[2, 0], dr[1, 0] - dr[0, 1]]))
        small = (sin_turn < tol) & (jnp.linalg.norm(dt) < tol * distance)
        return (jnp.where(ok, dr @ r, r), jnp.where(ok, dr @ t + dt, t), i + 1, small | ~ok)

    r, t, _, _ = jax.lax.while_loop(lambda st: (st[2] < rounds) & ~st[3], body,
                                    (r, t, jnp.int32(0), jnp.bool_(False)))
    return eqx.tree_at(lambda res: (res.R, res.t), coarse, (r, sc * t + c - r @ c))


def _crop_pair(n_points: int, keep: float, seed: int):
    """Two independent bunny samples cropped along x: source keeps the low ``keep`` fraction, target the high."""
    from ..data import surface_points

    a, b = surface_points("bunny", n_points, seed), surface_points("bunny", n_points, seed + 1)
    xs = a[a[:, 0] <= np.quantile(a[:, 0], keep)]
    xt = b[b[:, 0] >= np.quantile(b[:, 0], 1.0 - keep)]
    return xs, xt


def _measure_global(n_points: int = 2600, angle_deg: float = 60.0, overlap: float = 0.7, seed: int = 0,
                    n_hypotheses: int = 16384, radius: float = 0.025, distance: float = 0.01,
                    refine_points: int = 10000, descriptor: str = "fpfh") -> dict:
    """The tour/test scene of issue 4 item 2: 60 deg, 70 % overlap, FPFH + RANSAC, then trimmed ICP.

    FPFH + RANSAC run on crops of ``n_points`` samples; the point-to-plane ICP refinement on denser
    crops of ``refine_points`` samples (features on a sparse cloud, the fine fit on a dense one).
    """
    from .rigid import rotation_error_deg, rotation_from_axis_angle

    keep = 1.0 / (2.0 - overlap)  # shared part (2 keep - 1) is `overlap` of each crop
    r = np.asarray(rotation_from_axis_angle(jnp.array([0.2, 1.0, 0.5]), angle_deg))
    shift = np.array([0.05, 0.02, -0.03])
    xs, xt = _crop_pair(n_points, keep, seed)
    src = (xs - shift) @ r  # target = R src + shift
    res = global_registration(jax.random.key(seed), jnp.asarray(src), jnp.asarray(xt), radius=radius,
                              distance=distance, n_hypotheses=n_hypotheses, refine=None, descriptor=descriptor)
    ds, dt = _crop_pair(refine_points, keep, seed + 10)
    dsrc = (ds - shift) @ r
    fine = icp(jnp.asarray(dsrc), jnp.asarray(dt), method="point_to_plane", init_R=res.coarse.R, init_t=res.coarse.t,
               overlap=overlap, max_correspondence_distance=2.0 * distance, min_inlier_fraction=0.5 * overlap,
               max_iterations=100, rot_tol=1e-5, trans_tol=1e-5)
    rt = jnp.asarray(r)
    return {
        "n_source": len(xs), "n_target": len(xt), "n_refine": len(ds), "keep": keep, "angle_deg": angle_deg,
        "coarse_error_deg": float(rotation_error_deg(res.coarse.R, rt)),
        "matches_only_error_deg": float(rotation_error_deg(res.coarse_matches_R, rt)),
        "refined_error_deg": float(rotation_error_deg(fine.R, rt)),
        "coarse_t_error": float(np.linalg.norm(np.asarray(res.coarse.t) - shift)),
        "refined_t_error": float(np.linalg.norm(np.asarray(fine.t) - shift)),
        "n_matches": int(res.coarse.n_matches), "n_inliers": int(res.coarse.n_inliers),
        "n_checked": int(res.coarse.n_checked), "coarse_converged": bool(res.coarse.converged),
        "refined_converged": bool(fine.converged), "icp_iterations": int(fine.iterations),
        "null_error_deg": angle_deg, "src": src, "tgt": xt, "R": r, "t": shift,
    }
