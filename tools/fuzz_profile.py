"""Profile the chain fuzzer: where a chain's time goes, and how many programs compile.

    python tools/fuzz_profile.py --chains 20 --length 6 --seed 0

Prints wall time, chains/min, the per-way breakdown the runner records (``Outcome.times``),
and the backend compiles with their summed compile and trace durations (jax.monitoring).
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
    p.add_argument("--whole", type=float, default=None, help="fraction of chains compiled whole (default: fuzz's)")
    a = p.parse_args()
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
    from fsjax.registry import list_ops

    list_ops()
    t0 = time.perf_counter()
    kw = {} if a.whole is None else {"whole_chain_fraction": a.whole}
    try:
        run = fz.fuzz(a.chains, a.length, a.seed, minimise_failures=False, grad=not a.no_grad, **kw)
    except TypeError:  # the fuzzer before per-stage programs: every chain compiled whole
        run = fz.fuzz(a.chains, a.length, a.seed, minimise_failures=False, grad=not a.no_grad)
    wall = time.perf_counter() - t0
    ways = collections.Counter()
    for _, o in run.results:
        for k, v in o.times.items():
            ways[k] += float(v)
    print(f"chains {len(run.results)}  wall {wall:.1f} s  cpu {run.cpu_seconds:.1f} s  "
          f"chains/min {60 * len(run.results) / wall:.1f}  load {os.getloadavg()[0]:.2f}")
    print("per way (s):", {k: round(v, 1) for k, v in sorted(ways.items())})
    for k, (n, s) in sorted(ev.items()):
        print(f"  {k}: n={n} total={s:.1f} s")
    print("runner cache:", getattr(run, "stats", None))
    st = collections.Counter(o.status for _, o in run.results)
    print("outcomes:", dict(st), "classes:", {k: v for k, v in run.class_counts().items() if v})
    print("mean length", sum(len(c.stages) for c, _ in run.results) / max(1, len(run.results)))


if __name__ == "__main__":
    main()
