"""Running one chain four ways (eager, ``jit``, ``vmap`` over a batch of 2, ``grad``) and
classifying what goes wrong.

Each chain ends in one outcome: ``ok``, ``refused`` (an op raised fsjax's own clear error,
a ``ValueError``/``TypeError`` naming the op: the chain is cut there and its prefix still
runs the other ways; not a failure) or ``failed`` with exactly one class: the first check
that fails, in the order eager -> jit -> recompile -> vmap -> grad, and within a stage
CONTRACT -> SILENT_OVERFLOW -> GROWTH -> NONFINITE.

Tolerances (stated, for MISMATCH): a floating leaf agrees when
``|x - y| <= rtol * max(1, max|y|)`` element-wise (``rtol`` 1e-6 in float64, 2e-3 in
float32; NaN equals NaN; slots a ``valid`` mask marks unused are ignored); a bool or
integer leaf agrees when at most 1 % of its elements differ (a float that rounds across a
threshold flips a pixel), and a 0-d one must be equal; a solver's ``iterations`` is not
compared (a batched solve may take a step more or less, with the same answer); a record that
both ways refuse (its 0-d ``valid`` False in both) is compared on ``valid`` and ``reason`` only:
its other fields describe a failed solve (a non-converged iterate's score depends on the
path). A value that is NaN under the trace
where the eager call is finite is not a MISMATCH: a traced way may fail closed where an eager
call sizes its buffers from the data (``render_depth``); the traced output is then checked
as NONFINITE (explained only by a flag or a sort's documented NaN) and later stages, which
saw other data, are not compared. A stage after the first that differs is judged on the same
input: its compiled program is called on the stage's eager input, and if it agrees there the
difference is upstream round-off amplified by the op's conditioning (``Outcome.conditioned``,
not a failure; later stages not compared); otherwise it is a MISMATCH.
"""

from __future__ import annotations

import dataclasses
import re
import time
from collections.abc import Sequence
from typing import Any

from ._gen import SIZES, Chain, build_input, float_dtype, knob_values, raster_size

__all__ = ["CLASSES", "Outcome", "Runner"]

CLASSES = ("CONTRACT", "SUSPECT", "TYPEMISS", "NONFINITE", "MISMATCH", "GRADNAN", "RECOMPILE", "GROWTH",
           "SILENT_OVERFLOW")

RTOL = {"float64": 1e-6, "float32": 2e-3}
DISCRETE_FRACTION = 0.01
# solver diagnostics not compared: an iterative fit's step count may differ by a step between a
# batched and a single solve (rounding in the accept/reject test), with equal parameters
DIAGNOSTIC_FIELDS = ("iterations",)
GROWTH_FACTOR = 64          # output bytes > 64 x input bytes + 1 MiB
GROWTH_SLACK = 1 << 20
_FLAGS_EXPLAIN = ("converged", "found")


@dataclasses.dataclass
class Outcome:
    status: str                     # "ok" | "refused" | "failed" | "error" (the fuzzer's own trouble)
    cls: str | None = None
    signature: str | None = None
    stage: int | None = None        # 0-based stage blamed (None: the chain as a whole)
    op: str | None = None
    mode: str | None = None         # eager | jit | recompile | vmap | grad | check
    message: str = ""
    executed: tuple[str, ...] = ()  # ops whose eager call completed
    refused: tuple[str, str] | None = None   # (op, message) of a clear refusal
    refused_traced: tuple[str, str] | None = None
    # a stage whose traced output differed from the eager one only because its input did (the
    # upstream round-off, amplified by an ill-conditioned op): (op, stage, detail); not a failure
    conditioned: tuple[str, int, str] | None = None
    seconds: float = 0.0
    times: dict = dataclasses.field(default_factory=dict)   # seconds per way (eager, jit, vmap, grad)

    def to_json(self) -> dict:
        return dataclasses.asdict(self)


class _Fail(Exception):
    def __init__(self, cls: str, stage: int | None, op: str | None, mode: str, detail: str, message: str = ""):
        super().__init__(message or detail)
        self.cls, self.stage, self.op, self.mode, self.detail = cls, stage, op, mode, detail
        self.message = message or detail


# ---------------------------------------------------------------------------
# compile counting
# ---------------------------------------------------------------------------

_COMPILES = {"n": 0, "s": 0.0}   # backend compiles + traces, and their seconds
_LISTENING = {"on": False}


def _listen() -> None:
    if _LISTENING["on"]:
        return
    import jax.monitoring

    events = ("/jax/core/compile/backend_compile_duration", "/jax/core/compile/jaxpr_trace_duration")

    def on(event, duration, **kw):
        if event in events:
            _COMPILES["n"] += 1
            _COMPILES["s"] += float(duration)

    jax.monitoring.register_event_duration_secs_listener(on)
    _LISTENING["on"] = True


# ---------------------------------------------------------------------------
# errors
# ---------------------------------------------------------------------------

_TRACER_ERRORS: tuple = ()


def _tracer_errors() -> tuple:
    global _TRACER_ERRORS
    if not _TRACER_ERRORS:
        import jax

        _TRACER_ERRORS = (jax.errors.ConcretizationTypeError, jax.errors.TracerArrayConversionError,
                          jax.errors.TracerIntegerConversionError, jax.errors.TracerBoolConversionError,
                          jax.errors.UnexpectedTracerError)
    return _TRACER_ERRORS


_SORT_REFUSAL = re.compile(r"argument '?\w+'? must be [A-Z]\w*, got |takes \d+ positional input")


def _first_line(e: BaseException) -> str:
    text = str(e).strip().split("\n")[0]
    return f"{type(e).__name__}: {text[:300]}"


def _norm(text: str) -> str:
    """Message with numbers and quoted values blanked, for grouping duplicates."""
    text = re.sub(r"-?\d+(\.\d+)?(e-?\d+)?", "N", text)
    text = re.sub(r"\(N(, N)*\)", "(shape)", text)
    return text[:120]


def classify_exception(e: BaseException, op: str, stage: int, mode: str) -> tuple[str, str] | _Fail:
    """A clear fsjax refusal -> ``("refused", message)``; anything else -> a ``_Fail``."""
    msg = str(e)
    if isinstance(e, _tracer_errors()):
        return _Fail("SUSPECT", stage, op, mode, f"{type(e).__name__}", _first_line(e))
    head = msg[:400]
    names_op = op in head
    if isinstance(e, (ValueError, TypeError)) and names_op:
        if isinstance(e, TypeError) and _SORT_REFUSAL.search(head):
            return _Fail("TYPEMISS", stage, op, mode, "op refused a sort the checker accepted", _first_line(e))
        return ("refused", _first_line(e))
    if "Equinox" in type(e).__name__ or (type(e).__name__ in ("XlaRuntimeError", "JaxRuntimeError")
                                          and "equinox" in msg.lower()):
        # an op's own run-time refusal (``equinox.error_if``): under jit it arrives wrapped in the
        # runtime's callback traceback; the op's message is on the EquinoxRuntimeError line
        m = re.search(r"EquinoxRuntimeError: ([^\n]+)", msg)
        text = m.group(1) if m else head
        if op in text:
            return ("refused", f"{type(e).__name__}: {text[:300]}")
    return _Fail("SUSPECT", stage, op, mode, f"{type(e).__name__}: {_norm(msg.strip().split(chr(10))[0])}",
                 _first_line(e))


# ---------------------------------------------------------------------------
# tree helpers
# ---------------------------------------------------------------------------


def _leaves_with_mask(tree):
    """``(leaf, mask)`` pairs: mask marks meaningful elements (a ``valid`` mask where it applies)."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    valid = getattr(tree, "valid", None)
    if valid is not None:
        valid = np.asarray(valid)
        if valid.dtype != np.bool_ or valid.ndim == 0:
            valid = None
    out = []
    for path, leaf in jax.tree_util.tree_flatten_with_path(tree)[0]:
        a = np.asarray(leaf)
        m = None
        if valid is not None and a.ndim >= valid.ndim and a.shape[: valid.ndim] == valid.shape \
                and not (a.dtype == np.bool_ and a.shape == valid.shape and np.array_equal(a, valid)):
            m = valid.reshape(valid.shape + (1,) * (a.ndim - valid.ndim))
            m = np.broadcast_to(m, a.shape)
        out.append((a, m, jnp.issubdtype(a.dtype, jnp.inexact), jax.tree_util.keystr(path)))
    return out


def _traced_overflow_eager_grew(x, y) -> bool:
    """True when the traced record ``x`` is flagged ``truncated`` and the eager ``y`` is not: the
    registry grows a defaulted ``capacity`` / ``max_neighbors`` in eager calls only, so the traced
    way reports the overflow (fails closed) where the eager way measured everything. A traced
    record NOT flagged while the eager one is, or flags that agree, are compared as usual."""
    import numpy as np

    tx, ty = getattr(x, "truncated", None), getattr(y, "truncated", None)
    if tx is None or ty is None:
        return False
    tx, ty = np.asarray(tx), np.asarray(ty)
    return tx.dtype == np.bool_ and bool(np.any(tx)) and not bool(np.any(ty))


def _undefined_circularity_only(props) -> bool:
    """True when every NaN in a RegionProps' valid rows is a ``circularity`` whose row's ``perimeter``
    is 0 (the measure ops document it: "circularity = 4 pi area / perimeter^2, NaN for a zero
    perimeter"; a one-pixel region has perimeter 0). Any other NaN, or a NaN circularity beside a
    positive perimeter, or a table without the perimeter column, is not explained."""
    import numpy as np

    names = list(getattr(props, "names", ()) or ())
    if "circularity" not in names or "perimeter" not in names:
        return False
    table = np.asarray(props.table)
    rows = np.asarray(props.valid, bool)
    if table.ndim < 2 or rows.shape != table.shape[:-1]:
        return False
    t = table[rows]   # (valid rows over any batch, F)
    nan = np.isnan(t)
    ci, pi = names.index("circularity"), names.index("perimeter")
    others = np.delete(nan, ci, axis=1)
    return not others.any() and bool(np.all(t[nan[:, ci], pi] == 0))


def _nbytes(tree) -> int:
    import jax

    return sum(int(getattr(v, "nbytes", 0)) for v in jax.tree_util.tree_leaves(tree))


def _both_refused(x, y) -> bool:
    """True when both records carry a 0-d boolean ``valid`` that is False (both ways refuse)."""
    import numpy as np

    def refused(r):
        v = getattr(r, "valid", None)
        if v is None:
            return False
        v = np.asarray(v)
        return v.ndim == 0 and v.dtype == np.bool_ and not bool(v)

    return refused(x) and refused(y)


def _differ(x, y, dtype: str, nan_only: list | None = None) -> str | None:
    """``None`` when trees agree within the stated tolerance, else a short description.

    Floating values that are NaN in ``x`` (the traced way) where ``y`` (eager) is finite are
    not counted as a difference when ``nan_only`` is a list: their counts are appended to it,
    and the caller checks the traced output as a NONFINITE candidate instead (a traced way
    may fail closed where an eager call could size its buffers from the data). Likewise a traced
    record flagged ``truncated`` against an eager one that is not: an eager call whose capacity was
    left at its default grows it and runs again (``fsjax.registry._grow_when_eager``), a traced
    call cannot and says so (:func:`_traced_overflow_eager_grew`).
    """
    import jax
    import numpy as np

    if nan_only is None:
        nan_only = []
        strict = True
    else:
        strict = False
    if type(x) is not type(y):
        return f"sorts differ ({type(x).__name__} vs {type(y).__name__})"
    tx, ty = jax.tree_util.tree_structure(x), jax.tree_util.tree_structure(y)
    if tx != ty:
        return "tree structure or static fields differ"
    if not strict and _traced_overflow_eager_grew(x, y):
        nan_only.append(0)   # the traced way failed closed: the caller stops comparing this chain
        return None
    if _both_refused(x, y):
        rx, ry = getattr(x, "reason", None), getattr(y, "reason", None)
        if rx is not None and ry is not None and not np.array_equal(np.asarray(rx), np.asarray(ry)):
            return f"reason: {np.asarray(rx)} vs {np.asarray(ry)} (both refused)"
        return None
    rtol = RTOL.get(dtype, 2e-3)
    for (a, m, fl, name), (b, _, _, _) in zip(_leaves_with_mask(x), _leaves_with_mask(y)):
        if a.shape != b.shape:
            return f"{name}: shape {a.shape} vs {b.shape}"
        if name.split(".")[-1] in DIAGNOSTIC_FIELDS:
            continue
        if fl:
            fa, fb = np.asarray(a, float), np.asarray(b, float)
            scale = max(1.0, float(np.max(np.abs(fb[np.isfinite(fb)]), initial=0.0)))
            close = np.isclose(fa, fb, rtol=0.0, atol=rtol * scale, equal_nan=True)
            if m is not None:
                close |= ~m
            if not close.all():
                bad = ~close
                if not strict and np.all(np.isnan(fa[bad]) & np.isfinite(fb[bad])):
                    nan_only.append(int(bad.sum()))
                    continue
                d = np.abs(fa - fb)[bad & np.isfinite(fa) & np.isfinite(fb)]
                return (f"{name}: {int(bad.sum())} of {bad.size} values differ (max {float(d.max()) if d.size else float('nan'):.3g}"
                        f", scale {scale:.3g})")
        else:
            ne = a != b
            if m is not None:
                ne &= m
            n = int(np.sum(ne))
            if n and (a.ndim == 0 or n > DISCRETE_FRACTION * a.size):
                return f"{name}: {n} of {a.size} discrete values differ"
    return None


# ---------------------------------------------------------------------------
# the runner
# ---------------------------------------------------------------------------


class Runner:
    """Runs chains over the ops ``specs`` (``OpSpec`` list) and classifies the outcome.

    ``whole_chain``: besides the per-stage compiled programs (always), also compile the
    chain whole (``jit(vmap(chain))`` and ``jit(value_and_grad)``) -- the default of
    :meth:`run`; :func:`fsjax.fuzz.fuzz` turns it on for a stated fraction of chains.
    Compiled stage programs, pool inputs and eager recompile checks are cached on the
    runner across chains (the cache is the point: one runner per run).
    """

    def __init__(self, specs: Sequence[Any], *, grad: bool = True, vmap: bool = True, whole_chain: bool = False):
        _listen()
        self.specs = {s.name: s for s in specs}
        self.sorts = {}
        for s in specs:
            for t in (*s.takes, s.gives):
                self.sorts[t.__name__] = t
        self.do_grad = grad
        self.do_vmap = vmap
        self.whole_chain = whole_chain
        self._pool: dict = {}          # (sort, kind, size, dtype, variant) -> input
        self._vprog: dict = {}         # stage key -> jit(vmap(stage))
        self._jprog: dict = {}         # stage key -> jit(stage)
        self._gprog: dict = {}         # stage key -> jit(vjp of stage)
        self._eager_seen: set = set()  # eager stage keys whose second call was checked
        # results of chain prefixes that passed every check, keyed by (input, stages so far):
        # a chain extending an earlier chain's prefix (the generator's reuse phase) takes them
        # instead of running those stages again (the same input, op, knob values and
        # parameters give the same result; they were checked the first time)
        self._eager_done: dict = {}    # prefix key -> (stage inputs, eager output)
        self._staged_done: dict = {}   # prefix key -> running batch after the stage program
        self._stage_ins = None         # the running chain's eager stage inputs (the whole-chain way)
        self.stats = {"stage_calls": 0, "stage_hits": 0, "grad_calls": 0, "grad_hits": 0, "whole": 0,
                      "eager_calls": 0, "eager_hits": 0, "staged_prefix_hits": 0}

    # -- pieces -----------------------------------------------------------
    def release_if_needed(self) -> bool:
        """Drop every compiled program (the runner's and JAX's caches) when the process holds more
        than half of the kernel's ``vm.max_map_count`` memory mappings: each XLA:CPU executable
        keeps a few, and at the limit the JIT linker fails ("Failed to materialize symbols") and
        the process dies. Programs are compiled again on demand. True when released."""
        from .._cache import near_map_limit

        if not near_map_limit():
            return False
        import gc

        import jax

        self._vprog.clear()
        self._jprog.clear()
        self._gprog.clear()
        self._staged_done.clear()
        jax.clear_caches()
        gc.collect()
        self.stats["released"] = self.stats.get("released", 0) + 1
        return True

    def _build(self, sort: type, kind: str, size: tuple, dtype: str, variant: int):
        key = (sort.__name__, kind, tuple(size), dtype, variant)
        x = self._pool.get(key)
        if x is None:
            x = self._pool[key] = build_input(sort, kind, tuple(size), dtype, variant)
        return x

    def _inputs(self, chain: Chain, variant: int):
        i = chain.inp
        return self._build(self.sorts[i["sort"]], i["kind"], tuple(i["size"]), i["dtype"], variant)

    def _assemble(self, st, spec, cur, dtype: str) -> tuple:
        args = []
        for j, t in enumerate(spec.takes):
            if j == st.slot:
                args.append(cur)
            else:
                args.append(self._build(t, "scene", raster_size(cur) or SIZES[0], dtype, 1))
        return tuple(args)

    def _traced(self, chain: Chain, dtype: str):
        specs = [self.specs[s.op] for s in chain.stages]

        def f(x, knobs):
            outs = []
            cur = x
            for i, (st, spec) in enumerate(zip(chain.stages, specs)):
                a = knobs[i, 0] if st.a is not None else None
                b = knobs[i, 1] if st.b is not None else None
                kp = spec.knob_params(a, b, strict=False)
                cur = spec.fn(*self._assemble(st, spec, cur, dtype), **kp, **dict(st.params))
                outs.append(cur)
            return tuple(outs)

        return f

    # -- per-stage compiled programs ------------------------------------------------
    @staticmethod
    def _stage_fn(st, spec):
        params = dict(st.params)

        def f(x, extras, kn):
            args = list(extras)
            args.insert(st.slot, x)
            a = kn[0] if st.a is not None else None
            b = kn[1] if st.b is not None else None
            return spec.fn(*args, **spec.knob_params(a, b, strict=False), **params)

        return f

    @staticmethod
    def _stage_key(st, x, extras, dtype: str) -> tuple:
        """What a compiled stage program depends on: the op, its static choices, the input avals."""
        return (st.op, st.slot, st.params, st.a is None, st.b is None, dtype, _avals(x), _avals(extras))

    def _call(self, cache: dict, key: tuple, make, *args):
        """``(output, hit)``: the cached program for ``key`` (made on a miss) called on ``args``;
        a hit that compiles again is a RECOMPILE (raised by the caller: ``hit`` and ``compiled``)."""
        import jax

        prog = cache.get(key)
        hit = prog is not None
        if not hit:
            prog = cache[key] = make()
        c0 = _COMPILES["n"]
        y = jax.block_until_ready(prog(*args))
        return y, hit, _COMPILES["n"] != c0

    # -- checks on one eager stage output ------------------------------------
    def _check_stage(self, i: int, spec, ins: tuple, out, kp: dict, params: tuple) -> None:
        import jax.numpy as jnp
        import numpy as np

        op = spec.name
        if not isinstance(out, spec.gives):
            raise _Fail("CONTRACT", i, op, "eager", f"returned {type(out).__name__}, declared {spec.gives.__name__}")
        try:
            bshape = out.batch_shape
        except Exception:  # noqa: BLE001 - a sort without batch_shape is itself a contract break
            bshape = None
        want = _declared_batch(spec, params)
        if bshape != want:
            raise _Fail("CONTRACT", i, op, "eager", f"output batch shape {bshape}, expected {want}")
        # the inputs' floating dtypes promoted together (a float64 template beside a float32 image
        # gives float64, as JAX promotes; the fifth run's false CONTRACT in shape_locate, whose
        # template came from distance_transform of a Region: float64 with x64 on)
        dts = [d for d in (float_dtype(a) for a in ins) if d]
        in_dt = str(jnp.result_type(*dts)) if dts else None
        out_dt = float_dtype(out)
        if in_dt and out_dt and in_dt != out_dt:
            raise _Fail("CONTRACT", i, op, "eager", f"dtype not kept ({in_dt} in, {out_dt} out)")
        if type(out).__name__ == "Labels":
            d = np.asarray(out.data)
            c = int(np.asarray(out.count))
            if d.size and (d.min() < 0 or d.max() > c):
                raise _Fail("CONTRACT", i, op, "eager", "label values outside 0..count")
        # capacity: a truncated input must pass its flag on; a full fixed capacity smaller than
        # the input with no flag set has very likely dropped data silently
        t_out = getattr(out, "truncated", None)
        if t_out is not None:
            lost = any(bool(np.any(np.asarray(getattr(a, "truncated", False)))) for a in ins)
            if lost and not bool(np.any(np.asarray(t_out))):
                raise _Fail("SILENT_OVERFLOW", i, op, "eager", "input truncated, output flag not set")
            cap = dict(params).get("capacity")
            default = spec.params.get("capacity")
            if isinstance(cap, int) and isinstance(default, int) and cap < default \
                    and not bool(np.any(np.asarray(t_out))):
                # a capacity below the default: the same call at the default capacity must not find
                # more items than fitted, unless the flag says so
                big = spec.fn(*ins, **kp, **{**dict(params), "capacity": default})
                n_small, n_big = _n_found(out), _n_found(big)
                if n_small is not None and n_big is not None and n_big > n_small:
                    raise _Fail("SILENT_OVERFLOW", i, op, "eager",
                                f"capacity {cap}: {n_small} items kept of {n_big}, truncated not set")
        nb_in = sum(_nbytes(a) for a in ins)
        nb_out = _nbytes(out)
        if nb_out > GROWTH_FACTOR * nb_in + GROWTH_SLACK:
            raise _Fail("GROWTH", i, op, "eager", f"output {nb_out} bytes from {nb_in} bytes of input")
        self._check_finite(i, op, out, "eager", params)

    def _check_finite(self, i: int, op: str, out, mode: str, params=None) -> None:
        import numpy as np

        bad = False
        infs = False
        for a, m, fl, _ in _leaves_with_mask(out):
            if not fl:
                continue
            nf = ~np.isfinite(a)
            if m is not None:
                nf &= m
            if nf.any():
                bad = True
                infs |= bool(np.isinf(a[nf]).any())
        if not bad:
            return
        for f in _FLAGS_EXPLAIN:
            v = getattr(out, f, None)
            if v is not None and not bool(np.all(np.asarray(v))):
                return
        v = getattr(out, "valid", None)  # a record's own validity flag (Match3D: NaN pose when not valid)
        if v is not None and np.ndim(v) == 0 and np.asarray(v).dtype == np.bool_ and not bool(v):
            return
        t = getattr(out, "truncated", None)
        if t is not None and bool(np.any(np.asarray(t))):
            return
        if type(out).__name__ in ("Feature", "Depth") and not infs:
            return  # documented: a NaN Feature is "could not measure", a NaN depth "no return"
        if type(out).__name__ == "RegionProps" and not infs and _undefined_circularity_only(out):
            return  # documented: circularity is NaN for a region of zero perimeter (one pixel)
        if self._documented_neg_inf(op, out, params):
            return
        raise _Fail("NONFINITE", i, op, mode, "inf in the output" if infs else "NaN in the output")

    def _documented_neg_inf(self, op: str, out, params) -> bool:
        """True when ``out``'s only non-finite values are ones the op documents: NaN for an op in
        ``DOCUMENTED_NAN``, +-inf for one in ``DOCUMENTED_OVERFLOW``, one infinity over the whole
        output for one in ``DOCUMENTED_ALL_INF``, -inf for the parameter values in
        ``DOCUMENTED_NEG_INF``."""
        import numpy as np

        if params is None:
            return False
        if op in DOCUMENTED_NAN:   # NaN (not inf) where the op documents "undefined"
            return all(not (fl and np.any(np.isinf(a))) for a, _, fl, _ in _leaves_with_mask(out))
        if op in DOCUMENTED_OVERFLOW:   # +-inf (not NaN) where the op documents overflow
            return all(not (fl and np.any(np.isnan(a))) for a, _, fl, _ in _leaves_with_mask(out))
        if op in DOCUMENTED_ALL_INF:   # one infinity over the whole output (an empty class)
            return all(not fl or (a.size > 0 and bool(np.all(np.isinf(a))) and bool(np.all(a == a.flat[0])))
                       for a, _, fl, _ in _leaves_with_mask(out))
        rule = DOCUMENTED_NEG_INF.get(op)
        if rule is None:
            return False
        name, value = rule
        given = dict(params).get(name, self.specs[op].params.get(name) if op in self.specs else None)
        if given != value:
            return False
        for a, _, fl, _ in _leaves_with_mask(out):
            if fl and np.any(np.isnan(a) | (np.isinf(a) & (a > 0))):
                return False
        return True

    # -- the four ways ----------------------------------------------------------
    def run(self, chain: Chain, *, whole: bool | None = None) -> Outcome:
        """Run ``chain`` every way; ``whole`` (default: the runner's ``whole_chain``) also
        compiles the chain whole."""
        t0, p0 = time.perf_counter(), time.process_time()
        c0, s0 = _COMPILES["n"], _COMPILES["s"]
        out = Outcome("ok")
        self._pending = None
        whole = self.whole_chain if whole is None else whole
        try:
            self._run(chain, out, whole)
            if self._pending is not None:
                raise self._pending
        except _Fail as f:
            out.status = "failed"
            out.cls, out.stage, out.op, out.mode, out.message = f.cls, f.stage, f.op, f.mode, f.message
            out.signature = f"{f.cls} {f.op or 'chain'} [{f.mode}] {_norm(f.detail)}"
        except Exception as e:  # noqa: BLE001 - the fuzzer's own trouble (an input it cannot build)
            out.status = "error"
            out.message = _first_line(e)
        out.seconds = time.perf_counter() - t0
        out.times["compiles"] = _COMPILES["n"] - c0
        out.times["compile_s"] = _COMPILES["s"] - s0
        out.times["whole"] = bool(whole)
        out.times["cpu_s"] = time.process_time() - p0   # process CPU time (the machine may be shared)
        return out

    def _run(self, chain: Chain, out: Outcome, whole: bool) -> None:
        import jax
        import jax.numpy as jnp

        from fsjax.pipeline import PipelineTypeError, pipeline
        from fsjax.pipeline import Stage as PStage

        specs = [self.specs[s.op] for s in chain.stages]
        dtype = chain.inp["dtype"]
        # the pipeline checker must accept a type-correct linear chain
        if all(s.linear for s in specs) and all(st.slot == 0 for st in chain.stages):
            try:
                pipeline([PStage(sp, params=st.params) for sp, st in zip(specs, chain.stages)])
            except PipelineTypeError as e:
                raise _Fail("TYPEMISS", e.index, e.op, "check", "pipeline checker refused a type-correct chain",
                            _first_line(e)) from None
        x = self._inputs(chain, 0)
        # eager
        t_start = time.perf_counter()
        executed = []
        cur = x
        eager_outs = []
        stage_ins = []   # the eager inputs of every stage (all slots)
        n_ok = len(chain.stages)
        ikey = tuple(sorted(chain.inp.items()))
        c_eager = _COMPILES["s"]
        cached: set = set()   # stages whose eager result came from an earlier chain's prefix
        for i, (st, spec) in enumerate(zip(chain.stages, specs)):
            self.stats["eager_calls"] += 1
            done = self._eager_done.get((ikey, chain.stages[: i + 1]))
            if done is not None:  # this prefix ran and passed every check before: its result
                self.stats["eager_hits"] += 1
                cached.add(i)
                ins, y = done
                executed.append(spec.name)
                eager_outs.append(y)
                stage_ins.append(ins)
                cur = y
                continue
            ins = self._assemble(st, spec, cur, dtype)
            try:
                kp = spec.knob_params(st.a, st.b, strict=True)
                y = spec.fn(*ins, **kp, **dict(st.params))
            except Exception as e:  # noqa: BLE001 - classified
                r = classify_exception(e, spec.name, i, "eager")
                if isinstance(r, _Fail):
                    raise r from None
                out.status, out.refused = "refused", (spec.name, r[1])
                n_ok = i
                break
            if chain.inp["kind"] == "nan" and i == 0:
                raise _Fail("CONTRACT", 0, spec.name, "eager", "all-NaN input accepted at the door")
            self._check_stage(i, spec, ins, y, kp, st.params)
            self._remember(self._eager_done, (ikey, chain.stages[: i + 1]), (ins, y))
            executed.append(spec.name)
            eager_outs.append(y)
            stage_ins.append(ins)
            cur = y
        out.executed = tuple(executed)
        if n_ok == 0:
            return
        chain = chain.replace(stages=chain.stages[:n_ok])
        specs = specs[:n_ok]
        # eager again on the same input: op-by-op dispatch is cached, nothing may compile. Checked
        # the first time a stage (op, knob values, parameters, input shapes) is seen in this run.
        self._pending = None
        for i, (st, spec) in enumerate(zip(chain.stages, specs)):
            ins = stage_ins[i]
            ekey = (st.op, st.slot, st.a, st.b, st.params, dtype, _avals(ins))
            if ekey in self._eager_seen:
                continue
            self._eager_seen.add(ekey)
            kp = spec.knob_params(st.a, st.b, strict=True)
            if i in cached:
                # not called in this chain (its result came from an earlier chain, whose check
                # did not run if that chain failed): a first call, since the compiled programs
                # may have been released in between (release_if_needed)
                jax.block_until_ready(spec.fn(*ins, **kp, **dict(st.params)))
            c0 = _COMPILES["n"]
            jax.block_until_ready(spec.fn(*ins, **kp, **dict(st.params)))
            if _COMPILES["n"] != c0 and self._pending is None:
                # reported only when nothing else fails: the traced ways still run
                self._pending = _Fail("RECOMPILE", i, spec.name, "eager",
                                      "a second eager call with the same input compiled again")
        out.times["eager"] = time.perf_counter() - t_start
        out.times["eager_compile_s"] = _COMPILES["s"] - c_eager
        x2 = self._inputs(chain, 1)
        self._stage_ins = stage_ins
        t_start, c_s = time.perf_counter(), _COMPILES["s"]
        self._staged(chain, specs, x, x2, stage_ins, eager_outs, dtype, out, ikey)
        out.times["staged"] = time.perf_counter() - t_start
        out.times["staged_compile_s"] = _COMPILES["s"] - c_s
        differentiable = self.do_grad and all(s.differentiable for s in specs)
        if differentiable:
            t_start, c_s = time.perf_counter(), _COMPILES["s"]
            self._grad_staged(chain, specs, stage_ins, eager_outs, dtype)
            out.times["grad"] = time.perf_counter() - t_start
            out.times["grad_compile_s"] = _COMPILES["s"] - c_s
        if not whole:
            return
        self.stats["whole"] += 1
        knobs = jnp.asarray(knob_values(chain), dtype=dtype)
        f = self._traced(chain, dtype)
        t_start = time.perf_counter()
        self._whole(chain, f, x, x2, knobs, eager_outs, dtype, out)
        out.times["whole_traced"] = time.perf_counter() - t_start
        if differentiable:
            t_start = time.perf_counter()
            self._grad(chain, f, x, knobs, (stage_ins, eager_outs))
            out.times["whole_grad"] = time.perf_counter() - t_start

    # -- the traced ways, stage by stage -------------------------------------------
    @staticmethod
    def _remember(cache: dict, key, value, limit: int = 3000) -> None:
        cache[key] = value
        if len(cache) > limit:  # the oldest first
            del cache[next(iter(cache))]

    def _staged(self, chain, specs, x, x2, stage_ins, eager_outs, dtype, out, ikey=None) -> None:
        """Each stage through its cached ``jit(vmap(stage))`` over the batch ``[x, x2]`` (member 0
        must equal the eager result); the running batch feeds the next stage's program."""
        import jax

        batched = False
        cur = x
        if self.do_vmap:
            try:
                cur = _host_stack(x, x2)
                batched = True
            except ValueError:
                cur = x  # the two variants differ in static fields: no batch
        for i, (st, spec) in enumerate(zip(chain.stages, specs)):
            op = spec.name
            extras = tuple(a for j, a in enumerate(stage_ins[i]) if j != st.slot)
            kn = _knob_array(st, dtype)
            pkey = (ikey, batched, chain.stages[: i + 1])
            done = self._staged_done.get(pkey) if ikey is not None else None
            if done is not None:  # this prefix passed its stage programs before: their batch
                self.stats["staged_prefix_hits"] += 1
                cur = done
                continue
            member = _device(_host_index(cur, 0)) if batched else cur
            key = self._stage_key(st, member, extras, dtype)
            f = self._stage_fn(st, spec)
            mode = "vmap" if batched else "jit"
            self.stats["stage_calls"] += 1
            try:
                if batched:
                    y, hit, compiled = self._call(self._vprog, key, lambda f=f: _jit(jax.vmap(f, in_axes=(0, None, None))),
                                                  cur, extras, kn)
                else:
                    y, hit, compiled = self._call(self._jprog, key, lambda f=f: _jit(f), cur, extras, kn)
            except Exception as e:  # noqa: BLE001 - classified
                if not batched or self._stage_jit(i, st, f, key, member, extras, kn, eager_outs[i], dtype, out):
                    self._stage_error(e, i, op, mode, out)
                return
            self.stats["stage_hits"] += hit
            if hit and compiled:
                raise _Fail("RECOMPILE", i, op, mode, "a cached stage program called again with the same shapes "
                            "compiled again")
            got = _host_index(y, 0) if batched else y
            nans: list = []
            d = _differ(got, eager_outs[i], dtype, nans)
            if nans and not d:
                self._check_finite(i, op, got, mode, st.params)
                return  # failed closed under the trace: later stages would see other data
            if d:
                if not batched:
                    if self._same_input_agrees(i, st, spec, stage_ins, eager_outs, dtype, d, out):
                        return  # conditioning, not the traced way: later stages saw other data
                    raise _Fail("MISMATCH", i, op, mode, f"{mode} vs eager: " + d.split(" (")[0], d)
                if self._stage_jit(i, st, f, key, member, extras, kn, eager_outs[i], dtype, out,
                                   (spec, stage_ins, eager_outs)):
                    raise _Fail("MISMATCH", i, op, mode, f"{mode} vs eager: " + d.split(" (")[0], d)
                return
            if not hit:
                # a new program: called again with the same shapes (the batch reversed) it must not
                # compile, and a member's answer must not depend on its position
                rev = jax.block_until_ready(_device(_host_index(cur, slice(None, None, -1)))) if batched else None
                c0 = _COMPILES["n"]
                if batched:
                    y2 = jax.block_until_ready(self._vprog[key](rev, extras, kn))
                else:
                    y2 = jax.block_until_ready(self._jprog[key](cur, extras, kn))
                if _COMPILES["n"] != c0:
                    raise _Fail("RECOMPILE", i, op, mode, "a compiled stage program called again with the same shapes "
                                "compiled again")
                if batched:
                    d = _differ(_host_index(y2, 1), got, dtype)
                    if d:
                        raise _Fail("MISMATCH", i, op, "vmap", "batch member depends on its position: " + d.split(" (")[0],
                                    d)
            cur = y
            if ikey is not None:
                self._remember(self._staged_done, pkey, y)

    def _stage_jit(self, i, st, f, key, member, extras, kn, ye, dtype, out, same=None) -> bool:
        """Plain ``jit(stage)`` on member 0's input: raises a ``_Fail`` for a broken jit way; True
        when jit is sound (so the vmap way is to blame). ``same = (spec, stage_ins, eager_outs)``
        lets a jit difference be judged on the eager input (:meth:`_same_input_agrees`)."""

        try:
            yj, _, _ = self._call(self._jprog, key, lambda: _jit(f), member, extras, kn)
        except Exception as e:  # noqa: BLE001 - classified
            self._stage_error(e, i, st.op, "jit", out)
            return False
        nans: list = []
        d = _differ(yj, ye, dtype, nans)
        if nans and not d:
            self._check_finite(i, st.op, yj, "jit", st.params)
            return False
        if d:
            if same is not None and self._same_input_agrees(i, st, same[0], same[1], same[2], dtype, d, out):
                return False
            raise _Fail("MISMATCH", i, st.op, "jit", "jit vs eager: " + d.split(" (")[0], d)
        return True

    def _same_input_agrees(self, i, st, spec, stage_ins, eager_outs, dtype, d, out) -> bool:
        """True when stage ``i``'s compiled program, given the **eager** input of the stage, agrees
        with the eager output: the traced way computes the op as the eager one does, and the
        chain's difference at this stage is the upstream stages' round-off (each within the
        tolerance) amplified by an ill-conditioned op (the phase of a coefficient near round-off,
        the histogram of a near-flat image). Recorded in ``out.conditioned`` and the run's
        ``stats["conditioned"]``; the chain's later stages are not compared (they saw other data).
        A first stage sees the same input both ways, so it never qualifies; nor does a program
        that fails on the eager input, or disagrees on it (that is the op's own MISMATCH)."""
        import jax

        if i == 0 or stage_ins is None:
            return False
        ins = stage_ins[i]
        member = ins[st.slot]
        extras = tuple(a for j, a in enumerate(ins) if j != st.slot)
        kn = _knob_array(st, dtype)
        f = self._stage_fn(st, spec)
        key = self._stage_key(st, member, extras, dtype)
        try:
            yj, _, _ = self._call(self._jprog, key, lambda: _jit(f), member, extras, kn)
            yj = jax.block_until_ready(yj)
        except Exception:  # noqa: BLE001 - the caller reports the difference it saw
            return False
        if _differ(yj, eager_outs[i], dtype) is not None:
            return False
        out.conditioned = (st.op, i, d)
        self.stats["conditioned"] = self.stats.get("conditioned", 0) + 1
        return True

    def _stage_error(self, e: BaseException, i: int, op: str, mode: str, out: Outcome) -> None:
        r = classify_exception(e, op, i, mode)
        if isinstance(r, _Fail):
            raise r from None
        out.refused_traced = (op, r[1])

    def _grad_staged(self, chain, specs, stage_ins, eager_outs, dtype) -> None:
        """``grad`` of the scalar of :func:`_output_weights` through the chain, as the composition of
        each stage's cached ``jit(vjp(stage))`` at the eager inputs (the chain rule, stage by
        stage); a NaN cotangent from a finite one blames that stage."""
        import jax
        import jax.numpy as jnp
        import numpy as np

        terms = _output_weights(eager_outs[-1], np)   # on the host: nothing compiles
        total = sum(float(np.sum(np.where(ok, leaf, 0.0) * w)) for leaf, w, ok in terms)
        ct = _device([np.where(ok, w, 0).astype(w.dtype) for _, w, ok in terms])
        if not np.isfinite(total):
            return  # forward not finite: NONFINITE's business
        for i in range(len(chain.stages) - 1, -1, -1):
            st, spec = chain.stages[i], specs[i]
            ins = stage_ins[i]
            xin = ins[st.slot]
            extras = tuple(a for j, a in enumerate(ins) if j != st.slot)
            kn = _knob_array(st, dtype)
            leaves, tdef = jax.tree_util.tree_flatten(xin)
            fl = tuple(k for k, v in enumerate(leaves) if jnp.issubdtype(jnp.result_type(v), jnp.inexact))
            xf = [leaves[k] for k in fl]
            xo = [v for k, v in enumerate(leaves) if k not in fl]
            key = ("grad",) + self._stage_key(st, xin, extras, dtype)
            self.stats["grad_calls"] += 1
            g = self._stage_fn(st, spec)
            try:
                (gx, gk), hit, compiled = self._call(self._gprog, key, lambda g=g, t=tdef, k=fl: _jit(
                    _vjp_program(g, t, k)), xf, xo, extras, kn, ct)
            except Exception as e:  # noqa: BLE001 - classified
                self._stage_error(e, i, st.op, "grad", Outcome("ok"))
                return
            self.stats["grad_hits"] += hit
            if hit and compiled:
                raise _Fail("RECOMPILE", i, st.op, "grad", "a cached stage program called again with the same shapes "
                            "compiled again")
            if any(not bool(np.all(np.isfinite(np.asarray(g)))) for g in (*gx, gk)):
                if not (_all_finite(xin) and _all_finite(eager_outs[i])):
                    # the stage's own forward is not finite (a documented -inf/inf/NaN passed the
                    # forward checks): its gradient is undefined, not a GRADNAN ("finite forward")
                    return
                raise _Fail("GRADNAN", i, st.op, "grad", "NaN gradient, finite forward")
            ct = list(gx)

    # -- the traced ways, the chain compiled whole ---------------------------------
    def _whole(self, chain, f, x, x2, knobs, eager_outs, dtype, out) -> None:
        """``jit(vmap(chain))`` over ``[x, x2]``: member 0 must equal the eager result; plain
        ``jit(chain)`` is compiled only to say which way broke."""
        import jax
        import jax.numpy as jnp

        xb = None
        if self.do_vmap:
            try:
                xb = jax.tree_util.tree_map(lambda a, b: jnp.stack([a, b]), x, x2)
            except ValueError:
                xb = None  # the two variants differ in static fields: no batch
        if xb is None:
            self._jit_way(chain, f, x, x2, knobs, eager_outs, dtype, out)
            return
        vf = _jit_whole(jax.vmap(f, in_axes=(0, None)))
        try:
            yb = jax.block_until_ready(vf(xb, knobs))
        except Exception as e:  # noqa: BLE001 - classified
            if self._jit_way(chain, f, x, x2, knobs, eager_outs, dtype, out):
                self._traced_error(e, chain, "vmap", out)
            return
        for i, ye in enumerate(eager_outs):
            got = jax.tree_util.tree_map(lambda v: v[0], yb[i])
            nans: list = []
            d = _differ(got, ye, dtype, nans)
            if nans and not d:
                self._check_finite(i, chain.stages[i].op, got, "vmap", chain.stages[i].params)
                break  # failed closed under the trace: later stages saw other data
            if d:
                if self._jit_way(chain, f, x, x2, knobs, eager_outs, dtype, out):
                    raise _Fail("MISMATCH", i, chain.stages[i].op, "vmap", "vmap vs eager: " + d.split(" (")[0], d)
                return
        xs = jax.tree_util.tree_map(lambda v: v[::-1], xb)
        c0 = _COMPILES["n"]
        yb2 = jax.block_until_ready(vf(xs, knobs))
        if _COMPILES["n"] != c0:
            raise _Fail("RECOMPILE", None, None, "jit",
                        "second call of the compiled chain with the same shapes compiled again")
        for i in range(len(eager_outs)):
            d = _differ(jax.tree_util.tree_map(lambda v: v[1], yb2[i]),
                        jax.tree_util.tree_map(lambda v: v[0], yb[i]), dtype)
            if d:
                raise _Fail("MISMATCH", i, chain.stages[i].op, "vmap",
                            "batch member depends on its position: " + d.split(" (")[0], d)

    def _jit_way(self, chain, f, x, x2, knobs, eager_outs, dtype, out) -> bool:
        """Plain ``jit(chain)``: raises a ``_Fail`` for a broken jit way; True when jit is sound."""
        import jax

        jf = _jit_whole(f)
        try:
            ys = jax.block_until_ready(jf(x, knobs))
        except Exception as e:  # noqa: BLE001 - classified
            self._traced_error(e, chain, "jit", out)
            return False
        for i, (ye, yj) in enumerate(zip(eager_outs, ys)):
            nans: list = []
            d = _differ(yj, ye, dtype, nans)
            if nans and not d:
                self._check_finite(i, chain.stages[i].op, yj, "jit", chain.stages[i].params)
                break  # failed closed under the trace: later stages saw other data
            if d:
                st = chain.stages[i]
                if self._same_input_agrees(i, st, self.specs[st.op], self._stage_ins, eager_outs, dtype, d, out):
                    return False   # conditioning: the chain is not compared further
                raise _Fail("MISMATCH", i, st.op, "jit", "jit vs eager: " + d.split(" (")[0], d)
        c0 = _COMPILES["n"]
        jax.block_until_ready(jf(x2, knobs))
        if _COMPILES["n"] != c0:
            raise _Fail("RECOMPILE", None, None, "jit", "second call of the compiled chain with the same shapes compiled again")
        return True

    def _traced_error(self, e: BaseException, chain: Chain, mode: str, out: Outcome) -> None:
        # which stage? the message names ops; blame the first op named, else the chain (an op's
        # run-time error under jit names it on the EquinoxRuntimeError line, after the traceback)
        m = re.search(r"EquinoxRuntimeError: ([^\n]+)", str(e))
        head = m.group(1) if m else str(e)[:400]
        op = next((s.op for s in chain.stages if s.op in head), None)
        stage = next((i for i, s in enumerate(chain.stages) if s.op == op), None)
        r = classify_exception(e, op or "\0", stage, mode)
        if isinstance(r, _Fail):
            raise r from None
        out.refused_traced = (op, r[1])

    def _grad(self, chain: Chain, f, x, knobs, y_last) -> None:
        r = self._grad_nan(chain, f, x, knobs)
        if r is None or not r:
            return
        # blame the shortest prefix whose gradient is NaN with a finite forward
        n = len(chain.stages)
        for k in range(1, n):
            sub = chain.replace(stages=chain.stages[:k])
            if self._grad_nan(sub, self._traced(sub, chain.inp["dtype"]), x, knobs[:k]):
                n = k
                break
        if y_last is not None:   # (stage inputs, eager outputs): as the stage-by-stage grad, a stage
            ins, outs = y_last    # whose own forward is not finite has no "finite forward"
            if not (_all_finite(ins[n - 1][chain.stages[n - 1].slot]) and _all_finite(outs[n - 1])):
                return
        raise _Fail("GRADNAN", n - 1, chain.stages[n - 1].op, "grad", "NaN gradient, finite forward")

    def _grad_nan(self, chain: Chain, f, x, knobs) -> bool | None:
        """True: finite forward scalar, NaN gradient; None: the gradient could not be taken."""
        import jax
        import jax.numpy as jnp
        import numpy as np

        leaves, tdef = jax.tree_util.tree_flatten(x)
        fl = [i for i, v in enumerate(leaves) if jnp.issubdtype(jnp.result_type(v), jnp.floating)]

        def loss(xf, kn):
            new = list(leaves)
            for i, v in zip(fl, xf):
                new[i] = v
            y = f(jax.tree_util.tree_unflatten(tdef, new), kn)[-1]
            return sum((jnp.sum(jnp.where(ok, leaf, 0.0) * w) for leaf, w, ok in _output_weights(y)), 0.0)

        xf = [leaves[i] for i in fl]
        try:
            val, (gx, gk) = _jit_whole(jax.value_and_grad(loss, argnums=(0, 1)))(xf, knobs)
        except Exception as e:  # noqa: BLE001 - classified
            self._traced_error(e, chain, "grad", Outcome("ok"))
            return None
        if not np.isfinite(float(val)):
            return False  # forward not finite: NONFINITE's business (flagged, or caught eagerly)
        return any(not bool(np.all(np.isfinite(np.asarray(g)))) for g in (*gx, gk))


# per-stage programs compile at XLA's backend (LLVM) optimisation level 0: about half the compile
# time on a 16 x 16 input, where running costs milliseconds either way. The HLO passes (fusion,
# algebraic simplification) run as at the default level; LLVM at level 0 keeps IEEE semantics
# (no fast-math), so a result may differ only by what differs at every level.
STAGE_COMPILER_OPTIONS = {"xla_backend_optimization_level": 0}


# the chain compiled whole compiles at XLA's default backend level (3), explicitly: worker processes
# set level 0 for every other program (fsjax.fuzz._report.WORKER_XLA_FLAGS), and these chains are
# the fuzzer's test of the code XLA optimises fully
WHOLE_COMPILER_OPTIONS = {"xla_backend_optimization_level": 3}


def _jit(f):
    import jax

    return jax.jit(f, compiler_options=STAGE_COMPILER_OPTIONS)


def _jit_whole(f):
    import jax

    return jax.jit(f, compiler_options=WHOLE_COMPILER_OPTIONS)


def _output_weights(y, xp=None) -> list:
    """The random-weighted scalar that ``grad`` differentiates, as ``(leaf, w, ok)`` per inexact
    output leaf: ``w`` standard-normal weights (numpy's generator seeded ``[7, j]``, ``j`` the
    leaf's index among all leaves; a host constant, so nothing compiles for it), ``ok`` the
    elements that count (finite, and marked by the output's ``valid`` mask where it applies).
    The scalar is ``sum(where(ok, leaf, 0) * w)``, the cotangent ``where(ok, w, 0)``. One
    definition for the stage-by-stage grad (``xp=numpy``: computed on the host) and the chain
    compiled whole (``jax.numpy``, traced)."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    xp = jnp if xp is None else xp
    valid = getattr(y, "valid", None)
    out = []
    for j, leaf in enumerate(jax.tree_util.tree_leaves(y)):
        if not jnp.issubdtype(jnp.result_type(leaf), jnp.inexact):
            continue
        dt = jnp.result_type(leaf)
        w = np.random.default_rng([7, j]).standard_normal(np.shape(leaf)).astype(dt)
        if xp is np:
            leaf = np.asarray(leaf)
        ok = xp.isfinite(leaf)
        if valid is not None and valid.dtype == jnp.bool_ and valid.ndim and leaf.shape[: valid.ndim] == valid.shape:
            ok = ok & xp.asarray(valid).reshape(valid.shape + (1,) * (leaf.ndim - valid.ndim))
        out.append((leaf, w, ok))
    return out


def _host_index(tree, index):
    """``v[index]`` for every leaf, on the host (numpy): the fuzzer's own slicing compiled a program
    per shape as eager dispatch. A weak-typed leaf keeps jax's indexing, so the stage programs'
    keys and input types stay those of the jax arrays. A result fed to a compiled program goes
    through :func:`_device` first."""
    import jax
    import numpy as np

    return jax.tree_util.tree_map(lambda v: v[index] if getattr(v, "weak_type", False) else np.asarray(v)[index],
                                  tree)


def _device(tree):
    """Host (numpy) leaves as device arrays (``jax.device_put``: nothing compiles). A compiled
    program is always called with device arrays: jit's fast path keys its cache on the argument's
    type too, so a program first called with a numpy array and later with a device array (a
    stage's output) leaves the fast path, and once JAX's bounded trace caches (2048-4096 entries,
    the eager primitives included) have dropped its entry, it traces and compiles again -- a false
    RECOMPILE (watershed_split, the full run of this branch)."""
    import jax
    import numpy as np

    return jax.tree_util.tree_map(lambda v: jax.device_put(v) if isinstance(v, (np.ndarray, np.generic)) else v,
                                  tree)


def _host_stack(x, x2):
    """The batch ``[x, x2]`` of two pool inputs, stacked on the host (see :func:`_host_index`), as
    device arrays (:func:`_device`)."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    def stack(a, b):
        if getattr(a, "weak_type", False) or getattr(b, "weak_type", False):
            return jnp.stack([a, b])
        return np.stack([np.asarray(a), np.asarray(b)])

    return _device(jax.tree_util.tree_map(stack, x, x2))


def _knob_array(st, dtype: str):
    """A stage's two knob values (``None`` -> 0.5, never read) as the stage programs' argument (a
    device array, :func:`_device`)."""
    import numpy as np

    return _device(np.asarray([0.5 if st.a is None else st.a, 0.5 if st.b is None else st.b], dtype=dtype))


def _all_finite(tree) -> bool:
    """Every inexact leaf of ``tree`` finite (where its ``valid`` mask applies)."""
    import numpy as np

    for a, m, fl, _ in _leaves_with_mask(tree):
        if fl:
            ok = np.isfinite(a)
            if m is not None:
                ok |= ~m
            if not ok.all():
                return False
    return True


def _avals(tree) -> tuple:
    """Tree structure (static fields included) and every leaf's shape, dtype and weak type."""
    import jax
    import jax.numpy as jnp

    leaves, tdef = jax.tree_util.tree_flatten(tree)
    return (tdef, tuple((jnp.shape(v), str(jnp.result_type(v)), bool(getattr(v, "weak_type", False)))
                        for v in leaves))


def _vjp_program(f, tdef, fl: tuple):
    """``(xf, xo, extras, kn, ct) -> (d xf, d kn)``: the pull-back of one stage ``f(x, extras, kn)``
    through its inexact input leaves ``xf`` (``xo``: the others) and knobs, for the cotangent
    ``ct`` of its inexact output leaves."""
    import jax
    import jax.numpy as jnp

    def prog(xf, xo, extras, kn, ct):
        def fwd(xf_, kn_):
            it_f, it_o = iter(xf_), iter(xo)
            leaves = [next(it_f) if k in fl else next(it_o) for k in range(len(xf_) + len(xo))]
            y = f(jax.tree_util.tree_unflatten(tdef, leaves), extras, kn_)
            return [v for v in jax.tree_util.tree_leaves(y) if jnp.issubdtype(jnp.result_type(v), jnp.inexact)]

        ys, pull = jax.vjp(fwd, list(xf), kn)
        return pull([jnp.asarray(c, dtype=jnp.result_type(p)) for c, p in zip(ct, ys)])

    return prog


# documented -inf outputs: op -> (parameter, value) under which the op writes -inf as "no data"
# (the op's docstring says so); only -inf is explained, NaN or +inf still fail
DOCUMENTED_NEG_INF = {
    "tsdf_fuse": ("fill_holes", False),   # unobserved voxels are -inf with fill_holes=False
    "depth_to_tsdf": ("fill_holes", False),   # "or both -inf, no data (False)" (reported NONFINITE, seed 1)
}
# ops whose Image output documents NaN where the value is undefined (an Image has no flag);
# only NaN is explained, an inf still fails
DOCUMENTED_NAN = frozenset({
    "sobel_dir",   # "NaN where the gradient is zero up to rounding (a flat area); mask it with sobel_amp"
    "absolute_phase",   # "Negative codes (-1: undecidable; any code rounding below 0) give NaN"
})
# ops that document one infinity over the whole output when one class of voxels is empty; a NaN,
# or an infinity beside finite values, still fails
DOCUMENTED_ALL_INF = frozenset({
    "volume_to_sdf",   # "+inf everywhere when there is no foreground voxel, -inf when there is no background voxel"
})
# ops whose Image output documents +-inf where the result overflows the dtype (IEEE overflow of an
# exponential, on input far outside [0, 1]); only infinities are explained, a NaN still fails
DOCUMENTED_OVERFLOW = frozenset({
    "exp_transform",   # "+-inf where (1 + c)^|x| overflows the dtype"
})


def _declared_batch(spec, params) -> tuple:
    """The output batch shape an op declares: ``()``, or ``(max_instances,)`` for an op with a
    static ``max_instances`` parameter (it returns that many instance slots, best first, as
    ``generalised_hough3d`` documents)."""
    if "max_instances" in spec.params:
        n = dict(params).get("max_instances", spec.params["max_instances"])
        if isinstance(n, int):
            return (n,)
    return ()


def _n_found(x) -> int | None:
    """Items a fixed-capacity output holds: valid slots, or a Labels count."""
    import numpy as np

    v = getattr(x, "valid", None)
    if v is not None and np.asarray(v).dtype == np.bool_ and np.ndim(v) >= 1:
        return int(np.sum(np.asarray(v)))
    c = getattr(x, "count", None)
    if c is not None:
        return int(np.asarray(c))
    return None
