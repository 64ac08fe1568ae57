"""Loop subdivision of a triangle mesh (``Mesh -> Mesh``).

Conventions:

* One step splits every valid face into four: a new ("odd") vertex on each undirected edge,
  and every old ("even") vertex moved (Loop 1987). Odd vertex of an interior edge ``ab`` with
  opposite vertices ``c, d``: ``3/8 (a + b) + 1/8 (c + d)``. Even vertex of valence ``n``:
  ``(1 - n beta) v + beta * sum(neighbours)`` with Loop's
  ``beta = (5/8 - (3/8 + cos(2 pi / n) / 4)^2) / n``.
* **Creases** (Hoppe et al. 1994): an edge used by one valid face (boundary) or by three or
  more (non-manifold) is a crease. Its odd vertex is its midpoint; an even vertex on exactly
  two crease edges follows the curve rule ``3/4 v + 1/8 (n1 + n2)``; on one or more than two
  crease edges (a corner, a dart) it stays where it is. A boundary therefore stays a
  cubic B-spline of its own vertices, never pulled by the interior.
* Output layout: vertices ``[old vertices; one per edge slot]`` and faces ``4 F`` in the
  order ``(a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca)`` per input face, so the
  winding is kept. Edges are found by one sort of the ``3 F`` half-edges (memory ``O(F)``).
  The vertex array has the static capacity ``V + 3 F`` (eager and under ``jit`` alike, so
  the two agree) and ``vertex_valid`` marks the ``V + E`` real ones, edge vertices first (a
  closed mesh has ``E = 3 F / 2``: about half of the new slots stay unused). ``steps``
  steps multiply the faces by ``4^steps``. Invalid input faces give invalid output faces.
* Vertices a valid face does not use are copied unchanged (and stay as they are valid or not).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from jax import lax

from ..._checks import check_static_int
from ...registry import register
from ...types import Mesh
from .._common import check_one

__all__ = ["loop_subdivide"]

_INT_MAX = jnp.iinfo(jnp.int32).max
_LOOP = ("C. Loop, Smooth subdivision surfaces based on triangles, M.S. thesis, "
         "University of Utah, 1987")
_HOPPE = ("H. Hoppe, T. DeRose, T. Duchamp, M. Halstead, H. Jin, J. McDonald, J. Schweitzer, "
          "W. Stuetzle, Piecewise smooth surface reconstruction, SIGGRAPH 1994 (crease rules)")


def _half_edge_runs(faces, face_valid):
    """Undirected edge id of every half-edge (``-1`` for invalid faces) and per-edge data.

    Half-edge ``3 f + k`` runs from ``faces[f, k]`` to ``faces[f, (k + 1) % 3]``; its opposite
    vertex is ``faces[f, (k + 2) % 3]``. Returns ``(edge_of, lo, hi, count, n_edges)`` with
    ``lo/hi/count`` per edge slot ``(3 F,)``.
    """
    n = faces.shape[0] * 3
    a = faces.reshape(-1)
    b = jnp.roll(faces, -1, axis=1).reshape(-1)
    ok = jnp.repeat(face_valid, 3)
    lo = jnp.where(ok, jnp.minimum(a, b), _INT_MAX)
    hi = jnp.where(ok, jnp.maximum(a, b), _INT_MAX)
    idx = jnp.arange(n, dtype=jnp.int32)
    slo, shi, sidx = lax.sort((lo, hi, idx), num_keys=2)
    sok = slo != _INT_MAX
    first = jnp.arange(n) == 0
    new = sok & ((slo != jnp.roll(slo, 1)) | (shi != jnp.roll(shi, 1)) | first)
    run = jnp.cumsum(new.astype(jnp.int32)) - 1
    run = jnp.where(sok, run, n - 1)
    edge_of = jnp.zeros(n, jnp.int32).at[sidx].set(jnp.where(sok, run, -1))
    count = jax.ops.segment_sum(sok.astype(jnp.int32), run, num_segments=n)
    elo = jnp.zeros(n, jnp.int32).at[jnp.where(new, run, n)].set(slo, mode="drop")
    ehi = jnp.zeros(n, jnp.int32).at[jnp.where(new, run, n)].set(shi, mode="drop")
    return edge_of, elo, ehi, count, jnp.sum(new)


@jax.jit
def _loop_core(vertices, faces, face_valid, vertex_valid):
    nv, nf = vertices.shape[0], faces.shape[0]
    n = 3 * nf
    dt = vertices.dtype
    edge_of, elo, ehi, count, n_edges = _half_edge_runs(faces, face_valid)
    is_edge = jnp.arange(n) < n_edges
    crease = is_edge & (count != 2)
    interior = is_edge & (count == 2)
    opp = jnp.roll(faces, -2, axis=1).reshape(-1)
    hok = edge_of >= 0
    seg = jnp.where(hok, edge_of, n)
    opp_sum = jax.ops.segment_sum(jnp.where(hok[:, None], vertices[opp], 0), seg, num_segments=n + 1)[:n]
    va, vb = vertices[elo], vertices[ehi]
    odd = jnp.where(interior[:, None], 0.375 * (va + vb) + 0.125 * opp_sum, 0.5 * (va + vb))
    odd = jnp.where(is_edge[:, None], odd, 0)
    # even vertices: valence, neighbour sums over all edges and over crease edges
    ends = jnp.concatenate([jnp.where(is_edge, elo, nv), jnp.where(is_edge, ehi, nv)])
    other = jnp.concatenate([ehi, elo])
    ce = jnp.concatenate([crease, crease])
    valence = jax.ops.segment_sum(jnp.ones(2 * n, dt), ends, num_segments=nv + 1)[:nv]
    nsum = jax.ops.segment_sum(vertices[other], ends, num_segments=nv + 1)[:nv]
    ncre = jax.ops.segment_sum(ce.astype(jnp.int32), ends, num_segments=nv + 1)[:nv]
    csum = jax.ops.segment_sum(jnp.where(ce[:, None], vertices[other], 0), ends, num_segments=nv + 1)[:nv]
    k = jnp.maximum(valence, 1.0)
    beta = (0.625 - (0.375 + 0.25 * jnp.cos(2.0 * jnp.pi / k)) ** 2) / k
    smooth = (1.0 - k * beta)[:, None] * vertices + beta[:, None] * nsum
    curve = 0.75 * vertices + 0.125 * csum
    even = jnp.where((ncre == 0)[:, None] & (valence > 0)[:, None], smooth,
                     jnp.where((ncre == 2)[:, None], curve, vertices))
    new_v = jnp.concatenate([even, odd], axis=0)
    new_valid = jnp.concatenate([vertex_valid, is_edge])
    e = edge_of.reshape(nf, 3) + nv                       # edge k runs from corner k to k+1
    a, b, c = faces[:, 0], faces[:, 1], faces[:, 2]
    ab, bc, ca = e[:, 0], e[:, 1], e[:, 2]
    quads = jnp.stack([jnp.stack([a, ab, ca], 1), jnp.stack([b, bc, ab], 1),
                       jnp.stack([c, ca, bc], 1), jnp.stack([ab, bc, ca], 1)], 1)
    quads = jnp.where(face_valid[:, None, None], quads, 0).reshape(4 * nf, 3).astype(jnp.int32)
    new_fv = jnp.repeat(face_valid, 4)
    return new_v, quads, new_valid, new_fv, nv + n_edges


@functools.partial(jax.jit, static_argnames=("steps",))
def _loop_steps(vertices, faces, face_valid, vertex_valid, *, steps: int):
    out = (vertices, faces, vertex_valid, face_valid)
    for _ in range(steps):                                # shapes grow each step: unrolled by design
        v, f, vv, fv, _ = _loop_core(out[0], out[1], out[3], out[2])
        out = (v, f, vv, fv)
    return out


@register(family="mesh", takes=Mesh, gives=Mesh, differentiable=True, refs=[_LOOP, _HOPPE])
def loop_subdivide(mesh: Mesh, /, *, steps: int = 1) -> Mesh:
    """Loop subdivision: each step splits every face into four and smooths the surface.

    Args:
      mesh: ``Mesh``; only valid faces count.
      steps: number of subdivision steps (static int, 0 to 5; default 1). Faces grow
        ``4^steps``-fold.

    Returns:
      ``Mesh`` (layout, crease rules and capacities in the module notes). Differentiable in
      the vertex positions (the new vertices are fixed linear combinations of the old).

    Example:
      One step of an icosahedron inscribed in the unit sphere: 12 + 30 vertices, 80 faces;
      an old vertex (valence 5) moves to radius ``1 - 5 beta + 5 beta / sqrt(5)`` (its
      neighbours lie at ``cos = 1 / sqrt(5)``), closer to the sphere than midpoint
      subdivision would leave the new vertices:

      >>> import numpy as np, jax.numpy as jnp, fsjax
      >>> from fsjax.synth import icosphere
      >>> v, f = icosphere(0)
      >>> m = fsjax.ops.loop_subdivide(fsjax.Mesh(jnp.asarray(v), jnp.asarray(f)))
      >>> int(m.vertex_valid.sum()), m.faces.shape
      (42, (80, 3))
      >>> beta = (5 / 8 - (3 / 8 + np.cos(2 * np.pi / 5) / 4) ** 2) / 5
      >>> r = np.linalg.norm(np.asarray(m.vertices), axis=1)
      >>> bool(np.allclose(r[:12], 1 - 5 * beta + 5 * beta / np.sqrt(5)))
      True
      >>> int(fsjax.ops.mesh_topology(m).euler), bool(fsjax.ops.mesh_topology(m).closed)
      (2, True)
    """
    op = "loop_subdivide"
    check_one(op, "mesh", mesh, Mesh, "vertices")
    s = check_static_int(op, "steps", steps, lo=0, hi=5)
    nf = mesh.faces.shape[0]
    if nf * 4 ** s > 50_000_000:
        raise ValueError(f"{op}: argument 'steps'={s} would make {nf * 4 ** s:,} faces from {nf:,}; "
                         "the bound is 50,000,000 (memory)")
    v, f, vv, fv = _loop_steps(mesh.vertices, mesh.faces, mesh.face_valid, mesh.vertex_valid, steps=s)
    return Mesh(v, f, vv, fv, mesh.truncated)
