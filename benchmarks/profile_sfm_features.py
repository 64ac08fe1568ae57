"""Where the features' time goes: each stage of :func:`fsjax.sfm.detect_and_describe` as its own
compiled program on one photograph, CPU time (``time.process_time``, all threads) and wall time,
medians of ``--repeats`` interleaved rounds in one process (compiled first, untimed).

Stages (the module's private pieces, so the split follows the code): scale space (upsampling, base
blur, Gaussian octaves, DoG), extrema (3x3x3 test on the inner scales), candidate selection
(``_select``: the per-octave strongest candidates), refinement (Newton steps of the candidates), final
selection (the ``n_max`` strongest refined), gradients (``_grads`` per octave), orientation and
descriptor (on the eager path's bucket of rows), and the two whole programs the eager path runs.

Run ``python benchmarks/profile_sfm_features.py [--image fountain-P11/0005.jpg] [--repeats 7]``.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
sys.path.insert(0, str(HERE))

from _harness import load_average  # noqa: E402

DATA = HERE.parent.parent / "shared" / "data" / "sfm"
if not DATA.exists():
    DATA = Path("/work/shared/data/sfm")


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--image", default="fountain-P11/0005.jpg")
    ap.add_argument("--repeats", type=int, default=7)
    args = ap.parse_args(argv)

    import cv2
    import jax
    import jax.numpy as jnp

    from fsjax.sfm import features as F

    img = jnp.asarray(cv2.imread(str(DATA / args.image), cv2.IMREAD_GRAYSCALE).astype(np.float32) / 255)
    contrast = jnp.asarray(0.04, jnp.float32)
    n_max, n_oct = 4096, 5

    # scale space: every octave's Gaussian stack and DoG
    def scale_space(im):
        im = F._upsample2(im)
        base = F._blur(im, math.sqrt(F._SIGMA0 ** 2 - 1.0))
        out = []
        for _ in range(n_oct):
            G = F._octave(base)
            out.append((G, G[1:] - G[:-1]))
            base = G[F._S][::2, ::2]
        return out

    ss = jax.jit(scale_space)
    pyr = jax.block_until_ready(ss(img))
    Ds = [d for _, d in pyr]
    Gs = [g for g, _ in pyr]

    ext = jax.jit(lambda Ds: [F._extrema_score(D, 0.5 * contrast / F._S) for D in Ds])
    scores = jax.block_until_ready(ext(Ds))
    n_scores = sum(int(s.size) for s in scores)

    # the whole detection program and the eager describe program
    kp_full = lambda: F._keypoints_jit(img, contrast, n_max, n_oct, True)  # noqa: E731
    gx, gy, kp, n_pass = jax.block_until_ready(kp_full())
    cap = F._capacity(kp[-1], n_max)
    desc_full = lambda: F._describe_jit(gx, gy, kp, n_pass, img.dtype, True, n_max, cap)  # noqa: E731
    jax.block_until_ready(desc_full())

    sel_fn = getattr(F, "_select_candidates", None)
    stages = {"scale space": lambda: ss(img), "extrema": lambda: ext(Ds)}
    if sel_fn is not None:
        sel = jax.jit(lambda sc, Ds: sel_fn(sc, Ds, contrast, n_max, True))
        stages["candidate selection"] = lambda: sel(scores, Ds)
    else:
        def topk(sc):
            out = []
            for o, s in enumerate(sc):
                c = min(max(n_max >> max(o - 1, 0), 64), s.size)
                out.append(jax.lax.top_k(s.ravel(), c))
            return out
        tk = jax.jit(topk)
        stages["candidate top-k"] = lambda: tk(scores)
    # refinement and final selection on the detection program's own candidates (rebuilt here)
    def cands(sc):
        out = []
        offD = 0
        for o, (s, D) in enumerate(zip(sc, Ds)):
            H, W = D.shape[1:]
            hi, wi = H - 10, W - 10
            c = min(max(n_max >> max(o - 1, 0), 64), s.size)
            val, idx = jax.lax.top_k(s.ravel(), c)
            full = lambda v, c=c: jnp.full((c,), v, jnp.int32)  # noqa: E731
            out.append((val, idx // (hi * wi) + 1, (idx // wi) % hi + 5, idx % wi + 5, full(offD), full(H), full(W)))
            offD += D.size
        return [jnp.concatenate(a) for a in zip(*out)]
    cv = jax.block_until_ready(jax.jit(cands)(scores))
    Dflat = jnp.concatenate([D.ravel() for D in Ds])
    ref = jax.jit(lambda cv: F._refine(Dflat, cv[4], cv[5], cv[6], cv[1], cv[2], cv[3], contrast))
    stages[f"refinement ({cv[0].shape[0]} candidates)"] = lambda: ref(cv)
    rr = jax.block_until_ready(ref(cv))
    fin = jax.jit(lambda resp, ok: jax.lax.top_k(jnp.where(ok, resp, -1.0), n_max))
    stages["final top-k"] = lambda: fin(rr[3], rr[4] & (cv[0] > 0))
    xr, yr, sr, resp, oc, oG, H, W, v = (a[:cap] for a in kp)
    sig = F._SIGMA0 * 2.0 ** (sr / F._S)
    lvl = jnp.clip(jnp.round(sr), 1, F._S + 1).astype(jnp.int32) - 1
    pyrk = (oG[:, None], H[:, None], W[:, None], lvl[:, None])
    ori = jax.jit(lambda: F._orientation(gx, gy, pyrk, xr, yr, sig))
    th = jax.block_until_ready(ori())
    stages[f"orientation ({cap} rows)"] = ori
    des = jax.jit(lambda: F._descriptor(gx, gy, pyrk, xr, yr, sig, th))
    stages[f"descriptor ({cap} rows)"] = des
    gr = jax.jit(lambda Gs: [F._grads(G[1:F._S + 2]) for G in Gs])
    stages["gradients"] = lambda: gr(Gs)
    stages["detection program (eager path)"] = kp_full
    stages["describe program (eager path)"] = desc_full
    for f in stages.values():
        jax.block_until_ready(f())

    cpu = {k: [] for k in stages}
    wall = {k: [] for k in stages}
    names = list(stages)
    for r in range(args.repeats):
        for k in names[r % len(names):] + names[:r % len(names)]:
            c0, w0 = time.process_time(), time.perf_counter()
            jax.block_until_ready(stages[k]())
            cpu[k].append(time.process_time() - c0)
            wall[k].append(time.perf_counter() - w0)
    print(f"{args.image}: {int(kp[-1].sum())} valid keypoints, {n_pass} passed, describe rows {cap}, "
          f"{n_scores} extremum scores; load {load_average()}")
    print("| stage | CPU (s) | wall (s) |\n|---|---|---|")
    for k in names:
        print(f"| {k} | {np.median(cpu[k]):.3f} | {np.median(wall[k]):.3f} |")


if __name__ == "__main__":
    main()
