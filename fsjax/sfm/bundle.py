"""Bundle adjustment for incremental SfM: observation lists with weights, fixed capacities, frozen cameras.

Why not :func:`fsjax.fit.bundle_adjust` directly: an incremental reconstruction calls bundle
adjustment after every registered image, with a growing set of cameras, points and observations.
Each new shape would be a new XLA compile (seconds each). Here capacities are padded: what is not
in the problem has weight 0 (observations) or is frozen (cameras, points), so one compiled solver
serves every problem of a bucket (:func:`fsjax.sfm.reconstruct` pads each problem to one power-of-two
level of its observations, points and observation pairs: herzjesu-P8 compiles three).

Model: camera ``i`` maps world to camera as ``x = R_i X + t_i`` (``camera_from_world``), updated
as ``R_i <- exp(dw) R_i``, ``t_i <- t_i + dt``; points ``X_p <- X_p + dX``; shared intrinsics ``K``
(no distortion). Residual: projected minus observed pixel. Robust loss: Cauchy of scale
``loss_scale_px`` by iteratively reweighted least squares (weights ``1 / (1 + r^2 / s^2)``),
objective ``sum w_k s^2 log(1 + r_k^2 / s^2)``.

Solver: Levenberg-Marquardt with Marquardt's diagonal damping; the normal equations are reduced to
the cameras by the Schur complement (Triggs et al. 2000, sec. 6.1; Hartley and Zisserman 2004,
A6.3): per-observation Jacobian blocks (2x6, 2x3), ``U`` and ``V`` accumulated by segment sums over
the observation list, point blocks inverted 3x3 each. With ``obs_pairs`` (what
:func:`fsjax.sfm.reconstruct` passes) the reduced camera matrix ``S = U - W V^-1 W^T`` is summed
over the pairs of observations of one point, ``S_ij -= W_a V_p^-1 W_b^T``, a segment sum into
``(N, N)`` 6x6 blocks: cost and memory follow the observations, not cameras x points. Only the
unordered pairs ``a < b`` are listed: the term of ``(b, a)`` is the transpose of that of ``(a, b)``
(``V_p^-1`` is symmetric), and the terms ``a = b`` are a segment sum over the observations, so the
scatter (the costliest step of an iteration) moves ``sum c(c-1)/2`` blocks for tracks of lengths
``c`` instead of ``sum c^2`` (herzjesu-P8: 10,400 instead of 28,200).
Jacobian blocks are analytic (``d proj / d x`` times ``-[R X]_x``, ``I``, ``R``). Without it,
the coupling is scattered into a dense ``(N*6, M*3)`` matrix and ``S`` is one matrix product
(18 N M numbers; kept as the reference the pair path is tested against). ``S`` itself is solved
densely (``6N x 6N``): fine for hundreds of cameras, not for tens of thousands.

Gauge: the caller freezes one camera fully and one translation coordinate of a second (7 dof).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ..fit.rigid import so3_exp

__all__ = ["bundle_adjust_masked", "observation_pairs"]


def _project(K, R, t, X):
    x = R @ X + t
    z = jnp.where(jnp.abs(x[2]) > 1e-12, x[2], 1e-12)
    return jnp.stack([K[0, 0] * x[0] / z + K[0, 2], K[1, 1] * x[1] / z + K[1, 2]])


def _inv3(A):
    c = jnp.stack([
        jnp.stack([A[:, 1, 1] * A[:, 2, 2] - A[:, 1, 2] * A[:, 2, 1], A[:, 0, 2] * A[:, 2, 1] - A[:, 0, 1] * A[:, 2, 2],
                   A[:, 0, 1] * A[:, 1, 2] - A[:, 0, 2] * A[:, 1, 1]], -1),
        jnp.stack([A[:, 1, 2] * A[:, 2, 0] - A[:, 1, 0] * A[:, 2, 2], A[:, 0, 0] * A[:, 2, 2] - A[:, 0, 2] * A[:, 2, 0],
                   A[:, 0, 2] * A[:, 1, 0] - A[:, 0, 0] * A[:, 1, 2]], -1),
        jnp.stack([A[:, 1, 0] * A[:, 2, 1] - A[:, 1, 1] * A[:, 2, 0], A[:, 0, 1] * A[:, 2, 0] - A[:, 0, 0] * A[:, 2, 1],
                   A[:, 0, 0] * A[:, 1, 1] - A[:, 0, 1] * A[:, 1, 0]], -1)], -2)
    det = jnp.sum(A[:, 0, :] * c[:, :, 0], -1)
    ok = jnp.abs(det) > 0
    return c / jnp.where(ok, det, 1.0)[:, None, None], ok


def observation_pairs(pi, capacity: int | None = None) -> np.ndarray:
    """Every unordered pair ``a < b`` of two observations of one point, from the point index
    ``pi (O,)`` of each observation, as an ``(P, 2)`` int32 array padded with -1 to ``capacity``
    (default: no padding). Host-side numpy, once per observation list."""
    pi = np.asarray(pi)
    order = np.argsort(pi, kind="stable")
    _, start, count = np.unique(pi[order], return_index=True, return_counts=True)
    a_list, b_list = [], []
    for c in np.unique(count):
        if c < 2:
            continue
        rows = np.sort(order[start[count == c][:, None] + np.arange(c)], axis=1)  # (tracks of length c, c)
        ia, ib = np.triu_indices(c, 1)
        a_list.append(rows[:, ia].ravel())
        b_list.append(rows[:, ib].ravel())
    out = np.stack([np.concatenate(a_list), np.concatenate(b_list)], 1).astype(np.int32) if a_list else \
        np.zeros((0, 2), np.int32)
    if capacity is not None:
        if capacity < len(out):
            raise ValueError(f"observation_pairs: argument 'capacity' must be >= {len(out)} pairs, got {capacity}")
        out = np.concatenate([out, np.full((capacity - len(out), 2), -1, np.int32)])
    return out


def _residual_and_jacobian(K, o, R, t, X):
    """Residual ``proj(R X + t) - o`` (2,) and its Jacobian (2, 9) in ``(dw, dt, dX)`` for the update
    ``R <- exp(dw) R``: with ``x = R X + t`` and ``P = d proj / d x`` (2x3), the blocks are
    ``P (-[R X]_x)``, ``P`` and ``P R`` (analytic; the same as ``jax.jacfwd`` through ``so3_exp``,
    tested, at a third of the cost)."""
    y = R @ X
    x = y + t
    z = jnp.where(jnp.abs(x[2]) > 1e-12, x[2], 1e-12)
    f0, f1 = K[0, 0] / z, K[1, 1] / z
    zero = jnp.zeros((), x.dtype)
    P = jnp.stack([jnp.stack([f0, zero, -f0 * x[0] / z]), jnp.stack([zero, f1, -f1 * x[1] / z])])
    r = jnp.stack([f0 * x[0] + K[0, 2], f1 * x[1] + K[1, 2]]) - o
    neg_skew = jnp.stack([jnp.stack([zero, y[2], -y[1]]), jnp.stack([-y[2], zero, y[0]]), jnp.stack([y[1], -y[0], zero])])
    return r, jnp.concatenate([P @ neg_skew, P, P @ R], 1)


def _residuals(K, R, t, X, ci, pi, uv):
    return jax.vmap(lambda c, p, o: _project(K, R[c], t[c], X[p]) - o)(ci, pi, uv)


@jax.jit
def bundle_adjust_masked(K, R, t, X, ci, pi, uv, w_obs, cam_free, pt_free, *, obs_pairs=None, loss_scale_px=1.0,
                         max_iter=20, tol=1e-8):
    """LM + Schur bundle adjustment over weighted observation lists (see the module notes).

    Args:
      K: ``(3, 3)``. R: ``(N, 3, 3)``, t: ``(N, 3)`` ``camera_from_world``. X: ``(M, 3)``.
      ci, pi: ``(O,)`` camera and point index of each observation; uv: ``(O, 2)`` pixels.
      w_obs: ``(O,)`` observation weights (0 = not in the problem).
      cam_free: ``(N, 6)`` 1 where a camera parameter (dw, dt) may move. pt_free: ``(M,)``.
      obs_pairs: optional ``(P, 2)`` int: every unordered pair ``a < b`` of observations of one
        point, padded with -1 (:func:`observation_pairs`). Given, the Schur complement is summed
        over these pairs and their transposes (``S_ij -= W_a V_p^-1 W_b^T``), with no dense
        ``(N, M)`` coupling; the same normal equations up to the order of the sums.
      loss_scale_px: Cauchy scale. max_iter: LM cap (traced: no recompile). tol: relative cost decrease to stop.

    Returns:
      ``(R, t, X, rms_px, iterations)``: RMS of the residual norms of the observations with weight > 0.
    """
    n, m = R.shape[0], X.shape[0]
    dt_ = X.dtype
    s2 = loss_scale_px ** 2
    wo = w_obs.astype(dt_)
    cf = cam_free.astype(dt_)
    pf = pt_free.astype(dt_)
    has = jax.ops.segment_sum(wo, pi, m) > 0
    pf = pf * has

    def cost_of(R, t, X):
        r = _residuals(K, R, t, X, ci, pi, uv)
        q = jnp.sum(r * r, -1)
        return jnp.sum(wo * s2 * jnp.log1p(q / s2))

    def body(s):
        R, t, X, lam = s["R"], s["t"], s["X"], s["lam"]
        r, J = jax.vmap(_residual_and_jacobian, (None, 0, 0, 0, 0))(K, uv, R[ci], t[ci], X[pi])  # (O, 2), (O, 2, 9)
        q = jnp.sum(r * r, -1)
        wk = wo / (1.0 + q / s2)
        Jc, Jp = J[:, :, :6] * cf[ci][:, None, :], J[:, :, 6:] * pf[pi][:, None, None]
        U = jax.ops.segment_sum(wk[:, None, None] * jnp.einsum("kai,kaj->kij", Jc, Jc), ci, n)
        V = jax.ops.segment_sum(wk[:, None, None] * jnp.einsum("kai,kaj->kij", Jp, Jp), pi, m)
        Wk = wk[:, None, None] * jnp.einsum("kai,kaj->kij", Jc, Jp)  # (O, 6, 3)
        gc = jax.ops.segment_sum(wk[:, None] * jnp.einsum("kai,ka->ki", Jc, r), ci, n)
        gp = jax.ops.segment_sum(wk[:, None] * jnp.einsum("kai,ka->ki", Jp, r), pi, m)
        eye6, eye3 = jnp.eye(6, dtype=dt_), jnp.eye(3, dtype=dt_)
        Ud = U + lam * jnp.diagonal(U, axis1=1, axis2=2)[:, :, None] * eye6 + (1 - cf)[:, :, None] * eye6
        Ud = Ud + 1e-12 * eye6
        Vd = V + lam * jnp.diagonal(V, axis1=1, axis2=2)[:, :, None] * eye3 + (1 - pf)[:, None, None] * eye3
        Vd = Vd + 1e-12 * eye3
        Vi, okv = _inv3(Vd)
        S = jnp.zeros((n, 6, n, 6), dt_).at[jnp.arange(n), :, jnp.arange(n), :].set(Ud)
        if obs_pairs is None:
            Wd = jnp.zeros((n, m, 6, 3), dt_).at[ci, pi].add(Wk)  # dense camera x point coupling
            Y = jnp.einsum("nmij,mjk->nmik", Wd, Vi)
            S = S.reshape(6 * n, 6 * n) - Y.transpose(0, 2, 1, 3).reshape(6 * n, 3 * m) @ \
                Wd.transpose(0, 2, 1, 3).reshape(6 * n, 3 * m).T
            rhs = -gc.reshape(-1) + (Y.transpose(0, 2, 1, 3).reshape(6 * n, 3 * m) @ gp.reshape(-1))
            dc = jnp.linalg.solve(S, rhs).reshape(n, 6) * cf
            dp = -jnp.einsum("mij,mj->mi", Vi, gp + jnp.einsum("nmij,ni->mj", Wd, dc)) * pf[:, None]
        else:
            Yk = jnp.einsum("kij,kjl->kil", Wk, Vi[pi])  # (O, 6, 3): W_a V_p^-1
            pa, pb = obs_pairs[:, 0], obs_pairs[:, 1]
            pv = (pa >= 0).astype(dt_)
            pa, pb = jnp.maximum(pa, 0), jnp.maximum(pb, 0)
            blocks = jnp.einsum("kil,kjl->kij", Yk[pa], Wk[pb]) * pv[:, None, None]  # (P, 6, 6), a < b
            L = jax.ops.segment_sum(blocks, ci[pa] * n + ci[pb], n * n).reshape(n, n, 6, 6)
            L = L.transpose(0, 2, 1, 3).reshape(6 * n, 6 * n)
            D = jax.ops.segment_sum(jnp.einsum("kil,kjl->kij", Yk, Wk), ci, n)  # a = b
            S = (S - jnp.zeros((n, 6, n, 6), dt_).at[jnp.arange(n), :, jnp.arange(n), :].set(D)).reshape(6 * n, 6 * n)
            S = S - L - L.T
            rhs = -gc + jax.ops.segment_sum(jnp.einsum("kil,kl->ki", Yk, gp[pi]), ci, n)
            dc = jnp.linalg.solve(S, rhs.reshape(-1)).reshape(n, 6) * cf
            back = jax.ops.segment_sum(jnp.einsum("kij,ki->kj", Wk, dc[ci]), pi, m)  # sum_a W_a^T dc
            dp = -jnp.einsum("mij,mj->mi", Vi, gp + back) * pf[:, None]
        Rn = so3_exp(dc[:, :3]) @ R
        tn, Xn = t + dc[:, 3:], X + dp
        c0, c1 = s["cost"], cost_of(Rn, tn, Xn)  # the cost of the current state is carried
        acc = jnp.isfinite(c1) & (c1 < c0) & jnp.all(okv)
        small = acc & ((c0 - c1) <= tol * c0)
        return dict(R=jnp.where(acc, Rn, R), t=jnp.where(acc, tn, t), X=jnp.where(acc, Xn, X),
                    cost=jnp.where(acc, c1, c0), lam=jnp.where(acc, lam * 0.3, lam * 5.0), it=s["it"] + 1,
                    done=small | (lam > 1e10))

    s0 = dict(R=R, t=t, X=X, cost=cost_of(R, t, X), lam=jnp.asarray(1e-4, dt_), it=jnp.asarray(0),
              done=jnp.asarray(False))
    s = jax.lax.while_loop(lambda s: (~s["done"]) & (s["it"] < max_iter), body, s0)
    r = _residuals(K, s["R"], s["t"], s["X"], ci, pi, uv)
    on = wo > 0
    rms = jnp.sqrt(jnp.sum(jnp.where(on, jnp.sum(r * r, -1), 0.0)) / jnp.maximum(jnp.sum(on), 1))
    return s["R"], s["t"], s["X"], rms, s["it"]
