"""Triangle-mesh measurements, topology and smoothing (``Mesh -> Feature | MeshTopology | Mesh``).

Conventions:

* Only valid faces (``Mesh.face_valid``) count; a vertex counts when a valid face uses it.
  Lengths are in the mesh's own unit (the ``Feature.unit`` says ``length^2`` / ``length^3``).
* **Edges** are found by one sort of the ``3 F`` half-edges by their (smaller, larger) vertex
  pair: a run of one is a boundary edge, of two a manifold edge (consistently oriented when
  the two faces traverse it in opposite directions), of three or more a non-manifold edge.
  Memory is ``O(F)``; nothing is ``O(V^2)``.
* **Enclosed volume** is the divergence-theorem sum of signed tetrahedra (apex at the mean
  of the used vertices, which keeps the sum well conditioned far from the origin). It is a
  volume only for a closed, consistently oriented surface: otherwise the op returns NaN
  (never a number that depends on where the origin is). Outward winding gives a positive
  volume, inward winding a negative one: the sign reports the orientation.
* **Smoothing** moves every used vertex towards the mean of its edge neighbours (the
  umbrella operator; an edge shared by two faces counts twice, so on a closed surface all
  neighbours weigh the same). ``laplacian_smooth`` takes ``iterations`` steps of
  ``lam``; it shrinks a closed surface (the null). ``taubin_smooth`` alternates a shrinking
  step ``lam`` and an inflating step ``mu = 1 / (k_pb - 1 / lam)`` (Taubin 1995: a low-pass
  filter with pass-band frequency ``k_pb``), which removes noise and keeps the volume.
  Faces and validity are unchanged; a vertex no valid face uses does not move.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from jax import lax

from ..._checks import check_range, check_static_int
from ...registry import register
from ...types import Feature, Mesh, MeshTopology
from .._common import check_one

__all__ = ["mesh_area", "mesh_volume", "mesh_topology", "laplacian_smooth", "taubin_smooth"]

_TAUBIN = "G. Taubin, A signal processing approach to fair surface design, SIGGRAPH 1995"
_INT_MAX = jnp.iinfo(jnp.int32).max


def _check_mesh(op: str, mesh) -> None:
    check_one(op, "mesh", mesh, Mesh, "vertices")


def _edge_runs(faces, face_valid):
    """Sorted half-edges grouped into undirected edges.

    Returns ``(count, forward, is_edge)`` per run slot ``(3F,)``: how many valid half-edges
    the edge has, how many of them run from the smaller to the larger vertex, and whether
    the slot is an edge at all.
    """
    a = faces.reshape(-1)
    b = jnp.roll(faces, -1, axis=1).reshape(-1)
    ok = jnp.repeat(face_valid, 3)
    lo = jnp.where(ok, jnp.minimum(a, b), _INT_MAX)
    hi = jnp.where(ok, jnp.maximum(a, b), _INT_MAX)
    fwd = (a < b).astype(jnp.int32)
    lo, hi, fwd, ok = lax.sort((lo, hi, fwd, ok.astype(jnp.int32)), num_keys=2)
    ok = ok > 0
    new = ok & ((lo != jnp.roll(lo, 1)) | (hi != jnp.roll(hi, 1)) | (jnp.arange(lo.shape[0]) == 0))
    run = jnp.cumsum(new.astype(jnp.int32)) - 1
    run = jnp.where(ok, run, lo.shape[0] - 1)
    n = lo.shape[0]
    count = jax.ops.segment_sum(ok.astype(jnp.int32), run, num_segments=n)
    forward = jax.ops.segment_sum(jnp.where(ok, fwd, 0), run, num_segments=n)
    is_edge = jnp.arange(n) < jnp.sum(new)
    return count, forward, is_edge


def _used(mesh):
    nv = mesh.vertices.shape[0]
    f = jnp.where(mesh.face_valid[:, None], mesh.faces, nv)
    return jnp.zeros(nv + 1, bool).at[f.reshape(-1)].set(True)[:nv]


@jax.jit
def _topology_core(faces, face_valid, used):
    nv = used.shape[0]
    count, forward, is_edge = _edge_runs(faces, face_valid)
    e = jnp.sum(is_edge)
    boundary = jnp.sum(is_edge & (count == 1))
    nonmanifold = jnp.sum(is_edge & (count >= 3))
    flipped = jnp.sum(is_edge & (count == 2) & (forward != 1))
    # connected components: minimum-label propagation over faces with pointer jumping
    fv = jnp.where(face_valid[:, None], faces, nv)

    def body(state):
        lab, _ = state
        ext = jnp.concatenate([lab, jnp.asarray([_INT_MAX], lab.dtype)])
        m = jnp.min(ext[fv], axis=1)
        new = ext.at[fv.reshape(-1)].min(jnp.repeat(m, 3))[:nv]
        new = new[new]
        new = new[new]
        return new, jnp.any(new != lab)

    lab, _ = lax.while_loop(lambda s: s[1], body, (jnp.arange(nv, dtype=jnp.int32), jnp.asarray(True)))
    comps = jnp.sum(used & (lab == jnp.arange(nv)))
    nf = jnp.sum(face_valid)
    nvu = jnp.sum(used)
    i32 = jnp.int32
    return (nvu.astype(i32), nf.astype(i32), e.astype(i32), boundary.astype(i32), nonmanifold.astype(i32),
            flipped.astype(i32), comps.astype(i32), (nvu - e + nf).astype(i32))


@register(family="mesh", takes=Mesh, gives=MeshTopology, differentiable=False,
          refs=["M. Botsch, L. Kobbelt, M. Pauly, P. Alliez, B. Levy, Polygon Mesh Processing, "
                "A K Peters 2010, ch. 2 (surface representations, manifoldness, Euler formula)"])
def mesh_topology(mesh: Mesh, /) -> MeshTopology:
    """Boundary, non-manifold and flipped edges, components and Euler characteristic of a mesh.

    Args:
      mesh: ``Mesh``; only valid faces count.

    Returns:
      ``MeshTopology`` (counts; ``.closed``, ``.oriented``, ``.manifold`` as booleans).

    Example:
      An icosahedron is closed, oriented, one component, Euler characteristic 2; flipping
      one face's winding leaves it closed but makes its three edges flipped; dropping a face
      opens three boundary edges:

      >>> import jax.numpy as jnp, fsjax
      >>> from fsjax.synth import icosphere
      >>> v, f = icosphere(0)
      >>> t = fsjax.ops.mesh_topology(fsjax.Mesh(jnp.asarray(v), jnp.asarray(f)))
      >>> int(t.vertices), int(t.edges), int(t.faces), int(t.euler), int(t.components), bool(t.closed), bool(t.oriented)
      (12, 30, 20, 2, 1, True, True)
      >>> flipped = fsjax.Mesh(jnp.asarray(v), jnp.asarray(f).at[0].set(jnp.asarray(f[0][::-1])))
      >>> int(fsjax.ops.mesh_topology(flipped).flipped_edges)
      3
      >>> m = fsjax.Mesh(jnp.asarray(v), jnp.asarray(f), face_valid=jnp.arange(20) != 5)
      >>> int(fsjax.ops.mesh_topology(m).boundary_edges)
      3
    """
    _check_mesh("mesh_topology", mesh)
    return MeshTopology(*_topology_core(mesh.faces, mesh.face_valid, _used(mesh)))


@jax.jit
def _area_core(vertices, faces, face_valid):
    t = vertices[faces]
    n = jnp.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    a = 0.5 * jnp.sqrt(jnp.maximum(jnp.sum(n * n, axis=-1), jnp.finfo(vertices.dtype).tiny))
    return jnp.sum(jnp.where(face_valid, a, 0.0))


@register(family="mesh", takes=Mesh, gives=Feature, differentiable=True,
          refs=["M. Botsch et al., Polygon Mesh Processing, A K Peters 2010"])
def mesh_area(mesh: Mesh, /) -> Feature:
    """Total area of the valid faces, in the mesh's unit squared.

    Args:
      mesh: ``Mesh``.

    Returns:
      ``Feature`` (unit ``length^2``); 0 for a mesh with no valid face.

    Example:
      The unit cube's twelve triangles have area 6; an icosphere of radius 1 approaches 4 pi
      from below as it is subdivided:

      >>> import numpy as np, jax.numpy as jnp, fsjax
      >>> from fsjax.synth import icosphere
      >>> v, f = icosphere(3)
      >>> a = float(fsjax.ops.mesh_area(fsjax.Mesh(jnp.asarray(v), jnp.asarray(f))))
      >>> round(a, 3), round(4 * np.pi, 3)
      (12.506, 12.566)
    """
    _check_mesh("mesh_area", mesh)
    return Feature(_area_core(mesh.vertices, mesh.faces, mesh.face_valid), unit="length^2")


@jax.jit
def _volume_core(vertices, faces, face_valid, used):
    count, forward, is_edge = _edge_runs(faces, face_valid)
    closed = ~jnp.any(is_edge & ((count != 2) | (forward != 1)))
    w = used.astype(vertices.dtype)
    c0 = jnp.sum(vertices * w[:, None], axis=0) / jnp.maximum(jnp.sum(w), 1.0)
    t = vertices[faces] - c0
    six = jnp.sum(t[:, 0] * jnp.cross(t[:, 1], t[:, 2]), axis=-1)
    vol = jnp.sum(jnp.where(face_valid, six, 0.0)) / 6.0
    return jnp.where(closed & jnp.any(face_valid), vol, jnp.nan)


@register(family="mesh", takes=Mesh, gives=Feature, differentiable=True,
          refs=["C. Zhang, T. Chen, Efficient feature extraction for 2D/3D objects in mesh "
                "representation, ICIP 2001 (signed tetrahedron volumes)"])
def mesh_volume(mesh: Mesh, /) -> Feature:
    """Signed volume enclosed by a closed, consistently oriented mesh (NaN otherwise).

    Args:
      mesh: ``Mesh``; only valid faces count.

    Returns:
      ``Feature`` (unit ``length^3``): positive for outward winding, negative for inward;
      NaN when the surface has a boundary, a non-manifold or a flipped edge, or no face
      (use ``mesh_topology`` to see which).

    Example:
      An icosphere of radius 2 (1,280 faces): close to 4/3 pi 8 = 33.51; the flipped winding
      gives the negative; with one face dropped the volume is undefined:

      >>> import jax.numpy as jnp, fsjax
      >>> from fsjax.synth import icosphere
      >>> v, f = icosphere(3, radius=2.0)
      >>> m = fsjax.Mesh(jnp.asarray(v), jnp.asarray(f))
      >>> round(float(fsjax.ops.mesh_volume(m)), 2)
      33.22
      >>> round(float(fsjax.ops.mesh_volume(fsjax.Mesh(m.vertices, m.faces[:, ::-1]))), 2)
      -33.22
      >>> float(fsjax.ops.mesh_volume(fsjax.Mesh(m.vertices, m.faces, face_valid=jnp.arange(1280) != 0)))
      nan
    """
    _check_mesh("mesh_volume", mesh)
    return Feature(_volume_core(mesh.vertices, mesh.faces, mesh.face_valid, _used(mesh)), unit="length^3")


@functools.partial(jax.jit, static_argnames=("iterations",))
def _smooth_core(vertices, faces, face_valid, used, steps, *, iterations: int):
    nv = vertices.shape[0]
    a = faces.reshape(-1)
    b = jnp.roll(faces, -1, axis=1).reshape(-1)
    ok = jnp.repeat(face_valid, 3)
    src = jnp.concatenate([jnp.where(ok, a, nv), jnp.where(ok, b, nv)])
    dst = jnp.concatenate([b, a])
    deg = jax.ops.segment_sum(jnp.ones_like(src, vertices.dtype), src, num_segments=nv + 1)[:nv]
    move = (used & (deg > 0)).astype(vertices.dtype)[:, None]

    def step(x, s):
        nb = jax.ops.segment_sum(x[dst], src, num_segments=nv + 1)[:nv] / jnp.maximum(deg, 1.0)[:, None]
        return x + s * move * (nb - x)

    def body(i, x):
        return step(x, steps[i % steps.shape[0]])

    return lax.fori_loop(0, iterations, body, vertices)


def _smooth(op, mesh, iterations, steps):
    _check_mesh(op, mesh)
    it = check_static_int(op, "iterations", iterations, lo=0, hi=100_000)
    v = _smooth_core(mesh.vertices, mesh.faces, mesh.face_valid, _used(mesh),
                     jnp.asarray(steps, mesh.vertices.dtype), iterations=it)
    return Mesh(v, mesh.faces, mesh.vertex_valid, mesh.face_valid, mesh.truncated)


@register(family="mesh", takes=Mesh, gives=Mesh, differentiable=True, refs=[_TAUBIN])
def laplacian_smooth(mesh: Mesh, /, *, iterations: int = 10, lam: float = 0.5) -> Mesh:
    """Umbrella (Laplacian) smoothing: ``iterations`` steps of ``x += lam (mean of neighbours - x)``.

    Removes noise and shrinks the surface (the null that ``taubin_smooth`` beats).

    Args:
      mesh: ``Mesh``.
      iterations: number of steps (static int, 0 to 100,000; default 10).
      lam: step in ``(0, 1]`` (default 0.5).

    Returns:
      ``Mesh`` with moved vertices; faces and validity unchanged.

    Example:
      Ten steps on an icosphere of radius 1 pull its vertices inwards:

      >>> import numpy as np, jax.numpy as jnp, fsjax
      >>> from fsjax.synth import icosphere
      >>> v, f = icosphere(2)
      >>> s = fsjax.ops.laplacian_smooth(fsjax.Mesh(jnp.asarray(v), jnp.asarray(f)))
      >>> round(float(np.linalg.norm(np.asarray(s.vertices), axis=1).mean()), 3)
      0.798
    """
    check_range("laplacian_smooth", "lam", lam, lo=0.0, hi=1.0, lo_open=True)
    return _smooth("laplacian_smooth", mesh, iterations, [lam])


@register(family="mesh", takes=Mesh, gives=Mesh, differentiable=True, refs=[_TAUBIN])
def taubin_smooth(mesh: Mesh, /, *, iterations: int = 10, lam: float = 0.5, k_pb: float = 0.1) -> Mesh:
    """Taubin's lambda|mu smoothing: removes noise without shrinking the surface.

    Each iteration is a shrinking step ``lam`` then an inflating step
    ``mu = 1 / (k_pb - 1 / lam)`` (negative), a low-pass filter on the mesh.

    Args:
      mesh: ``Mesh``.
      iterations: number of lambda|mu pairs (static int, 0 to 100,000; default 10).
      lam: shrinking step in ``(0, 1]`` (default 0.5).
      k_pb: pass-band frequency in ``(0, 1 / lam)`` (default 0.1, Taubin's usual value).

    Returns:
      ``Mesh`` with moved vertices; faces and validity unchanged.

    Example:
      A noisy icosphere: Taubin smoothing reduces the radial noise and keeps the mean radius
      (Laplacian smoothing with the same steps loses ~6 % of it, 16 % of the volume):

      >>> import numpy as np, jax.numpy as jnp, fsjax
      >>> from fsjax.synth import icosphere
      >>> v, f = icosphere(3)
      >>> v = v * (1 + 0.02 * np.random.default_rng(0).standard_normal((len(v), 1)))
      >>> s = fsjax.ops.taubin_smooth(fsjax.Mesh(jnp.asarray(v), jnp.asarray(f)))
      >>> r0, r1 = np.linalg.norm(v, axis=1), np.linalg.norm(np.asarray(s.vertices), axis=1)
      >>> bool(r1.std() < 0.5 * r0.std()), bool(abs(r1.mean() - 1) < 0.01)
      (True, True)
    """
    op = "taubin_smooth"
    check_range(op, "lam", lam, lo=0.0, hi=1.0, lo_open=True)
    check_range(op, "k_pb", k_pb, lo=0.0, hi=1.0 / float(lam), lo_open=True, hi_open=True)
    mu = 1.0 / (float(k_pb) - 1.0 / float(lam))
    return _smooth(op, mesh, 2 * check_static_int(op, "iterations", iterations, lo=0, hi=100_000), [lam, mu])
