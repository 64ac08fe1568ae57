"""Focal length from verified two-view matches when no intrinsics are given (issue 14).

Self-calibration by the criterion of Mendonca and Cipolla ("A simple technique for
self-calibration", CVPR 1999): for the right intrinsics ``K`` every fundamental matrix ``F`` of the
set gives an essential matrix ``E = K^T F K`` whose two non-zero singular values are equal. With
one shared focal length ``f`` (``fx = fy``, zero skew, principal point given: the image centre
unless known) the cost ``sum_pairs w (s1 - s2) / s2`` is a function of ``f`` alone; it is
minimised by a log-spaced 1-D search over ``[0.3, 3] x max(W, H)`` followed by golden-section
refinement of the best bracket. Each ``F`` is fitted by the normalised 8-point algorithm
(Hartley, "In defense of the eight-point algorithm", TPAMI 1997) on the pair's inlier matches (the
inliers of the essential-matrix RANSAC run with the guessed focal length: the Sampson test is a
test against a fundamental matrix, so the inlier sets hold under a wrong focal length), rank 2
enforced; pairs are weighted by their inlier count. Host numpy: a few tens of 3x3 SVDs per
candidate.
"""
from __future__ import annotations

import numpy as np


def fundamental_8point(uv1: np.ndarray, uv2: np.ndarray) -> np.ndarray:
    """Normalised 8-point fundamental matrix with ``uv2^T F uv1 = 0`` (pixels), rank 2, unit norm."""
    uv1, uv2 = np.asarray(uv1, np.float64), np.asarray(uv2, np.float64)
    if uv1.shape != uv2.shape or uv1.ndim != 2 or uv1.shape[1] != 2 or len(uv1) < 8:
        raise ValueError(f"fundamental_8point: arguments 'uv1', 'uv2' must be matching (N >= 8, 2) arrays, "
                         f"got {uv1.shape} and {uv2.shape}")

    def norm(p):
        c = p.mean(0)
        s = np.sqrt(2) / max(np.sqrt(((p - c) ** 2).sum(1)).mean(), 1e-12)
        return np.array([[s, 0, -s * c[0]], [0, s, -s * c[1]], [0, 0, 1.0]])

    T1, T2 = norm(uv1), norm(uv2)
    p1 = np.c_[uv1, np.ones(len(uv1))] @ T1.T
    p2 = np.c_[uv2, np.ones(len(uv2))] @ T2.T
    A = (p2[:, :, None] * p1[:, None, :]).reshape(len(p1), 9)
    F = np.linalg.svd(A)[2][-1].reshape(3, 3)
    U, s, Vt = np.linalg.svd(F)
    F = U @ np.diag([s[0], s[1], 0.0]) @ Vt
    F = T2.T @ F @ T1
    return F / np.linalg.norm(F)


def focal_cost(f: float, Fs: np.ndarray, weights: np.ndarray, cx: float, cy: float) -> float:
    """Mendonca-Cipolla cost ``sum w (s1 - s2) / s2`` of ``E = K^T F K`` for the focal length ``f``."""
    K = np.array([[f, 0, cx], [0, f, cy], [0, 0, 1.0]])
    s = np.linalg.svd(np.einsum("ji,njk,kl->nil", K, Fs, K), compute_uv=False)
    return float(np.sum(weights * (s[:, 0] - s[:, 1]) / np.maximum(s[:, 1], 1e-300)) / np.sum(weights))


def estimate_focal(pairs_uv, image_size, *, principal_point=None, lo: float = 0.3, hi: float = 3.0,
                   n_grid: int = 200) -> dict:
    """Shared focal length (pixels) from the inlier matches of verified pairs (module notes).

    Args:
      pairs_uv: sequence of ``(uv1, uv2)`` inlier correspondences (``(N, 2)`` pixels each, N >= 8).
      image_size: ``(W, H)``. principal_point: ``(cx, cy)``; default the image centre
        ``((W - 1) / 2, (H - 1) / 2)`` (pixel centres on integers).
      lo, hi: search range in units of ``max(W, H)``. n_grid: log-spaced candidates.

    Returns:
      dict with ``focal_px``, ``cost`` (at the minimum), ``n_pairs``, ``at_bound`` (the minimum lies
      at an end of the range: the estimate is then not trustworthy) and ``method``.
    """
    w, h = image_size
    cx, cy = principal_point if principal_point is not None else ((w - 1) / 2, (h - 1) / 2)
    Fs, wts = [], []
    for uv1, uv2 in pairs_uv:
        if len(uv1) >= 8:
            Fs.append(fundamental_8point(uv1, uv2))
            wts.append(len(uv1))
    if not Fs:
        raise ValueError("estimate_focal: argument 'pairs_uv' holds no pair with >= 8 correspondences")
    Fs, wts = np.stack(Fs), np.asarray(wts, np.float64)
    m = max(w, h)
    grid = m * np.geomspace(lo, hi, n_grid)
    costs = np.array([focal_cost(f, Fs, wts, cx, cy) for f in grid])
    k = int(np.argmin(costs))
    a, b = grid[max(k - 1, 0)], grid[min(k + 1, n_grid - 1)]
    g = (np.sqrt(5) - 1) / 2
    c, d = b - g * (b - a), a + g * (b - a)
    fc, fd = focal_cost(c, Fs, wts, cx, cy), focal_cost(d, Fs, wts, cx, cy)
    for _ in range(60):
        if fc < fd:
            b, d, fd = d, c, fc
            c = b - g * (b - a)
            fc = focal_cost(c, Fs, wts, cx, cy)
        else:
            a, c, fc = c, d, fd
            d = a + g * (b - a)
            fd = focal_cost(d, Fs, wts, cx, cy)
    f = (a + b) / 2
    return dict(focal_px=float(f), cost=focal_cost(f, Fs, wts, cx, cy), n_pairs=len(Fs),
                at_bound=k in (0, n_grid - 1), principal_point=(float(cx), float(cy)),
                method="Mendonca-Cipolla self-calibration (equal singular values of K^T F K) over "
                       f"{len(Fs)} verified pairs, 1-D search over [{lo}, {hi}] x max(W, H)")
