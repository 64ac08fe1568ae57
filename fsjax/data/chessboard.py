"""The bundled chessboard calibration photographs (OpenCV sample set ``left01..14``).

Fourteen 640x512 greyscale JPEGs of a printed chessboard with 9 x 6 inner corners, the
classic OpenCV camera-calibration sample (from the OpenCV book samples; "right to use this
code in any way you want"), stored unchanged in ``fsjax/data/chessboard/`` (see the
README there). The square size is not stated by the source: board coordinates are in
square units.

Import from this submodule: ``from fsjax.data.chessboard import chessboard_images``.
"""

from __future__ import annotations

from functools import cache
from pathlib import Path

import numpy as np

__all__ = ["chessboard_images", "chessboard_paths", "CHESSBOARD_SOURCE", "CHESSBOARD_PATTERN"]

_DIR = Path(__file__).resolve().parent / "chessboard"

CHESSBOARD_SOURCE = ("OpenCV sample calibration images left01..left14.jpg (OpenCV book samples; "
                     "'right to use this code in any way you want')")
CHESSBOARD_PATTERN = (9, 6)  # inner corners (columns, rows)


def chessboard_paths() -> list[Path]:
    """Paths of the 14 bundled JPEGs, ``left01.jpg`` .. ``left14.jpg`` in order."""
    paths = [_DIR / f"left{i:02d}.jpg" for i in range(1, 15)]
    missing = [p.name for p in paths if not p.exists()]
    if missing:
        raise FileNotFoundError(f"fsjax.data.chessboard: bundled images missing in {_DIR}: {missing}")
    return paths


@cache
def _load_all() -> np.ndarray:
    from PIL import Image as _PIL

    return np.stack([np.asarray(_PIL.open(p).convert("L"), dtype=np.uint8) for p in chessboard_paths()])


def chessboard_images(*, as_float: bool = True) -> np.ndarray:
    """The 14 photographs as one array ``(14, 512, 640)``.

    Args:
      as_float: ``True`` (default) gives float64 in [0, 1] (``uint8 / 255``); ``False`` the
        raw ``uint8`` pixels (as OpenCV reads them).

    Example:
        >>> from fsjax.data.chessboard import chessboard_images
        >>> chessboard_images().shape
        (14, 512, 640)
    """
    raw = _load_all()
    return raw.astype(np.float64) / 255.0 if as_float else raw.copy()
