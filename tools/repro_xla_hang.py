"""Reproducer for the intermittent XLA:CPU hang in ``jit(vmap(select_model))`` (issue 13).

Symptom seen in full test runs: the main thread waits in ``BlockUntilReady`` on the
vmapped model-selection fit of tests/fit/test_primitives3d.py (200 trials per model),
every XLA thread idle, forever.

Cause (native stacks by gdb of hung runs, jax/jaxlib 0.10.2): every XLA:CPU worker thread
("tf_XLAEigen", one per core: 2 here) sits in ``jax::ParallelBatchMap`` ->
``absl::BlockingCounter::Wait`` inside a LAPACK FFI kernel (``lapack_dsyevd_ffi``, i.e. a
batched ``jnp.linalg.eigh``) that the thunk executor started on that same thread. jaxlib's
batched LAPACK kernels (eigh, LU/solve, QR, Cholesky, triangular solve, ...) split the batch
into tasks on XLA's intra-op pool and block until they finish; when as many such calls run
concurrently as the pool has threads, no thread is left to run the tasks: a deadlock with
every thread idle. The main thread waits in ``BlockUntilReady``. Triggers: a batched LAPACK
call (``vmap`` batches every call of a fit) + independent LAPACK calls that the executor may
run at once + a small pool (few cores make it more likely). Not triggers: async dispatch
(synchronous dispatch hangs too), ``--xla_backend_optimization_level=0`` (the ``default``
configuration can hang as well), and ``--xla_cpu_multi_thread_eigen=false`` does not
prevent it. The library's workaround: :func:`fsjax.fit.select_model` and the 3-D primitive
fits use no LAPACK at all (``fsjax/_linalg.py``).

This script runs the workload N times, each in a fresh subprocess, and reports how many
runs hung (see below). On a hang it can dump the native stacks of every thread with gdb
(``--stacks DIR``) before killing the child.

Usage::

    python tools/repro_xla_hang.py --runs 20                          # as the tests run it
    python tools/repro_xla_hang.py --runs 20 --config eigen_single     # with a candidate fix
    python tools/repro_xla_hang.py --list                              # the configurations

Configurations (``--config``; several may be given, they are interleaved A B A B ...):

* ``tests``: what tests/conftest.py sets: float64, ``--xla_backend_optimization_level=0``,
  synchronous CPU dispatch.
* ``default``: JAX defaults (float64 on, async dispatch, default optimisation level).
* ``async``: as ``tests`` but asynchronous dispatch.
* ``eigen_single``: as ``tests`` plus ``--xla_cpu_multi_thread_eigen=false``.

Workloads (``--workload``):

* ``select_model``: ``jit(vmap(select_model))`` on 3 x ``--trials`` noisy patches (the test),
  with the fsjax found under ``--code`` (default: this checkout).
* ``minimal``: pure JAX, no fsjax: one jitted program whose large elementwise kernel (run
  partitioned on XLA:CPU's intra-op pool) feeds ``--k`` independent batched ``jnp.linalg.eigh``
  calls on ``(--batch, 3, 3)`` matrices, called ``--iters`` times.

A run counts as a hang when its process has used no CPU time for ``--idle`` seconds (a
deadlock: every thread waits; a slow run on a loaded machine still accrues CPU time) -- not
merely because it is slow. ``--timeout`` only bounds runs that are still computing.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time

CONFIGS = {
    "tests": {"flags": "--xla_backend_optimization_level=0", "async": False},
    "default": {"flags": "", "async": True},
    "async": {"flags": "--xla_backend_optimization_level=0", "async": True},
    "eigen_single": {"flags": "--xla_backend_optimization_level=0 --xla_cpu_multi_thread_eigen=false",
                     "async": False},
}


def _sample(kind, seed, n=150, noise=0.01):
    # the generator of tests/fit/test_primitives3d.py (sample), repeated so that this script stands alone
    import numpy as np

    rng = np.random.default_rng(seed)
    if kind == "plane":
        g = rng.uniform(-1, 1, (n, 2))
        p, nr = np.c_[g, np.zeros(n)], np.tile([0.0, 0.0, 1.0], (n, 1))
    elif kind == "sphere":
        u = rng.normal(size=(12 * n, 3))
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        p = nr = u[u[:, 2] > 0.5][:n]
    else:
        th, z = rng.uniform(-np.pi / 2, np.pi / 2, n), rng.uniform(-1, 1, n)
        p, nr = np.c_[np.cos(th), np.sin(th), z], np.c_[np.cos(th), np.sin(th), 0 * z]
    p = p + noise * rng.normal(size=(n, 1)) * nr
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    return p @ (q * np.sign(np.diag(r))).T + rng.uniform(-2, 2, 3)


def child(args) -> None:
    cfg = CONFIGS[args.config]
    flags = cfg["flags"]
    if args.extra_flags:
        flags = (flags + " " + args.extra_flags).strip()
    os.environ["XLA_FLAGS"] = flags
    import jax

    jax.config.update("jax_enable_x64", True)
    jax.config.update("jax_cpu_enable_async_dispatch", cfg["async"])
    import jax.numpy as jnp
    import numpy as np

    if args.workload == "minimal":
        K, B = args.k, args.batch

        @jax.jit
        def f(x):
            y = jnp.sin(x) + 2.0  # large elementwise kernel: executed partitioned on the intra-op pool
            m = y @ jnp.swapaxes(y, -1, -2)  # K x B symmetric positive definite 3x3 matrices
            return [jnp.linalg.eigh(m[k])[0] for k in range(K)]  # K independent batched LAPACK calls

        x = jnp.asarray(np.random.default_rng(0).normal(size=(K, B, 3, 3)))
        t0 = time.perf_counter()
        for _ in range(args.iters):
            jax.block_until_ready(f(x))
    else:
        from fsjax.fit import select_model

        f = jax.jit(jax.vmap(lambda x: select_model(x)))
        t0 = time.perf_counter()
        for _ in range(args.reps):
            for i, kind in enumerate(("plane", "sphere", "cylinder")):
                x = jnp.asarray(np.stack([_sample(kind, 1000 * i + t) for t in range(args.trials)]))
                jax.block_until_ready(f(x))
    print(f"done {time.perf_counter() - t0:.1f}s", flush=True)


def _stacks(pid: int, path: str) -> None:
    try:
        out = subprocess.run(["gdb", "-p", str(pid), "-batch", "-ex", "thread apply all bt 25"],
                             capture_output=True, text=True, timeout=120)
        with open(path, "w") as fh:
            fh.write(out.stdout + "\n" + out.stderr)
    except (OSError, subprocess.TimeoutExpired) as e:  # gdb missing or ptrace refused
        with open(path, "w") as fh:
            fh.write(f"no native stacks: {e}\n")


def _cpu_s(pid: int) -> float:
    """User + system CPU seconds of a process and all its threads (Linux /proc)."""
    try:
        with open(f"/proc/{pid}/stat") as fh:
            f = fh.read().rsplit(")", 1)[1].split()
        return (int(f[11]) + int(f[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return float("nan")


def _watch(p, args) -> str:
    """Wait for the child: "ok" when it exits, "HANG" when it has used no CPU for ``--idle`` seconds
    (a deadlock: every thread waits), "SLOW" when it is still computing at ``--timeout``."""
    t0 = time.perf_counter()
    last_cpu, last_change = _cpu_s(p.pid), t0
    while True:
        try:
            p.wait(timeout=2.0)
            return "ok"
        except subprocess.TimeoutExpired:
            pass
        now = time.perf_counter()
        cpu = _cpu_s(p.pid)
        if cpu > last_cpu + 0.05:  # still computing (compiling or running)
            last_cpu, last_change = cpu, now
        elif now - last_change > args.idle:
            return "HANG"
        if now - t0 > args.timeout:
            return "SLOW"


def parent(args) -> None:
    configs = args.config_list or ["tests"]
    tally = {c: [0, 0, [], 0] for c in configs}  # runs, hangs, times of finished runs, still busy at timeout
    env = dict(os.environ)
    env["PYTHONPATH"] = os.path.abspath(args.code) if args.code else os.path.dirname(
        os.path.dirname(os.path.abspath(__file__)))
    print(f"workload {args.workload}, code {env['PYTHONPATH']}, trials {args.trials} per model, reps {args.reps}, "
          f"k {args.k} batch {args.batch} iters {args.iters}, timeout {args.timeout} s, "
          f"load {os.getloadavg()}", flush=True)
    for k in range(args.runs):
        for c in configs:
            cmd = [sys.executable, os.path.abspath(__file__), "--child", "--config", c, "--workload", args.workload,
                   "--trials", str(args.trials), "--reps", str(args.reps), "--k", str(args.k),
                   "--batch", str(args.batch), "--iters", str(args.iters)]
            if args.extra_flags:
                cmd += ["--extra-flags", args.extra_flags]
            t0 = time.perf_counter()
            p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
            status = _watch(p, args)
            dt = time.perf_counter() - t0
            if status == "HANG":
                tally[c][1] += 1
                if args.stacks:
                    os.makedirs(args.stacks, exist_ok=True)
                    _stacks(p.pid, os.path.join(args.stacks, f"hang_{c}_{k}_{p.pid}.txt"))
            if p.poll() is None:
                p.kill()
            out, err = p.communicate()
            if status == "ok" and not (p.returncode == 0 and "done" in out):
                status = f"error rc={p.returncode}: {err.strip().splitlines()[-1:]}"
            if status == "ok":
                tally[c][2].append(dt)
            if status == "SLOW":
                tally[c][3] += 1
            tally[c][0] += 1
            print(f"run {k + 1:3d} {c:13s} {status:5s} {dt:7.1f} s  load {os.getloadavg()[0]:.1f}", flush=True)
    print("summary:")
    for c, (n, h, ts, slow) in tally.items():
        med = sorted(ts)[len(ts) // 2] if ts else float("nan")
        print(f"  {c:13s} {h} hangs in {n} runs; {len(ts)} finished (median {med:.1f} s), "
              f"{slow} still busy at the timeout (not counted as hangs)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--config", dest="config_list", action="append", choices=sorted(CONFIGS))
    ap.add_argument("--workload", default="select_model", choices=["select_model", "minimal"])
    ap.add_argument("--code", default="", help="fsjax checkout to import (select_model workload)")
    ap.add_argument("--k", type=int, default=4, help="minimal: independent eigh calls")
    ap.add_argument("--batch", type=int, default=5000, help="minimal: matrices per eigh call")
    ap.add_argument("--iters", type=int, default=100, help="minimal: calls of the program")
    ap.add_argument("--runs", type=int, default=10)
    ap.add_argument("--trials", type=int, default=200, help="patches per model (the skipped test: 200)")
    ap.add_argument("--reps", type=int, default=1, help="repeat the 3 calls this often in one process")
    ap.add_argument("--timeout", type=float, default=600.0, help="give up on a run still computing after this")
    ap.add_argument("--idle", type=float, default=20.0,
                    help="a run whose process used no CPU for this many seconds is a hang")
    ap.add_argument("--extra-flags", default="", help="appended to XLA_FLAGS in the child")
    ap.add_argument("--stacks", default="", help="directory for gdb native stacks of hung runs")
    ap.add_argument("--list", action="store_true")
    args = ap.parse_args()
    if args.list:
        for k, v in CONFIGS.items():
            print(k, v)
        return
    if args.child:
        args.config = (args.config_list or ["tests"])[0]
        child(args)
    else:
        parent(args)


if __name__ == "__main__":
    main()
