"""Sweep every registered op's numeric parameters under ``jit`` (issue 20, item 3 and its sweep).

For each op and each keyword parameter that takes a number (int or float default, and the
``None``-default numeric parameters listed in ``EXTRA``), the sweep calls the op on the
standard inputs (``fsjax.synth.standard_input``; multi-input ops get one input per sort)

* eagerly with a set of probe values (negative, zero, the default, around the knob range,
  far above it, non-integer for int parameters, NaN), and
* under ``jax.jit`` with the same value *traced* (float32, one compile per parameter),

and classifies each value:

* ``ok-refused``   eager refuses, traced output poisoned (every float leaf NaN) or raises;
* ``ok-equal``     eager accepts, traced equals eager (float32 tolerances);
* ``ok-static``    the parameter fixes a shape: tracing it is refused with a TypeError;
* ``cautious``     eager accepts, traced poisoned (conservative, not wrong);
* ``FAIL-plausible`` eager refuses but the traced output is a normal-looking result;
* ``FAIL-differs`` eager accepts, traced differs and is not poisoned.

Run with x64 off (the user's default): ``python tools/sweep_traced_params.py [--start OP]
[--ops a,b] [--out sweep.jsonl]``. Prints one line per FAIL and a summary per op.
"""

from __future__ import annotations

import argparse
import json
import math
import signal
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

import fsjax
from fsjax.synth import standard_input

# numeric parameters whose default is None: probe values chosen per parameter
EXTRA = {
    ("measure_pairs", "row"): 10.0, ("measure_pairs", "col"): 10.0, ("measure_pairs", "length"): 10.0,
    ("measure_pos", "row"): 10.0, ("measure_pos", "col"): 10.0, ("measure_pos", "length"): 10.0,
    ("measure_projection", "row"): 10.0, ("measure_projection", "col"): 10.0,
    ("measure_projection", "length"): 10.0,
    ("decorrelation_stretch", "target_sigma"): 0.2,
    ("fft_phase", "floor"): 1e-3,
    ("blobness3d", "c"): 0.1, ("vesselness3d", "c"): 0.1,
    ("li", "tolerance"): 1e-3, ("li_level", "tolerance"): 1e-3,
}


class Timeout(Exception):
    pass


def _alarm(signum, frame):
    raise Timeout()


def probe_values(spec, name, default):
    d = float(default)
    vals = [-1.0, 0.0, d, 0.5 * d, 2.0 * d, d + 10.0, 1e4, math.nan, -d]
    k = spec.knobs.get(name)
    if k is not None:
        vals += [k.lo, k.hi, 1.5 * k.hi + 1.0, k.lo - 1.0]
    if isinstance(default, int):
        vals += [1.0, 2.0, d + 1.0, d + 0.5, 2.5]
    else:
        vals += [1e-6, 0.999 * d, 1.0]
    out = []
    for v in vals:
        if not any((math.isnan(v) and math.isnan(u)) or v == u for u in out):
            out.append(v)
    return out


def float_leaves(tree):
    return [np.asarray(x) for x in jax.tree_util.tree_leaves(tree)
            if hasattr(x, "dtype") and jnp.issubdtype(x.dtype, jnp.inexact)]


def poisoned(out) -> bool:
    fl = float_leaves(out)
    return bool(fl) and all(np.all(np.isnan(x)) for x in fl if x.size)


def flagged(out) -> bool:
    for f in ("valid", "converged", "found"):
        v = getattr(out, f, None)
        if v is not None and not bool(np.any(np.asarray(v))):
            return True
    return False


def max_diff(a, b):
    la, ta = jax.tree_util.tree_flatten(a)
    lb, tb = jax.tree_util.tree_flatten(b)
    if ta != tb:
        return math.inf
    d = 0.0
    for x, y in zip(la, lb):
        x, y = np.asarray(x), np.asarray(y)
        if x.shape != y.shape:
            return math.inf
        if np.issubdtype(x.dtype, np.inexact):
            xf, yf = x.astype(float), y.astype(float)
            nx, ny = np.isnan(xf), np.isnan(yf)
            if np.any(nx != ny):
                return math.inf
            m = ~nx & np.isfinite(xf) & np.isfinite(yf)
            if np.any(np.isinf(xf) != np.isinf(yf)):
                return math.inf
            if m.any():
                scale = max(1.0, float(np.max(np.abs(xf[m]))))
                d = max(d, float(np.max(np.abs(xf[m] - yf[m]))) / scale)
        elif not np.array_equal(x, y):
            return math.inf
    return d


def call(fn, timeout):
    signal.alarm(timeout)
    try:
        return fn(), None
    except Timeout:
        return None, "timeout"
    except Exception as e:  # noqa: BLE001 - the sweep records every refusal
        return None, f"{type(e).__name__}: {str(e).splitlines()[0][:160] if str(e) else ''}"
    finally:
        signal.alarm(0)


def sweep_param(spec, inputs, name, default, timeout, tol=2e-4):
    rows = []
    traced = jax.jit(lambda v: spec.fn(*inputs, **{name: v}))
    for v in probe_values(spec, name, default):
        pv = int(v) if (isinstance(default, int) and not math.isnan(v) and v == int(v)) else v
        eager, eerr = call(lambda pv=pv: jax.block_until_ready(spec.fn(*inputs, **{name: pv})), timeout)
        tr, terr = call(lambda v=v: jax.block_until_ready(traced(jnp.asarray(v, jnp.float32))), timeout)
        if terr is not None and ("static" in terr or "TracerIntegerConversion" in terr
                                 or "ConcretizationTypeError" in terr or "must be a static" in terr
                                 or "TracerBoolConversion" in terr):
            cls = "ok-static"
        elif eerr is not None and eerr != "timeout":
            if terr is not None:
                cls = "ok-refused"
            elif poisoned(tr):
                cls = "ok-refused"
            elif flagged(tr):
                cls = "flagged-refused"
            else:
                cls = "FAIL-plausible"
        elif eerr == "timeout" or terr == "timeout":
            cls = "timeout"
        else:
            if terr is not None:
                cls = "cautious-raises"
            elif poisoned(tr) and not poisoned(eager):
                cls = "cautious"
            else:
                d = max_diff(eager, tr)
                cls = "ok-equal" if d <= tol else "FAIL-differs"
        rows.append({"op": spec.name, "param": name, "value": v, "class": cls,
                     "eager": eerr or "ok", "traced": terr or ("poisoned" if tr is not None and poisoned(tr) else "ok")})
        if cls == "ok-static":
            break
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--ops", default="")
    ap.add_argument("--start", default="")
    ap.add_argument("--out", default="sweep_traced.jsonl")
    ap.add_argument("--timeout", type=int, default=60)
    args = ap.parse_args(argv)
    signal.signal(signal.SIGALRM, _alarm)
    specs = fsjax.list_ops()
    if args.ops:
        want = set(args.ops.split(","))
        specs = [s for s in specs if s.name in want]
    if args.start:
        names = [s.name for s in specs]
        specs = specs[names.index(args.start):]
    fails = 0
    with open(args.out, "a") as fh:
        for spec in specs:
            t0 = time.time()
            try:
                inputs = tuple(standard_input(t, i % 2) for i, t in enumerate(spec.takes))
            except Exception as e:  # noqa: BLE001
                print(f"{spec.name}: no standard input ({e})", flush=True)
                continue
            params = [(k, v) for k, v in spec.params.items()
                      if isinstance(v, (int, float)) and not isinstance(v, bool)]
            params += [(p, d) for (o, p), d in EXTRA.items() if o == spec.name]
            counts: dict[str, int] = {}
            for name, default in params:
                for r in sweep_param(spec, inputs, name, default, args.timeout):
                    fh.write(json.dumps(r) + "\n")
                    counts[r["class"]] = counts.get(r["class"], 0) + 1
                    if r["class"].startswith("FAIL") or r["class"] in ("timeout", "flagged-refused"):
                        fails += r["class"].startswith("FAIL")
                        print(f"  {r['class']}: {spec.name}({name}={r['value']}) eager={r['eager']} "
                              f"traced={r['traced']}", flush=True)
            fh.flush()
            print(f"{spec.name}: {len(params)} params, {counts} ({time.time() - t0:.1f} s)", flush=True)
    print(f"{fails} FAIL rows", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
