"""Tour section for splatting: runs in quick mode, beats its null (centre-only culling)."""

from fsjax.tour import Section
from fsjax.tour import splat as T


def test_near_plane_section(tmp_path):
    sec = T.near_plane(tmp_path, True)
    assert isinstance(sec, Section) and sec.figure and (tmp_path / sec.figure).stat().st_size > 0
    print(f"{sec.title}: {sec.fsjax_figure} | null: {sec.null_figure}")
    assert sec.beats_null
