"""Tour sections for issue 4 registration (self-registration, basin, global), quick mode."""

from __future__ import annotations

import pytest

from fsjax.tour import Section
from fsjax.tour import registration as T


@pytest.mark.slow
@pytest.mark.parametrize("fn", T.SECTIONS, ids=lambda f: f.__name__)
def test_section_runs(fn, tmp_path):
    sec = fn(tmp_path, True)
    assert isinstance(sec, Section)
    if sec.figure:
        assert (tmp_path / sec.figure).stat().st_size > 0
    assert sec.rows and sec.truth and sec.fsjax_figure and sec.null_figure
    print(f"{sec.title}: {sec.fsjax_figure} | null: {sec.null_figure}")
    for name, fig in sec.rows:
        print(f"  {name}: {fig}")
    assert sec.beats_null
