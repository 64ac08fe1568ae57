"""Synthetic multi-view scenes with known truth (bundle adjustment, two-view tests).

:func:`bundle_scene`: ``n_cams`` cameras on a ring of radius ``radius`` around the origin at
mixed heights, all looking at the origin (OpenCV frame, shared intrinsics), ``n_pts`` points
uniform in the cube ``[-1, 1]^3``; every point seen by every camera; observations with Gaussian
pixel noise ``noise_px`` per coordinate; a perturbed initial guess (rotations by
``rot_noise`` rad, translations by ``trans_noise``, points by ``point_noise``, all Gaussian).
Deterministic under ``seed`` (NumPy's PCG64).
"""

from __future__ import annotations

import numpy as np

__all__ = ["bundle_scene"]


def _rotvec_to_matrix(w):
    th = np.linalg.norm(w)
    if th < 1e-15:
        return np.eye(3)
    k = w / th
    Kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(th) * Kx + (1 - np.cos(th)) * Kx @ Kx


def _matrix_to_rotvec(R):
    c = np.clip((np.trace(R) - 1) / 2, -1.0, 1.0)
    th = np.arccos(c)
    if th < 1e-12:
        return np.zeros(3)
    v = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) / (2 * np.sin(th))
    return v * th


def bundle_scene(n_cams: int = 20, n_pts: int = 2000, *, noise_px: float = 2.0, radius: float = 6.0,
                 focal: float = 800.0, size: tuple[int, int] = (1280, 960), rot_noise: float = 0.02,
                 trans_noise: float = 0.1, point_noise: float = 0.05, seed: int = 0) -> dict:
    """A bundle-adjustment problem; returns a dict of NumPy arrays (see the module docstring).

    Keys: ``K``; truth ``rotvecs``, ``translations`` (camera_from_world), ``points``;
    ``init_rotvecs``, ``init_translations``, ``init_points``; ``cam_idx``, ``pt_idx``, ``uv``.
    """
    if n_cams < 2 or n_pts < 1:
        raise ValueError(f"bundle_scene: need n_cams >= 2 and n_pts >= 1, got {n_cams}, {n_pts}")
    rng = np.random.default_rng(seed)
    w, h = size
    K = np.array([[focal, 0.0, (w - 1) / 2], [0.0, focal, (h - 1) / 2], [0.0, 0.0, 1.0]])
    X = rng.uniform(-1.0, 1.0, (n_pts, 3))
    rot, trans = [], []
    for i in range(n_cams):
        a = 2 * np.pi * i / n_cams
        eye = np.array([radius * np.cos(a), 0.8 * np.sin(3 * a), radius * np.sin(a)])
        z = -eye / np.linalg.norm(eye)
        up = np.array([0.0, -1.0, 0.0])  # world y up appears up: camera y (down) ~ -up
        y = -up - np.dot(-up, z) * z
        y /= np.linalg.norm(y)
        x = np.cross(y, z)
        Rwc = np.stack([x, y, z], axis=1)
        Rcw = Rwc.T
        rot.append(_matrix_to_rotvec(Rcw))
        trans.append(-Rcw @ eye)
    rot, trans = np.array(rot), np.array(trans)
    cam_idx = np.repeat(np.arange(n_cams), n_pts)
    pt_idx = np.tile(np.arange(n_pts), n_cams)
    uv = np.empty((n_cams * n_pts, 2))
    for i in range(n_cams):
        xc = X @ _rotvec_to_matrix(rot[i]).T + trans[i]
        p = xc[:, :2] / xc[:, 2:3]
        uv[i * n_pts:(i + 1) * n_pts] = p * focal + K[:2, 2]
    uv_noisy = uv + rng.normal(0.0, noise_px, uv.shape)
    init_rot = rot + rng.normal(0.0, rot_noise, rot.shape)
    init_trans = trans + rng.normal(0.0, trans_noise, trans.shape)
    init_rot[0], init_trans[0] = rot[0], trans[0]  # the gauge camera starts at its true pose
    j = int(np.argmax(np.abs(trans[1])))
    init_trans[1, j] = trans[1, j]  # and so does the scale-fixing coordinate
    init_pts = X + rng.normal(0.0, point_noise, X.shape)
    return dict(K=K, rotvecs=rot, translations=trans, points=X, init_rotvecs=init_rot, init_translations=init_trans,
                init_points=init_pts, cam_idx=cam_idx, pt_idx=pt_idx, uv=uv_noisy, uv_clean=uv)
