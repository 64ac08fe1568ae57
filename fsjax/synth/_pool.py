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

from ..types import Color, Feature, Image, Labels, Region, Signal, Sort

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
