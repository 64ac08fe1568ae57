"""Bundle adjustment: N cameras x M points, Levenberg-Marquardt with the Schur complement.

Model and conventions:

* Cameras share known intrinsics ``K`` (pixels; no distortion in this solver: undistort the
  observations first with :func:`fsjax.render.undistort_normalized`). Each camera's pose is
  solved as ``camera_from_world`` ``(w, t)``: rotation vector ``w`` (``R = so3_exp(w)``) and
  translation ``t``, so a world point ``X`` is seen at ``x = R X + t``; the result record also
  gives the library's ``world_from_camera`` poses (``R^T``, ``-R^T t``).
* Observations are rows ``(camera index, point index, u, v)``: ``u`` column, ``v`` row, pixel
  centres on integers (the camera model of :mod:`fsjax.render.camera`).
* Residual ``r_k = pi(K, R_c X_p + t_c) - uv_k``. Robust losses (``"huber"``, ``"cauchy"``,
  scale ``loss_scale`` px) by iteratively reweighted least squares: every LM iteration weights
  the observation by ``rho'(|r|^2) `` (Triggs et al. 2000, sec. 6.8), the objective being
  ``sum rho(|r_k|^2)``; ``"linear"`` is plain least squares.
* Gauge: the 7 degrees of freedom of a similarity are fixed by holding camera 0's pose and the
  largest-magnitude translation coordinate of camera 1 at their initial values.
* Solver: the normal equations ``[[U, W], [W^T, V]]`` are reduced to the camera block by the
  Schur complement ``S = U - W V^-1 W^T`` (Triggs et al. 2000, sec. 6.1; Hartley & Zisserman
  2004, A6.3): ``V`` is block diagonal (one 3x3 block per point, inverted independently), the
  Jacobian is never formed as a matrix (per-observation 2x6 and 2x3 blocks from ``jax.jacfwd``,
  accumulated by segment sums), and ``S`` (6N x 6N) is solved by Cholesky. The camera-point
  coupling ``W`` is held as an ``(N, M, 6, 3)`` array: memory ``18 N M`` numbers, the size of the
  Jacobian's non-zeros when most points are seen by most cameras (not when visibility is
  very sparse; a per-observation pair list would then be better). Damping: Marquardt's
  ``lambda diag(JtJ)`` with Nielsen's update, in a ``lax.while_loop`` (own loop, not
  optimistix: optimistix's Levenberg-Marquardt solves the damped system through a lineax
  operator of the full Jacobian and offers no place for the Schur reduction).
* Gradient of the solution with respect to the observations: ``bundle_adjust`` has a custom
  VJP by the implicit function theorem at the optimum (``d theta / d uv = H^-1 J^T Omega``
  with the gauge-fixed *exact* Hessian ``H`` of the weighted objective, Gauss-Newton term plus
  residual curvature, and the final robust weights ``Omega``, whose own dependence on ``uv``
  is neglected: exact for ``loss="linear"``), solved with the same Schur machinery.
* Fails closed: non-finite input, fewer than 2 cameras, an index out of range, or a singular
  reduced system give ``converged=False``, a ``reason`` and NaN parameters.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from .._checks import check_positive
from .._linalg import jit_fast_compile
from ..types.results import FitResult, Legacy, deprecated_name, renamed
from .rigid import so3_exp

__all__ = ["BundleResult", "bundle_adjust", "reprojection_residuals"]

#: the old bundle-adjustment codes 0..3 (deprecated ``legacy_reason`` and ``BA_REASONS``)
_LEGACY = Legacy(("ok", "max_iterations", "degenerate", "invalid_input"))


def __getattr__(name):
    if name == "BA_REASONS":
        deprecated_name("fsjax.fit.bundle_adjust.BA_REASONS", "fsjax.types.RESULTS (reason_message)")
        return _LEGACY.table()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


class BundleResult(FitResult):
    """Result of :func:`bundle_adjust`.

    ``rotvecs (N, 3)``, ``translations (N, 3)``: ``camera_from_world`` poses; ``R_world_from_camera
    (N, 3, 3)`` and ``centers (N, 3)``: the same poses in the library's convention; ``points (M, 3)``;
    ``rms_px_initial`` / ``rms_px``: unweighted RMS over all residual coordinates (u and v,
    pixels) before and after (SciPy's convention: ``sqrt(mean(r^2))`` of the stacked residual
    vector; were ``rmse_initial`` / ``rmse``); ``cost``: final robust objective; ``iterations``;
    ``converged``; ``reason``: code of :data:`fsjax.types.RESULTS` (``ok``, ``max_iterations``,
    ``degenerate``: singular reduced camera system, ``invalid_input``).
    """

    rotvecs: Float[Array, "N 3"]
    translations: Float[Array, "N 3"]
    R_world_from_camera: Float[Array, "N 3 3"]
    centers: Float[Array, "N 3"]
    points: Float[Array, "M 3"]
    rms_px_initial: Float[Array, ""]
    rms_px: Float[Array, ""]
    cost: Float[Array, ""]
    iterations: Int[Array, ""]
    converged: Bool[Array, ""]
    reason: Int[Array, ""]
    residual_name = "rms_px"

    rmse = renamed("rms_px")
    rmse_initial = renamed("rms_px_initial")
    legacy_reason = _LEGACY.property()


def _project(K, w, t, X):
    x = so3_exp(w) @ X + t
    z = x[2]
    zs = jnp.where(jnp.abs(z) > 0, z, 1.0)
    u = K[0, 0] * x[0] / zs + K[0, 1] * x[1] / zs + K[0, 2]
    v = K[1, 1] * x[1] / zs + K[1, 2]
    return jnp.stack([u, v])


def reprojection_residuals(K, rotvecs, translations, points, cam_idx, pt_idx, uv):
    """Per-observation residuals ``(n_obs, 2)``: projected minus observed pixel (u, v)."""
    return _reprojection_residuals(K, rotvecs, translations, points, cam_idx, pt_idx, uv)


@jax.jit  # one program (called eagerly, the vmap compiled ~40 small ones)
def _reprojection_residuals(K, rotvecs, translations, points, cam_idx, pt_idx, uv):
    return jax.vmap(lambda c, p, o: _project(K, rotvecs[c], translations[c], points[p]) - o)(cam_idx, pt_idx, uv)


def _rho(loss: str, s2, scale):
    """Robust objective per observation and its derivative w.r.t. the squared residual ``s2``."""
    c2 = scale * scale
    if loss == "linear":
        return s2, jnp.ones_like(s2)
    if loss == "huber":
        small = s2 <= c2
        ss = jnp.where(small, c2, s2)
        return jnp.where(small, s2, 2.0 * scale * jnp.sqrt(ss) - c2), jnp.where(small, 1.0, scale / jnp.sqrt(ss))
    if loss == "cauchy":
        return c2 * jnp.log1p(s2 / c2), 1.0 / (1.0 + s2 / c2)
    raise ValueError(f"bundle_adjust: argument 'loss' must be one of 'linear', 'huber', 'cauchy'; got {loss!r}")


class _Problem(eqx.Module):
    K: Array
    cam_idx: Array
    pt_idx: Array
    n_cams: int = eqx.field(static=True)
    n_pts: int = eqx.field(static=True)
    loss: str = eqx.field(static=True)
    scale: float = eqx.field(static=True)


def _blocks(pb: _Problem, cams, pts, uv):
    """Residuals, per-observation Jacobian blocks and robust weights."""
    K = pb.K

    def one(c6, X, o):
        f = lambda c6_, X_: _project(K, c6_[:3], c6_[3:], X_) - o  # noqa: E731
        r = f(c6, X)
        Jc, Jp = jax.jacfwd(f, argnums=(0, 1))(c6, X)
        return r, Jc, Jp

    r, Jc, Jp = jax.vmap(one)(cams[pb.cam_idx], pts[pb.pt_idx], uv)
    s2 = jnp.sum(r * r, axis=-1)
    rho, w = _rho(pb.loss, s2, pb.scale)
    return r, Jc, Jp, rho, w


def _normal_blocks(pb: _Problem, r, Jc, Jp, w):
    n, m = pb.n_cams, pb.n_pts
    wJc = Jc * w[:, None, None]
    U = jax.ops.segment_sum(jnp.einsum("kai,kaj->kij", wJc, Jc), pb.cam_idx, n)
    V = jax.ops.segment_sum(jnp.einsum("kai,kaj->kij", Jp * w[:, None, None], Jp), pb.pt_idx, m)
    Wk = jnp.einsum("kai,kaj->kij", wJc, Jp)  # (n_obs, 6, 3)
    W = jnp.zeros((n, m, 6, 3), r.dtype).at[pb.cam_idx, pb.pt_idx].add(Wk)
    gc = jax.ops.segment_sum(jnp.einsum("kai,ka->ki", wJc, r), pb.cam_idx, n)
    gp = jax.ops.segment_sum(jnp.einsum("kai,ka->ki", Jp * w[:, None, None], r), pb.pt_idx, m)
    return U, V, W, gc, gp


def _schur_solve(U, V, W, gc, gp, mask, lam):
    """Solve ``(H + lam diag(H)) d = -g`` with H gauge-masked, via the camera Schur complement.

    ``mask (N, 6)``: 1 for free camera parameters. Returns ``(dc (N, 6), dp (M, 3), ok)``.
    """
    n = U.shape[0]
    dt = U.dtype
    eye6 = jnp.eye(6, dtype=dt)
    eye3 = jnp.eye(3, dtype=dt)
    dU = jnp.diagonal(U, axis1=-2, axis2=-1)
    dV = jnp.diagonal(V, axis1=-2, axis2=-1)
    Ud = U + lam * dU[..., None] * eye6
    Vd = V + lam * dV[..., None] * eye3
    Vinv = jnp.linalg.inv(Vd)
    mm = mask[:, None, :, None]  # mask camera rows of W
    Wm = W * mm
    Y = jnp.einsum("cmij,mjk->cmik", Wm, Vinv)  # (N, M, 6, 3)
    S = -jnp.einsum("cmik,dmjk->cidj", Y, Wm).reshape(6 * n, 6 * n)
    Um = Ud * mask[:, :, None] * mask[:, None, :] + (1.0 - mask)[:, :, None] * eye6  # fixed params: identity
    S = S + _block_diag(Um)
    rhs = -(gc * mask) + jnp.einsum("cmij,mj->ci", Y, gp)
    L, low = jax.scipy.linalg.cho_factor(S, lower=True)
    dc = jax.scipy.linalg.cho_solve((L, low), rhs.reshape(-1)).reshape(n, 6) * mask
    ok = jnp.all(jnp.isfinite(dc))
    dp = -jnp.einsum("mij,mj->mi", Vinv, gp + jnp.einsum("cmij,ci->mj", Wm, dc))
    return dc, dp, ok


def _block_diag(B):
    n = B.shape[0]
    out = jnp.zeros((n, 6, n, 6), B.dtype)
    idx = jnp.arange(n)
    out = out.at[idx, :, idx, :].set(B)
    return out.reshape(6 * n, 6 * n)


def _gauge_mask(translations0, dtype) -> jnp.ndarray:
    n = translations0.shape[0]
    mask = jnp.ones((n, 6), dtype).at[0].set(0.0)
    j = jnp.argmax(jnp.abs(translations0[1]))
    return mask.at[1, 3 + j].set(0.0)


def _solve(pb: _Problem, cams0, pts0, uv, max_iter: int, tol: float):
    mask = _gauge_mask(cams0[:, 3:], cams0.dtype)

    def cost_of(cams, pts):
        r = reprojection_residuals(pb.K, cams[:, :3], cams[:, 3:], pts, pb.cam_idx, pb.pt_idx, uv)
        return jnp.sum(_rho(pb.loss, jnp.sum(r * r, -1), pb.scale)[0])

    def cond(s):
        return (~s["done"]) & (s["it"] < max_iter)

    def body(s):
        cams, pts, lam, nu = s["cams"], s["pts"], s["lam"], s["nu"]
        r, Jc, Jp, rho, w = _blocks(pb, cams, pts, uv)
        cost = jnp.sum(rho)
        U, V, W, gc, gp = _normal_blocks(pb, r, Jc, Jp, w)
        dc, dp, ok = _schur_solve(U, V, W, gc, gp, mask, lam)
        new_c, new_p = cams + dc, pts + dp
        new_cost = cost_of(new_c, new_p)
        # predicted decrease of the (IRLS-weighted) quadratic model
        g = jnp.concatenate([(gc * mask).ravel(), gp.ravel()])
        d = jnp.concatenate([dc.ravel(), dp.ravel()])
        dU = jnp.diagonal(U, axis1=-2, axis2=-1) * mask
        dV = jnp.diagonal(V, axis1=-2, axis2=-1)
        damp = jnp.concatenate([(dU * dc * dc).ravel(), (dV * dp * dp).ravel()])
        pred = -(g @ d) + lam * jnp.sum(damp)  # = 0.5 d^T (H + lam D) d - ... times 2; sign-checked below
        pred = jnp.maximum(pred, 1e-300)
        rho_ratio = (cost - new_cost) / pred
        accept = ok & jnp.isfinite(new_cost) & (new_cost < cost)
        step_small = jnp.sqrt(d @ d) <= tol * (jnp.sqrt(jnp.sum(cams * cams) + jnp.sum(pts * pts)) + tol)
        rel_small = accept & ((cost - new_cost) <= tol * cost)
        lam_acc = lam * jnp.maximum(1.0 / 3.0, 1.0 - (2.0 * rho_ratio - 1.0) ** 3)
        s = dict(
            cams=jnp.where(accept, new_c, cams), pts=jnp.where(accept, new_p, pts),
            lam=jnp.where(accept, lam_acc, lam * nu), nu=jnp.where(accept, 2.0, nu * 2.0),
            it=s["it"] + 1, fail=s["fail"] | ~ok & (lam * nu > 1e12),
            done=(accept & (rel_small | step_small)) | (~accept & (lam * nu > 1e16)) | step_small,
        )
        return s

    dt = cams0.dtype
    s0 = dict(cams=cams0, pts=pts0, lam=jnp.asarray(1e-3, dt), nu=jnp.asarray(2.0, dt), it=jnp.asarray(0),
              fail=jnp.asarray(False), done=jnp.asarray(False))
    s = jax.lax.while_loop(cond, body, s0)
    return s["cams"], s["pts"], s["it"], s["done"], s["fail"]


def _final_weights(pb: _Problem, cams, pts, uv):
    r, Jc, Jp, rho, w = _blocks(pb, cams, pts, uv)
    return r, Jc, Jp, w


def _exact_hessian_blocks(pb: _Problem, cams, pts, uv, w):
    """Blocks of the exact Hessian of ``0.5 sum w_k |r_k|^2`` (Gauss-Newton term plus the
    residual-curvature term ``sum w r . grad^2 r``, which the implicit gradient needs: the
    Gauss-Newton matrix alone is off by several per cent at noisy optima)."""
    K = pb.K
    n, m = pb.n_cams, pb.n_pts

    def one(c6, X, o, wk):
        def e(z):
            r = _project(K, z[:3], z[3:6], z[6:]) - o
            return 0.5 * wk * jnp.sum(r * r)

        return jax.hessian(e)(jnp.concatenate([c6, X]))

    Hk = jax.vmap(one)(cams[pb.cam_idx], pts[pb.pt_idx], uv, w)  # (n_obs, 9, 9)
    U = jax.ops.segment_sum(Hk[:, :6, :6], pb.cam_idx, n)
    V = jax.ops.segment_sum(Hk[:, 6:, 6:], pb.pt_idx, m)
    W = jnp.zeros((n, m, 6, 3), Hk.dtype).at[pb.cam_idx, pb.pt_idx].add(Hk[:, :6, 6:])
    return U, V, W


@eqx.filter_custom_vjp
def _ba_core(uv, pb, cams0, pts0, max_iter, tol):
    cams, pts, it, done, fail = _solve(pb, cams0, pts0, uv, max_iter, tol)
    return cams, pts, it, done, fail


@_ba_core.def_fwd
def _ba_fwd(perturbed, uv, pb, cams0, pts0, max_iter, tol):
    out = _ba_core.fn(uv, pb, cams0, pts0, max_iter, tol)
    return out, (out[0], out[1])


@_ba_core.def_bwd
def _ba_bwd(residuals, g_out, perturbed, uv, pb, cams0, pts0, max_iter, tol):
    cams, pts = residuals
    gc_bar, gp_bar = g_out[0], g_out[1]
    gc_bar = jnp.zeros_like(cams) if gc_bar is None else gc_bar
    gp_bar = jnp.zeros_like(pts) if gp_bar is None else gp_bar
    mask = _gauge_mask(cams0[:, 3:], cams.dtype)
    r, Jc, Jp, w = _final_weights(pb, cams, pts, uv)
    U, V, W = _exact_hessian_blocks(pb, cams, pts, uv, jax.lax.stop_gradient(w))
    # solve H x = theta_bar (gauge-masked): reuse the LM solve with lam = 0 and g = -theta_bar
    xc, xp, _ = _schur_solve(U, V, W, -gc_bar, -gp_bar, mask, jnp.asarray(0.0, cams.dtype))
    # theta(uv): H dtheta = J^T Omega duv  ->  uv_bar = Omega J x
    uv_bar = w[:, None] * (jnp.einsum("kai,ki->ka", Jc, xc[pb.cam_idx]) + jnp.einsum("kai,ki->ka", Jp, xp[pb.pt_idx]))
    return uv_bar


def bundle_adjust(K, rotvecs, translations, points, cam_idx, pt_idx, uv, *, loss: str = "linear",
                  loss_scale: float = 1.0, max_iter: int = 100, tol: float = 1e-10) -> BundleResult:
    """Refine camera poses and 3-D points to minimise reprojection error (LM + Schur complement).

    Args:
      K: ``(3, 3)`` shared intrinsics (pixels).
      rotvecs, translations: ``(N, 3)`` initial ``camera_from_world`` poses (rotation vectors,
        translations), N >= 2.
      points: ``(M, 3)`` initial world points.
      cam_idx, pt_idx: ``(n_obs,)`` int indices of each observation's camera and point.
      uv: ``(n_obs, 2)`` observed pixels (u = column, v = row).
      loss: ``"linear"``, ``"huber"`` or ``"cauchy"``; ``loss_scale`` its scale in pixels.
      max_iter: LM iteration cap (reported when hit). tol: relative cost / step tolerance.

    Returns:
      :class:`BundleResult`. Differentiable w.r.t. ``uv`` (implicit; see the module notes).

    Example:
        >>> import numpy as np
        >>> from fsjax.fit.bundle_adjust import bundle_adjust, reprojection_residuals
        >>> rng = np.random.default_rng(0)
        >>> K = jnp.asarray([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
        >>> X = jnp.asarray(rng.uniform(-1, 1, (40, 3)))
        >>> w = jnp.asarray([[0.0, 0.0, 0.0], [0.0, 0.2, 0.0], [0.1, -0.2, 0.0]])
        >>> t = jnp.asarray([[0.0, 0.0, 5.0], [-1.0, 0.0, 5.2], [1.0, 0.5, 5.1]])
        >>> ci, pi = np.repeat(np.arange(3), 40), np.tile(np.arange(40), 3)
        >>> uv = reprojection_residuals(K, w, t, X, ci, pi, jnp.zeros((120, 2)))
        >>> res = bundle_adjust(K, w + 0.01, t.at[2].add(0.05), X + 0.02, ci, pi, uv)
        >>> bool(res.converged), float(res.rms_px) < 1e-8, float(res.rms_px_initial) > 1.0
        (True, True, True)
    """
    fn = "bundle_adjust"
    K = jnp.asarray(K)
    dt = jnp.result_type(K.dtype, jnp.asarray(points).dtype, float)
    K = K.astype(dt)
    w0 = jnp.asarray(rotvecs, dt)
    t0 = jnp.asarray(translations, dt)
    X0 = jnp.asarray(points, dt)
    uv = jnp.asarray(uv, dt)
    ci = jnp.asarray(cam_idx, jnp.int32)
    pi = jnp.asarray(pt_idx, jnp.int32)
    for name, a, tail in (("rotvecs", w0, (3,)), ("translations", t0, (3,)), ("points", X0, (3,)), ("uv", uv, (2,))):
        if a.ndim != 2 or a.shape[1:] != tail:
            raise ValueError(f"{fn}: argument {name!r} must have shape (n, {tail[0]}), got {tuple(a.shape)}")
    n, m = w0.shape[0], X0.shape[0]
    if t0.shape[0] != n:
        raise ValueError(f"{fn}: argument 'translations' must hold one pose per rotation vector ({n}), got {t0.shape[0]}")
    if not (ci.shape == pi.shape == uv.shape[:1]):
        raise ValueError(f"{fn}: arguments 'cam_idx', 'pt_idx', 'uv' must have equal lengths, got {ci.shape}, "
                         f"{pi.shape}, {uv.shape[:1]}")
    _rho(loss, jnp.zeros(()), 1.0)  # validates the name
    check_positive(fn, "loss_scale", loss_scale)
    bad = n < 2
    concrete = not any(isinstance(a, jax.core.Tracer) for a in (ci, pi, uv, w0, t0, X0))
    if concrete:
        bad = bad or bool(np.any(np.asarray(ci) < 0) or np.any(np.asarray(ci) >= n) or np.any(np.asarray(pi) < 0)
                          or np.any(np.asarray(pi) >= m))
    pb = _Problem(K=K, cam_idx=jnp.clip(ci, 0, n - 1), pt_idx=jnp.clip(pi, 0, m - 1), n_cams=n, n_pts=m, loss=loss,
                  scale=float(loss_scale))
    return _run(pb, w0, t0, X0, uv, jnp.asarray(bad), int(max_iter), float(tol))


# compiled with fsjax._linalg.FAST_COMPILE at top level (the docstring's 3 cameras x 40 points,
# float32, compile CPU 3.46 -> 1.36 s, load ~4; under a user's jit the enclosing program's options)
@jit_fast_compile(static_argnames=("max_iter", "tol"))
def _run(pb: _Problem, w0, t0, X0, uv, bad, max_iter: int, tol: float) -> BundleResult:
    K, loss, loss_scale = pb.K, pb.loss, pb.scale
    finite = jnp.all(jnp.isfinite(uv)) & jnp.all(jnp.isfinite(w0)) & jnp.all(jnp.isfinite(t0)) & \
        jnp.all(jnp.isfinite(X0))
    cams0 = jnp.concatenate([w0, t0], axis=1)
    r0 = reprojection_residuals(K, w0, t0, X0, pb.cam_idx, pb.pt_idx, uv)
    rmse0 = jnp.sqrt(jnp.mean(r0 * r0))
    cams, pts, it, done, fail = _ba_core(uv, pb, cams0, X0, max_iter, tol)
    r = reprojection_residuals(K, cams[:, :3], cams[:, 3:], pts, pb.cam_idx, pb.pt_idx, uv)
    rmse = jnp.sqrt(jnp.mean(r * r))
    cost = jnp.sum(_rho(loss, jnp.sum(r * r, -1), float(loss_scale))[0])
    invalid = bad | ~finite
    reason = jnp.where(invalid, 3, jnp.where(fail, 2, jnp.where(done, 0, 1))).astype(jnp.int32)
    converged = reason == 0
    reason = _LEGACY.new(reason).astype(jnp.int32)
    nanif = lambda a: jnp.where(invalid | fail, jnp.nan, a)  # noqa: E731
    R = so3_exp(cams[:, :3])
    Rwc = jnp.swapaxes(R, -1, -2)
    centers = -jnp.einsum("nij,nj->ni", Rwc, cams[:, 3:])
    return BundleResult(rotvecs=nanif(cams[:, :3]), translations=nanif(cams[:, 3:]), R_world_from_camera=nanif(Rwc),
                        centers=nanif(centers), points=nanif(pts), rms_px_initial=rmse0, rms_px=nanif(rmse),
                        cost=nanif(cost), iterations=it, converged=converged, reason=reason)
