"""``fsjax sfm VIDEO.mp4`` on a video rendered by fsjax along a known orbit (docs/sfm.md, "Video").

The video: :func:`fsjax.synth.orbit_video` (textured boxes in a textured room, the camera orbiting
at 0.6 deg per frame at both ends and 3 deg in the middle), written as H.264 by
:func:`fsjax.sfm.video.write_video`. Measured:

* the rotation between consecutive frames (estimated on grey copies downsampled to 320 px) against
  the known poses: geodesic error per step, median and max;
* the chosen frames (threshold ``--rotation-deg``): the *known* rotation accumulated between
  consecutive chosen frames, beside the null of every k-th frame (as many frames);
* the whole command (``run_video``, as ``fsjax sfm VIDEO --intrinsics ...``): registered frames,
  rotation and centre errors after a similarity alignment to the known poses, time per stage.

Run ``python benchmarks/bench_sfm_video.py [--frames 60] [--size 384x256] [--rotation-deg 10]``; writes
``benchmarks/results/sfm_video.json`` and prints the figures quoted in ``docs/sfm.md``.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(ROOT))

from _harness import load_average, machine_info  # noqa: E402


def _angle(R):
    return np.degrees(np.arccos(np.clip((np.trace(R, axis1=-2, axis2=-1) - 1) / 2, -1, 1)))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--size", default="384x256")
    ap.add_argument("--rotation-deg", type=float, default=10.0)
    ap.add_argument("--out", default=None, help="output folder (default: a temporary one)")
    args = ap.parse_args(argv)
    from fsjax._cache import enable_compile_cache
    from fsjax.sfm.reconstruct import align_to_ground_truth
    from fsjax.sfm.video import (
        _scale_K,
        _small,
        consecutive_rotations,
        run_video,
        select_video_frames,
        write_video,
    )
    from fsjax.synth import orbit_video

    enable_compile_cache()
    w, h = (int(v) for v in args.size.split("x"))
    out = Path(args.out or tempfile.mkdtemp(prefix="fsjax_sfm_video_"))
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    d = orbit_video(args.frames, width=w, height=h)
    t_render = time.perf_counter() - t0
    video = write_video(out / "orbit.mp4", d["frames"], fps=10)
    R_rel = np.einsum("nji,njk->nik", d["R"][1:], d["R"][:-1])
    true = _angle(R_rel)

    # 1. steps and selection (the frames as the command sees them: decoded, downsampled to 320 px)
    from fsjax.sfm.video import read_video

    frames = read_video(video)
    small = [_small(f, 320) for f in frames]
    hs, ws = small[0].shape
    rot = consecutive_rotations(small, _scale_K(d["K"], (w, h), (ws, hs)))
    err = _angle(np.einsum("nji,njk->nik", rot.R, R_rel))
    sel = select_video_frames(rot, threshold_deg=args.rotation_deg)
    idx = sel.indices
    acc = np.array([true[a:b].sum() for a, b in zip(idx[:-1], idx[1:])])
    k = max(1, (args.frames - 1) // (len(idx) - 1))
    uni = np.arange(0, args.frames, k)
    acc_u = np.array([true[a:b].sum() for a, b in zip(uni[:-1], uni[1:])])

    # 2. the whole command
    fx, fy, cx, cy = d["K"][0, 0], d["K"][1, 1], d["K"][0, 2], d["K"][1, 2]
    t0 = time.perf_counter()
    rec, sel2 = run_video(video, out / "sfm", intrinsics=(fx, fy, cx, cy), threshold_deg=args.rotation_deg, log=print)
    t_run = time.perf_counter() - t0
    reg = [i for i in range(len(rec.names)) if rec.registered[i]]
    gi = sel2.indices[reg]
    rerr, cerr = align_to_ground_truth(rec.centres[reg], rec.R[reg], d["centres"][gi], d["R"][gi])
    res = {
        "machine": machine_info(), "load_average": load_average(),
        "video": {"frames": args.frames, "size": [w, h], "true_step_deg_min_max": [float(true.min()), float(true.max())],
                  "total_rotation_deg": float(true.sum()), "render_s": t_render},
        "steps": {"known": int(rot.known.sum()), "of": len(rot.known), "flags": sorted({f.split(" (")[0] for f in rot.flag}),
                  "error_deg_median": float(np.nanmedian(err)), "error_deg_max": float(np.nanmax(err)),
                  "size": list(rot.size), "times_s": rot.times_s},
        "selection": {"threshold_deg": args.rotation_deg, "indices": idx.tolist(),
                      "true_accumulated_deg": np.round(acc, 3).tolist(),
                      "estimated_accumulated_deg": np.round(sel.accumulated_deg[1:], 3).tolist(),
                      "null_every_k": int(k), "null_true_accumulated_deg": np.round(acc_u, 3).tolist()},
        "run": {"chosen": sel2.indices.tolist(), "registered": f"{len(reg)}/{len(rec.names)}",
                "rotation_error_deg_median_max": [float(np.median(rerr)), float(rerr.max())],
                "centre_error_median_max_pct_of_radius": [float(100 * np.median(cerr) / 3.0), float(100 * cerr.max() / 3.0)],
                "points": len(rec.points), "rms_px": rec.rms_px, "times_s": rec.times_s, "total_s": t_run},
    }
    (HERE / "results").mkdir(exist_ok=True)
    (HERE / "results" / "sfm_video.json").write_text(json.dumps(res, indent=1, default=float) + "\n")
    print(f"\nload average {res['load_average']}")
    print(f"steps: {rot.known.sum()}/{len(rot.known)} known on {ws}x{hs}; error median {np.nanmedian(err):.3f} "
          f"max {np.nanmax(err):.3f} deg (true steps {true.min():.2f}..{true.max():.2f} deg)")
    print(f"selection (threshold {args.rotation_deg:g} deg): {len(idx)} frames {idx.tolist()}")
    print(f"  known rotation between chosen frames: {np.round(acc, 2).tolist()} (|x - T| max {np.abs(acc - args.rotation_deg).max():.2f}, "
          f"sd {acc.std():.2f})")
    print(f"  null every {k}th: {np.round(acc_u, 2).tolist()} (|x - T| max {np.abs(acc_u - args.rotation_deg).max():.2f}, "
          f"sd {acc_u.std():.2f})")
    print(f"run: registered {len(reg)}/{len(rec.names)}, rotation error median/max {np.median(rerr):.3f}/{rerr.max():.3f} deg, "
          f"centre error median/max {np.median(cerr):.4f}/{cerr.max():.4f} (orbit radius 3), {len(rec.points)} points, "
          f"rms {rec.rms_px:.3f} px, {t_run:.1f} s; stages {json.dumps({k: round(v, 1) for k, v in rec.times_s.items()})}")
    print(f"report: {out / 'sfm' / 'report.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
