"""The ``ncc3d_pyramid`` column of the 3-D matching grid (coarse-to-fine NCC, :func:`fsjax.ops.ncc3d_pyramid`).

The cells run on the scenes of the ``ncc3d`` column (:func:`fsjax.synth.run_grid_cell` for the voxel,
points, mesh and Gaussians rows; :func:`fsjax.synth.run_depth_cell` for the depth row), with the op's
default levels (one reduction for the 24^3 template: 12^3 at the top). Over seeds 0-2 every cell found
the same placement as ``ncc3d`` (the same integer peak and Newton step), so the tolerances are the
``ncc3d`` column's.
"""

from __future__ import annotations

from ._match3d import MATCH3D_CELL_TOL
from ._match3d_depth import MATCH3D_DEPTH_CELL_TOL

__all__ = ["MATCH3D_PYR_METHODS", "MATCH3D_PYR_CELL_TOL"]

MATCH3D_PYR_METHODS = ("ncc3d_pyramid",)

MATCH3D_PYR_CELL_TOL = {
    **{(s, "ncc3d_pyramid"): MATCH3D_CELL_TOL[(s, "ncc3d")] for s in ("voxel", "points", "mesh", "gaussians")},
    ("depth", "ncc3d_pyramid"): MATCH3D_DEPTH_CELL_TOL["ncc3d_pyramid"],
}
