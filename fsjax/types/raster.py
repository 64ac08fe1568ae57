"""2-D and 3-D rasters: grey, colour and label images, 1-D signals, voxel volumes, and the image
stacks and normal maps of photometric stereo and structured light.
"""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from ._base import Sort, _as_array, _from_uint, is_concrete

__all__ = ["Image", "Color", "HSV", "Lab", "Region", "Labels", "Signal", "Volume", "LabelVolume", "LightStack", "NormalMap",
           "FringeStack", "GrayStack"]


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


class LabelVolume(Sort):
    """Label volume, shape ``(*batch, D, H, W)`` int32; 0 = background, ``1..count``.

    ``count`` and ``truncated`` mean what they mean for :class:`Labels`; ``spacing``
    ``(dz, dy, dx)`` in ``unit`` is carried over from the ``Volume`` that was labelled.
    """

    _array_field = "data"

    data: Int[Array, "*batch D H W"]
    count: Int[Array, "*batch"]
    truncated: Bool[Array, "*batch"]
    spacing: tuple[float, float, float] = eqx.field(static=True, default=(1.0, 1.0, 1.0))
    unit: str = eqx.field(static=True, default="mm")

    def __init__(self, data: Any, count: Any = None, truncated: Any = False,
                 spacing: tuple[float, float, float] = (1.0, 1.0, 1.0), unit: str = "mm"):
        self.data = _as_array(data, sort="LabelVolume", field="data", kind="int", min_ndim=3, spatial=3)
        if count is None:
            if not is_concrete(self.data):
                raise ValueError("LabelVolume(count=None) needs a concrete label array; pass count under jit")
            count = np.max(np.asarray(self.data), axis=(-3, -2, -1), initial=0)
        self.count = jnp.asarray(count, dtype=jnp.int32)
        self.truncated = jnp.asarray(truncated, dtype=bool)
        sp = tuple(float(s) for s in spacing)
        if len(sp) != 3 or not all(s > 0 for s in sp):
            raise ValueError(f"LabelVolume(spacing=...): expected three positive numbers (dz, dy, dx), got {spacing}")
        self.spacing = sp
        self.unit = unit

    @property
    def batch_shape(self) -> tuple[int, ...]:
        return tuple(self.data.shape[:-3])


# ---------------------------------------------------------------------------
# image stacks and maps of the 3-D measurement families (photometric stereo, structured light);
# conventions in fsjax.ops.measure3d (camera frame: OpenCV, x right, y down, z forward)
# ---------------------------------------------------------------------------


class LightStack(Sort):
    """``K`` images ``data (*batch, K, H, W)`` under distant lights ``lights (*batch, K, 3)``.

    ``lights`` are unit directions towards the lights in the camera frame (normalised on
    construction; a zero-length direction is refused).
    """

    data: Float[Array, "*batch K H W"]
    lights: Float[Array, "*batch K 3"]
    _float_fields = ("data", "lights")

    def __init__(self, data: Any, lights: Any):
        self.data = _as_array(data, sort="LightStack", field="data", kind="float", min_ndim=3)
        lights = _as_array(lights, sort="LightStack", field="lights", kind="float", min_ndim=2, trailing=(3,))
        if lights.shape[-2] != self.data.shape[-3]:
            raise ValueError(f"LightStack(lights=...): {lights.shape[-2]} lights for {self.data.shape[-3]} images")
        nn = jnp.linalg.norm(lights, axis=-1, keepdims=True)
        if is_concrete(nn) and not bool(np.all(np.asarray(nn) > 0)):
            raise ValueError("LightStack(lights=...): a light direction has zero length")
        self.lights = lights / jnp.where(nn > 0, nn, jnp.nan)

    @property
    def batch_shape(self) -> tuple[int, ...]:
        return tuple(self.data.shape[:-3])


class NormalMap(Sort):
    """Unit normals ``(*batch, H, W, 3)`` (camera frame), ``albedo (*batch, H, W)``, ``valid (*batch, H, W)``."""

    normals: Float[Array, "*batch H W 3"]
    albedo: Float[Array, "*batch H W"]
    valid: Bool[Array, "*batch H W"]
    _float_fields = ()

    def __init__(self, normals: Any, albedo: Any, valid: Any = None):
        self.normals = _as_array(normals, sort="NormalMap", field="normals", kind="float", min_ndim=3, trailing=(3,))
        self.albedo = _as_array(albedo, sort="NormalMap", field="albedo", kind="float", min_ndim=2)
        if self.albedo.shape != self.normals.shape[:-1]:
            raise ValueError(f"NormalMap(albedo=...): shape {self.albedo.shape} does not match normals "
                             f"{self.normals.shape[:-1]}")
        v = jnp.isfinite(self.albedo) if valid is None else valid
        self.valid = _as_array(v, sort="NormalMap", field="valid", kind="bool", min_ndim=2)

    @property
    def batch_shape(self) -> tuple[int, ...]:
        return tuple(self.albedo.shape[:-2])


class FringeStack(Sort):
    """``N >= 3`` phase-shifted fringe images ``data (*batch, N, H, W)``, shifts ``2 pi k / N``."""

    data: Float[Array, "*batch N H W"]
    _float_fields = ("data",)

    def __init__(self, data: Any):
        self.data = _as_array(data, sort="FringeStack", field="data", kind="float", min_ndim=3)

    @property
    def batch_shape(self) -> tuple[int, ...]:
        return tuple(self.data.shape[:-3])


class GrayStack(Sort):
    """``2 n`` Gray-code frames ``data (*batch, 2n, H, W)``: bit pattern then its inverse, MSB first."""

    data: Float[Array, "*batch F H W"]
    _float_fields = ("data",)

    def __init__(self, data: Any):
        self.data = _as_array(data, sort="GrayStack", field="data", kind="float", min_ndim=3)
        if self.data.shape[-3] % 2:
            raise ValueError(f"GrayStack(data=...): needs pattern/inverse pairs, got {self.data.shape[-3]} frames")

    @property
    def batch_shape(self) -> tuple[int, ...]:
        return tuple(self.data.shape[:-3])
