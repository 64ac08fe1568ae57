"""The sorts' base class and the array checks every sort's constructor uses.

The sorts themselves live in :mod:`fsjax.types.raster`, :mod:`fsjax.types.geometry` and
:mod:`fsjax.types.records`; :mod:`fsjax.types` re-exports them. The conventions below hold
for all of them.

A sort is an :class:`equinox.Module` subclass; the *class itself* is the static
type tag. Pipelines are type-checked from classes before anything is traced,
so the check costs nothing at run time. Array fields hold data; metadata that
fixes shapes or meaning is a static field.

Conventions (fixed project-wide, see ``docs/architecture.md``):

* Arrays are indexed ``(row, col)``; pixel centres sit on integer indices.
* ``Image`` holds grey values nominally in ``[0, 1]``. Ops that produce a signed
  response (derivatives, Laplacian, high-pass filters) still return ``Image``
  and say so in their docstring; they never clip silently.
* ``Color`` is *linear* RGB in ``[0, 1]``. ``HSV`` and ``Lab`` are separate sorts,
  because an HSV triple read as RGB gives a plausible wrong picture.
* Camera: OpenCV convention (x right, y down, z forward), poses are
  ``world_from_camera``.
* Every sort accepts leading batch axes (``(*batch, H, W)`` for ``Image``).
  Ops are written for one instance; batching is ``jax.vmap``.

Construction from a plain array validates rank, trailing shape and dtype and
raises ``TypeError``/``ValueError`` that says exactly what is wrong. Integer
arrays are refused by the float sorts: use :meth:`Image.from_uint` (or
:func:`fsjax.io.read_image`), which converts to ``[0, 1]`` *and records the
conversion* in the static ``conversion`` field.
"""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from .._checks import is_concrete

__all__ = ["Sort", "is_concrete"]


def _describe(x: Any) -> str:
    shape = getattr(x, "shape", None)
    dtype = getattr(x, "dtype", None)
    if shape is None:
        return type(x).__name__
    return f"{type(x).__name__} of shape {tuple(shape)} and dtype {dtype}"


def _as_array(x: Any, *, sort: str, field: str, kind: str, min_ndim: int,
              trailing: tuple[int, ...] = (), spatial: int = 0) -> Array:
    """Convert ``x`` to a JAX array and check rank, trailing shape and dtype kind.

    ``kind`` is one of ``"float"``, ``"bool"``, ``"int"``.
    """
    if isinstance(x, Sort):
        raise TypeError(
            f"{sort}({field}=...): got a {type(x).__name__} sort; pass its array "
            f"(e.g. `.data`) or use a conversion op"
        )
    if not isinstance(x, (jax.Array, np.ndarray, jax.core.Tracer)):
        try:
            x = np.asarray(x)
        except Exception as e:  # pragma: no cover - exotic inputs
            raise TypeError(f"{sort}({field}=...): cannot convert {_describe(x)} to an array") from e
    dtype = jnp.result_type(x)
    if kind == "float":
        if jnp.issubdtype(dtype, jnp.bool_):
            raise TypeError(
                f"{sort}({field}=...): expected a float array, got bool; a boolean mask is a Region"
            )
        if jnp.issubdtype(dtype, jnp.integer):
            raise TypeError(
                f"{sort}({field}=...): expected a float array, got {dtype}; integer images must be "
                f"converted with {sort}.from_uint(x) (or fsjax.io.read_image), which scales to "
                f"[0, 1] and records the conversion"
            )
        if jnp.issubdtype(dtype, jnp.complexfloating):
            raise TypeError(f"{sort}({field}=...): expected a real float array, got {dtype}")
        if not jnp.issubdtype(dtype, jnp.floating):
            raise TypeError(f"{sort}({field}=...): expected a float array, got {dtype}")
    elif kind == "bool":
        if not jnp.issubdtype(dtype, jnp.bool_):
            raise TypeError(
                f"{sort}({field}=...): expected a bool array, got {dtype}; threshold an Image "
                f"(e.g. fsjax.ops.threshold) to make a Region"
            )
    elif kind == "int":
        if not jnp.issubdtype(dtype, jnp.integer):
            raise TypeError(f"{sort}({field}=...): expected an integer array, got {dtype}")
    ndim = len(np.shape(x))
    if ndim < min_ndim:
        raise ValueError(
            f"{sort}({field}=...): expected at least {min_ndim} dimensions, got shape {tuple(np.shape(x))}"
        )
    if trailing:
        got = tuple(np.shape(x))[ndim - len(trailing):]
        if got != trailing:
            want = ", ".join(["..."] + [str(t) for t in trailing])
            raise ValueError(
                f"{sort}({field}=...): expected shape ({want}), got {tuple(np.shape(x))}"
            )
    if spatial:
        shp = tuple(np.shape(x))
        axes = shp[ndim - len(trailing) - spatial: ndim - len(trailing)]
        if 0 in axes:
            raise ValueError(
                f"{sort}({field}=...): empty {sort} (spatial size {'x'.join(map(str, axes))}, "
                f"shape {shp}); fsjax ops need at least one pixel per axis"
            )
    x = jnp.asarray(x)
    if kind == "int" and x.dtype != jnp.int32:
        x = x.astype(jnp.int32)
    return x


def _has_nonfinite(x: Array) -> bool:
    # numpy, not jnp: inside a jit trace, jnp ops on concrete arrays are staged.
    return not bool(np.all(np.isfinite(np.asarray(x))))


class Sort(eqx.Module):
    """Base class of every sort.

    Subclasses implement ``_float_fields`` (names of float array fields checked for
    NaN/inf on eager input) and may override :meth:`check`.
    """

    _float_fields = ()
    _array_field = None  # the field np.asarray(sort) returns (None: no single array)

    def __array__(self, dtype=None, copy=None):
        """``np.asarray(sort)``: the sort's main array (``Image.data``, ``Points.xyz``, ...).

        Sorts made of several equally important arrays (``Mesh``, ``Camera``, ``Fit``, ...)
        raise ``TypeError`` naming their fields instead of giving a 0-d object array.
        """
        name = type(self).__name__
        if self._array_field is None:
            fields = [f for f in self.__dataclass_fields__ if not f.startswith("_")]
            raise TypeError(f"np.asarray(fsjax.{name}): a {name} has no single array; "
                            f"use one of its fields ({', '.join(fields)})")
        arr = np.asarray(getattr(self, self._array_field))
        if dtype is not None:
            arr = arr.astype(dtype, copy=False)
        return arr

    def check(self, *, op: str, arg: str, allow_inf: bool = False) -> None:
        """Eager validation of an op input (skipped for traced values).

        Raises ``ValueError`` naming ``op`` and ``arg`` when a float field holds NaN
        or infinity (NaN only, with ``allow_inf``: ops registered ``infinite_ok``).
        """
        for name in self._float_fields:
            v = getattr(self, name)
            if v is None or not is_concrete(v):
                continue
            if _has_nonfinite(v):
                a = np.asarray(v)
                if allow_inf:
                    n_nan = int(np.sum(np.isnan(a)))
                    if n_nan:
                        raise ValueError(
                            f"{op}: argument '{arg}' ({type(self).__name__}.{name}) contains "
                            f"{n_nan} NaN value(s); {op} accepts +-inf but not NaN")
                    continue
                n_bad = int(np.sum(~np.isfinite(a)))
                raise ValueError(
                    f"{op}: argument '{arg}' ({type(self).__name__}.{name}) contains "
                    f"{n_bad} NaN/inf value(s); fsjax ops need finite input "
                    f"(mask invalid pixels explicitly)"
                )

    @property
    def batch_shape(self) -> tuple[int, ...]:
        """Leading batch axes (empty for a single instance)."""
        raise NotImplementedError


def _from_uint(sort: str, data: Any, bit_depth: int | None, trailing: tuple[int, ...]):
    arr = np.asarray(data)
    if arr.dtype not in (np.uint8, np.uint16):
        raise TypeError(f"{sort}.from_uint: expected uint8 or uint16 data, got {arr.dtype}")
    native = 8 if arr.dtype == np.uint8 else 16
    bits = native if bit_depth is None else int(bit_depth)
    if not 1 <= bits <= native:
        raise ValueError(f"{sort}.from_uint: bit_depth must be in [1, {native}] for {arr.dtype}, got {bit_depth}")
    full = float(2**bits - 1)
    if int(arr.max(initial=0)) > full:
        raise ValueError(
            f"{sort}.from_uint: values up to {int(arr.max())} exceed bit_depth={bits} (max {int(full)})"
        )
    conv = f"{arr.dtype} / {int(full)}"
    return jnp.asarray(arr.astype(np.float64) / full, dtype=jnp.result_type(float)), conv
