"""The covariance of every indexed point's own ``k`` nearest points, without neighbour lists.

Normals and GICP covariances need, per point, only the *set* of its ``k`` nearest points (their
covariance does not depend on their order). :func:`self_cov_sorted` finds that set in the grid's
27-cell block by a threshold instead of a sorted top-``k`` list (XLA:CPU's ``lax.top_k`` costs
~1-4 us per row, 70-75 % of a self-query at 20,000-100,000 points; ``docs/benchmarks_points.md``):

1. the candidates of the block, their squared distances ``d`` in the search's own arithmetic
   (:func:`fsjax.ops.points._search._query_grid_knn`'s loop-free first pass);
2. keys ``floor(d Q / L)`` (``Q = 32767``, int16) with ``L`` the block's certified limit
   (the squared distance to its faces, less 64 ulp): rounding and ``floor`` are monotone, so a key
   order is never the reverse of the distance order;
3. the smallest key ``t`` with at least ``k`` keys ``<= t``: 15 bisection steps of a vectorised
   count (int16 lanes; ~4x faster than ``top_k`` on 100,000 rows of 304 candidates);
4. exactly ``k`` keys ``<= t`` and ``t < Q``: those are the ``k`` nearest (every other candidate has
   a larger key, so a strictly larger distance; every point outside the block is farther than
   ``L``), the same set as :func:`knn`'s; their moments are masked sums over the candidates.

A row is *not* answered (``ok`` False) when its block overflows the candidate slots, its k-th
distance reaches ``L``, or more than ``k`` keys tie at ``t`` (a bucket holding the k-th and the
(k+1)-th distance: ~0.5 % of rows on a scanned surface, most rows of an exact lattice): the caller
computes those rows from exact neighbour lists. The covariance is ``E[e e^T] - E[e] E[e]^T`` of
the offsets ``e = p - q`` from the query point (small numbers: no cancellation of coordinates).
"""

from __future__ import annotations

import jax.numpy as jnp
from jax import lax

from ._search import GridIndex, _batched, _block_slots, _fixed_slots

_Q = 32767  # key levels (int16)
_STEPS = 15  # bisection steps: 2^15 > _Q
_B = 1024  # query rows per batch


def self_cov_sorted(g: GridIndex, k: int):
    """Covariance ``(N, 3, 3)`` of each indexed point's ``k`` nearest indexed points (itself included),
    rows in the grid's sorted order, and ``ok`` ``(N,)``: the rows answered (see the module doc; the
    others, invalid points' rows included, hold garbage for the caller to replace).

    Two passes over the rows (``_B`` at a time), each computing the candidates' distances: the
    bisection, then the masked sums (in one pass, XLA:CPU made the sums after the bisection's loop
    2.5x slower than the two passes together; 100,000 bunny points, k = 30: 259 ms float32, 273 ms
    float64, against 291 / 362 ms for the sorted top-k lists of ``_self_knn_sorted``)."""
    n = g.spts.shape[0]
    dtype = g.spts.dtype
    C = _fixed_slots(k)
    eps = jnp.finfo(dtype).eps
    xyz = (g.spts[:, 0], g.spts[:, 1], g.spts[:, 2])

    def candidates(q):
        """Offsets ``p - q`` of the block's candidates, their keys, and whether the block fit."""
        pos, live, total, bound = _block_slots(g, q, C)
        dx, dy, dz = (c[pos] - q[:, i:i + 1] for i, c in enumerate(xyz))
        d2 = (dx * dx + dy * dy) + dz * dz  # the search's own arithmetic and order
        b = jnp.maximum(bound, 0.0)
        lim = (b * b) * (1 - 64 * eps)
        scale = jnp.where(lim > 0, _Q / jnp.where(lim > 0, lim, 1.0), 0.0)
        x = d2 * scale[:, None]
        key = jnp.where(live & (x < _Q), jnp.floor(x), _Q).astype(jnp.int16)
        return (dx, dy, dz), key, total <= C

    def threshold(q):
        _, key, fits = candidates(q)
        lo = jnp.zeros(q.shape[0], jnp.int16)
        hi = jnp.full(q.shape[0], _Q, jnp.int16)

        def step(_, lh):  # a fori_loop: unrolled, the 15 steps measured 3.5x slower (100,000 rows)
            lo, hi = lh
            mid = lo + (hi - lo) // 2
            ge = jnp.sum((key <= mid[:, None]).astype(jnp.int16), axis=1) >= k
            return jnp.where(ge, lo, mid + 1), jnp.where(ge, mid, hi)

        _, t = lax.fori_loop(0, _STEPS, step, (lo, hi))
        return t, fits & (t < _Q)

    def moments(q, t):
        e, key, _ = candidates(q)
        sel = key <= t[:, None]
        z = jnp.zeros((), dtype)
        terms = [jnp.where(sel, a, z) for a in (*e, e[0] * e[0], e[1] * e[1], e[2] * e[2], e[0] * e[1],
                                                 e[0] * e[2], e[1] * e[2])]
        # one variadic reduction (nine separate sums measured 1.2x slower)
        sums = lax.reduce(tuple(terms) + (sel.astype(jnp.int32),), (z,) * 9 + (jnp.int32(0),),
                          lambda a, b: tuple(x + y for x, y in zip(a, b)), (1,))
        m = jnp.stack(sums[:3], -1) / k
        s2 = jnp.stack(sums[3:9], -1) / k
        cov = jnp.stack([s2[:, 0], s2[:, 3], s2[:, 4], s2[:, 3], s2[:, 1], s2[:, 5], s2[:, 4], s2[:, 5], s2[:, 2]],
                        -1).reshape(-1, 3, 3) - m[:, :, None] * m[:, None, :]
        return cov, sums[9] == k  # exactly k keys at or below t: no tie across the cut

    B = min(_B, n)
    nv = g.cstart[-1]
    t, ok1 = _batched(threshold, (g.spts,), B, nv)
    cov, ok2 = _batched(moments, (g.spts, t), B, nv)
    return cov, ok1 & ok2 & (jnp.arange(n) < nv)
