"""`fsjax splat SFM_DIR`: splats trained on the photographs of a COLMAP-format SfM result.

The SfM result is synthetic with known cameras: a textured wall and a block in front of it, made of
opaque splats, photographed by 8 cameras on a line (64 x 48 px); the "sparse points" are 250 of the
scene's splat centres (jittered) with their colours; the model is written by fsjax's own COLMAP
exporter (`write_colmap_text`) and the photographs as PNGs in SFM_DIR/images. The command must hold
out every 4th view, beat the null (the sparse points rendered as splats before training) on those
views in PSNR and SSIM, report no evaluation overflow and write the exports."""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from fsjax.cli import main
from fsjax.io.splat import read_splat
from fsjax.render.splat import render_splats, rgb_to_sh0
from fsjax.sfm.export import write_colmap_text
from fsjax.sfm.reconstruct import Reconstruction
from fsjax.sfm.splat import init_from_points, load_sfm_views
from fsjax.types import Camera, Gaussians

W, H, F = 64, 48, 56.0


def _scene(rng):
    u, v = np.meshgrid(np.linspace(-2.2, 2.2, 44), np.linspace(-1.6, 1.6, 32))
    wall = np.stack([u.ravel(), v.ravel(), np.full(u.size, 5.0)], 1)
    a, b = np.meshgrid(np.linspace(-0.6, 0.6, 12), np.linspace(-0.5, 0.5, 10))
    block = np.stack([a.ravel() + 0.4, b.ravel() + 0.2, np.full(a.size, 3.5)], 1)
    X = np.concatenate([wall, block])
    col = np.concatenate([
        0.5 + 0.4 * np.stack([np.sin(3 * wall[:, 0]), np.cos(2 * wall[:, 1]), np.sign(np.sin(5 * wall[:, 0] + 4 * wall[:, 1]))], 1),
        np.tile([[0.9, 0.2, 0.1]], (len(block), 1)) * (0.7 + 0.3 * np.sign(np.sin(9 * block[:, :1])))])
    col = np.clip(col, 0, 1)
    n = len(X)
    g = Gaussians(jnp.asarray(X), jnp.full((n, 3), np.log(0.07)), jnp.tile(jnp.asarray([1.0, 0, 0, 0]), (n, 1)),
                  jnp.full((n,), 4.0), jnp.asarray(rgb_to_sh0(jnp.asarray(col)))[:, None, :])
    return g, X, col


def _write_sfm_dir(root):
    from PIL import Image

    rng = np.random.default_rng(0)
    g, X, col = _scene(rng)
    K = np.array([[F, 0, (W - 1) / 2], [0, F, (H - 1) / 2], [0, 0, 1.0]])
    n = 8
    Rc, tc, names = [], [], []
    (root / "images").mkdir(parents=True)
    for i in range(n):
        C = np.array([-1.2 + 2.4 * i / (n - 1), 0.15 * np.sin(i), 0.0])
        yaw = -0.12 * C[0]  # turn slightly towards the middle
        Rw = np.array([[np.cos(yaw), 0, np.sin(yaw)], [0, 1, 0], [-np.sin(yaw), 0, np.cos(yaw)]])  # world_from_camera
        cam = Camera(jnp.asarray(K), width=W, height=H, R=jnp.asarray(Rw), t=jnp.asarray(C))
        img = np.clip(np.asarray(render_splats(g, cam, distortion=False).color), 0, 1)
        name = f"{i:04d}.png"
        Image.fromarray((img * 255 + 0.5).astype(np.uint8)).save(root / "images" / name)
        Rc.append(Rw.T)
        tc.append(-Rw.T @ C)
        names.append(name)
    # sparse points: a subset of the scene's centres, jittered, with their colours and their projections
    pick = rng.choice(len(X), 250, replace=False)
    P = X[pick] + rng.normal(scale=0.02, size=(250, 3))
    kps = [[] for _ in range(n)]
    obs = []
    for p in P:
        o = []
        for i in range(n):
            x = Rc[i] @ p + tc[i]
            uv = K[:2, :2] @ (x[:2] / x[2]) + K[:2, 2]
            if 0 <= uv[0] < W and 0 <= uv[1] < H:
                o.append((i, len(kps[i])))
                kps[i].append(uv)
        obs.append(o)
    rec = Reconstruction(names=names, K=K, size=(W, H), registered=np.ones(n, bool), R=np.array(Rc), t=np.array(tc),
                         keypoints=[np.array(k).reshape(-1, 2) for k in kps], points=P,
                         colors=(col[pick] * 255 + 0.5).astype(np.uint8), point_obs=obs, reasons={}, view_graph=[])
    write_colmap_text(rec, root / "sparse")
    return names


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    root = tmp_path_factory.mktemp("sfmsplat")
    names = _write_sfm_dir(root / "sfm")
    out = root / "out"
    code = main(["splat", str(root / "sfm"), "--out", str(out), "--width", str(W), "--steps", "150",
                 "--max-splats", "1024"])
    return root, names, out, code


def test_splat_from_sfm_beats_the_null_on_held_out_views(run):
    root, names, out, code = run
    m = json.loads((out / "metrics.json").read_text())
    assert m["held_out"] == [names[3], names[7]]  # every 4th image
    assert m["size"] == [W, H] and m["steps"] == 150
    for k in ("null", "null_opaque", "trained", "trained_train_views"):
        assert m[k]["overflow"] == 0 and all(b >= p for b, p in zip(m[k]["buffer"], m[k]["pairs"]))
    tr, null, op = m["trained"], m["null"], m["null_opaque"]
    assert tr["psnr"] > null["psnr"] + 3.0 and tr["psnr"] > op["psnr"] + 1.0, (tr["psnr"], null["psnr"], op["psnr"])
    assert tr["ssim"] > null["ssim"] and tr["ssim"] > op["ssim"]
    assert m["beats_null"] and code == 0
    assert 250 <= m["n_splats"] <= 1024
    # exports: the .splat holds the trained splats, the viewer embeds them, the report states the figures
    assert len(read_splat(out / "splats.splat").means) == m["n_splats"]
    assert (out / "splats.ply").stat().st_size > 62 * m["n_splats"]
    assert "FSJAX_SPLAT_B64" in (out / "viewer.html").read_text()
    rep = (out / "report.md").read_text()
    assert f"{tr['psnr']:.2f}" in rep and f"{null['psnr']:.2f}" in rep and "beat both nulls (PSNR and SSIM): **yes**" in rep


def test_load_sfm_views_cameras_and_init(run, tmp_path):
    root, names, out, _ = run
    v = load_sfm_views(root / "sfm", width=32)  # half size: K scaled about pixel centres
    d = v.data
    assert (d.cameras.width, d.cameras.height) == (32, 24) and d.images.shape == (8, 24, 32, 3)
    K = np.asarray(d.cameras.K[0])
    np.testing.assert_allclose(K[:2, :2], np.diag([F / 2, F / 2]), rtol=1e-12)
    np.testing.assert_allclose(K[:2, 2], [(((W - 1) / 2) + 0.5) / 2 - 0.5, (((H - 1) / 2) + 0.5) / 2 - 0.5], atol=1e-9)
    np.testing.assert_allclose(np.asarray(d.cameras.t[0]), [-1.2, 0.0, 0.0], atol=1e-9)  # world_from_camera: centre
    assert list(d.test) == [3, 7] and list(d.train) == [0, 1, 2, 4, 5, 6]
    xyz, rgb = d.points
    g = init_from_points(xyz, rgb, 300)
    assert int(np.sum(np.asarray(g.valid))) == 250 and g.means.dtype == jnp.float32
    assert np.all(np.isfinite(np.asarray(g.log_scales))) and float(np.ptp(np.asarray(g.log_scales)[:250, 0])) > 0
    with pytest.raises(ValueError, match="max_splats"):
        init_from_points(xyz, rgb, 100)
    # the layout of `fsjax sfm VIDEO`: the chosen frames in SFM_DIR/frames
    import shutil

    shutil.copytree(root / "sfm" / "sparse", tmp_path / "vid" / "sparse")
    shutil.copytree(root / "sfm" / "images", tmp_path / "vid" / "frames")
    vv = load_sfm_views(tmp_path / "vid", width=32)
    assert vv.image_dir == tmp_path / "vid" / "frames" and np.array_equal(np.asarray(vv.data.images), np.asarray(d.images))
    with pytest.raises(FileNotFoundError, match="--images"):
        load_sfm_views(root / "sfm" / "sparse")  # a bare model folder: no photographs found
    with pytest.raises(FileNotFoundError, match="COLMAP"):
        load_sfm_views(tmp_path)


def test_train_splats_refuses_a_bad_init():
    from fsjax.fit import train_splats

    class _Data:  # only the camera width is read before the init is checked
        class cameras:
            width = 8

    g = init_from_points(np.zeros((2, 3)) + [[0, 0, 1], [0, 1, 1]], np.full((2, 3), 0.5), 4)
    batched = Gaussians(*(jnp.stack([a, a]) for a in (g.means, g.log_scales, g.quats, g.opacity_logits, g.colors)))
    with pytest.raises(ValueError, match="train_splats: argument 'init'"):
        train_splats(jax.random.PRNGKey(0), _Data, init=batched, iterations=1)
