"""The result vocabulary every fit shares: one ``RESULTS`` enumeration, base fields, deprecations.

Learned from optimistix (``Solution.result``) and equinox (``eqx.Enumeration``): every record a
fit in :mod:`fsjax.fit` returns says *whether* it worked and *why not* in the same words.

Base fields (every fit result, :class:`FitResult`):

* ``converged`` -- bool array: the result is usable (``reason == RESULTS.ok``; for
  :class:`~fsjax.fit.TwoViewResult` a pure rotation is usable too, see its docstring);
* ``reason`` -- int32 array, a code of :class:`RESULTS` (the same code means the same thing in
  every fit). It is a plain integer array so that it ``jit``s, ``vmap``s, stacks and compares
  like any other leaf (``res.reason == reason_code("too_few")``); ``res.result`` views it as an
  ``eqx.Enumeration`` item (``res.result == RESULTS.too_few``) and ``res.message`` gives the
  text (one string, or an array of strings for a batched record);
* ``iterations`` -- int32 array, solver steps (0 for closed-form fits);
* a residual named with its unit, given by the class attribute ``residual_name``: ``rms_px``
  (pixels), ``rms_len`` (the length unit of the input points: metres for the bundled data,
  millimetres if the input was in millimetres) or ``sampson_rms_px``. ``res.residual`` reads it.

Under ``vmap`` a record comes back batched leaf by leaf: ``reason`` has the batch shape, so
``res.reason == reason_code("ok")`` is a boolean mask and ``reason_message(res.reason)`` an
array of texts.

Renamed fields (``rms``, ``rmse``, ``valid``, ``found``...) stay readable for one release as
properties that emit a ``DeprecationWarning`` naming the new field (:func:`renamed`).
"""

from __future__ import annotations

import warnings
from typing import Any, ClassVar

import equinox as eqx
import jax.numpy as jnp
import numpy as np

__all__ = ["RESULTS", "FitResult", "WrappedFit", "reason_code", "reason_message", "result_item", "renamed", "deprecated_name"]


class RESULTS(eqx.Enumeration):
    """Why a fit ended. The code of a member is its position here (:func:`reason_code`)."""

    ok = "ok"
    max_iterations = ("maximum number of iterations reached before the tolerance was met "
                      "(the iterative solver did not converge)")
    too_few = "too few points or correspondences (fewer valid / inlier pairs than the model needs)"
    degenerate = ("degenerate geometry (collinear or rank-deficient points, singular normal equations "
                  "or reduced camera system)")
    invalid_input = ("invalid input (empty or all-invalid data, non-finite values, bad indices, "
                     "too few views)")
    poor_fit = "the fit is poor: inlier fraction (consensus) below min_inlier_fraction"
    no_hypothesis = "no consistent hypothesis (RANSAC found no hypothesis with enough inliers)"
    too_few_inliers = "too few RANSAC inliers for the model (PnP needs 6, the essential matrix 8)"
    coplanar = "coplanar points (the DLT needs non-coplanar 3-D points)"
    pure_rotation = "pure rotation: no parallax (t undefined; R from bearing alignment)"
    cheirality = "no pose puts the inliers in front of both cameras"
    unsupported_model = ("unsupported model: the points do not resolve it (3-D: the inliers also lie "
                         "within threshold of a plane, no curvature resolved, or the points do not thin "
                         "out beyond the threshold, a slice through a volume; 2-D circle / ellipse: "
                         "misfit or uncertainty above max_rel_rms / max_rel_se of its size)")
    not_found = "the pattern was not found (no response, too few candidates or no complete grid)"
    pattern_mismatch = "the pattern does not match the board (more or fewer inner corners)"
    refinement_failed = "sub-pixel refinement failed or merged neighbouring corners"
    no_model_fits = ("no candidate model explains the points: every fit's residuals are far above the "
                     "noise (or, with no noise given, above max_rel_rms of the points' spread)")
    capacity_exceeded = ("a static capacity was exceeded (more items than the op's fixed buffer holds); the "
                         "result would miss data, so it is refused: raise the capacity argument")


def reason_code(name: str) -> int:
    """The int32 code of member ``name`` of :class:`RESULTS` (what a record's ``reason`` holds)."""
    return int(getattr(RESULTS, name)._value)


def result_item(code: Any):
    """The :class:`RESULTS` item of an int code (works on traced and batched codes)."""
    from equinox._enum import EnumerationItem  # eqx.Enumeration offers no public int -> item

    return EnumerationItem(jnp.asarray(code, jnp.int32), RESULTS)


def reason_message(code: Any) -> Any:
    """The text of a reason code: ``str`` for a scalar, an array of ``str`` for a batched code.

    Needs a concrete code (outside ``jit``); inside ``jit`` return the record and read it after.
    """
    msgs = RESULTS._index_to_message
    arr = np.asarray(code)

    def one(c):
        c = int(c)
        return msgs[c] if 0 <= c < len(msgs) else f"unknown reason code {c}"

    if arr.ndim == 0:
        return one(arr)
    return np.vectorize(one, otypes=[object])(arr)


def deprecated_name(old: str, new: str, stacklevel: int = 3) -> None:
    """Emit the one deprecation message of this package: ``old`` is deprecated, use ``new``."""
    warnings.warn(f"{old} is deprecated and will be removed in the next release; use {new}",
                  DeprecationWarning, stacklevel=stacklevel)


def renamed(new: str, doc: str = "") -> property:
    """A read-only property for a renamed field: warns (naming ``new``) and returns ``self.<new>``."""

    class _Renamed(property):
        def __set_name__(self, owner, name):
            self._old = f"{owner.__name__}.{name}"

    def get(self):
        deprecated_name(prop._old, f"{type(self).__name__}.{new}")
        return getattr(self, new)

    prop = _Renamed(get, doc=doc or f"Deprecated: renamed ``{new}``.")
    prop._old = "field"
    return prop


class FitResult(eqx.Module):
    """Mixin of every fit result: ``message``, ``result``, ``residual`` from the base fields.

    A subclass declares the base fields ``converged``, ``reason``, ``iterations`` (as fields, or
    as properties for a record that wraps others) and names its residual in ``residual_name``
    (``None`` when the record has no residual; its docstring says why).
    """

    residual_name: ClassVar[str | None] = None

    @property
    def message(self) -> Any:
        """Text of ``reason`` (concrete records; an array of texts when batched)."""
        return reason_message(self.reason)

    @property
    def result(self):
        """``reason`` as an item of the :class:`RESULTS` enumeration (jit- and vmap-safe)."""
        return result_item(self.reason)

    @property
    def residual(self) -> Any:
        """The residual field named by ``residual_name`` (``None`` if the record has none)."""
        return None if self.residual_name is None else getattr(self, self.residual_name)


class WrappedFit(FitResult):
    """A result that wraps another fit result: its base fields are those of the field ``inner``."""

    inner: ClassVar[str] = ""

    @property
    def converged(self) -> Any:
        return getattr(self, self.inner).converged

    @property
    def reason(self) -> Any:
        return getattr(self, self.inner).reason

    @property
    def iterations(self) -> Any:
        return getattr(self, self.inner).iterations

    @property
    def residual(self) -> Any:
        return getattr(getattr(self, self.inner), self.residual_name)


class Legacy:
    """The old per-fit reason codes of one fit (deprecated; kept one release for ``legacy_reason``).

    ``names[i]`` is the :class:`RESULTS` member that old code ``i`` became; ``also`` maps further
    members to an old code (e.g. ``max_iterations`` of PnP, once reported as 0 with
    ``converged=False``).
    """

    def __init__(self, names: tuple[str, ...], also: dict[str, int] | None = None):
        self.names = tuple(names)
        self._new = np.asarray([reason_code(n) for n in self.names], np.int32)
        old = np.full(len(RESULTS), -1, np.int32)
        for i, n in enumerate(self.names):
            old[reason_code(n)] = i
        for n, i in (also or {}).items():
            old[reason_code(n)] = i
        self._old = old

    def new(self, old_code: Any) -> Any:
        """New code of an old code (jit-safe)."""
        return jnp.asarray(self._new)[jnp.asarray(old_code, jnp.int32)]

    def old(self, new_code: Any) -> Any:
        """Old code of a new code (jit-safe; -1 where the old table had none)."""
        return jnp.asarray(self._old)[jnp.asarray(new_code, jnp.int32)]

    def table(self) -> dict[int, str]:
        """``{new code: message}`` of the members this fit can return (the deprecated ``*_REASONS``)."""
        return legacy_table(self.names)

    def property(self) -> property:
        """A deprecated ``legacy_reason`` property: the old code of the record's ``reason``."""
        legacy = self

        class _Prop(property):
            def __set_name__(self, owner, name):
                self._owner = owner.__name__

        def get(rec):
            deprecated_name(f"{prop._owner}.legacy_reason (the old per-fit reason codes)",
                            f"{prop._owner}.reason (codes of fsjax.types.RESULTS)")
            return legacy.old(rec.reason)

        prop = _Prop(get, doc="Deprecated: the reason in this fit's old codes.")
        prop._owner = "record"
        return prop


def legacy_table(messages: tuple[str, ...]) -> dict[int, str]:
    """``{new code: message}`` restricted to the members a fit can return (deprecated tables)."""
    return {reason_code(n): RESULTS._index_to_message[reason_code(n)] for n in messages}
