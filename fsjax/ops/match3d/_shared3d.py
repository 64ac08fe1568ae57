"""Helpers shared by the 3-D matching ops: argument checks, the result record, sub-voxel peaks.

Conventions of the whole family (stated once):

* A pose maps template coordinates to scene coordinates, ``scene = scale R p + t``, with ``p``
  and ``t`` as ``(x, y, z)`` in the grids' physical unit; voxel ``[k, i, j]`` of a ``Volume``
  sits at ``(j dx, i dy, k dz)`` (:class:`fsjax.Match3D`). A template volume placed with its
  voxel ``[0, 0, 0]`` on scene voxel ``[k, i, j]`` has ``t = (j dx, i dy, k dz)``.
* Scene and template must share one spacing (``ValueError`` otherwise: resample first).
* An invalid match holds NaN in ``R``, ``t``, ``scale`` and says why in ``reason``
  (codes of :class:`fsjax.types.RESULTS`); the score stays readable.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ..._linalg import solve_small
from ...types import Match3D, Volume, reason_code

_OK, _NOT_FOUND, _DEGENERATE, _INVALID, _MAXIT = (reason_code(n) for n in (
    "ok", "not_found", "degenerate", "invalid_input", "max_iterations"))


def check_pair(op: str, scene: Volume, template: Volume, tname: str = "template", same: bool = False,
               fits: bool = True):
    """Static checks of a (scene, template) volume pair; returns their shapes and the common dtype."""
    for name, v in (("scene", scene), (tname, template)):
        if not isinstance(v, Volume):
            raise TypeError(f"{op}: argument {name!r} must be a Volume; got {type(v).__name__}")
        if v.data.ndim != 3:
            raise ValueError(f"{op}: argument {name!r} must be one volume (batch with jax.vmap); got data of "
                             f"shape {v.data.shape}")
    if tuple(scene.spacing) != tuple(template.spacing):
        raise ValueError(f"{op}: argument {tname!r} has spacing {template.spacing}, 'scene' {scene.spacing}; "
                         f"they must be equal (resample one of them first)")
    S, T = tuple(scene.data.shape), tuple(template.data.shape)
    if same and S != T:
        raise ValueError(f"{op}: argument {tname!r} has shape {T}; it must equal the shape of 'scene' {S}")
    if fits and any(t > s for t, s in zip(T, S)):
        raise ValueError(f"{op}: argument {tname!r} of shape {T} is larger than 'scene' {S} in at least one axis")
    return S, T, jnp.result_type(scene.data.dtype, template.data.dtype)


def xyz_of(kij, spacing):
    """``(k, i, j)`` voxel offsets -> ``(x, y, z)`` physical (``spacing = (dz, dy, dx)``)."""
    dz, dy, dx = spacing
    return jnp.stack([kij[..., 2] * dx, kij[..., 1] * dy, kij[..., 0] * dz], -1)


def kij_of(xyz, spacing):
    """``(x, y, z)`` physical -> ``(k, i, j)`` voxel offsets."""
    dz, dy, dx = spacing
    return jnp.stack([xyz[..., 2] / dz, xyz[..., 1] / dy, xyz[..., 0] / dx], -1)


def make_match(R, t, score, valid, reason, scale=None, iterations=0) -> Match3D:
    """A ``Match3D`` with NaN pose where ``valid`` is False and ``reason`` forced to ok where valid."""
    dt = t.dtype
    nan = jnp.asarray(jnp.nan, dt)
    scale = jnp.ones((), dt) if scale is None else jnp.asarray(scale, dt)
    reason = jnp.where(valid, _OK, jnp.where(reason == _OK, _NOT_FOUND, reason)).astype(jnp.int32)
    return Match3D(jnp.where(valid, R, nan), jnp.where(valid, t, nan), score, valid, reason,
                   scale=jnp.where(valid, scale, nan), iterations=iterations)


def turned_template(T, a):
    """The template's intensities turned about z by ``a`` (radians, counter-clockwise from +x towards +y;
    about the box centre, trilinear, 0 outside the box) and the cylinder inscribed in the box about z (the
    voxels that stay inside at every angle): the turned matchers' templates."""
    d, h, w = T.shape
    dt = T.dtype
    ci, cj = (h - 1) / 2.0, (w - 1) / 2.0
    r = (min(h, w) - 1) / 2.0
    k, i, j = jnp.meshgrid(jnp.arange(d, dtype=dt), jnp.arange(h, dtype=dt), jnp.arange(w, dtype=dt), indexing="ij")
    x, y = j - cj, i - ci
    ca, sa = jnp.cos(a), jnp.sin(a)
    # the turned template at (x, y) is the template at Rz(-a) (x, y)
    xs, ys = ca * x + sa * y, -sa * x + ca * y
    v = jax.scipy.ndimage.map_coordinates(T, [k, ys + ci, xs + cj], order=1, mode="constant", cval=0.0)
    return v, x * x + y * y <= r * r


def turned_pose(a, off, tshape, spacing, dt):
    """The pose of a template turned about z by ``a`` (radians; any batch shape) through its box centre and
    placed with the turned box's voxel ``[0, 0, 0]`` at ``off`` (``(..., 3)`` (k, i, j) voxels): ``R = Rz(a)``
    (counter-clockwise from +x towards +y) and ``t`` such that a template point ``p`` lands at ``R p + t``
    (the box centre ``c`` at ``off + c``)."""
    ca, sa = jnp.cos(a), jnp.sin(a)
    z, o = jnp.zeros_like(a), jnp.ones_like(a)
    R = jnp.stack([jnp.stack([ca, -sa, z], -1), jnp.stack([sa, ca, z], -1), jnp.stack([z, z, o], -1)], -2).astype(dt)
    c_xyz = xyz_of((jnp.asarray(tshape, dt) - 1) / 2, spacing).astype(dt)
    return R, xyz_of(off, spacing).astype(dt) + c_xyz - R @ c_xyz


def det3(H):
    """Determinant of a general 3x3 matrix (cofactor expansion; no LAPACK)."""
    return (H[0, 0] * (H[1, 1] * H[2, 2] - H[1, 2] * H[2, 1]) - H[0, 1] * (H[1, 0] * H[2, 2] - H[1, 2] * H[2, 0])
            + H[0, 2] * (H[1, 0] * H[2, 1] - H[1, 1] * H[2, 0]))


def neighbourhood3(S, idx):
    """The 3x3x3 values of ``S`` around integer ``idx (3,)`` (edge-clamped) and, per axis, whether
    both neighbours exist."""
    shp = jnp.asarray(S.shape)
    o = jnp.arange(-1, 2)
    k = jnp.clip(idx[0] + o, 0, S.shape[0] - 1)
    i = jnp.clip(idx[1] + o, 0, S.shape[1] - 1)
    j = jnp.clip(idx[2] + o, 0, S.shape[2] - 1)
    v = S[k[:, None, None], i[None, :, None], j[None, None, :]]
    return v, (idx >= 1) & (idx <= shp - 2)


def newton_peak3(v, ok):
    """Sub-voxel offset ``(dk, di, dj)`` of the maximum of a 3x3x3 neighbourhood ``v``.

    Least-squares quadratic ``f = c + g.d + d^T H d / 2`` on the 27 samples (orthogonal basis on
    the 3x3x3 grid: ``g_a = sum d_a v / 18``, ``H_aa = sum (d_a^2 - 2/3) v / 3``,
    ``H_ab = sum d_a d_b v / 12``), then one Newton step ``d = -H^-1 g`` with the full 3x3 Hessian
    when ``H`` is negative definite and the step stays within one voxel; else per-axis parabolas
    (each clipped to +-0.5). An axis without both neighbours (``ok`` False) gets 0, and the Newton
    step is used only when all three axes are complete.
    """
    dt = v.dtype
    o = jnp.asarray([-1.0, 0.0, 1.0], dt)
    d = [o[:, None, None] + 0 * v, o[None, :, None] + 0 * v, o[None, None, :] + 0 * v]
    g = jnp.stack([jnp.sum(da * v) / 18 for da in d])
    diag = [jnp.sum((da * da - 2.0 / 3.0) * v) / 3 for da in d]
    h01, h02, h12 = (jnp.sum(d[a] * d[b] * v) / 12 for a, b in ((0, 1), (0, 2), (1, 2)))
    H = jnp.stack([jnp.stack([diag[0], h01, h02]), jnp.stack([h01, diag[1], h12]), jnp.stack([h02, h12, diag[2]])])
    m1 = H[0, 0]
    m2 = H[0, 0] * H[1, 1] - H[0, 1] ** 2
    m3 = det3(H)
    nd = (m1 < 0) & (m2 > 0) & (m3 < 0)
    step = -solve_small(jnp.where(nd, H, -jnp.eye(3, dtype=dt)), g)
    good = nd & jnp.all(jnp.abs(step) <= 1) & jnp.all(ok)
    # per-axis parabolas through the centre lines
    c = v[1, 1, 1]
    lines = ((v[0, 1, 1], v[2, 1, 1]), (v[1, 0, 1], v[1, 2, 1]), (v[1, 1, 0], v[1, 1, 2]))
    par = []
    for a, (m, p) in enumerate(lines):
        den = m - 2 * c + p
        okd = (den < 0) & ok[a]
        par.append(jnp.where(okd, jnp.clip(0.5 * (m - p) / jnp.where(okd, den, -1.0), -0.5, 0.5), 0.0))
    return jnp.where(good, step, jnp.stack(par))


def peak3(S):
    """The integer maximum ``idx (3,)`` of a score map ``S`` and its sub-voxel position (:func:`newton_peak3`)."""
    idx = jnp.asarray(jnp.unravel_index(jnp.argmax(S), S.shape))
    v, ok = neighbourhood3(S, idx)
    return idx, idx.astype(S.dtype) + newton_peak3(v, ok)
