"""Two-view geometry: normalised 8-point F and E, essential decomposition, triangulation, RANSAC;
homographies (normalised DLT, RANSAC, decomposition) for planar scenes and rotation-only pairs.

Conventions:

* Image points are ``(u, v) = (column, row)`` pixels, ``(N, 2)``; intrinsics ``K (3, 3)``
  as in :mod:`fsjax.render.camera` (OpenCV frame), optional Brown-Conrady ``dist (5,)``
  undone by :func:`fsjax.render.undistort_normalized` before any geometry.
* Epipolar constraint ``[uv2, 1] F [uv1, 1]^T = 0``; ``E = K2^T F K1``.
* The relative pose is ``camera2_from_camera1``: a point ``X1`` in camera-1 coordinates is
  ``X2 = R X1 + t`` in camera 2 (OpenCV ``recoverPose``). ``t`` is a unit vector (the scale
  is unobservable from two views); triangulated points are in camera-1 coordinates in
  units of the baseline.
* Everything is jit-compiled JAX; RANSAC hypotheses are drawn with a ``key`` and fitted and
  scored in one ``vmap``. Failures are reported in the record (``converged``, a ``reason``
  code of :data:`fsjax.types.RESULTS`) with NaN pose fields, never a plausible pose.

Degeneracy: a camera that only rotates has no parallax; ``E`` is then undefined and any
``t`` "fits". :func:`relative_pose` therefore tests parallax directly: it aligns the two
sets of inlier bearing vectors with ONE rotation (orthogonal Procrustes / Kabsch on unit
vectors) and looks at the residual angle, converted to pixels by the focal length. Below
``min_parallax_px`` (default 1.5 px, i.e. a few times the corner noise) the pair is
reported ``degenerate`` with the rotation from the alignment and ``t = NaN``.

References: Hartley, R. (1997) "In defense of the eight-point algorithm", IEEE TPAMI 19(6);
Hartley, R. and Zisserman, A. (2004) "Multiple View Geometry", 2nd ed., sections 9.6
(essential decomposition), 11.4 (Sampson distance), 12.2 (DLT triangulation); Fischler, M.
and Bolles, R. (1981) "Random sample consensus", CACM 24(6); Torr, P. and Zisserman, A.
(2000) "MLESAC", CVIU 78 (the truncated-quadratic MSAC score).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import optimistix as optx
from jaxtyping import Array, Bool, Float, Int

from .._linalg import jit_fast_compile, levenberg_marquardt
from ..render.camera import undistort_normalized
from ..types.results import FitResult, Legacy, deprecated_name, reason_code
from .calibrate import rodrigues

__all__ = [
    "TwoViewResult",
    "fundamental_8point",
    "essential_8point",
    "decompose_essential",
    "triangulate_dlt",
    "sampson_distance",
    "normalized_points",
    "rotation_parallax",
    "relative_pose",
    "fit_homography",
    "homography_transfer_px",
    "HomographyResult",
    "homography_ransac",
    "decompose_homography",
]

#: the old two-view codes 0..4 (deprecated ``legacy_reason`` and ``TWOVIEW_REASONS``)
_LEGACY = Legacy(("ok", "too_few", "too_few_inliers", "pure_rotation", "cheirality"))


def __getattr__(name):
    if name == "TWOVIEW_REASONS":
        deprecated_name("fsjax.fit.twoview.TWOVIEW_REASONS", "fsjax.types.RESULTS (reason_message)")
        return _LEGACY.table()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def _hartley(p, w):
    ws = jnp.maximum(jnp.sum(w), 1e-300)
    c = jnp.sum(p * w[:, None], 0) / ws
    d = jnp.sum(jnp.linalg.norm(p - c, axis=1) * w) / ws
    s = jnp.sqrt(2.0) / jnp.where(d > 0, d, 1.0)
    T = jnp.array([[s, 0, -s * c[0]], [0, s, -s * c[1]], [0, 0, 1.0]], dtype=p.dtype)
    return (p - c) * s, T


def fundamental_8point(uv1, uv2, weights=None) -> Float[Array, "3 3"]:
    """Normalised 8-point fundamental matrix (rank 2, Frobenius norm 1), optionally weighted.

    Hartley normalisation of each image, the linear system ``A f = 0`` solved by SVD (with
    per-row weights), rank 2 enforced by zeroing the smallest singular value.

    Example:
        >>> from fsjax.fit.twoview import fundamental_8point, sampson_distance
        >>> rng = np.random.default_rng(0)
        >>> X = rng.uniform([-1, -1, 4], [1, 1, 6], (20, 3))
        >>> uv1 = 500 * X[:, :2] / X[:, 2:] + 320
        >>> X2 = X + [0.5, 0.0, 0.1]
        >>> uv2 = 500 * X2[:, :2] / X2[:, 2:] + 320
        >>> F = fundamental_8point(jnp.asarray(uv1), jnp.asarray(uv2))
        >>> float(jnp.max(sampson_distance(F, jnp.asarray(uv1), jnp.asarray(uv2)))) < 1e-8
        True
    """
    uv1 = jnp.asarray(uv1)
    uv2 = jnp.asarray(uv2, uv1.dtype)
    w = jnp.ones(uv1.shape[0], uv1.dtype) if weights is None else jnp.asarray(weights, uv1.dtype)
    p1, T1 = _hartley(uv1, w)
    p2, T2 = _hartley(uv2, w)
    x1, y1 = p1[:, 0], p1[:, 1]
    x2, y2 = p2[:, 0], p2[:, 1]
    one = jnp.ones_like(x1)
    A = jnp.stack([x2 * x1, x2 * y1, x2, y2 * x1, y2 * y1, y2, x1, y1, one], 1) * w[:, None]
    # the null vector of A^T A (9 x 9): fixed size whatever N is
    _, vec = jnp.linalg.eigh(A.T @ A)
    F = vec[:, 0].reshape(3, 3)
    U, S, Vt = jnp.linalg.svd(F)
    F = U @ jnp.diag(S.at[2].set(0.0)) @ Vt
    F = T2.T @ F @ T1
    return F / jnp.linalg.norm(F)


def essential_8point(x1, x2, weights=None) -> Float[Array, "3 3"]:
    """Essential matrix from normalised coordinates ``(N, 2)`` (8-point, projected to singular values (1, 1, 0))."""
    E = fundamental_8point(x1, x2, weights)
    U, _, Vt = jnp.linalg.svd(E)
    E = U @ jnp.diag(jnp.asarray([1.0, 1.0, 0.0], E.dtype)) @ Vt
    return E / jnp.linalg.norm(E)


def decompose_essential(E) -> tuple[Float[Array, "4 3 3"], Float[Array, "4 3"]]:
    """The four ``(R, t)`` candidates of an essential matrix (``t`` unit, proper rotations)."""
    U, _, Vt = jnp.linalg.svd(E)
    U = U * jnp.where(jnp.linalg.det(U) < 0, -1.0, 1.0)
    Vt = Vt * jnp.where(jnp.linalg.det(Vt) < 0, -1.0, 1.0)
    W = jnp.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], E.dtype)
    R1 = U @ W @ Vt
    R2 = U @ W.T @ Vt
    t = U[:, 2]
    return jnp.stack([R1, R1, R2, R2]), jnp.stack([t, -t, t, -t])


def triangulate_dlt(P1, P2, x1, x2) -> Float[Array, "N 3"]:
    """Linear (DLT) triangulation of ``(N, 2)`` correspondences under 3x4 projection matrices.

    Each point solves ``[x P^3 - P^1; y P^3 - P^2]`` (both views) by its smallest singular
    vector; rows are normalised first. Points at infinity give non-finite coordinates.
    """
    def one(a, b):
        A = jnp.stack([a[0] * P1[2] - P1[0], a[1] * P1[2] - P1[1], b[0] * P2[2] - P2[0], b[1] * P2[2] - P2[1]])
        A = A / jnp.linalg.norm(A, axis=1, keepdims=True)
        X = jnp.linalg.svd(A)[2][-1]
        return X[:3] / X[3]

    return jax.vmap(one)(jnp.asarray(x1), jnp.asarray(x2))


def sampson_distance(F, uv1, uv2) -> Float[Array, " N"]:
    """First-order geometric (Sampson) distance of correspondences to ``F``, in the units of the points.

    ``d^2 = (x2^T F x1)^2 / ((F x1)_1^2 + (F x1)_2^2 + (F^T x2)_1^2 + (F^T x2)_2^2)``; returns ``d``.
    """
    uv1 = jnp.asarray(uv1)
    h1 = jnp.concatenate([uv1, jnp.ones_like(uv1[:, :1])], 1)
    h2 = jnp.concatenate([jnp.asarray(uv2, uv1.dtype), jnp.ones_like(uv1[:, :1])], 1)
    Fx1 = h1 @ F.T
    Ftx2 = h2 @ F
    num = jnp.sum(h2 * Fx1, 1)
    den = Fx1[:, 0] ** 2 + Fx1[:, 1] ** 2 + Ftx2[:, 0] ** 2 + Ftx2[:, 1] ** 2
    return jnp.abs(num) / jnp.sqrt(jnp.where(den > 0, den, 1.0))


def normalized_points(uv, K, dist=None) -> Float[Array, "N 2"]:
    """Normalised camera coordinates ``K^-1 [u, v, 1]`` of pixels, undistorted when ``dist`` is given."""
    uv = jnp.asarray(uv)
    K = jnp.asarray(K, uv.dtype)
    y = (uv[:, 1] - K[1, 2]) / K[1, 1]
    x = (uv[:, 0] - K[0, 2] - K[0, 1] * y) / K[0, 0]
    xy = jnp.stack([x, y], 1)
    if dist is not None:
        xy = undistort_normalized(jnp.asarray(dist, uv.dtype), xy).xy
    return xy


def _bearings(xy):
    b = jnp.concatenate([xy, jnp.ones_like(xy[:, :1])], 1)
    return b / jnp.linalg.norm(b, axis=1, keepdims=True)


def rotation_parallax(x1, x2, weights=None):
    """Best single rotation aligning bearing vectors of view 1 to view 2, and the residual angles.

    Solves ``min_R sum w |f2 - R f1|^2`` (Kabsch on unit vectors, proper rotation). With no
    translation the residual is noise only; with parallax it is not.

    Returns:
      ``(R (3, 3), residual_rad (N,))``: the rotation ``camera2_from_camera1`` of the best
      pure-rotation model and each correspondence's residual angle (radians).
    """
    f1, f2 = _bearings(jnp.asarray(x1)), _bearings(jnp.asarray(x2))
    w = jnp.ones(f1.shape[0], f1.dtype) if weights is None else jnp.asarray(weights, f1.dtype)
    H = (f1 * w[:, None]).T @ f2
    U, _, Vt = jnp.linalg.svd(H)
    d = jnp.sign(jnp.linalg.det(Vt.T @ U.T))
    R = Vt.T @ jnp.diag(jnp.asarray([1.0, 1.0, 1.0], f1.dtype).at[2].set(d)) @ U.T
    c = jnp.clip(jnp.sum((f1 @ R.T) * f2, 1), -1.0, 1.0)
    s = jnp.linalg.norm(jnp.cross(f1 @ R.T, f2), axis=1)
    return R, jnp.arctan2(s, c)


class TwoViewResult(FitResult):
    """Result of :func:`relative_pose`.

    Attributes:
        R: ``(3, 3)`` ``camera2_from_camera1`` rotation (from the bearing alignment when
          ``degenerate``; NaN when neither ``converged`` nor a pure rotation).
        t: ``(3,)`` unit translation (NaN unless ``converged``).
        E: ``(3, 3)`` essential matrix of the inliers. F: ``(3, 3)`` fundamental matrix.
        inliers: ``(N,)`` RANSAC inliers (Sampson distance below the threshold).
        n_inliers: their count.
        points: ``(N, 3)`` triangulated inliers in camera-1 coordinates (baseline units;
          NaN for outliers, behind-camera points, or when degenerate).
        parallax_px: median residual (px, via the mean focal length) of the best pure
          rotation aligning the inlier bearings: ~noise for a rotation-only pair.
        sampson_rms_px: RMS Sampson distance of the inliers (px).
        degenerate: no parallax (pure rotation).
        converged: the full pose ``R``, ``t`` is determined (``reason`` is ``ok``).
        reason: int32 code of :data:`fsjax.types.RESULTS`: ``ok``, ``too_few`` (fewer than 8
          correspondences), ``too_few_inliers``, ``pure_rotation`` (``R`` meaningful, ``t`` not),
          ``cheirality``.
        iterations: RANSAC hypotheses drawn (``n_hypotheses``).
        valid: deprecated, ``R`` is meaningful (``reason`` is ``ok`` or ``pure_rotation``).
    """

    R: Float[Array, "3 3"]
    t: Float[Array, "3"]
    E: Float[Array, "3 3"]
    F: Float[Array, "3 3"]
    inliers: Bool[Array, " N"]
    n_inliers: Int[Array, ""]
    points: Float[Array, "N 3"]
    parallax_px: Float[Array, ""]
    sampson_rms_px: Float[Array, ""]
    degenerate: Bool[Array, ""]
    converged: Bool[Array, ""]
    reason: Int[Array, ""]
    iterations: Int[Array, ""]
    residual_name = "sampson_rms_px"

    @property
    def valid(self):
        """Deprecated: ``R`` is meaningful (``reason`` is ``ok`` or ``pure_rotation``)."""
        deprecated_name("TwoViewResult.valid", "TwoViewResult.reason (ok or pure_rotation) / .converged")
        return (self.reason == reason_code("ok")) | (self.reason == reason_code("pure_rotation"))

    legacy_reason = _LEGACY.property()


def _skew(v):
    z = jnp.zeros_like(v[0])
    return jnp.stack([jnp.stack([z, -v[2], v[1]]), jnp.stack([v[2], z, -v[0]]), jnp.stack([-v[1], v[0], z])])


def _pose_from(y, R0):
    t = y[3:]
    tn = jnp.linalg.norm(t)
    return rodrigues(y[:3]) @ R0, t / jnp.where(tn > 0, tn, 1.0)


def _sampson_resid(y, args):
    R0, u1, u2, w, K1, K2 = args
    R, t = _pose_from(y, R0)
    F = _f_from_e(_skew(t) @ R, K1, K2)
    return w * sampson_distance(F, u1, u2)


def _f_from_e(E, K1, K2):
    F = jnp.linalg.inv(K2).T @ E @ jnp.linalg.inv(K1)
    return F / jnp.linalg.norm(F)



def _check_pairs(fn: str, uv1, uv2, n_hypotheses):
    """The matched pixel arrays of a two-view RANSAC, checked: ``(N, 2)`` each, equal shapes, and at
    least one hypothesis."""
    uv1 = jnp.asarray(uv1)
    if uv1.ndim != 2 or uv1.shape[1] != 2:
        raise ValueError(f"{fn}: argument 'uv1' must have shape (N, 2), got {uv1.shape}")
    uv2 = jnp.asarray(uv2, uv1.dtype)
    if uv2.shape != uv1.shape:
        raise ValueError(f"{fn}: argument 'uv2' must have shape {uv1.shape}, got {uv2.shape}")
    if int(n_hypotheses) < 1:
        raise ValueError(f"{fn}: argument 'n_hypotheses' must be >= 1, got {n_hypotheses}")
    return uv1, uv2


def relative_pose(key, uv1, uv2, K1, K2=None, *, dist1=None, dist2=None, threshold_px: float = 1.0,
                  n_hypotheses: int = 256, min_parallax_px: float = 1.5) -> TwoViewResult:
    """Relative pose of two calibrated views by RANSAC over normalised 8-point essential matrices.

    1. Pixels -> normalised coordinates (undistorted if ``dist`` given).
    2. ``n_hypotheses`` random 8-point samples, each fitted (normalised 8-point on the
       normalised coordinates) and scored by the truncated-quadratic MSAC cost of the
       Sampson distance in pixels (``F = K2^-T E K1^-1``), all in one ``vmap``; the best
       hypothesis's inliers (distance < ``threshold_px``) are refitted twice.
       The refit is projected to an essential matrix, decomposed (cheirality, below) and
       ``(R, t)`` refined by ``optimistix.LevenbergMarquardt`` on the inliers' Sampson
       distances (rotation update ``exp(w) R0``, ``t`` normalised); inliers are re-read.
    3. Parallax test (:func:`rotation_parallax`): median residual below ``min_parallax_px``
       -> ``degenerate`` (pure rotation), ``R`` from the alignment, ``t = NaN``.
    4. The essential decomposition whose DLT-triangulated inliers lie in front of both
       cameras most often (cheirality) gives the start ``(R0, t0)`` of the refinement.

    Args:
      key: ``jax.random`` key for the samples.
      uv1, uv2: ``(N, 2)`` corresponding pixels (N >= 8).
      K1, K2: intrinsics (``K2`` defaults to ``K1``). dist1, dist2: optional distortion.
      threshold_px: inlier threshold on the Sampson distance (px).
      n_hypotheses: static number of RANSAC samples.
      min_parallax_px: parallax (px) below which the pair is reported degenerate.

    Returns:
      :class:`TwoViewResult`.

    Example:
        >>> from fsjax.fit.twoview import relative_pose
        >>> from fsjax.fit.calibrate import rodrigues
        >>> rng = np.random.default_rng(0)
        >>> X = rng.uniform([-2, -2, 6], [2, 2, 10], (60, 3))
        >>> R = np.asarray(rodrigues(jnp.asarray([0.0, 0.1, 0.0]))); t = np.array([-1.0, 0.0, 0.0])
        >>> K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
        >>> pr = lambda P: (P[:, :2] / P[:, 2:]) * 500 + [320, 240]
        >>> res = relative_pose(jax.random.PRNGKey(0), pr(X), pr(X @ R.T + t), K)
        >>> bool(res.converged), bool(res.degenerate), float(np.abs(np.asarray(res.t) - t).max()) < 1e-6
        (True, False, True)
    """
    uv1, uv2 = _check_pairs("relative_pose", uv1, uv2, n_hypotheses)
    K1 = jnp.asarray(K1, uv1.dtype)
    K2 = K1 if K2 is None else jnp.asarray(K2, uv1.dtype)
    return _relative_pose(key, uv1, uv2, K1, K2, dist1, dist2, jnp.asarray(threshold_px, uv1.dtype),
                          int(n_hypotheses), jnp.asarray(min_parallax_px, uv1.dtype))


# Compiled with XLA:CPU's older loop emitters at optimisation level 2 when called at top level
# (fsjax._linalg.jit_fast_compile): 500 correspondences, 256 hypotheses, float32, one process,
# interleaved (python benchmarks/bench_fast_compile.py --only relative_pose): compile 5.8-6.2 ->
# 2.9-3.0 s CPU, run time equal within noise, outputs within 6e-5.
@jit_fast_compile(static_argnames=("n_hyp",))
def _relative_pose(key, uv1, uv2, K1, K2, dist1, dist2, thr, n_hyp, min_par):
    n = uv1.shape[0]
    dt = uv1.dtype
    x1 = normalized_points(uv1, K1, dist1)
    x2 = normalized_points(uv2, K2, dist2)
    # pixel-scale Sampson distance through F = K2^-T E K1^-1 on the *undistorted* pixels
    u1 = x1 @ K1[:2, :2].T + K1[:2, 2]
    u2 = x2 @ K2[:2, :2].T + K2[:2, 2]
    finite = jnp.all(jnp.isfinite(x1), 1) & jnp.all(jnp.isfinite(x2), 1)
    x1 = jnp.where(finite[:, None], x1, 0.0)
    x2 = jnp.where(finite[:, None], x2, 0.0)
    u1 = jnp.where(finite[:, None], u1, 0.0)
    u2 = jnp.where(finite[:, None], u2, 0.0)
    keys = jax.random.split(key, n_hyp)
    m = min(8, n)

    def hypothesis(k):
        idx = jax.random.choice(k, n, (m,), replace=False, p=finite / jnp.maximum(jnp.sum(finite), 1))
        # score the unconstrained 8-point F of the sample (projecting a noisy minimal
        # sample onto the essential manifold first makes it much worse)
        Fn = fundamental_8point(x1[idx], x2[idx])
        d = sampson_distance(_f_from_e(Fn, K1, K2), u1, u2)
        cost = jnp.sum(jnp.where(finite, jnp.minimum(d * d, thr * thr), thr * thr))
        return cost, Fn

    costs, Fns = jax.vmap(hypothesis)(keys)
    Fn = Fns[jnp.argmin(costs)]
    for _ in range(2):  # inliers -> weighted refit
        inl = (sampson_distance(_f_from_e(Fn, K1, K2), u1, u2) < thr) & finite
        Fn = fundamental_8point(x1, x2, inl.astype(dt))
    inl = (sampson_distance(_f_from_e(Fn, K1, K2), u1, u2) < thr) & finite
    w = inl.astype(dt)
    n_in = jnp.sum(inl)
    U, _, Vt = jnp.linalg.svd(Fn)
    E0 = U @ jnp.diag(jnp.asarray([1.0, 1.0, 0.0], dt)) @ Vt
    # cheirality over the four decompositions
    Rs, ts = decompose_essential(E0)
    P1 = jnp.concatenate([jnp.eye(3, dtype=dt), jnp.zeros((3, 1), dt)], 1)

    def front(R, t):
        P2 = jnp.concatenate([R, t[:, None]], 1)
        X = triangulate_dlt(P1, P2, x1, x2)
        z2 = X @ R[2] + t[2]
        ok = (X[:, 2] > 0) & (z2 > 0) & jnp.all(jnp.isfinite(X), 1) & inl
        return jnp.sum(ok), X, ok

    counts, _, _ = jax.vmap(front)(Rs, ts)
    b = jnp.argmax(counts)
    R0, t0 = Rs[b], ts[b]
    # gold-standard refinement of (R, t) on the inliers' Sampson distances (optimistix LM)
    sol = optx.least_squares(_sampson_resid, levenberg_marquardt(1e-10, 1e-12),
                             jnp.concatenate([jnp.zeros(3, dt), t0]), (R0, u1, u2, w, K1, K2),
                             max_steps=50, throw=False)
    Rr, tr = _pose_from(sol.value, R0)
    E = _skew(tr) @ Rr
    F = _f_from_e(E, K1, K2)
    d = sampson_distance(F, u1, u2)
    inl = (d < thr) & finite
    w = inl.astype(dt)
    n_in = jnp.sum(inl)
    srms = jnp.sqrt(jnp.sum(w * d * d) / jnp.maximum(n_in, 1))
    # parallax: the best single rotation and its median residual (px)
    Rrot, res = rotation_parallax(x1, x2, w)
    fmean = 0.25 * (K1[0, 0] + K1[1, 1] + K2[0, 0] + K2[1, 1])
    res_in = jnp.where(inl, res, jnp.inf)
    par = jnp.sort(res_in)[jnp.maximum(n_in - 1, 0) // 2] * fmean
    degenerate = par < min_par
    cnt, X, okf = front(Rr, tr)
    counts = cnt[None]
    b = 0
    Xs, oks, Rs, ts = X[None], okf[None], Rr[None], tr[None]
    few = n < 8
    few_in = n_in < 8
    no_front = counts[b] < 0.5 * n_in
    reason = jnp.where(few, 1, jnp.where(few_in, 2, jnp.where(degenerate, 3, jnp.where(no_front, 4, 0))))
    valid = (reason == 0) | (reason == 3)
    R = jnp.where(degenerate, Rrot, Rs[b])
    R = jnp.where(valid, R, jnp.nan)
    t = jnp.where((reason == 0), ts[b], jnp.nan)
    pts = jnp.where((oks[b] & (reason == 0))[:, None], Xs[b], jnp.nan)
    return TwoViewResult(R=R, t=t, E=E, F=F, inliers=inl, n_inliers=n_in, points=pts, parallax_px=par,
                         sampson_rms_px=srms, degenerate=degenerate, converged=reason == 0,
                         reason=_LEGACY.new(reason).astype(jnp.int32), iterations=jnp.asarray(n_hyp, jnp.int32))


# ---------------------------------------------------------------------------
# homography: planar scenes and rotation-only pairs
# ---------------------------------------------------------------------------


def fit_homography(uv1, uv2, weights=None) -> Float[Array, "3 3"]:
    """Homography ``H`` with ``[uv2, 1] ~ H [uv1, 1]`` by the normalised DLT, optionally weighted (JAX).

    Hartley normalisation of each image (weighted centroid and mean distance sqrt 2), two rows
    per correspondence of ``A h = 0`` (Hartley and Zisserman 2004, algorithm 4.2), ``h`` the
    eigenvector of the smallest eigenvalue of the 9 x 9 ``A^T A`` (fixed size whatever ``N``
    is, so it ``vmap``s over samples), denormalised and scaled to Frobenius norm 1. Four points
    in general position determine it; three collinear ones leave it rank-deficient (a large
    transfer error, never a raise). :func:`fsjax.fit.calibrate.homography_dlt` is the eager
    NumPy twin used by calibration.

    Example:
        >>> from fsjax.fit.twoview import fit_homography
        >>> H0 = np.array([[1.1, 0.05, 12.0], [-0.03, 0.95, -7.0], [2e-4, -1e-4, 1.0]])
        >>> uv1 = np.random.default_rng(0).uniform(0, 500, (12, 2))
        >>> p = np.c_[uv1, np.ones(12)] @ H0.T; uv2 = p[:, :2] / p[:, 2:]
        >>> H = np.asarray(fit_homography(jnp.asarray(uv1), jnp.asarray(uv2)))
        >>> bool(np.allclose(H / H[2, 2], H0, atol=1e-9))
        True
    """
    uv1 = jnp.asarray(uv1)
    uv2 = jnp.asarray(uv2, uv1.dtype)
    w = jnp.ones(uv1.shape[0], uv1.dtype) if weights is None else jnp.asarray(weights, uv1.dtype)
    p1, T1 = _hartley(uv1, w)
    p2, T2 = _hartley(uv2, w)
    h1 = jnp.concatenate([p1, jnp.ones_like(p1[:, :1])], 1)
    z = jnp.zeros_like(h1)
    r1 = jnp.concatenate([z, -h1, p2[:, 1:2] * h1], 1)
    r2 = jnp.concatenate([h1, z, -p2[:, 0:1] * h1], 1)
    A = jnp.concatenate([r1 * w[:, None], r2 * w[:, None]], 0)
    _, vec = jnp.linalg.eigh(A.T @ A)
    Hn = vec[:, 0].reshape(3, 3)
    # T2^-1 in closed form (a scale and a shift): no general inverse
    s2 = T2[0, 0]
    T2inv = jnp.array([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]], uv1.dtype) / s2
    T2inv = T2inv.at[0, 2].set(-T2[0, 2] / s2).at[1, 2].set(-T2[1, 2] / s2).at[2, 2].set(1.0)
    H = T2inv @ Hn @ T1
    return H / jnp.linalg.norm(H)


def _adjugate3(H):
    # H^-1 up to scale (a homography is defined up to scale): the adjugate, finite when H is singular
    return jnp.stack([jnp.cross(H[1], H[2]), jnp.cross(H[2], H[0]), jnp.cross(H[0], H[1])], 1)


def _map(H, uv):
    p = uv @ H[:, :2].T + H[:, 2]
    z = p[:, 2:]
    ok = jnp.abs(z[:, 0]) > 1e-12 * jnp.maximum(jnp.linalg.norm(p, axis=1), 1e-300)
    return p[:, :2] / jnp.where(ok[:, None], z, 1.0), ok


def homography_transfer_px(H, uv1, uv2) -> Float[Array, " N"]:
    """Symmetric transfer distance (px) of correspondences to ``H``: ``sqrt((|uv2 - H uv1|^2 +
    |uv1 - H^-1 uv2|^2) / 4)``, the same in either image order; a point mapped to infinity scores
    ``inf``.

    The symmetric transfer error of Hartley and Zisserman (2004, eq. 4.7) divided by four: each
    transfer error carries the noise of both images, so with ``sigma`` px of noise per coordinate
    and image (and ``H`` near a similarity) its square is about ``sigma^2 chi^2_2``, the law of the
    geometric (reprojection) distance of a codimension-2 model; a threshold is then set as in
    H&Z table 4.1 (``t^2 = 5.99 sigma^2`` at 95 %, against ``3.84 sigma^2`` for the Sampson
    distance to ``F``)."""
    uv1 = jnp.asarray(uv1)
    uv2 = jnp.asarray(uv2, uv1.dtype)
    f, okf = _map(H, uv1)
    b, okb = _map(_adjugate3(H), uv2)
    d2 = 0.25 * (jnp.sum((f - uv2) ** 2, 1) + jnp.sum((b - uv1) ** 2, 1))
    return jnp.where(okf & okb, jnp.sqrt(d2), jnp.inf)


class HomographyResult(FitResult):
    """Result of :func:`homography_ransac`.

    Attributes:
        H: ``(3, 3)`` homography ``[uv2, 1] ~ H [uv1, 1]``, Frobenius norm 1 (NaN unless ``converged``).
        inliers: ``(N,)`` symmetric transfer distance below the threshold.
        n_inliers: their count.
        rms_px: RMS symmetric transfer distance of the inliers (px).
        converged: ``reason`` is ``ok``.
        reason: int32 code of :data:`fsjax.types.RESULTS`: ``ok``, ``too_few`` (fewer than 4
          correspondences), ``too_few_inliers`` (fewer than 4 inliers).
        iterations: RANSAC hypotheses drawn (``n_hypotheses``).
    """

    H: Float[Array, "3 3"]
    inliers: Bool[Array, " N"]
    n_inliers: Int[Array, ""]
    rms_px: Float[Array, ""]
    converged: Bool[Array, ""]
    reason: Int[Array, ""]
    iterations: Int[Array, ""]
    residual_name = "rms_px"


def homography_ransac(key, uv1, uv2, *, threshold_px: float = 1.5, n_hypotheses: int = 256) -> HomographyResult:
    """Homography between two views by RANSAC over 4-point normalised DLTs, refined on the inliers.

    1. ``n_hypotheses`` random 4-point samples, each fitted by :func:`fit_homography` and scored
       by the truncated-quadratic MSAC cost of the symmetric transfer distance
       (:func:`homography_transfer_px`), all in one ``vmap``.
    2. Refinement on the inliers: the best hypothesis's inliers (distance < ``threshold_px``)
       refitted twice by the weighted normalised DLT (H&Z algorithm 4.6, step iii), each refit
       kept only when it does not lose inliers (LO-RANSAC's acceptance rule). Not done: a
       Levenberg-Marquardt polish of the transfer residuals (the "gold standard" of H&Z 4.2): tried
       with optimistix, it cost 0.45 s CPU per call against 0.02 s for the rest (512 padded
       correspondences, float32) and changed neither the inliers nor the RMS on a test scene
       (200 / 200, 0.4625 px).

    Non-finite rows (padding) are never sampled nor counted. Used by :mod:`fsjax.sfm` to tell
    general pairs from planar scenes and rotation-only pairs (the inlier count against the
    essential matrix's).

    Args:
      key: ``jax.random`` key. uv1, uv2: ``(N, 2)`` corresponding pixels.
      threshold_px: inlier threshold on the symmetric transfer distance (px).
      n_hypotheses: static number of RANSAC samples.

    Returns:
      :class:`HomographyResult`.

    Example:
        >>> from fsjax.fit.twoview import homography_ransac
        >>> rng = np.random.default_rng(1)
        >>> H0 = np.array([[1.1, 0.05, 12.0], [-0.03, 0.95, -7.0], [2e-4, -1e-4, 1.0]])
        >>> uv1 = rng.uniform(0, 500, (80, 2))
        >>> p = np.c_[uv1, np.ones(80)] @ H0.T; uv2 = p[:, :2] / p[:, 2:]
        >>> uv2[:20] = rng.uniform(0, 500, (20, 2))  # 25 % outliers
        >>> res = homography_ransac(jax.random.PRNGKey(0), uv1, uv2)
        >>> bool(res.converged), int(res.n_inliers), bool(np.asarray(res.inliers)[:20].any())
        (True, 60, False)
    """
    uv1, uv2 = _check_pairs("homography_ransac", uv1, uv2, n_hypotheses)
    if not float(threshold_px) > 0:
        raise ValueError(f"homography_ransac: argument 'threshold_px' must be > 0, got {threshold_px}")
    return _homography_ransac(key, uv1, uv2, jnp.asarray(threshold_px, uv1.dtype), int(n_hypotheses))


@jit_fast_compile(static_argnames=("n_hyp",))
def _homography_ransac(key, uv1, uv2, thr, n_hyp):
    n = uv1.shape[0]
    dt = uv1.dtype
    finite = jnp.all(jnp.isfinite(uv1), 1) & jnp.all(jnp.isfinite(uv2), 1)
    u1 = jnp.where(finite[:, None], uv1, 0.0)
    u2 = jnp.where(finite[:, None], uv2, 0.0)
    keys = jax.random.split(key, n_hyp)
    m = min(4, n)

    def dist(H):
        return jnp.where(finite, homography_transfer_px(H, u1, u2), jnp.inf)

    def hypothesis(k):
        idx = jax.random.choice(k, n, (m,), replace=False, p=finite / jnp.maximum(jnp.sum(finite), 1))
        H = fit_homography(u1[idx], u2[idx])
        d = dist(H)
        return jnp.sum(jnp.minimum(d * d, thr * thr)), H

    costs, Hs = jax.vmap(hypothesis)(keys)
    H = Hs[jnp.argmin(costs)]
    best = jnp.sum(dist(H) < thr)
    for _ in range(2):  # inliers -> weighted refit, kept when it loses no inliers
        inl = dist(H) < thr
        Hr = fit_homography(u1, u2, inl.astype(dt))
        nr = jnp.sum(dist(Hr) < thr)
        H = jnp.where(nr >= best, Hr, H)
        best = jnp.maximum(nr, best)
    d = dist(H)
    inl = d < thr
    n_in = jnp.sum(inl)
    rms = jnp.sqrt(jnp.sum(jnp.where(inl, d * d, 0.0)) / jnp.maximum(n_in, 1))
    reason = jnp.where(jnp.sum(finite) < 4, reason_code("too_few"),
                       jnp.where(n_in < 4, reason_code("too_few_inliers"), reason_code("ok"))).astype(jnp.int32)
    ok = reason == reason_code("ok")
    return HomographyResult(H=jnp.where(ok, H, jnp.nan), inliers=inl & ok, n_inliers=jnp.where(ok, n_in, 0),
                            rms_px=rms, converged=ok, reason=reason,
                            iterations=jnp.asarray(n_hyp, jnp.int32))


def decompose_homography(H, K1, K2=None) -> tuple[Float[Array, "4 3 3"], Float[Array, "4 3"], Float[Array, "4 3"]]:
    """The four ``(R, t, n)`` of a plane-induced homography: ``K2^-1 H K1 ~ R + t n^T``.

    ``R``, ``t`` are ``camera2_from_camera1`` (``X2 = R X1 + t``), ``n`` the plane's unit normal in
    camera 1 with the plane ``n . X1 = d``, and ``t`` in units of ``d`` (the plane's distance).
    Method of Ma, Soatto, Kosecka and Sastry ("An Invitation to 3-D Vision", 2004, section 5.3.3):
    the calibrated homography scaled to middle singular value 1, the eigenvectors of ``H^T H``
    give two rotations and normals, each with ``(n, t)`` or ``(-n, -t)``. Solutions 0, 1 have
    ``n_z > 0`` (the plane faces camera 1, the "positive depth" choice), 2, 3 their mirrors.
    Two views of a plane leave two physical solutions in general (Longuet-Higgins 1986, "The
    reconstruction of a plane surface from two perspective projections", Proc. R. Soc. B 227):
    which one is true needs a third view or prior knowledge. ``H`` is taken up to scale and
    sign: the sign making ``det(K2^-1 H K1) > 0`` is used (``det(R + t n^T) = 1 - n . C2 / d``,
    positive when both cameras see the plane from the same side). A pure rotation (all singular
    values equal) gives NaN normals.

    Example:
        >>> from fsjax.fit.twoview import decompose_homography
        >>> from fsjax.fit.calibrate import rodrigues
        >>> K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
        >>> R = np.asarray(rodrigues(jnp.asarray([0.05, -0.1, 0.02]))); t = np.array([0.3, 0.05, -0.1])
        >>> n = np.array([0.0, 0.6, 0.8])  # the plane n . X1 = 1
        >>> H = -2.0 * K @ (R + np.outer(t, n)) @ np.linalg.inv(K)  # any scale and sign
        >>> Rs, ts, ns = decompose_homography(H, K)
        >>> [bool(np.allclose(Rs[i], R, atol=1e-9) and np.allclose(ts[i], t) and np.allclose(ns[i], n)) for i in range(4)]
        [True, False, False, False]
    """
    K1 = jnp.asarray(K1)
    K2 = K1 if K2 is None else jnp.asarray(K2, K1.dtype)
    Hc = jnp.linalg.inv(K2) @ jnp.asarray(H, K1.dtype) @ K1
    Hc = Hc / (jnp.linalg.svd(Hc, compute_uv=False)[1] * jnp.sign(jnp.linalg.det(Hc)))
    evals, V = jnp.linalg.eigh(Hc.T @ Hc)  # ascending: sigma3^2, 1, sigma1^2
    s3, s1 = evals[0], evals[2]
    v1, v2, v3 = V[:, 2], V[:, 1], V[:, 0]
    den = jnp.sqrt(s1 - s3)
    a = jnp.sqrt(jnp.maximum(1.0 - s3, 0.0))
    b = jnp.sqrt(jnp.maximum(s1 - 1.0, 0.0))
    Rs, ts, ns = [], [], []
    for u in ((a * v1 + b * v3) / den, (a * v1 - b * v3) / den):
        U = jnp.stack([v2, u, jnp.cross(v2, u)], 1)
        W = jnp.stack([Hc @ v2, Hc @ u, jnp.cross(Hc @ v2, Hc @ u)], 1)
        R = W @ U.T
        nrm = jnp.cross(v2, u)
        t = (Hc - R) @ nrm
        sgn = jnp.where(nrm[2] < 0, -1.0, 1.0)
        Rs.append(R)
        ts.append(sgn * t)
        ns.append(sgn * nrm)
    return (jnp.stack(Rs + Rs), jnp.stack(ts + [-ts[0], -ts[1]]), jnp.stack(ns + [-ns[0], -ns[1]]))
