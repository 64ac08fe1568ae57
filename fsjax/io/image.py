"""Image file input/output (Pillow), with the integer-to-float conversion recorded.

Reading:

* ``uint8`` and ``uint16`` pixel values become floats in ``[0, 1]`` through
  :meth:`fsjax.Image.from_uint` / :meth:`fsjax.Color.from_uint`, which record the
  conversion in the sort's static ``conversion`` field (``"uint8 / 255"``,
  ``"uint16 / 65535"``, ``"uint16 / 4095"`` for ``bit_depth=12``). Further steps
  are appended after ``"; "``: ``"sRGB decoded"`` (``linearize=True``),
  ``"grey = BT.709 luminance"`` (``as_grey=True`` on a colour file), ``"alpha
  dropped"``, ``"palette expanded"``.
* File values are returned as stored unless ``linearize=True``: most 8-bit
  files are sRGB-*encoded*, while :class:`fsjax.Color` is meant to hold linear
  light. ``linearize=True`` applies the sRGB EOTF (IEC 61966-2-1) to grey and
  colour files alike, before any grey conversion.
* Pillow reads 16-bit-per-channel *colour* PNGs as 8-bit RGB; such files are
  returned at 8-bit precision and the conversion string says so.

Writing (:func:`write_image`): 8-bit PNG by default (16-bit for grey images on
request). Values are clipped to ``[0, 1]`` and quantised as ``floor(v * (2^b -
1) + 0.5)`` (round half up), so ``k / 255`` round-trips exactly; a ``Region``
is written as 0 / 255. NaN or infinite values are refused, never written as a
plausible grey.

Pillow is an optional dependency, imported inside the functions.
"""

from __future__ import annotations

import os

import numpy as np

from ..types import Color, Image, Region, Sort

__all__ = ["read_image", "write_image"]

_LUMA = (0.2126, 0.7152, 0.0722)


def _pil():
    try:
        from PIL import Image as PILImage
    except ImportError as e:  # pragma: no cover - exercised by monkeypatching in tests
        raise ImportError(
            "fsjax.io needs the 'pillow' package to read and write image files; "
            "install it with `pip install pillow`"
        ) from e
    return PILImage


def read_image(path: str | os.PathLike, *, as_grey: bool | None = None, linearize: bool = False,
               bit_depth: int | None = None) -> Image | Color:
    """Read an image file into an ``Image`` (grey) or ``Color`` (RGB) in ``[0, 1]``.

    Args:
      path: file path (any format Pillow reads: PNG, TIFF, JPEG, BMP, ...).
      as_grey: ``None`` (default) keeps the file's kind (grey file -> ``Image``,
        colour file -> ``Color``); ``True`` returns an ``Image``, converting colour
        with the BT.709 luminance weights ``0.2126, 0.7152, 0.0722`` (applied
        after linearisation when ``linearize=True``); ``False`` returns a
        ``Color``, replicating a grey file into three equal channels.
      linearize: apply the sRGB decoding curve (file values are assumed
        sRGB-encoded) so the result is linear light; recorded as ``"sRGB decoded"``.
      bit_depth: significant bits of a ``uint16`` file (e.g. 12 for a 12-bit
        sensor stored in 16-bit words: values are divided by 4095); ``None``
        uses the container's depth (255 or 65535).

    Returns:
      ``Image`` ``(H, W)`` or ``Color`` ``(H, W, 3)``, float (float64 when JAX
      x64 is enabled), with ``.conversion`` describing every step.

    Raises:
      FileNotFoundError: ``path`` does not exist.
      ValueError: Pillow cannot decode the file, or its pixel mode is not
        supported (e.g. CMYK is converted, but 32-bit integer images with values
        beyond 16 bits are refused).
      ImportError: Pillow is not installed.

    Example:
      >>> import tempfile, os, jax.numpy as jnp, fsjax
      >>> from fsjax.io import read_image, write_image
      >>> p = os.path.join(tempfile.mkdtemp(), "g.png")
      >>> write_image(p, fsjax.Image(jnp.array([[0.0, 51 / 255], [1.0, 0.5]])))
      >>> img = read_image(p)
      >>> img.conversion, [round(float(v) * 255) for v in img.data.ravel()]
      ('uint8 / 255', [0, 51, 255, 128])
    """
    PILImage = _pil()
    path = os.fspath(path)
    if not os.path.exists(path):
        raise FileNotFoundError(f"read_image: no such file: {path!r}")
    if os.path.isdir(path):
        raise IsADirectoryError(f"read_image: {path!r} is a directory, not an image file")
    if as_grey not in (None, True, False):
        raise TypeError(f"read_image: argument 'as_grey' must be None, True or False, got {as_grey!r}")
    try:
        pim = PILImage.open(path)
        # the raw mode of the file ("RGB;16B") is only visible before load()
        raw16_colour = pim.mode in ("RGB", "RGBA") and any(
            ";16" in str(getattr(t, "args", "")) for t in (pim.tile or []))
        pim.load()
    except Exception as e:  # Pillow raises UnidentifiedImageError, OSError, SyntaxError, ...
        raise ValueError(f"read_image: Pillow cannot decode {path!r}: {e}") from e

    notes: list[str] = []
    mode = pim.mode
    if mode == "P":
        pim = pim.convert("RGBA" if "transparency" in pim.info else "RGB")
        notes.append("palette expanded")
        mode = pim.mode
    if mode == "PA":
        pim = pim.convert("RGBA")
        notes.append("palette expanded")
        mode = pim.mode
    if mode == "1":
        pim = pim.convert("L")
        mode = "L"
    if mode in ("CMYK", "YCbCr", "LAB", "HSV"):
        pim = pim.convert("RGB")
        notes.append(f"{mode} converted to RGB by Pillow")
        mode = "RGB"
    if mode == "LA":
        pim = pim.getchannel("L")
        notes.append("alpha dropped")
        mode = "L"
    if mode == "RGBA":
        pim = pim.convert("RGB")
        notes.append("alpha dropped")
        mode = "RGB"

    if mode == "F":
        arr = np.asarray(pim, dtype=np.float32)
        grey, conv = True, "float32 file values (not rescaled)"
        data = arr.astype(np.float64)
    else:
        arr = np.asarray(pim)
        if mode in ("I", "I;16", "I;16B", "I;16L", "I;16N"):
            a = arr.astype(np.int64)
            if a.size and (a.min() < 0 or a.max() > 65535):
                raise ValueError(
                    f"read_image: {path!r} holds 32-bit integer values in [{a.min()}, {a.max()}]; "
                    f"only unsigned 8- and 16-bit images are supported"
                )
            arr = a.astype(np.uint16)
        elif mode not in ("L", "RGB"):
            raise ValueError(f"read_image: unsupported Pillow mode {mode!r} in {path!r}")
        grey = arr.ndim == 2
        sort = Image if grey else Color
        try:
            made = sort.from_uint(arr, bit_depth=bit_depth)
        except (TypeError, ValueError) as e:
            raise ValueError(f"read_image: {path!r}: {e}") from e
        data, conv = np.asarray(made.data), made.conversion
        if raw16_colour:
            conv += " (file is 16-bit colour; Pillow reads it at 8 bits)"

    import jax.numpy as jnp

    out = jnp.asarray(data, dtype=jnp.result_type(float))
    if linearize:
        from ..ops.image._color import srgb_to_linear

        out = srgb_to_linear(out)
        notes.append("sRGB decoded")
    if not grey and as_grey:
        out = _LUMA[0] * out[..., 0] + _LUMA[1] * out[..., 1] + _LUMA[2] * out[..., 2]
        notes.append("grey = BT.709 luminance")
        grey = True
    elif grey and as_grey is False:
        out = jnp.stack([out, out, out], axis=-1)
        notes.append("grey replicated to RGB")
        grey = False
    conversion = "; ".join([conv, *notes])
    return Image(out, conversion=conversion) if grey else Color(out, conversion=conversion)


def write_image(path: str | os.PathLike, img: Image | Color | Region, *, bit_depth: int = 8,
                srgb: bool = False) -> None:
    """Write an ``Image``, ``Color`` or ``Region`` to a PNG file.

    Quantisation: values are clipped to ``[0, 1]`` (out-of-range values
    saturate, as a display would) and mapped to ``floor(v * M + 0.5)`` with
    ``M = 255`` (``bit_depth=8``) or ``65535`` (``bit_depth=16``, grey only,
    because Pillow cannot write 16-bit colour PNGs). A ``Region`` is written as
    8-bit 0 / 255.

    Args:
      path: destination; must end in ``.png``.
      img: a single (unbatched) ``Image`` ``(H, W)``, ``Color`` ``(H, W, 3)`` or
        ``Region`` ``(H, W)``.
      bit_depth: 8 (default) or 16.
      srgb: apply the sRGB encoding curve before quantising (for linear data that
        should display correctly); default ``False`` writes the values as they are,
        so ``read_image(write_image(x))`` returns ``x`` up to quantisation.

    Raises:
      TypeError: ``img`` is not an ``Image``, ``Color`` or ``Region`` (e.g. ``HSV``,
        ``Lab``, ``Labels``: convert first).
      ValueError: NaN or infinite values, a batched sort, a non-PNG path, a bad
        ``bit_depth``, or 16-bit colour.
      ImportError: Pillow is not installed.

    Example:
      >>> import tempfile, os, jax.numpy as jnp, fsjax
      >>> from fsjax.io import read_image, write_image
      >>> p = os.path.join(tempfile.mkdtemp(), "r.png")
      >>> write_image(p, fsjax.Region(jnp.array([[True, False]])))
      >>> [float(v) for v in read_image(p).data.ravel()]
      [1.0, 0.0]
    """
    path = os.fspath(path)
    if not isinstance(img, (Image, Color, Region)):
        what = type(img).__name__
        hint = " (convert with fsjax.ops.hsv_to_rgb / lab_to_rgb first)" if what in ("HSV", "Lab") else ""
        if not isinstance(img, Sort):
            hint = "; wrap an array with fsjax.Image(x) or fsjax.Color(x)"
        raise TypeError(f"write_image: argument 'img' must be Image, Color or Region, got {what}{hint}")
    if not path.lower().endswith(".png"):
        raise ValueError(f"write_image: only PNG is written; argument 'path' must end in '.png', got {path!r}")
    if bit_depth not in (8, 16) or isinstance(bit_depth, bool):
        raise ValueError(f"write_image: argument 'bit_depth' must be 8 or 16, got {bit_depth!r}")
    if img.batch_shape:
        raise ValueError(
            f"write_image: argument 'img' is a batch of shape {img.batch_shape}; write one image at a time"
        )
    PILImage = _pil()
    arr = np.asarray(img.data)
    if isinstance(img, Region):
        out = np.where(arr, 255, 0).astype(np.uint8)
        PILImage.fromarray(out).save(path, format="PNG")
        return None
    arr = arr.astype(np.float64)
    bad = ~np.isfinite(arr)
    if bad.any():
        raise ValueError(
            f"write_image: argument 'img' contains {int(bad.sum())} NaN/inf value(s); "
            f"refusing to write them as grey values"
        )
    if isinstance(img, Color) and bit_depth == 16:
        raise ValueError("write_image: bit_depth=16 is supported for Image only (Pillow writes 8-bit colour PNG)")
    if srgb:
        from ..ops.image._color import linear_to_srgb

        arr = np.asarray(linear_to_srgb(np.clip(arr, 0.0, 1.0)))
    full = 255.0 if bit_depth == 8 else 65535.0
    q = np.floor(np.clip(arr, 0.0, 1.0) * full + 0.5)
    q = q.astype(np.uint8 if bit_depth == 8 else np.uint16)
    PILImage.fromarray(q).save(path, format="PNG")
    return None

