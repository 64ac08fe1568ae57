"""Unknown focal length (issue 14): ``fsjax sfm`` without intrinsics on the Strecha sets, the
self-calibrated focal length (``fsjax.sfm.focal``) against the ground truth ``K_full[0, 0] / 4``
(see ``../shared/data/sfm/README.md``), and the camera errors after similarity alignment.

Run ``python benchmarks/bench_sfm_focal.py [--sets fountain-P11,herzjesu-P8]``; writes
``benchmarks/results/sfm_focal.json`` and prints one Markdown row per set (quoted in docs/sfm.md).
"""
from __future__ import annotations

import argparse
import json
import os
import tempfile
from pathlib import Path

from fsjax.sfm.run import evaluate, load_ground_truth, run_folder

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "sfm"
if not DATA.is_dir():  # a worktree outside the project's parent folder
    DATA = Path("/work/shared/data/sfm")


def main():
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--sets", default="fountain-P11,herzjesu-P8")
    ap.add_argument("--data", default=str(DATA))
    a = ap.parse_args()
    rows = {}
    for s in a.sets.split(","):
        d = Path(a.data) / s
        gt = json.loads((d / "cameras.json").read_text())
        f_gt = gt["cameras"][0]["K_full"][0][0] / gt["downsample"]
        with tempfile.TemporaryDirectory() as out:
            rec = run_folder(d, out, log=lambda m: None)
        ev = evaluate(rec, load_ground_truth(d / "cameras.json"))
        f = float(rec.K[0, 0])
        rows[s] = dict(focal_px=f, focal_gt_px=f_gt, error_percent=100 * (f - f_gt) / f_gt,
                       guess_px=rec.focal["guess_px"], load=os.getloadavg()[0],
                       **{k: v for k, v in ev.items() if not k.startswith("_")})
        r = rows[s]
        print(f"| {s} | {f:.1f} | {f_gt:.2f} | {r['error_percent']:+.2f} % | {r['guess_px']:.0f} "
              f"({100 * (r['guess_px'] - f_gt) / f_gt:+.0f} %) | " + " | ".join(str(v) for k, v in ev.items()
                                                                             if not k.startswith("_")) + " |",
              flush=True)
    res = Path(__file__).resolve().parent / "results" / "sfm_focal.json"
    res.write_text(json.dumps(rows, indent=1, default=str) + "\n")


if __name__ == "__main__":
    main()
