"""Where the reconstruction stage of :func:`fsjax.sfm.reconstruct` spends its time, this tree against a
baseline commit, in one process, interleaved.

The stages before it (features, matching, verification) are memoised (same inputs, same outputs), so
each repeat times the incremental reconstruction: PnP registrations, triangulation, bundle
adjustments. For each version: the number of bundle-adjustment (BA) calls, their compiled shapes
(points, observations, observation pairs) and iterations, BA and PnP time, the reconstruction
stage's wall time and the whole call's CPU time (medians over the repeats), and the accuracy
against the ground truth (similarity-aligned, as ``bench_sfm.py``). The first call of each version
compiles (reported apart).

Run ``python benchmarks/profile_sfm_reconstruction.py [--set herzjesu-P8] [--baseline main] [--repeats 5]``.
"""

from __future__ import annotations

import argparse
import hashlib
import importlib.util
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(ROOT))

DATA = ROOT.parent / "shared" / "data" / "sfm"
if not DATA.exists():
    DATA = Path("/work/shared/data/sfm")


def _baseline_modules(rev):
    """The baseline's reconstruct.py and bundle.py loaded as modules of the fsjax.sfm package."""
    import fsjax.sfm  # noqa: F401

    tmp = Path(tempfile.mkdtemp())
    mods = {}
    for name in ("bundle", "reconstruct"):
        src = subprocess.run(["git", "show", f"{rev}:fsjax/sfm/{name}.py"], cwd=ROOT, capture_output=True, text=True,
                             check=True).stdout
        src = src.replace("from .bundle import", "from ._baseline_bundle import")
        path = tmp / f"_baseline_{name}.py"
        path.write_text(src)
        spec = importlib.util.spec_from_file_location(f"fsjax.sfm._baseline_{name}", path)
        mod = importlib.util.module_from_spec(spec)
        sys.modules[spec.name] = mod
        spec.loader.exec_module(mod)
        mods[name] = mod
    return mods["reconstruct"]


def _digest(args, kwargs):
    h = hashlib.sha1()
    for a in list(args) + sorted(kwargs.items()):
        if isinstance(a, tuple) and len(a) == 2 and isinstance(a[0], str):
            h.update(a[0].encode())
            a = a[1]
        try:
            h.update(np.ascontiguousarray(np.asarray(a)).tobytes())
        except (TypeError, ValueError):
            h.update(repr(a).encode())
    return h.hexdigest()


class _Instrument:
    """Memoises the front stages of a reconstruct module and records its BA / PnP calls."""

    memo: dict = {}

    def __init__(self, mod):
        import jax

        self.calls = []
        for fn in ("detect_and_describe", "match_pairs", "relative_pose"):
            orig = getattr(mod, fn)

            def memo(*a, _orig=orig, _fn=fn, **k):
                key = (_fn, _digest(a, k))
                if key not in _Instrument.memo:
                    _Instrument.memo[key] = jax.block_until_ready(_orig(*a, **k))
                return _Instrument.memo[key]

            setattr(mod, fn, memo)
        ba, pnp = mod.bundle_adjust_masked, mod.solve_pnp_ransac

        def ba_wrap(*a, **k):
            t0 = time.perf_counter()
            out = jax.block_until_ready(ba(*a, **k))
            pairs = k.get("obs_pairs")
            self.calls.append(dict(kind="ba", shape=(a[3].shape[0], a[4].shape[0], None if pairs is None else pairs.shape[0]),
                                   active=int(np.asarray(a[7]).astype(bool).sum()), max_iter=int(k.get("max_iter", 0)),
                                   iterations=int(out[4]), s=time.perf_counter() - t0))
            return out

        def pnp_wrap(*a, **k):
            t0 = time.perf_counter()
            out = jax.block_until_ready(pnp(*a, **k))
            self.calls.append(dict(kind="pnp", shape=(a[1].shape[0],), inliers=int(out.n_inliers),
                                   s=time.perf_counter() - t0))
            return out

        mod.bundle_adjust_masked, mod.solve_pnp_ransac = ba_wrap, pnp_wrap


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--set", default="herzjesu-P8")
    ap.add_argument("--baseline", default="main", help="git revision whose reconstruct.py / bundle.py are compared")
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args(argv)
    sys.path.insert(0, str(HERE))
    from _harness import load_average

    from fsjax.sfm import align_to_ground_truth
    from fsjax.sfm.export import load_image_dir
    from fsjax.sfm.run import load_ground_truth

    new = sys.modules["fsjax.sfm.reconstruct"]
    old = _baseline_modules(args.baseline)
    gt = load_ground_truth(DATA / args.set / "cameras.json")
    names, imgs = load_image_dir(DATA / args.set)
    K = gt[names[0]][0]
    print(f"{args.set}: baseline {args.baseline} vs this tree; load {load_average()} (pid {os.getpid()})")
    versions = {"baseline": (old, _Instrument(old)), "new": (new, _Instrument(new))}
    stats = {v: dict(rec_s=[], ba_s=[], cpu_s=[], first=None) for v in versions}
    # the baseline's first call fills the memo of the front stages and compiles the baseline's programs
    stats["baseline"]["first"] = dict(rec_s=old.reconstruct(imgs, K, names=names).times_s["reconstruction"])
    for r in range(args.repeats + 1):
        for v in (("baseline", "new") if r % 2 == 0 else ("new", "baseline")):
            mod, ins = versions[v]
            ins.calls.clear()
            c0 = time.process_time()
            rec = mod.reconstruct(imgs, K, names=names)
            cpu = time.process_time() - c0
            st = stats[v]
            if r == 0:  # the new version's first call compiles its programs; the baseline's warm-up
                if v == "new":
                    st["first"] = dict(rec_s=rec.times_s["reconstruction"])
                continue
            st["rec_s"].append(rec.times_s["reconstruction"])
            st["ba_s"].append(rec.times_s["bundle_adjustment"])
            st["cpu_s"].append(cpu)
            st["calls"] = list(ins.calls)
            idx = np.nonzero(rec.registered)[0]
            rot, cen = align_to_ground_truth(rec.centres[idx], rec.R[idx], np.array([gt[names[i]][2] for i in idx]),
                                             np.array([gt[names[i]][1] for i in idx]))
            st["acc"] = (f"{len(idx)}/{len(names)} registered, rotation {np.median(rot):.3f} / {rot.max():.3f} deg, "
                         f"centre {1000 * np.median(cen):.1f} / {1000 * cen.max():.1f} mm, {len(rec.points)} points, "
                         f"rms {rec.rms_px:.3f} px")
    for v, st in stats.items():
        calls = st["calls"]
        bas = [c for c in calls if c["kind"] == "ba"]
        print(f"\n{v}: reconstruction {np.median(st['rec_s']):.3f} s wall (BA {np.median(st['ba_s']):.3f} s), "
              f"whole call {np.median(st['cpu_s']):.3f} s CPU, medians of {args.repeats}; first call's reconstruction "
              f"(compiles) {st['first']['rec_s']:.2f} s wall")
        print(f"  {st['acc']}")
        print(f"  BA calls {len(bas)}, distinct shapes (points, observations, pairs) "
              f"{sorted({c['shape'] for c in bas}, key=str)}; PnP calls "
              f"{sum(c['kind'] == 'pnp' for c in calls)}, {sum(c['s'] for c in calls if c['kind'] == 'pnp'):.3f} s "
              "(last repeat)")
        for c in calls:
            if c["kind"] == "ba":
                print(f"    BA {c['shape']} active obs {c['active']}, {c['iterations']}/{c['max_iter']} it, {c['s']:.3f} s")
            else:
                print(f"    PnP {c['shape']}, {c['inliers']} inliers, {c['s']:.3f} s")
    print(f"\nload {load_average()}")


if __name__ == "__main__":
    main()
