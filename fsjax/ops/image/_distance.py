"""Distance transforms of a ``Region`` (``Region -> Image``).

Conventions:

* The output is a *distance map*, not a grey image: each foreground pixel holds
  its distance to the nearest background pixel (``False``), in pixels (or in the
  unit of ``sampling``); background pixels hold 0. The ``[0, 1]`` convention of
  ``Image`` does not hold. Distances are measured between pixel centres on
  integer ``(row, col)`` indices.
* Border: pixels outside the image are *not* background (SciPy's convention):
  an object touching the image edge is measured only to background pixels
  inside the image.
* No background pixel at all: the frame of pixels just outside the image is taken
  as the background, so every pixel holds its distance to the image frame,
  ``min((i + 1) s0, (H - i) s0, (j + 1) s1, (W - j) s1)`` in every metric (finite;
  the chain fuzzer found the ``+inf`` this used to be, the distance to an empty
  set, flowing unflagged into later stages). Test ``region.data.all()`` to tell the
  case apart. SciPy returns distances to one virtual pixel at ``(-1, 0)``
  (``distance_transform_edt``) or ``-1`` (``distance_transform_cdt``) there.
* Metrics: ``"euclidean"`` (exact), ``"cityblock"`` (L1, ``|di| + |dj|``) and
  ``"chessboard"`` (L-infinity, ``max(|di|, |dj|)``), all exact.
* Exactness: with unit sampling every squared Euclidean distance is an integer
  computed exactly in floating point (exact in float64; in float32 while it is
  below ``2**24``, i.e. images up to about 2,900 px on a side), so the result
  is the correctly rounded square root, bit-identical to SciPy's.
* Batching is ``jax.vmap``; the data-dependent loops (``lax.while_loop``) run
  until every member of the batch is done.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from jax import lax

from ..._checks import check_choice, check_positive
from ...registry import register
from ...types import Image, Region

__all__ = ["distance_transform"]

METRICS = ("euclidean", "cityblock", "chessboard")


# ---------------------------------------------------------------------------
# 1-D passes
# ---------------------------------------------------------------------------


def _line_dist(bg, dtype):
    """Samples to the nearest ``True`` along axis 0 of ``bg`` ``(n, L)``; ``inf`` if none.

    Two sequential scans (forward and backward), vectorised over the ``L`` lanes.
    """

    def step(c, b):
        c = jnp.where(b, jnp.zeros_like(c), c + 1)
        return c, c

    init = jnp.full(bg.shape[1:], jnp.inf, dtype)
    _, fwd = lax.scan(step, init, bg)
    _, bwd = lax.scan(step, init, bg, reverse=True)
    return jnp.minimum(fwd, bwd)


def _l1_pass(g, h):
    """``out[i] = min_k g[k] + |i - k| h`` along axis 0 (two scans; exact)."""

    def step(c, gi):
        c = jnp.minimum(gi, c + h)
        return c, c

    init = jnp.full(g.shape[1:], jnp.inf, g.dtype)
    _, fwd = lax.scan(step, init, g)
    _, bwd = lax.scan(step, init, g, reverse=True)
    return jnp.minimum(fwd, bwd)


def _parabola_envelope(f, h):
    """Lower envelope of parabolas along axis 0: ``out[i] = min_k f[k] + ((i - k) h)^2``.

    Felzenszwalb & Huttenlocher (2012), vectorised over the ``L`` lanes of
    ``f`` ``(n, L)``; sites with ``f = inf`` are skipped. The envelope stack is
    kept as a linked list: when site ``q`` is pushed, ``prev[q]`` is the site
    below it and ``z[q]`` the abscissa where its parabola starts to win, so the
    stack top is always the last pushed site and a pop follows ``prev``. Both
    arrays are written at the static row ``q`` of the scan; pops and the final
    read-out gather from them (one ``lax.while_loop`` per site that runs until
    no lane pops any more). Amortised O(n) per lane.
    """
    n, L = f.shape
    dt = f.dtype
    lanes = jnp.arange(L, dtype=jnp.int32)
    x = jnp.arange(n, dtype=dt) * h
    a = f + (x * x)[:, None]  # parabola of site k: x^2 - 2 x x_k + a_k
    a_flat = a.reshape(-1)
    finite = jnp.isfinite(f)
    inf = jnp.asarray(jnp.inf, dt)

    def record(prev, z, u):
        idx = jnp.maximum(u, 0) * L + lanes
        return prev[idx], z[idx], a_flat[idx]

    def push(carry, q):
        prev, z, u, pu, zu, au = carry  # u: stack top (last pushed site), its prev, z, a
        aq, xq, ok = a[q], x[q], finite[q]
        has = u >= 0

        def cross(au, u):
            return (aq - au) / (2 * (xq - x[jnp.maximum(u, 0)]))

        s = cross(au, u)
        act = ok & has & (pu >= 0) & (s <= zu)

        def body(st):
            u, pu, zu, au, s, act = st
            nu = jnp.where(act, pu, u)
            npu, nzu, nau = record(prev, z, nu)
            npu = jnp.where(act, npu, pu)
            nzu = jnp.where(act, nzu, zu)
            nau = jnp.where(act, nau, au)
            ns = jnp.where(act, cross(nau, nu), s)
            return nu, npu, nzu, nau, ns, act & (npu >= 0) & (ns <= nzu)

        u, pu, zu, au, s, _ = lax.while_loop(lambda st: jnp.any(st[-1]), body, (u, pu, zu, au, s, act))
        linked = ok & has
        newp = jnp.where(linked, u, -1)
        newz = jnp.where(linked, s, -inf)
        prev = lax.dynamic_update_slice(prev, newp, (q * L,))
        z = lax.dynamic_update_slice(z, newz, (q * L,))
        u = jnp.where(ok, q, u)
        pu = jnp.where(ok, newp, pu)
        zu = jnp.where(ok, newz, zu)
        au = jnp.where(ok, aq, au)
        return (prev, z, u, pu, zu, au), None

    init = (jnp.full((n * L,), -1, jnp.int32), jnp.full((n * L,), -inf, dt),
            jnp.full((L,), -1, jnp.int32), jnp.full((L,), -1, jnp.int32),
            jnp.full((L,), -inf, dt), jnp.zeros((L,), dt))
    (prev, z, top, ptop, ztop, atop), _ = lax.scan(push, init, jnp.arange(n, dtype=jnp.int32))

    def read(carry, j):
        p, pp, zp, ap = carry
        xj = x[j]

        def body(st):
            p, pp, zp, ap, act = st
            nparr = jnp.where(act, pp, p)
            npp, nzp, nap = record(prev, z, nparr)
            npp = jnp.where(act, npp, pp)
            nzp = jnp.where(act, nzp, zp)
            nap = jnp.where(act, nap, ap)
            return nparr, npp, nzp, nap, act & (nzp > xj)

        act = (p >= 0) & (zp > xj)
        p, pp, zp, ap, _ = lax.while_loop(lambda st: jnp.any(st[-1]), body, (p, pp, zp, ap, act))
        xp = x[jnp.maximum(p, 0)]
        val = jnp.where(p >= 0, (ap - xp * xp) + (xj - xp) ** 2, inf)
        return (p, pp, zp, ap), val

    _, out = lax.scan(read, (top, ptop, ztop, atop), jnp.arange(n - 1, -1, -1, dtype=jnp.int32))
    return out[::-1]


# ---------------------------------------------------------------------------
# 2-D transforms
# ---------------------------------------------------------------------------


def _edt_sq(bg, s0, s1, dtype):
    """Squared Euclidean distance to the nearest ``True`` of ``bg`` ``(H, W)``."""
    g = _line_dist(bg.T, dtype) * s1  # (W, H): distance along the columns axis
    return _parabola_envelope((g * g).T, s0)


def _cityblock(bg, s0, s1, dtype):
    g = _line_dist(bg.T, dtype) * s1
    return _l1_pass(g.T, jnp.asarray(s0, dtype))


def _chessboard(bg, dtype):
    """L-infinity distance via the 45-degree rotated lattice: ``max(|di|, |dj|) = (|du| + |dv|) / 2``
    with ``u = i + j``, ``v = i - j``; the L1 transform on the ``(H + W - 1)^2`` rotated grid
    (whose off-lattice points are never background) is exact."""
    h, w = bg.shape
    n = h + w - 1
    ii, jj = jnp.meshgrid(jnp.arange(h), jnp.arange(w), indexing="ij")
    u = (ii + jj).reshape(-1)
    v = (ii - jj + (w - 1)).reshape(-1)
    grid = jnp.zeros((n, n), bool).at[u, v].set(bg.reshape(-1))
    g = _line_dist(grid.T, dtype)
    d = _l1_pass(g.T, jnp.asarray(1, dtype))
    return (d[u, v] / 2).reshape(h, w)


@functools.partial(jax.jit, static_argnames=("metric", "sampling"))
def _distance_core(mask, *, metric: str, sampling: tuple[float, float]):
    dtype = jnp.result_type(float)
    bg = ~mask
    s0, s1 = sampling
    if metric == "euclidean":
        out = jnp.sqrt(_edt_sq(bg, s0, s1, dtype))
    elif metric == "cityblock":
        out = _cityblock(bg, s0, s1, dtype)
    else:
        out = _chessboard(bg, dtype)
    # no background pixel: the frame just outside the image is the background (module notes)
    h, w = mask.shape
    i = jnp.arange(h, dtype=dtype)[:, None]
    j = jnp.arange(w, dtype=dtype)[None, :]
    frame = jnp.minimum(jnp.minimum(i + 1, h - i) * s0, jnp.minimum(j + 1, w - j) * s1)
    out = jnp.where(jnp.any(bg), out, frame)
    return jnp.where(bg, jnp.zeros((), dtype), out)


def _check_sampling(op: str, sampling) -> tuple[float, float]:
    try:
        vals = tuple(float(s) for s in (sampling if hasattr(sampling, "__len__") else (sampling, sampling)))
    except (TypeError, ValueError):
        raise TypeError(f"{op}: argument 'sampling' must be a float or a (row, col) pair of floats, "
                        f"got {sampling!r}") from None
    if len(vals) != 2:
        raise ValueError(f"{op}: argument 'sampling' must have 2 entries (row, col), got {len(vals)}")
    for v in vals:
        check_positive(op, "sampling", v)
    return vals


@register(
    family="distance",
    takes=Region,
    gives=Image,
    differentiable=False,
    refs=["P. F. Felzenszwalb, D. P. Huttenlocher, Distance transforms of sampled functions, "
          "Theory of Computing 8, 2012, 415-428",
          "G. Borgefors, Distance transformations in digital images, Computer Vision, Graphics, "
          "and Image Processing 34(3), 1986 (city-block and chessboard metrics)"],
)
def distance_transform(region: Region, /, *, metric: str = "euclidean",
                       sampling: float | tuple[float, float] = (1.0, 1.0)) -> Image:
    """Distance of every foreground pixel to the nearest background pixel (a distance map).

    ``out[p] = min_{q : region[q] = False} d(p, q)`` with ``d`` the Euclidean,
    city-block (``|di| s0 + |dj| s1``) or chessboard (``max(|di|, |dj|)``) metric
    between pixel centres; 0 on the background. The Euclidean transform is
    exact and separable: a scan per row finds the nearest background pixel along
    the row, then the lower envelope of the parabolas ``g_k^2 + ((i - k) s0)^2``
    along each column gives the squared distance (Felzenszwalb & Huttenlocher).

    Args:
      region: input mask ``(H, W)``; ``True`` is foreground.
      metric: ``"euclidean"`` (default), ``"cityblock"`` or ``"chessboard"`` (static).
      sampling: pixel spacing ``(row, col)`` (or one float for both) in a length
        unit of your choice; distances come out in that unit. Default ``(1, 1)``:
        pixels. Static; supported for ``"euclidean"`` and ``"cityblock"``, the
        chessboard metric needs unit sampling.

    Returns:
      ``Image`` holding distances (not in ``[0, 1]``): 0 on the background, >= 1
      sample spacing on the foreground. When the region has no background pixel,
      the distance to the frame just outside the image (finite; module notes).

    Matches ``scipy.ndimage.distance_transform_edt(x, sampling=...)`` to 1e-9
    (bit-identical with unit sampling) and ``distance_transform_cdt(x,
    metric="taxicab" | "chessboard")`` exactly, on thresholded ``coins()`` and
    adversarial masks (a single background pixel, thin lines, random noise);
    they differ only when there is no background (see the module notes).

    Example:
      With one background pixel at the centre of a 7x7 image, the corner is at
      distance ``sqrt(3^2 + 3^2)``, 6 in city-block and 3 in chessboard:

      >>> import jax.numpy as jnp, fsjax
      >>> m = fsjax.Region(jnp.ones((7, 7), bool).at[3, 3].set(False))
      >>> d = fsjax.ops.distance_transform(m)
      >>> abs(float(d.data[0, 0]) - 18 ** 0.5) < 1e-12
      True
      >>> [float(fsjax.ops.distance_transform(m, metric=k).data[0, 0]) for k in ("cityblock", "chessboard")]
      [6.0, 3.0]
    """
    op = "distance_transform"
    check_choice(op, "metric", metric, METRICS)
    samp = _check_sampling(op, sampling)
    if metric == "chessboard" and samp != (1.0, 1.0):
        raise ValueError(f"{op}: argument 'sampling' must be (1, 1) for metric='chessboard' "
                         f"(max(|di| s0, |dj| s1) is not supported), got {sampling!r}")
    return Image(_distance_core(region.data, metric=metric, sampling=samp))


def edt_squared(mask, sampling: tuple[float, float] = (1.0, 1.0)):
    """Squared exact Euclidean distance map of a bool array ``(H, W)`` (traceable helper
    for other families; 0 on ``False`` pixels, ``inf`` when there is none)."""
    dtype = jnp.result_type(float)
    bg = ~mask
    return jnp.where(bg, jnp.zeros((), dtype), _edt_sq(bg, float(sampling[0]), float(sampling[1]), dtype))
