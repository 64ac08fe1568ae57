"""Tour sections for measurement by rendering (issue 5, results 1 and 6), quick mode.

The figures are asserted on the numbers of the pure ``measure_*`` functions.
"""

from __future__ import annotations

import pytest

from fsjax.tour import Section
from fsjax.tour import render as T

pytestmark = pytest.mark.slow  # tour quick mode repeats measurements tested elsewhere; runs last

# Each section in quick mode makes exactly the measurement its figure test asserts on
# (``measure_channels(96)``, ``measure_bunny(96, 8)``); they used to be made twice (the bunny twice
# cost ~22 s). So each section is run once, in one test, and both its measurement and its section
# are checked on that one result: the measurement is caught on its way into the section.


def _run_section(fn, args, tmp_path, monkeypatch):
    """Run the quick ``fn`` section; return it and the result of its one ``measure_*(*args)`` call."""
    name = "measure_" + fn.__name__
    real, seen = getattr(T, name), []

    def spy(*a, **kw):
        seen.append(((a, kw), real(*a, **kw)))
        return seen[-1][1]

    monkeypatch.setattr(T, name, spy)
    sec = fn(tmp_path, True)
    assert [c for c, _ in seen] == [(args, {})], f"section {fn.__name__} measured with {[c for c, _ in seen]}"
    return sec, seen[0][1]


def _check_section(sec, tmp_path):
    assert isinstance(sec, Section)
    assert sec.figure and (tmp_path / sec.figure).stat().st_size > 0
    assert sec.rows and sec.truth and sec.fsjax_figure and sec.null_figure
    print(f"{sec.title}: {sec.fsjax_figure} | null: {sec.null_figure}")
    assert sec.beats_null


def test_sections_are_the_tested_ones():
    assert [f.__name__ for f in T.SECTIONS] == ["channels", "bunny"]


def test_channels_depth_edges_from_sobel(tmp_path, monkeypatch):
    # merged: test_section_runs[channels] (same measure_channels(96) call)
    sec, r = _run_section(T.channels, (96,), tmp_path, monkeypatch)
    _check_section(sec, tmp_path)
    print(f"channels: sobel_amp of rendered depth, silhouette median {r['silhouette_median']:.4f} / interior "
          f"median {r['interior_median']:.4f} = {r['ratio']:.1f}x (target >= 20x); null (Lambert-shaded image) "
          f"{r['null_ratio']:.1f}x")
    assert r["ratio"] >= 20.0
    assert r["ratio"] > r["null_ratio"]


def test_bunny_channels_on_the_mesh_and_sun_shadows(tmp_path, monkeypatch):
    # merged: test_section_runs[bunny] (same measure_bunny(96, 8) call)
    sec, r = _run_section(T.bunny, (96, 8), tmp_path, monkeypatch)
    _check_section(sec, tmp_path)
    print(f"bunny ({r['bunny_faces']} faces + ground, 96x96): back-projected depth to hit-triangle plane max "
          f"{r['max_plane_distance_m']:.1e} m (depth {r['depth_m'][0]:.3f}-{r['depth_m'][1]:.3f} m), outside "
          f"triangle by {r['max_bary_outside']:.1e} (barycentric); normal vs face normal max "
          f"{r['max_normal_angle_deg']:.1e} deg; null nearest-vertex distance median "
          f"{r['null_median_vertex_distance_m']:.1e} m")
    print(f"bunny shading: Hapke, sun 0.53 deg (8 samples), zero ambient: {100 * r['shadowed_fraction']:.1f} % of "
          f"lit-facing pixels in umbra, {r['penumbra_pixels']} penumbra pixels, umbra radiance "
          f"{r['max_radiance_in_umbra']}, tile overflow {r['overflow']}, shadow-grid overflow {r['shadow_overflow']}")
    assert r["overflow"] == 0 and r["shadow_overflow"] == 0 and r["bad_faces"] == 0
    assert r["coverage"] > 0.3
    assert r["max_plane_distance_m"] <= 1e-12  # rounding, float64, depths ~0.3-0.5 m
    assert r["max_bary_outside"] <= 1e-9
    assert r["max_normal_angle_deg"] <= 1e-9
    assert r["max_plane_distance_m"] < 1e-6 * r["null_median_vertex_distance_m"]
    # zero ambient: umbra exactly black; cast shadows and penumbrae exist
    assert r["max_radiance_in_umbra"] == 0.0 and r["max_radiance_lit"] > 0
    assert 0.02 < r["shadowed_fraction"] < 0.8 and r["penumbra_pixels"] > 0

