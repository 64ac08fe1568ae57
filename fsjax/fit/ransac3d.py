"""RANSAC for 3-D primitives: plane, sphere, line, cylinder.

Every hypothesis is drawn from a ``key`` (minimal samples of distinct valid
points, Gumbel top-k), all of them are scored in ONE ``vmap`` (inlier count:
valid points within ``threshold`` orthogonal distance), the best one (most
inliers; ties to the lowest hypothesis index) is refitted by least squares on
its inliers, and the inlier set is re-derived from the refitted model
(``rounds`` times, default 3). The result is a :class:`RansacResult` record.

Models, parameters and residuals (orthogonal distance, in the unit of ``xyz``):

* ``"plane"``: ``(nx, ny, nz, d)``, unit ``n``, ``n . x = d``; sample 3 points;
  refit: total least squares (PCA), closed form.
* ``"line"``: ``(px, py, pz, dx, dy, dz)``, ``p`` the inlier centroid, unit
  ``d``; sample 2 points; refit: PCA, closed form.
* ``"sphere"``: ``(cx, cy, cz, r)``; sample 4 non-coplanar points (linear
  solve); refit: algebraic fit, then geometric Levenberg-Marquardt
  (``optimistix``) on ``|x - c| - r``.
* ``"cylinder"``: ``(cx, cy, cz, ax, ay, az, r)``, unit axis ``a``, ``c`` the
  axis point closest to the origin; sample 2 points with normals (the
  input's ``normals``, else PCA normals from 12 neighbours); refit: geometric
  Levenberg-Marquardt (``optimistix``) on the radial distance minus ``r``.

Unit vectors are sign-canonical (their largest-magnitude component is
positive), so results are deterministic under a key.

Failing closed: ``converged`` is False and ``params`` NaN when there are
fewer valid points than a sample needs, when a valid point has a non-finite
coordinate, when every sample was degenerate (collinear points for a plane,
coplanar for a sphere, parallel normals for a cylinder), when the refitted
inlier set is degenerate (a plane's inliers must spread more than
``threshold`` across two directions, a line's along one), when a sphere's or
cylinder's inliers all lie within ``threshold`` of one plane (the data do not
resolve any curvature: a huge radius would fit a flat patch), when the points do not
thin out beyond the threshold (more than ``max_shell_ratio`` of the inlier count in the
shell ``threshold < d <= 2 threshold``: a plane, sphere or cylinder cut through two
blobs of points took 28 % of them as "inliers"), when the consensus
is below ``min_inlier_fraction`` of the valid points (the usual symptom of
too many outliers for the hypothesis count), or when the nonlinear refit did
not converge. ``reason`` gives the code of :data:`fsjax.types.RESULTS` (``too_few``,
``invalid_input``, ``degenerate``, ``unsupported_model``, ``poor_fit``, ``max_iterations``;
``result.message`` eagerly). ``raw_params`` keeps the refitted
parameters before this gate, for diagnostics only.

Hypothesis count: with inlier ratio ``w`` and sample size ``s``, ``H``
hypotheses miss every all-inlier sample with probability ``(1 - w^s)^H``
(Fischler & Bolles 1981); ``n_hypotheses`` is static and fixed, so this is
the breakdown the tests pin.
"""

from __future__ import annotations

import functools
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx
from jax import lax
from jaxtyping import Array, Bool, Float, Int

from .._checks import check_choice, check_positive, check_range, check_static_int, is_concrete
from .._linalg import levenberg_marquardt
from ..ops import estimate_normals
from ..types import NamedParams, Points
from ..types.results import FitResult, Legacy, deprecated_name, renamed
from ._cloud import as_cloud

__all__ = ["RansacResult", "MODELS", "ransac", "ransac_plane", "ransac_sphere", "ransac_line",
           "ransac_cylinder"]

#: the old RANSAC codes 0..6 (deprecated ``legacy_reason`` and ``REASONS``)
_LEGACY = Legacy(("ok", "too_few", "invalid_input", "degenerate", "poor_fit", "max_iterations",
                  "unsupported_model"))


def __getattr__(name):
    if name == "REASONS":
        deprecated_name("fsjax.fit.ransac3d.REASONS", "fsjax.types.RESULTS (reason_message)")
        return _LEGACY.table()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


MODELS = {
    "plane": (("nx", "ny", "nz", "d"), 3),
    "line": (("px", "py", "pz", "dx", "dy", "dz"), 2),
    "sphere": (("cx", "cy", "cz", "r"), 4),
    "cylinder": (("cx", "cy", "cz", "ax", "ay", "az", "r"), 2),
}


class RansacResult(NamedParams, FitResult):
    """Result record of a 3-D RANSAC fit.

    ``params`` (NaN unless ``converged``), ``inliers`` ``(N,)`` mask (all
    False unless ``converged``), ``n_inliers`` and ``inlier_fraction`` (of the
    valid points; the consensus of the final model even when rejected), ``rms_len`` of the
    orthogonal residuals over the inliers (input length unit; was ``rms``), ``converged``,
    ``reason`` (code of :data:`fsjax.types.RESULTS`), ``hypothesis_inliers`` (consensus of the best hypothesis
    before the refit), ``iterations`` (solver steps of the last refit),
    ``raw_params`` (before the acceptance gate; diagnostics only).
    """

    params: Float[Array, "*batch P"]
    raw_params: Float[Array, "*batch P"]
    inliers: Bool[Array, "*batch N"]
    n_inliers: Int[Array, "*batch"]
    inlier_fraction: Float[Array, "*batch"]
    rms_len: Float[Array, "*batch"]
    converged: Bool[Array, "*batch"]
    reason: Int[Array, "*batch"]
    hypothesis_inliers: Int[Array, "*batch"]
    iterations: Int[Array, "*batch"]
    kind: str = eqx.field(static=True, default="")
    names: tuple[str, ...] = eqx.field(static=True, default=())
    residual_name = "rms_len"

    rms = renamed("rms_len")
    legacy_reason = _LEGACY.property()

    def reason_text(self) -> str:
        """Deprecated: the reason as text; use ``message``."""
        deprecated_name("RansacResult.reason_text()", "RansacResult.message")
        return self.message


# ---------------------------------------------------------------------------
# small geometry helpers
# ---------------------------------------------------------------------------


def _canon(v):
    """Sign-canonical unit vector: largest-magnitude component positive."""
    i = jnp.argmax(jnp.abs(v), axis=-1)
    s = jnp.take_along_axis(v, i[..., None], axis=-1)
    return jnp.where(s < 0, -v, v)


def _unit(v):
    n2 = jnp.sum(v * v, axis=-1, keepdims=True)
    ok = n2 > 0
    return jnp.where(ok, v / jnp.sqrt(jnp.where(ok, n2, 1.0)), 0.0), ok[..., 0]


def _safe_norm(v, axis=-1):
    n2 = jnp.sum(v * v, axis=axis)
    ok = n2 > 0
    return jnp.where(ok, jnp.sqrt(jnp.where(ok, n2, 1.0)), 0.0)


def _weighted_pca(xyz, w):
    ws = jnp.maximum(jnp.sum(w), 1e-300)
    c = jnp.sum(xyz * w[:, None], axis=0) / ws
    d = (xyz - c) * jnp.sqrt(w)[:, None]
    evals, evecs = jnp.linalg.eigh(d.T @ d / ws)
    return c, jnp.maximum(evals, 0.0), evecs


def _perp_basis(a):
    """Two unit vectors completing ``a`` to an orthonormal frame."""
    t = jnp.where(jnp.abs(a[0]) < 0.9, jnp.array([1.0, 0.0, 0.0], a.dtype), jnp.array([0.0, 1.0, 0.0], a.dtype))
    e1, _ = _unit(jnp.cross(a, t))
    return e1, jnp.cross(a, e1)


def _tols(dtype):
    return (1e-10, 1e-12) if dtype == jnp.float64 else (1e-5, 1e-6)


# ---------------------------------------------------------------------------
# models: hypothesis from a minimal sample, distance, refit
# ---------------------------------------------------------------------------


def _plane_hyp(p, nrm, thr):
    a, b, c = p[0], p[1], p[2]
    n = jnp.cross(b - a, c - a)
    den = _safe_norm(b - a) * _safe_norm(c - a)
    ok = _safe_norm(n) > 1e-9 * den
    n, _ = _unit(n)
    n = _canon(n)
    return jnp.concatenate([n, jnp.dot(n, a)[None]]), ok


def _plane_dist(q, xyz):
    return jnp.abs(xyz @ q[:3] - q[3])


def _plane_refit(q, xyz, w, thr, max_steps):
    c, ev, evecs = _weighted_pca(xyz, w)
    n = _canon(evecs[:, 0])
    ok = jnp.sqrt(ev[1]) > thr  # inliers must spread across two directions
    return jnp.concatenate([n, jnp.dot(n, c)[None]]), ok, jnp.asarray(0, jnp.int32)


def _line_hyp(p, nrm, thr):
    d, ok = _unit(p[1] - p[0])
    return jnp.concatenate([p[0], _canon(d)]), ok


def _line_dist(q, xyz):
    return _safe_norm(jnp.cross(xyz - q[:3], q[3:6]))


def _line_refit(q, xyz, w, thr, max_steps):
    c, ev, evecs = _weighted_pca(xyz, w)
    ok = jnp.sqrt(ev[2]) > thr
    return jnp.concatenate([c, _canon(evecs[:, 2])]), ok, jnp.asarray(0, jnp.int32)


def _sphere_hyp(p, nrm, thr):
    A = 2.0 * (p[1:] - p[0])
    b = jnp.sum(p[1:] ** 2, axis=1) - jnp.sum(p[0] ** 2)
    scale = jnp.prod(_safe_norm(A))
    det = jnp.linalg.det(A)
    ok = jnp.abs(det) > 1e-9 * scale
    c = jnp.linalg.solve(jnp.where(ok, A, jnp.eye(3, dtype=p.dtype)), jnp.where(ok, b, 0.0))
    return jnp.concatenate([c, _safe_norm(p[0] - c)[None]]), ok


def _sphere_dist(q, xyz):
    return jnp.abs(_safe_norm(xyz - q[:3]) - q[3])


def _sphere_resid(y, args):
    xyz, w = args
    return jnp.sqrt(w) * (_safe_norm(xyz - y[:3]) - y[3])


def _sphere_refit(q, xyz, w, thr, max_steps):
    # algebraic start |x|^2 = 2 c.x + (r^2 - |c|^2), weighted, in centred coordinates
    ws = jnp.maximum(jnp.sum(w), 1e-300)
    m = jnp.sum(xyz * w[:, None], axis=0) / ws
    x = xyz - m
    A = jnp.concatenate([2 * x, jnp.ones_like(x[:, :1])], axis=1) * jnp.sqrt(w)[:, None]
    b = jnp.sum(x * x, axis=1) * jnp.sqrt(w)
    ata = A.T @ A
    ok0 = jnp.linalg.eigvalsh(ata)[0] > 1e-12 * jnp.maximum(jnp.trace(ata), 1e-300)
    s = jnp.linalg.solve(jnp.where(ok0, ata, jnp.eye(4, dtype=x.dtype)), A.T @ b)
    r2 = s[3] + jnp.sum(s[:3] ** 2)
    y0 = jnp.concatenate([s[:3] + m, jnp.sqrt(jnp.maximum(r2, 0.0))[None]])
    y0 = jnp.where(ok0 & (r2 > 0), y0, q)
    rtol, atol = _tols(xyz.dtype)
    sol = optx.least_squares(_sphere_resid, levenberg_marquardt(rtol, atol), y0, args=(xyz, w),
                             max_steps=max_steps, throw=False)
    y = sol.value
    ok = (sol.result == optx.RESULTS.successful) & jnp.all(jnp.isfinite(y))
    y = y.at[3].set(jnp.abs(y[3]))
    return y, ok, jnp.asarray(sol.stats["num_steps"], jnp.int32)


def _cyl_canon(c, a, r):
    a = _canon(a)
    c = c - jnp.dot(c, a) * a
    return jnp.concatenate([c, a, jnp.abs(r)[None]])


def _cyl_hyp(p, nrm, thr):
    n1, n2 = nrm[0], nrm[1]
    ax = jnp.cross(n1, n2)
    ok = (_safe_norm(ax) > 1e-3) & jnp.all(jnp.isfinite(nrm))
    a, _ = _unit(ax)
    # closest approach of the two normal lines p_i + t_i n_i in the plane normal to a
    M = jnp.stack([n1, -n2], axis=1)
    rhs = p[1] - p[0]
    mtm = M.T @ M
    t = jnp.linalg.solve(jnp.where(ok, mtm, jnp.eye(2, dtype=p.dtype)), M.T @ rhs)
    c = 0.5 * ((p[0] + t[0] * n1) + (p[1] + t[1] * n2))
    r = 0.5 * (jnp.abs(t[0]) + jnp.abs(t[1]))
    return _cyl_canon(c, a, r), ok


def _cyl_dist(q, xyz):
    d = xyz - q[:3]
    a = q[3:6]
    radial = d - (d @ a)[:, None] * a
    return jnp.abs(_safe_norm(radial) - q[6])


def _cyl_resid(y, args):
    xyz, w, c0, e1, e2, a0 = args
    a, _ = _unit(a0 + y[0] * e1 + y[1] * e2)
    c = c0 + y[2] * e1 + y[3] * e2
    d = xyz - c
    radial = d - (d @ a)[:, None] * a
    return jnp.sqrt(w) * (_safe_norm(radial) - y[4])


def _cyl_refit(q, xyz, w, thr, max_steps):
    c0, a0, r0 = q[:3], q[3:6], q[6]
    e1, e2 = _perp_basis(a0)
    y0 = jnp.array([0.0, 0.0, 0.0, 0.0, 1.0], xyz.dtype) * r0
    rtol, atol = _tols(xyz.dtype)
    sol = optx.least_squares(_cyl_resid, levenberg_marquardt(rtol, atol), y0,
                             args=(xyz, w, c0, e1, e2, a0), max_steps=max_steps, throw=False)
    y = sol.value
    a, oka = _unit(a0 + y[0] * e1 + y[1] * e2)
    c = c0 + y[2] * e1 + y[3] * e2
    ok = (sol.result == optx.RESULTS.successful) & oka & jnp.all(jnp.isfinite(y))
    return _cyl_canon(c, a, y[4]), ok, jnp.asarray(sol.stats["num_steps"], jnp.int32)


_IMPL = {
    "plane": (_plane_hyp, _plane_dist, _plane_refit),
    "line": (_line_hyp, _line_dist, _line_refit),
    "sphere": (_sphere_hyp, _sphere_dist, _sphere_refit),
    "cylinder": (_cyl_hyp, _cyl_dist, _cyl_refit),
}


# ---------------------------------------------------------------------------
# the RANSAC driver
# ---------------------------------------------------------------------------


@functools.partial(jax.jit, static_argnames=("model", "n_hyp", "max_steps", "rounds"))
def _core(key, xyz, valid, normals, thr, min_frac, max_shell, plane_share, *, model, n_hyp, max_steps, rounds):
    hyp, dist, refit = _IMPL[model]
    names, s = MODELS[model]
    dt = xyz.dtype
    n = xyz.shape[0]
    finite = jnp.all(jnp.isfinite(xyz), axis=-1)
    bad_coord = jnp.any(valid & ~finite)
    valid = valid & finite
    x = jnp.where(valid[:, None], xyz, 0.0)
    nv = jnp.sum(valid)
    enough = nv >= s
    if normals is None:
        nrm = jnp.zeros_like(x)
    else:
        nrm = jnp.where(valid[:, None] & jnp.all(jnp.isfinite(normals), -1, keepdims=True), normals, 0.0)

    # minimal samples: s distinct valid indices per hypothesis (Gumbel top-k)
    g = jax.random.gumbel(key, (n_hyp, n), dtype=dt)
    g = jnp.where(valid[None, :], g, -jnp.inf)
    _, idx = lax.top_k(g, min(s, n))
    if idx.shape[1] < s:
        idx = jnp.pad(idx, ((0, 0), (0, s - idx.shape[1])))
    samp_ok = jnp.all(valid[idx], axis=1)
    params, hok = jax.vmap(lambda i: hyp(x[i], nrm[i], thr))(idx)
    hok = hok & samp_ok & jnp.all(jnp.isfinite(params), axis=1)
    # score every hypothesis in one vmap
    d = jax.vmap(lambda q: dist(q, x))(params)
    cnt = jnp.sum((d <= thr) & valid[None, :], axis=1)
    cnt = jnp.where(hok, cnt, -1)
    best = jnp.argmax(cnt)
    q = params[best]
    any_ok = cnt[best] >= 0
    inl = (dist(q, x) <= thr) & valid

    def round_(_, carry):  # one compiled refit, looped (not unrolled)
        q, inl, _, _ = carry
        q_new, ok_r, steps = refit(q, x, inl.astype(dt), thr, max_steps)
        q = jnp.where(ok_r, q_new, q)
        return q, (dist(q, x) <= thr) & valid, ok_r, steps

    q, inl, ok_refit, steps = lax.fori_loop(0, rounds, round_,
                                            (q, inl, jnp.asarray(True), jnp.asarray(0, jnp.int32)))
    n_in = jnp.sum(inl)
    frac = n_in / jnp.maximum(nv, 1).astype(dt)
    r = dist(q, x)
    rms = jnp.sqrt(jnp.sum(jnp.where(inl, r * r, 0.0)) / jnp.maximum(n_in, 1).astype(dt))
    low = frac < min_frac
    if model in ("sphere", "cylinder"):
        # a curved model the data does not support: when the inliers lie within the threshold
        # of one plane, a sphere or cylinder of any large radius explains them (a plane gave
        # radius 143 for a 2-unit patch), so refuse it. "One plane" is robust: the inliers'
        # total-least-squares plane refitted on its own in-threshold points must hold at least
        # plane_share of them (a plane patch and 5 points of a second plane, 216 + 5 inliers,
        # gave a converged "sphere" of radius 8.3 under the all-inliers rule). A true sphere's
        # inliers put thr / r of themselves near any plane (3 % at r = 0.35, thr = 0.012)
        c0, _, ev0 = _weighted_pca(x, inl.astype(dt))
        near = inl & (jnp.abs((x - c0) @ ev0[:, 0]) <= thr)
        c1, _, ev1 = _weighted_pca(x, near.astype(dt))
        on_plane = jnp.sum(inl & (jnp.abs((x - c1) @ ev1[:, 0]) <= thr))
        flat = (n_in >= 3) & (on_plane >= plane_share * n_in.astype(dt))
    else:
        flat = jnp.asarray(False)
    # a surface (or line) thins out beyond the threshold; a slice through a volume of points
    # does not: as many points lie in the shell thr < d <= 2 thr as within thr (two blobs
    # gave an accepted plane, sphere and cylinder with 28 % "inliers"), so refuse the model
    shell = jnp.sum((r > thr) & (r <= 2 * thr) & valid)
    thick = shell > max_shell * n_in.astype(dt)
    reason = jnp.select(
        [~enough, bad_coord, ~any_ok, low, ~ok_refit, flat | thick],
        [1, 2, 3, 4, 5, 6], 0).astype(jnp.int32)
    # a degenerate refitted set (plane/line) is a degeneracy, not a solver failure
    if model in ("plane", "line"):
        reason = jnp.where((reason == 5), 3, reason)
    conv = reason == 0
    reason = _LEGACY.new(reason).astype(jnp.int32)
    return RansacResult(
        params=jnp.where(conv, q, jnp.nan), raw_params=q, inliers=inl & conv,
        n_inliers=n_in.astype(jnp.int32), inlier_fraction=frac, rms_len=jnp.where(n_in > 0, rms, jnp.nan),
        converged=conv, reason=reason, hypothesis_inliers=jnp.maximum(cnt[best], 0).astype(jnp.int32),
        iterations=steps, kind=model, names=names)


@jax.jit
def _pca_normals(xyz, v):
    """PCA normals of 12 neighbours (:func:`fsjax.ops.estimate_normals`; the sign is irrelevant here)."""
    vv = v & jnp.all(jnp.isfinite(xyz), axis=-1)
    x0 = jnp.where(vv[:, None], xyz, 0.0)
    return estimate_normals(Points(x0, valid=vv), k=12).normals


def ransac(key, points, model: str = "plane", *, threshold: float = 0.01, n_hypotheses: int = 256,
           min_inlier_fraction: float = 0.15, valid=None, normals=None, max_steps: int = 100,
           rounds: int = 3, max_shell_ratio: float = 0.5, max_plane_share: float = 0.8) -> RansacResult:
    """RANSAC fit of a plane, line, sphere or cylinder to a 3-D point set.

    Args:
      key: ``jax.random`` key; the result is a deterministic function of it.
      points: a :class:`fsjax.Points` or an ``(N, 3)`` array (then ``valid``
        ``(N,)`` optional).
      model: ``"plane"``, ``"line"``, ``"sphere"`` or ``"cylinder"`` (static).
      threshold: inlier distance (orthogonal residual) in the unit of ``xyz``
        (may be traced).
      n_hypotheses: number of minimal samples, all scored in one ``vmap``
        (static int).
      min_inlier_fraction: the smallest consensus (fraction of valid points)
        accepted as a fit (default 0.15); below it the result says
        ``converged=False``. A wrong model found when every sample was
        contaminated gathers a few per cent of chance inliers, so this gate
        is what turns a missed model into a reported failure (the breakdown
        test pins it: no accepted plane with a normal error > 1 deg).
      normals: ``(N, 3)`` normals for the cylinder's 2-point samples (default:
        the cloud's, else PCA normals from 12 neighbours).
      max_steps: Levenberg-Marquardt step cap of the nonlinear refits.
      rounds: refit / re-derive inliers rounds (static, default 3).
      max_shell_ratio: the model is refused (``unsupported_model``) when more than this
        fraction of its inlier count lies in the shell ``threshold < d <= 2 threshold``
        (default 0.5): the points do not thin out beyond the threshold, so the "inliers"
        are a slice through a volume of points, not a surface or line. Gaussian noise of
        sigma = threshold gives 0.40, sigma = threshold / 2 0.05; a uniform volume ~1
        (module notes). ``inf`` disables the test.
      max_plane_share: a sphere or cylinder is refused (``unsupported_model``) when at least
        this fraction of its inliers lie within ``threshold`` of one plane (the inliers' plane,
        refitted on its own in-threshold points): the data do not resolve the curvature, and a
        large radius explains a flat patch (a floor patch and 5 points of a wall gave a "sphere"
        of radius 8.3). A true sphere puts about ``threshold / r`` of its inliers near any plane.
        A value above 1 disables the test; plane and line models ignore it.

    Returns:
      :class:`RansacResult` (``kind`` = model, ``names`` its parameters).

    Example:
      >>> import jax, jax.numpy as jnp, numpy as np
      >>> from fsjax.fit import ransac
      >>> g = np.random.default_rng(0).uniform(-1, 1, (200, 2))
      >>> xyz = np.c_[g, 0.3 + 0.0 * g[:, 0]]
      >>> res = ransac(jax.random.PRNGKey(0), jnp.asarray(xyz), "plane", threshold=0.01)
      >>> bool(res.converged), round(abs(float(res["nz"])), 6), round(abs(float(res["d"])), 6)
      (True, 1.0, 0.3)
    """
    fn = "ransac"
    check_choice(fn, "model", model, tuple(MODELS))
    n_hypotheses = check_static_int(fn, "n_hypotheses", n_hypotheses, lo=1)
    check_positive(fn, "threshold", threshold)
    check_range(fn, "min_inlier_fraction", min_inlier_fraction, 0.0, 1.0)
    if is_concrete(max_shell_ratio) and not float(max_shell_ratio) > 0:  # inf allowed: no test
        raise ValueError(f"{fn}: argument 'max_shell_ratio' must be a positive number (inf: no test); "
                         f"got {max_shell_ratio!r}")
    xyz, v, nrm = as_cloud(fn, "points", points, valid, normals)
    if model == "cylinder" and nrm is None:
        nrm = _pca_normals(xyz, v)
    dt = xyz.dtype
    if is_concrete(max_plane_share) and not float(max_plane_share) > 0:
        raise ValueError(f"{fn}: argument 'max_plane_share' must be a positive number (above 1: no test); "
                         f"got {max_plane_share!r}")
    return _core(key, xyz, v, nrm, jnp.asarray(threshold, dt), jnp.asarray(min_inlier_fraction, dt),
                 jnp.asarray(max_shell_ratio, dt), jnp.asarray(max_plane_share, dt), model=model, n_hyp=int(n_hypotheses), max_steps=int(max_steps), rounds=int(rounds))


def ransac_plane(key, points, **kw: Any) -> RansacResult:
    """RANSAC plane ``n . x = d`` (see :func:`ransac`)."""
    return ransac(key, points, "plane", **kw)


def ransac_line(key, points, **kw: Any) -> RansacResult:
    """RANSAC 3-D line through ``p`` along ``d`` (see :func:`ransac`)."""
    return ransac(key, points, "line", **kw)


def ransac_sphere(key, points, **kw: Any) -> RansacResult:
    """RANSAC sphere, centre ``c`` and radius ``r`` (see :func:`ransac`)."""
    return ransac(key, points, "sphere", **kw)


def ransac_cylinder(key, points, **kw: Any) -> RansacResult:
    """RANSAC cylinder, axis point ``c``, unit axis ``a``, radius ``r`` (see :func:`ransac`)."""
    return ransac(key, points, "cylinder", **kw)
