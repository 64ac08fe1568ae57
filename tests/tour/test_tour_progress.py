"""The tour's progress lines, section selection by name, and per-section accounting."""

from __future__ import annotations

import time

import pytest

from fsjax import tour


def _slow(out, quick):
    tour.step("waiting on purpose")
    time.sleep(0.8)
    return tour.Section("slow", "none", [("m", "1")], "a", "b", True)


def test_heartbeat_names_section_and_step(tmp_path, capsys):
    secs = tour.run_tour(tmp_path, sections=[_slow], heartbeat_s=0.25)
    out = capsys.readouterr().out
    assert "... _slow still running" in out and "waiting on purpose" in out
    assert secs[0].seconds >= 0.8 and secs[0].cpu_seconds >= 0.0
    assert secs[0].peak_mb is None or secs[0].peak_mb > 10
    assert "peak" in (tmp_path / "report.md").read_text()


def test_no_heartbeat_for_a_short_section(tmp_path, capsys):
    def quick_one(out, quick):
        return tour.Section("q", "none", [("m", "1")], "a", "b", True)

    tour.run_tour(tmp_path, sections=[quick_one], heartbeat_s=5.0)
    assert "still running" not in capsys.readouterr().out


def test_sections_by_name_and_unknown_refused(tmp_path):
    names = tour.section_names()
    assert len(names) == 30 and names[0] == "denoise" and "basin" in names
    with pytest.raises(ValueError, match="unknown section"):
        tour.run_tour(tmp_path, sections=["no_such_section"])
