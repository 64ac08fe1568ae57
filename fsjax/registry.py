"""Op specs, the ``@register`` decorator, knobs, lookup and search.

One decorator registers an op; the uniform call (:func:`fsjax.apply`), the
pipelines, the evolutionary search space, the generated docs and the contract
tests all read the registry and nothing else.

An op is a plain function::

    @register(family="filters", takes=Image, gives=Image,
              knobs={"sigma": LogKnob(0.3, 8.0)}, differentiable=True,
              refs=["Lindeberg 1994"])
    def gaussian(img: Image, /, *, sigma: float = 1.0) -> Image: ...

Rules enforced at registration (so every op is usable by every consumer):

* inputs are positional (one per entry of ``takes``); every other parameter is
  keyword-only *with a default*;
* at most two knobs, each naming a keyword parameter; the first is knob ``a``,
  the second knob ``b``;
* the docstring has a one-line summary (it becomes the op's ``summary``).

Knobs map a unit value ``u`` in ``[0, 1]`` onto the parameter's physical range.
The mapping is traced arithmetic, so a knob stays a traced scalar under
``jit``/``vmap``/``grad``; an op whose knob fixes an array size uses a static
maximum support and masks.
"""

from __future__ import annotations

import contextlib
import dataclasses
import difflib
import functools
import importlib
import inspect
import math
from collections.abc import Callable, Sequence
from typing import Any

import jax.numpy as jnp
import numpy as np

from ._checks import traced_checks
from .types import Sort, is_concrete

__all__ = [
    "Knob",
    "LinKnob",
    "LogKnob",
    "IntKnob",
    "OpSpec",
    "register",
    "get_op",
    "list_ops",
    "families",
    "UnknownOpError",
    "compiled_calls",
    "add_op_provider",
]


# ---------------------------------------------------------------------------
# Knobs
# ---------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Knob:
    """Maps a unit value in ``[0, 1]`` onto a parameter range ``[lo, hi]``."""

    lo: float
    hi: float
    unit: str = ""

    def __post_init__(self):
        if not (math.isfinite(self.lo) and math.isfinite(self.hi)) or not self.lo < self.hi:
            raise ValueError(f"{type(self).__name__}: need finite lo < hi, got lo={self.lo}, hi={self.hi}")

    def to_param(self, u):  # pragma: no cover - abstract
        raise NotImplementedError

    def to_unit(self, v: float) -> float:  # pragma: no cover - abstract
        raise NotImplementedError

    def describe(self) -> str:
        unit = f" {self.unit}" if self.unit else ""
        return f"{type(self).__name__}: [{self.lo:g}, {self.hi:g}]{unit}"


@dataclasses.dataclass(frozen=True)
class LinKnob(Knob):
    """Linear map: ``p = lo + u (hi - lo)``."""

    def to_param(self, u):
        return self.lo + u * (self.hi - self.lo)

    def to_unit(self, v: float) -> float:
        return (v - self.lo) / (self.hi - self.lo)


@dataclasses.dataclass(frozen=True)
class LogKnob(Knob):
    """Geometric map: ``p = lo (hi / lo) ** u`` (``lo > 0``); for scales such as sigma."""

    def __post_init__(self):
        super().__post_init__()
        if not self.lo > 0:
            raise ValueError(f"LogKnob: lo must be > 0, got {self.lo}")

    def to_param(self, u):
        return self.lo * jnp.exp(u * math.log(self.hi / self.lo))

    def to_unit(self, v: float) -> float:
        return math.log(v / self.lo) / math.log(self.hi / self.lo)


@dataclasses.dataclass(frozen=True)
class IntKnob(Knob):
    """Integer-valued parameter: ``p = round(lo + u (hi - lo))``, returned as a traced float.

    The op must accept a traced value (static maximum ``hi`` and masks), and is
    piecewise constant in ``u`` (not differentiable through this knob).
    """

    def to_param(self, u):
        return jnp.round(self.lo + u * (self.hi - self.lo))

    def to_unit(self, v: float) -> float:
        return (v - self.lo) / (self.hi - self.lo)


# ---------------------------------------------------------------------------
# Specs and the registry
# ---------------------------------------------------------------------------


class UnknownOpError(KeyError, ValueError):
    """Raised for an op name that is not registered."""

    def __str__(self) -> str:  # KeyError quotes its message; keep it readable
        return str(self.args[0]) if self.args else ""


@dataclasses.dataclass(frozen=True)
class OpSpec:
    """Everything the library knows about one op."""

    name: str
    family: str
    takes: tuple[type, ...]
    gives: type
    knobs: dict[str, Knob]
    differentiable: bool
    refs: tuple[str, ...]
    summary: str
    fn: Callable[..., Any]
    raw: Callable[..., Any]
    input_names: tuple[str, ...]
    params: dict[str, Any]  # keyword parameter -> default
    module: str
    infinite_ok: bool = False  # inputs may hold +-inf (not NaN): signed distances, "empty set"

    @property
    def n_inputs(self) -> int:
        return len(self.takes)

    @property
    def linear(self) -> bool:
        """True when the op takes one input and can be a stage of a linear pipeline."""
        return len(self.takes) == 1

    @property
    def knob_names(self) -> tuple[str, ...]:
        return tuple(self.knobs)

    @property
    def doc(self) -> str:
        return inspect.getdoc(self.raw) or ""

    def signature_str(self) -> str:
        ins = ", ".join(t.__name__ for t in self.takes)
        return f"({ins}) -> {self.gives.__name__}"

    def knob_params(self, a=None, b=None, *, strict: bool = True, caller: str | None = None) -> dict[str, Any]:
        """Map knob values ``a``, ``b`` in ``[0, 1]`` to keyword parameters.

        ``None`` leaves a parameter at its default. With ``strict``, a knob given
        to an op that has no such knob is an error; otherwise it is ignored.
        Concrete knob values outside ``[0, 1]`` raise ``ValueError``.
        """
        who = caller or f"apply({self.name!r})"
        out: dict[str, Any] = {}
        names = list(self.knobs)
        for i, (label, u) in enumerate((("a", a), ("b", b))):
            if u is None:
                continue
            if i >= len(names):
                if strict:
                    raise ValueError(
                        f"{who}: op {self.name!r} has {len(names)} knob(s) "
                        f"({', '.join(names) or 'none'}); knob {label!r} is not defined"
                    )
                continue
            pname = names[i]
            if is_concrete(u):
                try:
                    uval = np.asarray(u, dtype=float)
                except (TypeError, ValueError):
                    raise TypeError(f"{who}: knob {label!r} ({pname}) must be a number in [0, 1], "
                                    f"got {type(u).__name__} {u!r}") from None
                if isinstance(u, (str, bytes)):
                    raise TypeError(f"{who}: knob {label!r} ({pname}) must be a number in [0, 1], got str {u!r}")
                if uval.size and (not np.all(np.isfinite(uval)) or bool(np.any((uval < 0) | (uval > 1)))):
                    raise ValueError(
                        f"{who}: knob {label!r} ({pname}) must be in [0, 1], got {_fmt(u)}"
                    )
                out[pname] = self.knobs[pname].to_param(u)
            else:
                # a traced knob cannot be refused here: map its value clipped into [0, 1] (NaN -> 0)
                # so the op does bounded work; callers that promise fail-closed results
                # (apply, pipelines) poison the output with knob_out_of_range()
                uc = jnp.clip(jnp.nan_to_num(u, nan=0.0), 0.0, 1.0)
                out[pname] = self.knobs[pname].to_param(uc)
        return out

    def knob_out_of_range(self, a=None, b=None):
        """Traced bool: a *traced* knob among ``a``, ``b`` that is outside ``[0, 1]`` or NaN.

        ``None`` when no knob is traced (concrete knobs are refused eagerly by
        :meth:`knob_params`). Knobs the op does not have are ignored.
        """
        bad = None
        for i, u in enumerate((a, b)):
            if u is None or is_concrete(u) or i >= len(self.knobs):
                continue
            b_i = ~((u >= 0) & (u <= 1))
            bad = b_i if bad is None else bad | b_i
        return bad


_FLAG_FIELDS = ("valid", "converged", "found", "vertex_valid", "face_valid")


def poison(out: Any, bad: Any, *, who: str) -> Any:
    """Fail closed on a traced condition ``bad`` (a traced bool, or ``None`` for nothing to do).

    Where ``bad`` holds, every floating leaf of the sort ``out`` becomes NaN and its
    validity flags (``valid``, ``converged``, ``found``, mesh ``vertex_valid`` /
    ``face_valid``) become False, so the result cannot pass for a measurement; a record's
    ``reason`` that said ``ok`` becomes ``invalid_input``. A sort with
    no floating leaf (``Region``, ``Labels``) cannot carry NaN: there the call raises at run
    time through ``equinox.error_if`` (under ``vmap`` when any member is bad).
    """
    if bad is None:
        return out
    import equinox as eqx
    import jax

    leaves = jax.tree_util.tree_leaves(out)
    if not any(hasattr(v, "dtype") and jnp.issubdtype(v.dtype, jnp.inexact) for v in leaves):
        first = next(i for i, v in enumerate(leaves) if hasattr(v, "dtype"))
        leaves[first] = eqx.error_if(leaves[first], bad, f"{who}: a traced knob or parameter is out of range "
                                     "and this sort cannot carry NaN")
        return jax.tree_util.tree_unflatten(jax.tree_util.tree_structure(out), leaves)

    def nan(v):
        if hasattr(v, "dtype") and jnp.issubdtype(v.dtype, jnp.inexact):
            return jnp.where(bad, jnp.nan, v)
        return v

    out = jax.tree_util.tree_map(nan, out)
    for f in _FLAG_FIELDS:
        v = getattr(out, f, None)
        if v is not None and hasattr(v, "dtype") and v.dtype == jnp.bool_:
            out = eqx.tree_at(lambda o, f=f: getattr(o, f), out, jnp.where(bad, False, v))
    r = getattr(out, "reason", None)
    if r is not None and hasattr(r, "dtype") and jnp.issubdtype(r.dtype, jnp.integer):
        # a record that says why it failed: a result that was ok is now invalid input (the
        # caller's value or a truncated input); an earlier, more specific reason is kept
        from .types.results import reason_code

        out = eqx.tree_at(lambda o: o.reason, out,
                          jnp.where(bad & (r == reason_code("ok")), reason_code("invalid_input"), r).astype(r.dtype))
    return out


def truncation_poison(spec: OpSpec, args: tuple, out: Any) -> Any:
    """Fail closed on capacity overflow: an op that reduces an input whose fixed capacity
    overflowed (``truncated``: a Contour, Labels or Points missing data) to a number
    (``Feature``, ``Fit``) gets a NaN result (``Fit``: ``converged`` False), because a length,
    area or fit of the points that fitted would be a plausible wrong number. Ops whose output
    carries ``truncated`` itself pass the flag on instead."""
    from .types import Feature, Fit

    if spec.gives not in (Feature, Fit):
        return out
    bad = None
    for a in args:
        t = getattr(a, "truncated", None)
        if t is None or (is_concrete(t) and not bool(np.any(np.asarray(t)))):
            continue
        b = jnp.any(jnp.asarray(t))
        bad = b if bad is None else bad | b
    return poison(out, bad, who=spec.name)


_GROWTH = 4  # capacity factor per re-run
# result capacities an eager call may size from the input, with the op's own static upper bound
_GROWABLE = {"capacity": None, "max_neighbors": 256}


def _capacity_limit(args: tuple) -> int:
    """The most any capacity can usefully be for these inputs: 4 x the elements of the largest
    array among them (points of a contour <= 4 per pixel edge crossing, labels and instances
    <= pixels, clusters <= points)."""
    import jax

    n = max((int(np.size(v)) for v in jax.tree_util.tree_leaves(args) if hasattr(v, "shape")), default=0)
    return 4 * max(n, 1)


def _grow_when_eager(spec: OpSpec, args: tuple, kwargs: dict, out: Any) -> Any:
    """An eager call that left ``capacity`` (and ``max_neighbors``) at its default and overflowed
    it is re-run with a larger capacity until nothing is lost (issue 20 item 4: a default must give a correct
    result on the library's own data, or size itself from the input when eager). A capacity
    the caller passed is kept (the result says ``truncated``), and under ``jit``/``vmap`` the
    buffer is static: ``truncated`` is reported and numbers reduced from it are NaN."""
    grow = {k: int(spec.params[k]) for k in _GROWABLE
            if k in spec.params and k not in kwargs and isinstance(spec.params[k], int)}
    if not grow:
        return out
    t = getattr(out, "truncated", None)
    if t is None or not is_concrete(t) or not bool(np.any(np.asarray(t))) or _any_tracer((args, kwargs)):
        return out
    if any(bool(np.any(np.asarray(getattr(a, "truncated", False)))) for a in args):
        return out  # the loss is the input's (its flag is passed on): a larger buffer cannot help
    limit = _capacity_limit(args)
    lim = {k: min(limit, _GROWABLE[k] or limit) for k in grow}
    while bool(np.any(np.asarray(out.truncated))) and any(v < lim[k] for k, v in grow.items()):
        grow = {k: max(v, min(v * _GROWTH, lim[k])) for k, v in grow.items()}
        out = _call(spec.name, spec.raw, args, {**kwargs, **grow})
    return out


def _fmt(u) -> str:
    try:
        return f"{float(u):g}"
    except (TypeError, ValueError):
        return repr(u)


_REGISTRY: dict[str, OpSpec] = {}


def _summary_of(fn: Callable) -> str:
    doc = inspect.getdoc(fn) or ""
    first = doc.strip().split("\n\n")[0].replace("\n", " ").strip()
    return first


def register(
    *,
    family: str,
    takes: type | tuple[type, ...],
    gives: type,
    knobs: dict[str, Knob] | None = None,
    differentiable: bool = False,
    refs: Sequence[str] = (),
    name: str | None = None,
    infinite_ok: bool = False,
) -> Callable[[Callable], Callable]:
    """Register a function as an fsjax op.

    Args:
      family: op family (e.g. ``"filters"``); one module per family.
      takes: input sort, or a tuple of sorts for multi-input ops (those are
        callable and documented, but linear pipelines do not offer them).
      gives: output sort.
      knobs: up to two ``{param: Knob}`` entries; order defines knobs ``a``, ``b``.
      differentiable: the op is smooth in its knob-mapped parameters and inputs;
        the contract suite checks ``jax.grad`` against finite differences.
      refs: references (papers, textbooks) the implementation follows.
      name: registry name; defaults to the function name.
      infinite_ok: the op gives a defined result for ``+-inf`` in its inputs' float fields
        (e.g. a signed distance of ``+inf``, the empty set); NaN is still refused.

    Returns the op wrapped with eager input validation (sort, NaN), otherwise
    identical to the function.
    """
    takes_t = takes if isinstance(takes, tuple) else (takes,)
    knobs = dict(knobs or {})

    def deco(fn: Callable) -> Callable:
        opname = name or fn.__name__
        where = f"register({opname!r})"
        if opname in _REGISTRY:
            raise ValueError(f"{where}: an op named {opname!r} is already registered "
                             f"(in {_REGISTRY[opname].module})")
        for t in (*takes_t, gives):
            if not (isinstance(t, type) and issubclass(t, Sort)):
                raise TypeError(f"{where}: takes/gives must be sort classes, got {t!r}")
        if len(knobs) > 2:
            raise ValueError(f"{where}: at most two knobs, got {list(knobs)}")
        for k in knobs.values():
            if not isinstance(k, Knob):
                raise TypeError(f"{where}: knob specs must be Knob instances, got {k!r}")
        summary = _summary_of(fn)
        if not summary:
            raise ValueError(f"{where}: the op needs a docstring with a one-line summary")
        sig = inspect.signature(fn)
        ps = list(sig.parameters.values())
        if len(ps) < len(takes_t):
            raise TypeError(f"{where}: takes {len(takes_t)} input(s) but the function has {len(ps)} parameters")
        inputs, rest = ps[: len(takes_t)], ps[len(takes_t):]
        for p in inputs:
            if p.kind not in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD):
                raise TypeError(f"{where}: input parameter {p.name!r} must be positional")
        params: dict[str, Any] = {}
        for p in rest:
            if p.kind != p.KEYWORD_ONLY:
                raise TypeError(f"{where}: parameter {p.name!r} must be keyword-only (put it after `*`)")
            if p.default is p.empty:
                raise TypeError(f"{where}: parameter {p.name!r} needs a default")
            params[p.name] = p.default
        for k in knobs:
            if k not in params:
                raise ValueError(f"{where}: knob {k!r} is not a keyword parameter of {fn.__name__}")
        input_names = tuple(p.name for p in inputs)

        @functools.wraps(fn)
        def wrapper(*args, **kwargs):
            if len(args) != len(takes_t):
                raise TypeError(
                    f"{opname}: takes {len(takes_t)} positional input(s) "
                    f"({', '.join(t.__name__ for t in takes_t)}), got {len(args)}; "
                    f"parameters are keyword-only"
                )
            for arg, sort, pname in zip(args, takes_t, input_names):
                if not isinstance(arg, sort):
                    hint = ""
                    if not isinstance(arg, Sort):
                        hint = f"; wrap an array with fsjax.{sort.__name__}(x)"
                    raise TypeError(
                        f"{opname}: argument {pname!r} must be {sort.__name__}, "
                        f"got {type(arg).__name__}{hint}"
                    )
                bshape = arg.batch_shape
                if bshape:
                    raise ValueError(
                        f"{opname}: argument {pname!r} has batch shape {bshape} in front of one "
                        f"{sort.__name__}; ops take one instance, batch with jax.vmap"
                    )
                arg.check(op=opname, arg=pname, allow_inf=infinite_ok)
            # a traced parameter that an eager call would refuse (check_range & co. in the op)
            # poisons the output instead of giving a plausible number computed from it
            with traced_checks(kwargs.values()) as bad:
                out = _call(opname, fn, args, kwargs)
            if bad:
                out = poison(out, functools.reduce(jnp.logical_or, bad), who=opname)
            out = _grow_when_eager(spec, args, kwargs, out)
            return truncation_poison(spec, args, out)

        spec = OpSpec(
            name=opname,
            family=family,
            takes=takes_t,
            gives=gives,
            knobs=knobs,
            differentiable=bool(differentiable),
            refs=tuple(refs),
            summary=summary,
            fn=wrapper,
            raw=fn,
            input_names=input_names,
            params=params,
            module=fn.__module__,
            infinite_ok=bool(infinite_ok),
        )
        _REGISTRY[opname] = spec
        wrapper.spec = spec  # type: ignore[attr-defined]
        return wrapper

    return deco


# ---------------------------------------------------------------------------
# Compiled eager calls
# ---------------------------------------------------------------------------

# By default an op called outside any transformation runs eagerly, primitive by primitive,
# and every check in its body sees concrete values. Inside ``compiled_calls()`` such a call
# runs as one compiled XLA program instead (cached per op, input shapes and static
# parameters): op-by-op dispatch compiles one small program per primitive, which for a
# one-off call on a small input costs far more than the op's own work. The compiled path
# is taken only when every keyword parameter is a plain hashable Python value (number,
# str, None, bool, or a tuple of those), which becomes a static argument, so the op's
# checks on its parameters run exactly as in an eager call; any array or pytree
# parameter, any traced value, or an op that needs concrete input values (it raises a
# tracer-conversion error when traced) takes the eager call. What is lost: checks in an
# op's body on the *values* of its inputs (beyond the sort and NaN checks every call
# makes first) are skipped, as they are under ``jit``.
_SCALARS = (bool, int, float, complex, str, type(None))
_COMPILED: dict[str, Callable] = {}
_NEEDS_EAGER: set[tuple] = set()
_MODE = {"compiled": False}


@contextlib.contextmanager
def compiled_calls(enabled: bool = True):
    """Context manager: ops called outside ``jit`` run as one compiled program each.

    Within ``with fsjax.compiled_calls():`` a direct op call such as
    ``fsjax.ops.gaussian(img, sigma=2.0)`` is compiled whole (and cached) instead of being
    dispatched primitive by primitive. Results are those of ``jax.jit`` of the op.
    Keyword parameters become static (a new value compiles a new program); calls with
    array-valued parameters or traced values are unchanged. Checks that an op makes on
    the values of its inputs are skipped, as under ``jit``.

    Example:
        >>> img = fsjax.Image(jnp.zeros((8, 8)).at[4, 4].set(1.0))
        >>> with fsjax.compiled_calls():
        ...     y = fsjax.ops.gaussian(img, sigma=1.0)
        >>> bool(jnp.allclose(y.data, fsjax.ops.gaussian(img, sigma=1.0).data))
        True
    """
    old = _MODE["compiled"]
    _MODE["compiled"] = bool(enabled)
    try:
        yield
    finally:
        _MODE["compiled"] = old


def _static_ok(v) -> bool:
    if isinstance(v, _SCALARS):
        return True
    if isinstance(v, tuple):
        return all(_static_ok(x) for x in v)
    return False


def _any_tracer(tree) -> bool:
    import jax

    return any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree_util.tree_leaves(tree))


def _call(opname: str, fn: Callable, args: tuple, kwargs: dict):
    if not _MODE["compiled"] or not all(_static_ok(v) for v in kwargs.values()) or _any_tracer(args):
        return fn(*args, **kwargs)
    import jax

    static = tuple(sorted(kwargs.items()))
    key = (opname, static)
    if key in _NEEDS_EAGER:
        return fn(*args, **kwargs)
    jf = _COMPILED.get(opname)
    if jf is None:

        def run(args, static):
            return fn(*args, **dict(static))

        jf = _COMPILED[opname] = jax.jit(run, static_argnums=1)
    try:
        return jf(args, static)
    except (jax.errors.ConcretizationTypeError, jax.errors.TracerArrayConversionError,
            jax.errors.TracerBoolConversionError, jax.errors.TracerIntegerConversionError):
        # the op inspects concrete input values (data-dependent shapes or checks)
        _NEEDS_EAGER.add(key)
        return fn(*args, **kwargs)


# Modules whose import registers ops. The registry sits below the ops in the layering
# (docs/architecture.md) and names no op module itself: the top-level package, which wires
# the layers, lists the providers (``fsjax.OP_PROVIDERS``), and a plug-in may add its own
# with :func:`add_op_provider`.
_PROVIDERS: list[str] = []
_LOADED: set[str] = set()


def add_op_provider(module: str) -> None:
    """Name a module whose import registers ops; lookups import it on first use.

    ``fsjax`` itself adds ``"fsjax.ops"``; a package of further ops calls this once at
    import time so that :func:`get_op`, :func:`list_ops` and pipelines see its ops.
    """
    if not isinstance(module, str) or not module:
        raise TypeError(f"add_op_provider: argument 'module' must be a module name (str), got {module!r}")
    if module not in _PROVIDERS:
        _PROVIDERS.append(module)


def _ensure_loaded() -> None:
    from . import OP_PROVIDERS  # the package's wiring (a tuple of module names, no import)

    for name in (*OP_PROVIDERS, *_PROVIDERS):
        if name not in _LOADED:
            importlib.import_module(name)
            _LOADED.add(name)


def get_op(name: str) -> OpSpec:
    """The spec of the op called ``name``; raises :class:`UnknownOpError` with suggestions."""
    _ensure_loaded()
    if isinstance(name, OpSpec):
        return name
    if not isinstance(name, str):
        raise TypeError(f"get_op: op name must be a str, got {type(name).__name__}")
    try:
        return _REGISTRY[name]
    except KeyError:
        close = difflib.get_close_matches(name, list(_REGISTRY), n=3)
        hint = f"; did you mean {', '.join(repr(c) for c in close)}?" if close else ""
        raise UnknownOpError(f"unknown op {name!r}{hint} (see fsjax.list_ops())") from None


def list_ops(
    family: str | None = None,
    takes: type | tuple[type, ...] | None = None,
    gives: type | None = None,
    search: str | None = None,
) -> list[OpSpec]:
    """Registered ops, sorted by family then name, optionally filtered.

    Args:
      family: keep ops of this family.
      takes: keep ops whose inputs are exactly this sort (or tuple of sorts).
      gives: keep ops that return this sort.
      search: case-insensitive substring of the name, family or summary.
    """
    _ensure_loaded()
    out = list(_REGISTRY.values())
    if family is not None:
        if family not in families():
            raise ValueError(f"list_ops: unknown family {family!r}; known: {', '.join(families())}")
        out = [s for s in out if s.family == family]
    if takes is not None:
        tt = takes if isinstance(takes, tuple) else (takes,)
        out = [s for s in out if s.takes == tt]
    if gives is not None:
        out = [s for s in out if s.gives is gives]
    if search:
        q = search.lower()
        out = [s for s in out if q in s.name.lower() or q in s.family.lower() or q in s.summary.lower()]
    return sorted(out, key=lambda s: (s.family, s.name))


def families() -> list[str]:
    """Names of the registered op families."""
    _ensure_loaded()
    return sorted({s.family for s in _REGISTRY.values()})
