"""Tour section for evolution (issue 6): baselines first, a small GA, the locked split scored once.

:func:`measure_evolution` runs :func:`fsjax.evolve.run_problem` on the
``binarize`` problem (bright blobs under an illumination ramp, exact masks)
with a small vocabulary, one seed and a short GA, and returns the locked-split
IoU of every method. The null is the identity baseline (a fixed global
threshold at 0.5); the section also reports random search at equal budget and
the hand pipeline beside the evolved champion.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from pathlib import Path

import numpy as np

from fsjax.evolve import genome as G
from fsjax.evolve.problems import make_problem
from fsjax.evolve.runs import run_problem
from fsjax.evolve.search import GAConfig

from ._core import Section, _panel

__all__ = ["measure_evolution", "SECTIONS", "TOUR_VOCABULARY"]

#: A small vocabulary for the tour (fast to compile); the library default is larger.
TOUR_VOCABULARY = ("gaussian", "box_filter", "top_hat", "gamma", "invert", "threshold", "otsu", "local_mean",
                   "region_open", "region_close", "remove_small")


@functools.lru_cache(maxsize=2)
def measure_evolution(quick: bool = True) -> dict:
    """Baselines, GA and refinement on ``binarize``; locked-split IoU of every method and a champion output.

    Deterministic (fixed data and GA seeds), so the result is cached per ``quick``.
    """
    import jax.numpy as jnp

    import fsjax

    size = (32, 32) if quick else (48, 48)
    pr = make_problem("binarize", size=size, n_train=6 if quick else 12, n_holdout=3 if quick else 6,
                      n_locked=9 if quick else 18, n_stages=4)
    cfg = GAConfig(pop=16, gens=6 if quick else 15, elite=2)
    rep = run_problem(pr, seeds=[0], cfg=cfg, vocabulary=TOUR_VOCABULARY, refine_steps=6, progress=False,
                      dtype=np.float64)
    s = rep.seeds[0]
    stages = G.pipeline_stages(s.champion["stages"])
    x = pr.locked.inputs[0]
    y = fsjax.pipeline(stages)(fsjax.Image(jnp.asarray(x))).data if stages else x > 0.5
    return {
        "report": rep, "problem": pr, "image": x, "truth": pr.locked.targets[0], "output": np.asarray(y),
        "identity": rep.baselines["identity"].locked, "single": rep.baselines["single"].locked,
        "hand": rep.baselines["hand"].locked, "random": s.random.locked, "evolved": s.evolved.locked,
        "refined": s.refined.locked, "refine_method": s.refine_method,
        "champion": [st["op"] for st in s.champion["stages"]], "evaluations": cfg.pop * cfg.gens,
        "trajectory": [g.best_train for g in s.log],
    }


def evolution(out: Path, quick: bool) -> Section:
    r = measure_evolution(quick)
    fig = _panel(out / "evolution.png", [r["image"], r["truth"], r["output"]],
                 ["locked input", "true mask", "evolved champion"])
    chain = " -> ".join(r["champion"])
    return Section(
        title="Evolution: a typed pipeline searched by a GA, scored on a locked split",
        truth=(f"{len(r['problem'].locked)} locked images of bright blobs under an illumination ramp (noise sd "
               f"0.06), exact masks; selection on {len(r['problem'].train)} train images only"),
        rows=[("identity (null): global threshold 0.5", f"IoU {r['identity']:.3f}"),
              ("best single op (knobs on a 5 x 5 grid)", f"IoU {r['single']:.3f}"),
              ("hand pipeline (gaussian, local_mean, region_open)", f"IoU {r['hand']:.3f}"),
              (f"random search ({r['evaluations']} genomes)", f"IoU {r['random']:.3f}"),
              (f"GA, same budget: {chain}", f"IoU {r['evolved']:.3f}"),
              (f"GA + knob refinement ({r['refine_method']})", f"IoU {r['refined']:.3f}")],
        fsjax_figure=f"IoU {r['refined']:.3f}", null_figure=f"IoU {r['identity']:.3f}",
        beats_null=r["refined"] > r["identity"], figure=fig,
        notes="A tiny run (one seed, pop 16); docs/evolution.md has the four problems with seed spread.",
    )


SECTIONS: list[Callable[[Path, bool], Section]] = [evolution]
