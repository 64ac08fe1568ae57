"""3-D metrology primitives (closed form) and model selection among surfaces.

Representations (all lengths in the unit of the input, angles in degrees):

* plane ``(nx, ny, nz, d)``: unit normal ``n`` (sign-canonical: largest
  component positive), points ``x`` with ``n . x = d``;
* line ``(px, py, pz, dx, dy, dz)``: a point ``p`` (the centroid for fits)
  and a unit direction ``d`` (sign-canonical);
* sphere ``(cx, cy, cz, r)``; 3-D circle ``(cx, cy, cz, nx, ny, nz, r)``;
  cylinder ``(cx, cy, cz, ax, ay, az, r)`` with ``c`` the axis point closest to
  the origin; quadric: a second-order height patch over the points' PCA
  plane (see :func:`fit_quadric` for why not the general implicit quadric).

Everything is written in ``jax.numpy`` (jittable, ``vmap``-able) and
validated in float64. Distances and angles are closed form; fits of line,
plane (total least squares) are closed form; sphere, circle and cylinder
start from an algebraic fit and are refined on the geometric residual with
``optimistix.LevenbergMarquardt``. Every fit returns a :class:`Fit3D` record
with the per-point orthogonal residuals. Degenerate input (too few points,
collinear points for a plane, coplanar ones for a sphere, parallel elements
for an intersection) fails closed: ``converged``/``ok`` False and NaN.

Model selection (:func:`select_model`): plane, sphere, cylinder and general
quadric are fitted to the same points and compared by AIC and BIC under the
noise model *independent Gaussian orthogonal residuals of unknown variance*
(profiled out): ``-2 log L = n log(RSS / n) + const``,
``AIC = n log(RSS/n) + 2 k``, ``BIC = n log(RSS/n) + k log n`` with ``k`` the
free shape parameters: plane 3, sphere 4, cylinder 5, quadric patch 6 (the common
variance parameter adds the same 1 to each and is left out). The choice is
the minimum of the criterion (BIC by default: it is consistent, so a model is
not more complex than the data supports as ``n`` grows; AIC over-selects a
nested larger model with probability about ``P(chi2_1 > 2) = 16 %``). The
quadric patch's residual is its first-order orthogonal distance. The criteria only
rank the candidates; a candidate is chosen only if its residuals are consistent with the
noise (``noise`` given, a chi-square bound) or small beside the points' spread
(``max_rel_rms``), so points that no candidate explains (a random blob, a torus) give
``valid`` False and ``choice`` -1 rather than the least bad model.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx
from jaxtyping import Array, Bool, Float, Int

from .._checks import check_positive
from .._linalg import (
    SmallQR,
    eigh_small,
    jit_fast_compile,
    levenberg_marquardt,
    solve_small,
    solve_spd_eig,
)
from ..types import NamedParams
from ..types.results import FitResult, deprecated_name, reason_code, renamed

__all__ = [
    "Fit3D", "ModelSelection", "MODEL_PARAMS", "fit_plane", "fit_line3d", "fit_sphere", "fit_circle3d",
    "fit_cylinder", "fit_quadric", "select_model", "point_plane_distance", "point_line_distance",
    "line_line_distance", "angle_lines", "angle_planes", "angle_line_plane", "intersect_line_plane",
    "intersect_planes",
]


class Fit3D(NamedParams, FitResult):
    """Result record of a 3-D primitive fit.

    ``params`` (NaN when not ``converged``; ``fit["r"]`` reads one by name), ``residuals``
    ``(N,)`` orthogonal distances (NaN for invalid points), ``rss`` and ``rms_len`` over the
    valid points (input length unit; was ``rms``), ``n_used``, ``iterations`` (solver steps; 0
    for closed forms), ``converged`` (False for degenerate input or a failed solve) and
    ``reason`` (code of :data:`fsjax.types.RESULTS`: ``ok``, ``too_few``, ``degenerate`` or
    ``max_iterations`` when the Levenberg-Marquardt refinement did not converge).
    """

    params: Float[Array, "*batch P"]
    residuals: Float[Array, "*batch N"]
    rss: Float[Array, "*batch"]
    rms_len: Float[Array, "*batch"]
    n_used: Int[Array, "*batch"]
    iterations: Int[Array, "*batch"]
    converged: Bool[Array, "*batch"]
    reason: Int[Array, "*batch"]
    kind: str = eqx.field(static=True, default="")
    names: tuple[str, ...] = eqx.field(static=True, default=())
    residual_name = "rms_len"

    rms = renamed("rms_len")


MODEL_PARAMS = {"plane": 3, "sphere": 4, "cylinder": 5, "quadric": 6}


# ---------------------------------------------------------------------------
# helpers
# ---------------------------------------------------------------------------


def _nrm(v, axis=-1):
    n2 = jnp.sum(v * v, axis=axis)
    ok = n2 > 0
    return jnp.where(ok, jnp.sqrt(jnp.where(ok, n2, 1.0)), 0.0)


def _unit(v):
    n = _nrm(v)[..., None]
    ok = n > 0
    return jnp.where(ok, v / jnp.where(ok, n, 1.0), jnp.nan)


def _canon(v):
    i = jnp.argmax(jnp.abs(v), axis=-1)
    s = jnp.take_along_axis(v, i[..., None], axis=-1)
    return jnp.where(s < 0, -v, v)


def _prep(xyz, valid, fn: str = "fit"):
    xyz = jnp.asarray(xyz)
    if xyz.ndim != 2 or xyz.shape[-1] != 3:
        raise ValueError(f"{fn}: argument 'xyz' must have shape (N, 3), got {tuple(xyz.shape)}")
    v = jnp.ones(xyz.shape[0], bool) if valid is None else jnp.asarray(valid, bool)
    v = v & jnp.all(jnp.isfinite(xyz), axis=-1)
    return jnp.where(v[:, None], xyz, 0.0), v


def _pca(x, v):
    w = v.astype(x.dtype)
    n = jnp.maximum(jnp.sum(w), 1.0)
    c = jnp.sum(x * w[:, None], 0) / n
    d = (x - c) * w[:, None]
    ev, evec = eigh_small(d.T @ d / n)
    return c, jnp.maximum(ev, 0.0), evec


def _spread_ok(x, v, ev_small, ev_big):
    """Traced bool: a principal variance ``ev_small`` is resolved, not rounding.

    Relative to the largest (``> max(1e-12, 32 eps) ev_big``: the eigen-solver's own
    error is ~``eps ev_big``) and above the floor that rounding the coordinates leaves: centring points at distance ``R`` from the origin in a dtype with
    machine epsilon ``eps`` scatters them by ~``eps R``; the axis must spread more than
    ``32 eps R`` (measured: collinear float32 points at R = 1e4 give a second axis of
    ~``8 eps R``). So collinear points in float32 fail closed as they do in float64,
    whatever the units.
    """
    eps = float(jnp.finfo(x.dtype).eps)
    R = jnp.max(jnp.where(v[:, None], jnp.abs(x), 0.0))
    return (ev_small > max(1e-12, 32 * eps) * ev_big) & (ev_small > (32 * eps * R) ** 2)


_NEED = {"plane": 3, "line": 2, "sphere": 4, "circle3d": 3, "cylinder": 5, "quadric": 6}


def _finish(kind, names, params, res, v, ok, steps=0, solved=True, supported=True):
    """The :class:`Fit3D` record; ``solved`` False = the iterative refinement did not converge;
    ``supported`` False = the data do not resolve the model (reason ``unsupported_model``)."""
    r = jnp.where(v, res, jnp.nan)
    n = jnp.sum(v)
    rss = jnp.sum(jnp.where(v, res * res, 0.0))
    ok = ok & jnp.all(jnp.isfinite(params)) & jnp.isfinite(rss)
    reason = jnp.where(ok & supported, reason_code("ok"), jnp.where(
        n < _NEED[kind], reason_code("too_few"),
        jnp.where(~ok, jnp.where(solved, reason_code("degenerate"), reason_code("max_iterations")),
                  reason_code("unsupported_model"))))
    ok = ok & supported
    return Fit3D(params=jnp.where(ok, params, jnp.nan), residuals=jnp.where(ok, r, jnp.nan),
                 rss=jnp.where(ok, rss, jnp.nan), rms_len=jnp.where(ok, jnp.sqrt(rss / jnp.maximum(n, 1)), jnp.nan),
                 n_used=n.astype(jnp.int32), iterations=jnp.asarray(steps, jnp.int32), converged=ok,
                 reason=reason.astype(jnp.int32), kind=kind, names=names)


def _tols(dt):
    return (1e-10, 1e-12) if dt == jnp.float64 else (1e-5, 1e-6)


def _lm(fn, y0, args, max_steps):
    rtol, atol = _tols(y0.dtype)
    sol = optx.least_squares(fn, levenberg_marquardt(rtol, atol, linear_solver=SmallQR()), y0, args=args,
                             max_steps=max_steps, throw=False)
    return sol.value, sol.result == optx.RESULTS.successful, sol.stats["num_steps"]


# ---------------------------------------------------------------------------
# closed-form fits
# ---------------------------------------------------------------------------


@jit_fast_compile
def fit_plane(xyz, valid=None) -> Fit3D:
    """Total-least-squares plane ``n . x = d`` (PCA: ``n`` = smallest-eigenvalue eigenvector).

    Minimises the sum of squared orthogonal distances (closed form). Fails
    closed (``converged`` False) for fewer than 3 valid points or collinear
    ones (second eigenvalue below ``max(1e-12, 32 eps)`` of the largest, or its spread
    below ``32 eps`` times the points' distance from the origin: rounding, in any dtype).

    Example:
      >>> import jax.numpy as jnp
      >>> from fsjax.fit import fit_plane
      >>> f = fit_plane(jnp.array([[0.0, 0, 2], [1, 0, 2], [0, 1, 2], [1, 1, 2]]))
      >>> [round(float(v), 6) for v in f.params]
      [0.0, 0.0, 1.0, 2.0]
    """
    x, v = _prep(xyz, valid, "fit_plane")
    c, ev, evec = _pca(x, v)
    n = _canon(evec[:, 0])
    ok = (jnp.sum(v) >= 3) & _spread_ok(x, v, ev[1], ev[2]) & (ev[2] > 0)
    p = jnp.concatenate([n, jnp.dot(n, c)[None]])
    return _finish("plane", ("nx", "ny", "nz", "d"), p + 0.0, x @ n - p[3], v, ok)


@jit_fast_compile
def fit_line3d(xyz, valid=None) -> Fit3D:
    """Total-least-squares 3-D line through the centroid along the largest principal axis.

    Residuals are orthogonal distances; fails closed for fewer than 2 distinct
    valid points. (Was ``fsjax.fit.fit_line``; the 2-D contour fit is :func:`fsjax.ops.fit_line`.)

    Example:
      >>> import jax.numpy as jnp
      >>> from fsjax.fit import fit_line3d
      >>> f = fit_line3d(jnp.array([[0.0, 0, 0], [1, 2, 2], [2, 4, 4]]))
      >>> [round(float(v), 6) for v in f.params[3:]]
      [0.333333, 0.666667, 0.666667]
    """
    x, v = _prep(xyz, valid, "fit_line3d")
    c, ev, evec = _pca(x, v)
    d = _canon(evec[:, 2])
    ok = (jnp.sum(v) >= 2) & (ev[2] > 0)
    return _finish("line", ("px", "py", "pz", "dx", "dy", "dz"), jnp.concatenate([c, d]),
                   _nrm(jnp.cross(x - c, d)), v, ok)


# ---------------------------------------------------------------------------
# nonlinear fits
# ---------------------------------------------------------------------------


def _sphere_alg(x, v):
    w = v.astype(x.dtype)
    n = jnp.maximum(jnp.sum(w), 1.0)
    m = jnp.sum(x * w[:, None], 0) / n
    y = (x - m) * w[:, None]
    s = jnp.sqrt(jnp.sum(y * y) / n)
    s = jnp.where(s > 0, s, 1.0)
    y = y / s
    A = jnp.concatenate([2 * y, w[:, None]], 1)
    b = jnp.sum(y * y, 1)
    ata = A.T @ A
    ev, evec = eigh_small(ata)
    ok = ev[0] > 1e-10 * ev[3]
    sol = solve_spd_eig(jnp.where(ok, ev, 1.0), evec, A.T @ b)
    r2 = sol[3] + jnp.sum(sol[:3] ** 2)
    ok = ok & (r2 > 0)
    return jnp.concatenate([m + s * sol[:3], (s * jnp.sqrt(jnp.where(r2 > 0, r2, 1.0)))[None]]), ok


def _sphere_res(y, args):
    x, w = args
    return w * (_nrm(x - y[:3]) - y[3])


@jit_fast_compile(static_argnames=("max_steps",))
def fit_sphere(xyz, valid=None, *, max_steps: int = 100) -> Fit3D:
    """Sphere: algebraic (Kasa-style) start, then geometric Levenberg-Marquardt on ``|x - c| - r``.

    Fails closed for fewer than 4 valid points or coplanar ones.

    Example:
      >>> import jax.numpy as jnp
      >>> from fsjax.fit import fit_sphere
      >>> pts = jnp.array([[3.0, 0, 0], [1, 2, 0], [1, 0, 2], [-1, 0, 0], [1, -2, 0], [1, 0, -2]])
      >>> [round(float(v), 6) for v in fit_sphere(pts).params]
      [1.0, 0.0, 0.0, 2.0]
    """
    x, v = _prep(xyz, valid, "fit_sphere")
    y0, ok = _sphere_alg(x, v)
    y0 = jnp.where(ok, y0, jnp.array([0.0, 0.0, 0.0, 1.0], x.dtype))
    y, conv, steps = _lm(_sphere_res, y0, (x, v.astype(x.dtype)), max_steps)
    y = y.at[3].set(jnp.abs(y[3]))
    ok = ok & conv & (jnp.sum(v) >= 4)
    return _finish("sphere", ("cx", "cy", "cz", "r"), y, _nrm(x - y[:3]) - y[3], v, ok, steps, conv)


def _circle2d_res(y, args):
    u, w = args
    return w * (_nrm(u - y[:2]) - y[2])


@jit_fast_compile(static_argnames=("max_steps",))
def fit_circle3d(xyz, valid=None, *, max_steps: int = 100) -> Fit3D:
    """3-D circle: TLS plane, then a geometric circle fit of the points projected into it.

    Residual of a point: ``sqrt(h^2 + (rho - r)^2)`` with ``h`` its distance to
    the plane and ``rho`` its in-plane distance to the centre (the exact
    distance to the circle). The plane and the in-plane circle are fitted in
    sequence (not jointly), which is exact for noise-free data and a close
    approximation otherwise. Fails closed for fewer than 3 points or collinear ones.

    Example:
      >>> import jax.numpy as jnp, numpy as np
      >>> from fsjax.fit import fit_circle3d
      >>> t = np.linspace(0, 5, 12)
      >>> pts = np.c_[1 + 2 * np.cos(t), 2 * np.sin(t), np.full(12, 3.0)]
      >>> [round(float(v), 6) + 0.0 for v in fit_circle3d(jnp.asarray(pts)).params]
      [1.0, 0.0, 3.0, 0.0, 0.0, 1.0, 2.0]
    """
    x, v = _prep(xyz, valid, "fit_circle3d")
    c, ev, evec = _pca(x, v)
    n = _canon(evec[:, 0])
    e1, e2 = evec[:, 2], jnp.cross(n, evec[:, 2])
    d = x - c
    u = jnp.stack([d @ e1, d @ e2], -1)
    w = v.astype(x.dtype)
    # algebraic start (Kasa) in the plane
    A = jnp.concatenate([2 * u, jnp.ones_like(u[:, :1])], 1) * w[:, None]
    b = jnp.sum(u * u, 1) * w
    ata = A.T @ A
    ok = (jnp.sum(v) >= 3) & _spread_ok(x, v, ev[1], ev[2])
    s = solve_small(jnp.where(ok, ata, jnp.eye(3, dtype=x.dtype)), A.T @ b)
    r2 = s[2] + s[0] ** 2 + s[1] ** 2
    y0 = jnp.stack([s[0], s[1], jnp.sqrt(jnp.where(r2 > 0, r2, 1.0))])
    y, conv, steps = _lm(_circle2d_res, y0, (u, w), max_steps)
    cen = c + y[0] * e1 + y[1] * e2
    h = d @ n
    rho = _nrm(u - y[:2])
    res = jnp.sqrt(h * h + (rho - jnp.abs(y[2])) ** 2)
    p = jnp.concatenate([cen, n, jnp.abs(y[2])[None]])
    return _finish("circle3d", ("cx", "cy", "cz", "nx", "ny", "nz", "r"), p, res, v, ok & conv & (r2 > 0), steps,
                   conv)


def _perp(a):
    t = jnp.where(jnp.abs(a[0]) < 0.9, jnp.array([1.0, 0.0, 0.0], a.dtype), jnp.array([0.0, 1.0, 0.0], a.dtype))
    e1 = _unit(jnp.cross(a, t))
    return e1, jnp.cross(a, e1)


def _cyl_res(y, args):
    x, w, c0, e1, e2, a0 = args
    a = _unit(a0 + y[0] * e1 + y[1] * e2)
    d = x - (c0 + y[2] * e1 + y[3] * e2)
    return w * (_nrm(d - (d @ a)[:, None] * a) - y[4])


def _cyl_from_axis(x, v, a, max_steps):
    """Cylinder with the axis started at ``a``: in-plane Kasa circle, then LM over 5 parameters."""
    w = v.astype(x.dtype)
    e1, e2 = _perp(a)
    u = jnp.stack([x @ e1, x @ e2], -1)
    m = jnp.sum(u * w[:, None], 0) / jnp.maximum(jnp.sum(w), 1.0)
    uu = (u - m) * w[:, None]
    A = jnp.concatenate([2 * uu, w[:, None]], 1)
    b = jnp.sum(uu * uu, 1)
    ata = A.T @ A
    ev, evec = eigh_small(ata)
    good = ev[0] > 1e-12 * jnp.trace(ata)
    s = solve_spd_eig(jnp.where(good, ev, 1.0), evec, A.T @ b)
    r2 = s[2] + s[0] ** 2 + s[1] ** 2
    c0 = (m[0] + s[0]) * e1 + (m[1] + s[1]) * e2
    r0 = jnp.sqrt(jnp.where(r2 > 0, r2, 1.0))
    y0 = jnp.array([0.0, 0.0, 0.0, 0.0, 1.0], x.dtype) * r0
    y, conv, steps = _lm(_cyl_res, y0, (x, w, c0, e1, e2, a), max_steps)
    res = _cyl_res(y, (x, jnp.ones_like(w), c0, e1, e2, a))
    ax = _canon(_unit(a + y[0] * e1 + y[1] * e2))
    c = c0 + y[2] * e1 + y[3] * e2
    c = c - jnp.dot(c, ax) * ax
    rss = jnp.sum(jnp.where(v, res * res, 0.0))
    ok = good & conv & (r2 > 0) & jnp.isfinite(rss)
    return jnp.concatenate([c, ax, jnp.abs(y[4])[None]]), res, jnp.where(ok, rss, jnp.inf), ok, steps


def _local_normals(x, v, idx):
    """Normal of each point's neighbourhood ``idx`` ``(N, k)``: smallest-eigenvalue eigenvector of its covariance."""
    m = (idx >= 0) & v[jnp.maximum(idx, 0)]
    nb = x[jnp.maximum(idx, 0)]
    cs = jnp.maximum(jnp.sum(m, axis=1), 1).astype(x.dtype)[:, None]
    mu = jnp.sum(jnp.where(m[..., None], nb, 0.0), axis=1) / cs
    d = jnp.where(m[..., None], nb - mu[:, None, :], 0.0)
    return eigh_small(jnp.einsum("nki,nkj->nij", d, d) / cs[..., None])[1][..., 0]


@jit_fast_compile(static_argnames=("max_steps",))
def fit_cylinder(xyz, valid=None, *, max_steps: int = 200) -> Fit3D:
    """Cylinder: multi-start geometric Levenberg-Marquardt, best of four axis starts.

    Starts: the three principal axes of the points and the axis least
    represented in the PCA normals of 12-neighbourhoods (normals of a cylinder
    are perpendicular to its axis); each start gets an in-plane algebraic
    circle, then LM on the radial residual ``|(x - c) x a| - r``; the
    converged start with the smallest residual sum wins (the four one after
    another in a ``lax.map``: a batched LM loop compiles slower). Fails closed
    with fewer than 5 valid points or no converged start, and with reason ``unsupported_model`` when the points do not resolve any
    curvature: the best plane explains them about as well (F-test of the two extra
    parameters, ``F < 7``, i.e. the 0.1 % level) or they are flat to rounding.

    Example:
      >>> import jax.numpy as jnp, numpy as np
      >>> from fsjax.fit import fit_cylinder
      >>> t, z = np.meshgrid(np.linspace(0, 3, 12), np.linspace(-1, 1, 8))
      >>> pts = np.c_[0.5 * np.cos(t).ravel(), 0.5 * np.sin(t).ravel(), z.ravel()]
      >>> f = fit_cylinder(jnp.asarray(pts))
      >>> round(float(f["r"]), 6), round(float(f["az"]), 6)
      (0.5, 1.0)
    """
    from ..ops.points._cloud import knn

    x, v = _prep(xyz, valid, "fit_cylinder")
    c, ev, evec = _pca(x, v)
    xc = x - c
    idx, _ = knn(xc, xc, min(12, x.shape[0]), ref_valid=v)
    nrm = jnp.where(v[:, None], _local_normals(xc, v, idx), 0.0)
    a_n = eigh_small(nrm.T @ nrm)[1][:, 0]
    axes = jnp.stack([evec[:, 0], evec[:, 1], evec[:, 2], a_n])
    p, res, rss, ok, steps = jax.lax.map(lambda a: _cyl_from_axis(xc, v, a, max_steps), axes)
    best = jnp.argmin(rss)
    pb = p[best]
    cen = pb[:3] + c
    cen = cen - jnp.dot(cen, pb[3:6]) * pb[3:6]
    # curvature the data resolve: the best plane (3 parameters) must explain the points
    # significantly worse than the cylinder (5): F = ((rss_p - rss_c) / 2) / (rss_c / (n - 5))
    # above 7 (~ F(2, n - 5) at the 0.1 % level for n >~ 50), and the points must leave the
    # plane by more than rounding. Else a flat patch gave a confident cylinder (radius 154
    # for a 2 x 2 patch with 0.01 noise).
    n = jnp.sum(v).astype(x.dtype)
    rss_p = n * ev[0]
    eps = float(jnp.finfo(x.dtype).eps)
    R = jnp.max(jnp.where(v[:, None], jnp.abs(x), 0.0))
    curved = (rss_p > rss[best] * (1 + 14 / jnp.maximum(n - 5, 1))) & (ev[0] > (32 * eps * R) ** 2)
    return _finish("cylinder", ("cx", "cy", "cz", "ax", "ay", "az", "r"), jnp.concatenate([cen, pb[3:]]),
                   res[best], v, ok[best] & (jnp.sum(v) >= 5), steps[best], supported=curved)


@jit_fast_compile
def fit_quadric(xyz, valid=None) -> Fit3D:
    """Quadric surface patch: height ``h = a u^2 + b uv + c v^2 + d u + e v + f`` over the PCA plane.

    In the principal frame of the points (centroid ``o``, axes ``e1, e2``
    spanning the best plane, normal ``n``), the height ``w = (x - o) . n`` is
    fitted by linear least squares over ``u = (x - o) . e1``,
    ``v = (x - o) . e2``; the residual reported is the first-order orthogonal
    distance ``(w - h) / sqrt(1 + h_u^2 + h_v^2)``. Six free parameters
    (the frame is fixed by the PCA, as for the plane). ``params`` =
    ``(ox, oy, oz, nx, ny, nz, e1x, e1y, e1z, a, b, c, d, e, f)``.

    Why a patch and not the general implicit quadric: a general quadric
    includes degenerate pairs of parallel planes ``w^2 = eps^2``, which
    "explain" Gaussian noise about a plane (folding it: RSS ``0.36 sigma^2``
    per point instead of ``sigma^2``), so an information criterion would pick
    it on every plane. The height patch is the second-order surface that
    nests the plane without that pathology. Fails closed with fewer than 6
    valid points or collinear ones.

    Example:
      >>> import jax.numpy as jnp, numpy as np
      >>> from fsjax.fit import fit_quadric
      >>> g = np.stack(np.meshgrid(np.linspace(-1, 1, 7), np.linspace(-1, 1, 5)), -1).reshape(-1, 2)
      >>> pts = np.c_[g, 0.1 * g[:, 0] ** 2 - 0.05 * g[:, 1] ** 2]
      >>> round(float(fit_quadric(jnp.asarray(pts)).rms_len), 9)
      0.0
    """
    x, v = _prep(xyz, valid, "fit_quadric")
    c, ev, evec = _pca(x, v)
    n, e1 = evec[:, 0], evec[:, 2]
    e2 = jnp.cross(n, e1)
    d = x - c
    u, vv, w = d @ e1, d @ e2, d @ n
    sc = jnp.sqrt(jnp.maximum(ev[2], 1e-300))
    U, V = u / sc, vv / sc
    wt = v.astype(x.dtype)
    A = jnp.stack([U * U, U * V, V * V, U, V, jnp.ones_like(U)], 1) * wt[:, None]
    ata = A.T @ A
    eg, egv = eigh_small(ata)
    ok = (jnp.sum(v) >= 6) & (eg[0] > 1e-12 * eg[-1]) & _spread_ok(x, v, ev[1], ev[2])
    q = solve_spd_eig(jnp.where(ok, eg, 1.0), egv, A.T @ (w * wt))
    h = jnp.stack([U * U, U * V, V * V, U, V, jnp.ones_like(U)], 1) @ q
    hu = (2 * q[0] * U + q[1] * V + q[3]) / sc
    hv = (q[1] * U + 2 * q[2] * V + q[4]) / sc
    res = (w - h) / jnp.sqrt(1 + hu * hu + hv * hv)
    coef = jnp.stack([q[0] / sc, q[1] / sc, q[2] / sc, q[3], q[4], q[5] * sc])
    names = ("ox", "oy", "oz", "nx", "ny", "nz", "e1x", "e1y", "e1z", "a", "b", "c", "d", "e", "f")
    return _finish("quadric", names, jnp.concatenate([c, n, e1, coef]), res, v, ok)


# ---------------------------------------------------------------------------
# model selection
# ---------------------------------------------------------------------------


class ModelSelection(eqx.Module):
    """Evidence of :func:`select_model`: one entry per candidate in ``names`` order.

    Not a fit result (no ``converged``): it compares the :class:`Fit3D` results of the
    candidates; each candidate's failure shows as ``inf`` criteria. ``valid`` False and
    ``choice == -1`` say that no candidate fits: ``reason`` is ``degenerate`` when no fit
    succeeded, ``no_model_fits`` when fits succeeded but none explains the points (its
    residuals are far above the noise, see :func:`select_model`).

    ``rss`` residual sum of squares, ``rms_len`` (input length unit; was ``rms``), ``k`` free parameters, ``aic``,
    ``bic`` (``inf`` for a fit that failed), ``supported`` per candidate: its residuals are
    consistent with the noise, ``choice`` index of the chosen model under ``criterion`` among the
    supported ones (``-1`` when none), ``nearest`` the criterion's minimum among the fits that
    succeeded whether supported or not (diagnostic only), ``n`` points used.
    """

    rss: Float[Array, "*batch M"]
    rms_len: Float[Array, "*batch M"]
    k: Int[Array, "*batch M"]
    aic: Float[Array, "*batch M"]
    bic: Float[Array, "*batch M"]
    choice: Int[Array, "*batch"]
    n: Int[Array, "*batch"]
    supported: Bool[Array, "*batch M"]
    nearest: Int[Array, "*batch"]
    valid: Bool[Array, "*batch"]
    reason: Int[Array, "*batch"]
    names: tuple[str, ...] = eqx.field(static=True, default=())
    criterion: str = eqx.field(static=True, default="bic")

    rms = renamed("rms_len")

    def chosen(self) -> str:
        """Name of the chosen model (eager, single result); ``"none"`` when no model fits."""
        c = int(self.choice)
        return self.names[c] if c >= 0 else "none"


@jit_fast_compile(static_argnames=("criterion",))
def select_model(xyz, valid=None, *, criterion: str = "bic", noise=None, max_rel_rms=0.1) -> ModelSelection:
    """Choose among plane, sphere, cylinder and quadric by AIC or BIC (see the module docstring).

    A model is chosen only if it explains the points (fails closed, issue 20): with ``noise``
    (the standard deviation of the points' distance to the true surface, input length unit)
    a candidate is *supported* when its residual sum of squares is within the chi-square
    bound ``noise^2 (d + 4 sqrt(2 d))``, ``d = n - k`` (about 4 standard deviations of the
    chi-square); without it, when its rms distance is at most ``max_rel_rms`` times the
    points' rms distance from their centroid (the default 0.1: a random blob, a cube or a
    torus leave 0.16-0.55 with every candidate; the patches of the tests, 0.01 noise, 0.02).
    The criterion picks among the supported candidates; when none is supported ``valid`` is
    False, ``choice`` -1 and ``reason`` says why (``no_model_fits``). ``max_rel_rms=None``
    without ``noise`` restores the plain comparison (always names the criterion's best).

    Example:
      Noisy points on a sphere cap select the sphere; a random blob selects none:

      >>> import jax.numpy as jnp, numpy as np
      >>> from fsjax.fit import select_model
      >>> rng = np.random.default_rng(0)
      >>> u = rng.normal(size=(600, 3)); u = u / np.linalg.norm(u, axis=1, keepdims=True)
      >>> pts = u[u[:, 2] > 0.3][:150] + 0.01 * rng.normal(size=(150, 3))
      >>> select_model(jnp.asarray(pts)).chosen()
      'sphere'
      >>> select_model(jnp.asarray(rng.normal(size=(150, 3)))).chosen()
      'none'
    """
    if criterion not in ("aic", "bic"):
        raise ValueError(f"select_model: argument 'criterion' must be 'aic' or 'bic'; got {criterion!r}")
    if noise is not None:
        check_positive("select_model", "noise", noise)
    if max_rel_rms is not None:
        check_positive("select_model", "max_rel_rms", max_rel_rms)
    fits = (fit_plane(xyz, valid), fit_sphere(xyz, valid), fit_cylinder(xyz, valid), fit_quadric(xyz, valid))
    names = ("plane", "sphere", "cylinder", "quadric")
    rss = jnp.stack([f.rss for f in fits])
    rms = jnp.stack([f.rms_len for f in fits])
    ok = jnp.stack([f.converged for f in fits]) & (rss > 0)
    n = fits[0].n_used
    nf = n.astype(rss.dtype)
    k = jnp.array([MODEL_PARAMS[m] for m in names], jnp.int32)
    ll = nf * jnp.log(jnp.where(ok, rss, 1.0) / jnp.maximum(nf, 1.0))
    aic = jnp.where(ok, ll + 2 * k, jnp.inf)
    bic = jnp.where(ok, ll + k * jnp.log(jnp.maximum(nf, 1.0)), jnp.inf)
    crit = aic if criterion == "aic" else bic
    if noise is not None:
        dof = jnp.maximum(nf - k.astype(rss.dtype), 1.0)
        sig = jnp.asarray(noise, rss.dtype)
        supported = ok & (rss <= sig * sig * (dof + 4.0 * jnp.sqrt(2.0 * dof)))
    elif max_rel_rms is not None:
        x = jnp.asarray(xyz)
        w = jnp.ones(x.shape[:-1], bool) if valid is None else jnp.asarray(valid, bool)
        w = w & jnp.all(jnp.isfinite(x), axis=-1)
        wf = w.astype(rss.dtype)
        c = jnp.sum(jnp.where(w[:, None], x, 0.0), axis=0) / jnp.maximum(jnp.sum(wf), 1.0)
        spread = jnp.sqrt(jnp.sum(jnp.where(w[:, None], (x - c) ** 2, 0.0)) / jnp.maximum(jnp.sum(wf), 1.0))
        supported = ok & (rms <= jnp.asarray(max_rel_rms, rss.dtype) * spread)
    else:
        supported = ok
    nearest = jnp.where(jnp.any(ok), jnp.argmin(crit), -1).astype(jnp.int32)
    choice = jnp.where(jnp.any(supported), jnp.argmin(jnp.where(supported, crit, jnp.inf)), -1).astype(jnp.int32)
    reason = jnp.where(jnp.any(supported), reason_code("ok"),
                       jnp.where(jnp.any(ok), reason_code("no_model_fits"), reason_code("degenerate")))
    return ModelSelection(rss=rss, rms_len=rms, k=k, aic=aic, bic=bic, choice=choice, n=n, supported=supported,
                          nearest=nearest, valid=choice >= 0, reason=reason.astype(jnp.int32), names=names,
                          criterion=criterion)


# ---------------------------------------------------------------------------
# distances, angles, intersections (closed form)
# ---------------------------------------------------------------------------


def point_plane_distance(p, plane):
    """Signed distance ``n . p - d`` of point(s) ``p`` ``(..., 3)`` to ``plane`` ``(nx, ny, nz, d)``.

    ``n`` need not be unit: the distance is divided by ``|n|`` (NaN for ``n = 0``).

    Example:
      >>> import jax.numpy as jnp
      >>> from fsjax.fit import point_plane_distance
      >>> float(point_plane_distance(jnp.array([1.0, 2.0, 5.0]), jnp.array([0.0, 0.0, 2.0, 4.0])))
      3.0
    """
    p, plane = jnp.asarray(p), jnp.asarray(plane)
    nn = _nrm(plane[:3])
    return jnp.where(nn > 0, (p @ plane[:3] - plane[3]) / jnp.where(nn > 0, nn, 1.0), jnp.nan)


def point_line_distance(p, line):
    """Distance of point(s) ``p`` to ``line`` ``(p0, d)`` (``d`` any non-zero length; NaN for 0).

    Example:
      >>> import jax.numpy as jnp
      >>> from fsjax.fit import point_line_distance
      >>> float(point_line_distance(jnp.array([0.0, 3.0, 4.0]), jnp.array([0.0, 0, 0, 2.0, 0, 0])))
      5.0
    """
    p, line = jnp.asarray(p), jnp.asarray(line)
    d = _unit(line[3:6])
    return _nrm(jnp.cross(p - line[:3], d))


def line_line_distance(l1, l2):
    """Shortest distance between two 3-D lines (skew: along the common normal; parallel: point-line).

    Example:
      >>> import jax.numpy as jnp
      >>> from fsjax.fit import line_line_distance
      >>> float(line_line_distance(jnp.array([0.0, 0, 0, 1, 0, 0]), jnp.array([0.0, 0, 2, 0, 1, 0])))
      2.0
    """
    l1, l2 = jnp.asarray(l1), jnp.asarray(l2)
    d1, d2 = _unit(l1[3:6]), _unit(l2[3:6])
    cr = jnp.cross(d1, d2)
    cn = _nrm(cr)
    w = l2[:3] - l1[:3]
    # the skew formula's rounding error is ~eps |w| / sin(angle), the parallel one's departure
    # from the minimum ~|w| sin(angle): switch where they meet (sin = 2 sqrt(eps)), so the
    # error stays below ~2 sqrt(eps) |w| in any dtype. The fixed switch at 1e-12 sat below
    # float32's rounding: float32 lines parallel to their precision gave 0.0 for 1.41 and 70.7 or
    # 346 for 141 (issue 20 sweep).
    skew_ok = cn > 2.0 * jnp.sqrt(jnp.finfo(cn.dtype).eps)
    skew = jnp.abs(w @ cr) / jnp.where(skew_ok, cn, 1.0)
    par = _nrm(jnp.cross(w, d1))
    return jnp.where(skew_ok, skew, par)


def _acute(cosv):
    return jnp.degrees(jnp.arccos(jnp.clip(jnp.abs(cosv), 0.0, 1.0)))


def angle_lines(l1, l2):
    """Angle between two lines in degrees, in ``[0, 90]`` (direction signs ignored).

    Example:
      >>> import jax.numpy as jnp
      >>> from fsjax.fit import angle_lines
      >>> round(float(angle_lines(jnp.array([0.0, 0, 0, 1, 0, 0]), jnp.array([0.0, 0, 0, -1, 1, 0]))), 6)
      45.0
    """
    return _acute(_unit(jnp.asarray(l1)[3:6]) @ _unit(jnp.asarray(l2)[3:6]))


def angle_planes(p1, p2):
    """Dihedral angle between two planes in degrees, in ``[0, 90]``.

    Example:
      >>> import jax.numpy as jnp
      >>> from fsjax.fit import angle_planes
      >>> round(float(angle_planes(jnp.array([0.0, 0, 1, 0]), jnp.array([0.0, 1, 1, 3]))), 6)
      45.0
    """
    return _acute(_unit(jnp.asarray(p1)[:3]) @ _unit(jnp.asarray(p2)[:3]))


def angle_line_plane(line, plane):
    """Angle between a line and a plane in degrees, in ``[0, 90]`` (90 = along the normal).

    Example:
      >>> import jax.numpy as jnp
      >>> from fsjax.fit import angle_line_plane
      >>> round(float(angle_line_plane(jnp.array([0.0, 0, 0, 1, 0, 1]), jnp.array([0.0, 0, 1, 0]))), 6)
      45.0
    """
    c = _unit(jnp.asarray(line)[3:6]) @ _unit(jnp.asarray(plane)[:3])
    return 90.0 - _acute(c)


def intersect_line_plane(line, plane, *, min_angle_deg: float = 1e-6):
    """Intersection point of a line and a plane: ``(point (3,), ok)``.

    Parallel (angle below ``min_angle_deg``) fails closed: NaN point, ``ok`` False.

    Example:
      >>> import jax.numpy as jnp
      >>> from fsjax.fit import intersect_line_plane
      >>> p, ok = intersect_line_plane(jnp.array([1.0, 1, 0, 0, 0, 1]), jnp.array([0.0, 0, 1, 3]))
      >>> [float(v) for v in p], bool(ok)
      ([1.0, 1.0, 3.0], True)
    """
    line, plane = jnp.asarray(line), jnp.asarray(plane)
    d = _unit(line[3:6])
    nn = _unit(plane[:3])
    scale = _nrm(plane[:3])
    den = d @ nn
    ok = jnp.abs(den) > jnp.sin(jnp.radians(min_angle_deg))
    ok = ok & jnp.isfinite(den)
    t = (plane[3] / jnp.where(scale > 0, scale, 1.0) - line[:3] @ nn) / jnp.where(ok, den, 1.0)
    return jnp.where(ok, line[:3] + t * d, jnp.nan), ok


def intersect_planes(p1, p2, *, min_angle_deg: float = 1e-6):
    """Intersection line of two planes: ``(line (6,) = point closest to the origin + unit direction, ok)``.

    Parallel planes fail closed (NaN, ``ok`` False).

    Example:
      >>> import jax.numpy as jnp
      >>> from fsjax.fit import intersect_planes
      >>> ln, ok = intersect_planes(jnp.array([1.0, 0, 0, 2]), jnp.array([0.0, 1, 0, 3]))
      >>> [float(v) + 0.0 for v in ln], bool(ok)
      ([2.0, 3.0, 0.0, 0.0, 0.0, 1.0], True)
    """
    p1, p2 = jnp.asarray(p1), jnp.asarray(p2)
    s1, s2 = _nrm(p1[:3]), _nrm(p2[:3])
    n1, n2 = _unit(p1[:3]), _unit(p2[:3])
    d1, d2 = p1[3] / jnp.where(s1 > 0, s1, 1.0), p2[3] / jnp.where(s2 > 0, s2, 1.0)
    cr = jnp.cross(n1, n2)
    cn = _nrm(cr)
    ok = (cn > jnp.sin(jnp.radians(min_angle_deg))) & jnp.isfinite(cn)
    u = _canon(cr / jnp.where(ok, cn, 1.0))
    # point on both planes closest to the origin: solve [n1; n2; u] x = [d1, d2, 0]
    M = jnp.stack([n1, n2, u])
    x = solve_small(jnp.where(ok, M, jnp.eye(3, dtype=M.dtype)), jnp.stack([d1, d2, jnp.zeros_like(d1)]))
    return jnp.where(ok, jnp.concatenate([x, u]), jnp.nan), ok


def __getattr__(name):
    if name == "fit_line":
        deprecated_name("fsjax.fit.fit_line (3-D)", "fsjax.fit.fit_line3d")
        return fit_line3d
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
