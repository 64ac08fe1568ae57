"""The camera model: round trips, undistortion, look_at, GL conversion, gradients, bad input."""

import doctest

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fsjax
from fsjax import Camera, Depth
from fsjax.render import camera as C


def _cam(dist=None):
    R, t = C.look_at([0.3, -0.2, -3.0], [0.0, 0.1, 0.2], up=[0.0, -1.0, 0.0])
    K = jnp.asarray([[520.0, 0.3, 318.2], [0.0, 515.0, 247.9], [0.0, 0.0, 1.0]])
    return Camera(K, width=640, height=480, dist=dist, R=R, t=t)


DIST = jnp.asarray([-0.28, 0.09, 0.0012, -0.0007, -0.012])


def test_module_examples():
    res = doctest.testmod(C, extraglobs={"fsjax": fsjax, "jnp": jnp, "np": np, "jax": jax})
    assert res.attempted >= 20 and res.failed == 0


@pytest.mark.parametrize("dist", [None, DIST])
def test_project_backproject_round_trip(dist):
    cam = _cam(dist)
    rng = np.random.default_rng(0)
    X = jnp.asarray(rng.uniform(-0.8, 0.8, (500, 3)) + np.array([0.0, 0.0, 0.5]))
    uv, z = C.project(cam, X)
    assert bool(jnp.all(z > 0))
    back = C.backproject(cam, uv, z)
    err = float(jnp.max(jnp.abs(back - X)))
    print(f"camera round trip (dist={'BC5' if dist is not None else 'none'}): max |X - X'| = {err:.1e}")
    assert err < 1e-12


def test_undistort_converges_below_1e10_px():
    rng = np.random.default_rng(1)
    xy = jnp.asarray(rng.uniform(-0.55, 0.55, (2000, 2)))
    xd = C.distort_normalized(DIST, xy)
    u = C.undistort_normalized(DIST, xd)
    f = 520.0
    px = float(jnp.max(jnp.linalg.norm(u.xy - xy, axis=-1))) * f
    res_px = float(jnp.max(u.residual)) * f
    print(f"undistort: max error {px:.1e} px, max residual {res_px:.1e} px, max iterations {int(u.iterations.max())}")
    assert bool(jnp.all(u.converged)) and px < 1e-10 and res_px < 1e-10


def test_undistort_fails_closed_outside_invertible_region():
    # strong barrel distortion folds back beyond r ~ 1/sqrt(3|k1|): a far target has no preimage
    d = jnp.asarray([-0.5, 0.0, 0.0, 0.0, 0.0])
    u = C.undistort_normalized(d, jnp.asarray([[2.0, 0.0], [0.1, 0.05]]))
    assert not bool(u.converged[0]) and bool(jnp.all(jnp.isnan(u.xy[0])))
    assert bool(u.converged[1])


def test_undistort_gradient_matches_finite_difference():
    xd = jnp.asarray([0.31, -0.22])

    def loss(d):
        return jnp.sum(C.undistort_normalized(d, xd).xy ** 2)

    g = jax.grad(loss)(DIST)
    h = 1e-6
    fd = np.array([(loss(DIST.at[i].add(h)) - loss(DIST.at[i].add(-h))) / (2 * h) for i in range(5)])
    print(f"undistort grad vs FD: max |diff| = {np.max(np.abs(np.asarray(g) - fd)):.1e}, |g| = {np.linalg.norm(g):.3f}")
    assert np.linalg.norm(g) > 1e-3
    np.testing.assert_allclose(np.asarray(g), fd, rtol=1e-6, atol=1e-9)


def test_projection_gradient_wrt_intrinsics_nonzero_and_fd():
    X = jnp.asarray([[0.1, 0.2, 0.4], [-0.3, 0.1, 0.1]])

    def loss(K):
        cam = _cam(DIST)
        cam = Camera(K, width=640, height=480, dist=cam.dist, R=cam.R, t=cam.t)
        return jnp.sum(C.project(cam, X)[0])

    K0 = _cam().K
    g = jax.grad(loss)(K0)
    h = 1e-5
    fd = (loss(K0.at[0, 0].add(h)) - loss(K0.at[0, 0].add(-h))) / (2 * h)
    assert abs(float(g[0, 0])) > 1e-3
    assert abs(float(g[0, 0]) - float(fd)) < 1e-6 * max(1.0, abs(float(fd)))


def test_look_at_frame_and_axes():
    R, t = C.look_at([2.0, 1.0, -4.0], [0.0, 0.0, 0.0], up=[0.0, 1.0, 0.0])
    assert np.allclose(np.asarray(R.T @ R), np.eye(3), atol=1e-14)
    assert abs(float(jnp.linalg.det(R)) - 1.0) < 1e-14
    cam = Camera.from_intrinsics(100.0, 100.0, 49.5, 49.5, width=100, height=100, R=R, t=t)
    uv, z = C.project(cam, jnp.zeros(3))
    assert np.allclose(np.asarray(uv), [49.5, 49.5], atol=1e-12)
    assert abs(float(z) - float(np.linalg.norm([2.0, 1.0, -4.0]))) < 1e-12
    # world up projects upward in the image (smaller row)
    uv_up, _ = C.project(cam, jnp.asarray([0.0, 0.3, 0.0]))
    assert float(uv_up[1]) < 49.5


def test_gl_pose_used_as_cv_gives_wrong_but_plausible_depths():
    """The trap the convention rule exists for: a GL pose read as OpenCV sees the scene from behind."""
    R, t = C.look_at([0.0, 0.0, -4.0], [0.0, 0.0, 0.0], up=[0.0, 1.0, 0.0])
    Rg, tg = C.gl_from_cv_pose(R, t)
    Rc, tc = C.cv_from_gl_pose(Rg, tg)
    assert np.allclose(np.asarray(Rc), np.asarray(R), atol=1e-15)
    good = Camera.from_intrinsics(100.0, 100.0, 49.5, 49.5, width=100, height=100, R=R, t=t)
    wrong = Camera.from_intrinsics(100.0, 100.0, 49.5, 49.5, width=100, height=100, R=Rg, t=tg)
    X = jnp.asarray([0.2, 0.1, 0.0])
    _, z_good = C.project(good, X)
    _, z_wrong = C.project(wrong, X)
    assert abs(float(z_good) - 4.0) < 1e-12
    assert float(z_wrong) < 0  # behind the camera: project refuses it (NaN uv)
    assert bool(jnp.all(jnp.isnan(C.project(wrong, X)[0])))


def test_intrinsics_from_fov():
    K = C.intrinsics_from_fov(640, 480, fov_y_deg=60.0)
    assert abs(float(K[1, 1]) - 240.0 / np.tan(np.radians(30.0))) < 1e-9
    assert float(K[0, 0]) == float(K[1, 1])


def test_depth_to_points_on_a_plane():
    R, t = C.look_at([0.0, 0.0, -5.0], [0.0, 0.0, 0.0], up=[0.0, -1.0, 0.0])
    cam = Camera.from_intrinsics(60.0, 60.0, 15.5, 11.5, width=32, height=24, R=R, t=t)
    z = jnp.full((24, 32), 5.0).at[0, 0].set(0.0).at[1, 1].set(jnp.nan)
    pts = fsjax.ops.depth_to_points(Depth(z, cam))
    xyz = np.asarray(pts.xyz)[np.asarray(pts.valid)]
    assert int(pts.valid.sum()) == 24 * 32 - 2
    assert np.max(np.abs(xyz[:, 2])) < 1e-12  # every valid point lies on the world plane z = 0


def test_bad_input():
    with pytest.raises(ValueError, match="look_at.*up"):
        C.look_at([0.0, 0.0, -1.0], [0.0, 0.0, 0.0], up=[0.0, 0.0, 1.0])
    with pytest.raises(ValueError, match="look_at.*coincide"):
        C.look_at([1.0, 0.0, 0.0], [1.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="intrinsics_from_fov.*fov_x_deg"):
        C.intrinsics_from_fov(10, 10, fov_x_deg=180.0)
    batch = Camera(jnp.stack([jnp.eye(3)] * 2), width=4, height=4)
    with pytest.raises(ValueError, match="project.*vmap"):
        C.project(batch, jnp.zeros(3))
    with pytest.raises(TypeError, match="project.*Camera"):
        C.project("cam", jnp.zeros(3))
