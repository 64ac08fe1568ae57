"""ops.decimate (quadric-error edge collapses in parallel rounds): sharp features kept exactly
(a subdivided box back to its 12 triangles), curved surfaces kept close (icosphere), boundaries
kept by their constraint planes (beside the null without them), topology preserved, and the
cases it must refuse or cannot finish."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

from fsjax import Mesh
from fsjax.ops import decimate, mesh_topology, mesh_volume
from fsjax.synth import icosphere

HALF = np.array([1.0, 0.7, 0.5])


def _grid_box(n: int = 6):
    """A box with each face an n x n grid of squares split into two triangles, wound outwards."""
    verts, faces, index = [], [], {}

    def vid(p):
        key = tuple(np.round(p, 9))
        if key not in index:
            index[key] = len(verts)
            verts.append(p)
        return index[key]

    for ax in range(3):
        u, w = [a for a in range(3) if a != ax]
        for sgn in (-1, 1):
            def point(i, j, ax=ax, u=u, w=w, sgn=sgn):
                p = np.zeros(3)
                p[ax], p[u], p[w] = sgn * HALF[ax], -HALF[u] + 2 * HALF[u] * i / n, -HALF[w] + 2 * HALF[w] * j / n
                return vid(p)

            for i in range(n):
                for j in range(n):
                    a, b, c, d = point(i, j), point(i + 1, j), point(i + 1, j + 1), point(i, j + 1)
                    for t in ((a, b, c), (a, c, d)):
                        pa, pb, pc = (np.asarray(verts[k]) for k in t)
                        outward = np.cross(pb - pa, pc - pa)[ax] * sgn > 0
                        faces.append(t if outward else t[::-1])
    return np.asarray(verts), np.asarray(faces)


def _topo(m):
    t = mesh_topology(m)
    return {k: int(getattr(t, k)) for k in ("faces", "vertices", "boundary_edges", "nonmanifold_edges",
                                             "flipped_edges", "components", "euler")}


def test_box_returns_to_its_twelve_triangles():
    """432 faces of a subdivided 2 x 1.4 x 1 box -> 12: exactly the eight corners remain and the
    volume is exact, because every collapse along a face or crease costs nothing and every move
    off a crease costs (sharp features kept)."""
    v, f = _grid_box()
    m = Mesh(jnp.asarray(v), jnp.asarray(f))
    d = decimate(m, target_faces=12)
    t = _topo(d)
    assert t == {"faces": 12, "vertices": 8, "boundary_edges": 0, "nonmanifold_edges": 0, "flipped_edges": 0,
                 "components": 1, "euler": 2}
    corners = np.asarray(d.vertices)[np.asarray(d.vertex_valid)]
    assert np.allclose(np.sort(np.abs(corners), axis=0), np.tile(HALF, (8, 1)), atol=1e-12)
    assert abs(float(mesh_volume(d).value) - 8 * np.prod(HALF)) < 1e-12


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
@pytest.mark.parametrize("ratio", [0.25, 0.1])
def test_no_face_is_left_without_area(dtype, ratio):
    """On the box, part-way down, a merged vertex could land on another vertex or on the line
    through two (the crease quadrics meet there at zero cost) and leave a face of zero area whose
    rounding-error normal passed the fold test. Such a face now counts as folded: the smallest
    face keeps at least 1e-6 of the median area (without the rule: 2e-16 in float64, 0 and a
    duplicated vertex in float32)."""
    v, f = _grid_box()
    d = decimate(Mesh(jnp.asarray(v, dtype), jnp.asarray(f)), ratio=ratio)
    p = np.asarray(d.vertices, np.float64)
    t = np.asarray(d.faces)[np.asarray(d.face_valid)]
    area = 0.5 * np.linalg.norm(np.cross(p[t[:, 1]] - p[t[:, 0]], p[t[:, 2]] - p[t[:, 0]]), axis=1)
    assert len(t) <= int(np.ceil(ratio * len(f)))
    assert area.min() > 1e-6 * np.median(area), area.min() / np.median(area)
    used = p[np.unique(t)]
    assert len(np.unique(np.round(used, 9), axis=0)) == len(used)


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_icosphere_stays_round_and_closed(dtype):
    """1,280 faces -> 10 %: closed, oriented, genus 0; vertices within 5 % of the unit sphere
    (QEM places them slightly outside, where the planes of their faces meet), and the enclosed
    volume closer to the sphere's than that of the 80-face icosphere (the nearest regular
    tessellation below 128 faces, vertices exactly on the sphere: the null)."""
    v, f = icosphere(3)
    d = decimate(Mesh(jnp.asarray(v, dtype), jnp.asarray(f)), ratio=0.1)
    assert d.vertices.dtype == dtype
    t = _topo(d)
    assert t["faces"] in (127, 128) and t["euler"] == 2 and t["boundary_edges"] == 0
    assert t["nonmanifold_edges"] == 0 and t["flipped_edges"] == 0
    r = np.linalg.norm(np.asarray(d.vertices)[np.asarray(d.vertex_valid)], axis=1)
    assert np.max(np.abs(r - 1)) < 0.05, np.max(np.abs(r - 1))
    sphere = 4 / 3 * np.pi
    err = abs(float(mesh_volume(d).value) / sphere - 1)
    v1, f1 = icosphere(1)  # 80 faces, vertices exactly on the sphere
    err_null = abs(float(mesh_volume(Mesh(jnp.asarray(v1), jnp.asarray(f1))).value) / sphere - 1)
    print(f"icosphere 1280 -> {t['faces']} faces: volume error {err:.2%} (80-face icosphere {err_null:.2%})")
    assert err < err_null


def _open_cap():
    """The upper part (z > -0.3) of a level-3 icosphere: a mesh with one boundary loop."""
    v, f = icosphere(3)
    keep = np.all(v[f][:, :, 2] > -0.3, axis=1)
    return v, f[keep]


@pytest.mark.parametrize("weight", [1000.0, 0.0])
def test_boundary_is_kept_by_its_constraint_planes(weight):
    """With the boundary planes (default weight) every boundary vertex of the result stays near the
    original rim polygon (constraint planes through each rim edge, perpendicular to its face);
    without them (the null, weight 0) the rim moves inwards ten times further."""
    v, f = _open_cap()
    m = Mesh(jnp.asarray(v), jnp.asarray(f))
    before = _topo(m)
    assert before["boundary_edges"] > 0
    d = decimate(m, ratio=0.2, boundary_weight=weight)
    t = _topo(d)
    assert t["nonmanifold_edges"] == 0 and t["flipped_edges"] == 0 and t["components"] == 1
    assert t["euler"] == before["euler"]  # still a disc

    def rim_edges(faces):
        a, b = faces.reshape(-1), np.roll(faces, -1, axis=1).reshape(-1)
        e, c = np.unique(np.sort(np.stack([a, b], 1), axis=1), axis=0, return_counts=True)
        return e[c == 1]

    fv = np.asarray(d.faces)[np.asarray(d.face_valid)]
    p = np.asarray(d.vertices)[np.unique(rim_edges(fv))]
    seg = v[rim_edges(f)]  # (S, 2, 3) original rim segments
    s0, s1 = seg[:, 0], seg[:, 1]
    tt = np.clip(np.einsum("psk,sk->ps", p[:, None] - s0[None], s1 - s0) / np.sum((s1 - s0) ** 2, -1), 0, 1)
    dist = np.min(np.linalg.norm(p[:, None] - (s0 + tt[..., None] * (s1 - s0))[None], axis=-1), axis=1)
    print(f"boundary weight {weight}: rim vertices off the original rim polygon: max {dist.max():.2e}")
    if weight > 0:
        assert dist.max() < 0.025  # an eighth of a rim edge (0.15)
    else:
        assert dist.max() > 0.1


def test_a_tetrahedron_cannot_be_decimated_and_says_so():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float)
    f = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    d = decimate(Mesh(jnp.asarray(v), jnp.asarray(f)), target_faces=2)
    assert int(jnp.sum(d.face_valid)) == 4  # every collapse breaks the link condition: nothing forced


def test_bad_arguments_are_refused():
    v, f = icosphere(1)
    m = Mesh(jnp.asarray(v), jnp.asarray(f))
    with pytest.raises(ValueError, match="decimate.*'ratio'"):
        decimate(m, ratio=0.0)
    with pytest.raises(ValueError, match="decimate.*'ratio'"):
        decimate(m, ratio=1.5)
    with pytest.raises(ValueError, match="decimate.*'target_faces'"):
        decimate(m, target_faces=0)
    with pytest.raises(ValueError, match="decimate.*'boundary_weight'"):
        decimate(m, boundary_weight=-1.0)
