"""Run the calibration tour sections in full size and write their figures (issue 7).

Usage: ``python tools/calibration_figures.py --write-docs`` writes ``docs/figures/calibration_*.png``
(the figures ``docs/calibration.md`` shows) and prints each section's rows; ``--out DIR``
writes them elsewhere. The sections are :mod:`fsjax.tour.calibration`'s (real chessboard vs
OpenCV, plumb line, length sensitivity); ``tests/tour/test_tour_calibration.py`` asserts
the numbers they measure.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # `python tools/calibration_figures.py` from a checkout
    sys.path.insert(0, str(ROOT))


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n", 1)[0])
    ap.add_argument("--write-docs", action="store_true", help="write the figures into docs/figures")
    ap.add_argument("--out", default=None, help="output folder (default: docs/figures with --write-docs)")
    a = ap.parse_args(argv)
    import jax

    jax.config.update("jax_enable_x64", True)
    from fsjax.tour import calibration

    out = Path(a.out) if a.out else (ROOT / "docs" / "figures" if a.write_docs else Path("."))
    out.mkdir(parents=True, exist_ok=True)
    for fn in calibration.SECTIONS:
        t0 = time.perf_counter()
        sec = fn(out, False)
        print(f"## {sec.title} ({time.perf_counter() - t0:.1f} s)\nfigure: {sec.figure}")
        for k, v in sec.rows:
            print(f"| {k} | {v} |")


if __name__ == "__main__":
    main()
