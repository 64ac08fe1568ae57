"""Particle-counting scene: discs of random size and brightness, some pairs touching.

``n_particles`` discs of radius ``radius[0] .. radius[1]`` px; ``n_pairs`` pairs
of them *touch*: their centres are ``r1 + r2 - overlap`` apart, so the two
discs overlap by ``overlap`` px along the line of centres and merge into one
blob in a plain labelling. Every other two discs are at least ``gap`` px apart
(edge to edge), so they stay separate. The placement is drawn by a seeded
generator and then *checked with exact geometry* on the digitised discs (a
pixel belongs to a disc when its centre lies inside the circle):

* each touching pair's union is one 8-connected component;
* any two discs that do not form a pair have at least two background pixels
  between them (chessboard distance >= 3 between their pixels), so they stay
  apart in an 8-connected labelling even if one of them grows by a pixel
  through the blur and the threshold,

so the union of the digitised discs has exactly ``n_particles - n_pairs``
8-connected components. A violation raises.

Rendering: background ``background``; each disc is painted in turn with its
own grey value ``g_k`` (drawn from ``intensity``) over what is already there,
with its exact area coverage per pixel estimated on an ``ss x ss`` sub-pixel
grid (``I <- I (1 - a) + g_k a``, so a later disc of a touching pair occludes
the earlier one); then a Gaussian blur of standard deviation ``blur`` px
(periodic, by FFT: the border is flat background, so the wrap-around adds
nothing) and white noise of standard deviation ``noise``. Positions are
``(row, col)`` in pixels, pixel centres on integer indices. Only numpy is used.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["particle_scene"]


def _components8(mask: np.ndarray) -> int:
    """Number of 8-connected components of a small bool array (iterative flood fill)."""
    seen = np.zeros_like(mask)
    n = 0
    h, w = mask.shape
    for i0, j0 in zip(*np.nonzero(mask), strict=True):
        if seen[i0, j0]:
            continue
        n += 1
        stack = [(i0, j0)]
        seen[i0, j0] = True
        while stack:
            i, j = stack.pop()
            for di in (-1, 0, 1):
                for dj in (-1, 0, 1):
                    a, b = i + di, j + dj
                    if 0 <= a < h and 0 <= b < w and mask[a, b] and not seen[a, b]:
                        seen[a, b] = True
                        stack.append((a, b))
    return n


def _disc_pixels(shape, y, x, r):
    rr, cc = np.mgrid[0 : shape[0], 0 : shape[1]]
    return (rr - y) ** 2 + (cc - x) ** 2 <= r * r


def particle_scene(
    size: tuple[int, int] = (256, 256),
    *,
    n_particles: int = 60,
    n_pairs: int = 6,
    radius: tuple[float, float] = (5.0, 9.0),
    intensity: tuple[float, float] = (0.45, 0.9),
    background: float = 0.15,
    overlap: float = 1.0,
    gap: float = 4.5,
    margin: float = 4.0,
    blur: float = 0.7,
    noise: float = 0.02,
    ss: int = 4,
    seed: int = 0,
):
    """Discs of random radius and grey value; ``n_pairs`` pairs touch, the rest are isolated.

    Args:
      size: ``(H, W)`` in pixels.
      n_particles: number of discs (``2 n_pairs`` of them in touching pairs).
      n_pairs: number of touching pairs.
      radius: smallest and largest radius (px), uniform.
      intensity: darkest and brightest disc grey value, uniform.
      background: background grey value.
      overlap: how far the two discs of a pair overlap along their line of centres (px).
      gap: smallest edge-to-edge distance between discs that are not a pair (px).
      margin: smallest distance from a disc to the image border (px).
      blur: standard deviation of the Gaussian optics blur (px).
      noise: standard deviation of the white noise.
      ss: sub-pixel samples per axis for the area coverage.
      seed: seed of the placement, grey values and noise.

    Returns:
      ``(image, truth)``: the float64 ``(H, W)`` image, and a dict with
      ``centres`` ``(N, 2)`` (row, col), ``radii`` ``(N,)``, ``intensity`` ``(N,)``,
      ``pairs`` (list of index pairs of touching discs), ``masks`` ``(N, H, W)``
      digitised discs, ``mask`` their union, ``n_particles`` and
      ``n_components`` (the count of a plain 8-connected labelling of ``mask``).
    """
    if 2 * n_pairs > n_particles:
        raise ValueError(f"particle_scene: n_pairs={n_pairs} needs at least {2 * n_pairs} particles")
    if not 0 < overlap < 2 * radius[0]:
        raise ValueError(f"particle_scene: overlap must be in (0, {2 * radius[0]}) px, got {overlap}")
    if gap < 3 * math.sqrt(2):
        raise ValueError(f"particle_scene: gap must be >= 3 * sqrt(2) px (two background pixels), got {gap}")
    h, w = size
    rng = np.random.default_rng(seed)
    discs: list[tuple[float, float, float]] = []

    def fits(cands):
        for y, x, r in cands:
            if y - r < margin or y + r > h - 1 - margin or x - r < margin or x + r > w - 1 - margin:
                return False
            if any(math.hypot(y - y2, x - x2) < r + r2 + gap for y2, x2, r2 in discs):
                return False
        return True

    tries = 0  # since the last placed disc
    pairs = []
    while len(discs) < n_particles:
        tries += 1
        if tries > 20_000:
            raise ValueError(f"particle_scene: cannot place {n_particles} discs in {size}; use a larger size")
        if len(pairs) < n_pairs:
            r1, r2 = rng.uniform(*radius, 2)
            y, x, a = rng.uniform(0, h), rng.uniform(0, w), rng.uniform(0, 2 * math.pi)
            dist = r1 + r2 - overlap
            cand = [(y, x, r1), (y + dist * math.sin(a), x + dist * math.cos(a), r2)]
            if fits(cand):
                pairs.append((len(discs), len(discs) + 1))
                discs += cand
                tries = 0
        else:
            r, y, x = rng.uniform(*radius), rng.uniform(0, h), rng.uniform(0, w)
            if fits([(y, x, r)]):
                discs.append((y, x, r))
                tries = 0

    centres = np.array([(y, x) for y, x, _ in discs])
    radii = np.array([r for _, _, r in discs])
    grey = rng.uniform(*intensity, len(discs))
    masks = np.stack([_disc_pixels(size, y, x, r) for y, x, r in discs])

    # exact-geometry checks on the digitised discs
    partner = {i: j for a, b in pairs for i, j in ((a, b), (b, a))}
    for a, b in pairs:
        if _components8(masks[a] | masks[b]) != 1:
            raise AssertionError(f"particle_scene: touching pair {a, b} is not one 8-connected blob")
    pix = [np.argwhere(m) for m in masks]
    for i in range(len(discs)):
        for j in range(i + 1, len(discs)):
            if partner.get(i) == j or np.hypot(*(centres[i] - centres[j])) > radii[i] + radii[j] + 6:
                continue  # (farther discs are more than 3 px apart in the chessboard metric too)
            d = np.abs(pix[i][:, None, :] - pix[j][None, :, :]).max(-1).min()  # chessboard distance
            if d < 3:
                raise AssertionError(f"particle_scene: discs {i} and {j} are {d} px apart (need >= 3)")
    union = masks.any(0)

    # rendering: painted discs with sub-pixel area coverage, blur, noise
    img = np.full(size, float(background))
    off = (np.arange(ss) + 0.5) / ss - 0.5
    for (y, x, r), g in zip(discs, grey, strict=True):
        r0, r1 = max(0, int(y - r) - 1), min(h, int(y + r) + 3)
        c0, c1 = max(0, int(x - r) - 1), min(w, int(x + r) + 3)
        rr, cc = np.mgrid[r0:r1, c0:c1].astype(float)
        cov = np.zeros(rr.shape)
        for dy in off:
            for dx in off:
                cov += (rr + dy - y) ** 2 + (cc + dx - x) ** 2 <= r * r
        cov /= ss * ss
        img[r0:r1, c0:c1] = img[r0:r1, c0:c1] * (1 - cov) + g * cov
    if blur > 0:
        fr = np.fft.fftfreq(h)[:, None]
        fc = np.fft.rfftfreq(w)[None, :]
        tf = np.exp(-2 * math.pi**2 * blur**2 * (fr**2 + fc**2))
        img = np.fft.irfft2(np.fft.rfft2(img) * tf, s=size)
    img = img + noise * rng.standard_normal(size)
    truth = {
        "centres": centres,
        "radii": radii,
        "intensity": grey,
        "pairs": pairs,
        "masks": masks,
        "mask": union,
        "n_particles": len(discs),
        "n_components": len(discs) - len(pairs),
    }
    return img, truth
