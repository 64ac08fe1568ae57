"""The sorts: typed pytrees that flow between fsjax ops.

A sort is an :class:`equinox.Module` subclass; the *class itself* is the static
type tag. Pipelines are type-checked from classes before anything is traced,
so the check costs nothing at run time. Array fields hold data; metadata that
fixes shapes or meaning is a static field.

Conventions (fixed project-wide, see ``DESIGN.md``):

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
from jaxtyping import Array, Bool, Float, Int

__all__ = [
    "Sort",
    "Image",
    "Color",
    "HSV",
    "Lab",
    "Region",
    "Labels",
    "Feature",
    "Contour",
    "Signal",
    "Volume",
    "Points",
    "Mesh",
    "Gaussians",
    "Camera",
    "Depth",
    "Match",
    "RegionProps",
    "Fit",
    "Edges1D",
    "is_concrete",
]


def is_concrete(x: Any) -> bool:
    """True when ``x`` holds a concrete value (not a tracer inside ``jit``/``vmap``/``grad``)."""
    return not isinstance(x, jax.core.Tracer)


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

    def check(self, *, op: str, arg: str) -> None:
        """Eager validation of an op input (skipped for traced values).

        Raises ``ValueError`` naming ``op`` and ``arg`` when a float field holds NaN
        or infinity.
        """
        for name in self._float_fields:
            v = getattr(self, name)
            if v is None or not is_concrete(v):
                continue
            if _has_nonfinite(v):
                n_bad = int(np.sum(~np.isfinite(np.asarray(v))))
                raise ValueError(
                    f"{op}: argument '{arg}' ({type(self).__name__}.{name}) contains "
                    f"{n_bad} NaN/inf value(s); fsjax ops need finite input "
                    f"(mask invalid pixels explicitly)"
                )

    @property
    def batch_shape(self) -> tuple[int, ...]:
        """Leading batch axes (empty for a single instance)."""
        raise NotImplementedError


# ---------------------------------------------------------------------------
# 2-D rasters
# ---------------------------------------------------------------------------


class Image(Sort):
    """Grey-value image, shape ``(*batch, H, W)``, float, values nominally in ``[0, 1]``.

    ``conversion`` records how the data was obtained from integer file values
    (e.g. ``"uint8 / 255"``); it is ``None`` for data made in float.
    """

    _array_field = "data"

    data: Float[Array, "*batch H W"]
    conversion: str | None = eqx.field(static=True, default=None)
    _float_fields = ("data",)

    def __init__(self, data: Any, conversion: str | None = None):
        self.data = _as_array(data, sort="Image", field="data", kind="float", min_ndim=2, spatial=2)
        self.conversion = conversion

    @classmethod
    def from_uint(cls, data: Any, *, bit_depth: int | None = None) -> Image:
        """Build an ``Image`` from unsigned integer values, scaling to ``[0, 1]``.

        ``uint8`` is divided by 255, ``uint16`` by 65535 unless ``bit_depth`` says
        the sensor used fewer bits (e.g. 12 -> divide by 4095). The conversion is
        recorded in ``conversion``.
        """
        return cls(*_from_uint("Image", data, bit_depth, trailing=()))

    @property
    def shape(self) -> tuple[int, ...]:
        return tuple(self.data.shape)

    @property
    def batch_shape(self) -> tuple[int, ...]:
        return tuple(self.data.shape[:-2])


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


class Color(Sort):
    """Linear RGB image, shape ``(*batch, H, W, 3)``, float in ``[0, 1]``."""

    _array_field = "data"

    data: Float[Array, "*batch H W 3"]
    conversion: str | None = eqx.field(static=True, default=None)
    _float_fields = ("data",)

    def __init__(self, data: Any, conversion: str | None = None):
        self.data = _as_array(data, sort="Color", field="data", kind="float", min_ndim=3, trailing=(3,),
                              spatial=2)
        self.conversion = conversion

    @classmethod
    def from_uint(cls, data: Any, *, bit_depth: int | None = None) -> Color:
        """Build a ``Color`` from ``uint8``/``uint16`` RGB values (no gamma decoding;
        use :func:`fsjax.io.read_image` with ``linearize=True`` for sRGB files)."""
        arr = np.asarray(data)
        if arr.ndim < 3 or arr.shape[-1] != 3:
            raise ValueError(f"Color.from_uint: expected shape (..., H, W, 3), got {arr.shape}")
        return cls(*_from_uint("Color", arr, bit_depth, trailing=(3,)))

    @property
    def batch_shape(self) -> tuple[int, ...]:
        return tuple(self.data.shape[:-3])


class HSV(Sort):
    """Hue/saturation/value image, shape ``(*batch, H, W, 3)``.

    Hue is in turns, ``[0, 1)`` (0 = red, 1/3 = green, 2/3 = blue); saturation and
    value in ``[0, 1]``.
    """

    _array_field = "data"

    data: Float[Array, "*batch H W 3"]
    _float_fields = ("data",)

    def __init__(self, data: Any):
        self.data = _as_array(data, sort="HSV", field="data", kind="float", min_ndim=3, trailing=(3,),
                              spatial=2)

    @property
    def batch_shape(self) -> tuple[int, ...]:
        return tuple(self.data.shape[:-3])


class Lab(Sort):
    """CIE L*a*b* image, shape ``(*batch, H, W, 3)``; L* in ``[0, 100]``, D65 white."""

    _array_field = "data"

    data: Float[Array, "*batch H W 3"]
    _float_fields = ("data",)

    def __init__(self, data: Any):
        self.data = _as_array(data, sort="Lab", field="data", kind="float", min_ndim=3, trailing=(3,),
                              spatial=2)

    @property
    def batch_shape(self) -> tuple[int, ...]:
        return tuple(self.data.shape[:-3])


class Region(Sort):
    """Foreground mask, shape ``(*batch, H, W)``, bool."""

    _array_field = "data"

    data: Bool[Array, "*batch H W"]

    def __init__(self, data: Any):
        self.data = _as_array(data, sort="Region", field="data", kind="bool", min_ndim=2, spatial=2)

    @property
    def batch_shape(self) -> tuple[int, ...]:
        return tuple(self.data.shape[:-2])


class Labels(Sort):
    """Label image, shape ``(*batch, H, W)`` int32; 0 = background, ``1..count``.

    ``count`` is the number of labels (traced int32 scalar); ``truncated`` is True
    when a fixed label capacity was exceeded and labels were lost.
    """

    _array_field = "data"

    data: Int[Array, "*batch H W"]
    count: Int[Array, "*batch"]
    truncated: Bool[Array, "*batch"]

    def __init__(self, data: Any, count: Any = None, truncated: Any = False):
        self.data = _as_array(data, sort="Labels", field="data", kind="int", min_ndim=2, spatial=2)
        if count is None:
            if not is_concrete(self.data):
                raise ValueError("Labels(count=None) needs a concrete label array; pass count under jit")
            count = np.max(np.asarray(self.data), axis=(-2, -1), initial=0)
        self.count = jnp.asarray(count, dtype=jnp.int32)
        self.truncated = jnp.asarray(truncated, dtype=bool)

    @property
    def batch_shape(self) -> tuple[int, ...]:
        return tuple(self.data.shape[:-2])


class Feature(Sort):
    """One measured number, shape ``(*batch,)``; ``unit`` names its unit (static)."""

    _array_field = "value"

    value: Float[Array, "*batch"]
    unit: str = eqx.field(static=True, default="")
    _float_fields = ()  # a measured NaN is a legitimate "could not measure"

    def __init__(self, value: Any, unit: str = ""):
        self.value = _as_array(value, sort="Feature", field="value", kind="float", min_ndim=0)
        self.unit = unit

    @property
    def batch_shape(self) -> tuple[int, ...]:
        return tuple(self.value.shape)

    def __float__(self) -> float:
        return float(self.value)


class Contour(Sort):
    """Fixed-capacity polyline(s), ``points`` ``(*batch, N, 2)`` as sub-pixel ``(row, col)``.

    ``valid`` marks used slots; ``truncated`` is True when the capacity was
    exceeded. ``closed`` tells whether the valid points form a closed curve.
    """

    _array_field = "points"

    points: Float[Array, "*batch N 2"]
    valid: Bool[Array, "*batch N"]
    truncated: Bool[Array, "*batch"]
    closed: bool = eqx.field(static=True, default=False)

    def __init__(self, points: Any, valid: Any = None, truncated: Any = False, closed: bool = False):
        self.points = _as_array(points, sort="Contour", field="points", kind="float", min_ndim=2, trailing=(2,))
        if valid is None:
            valid = jnp.ones(self.points.shape[:-1], dtype=bool)
        self.valid = _as_array(valid, sort="Contour", field="valid", kind="bool", min_ndim=1)
        if self.valid.shape != self.points.shape[:-1]:
            raise ValueError(
                f"Contour(valid=...): shape {self.valid.shape} does not match points {self.points.shape[:-1]}"
            )
        self.truncated = jnp.asarray(truncated, dtype=bool)
        self.closed = bool(closed)

    @property
    def batch_shape(self) -> tuple[int, ...]:
        return tuple(self.points.shape[:-2])


class Signal(Sort):
    """1-D profile or time series, shape ``(*batch, N)``; ``rate`` samples per ``unit``."""

    _array_field = "data"

    data: Float[Array, "*batch N"]
    rate: float = eqx.field(static=True, default=1.0)
    unit: str = eqx.field(static=True, default="px")
    _float_fields = ("data",)

    def __init__(self, data: Any, rate: float = 1.0, unit: str = "px"):
        self.data = _as_array(data, sort="Signal", field="data", kind="float", min_ndim=1)
        if not (float(rate) > 0):
            raise ValueError(f"Signal(rate=...): must be > 0, got {rate}")
        self.rate = float(rate)
        self.unit = unit

    @property
    def batch_shape(self) -> tuple[int, ...]:
        return tuple(self.data.shape[:-1])


class Volume(Sort):
    """Scalar volume, shape ``(*batch, D, H, W)``; ``spacing`` is ``(dz, dy, dx)`` in ``unit``."""

    _array_field = "data"

    data: Float[Array, "*batch D H W"]
    spacing: tuple[float, float, float] = eqx.field(static=True, default=(1.0, 1.0, 1.0))
    unit: str = eqx.field(static=True, default="mm")
    _float_fields = ("data",)

    def __init__(self, data: Any, spacing: tuple[float, float, float] = (1.0, 1.0, 1.0), unit: str = "mm"):
        self.data = _as_array(data, sort="Volume", field="data", kind="float", min_ndim=3, spatial=3)
        sp = tuple(float(s) for s in spacing)
        if len(sp) != 3 or not all(s > 0 for s in sp):
            raise ValueError(f"Volume(spacing=...): expected three positive numbers (dz, dy, dx), got {spacing}")
        self.spacing = sp
        self.unit = unit

    @property
    def batch_shape(self) -> tuple[int, ...]:
        return tuple(self.data.shape[:-3])


# ---------------------------------------------------------------------------
# 3-D geometry
# ---------------------------------------------------------------------------


class Points(Sort):
    """Fixed-capacity point set: ``xyz`` ``(*batch, N, 3)``, ``valid`` ``(*batch, N)``.

    Optional ``normals`` ``(*batch, N, 3)`` (unit length) and ``colors``
    ``(*batch, N, 3)`` linear RGB. ``truncated`` flags lost points.
    """

    _array_field = "xyz"

    xyz: Float[Array, "*batch N 3"]
    valid: Bool[Array, "*batch N"]
    normals: Float[Array, "*batch N 3"] | None
    colors: Float[Array, "*batch N 3"] | None
    truncated: Bool[Array, "*batch"]
    _float_fields = ("xyz", "normals", "colors")

    def __init__(self, xyz: Any, valid: Any = None, normals: Any = None, colors: Any = None, truncated: Any = False):
        self.xyz = _as_array(xyz, sort="Points", field="xyz", kind="float", min_ndim=2, trailing=(3,))
        if valid is None:
            valid = jnp.ones(self.xyz.shape[:-1], dtype=bool)
        self.valid = _as_array(valid, sort="Points", field="valid", kind="bool", min_ndim=1)
        if self.valid.shape != self.xyz.shape[:-1]:
            raise ValueError(f"Points(valid=...): shape {self.valid.shape} does not match xyz {self.xyz.shape[:-1]}")
        self.normals = None if normals is None else _as_array(
            normals, sort="Points", field="normals", kind="float", min_ndim=2, trailing=(3,))
        self.colors = None if colors is None else _as_array(
            colors, sort="Points", field="colors", kind="float", min_ndim=2, trailing=(3,))
        for name in ("normals", "colors"):
            v = getattr(self, name)
            if v is not None and v.shape != self.xyz.shape:
                raise ValueError(f"Points({name}=...): shape {v.shape} does not match xyz {self.xyz.shape}")
        self.truncated = jnp.asarray(truncated, dtype=bool)

    @property
    def batch_shape(self) -> tuple[int, ...]:
        return tuple(self.xyz.shape[:-2])


class Mesh(Sort):
    """Triangle mesh: ``vertices`` ``(V, 3)``, ``faces`` ``(F, 3)`` int32, outward winding.

    ``vertex_valid``/``face_valid`` mark used slots of fixed capacities.
    """

    vertices: Float[Array, "*batch V 3"]
    faces: Int[Array, "*batch F 3"]
    vertex_valid: Bool[Array, "*batch V"]
    face_valid: Bool[Array, "*batch F"]
    truncated: Bool[Array, "*batch"]
    _float_fields = ("vertices",)

    def __init__(self, vertices: Any, faces: Any, vertex_valid: Any = None, face_valid: Any = None,
                 truncated: Any = False):
        self.vertices = _as_array(vertices, sort="Mesh", field="vertices", kind="float", min_ndim=2, trailing=(3,))
        self.faces = _as_array(faces, sort="Mesh", field="faces", kind="int", min_ndim=2, trailing=(3,))
        if vertex_valid is None:
            vertex_valid = jnp.ones(self.vertices.shape[:-1], dtype=bool)
        if face_valid is None:
            face_valid = jnp.ones(self.faces.shape[:-1], dtype=bool)
        self.vertex_valid = _as_array(vertex_valid, sort="Mesh", field="vertex_valid", kind="bool", min_ndim=1)
        self.face_valid = _as_array(face_valid, sort="Mesh", field="face_valid", kind="bool", min_ndim=1)
        if is_concrete(self.faces) and self.faces.size:
            nv = self.vertices.shape[-2]
            f = np.asarray(self.faces)
            if int(f.min()) < 0 or int(f.max()) >= nv:
                raise ValueError(
                    f"Mesh(faces=...): indices must be in [0, {nv - 1}], got range "
                    f"[{int(f.min())}, {int(f.max())}]"
                )
        self.truncated = jnp.asarray(truncated, dtype=bool)

    @property
    def batch_shape(self) -> tuple[int, ...]:
        return tuple(self.vertices.shape[:-2])


class Gaussians(Sort):
    """3-D Gaussian splats in the 3DGS parameterisation (Kerbl et al. 2023).

    ``means`` ``(N, 3)``; ``log_scales`` ``(N, 3)``; ``quats`` ``(N, 4)`` as
    ``(w, x, y, z)`` (normalised at use; a zero-length quaternion is an error);
    ``opacity_logits`` ``(N,)``; ``colors`` ``(N, K, 3)`` spherical-harmonic
    coefficients (``K = 1`` is a plain colour); ``valid`` ``(N,)``.
    """

    means: Float[Array, "*batch N 3"]
    log_scales: Float[Array, "*batch N 3"]
    quats: Float[Array, "*batch N 4"]
    opacity_logits: Float[Array, "*batch N"]
    colors: Float[Array, "*batch N K 3"]
    valid: Bool[Array, "*batch N"]
    _float_fields = ("means", "log_scales", "quats", "opacity_logits", "colors")

    def __init__(self, means: Any, log_scales: Any, quats: Any, opacity_logits: Any, colors: Any, valid: Any = None):
        self.means = _as_array(means, sort="Gaussians", field="means", kind="float", min_ndim=2, trailing=(3,))
        self.log_scales = _as_array(log_scales, sort="Gaussians", field="log_scales", kind="float", min_ndim=2,
                                    trailing=(3,))
        self.quats = _as_array(quats, sort="Gaussians", field="quats", kind="float", min_ndim=2, trailing=(4,))
        self.opacity_logits = _as_array(opacity_logits, sort="Gaussians", field="opacity_logits", kind="float",
                                        min_ndim=1)
        colors = jnp.asarray(colors)
        if colors.ndim == self.means.ndim:
            colors = colors[..., None, :]
        self.colors = _as_array(colors, sort="Gaussians", field="colors", kind="float", min_ndim=3, trailing=(3,))
        if valid is None:
            valid = jnp.ones(self.means.shape[:-1], dtype=bool)
        self.valid = _as_array(valid, sort="Gaussians", field="valid", kind="bool", min_ndim=1)
        n = self.means.shape[:-1]
        for name, arr, tail in (("log_scales", self.log_scales, 1), ("quats", self.quats, 1),
                                ("opacity_logits", self.opacity_logits, 0), ("colors", self.colors, 2),
                                ("valid", self.valid, 0)):
            lead = arr.shape[: arr.ndim - tail]
            if lead != n:
                raise ValueError(f"Gaussians({name}=...): leading shape {lead} does not match means {n}")
        if is_concrete(self.quats) and is_concrete(self.valid):
            norms = np.linalg.norm(np.asarray(self.quats), axis=-1)
            if bool(np.any((norms == 0) & np.asarray(self.valid))):
                raise ValueError("Gaussians(quats=...): a zero-length quaternion is not a rotation")

    @property
    def batch_shape(self) -> tuple[int, ...]:
        return tuple(self.means.shape[:-2])


class Camera(Sort):
    """Pinhole camera, OpenCV convention.

    ``K`` ``(3, 3)`` intrinsics ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`` in pixels;
    ``dist`` ``(5,)`` Brown-Conrady ``(k1, k2, p1, p2, k3)``; ``R`` ``(3, 3)`` and
    ``t`` ``(3,)`` give the pose ``world_from_camera`` (a camera-frame point ``p``
    maps to ``R @ p + t`` in the world). ``width``/``height`` in pixels (static).
    Camera frame: x right, y down, z forward.
    """

    K: Float[Array, "*batch 3 3"]
    dist: Float[Array, "*batch 5"]
    R: Float[Array, "*batch 3 3"]
    t: Float[Array, "*batch 3"]
    width: int = eqx.field(static=True, default=0)
    height: int = eqx.field(static=True, default=0)
    _float_fields = ("K", "dist", "R", "t")

    def __init__(self, K: Any, *, width: int, height: int, dist: Any = None, R: Any = None, t: Any = None):
        self.K = _as_array(K, sort="Camera", field="K", kind="float", min_ndim=2, trailing=(3, 3))
        batch = self.K.shape[:-2]
        dt = self.K.dtype
        self.dist = _as_array(jnp.zeros(batch + (5,), dt) if dist is None else dist, sort="Camera",
                              field="dist", kind="float", min_ndim=1, trailing=(5,))
        self.R = _as_array(jnp.broadcast_to(jnp.eye(3, dtype=dt), batch + (3, 3)) if R is None else R,
                           sort="Camera", field="R", kind="float", min_ndim=2, trailing=(3, 3))
        self.t = _as_array(jnp.zeros(batch + (3,), dt) if t is None else t, sort="Camera", field="t",
                           kind="float", min_ndim=1, trailing=(3,))
        if int(width) <= 0 or int(height) <= 0:
            raise ValueError(f"Camera(width=..., height=...): must be positive, got {width} x {height}")
        self.width = int(width)
        self.height = int(height)

    @classmethod
    def from_intrinsics(cls, fx: float, fy: float, cx: float, cy: float, *, width: int, height: int,
                        **kw: Any) -> Camera:
        """Camera from focal lengths and principal point (pixels)."""
        K = jnp.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        return cls(K, width=width, height=height, **kw)

    @property
    def batch_shape(self) -> tuple[int, ...]:
        return tuple(self.K.shape[:-2])


class Depth(Sort):
    """Depth map ``z`` ``(*batch, H, W)`` along the optical axis, with its ``camera``.

    0 or NaN means "no return"; NaN is therefore allowed in ``z``.
    """

    _array_field = "z"

    z: Float[Array, "*batch H W"]
    camera: Camera
    _float_fields = ()

    def __init__(self, z: Any, camera: Camera):
        self.z = _as_array(z, sort="Depth", field="z", kind="float", min_ndim=2, spatial=2)
        if not isinstance(camera, Camera):
            raise TypeError(f"Depth(camera=...): expected a Camera, got {type(camera).__name__}")
        self.camera = camera

    @property
    def batch_shape(self) -> tuple[int, ...]:
        return tuple(self.z.shape[:-2])


# ---------------------------------------------------------------------------
# Matching
# ---------------------------------------------------------------------------


class Match(Sort):
    """Found instances of a model, fixed capacity ``K``.

    Per instance: sub-pixel ``row``/``col`` of the model's reference point in the
    image, ``angle_deg`` (counter-clockwise as seen on screen, i.e. rotating the
    +col axis towards -row), ``scale``, ``score`` (method-specific, higher is
    better), ``valid``. Valid instances come first, sorted by descending score;
    ``truncated`` is True when more instances passed the acceptance test than
    the capacity holds. Unused slots carry no meaning (the matching ops fill
    them with zeros and scale 1): always read ``valid``.
    """

    row: Float[Array, "*batch K"]
    col: Float[Array, "*batch K"]
    angle_deg: Float[Array, "*batch K"]
    scale: Float[Array, "*batch K"]
    score: Float[Array, "*batch K"]
    valid: Bool[Array, "*batch K"]
    truncated: Bool[Array, "*batch"]
    _float_fields = ()  # unused slots are not checked

    def __init__(self, row: Any, col: Any, score: Any, valid: Any = None, angle_deg: Any = None,
                 scale: Any = None, truncated: Any = False):
        self.row = _as_array(row, sort="Match", field="row", kind="float", min_ndim=1)
        shape = self.row.shape
        dt = self.row.dtype
        self.col = _as_array(col, sort="Match", field="col", kind="float", min_ndim=1)
        self.score = _as_array(score, sort="Match", field="score", kind="float", min_ndim=1)
        self.angle_deg = _as_array(jnp.zeros(shape, dt) if angle_deg is None else angle_deg, sort="Match",
                                   field="angle_deg", kind="float", min_ndim=1)
        self.scale = _as_array(jnp.ones(shape, dt) if scale is None else scale, sort="Match", field="scale",
                               kind="float", min_ndim=1)
        self.valid = _as_array(jnp.ones(shape, bool) if valid is None else valid, sort="Match", field="valid",
                               kind="bool", min_ndim=1)
        for name in ("col", "score", "angle_deg", "scale", "valid"):
            if getattr(self, name).shape != shape:
                raise ValueError(f"Match({name}=...): shape {getattr(self, name).shape} does not match row {shape}")
        self.truncated = jnp.asarray(truncated, dtype=bool)

    @property
    def batch_shape(self) -> tuple[int, ...]:
        return tuple(self.row.shape[:-1])


# ---------------------------------------------------------------------------
# Measurements
# ---------------------------------------------------------------------------


class RegionProps(Sort):
    """Per-label measurements, fixed capacity ``K``: a table ``(K, F)`` with named columns.

    ``names`` (static) names the ``F`` columns (e.g. ``"area"``,
    ``"centroid_row"``); ``label`` gives the label id of each row (row ``k``
    describes label ``k + 1``); ``valid`` marks labels that exist; ``truncated``
    says labels beyond the capacity were not measured. Invalid rows hold NaN.
    ``props["area"]`` returns a column.
    """

    table: Float[Array, "*batch K F"]
    label: Int[Array, "*batch K"]
    valid: Bool[Array, "*batch K"]
    truncated: Bool[Array, "*batch"]
    names: tuple[str, ...] = eqx.field(static=True, default=())
    _float_fields = ()

    def __init__(self, table: Any, names: tuple[str, ...], valid: Any, label: Any = None, truncated: Any = False):
        self.table = _as_array(table, sort="RegionProps", field="table", kind="float", min_ndim=2)
        self.names = tuple(str(n) for n in names)
        if len(self.names) != self.table.shape[-1]:
            raise ValueError(
                f"RegionProps(names=...): {len(self.names)} names for {self.table.shape[-1]} columns"
            )
        if len(set(self.names)) != len(self.names):
            raise ValueError("RegionProps(names=...): column names must be unique")
        self.valid = _as_array(valid, sort="RegionProps", field="valid", kind="bool", min_ndim=1)
        if self.valid.shape != self.table.shape[:-1]:
            raise ValueError(f"RegionProps(valid=...): shape {self.valid.shape} does not match table rows "
                             f"{self.table.shape[:-1]}")
        if label is None:
            label = jnp.broadcast_to(jnp.arange(1, self.table.shape[-2] + 1, dtype=jnp.int32), self.valid.shape)
        self.label = _as_array(label, sort="RegionProps", field="label", kind="int", min_ndim=1)
        self.truncated = jnp.asarray(truncated, dtype=bool)

    def __getitem__(self, name: str) -> Array:
        if name not in self.names:
            raise KeyError(f"RegionProps: no column {name!r}; columns: {', '.join(self.names)}")
        return self.table[..., self.names.index(name)]

    @property
    def batch_shape(self) -> tuple[int, ...]:
        return tuple(self.table.shape[:-2])


class Fit(Sort):
    """Result record of a geometric fit: named parameters plus diagnostics.

    ``kind`` (static) names the model (``"line"``, ``"circle"``, ``"ellipse"``,
    ...), ``names`` (static) its parameters, in units stated by the op.
    ``rms`` is the residual RMS, ``iterations`` the solver steps, ``converged``
    False (with NaN parameters) when the fit failed or was degenerate, and
    ``n_used`` the number of points that entered the final fit.
    """

    params: Float[Array, "*batch P"]
    rms: Float[Array, "*batch"]
    iterations: Int[Array, "*batch"]
    converged: Bool[Array, "*batch"]
    n_used: Int[Array, "*batch"]
    kind: str = eqx.field(static=True, default="")
    names: tuple[str, ...] = eqx.field(static=True, default=())
    _float_fields = ()

    def __init__(self, params: Any, names: tuple[str, ...], kind: str, rms: Any, converged: Any,
                 iterations: Any = 0, n_used: Any = 0):
        self.params = _as_array(params, sort="Fit", field="params", kind="float", min_ndim=1)
        self.names = tuple(str(n) for n in names)
        if len(self.names) != self.params.shape[-1]:
            raise ValueError(f"Fit(names=...): {len(self.names)} names for {self.params.shape[-1]} parameters")
        self.kind = str(kind)
        self.rms = jnp.asarray(rms, dtype=self.params.dtype)
        self.converged = jnp.asarray(converged, dtype=bool)
        self.iterations = jnp.asarray(iterations, dtype=jnp.int32)
        self.n_used = jnp.asarray(n_used, dtype=jnp.int32)

    def __getitem__(self, name: str) -> Array:
        if name not in self.names:
            raise KeyError(f"Fit: no parameter {name!r}; parameters: {', '.join(self.names)}")
        return self.params[..., self.names.index(name)]

    @property
    def batch_shape(self) -> tuple[int, ...]:
        return tuple(self.params.shape[:-1])


class Edges1D(Sort):
    """Edges found along a 1-D measure profile (calipers), fixed capacity ``K``.

    ``pos`` is the sub-pixel position along the profile in pixels from its start;
    ``row``/``col`` the image position; ``amplitude`` the signed derivative at the
    edge (positive = dark-to-light along the profile); ``width`` the distance to
    the paired edge for edge pairs (0 for single edges from ``measure_pos`` and for
    unused slots: read ``valid`` and the op that made it). Valid edges come first
    in profile order; ``truncated`` flags lost edges.
    """

    pos: Float[Array, "*batch K"]
    row: Float[Array, "*batch K"]
    col: Float[Array, "*batch K"]
    amplitude: Float[Array, "*batch K"]
    width: Float[Array, "*batch K"]
    valid: Bool[Array, "*batch K"]
    truncated: Bool[Array, "*batch"]
    _float_fields = ()

    def __init__(self, pos: Any, row: Any, col: Any, amplitude: Any, valid: Any, width: Any = None,
                 truncated: Any = False):
        self.pos = _as_array(pos, sort="Edges1D", field="pos", kind="float", min_ndim=1)
        shape, dt = self.pos.shape, self.pos.dtype
        self.row = _as_array(row, sort="Edges1D", field="row", kind="float", min_ndim=1)
        self.col = _as_array(col, sort="Edges1D", field="col", kind="float", min_ndim=1)
        self.amplitude = _as_array(amplitude, sort="Edges1D", field="amplitude", kind="float", min_ndim=1)
        self.width = _as_array(jnp.zeros(shape, dt) if width is None else width, sort="Edges1D",
                               field="width", kind="float", min_ndim=1)
        self.valid = _as_array(valid, sort="Edges1D", field="valid", kind="bool", min_ndim=1)
        for name in ("row", "col", "amplitude", "width", "valid"):
            if getattr(self, name).shape != shape:
                raise ValueError(f"Edges1D({name}=...): shape {getattr(self, name).shape} does not match pos {shape}")
        self.truncated = jnp.asarray(truncated, dtype=bool)

    @property
    def batch_shape(self) -> tuple[int, ...]:
        return tuple(self.pos.shape[:-1])
