"""Deprecated: use :mod:`fsjax.io.mesh` (or ``fsjax.io``, which re-exports its names).

Importing this module warns (``DeprecationWarning``) and gives the same objects as
:mod:`fsjax.io.mesh`; it will be removed in a later release.
"""

from __future__ import annotations

import warnings

from .io.mesh import __all__, read_mesh, read_points, write_mesh, write_points  # noqa: F401

warnings.warn("fsjax.io3d is deprecated; use fsjax.io.mesh (its names are also in fsjax.io)",
              DeprecationWarning, stacklevel=2)
