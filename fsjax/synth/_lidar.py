"""A LiDAR-style ground-truth scene: four objects on a sloped ground.

The scene: a square ground patch tilted by ``slope_deg`` about the ``y``
axis (``z = tan(slope) x``, ``+z`` up) carrying a sphere, a box, a vertical
cylinder and a cone, each resting on the ground. Surfaces are sampled
uniformly by area (ground on a jittered grid, so it has no holes; objects
with a higher density, as a nearby scanner sees them), only where they are
above the ground (the hidden bottoms are not sampled), then Gaussian noise
is added. Deterministic in ``seed``.

Ground truth (``info``): ``labels`` ``(N,)`` (0 ground, 1 sphere, 2 box,
3 cylinder, 4 cone), ``centroids`` ``(4, 3)`` (mean of each object's
noise-free samples), ``names``, ``ground_normal`` and ``slope_deg``.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from ..types import Points

__all__ = ["lidar_scene", "LIDAR_OBJECTS"]

LIDAR_OBJECTS = ("sphere", "box", "cylinder", "cone")


def _area_n(area, density, rng):
    return max(1, int(rng.poisson(area * density)))


def lidar_scene(seed: int = 0, *, extent: float = 5.0, slope_deg: float = 5.0, ground_spacing: float = 0.15,
                object_density: float = 150.0, noise: float = 0.01):
    """Points of the scene and its ground truth: ``(Points, info)`` (see the module docstring).

    Args:
      seed: random seed (deterministic).
      extent: the ground covers ``[-extent, extent]^2`` in ``x, y`` (metres).
      slope_deg: ground slope about the ``y`` axis.
      ground_spacing: jittered-grid spacing of the ground samples.
      object_density: object samples per square metre.
      noise: standard deviation of the Gaussian noise on every coordinate.
    """
    rng = np.random.default_rng(seed)
    t = np.tan(np.radians(slope_deg))

    def gz(x):
        return t * x

    # ground: jittered grid
    g = np.arange(-extent, extent + 1e-9, ground_spacing)
    gx, gy = np.meshgrid(g, g)
    gx = gx.ravel() + rng.uniform(-0.3, 0.3, gx.size) * ground_spacing
    gy = gy.ravel() + rng.uniform(-0.3, 0.3, gy.size) * ground_spacing
    parts = [np.c_[gx, gy, gz(gx)]]
    labels = [np.zeros(gx.size, np.int32)]
    d = object_density
    centres = {"sphere": (-2.5, -2.5), "box": (2.5, -2.5), "cylinder": (-2.5, 2.5), "cone": (2.5, 2.5)}
    objs = {}
    # sphere, radius 0.6, touching the ground at its lowest point (approximately, slope 5 deg)
    cx, cy = centres["sphere"]
    r = 0.6
    u = rng.normal(size=(_area_n(4 * np.pi * r * r, d, rng), 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    objs["sphere"] = np.array([cx, cy, gz(cx) + r / np.cos(np.radians(slope_deg))]) + r * u
    # box 1.2 x 0.8, height 1.0 above the ground at its centre (sides extend down to the ground)
    cx, cy = centres["box"]
    a, b, h = 0.6, 0.4, 1.0
    top = gz(cx) + h
    pts = []
    n_top = _area_n(4 * a * b, d, rng)
    pts.append(np.c_[cx + rng.uniform(-a, a, n_top), cy + rng.uniform(-b, b, n_top), np.full(n_top, top)])
    for axis, half, other in ((0, a, b), (1, b, a)):
        for sgn in (-1, 1):
            n_s = _area_n(2 * other * (h + 0.2), d, rng)
            s = rng.uniform(-other, other, n_s)
            z = rng.uniform(top - h - 0.2, top, n_s)
            if axis == 0:
                pts.append(np.c_[np.full(n_s, cx + sgn * half), cy + s, z])
            else:
                pts.append(np.c_[cx + s, np.full(n_s, cy + sgn * half), z])
    objs["box"] = np.concatenate(pts)
    # vertical cylinder, radius 0.4, height 1.4, with its top cap
    cx, cy = centres["cylinder"]
    r, h = 0.4, 1.4
    top = gz(cx) + h
    n_s = _area_n(2 * np.pi * r * (h + 0.1), d, rng)
    th = rng.uniform(0, 2 * np.pi, n_s)
    side = np.c_[cx + r * np.cos(th), cy + r * np.sin(th), rng.uniform(top - h - 0.1, top, n_s)]
    n_t = _area_n(np.pi * r * r, d, rng)
    rr, th = r * np.sqrt(rng.uniform(0, 1, n_t)), rng.uniform(0, 2 * np.pi, n_t)
    objs["cylinder"] = np.r_[side, np.c_[cx + rr * np.cos(th), cy + rr * np.sin(th), np.full(n_t, top)]]
    # cone, base radius 0.7, height 1.3 (lateral surface, uniform by area)
    cx, cy = centres["cone"]
    r, h = 0.7, 1.3
    base = gz(cx) - 0.1
    hh = h + 0.1
    n_c = _area_n(np.pi * r * np.hypot(r, hh), d, rng)
    s = np.sqrt(rng.uniform(0, 1, n_c))  # fraction of the slant from the apex, area-uniform
    th = rng.uniform(0, 2 * np.pi, n_c)
    objs["cone"] = np.c_[cx + s * r * np.cos(th), cy + s * r * np.sin(th), base + hh * (1 - s)]
    centroids = []
    for i, name in enumerate(LIDAR_OBJECTS, start=1):
        p = objs[name]
        p = p[p[:, 2] > gz(p[:, 0])]  # only what is above the ground exists
        parts.append(p)
        labels.append(np.full(len(p), i, np.int32))
        centroids.append(p.mean(0))
    xyz = np.concatenate(parts)
    lab = np.concatenate(labels)
    xyz = xyz + noise * rng.normal(size=xyz.shape)
    nrm = np.array([-t, 0.0, 1.0]) / np.hypot(t, 1.0)
    info = {"labels": lab, "centroids": np.asarray(centroids), "names": LIDAR_OBJECTS, "ground_normal": nrm,
            "slope_deg": float(slope_deg)}
    return Points(jnp.asarray(xyz)), info
