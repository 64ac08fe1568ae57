"""Small bundled real datasets and their loaders.

Meshes (vendored by ``tools/vendor_meshes.py`` from the project's shared data,
float32 vertices, int32 triangles, outward winding as in the source files):

* :func:`bunny` -- the Stanford Bunny range-scan reconstruction, 35,947 vertices,
  69,451 triangles, in metres (about 0.155 x 0.152 x 0.121 m), y up. Free for research
  use; credit the Stanford Computer Graphics Laboratory (Stanford 3D Scanning
  Repository, via A. Jacobson's common-3d-test-models collection).
* :func:`spot` -- Keenan Crane's "Spot" cow, 2,930 vertices, 5,856 triangles, unit-less
  (about 1.2 across). CC0 1.0.
* :func:`fandisk` -- H. Hoppe's Fandisk CAD part ("Mesh optimization", SIGGRAPH 1993),
  6,475 vertices, 12,946 triangles; sharp features, planar and curved faces.
  Research use, widely redistributed.

Each loader returns a :class:`fsjax.Mesh` in float64 when x64 is enabled, else float32;
:func:`mesh_source` returns the source and licence line; :func:`surface_points` samples a
bundled surface (deterministic numpy, for tests, tours and benchmarks).
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import numpy as np

_DIR = Path(__file__).resolve().parent

__all__ = ["bunny", "spot", "fandisk", "mesh_arrays", "mesh_source", "surface_points"]


@lru_cache(maxsize=None)
def _load(name: str) -> tuple[np.ndarray, np.ndarray, str]:
    path = _DIR / f"{name}.npz"
    if not path.exists():
        raise FileNotFoundError(f"fsjax.data: bundled mesh {name!r} not found at {path}")
    with np.load(path) as z:
        return z["vertices"], z["faces"], str(z["source"])


def mesh_arrays(name: str) -> tuple[np.ndarray, np.ndarray]:
    """``(vertices float64 (V, 3), faces int32 (F, 3))`` of a bundled mesh: 'bunny', 'spot', 'fandisk'."""
    if name not in ("bunny", "spot", "fandisk"):
        raise ValueError(f"fsjax.data.mesh_arrays(name=...): expected 'bunny', 'spot' or 'fandisk', got {name!r}")
    v, f, _ = _load(name)
    return v.astype(np.float64), f.copy()


def mesh_source(name: str) -> str:
    """Source and licence line of a bundled mesh."""
    mesh_arrays(name)
    return _load(name)[2]


def _mesh(name: str):
    import jax.numpy as jnp

    from fsjax.types import Mesh

    v, f = mesh_arrays(name)
    return Mesh(jnp.asarray(v), jnp.asarray(f))


def bunny():
    """The Stanford Bunny as a :class:`fsjax.Mesh` (metres, y up)."""
    return _mesh("bunny")


def spot():
    """Keenan Crane's Spot cow as a :class:`fsjax.Mesh`."""
    return _mesh("spot")


def fandisk():
    """Hoppe's Fandisk CAD part as a :class:`fsjax.Mesh`."""
    return _mesh("fandisk")


def surface_points(name: str, n: int, seed: int = 0, *, normals: bool = False):
    """``(n, 3)`` area-weighted samples of a bundled mesh's surface (numpy float64, deterministic).

    Triangles are drawn with probability proportional to their area, points uniformly inside
    by the square-root barycentric rule (Turk 1990, "Generating random points in triangles",
    Graphics Gems). The same ``(name, n, seed)`` gives the same points on every machine.
    ``normals=True`` returns ``(points, normals)``: each sample's triangle's unit normal (by
    the faces' winding; the same points as without).

    Example:
        >>> from fsjax.data import surface_points
        >>> x = surface_points("bunny", 1000, seed=0)
        >>> x.shape, bool(abs(x[:, 1].min() - 0.0330) < 0.003)  # the bunny's feet at y ~ 0.033 m
        ((1000, 3), True)
    """
    if not isinstance(n, (int, np.integer)) or isinstance(n, bool) or n < 1:
        raise ValueError(f"surface_points: argument 'n' must be a positive int, got {n!r}")
    v, f = mesh_arrays(name)
    v = v.astype(np.float64)
    rng = np.random.default_rng(seed)
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    tri = rng.choice(len(f), size=int(n), p=area / area.sum())
    r1, r2 = rng.random(int(n)), rng.random(int(n))
    s = np.sqrt(r1)
    p = (1 - s)[:, None] * a[tri] + (s * (1 - r2))[:, None] * b[tri] + (s * r2)[:, None] * c[tri]
    if not normals:
        return p
    nrm = np.cross(b - a, c - a)[tri]
    return p, nrm / np.linalg.norm(nrm, axis=1, keepdims=True)
