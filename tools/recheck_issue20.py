"""Re-check issue 20's six items as a new user meets them: float32, x64 off (JAX's default).

Run: python tools/recheck_issue20.py (prints one line per item; see docs/fail_closed.md)."""
import time

import jax
import jax.numpy as jnp
import numpy as np

import fsjax
from fsjax.data.chessboard import chessboard_images
from fsjax.fit import icp
from fsjax.fit.chessboard import find_chessboard

assert not jax.config.jax_enable_x64, "run with JAX's default float32 (x64 off)"

out = {}
P = jnp.asarray(fsjax.data.mesh_arrays("bunny")[0][::36], jnp.float32)
for m in ("point_to_plane", "gicp", "point_to_point"):
    r = icp(P, P, method=m)
    out[f"1 icp({m}) self, float32, metres"] = (int(r.reason), bool(r.converged))
img = chessboard_images(as_float=False)[0]
out["2 chessboard wrong sizes found"] = [bool(find_chessboard(img, p).converged) for p in [(7, 7), (5, 4), (8, 5), (10, 7)]]
x = fsjax.Image(jnp.asarray(np.random.default_rng(0).random((32, 32)), jnp.float32))
y = jax.jit(lambda a: fsjax.apply(x, "gaussian", a=a).data)(1.5)
out["3 traced knob a=1.5 -> all NaN"] = bool(jnp.all(jnp.isnan(y)))
y = jax.jit(lambda s: fsjax.ops.gaussian(x, sigma=s).data)(20.0)
out["3 traced sigma=20 > max_sigma -> all NaN"] = bool(jnp.all(jnp.isnan(y)))
v, f = fsjax.data.mesh_arrays("bunny")
mesh = fsjax.Mesh(jnp.asarray(v, jnp.float32), jnp.asarray(f))
c = v.mean(0)
R, t = fsjax.render.look_at(jnp.asarray(c + np.array([0, 0.05, 0.35]), jnp.float32), jnp.asarray(c, jnp.float32))
cam = fsjax.Camera.from_intrinsics(500.0, 500.0, 319.5, 239.5, width=640, height=480, R=R, t=t)
r = fsjax.render.rasterize(mesh, cam)
out["4 rasterize default capacity, bunny 640x480: overflow, incomplete px"] = (int(r.overflow), int(jnp.sum(r.incomplete)))
t0 = time.perf_counter()
try:
    g = fsjax.ops.gaussian(fsjax.Image(jnp.ones((128, 128))), sigma=1e6)
    out["5 gaussian sigma=1e6"] = f"{time.perf_counter() - t0:.2f} s, max |1 - y| {float(jnp.max(jnp.abs(g.data - 1))):.2e}"
except ValueError as e:
    out["5 gaussian sigma=1e6"] = f"refused in {time.perf_counter() - t0:.2f} s: {e}"
for name, fn in [("6 0x0 Image", lambda: fsjax.Image(jnp.zeros((0, 0)))),
                 ("6 sigma='2'", lambda: fsjax.ops.gaussian(x, sigma="2"))]:
    try:
        fn()
        out[name] = "accepted"
    except (TypeError, ValueError) as e:
        out[name] = f"{type(e).__name__}: {str(e)[:70]}"
out["6 np.asarray(img).shape"] = np.asarray(x).shape
out["6 fsjax.io.read_image"] = callable(fsjax.io.read_image)
# the sweep's detectors: a model the data do not support is refused with a reason
rng = np.random.default_rng(0)
t = rng.uniform(0, 40, 60)
for name, pts in [("scatter", rng.uniform(0, 30, (60, 2))),
                  ("line", np.stack([5 + 0.5 * t, 3 + t], -1) + 0.3 * rng.standard_normal((60, 2)))]:
    c = fsjax.Contour(jnp.asarray(pts, jnp.float32))
    out[f"sweep fit_circle / fit_ellipse on a {name}: reason"] = [fsjax.ops.fit_circle(c).message[:19],
                                                                fsjax.ops.fit_ellipse(c).message[:19]]
blobs = np.concatenate([rng.normal(0, 0.03, (200, 3)), rng.normal(0.8, 0.03, (200, 3))])
out["sweep ransac plane through two blobs: reason"] = int(
    fsjax.fit.ransac(jax.random.PRNGKey(0), jnp.asarray(blobs, jnp.float32), "plane", threshold=0.01).reason)
for k, val in out.items():
    print(f"{k}: {val}")
