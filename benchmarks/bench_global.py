"""FPFH + RANSAC global registration beside Open3D, one process (issue 12, the global part).

The scene of ``fsjax.fit.global_reg._measure_global``: two independent area-weighted samples of the
Stanford Bunny cropped along x so that 70 % of each crop is shared, the source turned by 60 deg and
moved; no initial guess. fsjax ``global_registration(refine=None)`` (FPFH r = 25 mm, mutual
matches, 16,384 hypotheses, then the point refit) against Open3D 0.20 (normals of 10 neighbours,
FPFH with the same radius and 48 neighbours at most, ``registration_ransac_based_on_feature_matching``
with mutual filter, edge-length 0.9 and distance checkers, 100,000 iterations, confidence 0.999).
Errors are those of the global stage's pose, before any ICP.

Parts (each a flag; float64 throughout, as bench_icp's global part):

* ``--seeds K``: rotation error of fsjax and Open3D on crop pairs 0..K-1 of 2,000 points
  (RANSAC key = seed), median and max; with ``--ab COMMIT`` the library's
  ``fsjax/fit/global_reg.py`` at ``COMMIT`` runs beside the current one.
* ``--stages``: per-stage CPU and wall time (FPFH per cloud, matching, RANSAC, point refit, the
  whole call) and Open3D's (normals + FPFH per cloud, RANSAC), medians of ``--repeats``
  interleaved runs; with ``--ab``, the old whole call interleaved with the new.
* ``--n20k``: crops of ~20,000 points each, voxel-downsampled first as a user would
  (``fsjax.ops.voxel_downsample`` with a capacity of 4,096 slots; Open3D's ``voxel_down_sample``;
  ``--voxel`` metres), then the same FPFH + RANSAC; time includes the downsampling.

Run: ``python benchmarks/bench_global.py --seeds 10 --stages --n20k [--ab 2d75574]``.
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
from _harness import load_average  # noqa: E402

import fsjax  # noqa: E402
import fsjax.fit.global_reg as gr  # noqa: E402
from fsjax.fit import rotation_error_deg, rotation_from_axis_angle  # noqa: E402

RADIUS, DIST, HYP = 0.025, 0.01, 16384
KEEP = 1.0 / 1.3  # 70 % of each crop shared
R_TRUE = np.asarray(rotation_from_axis_angle(jnp.array([0.2, 1.0, 0.5]), 60.0))
SHIFT = np.array([0.05, 0.02, -0.03])


def scene(seed: int, n_points: int = 2600):
    xs, xt = gr._crop_pair(n_points, KEEP, seed)
    return (xs - SHIFT) @ R_TRUE, xt


def load_old(commit: str):
    """``fsjax/fit/global_reg.py`` at ``commit`` as ``fsjax.fit._global_reg_old`` (in ``sys.modules``
    before it runs: its equinox classes look their module up while being defined)."""
    import importlib.util
    import subprocess
    import tempfile

    name = "fsjax.fit._global_reg_old"
    text = subprocess.run(["git", "show", f"{commit}:fsjax/fit/global_reg.py"], cwd=Path(__file__).resolve().parents[1],
                          check=True, capture_output=True, text=True).stdout
    path = Path(tempfile.mkdtemp()) / "_global_reg_old.py"
    path.write_text(text)
    spec = importlib.util.spec_from_file_location(name, path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    spec.loader.exec_module(mod)
    return mod


def fs_call(mod, seed, src, tgt):
    return jax.block_until_ready(mod.global_registration(jax.random.key(seed), src, tgt, radius=RADIUS, distance=DIST,
                                                         n_hypotheses=HYP, refine=None))


def o3d_call(src, tgt, voxel=None, radius=RADIUS, dist=DIST):
    import open3d as o3d

    reg = o3d.pipelines.registration
    clouds = []
    for pts in (src, tgt):
        pc = o3d.geometry.PointCloud()
        pc.points = o3d.utility.Vector3dVector(pts)
        if voxel is not None:
            pc = pc.voxel_down_sample(voxel)
        pc.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(10))
        f = reg.compute_fpfh_feature(pc, o3d.geometry.KDTreeSearchParamHybrid(radius=radius, max_nn=48))
        clouds.append((pc, f))
    return reg.registration_ransac_based_on_feature_matching(
        clouds[0][0], clouds[1][0], clouds[0][1], clouds[1][1], True, dist,
        reg.TransformationEstimationPointToPoint(False), 3,
        [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9), reg.CorrespondenceCheckerBasedOnDistance(dist)],
        reg.RANSACConvergenceCriteria(100000, 0.999))


def err(rot) -> float:
    return float(rotation_error_deg(jnp.asarray(rot), jnp.asarray(R_TRUE)))


def seeds_part(k: int, old) -> None:
    rows = {"fsjax": [], "Open3D": []}
    if old is not None:
        rows["fsjax old"] = []
    for seed in range(k):
        src, tgt = scene(seed)
        s, t = jnp.asarray(src), jnp.asarray(tgt)
        res = fs_call(gr, seed, s, t)
        rows["fsjax"].append(err(res.coarse.R))
        line = f"seed {seed}: fsjax {rows['fsjax'][-1]:.3f} (matches only {err(res.coarse_matches_R):.3f})"
        if old is not None:
            o = fs_call(old, seed, s, t)
            rows["fsjax old"].append(err(o.coarse.R))
            diff = max(float(jnp.abs(o.coarse.R - res.coarse.R).max()), float(jnp.abs(o.coarse.t - res.coarse.t).max()))
            line += f"  old {rows['fsjax old'][-1]:.3f} (max |new - old| of R, t {diff:.1e})"
        rows["Open3D"].append(err(o3d_call(src, tgt).transformation[:3, :3]))
        print(line + f"  Open3D {rows['Open3D'][-1]:.3f} deg", flush=True)
    for name, v in rows.items():
        print(f"{name}: rotation error over seeds 0-{k - 1}: median {np.median(v):.3f}, max {max(v):.3f}, "
              f"min {min(v):.3f} deg")


def _timed(fn):
    c0, w0 = time.process_time(), time.perf_counter()
    fn()
    return time.perf_counter() - w0, time.process_time() - c0


def _interleaved(parts: dict, repeats: int) -> dict:
    """Each callable once (warm-up: compile), then ``repeats`` rounds in rotated order: (wall, CPU) lists."""
    for f in parts.values():
        f()
    res = {k: [] for k in parts}
    for r in range(repeats):
        names = list(parts)
        names = names[r % len(names):] + names[:r % len(names)]
        for k in names:
            res[k].append(_timed(parts[k]))
    return res


def stages_part(repeats: int, old) -> None:
    src, tgt = scene(0)
    s, t = jnp.asarray(src), jnp.asarray(tgt)
    key = jax.random.key(0)
    vs = vt = jnp.ones(s.shape[0], bool)
    fs_ = gr._fpfh(s, radius=RADIUS)
    ft_ = gr._fpfh(t, radius=RADIUS)
    idx, ok = gr.match_descriptors(fs_[0], ft_[0], fs_[1], ft_[1])
    coarse = gr.ransac_registration(key, s, t[idx], ok, distance=DIST, n_hypotheses=HYP)
    half = jnp.asarray(0.5 * DIST, s.dtype)
    parts = {
        "fsjax FPFH (source)": lambda: jax.block_until_ready(gr._fpfh(s, radius=RADIUS)),
        "fsjax FPFH (target)": lambda: jax.block_until_ready(gr._fpfh(t, radius=RADIUS)),
        "fsjax matching": lambda: jax.block_until_ready(gr.match_descriptors(fs_[0], ft_[0], fs_[1], ft_[1])),
        "fsjax RANSAC": lambda: jax.block_until_ready(
            gr.ransac_registration(key, s, t[idx], ok, distance=DIST, n_hypotheses=HYP)),
        "fsjax point refit": lambda: jax.block_until_ready(
            gr._point_refit(coarse, s, t, ft_[3], vs, vt & ~ft_[4], half, 10)),
        "fsjax whole call": lambda: fs_call(gr, 0, s, t),
        "Open3D whole call": lambda: o3d_call(src, tgt),
    }
    if old is not None:
        parts["fsjax old whole call"] = lambda: fs_call(old, 0, s, t)
    res = _interleaved(parts, repeats)
    print(f"stages, 2,000-point crops, medians of {repeats} interleaved runs (wall / CPU ms):")
    for k, v in res.items():
        a = np.array(v) * 1e3
        print(f"  {k:24s} {np.median(a[:, 0]):8.1f} / {np.median(a[:, 1]):8.1f}")


def n20k_part(repeats: int, voxel: float, seeds: int, old=None) -> None:
    cap = 4096
    down = jax.jit(lambda x: fsjax.ops.voxel_downsample(fsjax.Points(x), voxel=voxel, capacity=cap))

    def fs_run(seed, src, tgt, mod=gr):
        a, b = down(src), down(tgt)
        return a, b, jax.block_until_ready(mod.global_registration(jax.random.key(seed), a, b, radius=RADIUS,
                                                                   distance=DIST, n_hypotheses=HYP, refine=None))

    e_fs, e_o3 = [], []
    for seed in range(seeds):
        src, tgt = scene(seed, 26000)
        s, t = jnp.asarray(src), jnp.asarray(tgt)
        a, b, res = fs_run(seed, s, t)
        o = o3d_call(src, tgt, voxel=voxel)
        e_fs.append(err(res.coarse.R))
        e_o3.append(err(o.transformation[:3, :3]))
        if old is not None:
            print(f"20k seed {seed}: old fsjax {err(fs_run(seed, s, t, old)[2].coarse.R):.3f} deg")
        print(f"20k seed {seed}: {len(src)} / {len(tgt)} points -> fsjax {int(a.valid.sum())} / {int(b.valid.sum())} "
              f"(truncated {bool(a.truncated)} / {bool(b.truncated)}); fsjax {e_fs[-1]:.3f} deg "
              f"({int(res.coarse.n_inliers)} inliers), Open3D {e_o3[-1]:.3f} deg", flush=True)
    print(f"20k, voxel {voxel * 1e3:.1f} mm, seeds 0-{seeds - 1}: fsjax median {np.median(e_fs):.3f} max {max(e_fs):.3f}; "
          f"Open3D median {np.median(e_o3):.3f} max {max(e_o3):.3f} deg")
    src, tgt = scene(0, 26000)
    s, t = jnp.asarray(src), jnp.asarray(tgt)
    parts = {"fsjax 20k (downsample + FPFH + RANSAC + refit)": lambda: fs_run(0, s, t),
             "Open3D 20k (downsample + FPFH + RANSAC)": lambda: o3d_call(src, tgt, voxel=voxel)}
    if old is not None:
        parts["fsjax old 20k"] = lambda: fs_run(0, s, t, old)
    res = _interleaved(parts, repeats)
    for k, v in res.items():
        a = np.array(v) * 1e3
        print(f"  {k:48s} {np.median(a[:, 0]):8.1f} / {np.median(a[:, 1]):8.1f} ms (wall / CPU)")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, default=0)
    ap.add_argument("--stages", action="store_true")
    ap.add_argument("--n20k", action="store_true")
    ap.add_argument("--n20k-seeds", type=int, default=5)
    ap.add_argument("--voxel", type=float, default=0.004)
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--ab", default=None, help="git commit of the old fsjax/fit/global_reg.py to run beside")
    args = ap.parse_args()
    print(f"load before: {load_average()}", flush=True)
    old = load_old(args.ab) if args.ab else None
    if args.seeds:
        seeds_part(args.seeds, old)
    if args.stages:
        stages_part(args.repeats, old)
    if args.n20k:
        n20k_part(args.repeats, args.voxel, args.n20k_seeds, old)
    print(f"load after: {load_average()}")


if __name__ == "__main__":
    main()
