"""Ray-mesh intersection (Moller-Trumbore) for hard shadows and sun penumbrae.

Conventions: world coordinates; a ray is ``origin + s * direction`` with ``s > s_min``;
directions need not be unit length (``s`` is then in units of the direction's length).

* :func:`intersect` finds the nearest hit of arbitrary rays by brute force, chunked over the
  triangles with ``lax.scan`` (memory ``O(rays x chunk)``): exact, for small meshes and
  as the reference of the faster paths.
* :func:`occluded_parallel` answers "does the ray towards a distant light hit anything?"
  for many points and ONE direction (all rays parallel, as for the sun): the triangles are
  projected along the direction onto a plane, binned into a ``grid x grid`` cell grid with a
  fixed per-cell ``capacity`` (overflow counted and flagged per ray, never silent), and each
  ray is tested with Moller-Trumbore against its cell's triangles only. It is exact ray
  casting, not a shadow map: no depth bias, no resolution-dependent aliasing.
* :func:`sun_visibility` averages :func:`occluded_parallel` over a fixed set of directions
  filling the solar disc (angular diameter 0.53 deg by default) for penumbrae.

Self-shadowing: a shadow ray starts on the surface; pass the point's own face in
``ignore_face`` and a small ``s_min`` (default ``1e-6`` times the scene size). A neighbouring
face can still shadow at grazing light (the usual terminator artefact of flat faces).
"""

from __future__ import annotations

import functools
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._checks import check_range, check_static_int
from ..types import Mesh
from .raster import _bin
from .shading import unit

__all__ = ["Hit", "intersect", "occluded_parallel", "sun_visibility", "sun_directions"]


class Hit(eqx.Module):
    """Nearest ray-mesh hits (``(N,)`` per field): ``s`` ray parameter (inf if none), ``face_id``
    (-1 if none), ``u``/``v`` barycentrics of vertices 1 and 2, ``hit`` bool."""

    s: jax.Array
    face_id: jax.Array
    u: jax.Array
    v: jax.Array
    hit: jax.Array


def _mt(o, d, v0, e1, e2, s_min):
    """Moller & Trumbore (1997) for rays ``(N, 3)`` x triangles ``(C, 3)`` (or ``(N, C, 3)``).

    Returns ``(s, u, v, ok)`` of shape ``(N, C)``."""
    if v0.ndim == 2:
        v0, e1, e2 = v0[None], e1[None], e2[None]
    dd = d[:, None, :]
    p = jnp.cross(dd, e2)
    det = jnp.sum(e1 * p, -1)
    scale = jnp.sqrt(jnp.sum(e1 * e1, -1) * jnp.sum(e2 * e2, -1) * jnp.sum(dd * dd, -1))
    good = jnp.abs(det) > 64 * jnp.finfo(det.dtype).eps * scale
    inv = 1.0 / jnp.where(good, det, 1.0)
    sv = o[:, None, :] - v0
    u = jnp.sum(sv * p, -1) * inv
    q = jnp.cross(sv, e1)
    v = jnp.sum(dd * q, -1) * inv
    s = jnp.sum(e2 * q, -1) * inv
    ok = good & (u >= 0) & (v >= 0) & (u + v <= 1) & (s > s_min)
    return s, u, v, ok


def _check_mesh(mesh, fn: str):
    if not isinstance(mesh, Mesh):
        raise TypeError(f"{fn}(mesh=...): expected a Mesh, got {type(mesh).__name__}")
    if mesh.faces.shape[0] == 0:
        raise ValueError(f"{fn}(mesh=...): the mesh is empty (0 faces)")


def _tri(mesh: Mesh, fn: str):
    if not isinstance(mesh, Mesh):
        raise TypeError(f"{fn}(mesh=...): expected a Mesh, got {type(mesh).__name__}")
    if mesh.faces.shape[0] == 0:
        raise ValueError(f"{fn}(mesh=...): the mesh is empty (0 faces)")
    T = mesh.vertices[mesh.faces]
    v0, e1, e2 = T[:, 0], T[:, 1] - T[:, 0], T[:, 2] - T[:, 0]
    ok = mesh.face_valid & jnp.all(jnp.isfinite(T), axis=(1, 2))
    return jnp.where(ok[:, None], v0, 0.0), jnp.where(ok[:, None], e1, 0.0), jnp.where(ok[:, None], e2, 0.0), ok


def intersect(mesh: Mesh, origins, directions, *, s_min=0.0, chunk: int = 1024) -> Hit:
    """Nearest intersection of each ray with the mesh, brute force over triangle chunks.

    Moller-Trumbore per (ray, triangle); the nearest hit with ``s > s_min`` wins (ties to the
    lowest face id). Invalid faces and faces with non-finite vertices are skipped. Cost
    ``O(N F)``: use it for small meshes and validation.

    Args:
      mesh: one :class:`fsjax.Mesh`.
      origins, directions: ``(N, 3)`` world rays (directions non-zero; not normalised here).
      s_min: smallest accepted ray parameter.
      chunk: static number of triangles per scan step.

    Returns:
      :class:`Hit`.

    Example:
        >>> m = fsjax.Mesh(jnp.asarray([[0.0, 0, 2], [1, 0, 2], [0, 1, 2]]), jnp.asarray([[0, 1, 2]]))
        >>> h = fsjax.render.intersect(m, jnp.asarray([[0.25, 0.25, 0.0]]), jnp.asarray([[0.0, 0, 1]]))
        >>> float(h.s[0]), int(h.face_id[0]), float(h.u[0]), float(h.v[0])
        (2.0, 0, 0.25, 0.25)
    """
    _check_mesh(mesh, "intersect")
    dt = mesh.vertices.dtype
    o = jnp.asarray(origins, dt).reshape(-1, 3)
    d = jnp.asarray(directions, dt).reshape(-1, 3)
    chunk = int(min(chunk, mesh.faces.shape[0]))
    return _intersect(mesh, o, d, s_min, chunk)


@functools.partial(jax.jit, static_argnames=("chunk",))
def _intersect(mesh, o, d, s_min, chunk):
    # jitted at module level: an eager lax.scan over a closure compiled again on every call
    v0, e1, e2, ok = _tri(mesh, "intersect")
    F = v0.shape[0]
    nch = -(-F // chunk)
    pad = nch * chunk - F
    ids = jnp.arange(nch * chunk, dtype=jnp.int32)
    okp = jnp.concatenate([ok, jnp.zeros(pad, bool)])
    padf = lambda a: jnp.concatenate([a, jnp.zeros((pad, 3), a.dtype)])  # noqa: E731
    xs = (padf(v0).reshape(nch, chunk, 3), padf(e1).reshape(nch, chunk, 3), padf(e2).reshape(nch, chunk, 3),
          okp.reshape(nch, chunk), ids.reshape(nch, chunk))
    N = o.shape[0]
    init = (jnp.full(N, jnp.inf, o.dtype), jnp.full(N, -1, jnp.int32), jnp.zeros(N, o.dtype), jnp.zeros(N, o.dtype))

    def step(carry, x):
        a0, a1, a2, okc, idc = x
        s, u, v, hit = _mt(o, d, a0, a1, a2, s_min)
        hit = hit & okc[None, :]
        s = jnp.where(hit, s, jnp.inf)
        k = jnp.argmin(s, axis=1)
        sb = jnp.take_along_axis(s, k[:, None], 1)[:, 0]
        better = sb < carry[0]
        new = (jnp.where(better, sb, carry[0]), jnp.where(better, idc[k], carry[1]),
               jnp.where(better, jnp.take_along_axis(u, k[:, None], 1)[:, 0], carry[2]),
               jnp.where(better, jnp.take_along_axis(v, k[:, None], 1)[:, 0], carry[3]))
        return new, None

    (s, f, u, v), _ = jax.lax.scan(step, init, xs)
    return Hit(s=s, face_id=f, u=u, v=v, hit=f >= 0)


class Occlusion(eqx.Module):
    """Result of :func:`occluded_parallel`: ``occluded`` (N,) bool, ``incomplete`` (N,) bool
    (the ray's cell dropped triangles: the answer may miss an occluder), ``overflow`` int32
    number of dropped (triangle, cell) pairs."""

    occluded: jax.Array
    incomplete: jax.Array
    overflow: jax.Array


def _basis(L):
    a = jnp.where(jnp.abs(L[0]) < 0.9, jnp.asarray([1.0, 0.0, 0.0], L.dtype), jnp.asarray([0.0, 1.0, 0.0], L.dtype))
    a = a - jnp.dot(a, L) * L
    a = a / jnp.linalg.norm(a)
    return a, jnp.cross(L, a)


@functools.partial(jax.jit, static_argnames=("grid", "capacity", "pairs", "batch", "fn"))
def _grid_occlusion(mesh, points, L, ignore_face, s_min, grid, capacity, pairs, batch, fn):
    """Any-hit of the parallel rays ``points + s * L`` through a grid binned along ``L``.

    Returns ``occluded (N,)``, ``incomplete (N,)``, ``overflow`` and the buffer sizes that
    would have held everything: the fullest cell's count and the total (triangle, cell) pairs.
    Jitted at module level (its ``lax.map`` over a closure compiled again on every eager call).
    """
    grid = check_static_int(fn, "grid", grid, lo=1)
    capacity = check_static_int(fn, "capacity", capacity, lo=1)
    v0, e1, e2, ok = _tri(mesh, fn)
    P = jnp.asarray(points, v0.dtype).reshape(-1, 3)
    N = P.shape[0]
    ign = jnp.full(N, -1, jnp.int32) if ignore_face is None else jnp.asarray(ignore_face, jnp.int32).reshape(N)
    Vv = jnp.where(mesh.vertex_valid[:, None] & jnp.all(jnp.isfinite(mesh.vertices), -1, keepdims=True),
                   mesh.vertices, jnp.nan).astype(v0.dtype)
    lo, hi = jnp.nanmin(Vv, axis=0), jnp.nanmax(Vv, axis=0)
    if s_min is None:
        s_min = 1e-6 * jnp.linalg.norm(hi - lo)
    a, b = _basis(L)
    T = jnp.stack([v0, v0 + e1, v0 + e2], axis=1)
    pa = jnp.where(ok[:, None], T @ a, 0.0)
    pb = jnp.where(ok[:, None], T @ b, 0.0)
    amin = jnp.min(jnp.where(ok[:, None], pa, jnp.inf))
    amax = jnp.max(jnp.where(ok[:, None], pa, -jnp.inf))
    bmin = jnp.min(jnp.where(ok[:, None], pb, jnp.inf))
    bmax = jnp.max(jnp.where(ok[:, None], pb, -jnp.inf))
    span = jnp.maximum(jnp.maximum(amax - amin, bmax - bmin), jnp.finfo(v0.dtype).tiny)
    cell = span * (1.0 + 1e-9) / grid
    a0, b0 = amin, bmin
    # a triangle covers cells floor(min) .. floor(max) (plus a rounding margin)
    tol = 1e-7
    c0 = jnp.floor((jnp.min(pa, 1) - a0) / cell - tol)
    c1 = jnp.floor((jnp.max(pa, 1) - a0) / cell + tol)
    r0 = jnp.floor((jnp.min(pb, 1) - b0) / cell - tol)
    r1 = jnp.floor((jnp.max(pb, 1) - b0) / cell + tol)
    if pairs is None:
        pairs = min(grid * grid * capacity, max(64 * v0.shape[0], 4 * grid * grid))
    table, count, kept, _, _ = _bin(c0, c1, r0, r1, ok, grid, grid, 1, capacity, pairs)
    qa = jnp.floor((P @ a - a0) / cell)
    qb = jnp.floor((P @ b - b0) / cell)
    inside = (qa >= 0) & (qa < grid) & (qb >= 0) & (qb < grid) & jnp.isfinite(qa) & jnp.isfinite(qb)
    cid = jnp.where(inside, qb.astype(jnp.int32) * grid + qa.astype(jnp.int32), 0)

    def one(args):
        p, c, ig, ins = args
        ids = table[c]
        g = jnp.maximum(ids, 0)
        use = (ids >= 0) & (ids != ig) & ins
        _, _, _, hit = _mt(p[None], L[None], v0[g][None], e1[g][None], e2[g][None], s_min)
        return jnp.any(hit[0] & use)

    occ = jax.lax.map(one, (P, cid, ign, inside), batch_size=min(batch, N))  # (N,)
    lost = (count - kept)[cid] > 0
    return (occ, inside & lost, jnp.sum(count - kept).astype(jnp.int32), jnp.max(count).astype(jnp.int32),
            jnp.sum(count).astype(jnp.int32))


def _pow2(n: int) -> int:
    return 1 << max(0, int(n - 1).bit_length())


def _occlusion_grown(run, capacity, pairs, fn):
    """Run ``run(capacity, pairs)``; when eager, with ``capacity`` / ``pairs`` left at their
    defaults (``None``), re-run once with buffers sized from the measured need if anything was
    dropped, so an eager answer is complete. A capacity the caller passes is kept and flagged;
    under ``jit`` the buffers are static and overflow is flagged (``incomplete``, ``overflow``)."""
    cap = 128 if capacity is None else check_static_int(fn, "capacity", capacity, lo=1)
    out = run(cap, pairs)
    ovf, need_cap, need_pairs = out[2], out[3], out[4]
    if (capacity is None or pairs is None) and not isinstance(ovf, jax.core.Tracer) and int(ovf) > 0:
        cap2 = max(cap, _pow2(int(need_cap))) if capacity is None else cap
        pairs2 = pairs if pairs is not None else _pow2(int(need_pairs))
        out = run(cap2, pairs2)
    return out[:3]


def occluded_parallel(mesh: Mesh, points, direction, *, ignore_face=None, s_min=None, grid: int = 64,
                      capacity: int | None = None, pairs: int | None = None, batch: int = 256) -> Occlusion:
    """Whether the ray from each point along ``direction`` (towards a distant light) hits the mesh.

    All rays are parallel, so the mesh is projected along ``direction`` onto the plane spanned
    by an orthonormal pair ``(a, b)``; the projected triangles are binned into a
    ``grid x grid`` cell grid over their bounding box (at most ``capacity`` per cell), and
    each ray is tested exactly (Moller-Trumbore, ``s > s_min``) against the triangles of
    the cell its projection falls in.

    Args:
      mesh: one :class:`fsjax.Mesh`.
      points: ``(N, 3)`` ray origins (e.g. visible surface points).
      direction: ``(3,)`` direction towards the light; zero length is refused.
      ignore_face: optional ``(N,)`` int face id per point to skip (the face the point lies on).
      s_min: smallest accepted ray parameter (default ``1e-6`` x the mesh's bounding-box diagonal).
      grid: static cells per side; capacity: static triangles per cell (default 128); pairs:
        static size of the (triangle, cell) pair buffer (default
        ``min(grid^2 capacity, max(64 F, 4 grid^2))``; pairs beyond it count as overflow);
        batch: static number of points tested together (memory). Left at their defaults in
        an eager call, ``capacity`` and ``pairs`` are re-sized from the measured need when
        anything was dropped, so the answer is complete; passed explicitly, or under
        ``jit``, they are kept and overflow is flagged.

    Returns:
      :class:`Occlusion`.

    Example:
        >>> v = jnp.asarray([[-1.0, -1, 1], [1, -1, 1], [0, 1, 1]])
        >>> m = fsjax.Mesh(v, jnp.asarray([[0, 1, 2]]))
        >>> pts = jnp.asarray([[0.0, 0.0, 0.0], [5.0, 0.0, 0.0]])
        >>> [bool(x) for x in fsjax.render.occluded_parallel(m, pts, jnp.asarray([0.0, 0, 1])).occluded]
        [True, False]
    """
    _check_mesh(mesh, "occluded_parallel")
    grid = check_static_int("occluded_parallel", "grid", grid, lo=1)
    L = unit(jnp.asarray(direction, dtype=mesh.vertices.dtype), name="direction", fn="occluded_parallel")

    def run(cap, prs):
        return _grid_occlusion(mesh, points, L, ignore_face, s_min, grid, cap, prs, batch, "occluded_parallel")

    occ, inc, ovf = _occlusion_grown(run, capacity, pairs, "occluded_parallel")
    return Occlusion(occluded=occ, incomplete=inc, overflow=ovf)


def sun_directions(direction, *, angular_diameter_deg=0.53, samples: int = 16) -> jnp.ndarray:
    """``(samples, 3)`` unit directions filling a disc of the given angular diameter around ``direction``.

    Deterministic, equal-area sampling: sample ``k`` sits at radius ``sqrt((k + 0.5) / n)``
    times the disc radius and golden-angle azimuth (Vogel's spiral), so the mean direction is
    the centre up to ``O(1/n)``. One sample gives the centre itself (a point light).

    Example:
        >>> d = fsjax.render.sun_directions(jnp.asarray([0.0, 0, 1]), samples=32)
        >>> ang = np.degrees(np.arccos(np.clip(np.asarray(d[:, 2]), -1, 1)))
        >>> bool(ang.max() <= 0.265), d.shape
        (True, (32, 3))
    """
    L = unit(jnp.asarray(direction, dtype=jnp.result_type(float)), name="direction", fn="sun_directions")
    check_range("sun_directions", "angular_diameter_deg", angular_diameter_deg, 0.0, 180.0, hi_open=True)
    samples = check_static_int("sun_directions", "samples", samples, lo=1)
    if int(samples) == 1:
        return L[None]
    a, b = _basis(L)
    k = np.arange(int(samples))
    rad = np.sqrt((k + 0.5) / samples)
    phi = k * math.pi * (3.0 - math.sqrt(5.0))
    half = jnp.deg2rad(jnp.asarray(angular_diameter_deg, L.dtype)) / 2.0
    th = rad * half  # angle from the centre, equal-area on the (small) disc
    ca, cb = jnp.asarray(np.cos(phi), L.dtype), jnp.asarray(np.sin(phi), L.dtype)
    return (jnp.cos(th)[:, None] * L + jnp.sin(th)[:, None] * (ca[:, None] * a + cb[:, None] * b))


def sun_visibility(mesh: Mesh, points, direction, *, angular_diameter_deg=0.53, samples: int = 16,
                   ignore_face=None, s_min=None, grid: int = 64, capacity: int | None = None, pairs: int | None = None,
                   batch: int = 256):
    """Fraction of the solar disc visible from each point: ``(visible (N,), incomplete (N,), overflow)``.

    Averages exact any-hit shadow rays (:func:`occluded_parallel`, one grid binned per
    direction) over :func:`sun_directions` (``samples`` rays over a disc of
    ``angular_diameter_deg``, 0.53 deg for the Sun seen from Earth), giving hard shadows with
    penumbrae of the right width. ``incomplete`` flags points whose cell overflowed for some
    direction; ``overflow`` sums the dropped (triangle, cell) pairs over the directions.
    ``capacity`` / ``pairs`` as in :func:`occluded_parallel` (re-sized when eager and left at
    their defaults).

    Example:
        >>> v = jnp.asarray([[-1.0, -1, 1], [1, -1, 1], [1, 1, 1], [-1, 1, 1]])
        >>> m = fsjax.Mesh(v, jnp.asarray([[0, 1, 2], [0, 2, 3]]))
        >>> vis, _, _ = fsjax.render.sun_visibility(m, jnp.asarray([[0.0, 0, 0], [3.0, 0, 0]]), jnp.asarray([0.0, 0, 1]))
        >>> [float(x) for x in vis]
        [0.0, 1.0]
    """
    _check_mesh(mesh, "sun_visibility")
    dirs = sun_directions(direction, angular_diameter_deg=angular_diameter_deg, samples=samples)
    dirs = dirs.astype(mesh.vertices.dtype)

    grid = check_static_int("sun_visibility", "grid", grid, lo=1)

    def run(cap, prs):
        check_static_int("sun_visibility", "capacity", cap, lo=1)
        return _sun_map(mesh, points, dirs, ignore_face, s_min, grid, cap, prs, batch)

    occ, inc, ovf = _occlusion_grown(run, capacity, pairs, "sun_visibility")
    vis = 1.0 - jnp.mean(occ.astype(dirs.dtype), axis=0)
    return vis, jnp.any(inc, axis=0), ovf


@functools.partial(jax.jit, static_argnames=("grid", "cap", "prs", "batch"))
def _sun_map(mesh, points, dirs, ignore_face, s_min, grid, cap, prs, batch):
    """:func:`_grid_occlusion` over the sun's directions, in one module-level program."""
    def one(d):
        return _grid_occlusion(mesh, points, d, ignore_face, s_min, grid, cap, prs, batch, "sun_visibility")

    occ, inc, ovf, need_cap, need_pairs = jax.lax.map(one, dirs)
    return occ, inc, jnp.sum(ovf).astype(jnp.int32), jnp.max(need_cap), jnp.max(need_pairs)
