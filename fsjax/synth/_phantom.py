"""A three-material CT phantom with real attenuation values and an analytic, noisy sinogram.

The phantom is built from signed distance functions (discs) in millimetres: a water
cylinder (radius 40 mm) holding two cortical-bone rods and one aluminium rod, in a field
of view of ``size`` pixels of ``pixel_mm``. Linear attenuation coefficients at 60 keV from
the NIST XCOM / Hubbell-Seltzer tables (mass attenuation times density):

* water: 0.2059 cm^2/g x 1.000 g/cm^3 = 0.2059 / cm
* cortical bone (ICRU-44): 0.3148 cm^2/g x 1.920 g/cm^3 = 0.6044 / cm
* aluminium: 0.2778 cm^2/g x 2.699 g/cm^3 = 0.7498 / cm

The sinogram is computed in closed form (chord lengths of discs averaged over each
detector bin's width, exactly, no pixel grid, so reconstructing it is not an "inverse crime"), in the geometry of
:func:`fsjax.ops.radon_transform` (detector bin ``n // 2`` on the axis, ``s = x cos(theta)
- y sin(theta)``, ``x`` right, ``y`` down), and made noisy by photon counting: counts are
Poisson with mean ``photons * exp(-p)``, and ``p = -ln(max(counts, 1) / photons)``.
"""

from __future__ import annotations

import numpy as np

__all__ = ["CT_MATERIALS", "ct_phantom", "ct_sinogram"]

#: linear attenuation at 60 keV, 1/cm (see the module docstring for the sources)
CT_MATERIALS = {"water": 0.2059 * 1.000, "bone": 0.3148 * 1.920, "aluminium": 0.2778 * 2.699}

# (material, centre x mm, centre y mm, radius mm); later discs replace earlier ones inside them
_DISCS = (("water", 0.0, 0.0, 40.0), ("bone", -17.0, -9.0, 9.0), ("bone", 14.0, 13.0, 7.0),
          ("aluminium", 8.0, -21.0, 6.0))
_LABEL = {"water": 1, "bone": 2, "aluminium": 3}


def _mu_steps():
    """Disc list with the attenuation *increment* each one adds (superposition)."""
    out = []
    for mat, x, y, r in _DISCS:
        mu = CT_MATERIALS[mat]
        inc = mu if mat == "water" else mu - CT_MATERIALS["water"]
        out.append((inc, x, y, r))
    return out


def ct_phantom(size: int = 128, pixel_mm: float = 0.75, supersample: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """The phantom on the pixel grid: ``(mu (size, size) in 1/cm, labels (size, size) int)``.

    ``mu`` is the area-weighted mean over ``supersample^2`` sub-pixel samples (partial
    volume); ``labels`` is the material at the pixel centre (0 air, 1 water, 2 bone,
    3 aluminium). Pixel ``(row, col)`` has centre ``((col - size // 2) pixel_mm,
    (row - size // 2) pixel_mm)``.
    """
    if size < 16 or pixel_mm <= 0 or supersample < 1:
        raise ValueError(f"ct_phantom: need size >= 16, pixel_mm > 0, supersample >= 1; got {size}, "
                         f"{pixel_mm}, {supersample}")
    c = size // 2
    k = supersample
    sub = (np.arange(k) + 0.5) / k - 0.5
    rr, cc = np.mgrid[0:size, 0:size].astype(float)
    mu = np.zeros((size, size))
    for dy in sub:
        for dx in sub:
            x = (cc + dx - c) * pixel_mm
            y = (rr + dy - c) * pixel_mm
            m = np.zeros((size, size))
            for inc, x0, y0, r in _mu_steps():
                m += np.where(np.hypot(x - x0, y - y0) - r <= 0, inc, 0.0)  # disc SDF <= 0
            mu += m
    mu /= k * k
    labels = np.zeros((size, size), np.int32)
    x = (cc - c) * pixel_mm
    y = (rr - c) * pixel_mm
    for mat, x0, y0, r in _DISCS:
        labels[np.hypot(x - x0, y - y0) <= r] = _LABEL[mat]
    return mu, labels


def ct_sinogram(n_angles: int = 180, size: int = 128, pixel_mm: float = 0.75, *, photons: float | None = 1e5,
                seed: int = 0, angle_range_deg: float = 180.0, center_offset_px: float = 0.0) -> np.ndarray:
    """Line integrals ``(size, n_angles)`` (dimensionless), noisy unless ``photons is None``.

    ``center_offset_px`` moves the rotation axis on the detector to bin
    ``size // 2 + center_offset_px`` (a mis-centred scan, for centre-of-rotation estimation).
    """
    if n_angles < 1:
        raise ValueError(f"ct_sinogram(n_angles=...): must be >= 1, got {n_angles}")
    if photons is not None and not photons > 0:
        raise ValueError(f"ct_sinogram(photons=...): must be > 0 or None, got {photons}")
    th = np.deg2rad(np.arange(n_angles) * (angle_range_deg / n_angles))
    s = (np.arange(size) - size // 2 - center_offset_px) * pixel_mm
    p = np.zeros((size, n_angles))

    def area(u, r):  # integral of the chord length 2 sqrt(r^2 - v^2) for v from 0 to u
        u = np.clip(u, -r, r)
        return u * np.sqrt(r * r - u * u) + r * r * np.arcsin(u / r)

    for inc, x0, y0, r in _mu_steps():
        s0 = x0 * np.cos(th) - y0 * np.sin(th)
        d = s[:, None] - s0[None, :]
        # each detector bin integrates over its width (mean chord over the bin, exact)
        chord_mm = (area(d + pixel_mm / 2, r) - area(d - pixel_mm / 2, r)) / pixel_mm
        p += inc * chord_mm / 10.0
    if photons is None:
        return p
    rng = np.random.default_rng(seed)
    counts = rng.poisson(photons * np.exp(-p))
    return -np.log(np.maximum(counts, 1) / photons)
