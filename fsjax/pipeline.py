"""The uniform call, and type-checked, compiled pipelines.

* :func:`apply` calls any registered op by name with its two knobs ``a``, ``b``
  in ``[0, 1]`` (mapped through the op's knob spec) and/or named parameters.
* :func:`pipeline` checks a chain of stages from the sort classes alone, before
  anything is traced, and returns a :class:`Pipeline`: a pure function
  ``(x, knobs=None) -> y`` compiled once with ``jax.jit``, ``vmap``-able over
  inputs and over knobs.

A stage is written as

* ``"gaussian"`` -- the op with its defaults;
* ``("gaussian", a, b)`` -- knob values in ``[0, 1]`` (``b`` may be omitted);
* ``("gaussian", {"sigma": 2.0})`` -- named parameters.

When a ``knobs`` array of shape ``(n_stages, 2)`` is passed at call time, it
sets every stage's knob-mapped parameters (explicit named parameters of a stage
still win); stages without knobs ignore their row.

Out-of-range knobs fail closed. Concrete knob values outside ``[0, 1]`` (or NaN)
raise ``ValueError`` at the call. Traced ones (the pipeline under ``jit``/``vmap``
of the caller, or a knob array built inside a transformation) are checked on the
values: a stage whose live knob is out of range runs on the clipped value and
its output is poisoned (floating fields NaN, validity flags False; a ``Region`` or
``Labels`` stage raises at run time through ``equinox.error_if``), and the NaN
propagates through the following stages. Knob rows of stages without knobs (and
of knobs overridden by a named parameter) are ignored. A knob inside ``[0, 1]`` maps
into the op's declared knob range, which every op computes exactly. Named stage parameters are concrete and
checked when the pipeline is traced; an out-of-range one raises ``ValueError``.

Stage numbers in error messages are 1-based (for people); the fields of
:class:`PipelineTypeError` are 0-based (for programs).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import jax.numpy as jnp
import numpy as np

from ._linalg import jit_fast_compile
from .registry import OpSpec, get_op, poison, truncation_poison
from .types import Sort, is_concrete

__all__ = ["apply", "pipeline", "run_pipeline", "Pipeline", "PipelineTypeError", "Stage"]


class PipelineTypeError(TypeError):
    """A pipeline whose sorts do not connect.

    Attributes (0-based): ``index`` of the offending stage, ``prev_index`` of the
    stage feeding it (``None`` for the pipeline input), ``op``, ``prev_op``,
    ``expected`` (sort the stage takes), ``got`` (sort it would receive).
    """

    def __init__(self, message: str, *, index: int, prev_index: int | None, op: str,
                 prev_op: str | None, expected: str, got: str):
        super().__init__(message)
        self.index = index
        self.prev_index = prev_index
        self.op = op
        self.prev_op = prev_op
        self.expected = expected
        self.got = got


def apply(x: Any, op: str, a: Any = None, b: Any = None, **params: Any) -> Any:
    """Call op ``op`` on ``x`` with knobs ``a``, ``b`` in ``[0, 1]`` and/or named parameters.

    Args:
      x: the input sort, or a tuple of sorts for multi-input ops.
      op: registered op name.
      a, b: knob values in ``[0, 1]`` (``None`` keeps the default); traced values
        are fine, so ``jax.vmap`` over ``a`` compiles once. A concrete knob outside
        ``[0, 1]`` (or NaN) raises ``ValueError``. A *traced* one cannot be refused
        before it has a value, so the call fails closed instead: the op runs on the
        knob clipped into ``[0, 1]`` (bounded work) and its output is poisoned --
        every floating field NaN and the validity flags (``valid``, ``converged``,
        ...) False; a sort with no floating field (``Region``, ``Labels``) raises at
        run time through ``equinox.error_if``. A named parameter that is traced
        fails closed the same way wherever an eager call would refuse its value
        (every range check an op makes on a parameter, e.g. ``sigma > 0``,
        ``channel`` in {0, 1, 2}, is recorded on a traced value by the registry
        and poisons the output); where the op's own rule is stricter it says so
        (``gaussian``: a traced sigma above ``max_sigma`` gives NaN). No traced
        value is clamped into a plausible result.
      **params: named keyword parameters (a parameter cannot be set both by a
        knob and by name).

    Example:
      >>> import fsjax, jax.numpy as jnp
      >>> img = fsjax.Image(jnp.zeros((5, 5)))
      >>> fsjax.apply(img, "gaussian", a=0.5).data.shape
      (5, 5)
    """
    spec = get_op(op)
    inputs = _as_inputs(spec, x, who=f"apply({spec.name!r})")
    kp = spec.knob_params(a, b, strict=True)
    clash = set(kp) & set(params)
    if clash:
        raise ValueError(f"apply({spec.name!r}): parameter(s) {sorted(clash)} set both by knob and by name")
    unknown = set(params) - set(spec.params)
    if unknown:
        raise TypeError(
            f"apply({spec.name!r}): unknown parameter(s) {sorted(unknown)}; "
            f"{spec.name} takes {', '.join(spec.params) or 'no parameters'}"
        )
    return poison(spec.fn(*inputs, **kp, **params), spec.knob_out_of_range(a, b), who=f"apply({spec.name!r})")


def _as_inputs(spec: OpSpec, x: Any, *, who: str) -> tuple:
    if spec.n_inputs == 1:
        return (x,)
    if not isinstance(x, (tuple, list)) or len(x) != spec.n_inputs:
        raise TypeError(
            f"{who}: op takes {spec.n_inputs} inputs "
            f"({', '.join(t.__name__ for t in spec.takes)}); pass them as a tuple"
        )
    return tuple(x)


@dataclasses.dataclass(frozen=True)
class Stage:
    """One parsed pipeline stage."""

    spec: OpSpec
    a: float | None = None
    b: float | None = None
    params: tuple[tuple[str, Any], ...] = ()

    @property
    def name(self) -> str:
        return self.spec.name

    def call(self, x: Any, knob_row: Any = None) -> Any:
        params = dict(self.params)
        if knob_row is not None:
            kp = self.spec.knob_params(knob_row[0], knob_row[1], strict=False)
        else:
            kp = self.spec.knob_params(self.a, self.b, strict=False)
        kp = {k: v for k, v in kp.items() if k not in params}
        out = truncation_poison(self.spec, (x,), self.spec.raw(x, **kp, **params))
        # a traced knob outside [0, 1] (or NaN): fail closed instead of computing a clamped value
        return poison(out, self.knob_bad(knob_row), who=f"pipeline stage ({self.name})")

    def knob_bad(self, knob_row: Any = None) -> Any:
        """Traced bool: a live traced knob of this stage is outside ``[0, 1]`` (``None``: none traced)."""
        if knob_row is None:
            return None
        params = dict(self.params)
        live = [knob_row[i] if i < len(self.spec.knobs) and self.spec.knob_names[i] not in params else None
                for i in range(2)]
        return self.spec.knob_out_of_range(*live)

    def __str__(self) -> str:
        if self.params:
            return f"{self.name}:" + ",".join(f"{k}={v}" for k, v in self.params)
        if self.a is not None:
            return f"{self.name}(a={self.a:g}" + (f", b={self.b:g})" if self.b is not None else ")")
        return self.name


def _parse_stage(s: Any, i: int) -> Stage:
    where = f"pipeline stage {i + 1}"
    if isinstance(s, Stage):
        return s
    if isinstance(s, str):
        return Stage(get_op(s))
    if isinstance(s, (tuple, list)) and s and isinstance(s[0], str):
        spec = get_op(s[0])
        rest = list(s[1:])
        if len(rest) == 1 and isinstance(rest[0], dict):
            params = rest[0]
            unknown = set(params) - set(spec.params)
            if unknown:
                raise TypeError(
                    f"{where} ({spec.name}): unknown parameter(s) {sorted(unknown)}; "
                    f"{spec.name} takes {', '.join(spec.params) or 'no parameters'}"
                )
            return Stage(spec, params=tuple(sorted(params.items())))
        if 1 <= len(rest) <= 2:
            a = rest[0]
            b = rest[1] if len(rest) == 2 else None
            spec.knob_params(a, b, strict=True, caller=f"{where} ({spec.name})")  # validates
            return Stage(spec, a=float(a), b=None if b is None else float(b))
        if not rest:
            return Stage(spec)
    raise TypeError(
        f"{where}: expected a name, (name, a[, b]) or (name, {{param: value}}), got {s!r}"
    )


class Pipeline:
    """A type-checked chain of ops, compiled once; call as ``p(x, knobs=None)``.

    Attributes:
      stages: the parsed stages.
      sorts: the sort after each stage.
      takes, gives: the pipeline's input and output sorts.
    """

    def __init__(self, stages: Sequence[Any]):
        if isinstance(stages, (str, tuple)) and not isinstance(stages, list):
            stages = [stages]
        stages = list(stages)
        if not stages:
            raise ValueError("pipeline: needs at least one stage")
        self.stages: tuple[Stage, ...] = tuple(_parse_stage(s, i) for i, s in enumerate(stages))
        for i, st in enumerate(self.stages):
            if not st.spec.linear:
                raise PipelineTypeError(
                    f"stage {i + 1} ({st.name}) takes {len(st.spec.takes)} inputs "
                    f"({', '.join(t.__name__ for t in st.spec.takes)}); linear pipelines take "
                    f"one-input ops only",
                    index=i, prev_index=i - 1 if i else None, op=st.name,
                    prev_op=self.stages[i - 1].name if i else None,
                    expected=" x ".join(t.__name__ for t in st.spec.takes),
                    got=self.stages[i - 1].spec.gives.__name__ if i else "input",
                )
            if i == 0:
                continue
            prev = self.stages[i - 1]
            want, got = st.spec.takes[0], prev.spec.gives
            if not issubclass(got, want):
                raise PipelineTypeError(
                    f"stage {i + 1} ({st.name}) takes {want.__name__} but stage {i} "
                    f"({prev.name}) gives {got.__name__}",
                    index=i, prev_index=i - 1, op=st.name, prev_op=prev.name,
                    expected=want.__name__, got=got.__name__,
                )
        self.takes: type = self.stages[0].spec.takes[0]
        self.gives: type = self.stages[-1].spec.gives
        self.sorts: tuple[type, ...] = tuple(st.spec.gives for st in self.stages)
        # called at top level, compiled with FAST_COMPILE (XLA's older loop emitters, LLVM level
        # 2): the 6-stage pipeline of docs/compile_times.md 2.6 -> 1.8 s of CPU, run time within
        # noise without a rank filter (+7 % with a traced-radius median); under a user's jit or
        # vmap the plain program is traced into theirs
        self._compiled = jit_fast_compile(self._run)

    def __len__(self) -> int:
        return len(self.stages)

    def __repr__(self) -> str:
        chain = " -> ".join(f"{st} [{st.spec.gives.__name__}]" for st in self.stages)
        return f"Pipeline({self.takes.__name__} -> {chain})"

    def _run(self, x: Any, knobs: Any = None) -> Any:
        bad = None
        for i, st in enumerate(self.stages):
            row = None if knobs is None else knobs[i]
            x = st.call(x, row)
            b = st.knob_bad(row)
            bad = b if bad is None else (bad if b is None else bad | b)
        # a poisoned stage poisons the result even when a later stage (a threshold, a count)
        # would turn its NaN into a plausible value
        return poison(x, bad, who="pipeline")

    def _check_call(self, x: Any, knobs: Any) -> None:
        if not isinstance(x, self.takes):
            raise TypeError(
                f"pipeline input: stage 1 ({self.stages[0].name}) takes {self.takes.__name__}, "
                f"got {type(x).__name__}"
            )
        x.check(op=f"pipeline stage 1 ({self.stages[0].name})", arg=self.stages[0].spec.input_names[0])
        if knobs is not None:
            shape = jnp.shape(knobs)
            if len(shape) < 2 or shape[-2:] != (len(self.stages), 2):
                raise ValueError(
                    f"pipeline knobs: expected shape ({len(self.stages)}, 2) (n_stages, 2), got {shape}"
                )
            if is_concrete(knobs):
                k = np.asarray(knobs, dtype=float)
                bad = ~np.isfinite(k) | (k < 0) | (k > 1)
                if bool(np.any(bad)):
                    idx = [int(v) for v in np.argwhere(bad)[0]]
                    raise ValueError(
                        f"pipeline knobs: value at stage {idx[-2] + 1} ({self.stages[idx[-2]].name}), "
                        f"knob {'ab'[idx[-1]]!r} must be in [0, 1], got {float(k[tuple(idx)]):g}"
                    )

    def __call__(self, x: Any, knobs: Any = None) -> Any:
        """Run the compiled pipeline on ``x`` (one instance; ``jax.vmap`` for batches)."""
        self._check_call(x, knobs)
        if knobs is not None:
            knobs = jnp.asarray(knobs)
        return self._compiled(x, knobs)

    def trace(self, x: Any, knobs: Any = None, *, on_stage: Any = None) -> list[Any]:
        """Stage diagnostics: the output of every stage (eager, not compiled).

        ``on_stage(i, stage, out)``, when given, is called after stage ``i`` (0-based) has
        finished (its output computed), so a caller can report progress stage by stage.
        """
        self._check_call(x, knobs)
        outs = []
        for i, st in enumerate(self.stages):
            x = st.call(x, None if knobs is None else jnp.asarray(knobs)[i])
            outs.append(x)
            if on_stage is not None:
                on_stage(i, st, x)
        return outs

    def describe(self) -> str:
        """One line per stage: number, op, sort produced."""
        lines = [f"input: {self.takes.__name__}"]
        for i, st in enumerate(self.stages):
            lines.append(f"stage {i + 1}: {st} -> {st.spec.gives.__name__}")
        return "\n".join(lines)


def pipeline(stages: Sequence[Any]) -> Pipeline:
    """Build a type-checked, compiled pipeline (see the module docstring for stage forms).

    Raises :class:`PipelineTypeError` at construction, before anything is traced,
    when consecutive sorts do not connect.

    Example:
      >>> import fsjax
      >>> p = fsjax.pipeline(["gaussian", "sobel_amp", "otsu"])
      >>> p.gives.__name__
      'Region'
    """
    return Pipeline(stages)


def run_pipeline(x: Sort, stages: Sequence[Any], knobs: Any = None) -> Any:
    """One-liner: build the pipeline for ``stages`` and run it on ``x``."""
    return pipeline(stages)(x, knobs)
