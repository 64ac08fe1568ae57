"""Argument checks shared by ops, fits and renderers: one message style.

Every refusal names the function and the argument and says what was expected and what
came, in one form::

    gaussian: argument 'sigma' must be > 0, got -1.0

Two tiers (docs/architecture.md, "Results and errors"): *static* problems (a wrong type, a shape-fixing int that
is not an int, an unknown option, a concrete value out of range) raise here, while
tracing, with that message; *traced* values (knobs inside ``jit``/``vmap``) cannot be
checked eagerly and are the op's business (poisoned output, ``eqx.error_if`` or a result
flag), so every check below lets a tracer through.

This module is the bottom layer: it imports nothing of fsjax, and ``fsjax.types``,
``fsjax.registry``, ``fsjax.ops``, ``fsjax.fit`` and ``fsjax.render`` use it.
"""

from __future__ import annotations

from typing import Any

import jax
import numpy as np

__all__ = ["is_concrete", "check_range", "check_positive", "check_static_int", "check_choice",
           "check_finite_number"]


def is_concrete(x: Any) -> bool:
    """True when ``x`` holds a concrete value (not a tracer inside ``jit``/``vmap``/``grad``)."""
    return not isinstance(x, jax.core.Tracer)


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

    Traced values are not checked (they come from knobs, which are range-mapped).
    """
    arr = _concrete_float(v, op, name)
    if arr is None:
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
