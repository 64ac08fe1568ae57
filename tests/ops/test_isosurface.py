"""Marching cubes (``fsjax.ops.marching_cubes``): closed oriented surfaces, the sphere beside
scikit-image and the analytic area and volume, spacing, capacity, fail-closed cases."""

from collections import Counter

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fsjax


def _mesh_np(m):
    v = np.asarray(m.vertices)[np.asarray(m.vertex_valid)]
    f = np.asarray(m.faces)[np.asarray(m.face_valid)]
    return v, f


def _area_volume(v, f):
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1).sum()
    vol = np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0
    return area, vol


def _open_edges(f):
    """Directed edges not matched by exactly one opposite edge (0 for a closed oriented surface)."""
    e = Counter()
    for a, b, c in f:
        for p, q in ((a, b), (b, c), (c, a)):
            e[(int(p), int(q))] += 1
    return sum(1 for (p, q), n in e.items() if n != 1 or e.get((q, p), 0) != 1)


def _sphere(n, radius, spacing=(1.0, 1.0, 1.0), dtype=np.float64):
    """Signed 'inside' field (radius - distance, physical units) of a sphere centred in the grid."""
    z, y, x = (np.mgrid[:n, :n, :n] - (n - 1) / 2.0) * np.asarray(spacing)[:, None, None, None]
    return (radius - np.sqrt(x**2 + y**2 + z**2)).astype(dtype)


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
def test_random_volumes_give_closed_oriented_surfaces(dtype):
    rng = np.random.default_rng(0)
    totals = []
    for _ in range(3):
        v = rng.random((7, 8, 9))
        v[[0, -1]] = 0.0
        v[:, [0, -1]] = 0.0
        v[:, :, [0, -1]] = 0.0
        m = fsjax.ops.marching_cubes(fsjax.Volume(jnp.asarray(v, dtype)), level=0.5)
        _, f = _mesh_np(m)
        assert not bool(m.truncated)
        assert len(f) > 100
        # every edge used by exactly two faces in opposite directions; no duplicate vertices
        assert _open_edges(f) == 0
        vv = np.asarray(m.vertices)[np.asarray(m.vertex_valid)]
        assert len(np.unique(np.round(vv, 9), axis=0)) == len(vv)
        totals.append(len(f))
    print(f"random 7x8x9 volumes ({jnp.dtype(dtype).name}): {totals} faces, 0 open or repeated edges")


def test_sphere_beside_skimage_and_analytic():
    skm = pytest.importorskip("skimage.measure")
    n, R = 48, 19.3
    vol = _sphere(n, R)
    m = fsjax.ops.marching_cubes(fsjax.Volume(jnp.asarray(vol)), level=0.0)
    v, f = _mesh_np(m)
    vs, fs, _, _ = skm.marching_cubes(vol, 0.0)       # (z, y, x) order, same points up to order
    c = (n - 1) / 2.0
    rad = np.abs(np.linalg.norm(v - c, axis=1) - R)
    rad_sk = np.abs(np.linalg.norm(vs - c, axis=1) - R)
    area, volume = _area_volume(v, f)
    area_sk, volume_sk = _area_volume(vs[:, ::-1], fs)
    ea, ev = area / (4 * np.pi * R**2) - 1, volume / (4 / 3 * np.pi * R**3) - 1
    print(f"sphere r={R} in {n}^3: fsjax {len(v)} vertices {len(f)} faces, radial error max "
          f"{rad.max():.5f} mean {rad.mean():.5f}, area {ea:+.5f}, volume {ev:+.5f}; skimage {len(vs)} "
          f"vertices {len(fs)} faces, radial max {rad_sk.max():.5f} mean {rad_sk.mean():.5f}, "
          f"area {area_sk / (4 * np.pi * R**2) - 1:+.5f}, volume {abs(volume_sk) / (4 / 3 * np.pi * R**3) - 1:+.5f}")
    assert len(v) == len(vs) and len(f) == len(fs)
    # skimage computes in float32: equal up to its rounding (1e-6 of a voxel)
    assert rad.max() <= rad_sk.max() + 1e-6 and rad.mean() <= rad_sk.mean() + 1e-6
    assert abs(ea) < 0.005 and abs(ev) < 0.005
    assert volume > 0                                  # outward winding
    assert _open_edges(f) == 0
    # the null: the voxel count as the volume (no sub-voxel interpolation) is further off
    null_ev = (vol > 0).sum() / (4 / 3 * np.pi * R**3) - 1
    assert abs(ev) < abs(null_ev)


def test_spacing_and_winding():
    # an anisotropic grid sampling the same physical sphere: vertices on the sphere in mm
    sp = (2.0, 1.0, 0.5)
    shape = (12, 24, 48)                                   # ~23 mm along every axis
    z, y, x = np.mgrid[:shape[0], :shape[1], :shape[2]].astype(float)
    c = np.array([(n - 1) / 2.0 * s for n, s in zip(shape, sp)])
    r = np.sqrt((z * sp[0] - c[0]) ** 2 + (y * sp[1] - c[1]) ** 2 + (x * sp[2] - c[2]) ** 2)
    R = 9.0
    m = fsjax.ops.marching_cubes(fsjax.Volume(jnp.asarray(R - r), spacing=sp), level=0.0)
    v, f = _mesh_np(m)
    rr = np.linalg.norm(v - c[::-1], axis=1)                          # vertices are (x, y, z)
    assert np.abs(rr - R).max() < 0.05 * max(sp)
    _, volume = _area_volume(v, f)
    assert abs(volume / (4 / 3 * np.pi * R**3) - 1) < 0.03 and volume > 0
    # the inverted field (inside below the level) flips every face: negative signed volume
    mi = fsjax.ops.marching_cubes(fsjax.Volume(jnp.asarray(r - R), spacing=sp), level=0.0)
    _, volume_i = _area_volume(*_mesh_np(mi))
    assert volume_i == pytest.approx(-volume, rel=1e-9)


def test_capacity_jit_flags_and_eager_grows():
    vol = fsjax.Volume(jnp.asarray(_sphere(20, 7.2)))
    full = fsjax.ops.marching_cubes(vol, level=0.0)
    nf = int(full.face_valid.sum())
    small = jax.jit(lambda v: fsjax.ops.marching_cubes(v, level=0.0, max_faces=nf // 2))(vol)
    assert bool(small.truncated) and int(small.face_valid.sum()) <= nf // 2
    # an eager call with the same too-small buffer is complete
    grown = fsjax.ops.marching_cubes(vol, level=0.0, max_faces=nf // 2)
    assert not bool(grown.truncated) and int(grown.face_valid.sum()) == nf
    # fewer face slots than active cubes (the face count is then known only after a second
    # call): the eager result is still the complete mesh, face for face
    tiny = fsjax.ops.marching_cubes(vol, level=0.0, max_faces=4)
    assert not bool(tiny.truncated)
    assert np.array_equal(_mesh_np(tiny)[1], _mesh_np(full)[1])
    assert np.array_equal(_mesh_np(tiny)[0], _mesh_np(full)[0])
    # too few vertex slots under jit: flagged, faces that lost a vertex dropped
    few = jax.jit(lambda v: fsjax.ops.marching_cubes(v, level=0.0, max_vertices=50))(vol)
    assert bool(few.truncated)
    kept = np.asarray(few.faces)[np.asarray(few.face_valid)]
    assert len(kept) < nf and (len(kept) == 0 or kept.max() < 50)


def test_level_is_traced_and_vertices_move_with_it():
    vol = fsjax.Volume(jnp.asarray(_sphere(16, 5.0)))
    f = jax.jit(lambda lv: fsjax.ops.marching_cubes(vol, level=lv).vertices)

    def mean_radius(lv):
        m = fsjax.ops.marching_cubes(vol, level=lv)
        v = m.vertices - 7.5
        w = m.vertex_valid.astype(v.dtype)
        return jnp.sum(jnp.linalg.norm(jnp.where(w[:, None] > 0, v, 1.0), axis=1) * w) / jnp.sum(w)

    # field = 5 - r: level 0.25 is the sphere of radius 4.75; d(mean radius)/d(level) is -1
    # up to the linear interpolation of r along the grid edges
    g = float(jax.grad(mean_radius)(0.25))
    fd = float((mean_radius(0.25 + 1e-6) - mean_radius(0.25 - 1e-6)) / 2e-6)
    assert g == pytest.approx(fd, rel=1e-5) and g != 0.0
    assert g == pytest.approx(-1.0, abs=0.1)
    assert f(0.25).shape == f(0.5).shape


def test_fails_closed():
    with pytest.raises(ValueError, match="marching_cubes: argument 'vol'"):
        fsjax.ops.marching_cubes(fsjax.Volume(jnp.zeros((1, 4, 4))))
    with pytest.raises(TypeError, match="marching_cubes: argument 'level'"):
        fsjax.ops.marching_cubes(fsjax.Volume(jnp.zeros((3, 4, 4))), level="0.5")
    with pytest.raises(ValueError, match="max_faces"):
        fsjax.ops.marching_cubes(fsjax.Volume(jnp.zeros((3, 4, 4))), max_faces=0)
    v = _sphere(12, 4.0)
    v[2, 3, 4] = np.nan
    # eager: refused with the op's name; traced: every vertex NaN (no surface guessed round a hole)
    with pytest.raises(ValueError, match="marching_cubes: argument 'vol'.*NaN"):
        fsjax.ops.marching_cubes(fsjax.Volume(jnp.asarray(v)), level=0.0)
    m = jax.jit(lambda x: fsjax.ops.marching_cubes(fsjax.Volume(x), level=0.0))(jnp.asarray(v))
    assert int(m.vertex_valid.sum()) > 0 and bool(jnp.all(jnp.isnan(m.vertices)))
    # no surface: an empty mesh, not a guessed one
    e = fsjax.ops.marching_cubes(fsjax.Volume(jnp.zeros((4, 5, 6))), level=0.5)
    assert int(e.face_valid.sum()) == 0 and int(e.vertex_valid.sum()) == 0 and not bool(e.truncated)


def test_infinite_voxels_carry_no_data():
    # a ball SDF with the half-space z < 8 marked no-data (-inf): the mesh is the upper part of
    # the sphere only, every vertex on it, open where the data stops; without the marks (the
    # null) the whole sphere closes
    z, y, x = np.mgrid[:20, :20, :20] - 9.5
    d = 6.0 - np.sqrt(x**2 + y**2 + z**2)
    full = fsjax.ops.marching_cubes(fsjax.Volume(jnp.asarray(d)), level=0.0)
    for val in (-np.inf, np.inf):
        cut = np.where(np.mgrid[:20, :20, :20][0] < 8, val, d)
        m = fsjax.ops.marching_cubes(fsjax.Volume(jnp.asarray(cut)), level=0.0)
        v = np.asarray(m.vertices)[np.asarray(m.vertex_valid)]
        r = np.linalg.norm(v - 9.5, axis=1)
        assert np.isfinite(v).all() and np.abs(r - 6.0).max() < 0.1
        assert v[:, 2].min() >= 8.0                     # nothing next to the no-data voxels
        t = fsjax.ops.mesh_topology(m)
        assert not bool(t.closed) and int(t.boundary_edges) > 0 and int(t.nonmanifold_edges) == 0
        nf = int(np.asarray(m.face_valid).sum())
        # the cap z >= 8 is (15.5 - 8) / 12 = 62.5 % of the sphere's area (Archimedes)
        assert 0.55 < nf / int(np.asarray(full.face_valid).sum()) < 0.66
    assert bool(fsjax.ops.mesh_topology(full).closed)
    with pytest.raises(ValueError, match="marching_cubes.*NaN"):
        fsjax.ops.marching_cubes(fsjax.Volume(jnp.asarray(np.where(cut > 5, np.nan, d))), level=0.0)
