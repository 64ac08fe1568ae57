"""Private helpers shared by the matching modules (:mod:`._correlation`, :mod:`._shape`).

Static checks of an (image, template) pair, greedy non-maximum suppression on a
score map or a candidate list, and the finite-filled :class:`~fsjax.Match`.
Conventions are those stated in :mod:`fsjax.ops.matching._correlation`.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ...types import Image, Match


def _check_pair(op: str, img: Image, tpl: Image, tname: str = "template", same: bool = False):
    """Static shape checks of an (image, template) pair; returns ``(H, W, h, w)``."""
    H, W = img.data.shape[-2:]
    h, w = tpl.data.shape[-2:]
    if same and (h, w) != (H, W):
        raise ValueError(f"{op}: argument {tname!r} has shape {(h, w)}; it must equal the shape of "
                         f"'img' {(H, W)}")
    if h > H or w > W:
        raise ValueError(f"{op}: argument {tname!r} of shape {(h, w)} is larger than 'img' {(H, W)} "
                         f"in at least one axis; the valid score map would be empty")
    return H, W, h, w


def _dtype(img: Image, tpl: Image):
    return jnp.result_type(img.data.dtype, tpl.data.dtype)


def _local_max(S):
    """Pixels >= all 8 neighbours (outside the map counts as -inf)."""
    Hm, Wm = S.shape
    P = jnp.pad(S, 1, constant_values=-jnp.inf)
    m = jnp.ones(S.shape, bool)
    for i in range(3):
        for j in range(3):
            if i == 1 and j == 1:
                continue
            m = m & (S >= P[i:i + Hm, j:j + Wm])
    return m


def _greedy_peaks(S, thr, min_dist, k: int):
    """Greedy non-maximum suppression on a score map.

    Candidates are the local maxima with ``S >= thr``; repeatedly take the best
    remaining one and drop every candidate within Euclidean distance
    ``<= min_dist`` of it. Returns ``(rows, cols, scores, valid, truncated,
    next_score)`` for the first ``k`` picks (descending score); ``truncated``
    says a ``(k + 1)``-th pick existed and ``next_score`` is its score (0 if
    none). Exact (scans the whole map ``k + 1`` times).
    """
    Hm, Wm = S.shape
    dt = S.dtype
    cand = jnp.where(_local_max(S) & (S >= thr) & jnp.isfinite(S), S, -jnp.inf)
    R = jnp.arange(Hm)[:, None]
    C = jnp.arange(Wm)[None, :]
    md2 = jnp.asarray(min_dist, dt) ** 2

    def body(i, carry):
        cand, rows, cols, scores, valid = carry
        idx = jnp.argmax(cand)
        s = cand.reshape(-1)[idx]
        r, c = (idx // Wm).astype(jnp.int32), (idx % Wm).astype(jnp.int32)
        ok = s > -jnp.inf
        rows = rows.at[i].set(r)
        cols = cols.at[i].set(c)
        scores = scores.at[i].set(jnp.where(ok, s, 0.0))
        valid = valid.at[i].set(ok)
        d2 = ((R - r) ** 2 + (C - c) ** 2).astype(dt)
        cand = jnp.where(ok & (d2 <= md2), -jnp.inf, cand)
        return cand, rows, cols, scores, valid

    init = (cand, jnp.zeros(k + 1, jnp.int32), jnp.zeros(k + 1, jnp.int32), jnp.zeros(k + 1, dt),
            jnp.zeros(k + 1, bool))
    _, rows, cols, scores, valid = jax.lax.fori_loop(0, k + 1, body, init)
    return rows[:k], cols[:k], scores[:k], valid[:k], valid[k], scores[k]


def _dedupe(rows, cols, scores, valid, min_dist, k: int):
    """Greedy NMS on a candidate list: best first, drop those within ``min_dist`` of a kept one.

    Returns ``(sel, valid, n_kept)``: indices of the first ``k`` kept candidates
    (descending score; index any per-candidate field with it), whether each of
    those slots holds a kept one, and how many were kept in all.
    """
    n = rows.shape[0]
    key = jnp.where(valid, scores, -jnp.inf)
    order = jnp.argsort(-key, stable=True)
    r, c, v = rows[order], cols[order], valid[order]
    md2 = jnp.asarray(min_dist, r.dtype) ** 2

    def body(i, kept):
        d2 = (r - r[i]) ** 2 + (c - c[i]) ** 2
        clash = jnp.any(kept & (d2 <= md2))
        return kept.at[i].set(v[i] & jnp.logical_not(clash))

    kept = jax.lax.fori_loop(0, n, body, jnp.zeros(n, bool))
    # stable compaction: kept ones first, in score order
    pos = jnp.argsort(jnp.logical_not(kept), stable=True)
    sel = order[pos][:k]
    n_kept = jnp.sum(kept)
    return sel, kept[pos][:k], n_kept


def _fill_match(row, col, score, valid, angle=None, truncated=False):
    """A ``Match`` with invalid slots filled by finite zeros (scale 1)."""
    z = jnp.zeros_like(row)
    row = jnp.where(valid, row, z)
    col = jnp.where(valid, col, z)
    score = jnp.where(valid, score, z)
    angle = z if angle is None else jnp.where(valid, angle, z)
    return Match(row, col, score, valid=valid, angle_deg=angle, scale=jnp.ones_like(row),
                 truncated=truncated)
