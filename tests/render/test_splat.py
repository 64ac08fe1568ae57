"""Splat rasteriser: tiled vs dense reference, FD gradients, overflow, near plane, compositing rules."""

import doctest

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fsjax
from fsjax import Camera, Gaussians
from fsjax.render import camera as C
from fsjax.render import splat as S


def _scene(n=40, k=4, seed=0, spread=0.6):
    rng = np.random.default_rng(seed)
    return Gaussians(rng.uniform(-spread, spread, (n, 3)), np.log(rng.uniform(0.03, 0.2, (n, 3))),
                     rng.normal(size=(n, 4)), rng.normal(0.0, 1.5, n), rng.normal(0.0, 0.5, (n, k, 3)))


def _cam(w=40, h=30, eye=(0.3, -0.4, -3.0)):
    R, t = C.look_at(list(eye), [0.0, 0.0, 0.0], up=[0.0, -1.0, 0.0])
    return Camera(C.intrinsics_from_fov(w, h, fov_x_deg=50.0), width=w, height=h, R=R, t=t)


FIELDS = ("color", "alpha", "depth", "median_depth", "distortion")


def test_module_examples():
    res = doctest.testmod(S, extraglobs={"fsjax": fsjax, "jnp": jnp, "np": np, "jax": jax})
    assert res.attempted >= 8 and res.failed == 0


@pytest.mark.parametrize("tile_size,capacity", [(8, 64), (16, 48)])
def test_tiled_matches_dense_images(tile_size, capacity):
    g, cam = _scene(), _cam()
    a = S.render_splats(g, cam, tile_size=tile_size, capacity=capacity, background=[0.1, 0.2, 0.3])
    b = S.render_splats_dense(g, cam, background=[0.1, 0.2, 0.3])
    assert int(a.overflow) == 0
    worst = max(float(jnp.max(jnp.abs(getattr(a, f) - getattr(b, f)))) for f in FIELDS)
    print(f"splat tiled ({tile_size}px, cap {capacity}) vs dense: max |diff| over 5 outputs = {worst:.1e}")
    assert worst < 1e-6
    assert float(jnp.max(a.alpha)) > 0.9 and float(jnp.min(a.alpha)) == 0.0  # a non-trivial image


def _loss_fn(renderer, cam_w=40, cam_h=30, *, seed=5, distortion=True):
    """A random linear functional of every output (``distortion=False``: of every output the
    distortion-free training path produces: colour, alpha, depth, median depth)."""
    rng = np.random.default_rng(seed)
    wc = jnp.asarray(rng.uniform(0, 1, (cam_h, cam_w, 3)))
    wa, wd, wm = (jnp.asarray(rng.uniform(0, 1, (cam_h, cam_w))) for _ in range(3))

    def loss(g, cam):
        out = renderer(g, cam)
        val = (jnp.sum(wc * out.color) + jnp.sum(wa * out.alpha) + 0.1 * jnp.sum(wd * out.depth)
               + 0.1 * jnp.sum(wm * out.median_depth))
        return val + jnp.sum(out.distortion) if distortion else val
    return loss


def _tiled(g, cam):
    # one static buffer for the eager (FD) and the traced (grad) calls: one compile, not two
    return S.render_splats(g, cam, tile_size=8, max_pairs=1024)


def test_tiled_matches_dense_gradients():
    g, cam = _scene(n=24), _cam()
    lt, ld = _loss_fn(_tiled), _loss_fn(S.render_splats_dense)
    gt = eqx.filter_grad(lambda gc: lt(*gc))((g, cam))
    gd = eqx.filter_grad(lambda gc: ld(*gc))((g, cam))
    worst, scale = 0.0, 0.0
    for name in ("means", "log_scales", "quats", "opacity_logits", "colors"):
        x, y = getattr(gt[0], name), getattr(gd[0], name)
        worst = max(worst, float(jnp.max(jnp.abs(x - y))))
        scale = max(scale, float(jnp.max(jnp.abs(y))))
        assert float(jnp.max(jnp.abs(y))) > 0, name
    for name in ("K", "R", "t"):
        x, y = getattr(gt[1], name), getattr(gd[1], name)
        worst = max(worst, float(jnp.max(jnp.abs(x - y))))
        assert float(jnp.max(jnp.abs(y))) > 0, name
    print(f"splat tiled vs dense gradients (every Gaussian field, K, R, t): max |diff| = {worst:.1e} "
          f"(largest component {scale:.1e})")
    assert worst < 1e-6


def _so3(w):
    th = jnp.sqrt(jnp.sum(w * w) + 1e-300)
    k = jnp.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
    return jnp.eye(3) + jnp.sin(th) / th * k + (1 - jnp.cos(th)) / th**2 * k @ k


def test_fd_gradients_every_parameter_and_pose():
    g, cam = _scene(n=16, seed=3), _cam()
    loss = _loss_fn(_tiled)
    rng = np.random.default_rng(1)
    grads = eqx.filter_grad(loss)(g, cam)
    eps = 1e-6
    figures = []
    for name in ("means", "log_scales", "quats", "opacity_logits", "colors"):
        d = jnp.asarray(rng.normal(size=getattr(g, name).shape))
        an = float(jnp.sum(getattr(grads, name) * d))
        gp = eqx_replace(g, name, getattr(g, name) + eps * d)
        gm = eqx_replace(g, name, getattr(g, name) - eps * d)
        fd = (float(loss(gp, cam)) - float(loss(gm, cam))) / (2 * eps)
        figures.append((name, an, fd))
    # pose: translation and a rotation increment applied on the right of R (camera frame)
    dt = jnp.asarray(rng.normal(size=3))

    def f_pose(s, w):
        c2 = Camera(cam.K, width=cam.width, height=cam.height, R=cam.R @ _so3(w), t=cam.t + s * dt)
        return loss(g, c2)

    w0 = jnp.asarray([1e-9, 0.0, 0.0])
    an_t = float(jax.grad(f_pose, 0)(0.0, w0))
    fd_t = (float(f_pose(eps, w0)) - float(f_pose(-eps, w0))) / (2 * eps)
    figures.append(("pose t", an_t, fd_t))
    dw = jnp.asarray(rng.normal(size=3))
    an_r = float(jnp.dot(jax.grad(f_pose, 1)(0.0, w0), dw))
    fd_r = (float(f_pose(0.0, w0 + eps * dw)) - float(f_pose(0.0, w0 - eps * dw))) / (2 * eps)
    figures.append(("pose R", an_r, fd_r))
    for name, an, fd in figures:
        rel = abs(an - fd) / max(abs(fd), 1e-12)
        print(f"splat FD check {name}: analytic {an:.6e} fd {fd:.6e} rel {rel:.1e}")
        assert abs(fd) > 1e-3, name  # non-zero guard
        assert rel < 1e-4, name


def eqx_replace(g, name, value):
    kw = {f: getattr(g, f) for f in ("means", "log_scales", "quats", "opacity_logits", "colors")}
    kw[name] = value
    return Gaussians(**kw, valid=g.valid)


def _brute_pairs(p, T=8, W=40, H=30):
    """(splat, tile) pairs from the projected support boxes, in emission order: splats by depth,
    tiles row-major within a splat."""
    uv, ext, vis, z = (np.asarray(a) for a in (p.uv, p.extent, p.visible, p.depth))
    pairs = []
    for i in np.argsort(np.where(vis, z, np.inf), kind="stable"):
        for ty in range(0, H, T):
            for tx in range(0, W, T):
                if (vis[i] and uv[i, 0] + ext[i, 0] >= tx and uv[i, 0] - ext[i, 0] <= tx + T - 1
                        and uv[i, 1] + ext[i, 1] >= ty and uv[i, 1] - ext[i, 1] <= ty + T - 1):
                    pairs.append((i, (ty // T) * (-(-W // T)) + tx // T))
    return pairs


def test_overflow_counted_and_surfaced():
    g, cam = _scene(n=60, seed=2), _cam()
    B = 120  # global pair buffer, far below the demand: the farthest splats' pairs are dropped
    a = S.render_splats(g, cam, tile_size=8, max_pairs=B)
    pairs = _brute_pairs(a.projected)
    tiles = np.array([t for _, t in pairs])
    demand = np.bincount(tiles, minlength=20)
    kept = np.bincount(tiles[:B], minlength=20)
    b = S.render_splats_dense(g, cam)
    diff = float(jnp.max(jnp.abs(a.color - b.color)))
    print(f"splat overflow with a {B}-pair buffer: demand {int(a.pairs)} pairs (brute force {len(pairs)}), "
          f"{int(a.overflow)} dropped in {int(a.overflow_tiles)} tiles (brute force "
          f"{int(np.sum(demand > kept))}); max |diff| vs dense {diff:.2f}")
    assert int(a.pairs) == len(pairs) > B
    assert int(a.overflow) == len(pairs) - B
    assert int(a.overflow_tiles) == int(np.sum(demand > kept)) > 0
    assert int(a.max_tile_count) == int(demand.max())
    assert diff > 1e-3  # the overflow changes the image, and the count says so
    # eager default: the buffer is sized from the measured demand, the render is exact (a
    # legacy per-tile `capacity` only sizes the buffer under tracing)
    big = S.render_splats(g, cam, tile_size=8, capacity=6)
    assert int(big.overflow) == 0 and int(big.pairs) == len(pairs)
    assert float(jnp.max(jnp.abs(big.color - b.color))) < 1e-12
    # under jit the buffer is static: the result reports the demand (count_splat_pairs gives
    # it eagerly), so a caller can re-run with a larger buffer (fsjax.fit.train_splats does)
    t = jax.jit(lambda g: S.render_splats(g, cam, tile_size=8, capacity=6))(g)  # B = 6 x 20 tiles = 120
    assert int(t.pairs) == S.count_splat_pairs(g, cam, tile_size=8) == len(pairs)
    assert int(t.overflow) == int(a.overflow) and float(jnp.max(jnp.abs(t.color - a.color))) < 1e-12


def _ground_splat(z_centre, scale_z):
    # one big splat, flattened in x and spread along the optical axis, under the camera
    return Gaussians(jnp.asarray([[0.0, 0.05, z_centre]]), jnp.log(jnp.asarray([[0.5, 0.02, scale_z]])),
                     jnp.asarray([[1.0, 0.0, 0.0, 0.0]]), jnp.asarray([4.0]), jnp.ones((1, 1, 3)))


def test_near_plane_culls_by_extent_not_centre():
    cam = Camera(C.intrinsics_from_fov(32, 24, fov_x_deg=60.0), width=32, height=24)
    near = 0.3
    straddle = _ground_splat(0.2, 0.5)  # centre behind the near plane, extent in front of it
    out = S.render_splats(straddle, cam, near=near)
    frac = float(jnp.mean(out.alpha > 0.5))
    print(f"splat straddling the near plane (centre z=0.2 < near=0.3, 3 sigma_z=1.5): "
          f"covered fraction {frac:.2f}; centre-only culling would give 0")
    assert bool(out.projected.visible[0]) and int(out.projected.n_culled_near) == 0
    assert frac > 0.2
    behind = _ground_splat(-1.0, 0.1)  # z + 3 sigma = -0.7 < near: culled
    out2 = S.render_splats(behind, cam, near=near)
    assert int(out2.projected.n_culled_near) == 1 and float(jnp.max(out2.alpha)) == 0.0
    d = S.render_splats_dense(straddle, cam, near=near)
    assert float(jnp.max(jnp.abs(d.alpha - out.alpha))) < 1e-12


def test_dilation_stated_value():
    g = Gaussians(jnp.asarray([[0.1, 0.0, 5.0]]), jnp.full((1, 3), -12.0), jnp.asarray([[1.0, 0.0, 0.0, 0.0]]),
                  jnp.asarray([0.0]), jnp.ones((1, 1, 3)))
    p = S.project_gaussians(g, _cam(), dilation_px2=0.3)
    assert np.allclose(np.asarray(p.cov2d[0]), [0.3, 0.0, 0.3], atol=1e-8)


def test_early_termination_and_median_depth():
    # five opaque splats (alpha 0.99) on the axis at depths 2..6: after two, T = 1e-4; the third
    # would take T to 1e-6 < t_min = 5e-5, so it and all behind it are skipped
    n = 5
    g = Gaussians(jnp.stack([jnp.zeros(n), jnp.zeros(n), 2.0 + jnp.arange(n)], -1), jnp.full((n, 3), -1.0),
                  jnp.tile(jnp.asarray([[1.0, 0.0, 0.0, 0.0]]), (n, 1)), jnp.full((n,), 30.0),
                  S.rgb_to_sh0(jnp.eye(3)[jnp.arange(n) % 3])[:, None, :])
    cam = Camera.from_intrinsics(30.0, 30.0, 7.0, 7.0, width=16, height=16)
    out = S.render_splats(g, cam, t_min=5e-5)
    centre = (7, 7)
    assert abs(float(out.alpha[centre]) - (1 - 0.01**2)) < 1e-12
    assert abs(float(out.median_depth[centre]) - 2.0) < 1e-12
    gr = jax.grad(lambda c: jnp.sum(S.render_splats(Gaussians(g.means, g.log_scales, g.quats,
                                                                g.opacity_logits, c), cam,
                                                      t_min=5e-5).color[centre]))(g.colors)
    assert float(jnp.max(jnp.abs(gr[2:]))) == 0.0 and float(jnp.max(jnp.abs(gr[:2]))) > 0
    # median depth: two splats of opacity 0.4 and 0.4 then 0.4: T = 0.6, 0.36 -> the second one
    g2 = Gaussians(g.means[:3], g.log_scales[:3], g.quats[:3], jnp.full((3,), float(jnp.log(0.4 / 0.6))),
                   g.colors[:3])
    o2 = S.render_splats(g2, cam)
    assert abs(float(o2.median_depth[centre]) - 3.0) < 1e-9


def test_distortion_equals_pairwise_sum_and_fd():
    g, cam = _scene(n=12, seed=4), _cam(24, 18)
    out = S.render_splats_dense(g, cam)
    # brute force: recompute the weights per pixel and sum over all pairs
    p = out.projected
    order = np.argsort(np.where(np.asarray(p.visible), np.asarray(p.depth), np.inf))
    r, c = 9, 11
    px = jnp.asarray([[float(c), float(r)]])
    al = np.asarray(S._alphas(px, p.uv[order], p.conic[order], p.opacity[order], 1 / 255, 0.99))[0]
    T = np.concatenate([[1.0], np.cumprod(1 - al)[:-1]])
    keep = np.cumprod(1 - al) >= 1e-4
    w = al * T * keep
    z = np.asarray(p.depth)[order]
    brute = float(np.sum(w[:, None] * w[None, :] * np.abs(z[:, None] - z[None, :])))
    assert brute > 1e-4
    assert abs(brute - float(out.distortion[r, c])) < 1e-12

    def L(means):
        return jnp.sum(S.render_splats(Gaussians(means, g.log_scales, g.quats, g.opacity_logits, g.colors),
                                       cam, tile_size=8, max_pairs=1024).distortion)
    d = jnp.asarray(np.random.default_rng(0).normal(size=g.means.shape))
    an = float(jnp.sum(jax.grad(L)(g.means) * d))
    eps = 1e-6
    fd = (float(L(g.means + eps * d)) - float(L(g.means - eps * d))) / (2 * eps)
    print(f"depth distortion: pairwise brute force {brute:.6e} = prefix-sum pass; grad analytic {an:.6e} "
          f"fd {fd:.6e}")
    assert abs(fd) > 1e-3 and abs(an - fd) < 1e-4 * abs(fd)


def test_distortion_off_same_images_and_gradients():
    # distortion=False skips the distortion prefix sums (training without that loss): every other
    # output and the colour gradient are the same numbers, the distortion is 0
    g, cam = _scene(n=12, seed=4), _cam(24, 18)
    a = S.render_splats(g, cam, tile_size=8, max_pairs=1024)
    b = S.render_splats(g, cam, tile_size=8, max_pairs=1024, distortion=False)
    worst = max(float(jnp.max(jnp.abs(getattr(a, f) - getattr(b, f)))) for f in FIELDS[:4])
    assert float(jnp.max(a.distortion)) > 1e-4 and float(jnp.max(jnp.abs(b.distortion))) == 0.0
    assert worst == 0.0

    def L(means, dist):
        return jnp.sum(S.render_splats(Gaussians(means, g.log_scales, g.quats, g.opacity_logits, g.colors),
                                       cam, tile_size=8, max_pairs=1024, distortion=dist).color)
    ga, gb = jax.grad(L)(g.means, True), jax.grad(L)(g.means, False)
    assert float(jnp.max(jnp.abs(ga))) > 1e-3 and float(jnp.max(jnp.abs(ga - gb))) < 1e-12


def test_degenerate_quaternion_under_jit_is_culled_and_counted():
    g = _scene(n=8)
    quats = g.quats.at[3].set(0.0)
    out = jax.jit(lambda q: S.render_splats(Gaussians(g.means, g.log_scales, q, g.opacity_logits, g.colors),
                                            _cam()))(quats)
    assert int(out.projected.n_degenerate) == 1 and not bool(out.projected.visible[3])
    assert bool(jnp.all(jnp.isfinite(out.color)))
    with pytest.raises(ValueError, match="zero-length"):
        Gaussians(g.means, g.log_scales, quats, g.opacity_logits, g.colors)


def test_bad_input():
    g = _scene(n=4)
    cam = _cam()
    with pytest.raises(ValueError, match="render_splats.*distortion"):
        S.render_splats(g, Camera(cam.K, width=40, height=30, dist=jnp.asarray([0.1, 0, 0, 0, 0])))
    with pytest.raises(ValueError, match="render_splats: argument 'capacity' must be >= 1"):
        S.render_splats(g, cam, capacity=0)
    with pytest.raises(ValueError, match="render_splats: argument 'max_pairs' must be >= 1"):
        S.render_splats(g, cam, max_pairs=-3)
    with pytest.raises(ValueError, match="render_splats: argument 'chunk' must be >= 1"):
        S.render_splats(g, cam, chunk=0)
    with pytest.raises(TypeError, match="render_splats: argument 'tile_size' must be an integer"):
        S.render_splats(g, cam, tile_size=8.5)
    with pytest.raises(ValueError, match="alpha_min"):
        S.render_splats(g, cam, alpha_min=0.0)
    with pytest.raises(TypeError, match="render_splats\\(gaussians"):
        S.render_splats(g.means, cam)
    with pytest.raises(ValueError, match="sh_to_rgb"):
        S.sh_to_rgb(jnp.ones((2, 3, 3)), jnp.ones((2, 3)))


def test_float32_runs_and_agrees():
    g = _scene(n=20)
    g32 = jax.tree_util.tree_map(lambda a: a.astype(jnp.float32) if a.dtype == jnp.float64 else a, g)
    cam = _cam()
    cam32 = Camera(cam.K.astype(jnp.float32), width=40, height=30, R=cam.R.astype(jnp.float32),
                   t=cam.t.astype(jnp.float32))
    a = S.render_splats(g32, cam32, tile_size=8, capacity=64)
    b = S.render_splats(g, cam, tile_size=8, capacity=64)
    assert a.color.dtype == jnp.float32
    d = float(jnp.max(jnp.abs(a.color - b.color)))
    print(f"splat float32 vs float64 colour: max |diff| = {d:.1e}")
    assert d < 1e-3


def test_default_is_exact_when_a_tile_holds_more_than_the_old_capacity():
    # issue 20: the old default (256 splats per tile) dropped pairs silently into r.overflow; an
    # eager call now sizes its pair buffer from the demand. 300 splats over one 16 x 16 tile.
    rng = np.random.default_rng(7)
    n = 300
    g = Gaussians(np.c_[rng.uniform(-0.3, 0.3, (n, 2)), rng.uniform(3.0, 6.0, n)], np.log(rng.uniform(0.05, 0.3, (n, 3))),
                  rng.normal(size=(n, 4)), rng.normal(-3.0, 0.5, n), rng.normal(0.0, 0.5, (n, 1, 3)))
    cam = Camera.from_intrinsics(20.0, 20.0, 7.5, 7.5, width=16, height=16)
    a = S.render_splats(g, cam)
    b = S.render_splats_dense(g, cam)
    d = max(float(jnp.max(jnp.abs(getattr(a, f) - getattr(b, f)))) for f in FIELDS)
    print(f"one tile, {int(a.max_tile_count)} splats on it: overflow {int(a.overflow)}, max |diff| vs dense {d:.1e}")
    assert int(a.max_tile_count) > 256 and int(a.overflow) == 0 and d < 1e-12


def _plain_loss(renderer):
    return _loss_fn(renderer, seed=7, distortion=False)


def _plain_tiled(g, cam):
    # distortion=False is the training path (the other gradient tests use distortion=True); chunk=4
    # makes several chunks per tile, so the state handed from chunk to chunk (and its cotangent) is
    # exercised
    return S.render_splats(g, cam, tile_size=8, max_pairs=2048, chunk=4, distortion=False)


def _opaque_scene():
    # a dense stack of nearly opaque splats: many pixels terminate early (T < t_min) inside a chunk
    g = _scene(n=40, seed=11, spread=0.25)
    return Gaussians(g.means, g.log_scales + 0.7, g.quats, jnp.abs(g.opacity_logits) + 3.0, g.colors)


@pytest.mark.parametrize("scene", ["mixed", "opaque"])
def test_distortion_off_gradients_match_dense(scene):
    g, cam = (_scene(n=24), _cam()) if scene == "mixed" else (_opaque_scene(), _cam())
    out = _plain_tiled(g, cam)
    assert int(out.overflow) == 0
    if scene == "opaque":  # termination really happens, and more than one chunk per tile is used
        assert float(jnp.max(out.alpha)) > 1 - 2e-4 and int(out.max_tile_count) > 8
    lt, ld = _plain_loss(_plain_tiled), _plain_loss(S.render_splats_dense)
    gt = eqx.filter_grad(lambda gc: lt(*gc))((g, cam))
    gd = eqx.filter_grad(lambda gc: ld(*gc))((g, cam))
    worst = 0.0
    pairs = [(gt[0], gd[0], n) for n in ("means", "log_scales", "quats", "opacity_logits", "colors")]
    pairs += [(gt[1], gd[1], n) for n in ("K", "R", "t")]
    for a, b, name in pairs:
        x, y = getattr(a, name), getattr(b, name)
        scale = float(jnp.max(jnp.abs(y)))
        assert scale > 0, name
        worst = max(worst, float(jnp.max(jnp.abs(x - y))) / scale)
    print(f"splat distortion-off, chunk 4 ({scene}) vs dense gradients: max relative |diff| = {worst:.1e}")
    assert worst < 1e-12


def test_distortion_off_fd_gradients():
    g, cam = _opaque_scene(), _cam()
    loss = _plain_loss(_plain_tiled)
    grads = eqx.filter_grad(loss)(g, cam)
    rng = np.random.default_rng(2)
    eps = 1e-6
    for name in ("means", "log_scales", "quats", "opacity_logits", "colors"):
        d = jnp.asarray(rng.normal(size=getattr(g, name).shape))
        an = float(jnp.sum(getattr(grads, name) * d))
        fd = (float(loss(eqx_replace(g, name, getattr(g, name) + eps * d), cam))
              - float(loss(eqx_replace(g, name, getattr(g, name) - eps * d), cam))) / (2 * eps)
        print(f"splat distortion-off FD check {name}: analytic {an:.6e} fd {fd:.6e}")
        assert abs(fd) > 1e-3, name
        assert abs(an - fd) < 1e-4 * abs(fd), name


def test_distortion_off_float32_gradients():
    g, cam = _scene(n=24), _cam()
    f32 = lambda t: jax.tree_util.tree_map(  # noqa: E731
        lambda a: a.astype(jnp.float32) if hasattr(a, "dtype") and a.dtype == jnp.float64 else a, t)
    g32 = f32(g)
    cam32 = Camera(cam.K.astype(jnp.float32), width=40, height=30, R=cam.R.astype(jnp.float32),
                   t=cam.t.astype(jnp.float32))
    loss = _plain_loss(_plain_tiled)
    a = eqx.filter_grad(loss)(g32, cam32)
    b = eqx.filter_grad(_plain_loss(S.render_splats_dense))(g, cam)
    for name in ("means", "log_scales", "opacity_logits", "colors"):
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == jnp.float32
        rel = float(jnp.max(jnp.abs(x - y))) / float(jnp.max(jnp.abs(y)))
        print(f"splat distortion-off float32 vs float64 dense gradient ({name}): max relative |diff| = {rel:.1e}")
        assert rel < 1e-3, name
