"""Argument checks shared by ops, fits and renderers: one message style.

Every refusal names the function and the argument and says what was expected and what
came, in one form::

    gaussian: argument 'sigma' must be > 0, got -1.0

Two tiers (docs/architecture.md, "Results and errors"): *static* problems (a wrong type, a shape-fixing int that
is not an int, an unknown option, a concrete value out of range) raise here, while
tracing, with that message; *traced* values (knobs inside ``jit``/``vmap``) cannot be
checked eagerly; every check below lets a tracer through, and records the violation for the
op's output instead when that tracer is a parameter the caller passed to a registered op
(see :func:`traced_checks`): the registry then poisons the op's output (NaN, validity flags
False; ``Region``/``Labels`` raise through ``equinox.error_if``), so a traced value that an
eager call would refuse never gives a plausible number.

This module is the bottom layer: it imports nothing of fsjax, and ``fsjax.types``,
``fsjax.registry``, ``fsjax.ops``, ``fsjax.fit`` and ``fsjax.render`` use it.
"""

from __future__ import annotations

import contextlib
from typing import Any

import jax
import numpy as np

__all__ = ["is_concrete", "check_range", "check_positive", "check_static_int", "check_choice",
           "check_finite_number", "traced_checks", "note_traced"]


def is_concrete(x: Any) -> bool:
    """True when ``x`` holds a concrete value (not a tracer inside ``jit``/``vmap``/``grad``)."""
    return not isinstance(x, jax.core.Tracer)


# The parameters watched by the innermost registered-op call in progress: ids of the traced
# keyword values its caller passed, the traced conditions recorded against them, and the
# trace the call runs in. Only those exact objects are watched, and only while that trace is
# current, so a check inside an op's own inner jit/vmap/scan (whose result would be a tracer
# of an inner trace, which must not leak out) records nothing.
_WATCH: list[tuple[frozenset, list, Any]] = []


def _current_trace():
    try:
        from jax._src import core  # the trace in progress (jax >= 0.4.36)

        return core.trace_ctx.trace
    except (ImportError, AttributeError):  # pragma: no cover - another jax: no guard, no record
        return None


@contextlib.contextmanager
def traced_checks(values: Any):
    """Collect traced range violations of ``values`` (the keyword values of one op call).

    Yields a list; every :func:`check_range`-family check (and :func:`note_traced`) made on
    one of these exact traced objects while the block runs appends a traced bool "out of
    range" to it. The registry wraps each op call in this and poisons the output with the
    OR of the list.
    """
    ids = frozenset(id(v) for v in values if isinstance(v, jax.core.Tracer))
    found: list = []
    if not ids:
        yield found
        return
    _WATCH.append((ids, found, _current_trace()))
    try:
        yield found
    finally:
        _WATCH.pop()


def note_traced(v: Any, bad: Any) -> None:
    """Record the traced condition ``bad`` (True = out of range) against parameter ``v``.

    Does nothing unless ``v`` is a traced keyword value of the registered-op call in progress
    (:func:`traced_checks`); ops whose eager check is not a :func:`check_range` call use this
    to fail closed the same way under ``jit``.
    """
    if _watched(v):
        import jax.numpy as jnp

        _WATCH[-1][1].append(jnp.any(bad))


def _watched(v) -> bool:
    if not (_WATCH and isinstance(v, jax.core.Tracer) and id(v) in _WATCH[-1][0]):
        return False
    trace = _WATCH[-1][2]
    return trace is not None and _current_trace() is trace


def _note_range(v, lo, hi, lo_open, hi_open) -> None:
    if not _watched(v):
        return
    import jax.numpy as jnp

    x = jnp.asarray(v)
    ok = jnp.isfinite(x)
    if lo is not None:
        ok &= (x > lo) if lo_open else (x >= lo)
    if hi is not None:
        ok &= (x < hi) if hi_open else (x <= hi)
    note_traced(v, ~ok)


def _concrete_float(v: Any, op: str = "", name: str = ""):
    if not is_concrete(v):
        return None
    if isinstance(v, (str, bytes)):  # np.asarray("2", dtype=float) would quietly accept it
        raise TypeError(f"{op}: argument {name!r} must be a number, got {type(v).__name__} {v!r}")
    try:
        arr = np.asarray(v, dtype=float)
    except (TypeError, ValueError):
        raise TypeError(f"{op}: argument {name!r} must be a number, got {type(v).__name__} {v!r}") from None
    return arr


def check_range(op: str, name: str, v: Any, lo: float | None = None, hi: float | None = None,
                *, lo_open: bool = False, hi_open: bool = False) -> None:
    """Eagerly check a concrete parameter against ``[lo, hi]`` (open ends optional).

    A traced value cannot be refused; when it is a parameter passed to a registered op, the
    violation is recorded and the op's output poisoned (:func:`traced_checks`).
    """
    arr = _concrete_float(v, op, name)
    if arr is None:
        _note_range(v, lo, hi, lo_open, hi_open)
        return
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{op}: argument {name!r} must be finite, got {v}")
    if lo is not None and (np.any(arr <= lo) if lo_open else np.any(arr < lo)):
        raise ValueError(f"{op}: argument {name!r} must be {'>' if lo_open else '>='} {lo:g}, got {v}")
    if hi is not None and (np.any(arr >= hi) if hi_open else np.any(arr > hi)):
        raise ValueError(f"{op}: argument {name!r} must be {'<' if hi_open else '<='} {hi:g}, got {v}")


def check_positive(op: str, name: str, v: Any) -> None:
    """Eagerly check that a concrete parameter is > 0."""
    check_range(op, name, v, 0.0, None, lo_open=True)


def check_static_int(op: str, name: str, v: Any, lo: int | None = None, hi: int | None = None) -> int:
    """A parameter that fixes an array shape must be a Python int (static); check and return it."""
    if not is_concrete(v) or isinstance(v, bool):
        raise TypeError(f"{op}: argument {name!r} fixes an array shape and must be a static int, got {type(v).__name__}")
    try:
        iv = int(v)
    except (TypeError, ValueError):
        raise TypeError(f"{op}: argument {name!r} must be an int, got {v!r}") from None
    if iv != v:
        raise TypeError(f"{op}: argument {name!r} must be an integer, got {v!r}")
    if lo is not None and iv < lo:
        raise ValueError(f"{op}: argument {name!r} must be >= {lo}, got {iv}")
    if hi is not None and iv > hi:
        raise ValueError(f"{op}: argument {name!r} must be <= {hi}, got {iv}")
    return iv


def check_choice(op: str, name: str, v: Any, choices: tuple[str, ...]) -> str:
    """Check a static string option against its allowed set."""
    if v not in choices:
        raise ValueError(f"{op}: argument {name!r} must be one of {', '.join(map(repr, choices))}; got {v!r}")
    return v


def check_finite_number(op: str, name: str, v: Any) -> None:
    """Eagerly check that a concrete parameter is a finite number (any sign)."""
    check_range(op, name, v)
