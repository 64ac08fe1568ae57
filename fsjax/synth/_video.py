"""A rendered video with known cameras: an orbit at varying speed around textured boxes in a room.

:func:`orbit_video` renders ``n_frames`` RGB frames with :func:`fsjax.render.rasterize`: a closed
room (walls, floor, ceiling; inward-facing box ``[-6, 6] x [0, 6] x [-6, 6]``, y up) and three boxes
near the centre, every surface textured by multi-scale random cells (value noise without
interpolation: sharp-cornered patches of random brightness and tint, so a scale-space detector
finds keypoints at several scales) evaluated at the world point of each pixel. The camera orbits the centre at ``radius``
and ``height``, looking at ``(0, 0.6, 0)`` (``fsjax.render.look_at``), its azimuth stepping by
``min_step_deg + (max_step_deg - min_step_deg) (1 - cos(2 pi k / n)) / 2`` degrees from frame k
to k+1: slow at both ends, fast in the middle, so frames chosen by accumulated rotation differ
from every k-th frame. Each frame is rendered at ``supersample`` times the size and box-filtered
down (antialiasing). Deterministic under ``seed``.
"""

from __future__ import annotations

import numpy as np

__all__ = ["orbit_video"]


def _box(lo, hi, inward: bool):
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    v = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    # quads as corner indices (index = 4 ix + 2 iy + iz), outward winding
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    f = []
    for a, b, c, d in quads:
        f += [(a, b, c), (a, c, d)]
    f = np.array(f)
    return v, (f[:, ::-1] if inward else f)


def _texture(p, seed):
    """(..., 3) colours in [0, 1] at world points ``p`` (..., 3): three scales of random cells, each
    cell a random brightness (what a grey detector sees) times a random tint in [0.6, 1]."""
    rng = np.random.default_rng(seed)
    table = rng.uniform(0, 1, (3, 4096, 4))
    out = np.zeros(p.shape[:-1] + (3,))
    for s, (cell, wgt) in enumerate(((0.9, 0.45), (0.3, 0.35), (0.1, 0.2))):
        ijk = np.floor(p / cell).astype(np.int64)
        h = (ijk[..., 0] * 73856093) ^ (ijk[..., 1] * 19349663) ^ (ijk[..., 2] * 83492791)
        t = table[s][np.mod(h, 4096)]
        out += wgt * t[..., :1] * (0.6 + 0.4 * t[..., 1:])
    return out / 0.8


def orbit_video(n_frames: int = 40, *, width: int = 192, height: int = 128, fov_x_deg: float = 60.0,
                radius: float = 3.0, cam_height: float = 1.6, min_step_deg: float = 0.6,
                max_step_deg: float = 3.0, supersample: int = 2, seed: int = 0) -> dict:
    """Frames and cameras of an orbit (module notes).

    Returns:
      dict with ``frames`` ``(n, H, W, 3)`` uint8, ``K`` ``(3, 3)`` (pixel centres on integers),
      ``R`` ``(n, 3, 3)`` world_from_camera, ``centres`` ``(n, 3)``, ``azimuth_deg`` ``(n,)``.
    """
    import jax.numpy as jnp

    from ..render.camera import look_at
    from ..render.raster import interpolate, rasterize
    from ..types import Camera, Mesh

    n = int(n_frames)
    if n < 2:
        raise ValueError(f"orbit_video: argument 'n_frames' must be >= 2, got {n_frames}")
    if width % 2 or height % 2:
        raise ValueError(f"orbit_video: arguments 'width', 'height' must be even (video encoders need it), got "
                         f"{width} x {height}")
    parts = [_box((-6, 0, -6), (6, 6, 6), True), _box((-0.9, 0, -0.5), (0.1, 1.2, 0.5), False),
             _box((0.4, 0, -0.9), (1.0, 0.6, -0.2), False), _box((0.2, 0, 0.5), (0.8, 1.6, 1.0), False)]
    verts, faces, off = [], [], 0
    for v, f in parts:
        verts.append(v)
        faces.append(f + off)
        off += len(v)
    V, F = np.concatenate(verts), np.concatenate(faces)
    mesh = Mesh(jnp.asarray(V), jnp.asarray(F, jnp.int32))
    k = np.arange(n - 1)
    steps = min_step_deg + (max_step_deg - min_step_deg) * (1 - np.cos(2 * np.pi * (k + 0.5) / (n - 1))) / 2
    az = np.concatenate([[0.0], np.cumsum(steps)])
    S = int(supersample)
    W2, H2 = width * S, height * S
    fx = (W2 / 2) / np.tan(np.radians(fov_x_deg) / 2)
    K2 = np.array([[fx, 0, (W2 - 1) / 2], [0, fx, (H2 - 1) / 2], [0, 0, 1.0]])
    frames, Rs, Cs = [], [], []
    for a in np.radians(az):
        eye = np.array([radius * np.sin(a), cam_height, radius * np.cos(a)])
        R, t = look_at(eye, [0.0, 0.6, 0.0])
        cam = Camera(jnp.asarray(K2), width=W2, height=H2, R=R, t=t)
        r = rasterize(mesh, cam)
        p = np.asarray(interpolate(r, mesh, jnp.asarray(V)))
        col = _texture(p, seed)
        # a little Lambert shading from a fixed direction keeps faces of one texture apart
        nrm = np.asarray(r.face_normal)
        shade = 0.75 + 0.25 * np.abs(nrm @ np.array([0.3, 0.8, 0.52]))
        img = (col * shade[..., None]).reshape(height, S, width, S, 3).mean((1, 3))
        frames.append(np.clip(np.round(img * 255), 0, 255).astype(np.uint8))
        Rs.append(np.asarray(R, float))
        Cs.append(np.asarray(t, float))
    K = np.array([[fx / S, 0, (width - 1) / 2], [0, fx / S, (height - 1) / 2], [0, 0, 1.0]])
    return {"frames": np.stack(frames), "K": K, "R": np.stack(Rs), "centres": np.stack(Cs), "azimuth_deg": az}
