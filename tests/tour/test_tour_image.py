"""``run_tour`` end to end (report and figures) on the 2-D sections (``fsjax.tour.image``) and the
inspection sections (``fsjax.tour.inspection``); every other section family has its own test file."""

from __future__ import annotations

from pathlib import Path

from fsjax import tour
from fsjax.tour import image, inspection


def test_tour_quick(tmp_path):
    """The sections of the other tour modules each run in quick mode in their own test file
    (``tests/tour/test_tour_<family>.py``); running them all again here doubled the suite's longest test.
    """
    todo = list(image.SECTIONS) + list(inspection.SECTIONS)
    secs = tour.run_tour(tmp_path, quick=True, sections=todo, log=lambda *a, **k: None)
    report = (tmp_path / "report.md").read_text()
    assert len(secs) == len(todo) >= 10
    for s in secs:
        print(f"{s.title}: fsjax {s.fsjax_figure} | null {s.null_figure}")
        assert s.beats_null, s.title
        assert s.title in report
        if s.figure:
            assert (tmp_path / s.figure).stat().st_size > 0
    # every other tour module's sections are part of the full tour and have their own test file
    names = [f.__name__ for f in tour.all_sections()]
    assert names[: len(todo)] == [f.__name__ for f in todo]


def test_every_section_family_is_listed_and_tested():
    """The tour runs every family's sections in order, and each family other than the two above has
    a quick-mode test file of its own."""
    assert tour.FAMILIES[:2] == (image, inspection)
    assert tour.SECTIONS == [fn for fam in tour.FAMILIES for fn in fam.SECTIONS]
    assert tour.section_names() == [fn.__name__ for fn in tour.SECTIONS]
    assert len(set(tour.section_names())) == len(tour.SECTIONS)  # names select sections: no clashes
    here = Path(__file__).parent
    for fam in tour.FAMILIES[2:]:
        short = fam.__name__.rsplit(".", 1)[-1]
        assert fam.__name__ == f"fsjax.tour.{short}"
        assert (here / f"test_tour_{short}.py").exists(), f"no quick-mode test for {fam.__name__}"
