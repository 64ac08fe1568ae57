"""Rigid alignment with known correspondences, SE(3) helpers, PCA canonical pose.

Conventions (stated once for the registration modules ``rigid``, ``icp``, ``global_reg``):

* Points are rows of ``(N, 3)`` arrays in any consistent length unit (the bunny is in metres).
  A pose ``(R, t)`` maps a *source* point ``p`` to the *target* frame: ``q = R p + t``
  (``target_from_source``). Rotations are proper: ``R^T R = I``, ``det R = +1``.
* The SE(3) tangent ``xi = (w, v)``: ``w`` is the rotation vector (axis times angle in radians),
  ``v`` the translational part; ``se3_exp(xi)`` is the group exponential (not ``(exp w, v)``).
  Updates in the ICP solvers are applied on the left: ``T <- exp(xi) T``.
* Weights are non-negative; a weight of 0 (or an invalid point) removes the point.
* Failing closed: every fit returns a record with the base fields of :mod:`fsjax.types.results`
  (``converged``, an int32 ``reason`` code of :data:`fsjax.types.RESULTS` with its ``message``,
  ``iterations``, the residual ``rms_len`` in the input's length unit). When the data cannot
  determine the pose (fewer than 3 weighted points, collinear points, non-finite input), the
  pose fields are NaN: never a plausible pose.
* Float64 is the validated precision (tests enable x64); float32 works, with rotation errors
  around 1e-4 deg instead of 1e-10 deg on noise-free data.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from ..types.results import (
    FitResult,
    deprecated_name,
    legacy_table,
    reason_code,
    reason_message,
    renamed,
)

__all__ = [
    "reason_message",
    "RigidFit",
    "kabsch_umeyama",
    "skew",
    "so3_exp",
    "so3_log",
    "se3_exp",
    "se3_log",
    "rotation_angle_deg",
    "rotation_error_deg",
    "rotation_from_axis_angle",
    "CanonicalPose",
    "pca_canonical_pose",
]

OK, MAX_ITER, TOO_FEW, DEGENERATE, INVALID, LOW_FITNESS, NO_HYPOTHESIS = (
    reason_code(n) for n in ("ok", "max_iterations", "too_few", "degenerate", "invalid_input", "poor_fit",
                             "no_hypothesis"))


def __getattr__(name):
    if name == "REGISTRATION_REASONS":
        deprecated_name("fsjax.fit.rigid.REGISTRATION_REASONS", "fsjax.types.RESULTS (reason_message)")
        return legacy_table(("ok", "max_iterations", "too_few", "degenerate", "invalid_input", "poor_fit",
                             "no_hypothesis"))
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def _eps(dtype) -> float:
    return float(jnp.finfo(dtype).eps)


# ---------------------------------------------------------------------------
# SO(3) / SE(3)
# ---------------------------------------------------------------------------


def skew(w: Float[Array, "*b 3"]) -> Float[Array, "*b 3 3"]:
    """The cross-product matrix ``[w]_x`` with ``[w]_x v = w x v``."""
    x, y, z = w[..., 0], w[..., 1], w[..., 2]
    o = jnp.zeros_like(x)
    return jnp.stack([jnp.stack([o, -z, y], -1), jnp.stack([z, o, -x], -1), jnp.stack([-y, x, o], -1)], -2)


def _vee(m):
    return jnp.stack([m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]], -1)


def _so3_coeffs(theta2):
    """``A = sin t / t``, ``B = (1 - cos t) / t^2``, ``C = (t - sin t) / t^3`` with Taylor branches near 0."""
    small = theta2 < 1e-6
    t2 = jnp.where(small, 1.0, theta2)
    t = jnp.sqrt(t2)
    a = jnp.where(small, 1.0 - theta2 / 6.0 + theta2**2 / 120.0, jnp.sin(t) / t)
    b = jnp.where(small, 0.5 - theta2 / 24.0 + theta2**2 / 720.0, (1.0 - jnp.cos(t)) / t2)
    c = jnp.where(small, 1.0 / 6.0 - theta2 / 120.0 + theta2**2 / 5040.0, (t - jnp.sin(t)) / (t2 * t))
    return a, b, c


def so3_exp(w: Float[Array, "*b 3"]) -> Float[Array, "*b 3 3"]:
    """Rodrigues' formula: the rotation by ``|w|`` radians about ``w / |w|`` (identity at ``w = 0``)."""
    w = jnp.asarray(w)
    k = skew(w)
    a, b, _ = _so3_coeffs(jnp.sum(w * w, -1))
    eye = jnp.eye(3, dtype=k.dtype)
    return eye + a[..., None, None] * k + b[..., None, None] * (k @ k)


def _quat_from_matrix(r):
    """Unit quaternion ``(w, x, y, z)`` of a rotation matrix (Shepperd's branch choice, NaN-free)."""
    m00, m11, m22 = r[..., 0, 0], r[..., 1, 1], r[..., 2, 2]
    tr = m00 + m11 + m22
    cands = jnp.stack([tr, m00, m11, m22], -1)
    i = jnp.argmax(cands, -1)
    # 4 q_i^2 = 1 + 2 cands_i - tr  for i = x, y, z; 4 w^2 = 1 + tr
    s = jnp.sqrt(jnp.maximum(1.0 + 2.0 * jnp.take_along_axis(cands, i[..., None], -1)[..., 0] - tr, 1e-300))
    d = _vee(r)  # (m21 - m12, m02 - m20, m10 - m01) = 4 w (x, y, z)
    sxy = r[..., 0, 1] + r[..., 1, 0]
    sxz = r[..., 0, 2] + r[..., 2, 0]
    syz = r[..., 1, 2] + r[..., 2, 1]
    q0 = jnp.stack([s, d[..., 0] / s, d[..., 1] / s, d[..., 2] / s], -1)
    q1 = jnp.stack([d[..., 0] / s, s, sxy / s, sxz / s], -1)
    q2 = jnp.stack([d[..., 1] / s, sxy / s, s, syz / s], -1)
    q3 = jnp.stack([d[..., 2] / s, sxz / s, syz / s, s], -1)
    qs = jnp.stack([q0, q1, q2, q3], -2)
    q = jnp.take_along_axis(qs, i[..., None, None], -2)[..., 0, :] * 0.5
    return q * jnp.where(q[..., :1] < 0, -1.0, 1.0)  # w >= 0: angle in [0, pi]


def so3_log(r: Float[Array, "*b 3 3"]) -> Float[Array, "*b 3"]:
    """Rotation vector of a rotation matrix, angle in ``[0, pi]``; exact near 0 and near pi.

    Goes through the unit quaternion (Shepperd), then ``w = 2 atan2(|v|, q_w) v / |v|``
    with a Taylor branch at ``|v| -> 0``.
    """
    q = _quat_from_matrix(jnp.asarray(r))
    v = q[..., 1:]
    n2 = jnp.sum(v * v, -1)
    small = n2 < 1e-16
    n = jnp.sqrt(jnp.where(small, 1.0, n2))
    ang = 2.0 * jnp.arctan2(n, q[..., 0])
    f = jnp.where(small, 2.0 / q[..., 0], ang / n)
    return v * f[..., None]


def se3_exp(xi: Float[Array, "*b 6"]) -> tuple[Float[Array, "*b 3 3"], Float[Array, "*b 3"]]:
    """Group exponential of ``xi = (w, v)``: ``R = exp([w]_x)``, ``t = V v``, ``V = I + B K + C K^2``."""
    xi = jnp.asarray(xi)
    w, v = xi[..., :3], xi[..., 3:]
    k = skew(w)
    a, b, c = _so3_coeffs(jnp.sum(w * w, -1))
    eye = jnp.eye(3, dtype=k.dtype)
    k2 = k @ k
    r = eye + a[..., None, None] * k + b[..., None, None] * k2
    vm = eye + b[..., None, None] * k + c[..., None, None] * k2
    return r, jnp.einsum("...ij,...j->...i", vm, v)


def se3_log(r: Float[Array, "*b 3 3"], t: Float[Array, "*b 3"]) -> Float[Array, "*b 6"]:
    """Inverse of :func:`se3_exp` for rotation angles below pi: ``xi = (log R, V^-1 t)``."""
    w = so3_log(r)
    k = skew(w)
    th2 = jnp.sum(w * w, -1)
    a, b, _ = _so3_coeffs(th2)
    small = th2 < 1e-6
    th2s = jnp.where(small, 1.0, th2)
    bs = jnp.where(small, 1.0, b)
    d = jnp.where(small, 1.0 / 12.0 + th2 / 720.0, (1.0 - a / (2.0 * bs)) / th2s)
    vinv = jnp.eye(3, dtype=k.dtype) - 0.5 * k + d[..., None, None] * (k @ k)
    return jnp.concatenate([w, jnp.einsum("...ij,...j->...i", vinv, t)], -1)


def rotation_angle_deg(r: Float[Array, "*b 3 3"]) -> Float[Array, "*b"]:
    """Rotation angle of ``R`` in degrees, ``atan2(|vee(R - R^T)| / 2, (tr R - 1) / 2)`` (accurate at 0)."""
    r = jnp.asarray(r)
    s = 0.5 * jnp.linalg.norm(_vee(r), axis=-1)
    c = 0.5 * (jnp.trace(r, axis1=-2, axis2=-1) - 1.0)
    return jnp.degrees(jnp.arctan2(s, c))


def rotation_error_deg(r_est: Float[Array, "*b 3 3"], r_true: Float[Array, "*b 3 3"]) -> Float[Array, "*b"]:
    """Angle of ``R_est R_true^T`` in degrees (geodesic distance on SO(3)); NaN in -> NaN out."""
    return rotation_angle_deg(jnp.asarray(r_est) @ jnp.swapaxes(jnp.asarray(r_true), -1, -2))


def rotation_from_axis_angle(axis, angle_deg) -> Float[Array, "*b 3 3"]:
    """Rotation by ``angle_deg`` degrees about ``axis`` (normalised here; a zero axis raises eagerly)."""
    axis = jnp.asarray(axis, dtype=jnp.result_type(float))
    n = jnp.linalg.norm(axis, axis=-1, keepdims=True)
    try:
        if not bool(jnp.all(n > 0)):
            raise ValueError("rotation_from_axis_angle: argument 'axis' must be non-zero, got a zero-length axis")
    except jax.errors.ConcretizationTypeError:
        pass
    return so3_exp(axis / n * jnp.radians(jnp.asarray(angle_deg, axis.dtype))[..., None])


# ---------------------------------------------------------------------------
# Umeyama / Kabsch
# ---------------------------------------------------------------------------


class RigidFit(FitResult):
    """Result of :func:`kabsch_umeyama`: ``dst ~ scale * R src + t``.

    Attributes:
        R: ``(3, 3)`` proper rotation (NaN when not ``converged``).
        t: ``(3,)`` translation (NaN when not ``converged``).
        scale: similarity scale (1 unless ``with_scale``; NaN when not ``converged``).
        rms_len: weighted RMS of ``|dst - (scale R src + t)|`` over the used pairs (input length unit).
        n_used: number of pairs with positive weight.
        converged: the pose is determined by the data (was ``valid``).
        reason: int32 code of :data:`fsjax.types.RESULTS` (0 when ``converged``); ``message`` its text.
        iterations: 0 (closed form).
    """

    R: Float[Array, "3 3"]
    t: Float[Array, " 3"]
    scale: Float[Array, ""]
    rms_len: Float[Array, ""]
    n_used: Int[Array, ""]
    converged: Bool[Array, ""]
    reason: Int[Array, ""]
    iterations: Int[Array, ""]
    residual_name = "rms_len"

    rms = renamed("rms_len")
    valid = renamed("converged")


def _weighted_kabsch(src, dst, w, with_scale: bool):
    """Core weighted Umeyama solve. Returns (R, t, scale, svals, sigma_src2, wsum)."""
    wsum = jnp.sum(w)
    ws = jnp.where(wsum > 0, wsum, 1.0)
    mu_s = jnp.sum(w[:, None] * src, 0) / ws
    mu_d = jnp.sum(w[:, None] * dst, 0) / ws
    a = src - mu_s
    b = dst - mu_d
    cov = (w[:, None] * b).T @ a / ws  # sum w (d - mu_d)(s - mu_s)^T
    u, s, vt = jnp.linalg.svd(cov)
    sgn = jnp.where(jnp.linalg.det(u) * jnp.linalg.det(vt) < 0, -1.0, 1.0).astype(src.dtype)
    dvec = jnp.stack([jnp.ones_like(sgn), jnp.ones_like(sgn), sgn])
    r = (u * dvec) @ vt
    var_s = jnp.sum(w * jnp.sum(a * a, -1)) / ws
    if with_scale:
        scale = jnp.sum(s * dvec) / jnp.where(var_s > 0, var_s, 1.0)
    else:
        scale = jnp.ones((), src.dtype)
    t = mu_d - scale * r @ mu_s
    return r, t, scale, s, var_s, wsum


def kabsch_umeyama(
    src: Float[Array, "N 3"],
    dst: Float[Array, "N 3"],
    *,
    weights: Float[Array, " N"] | None = None,
    with_scale: bool = False,
) -> RigidFit:
    """Least-squares rigid (or similarity) transform between corresponding point sets.

    Minimises ``sum_i w_i |dst_i - (s R src_i + t)|^2`` in closed form (Umeyama 1991): the
    weighted cross-covariance ``S = sum w (d - mu_d)(s - mu_s)^T = U D V^T`` gives
    ``R = U diag(1, 1, sign(det U det V)) V^T`` -- the sign term guards against a reflection
    (the Kabsch solution of reflected or noisy coplanar data would otherwise have det -1).
    With ``with_scale`` the scale is ``s = tr(D diag(1,1,+-1)) / var(src)``.

    Args:
        src: ``(N, 3)`` source points.
        dst: ``(N, 3)`` corresponding target points.
        weights: ``(N,)`` non-negative weights; ``None`` = all 1. Zero removes a pair.
        with_scale: also fit a similarity scale (static bool).

    Returns:
        :class:`RigidFit`. Fails closed (NaN pose, ``converged=False``) with reason 2 (fewer than
        3 weighted pairs), 3 (collinear or coincident points: the second singular value of the
        cross-covariance is below ``1e3 eps`` of the first) or 4 (non-finite input).

    Matches ``scipy.spatial.transform.Rotation.align_vectors`` (centred) to ~1e-12 in float64.

    Example:
        >>> import jax.numpy as jnp
        >>> from fsjax.fit import kabsch_umeyama, rotation_from_axis_angle, rotation_error_deg
        >>> src = jnp.array([[0., 0, 0], [1, 0, 0], [0, 2, 0], [0, 0, 3], [1, 1, 1]])
        >>> R = rotation_from_axis_angle(jnp.array([1., 2, 3]), 40.0)
        >>> fit = kabsch_umeyama(src, src @ R.T + jnp.array([0.5, -1.0, 2.0]))
        >>> bool(fit.converged), float(rotation_error_deg(fit.R, R)) < 1e-9, round(float(fit.t[1]), 9)
        (True, True, -1.0)
    """
    src = jnp.asarray(src)
    dst = jnp.asarray(dst)
    dtype = jnp.result_type(src.dtype, dst.dtype, jnp.float32)
    src, dst = src.astype(dtype), dst.astype(dtype)
    if src.ndim != 2 or src.shape[-1] != 3 or dst.shape != src.shape:
        raise ValueError(f"kabsch_umeyama: arguments 'src', 'dst' must be two (N, 3) arrays of equal shape, got {src.shape} "
                         f"and {dst.shape}")
    w = jnp.ones(src.shape[0], dtype) if weights is None else jnp.asarray(weights, dtype)
    if w.shape != src.shape[:1]:
        raise ValueError(f"kabsch_umeyama: argument 'weights' must have shape {src.shape[:1]}, got {w.shape}")
    return _kabsch_core(src, dst, w, bool(with_scale))


@functools.partial(jax.jit, static_argnames=("with_scale",))
def _kabsch_core(src, dst, w, with_scale: bool) -> RigidFit:
    """The body of :func:`kabsch_umeyama` after its shape checks, one program (an eager call
    compiled ~40 small ones)."""
    dtype = src.dtype
    use = w > 0
    finite = jnp.all(jnp.where(use[:, None], jnp.isfinite(src) & jnp.isfinite(dst), True)) & jnp.all(jnp.isfinite(w))
    w = jnp.where(use & finite, w, 0.0)
    src0 = jnp.where(use[:, None] & finite, src, 0.0)
    dst0 = jnp.where(use[:, None] & finite, dst, 0.0)
    r, t, scale, s, var_s, wsum = _weighted_kabsch(src0, dst0, w, with_scale)
    n_used = jnp.sum(use).astype(jnp.int32)
    rank_ok = s[1] > 1e3 * _eps(dtype) * s[0]
    reason = jnp.where(~finite, INVALID, jnp.where(n_used < 3, TOO_FEW, jnp.where(~rank_ok, DEGENERATE, OK)))
    valid = reason == OK
    res = dst0 - (scale * src0 @ r.T + t)
    rms = jnp.sqrt(jnp.sum(w * jnp.sum(res * res, -1)) / jnp.where(wsum > 0, wsum, 1.0))
    nan = jnp.asarray(jnp.nan, dtype)
    return RigidFit(
        R=jnp.where(valid, r, nan), t=jnp.where(valid, t, nan), scale=jnp.where(valid, scale, nan),
        rms_len=jnp.where(valid, rms, nan), n_used=n_used, converged=valid, reason=reason.astype(jnp.int32),
        iterations=jnp.zeros((), jnp.int32),
    )


# ---------------------------------------------------------------------------
# PCA canonical pose
# ---------------------------------------------------------------------------


class CanonicalPose(FitResult):
    """Result of :func:`pca_canonical_pose`.

    A fit result (base fields ``converged``, ``reason``, ``iterations``) without a residual:
    the pose is a closed-form function of the covariance and skewness, nothing is minimised
    (``residual_name`` is ``None``).

    Attributes:
        R: ``(3, 3)`` proper rotation whose columns are the canonical axes in world coordinates
            (``world_from_canonical``); canonical coordinates are ``(x - centroid) @ R``.
        centroid: ``(3,)`` mean of the valid points.
        eigenvalues: ``(3,)`` covariance eigenvalues, descending.
        skewness: ``(3,)`` third standardised moment along each final axis (>= 0 on the axes
            whose sign was chosen by it; see the rule).
        flipped_axis: int32 index of the axis flipped to make the frame right-handed (-1: none).
        ambiguous: ``True`` when the pose is not determined by the shape: two eigenvalues within
            ``eig_tol`` (relative), or an axis whose sign rests on a skewness below ``skew_tol``.
        converged: fewer than 4 valid points or non-finite input -> ``False`` and NaN fields
            (was ``valid``); ``reason`` says which (``too_few`` or ``invalid_input``).
        iterations: 0 (closed form).
    """

    R: Float[Array, "3 3"]
    centroid: Float[Array, " 3"]
    eigenvalues: Float[Array, " 3"]
    skewness: Float[Array, " 3"]
    flipped_axis: Int[Array, ""]
    ambiguous: Bool[Array, ""]
    converged: Bool[Array, ""]
    reason: Int[Array, ""]
    iterations: Int[Array, ""]

    valid = renamed("converged")


def pca_canonical_pose(
    xyz: Float[Array, "N 3"],
    valid: Bool[Array, " N"] | None = None,
    *,
    eig_tol: float = 1e-3,
    skew_tol: float = 1e-3,
) -> CanonicalPose:
    """Canonical pose of a point cloud from its principal axes, with signs and handedness fixed.

    Axes: eigenvectors of the covariance, ordered by descending eigenvalue. Signs: each axis
    ``e_k`` is oriented so that the third moment of the projections ``(x - c) . e_k`` is
    positive (the longer tail of the distribution points along ``+e_k``). Handedness: when the
    three sign-fixed axes form a left-handed frame (``det = -1``, which happens for a shape
    whose skewness frame is mirror-oriented, e.g. a reflected scan), the rule flips the axis
    with the *smallest* ``|skewness|`` -- the sign the data determines least reliably -- so the
    result is a proper rotation and never falls back to the identity. The rule depends only on
    the shape, so two rotated copies of one cloud get poses related by exactly that rotation:
    ``R_rel = R_b R_a^T``.

    Args:
        xyz: ``(N, 3)`` points.
        valid: ``(N,)`` mask; ``None`` = all valid.
        eig_tol: relative eigenvalue gap below which the axes are ambiguous.
        skew_tol: ``|skewness|`` below which an axis sign is ambiguous.

    Returns:
        :class:`CanonicalPose` (``ambiguous`` says when the pose is not unique, e.g. a sphere or a
        symmetric box; ``converged=False`` with NaN for fewer than 4 points or non-finite input).

    Example:
        >>> import jax, jax.numpy as jnp
        >>> from fsjax.fit import pca_canonical_pose, rotation_from_axis_angle, rotation_error_deg
        >>> x = jax.random.gamma(jax.random.key(0), 2.0, (500, 3)) * jnp.array([3.0, 2.0, 1.0])
        >>> Rtrue = rotation_from_axis_angle(jnp.array([0.3, -1.0, 0.5]), 130.0)
        >>> a, b = pca_canonical_pose(x), pca_canonical_pose(x @ Rtrue.T)
        >>> float(rotation_error_deg(b.R @ a.R.T, Rtrue)) < 1e-8
        True
    """
    xyz = jnp.asarray(xyz)
    xyz = xyz.astype(jnp.result_type(xyz.dtype, jnp.float32))
    if xyz.ndim != 2 or xyz.shape[-1] != 3:
        raise ValueError(f"pca_canonical_pose: argument 'xyz' must be an (N, 3) array, got {xyz.shape}")
    m = jnp.ones(xyz.shape[0], bool) if valid is None else jnp.asarray(valid, bool)
    finite = jnp.all(jnp.where(m[:, None], jnp.isfinite(xyz), True))
    w = (m & finite).astype(xyz.dtype)
    n = jnp.sum(w)
    ns = jnp.where(n > 0, n, 1.0)
    x0 = jnp.where(m[:, None] & finite, xyz, 0.0)
    c = jnp.sum(w[:, None] * x0, 0) / ns
    d = (x0 - c) * w[:, None]
    cov = d.T @ d / ns
    lam, vec = jnp.linalg.eigh(cov)
    lam, vec = lam[::-1], vec[:, ::-1]
    proj = d @ vec
    m3 = jnp.sum(w[:, None] * proj**3, 0) / ns
    sd = jnp.sqrt(jnp.maximum(lam, 0.0))
    sd3 = jnp.where(sd > 0, sd**3, 1.0)
    skw = jnp.where(sd > 0, m3 / sd3, 0.0)
    sgn = jnp.where(skw < 0, -1.0, 1.0).astype(xyz.dtype)
    vec = vec * sgn
    skw = skw * sgn
    left = jnp.linalg.det(vec) < 0
    k = jnp.argmin(jnp.abs(skw))
    flip = jnp.where(left & (jnp.arange(3) == k), -1.0, 1.0).astype(xyz.dtype)
    vec = vec * flip
    skw = skw * flip
    gap = jnp.abs(jnp.diff(lam)) / jnp.where(lam[0] > 0, lam[0], 1.0)
    ambiguous = jnp.any(gap < eig_tol) | jnp.any(jnp.abs(skw) < skew_tol)
    ok = finite & (n >= 4) & (lam[0] > 0)
    nan = jnp.asarray(jnp.nan, xyz.dtype)
    return CanonicalPose(
        R=jnp.where(ok, vec, nan), centroid=jnp.where(ok, c, nan), eigenvalues=jnp.where(ok, lam, nan),
        skewness=jnp.where(ok, skw, nan), flipped_axis=jnp.where(left, k, -1).astype(jnp.int32),
        ambiguous=ambiguous | ~ok, converged=ok,
        reason=jnp.where(~finite, INVALID, jnp.where(ok, OK, jnp.where(n >= 4, DEGENERATE, TOO_FEW))).astype(jnp.int32),
        iterations=jnp.zeros((), jnp.int32),
    )
