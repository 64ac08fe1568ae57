"""Standard inputs: one small deterministic instance per sort (two variants).

The standard scene is a ``(H, W)`` grey image in ``[0.05, 0.95]``: a bright
disc, a dark rectangle and a thin bright bar on a linear ramp, with mild
deterministic noise. Its ground truth (object masks, areas) is returned by
:func:`standard_scene` for tests that need it.
"""

from __future__ import annotations

from collections.abc import Callable

import jax.numpy as jnp
import numpy as np

from ..types import Camera, Color, Depth, Feature, Image, Labels, Mesh, Points, Region, Signal, Sort, Volume

_POOL: dict[type, Callable[[int, tuple[int, int]], Sort]] = {}

DEFAULT_SIZE = (24, 32)


def register_pool(sort: type):
    """Register ``fn(variant, size) -> sort instance`` as the standard input of ``sort``."""

    def deco(fn):
        _POOL[sort] = fn
        return fn

    return deco


def standard_scene(variant: int = 0, size: tuple[int, int] = DEFAULT_SIZE, noise: float = 0.02):
    """The standard scene and its ground truth.

    Returns ``(image, masks)`` where ``image`` is a float64 numpy array and
    ``masks`` maps ``"disc"``, ``"rect"``, ``"bar"`` to bool arrays.
    """
    h, w = size
    rng = np.random.default_rng(1234 + variant)
    rr, cc = np.mgrid[0:h, 0:w].astype(float)
    ramp = 0.25 + 0.2 * cc / max(w - 1, 1)
    cy, cx, r = h * (0.45 + 0.05 * variant), w * 0.3, min(h, w) * 0.22
    disc = (rr - cy) ** 2 + (cc - cx) ** 2 <= r**2
    rect = (rr >= h * 0.2) & (rr < h * 0.6) & (cc >= w * 0.6) & (cc < w * (0.85 - 0.05 * variant))
    bar = (rr >= h * 0.8) & (rr < h * 0.8 + 2) & (cc >= w * 0.15) & (cc < w * 0.85)
    img = ramp.copy()
    img[disc] = 0.85
    img[rect] = 0.1
    img[bar] = 0.75
    img = np.clip(img + noise * rng.standard_normal(size), 0.05, 0.95)
    return img, {"disc": disc, "rect": rect, "bar": bar}


def standard_input(sort: type, variant: int = 0, size: tuple[int, int] = DEFAULT_SIZE) -> Sort:
    """A small deterministic instance of ``sort`` (``variant`` 0 or 1 differ)."""
    if sort not in _POOL:
        known = ", ".join(sorted(t.__name__ for t in _POOL))
        raise KeyError(f"standard_input: no pool builder for sort {sort.__name__}; known: {known}")
    return _POOL[sort](variant, size)


@register_pool(Image)
def _image(variant, size):
    return Image(jnp.asarray(standard_scene(variant, size)[0]))


@register_pool(Color)
def _color(variant, size):
    g, _ = standard_scene(variant, size)
    h, w = size
    cc = np.mgrid[0:h, 0:w][1] / max(w - 1, 1)
    rgb = np.stack([g, np.clip(0.6 * g + 0.3 * cc, 0, 1), np.clip(1.0 - g * 0.8, 0, 1)], axis=-1)
    return Color(jnp.asarray(rgb))


@register_pool(Region)
def _region(variant, size):
    _, m = standard_scene(variant, size)
    return Region(jnp.asarray(m["disc"] | m["bar"]))


@register_pool(Labels)
def _labels(variant, size):
    _, m = standard_scene(variant, size)
    lab = np.zeros(size, np.int32)
    lab[m["disc"]] = 1
    lab[m["rect"]] = 2
    lab[m["bar"]] = 3
    return Labels(jnp.asarray(lab), count=3)


@register_pool(Feature)
def _feature(variant, size):
    return Feature(jnp.asarray(0.25 + 0.5 * variant))


@register_pool(Signal)
def _signal(variant, size):
    w = size[1]
    g, _ = standard_scene(variant, size)
    return Signal(jnp.asarray(g[size[0] // 2, :w]))


# ---------------------------------------------------------------------------
# 3-D sorts. ``size`` is ignored: these inputs have fixed small sizes.
# ---------------------------------------------------------------------------


@register_pool(Points)
def _points(variant, size):
    """128 points on an ellipsoid (semi-axes 1.0, 0.7, 0.5) with 0.01 noise; two slots invalid."""
    rng = np.random.default_rng(100 + variant)
    n = 128
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    xyz = u * np.array([1.0, 0.7, 0.5]) * (1.0 + 0.2 * variant) + 0.01 * rng.normal(size=(n, 3))
    valid = np.ones(n, bool)
    valid[-2:] = False
    return Points(jnp.asarray(xyz), valid=jnp.asarray(valid))


def icosphere(subdivisions: int = 1, radius: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Vertices ``(V, 3)`` and outward-wound faces ``(F, 3)`` of a subdivided icosahedron."""
    t = (1.0 + 5.0 ** 0.5) / 2.0
    v = [(-1, t, 0), (1, t, 0), (-1, -t, 0), (1, -t, 0), (0, -1, t), (0, 1, t), (0, -1, -t), (0, 1, -t),
         (t, 0, -1), (t, 0, 1), (-t, 0, -1), (-t, 0, 1)]
    f = [(0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11), (1, 5, 9), (5, 11, 4), (11, 10, 2),
         (10, 7, 6), (7, 1, 8), (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8), (3, 8, 9), (4, 9, 5), (2, 4, 11),
         (6, 2, 10), (8, 6, 7), (9, 8, 1)]
    verts = [np.asarray(p, float) / np.linalg.norm(p) for p in v]
    faces = list(f)
    for _ in range(subdivisions):
        cache: dict[tuple[int, int], int] = {}

        def mid(a, b):
            key = (min(a, b), max(a, b))
            if key not in cache:
                m = verts[a] + verts[b]
                verts.append(m / np.linalg.norm(m))
                cache[key] = len(verts) - 1
            return cache[key]

        new = []
        for a, b, c in faces:
            ab, bc, ca = mid(a, b), mid(b, c), mid(c, a)
            new += [(a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca)]
        faces = new
    return np.asarray(verts) * radius, np.asarray(faces, dtype=np.int32)


@register_pool(Mesh)
def _mesh(variant, size):
    """An icosphere (42 vertices, 80 faces), radius 1 (variant 1: stretched along x by 1.3)."""
    v, f = icosphere(1)
    v = v * np.array([1.0 + 0.3 * variant, 1.0, 1.0])
    return Mesh(jnp.asarray(v), jnp.asarray(f))


@register_pool(Volume)
def _volume(variant, size):
    """A ``(6, 12, 16)`` smooth blob in [0.05, 0.95], spacing (2, 1, 1) mm."""
    z, y, x = np.mgrid[0:6, 0:12, 0:16].astype(float)
    c = (2.5, 5.5 + variant, 7.5 - variant)
    r2 = ((z - c[0]) * 2.0) ** 2 + (y - c[1]) ** 2 + (x - c[2]) ** 2
    return Volume(jnp.asarray(0.05 + 0.9 * np.exp(-r2 / 18.0)), spacing=(2.0, 1.0, 1.0))


@register_pool(Camera)
def _camera(variant, size):
    """A 32 x 24 pinhole camera at (0, 0, -4) looking along +z (world_from_camera: R = I)."""
    f = 40.0 + 10.0 * variant
    return Camera.from_intrinsics(f, f, 15.5, 11.5, width=32, height=24, t=jnp.asarray([0.0, 0.0, -4.0]))


@register_pool(Depth)
def _depth(variant, size):
    """A tilted plane seen by the standard camera: z = 4 + 0.02 col + 0.01 row (+0.5 for variant 1)."""
    cam = _camera(variant, size)
    r, c = np.mgrid[0:24, 0:32].astype(float)
    return Depth(jnp.asarray(4.0 + 0.02 * c + 0.01 * r + 0.5 * variant), cam)
