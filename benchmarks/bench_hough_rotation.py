"""The cost of the rotation about z in the generalised Hough transform: ``generalised_hough3d``
(translation only) against ``generalised_hough_rotation_z3d`` (36 turned R-tables, then 9 angles per
instance found; and with ``n_fine=0``) on the matching grid's 48^3 voxel scene (seed 0, a 24^3
template), in one process: compile CPU time (``lower().compile()``, ``time.process_time``) and run
time (round-robin medians). Prints; writes nothing (the figures are quoted in the op's docstring and
docs/matching_grid.md).

    python benchmarks/bench_hough_rotation.py [--repeats 7]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)
sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from _harness import load_average, time_round_robin  # noqa: E402

from fsjax.ops.match3d._ghough3d import _ghough_core, _hough_args  # noqa: E402
from fsjax.ops.match3d._ghoughrot3d import _ghoughrot_core  # noqa: E402
from fsjax.synth._match3d_shape import _scene  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeats", type=int, default=7)
    args = ap.parse_args()
    print("load before", load_average(), flush=True)
    scene, tpl, _ = _scene("voxel", 0, True, None, False)
    _, _, arrays, static = _hough_args("bench", scene, tpl, 0.22, 4, None, 64, 15.0, 1.0, 0.3, 0.2, 512, 2 ** 20)
    lowered = {"generalised_hough3d": lambda: _ghough_core.lower(*arrays, **static),
               "generalised_hough_rotation_z3d": lambda: _ghoughrot_core.lower(*arrays, **static, n_angles=36,
                                                                               n_fine=4),
               "generalised_hough_rotation_z3d n_fine=0": lambda: _ghoughrot_core.lower(*arrays, **static,
                                                                                        n_angles=36, n_fine=0)}
    compiled = {}
    for name, low in lowered.items():
        lo = low()
        c0 = time.process_time()
        compiled[name] = lo.compile()
        print(f"{name}: compile {time.process_time() - c0:.2f} s CPU", flush=True)
    t = time_round_robin({n: (lambda c=c: jax.block_until_ready(c(*arrays))) for n, c in compiled.items()},
                         repeats=args.repeats, warmup=1)
    for n, tm in t.items():
        print(f"{n}: run median {tm.median:.3f} s (IQR {tm.iqr:.3f})", flush=True)
    print("load after", load_average(), flush=True)


if __name__ == "__main__":
    main()
