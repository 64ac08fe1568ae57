"""Surface-defect scene: scratches, dents and a foreign particle on brushed metal.

The scene is the sum of four independent layers, so every defect's footprint
and contrast is known exactly:

    I = L(r, c) + T(r, c) + sum_k D_k(r, c) + n(r, c)

* ``L``: illumination, a tilted plane plus a broad hot spot (grey values
  0.28 .. 0.62 across the image): far larger than any defect's contrast,
  so a global threshold cannot separate defects from background.
* ``T``: brushed-metal texture, white noise filtered by an anisotropic
  Gaussian transfer function (long along the brushing direction, short across
  it; periodic, computed by FFT), scaled to standard deviation ``texture``.
* ``D_k``: the defects, additive (their contrast does not depend on ``L``):

  - ``"scratch"``: a thin dark groove along a quadratic Bezier curve (straight
    or slightly bent), cross-section ``depth * exp(-d^2 / (2 w^2))`` with ``d``
    the distance to the curve (rounded ends);
  - ``"dent"``: a soft dark elliptical Gaussian ``depth * exp(-q / 2)``,
    ``q`` the Mahalanobis distance for axes ``sigma_major, sigma_minor`` (roundish,
    low contrast, large);
  - ``"particle"``: a small bright compact blob, a disc of radius ``R`` with a
    one-pixel linear edge ramp, ``height * clip(R + 1/2 - d, 0, 1)``.
* ``n``: white sensor noise of standard deviation ``noise``.

Each defect's ground-truth *footprint* (``Defect.mask``) is the set of pixels
where it changes the grey value by at least a quarter of its peak change,
``|D_k| >= |peak_k| / 4``. Positions are ``(row, col)`` in pixels, pixel
centres on integer indices. Defects are placed by a seeded generator with a
clearance between their bounding circles, so footprints never touch; the
result is deterministic for a given seed. Only numpy is used.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

__all__ = ["Defect", "DEFECT_KINDS", "surface_defects"]

DEFECT_KINDS = ("scratch", "dent", "particle")


@dataclasses.dataclass(frozen=True)
class Defect:
    """One ground-truth defect.

    Attributes:
      kind: ``"scratch"``, ``"dent"`` or ``"particle"``.
      centre: ``(row, col)`` of the defect's centre (curve midpoint, blob centre).
      mask: ``(H, W)`` bool footprint, ``|D| >= |peak| / 4``.
      contrast: signed peak grey-value change (negative = dark).
      params: the drawing parameters (lengths and widths in pixels, angles in degrees).
    """

    kind: str
    centre: tuple[float, float]
    mask: np.ndarray
    contrast: float
    params: dict


def _brushed_texture(size, rng, sigma_along: float, sigma_across: float, angle_deg: float, std: float):
    """Periodic anisotropic Gaussian-filtered white noise with standard deviation ``std``."""
    h, w = size
    white = rng.standard_normal(size)
    fr = np.fft.fftfreq(h)[:, None]
    fc = np.fft.rfftfreq(w)[None, :]
    a = math.radians(angle_deg)
    # brushing direction (row, col) = (-sin a, cos a): the angle is counter-clockwise on screen
    f_along = -fr * math.sin(a) + fc * math.cos(a)
    f_across = fr * math.cos(a) + fc * math.sin(a)
    tf = np.exp(-2 * math.pi**2 * (sigma_along**2 * f_along**2 + sigma_across**2 * f_across**2))
    t = np.fft.irfft2(np.fft.rfft2(white) * tf, s=size)
    t -= t.mean()
    return t * (std / t.std())


def _illumination(size, lo: float, hi: float):
    h, w = size
    rr, cc = np.mgrid[0:h, 0:w].astype(float)
    u, v = rr / (h - 1), cc / (w - 1)
    plane = 0.65 * v + 0.35 * u
    spot = np.exp(-((u - 0.3) ** 2 + (v - 0.7) ** 2) / (2 * 0.25**2))
    f = plane + 0.5 * spot
    f = (f - f.min()) / (f.max() - f.min())
    return lo + (hi - lo) * f


def _bezier(p0, p1, p2, n: int):
    t = np.linspace(0.0, 1.0, n)[:, None]
    return (1 - t) ** 2 * p0 + 2 * (1 - t) * t * p1 + t**2 * p2


def _dist_to_polyline(rr, cc, pts, reach: float):
    """Distance from each pixel centre to a polyline, exact within ``reach`` px (``inf`` beyond).

    Each segment updates the running minimum inside its own bounding box grown
    by ``reach``; ``rr, cc`` are the (integer-spaced) pixel-centre grids.
    """
    d2 = np.full(rr.shape, np.inf)
    r_lo, c_lo = rr[0, 0], cc[0, 0]
    for a, b in zip(pts[:-1], pts[1:], strict=True):
        i0 = max(0, int(math.floor(min(a[0], b[0]) - reach - r_lo)))
        i1 = min(rr.shape[0], int(math.ceil(max(a[0], b[0]) + reach - r_lo)) + 1)
        j0 = max(0, int(math.floor(min(a[1], b[1]) - reach - c_lo)))
        j1 = min(rr.shape[1], int(math.ceil(max(a[1], b[1]) + reach - c_lo)) + 1)
        pr, pc = rr[i0:i1, j0:j1] - a[0], cc[i0:i1, j0:j1] - a[1]
        ab = b - a
        t = np.clip((pr * ab[0] + pc * ab[1]) / float(ab @ ab), 0.0, 1.0)
        e2 = (pr - t * ab[0]) ** 2 + (pc - t * ab[1]) ** 2
        np.minimum(d2[i0:i1, j0:j1], e2, out=d2[i0:i1, j0:j1])
    return np.sqrt(d2)


def _scratch(size, centre, length, angle_deg, bend, width, depth):
    """Scratch layer: a Gaussian groove along a quadratic Bezier curve (window-limited)."""
    a = math.radians(angle_deg)
    d = np.array([-math.sin(a), math.cos(a)])  # direction (row, col), counter-clockwise on screen
    nrm = np.array([d[1], -d[0]])
    c = np.asarray(centre, float)
    p0, p2 = c - 0.5 * length * d, c + 0.5 * length * d
    # control point so that the curve's midpoint sits at ``centre + bend * length * nrm``
    p1 = c + 2.0 * bend * length * nrm
    pts = _bezier(p0, p1, p2, max(64, int(2 * length)))
    mid = _bezier(p0, p1, p2, 3)[1]
    h, w = size
    pad = int(math.ceil(5 * width)) + 2
    r0 = max(0, int(math.floor(pts[:, 0].min())) - pad)
    r1 = min(h, int(math.ceil(pts[:, 0].max())) + pad + 1)
    c0 = max(0, int(math.floor(pts[:, 1].min())) - pad)
    c1 = min(w, int(math.ceil(pts[:, 1].max())) + pad + 1)
    rr, cc = np.mgrid[r0:r1, c0:c1].astype(float)
    dist = _dist_to_polyline(rr, cc, pts, reach=float(pad))
    layer = np.zeros(size)
    layer[r0:r1, c0:c1] = depth * np.exp(-(dist**2) / (2 * width**2))
    return layer, (float(mid[0]), float(mid[1]))


def _dent(size, centre, s_major, s_minor, angle_deg, depth):
    h, w = size
    rr, cc = np.mgrid[0:h, 0:w].astype(float)
    a = math.radians(angle_deg)
    dr, dc = rr - centre[0], cc - centre[1]
    along = -dr * math.sin(a) + dc * math.cos(a)
    across = dr * math.cos(a) + dc * math.sin(a)
    q = (along / s_major) ** 2 + (across / s_minor) ** 2
    return depth * np.exp(-0.5 * q)


def _particle(size, centre, radius, height):
    h, w = size
    rr, cc = np.mgrid[0:h, 0:w].astype(float)
    d = np.hypot(rr - centre[0], cc - centre[1])
    return height * np.clip(radius + 0.5 - d, 0.0, 1.0)


def surface_defects(
    size: tuple[int, int] = (512, 512),
    *,
    seed: int = 0,
    texture: float = 0.012,
    noise: float = 0.004,
    illumination: tuple[float, float] = (0.28, 0.62),
    brushing_deg: float = 8.0,
    n_scratches: int = 3,
    n_dents: int = 2,
    n_particles: int = 1,
    margin: int = 24,
    clearance: float = 16.0,
):
    """Brushed-metal surface with scratches, dents and foreign particles (exact footprints).

    Args:
      size: ``(H, W)`` in pixels (default 512 x 512).
      seed: seed of the texture, noise and defect placement.
      texture: standard deviation of the brushed texture (grey values).
      noise: standard deviation of the white sensor noise.
      illumination: darkest and brightest value of the illumination layer.
      brushing_deg: brushing direction, counter-clockwise from the column axis.
      n_scratches, n_dents, n_particles: how many of each defect.
      margin: smallest distance of a defect's bounding circle from the border (px).
      clearance: smallest gap between two defects' bounding circles (px).

    Returns:
      ``(image, defects)``: a float64 ``(H, W)`` array in ``[0, 1]`` and a list of
      :class:`Defect` records (scratches first, then dents, then particles).

    Defect parameters drawn per defect: scratches of length 70..150 px, angles
    spread over 180 degrees (no two within 30 degrees), bend up to 6 % of the
    length, Gaussian half-width ``w`` 0.8..1.1 px, depth -0.13..-0.10; dents with
    ``sigma`` 7..9 px (axis ratio <= 1.25), depth -0.08..-0.07; particles of radius
    2.5..3.2 px and height +0.25..+0.30.
    """
    h, w = size
    rng = np.random.default_rng(seed)
    specs = []
    base = rng.uniform(0, 180)
    for i in range(n_scratches):
        ang = (base + i * 180.0 / max(n_scratches, 1) + rng.uniform(-15, 15)) % 180.0
        specs.append(dict(kind="scratch", length=rng.uniform(70, 150), angle_deg=ang,
                          bend=rng.uniform(-0.06, 0.06), width=rng.uniform(0.8, 1.1),
                          depth=-rng.uniform(0.10, 0.13)))
    for _ in range(n_dents):
        s_minor = rng.uniform(7, 8)
        specs.append(dict(kind="dent", s_major=s_minor * rng.uniform(1.0, 1.25), s_minor=s_minor,
                          angle_deg=rng.uniform(0, 180), depth=-rng.uniform(0.07, 0.08)))
    for _ in range(n_particles):
        specs.append(dict(kind="particle", radius=rng.uniform(2.5, 3.2), height=rng.uniform(0.25, 0.30)))

    def extent(s):
        if s["kind"] == "scratch":
            return 0.5 * s["length"] * (1 + 2 * abs(s["bend"])) + 4 * s["width"]
        if s["kind"] == "dent":
            return 3.0 * s["s_major"]
        return s["radius"] + 2.0

    placed: list[tuple[float, float, float]] = []
    for s in specs:
        ext = extent(s)
        if min(h, w) - 2 * (margin + ext) <= 0:
            raise ValueError(f"surface_defects: cannot place a {s['kind']} of extent {ext:.0f} px in {size} "
                             f"(margin {margin}); use a larger size")
        for _ in range(10_000):
            y, x = rng.uniform(margin + ext, h - margin - ext), rng.uniform(margin + ext, w - margin - ext)
            if all(math.hypot(y - y2, x - x2) >= ext + e2 + clearance for y2, x2, e2 in placed):
                break
        else:
            raise ValueError(f"surface_defects: cannot place {len(specs)} defects in {size} "
                             f"(margin {margin}, clearance {clearance}); use a larger size")
        placed.append((y, x, ext))
        s["centre"] = (float(y), float(x))

    image = _illumination(size, *illumination)
    image = image + _brushed_texture(size, rng, sigma_along=14.0, sigma_across=0.7,
                                     angle_deg=brushing_deg, std=texture)
    defects = []
    for s in specs:
        kind = s.pop("kind")
        if kind == "scratch":
            layer, centre = _scratch(size, s["centre"], s["length"], s["angle_deg"], s["bend"],
                                     s["width"], s["depth"])
            peak = s["depth"]
        elif kind == "dent":
            layer = _dent(size, s["centre"], s["s_major"], s["s_minor"], s["angle_deg"], s["depth"])
            centre, peak = s["centre"], s["depth"]
        else:
            layer = _particle(size, s["centre"], s["radius"], s["height"])
            centre, peak = s["centre"], s["height"]
        image = image + layer
        mask = np.abs(layer) >= 0.25 * abs(peak)
        params = {k: float(v) for k, v in s.items() if k != "centre"}
        defects.append(Defect(kind=kind, centre=(float(centre[0]), float(centre[1])), mask=mask,
                              contrast=float(peak), params=params))
    image = image + noise * rng.standard_normal(size)
    if image.min() < 0 or image.max() > 1:
        raise ValueError("surface_defects: grey values left [0, 1]; lower the contrasts")
    return image, defects
