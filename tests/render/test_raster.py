"""Tests of the tiled mesh rasteriser (fsjax.render.raster)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fsjax
from fsjax.render import interpolate, rasterize
from fsjax.synth._pool import icosphere


def _cam(W=48, H=40, fov=40.0, eye=(0.0, 0.0, -4.0), target=(0.0, 0.0, 0.0), up=(0.0, -1.0, 0.0)):
    K = fsjax.render.intrinsics_from_fov(W, H, fov_x_deg=fov)
    R, t = fsjax.render.look_at(jnp.asarray(eye), jnp.asarray(target), up=jnp.asarray(up))
    return fsjax.Camera(K, width=W, height=H, R=R, t=t)


def _sphere_hits(cam, radius):
    """Closed-form ray-sphere (centre 0) entry depth; NaN where the ray misses."""
    o, d = fsjax.render.pixel_rays(cam)
    b = jnp.sum(o * d, -1)
    c = jnp.sum(o * o, -1) - radius**2
    disc = b * b - c
    s = -b - jnp.sqrt(jnp.where(disc >= 0, disc, 0.0))
    axis = cam.R[:, 2]
    z = s * jnp.sum(d * axis, -1)
    return jnp.where(disc >= 0, z, jnp.nan)


def test_plane_at_known_depth_exact():
    cam = _cam(32, 24, fov=60.0, up=(0.0, -1.0, 0.0))
    cam = fsjax.Camera(cam.K, width=32, height=24)  # identity pose
    v = jnp.asarray([[-5.0, -5, 3], [5, -5, 3], [5, 5, 3], [-5, 5, 3]])
    r = rasterize(fsjax.Mesh(v, jnp.asarray([[0, 2, 1], [0, 3, 2]])), cam, tile=8, capacity=4)
    err = float(jnp.max(jnp.abs(r.depth - 3.0)))
    print(f"fronto-parallel plane z=3: max |depth - 3| = {err:.1e}, coverage {float(r.alpha.mean()):.3f}")
    assert err <= 1e-14 and float(r.alpha.mean()) == 1.0 and int(r.overflow) == 0
    # tilted plane n . X = h: depth = h / (n . d) for d = K^-1 (u, v, 1)
    nrm = jnp.asarray([0.3, -0.2, 1.0])
    h = 4.0
    xy = jnp.asarray([[-9.0, -9], [9, -9], [9, 9], [-9, 9]])
    z = (h - xy @ nrm[:2]) / nrm[2]
    vt = jnp.concatenate([xy, z[:, None]], axis=1)
    r = rasterize(fsjax.Mesh(vt, jnp.asarray([[0, 2, 1], [0, 3, 2]])), cam, tile=8, capacity=4)
    d = fsjax.render.raster._rays(cam.K, 24, 32, jnp.float64)
    zt = h / (d @ nrm)
    err = float(jnp.max(jnp.abs(r.depth - zt)))
    print(f"tilted plane: max |depth - h/(n.d)| = {err:.1e}")
    assert err <= 1e-13
    np.testing.assert_allclose(r.face_normal[5, 5], -nrm / jnp.linalg.norm(nrm), atol=1e-14)


def test_sphere_depth_sandwiched_by_closed_form():
    V, F = icosphere(4)
    Vn = V / np.linalg.norm(V, axis=1, keepdims=True)
    T = Vn[F]
    nrm = np.cross(T[:, 1] - T[:, 0], T[:, 2] - T[:, 0])
    r_in = float(np.min(np.abs(np.sum(nrm / np.linalg.norm(nrm, axis=1, keepdims=True) * T[:, 0], 1))))
    cam = _cam(64, 64, fov=36.0)
    r = rasterize(fsjax.Mesh(jnp.asarray(Vn), jnp.asarray(F)), cam, tile=16, capacity=1024, cull_backfaces=True)
    z1 = _sphere_hits(cam, 1.0)
    zi = _sphere_hits(cam, r_in)
    inner = np.isfinite(np.asarray(zi))
    err = float(jnp.nanmax(jnp.where(inner, jnp.abs(r.depth - z1), jnp.nan)))
    print(f"icosphere(4) ({len(F)} faces): inscribed radius {r_in:.6f}; depth vs unit sphere max err {err:.2e} "
          f"inside the inscribed sphere's image; overflow {int(r.overflow)}")
    assert int(r.overflow) == 0
    # Polytope lies between the inscribed sphere and the unit sphere: z1 <= z <= z_in on rays hitting both.
    tol = 1e-12
    assert bool(jnp.all(jnp.where(inner, (r.depth >= z1 - tol) & (r.depth <= zi + tol), True)))
    assert bool(jnp.all(r.alpha[inner] == 1.0))
    assert bool(jnp.all(r.alpha[~np.isfinite(np.asarray(z1))] == 0.0))
    assert err <= (1 - r_in) / 0.05  # loose global bound; the sandwich is the real test
    assert bool(jnp.all(r.front == (r.alpha > 0)))


def test_occlusion_stacked_and_interpenetrating():
    cam = fsjax.Camera(fsjax.render.intrinsics_from_fov(32, 32, fov_x_deg=50.0), width=32, height=32)
    big = 10.0

    def tri(z0, z1=None, flip=False):
        z1 = z0 if z1 is None else z1
        t = [[-big, -big, z0], [big, -big, z0], [0.0, big, z1]]
        return t[::-1] if flip else t

    # stacked parallel triangles at z = 4, 2, 3 (submission order must not matter)
    for order in ([4.0, 2.0, 3.0], [2.0, 3.0, 4.0], [3.0, 4.0, 2.0]):
        v = jnp.asarray(sum([tri(z) for z in order], []))
        f = jnp.arange(9, dtype=jnp.int32).reshape(3, 3)
        r = rasterize(fsjax.Mesh(v, f), cam, tile=8, capacity=8)
        cov = r.alpha > 0
        assert bool(jnp.all(r.depth[cov] == 2.0))
        assert bool(jnp.all(r.face_id[cov] == order.index(2.0)))
    # interpenetrating: plane z = 3 against a tilted plane crossing it along the middle row
    vA = [[-big, -big, 3.0], [big, -big, 3.0], [big, big, 3.0], [-big, big, 3.0]]
    vB = [[-big, -big, 1.0], [big, -big, 1.0], [big, big, 5.0], [-big, big, 5.0]]
    v = jnp.asarray(vA + vB)
    f = jnp.asarray([[0, 2, 1], [0, 3, 2], [4, 6, 5], [4, 7, 6]])
    r = rasterize(fsjax.Mesh(v, f), cam, tile=8, capacity=8)
    d = fsjax.render.raster._rays(cam.K, 32, 32, jnp.float64)
    # plane B: z = 3 + (y_world / big) * 2 with y = z * dy  ->  z = 3 / (1 - 2 dy / big)
    zB = 3.0 / (1.0 - 2.0 * d[..., 1] / big)
    truth = jnp.minimum(3.0, zB)
    err = float(jnp.max(jnp.abs(r.depth - truth)))
    print(f"interpenetrating planes: max |depth - min(zA, zB)| = {err:.1e}")
    assert err <= 1e-13
    assert bool(jnp.all(jnp.where(zB < 3.0 - 1e-9, r.face_id >= 2, True)))
    assert bool(jnp.all(jnp.where(zB > 3.0 + 1e-9, r.face_id <= 1, True)))


def test_overflow_counted_never_silent():
    cam = fsjax.Camera(fsjax.render.intrinsics_from_fov(16, 16, fov_x_deg=50.0), width=16, height=16)
    zs = np.arange(10, 0, -1, dtype=float) + 1.0  # far to near; the nearest has the highest id
    v = np.concatenate([[[-9, -9, z], [9, -9, z], [0, 9, z]] for z in zs])
    m = fsjax.Mesh(jnp.asarray(v), jnp.arange(30, dtype=jnp.int32).reshape(10, 3))
    full = rasterize(m, cam, tile=8, capacity=4)  # eager: buffer sized from the demand, complete
    demand = fsjax.render.count_fragments(m, cam)
    B = 4 * 256  # room for the candidates of 4 of the 10 full-screen triangles
    short = rasterize(m, cam, max_fragments=B)
    print(f"overflow: demand {demand} candidates; eager default -> {int(full.overflow)} dropped; buffer {B} -> "
          f"{int(short.overflow)} dropped, {int(short.incomplete.sum())} pixels flagged")
    assert demand == 10 * 256
    assert int(full.overflow) == 0 and not bool(full.incomplete.any())
    assert bool(jnp.all(full.depth[full.alpha > 0] == 2.0))
    assert int(short.overflow) == demand - B
    cov = short.alpha > 0
    # the nearest triangle (highest id) is lost: the result differs, and every such pixel is flagged
    assert bool(jnp.any(short.depth != full.depth))
    assert bool(jnp.all(jnp.where(short.depth != full.depth, short.incomplete, True)))
    assert bool(jnp.all(short.incomplete[cov]))
    # under jit the traced default buffer is 4 x capacity x tiles (here 4 x 4 x 4 = 64 < demand)
    j = jax.jit(lambda m: rasterize(m, cam, tile=8, capacity=4))(m)
    assert int(j.overflow) == demand - 64 and bool(jnp.all(j.incomplete[j.alpha > 0]))


def test_default_capacity_complete_on_bundled_bunny():
    # issue 20: at the old default (capacity 256 triangles per 16 x 16 tile) the bundled bunny at
    # 640 x 480 dropped 33,005 triangle-tile pairs and 1,453 pixels were wrong; an eager call now
    # sizes its buffer from the measured demand and is complete.
    b = fsjax.data.bunny()
    V = np.asarray(b.vertices, float)
    c = 0.5 * (V.min(0) + V.max(0))
    K = fsjax.render.intrinsics_from_fov(640, 480, fov_x_deg=40.0)
    R, t = fsjax.render.look_at(jnp.asarray(c + np.asarray([0.12, 0.09, 0.28])), jnp.asarray(c),
                                up=jnp.asarray([0.0, 1.0, 0.0]))  # the tour's view of the bunny
    cam = fsjax.Camera(K, width=640, height=480, R=R, t=t)
    m = fsjax.Mesh(jnp.asarray(V), jnp.asarray(b.faces, jnp.int32))
    r = rasterize(m, cam)
    cover = float(r.alpha.mean())
    print(f"bunny {m.faces.shape[0]} faces at 640 x 480, default arguments: overflow {int(r.overflow)}, "
          f"incomplete {int(r.incomplete.sum())} pixels, coverage {cover:.3f}")
    assert int(r.overflow) == 0 and not bool(r.incomplete.any()) and cover > 0.1


def test_matches_bruteforce_and_interpolate_perspective_correct():
    V, F = icosphere(2)
    V = V * np.asarray([1.0, 0.7, 1.2]) + 0.1 * np.sin(3 * V[:, [1, 2, 0]])
    m = fsjax.Mesh(jnp.asarray(V), jnp.asarray(F))
    cam = _cam(40, 32, fov=50.0, eye=(1.5, -1.0, -3.0))
    a = rasterize(m, cam, tile=8, capacity=256)
    b = rasterize(m, cam, tile=64, capacity=len(F))  # one tile, all triangles
    assert int(a.overflow) == 0
    assert bool(jnp.all(a.face_id == b.face_id))
    np.testing.assert_allclose(a.depth, b.depth, atol=1e-14)
    # barycentric interpolation of world positions lands on the back-projected depth
    X = interpolate(a, m, m.vertices)
    uv = fsjax.render.pixel_grid_uv(cam)
    Xb = fsjax.render.backproject(cam, uv, a.depth)
    cov = np.asarray(a.alpha > 0)
    err = float(jnp.max(jnp.abs(X - Xb)[cov]))
    print(f"interpolated world position vs back-projected depth: max err {err:.1e}")
    assert err <= 1e-12
    assert bool(jnp.all(jnp.abs(jnp.sum(a.bary, -1)[cov] - 1.0) <= 1e-12))
    assert bool(jnp.all(a.bary[cov] >= -1e-12))
    # jit gives the same answer
    c = jax.jit(lambda m, c: rasterize(m, c, tile=8, capacity=256))(m, cam)
    assert bool(jnp.all(c.face_id == a.face_id))


def test_gradient_interior_fd():
    V, F = icosphere(1)
    m0 = fsjax.Mesh(jnp.asarray(V), jnp.asarray(F))
    cam = _cam(24, 20, fov=45.0, eye=(0.5, -0.3, -3.5))
    w = jnp.asarray(np.random.default_rng(0).uniform(0.5, 1.5, (20, 24)))

    def loss(verts, t, K):
        c = fsjax.Camera(K, width=24, height=20, R=cam.R, t=t)
        r = rasterize(fsjax.Mesh(verts, m0.faces), c, tile=8, capacity=64)
        return jnp.sum(w * r.depth) + 3.0 * jnp.sum(w * r.bary[..., 0]) + jnp.sum(w * r.normal[..., 0])

    args = (m0.vertices, cam.t, cam.K)
    g = jax.jit(jax.grad(loss, argnums=(0, 1, 2)))(*args)
    loss = jax.jit(loss)

    @jax.jit
    def ids(verts, t, K):
        c = fsjax.Camera(K, width=24, height=20, R=cam.R, t=t)
        return rasterize(fsjax.Mesh(verts, m0.faces), c, tile=8, capacity=64).face_id

    rng = np.random.default_rng(1)
    ids0 = ids(*args)
    for k, name in enumerate(["vertices", "t", "K"]):
        dirn = jnp.asarray(rng.normal(size=args[k].shape))
        if name == "K":
            dirn = dirn * jnp.asarray([[1.0, 0, 1], [0, 1, 1], [0, 0, 0]]) * 10.0
        eps = 1e-6
        ap = list(args)
        am = list(args)
        ap[k] = args[k] + eps * dirn
        am[k] = args[k] - eps * dirn
        fd = (loss(*ap) - loss(*am)) / (2 * eps)
        an = float(jnp.sum(g[k] * dirn))
        for a_ in (ap, am):  # visibility must not change for an interior derivative
            assert bool(jnp.all(ids(*a_) == ids0))
        rel = abs(an - float(fd)) / abs(float(fd))
        print(f"raster gradient wrt {name}: analytic {an:.6f}, FD {float(fd):.6f}, rel {rel:.1e}")
        assert abs(an) > 1e-3
        assert rel < 1e-5


def test_bad_input():
    cam = _cam(16, 16)
    with pytest.raises(ValueError, match="rasterize.*empty"):
        rasterize(fsjax.Mesh(jnp.zeros((0, 3)), jnp.zeros((0, 3), jnp.int32)), cam)
    V, F = icosphere(1)
    m = fsjax.Mesh(jnp.asarray(V), jnp.asarray(F))
    with pytest.raises(ValueError, match="rasterize.*no valid face"):
        rasterize(fsjax.Mesh(m.vertices, m.faces, face_valid=jnp.zeros(len(F), bool)), cam)
    with pytest.raises(ValueError, match="rasterize: argument 'capacity' must be >= 1, got 0"):
        rasterize(m, cam, capacity=0)
    with pytest.raises(TypeError, match="rasterize: argument 'tile' must be an integer, got 2.5"):
        rasterize(m, cam, tile=2.5)
    dcam = fsjax.Camera(cam.K, width=16, height=16, R=cam.R, t=cam.t, dist=jnp.asarray([0.1, 0, 0, 0, 0]))
    with pytest.raises(ValueError, match="distortion"):
        rasterize(m, dcam)
    # NaN and degenerate triangles are skipped and counted
    Vb = np.asarray(V).copy()
    Fb = np.concatenate([F, [[0, 0, 1], [0, 1, 2]]])
    Vb = np.concatenate([Vb, [[np.nan, 0.0, 0.0]]])
    Fb[-1] = [len(V), 1, 2]
    r = rasterize(fsjax.Mesh(jnp.asarray(Vb), jnp.asarray(Fb)), cam)
    ref = rasterize(m, cam)
    assert int(r.bad_faces) == 2
    assert bool(jnp.all(jnp.isfinite(r.depth))) and bool(jnp.all(r.face_id == ref.face_id))
    # camera inside the object: sees back faces only (flagged by front == False)
    ri = rasterize(m, _cam(16, 16, eye=(0.0, 0.0, -0.2)))
    assert float(ri.alpha.mean()) == 1.0 and not bool(ri.front.any())
    # object behind the camera: nothing rendered, no crash
    rb = rasterize(m, _cam(16, 16, eye=(0.0, 0.0, -4.0), target=(0.0, 0.0, -8.0)))
    assert float(rb.alpha.sum()) == 0.0 and bool(jnp.all(rb.face_id == -1)) and bool(jnp.all(rb.depth == 0))
    # a triangle crossing the camera plane is clipped at the near plane, not mirrored
    v = jnp.asarray([[-1.0, -1.0, -2.0], [1.0, -1.0, -2.0], [0.0, 1.0, 6.0]])
    rc = rasterize(fsjax.Mesh(v, jnp.asarray([[0, 1, 2]])), fsjax.Camera(cam.K, width=16, height=16))
    assert bool(jnp.all(rc.depth[rc.alpha > 0] > 0)) and float(rc.alpha.sum()) > 0
