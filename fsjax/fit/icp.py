"""Iterative closest point: point-to-point, point-to-plane, trimmed, Generalized-ICP, multi-start.

Conventions are those of :mod:`fsjax.fit.rigid` (pose ``q = R p + t`` maps source to target,
SE(3) tangent ``(w, v)``, reason codes :data:`fsjax.fit.rigid.REGISTRATION_REASONS`). Clouds are
:class:`fsjax.Points` (the ``valid`` mask is honoured; target ``normals`` are used by
point-to-plane when present) or plain ``(N, 3)`` arrays.

One outer iteration: transform the source by the current pose, find each source point's
nearest valid target point (exact k-NN), keep pairs closer than ``max_correspondence_distance``,
then keep the ``overlap`` fraction with the smallest distances (trimmed ICP, Chetverikov et al.
2002; ``overlap=1`` is plain ICP), and solve for a pose increment applied on the left:

* ``point_to_point`` (Besl & McKay 1992): the weighted Umeyama/Kabsch closed form -- the exact
  minimiser of the per-iteration problem, so no iterative solver is used for it.
* ``point_to_plane`` (Chen & Medioni 1992): residuals ``n_q . (exp(xi) p - q)`` minimised over the
  SE(3) tangent ``xi`` by ``optimistix.least_squares`` (Gauss-Newton, ``inner_steps`` steps,
  ``throw=False``), centred on the target centroid for conditioning. Target normals: the
  ``Points.normals`` when given, else PCA normals of the ``normal_k`` nearest target points.
* ``gicp`` (Segal, Haehnel & Thrun 2009, plane-to-plane): residuals ``L_i^T (exp(xi) p_i - q_i)``
  with ``L_i L_i^T = (C_q + R C_p R^T)^-1``; covariances from the ``cov_k`` nearest neighbours,
  regularised to eigenvalues ``(eps, 1, 1)`` (``eps = 1e-3``) as in the paper. Same solver.

The loop is a ``lax.while_loop`` that stops when the increment is below ``rot_tol`` (radians)
and ``trans_tol`` (relative to the target's RMS radius), or at ``max_iterations`` (reported).

The record's ``rmse`` is the RMS point distance of the final (trimmed) correspondences,
``inlier_fraction`` the fraction of valid source points whose nearest target point is within
``inlier_distance`` (default: 3 x the target's median nearest-neighbour spacing). A run whose
increment converged but whose ``inlier_fraction`` is below ``min_inlier_fraction`` reports
``converged=False`` with reason 5: a wrong local minimum is flagged, not hidden.

Failing closed: empty or all-invalid clouds (reason 4), fewer valid points than the model needs (3 for
point-to-point, 6 otherwise; reason 2), non-finite coordinates among the valid points (reason 4),
too few correspondences within the distance gate (reason 2) or singular normal equations / collinear
pairs (reason 3) give NaN pose, NaN rmse and ``converged=False``.

Neighbour search: :func:`knn` here is an exact chunked brute force (memory O(chunk x N), any
dimension, also used for 33-D FPFH descriptors). ``fsjax.ops.knn`` (sorted-cell grid) has the same
signature; swapping it in was measured slower to compile (minutes for the ICP loop) and not faster
to run at these sizes on the shared 2-core machine, so the brute force stays for now.
"""

from __future__ import annotations

import functools
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx
from jaxtyping import Array, Bool, Float, Int

from ..types import Points
from .rigid import (
    DEGENERATE,
    INVALID,
    LOW_FITNESS,
    MAX_ITER,
    OK,
    TOO_FEW,
    _weighted_kabsch,
    reason_message,
    rotation_angle_deg,
    se3_exp,
)

__all__ = ["ICPResult", "icp", "MultiStartResult", "icp_multistart", "rotation_grid", "knn",
           "estimate_normals", "local_covariances"]

_METHODS = ("point_to_point", "point_to_plane", "gicp")


# ---------------------------------------------------------------------------
# neighbours, normals, covariances
# ---------------------------------------------------------------------------


def knn(ref_xyz, query_xyz, k: int, *, ref_valid=None):
    """Exact k nearest neighbours of each query point among the valid reference points.

    Works for any dimension D (used for 3-D points and for 33-D FPFH descriptors). Distances are
    computed as explicit differences for D <= 4 (exact) and by the ``|a|^2 - 2 a.b + |b|^2``
    expansion (clamped at 0) for larger D. Queries are processed in chunks so memory stays
    O(chunk x N).

    Args:
        ref_xyz: ``(N, D)`` reference points.
        query_xyz: ``(M, D)`` query points.
        k: number of neighbours (static int, ``1 <= k``).
        ref_valid: ``(N,)`` mask of usable reference points.

    Returns:
        ``idx`` int32 ``(M, k)`` (ascending distance, -1 when fewer than k valid references) and
        ``dist2`` ``(M, k)`` squared distances (``inf`` where missing).
    """
    ref = jnp.asarray(ref_xyz)
    qry = jnp.asarray(query_xyz)
    n, d = ref.shape
    m = qry.shape[0]
    kk = min(int(k), n)
    rv = jnp.ones(n, bool) if ref_valid is None else jnp.asarray(ref_valid, bool)
    chunk = int(max(1, min(512, 2_000_000 // max(1, n * (d if d <= 4 else 1)))))
    mp = -(-m // chunk) * chunk
    qp = jnp.pad(qry, ((0, mp - m), (0, 0)))
    rn = jnp.sum(ref * ref, -1)

    def one(qc):
        if d <= 4:
            diff = qc[:, None, :] - ref[None, :, :]
            d2 = jnp.sum(diff * diff, -1)
        else:
            d2 = jnp.maximum(jnp.sum(qc * qc, -1)[:, None] - 2.0 * qc @ ref.T + rn[None, :], 0.0)
        d2 = jnp.where(rv[None, :], d2, jnp.inf)
        # k rounds of argmin + mask: several times faster than lax.top_k on CPU for k <= 32
        rows = jnp.arange(d2.shape[0])
        ids, ds = [], []
        for i in range(kk):
            j = jnp.argmin(d2, axis=1)
            ids.append(j)
            ds.append(d2[rows, j])
            if i + 1 < kk:
                d2 = d2.at[rows, j].set(jnp.inf)
        return jnp.stack(ids, 1).astype(jnp.int32), jnp.stack(ds, 1)

    idx, d2 = jax.lax.map(one, qp.reshape(mp // chunk, chunk, d))
    idx = idx.reshape(mp, kk)[:m]
    d2 = d2.reshape(mp, kk)[:m]
    idx = jnp.where(jnp.isfinite(d2), idx, -1)
    if kk < k:
        idx = jnp.pad(idx, ((0, 0), (0, k - kk)), constant_values=-1)
        d2 = jnp.pad(d2, ((0, 0), (0, k - kk)), constant_values=jnp.inf)
    return idx, d2


def _neighbour_cov(xyz, valid, k: int):
    """Covariance (3, 3) of each point's k nearest valid neighbours (incl. itself) and the count used."""
    idx, _ = knn(xyz, xyz, k, ref_valid=valid)
    ok = idx >= 0
    nb = xyz[jnp.maximum(idx, 0)]
    w = ok.astype(xyz.dtype)
    cnt = jnp.sum(w, -1)
    cs = jnp.where(cnt > 0, cnt, 1.0)
    mu = jnp.sum(w[..., None] * nb, 1) / cs[:, None]
    dv = (nb - mu[:, None, :]) * w[..., None]
    cov = jnp.einsum("nki,nkj->nij", dv, dv) / cs[:, None, None]
    return cov, cnt


def estimate_normals(xyz, valid=None, *, k: int = 10):
    """Unit PCA normals: eigenvector of the smallest eigenvalue of the k-neighbour covariance.

    The sign is arbitrary (point-to-plane residuals do not depend on it). Points with fewer than
    3 valid neighbours get NaN normals.
    """
    xyz = jnp.asarray(xyz)
    valid = jnp.ones(xyz.shape[0], bool) if valid is None else jnp.asarray(valid, bool)
    cov, cnt = _neighbour_cov(xyz, valid, k)
    _, vec = jnp.linalg.eigh(cov)
    return jnp.where((cnt >= 3)[:, None], vec[..., 0], jnp.nan)


def local_covariances(xyz, valid=None, *, k: int = 20, eps: float = 1e-3):
    """GICP covariances (Segal et al. 2009): ``U diag(eps, 1, 1) U^T`` of each k-neighbour covariance.

    ``U`` holds the eigenvectors of the local covariance, smallest first, so the surface normal
    direction gets the small variance ``eps`` (dimensionless: only ratios matter to GICP).
    """
    xyz = jnp.asarray(xyz)
    valid = jnp.ones(xyz.shape[0], bool) if valid is None else jnp.asarray(valid, bool)
    cov, _ = _neighbour_cov(xyz, valid, k)
    _, vec = jnp.linalg.eigh(cov)
    lam = jnp.asarray([eps, 1.0, 1.0], xyz.dtype)
    return jnp.einsum("nij,j,nkj->nik", vec, lam, vec)


# ---------------------------------------------------------------------------
# records
# ---------------------------------------------------------------------------


class ICPResult(eqx.Module):
    """Result of :func:`icp` (``target ~ R source + t``).

    Attributes:
        R: ``(3, 3)`` rotation (NaN on bad input or degenerate geometry).
        t: ``(3,)`` translation (same).
        rmse: RMS distance of the final trimmed correspondences.
        iterations: outer iterations run.
        converged: the increment fell below tolerance, the fit is valid and the inlier fraction
            reaches ``min_inlier_fraction``.
        inlier_fraction: fraction of valid source points with a target point within
            ``inlier_distance`` at the final pose (the fitness).
        n_correspondences: pairs used in the last iteration.
        reason: int32 code of :data:`fsjax.fit.rigid.REGISTRATION_REASONS`.
    """

    R: Float[Array, "*b 3 3"]
    t: Float[Array, "*b 3"]
    rmse: Float[Array, "*b"]
    iterations: Int[Array, "*b"]
    converged: Bool[Array, "*b"]
    inlier_fraction: Float[Array, "*b"]
    n_correspondences: Int[Array, "*b"]
    reason: Int[Array, "*b"]

    @property
    def message(self) -> str:
        """Text of ``reason`` (a single, unbatched result)."""
        return reason_message(self.reason)


def _as_cloud(x, name: str, fn: str):
    if isinstance(x, Points):
        xyz, valid, normals = x.xyz, x.valid, x.normals
    else:
        xyz, valid, normals = jnp.asarray(x), None, None
    if xyz.ndim != 2 or xyz.shape[-1] != 3:
        raise ValueError(f"{fn}({name}): expected Points or an (N, 3) array, got shape {xyz.shape}")
    if xyz.shape[0] == 0:
        raise ValueError(f"{fn}({name}): empty cloud (0 points)")
    xyz = xyz.astype(jnp.result_type(xyz.dtype, jnp.float32))
    valid = jnp.ones(xyz.shape[0], bool) if valid is None else jnp.asarray(valid, bool)
    return xyz, valid, normals


def _check_method(method: str, fn: str):
    if method not in _METHODS:
        raise ValueError(f"{fn}(method=...): expected one of {_METHODS}, got {method!r}")


def _check_static_pos_int(v, name: str, fn: str):
    if not isinstance(v, (int, np.integer)) or isinstance(v, bool) or v < 1:
        raise ValueError(f"{fn}({name}=...): expected a static int >= 1, got {v!r}")


def _check_num(v, name: str, fn: str, lo: float, hi: float, lo_open=False):
    try:
        f = float(v)
    except (TypeError, jax.errors.ConcretizationTypeError):
        return
    if not (f > lo if lo_open else f >= lo) or f > hi or math.isnan(f):
        raise ValueError(f"{fn}({name}=...): expected a value in {'(' if lo_open else '['}{lo}, {hi}], got {v!r}")


# ---------------------------------------------------------------------------
# the solver
# ---------------------------------------------------------------------------


def _gn_solve(residual_fn, args, dtype, inner_steps: int):
    solver = optx.GaussNewton(rtol=1e-12 if dtype == jnp.float64 else 1e-6,
                              atol=1e-14 if dtype == jnp.float64 else 1e-8,
                              linear_solver=lx.Normal(lx.Cholesky()))
    sol = optx.least_squares(residual_fn, solver, jnp.zeros(6, dtype), args=args, max_steps=inner_steps,
                             throw=False)
    return sol.value


def _p2plane_res(xi, args):
    p, q, n, sw = args
    dr, dt = se3_exp(xi)
    return sw * jnp.sum(n * (p @ dr.T + dt - q), -1)


def _gicp_res(xi, args):
    p, q, lt, sw = args
    dr, dt = se3_exp(xi)
    d = p @ dr.T + dt - q
    return (sw[:, None] * jnp.einsum("nij,nj->ni", lt, d)).reshape(-1)


def _normal_eq_ok(res_fn, args, dtype):
    """Condition of J^T J (6 x 6) at xi = 0: False when a direction of the increment is not determined."""
    j = jax.jacfwd(res_fn)(jnp.zeros(6, dtype), args)
    ev = jnp.linalg.eigvalsh(j.T @ j)
    return ev[0] > 1e4 * jnp.finfo(dtype).eps * ev[-1]


@functools.partial(jax.jit, static_argnames=("method", "max_iterations", "inner_steps", "normal_k", "cov_k",
                                              "has_normals"))
def _icp_core(src, sv, tgt, tv, tnormals, r0, t0, max_corr, overlap, inlier_dist, min_inlier, rot_tol, trans_tol,
              *, method, max_iterations, inner_steps, normal_k, cov_k, has_normals):
    dtype = src.dtype
    min_pts = 3 if method == "point_to_point" else 6
    finite = (jnp.all(jnp.where(sv[:, None], jnp.isfinite(src), True))
              & jnp.all(jnp.where(tv[:, None], jnp.isfinite(tgt), True))
              & jnp.all(jnp.isfinite(r0)) & jnp.all(jnp.isfinite(t0)))
    ns, nt = jnp.sum(sv), jnp.sum(tv)
    input_ok = finite & (ns >= min_pts) & (nt >= min_pts)
    input_reason = jnp.where(~finite | (ns == 0) | (nt == 0), INVALID, jnp.where(input_ok, OK, TOO_FEW))
    src = jnp.where(sv[:, None] & finite, src, 0.0)
    tgt = jnp.where(tv[:, None] & finite, tgt, 0.0)
    r0 = jnp.where(finite, r0, jnp.eye(3, dtype=dtype))
    t0 = jnp.where(finite, t0, 0.0)
    ntf = jnp.maximum(nt, 1).astype(dtype)
    c = jnp.sum(jnp.where(tv[:, None], tgt, 0.0), 0) / ntf
    scale = jnp.sqrt(jnp.sum(jnp.where(tv, jnp.sum((tgt - c) ** 2, -1), 0.0)) / ntf)
    scale = jnp.where(scale > 0, scale, 1.0)
    # inlier distance default: 3 x the median nearest-neighbour spacing of the target
    if inlier_dist is None:
        _, d2s = knn(tgt, tgt, 2, ref_valid=tv)
        sp = jnp.sqrt(jnp.where(tv, d2s[:, 1], jnp.nan))
        inlier_dist = 3.0 * jnp.nanmedian(sp)
    if method == "point_to_plane":
        tn = tnormals if has_normals else estimate_normals(tgt, tv, k=normal_k)
        tn = jnp.where(jnp.isfinite(tn), tn, 0.0)
    if method == "gicp":
        ct = local_covariances(tgt, tv, k=cov_k)
        cs = local_covariances(src, sv, k=cov_k)
    n_src = src.shape[0]

    def correspond(r, t):
        p = src @ r.T + t
        idx, d2 = knn(tgt, p, 1, ref_valid=tv)
        j, d2 = idx[:, 0], d2[:, 0]
        ok = sv & (j >= 0) & (d2 <= max_corr**2)
        # trimming: keep the ceil(overlap * n_ok) smallest distances
        n_ok = jnp.sum(ok)
        keep_n = jnp.ceil(overlap * n_ok).astype(jnp.int32)
        ds = jnp.sort(jnp.where(ok, d2, jnp.inf))
        thr = ds[jnp.clip(keep_n - 1, 0, n_src - 1)]
        ok = ok & (d2 <= thr) & (keep_n > 0)
        return p, jnp.maximum(j, 0), d2, ok

    def step(r, t):
        p, j, _, ok = correspond(r, t)
        w = ok.astype(dtype)
        q = tgt[j]
        n_ok = jnp.sum(ok)
        if method == "point_to_point":
            dr, dt, _, s, _, _ = _weighted_kabsch(jnp.where(ok[:, None], p, 0.0), jnp.where(ok[:, None], q, 0.0),
                                                  w, False)
            geom_ok = s[1] > 1e3 * jnp.finfo(dtype).eps * s[0]
        else:
            pc, qc = p - c, q - c
            if method == "point_to_plane":
                args = (pc, qc, tn[j], w)
                fn = _p2plane_res
            else:
                m = ct[j] + jnp.einsum("ij,njk,lk->nil", r, cs, r)
                minv = jnp.linalg.inv(m)
                minv = 0.5 * (minv + jnp.swapaxes(minv, -1, -2))
                lt = jnp.swapaxes(jnp.linalg.cholesky(minv), -1, -2)
                lt = jnp.where(ok[:, None, None] & jnp.all(jnp.isfinite(lt), (-1, -2))[:, None, None], lt, 0.0)
                args = (pc, qc, lt, w)
                fn = _gicp_res
            geom_ok = _normal_eq_ok(fn, args, dtype)
            xi = _gn_solve(fn, args, dtype, inner_steps)
            dr, dtc = se3_exp(xi)
            dt = dtc + c - dr @ c  # increment about c, expressed about the origin
        r_new = dr @ r
        t_new = dr @ t + dt
        dang = jnp.radians(rotation_angle_deg(dr))
        dtr = jnp.linalg.norm(r_new @ c + t_new - (r @ c + t)) / scale
        small = (dang <= rot_tol) & (dtr <= trans_tol)
        bad = jnp.where(n_ok < min_pts, TOO_FEW, jnp.where(~geom_ok | ~jnp.all(jnp.isfinite(r_new)), DEGENERATE, OK))
        return r_new, t_new, small, bad, n_ok

    def cond(st):
        it, _, _, done, bad, _ = st
        return (it < max_iterations) & ~done & (bad == OK)

    def body(st):
        it, r, t, _, _, _ = st
        r2, t2, small, bad, n_ok = step(r, t)
        keep = bad == OK
        return (it + 1, jnp.where(keep, r2, r), jnp.where(keep, t2, t), small, bad.astype(jnp.int32),
                n_ok.astype(jnp.int32))

    init = (jnp.int32(0), r0, t0, ~input_ok, input_reason.astype(jnp.int32), jnp.int32(0))
    it, r, t, done, bad, n_ok = jax.lax.while_loop(cond, body, init)
    # final evaluation at the returned pose
    p, j, d2, ok = correspond(r, t)
    n_fin = jnp.sum(ok)
    rmse = jnp.sqrt(jnp.sum(jnp.where(ok, d2, 0.0)) / jnp.maximum(n_fin, 1))
    _, d2a = knn(tgt, p, 1, ref_valid=tv)
    inl = jnp.sum(sv & (d2a[:, 0] <= inlier_dist**2)) / jnp.maximum(ns, 1)
    reason = jnp.where(bad != OK, bad, jnp.where(~done, MAX_ITER, jnp.where(inl < min_inlier, LOW_FITNESS, OK)))
    failed = (reason == INVALID) | (reason == TOO_FEW) | (reason == DEGENERATE)
    nan = jnp.asarray(jnp.nan, dtype)
    return ICPResult(
        R=jnp.where(failed, nan, r), t=jnp.where(failed, nan, t), rmse=jnp.where(failed, nan, rmse),
        iterations=it, converged=reason == OK, inlier_fraction=jnp.where(reason == INVALID, 0.0, inl).astype(dtype),
        n_correspondences=jnp.where(bad != OK, n_ok, n_fin).astype(jnp.int32), reason=reason.astype(jnp.int32),
    )


def icp(
    source: Points | Float[Array, "N 3"],
    target: Points | Float[Array, "M 3"],
    *,
    method: str = "point_to_plane",
    init_R: Float[Array, "3 3"] | None = None,
    init_t: Float[Array, " 3"] | None = None,
    max_correspondence_distance: float = float("inf"),
    overlap: float = 1.0,
    inlier_distance: float | None = None,
    min_inlier_fraction: float | None = None,
    max_iterations: int = 50,
    rot_tol: float = 1e-7,
    trans_tol: float = 1e-7,
    inner_steps: int = 2,
    normal_k: int = 10,
    cov_k: int = 20,
) -> ICPResult:
    """Register ``source`` to ``target`` by ICP (point-to-point, point-to-plane or GICP; trimmed).

    See the module docstring for the algorithm. Compiles under ``jax.jit`` (``method`` and the
    integer arguments are static) and ``vmap``s over initial poses (:func:`icp_multistart`).

    Args:
        source: source cloud (``Points`` or ``(N, 3)``).
        target: target cloud (``Points`` or ``(M, 3)``); ``Points.normals`` used by point-to-plane.
        method: ``"point_to_point"``, ``"point_to_plane"`` (default) or ``"gicp"``.
        init_R: ``(3, 3)`` initial rotation (default identity).
        init_t: ``(3,)`` initial translation (default 0).
        max_correspondence_distance: distance gate for pairs (cloud units; default: no gate).
        overlap: trimmed ICP: fraction of gated pairs kept, the closest ones, in ``(0, 1]``.
        inlier_distance: distance defining ``inlier_fraction`` (default: 3 x the target's median
            nearest-neighbour spacing).
        min_inlier_fraction: below this fitness a converged run reports ``converged=False``
            (reason 5); default ``0.9 * overlap``. 0 disables the check. On the bunny (600
            points, full overlap) every correct alignment had fitness 1.0 and every wrong local
            minimum at most 0.83, from any initial rotation.
        max_iterations: outer iteration cap (static); hitting it is reported (reason 1).
        rot_tol: convergence: rotation increment in radians.
        trans_tol: convergence: increment of the moved centroid, relative to the target's RMS radius.
        inner_steps: Gauss-Newton steps per outer iteration (point-to-plane, GICP; static).
        normal_k: neighbours for target normals (static).
        cov_k: neighbours for GICP covariances (static).

    Returns:
        :class:`ICPResult`.

    Example:
        >>> import jax, jax.numpy as jnp
        >>> from fsjax.fit import icp, rotation_from_axis_angle, rotation_error_deg
        >>> u, v = jnp.meshgrid(jnp.linspace(-1, 1, 20), jnp.linspace(-1, 1, 20))
        >>> tgt = jnp.stack([u.ravel(), v.ravel(), 0.3 * jnp.sin(2 * u.ravel()) * v.ravel() ** 2], -1)
        >>> R = rotation_from_axis_angle(jnp.array([1.0, 1.0, 0.0]), 5.0)
        >>> src = (tgt - jnp.array([0.05, 0.0, 0.02])) @ R   # target = R source + t
        >>> res = icp(src, tgt, method="point_to_plane")
        >>> bool(res.converged), float(rotation_error_deg(res.R, R)) < 1e-6
        (True, True)
    """
    fn = "icp"
    _check_method(method, fn)
    for nm, v in (("max_iterations", max_iterations), ("inner_steps", inner_steps), ("normal_k", normal_k),
                  ("cov_k", cov_k)):
        _check_static_pos_int(v, nm, fn)
    _check_num(overlap, "overlap", fn, 0.0, 1.0, lo_open=True)
    _check_num(max_correspondence_distance, "max_correspondence_distance", fn, 0.0, float("inf"), lo_open=True)
    if min_inlier_fraction is None:
        min_inlier_fraction = 0.9 * overlap
    _check_num(min_inlier_fraction, "min_inlier_fraction", fn, 0.0, 1.0)
    if inlier_distance is not None:
        _check_num(inlier_distance, "inlier_distance", fn, 0.0, float("inf"), lo_open=True)
    src, sv, _ = _as_cloud(source, "source", fn)
    tgt, tv, tn = _as_cloud(target, "target", fn)
    dtype = jnp.result_type(src.dtype, tgt.dtype)
    src, tgt = src.astype(dtype), tgt.astype(dtype)
    r0 = jnp.eye(3, dtype=dtype) if init_R is None else jnp.asarray(init_R, dtype)
    t0 = jnp.zeros(3, dtype) if init_t is None else jnp.asarray(init_t, dtype)
    has_normals = tn is not None and method == "point_to_plane"
    tnormals = jnp.asarray(tn, dtype) if has_normals else jnp.zeros((1, 3), dtype)
    return _icp_core(src, sv, tgt, tv, tnormals, r0, t0, jnp.asarray(max_correspondence_distance, dtype),
                     jnp.asarray(overlap, dtype),
                     None if inlier_distance is None else jnp.asarray(inlier_distance, dtype),
                     jnp.asarray(min_inlier_fraction, dtype), jnp.asarray(rot_tol, dtype),
                     jnp.asarray(trans_tol, dtype), method=method, max_iterations=int(max_iterations),
                     inner_steps=int(inner_steps), normal_k=int(normal_k), cov_k=int(cov_k),
                     has_normals=has_normals)


# ---------------------------------------------------------------------------
# multi-start
# ---------------------------------------------------------------------------


def rotation_grid(n: int = 24, dtype=None) -> Float[Array, "n 3 3"]:
    """Deterministic, well-spread rotations: the 24 rotations of the cube group, then more if asked.

    ``n <= 24`` takes the first ``n`` cube rotations (identity first); every rotation lies within
    62.8 deg of one of the 24. ``n > 24`` appends ``n - 24`` super-Fibonacci-spiral rotations
    (Alexa 2022) for a denser cover.
    """
    if not isinstance(n, (int, np.integer)) or n < 1:
        raise ValueError(f"rotation_grid(n=...): expected an int >= 1, got {n!r}")
    mats = []
    import itertools
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product([1, -1], repeat=3):
            m = np.zeros((3, 3))
            for i, (pj, s) in enumerate(zip(perm, signs, strict=True)):
                m[i, pj] = s
            if np.linalg.det(m) > 0:
                mats.append(m)
    mats.sort(key=lambda m: -np.trace(m))
    mats = np.asarray(mats)
    if n > 24:
        k = n - 24
        phi, psi = math.sqrt(2.0), 1.533751168755204288118041
        i = np.arange(k) + 0.5
        s = i / k
        r, rr = np.sqrt(s), np.sqrt(1 - s)
        a, b = 2 * np.pi * i / phi, 2 * np.pi * i / psi
        q = np.stack([r * np.sin(a), r * np.cos(a), rr * np.sin(b), rr * np.cos(b)], -1)
        w, x, y, z = q.T
        extra = np.stack([
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)], -2)
        mats = np.concatenate([mats, extra], 0)
    return jnp.asarray(mats[:n], dtype=dtype or jnp.result_type(float))


class MultiStartResult(eqx.Module):
    """Result of :func:`icp_multistart`: the best start, its index and every start's record (batched)."""

    best: ICPResult
    index: Int[Array, ""]
    starts: ICPResult


def icp_multistart(
    source: Points | Float[Array, "N 3"],
    target: Points | Float[Array, "M 3"],
    rotations: Float[Array, "S 3 3"] | None = None,
    *,
    method: str = "point_to_plane",
    **kwargs,
) -> MultiStartResult:
    """ICP from a batch of initial rotations in one ``vmap``; the best run chosen by fitness.

    Each start ``R0`` rotates the source about its centroid onto the target centroid
    (``t0 = c_target - R0 c_source``). The best start maximises ``inlier_fraction`` (ties broken by
    the smaller ``rmse``); failed starts (NaN) never win.

    Args:
        source, target: as :func:`icp`.
        rotations: ``(S, 3, 3)`` initial rotations (default :func:`rotation_grid` ``(24)``).
        method: as :func:`icp`.
        **kwargs: the other keyword arguments of :func:`icp`.

    Returns:
        :class:`MultiStartResult`; ``best.converged`` is that start's own flag.
    """
    fn = "icp_multistart"
    _check_method(method, fn)
    src, sv, _ = _as_cloud(source, "source", fn)
    tgt, tv, tn = _as_cloud(target, "target", fn)
    rots = rotation_grid(24, src.dtype) if rotations is None else jnp.asarray(rotations, src.dtype)
    if rots.ndim != 3 or rots.shape[1:] != (3, 3):
        raise ValueError(f"{fn}(rotations=...): expected (S, 3, 3), got {rots.shape}")
    cs = jnp.sum(jnp.where(sv[:, None], jnp.nan_to_num(src), 0.0), 0) / jnp.maximum(jnp.sum(sv), 1)
    ct = jnp.sum(jnp.where(tv[:, None], jnp.nan_to_num(tgt), 0.0), 0) / jnp.maximum(jnp.sum(tv), 1)
    tcloud = target if isinstance(target, Points) else tgt

    def one(r0):
        return icp(source if isinstance(source, Points) else src, tcloud, method=method, init_R=r0,
                   init_t=ct - r0 @ cs, **kwargs)

    res = jax.vmap(one)(rots)
    score = jnp.where(jnp.isfinite(res.rmse), res.inlier_fraction - 1e-9 * res.rmse, -jnp.inf)
    k = jnp.argmax(score)
    best = jax.tree_util.tree_map(lambda a: a[k], res)
    return MultiStartResult(best=best, index=k.astype(jnp.int32), starts=res)


def _bunny_points(n: int, seed: int = 0) -> np.ndarray:
    """``(n, 3)`` area-weighted samples of the bundled Stanford Bunny surface (numpy, deterministic).

    Triangles are drawn with probability proportional to their area, points uniformly inside by
    the square-root barycentric rule. Used by the tests, the tour and the benchmark.
    """
    from ..data import mesh_arrays

    v, f = mesh_arrays("bunny")
    rng = np.random.default_rng(seed)
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    tri = rng.choice(len(f), size=n, p=area / area.sum())
    r1, r2 = rng.random(n), rng.random(n)
    s = np.sqrt(r1)
    return (1 - s)[:, None] * a[tri] + (s * (1 - r2))[:, None] * b[tri] + (s * r2)[:, None] * c[tri]
