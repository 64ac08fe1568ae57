"""Tour sections for issue 5 (photometric stereo, structured light) in quick mode: they run,
write their figure, beat their null; the numbers are asserted on the ``measure_*`` results.

Each test measures once and builds its section from that measurement (the section function is
called with ``measure_*`` patched to return it), so a section and its numbers cost one run.
"""

from __future__ import annotations

import functools

import pytest

from fsjax.tour import Section
from fsjax.tour import measure3d as T

pytestmark = pytest.mark.slow  # tour quick mode repeats measurements tested elsewhere; runs last


def _check_section(sec, tmp_path):
    assert isinstance(sec, Section)
    assert sec.figure and (tmp_path / sec.figure).stat().st_size > 0
    assert sec.rows and sec.truth and sec.fsjax_figure and sec.null_figure
    print(f"{sec.title}: {sec.fsjax_figure} | null: {sec.null_figure}")
    for method, figure in sec.rows:
        print(f"  {method}: {figure}")
    assert sec.beats_null


def test_sections_are_the_listed_ones():
    assert [f.__name__ for f in T.SECTIONS] == ["photometric", "structured_light"]


def test_photometric(tmp_path, monkeypatch):
    r = T.measure_photometric(quick=True)
    print(f"tour photometric (quick): robust {r['robust']['median_shadowed']:.1e} deg, LS {r['ls']['median_shadowed']:.2f} "
          f"deg on shadowed pixels; height RMS {r['height_rms']:.4f} vs flat {r['height_null_rms']:.4f}")
    assert r["shadowed_fraction"] > 0.05
    assert r["robust"]["median_shadowed"] <= 0.1 and r["robust"]["median_all"] <= 0.1
    assert r["ls"]["median_shadowed"] >= 1.0
    assert r["height_rms"] < 0.25 * r["height_null_rms"]
    monkeypatch.setattr(T, "measure_photometric", functools.partial(_same, r))
    _check_section(T.photometric(tmp_path, True), tmp_path)


def test_structured_light(tmp_path, monkeypatch):
    r = T.measure_structured_light(quick=True)
    print(f"tour structured light (quick): RMSE {r['rmse']:.4f} mm, {r['order_errors']} decode errors; Gray only "
          f"{r['gray_rmse']:.3f} mm, phase only {r['phase_rmse']:.1f} mm; span {r['span']:.1f} mm")
    assert r["order_errors"] == 0
    assert r["rmse"] <= 0.06  # 0.04 at full size (tests/ops/test_structured_light.py); coarser camera here
    assert r["gray_rmse"] >= 2 * r["rmse"] and r["phase_rmse"] >= 50.0
    monkeypatch.setattr(T, "measure_structured_light", functools.partial(_same, r))
    _check_section(T.structured_light(tmp_path, True), tmp_path)


def _same(r, quick=True):
    assert quick is True, "the section must measure in quick mode"
    return r
