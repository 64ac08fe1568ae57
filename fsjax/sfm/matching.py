"""Descriptor matching: mutual nearest neighbour plus Lowe's ratio test, blocked so memory stays bounded.

Conventions:

* Descriptors are unit L2 vectors (RootSIFT from :mod:`fsjax.sfm.features`), so squared
  Euclidean distance is ``2 - 2 a.b`` and the nearest neighbour is the largest dot product.
* A match of descriptor ``i`` of image A is ``match[i] = j`` in image B, ``-1`` when none: fixed
  shape ``(N,)``, no variable-length lists inside ``jit``.
* Ratio test (Lowe 2004, sec. 7.1): distance to the nearest over distance to the second nearest
  ``< ratio`` (0.8 by default); mutual: ``i`` is also ``j``'s nearest neighbour in A.
* Memory: the similarity matrix is formed ``block`` rows at a time (``lax.scan``), so a pair
  costs ``block x M`` floats instead of ``N x M``; the column maxima needed for the mutual check
  are carried through the scan.
* All pairs of a set: :func:`match_pairs` runs one compiled ``lax.map`` over a list of pairs
  (one pair's blocks in memory at a time).
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from .._checks import check_range, check_static_int

__all__ = ["match_descriptors", "match_pairs"]


def _match(da, va, db, vb, ratio, block: int):
    n, m = da.shape[0], db.shape[0]
    pad = (-n) % block
    da_p = jnp.pad(da, ((0, pad), (0, 0)))
    va_p = jnp.pad(va, (0, pad))
    nb = (n + pad) // block
    neg = jnp.asarray(-jnp.inf, da.dtype)

    def compute(carry, k, a, av):
        cval, cidx = carry
        sim = a @ db.T
        sim = jnp.where(av[:, None] & vb[None, :], sim, neg)
        j1 = jnp.argmax(sim, 1).astype(jnp.int32)
        s1 = jnp.max(sim, 1)
        s2 = jnp.max(jnp.where(jnp.arange(m)[None, :] == j1[:, None], neg, sim), 1)
        bi = jnp.argmax(sim, 0)
        bv = jnp.max(sim, 0)
        better = bv > cval
        carry = (jnp.where(better, bv, cval), jnp.where(better, bi + k * block, cidx).astype(jnp.int32))
        return carry, (j1, s1, s2)

    def skip(carry, k, a, av):  # a block without a valid row changes nothing and matches nothing
        return carry, (jnp.zeros((block,), jnp.int32), jnp.full((block,), neg), jnp.full((block,), neg))

    def body(carry, k):
        a = jax.lax.dynamic_slice_in_dim(da_p, k * block, block)
        av = jax.lax.dynamic_slice_in_dim(va_p, k * block, block)
        # valid descriptors come first in fsjax's features, so the tail blocks of a set padded to
        # its largest count are skipped (one fountain image: 3 of 5 blocks of 512 rows hold keypoints)
        return jax.lax.cond(jnp.any(av), compute, skip, carry, k, a, av)

    init = (jnp.full((m,), neg), jnp.zeros((m,), jnp.int32))
    (cval, cidx), (j1, s1, s2) = jax.lax.scan(body, init, jnp.arange(nb))
    j1, s1, s2 = j1.reshape(-1)[:n], s1.reshape(-1)[:n], s2.reshape(-1)[:n]
    d1 = jnp.sqrt(jnp.maximum(2.0 - 2.0 * s1, 0.0))
    d2 = jnp.sqrt(jnp.maximum(2.0 - 2.0 * s2, 0.0))
    ok = va & jnp.isfinite(s1) & (d1 < ratio * d2) & (cidx[j1] == jnp.arange(n))
    return jnp.where(ok, j1, -1).astype(jnp.int32), d1


@partial(jax.jit, static_argnames=("block",))
def _match_jit(da, va, db, vb, ratio, block: int):
    return _match(da, va, db, vb, ratio, block)


def match_descriptors(desc_a, valid_a, desc_b, valid_b, *, ratio: float = 0.8,
                      block: int = 512) -> tuple[Int[Array, " N"], Float[Array, " N"]]:
    """Mutual nearest-neighbour matches that pass the ratio test.

    Args:
      desc_a, desc_b: ``(N, D)``, ``(M, D)`` unit descriptors. valid_a, valid_b: their masks.
      ratio: Lowe's ratio on distances (in (0, 1]).
      block: static number of rows of A per similarity block (memory ``block x M``).

    Returns:
      ``(match, dist)``: ``match (N,)`` int32 index into B or -1; ``dist (N,)`` distance to the nearest.

    Example:
        >>> from fsjax.sfm.matching import match_descriptors
        >>> a = jnp.eye(4)[:3]; b = jnp.eye(4)[jnp.asarray([2, 0, 1, 3])]
        >>> m, _ = match_descriptors(a, jnp.ones(3, bool), b, jnp.ones(4, bool), block=2)
        >>> m.tolist()
        [1, 2, 0]
    """
    da, db = jnp.asarray(desc_a), jnp.asarray(desc_b)
    if da.ndim != 2 or db.ndim != 2 or da.shape[1] != db.shape[1]:
        raise ValueError(f"match_descriptors: arguments 'desc_a', 'desc_b' must be (N, D) and (M, D), got "
                         f"{da.shape} and {db.shape}")
    check_range("match_descriptors", "ratio", ratio, 0.0, 1.0, lo_open=True)
    check_static_int("match_descriptors", "block", block, lo=1)
    return _match_jit(da, jnp.asarray(valid_a, bool), db, jnp.asarray(valid_b, bool),
                      jnp.asarray(ratio, da.dtype), int(block))


@partial(jax.jit, static_argnames=("block",))
def _match_pairs(desc, valid, pairs, ratio, block: int):
    def one(p):
        return _match(desc[p[0]], valid[p[0]], desc[p[1]], valid[p[1]], ratio, block)[0]

    return jax.lax.map(one, pairs)


def match_pairs(desc: Float[Array, "B N D"], valid: Bool[Array, "B N"], pairs, *, ratio: float = 0.8,
                block: int = 512) -> Int[Array, "P N"]:
    """:func:`match_descriptors` for a list of image pairs ``(P, 2)`` of one set, in one compiled call.

    Returns ``(P, N)``: for pair ``(i, j)``, the index in image ``j`` of each keypoint of image ``i`` or -1.
    """
    desc = jnp.asarray(desc)
    pairs = jnp.asarray(pairs, jnp.int32)
    if desc.ndim != 3:
        raise ValueError(f"match_pairs: argument 'desc' must be (B, N, D), got {desc.shape}")
    if pairs.ndim != 2 or pairs.shape[1] != 2:
        raise ValueError(f"match_pairs: argument 'pairs' must be (P, 2), got {pairs.shape}")
    check_range("match_pairs", "ratio", ratio, 0.0, 1.0, lo_open=True)
    check_static_int("match_pairs", "block", block, lo=1)
    return _match_pairs(desc, jnp.asarray(valid, bool), pairs, jnp.asarray(ratio, desc.dtype), int(block))
