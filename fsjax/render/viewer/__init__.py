"""A small self-contained HTML/WebGL viewer for ``.splat`` exports (``index.html`` + ``viewer.js``).

:func:`viewer_page` returns one HTML file with the viewer script and the splats (base64) and
camera embedded, so it opens from disk (``file://``) in any WebGL browser without a server;
the same ``index.html``/``viewer.js`` also load ``?url=scene.splat`` when served over HTTP.
URL options: ``?cull=extent`` (default; near-plane culling by the splat's 3-sigma depth
extent, as :func:`fsjax.render.render_splats`) or ``?cull=centre`` (the common centre-only
rule, kept to show the defect), ``?mode=alpha`` (white splats on black: pixel value =
accumulated opacity). The viewer follows the rasteriser's conventions (OpenCV camera,
``world_from_camera`` pose, 0.3 px^2 dilation, alpha floor 1/255, clamp 0.99) but sorts
globally back to front and blends in 8-bit, so it matches the JAX renderer only to a few
grey levels.
"""

from __future__ import annotations

import base64
import json
import os
from pathlib import Path

import numpy as np

from ...types import Camera

__all__ = ["viewer_page", "write_viewer_page", "viewer_files"]

_HERE = Path(__file__).resolve().parent


def viewer_files() -> dict:
    """Paths of the packaged ``index.html`` and ``viewer.js``."""
    return {"index.html": _HERE / "index.html", "viewer.js": _HERE / "viewer.js"}


def _camera_json(cam: Camera, near: float) -> dict:
    if not isinstance(cam, Camera) or cam.batch_shape:
        raise TypeError("viewer_page(camera=...): expected one fsjax.Camera")
    K = np.asarray(cam.K, float)
    if K[0, 1] != 0:
        raise ValueError("viewer_page(camera=...): the viewer has no skew term; K[0, 1] must be 0")
    if np.any(np.asarray(cam.dist) != 0):
        raise ValueError("viewer_page(camera=...): the viewer is pinhole only; distortion must be zero")
    if not near > 0:
        raise ValueError(f"viewer_page(near=...): must be > 0, got {near}")
    return {"fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2], "width": cam.width,
            "height": cam.height, "R": np.asarray(cam.R, float).ravel().tolist(),
            "t": np.asarray(cam.t, float).tolist(), "near": float(near)}


def viewer_page(splat: bytes | str | os.PathLike, camera: Camera, *, near: float = 0.2) -> str:
    """One self-contained HTML page showing ``splat`` (bytes or a ``.splat`` path) from ``camera``."""
    data = splat if isinstance(splat, (bytes, bytearray)) else Path(splat).read_bytes()
    if len(data) % 32:
        raise ValueError(f"viewer_page(splat=...): {len(data)} bytes is not a multiple of 32")
    html = (_HERE / "index.html").read_text()
    js = (_HERE / "viewer.js").read_text()
    embed = (f"window.FSJAX_SPLAT_B64 = \"{base64.b64encode(bytes(data)).decode()}\";\n"
             f"window.FSJAX_CAMERA = {json.dumps(_camera_json(camera, near))};")
    return html.replace("/*FSJAX_DATA*/", embed).replace("/*FSJAX_VIEWER_JS*/", js)


def write_viewer_page(path: str | os.PathLike, splat, camera: Camera, *, near: float = 0.2) -> Path:
    """Write :func:`viewer_page` to ``path``; returns the path."""
    p = Path(path)
    p.write_text(viewer_page(splat, camera, near=near))
    return p
