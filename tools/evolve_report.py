"""Regenerate ``docs/evolution.md``: every problem, baselines first, seed spread, the locked split.

Usage: ``python tools/evolve_report.py --write-docs`` runs :func:`fsjax.evolve.report.run_reports`
(defaults: the settings the page states; every setting is a flag) and writes the page and one
trajectory chart per problem (``docs/figures/evolution_<problem>.png``). Without ``--write-docs``
it prints the tables only.
"""

from __future__ import annotations

import argparse
import inspect
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # `python tools/evolve_report.py` from a checkout
    sys.path.insert(0, str(ROOT))


def main(argv: list[str] | None = None) -> int:
    from fsjax.evolve.problems import PROBLEMS
    from fsjax.evolve.report import run_reports, write_docs

    default = {k: p.default for k, p in inspect.signature(run_reports).parameters.items()}
    ap = argparse.ArgumentParser(prog="python tools/evolve_report.py", description=__doc__.split("\n\n", 1)[0])
    ap.add_argument("--write-docs", action="store_true", help="write docs/evolution.md and its figures")
    ap.add_argument("--problems", default=",".join(PROBLEMS))
    for name in ("gens", "pop", "seeds", "size", "n_train", "n_holdout", "stages"):
        ap.add_argument("--" + name.replace("_", "-"), type=int, default=default[name])
    ap.add_argument("--quiet", action="store_true")
    a = ap.parse_args(argv)
    t0 = time.perf_counter()
    reports, settings = run_reports(a.problems.split(","), gens=a.gens, pop=a.pop, seeds=a.seeds, size=a.size,
                                    n_train=a.n_train, n_holdout=a.n_holdout, stages=a.stages,
                                    progress=not a.quiet, log=lambda text: print(text, flush=True))
    if a.write_docs:
        page = write_docs(reports, settings, time.perf_counter() - t0, ROOT / "docs")
        print(f"wrote {page}")
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
