"""Tour section: computed tomography of a three-material phantom (issue 5, measurement 4).

The phantom of :func:`fsjax.synth.ct_phantom` (water, cortical bone, aluminium at 60 keV,
0.75 mm pixels), an analytic sinogram with photon-counting noise, reconstructed by
``filtered_backprojection``; the nulls are unfiltered back-projection (given its best
scale) and FBP from 24 views. The scan is mis-centred by a known offset, which
``rotation_center`` recovers before reconstruction.
"""

from __future__ import annotations

from pathlib import Path

import jax.numpy as jnp
import numpy as np
from scipy import ndimage as ndi

from fsjax import Image
from fsjax import ops as O
from fsjax.synth import CT_MATERIALS, ct_phantom, ct_sinogram

from ._core import Section, _panel

__all__ = ["measure_ct", "tomography", "SECTIONS"]

_VALS = np.array([0.0, CT_MATERIALS["water"], CT_MATERIALS["bone"], CT_MATERIALS["aluminium"]])


def _scores(rec, mu, lab):
    seg = np.digitize(rec, (_VALS[1:] + _VALS[:-1]) / 2)
    dice = [2 * ((seg == k) & (lab == k)).sum() / ((seg == k).sum() + (lab == k).sum()) for k in (1, 2, 3)]
    err = [float((np.median(rec[ndi.binary_erosion(lab == k, iterations=2)]) - _VALS[k]) / _VALS[k] * 100)
           for k in (1, 2, 3)]
    return np.array(dice), np.array(err), float(np.sqrt(np.mean((rec - mu) ** 2)))


def measure_ct(size: int = 128, pixel_mm: float = 0.75, photons: float = 1e5, offset_px: float = 1.7) -> dict:
    """Reconstruct the phantom from a mis-centred noisy scan; nulls on the same data."""
    mu, lab = ct_phantom(size, pixel_mm)
    to_mu = 1.0 / (pixel_mm / 10.0)
    sino = ct_sinogram(180, size, pixel_mm, photons=photons, seed=0, center_offset_px=offset_px)
    c = float(O.rotation_center(Image(jnp.asarray(sino))).value)
    centred = ndi.shift(sino, (size // 2 - c, 0), order=3, mode="constant")
    fbp = lambda s: np.asarray(O.filtered_backprojection(Image(jnp.asarray(s)), filter="shepp-logan",  # noqa: E731
                                                         circle=True).data) * to_mu
    rec = fbp(centred)
    dice, err, rmse = _scores(rec, mu, lab)
    s24 = ct_sinogram(24, size, pixel_mm, photons=photons, seed=0, center_offset_px=offset_px)
    s24 = ndi.shift(s24, (size // 2 - c, 0), order=3, mode="constant")
    rec24 = fbp(s24)
    _, _, rmse24 = _scores(rec24, mu, lab)
    bp = np.asarray(O.backprojection(Image(jnp.asarray(centred)), circle=True).data)
    bp = bp * float((bp * mu).sum() / (bp * bp).sum())
    _, _, rmse_bp = _scores(bp, mu, lab)
    return dict(mu=mu, rec=rec, rec24=rec24, bp=bp, dice=dice, err=err, rmse=rmse, rmse24=rmse24,
                rmse_bp=rmse_bp, center_error=c - (size // 2 + offset_px), offset=offset_px)


def tomography(out: Path, quick: bool) -> Section:
    r = measure_ct(size=96 if quick else 128, pixel_mm=1.0 if quick else 0.75)
    fig = _panel(out / "tomography.png", [r["mu"], r["rec"], r["rec24"], r["bp"]],
                 ["truth (1/cm)", "FBP 180 views", "null: 24 views", "null: unfiltered"])
    d = ", ".join(f"{v:.3f}" for v in r["dice"])
    e = ", ".join(f"{v:+.2f}" for v in r["err"])
    return Section(
        title="Tomography: a three-material phantom (water, bone, aluminium at 60 keV) from a noisy scan",
        truth=("analytic sinogram of SDF discs, 1e5 photons per ray, detector axis mis-centred by "
               f"{r['offset']} px; attenuation 0.206 / 0.604 / 0.750 per cm"),
        rows=[("rotation_center", f"axis error {r['center_error']:+.4f} px"),
              ("FBP (Shepp-Logan), 180 views", f"Dice water/bone/Al {d}; attenuation error {e} %; "
                                                f"RMSE {r['rmse']:.4f} /cm"),
              ("null: FBP from 24 views", f"RMSE {r['rmse24']:.4f} /cm (x{r['rmse24'] / r['rmse']:.2f})"),
              ("null: unfiltered back-projection, best scale",
               f"RMSE {r['rmse_bp']:.4f} /cm (x{r['rmse_bp'] / r['rmse']:.2f})")],
        fsjax_figure=f"min Dice {r['dice'].min():.3f}, RMSE {r['rmse']:.4f} /cm",
        null_figure=f"RMSE {r['rmse24']:.4f} (24 views), {r['rmse_bp']:.4f} (unfiltered) /cm",
        beats_null=bool(r["rmse24"] >= 1.8 * r["rmse"] and r["rmse_bp"] >= 1.8 * r["rmse"]),
        figure=fig,
        notes="targets: Dice >= 0.88 per material; nulls beaten by >= 1.8x; axis to 0.01 px.",
    )


SECTIONS = [tomography]
