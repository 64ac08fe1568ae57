"""Cross-structure registration: a CAD mesh against a partial scan, fsjax vs Open3D, in one process.

Workload (issue 17, "CAD mesh vs partial point scan at 50 deg via FPFH"): ``fsjax.synth.cad_scan_pair``
(Hoppe's fandisk; a one-sided scan of 60,000 independent samples by a point z-buffer, range noise
0.1 % of the size, turned 50 deg and moved), seeds 0-2. Both pipelines get the same inputs: the
mesh's 20,000 area-weighted samples (``fsjax.ops.sample_surface``, seed 0) and the scan's points.

* fsjax: ``register_cross(mesh, scan, voxel=2 % of the size, overlap=0.5)`` -- voxel thinning,
  FPFH + correspondence RANSAC (16,384 hypotheses) + point refit, trimmed point-to-plane ICP on the
  dense sets.
* Open3D: ``voxel_down_sample`` (same voxel), normals from 10 neighbours, ``compute_fpfh_feature``
  (same radius, 48 neighbours at most), ``registration_ransac_based_on_feature_matching`` (mutual
  filter, edge-length 0.9 and distance checkers, 100,000 iterations, confidence 0.999), then
  point-to-plane ``registration_icp`` on the dense sets (gate 3 voxels, 50 iterations).

Steady-state medians (round robin), fsjax's first call (compile) apart, rotation error per seed;
printed as a Markdown table (docs/registration.md quotes it).
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

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _harness import load_average, machine_info, time_round_robin  # noqa: E402

import fsjax  # noqa: E402
from fsjax.fit import register_cross, rotation_error_deg  # noqa: E402
from fsjax.synth import cad_scan_pair  # noqa: E402


def open3d_pipeline(model_xyz, scan_xyz, voxel):
    import open3d as o3d

    reg = o3d.pipelines.registration
    radius, dist = 5 * voxel, 1.5 * voxel
    dense, thin, feats = [], [], []
    for pts in (model_xyz, scan_xyz):
        pc = o3d.geometry.PointCloud()
        pc.points = o3d.utility.Vector3dVector(np.array(pts, dtype=np.float64))
        pc.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(10))
        dense.append(pc)
        d = pc.voxel_down_sample(voxel)
        d.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(10))
        thin.append(d)
        feats.append(reg.compute_fpfh_feature(d, o3d.geometry.KDTreeSearchParamHybrid(radius=radius, max_nn=48)))
    coarse = reg.registration_ransac_based_on_feature_matching(
        thin[0], thin[1], feats[0], feats[1], True, dist, reg.TransformationEstimationPointToPoint(False), 3,
        [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9), reg.CorrespondenceCheckerBasedOnDistance(dist)],
        reg.RANSACConvergenceCriteria(100000, 0.999))
    fine = reg.registration_icp(dense[0], dense[1], 2 * dist, coarse.transformation,
                                reg.TransformationEstimationPointToPlane(),
                                reg.ICPConvergenceCriteria(max_iteration=50))
    return coarse.transformation, fine.transformation


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    load0 = load_average()
    info = machine_info()
    rows = []
    for seed in range(args.seeds):
        pair = cad_scan_pair("fandisk", angle_deg=50.0, seed=seed)
        voxel = 0.02 * pair["diag"]
        model = np.asarray(fsjax.ops.sample_surface(pair["mesh"], n=20000, seed=0).xyz)
        scan = fsjax.Points(jnp.asarray(pair["scan"]))
        R = jnp.asarray(pair["R"])

        def fs(mesh=pair["mesh"], scan=scan, voxel=voxel):
            return jax.block_until_ready(register_cross(mesh, scan, voxel=voxel, overlap=0.5))

        def o3(model=model, scan_xyz=pair["scan"], voxel=voxel):
            return open3d_pipeline(model, scan_xyz, voxel)

        t0 = time.perf_counter()
        res = fs()
        first = time.perf_counter() - t0
        oc, of = o3()
        tim = time_round_robin({"fsjax": fs, "Open3D": o3}, repeats=args.repeats, warmup=0)
        row = {"seed": seed, "n_scan": len(pair["scan"]), "fsjax_s": tim["fsjax"].median, "fsjax_first_s": first,
               "open3d_s": tim["Open3D"].median,
               "fsjax_coarse_deg": float(rotation_error_deg(res.coarse.R, R)),
               "fsjax_deg": float(rotation_error_deg(res.refined.R, R)), "fsjax_converged": bool(res.converged),
               "open3d_coarse_deg": float(rotation_error_deg(jnp.asarray(oc[:3, :3]), R)),
               "open3d_deg": float(rotation_error_deg(jnp.asarray(of[:3, :3]), R))}
        rows.append(row)
        print(row, flush=True)
    load1 = load_average()
    print(f"machine: {info.get('cpu', '?')}, {info.get('cores', '?')} cores; load {load0} -> {load1}")
    print("| seed | scan points | fsjax [s] (first call) | Open3D [s] | ratio | fsjax coarse / final [deg] | "
          "Open3D coarse / final [deg] |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['seed']} | {r['n_scan']} | {r['fsjax_s']:.2f} ({r['fsjax_first_s']:.1f}) | {r['open3d_s']:.2f} | "
              f"{r['fsjax_s'] / r['open3d_s']:.1f}x | {r['fsjax_coarse_deg']:.3f} / {r['fsjax_deg']:.4f} | "
              f"{r['open3d_coarse_deg']:.3f} / {r['open3d_deg']:.4f} |")


if __name__ == "__main__":
    main()
