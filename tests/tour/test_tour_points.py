"""Tour sections for 3-D points (issue 4): each runs in quick mode into ``tmp_path``, writes its
figure, and meets its target (4 LiDAR clusters within 0.13 while the null fuses; curvedness
within 2 %; RANSAC never accepts a wrong plane; BIC >= 95 % correct)."""

from __future__ import annotations

import pytest

from fsjax.tour import Section
from fsjax.tour import points as T

# the LiDAR and model-selection figures are also asserted by tests/ops/test_points_segment.py and
# tests/fit/test_primitives3d.py; their tour runs (compile-heavy) are marked slow
_HEAVY = ("lidar", "model_selection")
PARAMS = [pytest.param(f, id=f.__name__, marks=[pytest.mark.slow] if f.__name__ in _HEAVY else [])
          for f in T.SECTIONS]


@pytest.mark.parametrize("fn", PARAMS)
def test_section_runs(fn, tmp_path):
    sec = fn(tmp_path, True)
    assert isinstance(sec, Section)
    assert sec.figure and (tmp_path / sec.figure).stat().st_size > 0
    assert sec.rows and sec.truth and sec.fsjax_figure and sec.null_figure
    print(f"{sec.title}: {sec.fsjax_figure} | null: {sec.null_figure}")
    for method, figure in sec.rows:
        print(f"    {method}: {figure}")
    assert sec.beats_null
