"""The evolution tour section in quick mode: it runs, writes its figure, and the GA beats the null.

The test measures once and builds the section from that measurement (the section function is
called with ``measure_evolution`` patched to return it): the section and the figures it shows
used to be two tests that each ran the whole quick evolution.
"""

from __future__ import annotations

import numpy as np

from fsjax.tour import Section
from fsjax.tour import evolve as T


def _check_section(sec, tmp_path):
    assert isinstance(sec, Section)
    assert sec.figure and (tmp_path / sec.figure).stat().st_size > 0
    assert len(sec.rows) == 6 and sec.truth
    for method, figure in sec.rows:
        print(f"{method}: {figure}")
    assert sec.beats_null


def test_sections_are_the_listed_ones():
    assert [f.__name__ for f in T.SECTIONS] == ["evolution"]


def test_measure_evolution_figures_and_section(tmp_path, monkeypatch):
    # merged: test_evolution_section (it ran the same measure_evolution(quick=True) again)
    r = T.measure_evolution(quick=True)
    print(f"binarize locked IoU: identity {r['identity']:.3f}, best single {r['single']:.3f}, hand {r['hand']:.3f}, "
          f"random {r['random']:.3f}, GA {r['evolved']:.3f}, GA+refine {r['refined']:.3f}")
    vals = [r[k] for k in ("identity", "single", "hand", "random", "evolved", "refined")]
    assert all(0.0 <= v <= 1.0 for v in vals)
    assert r["refined"] > r["identity"] and r["evolved"] > r["identity"]
    assert r["trajectory"] == sorted(r["trajectory"])  # elitism
    assert r["output"].shape == r["truth"].shape and r["output"].dtype == bool
    assert np.isfinite(r["hand"]) and r["hand"] > r["identity"]

    def same(quick=True):
        assert quick is True, "the section must measure in quick mode"
        return r

    monkeypatch.setattr(T, "measure_evolution", same)
    _check_section(T.evolution(tmp_path, True), tmp_path)
