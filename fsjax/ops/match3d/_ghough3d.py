"""Generalised Hough transform in 3-D (Ballard 1981): an R-table of gradient directions, voting
by every scene edge voxel, several instances by non-maximum suppression.

* **R-table.** The template is smoothed (``sigma``) and differentiated as in
  :func:`fsjax.ops.shape_locate3d`; its edge voxels (gradient magnitude above
  ``model_contrast`` of its largest; at most ``max_points``, sampled evenly in index order
  when there are more) are the model points ``u`` with their gradient directions. A direction
  is quantised on ``n_dirs`` Fibonacci directions of the upper hemisphere (the axis, not the
  sign: a contrast reversal flips every gradient and changes no bin). The R-table of bin ``b``
  lists the offsets from the model points whose direction lies within ``angle_tol_deg`` of
  bin ``b``'s centre (so a scene direction a little off its model point's still finds it), and
  from those whose own direction falls in bin ``b`` (so a scene voxel of exactly the model
  point's direction always finds it). The reference point is the template's voxel ``[0, 0, 0]``
  (``t`` of :class:`fsjax.Match3D`), so a vote is ``o = s - u``.
* **Voting.** Each scene voxel whose gradient magnitude exceeds ``edge_contrast`` of the
  scene's largest is an edge voxel in the bin of its direction (:func:`scene_bins`: a table
  over polar angle and azimuth, the nearest bin for 97 % of directions); it votes once for
  every R-table entry of that bin. All votes at once, with a static capacity: scene edge
  voxels sorted by bin, the R-table entries' vote counts summed (prefix sums), vote
  ``p < max_votes`` mapped to its entry by a running maximum of the entries' first votes and
  to its scene voxel by its rank within the entry, and scatter-added into the accumulator
  of placements (those that keep the template inside the scene, as :func:`fsjax.ops.ncc3d`),
  in chunks of 65,536 votes, as many as there are votes (the capacity bounds them; the work
  follows the count).
  More votes than ``max_votes`` is an overflow: every instance is reported invalid (reason
  ``capacity_exceeded``), never a partial count.
* **Instances.** A placement's votes count the model points whose scene voxel agrees in
  position and direction, so ``score = votes / n_model`` is in ``[0, 1]`` (the fraction of the
  model seen; on the grid's scenes 0.76-0.95 for the whole bunny, 0.27-0.38 with half of its
  surface missing). Peaks: local maxima (3x3x3) of the
  accumulator smoothed by ``[1, 2, 1] / 4`` per axis (which also breaks ties of integer
  counts), taken greedily, best first, each suppressing the peaks within ``min_distance``;
  a peak is an instance when its score reaches ``min_votes``. Sub-voxel by the 3x3x3 Newton
  peak of the smoothed accumulator (:func:`ncc3d`'s).

The accumulator equals, at every placement, the number of (R-table entry, scene edge voxel)
pairs of one bin with ``s - u = o``: the tests count those pairs by a loop and compare.
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from ..._checks import check_range, check_static_int, is_concrete
from ...registry import LinKnob, register
from ...types import Match3D, Volume, reason_code
from ._hough3d import _hemisphere
from ._shape3d import _floor, gradient3, model_of
from ._shared3d import (
    _INVALID,
    _NOT_FOUND,
    _OK,
    check_pair,
    neighbourhood3,
    newton_peak3,
    xyz_of,
)

__all__ = ["generalised_hough3d"]

_REF_BALLARD = ("D. H. Ballard, Generalizing the Hough transform to detect arbitrary shapes, Pattern "
                "Recognition 13(2), 1981, 111-122")
_REF_NW = "J. Nocedal, S. J. Wright, Numerical Optimization, 2nd ed., Springer 2006, ch. 3 (Newton's method)"
_CAPACITY = reason_code("capacity_exceeded")
_MIN_MODEL_POINTS = 8


def _bins(n_dirs: int):
    return np.asarray(_hemisphere(n_dirs)[0])


_LUT_NZ, _LUT_NPHI = 64, 256


@functools.lru_cache(maxsize=8)
def _lut(n_dirs: int):
    """Nearest bin (largest ``|cos|``) of the centre of each cell of a (polar angle, azimuth) grid
    over the upper hemisphere: ``64 x 256`` cells (1.4 degrees in both at the equator)."""
    dirs = _bins(n_dirs)
    th = (np.arange(_LUT_NZ) + 0.5) * (0.5 * np.pi / _LUT_NZ)
    phi = -np.pi + (np.arange(_LUT_NPHI) + 0.5) * (2 * np.pi / _LUT_NPHI)
    r = np.sin(th)[:, None]
    d = np.stack([r * np.cos(phi), r * np.sin(phi), np.repeat(np.cos(th)[:, None], _LUT_NPHI, 1)], -1)
    return np.argmax(np.abs(d @ dirs.T), axis=-1).astype(np.int32)


def scene_bins(g, n_dirs: int):
    """Direction bin of each gradient ``g (3, N)`` ((z, y, x) components) through :func:`_lut`: the
    axis turned onto the upper hemisphere, its (polar angle, azimuth) cell, that cell's nearest bin
    (a direction's bin is its exact nearest for 97 % of random directions; otherwise a bin at
    most 1.8 degrees farther, on 100,000 random directions: tests/ops/test_match3d_shape.py)."""
    flip = jnp.where(g[0] < 0, -1.0, 1.0).astype(g.dtype)
    th = jnp.arctan2(jnp.sqrt(g[1] * g[1] + g[2] * g[2]), jnp.abs(g[0]))
    phi = jnp.arctan2(flip * g[1], flip * g[2])
    iz = jnp.clip(jnp.floor(th * (2 * _LUT_NZ / np.pi)), 0, _LUT_NZ - 1).astype(jnp.int32)
    ip = jnp.clip(jnp.floor((phi + np.pi) * (_LUT_NPHI / (2 * np.pi))), 0, _LUT_NPHI - 1).astype(jnp.int32)
    return jnp.asarray(_lut(n_dirs))[iz, ip]


def _smooth121(A):
    for ax in range(3):
        p = jnp.pad(A, [(1, 1) if a == ax else (0, 0) for a in range(3)])
        n = A.shape[ax]
        A = 0.25 * jax.lax.slice_in_dim(p, 0, n, axis=ax) + 0.5 * A + 0.25 * jax.lax.slice_in_dim(p, 2, n + 2, axis=ax)
    return A


def _local_max3(A):
    m = jax.lax.reduce_window(A, -jnp.inf, jax.lax.max, (3, 3, 3), (1, 1, 1), "SAME")
    return A >= m


def _model_points(t, sigma, spacing, model_contrast, max_points: int):
    """The model points: ``(P, 3)`` voxel indices (k, i, j), ``(P, 3)`` unit gradient directions ((z, y, x)
    components), ``(P,)`` validity (``P = max_points``, sampled evenly in index order when there are more edge
    voxels), and their number."""
    d, h, w = t.shape
    M, dm, nM = model_of(t, sigma, spacing, model_contrast)
    T = d * h * w
    idx = jnp.nonzero(M.reshape(-1), size=T, fill_value=0)[0]
    P = max_points
    r = jnp.arange(P)
    take = jnp.where(nM > P, jnp.floor((r + 0.5) * nM / P).astype(jnp.int32), r)
    n_model = jnp.minimum(nM, P)
    mi = idx[jnp.clip(take, 0, T - 1)]
    u = jnp.stack(jnp.unravel_index(mi, (d, h, w)), -1)
    return u, dm.reshape(3, -1)[:, mi].T, r < n_model, n_model


def _rtable(u, dirm, pv, cos_tol, dirs):
    """R-table entries of model points ``u (P, 3)`` with directions ``dirm (P, 3)`` ((z, y, x)): ``(E,)`` bins,
    ``(E, 3)`` offsets and validity, ``E = P * n_dirs`` (a point is listed under every bin within ``cos_tol`` of
    its direction and under the bin a scene voxel of its very direction falls in)."""
    c = jnp.abs(dirm @ jnp.asarray(dirs[:, ::-1].T, dirm.dtype))  # bins' (x, y, z) -> (z, y, x)
    own = scene_bins(dirm.T, dirs.shape[0])
    member = (c >= cos_tol) | (jnp.arange(dirs.shape[0])[None, :] == own[:, None])
    ev = (pv[:, None] & member).reshape(-1)
    eb = jnp.broadcast_to(jnp.arange(dirs.shape[0]), member.shape).reshape(-1)
    eu = jnp.broadcast_to(u[:, None, :], member.shape + (3,)).reshape(-1, 3)
    return eb, eu, ev


def _model_table(t, sigma, spacing, model_contrast, cos_tol, dirs, max_points: int):
    """R-table entries: ``(E,)`` bins, ``(E, 3)`` offsets (k, i, j) and validity, ``E = max_points * n_dirs``;
    and the number of model points."""
    u, dirm, pv, n_model = _model_points(t, sigma, spacing, model_contrast, max_points)
    return (*_rtable(u, dirm, pv, cos_tol, dirs), n_model)


def _scene_edges(x, sigma, spacing, edge_contrast, nb: int):
    """The scene's edge voxels by bin: flat indices sorted by bin (non-edge voxels last), and each bin's count
    and first position in that order."""
    g = gradient3(x, sigma, spacing).reshape(3, -1)
    mag = jnp.sqrt(jnp.sum(g * g, 0))
    edge = (mag > edge_contrast * jnp.max(mag)) & (jnp.max(mag) > _floor(x, spacing))
    key = jnp.where(edge, scene_bins(g, nb), nb)
    order = jnp.argsort(key, stable=True)
    counts = jnp.bincount(key, length=nb + 1)
    return order, counts, jnp.cumsum(counts) - counts


VOTE_CHUNK = 2 ** 16


def _vote(edges, eb, eu, ev, sshape, tshape, max_votes: int, dt):
    """The vote accumulator over placements ``(D-d+1, H-h+1, W-w+1)`` of the R-table ``(eb, eu, ev)`` against
    the scene's edges (:func:`_scene_edges`), and the total vote count.

    The votes are cast in chunks of :data:`VOTE_CHUNK` (a ``while_loop`` over ``ceil(min(total, max_votes) /
    chunk)`` chunks), so the work follows the votes there are, not the capacity: the first ``max_votes`` votes,
    each added once, as one scatter over the whole capacity would (counts are exact integers, so the order of
    the additions does not change the sums)."""
    order, counts, start = edges
    D, H, W = sshape
    d, h, w = tshape
    ce = jnp.where(ev, counts[eb], 0)
    cum = jnp.cumsum(ce)
    total = cum[-1]
    chunk = min(max_votes, VOTE_CHUNK)
    n_cast = jnp.minimum(total, max_votes)
    first = jnp.where(ce > 0, cum - ce, max_votes)
    ent = jnp.arange(ce.shape[0], dtype=jnp.int32)
    lim = jnp.asarray([D - d, H - h, W - w])
    shp = (D - d + 1, H - h + 1, W - w + 1)
    size = shp[0] * shp[1] * shp[2]

    def body(carry):
        i, A = carry
        base = i * chunk
        p = base + jnp.arange(chunk)
        # vote p belongs to the last entry starting at or before it: the entry holding vote ``base`` (a
        # binary search, once per chunk), then the entries starting inside the chunk marked at their first
        # vote and carried forward by a running maximum (O(chunk), no search per vote)
        e0 = jnp.searchsorted(cum, base, side="right").astype(jnp.int32)
        rel = jnp.where((first >= base) & (first < base + chunk), first - base, chunk)
        marks = jnp.zeros(chunk, jnp.int32).at[rel].max(ent, mode="drop")
        e = jnp.minimum(jnp.maximum(jax.lax.cummax(marks), e0), ce.shape[0] - 1)
        rank = p - (cum[e] - ce[e])
        s = order[jnp.clip(start[eb[e]] + rank, 0, D * H * W - 1)]
        sk = jnp.stack(jnp.unravel_index(s, (D, H, W)), -1)
        o = sk - eu[e]
        inside = (p < n_cast) & jnp.all((o >= 0) & (o <= lim), axis=1)
        flat = jnp.where(inside, (o[:, 0] * shp[1] + o[:, 1]) * shp[2] + o[:, 2], size)
        return i + 1, A.at[flat].add(1.0, mode="drop")

    n_chunks = (n_cast + chunk - 1) // chunk
    _, A = jax.lax.while_loop(lambda c: c[0] < n_chunks, body, (jnp.zeros((), n_cast.dtype), jnp.zeros(size, dt)))
    return A.reshape(shp), total


def _accumulate(x, eb, eu, ev, sigma, spacing, edge_contrast, dirs, tshape, max_votes: int):
    """The vote accumulator over placements ``(D-d+1, H-h+1, W-w+1)`` and the total vote count."""
    edges = _scene_edges(x, sigma, spacing, edge_contrast, dirs.shape[0])
    return _vote(edges, eb, eu, ev, x.shape, tshape, max_votes, x.dtype)


@functools.partial(jax.jit, static_argnames=("sigma", "spacing", "n_dirs", "max_points", "max_votes",
                                             "max_instances"))
def _ghough_core(x, t, model_contrast, edge_contrast, cos_tol, min_votes, min_dist, *, sigma: float, spacing,
                 n_dirs: int, max_points: int, max_votes: int, max_instances: int):
    dt = x.dtype
    dirs = _bins(n_dirs)
    eb, eu, ev, n_model = _model_table(t, sigma, spacing, model_contrast, cos_tol, dirs, max_points)
    A, total = _accumulate(x, eb, eu, ev, sigma, spacing, edge_contrast, dirs, t.shape, max_votes)
    score = A / jnp.maximum(n_model, 1).astype(dt)
    As = _smooth121(score)
    cand = jnp.where(_local_max3(As) & (score >= min_votes), As, -jnp.inf)
    grid = jnp.stack(jnp.meshgrid(*(jnp.arange(n, dtype=dt) for n in A.shape), indexing="ij"), -1)
    md2 = jnp.asarray(min_dist, dt) ** 2

    def pick(cand, _):
        i = jnp.argmax(cand)
        ok = cand.reshape(-1)[i] > -jnp.inf
        idx = jnp.asarray(jnp.unravel_index(i, A.shape))
        v, okn = neighbourhood3(As, idx)
        off = idx.astype(dt) + newton_peak3(v, okn)
        d2 = jnp.sum((grid - idx.astype(dt)) ** 2, -1)
        cand = jnp.where(ok & (d2 <= md2), -jnp.inf, cand)
        return cand, (off, score[idx[0], idx[1], idx[2]], ok)

    _, (off, sc, ok) = jax.lax.scan(pick, cand, None, length=max_instances)
    return off, sc, ok, n_model >= _MIN_MODEL_POINTS, total > max_votes, total


@register(family="match3d", takes=(Volume, Volume), gives=Match3D, differentiable=False,
          knobs={"min_votes": LinKnob(0.1, 0.8)}, refs=[_REF_BALLARD, _REF_NW])
def generalised_hough3d(scene: Volume, template: Volume, /, *, min_votes: float = 0.22, max_instances: int = 4,
                        min_distance: float | None = None, n_dirs: int = 64, angle_tol_deg: float = 15.0,
                        sigma: float = 1.0, model_contrast: float = 0.3, edge_contrast: float = 0.2,
                        max_points: int = 512, max_votes: int = 2 ** 20) -> Match3D:
    """Find instances of a template in a scene by the generalised Hough transform in 3-D (translation).

    Ballard's R-table (1981) keyed by the quantised gradient direction: the template's edge
    voxels store their offsets to the reference point under the bins of their direction; every
    scene edge voxel votes, through the R-table of its direction's bin, for the placements that
    would put a model point on it. All votes by one scatter-add into a static-capacity buffer;
    instances are the accumulator's peaks, best first, by non-maximum suppression. The direction
    bins are axes (hemisphere), so a contrast reversal or gain changes nothing; an occluded part
    of the object only removes its votes. Translation only.

    Args:
      scene: the scene ``(D, H, W)``.
      template: the template ``(d, h, w)``, no larger than the scene, same spacing.
      min_votes: an instance needs at least this fraction of the model points' votes (knob ``a``,
        linear on [0.1, 0.8]; default 0.22: on the grid's scenes the bunny gathers 0.76-0.95 at its
        place, the same scenes without it at most 0.17, and with half of its surface missing
        0.27-0.38 (seeds 0-2, cut across x or z): thin margins both ways, see
        tests/ops/test_match3d_shape.py).
      max_instances: instances reported (static int in [1, 64]), best first.
      min_distance: two instances are at least this far apart (voxels; default half the
        template's smallest side).
      n_dirs: direction bins on the hemisphere (static int in [8, 1024]).
      angle_tol_deg: a model point is listed under every bin within this angle of its direction
        (degrees, in [0, 90]) and under its own direction's bin.
      sigma: Gaussian smoothing before the gradients (spacing unit, static; 0 = none).
      model_contrast: template edge threshold, fraction of its largest gradient magnitude.
      edge_contrast: scene edge threshold, fraction of its largest gradient magnitude.
      max_points: model points at most (static int >= 8); more edge voxels are sampled evenly.
      max_votes: vote capacity (static int); more votes than this invalidate the result
        (``capacity_exceeded``). The grid's 48^3 scenes cast 0.1-0.2 million votes.

    Returns:
      ``Match3D`` of batch shape ``(max_instances,)``, best first: ``t`` = physical ``(x, y, z)``
      position of the template's voxel ``[0, 0, 0]`` (as :func:`ncc3d`), ``R = I``,
      ``scale = 1``, ``score`` = votes at the integer peak / model points (0 for an empty slot).
      Slots beyond the instances found are ``valid`` False (``not_found``); all are invalid with
      ``invalid_input`` (fewer than 8 model points) or ``capacity_exceeded`` (vote overflow).

    Example:
      Two balls of radius 3 in a scene (centres (7, 7, 8) and (16, 16, 14) as (k, i, j)) and a ball
      template of radius 3 centred in a 13^3 box (its voxel [0, 0, 0] sits 6 voxels before the
      centre on each axis, so ``t = (2, 1, 1)`` and ``(8, 10, 10)`` as (x, y, z)): both found
      (within 0.02 voxel: the Newton step on the smoothed vote counts), each with every model
      point's vote, and the third slot empty (in float32):

      >>> import jax.numpy as jnp, fsjax
      >>> k, i, j = jnp.mgrid[0:24, 0:24, 0:22]
      >>> ball = lambda c: jnp.clip(3.5 - jnp.sqrt((k - c[0]) ** 2 + (i - c[1]) ** 2 + (j - c[2]) ** 2), 0, 1)
      >>> scene = (ball((7, 7, 8)) + ball((16, 16, 14))).astype(jnp.float32)
      >>> tpl = ball((6, 6, 6))[:13, :13, :13].astype(jnp.float32)
      >>> m = fsjax.ops.generalised_hough3d(fsjax.Volume(scene), fsjax.Volume(tpl), max_instances=3)
      >>> m.valid.tolist(), m.t.dtype.name
      ([True, True, False], 'float32')
      >>> sorted([round(float(v), 1) + 0.0 for v in m.t[n]] for n in range(2))
      [[2.0, 1.0, 1.0], [8.0, 10.0, 10.0]]
      >>> [round(float(s), 6) for s in m.score]
      [1.0, 1.0, 0.0]
    """
    T, dt, arrays, static = _hough_args("generalised_hough3d", scene, template, min_votes, max_instances,
                                        min_distance, n_dirs, angle_tol_deg, sigma, model_contrast, edge_contrast,
                                        max_points, max_votes)
    off, sc, found, ok, over, _ = _ghough_core(*arrays, **static)
    return _hough_match(jnp.eye(3, dtype=dt), xyz_of(off, scene.spacing).astype(dt), sc, found, ok, over, dt)


def _hough_args(op, scene, template, min_votes, max_instances, min_distance, n_dirs, angle_tol_deg, sigma,
                model_contrast, edge_contrast, max_points, max_votes):
    """The Hough ops' argument checks: the template's shape, the dtype, and the core's arrays and static
    keywords (shared with :func:`fsjax.ops.generalised_hough_rotation_z3d`)."""
    S, T, dt = check_pair(op, scene, template)
    check_range(op, "min_votes", min_votes, 0.0, 1.0)
    k = check_static_int(op, "max_instances", max_instances, lo=1, hi=64)
    nd = check_static_int(op, "n_dirs", n_dirs, lo=8, hi=1024)
    P = check_static_int(op, "max_points", max_points, lo=8)
    V = check_static_int(op, "max_votes", max_votes, lo=1)
    for name, v in (("sigma", sigma), ("angle_tol_deg", angle_tol_deg)):
        if not is_concrete(v):
            raise TypeError(f"{op}: argument {name!r} must be a static float")
    check_range(op, "sigma", sigma, 0.0, 8.0)
    check_range(op, "angle_tol_deg", angle_tol_deg, 0.0, 90.0)
    check_range(op, "model_contrast", model_contrast, 0.0, 1.0, lo_open=True, hi_open=True)
    check_range(op, "edge_contrast", edge_contrast, 0.0, 1.0, lo_open=True, hi_open=True)
    if min(T) < 3:
        raise ValueError(f"{op}: argument 'template' of shape {T} is too small (need >= 3 voxels per axis)")
    md = 0.5 * min(T) if min_distance is None else min_distance
    check_range(op, "min_distance", md, 0.0, None)
    arrays = (scene.data.astype(dt), template.data.astype(dt), jnp.asarray(model_contrast, dt),
              jnp.asarray(edge_contrast, dt), jnp.asarray(math.cos(math.radians(angle_tol_deg)), dt),
              jnp.asarray(min_votes, dt), jnp.asarray(md, dt))
    static = dict(sigma=float(sigma), spacing=tuple(float(v) for v in scene.spacing), n_dirs=nd, max_points=P,
                  max_votes=V, max_instances=k)
    return T, dt, arrays, static


def _hough_match(R, t, sc, found, ok, over, dt) -> Match3D:
    """The instances as a ``Match3D`` (batch ``(max_instances,)``): NaN pose and a reason where not valid
    (``capacity_exceeded`` over all on a vote overflow, ``invalid_input`` without enough model points,
    else ``not_found``), score 0 in an empty slot."""
    valid = found & ok & ~over
    reason = jnp.where(over, _CAPACITY, jnp.where(ok, _NOT_FOUND, _INVALID))
    nan = jnp.asarray(jnp.nan, dt)
    R = jnp.where(valid[:, None, None], R, nan)
    t = jnp.where(valid[:, None], t, nan)
    reason = jnp.where(valid, _OK, reason).astype(jnp.int32)
    return Match3D(R, t, jnp.where(found, sc, 0.0), valid, reason, scale=jnp.where(valid, 1.0, nan).astype(dt))
