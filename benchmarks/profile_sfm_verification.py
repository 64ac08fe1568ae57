"""Cost of geometric verification per stage on a real set: the essential-matrix RANSAC
(``relative_pose``) and the homography RANSAC (``homography_ransac``) on every pair with >= 30
matches, compiled, interleaved, median of repeats (wall and process CPU); and each pair's H / E
inlier ratio (the planar / pure-rotation rule of ``fsjax.sfm.reconstruct`` flags >= 0.9).

    python benchmarks/profile_sfm_verification.py [--set fountain-P11] [--repeats 3]
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from fsjax.fit.twoview import homography_ransac, relative_pose
from fsjax.sfm.export import load_image_dir
from fsjax.sfm.features import detect_and_describe
from fsjax.sfm.matching import match_pairs
from fsjax.sfm.reconstruct import _bucket, _pad, grey_image
from fsjax.sfm.run import load_ground_truth

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "sfm"
if not DATA.exists():
    DATA = Path("/work/shared/data/sfm")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--set", default="fountain-P11")
    ap.add_argument("--repeats", type=int, default=3)
    a = ap.parse_args()
    names, imgs = load_image_dir(DATA / a.set)
    K = load_ground_truth(DATA / a.set / "cameras.json")[names[0]][0]
    feats = [detect_and_describe(jnp.asarray(grey_image(im))) for im in imgs]
    n_kp = _bucket(max(int(f.valid.sum()) for f in feats), 256, linear=True)
    uv = [np.asarray(f.uv, np.float64)[:n_kp] for f in feats]
    n = len(imgs)
    pairs = np.array([(i, j) for i in range(n) for j in range(i + 1, n)], np.int32)
    M = np.asarray(match_pairs(jnp.stack([f.descriptors[:n_kp] for f in feats]),
                               jnp.stack([f.valid[:n_kp] for f in feats]), jnp.asarray(pairs)))
    jobs = []
    for p, (i, j) in enumerate(pairs):
        m = np.nonzero(M[p] >= 0)[0]
        if len(m) >= 30:
            pad = min(n_kp, _bucket(len(m), 256))
            jobs.append((p, jnp.asarray(_pad(uv[i][m], pad)), jnp.asarray(_pad(uv[j][M[p][m]], pad))))
    key = jax.random.PRNGKey(0)
    Kj = jnp.asarray(K)

    counts = {}

    def run_e():
        for p, u1, u2 in jobs:
            r = relative_pose(jax.random.fold_in(key, p), u1, u2, Kj, threshold_px=1.5, n_hypotheses=512)
            counts[p, "E"] = int(jax.block_until_ready(r.n_inliers))

    def run_h():
        for p, u1, u2 in jobs:
            r = homography_ransac(jax.random.fold_in(key, 100_000 + p), u1, u2, threshold_px=np.sqrt(5.99 / 3.84) * 1.5,
                                  n_hypotheses=256)  # as fsjax.sfm.reconstruct: half of E's 512
            counts[p, "H"] = int(jax.block_until_ready(r.n_inliers))

    times = {"E": [], "H": []}
    run_e(), run_h()  # compile
    for r in range(a.repeats):
        for nm, f in (("E", run_e), ("H", run_h)) if r % 2 == 0 else (("H", run_h), ("E", run_e)):
            w, c = time.perf_counter(), time.process_time()
            f()
            times[nm].append((time.perf_counter() - w, time.process_time() - c))
    for nm, v in times.items():
        v = np.array(v)
        print(f"{a.set}: {nm} RANSAC on {len(jobs)} pairs: wall {np.median(v[:, 0]):.2f} s, CPU {np.median(v[:, 1]):.2f} s "
              f"(median of {a.repeats}; all wall {np.round(v[:, 0], 2).tolist()})")
    rows = sorted(((counts[p, "H"] / counts[p, "E"], *pairs[p], counts[p, "E"], counts[p, "H"]) for p, *_ in jobs
                   if counts[p, "E"] >= 30), reverse=True)
    print(f"H / E inlier ratio over {len(rows)} pairs with >= 30 E inliers: median {np.median([r[0] for r in rows]):.2f}; "
          "largest: " + ", ".join(f"{i}-{j} {q:.2f} ({e} E, {h} H)" for q, i, j, e, h in rows[:6]))


if __name__ == "__main__":
    main()
