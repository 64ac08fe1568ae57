"""The genetic algorithm, random search at equal budget, and knob refinement of a champion.

Selection reads the *train* split only. Each generation evaluates the
population once, in one call, on the train images and the held-out images
together (fitness is per image, so the held-out columns cannot influence the
train columns); the train columns are averaged into the selection fitness and
the held-out columns only go into the log (:class:`GenLog`). The functions
that choose parents and survivors (:func:`next_generation`) never receive the
held-out numbers. ``tests/evolve/test_search.py`` poisons the held-out split
and checks that the whole train trajectory and the champion are unchanged.

Determinism: every random choice comes from a NumPy generator seeded from the
JAX ``key`` (``jax.random.key_data``), so a run is a pure function of the key,
the problem and the configuration.

Operators (all type-preserving, because every genome of a skeleton has the same
stage signatures and a stage's op index always ranges over that stage's
vocabulary):

* tournament selection (size ``tournament``) on train fitness;
* one-point crossover of whole stages (op and knobs travel together);
* mutation: per stage, with probability ``p_op`` the op is redrawn from the
  stage's vocabulary (its knobs redrawn uniformly); with probability ``p_knob``
  each knob gets Gaussian noise (sd ``knob_sigma``), reflected into ``[0, 1]``;
* elitism: the ``elite`` best genomes pass unchanged.

The budget is counted in genome evaluations on the train split: a GA run of
``gens`` generations of ``pop`` genomes costs ``gens * pop`` (the initial
population is generation 1); :func:`random_search` gets exactly that many.
"""

from __future__ import annotations

import dataclasses
import time
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .genome import IDENTITY, Skeleton, random_population
from .population import Evaluator
from .problems import Problem

__all__ = ["GAConfig", "GenLog", "SearchResult", "evolve", "random_search", "next_generation", "refine",
           "RefineResult", "numpy_rng",
           "score_genomes", "search_batch"]


@dataclasses.dataclass(frozen=True)
class GAConfig:
    """GA settings (see the module docstring)."""

    pop: int = 64
    gens: int = 40
    tournament: int = 3
    elite: int = 2
    p_crossover: float = 0.7
    p_op: float | None = None  # default 1 / n_stages
    p_knob: float = 0.3
    knob_sigma: float = 0.15

    def __post_init__(self):
        if self.pop < 2 or self.gens < 1:
            raise ValueError(f"GAConfig: need pop >= 2 and gens >= 1, got pop={self.pop}, gens={self.gens}")
        if not 0 <= self.elite < self.pop:
            raise ValueError(f"GAConfig: elite must be in [0, pop), got {self.elite}")
        if not 1 <= self.tournament <= self.pop:
            raise ValueError(f"GAConfig: tournament must be in [1, pop], got {self.tournament}")


@dataclasses.dataclass(frozen=True)
class GenLog:
    """One generation: train fitness (best, mean), held-out fitness of the train-best genome."""

    gen: int
    best_train: float
    mean_train: float
    holdout_of_best: float
    evaluations: int
    seconds: float


@dataclasses.dataclass
class SearchResult:
    """Champion (by train fitness) of a GA or random search run."""

    ops: np.ndarray
    knobs: np.ndarray
    train: float
    log: list[GenLog]
    evaluations: int
    seconds: float


def numpy_rng(key: Any) -> np.random.Generator:
    """A NumPy generator seeded from a JAX key (typed or raw ``uint32[2]``)."""
    data = jax.random.key_data(key) if jnp.issubdtype(getattr(key, "dtype", None), jax.dtypes.prng_key) else key
    return np.random.default_rng(np.asarray(data, dtype=np.uint32).ravel().tolist())


def score_genomes(ev: Evaluator, ops: np.ndarray, knobs: np.ndarray, x: Any, t: Any, pop: int) -> np.ndarray:
    """Per-image fitness ``(n, N)`` of ``n`` genomes, evaluated in chunks of exactly ``pop``.

    Every call has the same population shape, so the evaluator compiles once; the
    last chunk is padded with copies of its first genome and the padding dropped.
    """
    ops = np.asarray(ops, np.int32)
    knobs = np.asarray(knobs, float)
    n = ops.shape[0]
    out = []
    for i in range(0, n, pop):
        o, k = ops[i:i + pop], knobs[i:i + pop]
        m = o.shape[0]
        if m < pop:
            o = np.concatenate([o, np.repeat(o[:1], pop - m, 0)])
            k = np.concatenate([k, np.repeat(k[:1], pop - m, 0)])
        out.append(ev(o, k, x, t)[:m])
    return np.concatenate(out)


def search_batch(problem: Problem, dtype: Any = np.float32) -> tuple[np.ndarray, np.ndarray, int]:
    """The images every search call evaluates: train then holdout, and the number of train images.

    Using one batch shape for the GA, random search, refinement and the single-op
    baseline means one compiled program per skeleton; only the first ``n_train``
    columns of a result may be used for any choice.
    """
    x = np.concatenate([problem.train.inputs, problem.holdout.inputs]).astype(dtype)
    t = np.concatenate([problem.train.targets, problem.holdout.targets])
    return x, t, len(problem.train)


def _reflect(x: np.ndarray) -> np.ndarray:
    x = np.mod(x, 2.0)
    return np.where(x > 1.0, 2.0 - x, x)


def next_generation(rng: np.random.Generator, sk: Skeleton, ops: np.ndarray, knobs: np.ndarray,
                    train_fitness: np.ndarray, cfg: GAConfig) -> tuple[np.ndarray, np.ndarray]:
    """Elitism + tournament selection + crossover + mutation, from *train* fitness only."""
    P, S = ops.shape
    order = np.argsort(-train_fitness, kind="stable")
    new_ops = [ops[order[:cfg.elite]]]
    new_knobs = [knobs[order[:cfg.elite]]]
    n_child = P - cfg.elite

    def pick(n):
        cand = rng.integers(0, P, size=(n, cfg.tournament))
        return cand[np.arange(n), np.argmax(train_fitness[cand], axis=1)]

    pa, pb = pick(n_child), pick(n_child)
    c_ops, c_knobs = ops[pa].copy(), knobs[pa].copy()
    cross = rng.uniform(size=n_child) < cfg.p_crossover
    cut = rng.integers(1, S, size=n_child) if S > 1 else np.ones(n_child, int)
    take_b = cross[:, None] & (np.arange(S)[None, :] >= cut[:, None])
    c_ops = np.where(take_b, ops[pb], c_ops)
    c_knobs = np.where(take_b[..., None], knobs[pb], c_knobs)
    p_op = 1.0 / S if cfg.p_op is None else cfg.p_op
    swap = rng.uniform(size=(n_child, S)) < p_op
    new_idx = np.stack([rng.integers(0, k, size=n_child) for k in sk.sizes], axis=1)
    c_ops = np.where(swap, new_idx, c_ops).astype(np.int32)
    c_knobs = np.where(swap[..., None], rng.uniform(size=(n_child, S, 2)), c_knobs)
    jig = rng.uniform(size=(n_child, S, 2)) < cfg.p_knob
    c_knobs = np.where(jig, _reflect(c_knobs + rng.normal(0.0, cfg.knob_sigma, size=c_knobs.shape)), c_knobs)
    return np.concatenate(new_ops + [c_ops]), np.concatenate(new_knobs + [c_knobs])


def _progress(total: int, desc: str, enabled: bool):
    if not enabled:
        return None
    from tqdm.auto import tqdm

    return tqdm(total=total, desc=desc, leave=False)


def evolve(key: Any, problem: Problem, sk: Skeleton, ev: Evaluator, cfg: GAConfig | None = None, *,
           progress: bool = True, dtype: Any = np.float32) -> SearchResult:
    """Run the GA on ``problem``'s train split; track the held-out split in the log only.

    Args:
      key: JAX PRNG key (the run is a pure function of it).
      problem: the problem (its ``train`` and ``holdout`` splits are used).
      sk: the skeleton; ``ev`` must be an :class:`Evaluator` of the same skeleton and metric.
      cfg: GA settings.
      progress: show a tqdm progress bar.
      dtype: image dtype of the evaluation (float32 by default for speed).

    Returns:
      :class:`SearchResult` with the best genome by train fitness over the whole run.
    """
    cfg = GAConfig() if cfg is None else cfg
    if ev.sk != sk:
        raise ValueError("evolve: the evaluator was built for another skeleton")
    rng = numpy_rng(key)
    x, t, ntr = search_batch(problem, dtype)
    ops, knobs = random_population(rng, sk, cfg.pop)
    best = (-np.inf, None, None)
    log: list[GenLog] = []
    bar = _progress(cfg.gens, f"evolve {problem.name}", progress)
    t_start = time.perf_counter()
    for g in range(cfg.gens):
        per_image = ev(ops, knobs, x, t)
        fit = per_image[:, :ntr].mean(axis=1)  # selection fitness: train columns only
        hold = per_image[:, ntr:].mean(axis=1)  # tracked, never passed to selection
        i = int(np.argmax(fit))
        if fit[i] > best[0]:
            best = (float(fit[i]), ops[i].copy(), knobs[i].copy())
        log.append(GenLog(g + 1, float(fit[i]), float(fit.mean()), float(hold[i]), (g + 1) * cfg.pop,
                          time.perf_counter() - t_start))
        if bar is not None:
            bar.set_postfix(train=f"{fit[i]:.4g}", holdout=f"{hold[i]:.4g}")
            bar.update(1)
        if g + 1 < cfg.gens:
            ops, knobs = next_generation(rng, sk, ops, knobs, fit, cfg)
    if bar is not None:
        bar.close()
    return SearchResult(best[1], best[2], best[0], log, cfg.gens * cfg.pop, time.perf_counter() - t_start)


def random_search(key: Any, problem: Problem, sk: Skeleton, ev: Evaluator, budget: int, *, batch: int = 64,
                  progress: bool = False, dtype: Any = np.float32) -> SearchResult:
    """Uniform random genomes of ``sk``, ``budget`` evaluations on train in batches; best by train fitness.

    Each batch is one evaluator call on the same image batch as the GA (train and
    holdout), of which only the train columns are read.
    """
    if budget < 1:
        raise ValueError(f"random_search: budget must be >= 1, got {budget}")
    rng = numpy_rng(key)
    x, t, ntr = search_batch(problem, dtype)
    best = (-np.inf, None, None)
    done = 0
    t_start = time.perf_counter()
    bar = _progress(budget, f"random {problem.name}", progress)
    while done < budget:
        n = min(batch, budget - done)
        ops, knobs = random_population(rng, sk, batch)
        fit = ev(ops, knobs, x, t)[:n, :ntr].mean(axis=1)  # fixed batch shape: one compile
        i = int(np.argmax(fit))
        if fit[i] > best[0]:
            best = (float(fit[i]), ops[i].copy(), knobs[i].copy())
        done += n
        if bar is not None:
            bar.update(n)
    if bar is not None:
        bar.close()
    return SearchResult(best[1], best[2], best[0], [], budget, time.perf_counter() - t_start)


# ---------------------------------------------------------------------------
# knob refinement
# ---------------------------------------------------------------------------


@dataclasses.dataclass
class RefineResult:
    """Refined knobs of a champion; ``method`` is ``"grad"`` or ``"local"``; train fitness before/after."""

    knobs: np.ndarray
    train_before: float
    train_after: float
    method: str
    steps: int


def _differentiable(problem: Problem, sk: Skeleton, ops: np.ndarray) -> bool:
    from ..registry import get_op

    if problem.metric != "psnr":  # IoU, F1 and counts are piecewise constant in the knobs
        return False
    for s, i in enumerate(ops):
        name = sk.vocabs[s][int(i)]
        if name != IDENTITY and get_op(name).knobs and not get_op(name).differentiable:
            return False
    return True


def refine(key: Any, problem: Problem, sk: Skeleton, ev: Evaluator, ops: np.ndarray, knobs: np.ndarray, *,
           steps: int = 30, pop: int = 64, dtype: Any = np.float32) -> RefineResult:
    """Refine a champion's knobs on the train split (its ops fixed).

    Where the metric and every knob-carrying op of the champion are
    differentiable, projected gradient ascent (Adam, learning rate 0.02, knobs
    clipped to ``[0, 1]``) with ``jax.grad`` through the champion's compiled
    :func:`fsjax.pipeline` (knobs as its ``(n_stages, 2)`` argument). Otherwise a
    local search batched like the population: each round evaluates ``pop``
    Gaussian perturbations of the current knobs in one evaluator call and keeps
    the best, halving the step after a round without improvement. Either way the
    knobs are only replaced when the train fitness improves, and only train
    columns are read.
    """
    import optax

    from ..pipeline import pipeline
    from .genome import decode, pipeline_stages

    rng = numpy_rng(key)
    x, t, ntr = search_batch(problem, dtype)
    ops = np.asarray(ops, np.int32)
    knobs = np.asarray(knobs, float)

    def train_fit(kn: np.ndarray) -> np.ndarray:
        return score_genomes(ev, np.repeat(ops[None], kn.shape[0], 0), kn, x, t, pop)[:, :ntr].mean(axis=1)

    before = float(train_fit(knobs[None])[0])
    real = [s for s in range(sk.n_stages) if sk.vocabs[s][int(ops[s])] != IDENTITY]
    if real and _differentiable(problem, sk, ops):
        from ..types import Image

        pipe = pipeline(pipeline_stages(decode(sk, ops, knobs)))
        xj, tj = jnp.asarray(x[:ntr]), jnp.asarray(t[:ntr], dtype)

        @jax.jit
        def value_and_grad(k):
            def f(k):
                y = jax.vmap(lambda xi: pipe(Image(xi), k).data)(xj)
                return jnp.mean(jax.vmap(problem.metric_fn)(y, tj))

            return jax.value_and_grad(f)(k)

        opt = optax.adam(0.02)
        k = jnp.asarray(knobs[real], dtype)
        state = opt.init(k)
        trail = []
        for _ in range(steps):
            _, g = value_and_grad(k)
            if not bool(jnp.all(jnp.isfinite(g))):
                break
            upd, state = opt.update(-g, state)
            k = jnp.clip(optax.apply_updates(k, upd), 0.0, 1.0)
            kv = knobs.copy()
            kv[real] = np.asarray(k, float)
            trail.append(kv)
        best_k, best_v = knobs, before
        if trail:
            fits = train_fit(np.stack(trail))  # score the whole trail in population calls
            i = int(np.argmax(fits))
            if fits[i] > best_v:
                best_k, best_v = trail[i], float(fits[i])
        return RefineResult(best_k, before, best_v, "grad", len(trail))
    best_k, best_v, sigma = knobs, before, 0.1
    rounds = max(1, steps // 3)
    for _ in range(rounds):
        cand = _reflect(best_k[None] + rng.normal(0, sigma, size=(pop,) + knobs.shape))
        cand[0] = best_k
        fit = train_fit(cand)
        i = int(np.argmax(fit))
        if fit[i] > best_v:
            best_k, best_v = cand[i], float(fit[i])
        else:
            sigma *= 0.5
    return RefineResult(best_k, before, best_v, "local", rounds)
