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
* ``point_to_plane`` (Chen & Medioni 1992): residuals ``n_q . (dR p + dt - q)`` linearised about the
  increment ``xi = (w, v)``: ``a_i = (p_i x n_i, n_i)``; the 6 x 6 normal equations and their
  right-hand side come from one reduction, the 7 x 7 moment ``sum_i w_i [a_i, r_i] [a_i, r_i]^T``,
  solved by Cholesky (``inner_steps`` Gauss-Newton steps on the same pairs). Target normals: the
  ``Points.normals`` when given, else PCA normals of the ``normal_k`` nearest target points.
* ``gicp`` (Segal, Haehnel & Thrun 2009, plane-to-plane): residuals ``d_i = dR p_i + dt - q_i``
  weighted by ``W_i = (C_q + R C_p R^T)^-1`` (closed-form symmetric 3 x 3 inverse); covariances
  from the ``cov_k`` nearest neighbours, regularised to eigenvalues ``(eps, 1, 1)`` (``eps = 1e-3``)
  as in the paper; the normal equations ``sum_i A_i^T W_i A_i`` (``A_i = [-[p_i]_x, I, d_i]``) again
  in one reduction.

Scale: both clouds are centred on the target centroid and divided by the target's RMS radius
before anything else, so every test is unit-free and a cloud in metres behaves like the same
cloud in millimetres, in float32 as in float64. The singularity test compares the smallest
eigenvalue of the 6 x 6 normal matrix to ``1e4 eps`` times its largest, in that normalised frame.

The loop is one ``lax.while_loop`` whose turn costs one nearest-neighbour pass plus O(N)
reductions; it stops when the pose increment is below ``rot_tol`` (radians) and ``trans_tol``
(relative to the target's RMS radius), or at ``max_iterations`` (reported). Tolerances below the
dtype's resolution (``64 eps``: 7.6e-6 in float32, 1.4e-14 in float64) are raised to it -- the
increment of a float32 run stalls at rounding noise and would otherwise never "converge".
Exact correspondences can also cycle once aligned (a tiny motion swaps two pair sets; seen in
float32 with period 4 and steps of 0.0013-0.0015 deg): the fit is called converged when, with
exact pairs, the mean squared distance has set no new low (by 1e-6 relative) for 4 turns and
no step in them exceeded 1e-4 rad (0.0057 deg), or no step exceeded 1e-3 rad (0.057 deg) and the
pose has come back, within ``rot_tol`` / ``trans_tol``, to one of the 4 exact-phase poses before it:
a limit cycle that no further turn leaves (float64 GICP on 1,500 bunny points: period 3, steps
0.0065 / 0.0067 / 0.0002 deg, ran all 50 iterations before this rule; the pose returned is one of the
cycle's, within its amplitude of the others). A drift with larger steps still runs out of
iterations. The approximate phase ends when the increment is small or the mean squared
distance stops falling.
Measured float32 accuracy on the bunny (two 20,000-point samples, 10 deg, ``docs/benchmarks_icp.md``):
rotation error 0.00240 deg (point-to-plane) and 0.00185 deg (GICP) in float32 and in float64
(equal to 1e-6 deg); point-to-point 0.0426 deg in float32 (converged, 47 iterations) vs 0.0430 deg
in float64 (50 iterations, the cap).

The record's ``rms_len`` is the RMS point distance of the final (trimmed) correspondences,
``inlier_fraction`` the fraction of valid source points whose nearest target point is within
``inlier_distance`` (default: 3 x the target's median nearest-neighbour spacing). A run whose
increment converged but whose ``inlier_fraction`` is below ``min_inlier_fraction`` reports
``converged=False`` with reason 5: a wrong local minimum is flagged, not hidden.

Failing closed: empty or all-invalid clouds (reason 4), fewer valid points than the model needs (3 for
point-to-point, 6 otherwise; reason 2), non-finite coordinates among the valid points (reason 4),
too few correspondences within the distance gate (reason 2) or singular normal equations / collinear
pairs (reason 3) give NaN pose, NaN ``rms_len`` and ``converged=False``.

Neighbour search: one index of the target, built once per call and reused by every iteration
inside the compiled loop, and by the normals / covariances / spacing pass
(:func:`fsjax.ops.build_index`, a sorted-cell grid with two coarser levels for the far queries of
the first iterations; exact, equal to ``cKDTree``; cells sized for the self-query's k, at least 10). On the grid the loop has two phases: first
the index's approximate mode (:func:`fsjax.ops.query_knn` ``approx=True``: a source point far
from the target may get a target point of the first cell block that holds one, not the nearest),
until the increment is small; then exact nearest neighbours until the increment is small again.
From 16,384 source points the approximate turns search every 4th source point only
(``_SUBSET``; Rusinkiewicz & Levoy 2001, "Efficient variants of the ICP algorithm", 3DIM: sampling),
the exact turns all of them: at 20,000 bunny points the first far search, the costliest turn, shrinks
4x (the whole call 0.60x / 0.77x / 0.91x CPU for point-to-point / point-to-plane / GICP, float32);
the registration is the same within 4.5e-7 (point-to-plane, GICP) / 6.3e-5 (point-to-point, whose
float32 fixed point drifts) in R, with 1-2 more iterations (point-to-point: 42 instead of 43; float64
45 instead of the cap, 50) (``docs/benchmarks_icp.md``). A subset turn with too few pairs for a step
(a distance gate that few source points meet) makes none and hands over to every point.
Point-to-point (tens of near turns) keeps a certified correspondence cache on the grid path
(``_CACHE_K = 4``; at 20,000 points, float32, one process, load 1.5: the call 193.7 -> 152.0 ms,
compile 3.5 -> 4.1 s CPU, outputs bit-identical): each source point's
4 nearest target points at ``p_c``, where it was last searched, and the 4th distance ``d_4``. Every
other target point is at least ``d_4 - |p - p_c|`` from the point's new position ``p``, so when the
nearest cached distance is below that (a 64 ulp margin for rounding; with a distance gate, the gate
below it suffices) the cached nearest is the exact nearest, ties included (every point at that
distance is cached; ties go to the smallest sorted position, the search's own rule). Only the rows
refused are searched (compacted, 4 nearest, exact, refreshing their cache), and a turn whose rows
are all certified searches nothing; the cache serves the exact phase only (serving the approximate
phase too was measured worse with the subset above). Outputs with and
without it are bit-identical (its answers are the exact search's). The returned pose, ``rms_len``
and ``inlier_fraction`` come from exact correspondences; the iteration count includes both phases.
Small problems (``N M <= 2**22``) use the same module's blocked brute force instead (same answers,
cheaper to compile). No (N, M) array is formed anywhere. One search program serves every query of the call: the loop's first turn
searches the target's own ``normal_k`` / ``cov_k`` / 2 nearest points (normals, covariances,
spacing), the other turns the k = 1 correspondences; the number of neighbours and of query rows
are traced (a selection as wide as the first turn's k, a query array ``max(N, M)`` rows long), so
the search is compiled once (it was twice; ICP point-to-plane at 20,000 points compiled in 15.3 s
CPU before, ``docs/benchmarks_icp.md``). GICP's source covariances go through the same search: the
source's index is built beside the target's (one vmapped build of both, padded to ``max(N, M)`` rows)
and a traced index picks the structure searched (``tests/fit/test_icp.py`` counts one search and
one build while tracing). The normals / covariances and the registration modules search with the one
public k-NN, :func:`fsjax.ops.knn` (any dimension, grid or brute force, a reusable index).

Batching: under ``jax.vmap`` a grid-path call (``N M > 2**22``) runs the problems one after the other
(``lax.map``, by a ``custom_vmap`` rule), so each stops at its own iteration count, keeps its branches
(batched lanes would turn every ``lax.cond`` into a select computing both sides) and returns exactly a
single ``jit`` call's answer (nested ``vmap`` s: the same iterations, the pose within float32 rounding,
7.5e-8 on 300 bunny points, as XLA compiles the nested maps apart): 64 problems of 5,000 bunny points took 12.98 s as lanes and 2.80 s one after the
other in one process (``docs/benchmarks_icp.md``). Small problems (the brute-force path, e.g.
:func:`icp_multistart` on a few hundred points) stay batched lanes.
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from .._checks import check_choice, check_range, check_static_int, is_concrete
from .._linalg import _has_tracer, jit_fast_compile
from ..ops import knn
from ..ops.points._cloud import smallest_eigvec3
from ..ops.points._search import (
    _BRUTE_LIMIT,
    GridIndex,
    _batched,
    _brute_batch,
    _brute_queries,
    _brute_refs,
    _query_grid_knn,
    build_index,
)
from ..types import Points
from ..types.results import FitResult, WrappedFit, deprecated_name, renamed
from ._cloud import as_cloud
from .rigid import (
    DEGENERATE,
    INVALID,
    LOW_FITNESS,
    MAX_ITER,
    OK,
    TOO_FEW,
    _weighted_kabsch,
    rotation_angle_deg,
    se3_exp,
)

__all__ = ["ICPResult", "icp", "MultiStartResult", "icp_multistart", "rotation_grid", "local_covariances"]

_METHODS = ("point_to_point", "point_to_plane", "gicp")
# exact-phase cycle test (see _icp_core): turns without a new low of the mean squared distance,
# and the largest rotation step allowed in them (radians; 0.0057 deg); when the pose has come back
# (within rot_tol / trans_tol) to one of the _CYCLE_ITERS poses before it -- a limit cycle that no
# further turn can leave -- steps up to _CYCLE_MAX (radians; 0.057 deg) are allowed
_CYCLE_ITERS = 4
_CYCLE_TOL = 1e-4
_CYCLE_MAX = 1e-3


# ---------------------------------------------------------------------------
# neighbours, normals, covariances
# ---------------------------------------------------------------------------


def _neighbour_cov(xyz, valid, k: int, index=None):
    """Covariance (3, 3) of each point's k nearest valid neighbours (incl. itself) and the count used."""
    valid = valid & jnp.all(jnp.isfinite(xyz), -1)
    x0 = jnp.where(valid[:, None], xyz, 0.0)
    idx, _ = knn(x0, x0, k, ref_valid=valid, index=index)
    cov, cnt = _cov_from_idx(x0, idx)
    return jnp.where(valid[:, None, None], cov, jnp.nan), cnt


def _gicp_cov(cov, eps: float = 1e-3):
    """``U diag(eps, 1, 1) U^T = I - (1 - eps) n n^T`` (``n`` the smallest eigenvector, closed form)."""
    n = smallest_eigvec3(cov)
    return jnp.eye(3, dtype=cov.dtype) - (1 - eps) * n[:, :, None] * n[:, None, :]


def _cov_from_idx(xyz, idx):
    """Covariance of the neighbours ``idx`` (N, k; -1 = none) of each point, and their count."""
    ok = idx >= 0
    nb = xyz[jnp.maximum(idx, 0)]
    w = ok.astype(xyz.dtype)
    cnt = jnp.sum(w, -1)
    cs = jnp.where(cnt > 0, cnt, 1.0)
    mu = jnp.sum(w[..., None] * nb, 1) / cs[:, None]
    dv = (nb - mu[:, None, :]) * w[..., None]
    cov = jnp.einsum("nki,nkj->nij", dv, dv) / cs[:, None, None]
    return cov, cnt


def _estimate_normals(xyz, valid=None, *, k: int = 10, index: GridIndex | None = None):
    """Unit PCA normals: eigenvector of the smallest eigenvalue of the k-neighbour covariance.

    Private (the public path is :func:`fsjax.ops.estimate_normals`); kept for the deprecated
    ``fsjax.fit.estimate_normals``.

    The sign is arbitrary (point-to-plane residuals do not depend on it). Points with fewer than
    3 valid neighbours get NaN normals. ``index``: the cloud's index, reused when given.
    """
    xyz = jnp.asarray(xyz)
    valid = jnp.ones(xyz.shape[0], bool) if valid is None else jnp.asarray(valid, bool)
    cov, cnt = _neighbour_cov(xyz, valid, k, index)
    return jnp.where((cnt >= 3)[:, None], smallest_eigvec3(cov), jnp.nan)


def local_covariances(xyz, valid=None, *, k: int = 20, eps: float = 1e-3, index: GridIndex | None = None):
    """GICP covariances (Segal et al. 2009): ``U diag(eps, 1, 1) U^T`` of each k-neighbour covariance.

    ``U`` holds the eigenvectors of the local covariance, smallest first, so the surface normal
    direction gets the small variance ``eps`` (dimensionless: only ratios matter to GICP).
    """
    xyz = jnp.asarray(xyz)
    valid = jnp.ones(xyz.shape[0], bool) if valid is None else jnp.asarray(valid, bool)
    cov, _ = _neighbour_cov(xyz, valid, k, index)
    return _gicp_cov(cov, eps)


# ---------------------------------------------------------------------------
# records
# ---------------------------------------------------------------------------


class ICPResult(FitResult):
    """Result of :func:`icp` (``target ~ R source + t``).

    Attributes:
        R: ``(3, 3)`` rotation (NaN on bad input or degenerate geometry).
        t: ``(3,)`` translation (same).
        rms_len: RMS distance of the final trimmed correspondences (input length unit; was ``rmse``).
        iterations: outer iterations run.
        converged: the increment fell below tolerance, the fit is valid and the inlier fraction
            reaches ``min_inlier_fraction``.
        inlier_fraction: fraction of valid source points with a target point within
            ``inlier_distance`` at the final pose (the fitness).
        n_correspondences: pairs used in the last iteration.
        reason: int32 code of :data:`fsjax.types.RESULTS`; ``message`` its text.
    """

    R: Float[Array, "*b 3 3"]
    t: Float[Array, "*b 3"]
    rms_len: Float[Array, "*b"]
    iterations: Int[Array, "*b"]
    converged: Bool[Array, "*b"]
    inlier_fraction: Float[Array, "*b"]
    n_correspondences: Int[Array, "*b"]
    reason: Int[Array, "*b"]
    residual_name = "rms_len"

    rmse = renamed("rms_len")


def _as_cloud(x, name: str, fn: str):
    """The fits' one cloud helper (:func:`fsjax.fit._cloud.as_cloud`), argument order of the ICP modules."""
    return as_cloud(fn, name, x)


def _check_distance(fn: str, name: str, v):
    """A distance in ``(0, inf]`` (``inf`` = no gate); traced values pass."""
    if is_concrete(v) and not isinstance(v, (str, bytes)):
        try:
            if float(v) == float("inf"):
                return
        except (TypeError, ValueError):
            pass
    check_range(fn, name, v, 0.0, None, lo_open=True)


# ---------------------------------------------------------------------------
# the solver
# ---------------------------------------------------------------------------


def _skew_rows(x):
    """``[x]_x`` for each row of ``x`` (N, 3) -> (N, 3, 3)."""
    z = jnp.zeros_like(x[:, 0])
    return jnp.stack([jnp.stack([z, -x[:, 2], x[:, 1]], -1), jnp.stack([x[:, 2], z, -x[:, 0]], -1),
                      jnp.stack([-x[:, 1], x[:, 0], z], -1)], -2)


def _sym_inv3(m):
    """Inverse of symmetric 3 x 3 matrices (N, 3, 3) by the adjugate; ``ok`` False where singular."""
    a, b, c = m[:, 0, 0], m[:, 0, 1], m[:, 0, 2]
    d, e, f = m[:, 1, 1], m[:, 1, 2], m[:, 2, 2]
    c00, c01, c02 = d * f - e * e, c * e - b * f, b * e - c * d
    c11, c12, c22 = a * f - c * c, b * c - a * e, a * d - b * b
    det = a * c00 + b * c01 + c * c02
    scale = jnp.maximum(jnp.maximum(jnp.abs(a), jnp.abs(d)), jnp.abs(f))
    ok = jnp.abs(det) > 1e3 * jnp.finfo(m.dtype).eps * scale**3
    dsafe = jnp.where(ok, det, 1.0)
    inv = jnp.stack([jnp.stack([c00, c01, c02], -1), jnp.stack([c01, c11, c12], -1),
                     jnp.stack([c02, c12, c22], -1)], -2) / dsafe[:, None, None]
    return jnp.where(ok[:, None, None], inv, 0.0), ok


def _solve6(m):
    """Gauss-Newton increment from the stacked 7 x 7 moment ``[[H, g], [g^T, .]]``; and a condition flag.

    ``H`` (6 x 6) is tested in the normalised frame (cloud centred and scaled to unit RMS radius,
    so rotation and translation columns have comparable size): singular when its smallest
    eigenvalue is below ``1e4 eps`` of its largest (unit-free).
    """
    h, g = m[:6, :6], m[:6, 6]
    ev = jnp.linalg.eigvalsh(h)
    ok = (ev[0] > 1e4 * jnp.finfo(m.dtype).eps * ev[-1]) & jnp.all(jnp.isfinite(ev))
    hs = jnp.where(ok, h, jnp.eye(6, dtype=m.dtype))
    cf = jax.scipy.linalg.cho_factor(hs)
    return -jax.scipy.linalg.cho_solve(cf, g), ok


def _p2plane_moment(x, q, n, w):
    """One reduction: ``sum_i w_i a_i a_i^T`` with ``a_i = (x_i x n_i, n_i, n_i . (x_i - q_i))``."""
    a = jnp.concatenate([jnp.cross(x, n), n, jnp.sum(n * (x - q), -1, keepdims=True)], -1)
    return jnp.einsum("ni,nj->ij", a * w[:, None], a)


def _gicp_moment(x, q, winv, w):
    """One reduction: ``sum_i w_i A_i^T W_i A_i`` with ``A_i = [-[x_i]_x, I, x_i - q_i]`` (3 x 7)."""
    eye = jnp.broadcast_to(jnp.eye(3, dtype=x.dtype), x.shape[:1] + (3, 3))
    a = jnp.concatenate([-_skew_rows(x), eye, (x - q)[:, :, None]], -1)
    return jnp.einsum("nki,nkl,nlj->ij", a * w[:, None, None], winv, a)


def _gn_steps(moment, x, q, aux, w, inner_steps: int = 1):
    """Increment ``(dR, dt)`` (x -> dR x + dt) by ``inner_steps`` Gauss-Newton steps on fixed pairs.

    ``moment(x, q, aux, w)`` gives the 7 x 7 moment at the current points; the condition flag is
    that of the first step (at the pose the pairs were found for).
    """
    def one(i, st):  # a loop, not unrolled: the solve is compiled once
        dr, dt, ok = st
        xi, oki = _solve6(moment(x @ dr.T + dt, q, aux, w))
        r1, t1 = se3_exp(xi)
        return r1 @ dr, r1 @ dt + t1, jnp.where(i == 0, oki, ok)

    return jax.lax.fori_loop(0, inner_steps, one, (jnp.eye(3, dtype=x.dtype), jnp.zeros(3, x.dtype), jnp.bool_(True)))


def _p2plane_step(x, q, n, w, inner_steps: int = 1):
    """Point-to-plane increment (see :func:`_gn_steps`)."""
    return _gn_steps(_p2plane_moment, x, q, n, w, inner_steps)


def _tolerance_floor(dtype):
    """Smallest increment a run in ``dtype`` can resolve (normalised units): rounding noise of the solve."""
    return 64 * float(jnp.finfo(dtype).eps)


def _progress_line(it, n_ok, rms, step_deg, exact):
    print(f"icp: iteration {int(it)}: {int(n_ok)} pairs, rms {float(rms):.6g}, rotation step "
          f"{float(step_deg):.3g} deg{'' if bool(exact) else ' (approximate neighbours)'}", flush=True)


_WARM_START = True  # the correspondence search starts from the last turn's pairs (a probe knob; same answers)
# certified correspondence cache (grid path, point-to-point): the _CACHE_K nearest target points of
# each source point at the position of its last search; a later turn takes its nearest from them
# when the certificate holds (see _cache_answer) and searches only the other rows (0: off, the plain
# search every turn; a probe knob), in the exact phase only (serving the approximate phase from a
# step of 0.01 rad on made point-to-point take 47 iterations with the subset below and run slower:
# docs/benchmarks_icp.md, "Tried and dropped")
# On (4) for point-to-point: at 20,000 bunny points, float32, with _SUBSET, one process, load 1.5
# (python benchmarks/ab_icp_cache.py --variants 0:0:4,4:0:4 --methods point_to_point): 193.7 -> 152.0 ms
# wall, compile 3.51 -> 4.13 s CPU (+18 %, still under issue 13's 5 s per fit), outputs bit-identical
_CACHE_K = 4
# approximate turns on every _SUBSET-th source point (grid path, from _SUBSET_FROM source points;
# 1: all points; probe knobs)
_SUBSET = 4
_SUBSET_FROM = 16384


def _cache_answer(spts, order, pos, pc, rad, p, gate):
    """Nearest target point of each row from its cached candidates, and whether that is certified exact.

    ``pos`` (N, K): the sorted positions (in the index) of the K nearest target points found for the
    row at ``pc`` (N, 3) (-1: none); ``rad`` (N,): the K-th distance there (the gate when fewer than
    K lay within it; -inf: no cache). Every target point outside the cache is at least ``rad`` from
    ``pc``, so at least ``rad - |p - pc|`` from ``p``: when the nearest cached distance ``d1`` (or the
    gate) is below that, with a relative margin of 64 ulp for rounding, the cached nearest is the exact
    nearest and every target point at its distance is cached. Ties go to the smallest sorted
    position, the search's rule for k = 1. Distances as the search computes them. Returns
    ``(idx (N,), d2 (N,), certified (N,))`` (beyond the gate: -1, inf).
    """
    eps = jnp.finfo(p.dtype).eps
    ok = pos >= 0
    pp = jnp.where(ok, pos, 0)
    dx, dy, dz = (spts[:, i][pp] - p[:, i:i + 1] for i in range(3))
    d2 = jnp.where(ok, (dx * dx + dy * dy) + dz * dz, jnp.inf)
    v = jnp.min(d2, axis=1)
    big = jnp.iinfo(jnp.int32).max
    bp = jnp.min(jnp.where(ok & (d2 == v[:, None]), pos, big), axis=1)
    delta = jnp.sqrt(jnp.sum((p - pc) ** 2, -1))
    m = 64 * eps
    lim = rad * (1 - m) - delta * (1 + m)
    cert = jnp.minimum(jnp.sqrt(v), gate) * (1 + m) < lim
    miss = (v > gate * gate) | (bp == big)
    idx = jnp.where(miss, -1, order[jnp.clip(bp, 0, order.shape[0] - 1)])
    return idx, jnp.where(miss, jnp.inf, v), cert


# At top level (an eager call of icp) the program compiles with FAST_COMPILE (XLA:CPU's older loop
# emitters, optimisation level pinned to 2; see fsjax._linalg): at 20,000 points, float32, one
# process, interleaved (python benchmarks/compile_knn.py --ab), compile CPU 4.7 -> 2.7 s
# (point-to-plane) and 6.3 -> 4.3 s (GICP), run time not worse, results within float32 rounding
# (docs/benchmarks_icp.md). Inside a user's jit / vmap the enclosing program's options apply.
@jit_fast_compile(static_argnames=("method", "max_iterations", "inner_steps", "normal_k", "cov_k",
                                   "has_normals", "verbose"))
def _icp_core(src, sv, tgt, tv, tnormals, r0, t0, max_corr, overlap, inlier_dist, min_inlier, rot_tol, trans_tol,
              *, method, max_iterations, inner_steps, normal_k, cov_k, has_normals, verbose=False):
    dtype = src.dtype
    min_pts = 3 if method == "point_to_point" else 6
    finite = (jnp.all(jnp.where(sv[:, None], jnp.isfinite(src), True))
              & jnp.all(jnp.where(tv[:, None], jnp.isfinite(tgt), True))
              & jnp.all(jnp.isfinite(r0)) & jnp.all(jnp.isfinite(t0)))
    ns, nt = jnp.sum(sv), jnp.sum(tv)
    input_ok = finite & (ns >= min_pts) & (nt >= min_pts)
    input_reason = jnp.where(~finite | (ns == 0) | (nt == 0), INVALID, jnp.where(input_ok, OK, TOO_FEW))
    sv = sv & finite
    tv = tv & finite
    src = jnp.where(sv[:, None], src, 0.0)
    tgt = jnp.where(tv[:, None], tgt, 0.0)
    r0 = jnp.where(finite, r0, jnp.eye(3, dtype=dtype))
    t0 = jnp.where(finite, t0, 0.0)
    # normalise: both clouds centred on the target centroid c and scaled by the target's RMS radius s,
    # so every tolerance and singularity test below is unit-free (metres and millimetres alike)
    ntf = jnp.maximum(nt, 1).astype(dtype)
    c = jnp.sum(tgt, 0) / ntf
    scale = jnp.sqrt(jnp.sum(jnp.where(tv, jnp.sum((tgt - c) ** 2, -1), 0.0)) / ntf)
    scale = jnp.where(scale > 0, scale, 1.0)
    src = jnp.where(sv[:, None], (src - c) / scale, 0.0)
    tgt = jnp.where(tv[:, None], (tgt - c) / scale, 0.0)
    t0 = (r0 @ c + t0 - c) / scale  # target = R source + t in the normalised frame
    max_corr = max_corr / scale
    floor = _tolerance_floor(dtype)
    rot_tol = jnp.maximum(rot_tol, floor)
    trans_tol = jnp.maximum(trans_tol, floor)
    # the one neighbour structure of the target, built once and reused by every query below: the
    # sorted-cell grid (with a coarse level for the far queries of the first iterations), or for
    # small problems the blocked brute force (same exact answers, cheaper to compile and to run).
    # One search program serves every query: the target's own k_self nearest points (spacing,
    # normals, covariances) in the loop's first turn, the k = 1 correspondences in the others.
    # The number of neighbours and of query rows are traced (the selection is k_self wide, the
    # query array max(N, M) rows long), so the search is compiled once.
    n_src, n_tgt = src.shape[0], tgt.shape[0]
    # the target's own neighbours: spacing (column 1), normals or covariances
    k_self = {"point_to_point": 2, "point_to_plane": 2 if has_normals else max(2, normal_k),
              "gicp": max(2, cov_k)}[method]
    need_self = method != "point_to_point" or inlier_dist is None
    brute = n_src * n_tgt <= _BRUTE_LIMIT
    # the certified cache's width: the grid path, point-to-point only (point-to-plane and GICP stop
    # after ~7 iterations, too few turns to pay for the cache's first, ck-wide search; measured)
    ck = _CACHE_K if not brute and method == "point_to_point" else 0
    kmax = max(k_self if need_self else 1, ck)
    # approximate turns on a strided subset of the source (Rusinkiewicz & Levoy 2001: sampling; the
    # exact turns use every point): its rows first in the query array, a static permutation
    # (from 16,384 source points: 64 problems of 5,000 bunny points took 8.4 -> 10.8 iterations on
    # average and no less time, while at 20,000 the far turns' search is most of a call)
    sub = _SUBSET if not brute and n_src >= _SUBSET_FROM else 1
    if sub > 1:
        keep_rows = np.arange(n_src) % sub == 0
        perm_sub = np.concatenate([np.nonzero(keep_rows)[0], np.nonzero(~keep_rows)[0]]).astype(np.int32)
        n_sub = int(keep_rows.sum())
        inv_sub = np.argsort(perm_sub).astype(np.int32)
    n_q = max(n_src, n_tgt) if need_self else n_src
    # GICP also needs the source's own neighbours (its covariances): the source's index (or brute
    # force blocks) is built like the target's, both padded to n_q rows, and the one search program
    # reads the structure picked by a traced ``which`` (0 target, 1 source) -- one compiled search
    two = method == "gicp"

    def pad_to(x, v):
        if x.shape[0] == n_q:
            return x, v
        return jnp.pad(x, ((0, n_q - x.shape[0]), (0, 0))), jnp.pad(v, (0, n_q - v.shape[0]))

    def structures(make):
        if not two:
            return make(tgt, tv)
        # both clouds' structures by one vmapped build: one compiled copy of the build, not two
        (xt, vt), (xs, vs) = pad_to(tgt, tv), pad_to(src, sv)
        return jax.vmap(make)(jnp.stack([xt, xs]), jnp.stack([vt, vs]))

    def pick(tree, which):
        return tree if not two else jax.tree.map(lambda a: a[which], tree)

    if brute:
        refs_all = structures(_brute_refs)
        bsz = _brute_batch(n_q, n_q if two else n_tgt)

        def nearest(x, k_used, n_rows, approx, gate, which=0, warm=None):  # exact always (small problems)
            refs = pick(refs_all, which)
            d2, idx, _ = _batched(lambda q: _brute_queries(refs, q, kmax), (x,), bsz, n_rows)
            miss = (jnp.arange(kmax)[None, :] >= k_used) | (jnp.arange(n_q)[:, None] >= n_rows) | (d2 > gate**2)
            return jnp.where(miss, -1, idx), jnp.where(miss, jnp.inf, d2)
    else:
        # cells sized for the widest query, the self-query's k (at least 10): GICP's k = 20 self-queries
        # on cells sized for 10 took 89 ms each at 20,000 points (most rows past the 27-cell block), 46 ms
        # on cells for 20; the k = 1 turns cost the same (one process, float32: the call 232 -> 192 ms)
        index_all = structures(lambda x, v: build_index(x, v, k=max(10, k_self), coarse=True))
        if ck:  # the target's index: its points in sorted order, and the sorted position of each point
            g_t = pick(index_all, 0)
            inv_order = jnp.zeros(g_t.order.shape, jnp.int32).at[g_t.order].set(
                jnp.arange(g_t.order.shape[0], dtype=jnp.int32))

        def nearest(x, k_used, n_rows, approx, gate, which=0, warm=None):
            # the fallback passes in one looped body: ~18 % less compile, ~8 % more run time at
            # 20,000 points (one process, float32; docs/benchmarks_icp.md). ``warm``: the last turn's
            # pairs, whose distances bound the search (same answers, fewer candidates; see _warm_pass)
            return _query_grid_knn(pick(index_all, which), x, kmax, approx, gate**2, k_used, n_rows, one_group=True,
                                   warm=warm)

    def pad_rows(x):
        return x if x.shape[0] == n_q else jnp.concatenate([x, jnp.zeros((n_q - x.shape[0], 3), x.dtype)])

    if method == "point_to_plane":
        aux0 = jnp.where(jnp.isfinite(tnormals), tnormals, 0.0) if has_normals else jnp.zeros((n_tgt, 3), dtype)
    elif method == "gicp":
        aux0 = jnp.zeros((n_tgt, 3, 3), dtype)
    else:
        aux0 = jnp.zeros((1,), dtype)
    inlier0 = jnp.asarray(0.0, dtype) if inlier_dist is None else inlier_dist / scale

    def from_self(idx_t, d2_t, aux, inl):
        """The target's spacing, normals or covariances from its own neighbours (the first turn)."""
        idx_t, d2_t = idx_t[:n_tgt], d2_t[:n_tgt]
        if inlier_dist is None:  # 3 x the median nearest-neighbour spacing of the target
            inl = 3.0 * jnp.nanmedian(jnp.sqrt(jnp.where(tv, d2_t[:, 1], jnp.nan)))
        if method == "point_to_plane" and not has_normals:
            cov, cnt = _cov_from_idx(tgt, idx_t[:, :normal_k])
            aux = jnp.where((cnt >= 3)[:, None], smallest_eigvec3(cov), 0.0)
            aux = jnp.where(jnp.isfinite(aux), aux, 0.0)
        if method == "gicp":
            aux = _gicp_cov(_cov_from_idx(tgt, idx_t[:, :cov_k])[0])
        return aux, inl

    gate = jnp.where(jnp.isfinite(max_corr), max_corr, jnp.inf)

    def correspond(j, d2):
        # pairs beyond the gate are dropped below: the grid need not search past it (far queries
        # of a partial target fell through to brute force: 20x on a model against a one-sided scan)
        ok = sv & (j >= 0) & (d2 <= max_corr**2)

        def trim(ok):  # keep the ceil(overlap * n_ok) smallest distances
            keep_n = jnp.ceil(overlap * jnp.sum(ok)).astype(jnp.int32)
            ds = jnp.sort(jnp.where(ok, d2, jnp.inf))
            thr = ds[jnp.clip(keep_n - 1, 0, n_src - 1)]
            return ok & (d2 <= thr) & (keep_n > 0)

        ok = jax.lax.cond(overlap < 1, trim, lambda ok: ok, ok)
        return jnp.maximum(j, 0), d2, ok

    def step(r, t, p, j, ok, aux, aux_src):
        w = ok.astype(dtype)
        q = tgt[j]
        n_ok = jnp.sum(ok)
        if method == "point_to_point":
            dr, dt, _, sing, _, _ = _weighted_kabsch(jnp.where(ok[:, None], p, 0.0),
                                                     jnp.where(ok[:, None], q, 0.0), w, False)
            geom_ok = sing[1] > 1e3 * jnp.finfo(dtype).eps * sing[0]
        elif method == "point_to_plane":
            dr, dt, geom_ok = _p2plane_step(p, q, aux[j], w, inner_steps)
        else:
            winv, inv_ok = _sym_inv3(aux[j] + jnp.einsum("ij,njk,lk->nil", r, aux_src, r))
            dr, dt, geom_ok = _gn_steps(_gicp_moment, p, q, winv, w * inv_ok, inner_steps)
        r_new = dr @ r
        t_new = dr @ t + dt
        dang = jnp.radians(rotation_angle_deg(dr))
        dtr = jnp.linalg.norm(t_new - t)  # the moved target centroid (0 here), relative to the RMS radius
        small = (dang <= rot_tol) & (dtr <= trans_tol)
        bad = jnp.where(n_ok < min_pts, TOO_FEW, jnp.where(~geom_ok | ~jnp.all(jnp.isfinite(r_new)), DEGENERATE, OK))
        return r_new, t_new, small, bad, n_ok, dang

    # one nearest-neighbour pass per loop turn: the turn after the last step only evaluates the
    # returned pose (rmse, fitness), so the search is compiled once
    def cond(st):
        return ~st[8]

    # two phases on the grid: approximate correspondences (a far source point may get the nearest
    # target point of the first cell block holding one, see query_knn) until the increment is
    # small or the mean squared distance stops falling, then exact ones until it is small; the returned pose, rms_len and fitness all
    # come from exact correspondences (the evaluation turn is exact). A first turn (``first``)
    # searches the target's own neighbours instead and only sets ``aux`` and the inlier distance.
    def body(st):
        (it, r, t, done, bad, n_ok, d2_prev, ok_prev, stop, exact, best, since, wmax, first, aux, inl, src_self, cs,
         hist, jprev, cache) = st
        stop = ~first & (done | (bad != OK) | (it >= max_iterations))
        p = src @ r.T + t
        # first turns: the source's own neighbours (GICP only), then the target's; then the pairs
        self_x = jnp.where(src_self, pad_rows(src), pad_rows(tgt)) if two else pad_rows(tgt)
        self_n = jnp.where(src_self, n_src, n_tgt) if two else n_tgt
        x_in, k_in, n_in = pad_rows(p), 1, n_src
        if ck:
            # a cache turn (the exact phase): rows whose cached nearest is certified are answered from
            # the cache, the others (compacted to the front) are searched for their ck nearest, exactly,
            # which refresh their cache rows
            cache_turn = ~first & exact
            approx_now = ~exact & ~stop

            def check(_):
                a_idx, a_d2, cert = _cache_answer(g_t.spts, g_t.order, *cache, p, gate)
                unc = ~cert
                n_unc = jnp.sum(unc).astype(jnp.int32)
                rows = jnp.nonzero(unc, size=n_src, fill_value=n_src)[0].astype(jnp.int32)
                return a_idx, a_d2, rows, n_unc

            def no_check(_):
                return (jnp.full((n_src,), -1, jnp.int32), jnp.full((n_src,), jnp.inf, dtype),
                        jnp.full((n_src,), n_src, jnp.int32), jnp.int32(0))

            a_idx, a_d2, rows, n_unc = jax.lax.cond(cache_turn, check, no_check, None)
            rows_c = jnp.minimum(rows, n_src - 1)
            x_in = jnp.where(cache_turn, pad_rows(p[rows_c]), x_in)
            n_in = jnp.where(cache_turn, n_unc, n_src)
            k_in = jnp.where(cache_turn, ck, 1)
            warm_in = jnp.where(cache_turn, -1, jprev)
            approx_in = approx_now & ~cache_turn
        else:
            cache_turn, warm_in, approx_in = jnp.bool_(False), jprev, ~exact & ~stop
        if sub > 1:  # an approximate turn: the strided subset of the source (its rows first), searched alone
            sub_turn = ~first & approx_in
            x_in = jnp.where(sub_turn, pad_rows(p[perm_sub]), x_in)
            n_in = jnp.where(sub_turn, n_sub, n_in)
            warm_in = jnp.where(sub_turn, jnp.concatenate([jprev[perm_sub], jprev[n_src:]]), warm_in)

        def search(_):
            return nearest(jnp.where(first, self_x, x_in), jnp.where(first, k_self, k_in),
                           jnp.where(first, self_n, n_in), ~first & approx_in,
                           jnp.where(first, jnp.inf, gate), (first & src_self).astype(jnp.int32),
                           jnp.where(first, -1, warm_in) if _WARM_START else None)

        if ck:  # every row certified: no search at all
            searching = ~cache_turn | (n_unc > 0)
            idx, d2 = jax.lax.cond(searching, search, lambda _: (jnp.full((n_q, kmax), -1, jnp.int32),
                                                                 jnp.full((n_q, kmax), jnp.inf, dtype)), None)
        else:
            idx, d2 = search(None)
        j_s, d2_s = idx[:n_src, 0], d2[:n_src, 0]
        if sub > 1:  # back in source order; the rows outside the subset: no pair (-1, inf)
            j_s, d2_s = jnp.where(sub_turn, j_s[inv_sub], j_s), jnp.where(sub_turn, d2_s[inv_sub], d2_s)
        if ck:
            live = jnp.arange(n_src) < n_unc
            at = jnp.where(live, rows, n_src)  # the searched rows' places (n_src: dropped)
            cached = cache

            def merge(_):
                """The searched rows' ck nearest into their cache rows; their nearest (the k = 1 tie rule:
                the smallest sorted position among equal distances) into the answers."""
                qi, qd = idx[:n_src, :ck], d2[:n_src, :ck]
                qpos = jnp.where(qi >= 0, inv_order[jnp.maximum(qi, 0)], -1)
                big = jnp.iinfo(jnp.int32).max
                bp = jnp.min(jnp.where((qpos >= 0) & (qd == qd[:, :1]), qpos, big), axis=1)
                j0 = jnp.where(bp == big, -1, g_t.order[jnp.clip(bp, 0, g_t.order.shape[0] - 1)])
                rad = jnp.where(jnp.isfinite(qd[:, -1]), jnp.sqrt(qd[:, -1]), gate)
                c2 = (cached[0].at[at].set(qpos, mode="drop"), cached[1].at[at].set(x_in[:n_src], mode="drop"),
                      cached[2].at[at].set(rad, mode="drop"))
                return (a_idx.at[at].set(j0, mode="drop"), a_d2.at[at].set(qd[:, 0], mode="drop")) + c2

            def searched(_):
                return (j_s, d2_s) + tuple(cached)

            def certified(_):
                return (a_idx, a_d2) + tuple(cached)

            outs = jax.lax.switch(jnp.where(cache_turn, jnp.where(n_unc > 0, 1, 2), 0),
                                  [searched, merge, certified], None)
            j_c, d2_c = outs[:2]
            cache = tuple(outs[2:])
        else:
            j_c, d2_c = j_s, d2_s

        def first_turn(_):
            if two:
                def src_turn(_):  # the covariances of local_covariances(src, sv, k=cov_k)
                    cov, _ = _cov_from_idx(src, idx[:n_src, :cov_k])
                    cs2 = _gicp_cov(jnp.where(sv[:, None, None], cov, jnp.nan))
                    return st[:16] + (jnp.bool_(False), cs2) + st[18:]

                def tgt_turn(_):
                    aux2, inl2 = from_self(idx, d2, aux, inl)
                    return st[:13] + (jnp.bool_(False), aux2, inl2) + st[16:]

                return jax.lax.cond(src_self, src_turn, tgt_turn, None)
            aux2, inl2 = from_self(idx, d2, aux, inl)
            return st[:13] + (jnp.bool_(False), aux2, inl2) + st[16:]

        def turn(_):
            j, d2c, ok = correspond(j_c, d2_c)
            r2, t2, small, bad2, n2, dang = step(r, t, p, j, ok, aux, cs)
            if sub > 1:  # the subset gave too few pairs (or no step): no step; the next turn, every point
                few = sub_turn & (bad2 != OK)
                r2, t2, bad2, small = jnp.where(few, r, r2), jnp.where(few, t, t2), jnp.where(few, OK, bad2), small & ~few
            else:
                few = jnp.bool_(False)
            # the approximate phase also ends when it stops paying: the mean squared distance no
            # longer falls (approximate pairs can cycle by ~1e-3 deg and never make the step small)
            ms = jnp.sum(jnp.where(ok, d2c, 0.0)) / jnp.maximum(jnp.sum(ok), 1)
            ms_prev = jnp.sum(jnp.where(ok_prev, d2_prev, 0.0)) / jnp.maximum(jnp.sum(ok_prev), 1)
            stalled = (it > 0) & (ms >= ms_prev * (1 - 1e-4))
            # exact pairs can cycle too (float32: period 2-4, steps ~2e-5 rad, two pair sets that a
            # tiny motion swaps): converged when, in the exact phase, the mean squared distance has
            # not set a new low (by 1e-6 relative) for CYCLE_ITERS turns and no step in them exceeded
            # _CYCLE_TOL; a drift (larger steps) still runs out of iterations
            better = ms < best * (1 - 1e-6)
            best2 = jnp.where(exact, jnp.minimum(best, ms), jnp.inf)
            since2 = jnp.where(exact & ~better, since + 1, 0)
            wmax2 = jnp.where(exact & ~better, jnp.maximum(wmax, dang), 0.0)
            # a limit cycle (float64 GICP on 1,500 bunny points: period 3, steps 0.0065 / 0.0067 /
            # 0.0002 deg, the pose back to 2e-16 after each period, for ever): the new pose equals one
            # of the last _CYCLE_ITERS exact-phase poses within the convergence tolerances
            hr, ht = hist
            back = jnp.any((jnp.radians(rotation_angle_deg(r2 @ jnp.swapaxes(hr, -1, -2))) <= rot_tol)
                           & (jnp.linalg.norm(t2 - ht, axis=-1) <= trans_tol))
            cycled = (since2 >= _CYCLE_ITERS) & ((wmax2 <= _CYCLE_TOL) | (back & (wmax2 <= _CYCLE_MAX)))
            upd = ~stop & (bad2 == OK)
            keep = exact & upd  # the history holds exact-phase poses only (NaN: none yet)
            hist2 = (jnp.where(keep, jnp.concatenate([hr[1:], r2[None]]), jnp.where(exact, hr, jnp.nan)),
                     jnp.where(keep, jnp.concatenate([ht[1:], t2[None]]), jnp.where(exact, ht, jnp.nan)))
            if verbose:  # static: no cost unless asked; one host line per iteration
                n_pairs = jnp.sum(ok)
                rms = jnp.sqrt(jnp.sum(jnp.where(ok, d2c, 0.0)) / jnp.maximum(n_pairs, 1)) * scale
                jax.lax.cond(stop, lambda: None, lambda: jax.debug.callback(
                    _progress_line, it, n_pairs, rms, rotation_angle_deg(r2 @ r.T), ~(~exact & ~stop)))
            return (jnp.where(stop, it, it + 1), jnp.where(upd, r2, r), jnp.where(upd, t2, t),
                    jnp.where(stop, done, (small | cycled) & exact), jnp.where(stop, bad, bad2.astype(jnp.int32)),
                    jnp.where(stop, n_ok, n2.astype(jnp.int32)), d2c, ok, stop, exact | small | stalled | few,
                    best2, since2, wmax2, first, aux, inl, src_self, cs, hist2,
                    jnp.concatenate([j_c, idx[n_src:, 0]]), cache)

        return jax.lax.cond(first, first_turn, turn, None)

    z = jnp.zeros(n_src, dtype)
    init = (jnp.int32(0), r0, t0, ~input_ok, input_reason.astype(jnp.int32), jnp.int32(0), z, sv, jnp.bool_(False),
            jnp.bool_(brute), jnp.asarray(jnp.inf, dtype), jnp.int32(0), jnp.asarray(0.0, dtype),
            jnp.bool_(need_self), aux0, inlier0, jnp.bool_(two),
            jnp.zeros((n_src, 3, 3) if two else (1,), dtype),
            (jnp.full((_CYCLE_ITERS, 3, 3), jnp.nan, dtype), jnp.full((_CYCLE_ITERS, 3), jnp.nan, dtype)),
            jnp.full((n_q,), -1, jnp.int32),
            (jnp.full((n_src, ck), -1, jnp.int32), jnp.zeros((n_src, 3), dtype), jnp.full((n_src,), -jnp.inf, dtype))
            if ck else ())
    out = jax.lax.while_loop(cond, body, init)
    it, r, t, done, bad, n_ok, d2a, ok = out[:8]
    inlier_dist = out[15]
    n_fin = jnp.sum(ok)
    rmse = jnp.sqrt(jnp.sum(jnp.where(ok, d2a, 0.0)) / jnp.maximum(n_fin, 1)) * scale
    inl = jnp.sum(sv & (d2a <= inlier_dist**2)) / jnp.maximum(ns, 1)
    reason = jnp.where(bad != OK, bad, jnp.where(~done, MAX_ITER, jnp.where(inl < min_inlier, LOW_FITNESS, OK)))
    failed = (reason == INVALID) | (reason == TOO_FEW) | (reason == DEGENERATE)
    nan = jnp.asarray(jnp.nan, dtype)
    t_out = scale * t + c - r @ c
    return ICPResult(
        R=jnp.where(failed, nan, r), t=jnp.where(failed, nan, t_out), rms_len=jnp.where(failed, nan, rmse),
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
    verbose: bool = False,
) -> ICPResult:
    """Register ``source`` to ``target`` by ICP (point-to-point, point-to-plane or GICP; trimmed).

    See the module docstring for the algorithm. Compiles under ``jax.jit`` (``method`` and the
    integer arguments are static) and ``vmap``s over initial poses (:func:`icp_multistart`) and
    clouds; on the grid path a ``vmap`` runs the problems one after the other (module docstring).

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
        rot_tol: convergence: rotation increment in radians (raised to ``64 eps`` of the dtype).
        trans_tol: convergence: increment of the moved centroid, relative to the target's RMS radius
            (raised to ``64 eps`` of the dtype).
        inner_steps: Gauss-Newton steps per outer iteration (point-to-plane, GICP; static).
        normal_k: neighbours for target normals (static).
        cov_k: neighbours for GICP covariances (static).
        verbose: print one progress line per iteration (pairs, rms in cloud units, rotation
            step) from inside the compiled loop (``jax.debug.callback``; static; default off).

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
    check_choice(fn, "method", method, _METHODS)
    for nm, v in (("max_iterations", max_iterations), ("inner_steps", inner_steps), ("normal_k", normal_k),
                  ("cov_k", cov_k)):
        check_static_int(fn, nm, v, lo=1)
    check_range(fn, "overlap", overlap, 0.0, 1.0, lo_open=True)
    _check_distance(fn, "max_correspondence_distance", max_correspondence_distance)
    if min_inlier_fraction is None:
        min_inlier_fraction = 0.9 * overlap
    check_range(fn, "min_inlier_fraction", min_inlier_fraction, 0.0, 1.0)
    if inlier_distance is not None:
        _check_distance(fn, "inlier_distance", inlier_distance)
    src, sv, _ = as_cloud(fn, "source", source)
    tgt, tv, tn = as_cloud(fn, "target", target)
    dtype = jnp.result_type(src.dtype, tgt.dtype)
    src, tgt = src.astype(dtype), tgt.astype(dtype)
    r0 = jnp.eye(3, dtype=dtype) if init_R is None else jnp.asarray(init_R, dtype)
    t0 = jnp.zeros(3, dtype) if init_t is None else jnp.asarray(init_t, dtype)
    has_normals = tn is not None and method == "point_to_plane"
    tnormals = jnp.asarray(tn, dtype) if has_normals else jnp.zeros((1, 3), dtype)
    args = (src, sv, tgt, tv, tnormals, r0, t0, jnp.asarray(max_correspondence_distance, dtype),
            jnp.asarray(overlap, dtype), None if inlier_distance is None else jnp.asarray(inlier_distance, dtype),
            jnp.asarray(min_inlier_fraction, dtype), jnp.asarray(rot_tol, dtype), jnp.asarray(trans_tol, dtype))
    statics = dict(method=method, max_iterations=int(max_iterations), inner_steps=int(inner_steps),
                   normal_k=int(normal_k), cov_k=int(cov_k), has_normals=has_normals, verbose=bool(verbose))
    if not _SEQUENTIAL_VMAP or src.shape[0] * tgt.shape[0] <= _BRUTE_LIMIT or not _has_tracer(args):
        return _icp_core(*args, **statics)  # (an eager call: the FAST_COMPILE program, no vmap to meet)
    return _one_after_the_other(functools.partial(_icp_core, **statics))(*args)


_SEQUENTIAL_VMAP = True  # vmap of a grid-path icp runs the problems by lax.map (a probe knob)


def _one_after_the_other(core):
    """``core`` whose ``vmap`` runs the problems one after the other (``lax.map``), not as lanes.

    Under ``vmap`` a ``while_loop`` runs every lane until the slowest has stopped and every
    ``lax.cond`` inside becomes a select that computes both branches: ICP's first turn (normals)
    on every turn, the search's k = 10 selection beside its k = 1 min, the row compactions of the
    fallback passes whether or not a row needs them. One problem at a time, each stops at its own
    iteration count and keeps its branches (64 problems of 5,000 points: ``docs/benchmarks_icp.md``).
    Only the grid path (``N M > 2**22``) takes this rule; the small brute-force problems of
    :func:`icp_multistart` stay lanes. Each problem's answer is that of a single call.
    """
    f = jax.custom_batching.custom_vmap(core)

    @f.def_vmap
    def _rule(axis_size, in_batched, *args):
        flags = [b is True for b in in_batched]  # None: an absent argument (inlier_distance)

        def one(xs):
            it = iter(xs)
            return f(*(next(it) if b else a for a, b in zip(args, flags, strict=True)))

        out = jax.lax.map(one, [a for a, b in zip(args, flags, strict=True) if b])
        return out, jax.tree.map(lambda _: True, out)

    return f


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
        raise ValueError(f"rotation_grid: argument 'n' must be an int >= 1, got {n!r}")
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


class MultiStartResult(WrappedFit):
    """Result of :func:`icp_multistart`: the best start, its index and every start's record (batched).

    The base fields (``converged``, ``reason``, ``iterations``, ``rms_len``) are those of ``best``.
    """

    best: ICPResult
    index: Int[Array, ""]
    starts: ICPResult
    residual_name = "rms_len"
    inner = "best"

    @property
    def rms_len(self):
        return self.best.rms_len


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
    the smaller ``rms_len``); failed starts (NaN) never win.

    Args:
        source, target: as :func:`icp`.
        rotations: ``(S, 3, 3)`` initial rotations (default :func:`rotation_grid` ``(24)``).
        method: as :func:`icp`.
        **kwargs: the other keyword arguments of :func:`icp`.

    Returns:
        :class:`MultiStartResult`; ``best.converged`` is that start's own flag.
    """
    fn = "icp_multistart"
    check_choice(fn, "method", method, _METHODS)
    src, sv, _ = as_cloud(fn, "source", source)
    tgt, tv, tn = as_cloud(fn, "target", target)
    rots = rotation_grid(24, src.dtype) if rotations is None else jnp.asarray(rotations, src.dtype)
    if rots.ndim != 3 or rots.shape[1:] != (3, 3):
        raise ValueError(f"{fn}: argument 'rotations' must have shape (S, 3, 3), got {tuple(rots.shape)}")
    cs = jnp.sum(jnp.where(sv[:, None], jnp.nan_to_num(src), 0.0), 0) / jnp.maximum(jnp.sum(sv), 1)
    ct = jnp.sum(jnp.where(tv[:, None], jnp.nan_to_num(tgt), 0.0), 0) / jnp.maximum(jnp.sum(tv), 1)
    tcloud = target if isinstance(target, Points) else tgt

    def one(r0):
        return icp(source if isinstance(source, Points) else src, tcloud, method=method, init_R=r0,
                   init_t=ct - r0 @ cs, **kwargs)

    res = jax.vmap(one)(rots)
    score = jnp.where(jnp.isfinite(res.rms_len), res.inlier_fraction - 1e-9 * res.rms_len, -jnp.inf)
    k = jnp.argmax(score)
    best = jax.tree_util.tree_map(lambda a: a[k], res)
    return MultiStartResult(best=best, index=k.astype(jnp.int32), starts=res)


def __getattr__(name):
    if name == "knn":
        deprecated_name("fsjax.fit.knn", "fsjax.ops.knn")
        return knn
    if name == "estimate_normals":
        deprecated_name("fsjax.fit.estimate_normals", "fsjax.ops.estimate_normals (takes Points; pass k)")
        return _estimate_normals
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
