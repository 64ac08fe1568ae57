"""The fuzz loop, coverage, the minimiser, replay and the report."""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import json
import math
import os
import random
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from ._gen import REPEAT_REDRAWS, Chain, DrawState, SortGraph, generate_chain
from ._run import CLASSES, Outcome, Runner

__all__ = ["FuzzRun", "fuzz", "load_journal", "minimise", "replay", "write_report", "temporary_ops", "pool_sorts",
           "BLOCKING"]

# the fraction of chains also compiled whole (every chain runs through the per-stage programs)
WHOLE_CHAIN_FRACTION = 0.05

# Worker processes (``fuzz(workers >= 2)``, ``fsjax fuzz``) compile every program at XLA's backend
# (LLVM) optimisation level 0, the eager way's op-by-op primitives and the ops' own jit programs
# included (the stage programs always are: ``STAGE_COMPILER_OPTIONS``). Cold, the eager way is over
# half of a chain's CPU and nearly all of it compiling; level 0 cut the CPU of the same 20 chains by
# 16 % (docs/fuzz.md). HLO passes run as usual and LLVM at level 0 keeps IEEE semantics; what the
# eager way no longer exercises is LLVM's optimised code of the ops' programs: the chains compiled
# whole (``whole_chain_fraction``) still compile at XLA's default level (``WHOLE_COMPILER_OPTIONS``).
# An in-process run (``workers=1``) leaves the process's XLA flags alone.
WORKER_XLA_FLAGS = "--xla_backend_optimization_level=0"


def _worker_xla_flags(current: str | None) -> str:
    """``XLA_FLAGS`` for a worker process: the parent's flags plus ``WORKER_XLA_FLAGS`` (a level the
    parent sets explicitly is kept)."""
    current = (current or "").strip()
    if "--xla_backend_optimization_level" in current:
        return current
    return (current + " " + WORKER_XLA_FLAGS).strip()


# classes a CI fuzz fails on (the goal: 0 of each)
BLOCKING = ("SUSPECT", "TYPEMISS", "MISMATCH", "SILENT_OVERFLOW", "GRADNAN")


@contextlib.contextmanager
def temporary_ops():
    """Context manager: ops registered inside it are removed from the registry on exit.

    For planted ops in tests (and experiments): ``with temporary_ops(): register(...)(fn)``.
    """
    from fsjax import registry

    registry.list_ops()  # every family loaded before the snapshot
    saved = dict(registry._REGISTRY)
    try:
        yield
    finally:
        registry._REGISTRY.clear()
        registry._REGISTRY.update(saved)


def pool_sorts(specs: Sequence[Any]) -> set[type]:
    """Sorts among the ops' inputs that :func:`fsjax.synth.standard_input` can build."""
    from fsjax.registry import list_ops
    from fsjax.synth._pool import _POOL

    list_ops()  # op families register the pool builders of the sorts they introduce
    # membership, not a build: standard_input(t) is defined exactly for the sorts in its pool
    return {t for s in specs for t in s.takes if t in _POOL}


@dataclasses.dataclass
class FuzzRun:
    """Everything a fuzz run found: per-chain outcomes, signatures, coverage, timing."""

    seed: int
    max_length: int
    specs: dict[str, Any]
    graph: SortGraph
    results: list[tuple[Chain, Outcome]] = dataclasses.field(default_factory=list)
    minimised: dict[str, Chain] = dataclasses.field(default_factory=dict)
    seconds: float = 0.0
    cpu_seconds: float = 0.0        # process CPU time while running chains (the machine may be shared)
    minimise_seconds: float = 0.0
    stopped_early: str = ""
    whole_chain_fraction: float = 0.0
    stats: dict = dataclasses.field(default_factory=dict)   # the runner's cache figures

    # -- figures ---------------------------------------------------------------
    @property
    def failures(self) -> list[tuple[Chain, Outcome]]:
        return [(c, o) for c, o in self.results if o.status == "failed"]

    def class_counts(self) -> dict[str, int]:
        c = collections.Counter(o.cls for _, o in self.failures)
        return {k: c.get(k, 0) for k in CLASSES}

    def signatures(self) -> dict[str, list[tuple[Chain, Outcome]]]:
        out: dict[str, list] = {}
        for c, o in self.failures:
            out.setdefault(o.signature, []).append((c, o))
        return out

    def blocking(self) -> dict[str, int]:
        cc = self.class_counts()
        return {k: cc[k] for k in BLOCKING if cc[k]}

    def coverage(self) -> dict[str, dict]:
        cov = {n: {"family": s.family, "drawn": 0, "executed": 0, "refused": 0, "failed": 0, "after_stop": 0,
                   "refusals": collections.Counter(), "fail_classes": collections.Counter()}
               for n, s in self.specs.items()}
        for c, o in self.results:
            ran = set(o.executed)
            stop = len(o.executed)
            for i, st in enumerate(c.stages):
                d = cov[st.op]
                d["drawn"] += 1
                if i > stop or (i == stop and o.status == "ok"):
                    d["after_stop"] += 1
            for op in ran:
                cov[op]["executed"] += 1
            if o.refused:
                cov[o.refused[0]]["refused"] += 1
                cov[o.refused[0]]["refusals"][o.refused[1][:160]] += 1
            if o.status == "failed" and o.op in cov:
                cov[o.op]["failed"] += 1
                cov[o.op]["fail_classes"][o.cls] += 1
        return cov

    def why_not_run(self, name: str, d: dict) -> str:
        spec = self.specs[name]
        if not self.graph.runnable(spec):
            return self.graph.why_unreachable(spec)
        if d["drawn"] == 0:
            return "never drawn"
        if d["refused"]:
            msg, _ = d["refusals"].most_common(1)[0]
            return f"always refused ({d['refused']}x): {msg}"
        if d["failed"]:
            return "failed every time: " + ", ".join(f"{k} {v}" for k, v in d["fail_classes"].items())
        return "drawn only after an earlier stage stopped the chain"

    def executed_fraction(self) -> float:
        cov = self.coverage()
        return sum(1 for d in cov.values() if d["executed"]) / max(1, len(cov))


def _default_specs():
    from fsjax.registry import list_ops

    return list_ops()


def fuzz(n_chains: int = 200, max_length: int = 6, seed: int = 0, *, specs: Sequence[Any] | None = None,
         minimise_failures: bool = True, grad: bool = True, vmap: bool = True,
         time_budget_s: float | None = None, progress: Callable[[str], None] | None = None,
         max_minimise_trials: int = 12, minimise_budget_s: float | None = None, journal: str | os.PathLike | None = None,
         whole_chain_fraction: float = WHOLE_CHAIN_FRACTION, workers: int = 1, coverage_share: float = 1.0,
         _part: tuple[int, int] | None = None) -> FuzzRun:
    """Generate and run ``n_chains`` random typed chains of length ``1..max_length``.

    Args:
      specs: the ops to draw from (default: the whole registry).
      minimise_failures: shrink the first chain of every signature (:func:`minimise`).
      time_budget_s: stop generating new chains after this many seconds (recorded).
      progress: called with a one-line status now and then (e.g. ``print``).
      minimise_budget_s: stop minimising after this many seconds (later signatures keep
        their first chain unminimised; recorded).
      journal: a file to which every chain and its outcome is appended as one JSON line as
        it finishes (a long run can be read while it goes).
      whole_chain_fraction: the fraction of chains also compiled whole (``jit(vmap(chain))``
        and ``grad`` of the whole chain) besides the per-stage programs every chain runs
        through; drawn per chain from ``(seed, index)``, so the chains themselves do not change.
      workers: processes running chains side by side (the whole registry only: ``specs`` must
        be ``None``). Worker ``w`` of ``W`` runs the chains ``w, w + W, ...``, drawn from its own
        generator (seeded by ``(seed, w, W)``), whose coverage phase draws every ``W``-th op
        (by name) first, so the workers share the coverage; each has its own compiled programs
        (and shares the persistent compile cache when one is on). Failures are minimised in
        this process afterwards. ``workers=1``: one process, the chains of ``seed`` as before.
      coverage_share: the share of the drawable ops the coverage phase draws first (a subset
        drawn from ``seed``); after it, chains repeat what was drawn and reach other ops at
        the generator's ``NEW_COMBO_RATE`` only. 1: every op (a full run); a bounded run (CI)
        takes a share to leave the compile-bound coverage phase early.
    """
    if not 0.0 <= whole_chain_fraction <= 1.0:
        raise ValueError(f"fuzz: argument 'whole_chain_fraction' must be in [0, 1], got {whole_chain_fraction!r}")
    if not (isinstance(workers, int) and workers >= 1):
        raise ValueError(f"fuzz: argument 'workers' must be an int >= 1, got {workers!r}")
    if workers > 1 and specs is not None:
        raise ValueError("fuzz: argument 'workers' must be 1 when 'specs' is given (worker processes draw from the "
                         "registry they import)")
    if not 0.0 < coverage_share <= 1.0:
        raise ValueError(f"fuzz: argument 'coverage_share' must be in (0, 1], got {coverage_share!r}")
    if workers > 1:
        return _fuzz_parallel(n_chains, max_length, seed, workers=workers, minimise_failures=minimise_failures,
                              grad=grad, vmap=vmap, time_budget_s=time_budget_s, progress=progress,
                              max_minimise_trials=max_minimise_trials, minimise_budget_s=minimise_budget_s,
                              journal=journal, whole_chain_fraction=whole_chain_fraction,
                              coverage_share=coverage_share)
    specs = list(_default_specs() if specs is None else specs)
    graph = SortGraph(specs, pool_sorts(specs))
    runner = Runner(specs, grad=grad, vmap=vmap)
    run = FuzzRun(seed, max_length, {s.name: s for s in specs}, graph, whole_chain_fraction=whole_chain_fraction)
    run.stats = runner.stats
    w, n_w = _part or (0, 1)
    rng = random.Random(seed) if n_w == 1 else random.Random(f"{seed}/{w}/{n_w}")
    state = DrawState()
    if n_w > 1 or coverage_share < 1.0:
        drawable = sorted(n for n, s in graph.specs.items() if graph.runnable(s))
        if coverage_share < 1.0:
            random.Random(f"cover:{seed}").shuffle(drawable)
            drawable = sorted(drawable[: max(1, math.ceil(coverage_share * len(drawable)))])
        state.cover = frozenset(drawable[w::n_w])
    tag = f"[worker {w}] " if n_w > 1 else ""
    t0, c0 = time.perf_counter(), time.process_time()
    for i in range(n_chains):
        k = w + n_w * i   # the chain's index in the whole run
        if time_budget_s is not None and time.perf_counter() - t0 > time_budget_s:
            run.stopped_early = f"{tag}time budget {time_budget_s:.0f} s reached after {i} chains"
            break
        chain = generate_chain(graph, rng, max_length, state)
        if state.covered and "coverage_chains" not in runner.stats:
            runner.stats["coverage_chains"] = i + 1   # the coverage phase ended with this chain
        whole = random.Random(f"{seed}:{k}").random() < whole_chain_fraction
        runner.release_if_needed()
        o = runner.run(chain, whole=whole)
        run.results.append((chain, o))
        _keep_prefix(state, chain, o)
        if journal is not None:
            line = json.dumps({"chain": chain.to_json(), "outcome": o.to_json(), "index": k}, default=str) + "\n"
            with open(journal, "a") as fh:
                fh.write(line)   # one write per line: workers append to the same journal
        if progress and (i + 1) % 25 == 0:
            cc = {c: n for c, n in run.class_counts().items() if n}
            progress(f"{tag}fuzz: {i + 1}/{n_chains} chains, {time.perf_counter() - t0:.0f} s, "
                     f"ops executed {100 * run.executed_fraction():.0f} %, failures {cc}")
    run.seconds = time.perf_counter() - t0
    run.cpu_seconds = time.process_time() - c0
    runner.stats["repeats"] = state.repeats   # exact repeats left after REPEAT_REDRAWS draws
    if minimise_failures:
        _minimise_all(run, runner, max_minimise_trials, minimise_budget_s)
    return run


def _minimise_all(run: FuzzRun, runner: Runner, max_trials: int, budget_s: float | None) -> None:
    t1 = time.perf_counter()
    for sig, items in run.signatures().items():
        if budget_s is not None and time.perf_counter() - t1 > budget_s:
            run.stopped_early += (("; " if run.stopped_early else "") + f"minimising stopped after {budget_s:.0f} s")
            break
        c, o = items[0]
        run.minimised[sig] = minimise(runner, c, o, max_trials=max_trials)
    run.minimise_seconds = time.perf_counter() - t1


def _worker(kw: dict):
    """One worker process of a parallel run: the same JAX settings as the parent, its share of
    the chains; returns what the parent merges (chains and outcomes pickle)."""
    import jax

    jax.config.update("jax_enable_x64", kw.pop("x64"))
    cache = kw.pop("compile_cache")
    if cache:
        from .._cache import enable_compile_cache

        enable_compile_cache(cache)
    quiet = not kw.pop("print_progress")
    run = fuzz(**kw, minimise_failures=False, progress=None if quiet else (lambda t: print(t, flush=True)))
    return run.results, run.stats, run.seconds, run.cpu_seconds, run.stopped_early


def _fuzz_parallel(n_chains, max_length, seed, *, workers, minimise_failures, grad, vmap, time_budget_s, progress,
                   max_minimise_trials, minimise_budget_s, journal, whole_chain_fraction, coverage_share) -> FuzzRun:
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    import jax

    specs = list(_default_specs())
    graph = SortGraph(specs, pool_sorts(specs))
    run = FuzzRun(seed, max_length, {s.name: s for s in specs}, graph, whole_chain_fraction=whole_chain_fraction)
    cache = jax.config.jax_compilation_cache_dir if jax.config.jax_enable_compilation_cache else None
    jobs = []
    for w in range(workers):
        n_w = len(range(w, n_chains, workers))
        jobs.append({"n_chains": n_w, "max_length": max_length, "seed": seed, "grad": grad, "vmap": vmap,
                     "time_budget_s": time_budget_s, "journal": None if journal is None else str(journal),
                     "whole_chain_fraction": whole_chain_fraction, "_part": (w, workers),
                     "coverage_share": coverage_share,
                     "x64": bool(jax.config.jax_enable_x64), "compile_cache": cache,
                     "print_progress": progress is not None})
    t0 = time.perf_counter()
    saved = os.environ.get("XLA_FLAGS")
    os.environ["XLA_FLAGS"] = _worker_xla_flags(saved)   # read by the spawned workers' XLA (WORKER_XLA_FLAGS)
    try:
        with ProcessPoolExecutor(workers, mp_context=mp.get_context("spawn")) as ex:
            futures = [ex.submit(_worker, j) for j in jobs]
            outs = [f.result() for f in futures]
    finally:
        if saved is None:
            os.environ.pop("XLA_FLAGS", None)
        else:
            os.environ["XLA_FLAGS"] = saved
    run.stats["worker_xla_flags"] = _worker_xla_flags(saved)
    run.seconds = time.perf_counter() - t0
    merged: list = []
    for w, (results, stats, _, cpu, stopped) in enumerate(outs):
        merged += [(w + workers * i, c, o) for i, (c, o) in enumerate(results)]
        run.cpu_seconds += cpu
        for key, v in stats.items():
            if key == "coverage_chains":
                run.stats.setdefault("coverage_chains_per_worker", []).append(v)
            elif isinstance(v, (int, float)) and not isinstance(v, bool):
                run.stats[key] = run.stats.get(key, 0) + v
            else:
                run.stats[key] = v
        if stopped:
            run.stopped_early += ("; " if run.stopped_early else "") + stopped
    run.results = [(c, o) for _, c, o in sorted(merged, key=lambda t: t[0])]
    run.stats["workers"] = workers
    if minimise_failures:
        _minimise_all(run, Runner(specs, grad=grad, vmap=vmap), max_minimise_trials, minimise_budget_s)
    return run


def _keep_prefix(state: DrawState, chain: Chain, o: Outcome) -> None:
    """Later chains extend only the part of ``chain`` that passed: a refused or failed chain is
    cut before the stage that stopped it (a prefix that stops again wastes the chain)."""
    if o.status == "ok":
        return
    n = len(o.executed) if o.status == "refused" else (o.stage or 0) if o.stage is not None else 0
    if state.history and state.history[-1] is chain:
        if n <= 0:
            state.history.pop()
        else:
            state.history[-1] = chain.replace(stages=chain.stages[:n])


def load_journal(path: str | os.PathLike, *, seed: int = -1, max_length: int = 0,
                 specs: Sequence[Any] | None = None) -> FuzzRun:
    """A :class:`FuzzRun` rebuilt from a journal (``fuzz(journal=...)``, ``DIR/chains.jsonl``),
    e.g. to report on a run that is still going or was stopped. Wall time is the sum of the
    chains' own times; nothing is minimised."""
    specs = list(_default_specs() if specs is None else specs)
    run = FuzzRun(seed, max_length, {s.name: s for s in specs}, SortGraph(specs, pool_sorts(specs)))
    for line in Path(path).read_text().splitlines():
        if not line.strip():
            continue
        d = json.loads(line)
        od = dict(d["outcome"])
        for k in ("refused", "refused_traced", "conditioned"):
            if od.get(k) is not None:
                od[k] = tuple(od[k])
        c = Chain.from_json(d["chain"])
        od["executed"] = tuple(od["executed"]) if "executed" in od else _infer_executed(c, od)
        o = Outcome(**od)
        run.results.append((c, o))
        run.max_length = max(run.max_length, len(c.stages))
        run.seconds += o.seconds
    return run


def _infer_executed(c: Chain, od: dict) -> tuple[str, ...]:
    # journals written before outcomes carried ``executed``: the ops whose eager call completed
    ops = [s.op for s in c.stages]
    n = len(ops)
    if od.get("refused"):
        n = ops.index(od["refused"][0]) if od["refused"][0] in ops else n
    if od["status"] == "error":
        n = 0
    elif od["status"] == "failed" and od.get("mode") in ("eager", "check") and od.get("cls") != "RECOMPILE":
        k = od.get("stage") or 0
        n = min(n, k + 1 if od.get("cls") in ("CONTRACT", "NONFINITE", "GROWTH", "SILENT_OVERFLOW") else k)
    return tuple(ops[:n])


# ---------------------------------------------------------------------------
# minimiser
# ---------------------------------------------------------------------------


def _type_ok(runner: Runner, chain: Chain) -> bool:
    cur = runner.sorts.get(chain.inp["sort"])
    if cur is None or not chain.stages:
        return False
    for st in chain.stages:
        spec = runner.specs.get(st.op)
        if spec is None or st.slot >= len(spec.takes) or not issubclass(cur, spec.takes[st.slot]):
            return False
        cur = spec.gives
    return True


def minimise(runner: Runner, chain: Chain, outcome: Outcome, *, max_trials: int = 12) -> Chain:
    """Shrink a failing chain to a shorter (simpler) one failing in the same class at the same op.

    Tries, keeping each change that still fails the same way: cutting the stages after the
    one blamed, dropping each earlier stage, default knobs and parameters, and simpler
    inputs (the standard scene at 16 x 16, float64). At most ``max_trials`` runs.
    """
    want = (outcome.cls, outcome.op)
    whole = bool(outcome.times.get("whole", runner.whole_chain))  # the way the failure was found
    trials = [0]

    def same(c: Chain) -> bool:
        if trials[0] >= max_trials or not _type_ok(runner, c):
            return False
        trials[0] += 1
        o = runner.run(c, whole=whole)
        return o.status == "failed" and (o.cls, o.op) == want

    best = chain
    if outcome.stage is not None and outcome.stage + 1 < len(best.stages):
        c = best.replace(stages=best.stages[: outcome.stage + 1])
        if same(c):
            best = c
    i = 0
    while i < len(best.stages) and len(best.stages) > 1:
        c = best.replace(stages=best.stages[:i] + best.stages[i + 1:])
        if _type_ok(runner, c) and same(c):
            best = c
        else:
            i += 1
    plain = tuple(dataclasses.replace(s, a=None, b=None, params=()) for s in best.stages)
    if plain != best.stages:
        c = best.replace(stages=plain)
        if same(c):
            best = c
    inp = best.inp
    for kw in ({"dtype": "float64"}, {"kind": "scene", "size": (16, 16)}):
        if all(inp.get(k) == v for k, v in kw.items()):
            continue
        c = best.with_input(**kw)
        if same(c):
            best = c
            inp = best.inp
    return best


# ---------------------------------------------------------------------------
# replay and report
# ---------------------------------------------------------------------------


def _record(chain: Chain, o: Outcome, minimised: Chain | None) -> dict:
    d = {"class": o.cls, "signature": o.signature, "op": o.op, "stage": o.stage, "mode": o.mode,
         "message": o.message, "chain": chain.to_json()}
    if minimised is not None:
        d["minimised"] = minimised.to_json()
    return d


def replay(path: str | os.PathLike, *, specs: Sequence[Any] | None = None,
           out: Callable[[str], None] = print) -> list[Outcome]:
    """Run every chain of a JSON-lines file (a failure record's ``minimised`` chain, else its
    ``chain``, or a bare chain) and print its outcome."""
    specs = list(_default_specs() if specs is None else specs)
    runner = Runner(specs, whole_chain=True)  # a replay runs every way, the chain compiled whole too
    outs = []
    for n, line in enumerate(Path(path).read_text().splitlines(), 1):
        if not line.strip():
            continue
        d = json.loads(line)
        cd = d.get("minimised") or d.get("chain") or d
        chain = Chain.from_json(cd)
        o = runner.run(chain)
        outs.append(o)
        what = o.signature if o.status == "failed" else (o.status + (f" ({o.refused[0]}: {o.refused[1]})"
                                                                     if o.refused else ""))
        out(f"{n}: {chain.describe()}\n   -> {what}")
    return outs


def write_report(run: FuzzRun, out_dir: str | os.PathLike, *, command: str = "") -> Path:
    """Write ``DIR/report.md`` and ``DIR/failures.jsonl`` (one replayable record per failure)."""
    import platform

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    sigs = run.signatures()
    with open(out_dir / "failures.jsonl", "w") as fh:
        for sig, items in sigs.items():
            for k, (c, o) in enumerate(items):
                fh.write(json.dumps(_record(c, o, run.minimised.get(sig) if k == 0 else None)) + "\n")
    with open(out_dir / "minimised.jsonl", "w") as fh:
        for sig, items in sigs.items():
            c, o = items[0]
            fh.write(json.dumps(_record(c, o, run.minimised.get(sig, c))) + "\n")
    cov = run.coverage()
    n = len(run.results)
    status = collections.Counter(o.status for _, o in run.results)
    lens = [len(c.stages) for c, _ in run.results]
    stages_run = sum(len(o.executed) for _, o in run.results)
    executed = sum(1 for d in cov.values() if d["executed"])
    cc = run.class_counts()
    L: list[str] = []
    L.append("# Chain fuzz report\n")
    if command:
        L.append(f"Command: `{command}`\n")
    L.append(f"Machine: {platform.machine()}, {os.cpu_count()} cores, load average "
             f"{', '.join(f'{v:.2f}' for v in os.getloadavg())} at the end; python {platform.python_version()}.\n")
    L.append("## Figures\n")
    L.append("| figure | value |\n|---|---|")
    L.append(f"| chains run | {n} (seed {run.seed}, length 1-{run.max_length}, mean {sum(lens) / max(1, n):.2f}) |")
    distinct = len({c for c, _ in run.results})
    L.append(f"| distinct chains | {distinct} (exact repeats: {n - distinct}; a worker redraws a repeat of its own "
             f"chains up to {REPEAT_REDRAWS} times) |")
    L.append(f"| chains per CPU-minute | {60 * n / max(run.cpu_seconds, 1e-9):.1f} ({60 * distinct / max(run.cpu_seconds, 1e-9):.1f} "
             f"distinct) |")
    L.append(f"| outcomes | {status.get('ok', 0)} ok, {status.get('refused', 0)} refused by a clear error, "
             f"{status.get('failed', 0)} failed, {status.get('error', 0)} fuzzer errors |")
    L.append(f"| stages executed eagerly | {stages_run} |")
    L.append(f"| wall time | {run.seconds:.0f} s running ({run.cpu_seconds:.0f} s of process CPU time) + "
             f"{run.minimise_seconds:.0f} s minimising |")
    L.append(f"| ops executed at least once | {executed} of {len(cov)} ({100 * executed / max(1, len(cov)):.1f} %) |")
    st = run.stats
    if st:
        comp = sum(int(o.times.get("compiles", 0)) for _, o in run.results)
        comp_s = sum(float(o.times.get("compile_s", 0.0)) for _, o in run.results)
        L.append(f"| chains per minute | {60 * n / max(run.seconds, 1e-9):.1f} |")
        L.append(f"| stage programs (jit(vmap(stage))) | {st['stage_calls']} calls, {st['stage_hits']} reused "
                 f"({100 * st['stage_hits'] / max(1, st['stage_calls']):.0f} %) |")
        L.append(f"| grad programs (jit(vjp(stage))) | {st['grad_calls']} calls, {st['grad_hits']} reused "
                 f"({100 * st['grad_hits'] / max(1, st['grad_calls']):.0f} %) |")
        L.append(f"| chains also compiled whole | {st['whole']} (fraction {run.whole_chain_fraction:g}) |")
        L.append(f"| compiled programs released (memory-map limit) | {st.get('released', 0)} time(s) |")
        L.append(f"| compiles (backend compiles + traces, all ways) | {comp} ({comp / max(1, n):.1f} per chain, "
                 f"{comp_s:.0f} s) |")
        L.append(f"| eager stages taken from an earlier chain's prefix | {st.get('eager_hits', 0)} of "
                 f"{st.get('eager_calls', 0)} ({100 * st.get('eager_hits', 0) / max(1, st.get('eager_calls', 0)):.0f} %;"
                 f" staged: {st.get('staged_prefix_hits', 0)}) |")
        L.append(f"| persistent compile cache | {st.get('compile_cache', 'not enabled (library call)')} |")
        L.append(f"| worker processes | {st.get('workers', 1)} (coverage phase: "
                 f"{st.get('coverage_chains_per_worker', st.get('coverage_chains', 'not ended'))} chains) |")
    if run.stopped_early:
        L.append(f"| stopped early | {run.stopped_early} |")
    L.append("")
    L.append("## Failure classes\n")
    L.append("| class | failures | signatures |\n|---|---|---|")
    for k in CLASSES:
        ns = sum(1 for s, it in sigs.items() if it[0][1].cls == k)
        L.append(f"| {k} | {cc[k]} | {ns} |")
    L.append("")
    cond = collections.Counter(o.conditioned[0] for _, o in run.results if getattr(o, "conditioned", None))
    L.append("## Ill-conditioned stages (not failures)\n")
    L.append("A stage whose traced output differed from the eager one while its compiled program, given "
             "the eager input, agreed: the upstream stages' round-off (each within the tolerance) "
             "amplified by the op's conditioning; the chain's later stages are not compared "
             "(`Runner._same_input_agrees`).\n")
    if not cond:
        L.append("None.\n")
    for op_, k in cond.most_common():
        first = next(o for _, o in run.results if getattr(o, "conditioned", None) and o.conditioned[0] == op_)
        L.append(f"* `{op_}`: {k} chain(s); first: `{first.conditioned[2][:200]}`")
    L.append("")
    L.append("## Signatures and minimised reproducers\n")
    if not sigs:
        L.append("None.\n")
    for sig, items in sorted(sigs.items(), key=lambda kv: (kv[1][0][1].cls, -len(kv[1]))):
        c, o = items[0]
        m = run.minimised.get(sig, c)
        L.append(f"### {sig}\n")
        L.append(f"{len(items)} chain(s). First: `{c.describe()}`\n")
        L.append(f"Message: `{o.message[:300]}`\n")
        L.append(f"Minimised ({len(m.stages)} stage(s)): `{m.describe()}`\n")
        L.append("```json\n" + json.dumps(m.to_json()) + "\n```\n")
    L.append("## Coverage per family\n")
    L.append("| family | ops | executed | drawn (stages) | ran (stages) | refused | failed |\n|---|---|---|---|---|---|---|")
    fams: dict[str, list] = {}
    for d in cov.values():
        fams.setdefault(d["family"], []).append(d)
    for fam in sorted(fams):
        ds = fams[fam]
        L.append(f"| {fam} | {len(ds)} | {sum(1 for d in ds if d['executed'])} | {sum(d['drawn'] for d in ds)} | "
                 f"{sum(d['executed'] for d in ds)} | {sum(d['refused'] for d in ds)} | "
                 f"{sum(d['failed'] for d in ds)} |")
    L.append("")
    L.append("## Ops never executed, and why\n")
    never = [(n_, d) for n_, d in sorted(cov.items()) if not d["executed"]]
    if not never:
        L.append("None: every op ran at least once.\n")
    for n_, d in never:
        L.append(f"* `{n_}` ({d['family']}): {run.why_not_run(n_, d)}")
    L.append("")
    L.append("## Coverage per op\n")
    L.append("| op | family | drawn | executed | refused | failed |\n|---|---|---|---|---|---|")
    for n_, d in sorted(cov.items(), key=lambda kv: (kv[1]["family"], kv[0])):
        L.append(f"| {n_} | {d['family']} | {d['drawn']} | {d['executed']} | {d['refused']} | {d['failed']} |")
    L.append("")
    L.append("## Most frequent refusals (clear errors, not failures)\n")
    ref = collections.Counter()
    for _, o in run.results:
        if o.refused:
            ref[f"{o.refused[0]}: {o.refused[1][:200]}"] += 1
    for msg, k in ref.most_common(15):
        L.append(f"* {k} x `{msg}`")
    L.append("")
    path = out_dir / "report.md"
    path.write_text("\n".join(L) + "\n")
    return path


def _compile_cache(where: str | None) -> str:
    """Switch on JAX's persistent compile cache for a CLI run (``--compile-cache DIR``, default
    the user's cache as :func:`fsjax.enable_compile_cache` resolves it; ``off`` disables) and
    say whether it was warm (held programs at the start) or cold: a warm cache loads programs an
    earlier run compiled, so the rate depends on it and the report states it."""
    from .._cache import enable_compile_cache

    d = enable_compile_cache(where)
    if d is None:
        return "off"
    n = sum(1 for _ in d.iterdir())
    return f"{'warm' if n else 'cold'} ({n} entries at the start, {d})"


def cli_main(args) -> int:
    """``fsjax fuzz``: run (``--chains``) or replay (``--replay FILE``).

    Turns on float64 (``jax_enable_x64``): the pool holds float64 and float32 inputs.
    """
    import jax

    jax.config.update("jax_enable_x64", True)
    if args.replay:
        outs = replay(args.replay)
        bad = [o for o in outs if o.status == "failed"]
        print(f"fsjax fuzz --replay: {len(outs)} chain(s), {len(bad)} still failing")
        return 1 if bad else 0
    if not args.out:
        raise ValueError("fuzz: --out DIR is required (unless --replay FILE)")
    cmd = "fsjax fuzz " + " ".join(sys.argv[2:]) if len(sys.argv) > 2 else ""
    Path(args.out).mkdir(parents=True, exist_ok=True)
    journal = Path(args.out) / "chains.jsonl"
    journal.write_text("")
    cache_note = _compile_cache(getattr(args, "compile_cache", None))
    workers = getattr(args, "workers", None) or min(2, os.cpu_count() or 1)
    run = fuzz(args.chains, args.length, args.seed, time_budget_s=args.minutes * 60 if args.minutes else None,
               progress=lambda s: print(s, flush=True), grad=not args.no_grad, journal=journal,
               minimise_budget_s=max(120.0, 0.15 * 60 * args.minutes) if args.minutes else None,
               whole_chain_fraction=WHOLE_CHAIN_FRACTION if getattr(args, "whole_chain", None) is None
               else args.whole_chain, workers=workers)
    run.stats["compile_cache"] = cache_note
    path = write_report(run, args.out, command=cmd)
    cc = {k: v for k, v in run.class_counts().items() if v}
    print(f"fsjax fuzz: {len(run.results)} chains in {run.seconds:.0f} s; ops executed "
          f"{100 * run.executed_fraction():.1f} %; failures {cc or 'none'}; report {path}")
    return 1 if (args.strict and run.blocking()) else 0
