"""Baselines measured before evolution: identity (the null), best single op, the hand pipeline.

Random search at equal budget is the fourth baseline; it depends on the seed
and lives in :func:`fsjax.evolve.search.random_search`.

* ``identity``: the problem's null stages (:attr:`Problem.null`): the input
  itself for ``denoise``, a fixed global threshold at 0.5 for the mask problems.
* ``best single op``: every op of the single-op skeleton's first stage
  (``Image -> Image`` or ``Image -> Region``; ``count_obj`` after it for
  ``count``) with its knobs on a ``grid x grid`` lattice (a one-knob op on
  ``grid`` values, a knob-less op once); all candidates are scored on train
  in population calls and the best by train fitness is kept.
* ``hand``: the problem's hand-written pipeline (:attr:`Problem.hand`).

Every candidate is scored per image on train, holdout and locked; choices use
train only.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ..pipeline import pipeline
from ..registry import get_op
from ..types import Image
from .genome import IDENTITY, STATE_SORTS, Skeleton, champion_record
from .population import Evaluator
from .problems import Problem
from .search import score_genomes, search_batch

__all__ = ["Candidate", "score_pipeline", "pipeline_candidate", "best_single_op", "genome_candidate"]


@dataclasses.dataclass
class Candidate:
    """A scored method: mean fitness on each split, and its stages by op name."""

    name: str
    stages: list[Any]  # stage dicts {op, a, b, params} or fsjax.pipeline stage forms
    train: float
    holdout: float
    locked: float

    def as_row(self) -> dict[str, Any]:
        return {"method": self.name, "train": self.train, "holdout": self.holdout, "locked": self.locked}


def score_pipeline(problem: Problem, stages: Sequence[Any], x: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Per-image fitness ``(N,)`` of a fixed pipeline (``fsjax.pipeline`` stages; empty = identity)."""
    metric, floor = problem.metric_fn, problem.floor
    if len(stages):
        pipe = pipeline(list(stages))
        if pipe.takes is not Image or pipe.gives is not problem.gives:
            raise ValueError(f"score_pipeline: pipeline maps {pipe.takes.__name__} -> {pipe.gives.__name__}, "
                             f"problem {problem.name!r} needs Image -> {problem.gives.__name__}")
        field = STATE_SORTS[pipe.gives]

        def run(xi):
            return getattr(pipe(Image(xi)), field)
    else:
        if problem.gives is not Image:
            raise ValueError(f"score_pipeline: the empty pipeline gives Image, {problem.name!r} needs "
                             f"{problem.gives.__name__}")

        def run(xi):
            return xi

    @jax.jit
    def f(x, t):
        v = jax.vmap(lambda xi, ti: metric(run(xi), ti))(x, t)
        return jnp.where(jnp.isfinite(v), v, floor)

    return np.asarray(f(jnp.asarray(x), jnp.asarray(t)))


def pipeline_candidate(name: str, problem: Problem, stages: Sequence[Any], dtype: Any = np.float32) -> Candidate:
    """Score a fixed pipeline on every split (train and holdout in one call, locked in another)."""
    x, t, ntr = search_batch(problem, dtype)
    v = score_pipeline(problem, stages, x, t)
    lk = score_pipeline(problem, stages, problem.locked.inputs.astype(dtype), problem.locked.targets)
    return Candidate(name, [_stage_str(s) for s in stages], float(v[:ntr].mean()), float(v[ntr:].mean()),
                     float(lk.mean()))


def _stage_str(s: Any) -> Any:
    if isinstance(s, str):
        return {"op": s}
    if isinstance(s, (tuple, list)) and len(s) == 2 and isinstance(s[1], dict):
        return {"op": s[0], "params": dict(s[1])}
    if isinstance(s, (tuple, list)):
        return {"op": s[0], "knobs": list(s[1:])}
    return s


def genome_candidate(name: str, problem: Problem, sk: Skeleton, ev: Evaluator, ops: np.ndarray,
                     knobs: np.ndarray, pop: int, dtype: Any = np.float32) -> Candidate:
    """Score one genome on every split with the skeleton's population program (padded to ``pop``)."""
    x, t, ntr = search_batch(problem, dtype)
    v = score_genomes(ev, ops[None], knobs[None], x, t, pop)[0]
    lk = score_genomes(ev, ops[None], knobs[None], problem.locked.inputs.astype(dtype), problem.locked.targets,
                       pop)[0]
    return Candidate(name, champion_record(sk, ops, knobs)["stages"], float(v[:ntr].mean()),
                     float(v[ntr:].mean()), float(lk.mean()))


def best_single_op(problem: Problem, vocabulary: Sequence[str] | None = None, *, grid: int = 5, pop: int = 64,
                   dtype: Any = np.float32, devices: list | None = None) -> Candidate:
    """The best single op of the vocabulary for the problem, knobs searched on a grid (train only)."""
    sk = problem.skeleton(vocabulary, sorts=problem.single_sorts)
    ev = Evaluator(sk, problem.metric_fn, floor=problem.floor, devices=devices)
    vals = np.linspace(0.0, 1.0, grid)
    ops, knobs = [], []
    for i, name in enumerate(sk.vocabs[0]):
        if name == IDENTITY:
            continue
        nk = len(get_op(name).knobs)
        pts = [(0.5, 0.5)] if nk == 0 else [(a, 0.5) for a in vals] if nk == 1 else [(a, b) for a in vals
                                                                                      for b in vals]
        for a, b in pts:
            o = np.zeros(sk.n_stages, np.int32)
            o[0] = i
            k = np.full((sk.n_stages, 2), 0.5)
            k[0] = (a, b)
            ops.append(o)
            knobs.append(k)
    ops, knobs = np.stack(ops), np.stack(knobs)
    x, t, ntr = search_batch(problem, dtype)
    fit = score_genomes(ev, ops, knobs, x, t, pop)[:, :ntr].mean(axis=1)
    j = int(np.argmax(fit))
    c = genome_candidate("best single op", problem, sk, ev, ops[j], knobs[j], pop, dtype)
    c.stages = [s for s in c.stages if s["op"] != IDENTITY]
    return c
