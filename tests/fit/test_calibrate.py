"""Camera calibration: real chessboards vs cv2.calibrateCamera, synthetic truth, failure cases."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

from fsjax.fit.calibrate import calibrate_camera, homography_dlt, project_board, rodrigues
from fsjax.fit.chessboard import board_points
from fsjax.render.camera import distort_normalized
from fsjax.tour.calibration import measure_real_chessboard


def test_real_chessboard_vs_opencv():
    r = measure_real_chessboard()
    cal, cv, on_cv = r["cal"], r["cv"], r["cal_on_cv"]
    K = cv["K"]
    ref = {"fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2]}
    p = cal.params
    rel = {k: abs(p[k] - ref[k]) / ref[k] for k in ref}
    print(f"real chessboard, fsjax corners + fsjax LM: RMS {float(cal.rms_px):.4f} px vs cv2.calibrateCamera "
          f"(cv2 corners) {cv['rms']:.4f} px ({100 * (float(cal.rms_px) / cv['rms'] - 1):+.1f} %); " + ", ".join(
              f"{k} {p[k]:.2f} vs {ref[k]:.2f} ({100 * rel[k]:.3f} %)" for k in ref))
    print("  std (J^T J)^-1 sigma^2: " + ", ".join(f"{n} {s:.3g}" for n, s in zip(p, np.asarray(cal.std)))
          + f"; converged {bool(cal.converged)} in {int(cal.iterations)} LM steps; Zhang init fx "
            f"{float(cal.init_K[0, 0]):.1f}")
    print(f"  per-view RMS {np.round(np.asarray(cal.per_view_rms_px), 3).tolist()}")
    assert bool(cal.converged)
    assert float(cal.rms_px) <= 1.05 * cv["rms"]  # within 5 % of OpenCV's or better
    assert max(rel.values()) < 0.01
    # the same corners in both solvers: the fit itself matches OpenCV's to rounding
    po = on_cv.params
    d_rms = abs(float(on_cv.rms_px) - cv["rms"]) / cv["rms"]
    d_k = max(abs(po[k] - ref[k]) / ref[k] for k in ref)
    d_dist = np.abs(np.asarray(on_cv.dist) - cv["dist"]).max()
    print(f"  fsjax LM on cv2's corners: RMS rel diff {d_rms:.1e}, fx/fy/cx/cy max rel diff {d_k:.1e}, "
          f"distortion max |diff| {d_dist:.1e}")
    assert d_rms < 1e-4 and d_k < 1e-4 and d_dist < 1e-3
    # the null: integer-pixel corners
    print(f"  null (integer-pixel corners): RMS {float(r['cal_null'].rms_px):.4f} px")
    assert float(cal.rms_px) < 0.5 * float(r["cal_null"].rms_px)


def _synthetic_views(truth, n_views, noise, seed, size=(640, 512)):
    P = board_points((9, 6))
    rng = np.random.default_rng(seed)
    out = []
    while len(out) < n_views:
        ax = rng.normal(size=3)
        ax[2] *= 0.3
        ax /= np.linalg.norm(ax)
        rv = ax * np.deg2rad(rng.uniform(25, 50))
        R = np.asarray(rodrigues(jnp.asarray(rv)))
        z = rng.uniform(6, 9)
        off = rng.uniform([-3, -2], [3, 2]) * z / 8
        t = np.array([off[0], off[1], z]) - R @ np.array([4.0, 2.5, 0.0])
        uv = np.asarray(project_board(jnp.asarray(truth), jnp.asarray(rv), jnp.asarray(t), P))
        if np.all(np.isfinite(uv)) and uv.min() > 5 and uv[:, 0].max() < size[0] - 5 and uv[:, 1].max() < size[1] - 5:
            out.append(uv + rng.normal(0, noise, uv.shape))
    return P, np.stack(out)


def test_synthetic_known_truth():
    truth = np.array([520.0, 515.0, 318.0, 262.0, -0.25, 0.12, 0.001, -0.0015, -0.03])
    P, uv = _synthetic_views(truth, 14, 0.2, seed=1)
    cal = calibrate_camera(P, uv, (640, 512))
    est = np.array(list(cal.params.values()))
    rel = np.abs(est - truth) / np.abs(truth)
    sd = np.asarray(cal.std) / np.abs(truth)
    g = np.stack(np.meshgrid(np.linspace(0, 639, 33), np.linspace(0, 511, 27)), -1).reshape(-1, 2)
    xy = (g - truth[2:4]) / truth[:2]
    d_t = np.asarray(distort_normalized(jnp.asarray(truth[4:]), jnp.asarray(xy))) - xy
    d_e = np.asarray(distort_normalized(jnp.asarray(est[4:]), jnp.asarray(xy))) - xy
    field = np.abs(d_e - d_t).max() / np.abs(d_t).max()
    names = list(cal.params)
    print(f"synthetic calibration, 14 views x 54 corners, 0.2 px noise: RMS {float(cal.rms_px):.4f} px; rel. error (1-sigma) "
          + ", ".join(f"{n} {100 * e:.3f} % ({100 * s:.3f} %)" for n, e, s in zip(names, rel, sd)))
    print(f"  distortion field (whole image) max error {100 * field:.3f} % of its max "
          f"({np.abs(d_t).max() * truth[0]:.1f} px); k1 {100 * rel[4]:.3f} %")
    assert bool(cal.converged)
    assert rel[:4].max() < 1e-3  # intrinsics to 0.1 %
    assert field < 0.01 and rel[4] < 0.01  # distortion to 1 % (field), k1 to 1 %
    # the std figures are calibrated: every error within 3 sigma
    assert np.all(rel <= 3 * sd + 1e-12)


def test_homography_and_degenerate_inputs():
    P = board_points((9, 6))
    with pytest.raises(ValueError, match="calibrate_camera.*image_uv"):
        calibrate_camera(P, np.zeros((1, 54, 2)), (640, 512))
    with pytest.raises(ValueError, match="calibrate_camera.*board_xyz"):
        calibrate_camera(P + [0, 0, 1.0], np.zeros((3, 54, 2)), (640, 512))
    with pytest.raises(ValueError, match="calibrate_camera.*non-finite"):
        calibrate_camera(P, np.full((3, 54, 2), np.nan), (640, 512))
    # all views parallel to the image plane (pure translations): Zhang's system is degenerate
    truth = jnp.asarray([500.0, 500.0, 320.0, 256.0, 0, 0, 0, 0, 0])
    uv = np.stack([np.asarray(project_board(truth, jnp.zeros(3), jnp.asarray([-4.0 + i, -2.0, 12.0 + i]), P))
                   for i in range(3)])
    with pytest.raises(ValueError, match="zhang_init"):
        calibrate_camera(P, uv, (640, 512))
    with pytest.raises(ValueError, match="homography_dlt"):
        homography_dlt(np.zeros((3, 2)), np.zeros((3, 2)))
