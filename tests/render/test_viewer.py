"""The HTML/WebGL viewer in headless Chromium: a low camera over an exported ground plane.

Chromium (Debian package ``chromium``) renders with SwiftShader (no GPU); the test skips only
where no Chromium binary exists (CI installs it).
"""

import shutil
import subprocess

import numpy as np
import pytest

import fsjax
from fsjax.io import splat_bytes
from fsjax.render import intrinsics_from_fov, look_at
from fsjax.render.viewer import viewer_page

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser") or shutil.which("google-chrome")
W, H = 256, 192


def ground_plane(spacing=0.1, half=1.5, far=4.0):
    """Flat splats on the plane y = 0 (world up is -y), checkerboard colours, from z=-0.5 to far."""
    xs = np.arange(-half, half + 1e-9, spacing)
    zs = np.arange(-0.5, far, spacing)
    X, Z = np.meshgrid(xs, zs)
    n = X.size
    means = np.stack([X.ravel(), np.zeros(n), Z.ravel()], 1)
    chk = ((np.floor(X.ravel() / 0.3) + np.floor(Z.ravel() / 0.3)) % 2)[:, None]
    rgb = chk * np.array([[0.85, 0.7, 0.45]]) + (1 - chk) * np.array([[0.35, 0.6, 0.4]])
    return fsjax.Gaussians(means, np.log(np.tile([[spacing * 0.8, 0.004, spacing * 0.8]], (n, 1))),
                           np.tile([[1.0, 0.0, 0.0, 0.0]], (n, 1)), np.full(n, 3.0),
                           fsjax.render.rgb_to_sh0(rgb)[:, None, :])


def low_camera(altitude=0.12):
    R, t = look_at([0.0, -altitude, 0.0], [0.0, 0.0, 1.5], up=[0.0, -1.0, 0.0])
    return fsjax.Camera(intrinsics_from_fov(W, H, fov_x_deg=70.0), width=W, height=H, R=R, t=t)


def _shoot(tmp_path, html, query, name):
    page = tmp_path / f"{name}.html"
    page.write_text(html)
    png = tmp_path / f"{name}.png"
    cmd = [CHROMIUM, "--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--use-angle=swiftshader",
           "--enable-unsafe-swiftshader", "--use-gl=angle", "--hide-scrollbars", "--no-first-run",
           f"--window-size={W},{H}", "--virtual-time-budget=10000", f"--screenshot={png}",
           f"file://{page}?{query}"]
    subprocess.run(cmd, check=True, capture_output=True, timeout=180)
    from PIL import Image

    return np.asarray(Image.open(png).convert("RGB"), dtype=np.float64) / 255.0


@pytest.mark.skipif(CHROMIUM is None, reason="no Chromium binary (CI installs Debian's chromium)")
@pytest.mark.slow  # heavy (20-60 s); slow suites run last
def test_viewer_ground_plane_low_near_plane(tmp_path):
    g, cam = ground_plane(), low_camera()
    near = 0.3  # the near plane reaches below the camera's altitude (0.12) into the ground
    html = viewer_page(splat_bytes(g), cam, near=near)
    color = _shoot(tmp_path, html, "mode=color", "color")
    alpha = _shoot(tmp_path, html, "mode=alpha", "alpha")[..., 0]
    alpha_centre = _shoot(tmp_path, html, "mode=alpha&cull=centre", "centre")[..., 0]
    assert color.shape == (H, W, 3)
    lit = float(np.mean(color.max(-1) > 0.1))
    bottom = slice(2 * H // 3, H)
    holes = float(np.mean(alpha[bottom] < 0.5))
    holes_centre = float(np.mean(alpha_centre[bottom] < 0.5))
    # the same scene through the JAX rasteriser (same near-plane rule)
    out = fsjax.render.render_splats(g, cam, near=near, capacity=1024)
    holes_jax = float(np.mean(np.asarray(out.alpha)[bottom] < 0.5))
    print(f"viewer (headless Chromium, SwiftShader): lit fraction {lit:.2f}; bottom-third hole fraction "
          f"{holes:.3f} with extent culling (JAX rasteriser {holes_jax:.3f}), {holes_centre:.3f} with "
          f"centre-only culling (the defect)")
    assert lit > 0.3  # the frame is not empty
    assert holes < 0.05
    assert holes_jax < 0.05
    assert holes_centre > holes  # the null: centre-only culling leaves holes the extent rule fills


def test_viewer_page_embeds_and_refuses_bad_input():
    g, cam = ground_plane(spacing=0.5), low_camera()
    html = viewer_page(splat_bytes(g), cam)
    assert "FSJAX_SPLAT_B64" in html and "renderSplats" in html and "/*FSJAX_VIEWER_JS*/" not in html
    with pytest.raises(ValueError, match="multiple of 32"):
        viewer_page(b"\0" * 31, cam)
    with pytest.raises(ValueError, match="near"):
        viewer_page(splat_bytes(g), cam, near=0.0)
