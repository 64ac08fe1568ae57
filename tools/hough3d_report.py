"""Figures behind hough_planes3d / hough_spheres3d (issue 17, detection column), printed.

Run: python tools/hough3d_report.py [--quick]

1. Five scenes of tests/ops/test_hough3d.py (three planes, a sphere, 300 clutter points, noise
   0.004): the Hough ops' errors and steady-state run time, beside sequential RANSAC
   (fsjax.fit.ransac: a plane, its inliers removed, three times; one sphere on all points;
   threshold 0.012 = 3 sigma, min_inlier_fraction 0.1).
2. Noise sweep on seed 0: where each op stops accepting (fails closed).
3. Uniform clouds (10 seeds, 2,150 and 6,000 points): accepted surfaces, also with
   min_support = 0 (the band and excess gates alone).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import fsjax  # noqa: E402
from fsjax.fit import ransac  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "ops"))
from test_hough3d import PLANE_KW, SPHERE_KW, plane_errors, scene  # noqa: E402


def _run(f, *a, **kw):
    jax.block_until_ready(f(*a, **kw))
    t = time.perf_counter()
    r = jax.block_until_ready(f(*a, **kw))
    return r, time.perf_counter() - t


def seeds(n):
    for seed in range(n):
        xyz, valid, planes, (c, r) = scene(seed)
        P = fsjax.Points(xyz, valid=valid)
        hp, tp = _run(fsjax.ops.hough_planes3d, P, **PLANE_KW)
        hs, ts = _run(fsjax.ops.hough_spheres3d, P, **SPHERE_KW)
        e = plane_errors(hp, planes)
        row = np.asarray(hs.table[0])
        print(f"seed {seed} hough : planes {int(hp.valid.sum())}, max angle {e[:, 0].max():.3f} deg, max offset "
              f"{e[:, 1].max():.4f} | spheres {int(hs.valid.sum())}, centre {np.linalg.norm(row[:3] - c):.4f}, "
              f"radius {abs(row[3] - r):.4f} | run {tp * 1e3:.0f} / {ts * 1e3:.0f} ms")
        v = jnp.asarray(valid)
        found = []
        for i in range(3):
            res = ransac(jax.random.PRNGKey(10 * seed + i), jnp.asarray(xyz), "plane", threshold=0.012, valid=v,
                         min_inlier_fraction=0.1)
            if not bool(res.converged):
                break
            found.append((np.array([res["nx"], res["ny"], res["nz"]], float), float(res["d"])))
            v = v & ~res.inliers
        errs = np.array([min(((np.degrees(np.arccos(min(1.0, abs(n @ m)))), abs(np.sign(n @ m) * dd - d))
                              for m, dd in found), default=(np.inf, np.inf)) for n, d in planes])
        rs = ransac(jax.random.PRNGKey(seed), jnp.asarray(xyz), "sphere", threshold=0.012, valid=jnp.asarray(valid),
                    min_inlier_fraction=0.1)
        q = np.asarray(rs.params)
        print(f"       ransac: planes {len(found)}, max angle {errs[:, 0].max():.3f} deg, max offset "
              f"{errs[:, 1].max():.4f} | sphere converged {bool(rs.converged)}, centre "
              f"{np.linalg.norm(q[:3] - c):.4f}, radius {abs(q[3] - r):.4f}")


def noise():
    for s in (0.004, 0.008, 0.010, 0.012, 0.014, 0.016, 0.02, 0.03):
        xyz, valid, planes, (c, r) = scene(noise=s)
        P = fsjax.Points(xyz, valid=valid)
        hp = fsjax.ops.hough_planes3d(P, **PLANE_KW)
        hs = fsjax.ops.hough_spheres3d(P, **SPHERE_KW)
        t = np.asarray(hp.table)[np.asarray(hp.valid)]
        ang = [min(np.degrees(np.arccos(min(1.0, abs(n @ row[:3])))) for n, _ in planes) for row in t]
        row = np.asarray(hs.table[0])
        print(f"noise {s:.3f}: planes {len(t)} (worst accepted {max(ang, default=np.nan):.3f} deg) | spheres "
              f"{int(hs.valid.sum())}, centre {np.linalg.norm(row[:3] - c):.4f}, radius {abs(row[3] - r):.4f}")


def uniform(n_seeds):
    for n in (2150, 6000):
        for ms in (0.5, 0.0):
            a = b = 0
            for seed in range(n_seeds):
                U = fsjax.Points(np.random.default_rng(100 + seed).uniform(-1, 1, (n, 3)))
                a += int(fsjax.ops.hough_planes3d(U, max_planes=4, min_support=ms).valid.sum())
                b += int(fsjax.ops.hough_spheres3d(U, r_min=0.1, r_max=0.6, max_spheres=3,
                                                   min_support=ms).valid.sum())
            print(f"uniform N {n}, {n_seeds} clouds, min_support {ms}: planes accepted {a}, spheres accepted {b}")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="2 scene seeds, 3 uniform clouds")
    args = ap.parse_args()
    seeds(2 if args.quick else 5)
    noise()
    uniform(3 if args.quick else 10)


if __name__ == "__main__":
    main()
