"""Robust runs: baselines first, then the GA over several seeds, the locked split scored at the end.

:func:`run_problem` is the whole discipline in one function:

1. build the skeleton (an empty stage vocabulary raises here) and check the
   problem has a hand pipeline (a missing baseline aborts the run);
2. measure the seed-independent baselines -- identity, best single op (knobs
   on a grid), hand pipeline -- and abort unless all three are present and
   finite;
3. for every seed: random search with the GA's evaluation budget, the GA
   (train for selection, holdout tracked), knob refinement of the champion
   (train only);
4. score every method once on the locked split and summarise across seeds
   (min / mean / max / std; how many seeds beat the hand pipeline and the best
   single op on the locked split).

:func:`write_run` writes ``champion.json`` (by op names and knobs, per seed),
``baselines.md`` (the table) and ``log.csv`` (per generation and seed).
"""

from __future__ import annotations

import csv
import dataclasses
import json
import math
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import jax
import numpy as np

from .baselines import Candidate, best_single_op, genome_candidate, pipeline_candidate
from .genome import DEFAULT_VOCABULARY, champion_record
from .population import Evaluator
from .problems import Problem
from .search import GAConfig, GenLog, evolve, random_search, refine

__all__ = ["SeedResult", "RunReport", "run_problem", "write_run", "BaselineMissingError"]


class BaselineMissingError(RuntimeError):
    """A run was asked to evolve without every baseline measured."""


@dataclasses.dataclass
class SeedResult:
    """One seed: random search, GA champion and refined champion (scored on all splits), the GA log."""

    seed: int
    random: Candidate
    evolved: Candidate
    refined: Candidate
    refine_method: str
    log: list[GenLog]
    champion: dict[str, Any]
    seconds: float


@dataclasses.dataclass
class RunReport:
    """Everything a run measured; :meth:`table` is the baseline/evolution table on the locked split."""

    problem: str
    metric: str
    skeleton: str
    vocabulary: tuple[str, ...]
    config: GAConfig
    baselines: dict[str, Candidate]
    seeds: list[SeedResult]
    compile_seconds: float
    seconds: float

    def spread(self, method: str, split: str = "locked") -> dict[str, float]:
        """min / mean / max / std across seeds of ``method`` (``random``, ``evolved``, ``refined``)."""
        v = np.array([getattr(getattr(s, method), split) for s in self.seeds])
        return {"min": float(v.min()), "mean": float(v.mean()), "max": float(v.max()), "std": float(v.std())}

    def beats(self, method: str, baseline: str, split: str = "locked") -> int:
        """Seeds whose ``method`` scores strictly above baseline ``baseline`` on ``split``."""
        ref = getattr(self.baselines[baseline], split)
        return sum(getattr(getattr(s, method), split) > ref for s in self.seeds)

    def table(self) -> str:
        """Markdown table: one row per method, locked score (seed spread), holdout and train."""
        n = len(self.seeds)
        lines = [f"| method | locked ({self.metric}) | holdout | train | seeds > hand | seeds > best single |",
                 "|---|---|---|---|---|---|"]
        for key, label in (("identity", "identity (null)"), ("single", "best single op"), ("hand", "hand pipeline")):
            c = self.baselines[key]
            lines.append(f"| {label} | {c.locked:.4g} | {c.holdout:.4g} | {c.train:.4g} | - | - |")
        for key, label in (("random", "random search (equal budget)"), ("evolved", "evolved (GA)"),
                           ("refined", "evolved + knob refinement")):
            lk, ho, tr = (self.spread(key, s) for s in ("locked", "holdout", "train"))
            lines.append(f"| {label} | {lk['mean']:.4g} (min {lk['min']:.4g}, max {lk['max']:.4g}, sd "
                         f"{lk['std']:.2g}) | {ho['mean']:.4g} | {tr['mean']:.4g} | {self.beats(key, 'hand')}/{n} | "
                         f"{self.beats(key, 'single')}/{n} |")
        return "\n".join(lines)

    def best_seed(self) -> SeedResult:
        """The seed whose refined champion has the best *train* fitness (never chosen on locked data)."""
        return max(self.seeds, key=lambda s: s.refined.train)


def _finite(c: Candidate | None) -> bool:
    return c is not None and all(math.isfinite(v) for v in (c.train, c.holdout, c.locked))


def run_problem(problem: Problem, *, seeds: Sequence[int] = (0,), cfg: GAConfig | None = None,
                vocabulary: Sequence[str] | None = None, refine_steps: int = 30, progress: bool = True,
                dtype: Any = np.float32, devices: list | None = None) -> RunReport:
    """Baselines, then GA + random search + refinement for each seed; see the module docstring.

    Args:
      problem: the problem (see :mod:`fsjax.evolve.problems`).
      seeds: one independent run per seed (``jax.random.key(seed)``).
      cfg: GA settings; random search gets ``cfg.gens * cfg.pop`` evaluations.
      vocabulary: op names searched (``None``: :data:`fsjax.evolve.genome.DEFAULT_VOCABULARY`).
      refine_steps: gradient steps (or 3 steps per local-search round).
      progress: tqdm bars for the GA.
      dtype: evaluation dtype.
      devices: devices to shard population calls over (``None``: all).

    Raises:
      ValueError: an empty stage vocabulary (before anything runs).
      BaselineMissingError: the problem has no hand pipeline, or a baseline is not finite.
    """
    cfg = GAConfig() if cfg is None else cfg
    t_start = time.perf_counter()
    seeds = list(seeds)
    if not seeds:
        raise ValueError("run_problem: need at least one seed")
    sk = problem.skeleton(vocabulary)
    if not problem.hand:
        raise BaselineMissingError(f"run_problem: problem {problem.name!r} has no hand pipeline; every run "
                                   f"measures identity, best single op, hand and random search first")
    base = {
        "identity": pipeline_candidate("identity", problem, problem.null, dtype),
        "single": best_single_op(problem, vocabulary, pop=cfg.pop, dtype=dtype, devices=devices),
        "hand": pipeline_candidate("hand pipeline", problem, problem.hand, dtype),
    }
    missing = [k for k in ("identity", "single", "hand") if not _finite(base.get(k))]
    if missing:
        raise BaselineMissingError(f"run_problem: baseline(s) {missing} missing or not finite; not evolving")
    ev = Evaluator(sk, problem.metric_fn, floor=problem.floor, devices=devices)
    from .search import search_batch

    x, t, _ = search_batch(problem, dtype)
    probe_ops = np.zeros((cfg.pop, sk.n_stages), np.int32)
    ev.compiled(probe_ops, np.full((cfg.pop, sk.n_stages, 2), 0.5), x, t)  # compile apart, timed
    compile_s = sum(ev.compile_seconds.values())
    results = []
    for seed in seeds:
        ts = time.perf_counter()
        k_rand, k_ga, k_ref = jax.random.split(jax.random.key(seed), 3)
        rs = random_search(k_rand, problem, sk, ev, cfg.gens * cfg.pop, batch=cfg.pop, dtype=dtype)
        rand = genome_candidate("random search", problem, sk, ev, rs.ops, rs.knobs, cfg.pop, dtype)
        ga = evolve(k_ga, problem, sk, ev, cfg, progress=progress, dtype=dtype)
        evo = genome_candidate("evolved", problem, sk, ev, ga.ops, ga.knobs, cfg.pop, dtype)
        rf = refine(k_ref, problem, sk, ev, ga.ops, ga.knobs, steps=refine_steps, pop=cfg.pop, dtype=dtype)
        ref = genome_candidate("evolved + refinement", problem, sk, ev, ga.ops, rf.knobs, cfg.pop, dtype)
        champ = champion_record(sk, ga.ops, rf.knobs, seed=seed, problem=problem.name, metric=problem.metric,
                                train=ref.train, holdout=ref.holdout, locked=ref.locked,
                                unrefined_knobs=np.asarray(ga.knobs).tolist(), refine_method=rf.method)
        results.append(SeedResult(seed, rand, evo, ref, rf.method, ga.log, champ, time.perf_counter() - ts))
    return RunReport(problem.name, problem.metric, sk.describe(),
                     tuple(DEFAULT_VOCABULARY if vocabulary is None else vocabulary), cfg, base, results,
                     compile_s, time.perf_counter() - t_start)


def write_run(report: RunReport, out: str | Path) -> dict[str, Path]:
    """Write ``champion.json``, ``baselines.md`` and ``log.csv`` into ``out``; return their paths."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    best = report.best_seed()
    champ = {"problem": report.problem, "metric": report.metric, "skeleton": report.skeleton,
             "best_seed_by_train": best.seed, "champion": best.champion,
             "per_seed": [s.champion for s in report.seeds], "config": dataclasses.asdict(report.config),
             "vocabulary": list(report.vocabulary)}
    paths = {"champion": out / "champion.json", "baselines": out / "baselines.md", "log": out / "log.csv"}
    paths["champion"].write_text(json.dumps(champ, indent=2))
    head = (f"# {report.problem}: baselines and evolution\n\nskeleton `{report.skeleton}`, "
            f"{len(report.seeds)} seed(s), pop {report.config.pop} x {report.config.gens} generations; "
            f"scores are means over the images of each split ({report.metric}, higher is better); "
            f"compile {report.compile_seconds:.1f} s, run {report.seconds:.1f} s.\n\n")
    paths["baselines"].write_text(head + report.table() + "\n")
    with open(paths["log"], "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["seed", "gen", "best_train", "mean_train", "holdout_of_best", "evaluations", "seconds"])
        for s in report.seeds:
            for g in s.log:
                w.writerow([s.seed, g.gen, g.best_train, g.mean_train, g.holdout_of_best, g.evaluations,
                            round(g.seconds, 3)])
    return paths
