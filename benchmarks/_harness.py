"""A small timing and memory harness for side-by-side benchmarks in one process.

Method, in short (repeated in ``docs/benchmarks.md``):

* **Steady-state time.** Every competitor is a zero-argument callable that runs
  the whole workload and *waits for the result* (JAX callables end in
  :func:`jax.block_until_ready`). After ``warmup`` untimed calls of each, the
  competitors run ``repeats`` times **round-robin**: repeat ``r`` runs every
  competitor once, starting at a rotated position, so slow drift of the machine
  (other processes, thermal state) hits all of them alike. Wall time by
  :func:`time.perf_counter`; we quote the median and the inter-quartile range.
* **Compile time** (JAX only) is measured apart, on a fresh ``jax.jit`` object:
  ``jit(f).lower(x).compile()`` timed as a whole (tracing + lowering + XLA
  compilation), before the function has ever been called.
* **Peak memory** is measured apart from timing, by the best means each runtime
  offers: XLA's ``compiled.memory_analysis()`` for JAX (temporary + output
  buffers of the compiled program; arguments excluded because the input
  exists before the call); :mod:`tracemalloc` peak of one call for numpy-based
  libraries (sees every numpy array, outputs included, but not scratch memory
  that C/C++ code mallocs itself); the growth of the process's peak resident
  set (``VmHWM`` after resetting it through ``/proc/self/clear_refs`` and
  ``malloc_trim``) for torch, whose allocations tracemalloc cannot see.
"""

from __future__ import annotations

import ctypes
import gc
import os
import platform
import time
import tracemalloc
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = [
    "Timing",
    "time_round_robin",
    "jax_compile",
    "xla_memory_bytes",
    "tracemalloc_peak_bytes",
    "rss_peak_bytes",
    "machine_info",
    "load_average",
    "module_at",
    "print_ab_rows",
]


@dataclass
class Timing:
    """Wall times (seconds) of one competitor over the timed repeats."""

    name: str
    times: list[float] = field(default_factory=list)

    @property
    def median(self) -> float:
        return float(np.median(self.times))

    @property
    def q1(self) -> float:
        return float(np.percentile(self.times, 25))

    @property
    def q3(self) -> float:
        return float(np.percentile(self.times, 75))

    @property
    def iqr(self) -> float:
        return self.q3 - self.q1


def time_round_robin(
    competitors: dict[str, Callable[[], Any]],
    *,
    repeats: int,
    warmup: int = 2,
    progress: Callable[[str], None] | None = None,
) -> dict[str, Timing]:
    """Time each zero-argument callable ``repeats`` times, alternating between them.

    Each callable must run the complete workload and block until its result is
    ready. ``warmup`` untimed calls per competitor come first (JAX compiles and
    fills its caches there; numpy libraries fault in their pages). Then repeat
    ``r`` calls every competitor once, starting at competitor ``r mod n``, so
    no competitor always runs first or last. The garbage collector is run
    before, and disabled during, each timed call.
    """
    names = list(competitors)
    for name in names:
        for _ in range(warmup):
            competitors[name]()
    out = {name: Timing(name) for name in names}
    n = len(names)
    for r in range(repeats):
        order = names[r % n:] + names[: r % n]
        for name in order:
            gc.collect()
            gc.disable()
            try:
                t0 = time.perf_counter()
                competitors[name]()
                dt = time.perf_counter() - t0
            finally:
                gc.enable()
            out[name].times.append(dt)
        if progress is not None:
            progress(f"repeat {r + 1}/{repeats}")
    return out


def jax_compile(fn: Callable, *args: Any) -> tuple[float, Any]:
    """Compile ``fn`` for ``args`` on a fresh ``jax.jit``; return (seconds, compiled).

    The time covers tracing, lowering to StableHLO and XLA compilation; the
    compiled executable is returned so its memory analysis can be read.
    """
    import jax

    jitted = jax.jit(fn)
    t0 = time.perf_counter()
    compiled = jitted.lower(*args).compile()
    return time.perf_counter() - t0, compiled


def xla_memory_bytes(compiled: Any) -> dict[str, int] | None:
    """Temp / argument / output / alias bytes from ``compiled.memory_analysis()``, or None."""
    try:
        ma = compiled.memory_analysis()
    except Exception:  # noqa: BLE001 - backend may not implement it
        return None
    if ma is None:
        return None
    if isinstance(ma, (list, tuple)):
        ma = ma[0]
    keys = {
        "temp": "temp_size_in_bytes",
        "argument": "argument_size_in_bytes",
        "output": "output_size_in_bytes",
        "alias": "alias_size_in_bytes",
    }
    return {k: int(getattr(ma, attr, 0) or 0) for k, attr in keys.items()}


def tracemalloc_peak_bytes(fn: Callable[[], Any]) -> int:
    """Peak bytes traced by :mod:`tracemalloc` during one call of ``fn``.

    The result of the call is kept alive until the peak has been read, so the
    output arrays count. Memory that C code allocates with ``malloc`` directly
    (not through numpy or Python) is invisible to this method.
    """
    gc.collect()
    tracemalloc.start()
    try:
        tracemalloc.reset_peak()
        base, _ = tracemalloc.get_traced_memory()
        result = fn()
        _, peak = tracemalloc.get_traced_memory()
        del result
    finally:
        tracemalloc.stop()
    return max(0, peak - base)


def _status_kb(key: str) -> int:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(key + ":"):
                return int(line.split()[1])
    raise KeyError(key)


def rss_peak_bytes(fn: Callable[[], Any]) -> int | None:
    """Growth of the peak resident set during one call of ``fn`` (Linux only).

    Frees what the C allocator holds (``malloc_trim(0)``), resets the kernel's
    high-water mark (``echo 5 > /proc/self/clear_refs``), then reports
    ``VmHWM - VmRSS(before)`` after the call. Memory that an allocator keeps
    mapped from earlier calls and reuses is not counted, so this is a lower
    bound; it is used only where nothing better exists (torch on CPU).
    """
    try:
        gc.collect()
        try:
            ctypes.CDLL("libc.so.6").malloc_trim(0)
        except OSError:
            pass
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        base = _status_kb("VmRSS")
        result = fn()
        peak = _status_kb("VmHWM")
        del result
    except (OSError, KeyError):
        return None
    return max(0, peak - base) * 1024


def load_average() -> tuple[float, float, float] | None:
    try:
        return os.getloadavg()
    except OSError:
        return None


def machine_info() -> dict[str, str]:
    """CPU model, core count, memory, OS and Python: the facts a reader needs."""
    info = {"python": platform.python_version(), "os": f"{platform.system()} {platform.release()}"}
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    info["cpu"] = line.split(":", 1)[1].strip()
                    break
    except OSError:
        info["cpu"] = platform.processor() or "unknown"
    info["cores"] = str(os.cpu_count())
    try:
        info["memory"] = f"{_meminfo_kb('MemTotal') / 2**20:.1f} GiB"
    except (OSError, KeyError):
        pass
    return info


def _meminfo_kb(key: str) -> int:
    with open("/proc/meminfo") as f:
        for line in f:
            if line.startswith(key + ":"):
                return int(line.split()[1])
    raise KeyError(key)


def json_subprocess(script: str, args: list[str], timeout: float, on_error: dict) -> dict:
    """Run ``python script *args`` and parse its last stdout line as JSON (a measurement made in a
    fresh process, e.g. peak memory); on any failure, ``on_error`` plus the error text."""
    import json
    import subprocess
    import sys

    try:
        txt = subprocess.run([sys.executable, script, *args], capture_output=True, text=True, timeout=timeout,
                             check=True).stdout
        return json.loads(txt.strip().splitlines()[-1])
    except Exception as e:  # noqa: BLE001
        return {**on_error, "error": str(e)[:300]}


def module_at(commit: str, relpath: str, name: str):
    """The library module ``relpath`` (e.g. ``fsjax/ops/volume/_label3d.py``) as it was at git
    ``commit``, imported as ``name`` beside the current one, with ``@register`` switched off
    while it loads (its ops are not registered a second time). For old-vs-new A/B timings in
    one process."""
    import importlib.util
    import subprocess
    import tempfile
    from pathlib import Path

    import fsjax.registry as reg

    root = Path(__file__).resolve().parents[1]
    src = subprocess.run(["git", "show", f"{commit}:{relpath}"], cwd=root, check=True, capture_output=True,
                         text=True).stdout
    path = Path(tempfile.mkdtemp()) / (name.rsplit(".", 1)[-1] + ".py")
    path.write_text(src)
    spec = importlib.util.spec_from_file_location(name, path)
    mod = importlib.util.module_from_spec(spec)
    real = reg.register
    reg.register = lambda **kw: (lambda f: f)
    try:
        spec.loader.exec_module(mod)
    finally:
        reg.register = real
    return mod


def print_ab_rows(tim: dict, old: str, ref: str = "scipy", suffixes: tuple = ("", " B=4")) -> None:
    """Print the old and current ("now") medians of an A/B timing beside the reference's, with their
    ratio, one row per suffix (single, batched): the profile_* scripts' table."""
    for k in (old, "now"):
        for sfx in suffixes:
            t, s = tim[k + sfx].median, tim[ref + sfx].median
            print(f"  {k + sfx:16s} {t * 1e3:8.1f} ms   {ref} {s * 1e3:8.1f} ms   ratio {t / s:.2f}")
