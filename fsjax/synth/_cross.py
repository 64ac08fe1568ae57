"""A CAD mesh and a partial point scan of it (issue 17, cross-structure registration)."""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["partial_scan", "cad_scan_pair"]


def partial_scan(xyz: np.ndarray, view_dir: Any, *, cell: float, depth_tol: float | None = None,
                 noise: float = 0.0, seed: int = 0) -> np.ndarray:
    """The part of a dense surface sample seen from far along ``view_dir`` (a point z-buffer).

    The samples are projected orthographically along ``view_dir`` onto a grid of square cells of
    edge ``cell``; in each cell the samples within ``depth_tol`` (default ``cell``) of the nearest one
    are kept (the visible surface), the rest are hidden behind it. Then ``noise`` (standard deviation,
    cloud units) is added along the viewing direction, as a range sensor would.

    Example:
        >>> from fsjax.synth import partial_scan

        Two unit squares, at z = 0 and z = 1, 4,000 samples each, seen from above: the upper one
        hides the lower one (a lower point shows only through a cell the upper sample left empty):

        >>> import numpy as np
        >>> g = np.random.default_rng(0).uniform(0, 1, (8000, 2))
        >>> two = np.c_[g, np.repeat([0.0, 1.0], 4000)]
        >>> seen = partial_scan(two, [0, 0, -1.0], cell=0.05)   # looking down from z = +inf
        >>> int(np.sum(seen[:, 2] == 1.0)), int(np.sum(seen[:, 2] == 0.0))
        (4000, 0)
    """
    x = np.asarray(xyz, float)
    d = np.asarray(view_dir, float)
    if x.ndim != 2 or x.shape[1] != 3 or d.shape != (3,) or not np.linalg.norm(d) > 0 or not cell > 0:
        raise ValueError("partial_scan: arguments 'xyz' (N, 3), 'view_dir' (3,) non-zero and 'cell' > 0 are required")
    d = d / np.linalg.norm(d)
    a = np.cross(d, [0.0, 0.0, 1.0] if abs(d[2]) < 0.9 else [1.0, 0.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(d, a)
    depth = x @ d
    ij = np.floor(np.c_[x @ a, x @ b] / cell).astype(np.int64)
    _, inv = np.unique(ij, axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    nearest = np.full(inv.max() + 1, np.inf)
    np.minimum.at(nearest, inv, depth)
    keep = depth <= nearest[inv] + (cell if depth_tol is None else depth_tol)
    rng = np.random.default_rng(seed)
    return x[keep] + (noise * rng.normal(size=int(keep.sum())))[:, None] * d


def cad_scan_pair(name: str = "fandisk", *, angle_deg: float = 50.0, axis: Any = (0.3, 1.0, 0.2),
                  shift: Any = (0.5, -0.3, 0.2), view_dir: Any = (0.3, -0.5, 1.0), n_dense: int = 60000,
                  cell_frac: float = 0.012, noise_frac: float = 0.001, seed: int = 0) -> dict:
    """A bundled mesh (the CAD model, in its own frame) and a partial scan of it, turned and moved.

    The scan: ``n_dense`` area-weighted surface samples (seed ``seed + 1``, independent of any sample
    of the model), the part seen along ``view_dir`` (:func:`partial_scan`, cells of ``cell_frac`` of the
    bounding-box diagonal), range noise of ``noise_frac`` of the diagonal, then
    ``scan = R (x - c) + c + shift`` with ``R`` the turn by ``angle_deg`` about ``axis`` and ``c`` the
    model's centroid. Returns ``{"mesh", "scan" (M, 3), "R", "t"}`` with ``scan ~ R model + t``.
    """
    from ..data import _mesh, mesh_arrays, surface_points
    from ..fit import rotation_from_axis_angle

    v, _ = mesh_arrays(name)
    diag = float(np.linalg.norm(v.max(0) - v.min(0)))
    dense = surface_points(name, n_dense, seed + 1)
    seen = partial_scan(dense, view_dir, cell=cell_frac * diag, noise=noise_frac * diag, seed=seed)
    R = np.asarray(rotation_from_axis_angle(np.asarray(axis, float), float(angle_deg)))
    c = v.astype(float).mean(0)
    t = c + np.asarray(shift, float) * diag / 10 - R @ c
    return {"mesh": _mesh(name), "scan": seen @ R.T + t, "R": R, "t": t, "diag": diag}
