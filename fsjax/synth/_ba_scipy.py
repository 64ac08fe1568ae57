"""SciPy reference for bundle adjustment (``scipy.optimize.least_squares``, trf, sparse Jacobian).

Same model, parameters and gauge as :func:`fsjax.fit.bundle_adjust.bundle_adjust`: camera 0
and the largest-magnitude translation coordinate of camera 1 are held fixed. Used by the
tests and the benchmark as the peer; not part of the library's API.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import lil_matrix
from scipy.spatial.transform import Rotation

__all__ = ["scipy_bundle_adjust"]


def scipy_bundle_adjust(K, rotvecs, translations, points, cam_idx, pt_idx, uv, *, loss: str = "linear",
                        loss_scale: float = 1.0, xtol: float = 1e-10, ftol: float = 1e-10):
    """Returns ``(rotvecs, translations, points, rmse, result)``; rmse over all residual coordinates."""
    K = np.asarray(K, float)
    rv0, t0, X0 = (np.asarray(a, float).copy() for a in (rotvecs, translations, points))
    ci, pi, uv = np.asarray(cam_idx), np.asarray(pt_idx), np.asarray(uv, float)
    n, m = len(rv0), len(X0)
    free = np.ones((n, 6), bool)
    free[0] = False
    free[1, 3 + int(np.argmax(np.abs(t0[1])))] = False
    cam0 = np.concatenate([rv0, t0], axis=1)

    def unpack(x):
        cams = cam0.copy()
        cams[free] = x[: free.sum()]
        return cams, x[free.sum():].reshape(m, 3)

    def fun(x):
        cams, X = unpack(x)
        R = Rotation.from_rotvec(cams[ci, :3])
        xc = R.apply(X[pi]) + cams[ci, 3:]
        u = K[0, 0] * xc[:, 0] / xc[:, 2] + K[0, 1] * xc[:, 1] / xc[:, 2] + K[0, 2]
        v = K[1, 1] * xc[:, 1] / xc[:, 2] + K[1, 2]
        return (np.stack([u, v], axis=1) - uv).ravel()

    col = -np.ones((n, 6), int)
    col[free] = np.arange(free.sum())
    nc = int(free.sum())
    A = lil_matrix((2 * len(ci), nc + 3 * m), dtype=int)
    rows = np.arange(len(ci))
    for j in range(6):
        c = col[ci, j]
        ok = c >= 0
        for k in (0, 1):
            A[2 * rows[ok] + k, c[ok]] = 1
    for j in range(3):
        for k in (0, 1):
            A[2 * rows + k, nc + 3 * pi + j] = 1
    x0 = np.concatenate([cam0[free], X0.ravel()])
    res = least_squares(fun, x0, jac_sparsity=A, method="trf", x_scale="jac", loss=loss, f_scale=loss_scale,
                        xtol=xtol, ftol=ftol)
    cams, X = unpack(res.x)
    r = fun(res.x)
    return cams[:, :3], cams[:, 3:], X, float(np.sqrt(np.mean(r * r))), res
