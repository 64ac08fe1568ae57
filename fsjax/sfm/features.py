"""Local features for structure from motion: a DoG scale-space detector with orientation and a
RootSIFT-normalised 128-d float descriptor, jit-compiled with a fixed capacity and a valid mask.

Conventions:

* Input: a grey image ``(H, W)`` with values in [0, 1] (``vmap`` over a stack of images of one
  size: :func:`detect_and_describe_batch`). It is assumed to carry a blur of 0.5 px (the camera).
* Keypoints are returned as ``uv (N, 2)`` = ``(column, row)`` in the input's pixels, pixel centres on
  integers (fsjax's convention); ``scale`` is the Gaussian sigma in input pixels; ``angle_rad``
  the dominant gradient orientation in image coordinates (x right, y down), so a rotation of the
  image by ``a`` adds ``a`` to it.
* Fixed capacity ``n_max``: the strongest ``n_max`` keypoints by DoG contrast; ``valid`` marks the
  real ones (the rest hold zeros); ``truncated`` says more keypoints passed the tests than fit.
* Two programs when called eagerly: detection, then orientation and descriptors for only a bucket
  of rows that holds the valid keypoints (the count rounded up to a multiple of 512: one compile
  per bucket), padded back to ``n_max``. Their cost grows with the rows: 0.61 s for 4,096 rows vs
  0.21 s for 1,536 on one fountain image (~1,500 valid), load ~9. Under ``jit``/``vmap`` of the
  caller the whole capacity runs in one program; both paths give the same features (tested).

Method (Lowe 2004, with the deviations noted):

1. Scale space: ``n_octaves`` octaves of ``S = 3`` intervals (``S + 3`` Gaussian images, base
   sigma 1.6, separable shift-and-add blur by the incremental sigma), each octave subsampled 2x from the image of sigma
   3.2; differences of Gaussians.
2. Extrema of the DoG over the 3x3x3 neighbourhood with ``|D| > 0.5 * contrast / S``; the best
   candidates per octave are refined by up to 3 quadratic (Newton) steps in (x, y, scale) as in
   Lowe (sec. 4) and kept when the interpolated contrast ``|D| >= contrast / S`` and the edge ratio
   ``tr(H)^2 / det(H) < (r + 1)^2 / r`` with ``r = 10``.
3. Orientation: 36-bin histogram of gradient angles in a window of radius ``4.5 sigma``, Gaussian
   weight ``1.5 sigma``, smoothed, parabolic peak. Deviation: one orientation per keypoint
   (Lowe adds a keypoint for every peak above 80 % of the maximum).
4. Descriptor: 4 x 4 cells of 3 sigma, 8 orientation bins; the gradient is sampled bilinearly on a
   16 x 16 grid rotated with the keypoint (Lowe and OpenCV visit every pixel of the window; the
   grid is the fixed-shape equivalent), Gaussian weight of half the window, trilinear binning,
   L2-normalised, clipped at 0.2, renormalised; then RootSIFT (Arandjelovic and Zisserman 2012):
   L1-normalise and take the square root, so Euclidean distance of RootSIFT vectors is the
   Hellinger distance of the SIFT histograms. Descriptors are unit L2 vectors.

References: Lowe, D. G. (2004) "Distinctive image features from scale-invariant keypoints",
IJCV 60(2), 91-110, doi:10.1023/B:VISI.0000029664.99615.94; Arandjelovic, R. and Zisserman, A.
(2012) "Three things everyone should know to improve object retrieval", CVPR.
"""

from __future__ import annotations

import math
from functools import partial

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from .._checks import check_positive, check_static_int

__all__ = ["Features", "detect_and_describe", "detect_and_describe_batch"]

_S = 3
_SIGMA0 = 1.6
_EDGE_R = 10.0
_ORI_BINS = 36
_GRID = 16  # descriptor samples per side (4 per cell)


class Features(eqx.Module):
    """Keypoints and descriptors of one image (or a batch: every field gains a leading axis).

    Attributes:
        uv: ``(N, 2)`` keypoint (column, row) in input pixels.
        scale: ``(N,)`` Gaussian sigma in input pixels.
        angle_rad: ``(N,)`` orientation (image frame, x right, y down).
        response: ``(N,)`` interpolated |DoG| contrast.
        descriptors: ``(N, 128)`` RootSIFT vectors (unit L2; zeros where not valid).
        valid: ``(N,)`` real keypoints.
        truncated: more keypoints passed than ``N`` (the weakest were dropped).
    """

    uv: Float[Array, "N 2"]
    scale: Float[Array, " N"]
    angle_rad: Float[Array, " N"]
    response: Float[Array, " N"]
    descriptors: Float[Array, "N 128"]
    valid: Bool[Array, " N"]
    truncated: Bool[Array, ""]


def _kernel(sigma: float) -> np.ndarray:
    r = max(1, int(math.ceil(3.5 * sigma)))
    x = np.arange(-r, r + 1, dtype=np.float64)
    k = np.exp(-0.5 * (x / sigma) ** 2)
    return k / k.sum()


def _blur(img, sigma: float):
    """Separable Gaussian by shift-and-add (reflect padding); ``sigma`` static."""
    k = _kernel(sigma)
    r = (len(k) - 1) // 2
    h, w = img.shape
    p = jnp.pad(img, ((0, 0), (r, r)), mode="reflect")
    out = sum(float(k[i]) * p[:, i:i + w] for i in range(len(k)))
    p = jnp.pad(out, ((r, r), (0, 0)), mode="reflect")
    return sum(float(k[i]) * p[i:i + h, :] for i in range(len(k)))


def _level_sigmas() -> list[float]:
    """Incremental blurs between the S + 3 Gaussian images of one octave."""
    kk = 2.0 ** (1.0 / _S)
    sig = [_SIGMA0 * kk ** i for i in range(_S + 3)]
    return [math.sqrt(sig[i] ** 2 - sig[i - 1] ** 2) for i in range(1, _S + 3)]


def _octave(base):
    """The S + 3 Gaussian images of one octave, each blurred from the previous one by the incremental
    sigma with its own static kernel (unrolled: a ``lax.scan`` over zero-padded kernels of one length
    compiled faster but ran 2.2x slower on the upsampled first octave, 0.37 vs 0.17 s; the dynamic
    taps and the padding to the longest kernel both cost)."""
    out = [base]
    for s in _level_sigmas():
        out.append(_blur(out[-1], s))
    return jnp.stack(out)  # (S+3, H, W)


def _extrema_score(D, threshold):
    """``|D|`` where a DoG sample of an inner scale is the maximum or the minimum of its 3x3x3
    neighbourhood and ``|D| > threshold``, else 0; the 5 px border is cut (``(S, H - 10, W - 10)``).
    The 3x3 maximum and minimum of every scale come from one pass over the nine shifts (0.12 s
    against 0.29 s for two separate 3x3x3 maxima on the upsampled first octave), read from the
    interior of ``D`` (no padded copy: the border is cut anyway)."""
    h, w = D.shape[1:]
    P = D[:, 4:h - 4, 4:w - 4]
    mx = mn = P[:, 1:-1, 1:-1]
    for dy in (0, 1, 2):
        for dx in (0, 1, 2):
            sh = P[:, dy:dy + h - 10, dx:dx + w - 10]
            mx, mn = jnp.maximum(mx, sh), jnp.minimum(mn, sh)
    mx = jnp.maximum(jnp.maximum(mx[:-2], mx[1:-1]), mx[2:])
    mn = jnp.minimum(jnp.minimum(mn[:-2], mn[1:-1]), mn[2:])
    Di = P[1:-1, 1:-1, 1:-1]
    ext = ((Di >= mx) | (Di <= mn)) & (jnp.abs(Di) > threshold)
    return jnp.where(ext, jnp.abs(Di), 0.0)


def _select(rows, cap: int):
    """The ``cap`` largest scores of ``rows (R, w)`` and their flat indices (``lax.top_k`` of the
    raveled array), computed only when some score is positive (else zeros: no candidate).

    The ``lax.cond`` is also what keeps this fast: its operand is materialised as the ``(R, w)`` array
    the extremum test writes, and raveled inside the branch. Raveled in the fusion that computes it,
    XLA:CPU indexes a 1-D output (a division per element, no vectorisation): test + selection took
    0.175 s on a first-octave-sized DoG stack against 0.057 s this way (same values and indices; the
    predicate as ``max > 0``: ``any(rows > 0)`` made XLA write a boolean copy, 0.078 s).
    Under ``vmap`` (``detect_and_describe_batch``) the ``cond`` becomes a ``select`` and that saving
    is lost, not the result: 4 fountain images 2.23 s CPU before and after. A ``lax.map`` over the
    images instead gave the same features but 1.18 s or 3.3 s from call to call (load ~10), so the
    batch stays ``vmap``ped."""
    return jax.lax.cond(jnp.max(rows) > 0, lambda r: tuple(jax.lax.top_k(r.reshape(-1), cap)),
                        lambda r: (jnp.zeros((cap,), r.dtype), jnp.zeros((cap,), jnp.int32)), rows)


def _deriv(D, ob, H, W, s, y, x):
    """Value, gradient and Hessian of the DoG at integer (s, y, x) (vectors of candidates), from one
    gather of the 3x3x3 neighbourhood. ``D`` is every octave's DoG stack flattened into one buffer;
    ``ob``, ``H``, ``W`` give each candidate's octave offset and size (one trace for all octaves)."""
    L = _S + 2
    s = jnp.clip(s, 1, L - 2)
    y = jnp.clip(y, 1, H - 2)
    x = jnp.clip(x, 1, W - 2)
    o = np.stack(np.meshgrid([-1, 0, 1], [-1, 0, 1], [-1, 0, 1], indexing="ij"), -1).reshape(27, 3)
    ss, yy, xx = s[:, None] + o[:, 0], y[:, None] + o[:, 1], x[:, None] + o[:, 2]
    P = D[ob[:, None] + (ss * H[:, None] + yy) * W[:, None] + xx].reshape(-1, 3, 3, 3)

    def at(ds, dy, dx):
        return P[:, 1 + ds, 1 + dy, 1 + dx]

    c = at(0, 0, 0)
    gx = 0.5 * (at(0, 0, 1) - at(0, 0, -1))
    gy = 0.5 * (at(0, 1, 0) - at(0, -1, 0))
    gs = 0.5 * (at(1, 0, 0) - at(-1, 0, 0))
    dxx = at(0, 0, 1) + at(0, 0, -1) - 2 * c
    dyy = at(0, 1, 0) + at(0, -1, 0) - 2 * c
    dss = at(1, 0, 0) + at(-1, 0, 0) - 2 * c
    dxy = 0.25 * (at(0, 1, 1) - at(0, 1, -1) - at(0, -1, 1) + at(0, -1, -1))
    dxs = 0.25 * (at(1, 0, 1) - at(1, 0, -1) - at(-1, 0, 1) + at(-1, 0, -1))
    dys = 0.25 * (at(1, 1, 0) - at(1, -1, 0) - at(-1, 1, 0) + at(-1, -1, 0))
    g = jnp.stack([gx, gy, gs], -1)
    Hm = jnp.stack([jnp.stack([dxx, dxy, dxs], -1), jnp.stack([dxy, dyy, dys], -1),
                    jnp.stack([dxs, dys, dss], -1)], -2)
    return c, g, Hm, s, y, x


def _solve3(Hm, g):
    """Batched 3x3 solve ``Hm^-1 g`` by the adjugate; ``ok`` false where |det| is tiny (relative)."""
    a = Hm
    c00 = a[:, 1, 1] * a[:, 2, 2] - a[:, 1, 2] * a[:, 2, 1]
    c01 = a[:, 1, 2] * a[:, 2, 0] - a[:, 1, 0] * a[:, 2, 2]
    c02 = a[:, 1, 0] * a[:, 2, 1] - a[:, 1, 1] * a[:, 2, 0]
    c10 = a[:, 0, 2] * a[:, 2, 1] - a[:, 0, 1] * a[:, 2, 2]
    c11 = a[:, 0, 0] * a[:, 2, 2] - a[:, 0, 2] * a[:, 2, 0]
    c12 = a[:, 0, 1] * a[:, 2, 0] - a[:, 0, 0] * a[:, 2, 1]
    c20 = a[:, 0, 1] * a[:, 1, 2] - a[:, 0, 2] * a[:, 1, 1]
    c21 = a[:, 0, 2] * a[:, 1, 0] - a[:, 0, 0] * a[:, 1, 2]
    c22 = a[:, 0, 0] * a[:, 1, 1] - a[:, 0, 1] * a[:, 1, 0]
    det = a[:, 0, 0] * c00 + a[:, 0, 1] * c01 + a[:, 0, 2] * c02
    scale = jnp.max(jnp.abs(a), axis=(1, 2))
    ok = jnp.abs(det) > 1e-9 * scale ** 3
    inv_det = 1.0 / jnp.where(ok, det, 1.0)
    adj = jnp.stack([jnp.stack([c00, c10, c20], -1), jnp.stack([c01, c11, c21], -1),
                     jnp.stack([c02, c12, c22], -1)], -2)
    return jnp.where(ok[:, None], jnp.einsum("nij,nj->ni", adj, g) * inv_det[:, None], 0.0), ok


def _refine(D, ob, H, W, s, y, x, contrast):
    """Up to 3 Newton steps in (x, y, scale); returns sub-pixel position, contrast and a keep mask."""
    L = _S + 2
    ok = jnp.ones_like(s, dtype=bool)
    off = jnp.zeros(s.shape + (3,), D.dtype)
    for _ in range(3):
        c, g, Hm, s, y, x = _deriv(D, ob, H, W, s, y, x)
        off, good = _solve3(Hm, -g)
        ok = ok & good
        step = jnp.round(off).astype(jnp.int32)
        move = jnp.any(jnp.abs(off) > 0.5, -1)
        x = jnp.where(move, x + step[:, 0], x)
        y = jnp.where(move, y + step[:, 1], y)
        s = jnp.where(move, s + step[:, 2], s)
        inside = (s >= 1) & (s <= L - 2) & (y >= 1) & (y <= H - 2) & (x >= 1) & (x <= W - 2)
        ok = ok & inside
    c, g, Hm, s, y, x = _deriv(D, ob, H, W, s, y, x)
    off, good = _solve3(Hm, -g)
    ok = ok & good & jnp.all(jnp.abs(off) < 0.6, -1)
    val = c + 0.5 * jnp.sum(g * off, -1)
    tr = Hm[:, 0, 0] + Hm[:, 1, 1]
    det2 = Hm[:, 0, 0] * Hm[:, 1, 1] - Hm[:, 0, 1] ** 2
    edge_ok = (det2 > 0) & (tr * tr * _EDGE_R < (_EDGE_R + 1) ** 2 * det2)
    ok = ok & edge_ok & (jnp.abs(val) >= contrast / _S)
    return x + off[:, 0], y + off[:, 1], s + off[:, 2], jnp.abs(val), ok


def _bilinear(buf, pyr, x, y):
    """Bilinear samples at (x, y) (N, P) of level ``lv`` of each keypoint's octave in the flat
    buffer ``buf``; ``pyr = (offset, h, w, lv)`` per keypoint (N, 1). One gather per corner."""
    ob, h, w, lv = pyr
    x = jnp.clip(x, 0.0, w - 1.0)
    y = jnp.clip(y, 0.0, h - 1.0)
    x0 = jnp.clip(jnp.floor(x).astype(jnp.int32), 0, w - 2)
    y0 = jnp.clip(jnp.floor(y).astype(jnp.int32), 0, h - 2)
    fx, fy = x - x0, y - y0
    i = ob + (lv * h + y0) * w + x0
    return ((1 - fy) * ((1 - fx) * buf[i] + fx * buf[i + 1]) + fy * ((1 - fx) * buf[i + w] + fx * buf[i + w + 1]))


def _grads(G):
    gx = jnp.pad(0.5 * (G[:, :, 2:] - G[:, :, :-2]), ((0, 0), (0, 0), (1, 1)))
    gy = jnp.pad(0.5 * (G[:, 2:, :] - G[:, :-2, :]), ((0, 0), (1, 1), (0, 0)))
    return gx, gy


_ORI_GRID = 17  # orientation window samples per side (radius 4.5 sigma -> spacing 0.56 sigma)


def _orientation(gx, gy, pyr, x, y, sig):
    """Dominant orientation of each keypoint: 36-bin histogram of gradients sampled on a grid of
    radius 4.5 sigma (Gaussian weight 1.5 sigma), smoothed twice, parabolic peak."""
    t = jnp.linspace(-1.0, 1.0, _ORI_GRID)
    oy, ox = jnp.meshgrid(t, t, indexing="ij")
    ox, oy = ox.ravel(), oy.ravel()
    inside = (ox * ox + oy * oy) <= 1.0
    rad = 4.5 * sig[:, None]
    px = x[:, None] + ox * rad
    py = y[:, None] + oy * rad
    ddx = _bilinear(gx, pyr, px, py)
    ddy = _bilinear(gy, pyr, px, py)
    mag = jnp.sqrt(ddx * ddx + ddy * ddy)
    ang = jnp.arctan2(ddy, ddx)
    r2 = (ox * ox + oy * oy) * 4.5 ** 2  # in sigma^2
    wgt = jnp.exp(-r2 / (2 * 1.5 ** 2)) * inside
    b = jnp.floor((ang + jnp.pi) * (_ORI_BINS / (2 * jnp.pi))).astype(jnp.int32) % _ORI_BINS
    n = x.shape[0]
    seg = (jnp.arange(n)[:, None] * _ORI_BINS + b).ravel()
    hist = jax.ops.segment_sum((wgt * mag).ravel(), seg, n * _ORI_BINS).reshape(n, _ORI_BINS)
    for _ in range(2):
        hist = (jnp.roll(hist, 1, 1) + jnp.roll(hist, -1, 1) + hist) / 3.0
    k = jnp.argmax(hist, 1)
    take = lambda j: jnp.take_along_axis(hist, (j % _ORI_BINS)[:, None], 1)[:, 0]  # noqa: E731
    l_, c_, r_ = take(k - 1), take(k), take(k + 1)
    den = l_ - 2 * c_ + r_
    nz = jnp.abs(den) > 0
    d = jnp.where(nz, 0.5 * (l_ - r_) / jnp.where(nz, den, 1.0), 0.0)
    return (k + 0.5 + d) * (2 * jnp.pi / _ORI_BINS) - jnp.pi


def _descriptor(gx, gy, pyr, x, y, sig, theta):
    """RootSIFT descriptors (N, 128) of keypoints at octave coordinates."""
    t = (jnp.arange(_GRID) + 0.5) * (4.0 / _GRID)  # cell units in [0, 4]
    gyy, gxx = jnp.meshgrid(t, t, indexing="ij")
    gxx, gyy = gxx.ravel(), gyy.ravel()
    wgauss = jnp.exp(-((gxx - 2) ** 2 + (gyy - 2) ** 2) / (2 * 2.0 ** 2))
    centres = jnp.arange(4) + 0.5
    wx = jnp.maximum(0.0, 1 - jnp.abs(gxx[:, None] - centres))  # (G2, 4)
    wy = jnp.maximum(0.0, 1 - jnp.abs(gyy[:, None] - centres))
    wsp = (wy[:, :, None] * wx[:, None, :]).reshape(-1, 16)  # (G2, 16) cells row-major
    cw = 3.0 * sig[:, None]
    ax, ay = (gxx - 2) * cw, (gyy - 2) * cw
    c, s = jnp.cos(theta)[:, None], jnp.sin(theta)[:, None]
    px = x[:, None] + c * ax - s * ay
    py = y[:, None] + s * ax + c * ay
    ddx = _bilinear(gx, pyr, px, py)
    ddy = _bilinear(gy, pyr, px, py)
    mag = jnp.sqrt(ddx * ddx + ddy * ddy) * wgauss
    rel = jnp.arctan2(ddy, ddx) - theta[:, None]
    ob = (rel % (2 * jnp.pi)) * (8 / (2 * jnp.pi))  # in [0, 8)
    dd = jnp.abs(ob[..., None] - jnp.arange(8))
    dd = jnp.minimum(dd, 8 - dd)
    wo = jnp.maximum(0.0, 1 - dd) * mag[..., None]  # (N, G2, 8)
    d = jnp.einsum("gc,ngo->nco", wsp.astype(wo.dtype), wo).reshape(x.shape[0], 128)
    nrm = lambda v, o: v / jnp.maximum(o, 1e-12)  # noqa: E731
    d = nrm(d, jnp.linalg.norm(d, axis=1, keepdims=True))
    d = jnp.minimum(d, 0.2)
    d = nrm(d, jnp.linalg.norm(d, axis=1, keepdims=True))
    d = nrm(d, jnp.sum(d, axis=1, keepdims=True))
    return jnp.sqrt(d)


def _upsample2(img):
    """2x bilinear upsampling; output pixel j sits at input coordinate j / 2."""
    h, w = img.shape
    a = jnp.zeros((h, 2 * w - 1), img.dtype).at[:, ::2].set(img).at[:, 1::2].set(0.5 * (img[:, 1:] + img[:, :-1]))
    b = jnp.zeros((2 * h - 1, 2 * w - 1), img.dtype).at[::2].set(a).at[1::2].set(0.5 * (a[1:] + a[:-1]))
    return b


def _keypoints(img, contrast, n_max: int, n_octaves: int, upsample: bool):
    """Scale space, extrema and refinement: the gradient buffers of every octave and the ``n_max``
    strongest keypoints sorted by contrast (valid ones first), plus the count that passed."""
    if upsample:
        img = _upsample2(img)
    base = _blur(img, math.sqrt(_SIGMA0 ** 2 - (1.0 if upsample else 0.5) ** 2))
    Ds, gxs, gys, cands = [], [], [], []
    offD = offG = 0
    for o in range(n_octaves):
        G = _octave(base)
        D = G[1:] - G[:-1]  # (S+2, H, W)
        H, W = D.shape[1:]
        # inner scales and a 5 px border excluded by slicing (a constant mask would be folded by XLA)
        score = _extrema_score(D, 0.5 * contrast / _S)
        hi, wi = H - 10, W - 10
        score = score.reshape(-1, wi)  # rows (scale, y): never raveled inside the fusion (see _select)
        cap = min(max(n_max >> max(o - int(upsample), 0), 64), score.size)
        val, idx = _select(score, cap)
        full = lambda v, cap=cap: jnp.full((cap,), v, jnp.int32)  # noqa: E731
        cands.append((val, idx // (hi * wi) + 1, (idx // wi) % hi + 5, idx % wi + 5, full(o), full(offD), full(offG),
                      full(H), full(W)))
        gx, gy = _grads(G[1:_S + 2])
        Ds.append(D.ravel())
        gxs.append(gx.ravel())
        gys.append(gy.ravel())
        offD += D.size
        offG += gx.size
        base = G[_S][::2, ::2]
    D, gx, gy = jnp.concatenate(Ds), jnp.concatenate(gxs), jnp.concatenate(gys)
    val, s, y, x, oc, oD, oG, H, W = (jnp.concatenate(a) for a in zip(*cands))
    xr, yr, sr, resp, ok = _refine(D, oD, H, W, s, y, x, contrast)
    ok = ok & (val > 0)
    n_pass = jnp.sum(ok)
    _, sel = jax.lax.top_k(jnp.where(ok, resp, -1.0), n_max)
    kp = tuple(a[sel] for a in (xr, yr, sr, resp, oc, oG, H, W, ok))
    return gx, gy, kp, n_pass


def _describe(gx, gy, kp, n_pass, dtype, upsample: bool, n_max: int):
    """Orientation and descriptor of the keypoints ``kp`` (any count ``<= n_max``), returned padded
    with invalid rows (zeros) to ``n_max``."""
    xr, yr, sr, resp, oc, oG, H, W, v = kp
    sig = _SIGMA0 * 2.0 ** (sr / _S)  # in octave pixels
    lvl = jnp.clip(jnp.round(sr), 1, _S + 1).astype(jnp.int32) - 1
    pyr = (oG[:, None], H[:, None], W[:, None], lvl[:, None])
    th = _orientation(gx, gy, pyr, xr, yr, sig)
    desc = _descriptor(gx, gy, pyr, xr, yr, sig, th)
    f = 2.0 ** (oc.astype(dtype) - (1 if upsample else 0))
    uv = jnp.stack([xr * f, yr * f], -1)
    pad = n_max - v.shape[0]

    def z(a):  # zero where not valid, padded to n_max
        a = jnp.where(v.reshape(v.shape + (1,) * (a.ndim - 1)), a, 0.0)
        return jnp.pad(a, ((0, pad),) + ((0, 0),) * (a.ndim - 1))

    return Features(uv=z(uv), scale=z(sig * f), angle_rad=z(th), response=z(resp), descriptors=z(desc).astype(dtype),
                    valid=jnp.pad(v, (0, pad)), truncated=n_pass > n_max)


@partial(jax.jit, static_argnames=("n_max", "n_octaves", "upsample"))
def _detect(img, contrast, n_max: int, n_octaves: int, upsample: bool):
    """The whole detector at full capacity: one program (used under ``jit`` / ``vmap``)."""
    gx, gy, kp, n_pass = _keypoints(img, contrast, n_max, n_octaves, upsample)
    return _describe(gx, gy, kp, n_pass, img.dtype, upsample, n_max)


_keypoints_jit = jax.jit(_keypoints, static_argnames=("n_max", "n_octaves", "upsample"))


@partial(jax.jit, static_argnames=("dtype", "upsample", "n_max", "cap"))
def _describe_jit(gx, gy, kp, n_pass, dtype, upsample: bool, n_max: int, cap: int):
    return _describe(gx, gy, tuple(a[:cap] for a in kp), n_pass, dtype, upsample, n_max)


_keypoints_batch = jax.jit(jax.vmap(_keypoints, in_axes=(0, None, None, None, None)),
                           static_argnums=(2, 3, 4))


@partial(jax.jit, static_argnames=("dtype", "upsample", "n_max", "cap"))
def _describe_batch(gx, gy, kp, n_pass, dtype, upsample: bool, n_max: int, cap: int):
    return jax.vmap(lambda a, b, k, m: _describe(a, b, tuple(x[:cap] for x in k), m, dtype, upsample, n_max))(
        gx, gy, kp, n_pass)


_DESC_BUCKET = 512


def _capacity(valid, n_max: int) -> int:
    """Rows carried through orientation and description: the valid count rounded up to a multiple
    of ``_DESC_BUCKET`` (one compile per bucket), at most ``n_max``."""
    k = int(jnp.max(jnp.sum(valid, -1)))
    return min(n_max, max(_DESC_BUCKET, -(-k // _DESC_BUCKET) * _DESC_BUCKET))


def _run(img, contrast, n_max: int, n_octaves: int, upsample: bool, batch: bool) -> Features:
    """Eager path: keypoints first, then orientation and descriptors only for a bucket of rows that
    holds the valid ones (valid keypoints come first). Traced input takes the one-program path."""
    if isinstance(img, jax.core.Tracer) or isinstance(contrast, jax.core.Tracer):
        if batch:
            return _detect_full_batch(img, contrast, n_max, n_octaves, upsample)
        return _detect(img, contrast, n_max, n_octaves, upsample)
    if batch:
        gx, gy, kp, n_pass = _keypoints_batch(img, contrast, n_max, n_octaves, upsample)
        return _describe_batch(gx, gy, kp, n_pass, img.dtype, upsample, n_max, _capacity(kp[-1], n_max))
    gx, gy, kp, n_pass = _keypoints_jit(img, contrast, n_max, n_octaves, upsample)
    return _describe_jit(gx, gy, kp, n_pass, img.dtype, upsample, n_max, _capacity(kp[-1], n_max))


def _check(fn, img, n_max, n_octaves, contrast, batch):
    img = jnp.asarray(img)
    if not jnp.issubdtype(img.dtype, jnp.floating):
        img = img.astype(jnp.float32)
    nd = 3 if batch else 2
    if img.ndim != nd:
        raise ValueError(f"{fn}: argument 'image' must have {nd} dimensions ({'B, ' if batch else ''}H, W), "
                         f"got shape {tuple(img.shape)}")
    check_static_int(fn, "n_max", n_max, lo=1)
    check_static_int(fn, "n_octaves", n_octaves, lo=1, hi=8)
    check_positive(fn, "contrast", contrast)
    h, w = img.shape[-2:]
    if min(h, w) >> (n_octaves - 2) < 16:
        raise ValueError(f"{fn}: argument 'n_octaves' must leave the last octave >= 16 px, got {n_octaves} "
                         f"octaves for a {h}x{w} image")
    return img


def detect_and_describe(image, *, n_max: int = 4096, n_octaves: int = 5, contrast: float = 0.04,
                        upsample: bool = True) -> Features:
    """DoG keypoints with orientation and RootSIFT descriptors of one grey image (see the module notes).

    Args:
      image: ``(H, W)`` grey values in [0, 1].
      n_max: static capacity (the strongest by contrast are kept).
      n_octaves: octaves (the last must be >= 16 px on its short side).
      upsample: start with an octave at twice the input resolution (Lowe's first octave -1, as
        OpenCV and COLMAP do): most small-scale keypoints come from it.
      contrast: DoG contrast threshold (Lowe's 0.04 over the 3 intervals, as OpenCV's default).

    Returns:
      :class:`Features`.

    Example:
        >>> from fsjax.sfm.features import detect_and_describe
        >>> yy, xx = np.mgrid[:96, :96]
        >>> img = jnp.asarray(np.exp(-((xx - 40.0) ** 2 + (yy - 50.0) ** 2) / (2 * 4.0 ** 2)))
        >>> f = detect_and_describe(img, n_max=8, n_octaves=3)
        >>> i = int(np.argmax(np.asarray(f.response)))
        >>> np.round(np.asarray(f.uv[i])).tolist(), bool(np.isclose(np.linalg.norm(f.descriptors[i]), 1))
        ([40.0, 50.0], True)
    """
    img = _check("detect_and_describe", image, n_max, n_octaves, contrast, False)
    return _run(img, jnp.asarray(contrast, img.dtype), int(n_max), int(n_octaves), bool(upsample), False)


def detect_and_describe_batch(images, *, n_max: int = 4096, n_octaves: int = 5, contrast: float = 0.04,
                              upsample: bool = True) -> Features:
    """:func:`detect_and_describe` ``vmap``ped over ``(B, H, W)`` images of one size (one compile)."""
    img = _check("detect_and_describe_batch", images, n_max, n_octaves, contrast, True)
    return _run(img, jnp.asarray(contrast, img.dtype), int(n_max), int(n_octaves), bool(upsample), True)


@partial(jax.jit, static_argnames=("n_max", "n_octaves", "upsample"))
def _detect_full_batch(img, contrast, n_max: int, n_octaves: int, upsample: bool):
    return jax.vmap(lambda im: _detect(im, contrast, n_max, n_octaves, upsample))(img)
