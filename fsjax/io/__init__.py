"""File input/output: images, point clouds and meshes, Gaussian splats.

One package, four modules, every public name re-exported here (``fsjax.io.<name>`` is
the path to use):

* :mod:`fsjax.io.image` -- image files through Pillow: :func:`read_image`, :func:`write_image`
  (integer-to-float conversion recorded on the sort).
* :mod:`fsjax.io.mesh` -- point clouds and meshes: PLY, OBJ, STL, XYZ, PCD
  (:func:`read_points`, :func:`write_points`, :func:`read_mesh`, :func:`write_mesh`).
* :mod:`fsjax.io.rle` -- run-length encoding of label volumes and masks (:func:`rle_encode`,
  :func:`rle_decode`, :class:`RunLength` with ``to_npz``, :func:`read_rle`).
* :mod:`fsjax.io.splat` -- :class:`fsjax.Gaussians` as 3DGS PLY and 32-byte ``.splat``
  (:func:`write_ply_gaussians`, :func:`read_ply_gaussians`, :func:`write_splat`,
  :func:`read_splat`, :func:`splat_bytes`, :data:`SPLAT_DTYPE`).

``fsjax.io3d`` and ``fsjax.io_splat`` (the former module paths) still import, with a
``DeprecationWarning`` naming the new path.
"""

from __future__ import annotations

from .image import read_image, write_image
from .mesh import read_mesh, read_points, write_mesh, write_points
from .rle import RunLength, read_rle, rle_decode, rle_encode
from .splat import (
    SPLAT_DTYPE,
    read_ply_gaussians,
    read_splat,
    splat_bytes,
    write_ply_gaussians,
    write_splat,
)

__all__ = ["read_image", "write_image",
           "read_points", "write_points", "read_mesh", "write_mesh",
           "RunLength", "rle_encode", "rle_decode", "read_rle",
           "write_ply_gaussians", "read_ply_gaussians", "write_splat", "read_splat", "splat_bytes", "SPLAT_DTYPE"]
