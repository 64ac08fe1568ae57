"""``fsjax tour``: a scored tour of what fsjax measures.

Each section builds a scene with a known answer, measures it with fsjax, and
measures the *null* (doing nothing, or the naive method) on the same data. The
report states the ground truth, the fsjax figure, the null figure and whether
fsjax beat the null; each section writes a PNG. Runs in float64.

Sections are plain functions ``(out_dir, quick) -> Section``, one module per family
(:mod:`fsjax.tour.image` for the 2-D basics, then inspection, metrology, points,
registration, render, measure3d, tomography, calibration, splat, evolve), each listing
its sections in ``SECTIONS``. :data:`SECTIONS` here is every section in report order;
other capabilities add their own by appending to it. The machinery (record, heartbeat,
runner, report) is in :mod:`fsjax.tour._core`. Nothing in the library imports this
package (the ``fsjax`` command does).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from . import (
    calibration,
    evolve,
    image,
    inspection,
    measure3d,
    metrology,
    points,
    registration,
    render,
    splat,
    tomography,
)
from ._core import Section, run_sections, step, write_report

__all__ = ["FAMILIES", "SECTIONS", "Section", "all_sections", "run_tour", "section_names", "step", "write_report"]

#: the section modules, in report order
FAMILIES = (image, inspection, metrology, points, registration, render, measure3d, tomography, calibration, splat,
            evolve)

#: every tour section, in report order
SECTIONS: list[Callable[[Path, bool], Section]] = [fn for fam in FAMILIES for fn in fam.SECTIONS]


def all_sections() -> list[Callable[[Path, bool], Section]]:
    """Every tour section, in report order: the 2-D basics, then inspection, metrology, 3-D scenes."""
    return list(SECTIONS)


def section_names() -> list[str]:
    """The names of every tour section, in report order (``fsjax tour --sections`` takes these)."""
    return [fn.__name__ for fn in all_sections()]


def run_tour(out_dir: str | Path, *, quick: bool = False, sections=None, log=print,
             heartbeat_s: float = 15.0, blas_threads: int | None = 1) -> list[Section]:
    """Run every section, write figures and ``report.md`` into ``out_dir``; return the sections.

    Args:
        out_dir: output directory (created).
        quick: smaller inputs (the form ``.ci/run`` and the tests use).
        sections: the section functions to run, or their names (see :func:`section_names`);
            ``None`` runs them all.
        log: ``print`` for the console progress lines, or a callable taking a section name.
        heartbeat_s: while a section runs, a line on stdout every this many seconds says it
            is still running and what it is doing (0 disables).
        blas_threads: OpenBLAS/LAPACK threads while the tour runs (numpy, scipy and jaxlib's CPU
            linear algebra), restored afterwards; ``None`` leaves the library default. The tour's
            matrices are small: with a thread per core, OpenBLAS spin-waits between calls and, on a
            machine with other work, one compiled 14-view ``calibrate_camera`` call took 2-3 s of
            CPU instead of 0.07 s (measured; results identical).
    """
    todo = all_sections() if sections is None else list(sections)
    if any(isinstance(fn, str) for fn in todo):
        by_name = {fn.__name__: fn for fn in all_sections()}
        unknown = [fn for fn in todo if isinstance(fn, str) and fn not in by_name]
        if unknown:
            raise ValueError(f"run_tour: unknown section(s) {unknown}; known: {sorted(by_name)}")
        todo = [by_name[fn] if isinstance(fn, str) else fn for fn in todo]
    return run_sections(out_dir, todo, quick=quick, log=log, heartbeat_s=heartbeat_s, blas_threads=blas_threads)
