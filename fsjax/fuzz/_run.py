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
compared (a batched solve may take a step more or less, with the same answer). A value that is NaN under the trace
where the eager call is finite is not a MISMATCH: a traced way may fail closed where an eager
call sizes its buffers from the data (``render_depth``); the traced output is then checked
as NONFINITE (explained only by a flag or a sort's documented NaN) and later stages, which
saw other data, are not compared.
"""

from __future__ import annotations

import dataclasses
import re
import time
from collections.abc import Sequence
from typing import Any

from ._gen import Chain, build_input, extra_input, float_dtype, knob_values

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

_COMPILES = {"n": 0}
_LISTENING = {"on": False}


def _listen() -> None:
    if _LISTENING["on"]:
        return
    import jax.monitoring

    events = ("/jax/core/compile/backend_compile_duration", "/jax/core/compile/jaxpr_trace_duration")

    def on(event, duration, **kw):
        if event in events:
            _COMPILES["n"] += 1

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
    if "Equinox" in type(e).__name__ or (type(e).__name__ == "XlaRuntimeError" and "equinox" in msg.lower()):
        if names_op:
            return ("refused", _first_line(e))
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


def _nbytes(tree) -> int:
    import jax

    return sum(int(getattr(v, "nbytes", 0)) for v in jax.tree_util.tree_leaves(tree))


def _differ(x, y, dtype: str, nan_only: list | None = None) -> str | None:
    """``None`` when trees agree within the stated tolerance, else a short description.

    Floating values that are NaN in ``x`` (the traced way) where ``y`` (eager) is finite are
    not counted as a difference when ``nan_only`` is a list: their counts are appended to it,
    and the caller checks the traced output as a NONFINITE candidate instead (a traced way
    may fail closed where an eager call could size its buffers from the data).
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
    """Runs chains over the ops ``specs`` (``OpSpec`` list) and classifies the outcome."""

    def __init__(self, specs: Sequence[Any], *, grad: bool = True, vmap: bool = True):
        _listen()
        self.specs = {s.name: s for s in specs}
        self.sorts = {}
        for s in specs:
            for t in (*s.takes, s.gives):
                self.sorts[t.__name__] = t
        self.do_grad = grad
        self.do_vmap = vmap

    # -- pieces -----------------------------------------------------------
    def _inputs(self, chain: Chain, variant: int):
        i = chain.inp
        return build_input(self.sorts[i["sort"]], i["kind"], tuple(i["size"]), i["dtype"], variant)

    def _assemble(self, st, spec, cur, dtype: str) -> tuple:
        args = []
        for j, t in enumerate(spec.takes):
            args.append(cur if j == st.slot else extra_input(t, cur, dtype, 1))
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

    # -- checks on one eager stage output ------------------------------------
    def _check_stage(self, i: int, spec, ins: tuple, out, kp: dict, params: tuple) -> None:
        import numpy as np

        op = spec.name
        if not isinstance(out, spec.gives):
            raise _Fail("CONTRACT", i, op, "eager", f"returned {type(out).__name__}, declared {spec.gives.__name__}")
        try:
            bshape = out.batch_shape
        except Exception:  # noqa: BLE001 - a sort without batch_shape is itself a contract break
            bshape = None
        if bshape != ():
            raise _Fail("CONTRACT", i, op, "eager", f"output batch shape {bshape}, expected ()")
        in_dt = float_dtype(ins[0]) if float_dtype(ins[0]) else None
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
        self._check_finite(i, op, out, "eager")

    def _check_finite(self, i: int, op: str, out, mode: str) -> None:
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
        t = getattr(out, "truncated", None)
        if t is not None and bool(np.any(np.asarray(t))):
            return
        if type(out).__name__ in ("Feature", "Depth") and not infs:
            return  # documented: a NaN Feature is "could not measure", a NaN depth "no return"
        raise _Fail("NONFINITE", i, op, mode, "inf in the output" if infs else "NaN in the output")

    # -- the four ways ----------------------------------------------------------
    def run(self, chain: Chain) -> Outcome:
        t0 = time.perf_counter()
        out = Outcome("ok")
        self._pending = None
        try:
            self._run(chain, out)
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
        return out

    def _run(self, chain: Chain, out: Outcome) -> None:
        import jax
        import jax.numpy as jnp
        import numpy as np

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
        n_ok = len(chain.stages)
        for i, (st, spec) in enumerate(zip(chain.stages, specs)):
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
            executed.append(spec.name)
            eager_outs.append(y)
            cur = y
        out.executed = tuple(executed)
        if n_ok == 0:
            return
        chain = chain.replace(stages=chain.stages[:n_ok])
        specs = specs[:n_ok]
        # eager again on the same input: op-by-op dispatch is cached, nothing may compile
        cur = x
        self._pending = None
        for i, (st, spec) in enumerate(zip(chain.stages, specs)):
            ins = self._assemble(st, spec, cur, dtype)
            kp = spec.knob_params(st.a, st.b, strict=True)
            c0 = _COMPILES["n"]
            cur = spec.fn(*ins, **kp, **dict(st.params))
            jax.block_until_ready(cur)
            if _COMPILES["n"] != c0 and self._pending is None:
                # reported only when nothing else fails: the traced ways still run
                self._pending = _Fail("RECOMPILE", i, spec.name, "eager",
                                "a second eager call with the same input compiled again")
        out.times["eager"] = time.perf_counter() - t_start
        x2 = self._inputs(chain, 1)
        knobs = jnp.asarray(knob_values(chain), dtype=dtype)
        f = self._traced(chain, dtype)
        t_start = time.perf_counter()
        xb = None
        if self.do_vmap:
            try:
                xb = jax.tree_util.tree_map(lambda a, b: jnp.stack([a, b]), x, x2)
            except ValueError:
                xb = None  # the two variants differ in static fields: no batch
        if xb is None:
            self._jit_way(chain, f, x, x2, knobs, eager_outs, dtype, out)
        else:
            # one compiled program serves both traced ways: jit(vmap(chain)) over [x, x2]; member 0
            # must equal the eager result. Plain jit(chain) is compiled only to say which way broke.
            vf = jax.jit(jax.vmap(f, in_axes=(0, None)))
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
                    self._check_finite(i, chain.stages[i].op, got, "vmap")
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
        out.times["traced"] = time.perf_counter() - t_start
        t_start = time.perf_counter()
        if self.do_grad and all(s.differentiable for s in specs):
            self._grad(chain, f, x, knobs, None)
            out.times["grad"] = time.perf_counter() - t_start

    def _jit_way(self, chain, f, x, x2, knobs, eager_outs, dtype, out) -> bool:
        """Plain ``jit(chain)``: raises a ``_Fail`` for a broken jit way; True when jit is sound."""
        import jax

        jf = jax.jit(f)
        try:
            ys = jax.block_until_ready(jf(x, knobs))
        except Exception as e:  # noqa: BLE001 - classified
            self._traced_error(e, chain, "jit", out)
            return False
        for i, (ye, yj) in enumerate(zip(eager_outs, ys)):
            nans: list = []
            d = _differ(yj, ye, dtype, nans)
            if nans and not d:
                self._check_finite(i, chain.stages[i].op, yj, "jit")
                break  # failed closed under the trace: later stages saw other data
            if d:
                raise _Fail("MISMATCH", i, chain.stages[i].op, "jit", "jit vs eager: " + d.split(" (")[0], d)
        c0 = _COMPILES["n"]
        jax.block_until_ready(jf(x2, knobs))
        if _COMPILES["n"] != c0:
            raise _Fail("RECOMPILE", None, None, "jit", "second call of the compiled chain with the same shapes compiled again")
        return True

    def _traced_error(self, e: BaseException, chain: Chain, mode: str, out: Outcome) -> None:
        # which stage? the message names ops; blame the first op named, else the chain
        op = next((s.op for s in chain.stages if s.op in str(e)[:400]), None)
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
        raise _Fail("GRADNAN", n - 1, chain.stages[n - 1].op, "grad", "NaN gradient, finite forward")

    def _grad_nan(self, chain: Chain, f, x, knobs) -> bool | None:
        """True: finite forward scalar, NaN gradient; None: the gradient could not be taken."""
        import jax
        import jax.numpy as jnp
        import numpy as np

        leaves, tdef = jax.tree_util.tree_flatten(x)
        fl = [i for i, v in enumerate(leaves) if jnp.issubdtype(jnp.result_type(v), jnp.floating)]
        key = jax.random.PRNGKey(7)

        def loss(xf, kn):
            new = list(leaves)
            for i, v in zip(fl, xf):
                new[i] = v
            y = f(jax.tree_util.tree_unflatten(tdef, new), kn)[-1]
            valid = getattr(y, "valid", None)
            total = 0.0
            for j, leaf in enumerate(jax.tree_util.tree_leaves(y)):
                if not jnp.issubdtype(jnp.result_type(leaf), jnp.inexact):
                    continue
                w = jax.random.normal(jax.random.fold_in(key, j), jnp.shape(leaf), dtype=jnp.result_type(leaf))
                ok = jnp.isfinite(leaf)
                if valid is not None and valid.dtype == jnp.bool_ and valid.ndim and \
                        leaf.shape[: valid.ndim] == valid.shape:
                    ok = ok & valid.reshape(valid.shape + (1,) * (leaf.ndim - valid.ndim))
                total = total + jnp.sum(jnp.where(ok, leaf, 0.0) * w)
            return total

        xf = [leaves[i] for i in fl]
        try:
            val, (gx, gk) = jax.jit(jax.value_and_grad(loss, argnums=(0, 1)))(xf, knobs)
        except Exception as e:  # noqa: BLE001 - classified
            self._traced_error(e, chain, "grad", Outcome("ok"))
            return None
        if not np.isfinite(float(val)):
            return False  # forward not finite: NONFINITE's business (flagged, or caught eagerly)
        return any(not bool(np.all(np.isfinite(np.asarray(g)))) for g in (*gx, gk))


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
