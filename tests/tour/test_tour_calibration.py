"""Tour sections for calibration (issue 7): each runs in quick mode, writes its figure and beats its null.

The numbers behind the sections are asserted in tests/fit/test_calibrate.py, test_chessboard.py
and test_diffmetrology.py (the measure_* functions are cached per process).
"""

from __future__ import annotations

import pytest

from fsjax.tour import Section
from fsjax.tour import calibration as T


@pytest.mark.slow  # repeats the cached measurements of tests/fit in its own process under xdist
@pytest.mark.parametrize("fn", T.SECTIONS, ids=lambda f: f.__name__)
def test_section_runs(fn, tmp_path):
    sec = fn(tmp_path, True)
    assert isinstance(sec, Section)
    assert sec.figure and (tmp_path / sec.figure).stat().st_size > 0
    assert sec.rows and sec.truth and sec.fsjax_figure and sec.null_figure
    print(f"{sec.title}: {sec.fsjax_figure} | null: {sec.null_figure}")
    assert sec.beats_null
