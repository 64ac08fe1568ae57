"""Tour sections for issue 3 scenes 2 (sub-pixel metrology), 3 (alignment) and 5 (bar edges).

Each section runs in quick mode into ``tmp_path`` (figure written, beats its
null); the scene figures are asserted on the numbers of the pure
``measure_*`` functions the sections report.
"""

from __future__ import annotations

import numpy as np
import pytest

from fsjax.tour import Section
from fsjax.tour import metrology as T


@pytest.mark.parametrize("fn", T.SECTIONS, ids=lambda f: f.__name__)
def test_section_runs(fn, tmp_path):
    sec = fn(tmp_path, True)
    assert isinstance(sec, Section)
    assert sec.figure and (tmp_path / sec.figure).stat().st_size > 0
    assert sec.rows and sec.truth and sec.fsjax_figure and sec.null_figure
    print(f"{sec.title}: {sec.fsjax_figure} | null: {sec.null_figure}")
    assert sec.beats_null


def test_scene2_shaft_diameters():
    r = T.measure_shaft()
    print(f"shaft diameters {r['diameters']} measured {np.round(r['measured'], 4)}: max |error| "
          f"{r['max_error']:.4f} px; null (max-gradient pixels) {r['null_max_error']:.3f} px")
    assert np.all(r["edges_per_caliper"] == 2)
    assert r["max_error"] <= 0.02
    assert r["max_error"] < r["null_max_error"]


def test_scene2_edge_sweep():
    r = T.measure_edge_sweep(21)
    assert np.allclose(np.diff(r["truth"]), 0.05) and r["truth"][-1] - r["truth"][0] == pytest.approx(1.0)
    print(f"edge sweep, 21 positions in 0.05 px steps: measure_pos RMS {r['rms']:.4f} px (max {r['max_error']:.4f}); "
          f"null (pixel of max gradient) RMS {r['null_rms']:.3f} px")
    assert np.all(r["edges_per_image"] == 1)
    assert r["rms"] <= 0.012
    assert 0.2 < r["null_rms"] < 0.35  # the null of the issue: about 0.28 px


def test_scene3_alignment():
    r = T.measure_alignment()
    print(f"alignment: {r['n_found']}/3 found, position errors {np.round(r['pos_errors'], 3)} px, angle errors "
          f"{np.round(r['angle_errors'], 3)} deg, decoy distances {np.round(r['decoy_distances'], 1)} px; "
          f"null ncc_locate (no rotation): {r['null_found']}/3")
    assert r["n_found"] == 3 and r["n_valid"] == 3 and not r["truncated"]
    assert r["max_pos_error"] <= 0.1
    assert r["max_angle_error"] <= 0.1
    assert r["decoys_matched"] == 0 and min(r["decoy_distances"]) > 20
    assert r["null_found"] == 0


def test_scene5_bars():
    r = T.measure_bars()
    print(f"45 bars: {r['n_edges']} edges, max |error| {r['max_error']:.3f} px (median {r['median_error']:.3f}); "
          f"null (max-gradient pixels): {r['null_n_edges']} edges, max {r['null_max_error']:.3f} px")
    assert r["n_edges"] == 90 and not r["truncated"]
    assert r["max_error"] <= 0.5
    assert r["median_error"] < r["null_median_error"]
