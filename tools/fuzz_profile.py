"""Profile the chain fuzzer: where a chain's time goes, and how many programs compile.

    python tools/fuzz_profile.py --chains 20 --length 6 --seed 0

Prints wall time, chains/min, the per-way breakdown the runner records (``Outcome.times``),
and the backend compiles with their summed compile and trace durations (jax.monitoring).

    python tools/fuzz_profile.py --read DIR/chains.jsonl --workers 2 --coverage 62,60

reads a run's journal instead (``fsjax fuzz`` writes it): CPU per chain in the coverage and
reuse phases (the report's "worker processes" row gives each worker's coverage-phase chains).
"""

from __future__ import annotations

import argparse
import collections
import os
import time


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--chains", type=int, default=20)
    p.add_argument("--length", type=int, default=6)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--no-grad", action="store_true")
    p.add_argument("--journal", help="also write every chain and outcome as JSON lines (cumulative figures later)")
    p.add_argument("--whole", type=float, default=None, help="fraction of chains compiled whole (default: fuzz's)")
    p.add_argument("--compile-cache", default="off",
                   help="persistent compile cache directory (default off: a cold measurement); warm or cold "
                        "is printed")
    p.add_argument("--read", help="a run's journal (DIR/chains.jsonl): print its phases' rates and stop")
    p.add_argument("--workers", type=int, default=1, help="with --read: the run's worker processes")
    p.add_argument("--coverage", help="with --read: coverage-phase chains per worker, comma-separated")
    p.add_argument("--minutes", type=float, default=None, help="stop drawing new chains after this many minutes")
    p.add_argument("--coverage-share", type=float, default=1.0,
                   help="the share of the ops the coverage phase draws first (fuzz's coverage_share)")
    a = p.parse_args()
    if a.read:
        read_journal(a.read, a.workers, [int(v) for v in a.coverage.split(",")] if a.coverage else None)
        return
    import jax
    import jax.monitoring

    jax.config.update("jax_enable_x64", True)
    ev = collections.defaultdict(lambda: [0, 0.0])

    def on(event, duration, **kw):
        if event.startswith("/jax/core/compile") or "compile" in event or "trace" in event:
            ev[event][0] += 1
            ev[event][1] += duration

    jax.monitoring.register_event_duration_secs_listener(on)
    import fsjax.fuzz as fz

    ways = _tag_ways()
    from fsjax.registry import list_ops

    list_ops()
    if a.compile_cache != "off":
        from fsjax.fuzz._report import _compile_cache

        print("compile cache:", _compile_cache(a.compile_cache))
    t0 = time.perf_counter()
    kw = {} if a.whole is None else {"whole_chain_fraction": a.whole}
    if a.minutes is not None:
        kw["time_budget_s"] = 60 * a.minutes
    if a.coverage_share != 1.0:
        kw["coverage_share"] = a.coverage_share
    if a.journal:
        kw["journal"] = a.journal
    try:
        run = fz.fuzz(a.chains, a.length, a.seed, minimise_failures=False, grad=not a.no_grad, **kw)
    except TypeError:  # the fuzzer before per-stage programs: every chain compiled whole
        run = fz.fuzz(a.chains, a.length, a.seed, minimise_failures=False, grad=not a.no_grad)
    wall = time.perf_counter() - t0
    print(f"chains {len(run.results)}  wall {wall:.1f} s  cpu {run.cpu_seconds:.1f} s  "
          f"chains/min {60 * len(run.results) / wall:.1f}  load {os.getloadavg()[0]:.2f}")
    _print_ways(ways, run)
    for k, (n, s) in sorted(ev.items()):
        print(f"  {k}: n={n} total={s:.1f} s")
    print("runner cache:", getattr(run, "stats", None))
    n = max(1, len(run.results))
    tot = collections.Counter()
    for _, o in run.results:
        for k in ("eager", "staged", "grad", "whole_traced", "whole_grad", "compile_s", "compiles", "cpu_s",
                  "eager_compile_s", "staged_compile_s", "grad_compile_s"):
            tot[k] += float(o.times.get(k, 0.0) or 0.0)
        tot["seconds"] += o.seconds
    comp = tot["compile_s"]
    print(f"per chain: {tot['seconds'] / n:.2f} s wall, {tot['cpu_s'] / n:.2f} s CPU; compiling {comp / n:.2f} s "
          f"({tot['compiles'] / n:.1f} compiles), running (the rest) {(tot['seconds'] - comp) / n:.2f} s; "
          f"eager {tot['eager'] / n:.2f} s (of it compiling {tot['eager_compile_s'] / n:.2f} s), staged "
          f"{tot['staged'] / n:.2f} s (compiling {tot['staged_compile_s'] / n:.2f}), grad {tot['grad'] / n:.2f} s "
          f"(compiling {tot['grad_compile_s'] / n:.2f}), whole {(tot['whole_traced'] + tot['whole_grad']) / n:.2f} s")
    st = getattr(run, "stats", None) or {}

    def rate(h, c):
        return f"{st.get(h, 0)}/{st.get(c, 0)} ({100 * st.get(h, 0) / max(1, st.get(c, 0)):.0f} %)"

    print(f"cache hits: stage programs {rate('stage_hits', 'stage_calls')}, grad programs "
          f"{rate('grad_hits', 'grad_calls')}, eager prefixes {rate('eager_hits', 'eager_calls')}, "
          f"staged prefixes {st.get('staged_prefix_hits', 0)}")
    print(f"chains per CPU-minute {60 * len(run.results) / max(run.cpu_seconds, 1e-9):.1f}; "
          f"ops executed {100 * run.executed_fraction():.1f} %")
    k = (getattr(run, "stats", None) or {}).get("coverage_chains")
    if k:   # the two phases of the generator apart
        for name, part in (("coverage phase", run.results[:k]), ("reuse phase", run.results[k:])):
            cpu = sum(float(o.times.get("cpu_s", 0.0)) for _, o in part)
            comp = {w: sum(float(o.times.get(f"{w}_compile_s", 0.0)) for _, o in part) for w in ("eager", "staged", "grad")}
            print(f"{name}: {len(part)} chains, {cpu:.0f} s CPU, {60 * len(part) / max(cpu, 1e-9):.1f} per CPU-minute; "
                  f"compiling: eager {comp['eager']:.0f} s, staged {comp['staged']:.0f} s, grad {comp['grad']:.0f} s, "
                  f"all ways {sum(float(o.times.get('compile_s', 0.0)) for _, o in part):.0f} s; "
                  f"chains that compiled nothing {sum(1 for _, o in part if not o.times.get('compiles'))}")
    st = collections.Counter(o.status for _, o in run.results)
    print("outcomes:", dict(st), "classes:", {k: v for k, v in run.class_counts().items() if v})
    print("mean length", sum(len(c.stages) for c, _ in run.results) / max(1, len(run.results)))


# eager op-by-op dispatch compiles a program per primitive (or jnp helper) and shape, named
# "jit(<name>)"; an op's own module-level jit program is named after an fsjax function
def _is_primitive(name: str) -> bool:
    import sys

    inner = name[4:-1] if name.startswith("jit(") else name
    names = _is_primitive.__dict__.get("names")
    if names is None:
        names = _is_primitive.names = {getattr(v, "__name__", None) for m, mod in list(sys.modules.items())
                                       if m.startswith("fsjax") and mod is not None
                                       for v in list(vars(mod).values()) if callable(v)}
    return inner not in names


def _tag_ways():
    """Tag the runner's ways (eager, staged, grad, whole) so that CPU time and every backend compile
    (by the program's name) are summed per way, per phase (coverage / reuse)."""
    import jax.monitoring

    from fsjax.fuzz._report import Runner

    state = {"way": "other", "phase": "coverage", "t": time.process_time()}
    cpu = collections.Counter()
    comp = collections.defaultdict(lambda: [0, 0.0])

    def switch(way):
        now = time.process_time()
        cpu[(state["phase"], state["way"])] += now - state["t"]
        state["t"], state["way"] = now, way

    def on(event, duration, fun_name="?", **kw):
        if event != "/jax/core/compile/backend_compile_duration":
            return
        way = state["way"]
        if way == "eager":
            way = "eager primitives" if _is_primitive(fun_name) else "eager op programs"
        c = comp[(state["phase"], way)]
        c[0] += 1
        c[1] += duration

    jax.monitoring.register_event_duration_secs_listener(on)

    def wrap(name, way):
        orig = getattr(Runner, name)

        def f(self, *a, **k):
            prev = state["way"]
            if name == "run":
                state["n"] = state.get("n", 0) + 1
                if state["n"] > self.stats.get("coverage_chains", 1 << 30):
                    state["phase"] = "reuse"
            switch(way)
            try:
                return orig(self, *a, **k)
            finally:
                switch(prev if name != "run" else "other")

        setattr(Runner, name, f)

    wrap("run", "eager")   # a chain starts with the checker and the eager way
    wrap("_staged", "staged")
    wrap("_grad_staged", "grad")
    wrap("_whole", "whole")
    wrap("_grad", "whole")
    return cpu, comp


def _print_ways(ways, run) -> None:
    cpu, comp = ways
    for phase in ("coverage", "reuse"):
        t = {k[1]: v for k, v in cpu.items() if k[0] == phase}
        if not t:
            continue
        n = sum(1 for _ in run.results) if phase == "coverage" and "coverage_chains" not in run.stats else (
            run.stats["coverage_chains"] if phase == "coverage" else len(run.results) - run.stats["coverage_chains"])
        total = sum(t.values())
        print(f"{phase} phase: {n} chains, {total:.0f} s CPU ({60 * n / max(total, 1e-9):.1f} per CPU-minute)")
        for way in ("eager", "staged", "grad", "whole", "other"):
            c = [(w, comp[(phase, w)]) for w in (("eager primitives", "eager op programs") if way == "eager" else (way,))]
            cs = ", ".join(f"{w}: {n_} compiles {s:.0f} s wall" for w, (n_, s) in c if n_)
            print(f"  {way:7s} CPU {t.get(way, 0.0):6.0f} s ({100 * t.get(way, 0.0) / max(total, 1e-9):4.1f} %)"
                  f"{'; ' + cs if cs else ''}")


def read_journal(path: str, workers: int, coverage: list[int] | None) -> None:
    import json

    rows = [json.loads(line) for line in open(path) if line.strip()]
    for k, d in enumerate(rows):
        d.setdefault("index", k)   # journals before workers: in order
    phases = {"all": rows}
    if coverage:
        phases["coverage phase"] = [d for d in rows if d["index"] // workers < coverage[d["index"] % workers]]
        phases["reuse phase"] = [d for d in rows if d["index"] // workers >= coverage[d["index"] % workers]]
    for name, part in phases.items():
        t = collections.Counter()
        for d in part:
            for k, v in d["outcome"]["times"].items():
                if isinstance(v, (int, float)) and not isinstance(v, bool):
                    t[k] += v
        none = sum(1 for d in part if not d["outcome"]["times"].get("compiles"))
        # an exact repeat of an earlier chain of the run tests nothing new (the generator redraws
        # them since branch fuzz19); counted apart
        distinct = len({json.dumps(d["chain"], sort_keys=True) for d in part})
        print(f"{name}: {len(part)} chains ({distinct} distinct), {t['cpu_s']:.0f} s CPU, "
              f"{60 * len(part) / max(t['cpu_s'], 1e-9):.1f} per CPU-minute ({60 * distinct / max(t['cpu_s'], 1e-9):.1f} "
              f"distinct); compiling (wall) eager {t['eager_compile_s']:.0f} s, staged {t['staged_compile_s']:.0f} s, "
              f"grad {t['grad_compile_s']:.0f} s of {t['compile_s']:.0f} s; wall {t['eager'] + t['staged'] + t['grad']:.0f} s "
              f"in eager/staged/grad; chains that compiled nothing {none}")


if __name__ == "__main__":
    main()
