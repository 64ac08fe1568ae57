"""Quadric-error mesh decimation (``Mesh -> Mesh``), by rounds of independent edge collapses.

Conventions:

* **Error metric** (Garland and Heckbert 1997): every vertex carries a quadric, the sum of
  the squared-distance quadrics ``K = p p^T`` of the planes ``p = (n, -n.x)`` of its faces,
  weighted by face area. An edge ``(a, b)`` collapses to the point ``v`` minimising
  ``v^T (Q_a + Q_b) v``: the solution of the 3x3 system where it is well conditioned and close
  to the edge, else the best of ``a``, ``b`` and the midpoint. The merged vertex keeps
  ``Q_a + Q_b``, so the error stays measured against the *original* planes: flat regions
  go first, creases and corners (several planes) last.
* **Boundaries** are kept by a constraint plane per boundary edge, through the edge and
  perpendicular to its face, weighted ``boundary_weight`` times the edge length squared;
  an interior edge joining two boundary vertices is never collapsed (it would pinch).
* **Parallel rounds** instead of a priority queue: each round takes the cheapest eighth of
  the legal edges as eligible or, while far from the target, as many as twice the collapses
  still needed, but none more than four sqrt(2) cost buckets dearer than the eighth's cut
  (costs bucketed by factors of sqrt(2); two histograms, the cost
  bucket and then a hash of the edge inside the last bucket, find the cut without a sort) and,
  as in Luby's independent sets, selects an eligible edge when its random priority (the hash,
  made unique by the edge's slot in its low bits) is the smallest among the candidates within
  one edge of either endpoint; up to six such passes run per round (fewer once no candidate
  is left), the candidates near a selected edge dropping out after each. Selected edges are therefore at least two edges apart: their
  neighbourhoods do not touch and they collapse at once, correctly (Papageorgiou and Platis
  2015 use an independence rule of this kind on the GPU). A round refuses a collapse that
  breaks the link condition (the endpoints share other neighbours than the edge's own
  triangles: it would create a non-manifold edge or a fin; counted per vertex by scatter-min
  levels over the selected edges around it), that turns a remaining face by more than ~84
  degrees for every candidate position (a fold-over) or leaves it without area, or whose
  cheapest non-folding position costs more than twice the cost it was ranked by. A refused
  edge waits until a collapse next to it changes its surroundings.
* The number of collapses of the last round is cut so that the face count lands on the
  target or one below it (an interior collapse removes two faces, a boundary one one). When no legal collapse
  remains before the target (a tetrahedron cannot be decimated), the result has more faces
  than asked: the output's valid-face count says so; nothing is forced.
* Shapes are fixed: the output has the input's vertex and face arrays; removed faces have
  ``face_valid = False`` and removed vertices ``vertex_valid = False``.
* Memory ``O(F)``. The edges are found by one sort before the first round; their slots then
  persist (a collapse renames its endpoints and merges the edge to each apex into its twin), so
  a round sorts nothing (the last one sorts its collapses by cost to land on the target).
* **Compaction**: the rounds run in two stages of array capacity (``F`` faces, then ``F / 3``;
  three edge slots per face): when the valid faces fit the smaller capacity, they and the edge
  slots they use move to the front of smaller arrays, in their order, so priorities and ties
  compare as before; the rounds after it cost about a third. Each stage is its own loop body,
  and a body is most of the compile time (fandisk float32, one process, load ~11: one stage
  4.2 s CPU and 510 ms a call, two 7.4 s and 284 ms, three (``F / 2``, ``F / 4``) 11.3 s and
  276 ms; ``python benchmarks/profile_decimate.py --old HEAD --stage-divs ...``).
* A round works on coordinate and quadric columns (structure of arrays), elementwise: the
  3x3 solve, the costs and the fold test as ``(m,)`` arrays instead of reductions over trailing
  axes of 3 and 4 (slow kernels on a CPU). That changes the last bit of some costs, so results
  are not bit-identical to the ``(m, 3)`` form; quality is (fandisk to 10 %: Hausdorff 0.00333
  vs 0.00330).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from jax import lax

from ..._checks import check_range, check_static_int
from ...registry import register
from ...types import Mesh
from ._mesh import _check_mesh

__all__ = ["decimate"]

_REFS = [
    "M. Garland, P. S. Heckbert, Surface simplification using quadric error metrics, SIGGRAPH 1997",
    "T. K. Dey, H. Edelsbrunner, S. Guha, D. V. Nekhayev, Topology preserving edge contraction, "
    "Publ. Inst. Math. (Beograd) 66(80), 1999 (the link condition)",
    "G. Papageorgiou, N. Platis, Triangular mesh simplification on the GPU, The Visual Computer 31, 2015",
    "M. Luby, A simple parallel algorithm for the maximal independent set problem, SIAM J. Comput. 15(4), 1986",
]
_INT_MAX = jnp.iinfo(jnp.int32).max
_LUBY_PASSES = 6
_STAGE_DIVS = (3,)  # later stages' face capacities: nf divided by these (arrays compacted between stages)
_MIN_CAP = 64
_N_BUCKETS = 256
_NEED_SPAN = 4  # buckets (factors of sqrt 2) the eligible costs may reach past the cheapest eighth's


def _plane_quadric(n, d):
    """Packed symmetric 4x4 quadric ``p p^T`` of planes ``p = (n, d)``; ``(..., 10)``."""
    p = jnp.concatenate([n, d[..., None]], axis=-1)
    i, j = jnp.triu_indices(4)
    return p[..., i] * p[..., j]


def _cols(p):
    """The x, y, z columns of ``(..., 3)`` points: the round works on columns (structure of
    arrays), elementwise; reductions over a trailing axis of 3 are slow kernels on a CPU."""
    return p[..., 0], p[..., 1], p[..., 2]


def _sub(u, v):
    return u[0] - v[0], u[1] - v[1], u[2] - v[2]


def _dot(u, v):
    return u[0] * v[0] + u[1] * v[1] + u[2] * v[2]


def _cross(u, v):
    return u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]


def _cost(q, v):
    """``h^T Q h`` with ``h = (v, 1)``, from the columns ``q`` of packed quadrics (slots in
    ``jnp.triu_indices(4)`` order) and the columns ``v`` of points, elementwise."""
    x, y, z = v
    c = (q[0] * x * x + q[4] * y * y + q[7] * z * z + q[9]
         + 2.0 * (q[1] * x * y + q[2] * x * z + q[5] * y * z + q[3] * x + q[6] * y + q[8] * z))
    return jnp.maximum(c, 0.0)


def _minimiser(q):
    """The point minimising a packed quadric ``[[A, b], [b^T, c]]``: ``A x = -b`` by Cramer's
    rule (``A`` symmetric, its columns from the packed slots); returns ``(x columns, det A)``."""
    c0, c1, c2, r = (q[0], q[1], q[2]), (q[1], q[4], q[5]), (q[2], q[5], q[7]), (-q[3], -q[6], -q[8])
    c12 = _cross(c1, c2)
    det = _dot(c0, c12)
    safe = jnp.where(det == 0, 1.0, det)
    return (_dot(r, c12) / safe, _dot(c0, _cross(r, c2)) / safe, _dot(c0, _cross(c1, r)) / safe), det


def _edges(faces, fvalid):
    """Undirected edges of the valid faces: ``(lo, hi, face, count, is_edge)`` per slot ``(3F,)``.

    ``face`` is one face holding the edge (the first in sort order); ``count`` the number of
    valid faces on it (1: boundary). Last, ``he_slot`` maps half-edge ``3 f + i`` (face ``f``'s
    edge from corner ``i`` to ``i + 1``) to its edge's slot.
    """
    nf = faces.shape[0]
    a = faces.reshape(-1)
    b = jnp.roll(faces, -1, axis=1).reshape(-1)
    ok = jnp.repeat(fvalid, 3)
    lo = jnp.where(ok, jnp.minimum(a, b), _INT_MAX)
    hi = jnp.where(ok, jnp.maximum(a, b), _INT_MAX)
    fid = jnp.repeat(jnp.arange(nf, dtype=jnp.int32), 3)
    lo, hi, fid, hidx = lax.sort((lo, hi, fid, jnp.arange(3 * nf, dtype=jnp.int32)), num_keys=2)
    ok = lo != _INT_MAX
    n = lo.shape[0]
    new = ok & ((lo != jnp.roll(lo, 1)) | (hi != jnp.roll(hi, 1)) | (jnp.arange(n) == 0))
    run = jnp.where(ok, jnp.cumsum(new.astype(jnp.int32)) - 1, n - 1)
    count = jax.ops.segment_sum(ok.astype(jnp.int32), run, num_segments=n)
    first = new
    idx = jnp.where(first, run, n)  # the first half-edge of each run describes the edge
    e_lo = jnp.full((n + 1,), _INT_MAX, jnp.int32).at[idx].set(lo)[:n]
    e_hi = jnp.full((n + 1,), _INT_MAX, jnp.int32).at[idx].set(hi)[:n]
    e_f = jnp.zeros((n + 1,), jnp.int32).at[idx].set(fid)[:n]
    is_edge = jnp.arange(n) < jnp.sum(new)
    he_slot = jnp.zeros((n,), jnp.int32).at[hidx].set(run)
    return e_lo, e_hi, e_f, count, is_edge, he_slot


def _face_normals(pos, faces):
    t = pos[faces]
    return jnp.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])  # length = 2 area


def _initial_quadrics(pos, faces, fvalid, boundary_weight):
    nv = pos.shape[0]
    n2 = _face_normals(pos, faces)
    dbl_area = jnp.sqrt(jnp.sum(n2 * n2, -1))
    unit = n2 / jnp.where(dbl_area > 0, dbl_area, 1.0)[:, None]
    d = -jnp.sum(unit * pos[faces[:, 0]], -1)
    kf = _plane_quadric(unit, d) * jnp.where(fvalid, 0.5 * dbl_area, 0.0)[:, None]
    q = jnp.zeros((nv, 10), pos.dtype).at[faces.reshape(-1)].add(jnp.repeat(kf, 3, axis=0))
    # boundary constraint planes
    lo, hi, ef, count, is_edge, _ = _edges(faces, fvalid)
    bnd = is_edge & (count == 1)
    lo_s, hi_s = jnp.where(bnd, lo, 0), jnp.where(bnd, hi, 0)
    e = pos[hi_s] - pos[lo_s]
    length2 = jnp.sum(e * e, -1)
    nb = jnp.cross(e, unit[ef])
    nb = nb / jnp.maximum(jnp.sqrt(jnp.sum(nb * nb, -1)), jnp.finfo(pos.dtype).tiny)[:, None]
    db = -jnp.sum(nb * pos[lo_s], -1)
    kb = _plane_quadric(nb, db) * jnp.where(bnd, boundary_weight * length2, 0.0)[:, None]
    q = q.at[lo_s].add(kb).at[hi_s].add(kb)
    on_boundary = jnp.zeros((nv,), bool).at[lo_s].max(bnd).at[hi_s].max(bnd)
    return q, on_boundary


def _small_cumsum(x):
    """Running sum of a short 1-D integer array as one windowed sum (n^2 adds, one kernel; the
    parallel scan of ``jnp.cumsum`` compiles to about nine)."""
    n = x.shape[0]
    return lax.reduce_window(x, jnp.zeros((), x.dtype), lax.add, (n,), (1,), [(n - 1, 0)])


def _spread(mark, a, b, is_edge):
    """Vertices marked, or one edge away from a marked vertex."""
    return mark.at[a].max(is_edge & mark[b]).at[b].max(is_edge & mark[a])


def _independent_edges(a, b, is_edge, eligible, prio, nv, passes=_LUBY_PASSES):
    """Eligible edges, pairwise at least two edges apart, by ``passes`` rounds of Luby's rule.

    ``prio`` holds unique ``uint32`` priorities. A pass selects each candidate whose priority is
    the smallest among the candidates within one edge of either endpoint; candidates within one
    edge of a selected endpoint then drop out, and the next pass runs on the rest. One pass
    alone selects about one edge per neighbourhood of candidates, which is few where the cheap
    edges cluster (a flat region); repeated passes approach a maximal set of such edges.
    """
    top = jnp.uint32(0xFFFFFFFF)

    def one_pass(carry):
        i, sel, cand = carry
        p = jnp.where(cand, prio, top)
        m1 = jnp.full((nv,), top, jnp.uint32).at[a].min(p).at[b].min(p)
        m2 = m1.at[a].min(jnp.where(is_edge, m1[b], top)).at[b].min(jnp.where(is_edge, m1[a], top))
        new = cand & (p == m2[a]) & (p == m2[b])
        taken = jnp.zeros((nv,), bool).at[a].max(new).at[b].max(new)
        near = _spread(taken, a, b, is_edge)
        return i + 1, sel | new, cand & ~new & ~near[a] & ~near[b]

    # the passes stop early once no candidate is left (the result is the same)
    _, sel, _ = lax.while_loop(lambda c: (c[0] < passes) & jnp.any(c[2]), one_pass,
                               (jnp.asarray(0, jnp.int32), jnp.zeros_like(eligible), eligible))
    return sel


def _common_neighbours(a, b, is_edge, partner, owner, nv, m, levels=4):
    """Per selected edge ``(a, b)``: how many vertices are neighbours of both, and whether that
    count is in doubt.

    Selected edges are two edges apart, so a vertex can neighbour the endpoints of several
    selected edges (at most about half its valence: two of them are never adjacent). Each
    vertex takes its selected edges in increasing order, ``levels`` of them, and counts the
    edges leading to each: a count of two is a common neighbour of that edge. A vertex with
    more selected edges around it than ``levels`` leaves those edges in doubt (not collapsed
    this round).
    """
    u = jnp.concatenate([a, b])
    w = jnp.concatenate([b, a])
    has = jnp.concatenate([is_edge, is_edge]) & (partner[u] >= 0) & (w != partner[u])
    e = jnp.where(has, owner[u], m)
    wd = jnp.where(has, w, nv)

    def level(_, carry):
        prev, common, covered = carry
        nxt = jnp.full((nv + 1,), m, jnp.int32).at[wd].min(jnp.where(has & (e > prev[wd]), e, m))
        hit = has & (e == nxt[wd])
        c = jnp.zeros((nv + 1,), jnp.int32).at[wd].add(hit.astype(jnp.int32))
        return nxt, common.at[jnp.where(c == 2, nxt, m)].add(1), covered | hit

    # a loop, not unrolled: one level's kernels compile once
    _, common, covered = lax.fori_loop(0, levels, level, (jnp.full((nv + 1,), -1, jnp.int32),
                                                         jnp.zeros((m + 1,), jnp.int32), jnp.zeros(e.shape, bool)))
    doubt = jnp.zeros((m + 1,), bool).at[jnp.where(has & ~covered, e, m)].set(True)[:m]
    return common[:m], doubt


def _round(state, target, nbits):
    pos, q, faces, fvalid, vvalid, on_bnd, blocked, e_lo, e_hi, fe, rounds, _ = state
    nv, m = pos.shape[0], e_lo.shape[0]
    # the edge slots are kept from round to round (one sort, before the first round): a
    # collapse renames its endpoints, and the edge (b, w) to each apex w merges into (a, w)
    count = jax.ops.segment_sum(jnp.repeat(fvalid.astype(jnp.int32), 3), fe.reshape(-1), num_segments=m)
    is_edge = count > 0
    a, b = jnp.where(is_edge, e_lo, 0), jnp.where(is_edge, e_hi, 0)
    qa = q[a] + q[b]
    qc = [qa[:, k] for k in range(10)]
    pa, pb = _cols(pos[a]), _cols(pos[b])
    mid = tuple(0.5 * (u + v) for u, v in zip(pa, pb))
    xs, det = _minimiser(qc)
    scale = (qc[0] + qc[4] + qc[7]) / 3
    elen = jnp.sqrt(_dot(_sub(pb, pa), _sub(pb, pa)))
    d = _sub(xs, mid)
    good = (jnp.abs(det) > 1e-5 * jnp.abs(scale) ** 3) & jnp.isfinite(xs[0]) & jnp.isfinite(xs[1]) \
        & jnp.isfinite(xs[2]) & (jnp.sqrt(_dot(d, d)) <= elen)
    cands = (tuple(jnp.where(good, x, c) for x, c in zip(xs, mid)), pa, pb, mid)
    costs = jnp.stack([_cost(qc, c) for c in cands], 1)  # (m, 4)
    ctab = jnp.stack([x for c in cands for x in c], 1)  # (m, 12): candidate k at columns 3k..3k+2
    cost = jnp.min(costs, axis=1)
    interior = count == 2
    legal = is_edge & (count <= 2) & ~(interior & on_bnd[a] & on_bnd[b])
    # an edge refused before (link condition, or every candidate folded) waits until a collapse
    # next to it changes its surroundings
    legal = legal & ~blocked
    # The eligible edges are the cheapest eighth or, while far from the target, as many as
    # twice the collapses still needed (the faces to remove: a sequential queue would take
    # about that many of the cheapest before their costs change much), whichever is more; by
    # costs bucketed by factors of sqrt(2) (a histogram, not a sort); inside the last bucket a
    # hash of the edge draws which ones, so a smooth run of costs does not leave one local
    # minimum per region.
    floor_c = 1e-9 * jnp.sum(jnp.where(is_edge, jnp.abs(scale) * elen * elen, 0.0)) / jnp.maximum(jnp.sum(is_edge), 1)
    bucket = jnp.floor(2.0 * jnp.log2(jnp.maximum(cost, floor_c) / floor_c))
    bucket = jnp.clip(jnp.nan_to_num(bucket, nan=_N_BUCKETS - 1), 0, _N_BUCKETS - 1).astype(jnp.int32)
    h = (a.astype(jnp.uint32) * jnp.uint32(2654435761)) ^ (b.astype(jnp.uint32) * jnp.uint32(2246822519))
    h = (h ^ (h >> 15)) * jnp.uint32(2654435769)
    n_legal = jnp.sum(legal)
    n_eighth = jnp.maximum(n_legal // 8, 1)
    n_elig = jnp.maximum(jnp.minimum(jnp.maximum(n_eighth, jnp.sum(fvalid) - target), n_legal), 1)
    hist = jax.ops.segment_sum(legal.astype(jnp.int32), bucket, num_segments=_N_BUCKETS)
    cum = _small_cumsum(hist)
    tb = jnp.argmax(cum >= n_elig)
    # ... but never costs above _NEED_SPAN buckets past the eighth's (the whole bucket then)
    tb_cap = jnp.argmax(cum >= n_eighth) + _NEED_SPAN
    n_elig = jnp.where(tb > tb_cap, cum[jnp.minimum(tb_cap, _N_BUCKETS - 1)], n_elig)
    tb = jnp.minimum(tb, tb_cap)
    # inside the last bucket, the edges with the smallest hashes (a second histogram, of the
    # hash's top 10 bits) make up the count
    hb = (h >> 22).astype(jnp.int32)
    in_tb = legal & (bucket == tb)
    cum_h = _small_cumsum(jax.ops.segment_sum(in_tb.astype(jnp.int32), hb, num_segments=1024))
    th = jnp.argmax(cum_h >= n_elig - (cum[tb] - hist[tb]))
    eligible = legal & ((bucket < tb) | (in_tb & (hb <= th)))
    # among them a random priority (the hash, as in Luby's independent sets; unique: its low
    # bits are the slot) picks edges two edges apart, many per round
    prio = (h & jnp.uint32((0xFFFFFFFF << nbits) & 0xFFFFFFFF)) | jnp.arange(m, dtype=jnp.uint32)
    sel = _independent_edges(a, b, is_edge, eligible, prio, nv)
    # link condition: common neighbours of a and b must be exactly the edge's triangles' apexes
    partner = jnp.full((nv,), -1, jnp.int32).at[jnp.where(sel, a, nv)].set(b, mode="drop") \
        .at[jnp.where(sel, b, nv)].set(a, mode="drop")
    owner = jnp.full((nv,), m, jnp.int32).at[jnp.where(sel, a, nv)].set(jnp.arange(m, dtype=jnp.int32), mode="drop") \
        .at[jnp.where(sel, b, nv)].set(jnp.arange(m, dtype=jnp.int32), mode="drop")
    common, doubt = _common_neighbours(a, b, is_edge, partner, owner, nv, m)
    # ... and two valence-3 endpoints of an interior edge span a tetrahedron (both triangles on
    # the apexes exist): collapsing would leave two faces back to back
    valence = jnp.zeros((nv,), jnp.int32).at[a].add(is_edge.astype(jnp.int32)).at[b].add(is_edge.astype(jnp.int32))
    tent = interior & (valence[a] == 3) & (valence[b] == 3)
    ok = sel & (common == count) & ~tent & ~doubt
    # fold-over: faces keeping one endpoint must not turn by more than ~84 degrees; of the four
    # candidate positions, the cheapest that folds nothing is taken
    fv = faces
    part = partner[fv]  # (nf, 3)
    moving = (part >= 0) & fvalid[:, None]
    both = jnp.any(moving[:, :, None] & (fv[:, None, :] == part[:, :, None]), axis=(1, 2))
    mv_slot = jnp.argmax(moving, axis=1)
    mv_any = jnp.any(moving, axis=1) & ~both
    e_of_face = jnp.where(mv_any, owner[jnp.take_along_axis(fv, mv_slot[:, None], 1)[:, 0]], m)
    newp = ctab[jnp.minimum(e_of_face, m - 1)]  # (nf, 12)
    t_old = [_cols(pos[fv[:, i]]) for i in range(3)]
    n_old = _cross(_sub(t_old[1], t_old[0]), _sub(t_old[2], t_old[0]))
    n_old2 = _dot(n_old, n_old)  # a face that is already degenerate cannot fold
    cosang, n_new2 = [], []
    for k in range(4):
        t_new = [tuple(jnp.where(mv_slot == i, newp[:, 3 * k + c], t_old[i][c]) for c in range(3)) for i in range(3)]
        n_new = _cross(_sub(t_new[1], t_new[0]), _sub(t_new[2], t_new[0]))
        cosang.append(_dot(n_old, n_new))
        n_new2.append(_dot(n_new, n_new))
    cosang, n_new2, n_old2 = jnp.stack(cosang, 1), jnp.stack(n_new2, 1), n_old2[:, None]
    # ... nor lose its area to rounding (a merged vertex landing on another vertex, or on the
    # line through two, leaves a normal of rounding errors and of either sign)
    eps = jnp.finfo(pos.dtype).eps
    flip = mv_any[:, None] & (n_old2 > 0) & ((cosang <= 0.1 * jnp.sqrt(n_old2 * n_new2)) | (n_new2 <= eps * n_old2))
    folds = jnp.zeros((m + 1, 4), bool).at[e_of_face].max(flip)[:m]
    costs_ok = jnp.where(folds, jnp.inf, costs)
    best = jnp.argmin(costs_ok, axis=1)
    target_pos = jnp.stack([jnp.take_along_axis(ctab, (3 * best + c)[:, None], 1)[:, 0] for c in range(3)], -1)
    # a candidate that folds nothing but costs more than the edge was ranked by is a worse
    # collapse than its turn in the order allows: the edge is refused instead
    veto = jnp.all(folds, axis=1) | (jnp.min(costs_ok, axis=1) > 2.0 * cost + 1e-6 * jnp.abs(scale) * elen * elen)
    refused = sel & (veto | (common != count) | tent | doubt)
    blocked = blocked | refused
    ok = ok & ~veto
    # land on the target: when this round would overshoot, keep the cheapest collapses needed
    # (a sort, run only then)
    removes = jnp.where(interior, 2, 1)
    need = jnp.maximum(jnp.sum(fvalid) - target, 0)

    def trim(ok):
        _, order = lax.sort((jnp.where(ok, cost, jnp.inf), jnp.arange(m, dtype=jnp.int32)), num_keys=1)
        ok_sorted = ok[order]
        cum_r = jnp.cumsum(jnp.where(ok_sorted, removes[order], 0))
        return jnp.zeros((m,), bool).at[order].set(ok_sorted & (cum_r - removes[order] < need))

    ok = lax.cond(jnp.sum(jnp.where(ok, removes, 0)) > need, trim, lambda o: o, ok)
    # collapse b into a
    to = jnp.arange(nv, dtype=jnp.int32).at[jnp.where(ok, b, nv)].set(a, mode="drop")
    pos = pos.at[jnp.where(ok, a, nv)].set(target_pos, mode="drop")
    q = q.at[jnp.where(ok, a, nv)].add(q[b], mode="drop")
    vvalid = vvalid.at[jnp.where(ok, b, nv)].set(False, mode="drop")
    on_bnd = on_bnd.at[jnp.where(ok, a, nv)].max(on_bnd[b], mode="drop")
    old = faces
    faces = to[faces]
    alive = (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])
    dying = fvalid & ~alive
    fvalid = fvalid & alive
    # a dying face (a, b, w): its edge (b, w) merges into its edge (w, a), the one without b
    x, y = old, jnp.roll(old, -1, axis=1)
    gone = to != jnp.arange(nv, dtype=jnp.int32)
    with_b = gone[x] | gone[y]
    s_keep = jnp.take_along_axis(fe, jnp.argmax(~with_b, axis=1)[:, None], 1)[:, 0]
    s_drop = jnp.take_along_axis(fe, jnp.argmax(with_b & (to[x] != to[y]), axis=1)[:, None], 1)[:, 0]
    redirect = jnp.arange(m, dtype=jnp.int32).at[jnp.where(dying, s_drop, m)].set(s_keep, mode="drop")
    fe = redirect[fe]
    e_lo, e_hi = jnp.minimum(to[e_lo], to[e_hi]), jnp.maximum(to[e_lo], to[e_hi])
    moved = jnp.zeros((nv + 1,), bool).at[jnp.where(ok, a, nv)].set(True, mode="drop")
    touched = fvalid & jnp.any(moved[faces], axis=1)
    near = jnp.zeros((nv + 1,), bool).at[jnp.where(touched[:, None], faces, nv)].set(True)
    blocked = blocked & ~near[e_lo] & ~near[e_hi]
    progress = jnp.sum(ok) + jnp.sum(refused)  # a refusal changes the next round's selection
    return (pos, q, faces, fvalid, vvalid, on_bnd, blocked, e_lo, e_hi, fe, rounds + 1,
            progress.astype(jnp.int32))


def _compact(state, fid, cap, nf):
    """Move the valid faces and the edge slots they use to the front of arrays of ``cap`` faces
    and ``3 cap`` slots, both in their order (so priorities and ties compare as before).

    ``fid`` maps a face to its index in the input. When the valid faces do not fit (the loop
    stopped early above ``cap``: at the target, out of rounds or of legal collapses), the
    returned state makes no progress and maps to no input face, so it changes nothing.
    """
    pos, q, faces, fvalid, vvalid, on_bnd, blocked, e_lo, e_hi, fe, rounds, progress = state
    m, mc = e_lo.shape[0], 3 * cap
    fits = jnp.sum(fvalid) <= cap
    fslot = jnp.where(fvalid, jnp.cumsum(fvalid, dtype=jnp.int32) - 1, cap)
    live = jnp.zeros((m,), bool).at[fe.reshape(-1)].max(jnp.repeat(fvalid, 3))
    eslot = jnp.where(live, jnp.cumsum(live, dtype=jnp.int32) - 1, mc)
    faces = jnp.zeros((cap, 3), faces.dtype).at[fslot].set(faces, mode="drop")
    fe = jnp.zeros((cap, 3), fe.dtype).at[fslot].set(eslot[fe], mode="drop")
    fid = jnp.full((cap,), nf, jnp.int32).at[fslot].set(jnp.where(fits, fid, nf), mode="drop")
    fvalid = jnp.zeros((cap,), bool).at[fslot].set(fvalid, mode="drop")
    e_lo = jnp.zeros((mc,), e_lo.dtype).at[eslot].set(e_lo, mode="drop")
    e_hi = jnp.zeros((mc,), e_hi.dtype).at[eslot].set(e_hi, mode="drop")
    blocked = jnp.zeros((mc,), bool).at[eslot].set(blocked, mode="drop")
    progress = jnp.where(fits, progress, 0)
    return (pos, q, faces, fvalid, vvalid, on_bnd, blocked, e_lo, e_hi, fe, rounds, progress), fid


@functools.partial(jax.jit, static_argnames=("max_rounds",))
def _decimate_core(pos, faces, fvalid, vvalid, target, boundary_weight, *, max_rounds):
    # Quadric costs v^T Q v cancel catastrophically far from the origin in float32: work on
    # coordinates centred on the used vertices and scaled to unit size, map back at the end.
    nv = pos.shape[0]
    used0 = jnp.zeros((nv + 1,), bool).at[jnp.where(fvalid[:, None], faces, nv)].set(True)[:nv]
    w = used0.astype(pos.dtype)[:, None]
    centre = jnp.sum(pos * w, 0) / jnp.maximum(jnp.sum(w), 1)
    size = jnp.max(jnp.where(used0[:, None], jnp.abs(pos - centre), 0.0))
    size = jnp.where(size > 0, size, 1.0)
    pos = (pos - centre) / size
    q, on_bnd = _initial_quadrics(pos, faces, fvalid, boundary_weight)
    e_lo, e_hi, _, _, is_edge, he_slot = _edges(faces, fvalid)
    e_lo, e_hi = jnp.where(is_edge, e_lo, 0), jnp.where(is_edge, e_hi, 0)

    nf = faces.shape[0]
    nbits = max(int(3 * nf).bit_length(), 1)  # the priorities' slot bits, fixed for every stage
    caps = [nf] + [c for c in (-(-nf // d) for d in _STAGE_DIVS) if c >= _MIN_CAP]
    state = (pos, q, faces, fvalid, vvalid, on_bnd, jnp.zeros(e_lo.shape, bool), e_lo, e_hi, he_slot.reshape(-1, 3),
             jnp.asarray(0, jnp.int32), jnp.asarray(1, jnp.int32))
    fid = jnp.arange(nf, dtype=jnp.int32)
    faces_out, fvalid_out = faces, fvalid
    for k in range(len(caps)):
        nxt = caps[k + 1] if k + 1 < len(caps) else 0

        def cond(s, nxt=nxt):
            n = jnp.sum(s[3])
            return (n > target) & (n > nxt) & (s[10] < max_rounds) & (s[11] > 0)

        state = lax.while_loop(cond, lambda s: _round(s, target, nbits), state)
        faces_out = faces_out.at[fid].set(state[2], mode="drop")
        fvalid_out = fvalid_out.at[fid].set(state[3], mode="drop")
        if nxt:
            state, fid = _compact(state, fid, nxt, nf)
    pos, vvalid, rounds = state[0], state[4], state[10]
    faces, fvalid = faces_out, fvalid_out
    used = jnp.zeros((pos.shape[0] + 1,), bool).at[jnp.where(fvalid[:, None], faces, pos.shape[0])].set(True)
    return pos * size + centre, faces, fvalid, vvalid & used[:-1], rounds


@register(family="mesh", takes=Mesh, gives=Mesh, differentiable=False, refs=_REFS)
def decimate(mesh: Mesh, /, *, ratio: float = 0.1, target_faces: int | None = None,
             boundary_weight: float = 1000.0, max_rounds: int = 2000) -> Mesh:
    """Reduce a triangle mesh to ``ratio`` of its faces by quadric-error edge collapses.

    Args:
      mesh: ``Mesh`` (manifold or with boundary; only valid faces count).
      ratio: fraction of the valid faces to keep, in ``(0, 1]`` (default 0.1).
      target_faces: a face count instead of ``ratio`` (>= 1; overrides it).
      boundary_weight: weight of the boundary constraint planes relative to the face
        planes (default 1000: boundaries stay put).
      max_rounds: cap on the rounds of parallel collapses (static; default 2000). The loop
        stops at the target (fandisk 12,946 -> 1,294 faces takes ~50 rounds).

    Returns:
      ``Mesh`` with the input's array shapes; removed faces and vertices are marked invalid.
      Its valid-face count is the target (or one fewer) unless no legal collapse was left
      before it (or ``max_rounds`` ran out): then it is larger.

    Example:
      An icosphere of 1,280 faces decimated to 10 %: 128 faces remain, still closed and
      oriented, and no vertex moved off the unit sphere by more than 5 %:

      >>> import jax.numpy as jnp, fsjax
      >>> v, f = fsjax.synth.icosphere(3)
      >>> d = fsjax.ops.decimate(fsjax.Mesh(jnp.asarray(v), jnp.asarray(f)), ratio=0.1)
      >>> t = fsjax.ops.mesh_topology(d)
      >>> int(t.faces), bool(t.closed), bool(t.oriented), int(t.euler)
      (128, True, True, 2)
      >>> r = jnp.linalg.norm(d.vertices[d.vertex_valid], axis=1)
      >>> bool(jnp.all(jnp.abs(r - 1) < 0.05))
      True
    """
    _check_mesh("decimate", mesh)
    if target_faces is None:
        check_range("decimate", "ratio", ratio, 0.0, 1.0, lo_open=True)
        total = jnp.sum(mesh.face_valid)
        target = jnp.ceil(ratio * total).astype(jnp.int32)
    else:
        target = jnp.asarray(check_static_int("decimate", "target_faces", target_faces, lo=1), jnp.int32)
    check_range("decimate", "boundary_weight", boundary_weight, 0.0, None)
    rounds = check_static_int("decimate", "max_rounds", max_rounds, lo=1)
    pos, faces, fvalid, vvalid, _ = _decimate_core(
        mesh.vertices, mesh.faces, mesh.face_valid, mesh.vertex_valid, target,
        jnp.asarray(boundary_weight, mesh.vertices.dtype), max_rounds=rounds)
    return Mesh(pos, faces, vertex_valid=vvalid, face_valid=fvalid, truncated=mesh.truncated)
