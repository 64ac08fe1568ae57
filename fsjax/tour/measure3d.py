"""Tour sections for measurement by rendering (issue 5): photometric stereo and structured light.

Each method is measured against the SDF renderer's own ground truth and beside its null:

* photometric stereo: the robust solver (shadows as inequalities) vs plain least squares,
  on the pixels a shadow touches; Frankot-Chellappa heights vs a flat surface;
* structured light: phase shifting + complementary Gray code vs Gray code alone (1-px
  stripes) and phase alone (no unwrapping).

The pure ``measure_*`` functions return dicts of numbers (asserted by
``tests/tour/test_tour_measure3d.py``); the section functions wrap them into
:class:`fsjax.tour.Section` with a PNG. Quick mode renders smaller images; the cost is
dominated by compiling the sphere tracer (a few seconds on an idle 2-core machine).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

import fsjax
from fsjax import ops as _ops
from fsjax import synth

from ._core import Section, _panel

__all__ = ["measure_photometric", "measure_structured_light", "SECTIONS"]

LOW_LIGHTS = _ops.light_directions([30, 35, 40, 45, 30, 35, 40, 45], [0, 45, 90, 135, 180, 225, 270, 315])


def measure_photometric(quick: bool = True) -> dict:
    """Still life under 8 low lights with cast and attached shadows; robust vs least squares;
    Frankot-Chellappa integration of the recovered normals vs the true depth."""
    size = dict(width=48, height=36, pixel_size=0.13) if quick else dict(width=96, height=72, pixel_size=0.066)
    scene = synth.still_life_scene()
    stack, tr = synth.render_light_stack(scene, LOW_LIGHTS, shadows=True, **size)
    n = np.asarray(tr["normals"])
    L = np.asarray(stack.lights)
    attached = np.einsum("hwc,kc->khw", n, L) <= 0
    cast = (np.asarray(tr["visibility"]) < 0.5) & ~attached
    sh = (attached | cast).any(0)
    out = {"image": np.asarray(stack.data[0]), "shadowed_fraction": float(sh.mean())}
    for m in ("robust", "ls"):
        nm = fsjax.ops.photometric_stereo(stack, method=m)
        e = synth.angular_error_deg(nm.normals, n)
        out[m] = {"median_shadowed": float(np.nanmedian(e[sh])), "median_all": float(np.nanmedian(e)),
                  "valid": float(np.asarray(nm.valid).mean()), "error_map": e}
        if m == "robust":
            z = np.asarray(fsjax.ops.frankot_chellappa(nm, pixel_size=size["pixel_size"]).data)
    d = np.asarray(tr["depth"])
    d = d - d.mean()
    out["height_rms"] = float(np.sqrt(np.mean((z - d) ** 2)))
    out["height_null_rms"] = float(np.sqrt(np.mean(d**2)))
    out["height_range"] = float(d.max() - d.min())
    out["height"] = -z
    return out


def measure_structured_light(quick: bool = True) -> dict:
    """Phase shifting + complementary Gray code on the ~100 mm deep still life, with its nulls."""
    rig = synth.standard_rig(64, 48) if quick else synth.standard_rig()
    g = synth.capture_geometry(synth.still_life_mm(), rig)
    fr = synth.capture_patterns(g)
    r = synth.decode_depth(fr, rig)
    lit = g["lit"]
    truth = g["depth"]

    def rmse(z, mask):
        return float(np.sqrt(np.mean((z[mask] - truth[mask]) ** 2)))

    Pp = fr["period_px"]
    return {
        "fringe": np.asarray(fr["fringes"].data[0]), "truth": truth, "depth": r["depth"], "lit": lit,
        "rmse": rmse(r["depth"], lit),
        "order_errors": int(np.sum(~(np.abs(r["column"][lit] - g["u_p"][lit]) < Pp / 2))),
        "gray_rmse": rmse(r["depth_gray"], lit & np.isfinite(r["depth_gray"])),
        "phase_rmse": rmse(r["depth_phase"], lit & np.isfinite(r["depth_phase"])),
        "span": float(np.nanmax(truth[g["hit"]]) - np.nanmin(truth[g["hit"]])),
        "lit_fraction": float(lit.mean()),
    }


def photometric(out: Path, quick: bool) -> Section:
    r = measure_photometric(quick)
    fig = _panel(out / "photometric_stereo.png",
                 [r["image"], np.minimum(np.nan_to_num(r["robust"]["error_map"]), 10.0),
                  np.minimum(np.nan_to_num(r["ls"]["error_map"]), 10.0), r["height"]],
                 ["one of 8 lights", "robust error (0-10 deg)", "LS error (0-10 deg)", "integrated height"])
    rb, ls = r["robust"], r["ls"]
    return Section(
        title="Photometric stereo with shadows",
        truth=f"SDF still life, Lambertian, 8 lights at 30-45 deg elevation; {r['shadowed_fraction']:.0%} of pixels "
              "have a cast or attached shadow; normals from the renderer",
        rows=[("photometric_stereo (robust: shadows as inequalities)",
               f"median error on shadowed pixels {rb['median_shadowed']:.1e} deg, valid {rb['valid']:.0%}"),
              ("null: least squares over all lights", f"median error on shadowed pixels {ls['median_shadowed']:.2f} deg"),
              ("frankot_chellappa on the recovered normals",
               f"height RMS {r['height_rms']:.4f} vs flat null {r['height_null_rms']:.4f} "
               f"(range {r['height_range']:.2f})")],
        fsjax_figure=f"{rb['median_shadowed']:.1e} deg median on shadowed pixels",
        null_figure=f"least squares {ls['median_shadowed']:.2f} deg",
        beats_null=rb["median_shadowed"] <= 0.1 < ls["median_shadowed"] and r["height_rms"] < r["height_null_rms"],
        figure=fig,
        notes="targets: robust <= 0.1 deg with shadows; least squares visibly biased.",
    )


def structured_light(out: Path, quick: bool) -> Section:
    r = measure_structured_light(quick)
    err = np.where(r["lit"], np.nan_to_num(r["depth"] - r["truth"]), 0.0)
    fig = _panel(out / "structured_light.png",
                 [r["fringe"], np.nan_to_num(r["truth"], nan=520.0), np.nan_to_num(r["depth"], nan=520.0), err],
                 ["fringe 1 of 8", "true depth", "measured depth", "error (signed)"], signed=(3,))
    return Section(
        title="Structured light: phase shifting + complementary Gray code",
        truth=f"SDF still life in mm spanning {r['span']:.0f} mm in depth; projector 150 mm beside the camera, "
              f"{r['lit_fraction']:.0%} of pixels lit by it",
        rows=[("8-step fringes (8 px) + complementary Gray code, triangulate_column",
               f"RMSE {r['rmse']:.4f} mm, {r['order_errors']} Gray-decode errors"),
              ("null: Gray code alone (1-px stripes)", f"RMSE {r['gray_rmse']:.3f} mm"),
              ("null: phase alone (no unwrapping)", f"RMSE {r['phase_rmse']:.1f} mm")],
        fsjax_figure=f"RMSE {r['rmse']:.4f} mm",
        null_figure=f"Gray only {r['gray_rmse']:.3f} mm, phase only {r['phase_rmse']:.0f} mm",
        beats_null=r["rmse"] < r["gray_rmse"] < r["phase_rmse"] and r["order_errors"] == 0,
        figure=fig,
        notes="targets: RMSE <= 0.04 mm, 0 Gray-decode errors (full size; quick mode uses a 64 x 48 camera).",
    )


SECTIONS: list[Callable[[Path, bool], Section]] = [photometric, structured_light]
