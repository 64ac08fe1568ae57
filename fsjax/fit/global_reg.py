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
  ``vmap`` -- by the number of matches within ``distance`` after the transform. The best is
  refitted on its inliers. Fewer than ``min_inliers`` inliers: reason 6, NaN pose.
  :func:`global_registration` then refits the pose on nearest-neighbour *point* pairs within
  ``distance`` (``refit_rounds``, closed-form Kabsch) and refines it by ICP.
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from .._checks import check_positive, check_static_int
from ..ops import estimate_normals, knn
from ..ops.points._search import _BRUTE_LIMIT, build_index
from ..types import Points
from ..types.results import FitResult, WrappedFit
from ._cloud import as_cloud
from .icp import ICPResult, icp
from .rigid import NO_HYPOTHESIS, OK, TOO_FEW, _weighted_kabsch, kabsch_umeyama

__all__ = ["fpfh", "match_descriptors", "CorrespondenceRansacResult", "ransac_registration", "GlobalResult",
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


@functools.partial(jax.jit, static_argnames=("capacity", "normal_k"))
def _fpfh_core(xyz, valid, normals, radius, *, capacity, normal_k):
    if normals is None:
        normals = estimate_normals(Points(xyz, valid=valid), k=normal_k).normals
        c = jnp.sum(jnp.where(valid[:, None], xyz, 0.0), 0) / jnp.maximum(jnp.sum(valid), 1)
        normals = normals * jnp.where(jnp.sum(normals * (xyz - c), -1) < 0, -1.0, 1.0)[:, None]
    nok = valid & jnp.all(jnp.isfinite(normals), -1)
    normals = jnp.where(nok[:, None], normals, 0.0)
    idx, d2 = knn(xyz, xyz, capacity + 1, ref_valid=nok)  # includes the point itself
    idx, d2 = idx[:, 1:], d2[:, 1:]
    inr = (idx >= 0) & (d2 <= radius**2) & (d2 > 0)
    truncated = inr[:, -1]
    j = jnp.maximum(idx, 0)
    al, ph, th, ok = _pair_features(xyz[:, None, :], normals[:, None, :], xyz[j], normals[j])
    m = (inr & ok).astype(xyz.dtype)
    spfh = jnp.concatenate([_hist(al, -1.0, 1.0, m), _hist(ph, -1.0, 1.0, m), _hist(th, -jnp.pi, jnp.pi, m)], -1)
    wk = m / jnp.sqrt(jnp.where(m > 0, d2, 1.0))
    ws = jnp.sum(wk, -1, keepdims=True)
    wk = wk / jnp.where(ws > 0, ws, 1.0)
    f = 0.5 * spfh + 0.5 * jnp.einsum("nk,nkf->nf", wk, spfh[j])
    good = nok & (jnp.sum(m, -1) >= 3)
    return jnp.where(good[:, None], f, 0.0), good, truncated


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
    fn = "fpfh"
    xyz, valid, normals = as_cloud(fn, "points", points)
    check_positive(fn, "radius", radius)
    capacity = check_static_int(fn, "capacity", capacity, lo=3)
    normal_k = check_static_int(fn, "normal_k", normal_k, lo=3, hi=32)
    nrm = None if normals is None else jnp.asarray(normals, xyz.dtype)
    return _fpfh_core(xyz, valid, nrm, jnp.asarray(radius, xyz.dtype), capacity=capacity, normal_k=int(normal_k))


def match_descriptors(desc_src, desc_tgt, valid_src=None, valid_tgt=None, *, mutual: bool = True):
    """Nearest-descriptor matches source -> target: ``(idx (Ns,) int32, ok (Ns,) bool)``.

    ``mutual=True`` keeps a match only when the source point is also the target point's nearest.
    """
    ds, dt = jnp.asarray(desc_src), jnp.asarray(desc_tgt)
    vs = jnp.ones(ds.shape[0], bool) if valid_src is None else jnp.asarray(valid_src, bool)
    vt = jnp.ones(dt.shape[0], bool) if valid_tgt is None else jnp.asarray(valid_tgt, bool)
    i_st, _ = knn(dt, ds, 1, ref_valid=vt)
    i_st = i_st[:, 0]
    ok = vs & (i_st >= 0)
    if mutual:
        i_ts, _ = knn(ds, dt, 1, ref_valid=vs)
        ok = ok & (i_ts[jnp.maximum(i_st, 0), 0] == jnp.arange(ds.shape[0]))
    return jnp.maximum(i_st, 0).astype(jnp.int32), ok


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
        converged: a hypothesis with at least ``min_inliers`` inliers was found.
        reason: code of :data:`fsjax.types.RESULTS`: ``ok``, ``too_few`` (fewer than 3 matches)
            or ``no_hypothesis``.
    """

    R: Float[Array, "3 3"]
    t: Float[Array, " 3"]
    n_matches: Int[Array, ""]
    n_inliers: Int[Array, ""]
    inlier_fraction: Float[Array, ""]
    n_checked: Int[Array, ""]
    converged: Bool[Array, ""]
    reason: Int[Array, ""]
    rms_len: Float[Array, ""] = None
    iterations: Int[Array, ""] = None
    residual_name = "rms_len"


@functools.partial(jax.jit, static_argnames=("n_hypotheses", "min_inliers"))
def _ransac_core(key, ps, pt, ok, distance, edge_ratio, *, n_hypotheses, min_inliers):
    dtype = ps.dtype
    n_match = jnp.sum(ok)
    logits = jnp.where(ok, 0.0, -jnp.inf)
    logits = jnp.where(n_match > 0, logits, 0.0)
    tri = jax.random.categorical(key, logits, shape=(n_hypotheses, 3))
    distinct = (tri[:, 0] != tri[:, 1]) & (tri[:, 0] != tri[:, 2]) & (tri[:, 1] != tri[:, 2])
    a, b = ps[tri], pt[tri]  # (H, 3, 3)
    ea = jnp.linalg.norm(a - jnp.roll(a, 1, axis=1), axis=-1)
    eb = jnp.linalg.norm(b - jnp.roll(b, 1, axis=1), axis=-1)
    lo, hi = jnp.minimum(ea, eb), jnp.maximum(ea, eb)
    edge_ok = jnp.all(lo >= edge_ratio * hi, -1) & jnp.all(hi > 0, -1)
    checked = distinct & edge_ok & jnp.all(ok[tri], -1)

    def hyp(a3, b3):
        r, t, _, s, _, _ = _weighted_kabsch(a3, b3, jnp.ones(3, dtype), False)
        res = ps @ r.T + t - pt
        inl = ok & (jnp.sum(res * res, -1) <= distance**2)
        return jnp.sum(inl), s[1] > 1e-9 * s[0]

    score, nondeg = jax.vmap(hyp)(a, b)
    score = jnp.where(checked & nondeg, score, -1)
    best = jnp.argmax(score)
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
    reason = jnp.where(n_match < 3, TOO_FEW, jnp.where((score[best] < min_inliers) | (n_in < min_inliers),
                                                       NO_HYPOTHESIS, OK))
    good = reason == OK
    nan = jnp.asarray(jnp.nan, dtype)
    return CorrespondenceRansacResult(R=jnp.where(good, r, nan), t=jnp.where(good, t, nan), n_matches=n_match.astype(jnp.int32),
                        n_inliers=n_in.astype(jnp.int32),
                        inlier_fraction=(n_in / jnp.maximum(n_match, 1)).astype(dtype),
                        n_checked=jnp.sum(checked).astype(jnp.int32), converged=good,
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
                        n_hypotheses=n_hypotheses, min_inliers=int(min_inliers))


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
    **icp_kwargs,
) -> GlobalResult:
    """FPFH descriptors, mutual matching, correspondence RANSAC, then ICP from the RANSAC pose.

    Args:
        key: PRNG key for RANSAC.
        source, target: clouds (``Points`` or ``(N, 3)``).
        radius: FPFH radius (cloud units).
        distance: RANSAC inlier threshold and ICP correspondence gate (2x) (cloud units).
        n_hypotheses: RANSAC hypotheses (static).
        mutual: mutual-nearest descriptor matches only.
        capacity: FPFH neighbour capacity (static).
        refine: ICP method for the refinement (``None``: none; the refined record then repeats the
            coarse pose with ``iterations=0``).
        overlap: trimmed-ICP overlap for the refinement (partial scans: about the shared fraction).
        refit_rounds: after RANSAC on the descriptor matches, this many least-squares refits of the
            coarse pose on *point* pairs (each source point and its nearest target point, pairs
            closer than ``distance / 2``); the matches of independent samples are only
            spacing-accurate, point pairs are many more. ``coarse_matches_R`` keeps the pure
            RANSAC rotation. 0 disables.
        **icp_kwargs: further :func:`fsjax.fit.icp` arguments.

    Returns:
        :class:`GlobalResult`. A failed RANSAC (reason != 0) gives a failed refinement (NaN) too.
    """
    fs, vs, trs = fpfh(source, radius=radius, capacity=capacity)
    ft, vt, trt = fpfh(target, radius=radius, capacity=capacity)
    xs, _, _ = as_cloud("global_registration", "source", source)
    xt, _, _ = as_cloud("global_registration", "target", target)
    idx, ok = match_descriptors(fs, ft, vs, vt, mutual=mutual)
    coarse = ransac_registration(key, xs, xt[idx], ok, distance=distance, n_hypotheses=n_hypotheses)
    r_matches = coarse.R
    if refit_rounds:
        coarse = _point_refit(coarse, xs, xt, jnp.asarray(0.5 * distance, xs.dtype), int(refit_rounds))
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


@functools.partial(jax.jit, static_argnames=("rounds",))
def _point_refit(coarse, xs, xt, distance, rounds):
    r, t = coarse.R, coarse.t
    index = build_index(xt, k=4) if xs.shape[0] * xt.shape[0] > _BRUTE_LIMIT else None  # built once
    for _ in range(rounds):
        p = xs @ r.T + t
        j, d2 = knn(xt, p, 1, index=index)
        fit = kabsch_umeyama(xs, xt[jnp.maximum(j[:, 0], 0)], weights=(d2[:, 0] <= distance**2).astype(xs.dtype))
        r = jnp.where(fit.converged, fit.R, r)
        t = jnp.where(fit.converged, fit.t, t)
    return eqx.tree_at(lambda c: (c.R, c.t), coarse, (r, t))


def _crop_pair(n_points: int, keep: float, seed: int):
    """Two independent bunny samples cropped along x: source keeps the low ``keep`` fraction, target the high."""
    from ..data import surface_points

    a, b = surface_points("bunny", n_points, seed), surface_points("bunny", n_points, seed + 1)
    xs = a[a[:, 0] <= np.quantile(a[:, 0], keep)]
    xt = b[b[:, 0] >= np.quantile(b[:, 0], 1.0 - keep)]
    return xs, xt


def _measure_global(n_points: int = 2600, angle_deg: float = 60.0, overlap: float = 0.7, seed: int = 0,
                    n_hypotheses: int = 16384, radius: float = 0.025, distance: float = 0.01,
                    refine_points: int = 10000) -> dict:
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
                              distance=distance, n_hypotheses=n_hypotheses, refine=None)
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
