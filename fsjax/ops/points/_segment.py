"""Segmentation of point clouds: Euclidean clustering and ground removal.

Conventions:

* Up is ``+z`` (the scanner/world frame of a LiDAR scene); ground removal
  accepts planes whose normal is within ``max_slope_deg`` of ``z``.
* Clusters are connected components of the radius graph (an edge joins two
  valid points at distance ``<= radius``). Each point's neighbour list holds
  at most ``max_neighbors`` entries (static); the graph is symmetrised, so an
  edge is lost only when *both* ends have more than ``max_neighbors`` closer
  neighbours, and then ``truncated`` is set (components might be split).
* Labels (:class:`PointLabels`): ``0`` = no cluster (invalid point, or a
  component smaller than ``min_size``), ``1..count`` numbered in the order of
  each cluster's lowest point index (deterministic). At most ``capacity``
  clusters (static); more set ``truncated`` and the extra clusters get 0.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from jax import lax

from ..._checks import check_positive, check_range, check_static_int
from ...registry import LinKnob, LogKnob, register
from ...types import PointLabels, Points
from ._cloud import _replace, _valid_mask
from ._search import radius_search

__all__ = ["euclidean_cluster", "remove_ground", "cluster_centroids"]


# ---------------------------------------------------------------------------
# Euclidean clustering
# ---------------------------------------------------------------------------


@jax.jit
def connected_components(idx, valid):
    """Component root (lowest index) of every node of the symmetrised graph ``idx`` ``(N, K)``.

    Label propagation (min over neighbours, both directions) with pointer
    jumping, in a ``lax.while_loop`` to the exact fixed point; returns
    ``(root (N,), iterations)``; invalid nodes get root ``N``.
    """
    n = idx.shape[0]
    big = jnp.int32(n)
    lab0 = jnp.where(valid, jnp.arange(n, dtype=jnp.int32), big)
    ok = (idx >= 0) & valid[:, None]
    j = jnp.where(ok, idx, 0)

    def step(lab):
        nb = jnp.where(ok, lab[j], big)
        new = jnp.minimum(lab, jnp.min(nb, axis=1))
        new = new.at[j.reshape(-1)].min(jnp.where(ok, new[:, None], big).reshape(-1))
        safe = jnp.minimum(new, n - 1)
        new = jnp.where(new < big, jnp.minimum(new, new[safe]), big)  # pointer jumping
        return new

    def cond(c):
        lab, prev, it = c
        return jnp.any(lab != prev) & (it < n + 1)

    def body(c):
        lab, _, it = c
        return step(lab), lab, it + 1

    lab1 = step(lab0)
    lab, _, it = lax.while_loop(cond, body, (lab1, lab0, jnp.int32(1)))
    return lab, it


@register(family="points", takes=Points, gives=PointLabels, knobs={"radius": LogKnob(0.05, 1.0)},
          differentiable=False,
          refs=["R. B. Rusu, Semantic 3D object maps for everyday manipulation in human living environments, "
                "PhD thesis, TU Munich, 2009 (Euclidean cluster extraction)",
                "Y. Shiloach, U. Vishkin, An O(log n) parallel connectivity algorithm, J. Algorithms 3(1), 1982 "
                "(hooking and pointer jumping)"])
def euclidean_cluster(pts: Points, /, *, radius: float = 0.2, min_size: int = 10, max_neighbors: int = 32,
                      capacity: int = 64) -> PointLabels:
    """Euclidean clustering: connected components of the radius graph, small components dropped.

    Two valid points are linked when their distance is ``<= radius``;
    clusters are the connected components (exact, by label propagation with
    pointer jumping to a fixed point under ``jit``); components with fewer
    than ``min_size`` points get label 0.

    Args:
      pts: the cloud.
      radius: link distance in the unit of ``xyz`` (knob ``a``, log 0.05..1; default 0.2).
      min_size: smallest cluster kept (default 10; may be traced).
      max_neighbors: neighbour-list capacity per point (static int, 1..256; default 32).
      capacity: maximum number of clusters (static int; default 64).

    Returns:
      :class:`PointLabels` (labels ``1..count`` by lowest point index).

    Note:
      Same partition as PCL's ``EuclideanClusterExtraction`` (and as
      ``scipy.sparse.csgraph.connected_components`` on the ``cKDTree``
      radius graph, which the tests compare exactly) when no neighbour list
      overflows.

    Example:
      Two groups of three points, 5 apart, with ``radius=1``:

      >>> import jax.numpy as jnp, fsjax
      >>> xyz = jnp.array([[0.0, 0, 0], [0.5, 0, 0], [1, 0, 0], [6, 0, 0], [6.5, 0, 0], [7, 0, 0]])
      >>> lab = fsjax.ops.euclidean_cluster(fsjax.Points(xyz), radius=1.0, min_size=2)
      >>> [int(v) for v in lab.labels], int(lab.count)
      ([1, 1, 1, 2, 2, 2], 2)
    """
    op = "euclidean_cluster"
    check_positive(op, "radius", radius)
    check_range(op, "min_size", min_size, 1, None)
    kmax = check_static_int(op, "max_neighbors", max_neighbors, lo=1, hi=256)
    cap = check_static_int(op, "capacity", capacity, lo=1)
    valid = _valid_mask(pts)
    xyz = jnp.where(valid[:, None], pts.xyz, 0.0)
    n = xyz.shape[0]
    idx, _, _, trunc = radius_search(xyz, xyz, jnp.asarray(radius, xyz.dtype), kmax, ref_valid=valid)
    root, _ = connected_components(idx, valid)
    size = jax.ops.segment_sum(valid.astype(jnp.int32), jnp.minimum(root, n), num_segments=n + 1)[:n]
    is_root = valid & (root == jnp.arange(n)) & (size >= jnp.asarray(min_size))
    rank = jnp.cumsum(is_root.astype(jnp.int32))  # 1-based label of each kept root
    count = rank[-1] if n else jnp.int32(0)
    r = jnp.minimum(root, n - 1)
    lab = jnp.where(valid & (root < n) & is_root[r], rank[r], 0)
    over = lab > cap
    lab = jnp.where(over, 0, lab).astype(jnp.int32)
    truncated = jnp.any(trunc & valid) | (count > cap)
    return PointLabels(lab, pts.valid, count=jnp.minimum(count, cap), truncated=truncated)


def cluster_centroids(pts: Points, labels: PointLabels, capacity: int = 64):
    """Centroids and sizes of clusters ``1..capacity``: ``(centroids (C, 3), sizes (C,), valid (C,))``.

    Rows of absent clusters hold NaN and size 0.
    """
    lab = labels.labels
    w = ((lab > 0) & (lab <= capacity) & _valid_mask(pts)).astype(pts.xyz.dtype)
    seg = jnp.where(w > 0, lab - 1, capacity)
    x = jnp.where(w[:, None] > 0, pts.xyz, 0.0)
    s = jax.ops.segment_sum(x, seg, num_segments=capacity + 1)[:capacity]
    c = jax.ops.segment_sum(w, seg, num_segments=capacity + 1)[:capacity]
    ok = c > 0
    return jnp.where(ok[:, None], s / jnp.where(ok, c, 1.0)[:, None], jnp.nan), c.astype(jnp.int32), ok


# ---------------------------------------------------------------------------
# ground removal
# ---------------------------------------------------------------------------


@functools.partial(jax.jit, static_argnames=("n_hypotheses", "rounds"))
def ground_plane(xyz, valid, threshold, max_slope_deg, n_hypotheses: int, seed: int, rounds: int = 3):
    """RANSAC plane among near-horizontal hypotheses; returns ``(plane (4,), ok)`` (``n_z > 0``)."""
    dt = xyz.dtype
    n = xyz.shape[0]
    key = jax.random.PRNGKey(seed)
    g = jax.random.gumbel(key, (n_hypotheses, n), dtype=dt)
    g = jnp.where(valid[None, :], g, -jnp.inf)
    _, idx = lax.top_k(g, min(3, n))
    p = xyz[idx]
    nv = jnp.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    nn = jnp.sqrt(jnp.sum(nv * nv, -1))
    ok = (nn > 0) & jnp.all(valid[idx], axis=1)
    nv = nv / jnp.where(ok, nn, 1.0)[:, None]
    nv = jnp.where(nv[:, 2:3] < 0, -nv, nv)
    cos_max = jnp.cos(jnp.radians(jnp.asarray(max_slope_deg, dt)))
    ok = ok & (nv[:, 2] >= cos_max)
    d = jnp.sum(nv * p[:, 0], -1)
    dist = jnp.abs(xyz @ nv.T - d[None, :])  # (N, H): all hypotheses scored at once
    cnt = jnp.sum((dist <= threshold) & valid[:, None], axis=0)
    cnt = jnp.where(ok, cnt, -1)
    b = jnp.argmax(cnt)
    plane = jnp.concatenate([nv[b], d[b][None]])
    found = cnt[b] >= 3

    def refit(_, pl):
        inl = (jnp.abs(xyz @ pl[:3] - pl[3]) <= threshold) & valid
        w = inl.astype(dt)
        sw = jnp.maximum(jnp.sum(w), 1.0)
        c = jnp.sum(xyz * w[:, None], 0) / sw
        dd = (xyz - c) * w[:, None]
        ev, evec = jnp.linalg.eigh(dd.T @ dd / sw)
        nr = evec[:, 0]
        nr = jnp.where(nr[2] < 0, -nr, nr)
        good = (jnp.sum(w) >= 3) & (ev[1] > 0) & (nr[2] >= cos_max)
        return jnp.where(good, jnp.concatenate([nr, jnp.dot(nr, c)[None]]), pl)

    plane = lax.fori_loop(0, rounds, refit, plane)
    return plane, found


@register(family="points", takes=Points, gives=Points,
          knobs={"threshold": LinKnob(0.02, 0.5), "max_slope_deg": LinKnob(2.0, 45.0)},
          differentiable=False,
          refs=["M. A. Fischler, R. C. Bolles, Random sample consensus, CACM 24(6), 1981",
                "B. Douillard et al., On the segmentation of 3D LIDAR point clouds, ICRA 2011"])
def remove_ground(pts: Points, /, *, threshold: float = 0.1, max_slope_deg: float = 15.0,
                  n_hypotheses: int = 128, seed: int = 0) -> Points:
    """Ground removal: drop the points of the dominant near-horizontal plane.

    RANSAC over planes through 3 valid points whose normal is within
    ``max_slope_deg`` of ``+z`` (all hypotheses scored in one pass), the
    plane with the most points within ``threshold`` wins and is refitted by
    total least squares on its inliers (3 rounds); every valid point within
    ``threshold`` of it, or below it, is marked invalid. A sloped ground
    (e.g. 5 deg) is one plane; a cloud with no admissible plane is returned
    unchanged.

    Args:
      pts: the cloud, ``+z`` up.
      threshold: ground band half-width in the unit of ``xyz`` (knob ``a``, 0.02..0.5; default 0.1).
      max_slope_deg: largest ground slope accepted (knob ``b``, 2..45 deg; default 15).
      n_hypotheses: RANSAC samples (static int; default 128).
      seed: sampling seed (static int; deterministic).

    Returns:
      ``pts`` with the ground (and anything below it) marked invalid.

    Note:
      The plane-RANSAC ground model of Douillard et al. (2011); no reference
      implementation is compared (Open3D's ``segment_plane`` has no slope
      constraint). Tested on the synthetic LiDAR scene: all ground points
      removed, no object point more than ``threshold`` above the ground.

    Example:
      A flat ground of 100 points at ``z = 0`` and a 4-point post above it:

      >>> import numpy as np, jax.numpy as jnp, fsjax
      >>> g = np.stack(np.meshgrid(np.arange(10.0), np.arange(10.0)), -1).reshape(-1, 2)
      >>> post = np.array([[5.0, 5.0, 0.5], [5.0, 5.0, 1.0], [5.0, 5.0, 1.5], [5.0, 5.0, 2.0]])
      >>> xyz = np.r_[np.c_[g, np.zeros(100)], post]
      >>> out = fsjax.ops.remove_ground(fsjax.Points(jnp.asarray(xyz)))
      >>> int(out.valid.sum()), bool(out.valid[100:].all())
      (4, True)
    """
    op = "remove_ground"
    check_positive(op, "threshold", threshold)
    check_range(op, "max_slope_deg", max_slope_deg, 0.0, 90.0)
    nh = check_static_int(op, "n_hypotheses", n_hypotheses, lo=1)
    sd = check_static_int(op, "seed", seed, lo=0)
    valid = _valid_mask(pts)
    xyz = jnp.where(valid[:, None], pts.xyz, 0.0)
    thr = jnp.asarray(threshold, xyz.dtype)
    plane, found = ground_plane(xyz, valid, thr, max_slope_deg, nh, sd)
    h = xyz @ plane[:3] - plane[3]
    ground = valid & found & (h <= thr)
    return _replace(pts, valid=pts.valid & ~ground)
