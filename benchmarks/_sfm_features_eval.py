"""Repeatability and matching score under a known homography (helper of bench_sfm.py, also used by a test)."""
from __future__ import annotations

import numpy as np


def homography(h: int, w: int, angle_deg: float, scale: float, persp: float) -> np.ndarray:
    """A homography about the image centre: rotation, isotropic scale, a little perspective."""
    c = np.array([[1, 0, w / 2 - 0.5], [0, 1, h / 2 - 0.5], [0, 0, 1.0]])
    a = np.deg2rad(angle_deg)
    A = np.array([[scale * np.cos(a), -scale * np.sin(a), 0], [scale * np.sin(a), scale * np.cos(a), 0],
                  [persp / w, 0.5 * persp / h, 1.0]])
    return c @ A @ np.linalg.inv(c)


def warp(img: np.ndarray, H: np.ndarray) -> np.ndarray:
    import cv2
    return cv2.warpPerspective(img, H, (img.shape[1], img.shape[0]), flags=cv2.INTER_LINEAR,
                               borderMode=cv2.BORDER_CONSTANT, borderValue=0)


def _apply(H, uv):
    p = np.c_[uv, np.ones(len(uv))] @ H.T
    return p[:, :2] / p[:, 2:]


def scores(uv_a, desc_a, uv_b, desc_b, H, shape, *, eps_px: float = 2.5, ratio: float = 0.8, margin: int = 8):
    """Repeatability and matching score (Mikolajczyk et al. 2005, simplified to positions):
    keypoints of A mapped by H and of B mapped back, restricted to the region both images see;
    repeatability = A points with a B point within eps / min(count A, count B);
    matching score = mutual-NN + ratio matches whose mapped error < eps / min(count A, count B)."""
    h, w = shape
    inside = lambda p: (p[:, 0] >= margin) & (p[:, 0] < w - margin) & (p[:, 1] >= margin) & (p[:, 1] < h - margin)  # noqa: E731
    ia = inside(_apply(H, uv_a)) & inside(uv_a)
    ib = inside(_apply(np.linalg.inv(H), uv_b)) & inside(uv_b)
    ua, da = uv_a[ia], desc_a[ia]
    ub, db = uv_b[ib], desc_b[ib]
    na, nb = len(ua), len(ub)
    pa = _apply(H, ua)
    d2 = ((pa[:, None, :] - ub[None, :, :]) ** 2).sum(-1)
    rep = float((d2.min(1) < eps_px ** 2).sum()) / max(min(na, nb), 1)
    da = da / np.linalg.norm(da, axis=1, keepdims=True)
    db = db / np.linalg.norm(db, axis=1, keepdims=True)
    sim = da @ db.T
    j1 = sim.argmax(1)
    s = np.sort(sim, 1)
    dd1 = np.sqrt(np.maximum(2 - 2 * s[:, -1], 0))
    dd2 = np.sqrt(np.maximum(2 - 2 * s[:, -2], 0))
    mutual = sim.argmax(0)[j1] == np.arange(na)
    ok = mutual & (dd1 < ratio * dd2)
    correct = ok & (d2[np.arange(na), j1] < eps_px ** 2)
    return dict(n_a=na, n_b=nb, repeatability=rep, matching_score=float(correct.sum()) / max(min(na, nb), 1),
                n_matches=int(ok.sum()), n_correct=int(correct.sum()))


def fsjax_features(img01: np.ndarray, n_max: int = 4096):
    import jax.numpy as jnp

    from fsjax.sfm.features import detect_and_describe
    f = detect_and_describe(jnp.asarray(img01, jnp.float32), n_max=n_max)
    v = np.asarray(f.valid)
    return np.asarray(f.uv)[v].astype(np.float64), np.asarray(f.descriptors)[v].astype(np.float64)


def opencv_features(img01: np.ndarray, n_max: int = 4096):
    """OpenCV SIFT with RootSIFT applied to its descriptors (same matcher for both)."""
    import cv2
    sift = cv2.SIFT_create(nfeatures=n_max)
    kp, d = sift.detectAndCompute(np.clip(img01 * 255 + 0.5, 0, 255).astype(np.uint8), None)
    uv = np.array([k.pt for k in kp], np.float64).reshape(-1, 2)
    d = d.astype(np.float64)
    d = np.sqrt(d / np.maximum(d.sum(1, keepdims=True), 1e-12))
    return uv, d
