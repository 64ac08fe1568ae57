"""Shape-based matching on gradient directions (part of the ``matching`` family).

Conventions are those of :mod:`fsjax.ops.matching._correlation` (positions of the
template CENTRE, ``angle_deg`` counter-clockwise on screen, fixed capacity,
finite fill of invalid slots). Specific to this module:

* Gradients are central differences of a Gaussian-smoothed image (``sigma``,
  taps to ``int(3 sigma + 0.5)``, boundary ``"nearest"``).
* Pyramid level ``l`` is the ``2^l x 2^l`` block mean (trailing rows/cols that
  do not fill a block are dropped). A level-``l`` pixel index ``i`` has its
  centre at full-resolution coordinate ``2^l i + (2^l - 1) / 2``.
* The model is a list of at most ``max_points`` edge points of the template
  (non-maximum-suppressed gradient magnitude above ``model_contrast`` times
  its maximum, sampled evenly, refined to sub-pixel along the gradient), with
  their unit gradient directions, as offsets from the template centre.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from ..._checks import check_range, check_static_int
from ..._linalg import jit_fast_compile
from ...registry import LinKnob, LogKnob, register
from ...types import Image, Match, is_concrete
from ._shared import _check_pair, _dedupe, _dtype, _fill_match, _greedy_peaks

__all__ = ["shape_locate"]

_REF_STEGER = ("C. Steger, Similarity measures for occlusion, clutter, and illumination invariant object "
               "recognition, DAGM 2001, LNCS 2191, 148-154")
_REF_STEGER2 = ("C. Steger, Occlusion, clutter, and illumination invariant object recognition, "
                "Int. Archives of Photogrammetry and Remote Sensing XXXIV(3A), 2002, 345-350")
_REF_TANIMOTO = "S. L. Tanimoto, Template matching in pyramids, CGIP 16(4), 1981, 356-369"


# ---------------------------------------------------------------------------
# image side: pyramid and gradients
# ---------------------------------------------------------------------------


def _grad_matrices(n: int, sigma: float):
    """Static ``(n, n)`` matrices: Gaussian smoothing ``S`` and its central difference ``D S``
    (boundary ``"nearest"``), so ``g = (D S) x`` along one axis."""
    r = max(1, int(3 * sigma + 0.5))
    k = np.arange(-r, r + 1)
    w = np.exp(-0.5 * (k / sigma) ** 2)
    w = w / w.sum()
    S = np.zeros((n, n))
    for i in range(n):
        np.add.at(S[i], np.clip(i + k, 0, n - 1), w)
    D = np.zeros((n, n))
    i = np.arange(n)
    D[i, np.clip(i + 1, 0, n - 1)] += 0.5
    D[i, np.clip(i - 1, 0, n - 1)] -= 0.5
    return S, D @ S


def _smooth_grad(x, sigma: float):
    """``(g_row, g_col)``: central differences of the Gaussian-smoothed image (grey / px).

    Four matrix products with static band matrices: a handful of ops to
    compile, whatever the support.
    """
    H, W = x.shape
    Sh, DSh = (jnp.asarray(m, x.dtype) for m in _grad_matrices(H, sigma))
    Sw, DSw = (jnp.asarray(m, x.dtype) for m in _grad_matrices(W, sigma))
    return DSh @ (x @ Sw.T), Sh @ (x @ DSw.T)


def _down2(x):
    H, W = x.shape
    return x[: H // 2 * 2, : W // 2 * 2].reshape(H // 2, 2, W // 2, 2).mean(axis=(1, 3))


def _bilinear(F, r, c):
    """Bilinear samples of a two-channel field ``F`` ``(H, W, 2)`` at real ``(r, c)``.

    Samples beyond the border read 0. Returns ``(values (..., 2), inside)``.
    """
    H, W = F.shape[:2]
    r0 = jnp.floor(r)
    c0 = jnp.floor(c)
    fr, fc = (r - r0)[..., None], (c - c0)[..., None]
    r0 = r0.astype(jnp.int32)
    c0 = c0.astype(jnp.int32)
    inside = (r >= 0) & (r <= H - 1) & (c >= 0) & (c <= W - 1)
    Fp = jnp.pad(F, ((1, 2), (1, 2), (0, 0)))  # one gather per corner, indices clipped into the zero ring
    i = jnp.clip(r0 + 1, 0, H + 1)
    j = jnp.clip(c0 + 1, 0, W + 1)
    v = ((1 - fr) * (1 - fc) * Fp[i, j] + (1 - fr) * fc * Fp[i, j + 1]
         + fr * (1 - fc) * Fp[i + 1, j] + fr * fc * Fp[i + 1, j + 1])
    return v, inside


def _parabola(m1, c0, p1):
    """Vertex offset of the parabola through ``(-1, m1), (0, c0), (1, p1)``, in [-0.5, 0.5]; 0 if not a max."""
    den = m1 - 2 * c0 + p1
    ok = den < 0
    return jnp.where(ok, jnp.clip(0.5 * (m1 - p1) / jnp.where(ok, den, -1.0), -0.5, 0.5), 0.0)


def _edge_offset(G, pr, pc, nr, nc, reach: int = 2):
    """Signed distance along the unit normal ``n`` from ``p`` to the nearest edge, sub-pixel.

    The projected gradient ``|<n, G>|`` is sampled on the line ``p + s n`` where it
    crosses the grid lines of the axis closest to ``n`` (rows if ``|n_r| >= |n_c|``),
    ``2 reach + 1`` crossings around ``p``; there only the other axis is
    interpolated (linearly, i.e. along the edge, where the profile is smooth),
    so the profile across the edge is not blurred by interpolation (bilinear or
    bicubic sampling along ``n`` biases it by up to ~0.05 px). A parabola
    through the strongest interior crossing and its neighbours gives the edge.
    The polarity of each point may flip (contrast invariance).

    Returns ``(distance, strength, agree, inside)`` with ``strength`` the
    projected gradient at the strongest crossing, ``agree`` the cosine between
    ``n`` and the image gradient there, and ``inside`` whether every sample lay
    inside the image. ``G`` is the gradient field ``(H, W, 2)``.
    """
    dt = G.dtype
    by_row = jnp.abs(nr) >= jnp.abs(nc)
    a0 = jnp.where(by_row, pr, pc)
    b0 = jnp.where(by_row, pc, pr)
    na = jnp.where(by_row, nr, nc)
    nb = jnp.where(by_row, nc, nr)
    ks = jnp.arange(-reach, reach + 1, dtype=dt)
    ak = jnp.round(a0)[..., None] + ks
    bk = b0[..., None] + (ak - a0[..., None]) * (nb / na)[..., None]
    r = jnp.where(by_row[..., None], ak, bk)
    c = jnp.where(by_row[..., None], bk, ak)
    g, ins = _bilinear(G, r, c)
    fr, fc = g[..., 0], g[..., 1]
    f = nr[..., None] * fr + nc[..., None] * fc
    f = f * jnp.sign(f[..., reach:reach + 1])
    k = jnp.argmax(f[..., 1:-1], axis=-1) + 1
    # pick samples k-1, k, k+1 with one-hot sums (cheaper to compile than gathers)
    pos = jnp.arange(2 * reach + 1)

    def pick(v, shift):
        return jnp.sum(jnp.where(pos == (k + shift)[..., None], v, 0.0), axis=-1)

    fk, fm, fp = pick(f, 0), pick(f, -1), pick(f, 1)
    a_edge = pick(ak, 0) + _parabola(fm, fk, fp)
    gk2 = pick(fr, 0) ** 2 + pick(fc, 0) ** 2
    ok = gk2 > 0
    agree = jnp.where(ok, fk / jnp.sqrt(jnp.where(ok, gk2, 1.0)), 0.0)
    return (a_edge - a0) / na, fk, agree, jnp.all(ins, axis=-1)


# ---------------------------------------------------------------------------
# model side: edge points of the template
# ---------------------------------------------------------------------------


def _model_points(t, n_pts: int, rel: float, sigma: float, ref):
    """Up to ``n_pts`` edge points ``(offsets (n, 2), dirs (n, 2), valid (n,), count)`` of ``t``.

    Offsets are sub-pixel ``(row, col)`` relative to ``ref``; dirs unit gradients.
    """
    h, w = t.shape
    gr, gc = _smooth_grad(t, sigma)
    G = jnp.stack([gr, gc], -1)
    mag2 = gr * gr + gc * gc
    safe = mag2 > 0
    mag = jnp.where(safe, jnp.sqrt(jnp.where(safe, mag2, 1.0)), 0.0)
    # non-maximum suppression across the edge (direction quantised to 45 deg)
    P = jnp.pad(mag, 1)
    nb = {(di, dj): P[1 + di:1 + di + h, 1 + dj:1 + dj + w] for di in (-1, 0, 1) for dj in (-1, 0, 1)}
    ang = jnp.mod(jnp.arctan2(gr, gc), math.pi)  # direction of the gradient, mod 180 deg
    q = jnp.mod(jnp.round(ang / (math.pi / 4)), 4).astype(jnp.int32)
    # q = 0: gradient along +col; 1: along (+row, +col); 2: along +row; 3: along (+row, -col)
    steps = [(0, 1), (1, 1), (1, 0), (1, -1)]
    f_q = sum(jnp.where(q == i, nb[st], 0.0) for i, st in enumerate(steps))
    b_q = sum(jnp.where(q == i, nb[(-st[0], -st[1])], 0.0) for i, st in enumerate(steps))
    thin = (mag >= f_q) & (mag > b_q)
    border = np.zeros((h, w), bool)
    border[1:h - 1, 1:w - 1] = True
    cand = thin & jnp.asarray(border) & (mag >= rel * jnp.max(mag)) & safe
    # raster-order rank of every candidate as matrix products (XLA:CPU compiles
    # cumsum/searchsorted slowly), then evenly spaced ranks
    cf = cand.astype(t.dtype)
    within = cf @ jnp.asarray(np.triu(np.ones((w, w))), t.dtype)  # inclusive count along the row
    before = jnp.asarray(np.tril(np.ones((h, h)), -1), t.dtype) @ within[:, -1]
    cum = jnp.round(within + before[:, None]).astype(jnp.int32).reshape(-1)
    count = cum[-1]
    k = jnp.arange(n_pts, dtype=jnp.int32)
    target = (k * jnp.maximum(count, 1)) // n_pts  # evenly spaced ranks
    valid = k < count
    idx = jnp.clip(jnp.sum(cum[None, :] <= target[:, None], axis=1), 0, h * w - 1)
    pr = (idx // w).astype(t.dtype)
    pc = (idx % w).astype(t.dtype)
    m = jnp.where(valid, mag.reshape(-1)[idx], 1.0)
    dr = jnp.where(valid, gr.reshape(-1)[idx] / m, 0.0)
    dc = jnp.where(valid, gc.reshape(-1)[idx] / m, 1.0)
    # sub-pixel along the gradient, by the same estimator as the image side
    d, _, _, _ = _edge_offset(G, pr, pc, dr, dc, reach=2)
    d = jnp.where(valid & (jnp.abs(d) <= 1.0), d, 0.0)
    pr = pr + d * dr
    pc = pc + d * dc
    off = jnp.stack([pr - ref[0], pc - ref[1]], -1)
    return off, jnp.stack([dr, dc], -1), valid, count


def _rot(off, th):
    """Rotate ``(n, 2)`` ``(row, col)`` offsets counter-clockwise on screen by ``th`` radians."""
    c, s = jnp.cos(th), jnp.sin(th)
    u, v = off[..., 0], off[..., 1]
    return jnp.stack([u * c - v * s, u * s + v * c], -1)


def _score(N, off, dirs, valid, y, x, th):
    """Steger's score at pose ``(y, x, th)``: mean over model points of ``|<R d, N(q + R p)>|``
    with bilinear samples of the contrast-normalised gradient field ``N``."""
    p = _rot(off, th)
    d = _rot(dirs, th)
    a, _ = _bilinear(N, y + p[:, 0], x + p[:, 1])
    ar, ac = a[:, 0], a[:, 1]
    s = jnp.abs(d[:, 0] * ar + d[:, 1] * ac)
    return jnp.sum(jnp.where(valid, s, 0.0)) / jnp.maximum(jnp.sum(valid), 1)


def _normalised_field(G, gmin):
    """``G / max(|G|, gmin)``: unit gradient on edges, fading to 0 where the contrast is below ``gmin``."""
    m2 = jnp.sum(G * G, axis=-1, keepdims=True)
    den = jnp.maximum(jnp.sqrt(jnp.where(m2 > 0, m2, 1.0)), gmin)
    return G / den


def _exhaustive(N, off, dirs, valid, angles, pad: int):
    """Best score and angle index at every integer position (nearest-neighbour offsets)."""
    H, W = N.shape[:2]
    Pr = jnp.pad(N[..., 0], pad)
    Pc = jnp.pad(N[..., 1], pad)
    n = off.shape[0]
    nv = jnp.maximum(jnp.sum(valid), 1)

    def one_angle(th):
        p = jnp.round(_rot(off, th)).astype(jnp.int32)
        d = _rot(dirs, th)

        def body(i, acc):
            a = jax.lax.dynamic_slice(Pr, (pad + p[i, 0], pad + p[i, 1]), (H, W))
            b = jax.lax.dynamic_slice(Pc, (pad + p[i, 0], pad + p[i, 1]), (H, W))
            return acc + jnp.where(valid[i], jnp.abs(d[i, 0] * a + d[i, 1] * b), 0.0)

        return jax.lax.fori_loop(0, n, body, jnp.zeros((H, W), N.dtype)) / nv

    def scan(carry, k):
        best, arg = carry
        s = one_angle(angles[k])
        better = s > best
        return (jnp.where(better, s, best), jnp.where(better, k, arg)), None

    init = (jnp.full((H, W), -1.0, N.dtype), jnp.zeros((H, W), jnp.int32))
    (best, arg), _ = jax.lax.scan(scan, init, jnp.arange(angles.shape[0], dtype=jnp.int32))
    return best, arg


# ---------------------------------------------------------------------------
# least-squares pose refinement (point-to-edge distances along the normals)
# ---------------------------------------------------------------------------


def _masked_median(v, mask):
    """Lower median of ``v[mask]`` (0 if the mask is empty)."""
    n = jnp.sum(mask)
    srt = jnp.sort(jnp.where(mask, v, jnp.inf))
    return jnp.where(n > 0, srt[jnp.maximum(n - 1, 0) // 2], 0.0)


def _solve3(M, b):
    """``M^-1 b`` for a symmetric positive definite 3x3 ``M`` (adjugate; NaN if singular)."""
    c00 = M[1, 1] * M[2, 2] - M[1, 2] * M[2, 1]
    c01 = M[1, 2] * M[2, 0] - M[1, 0] * M[2, 2]
    c02 = M[1, 0] * M[2, 1] - M[1, 1] * M[2, 0]
    c11 = M[0, 0] * M[2, 2] - M[0, 2] * M[2, 0]
    c12 = M[0, 2] * M[1, 0] - M[0, 0] * M[1, 2]
    c22 = M[0, 0] * M[1, 1] - M[0, 1] * M[1, 0]
    adj = jnp.array([[c00, c01, c02], [c01, c11, c12], [c02, c12, c22]])
    det = M[0, 0] * c00 + M[0, 1] * c01 + M[0, 2] * c02
    ok = det > 0
    return jnp.where(ok, adj @ b / jnp.where(ok, det, 1.0), jnp.nan)


# the refinement's normal matrix (angle as px at the outermost model point) must determine every
# pose direction: det M >= DET_MIN (tr M)^3, so the smallest eigenvalue is >= DET_MIN tr M. The
# workpiece of the docstring example: det / tr^3 >= 7.5e-3 at every step of every candidate;
# vertical stripes (no row information): |det| / tr^3 <= 3e-18, rounding
DET_MIN = 1e-6


def _ls_refine(G, off, dirs, valid, y, x, th, gmin, n_iter: int, tol: float):
    """Gauss-Newton on ``sum_i w_i (n_i . dp_i - delta_i)^2``, re-detecting edges each step.

    ``delta_i`` is the sub-pixel offset, along the rotated model normal, of the
    image edge next to model point ``i`` (:func:`_edge_offset`, +-2 grid
    lines); the weights are robust (see below). Returns the pose, whether the
    update fell below ``tol`` (px) within ``n_iter`` steps *and* the last step's normal
    matrix determined every pose direction, and the summed weight.

    Determined: ``det M >= DET_MIN * (tr M)^3`` for the weighted normal matrix ``M`` (row,
    col, and the angle as px at the outermost model point: commensurate units). Edges that are all
    parallel (stripes) leave the position along them undetermined (the aperture problem):
    ``M`` is singular up to rounding, the small regularisation alone picks a pose there, and
    a rounding-level change of the input moves it (a chain fuzzer MISMATCH between eager and
    compiled calls of 1e-3 px). Such an instance is not converged (fails closed).
    """
    dt = G.dtype
    rmax = jnp.max(jnp.where(valid, jnp.hypot(off[:, 0], off[:, 1]), 0.0))

    def step(pose):
        y, x, th = pose
        p = _rot(off, th)
        n = _rot(dirs, th)
        delta, strength, agree, ins = _edge_offset(G, y + p[:, 0], x + p[:, 1], n[:, 0], n[:, 1])
        # robust weights: an edge of the expected direction (within ~25 deg), not much
        # weaker than the instance's typical edge, and no outlier in distance (Tukey
        # biweight, scale from the median absolute deviation)
        use = valid & ins & (strength >= gmin) & (agree >= 0.9)
        use = use & (strength >= 0.25 * _masked_median(strength, use))
        med_d = _masked_median(delta, use)
        mad = _masked_median(jnp.abs(delta - med_d), use)
        c = 4.685 * jnp.maximum(1.4826 * mad, 0.1)
        u = (delta - med_d) / c
        w = jnp.where(use & (jnp.abs(u) < 1), (1 - u * u) ** 2, 0.0).astype(dt)
        # d p_i / d th for p_i = R(th) (u, v)
        jr = -p[:, 1]
        jc = p[:, 0]
        A = jnp.stack([n[:, 0], n[:, 1], n[:, 0] * jr + n[:, 1] * jc], -1)
        M = (A * w[:, None]).T @ A
        b = (A * w[:, None]).T @ delta
        tr = jnp.trace(M)
        # determined: the normal matrix with the angle as px at the outermost point (commensurate
        # with row and col) has det >= DET_MIN tr^3
        sc = jnp.stack([1.0, 1.0, 1.0 / jnp.maximum(rmax, 1.0)]).astype(dt)
        Ms = M * sc[:, None] * sc[None, :]
        det = Ms[0, 0] * (Ms[1, 1] * Ms[2, 2] - Ms[1, 2] * Ms[2, 1]) \
            - Ms[0, 1] * (Ms[1, 0] * Ms[2, 2] - Ms[1, 2] * Ms[2, 0]) + Ms[0, 2] * (Ms[1, 0] * Ms[2, 1] - Ms[1, 1] * Ms[2, 0])
        determined = det >= DET_MIN * jnp.trace(Ms) ** 3
        M = M + jnp.eye(3, dtype=dt) * (1e-9 * (tr + 1.0))
        upd = _solve3(M, b)
        return (y + upd[0], x + upd[1], th + upd[2]), upd, jnp.sum(w), determined

    def cond(c):
        i, _, upd, _, _ = c
        move = jnp.maximum(jnp.abs(upd[0]), jnp.maximum(jnp.abs(upd[1]), jnp.abs(upd[2]) * rmax))
        return (i < n_iter) & (move > tol)

    def body(c):
        i, pose, _, _, _ = c
        pose, upd, nw, det_ok = step(pose)
        return i + 1, pose, upd, nw, det_ok

    init = (0, (y, x, th), jnp.full(3, jnp.inf, dt), jnp.asarray(0.0, dt), jnp.asarray(False))
    i, pose, upd, nw, det_ok = jax.lax.while_loop(cond, body, init)
    move = jnp.maximum(jnp.abs(upd[0]), jnp.maximum(jnp.abs(upd[1]), jnp.abs(upd[2]) * rmax))
    return pose, (move <= tol) & det_ok, nw


# ---------------------------------------------------------------------------
# the op
# ---------------------------------------------------------------------------


def _auto_levels(h: int, w: int) -> int:
    lv = 1
    while lv < 4 and min(h, w) // 2 ** lv >= 12:
        lv += 1
    return lv


# Compiled with XLA:CPU's older loop emitters at optimisation level 2 when called at top level
# (fsjax._linalg.jit_fast_compile): 240 x 320 scene, 56 x 72 template, one process, interleaved
# (benchmarks/bench_fast_compile.py): compile 5.2 -> 2.3 s CPU, run time equal (73 / 83 ms float32,
# 92 / 89 ms float64), outputs equal to 3e-8 (float32) / bit-identical (float64).
@jit_fast_compile(static_argnames=("capacity", "levels", "max_points", "angle_start", "angle_extent",
                                   "angle_step", "model_contrast", "sigma", "coarse_factor",
                                   "max_candidates"))
def _shape_core(x, t, min_score, min_contrast, min_dist, *, capacity: int, levels: int, max_points: int,
                angle_start: float, angle_extent: float, angle_step: float, model_contrast: float,
                sigma: float, coarse_factor: float, max_candidates: int):
    dt = x.dtype
    H, W = x.shape
    h, w = t.shape
    ms = jnp.asarray(min_score, dt)
    gmin = jnp.asarray(min_contrast, dt)
    top = levels - 1

    # the model: edge points of the full-resolution template. A level-l model is
    # the same points with offsets divided by 2**l (exact for the block-mean pyramid,
    # whose level-l pixel i is centred at 2**l i + (2**l - 1) / 2).
    off, dirs, valid, count = _model_points(t, max_points, model_contrast, sigma, ((h - 1) / 2, (w - 1) / 2))

    # image pyramid; contrast-normalised gradient fields stacked (zero-padded) for a level loop
    ims = [x]
    for _ in range(top):
        ims.append(_down2(ims[-1]))
    G0 = jnp.stack(_smooth_grad(x, sigma), -1)
    fields = [_normalised_field(G0, gmin)]
    for im in ims[1:]:
        fields.append(_normalised_field(jnp.stack(_smooth_grad(im, sigma), -1), gmin))
    stack = jnp.stack([jnp.pad(f, ((0, H - f.shape[0]), (0, W - f.shape[1]), (0, 0))) for f in fields])

    # exhaustive search on the top level with an evenly thinned model
    n_top = max(16, max_points // 2 ** top)
    k = jnp.arange(n_top)
    pick = (k * jnp.maximum(count, 1)) // n_top
    off_t = off[pick] / 2 ** top
    dirs_t = dirs[pick]
    valid_t = valid[pick] & (k < count)
    step_top = angle_step * 2 ** top
    if angle_extent >= 360.0:
        n_ang = math.ceil(360.0 / step_top)
    else:
        n_ang = int(math.floor(angle_extent / step_top + 1e-9)) + 1
    angles = math.radians(angle_start) + math.radians(step_top) * jnp.arange(n_ang, dtype=dt)
    pad = int(math.ceil(math.hypot(h, w) / 2 / 2 ** top)) + 2
    best, arg = _exhaustive(fields[top], off_t, dirs_t, valid_t, angles, pad)
    cr, cc, _, cv, ctrunc, cnext = _greedy_peaks(best, coarse_factor * ms, min_dist / 2 ** top,
                                                  max_candidates)
    cth = angles[arg[cr, cc]]

    # coarse to fine: on every finer level search +-2 px and +-1 angle step (bilinear scores)
    dd = jnp.arange(-2, 3, dtype=dt)
    da = jnp.arange(-1, 2, dtype=dt)

    def refine(i, pose):
        lv = top - 1 - i
        f = 2.0 ** lv
        N = stack[lv]
        step = math.radians(angle_step) * f

        def one(y, x, th):
            yc = jnp.round(2 * y + 0.5)
            xc = jnp.round(2 * x + 0.5)
            Y, X, A = jnp.meshgrid(yc + dd, xc + dd, th + da * step, indexing="ij")
            Y, X, A = Y.reshape(-1), X.reshape(-1), A.reshape(-1)
            s = jax.vmap(lambda a, b, c: _score(N, off / f, dirs, valid, a, b, c))(Y, X, A)
            j = jnp.argmax(s)
            return Y[j], X[j], A[j]

        return jax.vmap(one)(*pose)

    cy, cx, cth = jax.lax.fori_loop(0, top, refine, (cr.astype(dt), cc.astype(dt), cth))

    # full resolution: least-squares refinement, then the score at the refined pose
    N0 = fields[0]

    def final(y, x, th):
        (y, x, th), conv, nw = _ls_refine(G0, off, dirs, valid, y, x, th, gmin, 12, 1e-4)
        s = _score(N0, off, dirs, valid, y, x, th)
        return y, x, th, s, conv & (nw >= 3)

    # sequential over candidates (lax.map): compiles like one candidate
    fy, fx, fth, fs, fok = jax.lax.map(lambda a: final(*a), (cy, cx, cth))
    fv = cv & fok & (fs >= ms) & jnp.isfinite(fy) & jnp.isfinite(fx) & jnp.isfinite(fth)
    sel, v, n_kept = _dedupe(fy, fx, fs, fv, min_dist, capacity)
    ang = jnp.degrees(fth[sel])
    ang = ang - 360.0 * jnp.floor((ang + 180.0) / 360.0)  # [-180, 180)
    ang = jnp.where(ang == -180.0, 180.0, ang)
    # a top-level peak that scored >= min_score was not followed: instances may be missing
    lost = ctrunc & (cnext >= ms)
    return fy[sel], fx[sel], ang, fs[sel], v, (n_kept > capacity) | lost


@register(
    family="matching",
    takes=(Image, Image),
    gives=Match,
    knobs={"min_score": LinKnob(0.5, 0.95), "min_contrast": LogKnob(0.005, 0.2)},
    differentiable=False,
    refs=[_REF_STEGER, _REF_STEGER2, _REF_TANIMOTO],
)
def shape_locate(img: Image, template: Image, /, *, min_score: float = 0.8, min_contrast: float = 0.04,
                 capacity: int = 8, min_distance: float | None = None, angle_start: float = -180.0,
                 angle_extent: float = 360.0, angle_step: float | None = None, levels: int | None = None,
                 max_points: int = 256, model_contrast: float = 0.3, sigma: float = 1.0,
                 coarse_factor: float = 0.75, max_candidates: int | None = None) -> Match:
    """Find rotated instances of a template by shape-based matching on gradient directions.

    The model is the template's edge points ``p_i`` (offsets from the template
    centre) with unit gradient directions ``d_i``. The score of a pose
    ``(q, a)`` is Steger's polarity-ignoring similarity
    ``s = (1/n) sum_i |<R_a d_i, G(q + R_a p_i)>| / max(|G|, min_contrast)``,
    the "local" variant: every point may flip contrast polarity on its own,
    so the score is invariant to the contrast sign and gain, and clutter or
    occlusion lowers it only by the fraction of model points affected. It is
    in ``[0, 1]``; a hidden point contributes 0.

    Search (coarse to fine, Tanimoto pyramids): on the top pyramid level every
    position and every angle ``angle_start + k * step * 2**(levels - 1)`` is
    scored; the best ``max_candidates`` peaks (score ``>= coarse_factor *
    min_score``, non-maximum suppression over positions) are followed down,
    each level searching +-2 px and +-1 angle step around the prediction. On
    full resolution the pose is refined by least squares: every model point
    finds the sub-pixel image edge along its rotated normal (extremum of the
    projected gradient, parabola), and a Gauss-Newton step in ``(row, col,
    angle)`` minimises the point-to-edge distances; this repeats to a fixed
    point (update < 1e-4 px, at most 12 steps). An instance is reported if the
    refinement converged and its score at the refined pose is ``>= min_score``.

    Args:
      img: image ``(H, W)``.
      template: model image ``(h, w)`` (``h <= H``, ``w <= W``); its reference
        point is its centre ``((h - 1) / 2, (w - 1) / 2)``.
      min_score: acceptance threshold on ``s`` (knob ``a``, linear on
        [0.5, 0.95]); a partly occluded instance scores about its visible
        fraction of model points.
      min_contrast: gradient magnitude (grey value per pixel) above which the
        image direction counts fully (knob ``b``, log-mapped to [0.005, 0.2]);
        weaker gradients (noise, flat areas) count proportionally less.
      capacity: maximum number of instances (static int >= 1).
      min_distance: minimum distance (px) between instances; default half
        the template's smaller side.
      angle_start, angle_extent: searched angle range in degrees (static);
        default all angles.
      angle_step: full-resolution angle step in degrees (static); default
        ``degrees(1 / r)`` with ``r`` the template half-diagonal.
      levels: pyramid levels (static); default: as many as keep the coarsest
        template side >= 12 px (at most 4).
      max_points: model points on full resolution (static); level ``l`` uses
        ``max(16, max_points // 2**l)``.
      model_contrast: model edges are template gradients above this fraction
        of the template's strongest gradient (static).
      sigma: Gaussian smoothing (px) before the gradients, on every level (static).
      coarse_factor: top-level candidates need ``coarse_factor * min_score`` (static).
      max_candidates: top-level candidates followed (static); default
        ``4 * capacity + 8``.

    Returns:
      ``Match``: ``row``/``col`` = sub-pixel position of the template centre,
      ``angle_deg`` in ``(-180, 180]`` counter-clockwise on screen,
      ``score`` = ``s`` at the refined pose, ``scale`` 1. ``truncated`` when more
      instances passed than ``capacity``, or more top-level candidates passed
      than ``max_candidates`` (instances may then be missing).

    On the alignment scene of :func:`fsjax.synth.alignment_scene` (three
    instances at 13.7, -41.3, 97.2 deg, two decoys, texture, illumination
    gradient, noise 0.01) the tests find all three within 0.1 px and 0.1 deg
    and no decoy. Fails closed under occlusion: the score falls with the
    hidden fraction of model points and the instance is dropped (not
    mislocated) once it is below ``min_score``. Fails closed on a template whose edges do
    not fix every pose direction (all edges parallel, e.g. stripes: the position along them is
    undetermined): the refinement's normal matrix is singular and no instance is reported
    (before, the regularisation picked a pose that rounding moved by 1e-3 px). No scale search.

    Example:
      One workpiece rotated by 30 deg about a sub-pixel position:

      >>> import jax.numpy as jnp, fsjax
      >>> from fsjax.synth import render_part, workpiece_template
      >>> scene = 0.3 + 0.5 * render_part((96, 112), 47.3, 55.6, 30.0)
      >>> m = fsjax.ops.shape_locate(fsjax.Image(jnp.asarray(scene)),
      ...                            fsjax.Image(jnp.asarray(workpiece_template())), capacity=2)
      >>> m.valid.tolist()
      [True, False]
      >>> abs(float(m.row[0]) - 47.3) < 0.05, abs(float(m.col[0]) - 55.6) < 0.05
      (True, True)
      >>> abs(float(m.angle_deg[0]) - 30.0) < 0.05, float(m.score[0]) > 0.9
      (True, True)
    """
    op = "shape_locate"
    H, W, h, w = _check_pair(op, img, template)
    cap = check_static_int(op, "capacity", capacity, lo=1)
    npts = check_static_int(op, "max_points", max_points, lo=8)
    check_range(op, "min_score", min_score, 0.0, 1.0)
    check_range(op, "min_contrast", min_contrast, 0.0, None, lo_open=True)
    for name, v in (("angle_start", angle_start), ("angle_extent", angle_extent), ("model_contrast",
                    model_contrast), ("sigma", sigma), ("coarse_factor", coarse_factor)):
        if not is_concrete(v):
            raise TypeError(f"{op}: argument {name!r} must be a static float")
    check_range(op, "angle_extent", angle_extent, 0.0, 360.0)
    check_range(op, "model_contrast", model_contrast, 0.0, 1.0, lo_open=True, hi_open=True)
    check_range(op, "sigma", sigma, 0.3, 5.0)
    check_range(op, "coarse_factor", coarse_factor, 0.0, 1.0, lo_open=True)
    if h < 5 or w < 5:
        raise ValueError(f"{op}: argument 'template' of shape {(h, w)} is too small (need >= 5x5)")
    if angle_step is None:
        angle_step = math.degrees(1.0 / max(1.0, 0.5 * math.hypot(h, w)))
    if not is_concrete(angle_step):
        raise TypeError(f"{op}: argument 'angle_step' must be a static float")
    check_range(op, "angle_step", angle_step, 0.01, 45.0)
    lv = _auto_levels(h, w) if levels is None else check_static_int(op, "levels", levels, lo=1, hi=6)
    if min(h, w) // 2 ** (lv - 1) < 5:
        raise ValueError(f"{op}: argument 'levels'={lv} leaves a coarsest template of "
                         f"{(h // 2 ** (lv - 1), w // 2 ** (lv - 1))} px; use fewer levels")
    if min_distance is None:
        min_distance = max(1.0, min(h, w) / 2)
    check_range(op, "min_distance", min_distance, 1.0, None)
    mc = 4 * cap + 8 if max_candidates is None else check_static_int(op, "max_candidates", max_candidates,
                                                                      lo=1)
    dt = _dtype(img, template)
    row, col, ang, s, v, trunc = _shape_core(
        img.data.astype(dt), template.data.astype(dt), min_score, min_contrast, min_distance, capacity=cap,
        levels=lv, max_points=npts, angle_start=float(angle_start), angle_extent=float(angle_extent),
        angle_step=float(angle_step), model_contrast=float(model_contrast), sigma=float(sigma),
        coarse_factor=float(coarse_factor), max_candidates=mc)
    return _fill_match(row, col, s, v, angle=ang, truncated=trunc)
