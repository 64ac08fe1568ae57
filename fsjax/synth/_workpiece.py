"""Alignment scene: rotated copies of a workpiece and decoy parts, with exact poses.

The workpiece is an L-shaped plate with a round hole and a rectangular notch,
asymmetric so that its angle is unique (no rotation or mirror symmetry). It is
defined in *model coordinates* ``(u, v)`` (row, col offsets in pixels from its
reference point, the centre of its bounding box):

* vertical arm ``-20 <= u <= 20``, ``-28 <= v <= -8``; bottom arm
  ``4 <= u <= 20``, ``-28 <= v <= 28``;
* hole: disc of radius 5 centred at ``(-8, -18)``;
* notch: ``14 <= u <= 20``, ``10 <= v <= 16`` cut from the bottom edge.

A part placed at ``(row, col)`` with ``angle_deg`` (counter-clockwise on
screen, :class:`fsjax.Match` convention) covers the image points
``(row, col) + (u cos a - v sin a, u sin a + v cos a)``. Rendering is
anti-aliased by exact-grid supersampling (``ss x ss`` samples per pixel, the
pixel value is the covered fraction), so an edge sits where the geometry says
to about ``1 / (2 ss)`` px per pixel.

Decoys (similar size, different shape): a plain ``28 x 48`` rectangle, and the
workpiece without its notch mirrored left-right (its hole and long arm on the
other side: not reachable by a rotation).
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage as ndi

__all__ = ["workpiece_template", "alignment_scene", "render_part", "PART_KINDS"]

PART_KINDS = ("workpiece", "rectangle", "mirrored_no_notch")

# model geometry (pixels)
_ARM_V = (-20.0, 20.0, -28.0, -8.0)  # u0, u1, v0, v1
_ARM_H = (4.0, 20.0, -28.0, 28.0)
_HOLE = (-8.0, -18.0, 5.0)  # u, v, radius
_NOTCH = (14.0, 20.0, 10.0, 16.0)
_RECT = (-14.0, 14.0, -24.0, 24.0)
RADIUS = float(np.hypot(20.0, 28.0))  # bounding radius of every part


def _in_box(u, v, box):
    u0, u1, v0, v1 = box
    return (u >= u0) & (u <= u1) & (v >= v0) & (v <= v1)


def _inside(kind: str, u, v):
    """Membership in model coordinates for each part kind."""
    if kind == "rectangle":
        return _in_box(u, v, _RECT)
    if kind == "mirrored_no_notch":
        v = -v
    plate = _in_box(u, v, _ARM_V) | _in_box(u, v, _ARM_H)
    hole = (u - _HOLE[0]) ** 2 + (v - _HOLE[1]) ** 2 <= _HOLE[2] ** 2
    part = plate & ~hole
    if kind == "workpiece":
        part = part & ~_in_box(u, v, _NOTCH)
    return part


def render_part(shape: tuple[int, int], row: float, col: float, angle_deg: float, kind: str = "workpiece",
                ss: int = 16, cut_v: float | None = None) -> np.ndarray:
    """Covered fraction ``(H, W)`` of a part at pose ``(row, col, angle_deg)``, anti-aliased.

    ``cut_v`` keeps only the part with model ``v < cut_v`` (used to occlude the
    right-hand side of an instance).
    """
    if kind not in PART_KINDS:
        raise ValueError(f"render_part: kind must be one of {PART_KINDS}, got {kind!r}")
    H, W = shape
    out = np.zeros(shape)
    r0, r1 = max(0, int(np.floor(row - RADIUS - 2))), min(H, int(np.ceil(row + RADIUS + 3)))
    c0, c1 = max(0, int(np.floor(col - RADIUS - 2))), min(W, int(np.ceil(col + RADIUS + 3)))
    if r0 >= r1 or c0 >= c1:
        return out
    sub = (np.arange(ss) + 0.5) / ss - 0.5  # sample offsets inside a pixel
    ys = (np.arange(r0, r1)[:, None] + sub[None, :]).reshape(-1)
    xs = (np.arange(c0, c1)[:, None] + sub[None, :]).reshape(-1)
    dy = ys[:, None] - row
    dx = xs[None, :] - col
    a = np.deg2rad(angle_deg)
    ca, sa = np.cos(a), np.sin(a)
    # inverse of (u, v) -> (u cos a - v sin a, u sin a + v cos a)
    u = dy * ca + dx * sa
    v = -dy * sa + dx * ca
    inside = _inside(kind, u, v)
    if cut_v is not None:
        inside = inside & (v < cut_v)
    cov = inside.reshape(r1 - r0, ss, c1 - c0, ss).mean(axis=(1, 3))
    out[r0:r1, c0:c1] = cov
    return out


def workpiece_template(shape: tuple[int, int] = (56, 72), *, background: float = 0.3,
                       foreground: float = 0.8, ss: int = 16) -> np.ndarray:
    """The model image: the workpiece at angle 0 with its reference point at the image
    centre ``((h - 1) / 2, (w - 1) / 2)``, on a plain background, no noise (float64)."""
    h, w = shape
    cov = render_part(shape, (h - 1) / 2, (w - 1) / 2, 0.0, "workpiece", ss=ss)
    return background + (foreground - background) * cov


# instances: (row, col, angle_deg); decoys: (row, col, angle_deg, kind)
_INSTANCES = ((58.37, 62.81, 13.7), (62.12, 252.55, -41.3), (176.64, 66.29, 97.2))
_DECOYS = ((178.3, 252.7, 25.0, "rectangle"), (118.2, 158.4, -60.0, "mirrored_no_notch"))


def alignment_scene(seed: int = 0, *, shape: tuple[int, int] = (240, 320), noise: float = 0.01,
                    occlusion: float = 0.0, ss: int = 16):
    """Deterministic alignment scene and its ground truth.

    Three workpieces at angles off any regular search grid (13.7, -41.3 and
    97.2 deg) at sub-pixel positions, and two decoys (a plain rectangle at
    (178.3, 252.7), and the notch-less workpiece mirrored at (118.2, 158.4)), on
    a textured background (low-pass noise) under a multiplicative
    illumination gradient (0.6 at the left to 1.1 at the right), with parts of
    different reflectance (0.8, 0.7, 0.85, decoys 0.8) and Gaussian pixel
    noise of standard deviation ``noise``.

    ``occlusion`` in [0, 1) hides that fraction of the first instance's model
    width (its ``v >= 28 - 56 * occlusion`` side) under a background-coloured
    cover; the covered fraction of its area is returned.

    Returns ``(image, truth)``: ``image`` float64 ``(H, W)`` in [0, 1];
    ``truth`` a dict with ``"poses"`` (list of ``(row, col, angle_deg)`` of the
    three instances), ``"decoys"`` (list of ``(row, col, angle_deg, kind)``) and
    ``"occluded_area"`` (fraction of instance 0's area hidden).
    """
    if not 0.0 <= occlusion < 1.0:
        raise ValueError(f"alignment_scene: occlusion must be in [0, 1), got {occlusion}")
    H, W = shape
    rng = np.random.default_rng(seed)
    tex = ndi.gaussian_filter(rng.standard_normal(shape), 3.0)
    tex = 0.04 * tex / tex.std()
    refl = 0.35 + tex
    levels = (0.8, 0.7, 0.85)
    occ_area = 0.0
    for k, (r, c, a) in enumerate(_INSTANCES):
        cut = None
        if k == 0 and occlusion > 0:
            cut = 28.0 - 56.0 * occlusion
            full = render_part(shape, r, c, a, "workpiece", ss=ss).sum()
            cov = render_part(shape, r, c, a, "workpiece", ss=ss, cut_v=cut)
            occ_area = float(1.0 - cov.sum() / full)
        else:
            cov = render_part(shape, r, c, a, "workpiece", ss=ss)
        refl = refl * (1 - cov) + (levels[k] + 0.5 * tex) * cov
    for r, c, a, kind in _DECOYS:
        cov = render_part(shape, r, c, a, kind, ss=ss)
        refl = refl * (1 - cov) + (0.8 + 0.5 * tex) * cov
    cc = np.arange(W)[None, :] / (W - 1)
    illum = np.broadcast_to(0.6 + 0.5 * cc, shape)
    img = refl * illum + noise * rng.standard_normal(shape)
    img = np.clip(img, 0.0, 1.0)
    truth = {"poses": [tuple(p) for p in _INSTANCES], "decoys": [tuple(d) for d in _DECOYS],
             "occluded_area": occ_area}
    return img, truth
