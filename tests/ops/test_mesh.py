"""Mesh ops: area, enclosed volume, topology counts, Laplacian and Taubin smoothing."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fsjax
from fsjax.synth import icosphere


def _mesh(sub=2, radius=1.0, dtype=jnp.float64):
    v, f = icosphere(sub, radius)
    return fsjax.Mesh(jnp.asarray(v, dtype), jnp.asarray(f))


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
def test_area_and_volume_of_a_box_far_from_the_origin(dtype):
    # an axis-aligned 2 x 3 x 4 box (12 outward triangles) placed 1e4 units from the origin
    c = np.array([[x, y, z] for z in (0, 4) for y in (0, 3) for x in (0, 2)], float) + 1e4
    f = np.array([[0, 2, 1], [1, 2, 3], [4, 5, 6], [5, 7, 6], [0, 1, 4], [1, 5, 4],
                  [2, 6, 3], [3, 6, 7], [0, 4, 2], [2, 4, 6], [1, 3, 5], [3, 7, 5]])
    m = fsjax.Mesh(jnp.asarray(c, dtype), jnp.asarray(f))
    area, vol = float(fsjax.ops.mesh_area(m)), float(fsjax.ops.mesh_volume(m))
    rel = 1e-12 if dtype == jnp.float64 else 1e-5
    print(f"box 2x3x4 at 1e4 ({jnp.dtype(dtype).name}): area {area} (52), volume {vol} (24)")
    assert area == pytest.approx(52.0, rel=rel)
    # the apex at the vertex mean keeps the sum exact far from the origin; the naive sum about
    # the origin (the null) loses it in float32
    assert vol == pytest.approx(24.0, rel=rel)
    t = jnp.asarray(c, dtype)[jnp.asarray(f)]
    naive = float(jnp.sum(jnp.sum(t[:, 0] * jnp.cross(t[:, 1], t[:, 2]), -1)) / 6)
    if dtype == jnp.float32:
        assert abs(naive - 24.0) > 100 * abs(vol - 24.0)
    topo = fsjax.ops.mesh_topology(m)
    assert bool(topo.closed) and bool(topo.oriented) and int(topo.euler) == 2


def test_volume_sign_reports_winding_and_open_surfaces_are_nan():
    m = _mesh(3, 2.0)
    v = float(fsjax.ops.mesh_volume(m))
    assert v == pytest.approx(4 / 3 * np.pi * 8, rel=0.01)
    assert float(fsjax.ops.mesh_volume(fsjax.Mesh(m.vertices, m.faces[:, ::-1]))) == pytest.approx(-v, rel=1e-12)
    # one face flipped: not consistently oriented -> no volume, and the topology says why
    bad = fsjax.Mesh(m.vertices, m.faces.at[7].set(m.faces[7, ::-1]))
    assert np.isnan(float(fsjax.ops.mesh_volume(bad)))
    assert int(fsjax.ops.mesh_topology(bad).flipped_edges) == 3
    # one face dropped: open -> NaN
    holed = fsjax.Mesh(m.vertices, m.faces, face_valid=jnp.arange(m.faces.shape[0]) != 3)
    assert np.isnan(float(fsjax.ops.mesh_volume(holed)))
    # no face at all: NaN, area 0
    empty = fsjax.Mesh(m.vertices, m.faces, face_valid=jnp.zeros(m.faces.shape[0], bool))
    assert np.isnan(float(fsjax.ops.mesh_volume(empty))) and float(fsjax.ops.mesh_area(empty)) == 0.0


def test_topology_counts():
    a = _mesh(1)
    b = fsjax.Mesh(a.vertices + 5.0, a.faces)
    # two disjoint spheres in one mesh
    two = fsjax.Mesh(jnp.concatenate([a.vertices, b.vertices]),
                     jnp.concatenate([a.faces, b.faces + a.vertices.shape[0]]))
    t = fsjax.ops.mesh_topology(two)
    assert (int(t.vertices), int(t.faces), int(t.edges), int(t.components), int(t.euler)) == (84, 160, 240, 2, 4)
    assert bool(t.closed) and bool(t.manifold)
    # a fin: a third face on an existing edge makes it non-manifold
    f = a.faces[0]
    fin = fsjax.Mesh(jnp.concatenate([a.vertices, jnp.asarray([[3.0, 3.0, 3.0]])]),
                     jnp.concatenate([a.faces, jnp.asarray([[f[0], f[1], 42]])]))
    tf = fsjax.ops.mesh_topology(fin)
    assert int(tf.nonmanifold_edges) == 1 and int(tf.boundary_edges) == 2 and not bool(tf.manifold)
    # an unused vertex does not count
    assert int(tf.vertices) == 43 and int(fsjax.ops.mesh_topology(a).vertices) == 42
    # the marching-cubes surface of a ball is one closed oriented sphere
    z, y, x = np.mgrid[:12, :12, :12] - 5.5
    mc = fsjax.ops.marching_cubes(fsjax.Volume(jnp.asarray(4.0 - np.sqrt(x**2 + y**2 + z**2))), level=0.0)
    tm = fsjax.ops.mesh_topology(mc)
    assert bool(tm.closed) and bool(tm.oriented) and int(tm.components) == 1 and int(tm.euler) == 2


def test_taubin_keeps_volume_where_laplacian_shrinks():
    v, f = icosphere(3)
    rng = np.random.default_rng(1)
    noisy = v * (1 + 0.02 * rng.standard_normal((len(v), 1)))
    m = fsjax.Mesh(jnp.asarray(noisy), jnp.asarray(f))
    v0 = float(fsjax.ops.mesh_volume(fsjax.Mesh(jnp.asarray(v), jnp.asarray(f))))
    tau = fsjax.ops.taubin_smooth(m, iterations=10)
    lap = fsjax.ops.laplacian_smooth(m, iterations=10)

    def noise(mm):
        r = np.linalg.norm(np.asarray(mm.vertices), axis=1)
        return r.std()

    dv_t = float(fsjax.ops.mesh_volume(tau)) / v0 - 1
    dv_l = float(fsjax.ops.mesh_volume(lap)) / v0 - 1
    print(f"noisy icosphere (radial noise {noise(m):.4f}): Taubin noise {noise(tau):.4f} volume {dv_t:+.4f}; "
          f"Laplacian (null) noise {noise(lap):.4f} volume {dv_l:+.4f}")
    assert noise(tau) < 0.5 * noise(m)
    assert abs(dv_t) < 0.01 and dv_l < -0.05
    # zero iterations: unchanged; faces untouched
    same = fsjax.ops.taubin_smooth(m, iterations=0)
    assert bool(jnp.all(same.vertices == m.vertices)) and bool(jnp.all(tau.faces == m.faces))


def test_smoothing_gradient_and_errors():
    m = _mesh(1)

    def loss(v):
        return jnp.sum(fsjax.ops.taubin_smooth(fsjax.Mesh(v, m.faces), iterations=2).vertices[:, 0] ** 2)

    g = jax.grad(loss)(m.vertices)
    d = jnp.zeros_like(m.vertices).at[3, 0].set(1e-6)
    fd = (loss(m.vertices + d) - loss(m.vertices - d)) / 2e-6
    assert float(g[3, 0]) == pytest.approx(float(fd), rel=1e-6) and float(g[3, 0]) != 0.0
    with pytest.raises(ValueError, match="taubin_smooth: argument 'k_pb'"):
        fsjax.ops.taubin_smooth(m, lam=0.5, k_pb=3.0)
    with pytest.raises(ValueError, match="laplacian_smooth: argument 'lam'"):
        fsjax.ops.laplacian_smooth(m, lam=0.0)
    with pytest.raises(TypeError, match="taubin_smooth: argument 'iterations'"):
        fsjax.ops.taubin_smooth(m, iterations=2.5)
    with pytest.raises(TypeError, match="mesh_area: argument 'mesh'"):
        fsjax.ops.mesh_area(m.vertices)


# ---------------------------------------------------------------------------
# mesh_to_volume
# ---------------------------------------------------------------------------


def test_distance_to_one_triangle_in_every_voronoi_region():
    tri = fsjax.Mesh(jnp.asarray([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]]), jnp.asarray([[0, 1, 2]]))
    # voxel [k, i, j] sits at origin + (j, i, k) * spacing: a 1 x 1 x 1 grid placed at each point
    cases = {(0.2, 0.2, 0.5): 0.5,                        # face interior
             (-1.0, -1.0, 0.0): np.sqrt(2.0),             # vertex a
             (2.0, 0.0, 0.0): 1.0,                        # vertex b
             (0.0, 1.5, -2.0): np.sqrt(0.25 + 4.0),       # vertex c
             (0.5, -1.0, 0.3): np.sqrt(1.0 + 0.09),       # edge ab
             (-0.5, 0.5, 0.0): 0.5,                       # edge ac
             (1.0, 1.0, 0.0): np.sqrt(0.5)}               # edge bc
    for p, want in cases.items():
        d = fsjax.ops.mesh_to_volume(tri, shape=(1, 1, 1), origin=p)
        # an open triangle has winding number < 0.5 everywhere: outside, distance negative
        assert float(-d.data[0, 0, 0]) == pytest.approx(want, abs=1e-12), p


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
def test_sdf_sign_winding_and_round_trip_through_marching_cubes(dtype):
    R, c = 2.0, 2.5
    v, f = icosphere(3, R)
    m = fsjax.Mesh(jnp.asarray(v + c, dtype), jnp.asarray(f))
    kw = dict(shape=(11, 11, 11), spacing=(0.5, 0.5, 0.5))
    sdf = np.asarray(fsjax.ops.mesh_to_volume(m, **kw).data)
    z, y, x = np.mgrid[:11, :11, :11] * 0.5
    r = np.sqrt((x - c) ** 2 + (y - c) ** 2 + (z - c) ** 2)
    # the icosphere's faces lie within 0.005 R of the sphere (3 subdivisions): |sdf - (R - r)| small
    tol = 0.01 * R + (1e-5 if dtype == jnp.float32 else 1e-12)
    assert np.abs(sdf - (R - r)).max() < tol
    w = np.asarray(fsjax.ops.mesh_to_volume(m, kind="winding", **kw).data)
    far = np.abs(r - R) > 0.05
    assert np.allclose(w[far & (r < R)], 1.0, atol=1e-4) and np.allclose(w[far & (r > R)], 0.0, atol=1e-4)
    # inward winding: w = -1 inside, reported, and classified outside (never silently flipped)
    inv = fsjax.Mesh(m.vertices, m.faces[:, ::-1])
    wi = np.asarray(fsjax.ops.mesh_to_volume(inv, kind="winding", **kw).data)
    assert np.allclose(wi[far & (r < R)], -1.0, atol=1e-4)
    assert float(fsjax.ops.mesh_to_volume(inv, kind="occupancy", **kw).data.sum()) == 0.0
    # round trip: marching cubes of the SDF lies on the sphere (grid origin at 0)
    back = fsjax.ops.marching_cubes(fsjax.Volume(jnp.asarray(sdf), spacing=(0.5, 0.5, 0.5)), level=0.0)
    vb = np.asarray(back.vertices)[np.asarray(back.vertex_valid)]
    assert np.abs(np.linalg.norm(vb - c, axis=1) - R).max() < 0.05
    # at 4 voxels per radius linear interpolation cuts corners: within 5 % of the source's volume
    assert float(fsjax.ops.mesh_volume(back)) == pytest.approx(float(fsjax.ops.mesh_volume(m)), rel=0.05)


def test_mesh_to_volume_fails_closed():
    m = _mesh(1)
    with pytest.raises(ValueError, match="mesh_to_volume: argument 'kind'"):
        fsjax.ops.mesh_to_volume(m, kind="distance")
    with pytest.raises(ValueError, match="mesh_to_volume: argument 'spacing'"):
        fsjax.ops.mesh_to_volume(m, spacing=(1.0, 0.0, 1.0))
    with pytest.raises(ValueError, match="mesh_to_volume: .* exceeds the bound"):
        fsjax.ops.mesh_to_volume(m, shape=(4096, 4096, 2048))
    # a hole: the winding number drops below 1 near it, and an open surface still has a distance
    holed = fsjax.Mesh(m.vertices + 2.0, m.faces, face_valid=jnp.arange(80) != 0)
    w = fsjax.ops.mesh_to_volume(holed, shape=(5, 5, 5), kind="winding")
    assert 0.5 < float(w.data[2, 2, 2]) < 1.0


def test_mesh_to_volume_axes_on_an_off_centre_sphere():
    # distinct centre coordinates, spacings and sizes per axis: any swapped axis or shifted
    # voxel centre moves the zero set away from the analytic one
    R, c = 1.5, np.array([2.1, 3.3, 2.7])                           # (x, y, z)
    v, f = icosphere(3, R)
    m = fsjax.Mesh(jnp.asarray(v + c), jnp.asarray(f))
    sp, shape, origin = (0.5, 0.4, 0.3), (11, 17, 15), (0.1, 0.2, 0.3)
    sdf = np.asarray(fsjax.ops.mesh_to_volume(m, shape=shape, spacing=sp, origin=origin).data)
    k, i, j = np.mgrid[:shape[0], :shape[1], :shape[2]]
    x, y, z = origin[0] + j * sp[2], origin[1] + i * sp[1], origin[2] + k * sp[0]
    r = np.sqrt((x - c[0]) ** 2 + (y - c[1]) ** 2 + (z - c[2]) ** 2)
    assert np.abs(sdf - (R - r)).max() < 0.01 * R


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
def test_vertex_normals_are_radial_on_a_sphere_and_flip_with_the_winding(dtype):
    # ground truth: on a sphere the outward normal at a vertex is its direction from the centre
    v, f = icosphere(3, 2.0)
    c = np.array([5.0, -3.0, 7.0])
    m = fsjax.Mesh(jnp.asarray(v + c, dtype), jnp.asarray(f))
    n = np.asarray(fsjax.render.vertex_normals(m), float)
    r = v / np.linalg.norm(v, axis=1, keepdims=True)
    err = np.degrees(np.arccos(np.clip((n * r).sum(1), -1.0, 1.0)))
    # the null: the normal of one face the vertex belongs to (no averaging)
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    fn /= np.linalg.norm(fn, axis=1, keepdims=True)
    one = np.zeros_like(v)
    for k in range(3):
        one[f[:, k]] = fn                               # a later face overwrites: one face each
    err_null = np.degrees(np.arccos(np.clip((one * r).sum(1), -1.0, 1.0)))
    print(f"icosphere 1280 faces ({jnp.dtype(dtype).name}): vertex normal off radial max {err.max():.3f} deg "
          f"(one face's normal: {err_null.max():.3f} deg)")
    assert np.allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-5)
    assert err.max() < 1.0 and err.max() < err_null.max()
    # a flipped winding flips every normal (reported, not silently corrected)
    nf = np.asarray(fsjax.render.vertex_normals(fsjax.Mesh(m.vertices, m.faces[:, ::-1])), float)
    assert np.allclose(nf, -n, atol=1e-6)
