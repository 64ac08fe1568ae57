"""Standard inputs: one small deterministic instance per sort (two variants).

The standard scene is a ``(H, W)`` grey image in ``[0.05, 0.95]``: a bright
disc, a dark rectangle and a thin bright bar on a linear ramp, with mild
deterministic noise. Its ground truth (object masks, areas) is returned by
:func:`standard_scene` for tests that need it.
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from ..types import (
    HSV,
    Camera,
    Color,
    Contour,
    Depth,
    DepthStack,
    Feature,
    FringeStack,
    Gaussians,
    GrayStack,
    Image,
    Lab,
    Labels,
    LabelVolume,
    LightStack,
    Mesh,
    MeshTopology,
    NormalMap,
    PointLabels,
    Points,
    PointValues,
    Region,
    RegionProps,
    Signal,
    Sort,
    StructuredLightRig,
    Volume,
)

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


@register_pool(HSV)
def _hsv(variant, size):
    """The colour pool converted by ``fsjax.ops.rgb_to_hsv``."""
    from ..ops import rgb_to_hsv

    return rgb_to_hsv(standard_input(Color, variant, size))


@register_pool(Lab)
def _lab(variant, size):
    """The colour pool converted by ``fsjax.ops.rgb_to_lab``."""
    from ..ops import rgb_to_lab

    return rgb_to_lab(standard_input(Color, variant, size))


@register_pool(Contour)
def _contour_pool(variant, size):
    """A closed, ordered polyline on an ellipse (about 1 px spacing) plus 4 unused slots."""
    h, w = size
    n = 40
    t = np.arange(n) * 2 * np.pi / n
    a, b = 0.3 * min(h, w), 0.2 * min(h, w)
    ang = 0.35 + 0.5 * variant
    rng = np.random.default_rng(77 + variant)
    u, v = a * np.cos(t), b * np.sin(t)
    col = w / 2 + 0.4 * variant + u * np.cos(ang) - v * np.sin(ang)
    row = h / 2 - u * np.sin(ang) - v * np.cos(ang)
    pts = np.stack([row, col], -1) + 0.05 * rng.standard_normal((n, 2))
    pts = np.concatenate([pts, np.zeros((4, 2))])
    valid = np.arange(n + 4) < n
    return Contour(jnp.asarray(pts), jnp.asarray(valid), closed=True)


@register_pool(RegionProps)
def _region_props(variant, size):
    """``fsjax.ops.region_props`` of the label pool over the image pool (capacity 4)."""
    from ..ops import region_props

    return region_props(standard_input(Labels, variant, size), standard_input(Image, variant, size), capacity=4)


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

        def mid(a, b, cache=cache):
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


@register_pool(MeshTopology)
def _mesh_topology(variant, size):
    """The counts of an icosphere (variant 1: with one face dropped, three boundary edges)."""
    if variant == 0:
        return MeshTopology(42, 80, 120, 0, 0, 0, 1, 2)
    return MeshTopology(42, 79, 120, 3, 0, 0, 1, 1)


@register_pool(Volume)
def _volume(variant, size):
    """A ``(6, 12, 16)`` smooth blob in [0.05, 0.95], spacing (2, 1, 1) mm."""
    z, y, x = np.mgrid[0:6, 0:12, 0:16].astype(float)
    c = (2.5, 5.5 + variant, 7.5 - variant)
    r2 = ((z - c[0]) * 2.0) ** 2 + (y - c[1]) ** 2 + (x - c[2]) ** 2
    return Volume(jnp.asarray(0.05 + 0.9 * np.exp(-r2 / 18.0)), spacing=(2.0, 1.0, 1.0))


@register_pool(LabelVolume)
def _label_volume(variant, size):
    """Two boxes labelled 1 and 2 in a ``(6, 12, 16)`` volume, spacing (2, 1, 1) mm."""
    lab = np.zeros((6, 12, 16), np.int32)
    lab[1:4, 2:6, 2 + variant:7] = 1
    lab[2:6, 7:11, 9:15 - variant] = 2
    return LabelVolume(jnp.asarray(lab), count=2, spacing=(2.0, 1.0, 1.0))


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


@register_pool(DepthStack)
def _depth_stack(variant, size):
    """Two views of the standard depth input's plane: the standard camera and one shifted 0.3 along x."""
    d = _depth(variant, size)
    cam2 = Camera(d.camera.K, width=d.camera.width, height=d.camera.height, dist=d.camera.dist, R=d.camera.R,
                  t=d.camera.t + jnp.asarray([0.3, 0.0, 0.0], d.camera.t.dtype))
    cams = jax.tree.map(lambda *a: jnp.stack(a), d.camera, cam2)
    return DepthStack(jnp.stack([d.z, d.z]), cams)



# ---------------------------------------------------------------------------
# Sorts of the 3-D measurement families (photometric stereo, structured light)
# and per-point results of the point-cloud families.
# ---------------------------------------------------------------------------


def _sphere_cap(h, w, variant):
    """Analytic normals/albedo of a sphere cap filling the frame (for the pool)."""
    r, c = np.mgrid[0:h, 0:w].astype(float)
    x = (c - (w - 1) / 2 - variant) / (0.9 * w)
    y = (r - (h - 1) / 2) / (0.9 * w)
    z = np.sqrt(np.maximum(1.0 - x * x - y * y, 0.0))
    n = np.stack([x, y, -z], -1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    alb = 0.5 + 0.3 * (c / w) + 0.1 * variant
    return n, alb


@register_pool(LightStack)
def _pool_lightstack(variant, size):
    """A Lambertian sphere cap (albedo ramp) under 6 lights at 50-70 deg elevation (no shadows)."""
    from ..ops import light_directions

    h, w = size
    n, alb = _sphere_cap(h, w, variant)
    L = light_directions([50, 60, 70, 50, 60, 70], [0, 60, 120, 180, 240, 300 + 10 * variant])
    data = alb[None] * np.maximum(np.einsum("hwc,kc->khw", n, L), 0.0)
    return LightStack(jnp.asarray(data), jnp.asarray(L))


@register_pool(NormalMap)
def _pool_normalmap(variant, size):
    """Normals and albedo of the pool's sphere cap (all valid)."""
    n, alb = _sphere_cap(*size, variant)
    return NormalMap(jnp.asarray(n), jnp.asarray(alb))


def _fringe_pool(variant, size):
    h, w = size
    r, c = np.mgrid[0:h, 0:w].astype(float)
    phi = 0.3 * c + 0.1 * r + 0.2 * variant - 3.0
    n = 4
    k = np.arange(n)[:, None, None]
    return 0.5 + 0.4 * np.cos(phi[None] - 2 * np.pi * k / n)


@register_pool(FringeStack)
def _pool_fringe(variant, size):
    """4-step fringes of a phase ramp ``0.3 col + 0.1 row - 3``, contrast 0.4."""
    return FringeStack(jnp.asarray(_fringe_pool(variant, size)))


@register_pool(GrayStack)
def _pool_gray(variant, size):
    """4-bit complementary Gray code of stripes 2 columns wide."""
    from ..ops import gray_frames

    h, w = size
    c = np.broadcast_to(np.arange(w), (h, w))
    return GrayStack(jnp.asarray(gray_frames((c + variant) // 2 % 16, 4)))


@register_pool(StructuredLightRig)
def _pool_rig(variant, size):
    """Camera of the raster ``size`` (32 x 24 at the default size; focal length 40 px scaled by
    width / 32, so the field of view stays; principal point at the centre) at the origin looking
    +z; 64-column projector 100 mm to the right, aimed at z = 500 mm. The camera takes ``size``
    so a column map of that size fits it (``triangulate_column`` in the chain fuzzer)."""
    from ..render.camera import look_at

    h, w = size
    f = 40.0 * w / 32.0
    cam = Camera.from_intrinsics(f, f, (w - 1) / 2.0, (h - 1) / 2.0, width=w, height=h)
    R, t = look_at([100.0 + 10.0 * variant, 0.0, 0.0], [0.0, 0.0, 500.0], up=[0.0, -1.0, 0.0])
    proj = Camera.from_intrinsics(80.0, 80.0, 31.5, 23.5, width=64, height=48, R=R, t=t)
    return StructuredLightRig(cam, proj)


@register_pool(Gaussians)
def _gaussians(variant, size):
    """12 anisotropic Gaussians inside the default 16^3 voxel grid: means in [3, 12], scales
    0.25-0.8, random rotations, opacities 0.3-0.9 (variant 1: another draw); the last slot invalid."""
    rng = np.random.default_rng(300 + variant)
    n = 12
    q = rng.normal(size=(n, 4))
    valid = np.ones(n, bool)
    valid[-1] = False
    return Gaussians(jnp.asarray(rng.uniform(3.0, 12.0, (n, 3))), jnp.asarray(np.log(rng.uniform(0.25, 0.8, (n, 3)))),
                     jnp.asarray(q / np.linalg.norm(q, axis=1, keepdims=True)),
                     jnp.asarray(np.log(1 / rng.uniform(0.3, 0.9, n) - 1) * -1.0), jnp.asarray(rng.uniform(0, 1, (n, 1, 3))),
                     valid=jnp.asarray(valid))


@register_pool(PointValues)
def _point_values(variant, size):
    """Two columns over 16 points (variant 1 shifted); the last slot invalid."""
    v = np.stack([np.linspace(0.0, 1.0, 16), np.linspace(1.0, 2.0, 16) ** 2], -1) + 0.5 * variant
    valid = np.ones(16, bool)
    valid[-1] = False
    return PointValues(jnp.asarray(v), ("a", "b"), jnp.asarray(valid))


@register_pool(PointLabels)
def _point_labels(variant, size):
    """Three clusters over 24 points (variant 1: relabelled), last slot invalid."""
    lab = np.repeat(np.arange(1, 4, dtype=np.int32), 8)
    if variant:
        lab = lab[::-1].copy()
    valid = np.ones(24, bool)
    valid[-1] = False
    lab[-1] = 0
    return PointLabels(jnp.asarray(lab), jnp.asarray(valid), count=3)
