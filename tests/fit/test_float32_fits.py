"""The fits in float32, the user's default dtype (issue 20).

Two ways a float32 user meets a fit: float32 data while x64 happens to be on (a library or
notebook enabled it), and JAX's default, x64 off. In the first, optimistix's stock
Levenberg-Marquardt started its trust-region step size in float64, so its damping rows were
float64 beside float32 residuals and lineax refused the solve with a raw
``ValueError: Vector and operator structures do not match`` (PnP, two-view, the 3-D primitive
fits, RANSAC sphere/cylinder refits; fit_circle/fit_ellipse were fixed earlier). Every LM fit
now builds its solver with ``fsjax._linalg.levenberg_marquardt``, which keeps the parameters'
dtype. Each case (one per LM call site) runs a scene with known truth in float32 and asserts a
converged float32 answer within the error bound the float64 tests use.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from fsjax.fit import fit_sphere, ransac
from fsjax.fit.calibrate import calibrate_camera
from fsjax.fit.pnp import solve_pnp
from fsjax.fit.twoview import relative_pose

import test_calibrate as tc  # noqa: E402  (sibling test module: its scene builders)
import test_pnp as tp  # noqa: E402  (sibling test module: its scene builders)
import test_twoview as tt  # noqa: E402  (sibling test module: its scene builders)

f32 = lambda a: jnp.asarray(a, jnp.float32)  # noqa: E731


def _pnp():
    X, uv, R, t, _ = tp._scene(4, noise=0.3, outliers=0.0)
    r = solve_pnp(f32(X), f32(uv), f32(tp.K))
    return r, r.R, max(tp._rot_err_deg(r.R, R) / 0.1, np.linalg.norm(np.asarray(r.t) - t) / 0.05)


def _twoview():
    uv1, uv2, R, t, _, _ = tt._scene(0)
    r = relative_pose(jax.random.PRNGKey(0), f32(uv1), f32(uv2), f32(tt.K), threshold_px=1.0)
    et = np.degrees(np.arccos(np.clip(np.dot(np.asarray(r.t, float), t / np.linalg.norm(t)), -1, 1)))
    return r, r.R, max(tt._rot_err_deg(r.R, R) / 0.5, et / 1.0)


def _sphere_pts(rng, n, c=(1.0, 2.0, 3.0), rad=0.7):
    u = rng.normal(size=(3 * n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    return np.asarray(c) + rad * u[u[:, 2] > -0.2][:n] + 0.002 * rng.normal(size=(n, 3))


def _fit_sphere():
    r = fit_sphere(f32(_sphere_pts(np.random.default_rng(1), 150)))
    return r, r.params, max(np.linalg.norm(np.asarray(r.params[:3]) - [1, 2, 3]), abs(float(r["r"]) - 0.7)) / 2e-3


def _ransac_sphere():
    rng = np.random.default_rng(2)
    x = np.r_[_sphere_pts(rng, 200), rng.uniform(0, 4, (60, 3))]
    r = ransac(jax.random.PRNGKey(0), f32(x), "sphere", threshold=0.01)
    return r, r.params, max(np.linalg.norm(np.asarray(r.params[:3]) - [1, 2, 3]), abs(float(r["r"]) - 0.7)) / 3e-3


def _ransac_cylinder():
    rng = np.random.default_rng(3)
    th, z = rng.uniform(0, np.pi, 300), rng.uniform(-1, 1, 300)
    cyl = np.c_[0.4 * np.cos(th), 0.4 * np.sin(th), z] + [0.5, 0.0, 0.0] + 0.002 * rng.normal(size=(300, 3))
    x = np.r_[cyl, rng.uniform(-1, 1, (80, 3))]
    r = ransac(jax.random.PRNGKey(0), f32(x), "cylinder", threshold=0.01)
    axis = abs(float(np.asarray(r.params[3:6]) @ [0, 0, 1.0]) / float(np.linalg.norm(np.asarray(r.params[3:6]))))
    return r, r.params, max(np.degrees(np.arccos(min(1.0, axis))) / 0.5, abs(float(r["r"]) - 0.4) / 3e-3)


# one case per Levenberg-Marquardt call site: pnp._refine, twoview (Sampson refinement),
# primitives3d._lm (fit_sphere, fit_cylinder, fit_circle3d), ransac3d sphere and cylinder refits
CASES = {
    "solve_pnp": _pnp,
    "relative_pose": _twoview,
    "fit_sphere": _fit_sphere,
    "ransac_sphere": _ransac_sphere,
    "ransac_cylinder": _ransac_cylinder,
}


@pytest.mark.parametrize("name", list(CASES))
def test_float32_data_with_x64_on(name):
    """Float32 data with x64 on: a converged float32 fit within the float64 tests' error bounds
    against the truth (before: lineax's raw ValueError)."""
    r, leaf, score = CASES[name]()
    print(f"{name}: float32 data with x64 on: converged {bool(r.converged)}, error {score:.2f} of the bound")
    assert bool(r.converged) and leaf.dtype == jnp.float32
    assert score < 1.0


def test_calibration_float32_default_dtype():
    """The synthetic calibration scene (14 views x 54 corners, 0.2 px) with x64 off, float32 throughout:
    the intrinsics as accurate as in float64 (0.1 %) and the same RMS."""
    truth = np.array([520.0, 515.0, 318.0, 262.0, -0.25, 0.12, 0.001, -0.0015, -0.03])
    P, uv = tc._synthetic_views(truth, 14, 0.2, seed=1)
    with jax.enable_x64(False):
        cal = calibrate_camera(f32(P), f32(uv), (640, 512))
        est = np.array([float(v) for v in cal.params.values()])
        dt = jnp.asarray(cal.rms_px).dtype
        rms, conv = float(cal.rms_px), bool(cal.converged)
    rel = np.abs(est - truth) / np.abs(truth)
    print(f"calibration in float32 (x64 off): RMS {rms:.4f} px, intrinsics rel. error max {100 * rel[:4].max():.3f} %, "
          f"k1 {100 * rel[4]:.3f} %")
    assert dt == jnp.float32 and conv
    assert rel[:4].max() < 1e-3 and rel[4] < 0.01 and rms < 0.3
