"""Parametric Hough transforms on point clouds: planes and spheres, fixed capacity.

Both ops share one scheme (Hough 1962; Duda and Hart 1972; the 3-D plane case after
Borrmann et al. 2011, spheres by voting along normals as in Ogundana et al. 2007):

1. **Vote.** Every valid point votes into a static accumulator, all points at once (one
   scatter-add, no loop over points). Planes: a Fibonacci sampling of the unit hemisphere
   (``n_dirs`` normals, static) times ``n_rho`` offset bins across the cloud's extent.
   Spheres: at each of ``n_radii`` radii the point votes for the two centres ``p +- r n``
   along its normal (both signs: the orientation of an estimated normal is arbitrary) into a
   ``grid^3`` voxel accumulator over the cloud's bounding box grown by the largest radius.
2. **Peaks.** Non-maximum suppression: a bin is a peak when it holds more votes than every
   neighbouring bin (planes: the 8 nearest normals, the antipodal wrap at the hemisphere's
   rim included, x offset +-1 bin; spheres: the 3^4 neighbourhood in radius x centre); ties
   are broken by bin index, so a plateau gives one peak. The ``4 * max_*`` strongest peaks
   with at least ``min_votes`` votes are the candidates.
3. **Refine.** Each candidate is refitted by least squares on its inliers (points within one
   bin width ``tol`` of the surface), three rounds: planes by total least squares (the
   smallest principal axis of the inliers), spheres by the algebraic fit of Kasa (1976)
   followed by Gauss-Newton steps on the geometric distance. The bin is coarse, and another
   surface passing within it pulls the fit (a sphere through the tilted plane of the tests
   turned it by 0.56 deg), so three more rounds follow on a narrowing band: the points within
   3 robust sigmas (1.4826 x their median distance) of the fit so far, inside the previous
   band (the test scene's planes: 0.04-0.13 deg over five seeds).
4. **Accept.** The final band ``t`` must be narrower than ``0.9 tol``: a fit whose points spread
   over the whole bin straddles a surface rather than lying on one (and a surface noisier than
   about 0.3 bins is refused rather than fitted loosely: pinned in the tests). The surface
   must stand out of the clutter around it: with ``n_in`` points within ``t`` and ``n_out``
   points between ``t`` and ``3 t``, the background expected within ``t`` is ``n_out`` times
   the ratio of the two shells' volumes (1/2 for a plane slab; exact spherical shells for a
   sphere). ``support = 1 - background / n_in`` must reach ``min_support`` and
   ``n_in - background`` must reach ``min_votes``. A uniform cloud has ``support`` near 0 (the
   accumulator's maxima of pure clutter are refused: tested), a surface near 1. Spheres must
   also have their radius in ``[r_min - t, r_max + t]``.
5. **Choose.** Candidates whose inlier sets overlap by more than half of the smaller one are
   the same surface: the one with more accumulator votes is kept (the votes, not the inlier
   count, decide: a loose fit gathers more inliers than the right one). The kept surfaces
   come first, by descending votes; ``truncated`` says more were kept than ``max_*`` holds.

The result is a :class:`fsjax.RegionProps` table, one row per surface (the record of named
per-item measurements with a fixed capacity and a ``valid`` mask; rows that are not valid hold
NaN): planes ``n . x = d`` with columns ``nx, ny, nz, d, votes, inliers, rms, support``;
spheres with ``cx, cy, cz, r, votes, inliers, rms, support``. ``votes`` is the accumulator
peak, ``inliers`` the points within the final band ``t`` of the refined surface, ``rms`` their
RMS distance to it (the point unit).

Invalid slots of the cloud neither vote nor count; points with a non-finite coordinate raise
outside ``jit`` (the registry's input check) and are treated as invalid slots inside it.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from ..._checks import check_range, check_static_int, is_concrete
from ...registry import register
from ...types import Points, RegionProps
from ..points._cloud import pca_frames
from ..points._search import knn

__all__ = ["hough_planes3d", "hough_spheres3d"]

_REF_HOUGH = "P. V. C. Hough, Method and means for recognizing complex patterns, US Patent 3,069,654, 1962"
_REF_DH = ("R. O. Duda, P. E. Hart, Use of the Hough transformation to detect lines and curves in pictures, "
           "Communications of the ACM 15(1), 1972, 11-15")
_REF_BORRMANN = ("D. Borrmann, J. Elseberg, K. Lingemann, A. Nuechter, The 3D Hough Transform for plane "
                 "detection in point clouds: a review and a new accumulator design, 3D Research 2(2), 2011")
_REF_OGUNDANA = ("O. O. Ogundana, C. R. Coggrave, R. L. Burguete, J. M. Huntley, Fast Hough transform for "
                 "automated detection of spheres in three-dimensional point clouds, Optical Engineering "
                 "46(5), 2007, 051002")
_REF_KASA = ("I. Kasa, A circle fitting procedure and its error analysis, IEEE Trans. Instrumentation and "
             "Measurement 25(1), 1976, 8-14")
_REF_GONZALEZ = ("A. Gonzalez, Measurement of areas on a sphere using Fibonacci and latitude-longitude "
                 "lattices, Mathematical Geosciences 42(1), 2010, 49-64")

PLANE_COLUMNS = ("nx", "ny", "nz", "d", "votes", "inliers", "rms", "support")
SPHERE_COLUMNS = ("cx", "cy", "cz", "r", "votes", "inliers", "rms", "support")
_ROUNDS = 3
_GN_STEPS = 4
_RESOLVED = 0.9  # the fit's 3-sigma band must be narrower than this fraction of the bin width


# ---------------------------------------------------------------------------
# shared pieces
# ---------------------------------------------------------------------------


def _check_points(op: str, points) -> None:
    if not isinstance(points, Points):
        raise TypeError(f"{op}: argument 'points' must be a Points; got {type(points).__name__}")
    if points.xyz.ndim != 2:
        raise ValueError(f"{op}: argument 'points' must be one cloud (N, 3) (batch with jax.vmap); got xyz of "
                         f"shape {points.xyz.shape}")


def _valid(points):
    return points.valid & jnp.all(jnp.isfinite(points.xyz), -1)


def _accept(n_in, n_out, shell_ratio, min_votes, min_support):
    """Excess of inliers over the clutter expected in the inner shell, its fraction, and the verdict."""
    bg = n_out * shell_ratio
    excess = n_in - bg
    support = jnp.where(n_in > 0, excess / jnp.maximum(n_in, 1.0), 0.0)
    return excess, support, (excess >= min_votes) & (support >= min_support)


def _select(keys, ok, inl, capacity):
    """Greedy choice among refined candidates: best ``keys`` first, a candidate whose inlier set
    overlaps an accepted one by more than half of the smaller is dropped. Returns the chosen
    candidates' indices ``(capacity,)``, their validity and the truncation flag."""
    c = keys.shape[0]
    f = inl.astype(keys.dtype)
    overlap = f @ f.T
    size = jnp.sum(f, -1)
    same = overlap > 0.5 * jnp.minimum(size[:, None], size[None, :])
    order = jnp.argsort(jnp.where(ok, -keys, jnp.inf))

    def step(kept, j):
        cand = order[j]
        dup = jnp.any(kept & same[cand])
        keep = ok[cand] & ~dup
        return kept.at[cand].set(keep), None

    kept, _ = jax.lax.scan(step, jnp.zeros(c, bool), jnp.arange(c))
    rank = jnp.argsort(jnp.where(kept, -keys, jnp.inf))
    chosen = rank[:capacity]
    return chosen, kept[chosen], jnp.sum(kept) > capacity


def _fine_rounds(dist_of, rnd, params, valid, tol):
    """The bin width ``tol`` is coarse: a surface or clutter passing near the fit pulls it. Three
    more rounds, each refitting (``rnd(params, band)``) on the points within 3 robust sigmas
    (1.4826 x their median distance) of the fit so far, among those in the previous round's band
    (at least ``tol / 10``). Returns the parameters and the last band."""

    def fine(carry, _):
        params, t = carry
        e = dist_of(params)
        inl = valid & (e < t)
        med = jnp.sort(jnp.where(inl, e, jnp.inf))[jnp.sum(inl) // 2]
        t = jnp.clip(3.0 * 1.4826 * jnp.where(jnp.isfinite(med), med, t), 0.1 * tol, t)
        params, _ = rnd(params, t)
        return (params, t), None

    (params, t), _ = jax.lax.scan(fine, (params, tol), None, length=_ROUNDS)
    return params, t


def _table(cols, valid):
    t = jnp.stack(cols, -1)
    return jnp.where(valid[:, None], t, jnp.nan)


# ---------------------------------------------------------------------------
# planes
# ---------------------------------------------------------------------------


@functools.lru_cache(maxsize=8)
def _hemisphere(m: int, k: int = 8):
    """``m`` Fibonacci directions on the upper unit hemisphere (z > 0) and, per direction, its
    ``k`` nearest other directions of the full sphere as (hemisphere index, flipped) pairs."""
    i = np.arange(m) + 0.5
    z = i / m
    phi = i * np.pi * (3.0 - np.sqrt(5.0))
    r = np.sqrt(1.0 - z * z)
    d = np.stack([r * np.cos(phi), r * np.sin(phi), z], -1)
    full = np.concatenate([d, -d])
    cosang = d @ full.T
    cosang[np.arange(m), np.arange(m)] = -2.0
    nb = np.argsort(-cosang, axis=1)[:, :k]
    return d, (nb % m).astype(np.int32), (nb >= m)


@functools.partial(jax.jit, static_argnames=("n_dirs", "n_rho", "capacity"))
def _planes_core(xyz, valid, min_votes, min_support, n_dirs, n_rho, capacity):
    dt = xyz.dtype
    dirs_np, nb_np, flip_np = _hemisphere(n_dirs)
    dirs = jnp.asarray(dirs_np, dt)
    vf = valid.astype(dt)
    cnt = jnp.sum(vf)
    c = jnp.sum(xyz * vf[:, None], 0) / jnp.maximum(cnt, 1.0)
    q = jnp.where(valid[:, None], xyz - c, 0.0)
    R = jnp.max(jnp.where(valid, jnp.linalg.norm(q, axis=-1), 0.0))
    R = jnp.where(R > 0, R, 1.0) * (1.0 + 1e-6)
    w = 2.0 * R / n_rho
    rho = q @ dirs.T  # (N, n_dirs)
    b = jnp.clip(jnp.floor((rho + R) / w).astype(jnp.int32), 0, n_rho - 1)
    flat = (jnp.arange(n_dirs, dtype=jnp.int32) * n_rho)[None, :] + b
    acc = jnp.zeros(n_dirs * n_rho, dt).at[flat.reshape(-1)].add(
        jnp.broadcast_to(vf[:, None], flat.shape).reshape(-1)).reshape(n_dirs, n_rho)
    # unique scores (ties broken by index), neighbours over normals x offsets
    S = acc + 0.5 * jnp.arange(n_dirs * n_rho, dtype=dt).reshape(n_dirs, n_rho) / (n_dirs * n_rho)
    Snb = S[jnp.asarray(nb_np)]  # (n_dirs, k, n_rho)
    Snb = jnp.where(jnp.asarray(flip_np)[..., None], Snb[..., ::-1], Snb)
    allnb = jnp.concatenate([Snb, S[:, None, :]], 1)
    pad = jnp.pad(allnb, ((0, 0), (0, 0), (1, 1)), constant_values=-1.0)
    m_shift = jnp.maximum(jnp.maximum(pad[..., :-2], pad[..., 2:]), pad[..., 1:-1])
    m_other = jnp.maximum(jnp.max(m_shift[:, :-1], 1), jnp.maximum(pad[:, -1, :-2], pad[:, -1, 2:]))
    peak = (S > m_other) & (acc >= min_votes)
    n_cand = 4 * capacity
    top, idx = jax.lax.top_k(jnp.where(peak, S, -1.0).reshape(-1), n_cand)
    has = top >= 0
    di, bi = idx // n_rho, idx % n_rho
    n0 = dirs[di]
    d0 = n0 @ c + (-R + (bi.astype(dt) + 0.5) * w)

    def refine(n, d):
        def rnd(carry, t):
            n, d = carry
            dist = xyz @ n - d
            inl = valid & (jnp.abs(dist) < t)
            f = inl.astype(dt)
            m = jnp.sum(f)
            mu = jnp.sum(xyz * f[:, None], 0) / jnp.maximum(m, 1.0)
            Q = (xyz - mu) * f[:, None]
            _, V = jnp.linalg.eigh(Q.T @ Q / jnp.maximum(m, 1.0))
            nn = V[:, 0]
            nn = jnp.where(nn @ n < 0, -nn, nn)
            good = m >= 3
            return (jnp.where(good, nn, n), jnp.where(good, nn @ mu, d)), None

        (n, d), _ = jax.lax.scan(rnd, (n, d), jnp.full(_ROUNDS, w))
        (n, d), t = _fine_rounds(lambda nd: jnp.abs(xyz @ nd[0] - nd[1]), rnd, (n, d), valid, w)
        dist = xyz @ n - d
        a = jnp.abs(dist)
        inl = valid & (a < t)
        n_in = jnp.sum(inl.astype(dt))
        n_out = jnp.sum((valid & (a >= t) & (a < 3 * t)).astype(dt))
        rms = jnp.sqrt(jnp.sum(jnp.where(inl, dist * dist, 0.0)) / jnp.maximum(n_in, 1.0))
        return n, d, inl, n_in, n_out, rms, t

    n, d, inl, n_in, n_out, rms, band = jax.vmap(refine)(n0, d0)
    excess, support, ok = _accept(n_in, n_out, 0.5, min_votes, min_support)
    ok = ok & has & (band < _RESOLVED * w)
    chosen, kv, truncated = _select(top, ok, inl, capacity)
    cols = [n[chosen, 0], n[chosen, 1], n[chosen, 2], d[chosen], jnp.floor(top[chosen]), n_in[chosen],
            rms[chosen], support[chosen]]
    return _table(cols, kv), kv, truncated


@register(family="match3d", takes=Points, gives=RegionProps, differentiable=False,
          refs=[_REF_HOUGH, _REF_DH, _REF_BORRMANN, _REF_GONZALEZ])
def hough_planes3d(points: Points, /, *, max_planes: int = 4, n_dirs: int = 1024, n_rho: int = 64,
                   min_votes: float = 20.0, min_support: float = 0.5) -> RegionProps:
    """Planes of a point cloud by a Hough transform over normals x offsets, refined by least squares.

    Every valid point votes once per sampled normal ``n`` (``n_dirs`` Fibonacci directions on the
    hemisphere ``z > 0``; Gonzalez 2010) for the offset bin of ``rho = n . (p - c)`` (``c`` the
    cloud's centroid; ``n_rho`` bins of width ``tol = 2 R / n_rho`` across ``[-R, R]``, ``R`` the
    largest distance of a point from ``c``). Peaks by non-maximum suppression over neighbouring
    normals and offsets, then each candidate is refitted by total least squares on the points
    within ``tol`` of it and then on a narrowing robust band, accepted when it stands out of the
    clutter around it (``support``; the module docstring gives the tests) and kept unless it
    repeats a plane with more votes.

    Args:
      points: the cloud ``(N, 3)``; invalid slots do not vote.
      max_planes: capacity ``K`` (static int, 1..32); ``4 K`` peaks are refined.
      n_dirs: sampled normals (static int, 64..8192): spacing ``~ sqrt(2 pi / n_dirs)`` rad
        (4.5 deg for 1024). Finer sampling separates close planes; refinement, not the
        sampling, sets the accuracy.
      n_rho: offset bins (static int, 8..1024); the bin width ``tol`` is also the first inlier
        distance. A plane whose noise sigma exceeds about ``0.3 tol`` is refused (fewer bins
        for noisier clouds).
      min_votes: least number of points a plane needs above the clutter expected in its slab
        (and least accumulator votes of a peak).
      min_support: least fraction of a plane's inliers that are not clutter (0..1; default 0.5).

    Returns:
      ``RegionProps`` of ``K`` rows, columns ``nx, ny, nz, d`` (the plane ``n . x = d``, unit
      ``n`` with ``nz >= 0`` up to refinement; ``d`` in the point unit), ``votes`` (accumulator
      peak), ``inliers``, ``rms`` (of the inliers' distances), ``support``. Valid rows first by
      descending votes; others NaN. ``truncated`` when more planes were accepted
      than ``K``.

    Example:
      Two perpendicular planes of 400 points each among 200 uniform clutter points are found,
      normals within 0.1 degree and offsets within 0.002:

      >>> import numpy as np, fsjax
      >>> rng = np.random.default_rng(0)
      >>> u = rng.uniform(-1, 1, (400, 2)); v = rng.uniform(-1, 1, (400, 2))
      >>> floor = np.c_[u, np.full(400, -0.5)]; wall = np.c_[np.full(400, 0.7), v]
      >>> xyz = np.r_[floor, wall, rng.uniform(-1, 1, (200, 3))] + 0.003 * rng.normal(size=(1000, 3))
      >>> res = fsjax.ops.hough_planes3d(fsjax.Points(xyz), max_planes=3)
      >>> int(res.valid.sum())
      2
      >>> nrm = np.asarray(res.table[:2, :3]) * np.sign(np.asarray(res["d"][:2]))[:, None]
      >>> ang = np.degrees(np.arccos(np.clip(np.abs(nrm @ np.eye(3).T), 0, 1))).min(0)
      >>> bool(ang[0] < 0.1 and ang[2] < 0.1)
      True
      >>> sorted(np.round(np.abs(np.asarray(res["d"][:2])), 2).tolist())
      [0.5, 0.7]
    """
    op = "hough_planes3d"
    _check_points(op, points)
    max_planes = check_static_int(op, "max_planes", max_planes, lo=1, hi=32)
    n_dirs = check_static_int(op, "n_dirs", n_dirs, lo=64, hi=8192)
    n_rho = check_static_int(op, "n_rho", n_rho, lo=8, hi=1024)
    check_range(op, "min_votes", min_votes, 0.0, None)
    check_range(op, "min_support", min_support, 0.0, 1.0)
    xyz = points.xyz
    dt = xyz.dtype
    valid = _valid(points)
    xyz = jnp.where(valid[:, None], xyz, 0.0)
    table, kv, trunc = _planes_core(xyz, valid, jnp.asarray(min_votes, dt), jnp.asarray(min_support, dt),
                                    n_dirs=n_dirs, n_rho=n_rho, capacity=max_planes)
    return RegionProps(table, PLANE_COLUMNS, kv, truncated=trunc)


# ---------------------------------------------------------------------------
# spheres
# ---------------------------------------------------------------------------


def _ball(r):
    return (4.0 / 3.0) * jnp.pi * jnp.maximum(r, 0.0) ** 3


def _sphere_fit(xyz, f, c, r):
    """Kasa's algebraic sphere (centred on the weighted mean for conditioning), then Gauss-Newton
    on the geometric distances. ``f`` weights the points (0/1). Returns (centre, radius, ok)."""
    dt = xyz.dtype
    m = jnp.sum(f)
    mu = jnp.sum(xyz * f[:, None], 0) / jnp.maximum(m, 1.0)
    P = xyz - mu
    A = jnp.concatenate([2.0 * P, jnp.ones_like(P[:, :1])], -1) * f[:, None]
    y = jnp.sum(P * P, -1) * f
    M = A.T @ A + 1e-12 * jnp.eye(4, dtype=dt) * jnp.maximum(jnp.trace(A.T @ A), 1.0)
    s = jnp.linalg.solve(M, A.T @ y)
    ck = s[:3]
    rk = jnp.sqrt(jnp.maximum(s[3] + ck @ ck, 0.0))
    ok = (m >= 4) & jnp.all(jnp.isfinite(s)) & (rk > 0)
    c1 = jnp.where(ok, ck + mu, c)
    r1 = jnp.where(ok, rk, r)

    def gn(carry, _):
        c, r = carry
        D = xyz - c
        dist = jnp.linalg.norm(D, axis=-1)
        u = D / jnp.where(dist > 0, dist, 1.0)[:, None]
        e = (dist - r) * f
        J = jnp.concatenate([-u, -jnp.ones_like(dist)[:, None]], -1) * f[:, None]
        H = J.T @ J + 1e-12 * jnp.eye(4, dtype=dt) * jnp.maximum(jnp.trace(J.T @ J), 1.0)
        step = jnp.linalg.solve(H, -(J.T @ e))
        good = jnp.all(jnp.isfinite(step))
        return (jnp.where(good, c + step[:3], c), jnp.where(good, r + step[3], r)), None

    (c2, r2), _ = jax.lax.scan(gn, (c1, r1), None, length=_GN_STEPS)
    return c2, jnp.abs(r2), ok


@functools.partial(jax.jit, static_argnames=("n_radii", "grid", "capacity"))
def _spheres_core(xyz, valid, nrm, r_lo, r_hi, min_votes, min_support, n_radii, grid, capacity):
    dt = xyz.dtype
    G = grid
    voter = valid & jnp.all(jnp.isfinite(nrm), -1) & (jnp.sum(nrm * nrm, -1) > 0.25)  # no normal: no vote
    nrm = jnp.where(voter[:, None], nrm, 0.0)
    lo = jnp.min(jnp.where(valid[:, None], xyz, jnp.inf), 0) - r_hi
    hi = jnp.max(jnp.where(valid[:, None], xyz, -jnp.inf), 0) + r_hi
    cell = jnp.max(hi - lo) / G
    cell = jnp.where(cell > 0, cell, 1.0)
    radii = r_lo + (r_hi - r_lo) * jnp.arange(n_radii, dtype=dt) / max(n_radii - 1, 1)
    dr = (r_hi - r_lo) / max(n_radii - 1, 1)
    tol = jnp.maximum(cell, dr)
    sgn = jnp.asarray([1.0, -1.0], dt)
    cen = xyz[:, None, None, :] + sgn[None, None, :, None] * radii[None, :, None, None] * nrm[:, None, None, :]
    ijk = jnp.floor((cen - lo) / cell).astype(jnp.int32)  # (N, n_radii, 2, 3)
    inside = jnp.all((ijk >= 0) & (ijk < G), -1) & voter[:, None, None]
    ijk = jnp.clip(ijk, 0, G - 1)
    ridx = jnp.broadcast_to(jnp.arange(n_radii, dtype=jnp.int32)[None, :, None], inside.shape)
    flat = ((ridx * G + ijk[..., 0]) * G + ijk[..., 1]) * G + ijk[..., 2]
    acc = jnp.zeros(n_radii * G ** 3, dt).at[flat.reshape(-1)].add(inside.reshape(-1).astype(dt))
    S = (acc + 0.5 * jnp.arange(acc.shape[0], dtype=dt) / acc.shape[0]).reshape(n_radii, G, G, G)
    mx = jax.lax.reduce_window(S, -jnp.inf, jax.lax.max, (3, 3, 3, 3), (1, 1, 1, 1), "SAME")
    peak = (S >= mx) & (acc.reshape(S.shape) >= min_votes)
    n_cand = 4 * capacity
    top, idx = jax.lax.top_k(jnp.where(peak, S, -1.0).reshape(-1), n_cand)
    has = top >= 0
    ri = idx // G ** 3
    rest = idx % G ** 3
    cidx = jnp.stack([rest // (G * G), (rest // G) % G, rest % G], -1)
    c0 = lo + (cidx.astype(dt) + 0.5) * cell
    r0 = radii[ri]

    def refine(c, r):
        def rnd(carry, t):
            c, r = carry
            e = jnp.linalg.norm(xyz - c, axis=-1) - r
            f = (valid & (jnp.abs(e) < t)).astype(dt)
            c, r, _ = _sphere_fit(xyz, f, c, r)
            return (c, r), None

        (c, r), _ = jax.lax.scan(rnd, (c, r), jnp.full(_ROUNDS, tol))
        (c, r), fine_tol = _fine_rounds(lambda cr: jnp.abs(jnp.linalg.norm(xyz - cr[0], axis=-1) - cr[1]), rnd,
                                        (c, r), valid, tol)
        e = jnp.linalg.norm(xyz - c, axis=-1) - r
        a = jnp.abs(e)
        t = fine_tol
        inl = valid & (a < t)
        n_in = jnp.sum(inl.astype(dt))
        n_out = jnp.sum((valid & (a >= t) & (a < 3 * t)).astype(dt))
        core = _ball(r + t) - _ball(r - t)
        outer = _ball(r + 3 * t) - _ball(r + t) + _ball(r - t) - _ball(r - 3 * t)
        ratio = core / jnp.where(outer > 0, outer, 1.0)
        rms = jnp.sqrt(jnp.sum(jnp.where(inl, e * e, 0.0)) / jnp.maximum(n_in, 1.0))
        return c, r, inl, n_in, n_out, ratio, rms, fine_tol

    c, r, inl, n_in, n_out, ratio, rms, band = jax.vmap(refine)(c0, r0)
    excess, support, ok = _accept(n_in, n_out, ratio, min_votes, min_support)
    ok = ok & has & (band < _RESOLVED * tol) & jnp.all(jnp.isfinite(c), -1) & (r >= r_lo - band) & (r <= r_hi + band)
    chosen, kv, truncated = _select(top, ok, inl, capacity)
    cols = [c[chosen, 0], c[chosen, 1], c[chosen, 2], r[chosen], jnp.floor(top[chosen]), n_in[chosen],
            rms[chosen], support[chosen]]
    return _table(cols, kv), kv, truncated


@functools.partial(jax.jit, static_argnames=("k",))
def _normals(xyz, valid, k):
    if xyz.shape[0] <= 4096:
        # one distance matrix and top_k: compiles in 0.2 s CPU where knn's exact brute force takes
        # 4 s and its grid index ~20 s (2,150 points); the neighbourhoods only orient the votes.
        # Distances of centred points, ranked in float32 (XLA's float64 top_k on a CPU is 15x
        # slower: 1.0 s against 0.07 s here); d2's own 7 digits are plenty to pick neighbours
        x = xyz - jnp.sum(jnp.where(valid[:, None], xyz, 0.0), 0) / jnp.maximum(jnp.sum(valid), 1)
        q = jnp.sum(x * x, -1)
        d2 = jnp.where(valid[None, :], q[:, None] + q[None, :] - 2.0 * x @ x.T, jnp.inf)
        top, idx = jax.lax.top_k(-d2.astype(jnp.float32), k)
        idx = jnp.where(jnp.isfinite(top), idx, -1)
    else:
        idx, _ = knn(xyz, xyz, k, ref_valid=valid)
    evals, evecs, _, cnt = pca_frames(xyz, valid, idx)
    ok = valid & (cnt >= 3) & (evals[:, 1] > 1e-6 * jnp.maximum(evals[:, 2], 0.0)) & (evals[:, 2] > 0)
    return jnp.where(ok[:, None], evecs[..., 0], jnp.nan)


@register(family="match3d", takes=Points, gives=RegionProps, differentiable=False,
          refs=[_REF_HOUGH, _REF_OGUNDANA, _REF_KASA])
def hough_spheres3d(points: Points, /, *, r_min: float | None = None, r_max: float | None = None,
                    max_spheres: int = 4, n_radii: int = 16, grid: int = 32, k: int = 16,
                    min_votes: float = 20.0, min_support: float = 0.5) -> RegionProps:
    """Spheres of a point cloud by Hough voting for centres along normals, refined by least squares.

    Each valid point with a normal votes, at each of ``n_radii`` radii ``r`` evenly spaced over
    ``[r_min, r_max]``, for the centres ``p + r n`` and ``p - r n`` in a ``grid^3`` accumulator
    over the cloud's bounding box grown by ``r_max`` (isotropic cells of side ``cell``). The
    normals are ``points.normals`` when the cloud has them, else the PCA normals of the ``k``
    nearest neighbours (Hoppe et al. 1992; their sign does not matter). Peaks by non-maximum
    suppression over radius x centre; each candidate is refitted on the points within
    ``tol = max(cell, radius step)`` of its surface (Kasa's algebraic fit, then Gauss-Newton on
    the geometric distance; then on a narrowing robust band), accepted when it stands out of the
    clutter in the shells around it and its radius lies in ``[r_min, r_max]`` (within the
    band), and kept unless it repeats a sphere with more votes.

    Args:
      points: the cloud ``(N, 3)``; invalid slots do not vote; points without a normal (a zero
        normal in ``points.normals``, a NaN one inside ``jit``, or a degenerate neighbourhood when
        the normals are estimated) do not vote but still count as inliers.
      r_min, r_max: radius range in the point unit (default 2 % and 50 % of the bounding box's
        largest side); ``0 < r_min < r_max``.
      max_spheres: capacity ``K`` (static int, 1..32); ``4 K`` peaks are refined.
      n_radii: radius bins (static int, 2..128).
      grid: centre bins per axis (static int, 8..128); ``tol = max(cell, radius step)`` is the
        first inlier distance, and a sphere noisier than about ``0.3 tol`` is refused.
      k: neighbours for estimated normals (static int, 4..32; unused when the cloud has normals).
      min_votes: least number of points a sphere needs above the clutter expected in its shell
        (and least accumulator votes of a peak).
      min_support: least fraction of a sphere's inliers that are not clutter (0..1; default 0.5).

    Returns:
      ``RegionProps`` of ``K`` rows, columns ``cx, cy, cz, r`` (centre and radius in the point
      unit), ``votes``, ``inliers``, ``rms`` (of the inliers' distances to the sphere),
      ``support``. Valid rows first by descending votes; others NaN. ``truncated``
      when more spheres were accepted than ``K``.

    Example:
      A sphere of radius 0.3 (500 points) on a floor plane with 200 clutter points is found to
      within 0.005 in centre and radius:

      >>> import numpy as np, fsjax
      >>> rng = np.random.default_rng(1)
      >>> u = rng.normal(size=(500, 3)); u /= np.linalg.norm(u, axis=1, keepdims=True)
      >>> ball = np.array([0.2, -0.1, 0.0]) + 0.3 * u
      >>> floor = np.c_[rng.uniform(-1, 1, (400, 2)), np.full(400, -0.3)]
      >>> xyz = np.r_[ball, floor, rng.uniform(-1, 1, (200, 3))] + 0.002 * rng.normal(size=(1100, 3))
      >>> res = fsjax.ops.hough_spheres3d(fsjax.Points(xyz), r_min=0.1, r_max=0.6, max_spheres=2)
      >>> int(res.valid.sum())
      1
      >>> c_err = np.linalg.norm(np.asarray(res.table[0, :3]) - [0.2, -0.1, 0.0])
      >>> bool(c_err < 0.005 and abs(float(res["r"][0]) - 0.3) < 0.005)
      True
    """
    op = "hough_spheres3d"
    _check_points(op, points)
    max_spheres = check_static_int(op, "max_spheres", max_spheres, lo=1, hi=32)
    n_radii = check_static_int(op, "n_radii", n_radii, lo=2, hi=128)
    grid = check_static_int(op, "grid", grid, lo=8, hi=128)
    k = check_static_int(op, "k", k, lo=4, hi=32)
    check_range(op, "min_votes", min_votes, 0.0, None)
    check_range(op, "min_support", min_support, 0.0, 1.0)
    for name, v in (("r_min", r_min), ("r_max", r_max)):
        if v is not None:
            check_range(op, name, v, 0.0, None, lo_open=True)
    if r_min is not None and r_max is not None and is_concrete(r_min) and is_concrete(r_max) \
            and not float(r_min) < float(r_max):
        raise ValueError(f"{op}: argument 'r_max' must be greater than r_min ({r_min}); got {r_max}")
    xyz = points.xyz
    dt = xyz.dtype
    valid = _valid(points)
    xyz = jnp.where(valid[:, None], xyz, 0.0)
    side = jnp.max(jnp.max(jnp.where(valid[:, None], xyz, -jnp.inf), 0)
                   - jnp.min(jnp.where(valid[:, None], xyz, jnp.inf), 0))
    side = jnp.where(jnp.isfinite(side) & (side > 0), side, 1.0)
    r_lo = 0.02 * side if r_min is None else jnp.asarray(r_min, dt)
    r_hi = 0.5 * side if r_max is None else jnp.asarray(r_max, dt)
    nrm = _normals(xyz, valid, k) if points.normals is None else points.normals.astype(dt)
    table, kv, trunc = _spheres_core(xyz, valid, nrm, jnp.asarray(r_lo, dt), jnp.asarray(r_hi, dt),
                                     jnp.asarray(min_votes, dt), jnp.asarray(min_support, dt),
                                     n_radii=n_radii, grid=grid, capacity=max_spheres)
    return RegionProps(table, SPHERE_COLUMNS, kv, truncated=trunc)
