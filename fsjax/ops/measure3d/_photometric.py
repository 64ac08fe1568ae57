"""Photometric stereo: normals and albedo from images under several distant lights.

Conventions:

* A :class:`LightStack` holds ``K`` linear-radiance images ``(K, H, W)`` of a static scene
  and the ``K`` unit directions *towards* the lights, ``(K, 3)``, in the **camera frame**
  (OpenCV: x right, y down, z forward; a light behind the camera has negative z).
  Values are >= 0 (not clipped to 1: a highlight may exceed it).
* A :class:`NormalMap` holds unit normals ``(H, W, 3)`` in the camera frame (facing the
  camera: ``n_z < 0``), the Lambertian albedo ``(H, W)`` and ``valid (H, W)``; invalid pixels
  (too few lit measurements, degenerate light geometry) hold NaN normals and albedo.
* Model: Lambertian, ``I_k = rho max(n . l_k, 0)`` (times a visibility in {0, 1} for cast
  shadows); the unknown per pixel is ``b = rho n`` (Woodham 1980).
* Heights from :func:`frankot_chellappa` assume an orthographic (telecentric) view: the
  camera-frame depth ``d(x, y)`` has gradient ``(-n_x / n_z, -n_y / n_z)``; the result is
  defined up to a constant (returned with zero mean), in the unit of ``pixel_size``.

Scenes with a known answer (:func:`fsjax.synth.still_life_scene`,
:func:`fsjax.synth.render_light_stack`) are rendered with the SDF tracer in :mod:`fsjax.synth`.

References: R. J. Woodham, "Photometric method for determining surface orientation from
multiple images", Optical Engineering 19(1) (1980); R. T. Frankot and R. Chellappa, "A method
for enforcing integrability in shape from shading algorithms", IEEE TPAMI 10(4) (1988);
P. J. Rousseeuw, "Least median of squares regression", JASA 79 (1984).
"""

from __future__ import annotations

import functools
import itertools
import math

import jax
import jax.numpy as jnp
import numpy as np

from ..._checks import check_choice, check_positive, check_range
from ...registry import LinKnob, register
from ...types import Image, LightStack, NormalMap

__all__ = ["light_directions", "photometric_stereo", "relight", "frankot_chellappa"]

_METHODS = ("robust", "ls", "lmeds")


def light_directions(elevation_deg, azimuth_deg) -> np.ndarray:
    """Camera-frame unit directions towards lights at ``elevation_deg`` above the image plane
    (towards the camera, i.e. negative z) and ``azimuth_deg`` from the +x (column) axis."""
    e = np.radians(np.asarray(elevation_deg, float))
    a = np.radians(np.asarray(azimuth_deg, float))
    e, a = np.broadcast_arrays(e, a)
    return np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), -np.sin(e)], axis=-1)


# ---------------------------------------------------------------------------
# per-pixel solvers
# ---------------------------------------------------------------------------


def _det(a):
    """Determinant of ``(..., 2, 2)`` or ``(..., 3, 3)`` matrices in closed form.

    The per-pixel solvers use no LAPACK: jaxlib 0.10's batched CPU LAPACK kernels (``det``
    and ``solve`` via LU, ``eigvalsh``) can deadlock XLA:CPU's thread pool when two run at
    once (tools/repro_xla_hang.py; this op hung that way), so the 2x2 / 3x3 algebra is
    written out (``fsjax/_linalg.py``).
    """
    if a.shape[-1] == 2:
        return a[..., 0, 0] * a[..., 1, 1] - a[..., 0, 1] * a[..., 1, 0]
    return (a[..., 0, 0] * (a[..., 1, 1] * a[..., 2, 2] - a[..., 1, 2] * a[..., 2, 1])
            - a[..., 0, 1] * (a[..., 1, 0] * a[..., 2, 2] - a[..., 1, 2] * a[..., 2, 0])
            + a[..., 0, 2] * (a[..., 1, 0] * a[..., 2, 1] - a[..., 1, 1] * a[..., 2, 0]))


def _wls(L, meas, w):
    """Weighted least squares ``argmin sum w (L b - meas)^2`` with a rank test (3 x 3 normal equations)."""
    from ..._linalg import eigh_small, solve_small  # no LAPACK: see _det below

    A = L.T @ (w[:, None] * L)
    y = L.T @ (w * meas)
    ev = eigh_small(A)[0]
    ok = (ev[-1] > 0) & (ev[0] > 1e-8 * ev[-1])
    b = solve_small(jnp.where(ok, A, jnp.eye(3, dtype=A.dtype)), y)
    return b, ok


def _two_light_qp(L, meas, lit, thr):
    """Exactly two lit lights: ``min |b|^2`` s.t. the two equalities and the shadowed inequalities.

    ``b = b0 + s v`` with ``b0`` the minimum-norm solution of the two equations and ``v`` their
    null direction; shadowed lights ``k`` give ``l_k . b <= thr``, facing the camera gives
    ``b_z <= 0``; the inequalities bound ``s`` to an interval and the minimum-norm point is the
    one of smallest ``|s|``. Infeasible (or unbounded) intervals are reported as not ok.
    """
    dt = L.dtype
    idx = jnp.argsort(~lit, stable=True)[:2]
    L2, I2 = L[idx], meas[idx]
    from ..._linalg import solve_small

    G = L2 @ L2.T
    detG = _det(G)
    okG = detG > 1e-8
    b0 = L2.T @ solve_small(jnp.where(okG, G, jnp.eye(2, dtype=dt)), I2)
    v = jnp.cross(L2[0], L2[1])
    vn = jnp.linalg.norm(v)
    v = v / jnp.where(vn > 0, vn, 1.0)
    # constraints a_j + s c_j <= u_j: shadowed lights and the facing condition
    A = jnp.concatenate([L @ b0, b0[2:3]])
    C = jnp.concatenate([L @ v, v[2:3]])
    U = jnp.concatenate([jnp.full(L.shape[0], thr, dt), jnp.zeros(1, dt)])
    use = jnp.concatenate([~lit, jnp.ones(1, bool)])
    big = jnp.asarray(jnp.inf, dt)
    pos = use & (C > 1e-12)
    neg = use & (C < -1e-12)
    bound = (U - A) / jnp.where(pos | neg, C, 1.0)
    hi = jnp.min(jnp.where(pos, bound, big))
    lo = jnp.max(jnp.where(neg, bound, -big))
    flat = use & ~pos & ~neg
    feas_flat = jnp.all(jnp.where(flat, A <= U + 1e-12, True))
    ok = okG & (lo <= hi) & feas_flat & jnp.isfinite(lo) & jnp.isfinite(hi)
    s = jnp.clip(0.0, lo, hi)
    return b0 + jnp.where(ok, s, 0.0) * v, ok


def _lmeds(L, meas, triplets, h):
    """Least median of squares over all light triplets: exact 3 x 3 solves, criterion = h-th smallest r^2."""
    Lt = L[triplets]  # (T, 3, 3)
    It = meas[triplets]  # (T, 3)
    from ..._linalg import solve_small

    det = _det(Lt)
    ok = jnp.abs(det) > 1e-6
    eye = jnp.eye(3, dtype=L.dtype)
    b = solve_small(jnp.where(ok[:, None, None], Lt, eye), It)  # (T, 3)
    r2 = (b @ L.T - meas[None]) ** 2  # (T, K)
    crit = jnp.sort(r2, axis=1)[:, h - 1]
    crit = jnp.where(ok, crit, jnp.inf)
    best = jnp.argmin(crit)
    return b[best], jnp.isfinite(crit[best])


@functools.partial(jax.jit, static_argnames="method")
def _stereo_core(data, lights, shadow_threshold, method: str):
    # module-level jit: the per-pixel solves are vmapped closures with loops, which run eagerly
    # would be traced and compiled again on every call (found by the chain fuzzer)
    K = data.shape[-3]
    L = lights
    dt = jnp.result_type(data.dtype, L.dtype)
    L = L.astype(dt)
    Hh, Ww = data.shape[-2:]
    meas = jnp.moveaxis(data.astype(dt), 0, -1).reshape(-1, K)
    thr = jnp.asarray(shadow_threshold, dt)

    if method == "ls":
        def one(i):
            return _wls(L, i, jnp.ones(K, dt))
    elif method == "lmeds":
        trip = jnp.asarray(list(itertools.combinations(range(K), 3)), jnp.int32)
        h = K // 2 + 1

        def one(i):
            return _lmeds(L, i, trip, h)
    else:
        def one(i):
            lit = i > thr
            n_lit = jnp.sum(lit)
            b3, ok3 = _wls(L, i, lit.astype(dt))
            b2, ok2 = _two_light_qp(L, i, lit, thr)
            use3 = (n_lit >= 3) & ok3
            use2 = (n_lit == 2) & ok2
            return jnp.where(use3, b3, b2), use3 | use2

    b, ok = jax.vmap(one)(meas)
    rho = jnp.linalg.norm(b, axis=-1)
    ok = ok & (rho > 0) & jnp.all(jnp.isfinite(b), axis=-1)
    n = b / jnp.where(ok, rho, 1.0)[:, None]
    n = jnp.where(ok[:, None], n, jnp.nan)
    rho = jnp.where(ok, rho, jnp.nan)
    return n.reshape(Hh, Ww, 3), rho.reshape(Hh, Ww), ok.reshape(Hh, Ww)


@register(family="photometric", takes=LightStack, gives=NormalMap,
          knobs={"shadow_threshold": LinKnob(0.0, 0.2)},
          refs=["Woodham 1980", "Rousseeuw 1984 (LMedS)"])
def photometric_stereo(stack: LightStack, /, *, shadow_threshold: float = 0.02, method: str = "robust") -> NormalMap:
    """Per-pixel normals and albedo from a Lambertian light stack (Woodham's photometric stereo).

    The unknown per pixel is ``b = rho n`` with ``I_k = l_k . b`` for lit measurements.

    * ``"robust"`` (default): measurements above ``shadow_threshold`` are equations, those at
      or below it are *inequalities* ``l_k . b <= shadow_threshold`` (attached shadow:
      ``n . l <= 0``), never equations. With 3 or more lit lights of full rank, ``b`` is the
      least-squares solution of the lit equations; a shadowed light whose inequality that
      solution violates is a cast shadow (occlusion, outside the Lambertian model) and is not
      used. With exactly 2 lit lights, ``b`` is the minimum-norm point of the line the two
      equations leave that satisfies all inequalities and faces the camera (a 1-D quadratic
      programme, solved in closed form). Fewer lit lights, or an infeasible or degenerate
      system: invalid (NaN).
    * ``"ls"``: least squares over all ``K`` measurements (shadows read as ``n . l = 0``): the
      null, biased wherever a pixel is shadowed.
    * ``"lmeds"``: least median of squares: every triplet of lights is solved exactly and the
      solution whose ``(K // 2 + 1)``-th smallest squared residual is least wins. It tolerates
      fewer than half of the lights contaminated (highlights) and breaks down at one half,
      the bound of any median-based estimator (tested).

    Args:
        stack: a :class:`LightStack` with ``K >= 3`` lights (camera frame).
        shadow_threshold: intensity at or below which a measurement counts as shadowed
            (``"robust"``); knob ``a`` in ``[0, 0.2]``. Unused by ``"ls"``/``"lmeds"``.
        method: ``"robust"``, ``"ls"`` or ``"lmeds"`` (static).

    Returns:
        :class:`NormalMap`: unit normals (camera frame), albedo ``|b|``, ``valid``.

    No reference implementation: the normals are checked against the renderer's analytic
    normals (median angular error <= 0.01 deg noise-free, <= 0.1 deg with shadows for
    ``"robust"``; tests).

    Example:
        >>> from fsjax.ops import light_directions
        >>> from fsjax.types import LightStack
        >>> L = light_directions([45, 45, 60, 70], [0, 90, 200, 300])
        >>> n = np.array([0.2, -0.1, -1.0]) / np.linalg.norm([0.2, -0.1, -1.0])
        >>> data = 0.7 * np.maximum(L @ n, 0)[:, None, None] * np.ones((4, 2, 3))
        >>> nm = fsjax.ops.photometric_stereo(LightStack(jnp.asarray(data), jnp.asarray(L)))
        >>> round(float(nm.albedo[1, 2]), 9), bool(np.allclose(nm.normals[1, 2], n, atol=1e-12))
        (0.7, True)
    """
    op = "photometric_stereo"
    check_choice(op, "method", method, _METHODS)
    check_range(op, "shadow_threshold", shadow_threshold, 0.0, None)
    K = stack.data.shape[-3]
    if K < 3:
        raise ValueError(f"{op}: argument 'stack' needs at least 3 lights, got {K}")
    return NormalMap(*_stereo_core(stack.data, stack.lights, shadow_threshold, method))


@register(family="photometric", takes=NormalMap, gives=Image,
          knobs={"azimuth_deg": LinKnob(-180.0, 180.0, "deg"), "elevation_deg": LinKnob(10.0, 90.0, "deg")},
          differentiable=True, refs=["Lambert 1760", "Woodham 1980"])
def relight(nm: NormalMap, /, *, azimuth_deg: float = 0.0, elevation_deg: float = 45.0) -> Image:
    """Lambertian image of a normal map under a new distant light: ``albedo max(n . l, 0)``.

    The light is at ``elevation_deg`` above the image plane (towards the camera) and
    ``azimuth_deg`` from the +x (column) axis: ``l = (cos e cos a, cos e sin a, -sin e)`` in the
    camera frame. Invalid pixels give 0. Smooth except on the terminator ``n . l = 0``.

    Args:
        nm: :class:`NormalMap` (camera frame), e.g. from :func:`photometric_stereo`.
        azimuth_deg: light azimuth, knob ``a`` in [-180, 180] deg.
        elevation_deg: light elevation, knob ``b`` in [10, 90] deg (90: light at the camera).

    Returns:
        :class:`Image` of radiance, in ``[0, max albedo]``.

    Relighting recovered normals and albedo reproduces a render under the same light to the
    normals' accuracy (tested against the SDF renderer).

    Example:
        >>> nm = fsjax.types.NormalMap(jnp.asarray([[[0.0, 0.0, -1.0]]]), jnp.asarray([[0.8]]))
        >>> round(float(fsjax.ops.relight(nm, elevation_deg=30.0).data[0, 0]), 12)  # 0.8 sin 30
        0.4
    """
    a = jnp.deg2rad(jnp.asarray(azimuth_deg))
    e = jnp.deg2rad(jnp.asarray(elevation_deg))
    dt = nm.normals.dtype
    light = jnp.stack([jnp.cos(e) * jnp.cos(a), jnp.cos(e) * jnp.sin(a), -jnp.sin(e)]).astype(dt)
    n = jnp.where(nm.valid[..., None], nm.normals, 0.0)
    rho = jnp.where(nm.valid, nm.albedo, 0.0)
    return Image(rho * jnp.maximum(n @ light, 0.0))


@register(family="photometric", takes=NormalMap, gives=Image, differentiable=True,
          refs=["Frankot and Chellappa 1988"])
def frankot_chellappa(nm: NormalMap, /, *, pixel_size: float = 1.0) -> Image:
    """Integrate a normal map to a depth map by projecting its gradients onto integrable fields.

    With ``p = -n_x / n_z``, ``q = -n_y / n_z`` (orthographic camera-frame depth gradients, times
    ``pixel_size`` per pixel), the least-squares integrable surface has the Fourier transform
    ``Z = -i (w_x P + w_y Q) / (w_x^2 + w_y^2)`` (Frankot-Chellappa 1988), periodic borders,
    zero mean. Invalid pixels, and pixels whose normal is within 1 deg of the image plane,
    contribute zero gradient.

    Args:
        nm: :class:`NormalMap` (camera frame, facing the camera).
        pixel_size: lateral size of a pixel in the output's length unit (default 1: depth in
            pixels).

    Returns:
        :class:`Image` of camera-frame depth relative to its mean (signed; larger = farther),
        in the unit of ``pixel_size``; not clipped to [0, 1].

    Exact for band-limited periodic surfaces; on a still life with creases the error is
    reported against the renderer's true depth (tests).

    Example:
        >>> H, W = 16, 16
        >>> c = np.arange(W)
        >>> d = np.broadcast_to(np.sin(2 * np.pi * c / W), (H, W))        # a periodic depth
        >>> dx = np.broadcast_to(2 * np.pi / W * np.cos(2 * np.pi * c / W), (H, W))
        >>> n = np.stack([dx, 0 * dx, -np.ones((H, W))], -1)
        >>> n /= np.linalg.norm(n, axis=-1, keepdims=True)
        >>> nm = fsjax.types.NormalMap(jnp.asarray(n), jnp.ones((H, W)))
        >>> z = fsjax.ops.frankot_chellappa(nm).data
        >>> float(jnp.max(jnp.abs(z - d))) < 1e-12
        True
    """
    check_positive("frankot_chellappa", "pixel_size", pixel_size)
    n = nm.normals
    dt = n.dtype
    nz = n[..., 2]
    good = nm.valid & (nz < -math.sin(math.radians(1.0)))
    nzs = jnp.where(good, nz, -1.0)
    p = jnp.where(good, -n[..., 0] / nzs, 0.0) * pixel_size
    q = jnp.where(good, -n[..., 1] / nzs, 0.0) * pixel_size
    Hh, Ww = p.shape
    wx = (2.0 * jnp.pi * jnp.fft.fftfreq(Ww)).astype(dt)[None, :]
    wy = (2.0 * jnp.pi * jnp.fft.fftfreq(Hh)).astype(dt)[:, None]
    den = wx * wx + wy * wy
    P, Q = jnp.fft.fft2(p), jnp.fft.fft2(q)
    nzf = den > 0
    Z = jnp.where(nzf, (-1j * (wx * P + wy * Q)) / jnp.where(nzf, den, 1.0), 0.0)
    return Image(jnp.real(jnp.fft.ifft2(Z)).astype(dt))
