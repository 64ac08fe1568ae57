"""Deprecated: use :mod:`fsjax.io` (the names live in :mod:`fsjax.io.splat`).

Importing this module warns (``DeprecationWarning``) and gives the same objects as
:mod:`fsjax.io.splat`; it will be removed in a later release.
"""

from __future__ import annotations

import warnings

from .io.splat import (  # noqa: F401
    SPLAT_DTYPE,
    __all__,
    read_ply_gaussians,
    read_splat,
    splat_bytes,
    write_ply_gaussians,
    write_splat,
)

warnings.warn("fsjax.io_splat is deprecated; use fsjax.io (module fsjax.io.splat)",
              DeprecationWarning, stacklevel=2)
