"""FFT-family 3-D matching on volumes: phase correlation (translation) and normalised
cross-correlation (template localisation), both with a sub-voxel Newton peak.

Both ops take TWO volumes ``(scene, template)`` of one spacing and return a
:class:`fsjax.Match3D` (conventions in :mod:`fsjax.ops.match3d._shared3d`: ``t`` is the
physical ``(x, y, z)`` position of the template's voxel ``[0, 0, 0]`` in the scene, ``R = I``,
``scale = 1``). Dtype-generic: float32 volumes compute with complex64 FFTs.
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.special import erfc

from ..._checks import check_choice, check_range, check_static_int
from ..._linalg import solve_small
from ...registry import register
from ...types import Match3D, Volume
from .._common import eps
from ..matching._correlation import _centre, _hann, _ncc_normalise, _template_stats, _win1
from ._shared3d import (
    _INVALID,
    _NOT_FOUND,
    check_pair,
    det3,
    make_match,
    neighbourhood3,
    newton_peak3,
    xyz_of,
)

__all__ = ["phase_correlation3d", "ncc3d"]

_REF_KH = ("C. D. Kuglin, D. C. Hines, The phase correlation image alignment method, Proc. IEEE Int. "
           "Conf. Cybernetics and Society, 1975, 163-165")
_REF_FOROOSH = ("H. Foroosh, J. B. Zerubia, M. Berthod, Extension of phase correlation to subpixel "
                "registration, IEEE Trans. Image Processing 11(3), 2002, 188-200")
_REF_LEWIS = "J. P. Lewis, Fast normalized cross-correlation, Vision Interface 1995, 120-123"
_REF_NW = "J. Nocedal, S. J. Wright, Numerical Optimization, 2nd ed., Springer 2006, ch. 3 (Newton's method)"
_REF_MRR = ("X.-L. Meng, R. Rosenthal, D. B. Rubin, Comparing correlated correlation coefficients, Psychological "
            "Bulletin 111(1), 1992, 172-175")
_REF_BARTLETT = ("M. S. Bartlett, Some aspects of the time-correlation problem in regard to tests of significance, "
                 "J. Royal Statistical Society 98(3), 1935, 536-543")
_REF_BERGER = ("R. L. Berger, Multiparameter hypothesis testing and acceptance sampling, Technometrics 24(4), 1982, "
               "295-300")


# ---------------------------------------------------------------------------
# phase correlation with a Newton peak on the band-limited interpolant
# ---------------------------------------------------------------------------


def _interp_derivs(R, x, freqs):
    """Value, gradient and Hessian at ``x (3,)`` (voxels, (k, i, j)) of the band-limited interpolant
    ``f(x) = Re sum_k R_k exp(i w.x)`` (``w_a = 2 pi k_a / N_a``), by separable contractions."""
    wz, wy, wx = freqs
    ez, ey, ex = (jnp.exp(1j * w * xa) for w, xa in ((wz, x[0]), (wy, x[1]), (wx, x[2])))
    Rx = [jnp.einsum("dhw,w->dh", R, (wx ** p) * ex) for p in range(3)]
    Ry = {(p, q): jnp.einsum("dh,h->d", Rx[p], (wy ** q) * ey) for p in range(3) for q in range(3 - p)}

    def S(r, q, p):
        return jnp.sum(Ry[(p, q)] * (wz ** r) * ez)

    f = jnp.real(S(0, 0, 0))
    g = -jnp.imag(jnp.stack([S(1, 0, 0), S(0, 1, 0), S(0, 0, 1)]))
    hzz, hyy, hxx = (-jnp.real(S(*e)) for e in ((2, 0, 0), (0, 2, 0), (0, 0, 2)))
    hzy, hzx, hyx = (-jnp.real(S(*e)) for e in ((1, 1, 0), (1, 0, 1), (0, 1, 1)))
    H = jnp.stack([jnp.stack([hzz, hzy, hzx]), jnp.stack([hzy, hyy, hyx]), jnp.stack([hzx, hyx, hxx])])
    return f, g, H


@functools.partial(jax.jit, static_argnames=("window", "newton_steps"))
def _phase3d_core(a, b, *, window: str, newton_steps: int):
    shp = a.shape
    dt = a.dtype
    e = eps(dt)
    scale = jnp.maximum(jnp.max(jnp.abs(a)), jnp.max(jnp.abs(b)))
    a, b = _centre(a), _centre(b)
    floor = a.size * (64 * e * scale) ** 2
    ok = (jnp.sum(a * a) > floor) & (jnp.sum(b * b) > floor)
    if window == "hann":
        win = _hann(shp[0], dt)[:, None, None] * _hann(shp[1], dt)[None, :, None] * _hann(shp[2], dt)[None, None, :]
        a, b = a * win, b * win
    X = jnp.conj(jnp.fft.fftn(a)) * jnp.fft.fftn(b)
    mag = jnp.abs(X)
    ks = [np.fft.fftfreq(n) * n for n in shp]
    band = np.ones(shp, bool)
    for ax, (k, n) in enumerate(zip(ks, shp)):
        sh = [1, 1, 1]
        sh[ax] = n
        band = band & (np.abs(k) < n / 2).reshape(sh)  # drop the Nyquist bins (no sub-voxel phase)
    nz = (mag > 1e3 * e * jnp.max(mag)) & jnp.asarray(band)
    n_nz = jnp.maximum(jnp.sum(nz), 1).astype(dt)
    R = jnp.where(nz, X / jnp.where(nz, mag, 1.0), 0.0)
    r = jnp.real(jnp.fft.ifftn(R)) * (a.size / n_nz)
    idx = jnp.asarray(jnp.unravel_index(jnp.argmax(r), shp))
    half = jnp.asarray([n // 2 for n in shp])
    x0 = jnp.where(idx > half, idx - jnp.asarray(shp), idx).astype(dt)
    freqs = tuple(jnp.asarray(2 * math.pi * k / n, dt) for k, n in zip(ks, shp))

    def step(_, x):
        _, g, H = _interp_derivs(R, x, freqs)
        m1, m2 = H[0, 0], H[0, 0] * H[1, 1] - H[0, 1] ** 2
        nd = (m1 < 0) & (m2 > 0) & (det3(H) < 0)
        d = -solve_small(jnp.where(nd, H, -jnp.eye(3, dtype=dt)), g)
        d = jnp.where(nd, d, 0.1 * jnp.sign(g))
        return x + jnp.clip(d, -0.5, 0.5)

    x = jax.lax.fori_loop(0, newton_steps, step, x0)
    x = jnp.where(jnp.all(jnp.abs(x - x0) <= 1.0), x, x0)
    f, _, _ = _interp_derivs(R, x, freqs)
    return x, f / n_nz, ok


@register(family="match3d", takes=(Volume, Volume), gives=Match3D, differentiable=False,
          refs=[_REF_KH, _REF_FOROOSH, _REF_NW])
def phase_correlation3d(scene: Volume, template: Volume, /, *, window: str = "none", newton_steps: int = 6,
                        min_score: float = 0.1) -> Match3D:
    """Translation of a volume by 3-D phase correlation, refined by Newton steps on the exact interpolant.

    The normalised cross-power spectrum ``R = conj(F_t) F_s / |conj(F_t) F_s|`` of the two
    mean-free volumes is a pure phase ramp for a circular shift, and its inverse DFT a delta at
    the shift (Kuglin and Hines 1975). From the integer peak, ``newton_steps`` Newton steps
    with the full 3x3 Hessian climb the band-limited interpolant
    ``f(x) = sum_k R_k exp(i w.x) / n`` of that correlation (Foroosh et al. 2002: the peak is a
    sampled Dirichlet kernel); value, gradient and Hessian at a real position are 10
    separable contractions of ``R`` (``O(N)`` each), so the sub-voxel peak is that of the
    continuous correlation, not of a fitted parabola. Nyquist bins and bins carrying no
    energy (below ``1e3 eps`` of the largest) are dropped.

    Args:
      scene: the moved volume ``(D, H, W)``.
      template: the reference volume, same shape and spacing (else ``ValueError``).
      window: ``"none"`` (default; exact for circular shifts and for content away from the
        borders) or ``"hann"`` (separable taper for content that touches the borders).
      newton_steps: Newton iterations (static int in [0, 50]; 0 = integer peak).
      min_score: ``valid`` needs a peak height of at least this (default 0.1; on the grid's
        48^3 scenes with noise and clutter the bunny peaks at 0.13-0.17, the same scenes without
        it at 0.02-0.052: a thin margin, see ``docs/matching_grid.md``).

    Returns:
      ``Match3D``: ``t`` = the shift ``(x, y, z)`` in the spacing's unit such that
      ``scene(p) ~ template(p - t)``, each component in ``(-N/2, N/2]`` voxels; ``R = I``;
      ``score`` = peak height (1 for a pure circular shift, lower with clutter, noise and
      partial overlap). ``valid`` False (``invalid_input``) for a constant volume, or
      (``not_found``) below ``min_score``.

    Example:
      A random volume circularly shifted by (2.0, -3.0, 1.0) voxels (x, y, z) and by a
      Fourier shift of (0.3, 0.0, -0.45) voxels: both recovered to 1e-6 voxel:

      >>> import numpy as np, jax, jax.numpy as jnp, fsjax
      >>> x = jax.random.normal(jax.random.PRNGKey(0), (16, 18, 20))
      >>> moved = jnp.roll(x, (1, -3, 2), axis=(0, 1, 2))
      >>> m = fsjax.ops.phase_correlation3d(fsjax.Volume(moved), fsjax.Volume(x))
      >>> [round(float(v), 6) for v in m.t], round(float(m.score), 6), bool(m.valid)
      ([2.0, -3.0, 1.0], 1.0, True)
      >>> k = [np.fft.fftfreq(n) for n in x.shape]
      >>> ph = np.exp(-2j * np.pi * (k[0][:, None, None] * -0.45 + k[2][None, None, :] * 0.3))
      >>> sub = jnp.real(jnp.fft.ifftn(jnp.fft.fftn(x) * ph))
      >>> m = fsjax.ops.phase_correlation3d(fsjax.Volume(sub), fsjax.Volume(x))
      >>> [round(float(v), 6) + 0.0 for v in m.t]
      [0.3, 0.0, -0.45]
    """
    op = "phase_correlation3d"
    _, _, dt = check_pair(op, scene, template, same=True)
    check_choice(op, "window", window, ("none", "hann"))
    steps = check_static_int(op, "newton_steps", newton_steps, lo=0, hi=50)
    check_range(op, "min_score", min_score, -1.0, 1.0)
    x, s, ok = _phase3d_core(template.data.astype(dt), scene.data.astype(dt), window=window, newton_steps=steps)
    valid = ok & (s >= jnp.asarray(min_score, dt))
    reason = jnp.where(ok, _NOT_FOUND, _INVALID)
    return make_match(jnp.eye(3, dtype=dt), xyz_of(x, scene.spacing).astype(dt), s, valid, reason)


# ---------------------------------------------------------------------------
# normalised cross-correlation
# ---------------------------------------------------------------------------


def _ncc3d_map(x, t):
    """Zero-mean NCC of template ``t (d, h, w)`` over every valid placement in ``x (D, H, W)``."""
    D, H, W = x.shape
    d, h, w = t.shape
    xc = _centre(x)
    t0, tn, tflat = _template_stats(t)
    X = jnp.fft.rfftn(xc)
    T = jnp.fft.rfftn(t0, s=(D, H, W))
    num = jnp.fft.irfftn(X * jnp.conj(T), s=(D, H, W))[: D - d + 1, : H - h + 1, : W - w + 1]
    s1 = _win1(_win1(_win1(xc, d, 0), h, 1), w, 2)
    s2 = _win1(_win1(_win1(xc * xc, d, 0), h, 1), w, 2)
    return _ncc_normalise(num, s1, s2, tn, tflat, d * h * w), tflat


# the seven mirror images of a template box (flips of one, two or all three axes; the identity left out):
# the alternatives of ncc3d's acceptance test
_FLIPS = tuple(f for f in ((a, b, c) for a in (0, 1) for b in (0, 1) for c in (0, 1)) if any(f))
# a mirror image that correlates with the template above this is the template itself (a sphere, a box, an
# axis-aligned ellipsoid: every mirror is): no alternative, left out of the test
MIRROR_SAME = 0.95
# the mirror images are scored within +-_MIRROR_WINDOW voxels of their centroid-aligned placement
_MIRROR_WINDOW = 2


def mirror_chance(x, t, p, s):
    """The chance that the scene box at integer placement ``p`` (its NCC with ``t`` is ``s``) is
    explained as well by a mirror image of the template: ``(p_value, z, n_alt)``.

    For each of the template's seven mirror images (axis flips) that is not the template itself (its
    correlation ``r_x`` with the template below :data:`MIRROR_SAME`), its best NCC ``r_m`` within
    ``+-2`` voxels of the placement that maps the template's centroid onto itself is compared with
    ``s`` by Meng, Rosenthal and Rubin's (1992) test of two correlations that share the scene box,
    ``Z = (atanh s - atanh r_m) sqrt((n - 3) / (2 (1 - r_x) h))``, with ``n`` Bartlett's (1935)
    effective number of independent voxels, ``n = N / sum_u rho_T(u) rho_S(u)`` (``rho``: the
    autocorrelations of the template and the scene box; smooth volumes have far fewer independent
    voxels than voxels). The null is the union "some mirror image fits the box as well as the
    template", so the template must beat every mirror image: an intersection-union test (Berger
    1982), whose p-value is the largest of the single ones, ``1 - Phi(min Z)``, at no multiplicity
    cost. ``n_alt = 0`` (every mirror image is the template) gives p-value 0: no test.
    """
    dt = x.dtype
    d = t.shape
    t0, tn, _ = _template_stats(t)
    a = jnp.abs(t0)
    grids = [jnp.arange(n, dtype=dt).reshape([n if k == ax else 1 for k in range(3)]) for ax, n in enumerate(d)]
    c = jnp.stack([jnp.sum(a * g) for g in grids]) / jnp.maximum(jnp.sum(a), jnp.finfo(dt).tiny)
    flips = jnp.asarray(_FLIPS, bool)
    mirrors = jnp.stack([jnp.flip(t, tuple(ax for ax in range(3) if f[ax])) for f in _FLIPS])
    w = _MIRROR_WINDOW
    size = tuple(min(n + 2 * w, m) for n, m in zip(d, x.shape))
    shift = jnp.where(flips, jnp.round(2 * c - (jnp.asarray(d, dt) - 1)).astype(jnp.int32), 0)
    # sameness at the best overlay within +-w voxels of the centroid-aligned one (the window the
    # mirror is scored in below): a symmetric object off the centre of its box is its own mirror
    # image moved, not an alternative (compared unmoved, a blob one voxel off centre correlated
    # below MIRROR_SAME with its mirror, which then fitted the scene as well as the template and
    # refused a true find)
    offs = jnp.asarray([(a, b, e) for a in range(-w, w + 1) for b in range(-w, w + 1) for e in range(-w, w + 1)],
                       jnp.int32)
    dd = jnp.asarray(d, jnp.int32)

    def same(f, sh):
        m = jnp.pad(jnp.flip(t0, tuple(ax for ax in range(3) if f[ax])), [(n, n) for n in d])

        def at(o):
            ms = jax.lax.dynamic_slice(m, jnp.clip(dd - sh - o, 0, 2 * dd), d)
            return jnp.sum(t0 * ms) / jnp.sqrt(jnp.maximum(tn * jnp.sum(ms * ms), jnp.finfo(dt).tiny))

        return jnp.max(jax.vmap(at)(offs))

    rx = jnp.stack([same(f, shift[k]) for k, f in enumerate(_FLIPS)])
    starts = jnp.clip(p[None, :] + shift - w, 0, jnp.asarray(x.shape) - jnp.asarray(size))

    def best(m, st):
        return jnp.max(_ncc3d_map(jax.lax.dynamic_slice(x, st, size), m)[0])

    rm = jax.vmap(best)(mirrors, starts)
    # Bartlett's effective sample size of the pair (template, scene box at p): linear autocorrelations
    box = _centre(jax.lax.dynamic_slice(x, p, d))
    shp = tuple(2 * n for n in d)

    def rho(v):
        f = jnp.fft.rfftn(v, s=shp)
        r = jnp.fft.irfftn(f * jnp.conj(f), s=shp)
        return r / jnp.where(r[0, 0, 0] > 0, r[0, 0, 0], 1.0)

    n_eff = t.size / jnp.maximum(jnp.sum(rho(t0) * rho(box)), 1.0)
    lim = 1.0 - 16 * eps(dt)
    r1 = jnp.clip(s, -lim, lim)
    r2 = jnp.clip(rm, -lim, lim)
    rb2 = (r1 * r1 + r2 * r2) / 2
    f = jnp.minimum((1 - rx) / (2 * (1 - rb2)), 1.0)
    h = (1 - f * rb2) / (1 - rb2)
    alt = rx < MIRROR_SAME
    z = (jnp.arctanh(r1) - jnp.arctanh(r2)) * jnp.sqrt(jnp.maximum(n_eff - 3, 0.0) / (2 * (1 - jnp.where(alt, rx, 0.0))
                                                                                      * h))
    zmin = jnp.min(jnp.where(alt, z, jnp.inf))
    n_alt = jnp.sum(alt)
    pval = jnp.where(n_alt > 0, 0.5 * erfc(zmin / math.sqrt(2.0)), 0.0)
    return pval.astype(dt), zmin.astype(dt), n_alt


@jax.jit
def _ncc3d_core(x, t):
    S, tflat = _ncc3d_map(x, t)
    idx = jnp.asarray(jnp.unravel_index(jnp.argmax(S), S.shape))
    v, ok = neighbourhood3(S, idx)
    off = idx.astype(x.dtype) + newton_peak3(v, ok)
    s = S[idx[0], idx[1], idx[2]]
    return off, s, tflat, mirror_chance(x, t, idx, s)[0]


@register(family="match3d", takes=(Volume, Volume), gives=Match3D, differentiable=False,
          refs=[_REF_LEWIS, _REF_NW, _REF_MRR, _REF_BARTLETT, _REF_BERGER])
def ncc3d(scene: Volume, template: Volume, /, *, min_score: float = 0.7, max_chance: float = 0.01) -> Match3D:
    """Locate a template volume in a scene by 3-D normalised cross-correlation, sub-voxel.

    ``R(o) = sum T'(u) S'(o + u) / sqrt(sum T'^2 sum S'^2)`` over the template's box, with
    ``T'`` the zero-mean template and ``S'`` the scene box minus its own mean (Lewis 1995):
    one FFT correlation for the numerator, box sums (binary doubling along each axis) for the
    local energy, so the score is in ``[-1, 1]`` and invariant to gain and offset of either
    volume. The best placement is refined by a Newton step with the full 3x3 Hessian of the
    least-squares quadratic through its 3x3x3 neighbourhood (per-axis parabolas when that
    quadratic has no maximum within a voxel; an offset of 0 along an axis where the peak
    sits on the map's border). Exhaustive (no pyramid yet): cost ``O(N log N)`` for the
    scene's ``N`` voxels.

    **Acceptance.** A fixed score does not tell the object from clutter: a blob of the object's size
    (a sphere or cube shell) reaches 0.5-0.73 against the bunny template of the matching grid, the
    bunny itself 0.87-0.99. So the best placement must also be *specific*: its box must correlate
    with the template significantly better than with every mirror image of the template (the seven
    flips of the box's axes, each scored at its best within +-2 voxels of the placement that keeps
    the template's centroid), by Meng, Rosenthal and Rubin's (1992) test of two correlations that
    share one variable, on Bartlett's (1935) effective number of independent voxels of the box; the
    template must beat every mirror image (an intersection-union test, Berger 1982: the p-value is
    the largest single one). A symmetric blob fits the template and its mirror images alike
    (measured on the five rows of ``docs/matching_grid.md``, seeds 0-2: ``z`` <= 0.25 on the scenes
    without the bunny, 2.9-10 with it; the empty 128^3 scene that scored 0.728 gives ``z`` 0.19); the
    object does not. Mirror images that
    correlate with the template above ``MIRROR_SAME`` = 0.95 are the template itself and are left out;
    a template that equals all of its mirror images (a sphere, a box, an axis-aligned ellipsoid) has no
    alternative, and then only ``min_score`` decides (a symmetric clutter blob of its size is
    accepted: the old risk). Cost: seven NCC maps of the template's box plus 4 voxels and two
    autocorrelations of twice its size, beside the scene's FFT.

    Args:
      scene: the scene ``(D, H, W)``.
      template: the template ``(d, h, w)``, no larger than the scene in any axis, same spacing.
      min_score: ``valid`` needs a best score of at least this (default 0.7; the bunny template
        scores 0.87-0.99 at its place in the grid scenes, the same scenes without it up to 0.69 at
        48^3 and 0.728 at 128^3).
      max_chance: ``valid`` needs the mirror test's p-value at most this (default 0.01, a one-sided
        ``z`` >= 2.33); 1 turns the test off.

    Returns:
      ``Match3D``: ``t`` = physical ``(x, y, z)`` position of the template's voxel
      ``[0, 0, 0]`` in the scene (its centre lands at ``t + ((w-1) dx, (h-1) dy, (d-1) dz) / 2``);
      ``R = I``, ``scale = 1``; ``score`` = the NCC at the integer peak. ``valid`` False
      (``invalid_input``) for a flat template, (``not_found``) when no placement reaches
      ``min_score`` or the best one is not specific (mirror test above ``max_chance``).

    Example:
      A smooth blob cut out of a scene is found where it was cut (the quadratic peak is
      within 1e-5 voxel of the exact integer placement here):

      >>> import jax.numpy as jnp, fsjax
      >>> k, i, j = jnp.mgrid[0:20, 0:22, 0:24]
      >>> scene = jnp.exp(-((k - 8.0) ** 2 + (i - 12.0) ** 2 + (j - 9.0) ** 2) / 6.0) + 0.01 * jnp.sin(j + 2 * i)
      >>> m = fsjax.ops.ncc3d(fsjax.Volume(scene), fsjax.Volume(scene[4:13, 8:17, 5:14]))
      >>> [round(float(v), 4) for v in m.t], round(float(m.score), 6)
      ([5.0, 8.0, 4.0], 1.0)
    """
    op = "ncc3d"
    _, _, dt = check_pair(op, scene, template)
    check_range(op, "min_score", min_score, -1.0, 1.0)
    check_range(op, "max_chance", max_chance, 0.0, 1.0)
    off, s, tflat, chance = _ncc3d_core(scene.data.astype(dt), template.data.astype(dt))
    valid = jnp.logical_not(tflat) & (s >= jnp.asarray(min_score, dt)) & (chance <= jnp.asarray(max_chance, dt))
    reason = jnp.where(tflat, _INVALID, _NOT_FOUND)
    return make_match(jnp.eye(3, dtype=dt), xyz_of(off, scene.spacing).astype(dt), s, valid, reason)
