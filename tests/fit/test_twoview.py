"""Two-view geometry on synthetic scenes with known truth (0.3 px noise, outliers, pure rotation)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from fsjax.fit.calibrate import rodrigues
from fsjax.fit.twoview import (
    decompose_essential,
    decompose_homography,
    fit_homography,
    fundamental_8point,
    homography_ransac,
    homography_transfer_px,
    normalized_points,
    relative_pose,
    sampson_distance,
    triangulate_dlt,
)
from fsjax.types import reason_code

K = np.array([[520.0, 0, 320.0], [0, 515.0, 240.0], [0, 0, 1.0]])


def _project(X):
    p = X @ K.T
    return p[:, :2] / p[:, 2:]


def _scene(seed, n=200, noise=0.3, outliers=0.2, t=(-1.0, 0.1, 0.2), rot=(0.05, -0.12, 0.03)):
    rng = np.random.default_rng(seed)
    X = rng.uniform([-3, -2, 6], [3, 2, 12], (n, 3))
    R = np.asarray(rodrigues(jnp.asarray(rot)))
    t = np.asarray(t, float)
    uv1 = _project(X) + rng.normal(0, noise, (n, 2))
    uv2 = _project(X @ R.T + t) + rng.normal(0, noise, (n, 2))
    k = int(outliers * n)
    uv2[:k] = rng.uniform([0, 0], [640, 480], (k, 2))
    return uv1, uv2, R, t, X, k


def _rot_err_deg(Ra, Rb):
    c = (np.trace(np.asarray(Ra).T @ Rb) - 1) / 2
    return np.degrees(np.arccos(np.clip(c, -1, 1)))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_relative_pose_accuracy(seed):
    uv1, uv2, R, t, X, k = _scene(seed)
    res = relative_pose(jax.random.PRNGKey(seed), uv1, uv2, K, threshold_px=1.0)
    er = _rot_err_deg(res.R, R)
    et = np.degrees(np.arccos(np.clip(np.dot(np.asarray(res.t), t / np.linalg.norm(t)), -1, 1)))
    inl = np.asarray(res.inliers)
    print(f"two-view seed {seed} (200 pts, 0.3 px noise, 20 % outliers): rotation error {er:.3f} deg, translation "
          f"direction {et:.3f} deg; inliers {int(res.n_inliers)} (outliers flagged {np.sum(~inl[:k])}/{k}); "
          f"Sampson RMS {float(res.sampson_rms_px):.3f} px; parallax {float(res.parallax_px):.1f} px")
    assert bool(res.converged) and not bool(res.degenerate) and res.message == "ok"
    assert er < 0.5 and et < 1.0
    assert np.sum(~inl[:k]) >= 0.95 * k
    # triangulated inliers: camera-1 coordinates in baseline units
    P = np.asarray(res.points)
    ok = np.all(np.isfinite(P), 1)
    scale = np.linalg.norm(t)
    dz = np.median(np.abs(P[ok, 2] * scale - X[ok, 2]) / X[ok, 2])
    print(f"  triangulated depth, median relative error {dz:.4f}")
    assert ok.sum() > 0.7 * 200 and dz < 0.05


def test_pure_rotation_is_degenerate():
    uv1, uv2, R, _, _, k = _scene(5, outliers=0.1, t=(0.0, 0.0, 0.0), rot=(0.02, 0.15, -0.05))
    deg = relative_pose(jax.random.PRNGKey(0), uv1, uv2, K)
    uv1h, uv2h, *_ = _scene(5, outliers=0.1)
    ok = relative_pose(jax.random.PRNGKey(0), uv1h, uv2h, K)
    print(f"parallax residual after the best single rotation: pure rotation {float(deg.parallax_px):.3f} px "
          f"(degenerate={bool(deg.degenerate)}, '{deg.message}'); healthy baseline {float(ok.parallax_px):.2f} px "
          f"(degenerate={bool(ok.degenerate)}); rotation from the alignment error {_rot_err_deg(deg.R, R):.4f} deg")
    assert bool(deg.degenerate) and int(deg.reason) == reason_code("pure_rotation") and np.all(np.isnan(np.asarray(deg.t)))
    assert np.all(np.isnan(np.asarray(deg.points)))
    assert _rot_err_deg(deg.R, R) < 0.1
    assert not bool(ok.degenerate) and float(ok.parallax_px) > 10 * float(deg.parallax_px)


def test_building_blocks():
    uv1, uv2, R, t, X, _ = _scene(3, noise=0.0, outliers=0.0)
    F = fundamental_8point(uv1, uv2)
    d = np.asarray(sampson_distance(F, uv1, uv2))
    x1, x2 = normalized_points(uv1, K), normalized_points(uv2, K)
    Rs, ts = decompose_essential(jnp.asarray(np.cross(np.eye(3), t / np.linalg.norm(t)) @ R))
    errs = [_rot_err_deg(r, R) for r in np.asarray(Rs)]
    P1 = np.c_[np.eye(3), np.zeros(3)]
    P2 = np.c_[R, t]
    Xt = np.asarray(triangulate_dlt(jnp.asarray(P1), jnp.asarray(P2), x1, x2))
    print(f"noise-free: max Sampson {d.max():.1e} px; decomposition recovers R to {min(errs):.1e} deg; "
          f"DLT triangulation max error {np.abs(Xt - X).max():.1e}")
    assert d.max() < 1e-6 and min(errs) < 1e-4 and np.abs(Xt - X).max() < 1e-8  # arccos near 1: ~1e-6 deg resolution


def test_fail_closed():
    uv1, uv2, *_ = _scene(0, n=6, outliers=0.0)
    r = relative_pose(jax.random.PRNGKey(0), uv1, uv2, K)
    assert not bool(r.converged) and "too few" in r.message and np.all(np.isnan(np.asarray(r.R)))
    rng = np.random.default_rng(0)
    r2 = relative_pose(jax.random.PRNGKey(0), rng.uniform(0, 640, (50, 2)), rng.uniform(0, 640, (50, 2)), K,
                       threshold_px=0.05)
    print(f"6 points -> {r.message!r}; random pairs, 0.05 px threshold -> {r2.message!r}")
    assert not bool(r2.converged) or bool(r2.degenerate)
    with pytest.raises(ValueError, match="relative_pose.*uv2"):
        relative_pose(jax.random.PRNGKey(0), np.zeros((10, 2)), np.zeros((9, 2)), K)


def _plane_scene(seed, n=200, noise=0.5, outliers=0.2, t=(-1.0, 0.1, 0.2), rot=(0.05, -0.12, 0.03)):
    rng = np.random.default_rng(seed)
    xy = rng.uniform([-3, -2], [3, 2], (n, 2))
    X = np.c_[xy, 8 + 0.3 * xy[:, 0] - 0.2 * xy[:, 1]]  # the plane z = 8 + 0.3 x - 0.2 y
    R = np.asarray(rodrigues(jnp.asarray(rot)))
    uv1 = _project(X) + rng.normal(0, noise, (n, 2))
    uv2 = _project(X @ R.T + np.asarray(t)) + rng.normal(0, noise, (n, 2))
    k = int(outliers * n)
    uv2[:k] = rng.uniform([0, 0], [640, 480], (k, 2))
    return uv1, uv2, R, np.asarray(t, float), X, k


@pytest.mark.parametrize("seed", [0, 1])
def test_homography_ransac_tells_planes_from_general_scenes(seed):
    # a plane: H holds the inliers E holds (thresholds matched as in H&Z table 4.1: 1.25x), rejects
    # the outliers and maps the noise-free points within the noise; a general scene: H holds few
    uv1, uv2, R, t, X, k = _plane_scene(seed)
    h = homography_ransac(jax.random.PRNGKey(seed), uv1, uv2, threshold_px=1.25 * 1.5)
    e = relative_pose(jax.random.PRNGKey(seed), uv1, uv2, K, threshold_px=1.5)
    inl = np.asarray(h.inliers)
    n = np.array([-0.3, 0.2, 1.0]) / 8.0  # n . X = 1 for the plane above
    Htrue = K @ (R + np.outer(t, n)) @ np.linalg.inv(K)
    d_true = np.asarray(homography_transfer_px(jnp.asarray(h.H), _project(X), _project(X @ R.T + t)))
    print(f"plane seed {seed}: H inliers {int(h.n_inliers)} (outliers kept {inl[:k].sum()}/{k}), E inliers "
          f"{int(e.n_inliers)} ('{e.message}'); transfer RMS {float(h.rms_px):.3f} px; noise-free points "
          f"off the fitted H by median {np.median(d_true[k:]):.3f} px")
    assert bool(h.converged) and h.message == "ok" and inl[:k].sum() == 0 and inl[k:].mean() > 0.95
    assert int(h.n_inliers) >= 0.9 * int(e.n_inliers)
    assert np.median(d_true[k:]) < 0.2
    Hn = np.asarray(h.H) / np.asarray(h.H)[2, 2]
    assert np.abs(Hn - Htrue / Htrue[2, 2]).max() < 0.05 * np.abs(Htrue / Htrue[2, 2]).max()
    # the true pose is one of the homography's two solutions facing camera 1; its twin is far from it
    Rs, ts, ns = (np.asarray(v) for v in decompose_homography(h.H, K))
    err = [_rot_err_deg(Rs[i], R) for i in range(2)]
    b = int(np.argmin(err))
    tdir = np.degrees(np.arccos(np.clip(ts[b] @ t / np.linalg.norm(ts[b]) / np.linalg.norm(t), -1, 1)))
    # (unrefined: 0.5 px noise on 160 points of a plane 8 baselines away gives ~0.4 deg, ~3 deg in t)
    assert err[b] < 1.0 and tdir < 5.0 and np.abs(ns[b] - n / np.linalg.norm(n)).max() < 0.05, (err, tdir, ns[b])
    assert err[1 - b] > 3 * err[b] + 2.0, err
    # null: a general scene of the same cameras
    uv1g, uv2g, *_ = _scene(seed, noise=0.5)
    hg = homography_ransac(jax.random.PRNGKey(seed), uv1g, uv2g, threshold_px=1.25 * 1.5)
    eg = relative_pose(jax.random.PRNGKey(seed), uv1g, uv2g, K, threshold_px=1.5)
    print(f"  general scene: H inliers {int(hg.n_inliers)}, E inliers {int(eg.n_inliers)}")
    assert int(hg.n_inliers) < 0.3 * int(eg.n_inliers)


def test_homography_building_blocks_and_fail_closed():
    rng = np.random.default_rng(3)
    H0 = np.array([[0.9, 0.1, 30.0], [-0.05, 1.1, -12.0], [3e-4, -2e-4, 1.0]])
    uv1 = rng.uniform(0, 600, (30, 2))
    p = np.c_[uv1, np.ones(30)] @ H0.T
    uv2 = p[:, :2] / p[:, 2:]
    H = np.asarray(fit_homography(uv1, uv2))
    assert np.abs(H / H[2, 2] - H0).max() < 1e-9
    # transfer distance: the same in either image order; d px off in one image -> about d / sqrt 2
    d = np.asarray(homography_transfer_px(H0, uv1, uv2))
    assert d.max() < 1e-9
    off = uv2 + [2.0, 0.0]
    d12 = np.asarray(homography_transfer_px(H0, uv1, off))
    d21 = np.asarray(homography_transfer_px(np.linalg.inv(H0), off, uv1))
    np.testing.assert_allclose(d12, d21, rtol=1e-9)
    assert 1.3 < np.median(d12) < 1.9  # 2 / sqrt 2, times the local scale of H^-1
    # padding rows (NaN) are never inliers; too few points and bad shapes fail closed
    pad = np.r_[uv1, np.full((10, 2), np.nan)]
    r = homography_ransac(jax.random.PRNGKey(0), pad, np.r_[uv2, np.full((10, 2), np.nan)])
    assert bool(r.converged) and int(r.n_inliers) == 30 and not np.asarray(r.inliers)[30:].any()
    r3 = homography_ransac(jax.random.PRNGKey(0), uv1[:3], uv2[:3])
    assert not bool(r3.converged) and "too few" in r3.message and np.all(np.isnan(np.asarray(r3.H)))
    with pytest.raises(ValueError, match="homography_ransac.*uv2"):
        homography_ransac(jax.random.PRNGKey(0), np.zeros((10, 2)), np.zeros((9, 2)))
    with pytest.raises(ValueError, match="homography_ransac.*threshold_px"):
        homography_ransac(jax.random.PRNGKey(0), uv1, uv2, threshold_px=0.0)
    # the checks shared with relative_pose name the calling function and the argument
    for fn in (homography_ransac, relative_pose):
        name = fn.__name__
        with pytest.raises(ValueError, match=f"{name}.*'uv1'.*\\(N, 2\\)"):
            fn(jax.random.PRNGKey(0), np.zeros((10, 3)), np.zeros((10, 3)), *(() if fn is homography_ransac else (np.eye(3),)))
        with pytest.raises(ValueError, match=f"{name}.*n_hypotheses"):
            fn(jax.random.PRNGKey(0), uv1, uv2, *(() if fn is homography_ransac else (np.eye(3),)), n_hypotheses=0)


def test_homography_ransac_float32():
    # float32 data (the library's default) with x64 on: same inliers as float64 within a few, H as good
    uv1, uv2, R, t, X, k = _plane_scene(0)
    r64 = homography_ransac(jax.random.PRNGKey(0), uv1, uv2, threshold_px=1.875)
    r32 = homography_ransac(jax.random.PRNGKey(0), jnp.asarray(uv1, jnp.float32), jnp.asarray(uv2, jnp.float32),
                            threshold_px=1.875)
    assert r32.H.dtype == jnp.float32 and bool(r32.converged)
    assert abs(int(r32.n_inliers) - int(r64.n_inliers)) <= 3 and not np.asarray(r32.inliers)[:k].any()
    d = np.asarray(homography_transfer_px(np.asarray(r32.H, float), _project(X), _project(X @ R.T + t)))
    assert np.median(d[k:]) < 0.2
