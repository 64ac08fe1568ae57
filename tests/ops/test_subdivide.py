"""Loop subdivision: against a plain-Python reference of Loop's and Hoppe's rules, exactness on
flat regular grids, smoothness against midpoint subdivision (the null), jit/eager agreement,
gradients and refusals."""

from collections import defaultdict

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fsjax
from fsjax.synth import icosphere


def _reference(v, f):
    """Loop subdivision written directly from the rules, with dictionaries (slow, obvious)."""
    v = np.asarray(v, float)
    f = np.asarray(f)
    edge_faces = defaultdict(list)
    for tri in f:
        for k in range(3):
            a, b, c = tri[k], tri[(k + 1) % 3], tri[(k + 2) % 3]
            edge_faces[(min(a, b), max(a, b))].append(c)
    edges = sorted(edge_faces)
    eid = {e: i for i, e in enumerate(edges)}
    nbrs, creases = defaultdict(set), defaultdict(list)
    odd = []
    for (a, b) in edges:
        opp = edge_faces[(a, b)]
        nbrs[a].add(b)
        nbrs[b].add(a)
        if len(opp) == 2:
            odd.append(0.375 * (v[a] + v[b]) + 0.125 * (v[opp[0]] + v[opp[1]]))
        else:
            odd.append(0.5 * (v[a] + v[b]))
            creases[a].append(b)
            creases[b].append(a)
    even = v.copy()
    for i in range(len(v)):
        n = len(nbrs[i])
        if n == 0:
            continue
        if len(creases[i]) == 0:
            beta = (5 / 8 - (3 / 8 + np.cos(2 * np.pi / n) / 4) ** 2) / n
            even[i] = (1 - n * beta) * v[i] + beta * sum(v[j] for j in nbrs[i])
        elif len(creases[i]) == 2:
            even[i] = 0.75 * v[i] + 0.125 * (v[creases[i][0]] + v[creases[i][1]])
    nv = len(v)
    faces = []
    for a, b, c in f:
        ab, bc, ca = (nv + eid[(min(x, y), max(x, y))] for x, y in ((a, b), (b, c), (c, a)))
        faces += [(a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca)]
    return np.concatenate([even, np.array(odd)]), np.array(faces)


def _grid(n=5, h=1.0):
    """A flat regular triangulation (every interior vertex of valence 6) of an n x n grid."""
    ys, xs = np.mgrid[0:n, 0:n]
    v = np.stack([xs.ravel() * h, ys.ravel() * h, np.zeros(n * n)], 1)
    f = []
    for i in range(n - 1):
        for j in range(n - 1):
            p = i * n + j
            f += [(p, p + 1, p + n + 1), (p, p + n + 1, p + n)]
    return v, np.array(f)


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
def test_equals_the_reference_on_closed_open_and_nonmanifold_meshes(dtype):
    rng = np.random.default_rng(0)
    v, f = icosphere(1)
    v = v * (1 + 0.1 * rng.standard_normal((len(v), 1)))
    cases = {"closed": (v, f), "open": (v, f[3:]), "grid": _grid(4)}
    # a non-manifold fan: three triangles share edge (0, 1)
    cases["nonmanifold"] = (np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1.0]]),
                            np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4]]))
    tol = 1e-12 if dtype == jnp.float64 else 2e-6
    for name, (vv, ff) in cases.items():
        m = fsjax.ops.loop_subdivide(fsjax.Mesh(jnp.asarray(vv, dtype), jnp.asarray(ff)))
        rv, rf = _reference(vv, ff)
        k = int(jnp.sum(m.vertex_valid))
        assert k == len(rv) and m.vertices.shape[0] == len(vv) + 3 * len(ff) and m.faces.shape == rf.shape, name
        assert bool(jnp.all(m.vertex_valid[:k])) and bool(jnp.all(m.face_valid))
        np.testing.assert_allclose(np.asarray(m.vertices[:k]), rv, atol=tol, err_msg=name)
        np.testing.assert_array_equal(np.asarray(m.faces), rf, err_msg=name)


def test_flat_regular_grid_interior_is_exact_midpoint_subdivision():
    # Loop's scheme reproduces linear functions: on a flat valence-6 grid the interior even
    # vertices stay and the odd ones are edge midpoints; the straight boundary stays straight.
    v, f = _grid(6, h=2.0)
    m = fsjax.ops.loop_subdivide(fsjax.Mesh(jnp.asarray(v), jnp.asarray(f)), steps=2)
    out = np.asarray(m.vertices)[np.asarray(m.vertex_valid)]
    assert np.all(out[:, 2] == 0.0)
    inner = (out[:, 0] > 2.0 + 1e-9) & (out[:, 0] < 8.0 - 1e-9) & (out[:, 1] > 2.0 + 1e-9) & (out[:, 1] < 8.0 - 1e-9)
    # after two steps the interior samples lie exactly on the grid of spacing h / 4 = 0.5
    assert inner.sum() > 50
    np.testing.assert_allclose(out[inner, :2] / 0.5, np.round(out[inner, :2] / 0.5), atol=1e-12)
    # the bottom boundary away from the corners (the corners are cut: curve rule) stays on y = 0,
    # at the h / 4 spacing: x = 2.5, 3.0, ..., 7.5
    low = out[(out[:, 1] < 0.3) & (out[:, 0] > 2.2) & (out[:, 0] < 7.8)]
    np.testing.assert_array_equal(low[:, 1], 0.0)
    np.testing.assert_allclose(np.sort(low[:, 0]), np.arange(2.5, 7.51, 0.5), atol=1e-12)
    assert np.all(out[:, 1] >= 0.0)


def _max_dihedral(m):
    v, f = np.asarray(m.vertices), np.asarray(m.faces)
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    owner = defaultdict(list)
    for i, t in enumerate(f):
        for k in range(3):
            owner[tuple(sorted((t[k], t[(k + 1) % 3])))].append(i)
    ang = [np.degrees(np.arccos(np.clip(n[a] @ n[b], -1, 1))) for a, b in owner.values()]
    return max(ang)


def test_smoother_than_midpoint_subdivision_the_null():
    v, f = icosphere(0)
    m = fsjax.Mesh(jnp.asarray(v), jnp.asarray(f))
    loop = fsjax.ops.loop_subdivide(m, steps=3)
    # the null: midpoint subdivision (all weights 1/2, no vertex moves) keeps the icosahedron's creases
    mid = m
    for _ in range(3):
        vv, ff = np.asarray(mid.vertices), np.asarray(mid.faces)
        rv, rf = _reference(vv, ff)
        nv = len(vv)
        rv[:nv] = vv
        rv[nv:] = [(vv[a] + vv[b]) / 2 for a, b in sorted({(min(x, y), max(x, y)) for t in ff
                                                          for x, y in ((t[0], t[1]), (t[1], t[2]), (t[2], t[0]))})]
        mid = fsjax.Mesh(jnp.asarray(rv), jnp.asarray(rf))
    d_loop, d_mid = _max_dihedral(loop), _max_dihedral(mid)
    # the scale: a sphere tessellated at the same resolution (icosphere(3), 1,280 faces)
    vs, fs = icosphere(3)
    d_sphere = _max_dihedral(fsjax.Mesh(jnp.asarray(vs), jnp.asarray(fs)))
    print(f"max dihedral after 3 steps: Loop {d_loop:.2f} deg, midpoint {d_mid:.2f} deg, "
          f"sphere at this resolution {d_sphere:.2f} deg")
    assert d_mid > 40.0                     # the icosahedron's 41.8 deg edges are still there
    assert d_loop < 1.5 * d_sphere
    topo = fsjax.ops.mesh_topology(loop)
    assert int(topo.faces) == 20 * 64 and bool(topo.closed) and bool(topo.oriented) and int(topo.euler) == 2
    # the limit surface lies inside the control polyhedron; its vertices are nearly cospherical
    r = np.linalg.norm(np.asarray(loop.vertices)[np.asarray(loop.vertex_valid)], axis=1)
    assert r.max() < 1.0 and r.std() / r.mean() < 0.01


def test_jit_equals_eager_on_an_open_mesh_and_gradient():
    v, f = icosphere(1)
    fv = jnp.arange(len(f)) != 7                    # one invalid face: an open mesh with a hole
    mesh = fsjax.Mesh(jnp.asarray(v), jnp.asarray(f), face_valid=fv)
    eager = fsjax.ops.loop_subdivide(mesh)
    traced = jax.jit(lambda m: fsjax.ops.loop_subdivide(m))(mesh)
    nv = int(jnp.sum(traced.vertex_valid))
    assert traced.vertices.shape == eager.vertices.shape and nv == len(v) + 120  # 117 interior + 3 hole edges
    np.testing.assert_array_equal(np.asarray(traced.vertex_valid), np.asarray(eager.vertex_valid))
    np.testing.assert_allclose(np.asarray(traced.vertices[:nv]), np.asarray(eager.vertices[:nv]), atol=1e-12)
    np.testing.assert_array_equal(np.asarray(traced.faces), np.asarray(eager.faces))
    assert int(jnp.sum(eager.face_valid)) == 4 * (len(f) - 1)
    assert int(fsjax.ops.mesh_topology(eager).boundary_edges) == 6      # the hole's 3 edges, split

    def area(x):
        return fsjax.ops.mesh_area(fsjax.ops.loop_subdivide(fsjax.Mesh(x, jnp.asarray(f)))).value

    g = jax.grad(area)(jnp.asarray(v))
    d = np.random.default_rng(1).standard_normal(v.shape)
    eps = 1e-6
    fd = (area(jnp.asarray(v + eps * d)) - area(jnp.asarray(v - eps * d))) / (2 * eps)
    assert abs(float(jnp.sum(g * d))) > 1e-3
    assert float(jnp.sum(g * d)) == pytest.approx(float(fd), rel=1e-6)


def test_refusals():
    v, f = icosphere(0)
    m = fsjax.Mesh(jnp.asarray(v), jnp.asarray(f))
    with pytest.raises(ValueError, match="loop_subdivide.*steps"):
        fsjax.ops.loop_subdivide(m, steps=6)
    with pytest.raises(TypeError, match="loop_subdivide.*steps"):
        fsjax.ops.loop_subdivide(m, steps=1.5)
    with pytest.raises((TypeError, ValueError), match="loop_subdivide"):
        fsjax.ops.loop_subdivide(fsjax.Image(jnp.zeros((4, 4))))
    assert fsjax.ops.loop_subdivide(m, steps=0).vertices.shape == (12, 3)
